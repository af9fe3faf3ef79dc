"""sd_notify spoken to a real AF_UNIX datagram socket standing in for systemd, and the daemon's use of it:
READY once started up, WATCHDOG only while every thread's heartbeat is fresh, STOPPING at the end."""

from __future__ import annotations

import itertools
import logging
import os
import re
import socket
import statistics
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from logger.config import defaults
from logger.runtime.daemon import OPEN_GRACE_S, Daemon
from logger.runtime.journal import ProblemJournal
from logger.runtime.notify import Notifier
from logger.runtime.sampler import Reading, Source
from logger.runtime.sampler import wait_until as sampler_wait_until
from logger.runtime.sources import Plan
from sensors.errors import BusError


class FakeSystemd:
    """The manager's end of NOTIFY_SOCKET: collects every datagram with its arrival time."""

    def __init__(self, address: str | bytes) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)
        self.sock.settimeout(0.05)
        self.messages: list[tuple[float, dict[str, str]]] = []
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._halt.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            fields = dict(line.split("=", 1) for line in data.decode().split("\n"))
            self.messages.append((time.monotonic(), fields))

    def wait_for(self, key: str, timeout_s: float = 20.0) -> dict[str, str]:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for _, m in list(self.messages):
                if key in m:
                    return m
            time.sleep(0.01)
        raise AssertionError(f"no {key} within {timeout_s} s: {self.messages}")

    def pings_between(self, t0: float, t1: float) -> int:
        return sum(1 for t, m in list(self.messages) if "WATCHDOG" in m and t0 <= t <= t1)

    def ping_times(self) -> list[float]:
        return [t for t, m in list(self.messages) if "WATCHDOG" in m]

    def close(self) -> None:
        self._halt.set()
        self._thread.join(2)
        self.sock.close()


@pytest.fixture
def systemd(tmp_path: Path) -> Iterator[tuple[FakeSystemd, str]]:
    path = str(tmp_path / "notify.sock")
    fake = FakeSystemd(path)
    yield fake, path
    fake.close()


# ---- the protocol ----------------------------------------------------------------------------------------------

def test_ready_status_and_watchdog_reach_a_path_socket(systemd: tuple[FakeSystemd, str]) -> None:
    fake, path = systemd
    n = Notifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "3000000"}, pid=os.getpid())
    assert n.enabled and n.watchdog_interval_s == 1.5
    assert n.ready("recording\nto x")
    assert n.watchdog()
    assert n.stopping()
    fake.wait_for("STOPPING")
    got = [m for _, m in fake.messages]
    assert got[0] == {"READY": "1", "STATUS": "recording to x"}  # a newline would start a new assignment
    assert got[1:] == [{"WATCHDOG": "1"}, {"STOPPING": "1"}]


def test_abstract_namespace_socket() -> None:
    name = f"vehicle-logger-test-{uuid.uuid4().hex}"
    fake = FakeSystemd(b"\0" + name.encode())
    try:
        n = Notifier.from_env({"NOTIFY_SOCKET": "@" + name})
        assert n.status("all well")
        assert fake.wait_for("STATUS") == {"STATUS": "all well"}
    finally:
        fake.close()


