"""The daemon: wires sensors, clock, recorder and status together, and shuts down cleanly.

Start order matters for data safety: the files a previous crash left unfinished are listed first, then the
recorder opens its new file (a bad output folder fails here, before any sensor is touched), the sampler threads
and the status server start, and only then are the listed files recovered, in a thread of their own: recovering
an hour's file takes minutes on the board's one core, and a drive must not go unrecorded (nor ``logger status``
say "not running") meanwhile. Stop order is the reverse, and the recorder drains its queue before finishing the
file; a recovery still running is given up (the file is kept as it was, for the next start).
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import logging
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from logger.config import Config
from logger.recording.files import McapFileError, RecoveryCancelled, being_written, is_finished, recover
from logger.recording.recorder import RETRY_S, Recorder
from logger.recording.records import (
    NO_FIX,
    clock_observer,
    health_record,
    stamped_batch,
    stamped_record,
    sync_record,
)
from logger.recording.settings import RecorderSettings
from logger.recording.storage import storage_problem
from logger.recording.topics import HEALTH, SYNC, TOPICS
from logger.runtime.gnss_watch import GnssWatch
from logger.runtime.journal import ProblemJournal
from logger.runtime.notify import Notifier
from logger.runtime.sampler import Reading, Sampler
from logger.runtime.sources import Plan
from logger.runtime.status_socket import SocketInUse, StatusServer
from logger.runtime.timebase import TimeBase, host_timebase
from logger.words import plural, size_text
from sync.stamp import FREERUN, FreeRunClock, Stamp, StampClock

log = logging.getLogger(__name__)

HEARTBEAT_STALE_S = 10.0
DROP_WINDOW_NS = 60 * 1_000_000_000
MISLABEL_SHOW_S = 600  # drive seconds a pairing found wrong stays a problem: the operator must see it
# What each of the daemon's own threads does, for the line that says it ended.
DAEMON_THREADS = {"service": "the journal's problem lines and systemd's watchdog",
                  "health": "the /health record", "sim-truth": "the simulation's truth records"}
# systemd's watchdog is pinged only while every thread proved it is alive within this many real seconds. It must
# exceed the longest legitimate silence of a thread: a sensor's reconnect back-off (10 s of drive) plus an open
# that waits for the device (receiver setup by ACK, an ELM327 protocol search).
HEARTBEAT_BOUND_S = 60.0
CLOCK = "clock"  # the clock's entry among the sensors' in Daemon.time_in_state
SILENT = "silent"  # the row state of a running sensor from which nothing comes (a receiver without a fix: NO_FIX)
# The service loop's status line and journal take the health loop's snapshot while it is this fresh (drive ns):
# that loop takes one every drive second, and a second snapshot a second cost the daemon as much again.
SHARED_SNAPSHOT_NS = 1_500_000_000
OPEN_GRACE_S = 15.0  # real seconds from the start a sensor's first open may take before it is a problem
READY_TIMEOUT_S = 60.0  # READY=1 even if a sensor's first open has not returned by then: degraded, not failed


@dataclass
class Attachments:
    """What a run attaches to the daemon beyond its sensors: periodic publishers (the simulation's truth), taps (the
    navigator), status sections, metadata for the file, and what to close at the end."""

    periodic: list[tuple[float, Callable[[], list[Reading]]]] = field(default_factory=list)
    taps: list[Any] = field(default_factory=list)  # objects with offer(topic, payload) -> None, never blocking
    # Extra status sections; one's "problems" (a list of lines) count in the status's verdict, as the sensors' do.
    sections: dict[str, Callable[[], dict[str, Any]]] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    close: list[Callable[[], None]] = field(default_factory=list)
    # Queues beside the recorder's (the navigator's): (depth, size) now, so that a simulated drive slows down
    # before one of them fills and drops records.
    backlogs: list[Callable[[], tuple[int, int]]] = field(default_factory=list)


def unfinished_files(out_dir: Path) -> list[Path]:
    """The MCAP files in ``out_dir`` that were not finished: what a crash left for recovery. Listed before the
    recorder opens its own (unfinished while it records), so that recovery can never take the file being
    written; nor one another logger is writing (:func:`being_written`)."""
    return [path for path in sorted(out_dir.glob("*.mcap")) if not is_finished(path) and not being_written(path)]


def recover_file(path: Path, cancel: Callable[[], bool] | None = None, reserve_bytes: int = 0) -> str:
    """Recover one unfinished file in place; returns its line for the log (what was kept and lost, or why not).

    ``reserve_bytes``: free space the copy must leave (the recorder's minimum, while it records beside the
    recovery): the drive being recorded comes first, and the cut file is readable as it is meanwhile (the drive
    reader reads up to the cut). ``cancel``: asked between chunks; the file is then kept as it was."""
    size = 0
    try:
        size = path.stat().st_size
        if reserve_bytes:
            st = os.statvfs(path.parent)
            free = st.f_bavail * st.f_frsize
            if free - size < reserve_bytes:
                return (f"did not recover {path.name}: its copy (up to {size_text(size)}) would leave less than "
                        f"the {size_text(reserve_bytes)} the recording needs free ({size_text(free)} free); it "
                        "is kept as it was (readable as it is), for the next start or `logger recover`")
        report = recover(path, cancel=cancel)
    except RecoveryCancelled:
        return f"recovery of {path.name} stopped with the daemon: it is kept as it was, for the next start"
    except OSError as exc:
        if exc.errno == errno.ENOSPC:
            return (f"could not recover {path.name}: no space left on the disk for its recovered copy "
                    f"({size_text(size)} at most); it is kept as it was, for "
                    "`logger recover` once there is room")
        return f"could not recover {path.name}: {exc.strerror or exc}"
    except McapFileError as exc:
        return f"could not recover {path.name}: {exc}"
    lost = report.lost()  # the same clause as `logger recover` gives: what was cut, what was damaged
    return (f"recovered {path.name}: {report.messages} messages from {report.chunks_ok} chunks"
            + (f"; {lost}" if lost else "; nothing lost"))


def remove_stale_copies(out_dir: Path) -> None:
    """Delete the copies of recoveries cut short (``*.mcap.recovering``): their sources are still there, whole,
    and are recovered again."""
    for stale in out_dir.glob("*.mcap.recovering"):
        stale.unlink(missing_ok=True)


def recover_unfinished(out_dir: Path) -> list[str]:
    """Recover every file a crash left unfinished, one after the other; returns one line per file for the log."""
    remove_stale_copies(out_dir)
    return [recover_file(path) for path in unfinished_files(out_dir)]


class Daemon:
    def __init__(self, cfg: Config, plans: list[Plan], timebase: TimeBase | None = None,
                 clock: StampClock | None = None, attachments: Attachments | None = None, out_dir: Path | None = None,
                 status_socket: Path | None = None, mode: str = "", notifier: Notifier | None = None) -> None:
        self.cfg = cfg
        self.tb = timebase or host_timebase()
        self.clock = clock or FreeRunClock(self.tb.monotonic_ns, imu_rate_hz=cfg["imu"]["rate_hz"])
        self.attachments = attachments or Attachments()
        self.plans = plans
        self.mode = mode
        self.out_dir = Path(out_dir or cfg["logger"]["out_dir"])
        self.status_socket = Path(status_socket or cfg["logger"]["status_socket"])
        self.recorder = Recorder(
            RecorderSettings.from_config(cfg["recorder"], self.out_dir), TOPICS, metadata=self.attachments.metadata,
            monotonic_ns=self.tb.monotonic_ns, time_scale=lambda: self.tb.scale, synced_unix_ns=self._synced_unix_ns)
        self.stop_event = threading.Event()
        self.samplers: list[Sampler] = []
        self._seq: dict[str, itertools.count[int]] = {}
        # Per topic, the board time and stamp of its last record: records of one read (a burst of NMEA epochs read
        # together) share their board time, and each one observed first steers the clock (a fix labels an edge):
        # stamped one by one, the later ones came out a few hundred ns earlier than the ones before, and readers
        # that go by log time met the epochs out of order (export dropped them as such).
        self._last_stamp: dict[str, tuple[int, Stamp]] = {}
        self._batch_seq: dict[str, int] = {}  # a batch topic's next sample number (one sampler thread each)
        self._started_mono = 0
        self._stopped_mono: int | None = None
        self.final_sensors: list[dict[str, Any]] | None = None  # the sensor rows when the run was told to stop
        self._threads: list[threading.Thread] = []
        self.status_server: Any = None
        self.startup_lines: list[str] = []  # the recovery thread's lines, one per cut file, as they are logged
        self._recovery: threading.Thread | None = None
        self._recovering: tuple[str, int] | None = None  # (name, bytes) of the file the recovery thread is on
        # Consumers of the stamped records besides the recorder (the navigator): ``offer`` must never block.
        # the receiver's fix, satellites and accuracy for the status, and its raw observations when asked for
        self.gnss_watch = GnssWatch(raw_asked=bool(cfg["gnss"]["raw_observations"]) and cfg["gnss"]["configure"]
                                    and cfg["gnss"]["source"] in ("serial", "sim"))
        self.taps: list[Any] = [self.gnss_watch, *self.attachments.taps]
        self._observe = clock_observer(self.clock)  # what each record tells the clock (PPS, time messages)
        self._drop_history: deque[tuple[int, int]] = deque()
        self._health_snapshot: dict[str, Any] | None = None  # the health loop's last, for the service loop
        # Service manager: READY, WATCHDOG, STATUS, STOPPING (no-ops outside systemd).
        self.notifier = notifier or Notifier.from_env()
        self.heartbeat_bound_s = HEARTBEAT_BOUND_S
        self.ready_timeout_s = READY_TIMEOUT_S
        self.ready = threading.Event()
        self.watchdog_pings = 0
        self._started = threading.Event()
        self.problem_journal = ProblemJournal()
        # name (a sensor's, or CLOCK) -> state -> drive seconds in it, counted by the health loop once a second
        self.time_in_state: dict[str, dict[str, float]] = {}

    # ---- the sink every sampler calls: stamp, count, queue ------------------------------------------------
    def sink(self, r: Reading) -> None:
        if r.times is not None:
            self._sink_batch(r)
            return
        seq = self._seq.get(r.topic)
        if seq is None:
            seq = self._seq.setdefault(r.topic, itertools.count())
        payload = r.payload
        observe = self._observe.get(r.topic)
        if observe is not None:
            observe(payload, r.t_mono_ns)  # PPS edges and time messages steer the clock
        own = None if r.stamped else payload.get("t_sync_ns")
        if isinstance(own, int):
            # A record that carries its own time (the filter's /nav/fix and /nav/state, stamped when their sample
            # was): logged at it, as replay logs them. Stamped again now, its log time moved by the clock's
            # corrections since (microseconds), and live and replayed fixes of one sample did not line up.
            log_ns = own
        else:
            last = self._last_stamp.get(r.topic)
            if last is not None and last[0] == r.t_mono_ns:
                stamp = last[1]
            else:
                stamp = self.clock.stamp(r.t_mono_ns)
                self._last_stamp[r.topic] = (r.t_mono_ns, stamp)
            if r.stamped:
                payload = stamped_record(r.t_mono_ns, stamp, next(seq), payload)
            log_ns = stamp.t_sync_ns
        self.recorder.submit(r.topic, payload, log_ns, r.t_mono_ns)
        for tap in self.taps:
            tap.offer(r.topic, payload)

    def _sink_batch(self, r: Reading) -> None:
        """A batch of samples (a FIFO read): every sample stamped, one record; its log time is the first sample's,
        so readers can put each sample back in time order among the other topics (logger.recording.drive)."""
        times = r.times
        assert times is not None
        if not times:
            return
        observe = self._observe.get(r.topic)
        if observe is not None:
            observe(r.payload, r.t_mono_ns)
        stamps = self.clock.stamp_many(times)
        seq = self._batch_seq.get(r.topic, 0)
        self._batch_seq[r.topic] = seq + len(times)
        payload = stamped_batch(stamps, seq, r.payload)
        self.recorder.submit(r.topic, payload, stamps.t_sync_ns[0], times[0])
        for tap in self.taps:
            tap.offer(r.topic, payload)

    # ---- life cycle ---------------------------------------------------------------------------------------
    def start(self) -> None:
        # The status socket first: another logger answering on it is running with this configuration, and a second
        # one took its open file for a crash's and rewrote it under it (its start-up recovery), recording into the
        # same folder. One logger at a time: refused before anything is opened or recovered.
        try:
            self.status_server = StatusServer(self.status_socket, self.snapshot)
        except SocketInUse as exc:
            raise OSError(errno.EADDRINUSE, f"{exc.strerror}: one logger records at a time; stop that one first",
                          str(self.status_socket)) from None
        except OSError as exc:
            log.error("status socket %s unavailable (%s); `logger status` will not work", self.status_socket,
                      exc.strerror or exc)
        self._start_thread("service", self._service_loop)  # pings while the sensors' first opens wait, too
        if storage_problem(self.out_dir) is None:  # else the recorder says why it records nothing, and waits
            self.out_dir.mkdir(parents=True, exist_ok=True)
        # Listed before the recorder opens its file, recovered after everything has started (_recover_cut_files).
        cut = unfinished_files(self.out_dir)
        remove_stale_copies(self.out_dir)
        self._started_mono = self.tb.monotonic_ns()
        path = self.recorder.start()
        if path is not None:
            log.info("recording to %s", path)
        else:  # the recorder said why (disk full, read-only, ...) in its own line; this one says what follows
            log.warning("started without recording into %s (%s); the recorder tries again every %.0f s",
                        self.out_dir, self.recorder.status().detail, RETRY_S)
        for plan in self.plans:
            s = Sampler(plan.source, self.sink, self.tb, plan.rate_hz, self.stop_event, plan.expected_hz)
            self.samplers.append(s)
        for s in self.samplers:
            s.start()
        self._start_thread("health", self._health_loop)
        for period, fn in self.attachments.periodic:
            self._start_thread("sim-truth", self._periodic_loop, period, fn)
        if self.status_server is not None:
            self.status_server.start()
        self._started.set()
        if cut:
            # Not one of self._threads: it ends when it is done, which is no hang for the watchdog to see.
            self._recovery = threading.Thread(target=self._recover_cut_files, args=(cut,), name="recovery",
                                              daemon=True)
            self._recovery.start()

    def _recover_cut_files(self, files: list[Path]) -> None:
        """Recover what the last run left unfinished while this one records (``files``, listed before the
        recorder opened its own), each file's line logged as it is done and the file shown in the status while
        it is recovered. At the lowest CPU priority the host gives a thread: the sensors' and the writer's
        threads share the board's one core with it and must keep their schedule."""
        with contextlib.suppress(OSError, AttributeError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)  # this thread only (Linux)
        reserve = self.recorder.settings.min_free_bytes
        for i, path in enumerate(files):
            if self.stop_event.is_set():
                line = (f"{plural(len(files) - i, 'cut file')} left unrecovered by the stop, for the next start: "
                        f"{', '.join(p.name for p in files[i:])}")
                self.startup_lines.append(line)
                log.warning(line)
                return
            if path in self.recorder.files():  # cannot be (listed before it opened one); never recover it
                continue
            with contextlib.suppress(OSError):
                self._recovering = (path.name, path.stat().st_size)
            try:
                line = recover_file(path, self.stop_event.is_set, reserve)
            except Exception:  # a bug must not end the recording: the file stays as it was
                log.exception("recovering %s failed", path.name)
                continue
            finally:
                self._recovering = None
            self.startup_lines.append(line)
            log.warning(line)

    def _start_thread(self, name: str, target: Callable[..., None], *args: Any) -> None:
        t = threading.Thread(target=target, args=args, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    @property
    def ended_mono_ns(self) -> int:
        """When the run was told to stop (drive time), or now while it runs."""
        return self._stopped_mono if self._stopped_mono is not None else self.tb.monotonic_ns()

    @property
    def run_span_s(self) -> float:
        """Drive time from the start of the recording to the stop (or to now while running)."""
        return max(0.0, (self.ended_mono_ns - self._started_mono) / 1e9) if self._started_mono else 0.0

    def stop(self) -> None:
        if self._stopped_mono is None:
            self._stopped_mono = self.tb.monotonic_ns()
            if self._started.is_set():
                # The sensors as they were when the run was told to stop (each says "stopped" once it has): what the
                # summary says a sensor ended as.
                self.final_sensors = self._sensor_rows(self._stopped_mono)[0]
        self.notifier.stopping("stopping: finishing the file")
        self.stop_event.set()
        if self._recovery is not None:
            self._recovery.join(10.0)  # it gives up between two chunks
            if self._recovery.is_alive():
                log.error("the recovery of a cut file did not stop within 10 s")
        for s in self.samplers:
            s.join(5.0)
            if s.is_alive():
                log.error("%s did not stop within 5 s", s.name)
        for t in self._threads:
            t.join(2.0)
        if self.status_server is not None:
            self.status_server.close()
        self.recorder.stop()
        for fn in self.attachments.close:
            try:
                fn()
            except Exception:
                log.debug("closing a simulated device failed", exc_info=True)

    def run(self, duration_s: float | None = None) -> int:
        """Run until SIGTERM/SIGINT/SIGHUP or ``duration_s`` of drive time; returns the process exit code.

        SIGHUP is a dropped SSH session under ``logger run`` in the foreground: the file is finished as on SIGTERM
        (its default would end the process like ``kill -9``, leaving the file for recovery)."""
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
                signal.signal(sig, lambda *_: self.stop_event.set())
        self.start()
        end = None if duration_s is None else self._started_mono + int(duration_s * 1e9)
        while not self.stop_event.is_set():
            if end is not None:
                left = (end - self.tb.monotonic_ns()) / 1e9
                if left <= 0:
                    break
                self.tb.wait(self.stop_event, min(left, 0.5))
            else:
                self.stop_event.wait(0.5)
        self.stop()
        return 0

    # ---- health ----------------------------------------------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        now = self.tb.monotonic_ns()
        rec = self.recorder.status()
        rec_section = dict(rec.__dict__)
        problems: list[str] = []
        critical = False
        if rec.state != "recording":
            problems.append(f"recorder: {rec.detail}")
            critical = True
        else:
            # "Recording" is what the writer last said of itself: a writer stuck in a write (a hung SD card) or
            # ended says nothing more, and the queue fills behind it. Its heartbeat says whether it still runs.
            silent_s = (now - self.recorder.heartbeat_mono_ns) / 1e9 / self.tb.scale  # real seconds
            if not self.recorder.alive:
                problems.append("recorder: its thread has ended; nothing is written")
            elif silent_s > HEARTBEAT_STALE_S:
                # Its heartbeat beats between drains: a writer stuck in one, not necessarily one that wrote nothing.
                problems.append(f"recorder: not responding for {silent_s:.0f} s ({rec.queue_depth} records waiting)")
            if problems:
                rec_section["state"] = "stalled"
                critical = True
        # The daemon's own threads: the service loop logs the problems and answers systemd's watchdog, the health
        # loop records the health once a second. One that ended (a bug) left the journal silent and the watchdog
        # unanswered while this snapshot said OK.
        if not self.stop_event.is_set():
            for t in self._threads:
                if not t.is_alive():
                    does = DAEMON_THREADS.get(t.name)
                    problems.append(f"daemon: its {t.name} thread has ended{f' ({does})' if does else ''}; restart "
                                    "the service")
                    critical = True
        sensors, sensor_problems = self._sensor_rows(now)
        problems += sensor_problems
        no_raw = self.gnss_watch.raw_problem(now)
        if no_raw:
            problems.append(f"gnss: {no_raw}")
        mislabel = self.clock.last_mislabel
        if mislabel is not None and now - mislabel[0] <= MISLABEL_SHOW_S * 1e9:
            problems.append(f"clock: {mislabel[1]}")
        doubt = self.clock.time_doubt()
        if doubt is not None:
            problems.append(f"clock: {doubt}")
        chrony = self.clock.chrony
        if chrony is not None and chrony.error is not None:
            problems.append(f"clock: PPS samples do not reach chrony ({chrony.error}; {chrony.failed} failed): "
                            "is chronyd running with its SOCK refclock?")
        if self.samplers and all(s["state"] not in ("ok", NO_FIX) for s in sensors):
            critical = True
            if not sensor_problems:  # every one still opening (OPEN_GRACE_S): the verdict still says why
                problems.append("sensors: none delivers yet (" + ", ".join(f"{s['name']} {s['state']}"
                                                                           for s in sensors) + ")")
        dropped = sum(rec.dropped.values())
        self._drop_history.append((now, dropped))
        while len(self._drop_history) > 2 and now - self._drop_history[0][0] > DROP_WINDOW_NS:
            self._drop_history.popleft()
        recent = dropped - self._drop_history[0][1]
        if recent:
            problems.append(f"recorder: {recent} records dropped in the last minute (queue full: writer too slow)")
        sections = {name: fn() for name, fn in self.attachments.sections.items()}
        for sec in sections.values():  # an attachment's own problems (the navigator's filter failing)
            problems += sec.get("problems", [])
        verdict = "critical" if critical else ("degraded" if problems else "ok")
        recovering = self._recovering
        if recovering is not None:
            # Shown, not a problem: the last run's cut file is being made whole while this run records as it should
            # (as a problem it made `logger status` say degraded, exit 1, for the minutes a board's recovery takes).
            rec_section["recovering"] = f"{recovering[0]} ({size_text(recovering[1])}), cut short by the last run"
        return {
            "verdict": verdict, "problems": problems, "mode": self.mode, "pid": os.getpid(), "t_mono_ns": now,
            "uptime_s": (now - self._started_mono) / 1e9, "sensors": sensors,
            "sync": self._sync_section(now), "gnss": self.gnss_watch.section(now),
            "recorder": rec_section, "pace": self.tb.pace(),
            **sections,
        }

    def _sensor_rows(self, now: int) -> tuple[list[dict[str, Any]], list[str]]:
        """Each sensor's row with the daemon's judgement in it (silent, stalled, no fix), and the problems they
        show."""
        sensors = [s.health.snapshot(now) for s in self.samplers]
        problems: list[str] = []
        no_fix = self.gnss_watch.problem(now)
        for s, snap in zip(self.samplers, sensors, strict=True):
            problem = self._sensor_problem(s, snap, now, no_fix)
            if problem:
                problems.append(f"{snap['name']}: {problem}")
            incident = s.health.recent_incident(now)
            if incident is not None:
                problems.append(f"{snap['name']}: {incident}")
        return sensors, problems

    def _recent_snapshot(self) -> dict[str, Any]:
        """The health loop's snapshot while it is fresh (:data:`SHARED_SNAPSHOT_NS`), else a new one (that loop
        stopped or late: the service loop never reports from an old one)."""
        snap = self._health_snapshot
        if snap is not None and self.tb.monotonic_ns() - snap["t_mono_ns"] <= SHARED_SNAPSHOT_NS:
            return snap
        return self.snapshot()

    def _sensor_problem(self, s: Sampler, snap: dict[str, Any], now: int, no_fix: str | None) -> str:
        """What is wrong with one sensor now ("" when nothing), with its row's state made to say the same: a sensor
        whose thread runs but that delivers nothing is ``silent`` (and shows no current rate), a receiver that
        talks without a fix is ``no fix``."""
        if snap["state"] != "ok":
            snap["measured_rate_hz"] = None
            if snap["state"] == "stopped" and self.stop_event.is_set():
                return ""  # told to stop (a SIGTERM): each sampler says so once it has, which is no fault
            if snap["last_error"]:
                return f"{snap['state']}: {snap['last_error']}"
            if snap["state"] == "starting":
                # Its first open still going on: an ELM327's protocol search, a receiver's set-up answered message
                # by message take seconds at every start, which is not a fault (the row says starting); an open that
                # has not returned after OPEN_GRACE_S is one.
                opening_s = (now - self._started_mono) / 1e9 / self.tb.scale  # real seconds
                return f"starting: opening the device for {opening_s:.0f} s" if opening_s > OPEN_GRACE_S else ""
            return snap["state"]
        if (now - s.health.heartbeat_mono_ns) / 1e9 / self.tb.scale > HEARTBEAT_STALE_S:  # real seconds
            snap["state"], snap["measured_rate_hz"] = "stalled", None
            return "thread not responding"
        age = snap["last_sample_age_s"]
        since_ok = (now - s.health.ok_since_mono_ns) / 1e9
        if age is not None and age > since_ok:
            # The last sample came before the device was opened again (a receiver unplugged and back): its silence
            # is counted from the reopening, as at the first start ("no sample for 27 s" the moment it was back).
            age = None
        limit = 3.0 / snap["rate_hz"] + 1.0 if snap["rate_hz"] else None
        if limit is not None and (age if age is not None else since_ok) > limit:
            snap["state"], snap["measured_rate_hz"] = SILENT, None
            what = "pulse" if snap["name"] == "pps" else "sample"
            why = " (the receiver pulses only with a fix)" if snap["name"] == "pps" and no_fix else ""
            if age is None:
                return f"no {what} since it was opened {since_ok:.0f} s ago{why}"
            return f"no {what} for {age:.0f} s{why}"
        if age is None:  # open, nothing from it (since it was opened) and not overdue: starting, not "ok at 0 Hz"
            snap["state"], snap["measured_rate_hz"] = "starting", None
            return ""
        if snap["name"] == "gnss" and no_fix:
            snap["state"] = NO_FIX
            return no_fix
        return ""

    def _sync_section(self, now: int) -> dict[str, Any]:
        """The clock's part of the snapshot: its tracking report, or the state and bound of its stamps."""
        report = self.clock.report(now)
        chrony = self.clock.chrony
        extra = {"chrony": chrony.section()} if chrony is not None else {}
        if report is not None:
            return {**sync_record(report), **extra}
        st = self.clock.stamp(now)
        return {"state": st.state, "err_ns": st.err_ns, **extra}

    def _health_loop(self) -> None:
        last = self.tb.monotonic_ns()
        while not self.tb.wait(self.stop_event, 1.0):
            snap = self._health_snapshot = self.snapshot()
            now = self.tb.monotonic_ns()
            self._count_time_in_state(snap, (now - last) / 1e9)
            last = now
            self.clock.recheck_wall(now)
            report = self.clock.report(now)
            if report is not None:
                self.sink(Reading(SYNC, sync_record(report), now, stamped=False))
            self.sink(Reading(HEALTH, health_record(snap, now), now, stamped=False))

    def _count_time_in_state(self, snap: dict[str, Any], dt_s: float) -> None:
        """Drive seconds each sensor and the clock spent in each state, for the end-of-run summary."""
        for h in snap["sensors"]:
            by_state = self.time_in_state.setdefault(h["name"], {})
            by_state[h["state"]] = by_state.get(h["state"], 0.0) + dt_s
        clock = self.time_in_state.setdefault(CLOCK, {})
        state = snap["sync"].get("state", "?")
        clock[state] = clock.get(state, 0.0) + dt_s

    def _periodic_loop(self, period_s: float, fn: Callable[[], list[Reading]]) -> None:
        start = self.tb.monotonic_ns()
        n = 0
        period_ns = int(period_s * 1e9)
        while not self.stop_event.is_set():
            n += 1
            due = start + int(n * period_s * 1e9)
            if self.tb.wait_until(self.stop_event, due):
                return
            woke = self.tb.monotonic_ns()
            for r in fn():
                self.sink(r)
            self.tb.late(woke - due, period_ns)  # how late the host woke it: a period of that loses a record

    # ---- the service manager: readiness, watchdog, status line, problems in the journal ---------------------
    def _synced_unix_ns(self, t_mono_ns: int) -> int | None:
        """Synchronised Unix time at a monotonic time, or None while the clock free-runs (the time is unknown).

        Names the recorder's files: a board without an RTC must not date them from its wall clock.
        """
        stamp = self.clock.stamp(t_mono_ns)
        return None if stamp.state == FREERUN else stamp.t_sync_ns

    def started_up(self) -> bool:
        """The first file is started (or refused with a reason) and every sensor's first open has returned."""
        return (self._started.is_set() and self.recorder.status().state != "starting"
                and all(s.health.state != "starting" for s in self.samplers))

    def stale_threads(self) -> list[str]:
        """Threads that died or whose heartbeat is older than ``heartbeat_bound_s`` real seconds: one line each.
        None once the daemon is stopping: its threads end then by design (the service and health loops at once),
        and a reader asking meanwhile (the soak's sampler) read them as dead."""
        if self.stop_event.is_set():
            return []
        now = self.tb.monotonic_ns()
        bound_ns = self.heartbeat_bound_s * 1e9 * self.tb.scale  # heartbeats are in drive time
        stale: list[str] = []
        for s in self.samplers:
            if not s.is_alive():
                stale.append(f"{s.name} has ended")
            elif now - s.health.heartbeat_mono_ns > bound_ns:
                stale.append(f"{s.name} silent for {(now - s.health.heartbeat_mono_ns) / 1e9 / self.tb.scale:.0f} s")
        rec = self.recorder.status()
        if not self.recorder.alive:
            stale.append("recorder has ended")
        elif now - self.recorder.heartbeat_mono_ns > bound_ns:
            stale.append(f"recorder silent for {(now - self.recorder.heartbeat_mono_ns) / 1e9 / self.tb.scale:.0f} s")
        elif rec.state == "failed" and not rec.storage_missing and now - rec.state_since_mono_ns > bound_ns:
            # Alive but writing nothing: a restart by systemd is the one remedy left to try. Not while the card is
            # not mounted: the recorder waits for it (and records once it is), which a restart cannot hasten.
            stale.append(f"recorder failing for {(now - rec.state_since_mono_ns) / 1e9 / self.tb.scale:.0f} s: "
                         f"{rec.detail}")
        stale += [f"{t.name} has ended" for t in self._threads
                  if t is not threading.current_thread() and not t.is_alive()]
        return stale

    def _service_loop(self) -> None:
        """READY=1 once started up; then WATCHDOG=1 every half timeout, but only while no thread is stale.

        Runs on the host's clock, not the drive's: systemd's watchdog counts real seconds. Until READY the
        pings go on unconditionally (a sensor's first open may wait for its device; TimeoutStartSec bounds
        that phase). A stale thread stops the pings, and systemd restarts the service. The recovery of the last
        run's cut files, which may take minutes, runs after READY in a thread the watchdog does not wait for.
        """
        interval = self.notifier.watchdog_interval_s
        # Once a second of drive, so that the journal sees what `logger status` sees (a simulated drive at 60x
        # included, within reason: never more often than every 50 ms of the host's time).
        t0 = time.monotonic()
        last_ping = -1e18
        last_status = ""
        stale_reported: set[str] = set()  # thread names: the lines carry a growing age, logged once per thread
        while True:
            now = time.monotonic()
            if not self.ready.is_set():
                if self.started_up() or (self._started.is_set() and now - t0 > self.ready_timeout_s):
                    snap = self.snapshot()
                    last_status = self._status_line(snap)
                    self.notifier.ready(last_status)
                    self.ready.set()
                    log.info("ready: %s", last_status)
                healthy = True
            else:
                snap = self._recent_snapshot()
                self._log_problem_changes(snap["problems"], snap["verdict"])
                line = self._status_line(snap)
                if line != last_status:
                    self.notifier.status(line)
                    last_status = line
                stale = self.stale_threads()
                names = {line.split(" ", 1)[0] for line in stale}
                if names - stale_reported:
                    log.error("not answering the watchdog: %s", "; ".join(stale))
                elif stale_reported and not stale:
                    log.warning("watchdog answered again: every thread is alive")
                stale_reported = names
                healthy = not stale
            if interval and healthy and now - last_ping >= interval:
                if self.notifier.watchdog():
                    self.watchdog_pings += 1
                last_ping = now
            self._report_backlogs()
            if self.stop_event.wait(max(0.05, min(interval or 1.0, 1.0 / self.tb.scale))):
                return

    def _report_backlogs(self) -> None:
        """The recorder's and the navigator's queues as lateness: a queue's depth against its size is the share
        of its slack used, which a simulated drive keeps low by slowing down (nothing to do on the host's clock)."""
        if not self.tb.paced:
            return
        rec = self.recorder.status()
        self.tb.late(rec.queue_depth, rec.queue_size)
        for backlog in self.attachments.backlogs:
            self.tb.late(*backlog())

    @staticmethod
    def _status_line(snap: dict[str, Any]) -> str:
        """One line for ``systemctl status``: the verdict, the sensors, and the first problem."""
        sensors = snap.get("sensors", [])
        ok = sum(1 for s in sensors if s["state"] == "ok")
        rec = snap.get("recorder", {})
        line = f"{snap['verdict']}: {ok}/{len(sensors)} sensors ok, recorder {rec.get('state', '?')}"
        problems = snap.get("problems") or []
        if problems:
            line += f"; {problems[0]}" + (f" (+{len(problems) - 1} more)" if len(problems) > 1 else "")
        return line

    def _log_problem_changes(self, problems: list[str], verdict: str) -> None:
        """Log each problem when it appears and when it clears, so that the journal shows every fault."""
        # Drive time, like every other health figure: a simulated drive at 60x logs what a real one would.
        for level, line in self.problem_journal.update(problems, self.tb.monotonic_ns() / 1e9):
            log.log(logging.ERROR if level == logging.WARNING and verdict == "critical" else level, "%s", line)
