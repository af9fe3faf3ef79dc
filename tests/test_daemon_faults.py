"""Faults injected at the bus while the whole daemon runs: the failing sensor is reported and comes back,
every other sensor keeps logging, and what was recorded stays readable."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from logger.compose import build
from logger.config import defaults
from logger.recording.drive import iter_messages, open_drive
from logger.recording.files import is_finished
from logger.runtime.status_socket import fetch


def sim_config(tmp_path: Path) -> Any:
    """Every sensor simulated; files, socket and clock state kept inside the test's folder."""
    cfg = defaults(sim=True)
    cfg.values["logger"].update(out_dir=str(tmp_path / "drives"), status_socket=str(tmp_path / "status.sock"),
                                state_dir=str(tmp_path / "state"))
    return cfg


@pytest.fixture
def running(tmp_path: Path) -> Iterator[tuple[Any, Any, Path]]:
    cfg = sim_config(tmp_path)
    cfg.values["sim"]["time_scale"] = 4.0
    daemon, vehicle = build(cfg, duration_s=3600)
    daemon.start()
    try:
        yield daemon, vehicle, tmp_path
    finally:
        daemon.stop()


def wait_for(what: str, predicate: Callable[[], bool], timeout_s: float = 60.0) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for: {what}")


def sensor(snap: dict, name: str) -> dict:
    return next(s for s in snap["sensors"] if s["name"] == name)


def samples(daemon: Any) -> dict[str, int]:
    return {s.health.name: s.health.samples for s in daemon.samplers}


def others_keep_logging(daemon: Any, failing: str, during: Callable[[], None]) -> None:
    """Run ``during`` and check that every sensor but ``failing`` delivered samples meanwhile."""
    before = samples(daemon)
    during()
    after = samples(daemon)
    stalled = [n for n in before if n != failing and after[n] <= before[n]]
    assert not stalled, f"stalled while {failing} failed: {stalled}"