def test_watchdog_belongs_to_the_pid_systemd_named() -> None:
    env = {"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "20000000", "WATCHDOG_PID": "1"}
    assert Notifier.from_env(env, pid=4242).watchdog_interval_s is None
    assert Notifier.from_env(env, pid=1).watchdog_interval_s == 10.0
    assert Notifier.from_env({"WATCHDOG_USEC": "abc", "NOTIFY_SOCKET": "/run/x"}).watchdog_interval_s is None


def test_without_systemd_everything_is_a_quiet_no_op(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    assert not Notifier.from_env({}).enabled
    assert Notifier.from_env({}).ready() is False
    assert not Notifier.from_env({"NOTIFY_SOCKET": "vsock:2:1234"}).enabled
    # A socket nobody listens on: False, one warning, never an exception (logging goes on regardless).
    n = Notifier.from_env({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})
    with caplog.at_level(logging.WARNING):
        assert n.watchdog() is False
        assert n.watchdog() is False
    assert len([r for r in caplog.records if "cannot notify" in r.getMessage()]) == 1


def test_status_is_cut_to_one_bounded_line(systemd: tuple[FakeSystemd, str]) -> None:
    fake, path = systemd
    Notifier(path).status("x" * 5000)
    assert len(fake.wait_for("STATUS")["STATUS"]) == 1024


# ---- the daemon under a manager --------------------------------------------------------------------------------

class TickSource(Source):
    """A periodic sensor whose read can be made to hang (a driver stuck in a kernel call) or its open to block."""

    def __init__(self, name: str, block_open: bool = False) -> None:
        self.name = name
        self.hang = threading.Event()
        self.release = threading.Event()
        self.open_gate = threading.Event()
        if not block_open:
            self.open_gate.set()

    def open(self) -> None:
        if not self.open_gate.wait(30):
            raise BusError("gate never opened")

    def read(self) -> list[Reading]:
        if self.hang.is_set():
            self.release.wait(30)
        return [Reading(f"/test/{self.name}", {"v": 1}, time.monotonic_ns())]

    def close(self) -> None:
        pass


def make_daemon(tmp_path: Path, sources: list[TickSource], notify_path: str, watchdog_usec: int = 200_000) -> Daemon:
    cfg = defaults(sim=True)
    cfg.values["logger"]["out_dir"] = str(tmp_path / "drives")
    cfg.values["logger"]["status_socket"] = str(tmp_path / "status.sock")
    plans = [Plan(s, 20.0, 20.0) for s in sources]
    notifier = Notifier.from_env({"NOTIFY_SOCKET": notify_path, "WATCHDOG_USEC": str(watchdog_usec)})
    d = Daemon(cfg, plans, notifier=notifier)
    d.heartbeat_bound_s = 1.0
    return d


def wait_until(condition: Callable[[], object], what: str, timeout_s: float = 20.0) -> None:
    """A deadline instead of a fixed sleep, so a loaded host only makes the test slower."""
    assert sampler_wait_until(lambda: bool(condition()), timeout_s), f"not within {timeout_s} s: {what}"


def count_passes(d: Daemon) -> tuple[list[int], Callable[[], list[str]]]:
    """Every pass of the service loop asks for the stale threads: counting the calls counts the chances it had
    to ping, so "no ping" is checked over passes that really ran, however slow the host. Returns the counter and
    the uncounted query."""
    passes = [0]
    stale_threads = d.stale_threads

    def counted_stale_threads() -> list[str]:
        passes[0] += 1
        return stale_threads()

    d.stale_threads = counted_stale_threads  # type: ignore[method-assign]
    return passes, stale_threads


def test_ready_after_start_then_pings_stop_while_a_sensor_thread_hangs(
        tmp_path: Path, systemd: tuple[FakeSystemd, str], caplog: pytest.LogCaptureFixture) -> None:
    fake, path = systemd
    steady, stuck = TickSource("steady"), TickSource("stuck")
    d = make_daemon(tmp_path, [steady, stuck], path)
    caplog.set_level(logging.INFO)
    passes, stale_threads = count_passes(d)
    d.start()
    try:
        ready = fake.wait_for("READY")
        assert "recorder recording" in ready["STATUS"]
        assert list((tmp_path / "drives").glob("*.mcap")), "READY before the first file was started"
        wait_until(lambda: len(fake.ping_times()) >= 8, "8 pings while every thread is alive")
        gaps = [b - a for a, b in itertools.pairwise(fake.ping_times())]
        # Every 0.1 s (half of WATCHDOG_USEC); the median shrugs off a ping the host delivered late.
        assert statistics.median(gaps) < 0.2, gaps

        stuck.hang.set()  # heartbeat bound 1 s, then silence
        wait_until(lambda: any("not answering the watchdog" in r.getMessage()
                               and "sampler-stuck silent" in r.getMessage() for r in caplog.records),
                   "the hung thread noticed")
        # The hung thread is the one named; any other (a late recorder heartbeat on a busy host) comes and goes.
        wait_until(lambda: (stale := stale_threads()) and all(s.startswith("sampler-stuck ") for s in stale),
                   "only the hung thread stale")
        pings_hung, passes_hung = d.watchdog_pings, passes[0]
        wait_until(lambda: passes[0] >= passes_hung + 5, "five more passes of the service loop")
        assert d.watchdog_pings == pings_hung, "WATCHDOG=1 sent while a thread is hung"

        stuck.release.set()  # the thread comes back: pings resume
        wait_until(lambda: d.watchdog_pings >= pings_hung + 2, "pings resumed after the thread came back")
    finally:
        stuck.release.set()
        d.stop()
    assert fake.wait_for("STOPPING")["STOPPING"] == "1"
    # The counter is what reached the manager's socket: every ping counted arrived, no other was sent.
    wait_until(lambda: len(fake.ping_times()) == d.watchdog_pings, "every ping counted received, no other")


def test_ready_waits_for_the_first_open_but_not_forever(tmp_path: Path, systemd: tuple[FakeSystemd, str]) -> None:
    fake, path = systemd
    slow = TickSource("slow", block_open=True)
    d = make_daemon(tmp_path, [slow], path)
    d.ready_timeout_s = 1.5
    t0 = time.monotonic()
    d.start()
    try:
        fake.wait_for("READY", timeout_s=10)
        t_ready = next(t for t, m in list(fake.messages) if "READY" in m)
        assert t_ready - t0 >= 1.5  # not before the timeout, while the sensor was still opening
        assert fake.pings_between(t0, t_ready) >= 2  # start-up is not a hang
        assert d.samplers[0].health.state == "starting"
        # An open under way is no fault for its first OPEN_GRACE_S (an ELM327's protocol search at every start)...
        snap = d.snapshot()
        assert not [p for p in snap["problems"] if p.startswith("slow")]
        # ... but with no sensor delivering the verdict is critical, and says why (it said nothing).
        assert snap["verdict"] == "critical" and snap["problems"] == ["sensors: none delivers yet (slow starting)"]
        # ... one that has not returned after it is (and says so: not "starting: " and nothing).
        d._started_mono -= int((OPEN_GRACE_S + 1) * 1e9)
        (said,) = [p for p in d.snapshot()["problems"] if p.startswith("slow")]
        m = re.fullmatch(r"slow: starting: opening the device for (\d+) s", said)
        assert m and int(m.group(1)) >= OPEN_GRACE_S + 1, said
    finally:
        slow.open_gate.set()
        d.stop()


def test_a_dead_recorder_stops_the_pings(tmp_path: Path, systemd: tuple[FakeSystemd, str]) -> None:
    fake, path = systemd
    d = make_daemon(tmp_path, [TickSource("a")], path)
    passes, stale_threads = count_passes(d)
    d.start()
    try:
        fake.wait_for("READY")
        d.recorder.stop()  # the writer thread ends while the sensors go on
        wait_until(lambda: "recorder has ended" in stale_threads(), "the ended recorder noticed")
        seen = passes[0]
        wait_until(lambda: passes[0] >= seen + 2, "a pass that had decided to ping before it noticed is over")
        pings, seen = d.watchdog_pings, passes[0]
        wait_until(lambda: passes[0] >= seen + 5, "five more passes of the service loop")
        assert d.watchdog_pings == pings  # what reaches the manager is what was counted (checked above)
    finally:
        d.stop()


def test_a_recorder_stuck_in_a_write_is_critical_in_the_status(tmp_path: Path, systemd: tuple[FakeSystemd, str],
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The writer blocks in a write that never returns (a hung SD card): its state still says "recording", but its
    heartbeat stops, and the status says so (critical, the row "stalled") instead of "ok" while the queue fills;
    an ended writer thread the same."""
    import logger.runtime.daemon as daemon_module

    monkeypatch.setattr(daemon_module, "HEARTBEAT_STALE_S", 1.0)
    fake, path = systemd
    d = make_daemon(tmp_path, [TickSource("a")], path)
    release = threading.Event()
    d.start()
    try:
        fake.wait_for("READY")
        assert d.snapshot()["verdict"] == "ok"
        d.recorder._drain = lambda: release.wait(30)  # type: ignore[method-assign]
        wait_until(lambda: d.snapshot()["verdict"] == "critical", "the stuck writer noticed")
        snap = d.snapshot()
        assert snap["recorder"]["state"] == "stalled"
        assert any(p.startswith("recorder: not responding for") for p in snap["problems"]), snap["problems"]
    finally:
        release.set()
        d.stop()
    assert not d.recorder.alive
    snap = d.snapshot()
    assert snap["verdict"] == "critical" and snap["recorder"]["state"] != "recording"


def test_a_recorder_slowly_draining_a_backlog_is_not_called_stuck(tmp_path: Path, systemd: tuple[FakeSystemd, str],
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A writer catching up on a backlog at 10 ms a record (a slow card) is in one drain for 5 s: its heartbeat
    beat only between drains, so it read as stuck in the kernel ("not responding", critical, the watchdog no longer
    pinged) while it wrote. It beats every HEARTBEAT_RECORDS records now (0.64 s here, against a staleness of
    2.5 s: a loaded host's scheduling has room)."""
    import logger.runtime.daemon as daemon_module

    monkeypatch.setattr(daemon_module, "HEARTBEAT_STALE_S", 2.5)
    fake, path = systemd
    d = make_daemon(tmp_path, [TickSource("a")], path)
    d.start()
    try:
        fake.wait_for("READY")
        write = d.recorder._write

        def slow(item: Any) -> None:
            time.sleep(0.010)
            write(item)
        d.recorder._write = slow  # type: ignore[method-assign]
        for i in range(500):  # 5 s of writing, queued at once
            assert d.recorder.submit("/a/backlog", {"i": i}, i, i)
        d.recorder._wake.set()
        seen = []
        wait_until(lambda: seen.append(d.snapshot()) or d.recorder.status().queue_depth == 0, "the backlog written",
                   timeout_s=30)
        assert len(seen) > 10
        assert all(s["recorder"]["state"] == "recording" for s in seen), [s["recorder"]["state"] for s in seen]
        assert not any(p.startswith("recorder: not responding") for s in seen for p in s["problems"])
    finally:
        d.stop()


def test_records_of_one_read_share_their_stamp(tmp_path: Path, systemd: tuple[FakeSystemd, str]) -> None:
    """Fixes read together (a late read of several NMEA epochs) share their board time, and each one, observed
    before it is stamped, may steer the clock: stamped one by one, a later epoch came out a few hundred ns before
    the one read with it, and readers going by log time met the epochs out of order (export dropped them). One
    read's records of a topic share one stamp, in the order read."""
    from sync.stamp import FREERUN, Stamp, StampClock

    class SteeredClock(StampClock):
        """Each stamp of the same instant 300 ns earlier than the last: a clock refitted between two calls."""

        def __init__(self) -> None:
            self.calls = 0

        def stamp(self, t_mono_ns: int) -> Stamp:
            self.calls += 1
            return Stamp(t_mono_ns - 300 * self.calls, FREERUN, 1, 0, 0)

    _, path = systemd
    d = make_daemon(tmp_path, [TickSource("a")], path)
    d.clock = SteeredClock()
    written: list[tuple[str, dict[str, Any], int]] = []
    d.recorder.submit = lambda topic, payload, log_ns, pub_ns: written.append((topic, payload, log_ns)) or True
    for epoch in (0.7, 0.8, 0.9):
        d.sink(Reading("/test/fix", {"epoch": epoch}, 5_000_000_000))
    d.sink(Reading("/test/fix", {"epoch": 1.0}, 5_100_000_000))
    stamps = [w[1]["t_sync_ns"] for w in written]
    assert stamps[0] == stamps[1] == stamps[2] < stamps[3]
    assert [w[2] for w in written] == stamps and [w[1]["epoch"] for w in written] == [0.7, 0.8, 0.9, 1.0]


class FailingSource(TickSource):
    """A sensor that answers, then stops answering (unplugged): its reads fail from ``fail`` on."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.fail = threading.Event()

    def read(self) -> list[Reading]:
        if self.fail.is_set():
            raise BusError("no answer (no ACK): check wiring")
        return super().read()

    def open(self) -> None:
        if self.fail.is_set():
            raise BusError("no answer (no ACK): check wiring")


def test_the_summary_says_a_sensor_ended_unwell(tmp_path: Path, systemd: tuple[FakeSystemd, str],
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """A sensor that stopped answering just before the run was told to stop: the summary says it ended unwell,
    with its error (each sampler says "stopped" once it has, which the summary read before)."""
    from logger.runtime.summary import run_summary

    fake, path = systemd
    unplugged = FailingSource("flaky")
    d = make_daemon(tmp_path, [TickSource("steady"), unplugged], path)
    d.start()
    try:
        fake.wait_for("READY")
        unplugged.fail.set()
        wait_until(lambda: next(h for h in d.snapshot()["sensors"] if h["name"] == "flaky")["state"] != "ok",
                   "the unplugged sensor noticed")
    finally:
        d.stop()
    # Told to stop, each sampler says "stopped": no problem of a sensor (a status asked meanwhile said DEGRADED).
    assert not [p for p in d.snapshot()["problems"] if p.startswith("steady")], d.snapshot()["problems"]
    text = run_summary(d)
    ended = [line for line in text.splitlines() if line.startswith("  ! flaky ended ")]
    assert len(ended) == 1 and "no answer (no ACK): check wiring" in ended[0], text
    assert not any(line.startswith("  ! steady") for line in text.splitlines()), text
    # Its file deleted after the run: the first line no longer says the drive is all there.
    assert "next:" in text and f"  logger info {d.recorder.files()[0]}" in text
    # The plot it suggests needs matplotlib, an optional extra: without it the line says so (the command, typed,
    # only failed with "matplotlib is not installed").
    plot = next(line for line in text.splitlines() if line.startswith("  logger plot "))
    assert plot.endswith("--out plots/") or "(needs matplotlib" in plot  # a board may lack the optional extra
    monkeypatch.setattr("logger.runtime.summary.find_spec", lambda name: None)
    plot = next(line for line in run_summary(d).splitlines() if line.startswith("  logger plot "))
    assert plot.endswith("--out plots/   (needs matplotlib: pip install matplotlib)"), plot
    (gone,) = d.recorder.files()
    gone.unlink()
    text = run_summary(d)
    first = text.splitlines()[0]
    assert first.endswith("(1 file of them no longer there: deleted or moved)"), first
    # ... and suggests no command on it (logger info of a deleted file fails): none left, no "next:" at all.
    assert "next:" not in text and str(gone) in text, text


# ---- problems into the journal ---------------------------------------------------------------------------------

def test_each_problem_is_logged_when_it_appears_and_clears() -> None:
    j = ProblemJournal(burst=3, refill_s=10.0)
    assert j.update(["pps: no sample for 4.1 s"], 0.0) == [(logging.WARNING, "problem: pps: no sample for 4.1 s")]
    assert j.update(["pps: no sample for 5.1 s"], 1.0) == []  # the same problem while it lasts
    assert j.update([], 2.0) == [(logging.INFO, "resolved: pps: no sample for 5.1 s (lasted 2 s)")]


def test_a_lasting_problem_is_said_once_a_minute_with_how_long() -> None:
    j = ProblemJournal(still_every_s=60.0)
    lines = []
    for second in range(200):
        lines += j.update([f"gnss: no fix for {second} s (0 satellites in use)"], float(second))
    lines += j.update([], 200.0)
    assert [text for _, text in lines] == [
        "problem: gnss: no fix for 0 s (0 satellites in use)",
        "still: gnss: no fix for 60 s (0 satellites in use) (for 60 s)",
        "still: gnss: no fix for 120 s (0 satellites in use) (for 120 s)",
        "still: gnss: no fix for 180 s (0 satellites in use) (for 180 s)",
        "resolved: gnss: no fix for 199 s (0 satellites in use) (lasted 200 s)"]


def test_the_lines_that_reach_a_person_are_capped_whatever_fails() -> None:
    """Many faults at once, each within its own limit: still at most the burst, then a few lines a second, the
    count of those held back in the next one through; errors always pass."""
    from logger.runtime.logs import LineCap

    now = [0.0]
    cap = LineCap(per_s=5.0, burst=20, clock=lambda: now[0])

    def record(level: int, msg: str) -> logging.LogRecord:
        return logging.LogRecord("x", level, __file__, 1, msg, None, None)

    passed = [r for r in (record(logging.WARNING, f"fault {i}") for i in range(1000)) if cap.filter(r)]
    assert len(passed) == 20  # the burst, all in the same instant
    error = record(logging.ERROR, "the writer died")
    assert cap.filter(error)  # an error is never held back, and it tells what was
    assert error.getMessage() == "the writer died (980 log lines held back before this one)"
    now[0] = 10.0  # ten seconds later the bucket is full again: another burst, no more
    later = [r for r in (record(logging.WARNING, f"fault {i}") for i in range(1000)) if cap.filter(r)]
    assert len(later) == 20 and later[0].getMessage() == "fault 0"
    now[0] = 11.0  # a second on: five more, the first telling of the 980 held back meanwhile
    again = [r for r in (record(logging.WARNING, f"fault {i}") for i in range(10)) if cap.filter(r)]
    assert len(again) == 5 and again[0].getMessage() == "fault 0 (980 log lines held back before this one)"


def test_a_flapping_sensor_is_rate_limited_and_counted() -> None:
    j = ProblemJournal(burst=3, refill_s=10.0)
    lines = []
    for second in range(20):  # appears and clears every other second
        lines += j.update(["imu: retrying: no answer"] if second % 2 == 0 else [], float(second))
    problems = [text for _, text in lines if text.startswith("problem")]
    # 3 from the burst, one more once a token refilled (telling how many were not logged), then silence.
    assert len(problems) == 4, lines
    assert "appeared 2 more times, not logged" in problems[3]
    assert len([t for _, t in lines if t.startswith("resolved")]) == 4


def test_the_service_loop_reports_from_the_health_loop_s_snapshot_while_it_is_fresh(
        tmp_path: Path, systemd: tuple[FakeSystemd, str]) -> None:
    """One snapshot a second serves both loops: the service loop's status line and journal take the health loop's
    while it is at most SHARED_SNAPSHOT_NS old, and a snapshot of their own once it is older (that loop stopped)."""
    from logger.runtime.daemon import SHARED_SNAPSHOT_NS

    _, path = systemd
    d = make_daemon(tmp_path, [TickSource("a")], path)
    taken = [0]
    snapshot = d.snapshot

    def counted() -> dict[str, object]:
        taken[0] += 1
        return snapshot()

    d.snapshot = counted  # type: ignore[method-assign]
    own = d._recent_snapshot()  # no health snapshot yet
    assert taken[0] == 1
    d._health_snapshot = shared = snapshot()
    assert d._recent_snapshot() is shared and taken[0] == 1
    shared["t_mono_ns"] = d.tb.monotonic_ns() - SHARED_SNAPSHOT_NS - 1
    fresh = d._recent_snapshot()
    assert fresh is not shared and fresh is not own and taken[0] == 2


def test_a_full_disk_is_one_line_that_lasts_and_the_summary_and_status_say_the_time_lost(
        tmp_path: Path, systemd: tuple[FakeSystemd, str], caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The review's disk-full runs: the start-up line read "recording to not recording: ...", the problem named the
    absolute path (2-3 lines on 80x24) and changed at every retry (the journal said "resolved" while still full),
    the summary said "recorded 200.0 s of drive" over 50 s without a file, the status row "0 dropped"."""
    import logger.recording.recorder as recorder_module
    from logger.cli.status_view import render
    from logger.runtime.summary import run_summary

    monkeypatch.setattr(recorder_module, "RETRY_S", 0.1)
    fake, path = systemd
    d = make_daemon(tmp_path, [TickSource("steady")], path)
    d.recorder.settings.min_free_bytes = 1 << 62  # full from the start
    caplog.set_level(logging.INFO)
    journal = ProblemJournal()
    said: list[str] = []
    d.start()
    try:
        fake.wait_for("READY")
        assert "started without recording into" in caplog.text and "recording to not" not in caplog.text
        wait_until(lambda: d.recorder.status().down_s >= 1.5 and d.recorder.status().unrecorded, "a spell without disk")
        for second in range(3):
            snap = d.snapshot()
            said += [t for _, t in journal.update(snap["problems"], float(second))]
            time.sleep(0.15)  # retries in between
        (problem,) = [p for p in snap["problems"] if p.startswith("recorder:")]
        assert problem.startswith("recorder: not recording: disk full (") and str(tmp_path) not in problem, problem
        assert len(said) == 1 and said[0].startswith("problem: recorder: not recording: disk full"), said
        screen = render(snap, 80, 24).splitlines()
        assert all(len(line) < 80 for line in screen)
        assert f"! {problem}" in screen  # one line
        rec_rows = [line for line in screen if line.startswith("rec ")]
        assert rec_rows and rec_rows[0].startswith("rec     disk-full ") and "no file started" in rec_rows[0], screen
        assert any(line.startswith("        not recorded for ") for line in screen), screen
        d.recorder.settings.min_free_bytes = 0
        wait_until(lambda: d.recorder.status().state == "recording", "recording once there is room")
        wait_until(lambda: d.recorder.status().written, "records on disk")
    finally:
        d.stop()
    text = run_summary(d)
    head = text.splitlines()[0]
    assert " s of a " in head and " s run into 1 file" in head, head
    assert any(line.startswith("  ! not recording for ") for line in text.splitlines()), text
    # The topics' rates are over the time it recorded, and say so (over the whole run they read low by the spell).
    (header,) = [line for line in text.splitlines() if line.lstrip().startswith("topic ")]
    assert header.endswith("(rates while recording)"), text
    rec = d.recorder.status()
    recorded_s = d.run_span_s - min(rec.down_s, d.run_span_s)
    lines = text.splitlines()
    topic, messages, rate = lines[lines.index(header) + 1].split()[:3]
    assert int(messages) == rec.written[topic] and float(rate) == pytest.approx(rec.written[topic] / recorded_s,
                                                                                 abs=0.01), text
    (f,) = d.recorder.files()
    assert f.name.endswith("_0001.mcap")  # the failed opens took no part number


def test_a_sensor_opened_again_counts_its_silence_from_then(tmp_path: Path) -> None:
    """A receiver unplugged for 20 s and back: the moment it was open again its row said silent, "no sample for
    27 s" (its last sample was before it went), and the journal logged a change. Its silence counts from the
    reopening, as at the first start: starting until a sample comes or its rate says one is overdue."""
    from types import SimpleNamespace

    d = make_daemon(tmp_path, [], "")
    now = d.tb.monotonic_ns()

    def judged(age_s: float | None, opened_s_ago: float) -> tuple[str, str]:
        health = SimpleNamespace(heartbeat_mono_ns=now, ok_since_mono_ns=now - int(opened_s_ago * 1e9))
        snap = {"name": "gnss", "state": "ok", "last_error": "", "last_sample_age_s": age_s, "rate_hz": 1.0,
                "measured_rate_hz": 1.0}
        problem = d._sensor_problem(SimpleNamespace(health=health), snap, now, None)  # type: ignore[arg-type]
        return snap["state"], problem

    assert judged(27.0, 0.5) == ("starting", "")  # opened again half a second ago: not silent for 27 s
    assert judged(27.0, 6.0) == ("silent", "no sample since it was opened 6 s ago")  # overdue since then
    assert judged(0.5, 6.0) == ("ok", "")  # a sample since it was opened
    assert judged(7.0, 60.0) == ("silent", "no sample for 7 s")  # open all along, then quiet