@pytest.mark.slow_on_board
def test_each_fault_is_reported_while_it_lasts_and_the_sensor_comes_back(running: tuple[Any, Any, Path]) -> None:
    daemon, vehicle, tmp = running
    sock = tmp / "status.sock"
    wait_for("all sensors ok", lambda: all(s["state"] == "ok" for s in fetch(sock)["sensors"]))
    wait_for("pps and gnss delivering", lambda: samples(daemon)["pps"] > 2 and samples(daemon)["gnss"] > 2)

    # 1. The MPU-6050 stops answering on the I2C bus (loose connector); the barometer on the same bus goes on.
    def imu_unplugged() -> None:
        vehicle.i2c.unplug(0x68)
        wait_for("imu reported", lambda: sensor(fetch(sock), "imu")["state"] in ("retrying", "missing"))
        snap = fetch(sock)
        assert snap["verdict"] == "degraded" and any(p.startswith("imu:") for p in snap["problems"])
        assert "no answer" in sensor(snap, "imu")["last_error"] or "I2C" in sensor(snap, "imu")["last_error"]
        time.sleep(1.0)

    others_keep_logging(daemon, "imu", imu_unplugged)
    vehicle.i2c.replug(0x68)
    wait_for("imu back", lambda: sensor(fetch(sock), "imu")["state"] == "ok")
    assert sensor(fetch(sock), "imu")["reconnects"] >= 1

    # 2. Transient I2C errors (EIO) on the bus: both chips see them, both come back.
    errors_before = sensor(fetch(sock), "imu")["errors"] + sensor(fetch(sock), "baro")["errors"]
    vehicle.i2c.fail_next(count=3)
    wait_for("errors counted",
             lambda: sensor(fetch(sock), "imu")["errors"] + sensor(fetch(sock), "baro")["errors"] > errors_before)
    wait_for("i2c sensors ok", lambda: all(sensor(fetch(sock), n)["state"] == "ok" for n in ("imu", "baro")))

    # 3. The receiver's USB serial vanishes and comes back under the same name.
    def gnss_unplugged() -> None:
        vehicle.gnss.vanish()
        wait_for("gnss reported", lambda: sensor(fetch(sock), "gnss")["state"] in ("retrying", "missing"))
        time.sleep(1.0)

    others_keep_logging(daemon, "gnss", gnss_unplugged)
    fixes_before = daemon.recorder.status().written.get("/gnss/fix", 0)
    vehicle.gnss.reappear()
    wait_for("gnss back", lambda: sensor(fetch(sock), "gnss")["state"] == "ok" and
             daemon.recorder.status().written.get("/gnss/fix", 0) > fixes_before + 2)

    # 4. Garbage on the receiver's line: counted and skipped by the framer, fixes keep coming.
    fixes_before = daemon.recorder.status().written.get("/gnss/fix", 0)
    for _ in range(3):
        vehicle.gnss.inject_garbage(400)
    wait_for("fixes through garbage", lambda: daemon.recorder.status().written.get("/gnss/fix", 0) > fixes_before + 3)
    wait_for("garbage reported", lambda: any(p.startswith("gnss: bytes of garbage") for p in fetch(sock)["problems"]))
    assert sensor(fetch(sock), "gnss")["incidents"]["bytes of garbage on the serial line"] >= 400

    # 5. The ELM327 resets mid-drive (a voltage dip): the driver sets it up again and speed keeps coming.
    obd_before = samples(daemon)["obd"]
    vehicle.elm327.reset()
    wait_for("speed after reset", lambda: samples(daemon)["obd"] > obd_before + 6)
    assert sensor(fetch(sock), "obd")["state"] == "ok"
    wait_for("reset reported", lambda: any(p.startswith("obd: ELM327 reset itself") for p in fetch(sock)["problems"]))
    assert sensor(fetch(sock), "obd")["incidents"] == {"ELM327 reset itself and was set up again": 1}

    # 6. The disk fills up: recording stops with a clear, critical status; the sensors keep sampling; when
    #    space is back, a new file starts. The file that was open is finished, not corrupted.
    first_file = Path(daemon.recorder.status().file)
    daemon.recorder.settings.min_free_bytes = 1 << 62

    def disk_full() -> None:
        wait_for("disk-full reported", lambda: fetch(sock)["recorder"]["state"] == "disk-full")
        snap = fetch(sock)
        assert snap["verdict"] == "critical"
        assert any(p.startswith("recorder: not recording: disk full (") and " free, " in p for p in snap["problems"])
        time.sleep(1.0)

    others_keep_logging(daemon, "", disk_full)
    assert is_finished(first_file)
    daemon.recorder.settings.min_free_bytes = 1 << 20
    wait_for("recording again", lambda: fetch(sock)["recorder"]["state"] == "recording")
    assert Path(fetch(sock)["recorder"]["file"]) != first_file
    wait_for("healthy again", lambda: fetch(sock)["verdict"] == "ok", timeout_s=90)


def test_a_sensor_missing_at_start_is_reported_and_the_rest_records(tmp_path: Path) -> None:
    cfg = sim_config(tmp_path)
    cfg.values["obd"].update(source="elm327", port=str(tmp_path / "ttyUSB9"))  # not plugged in
    daemon, _ = build(cfg, duration_s=60)
    daemon.start()
    try:
        sock = tmp_path / "status.sock"
        wait_for("obd reported missing", lambda: sensor(fetch(sock), "obd")["state"] == "missing")
        wait_for("imu recording", lambda: daemon.recorder.status().written.get("/imu/batch", 0) > 5)
        snap = fetch(sock)
        assert snap["verdict"] == "degraded"
        assert any(p.startswith("obd: missing") and "ttyUSB9" in p for p in snap["problems"]), snap["problems"]
    finally:
        daemon.stop()


@pytest.mark.slow_on_board
def test_the_fifo_keeps_every_sample_at_1khz(tmp_path: Path) -> None:
    cfg = sim_config(tmp_path)
    cfg.values["imu"]["rate_hz"] = 1000.0
    daemon, _ = build(cfg, duration_s=60)
    daemon.start()
    try:
        h = next(s for s in daemon.samplers if s.health.name == "imu").health
        wait_for("8 s of 1 kHz samples", lambda: h.samples > 8000)
    finally:
        daemon.stop()
    (path,) = sorted((tmp_path / "drives").glob("*.mcap"))
    from test_daemon_sim import read_messages

    # One record per FIFO read, not per sample: the recorder's and the filter's cost no longer grows with the rate.
    raw = read_messages(path)
    assert "/imu" not in raw
    batches = [m for _, _, m in raw["/imu/batch"]]
    assert len(batches) < sum(len(b["t_mono_ns"]) for b in batches) / 10
    # Each batch is logged at its first sample's synchronised time.
    assert all(log == m["t_sync_ns"][0] for log, _, m in raw["/imu/batch"])
    # Read back, the samples are /imu records as a low rate records them.
    imu = [m.msg for m in iter_messages(open_drive([path]), ["/imu"])]
    assert sum(len(b["t_mono_ns"]) for b in batches) == len(imu)
    assert all(m["fifo"] for m in imu)
    assert [m["seq"] for m in imu] == list(range(len(imu)))
    h = next(s for s in daemon.samplers if s.health.name == "imu").health
    assert h.errors == 0, h
    # The 85-frame FIFO holds 85 ms: only a poll the host ran over 45 ms late (counted as delayed) can let it
    # overflow, and then the loss is counted in the record after it. Nothing is lost silently, and on a host that
    # ran every poll in time nothing is lost at all.
    lost_at = {i for i, m in enumerate(imu) if m["lost"]}
    assert len(lost_at) <= h.delayed, (len(lost_at), h)
    t = [m["t_mono_ns"] for m in imu]
    steps = [b - a for a, b in itertools.pairwise(t)]
    assert min(steps) > 0  # counted frames: a poll preempted mid-read does not send time back
    # Every silence over 2.5 periods in the stamps is one the daemon counted as a gap, after a delayed poll.
    assert sum(st > 2.5e6 for st in steps) <= h.gaps <= h.delayed, h
    if h.delayed == 0:
        assert not lost_at and h.gaps == 0
    # The chip's rate, from counted stamps, over the stretches between overflows (each restarts the count): on a
    # host loaded enough to delay polls past the FIFO's 85 ms, no single stretch need last 2 s, their sum does.
    cuts = [0, *sorted(lost_at), len(t)]
    stretches = [(a, b) for a, b in itertools.pairwise(cuts) if b - a > 1]
    span_s = sum(t[b - 1] - t[a] for a, b in stretches) / 1e9
    assert span_s > 2.0, (span_s, len(lost_at))
    rate = sum(b - 1 - a for a, b in stretches) / span_s
    assert abs(rate - 1000.0) < 2.0, rate


def test_a_deleted_output_folder_is_critical_within_two_seconds_then_recording_resumes(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The drives folder deleted under the running daemon (a user's `rm -r`): the status is critical with the
    reason within 2 s (its rows say so too), the journal says it, and the daemon records again in a new file."""
    import shutil

    from logger.recording.files import walk

    cfg = sim_config(tmp_path)
    cfg.values["recorder"]["flush_interval_s"] = 0.5
    daemon, _ = build(cfg, duration_s=3600)
    daemon.start()
    out, sock = tmp_path / "drives", tmp_path / "status.sock"
    try:
        wait_for("recording", lambda: daemon.recorder.status().on_disk_mono_ns.get("/imu/batch") is not None)
        shutil.rmtree(out)
        deleted = time.monotonic()
        seen: list[dict] = []

        def critical() -> bool:
            seen.append(fetch(sock))
            return seen[-1]["verdict"] == "critical"

        wait_for("critical", critical, timeout_s=10.0)
        assert time.monotonic() - deleted <= 2.0 + 0.5  # one flush (0.5 s) and the socket's cache, well within 2 s
        assert "recorder: not recording: the output folder was deleted" in seen[-1]["problems"]  # the path: in the log
        wait_for("recording again in a new file",
                 lambda: fetch(sock)["recorder"]["state"] == "recording" and any(out.glob("*.mcap")), 30.0)
        wait_for("new records on disk", lambda: walk(next(out.glob("*.mcap"))).messages != [], 30.0)
        assert fetch(sock)["verdict"] in ("ok", "degraded")
    finally:
        daemon.stop()
    assert f"the output folder {out} was deleted while recording" in caplog.text
    (again,) = sorted(out.glob("*.mcap"))
    assert is_finished(again)
    # The run's rates are of every record that reached the disk, the deleted ones too: of those left alone, every
    # sensor's rate in the summary was understated by the share deleted (0.70 Hz for a 1 Hz barometer).
    from logger.runtime.summary import run_summary

    rec = daemon.recorder.status()
    assert rec.deleted_samples.get("/imu/batch", 0) > 0
    text = run_summary(daemon)
    assert "(rates of all recorded, deleted too)" in text, text
    (imu,) = [line for line in text.splitlines() if line.startswith("  /imu/batch ")]
    assert f"({rec.samples['/imu/batch'] + rec.deleted_samples['/imu/batch']} samples, " in imu, imu


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")  # the thread's end is the case
def test_the_daemons_service_thread_ending_is_critical_in_the_status(tmp_path: Path, monkeypatch) -> None:
    """The thread that logs the problems and answers systemd's watchdog ended on an error (the journal's KeyError of
    two components changing their problem in one second): `logger status` said OK while no problem reached the
    journal and systemd was about to kill the daemon. The status now says so, critical, and names the thread."""
    from logger.runtime.daemon import Daemon

    def broken(self: Any, problems: list[str], verdict: str) -> None:
        raise KeyError("a bug")

    monkeypatch.setattr(Daemon, "_log_problem_changes", broken)
    daemon, _ = build(sim_config(tmp_path), duration_s=3600)
    daemon.start()
    try:
        wait_for("the service thread's end", lambda: any(t.name == "service" and not t.is_alive()
                                                           for t in daemon._threads), 30.0)
        snap = fetch(tmp_path / "status.sock")
        assert snap["verdict"] == "critical" and (
            "daemon: its service thread has ended (the journal's problem lines and systemd's watchdog); restart the "
            "service") in snap["problems"], snap["problems"]
    finally:
        daemon.stop()


def test_a_cold_start_receivers_unconfirmed_leap_count_is_in_the_status_until_it_says_otherwise(
        tmp_path: Path) -> None:
    """The simulated receiver on a cold start (`[sim] leap_unconfirmed_s`): its NAV-TIMEGPS says the leap count is
    not yet the broadcast one for the first seconds after its fix. Through the real chain (UBX bytes on a pty, the
    decoder, the records, the clock, the status): the fix records say leap_unknown, the status names the doubt, and
    both end when the receiver says the count is confirmed."""
    cfg = sim_config(tmp_path)
    cfg.values["sim"].update(time_scale=4.0, leap_unconfirmed_s=12.0)
    daemon, _ = build(cfg, duration_s=3600)
    sock = tmp_path / "status.sock"
    daemon.start()
    seen: list[list[str]] = []
    try:
        def doubted() -> bool:
            seen.append(fetch(sock)["problems"])
            return any("no broadcast leap-second count" in p for p in seen[-1])

        wait_for("the leap doubt in the status", doubted)
        wait_for("the doubt gone", lambda: not doubted() and samples(daemon)["gnss"] > 20)
    finally:
        daemon.stop()
    said = [m.msg.get("leap_unknown") for m in iter_messages(open_drive(sorted((tmp_path / "drives").glob("*.mcap"))),
                                                             ["/gnss/fix"]) if m.msg.get("gnss_time_ns")]
    first_false = said.index(False)
    assert first_false >= 5 and set(said[:first_false]) == {True} and set(said[first_false:]) == {False}, said
