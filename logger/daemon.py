"""The daemon: wires sensors, clock, recorder and status together, and shuts down cleanly.

Start order matters for data safety: unfinished files from a previous crash are recovered first, then the
recorder opens its file (a bad output folder fails here, before any sensor is touched), then the sampler
threads start. Stop order is the reverse, and the recorder drains its queue before finishing the file.
"""

from __future__ import annotations

import itertools
import logging
import os
import signal
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from logger.config import Config
from logger.mcap_files import McapFileError, is_finished, recover
from logger.recorder import Recorder, RecorderSettings
from logger.sampler import Reading, Sampler
from logger.sources import Plan
from logger.timebase import TimeBase, host_timebase
from logger.topics import TOPICS
from sync.stamp import FreeRunClock, StampClock

log = logging.getLogger(__name__)

HEARTBEAT_STALE_S = 10.0
DROP_WINDOW_NS = 60 * 1_000_000_000


@dataclass
class Extras:
    """What a run adds beyond the sensors: simulation truth publishers, metadata for the file."""

    periodic: list[tuple[float, Callable[[], list[Reading]]]] = field(default_factory=list)
    taps: list[Any] = field(default_factory=list)  # objects with offer(topic, payload) -> None, never blocking
    sections: dict[str, Callable[[], dict[str, Any]]] = field(default_factory=dict)  # extra status sections
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    close: list[Callable[[], None]] = field(default_factory=list)


def recover_unfinished(out_dir: Path) -> list[str]:
    """Recover every file a crash left unfinished; returns one line per file for the log."""
    lines = []
    for path in sorted(out_dir.glob("*.mcap")):
        if is_finished(path):
            continue
        try:
            report = recover(path)
        except (McapFileError, OSError) as exc:
            lines.append(f"could not recover {path.name}: {exc}")
            continue
        lines.append(f"recovered {path.name}: {report.messages} messages from {report.chunks_ok} chunks"
                     + (f" ({report.chunks_bad} corrupt chunks skipped)" if report.chunks_bad else ""))
    for stale in out_dir.glob("*.mcap.recovering"):
        stale.unlink(missing_ok=True)  # a recovery cut short; its source is still there and was redone above
    return lines


class Daemon:
    def __init__(self, cfg: Config, plans: list[Plan], timebase: TimeBase | None = None,
                 clock: StampClock | None = None, extras: Extras | None = None, out_dir: Path | None = None,
                 status_socket: Path | None = None, mode: str = "") -> None:
        self.cfg = cfg
        self.tb = timebase or host_timebase()
        self.clock = clock or FreeRunClock(self.tb.monotonic_ns, imu_rate_hz=cfg["imu"]["rate_hz"])
        self.extras = extras or Extras()
        self.plans = plans
        self.mode = mode
        self.out_dir = Path(out_dir or cfg["logger"]["out_dir"])
        self.status_socket = Path(status_socket or cfg["logger"]["status_socket"])
        rc = cfg["recorder"]
        self.recorder = Recorder(RecorderSettings(
            out_dir=self.out_dir, flush_interval_s=rc["flush_interval_s"], rotate_duration_s=rc["rotate_duration_s"],
            rotate_size_bytes=int(rc["rotate_size_mb"] * 2**20), min_free_bytes=int(rc["min_free_mb"] * 2**20),
            compression=rc["compression"], queue_size=rc["queue_size"]), TOPICS, metadata=self.extras.metadata,
            monotonic_ns=self.tb.monotonic_ns, time_scale=self.tb.scale)
        self.stop_event = threading.Event()
        self.samplers: list[Sampler] = []
        self._seq: dict[str, itertools.count[int]] = {}
        self._started_mono = 0
        self._threads: list[threading.Thread] = []
        self.status_server: Any = None
        self.startup_lines: list[str] = []
        # Consumers of the stamped records besides the recorder (the navigator): ``offer`` must never block.
        self.taps: list[Any] = list(self.extras.taps)
        self._observe: Callable[[str, dict[str, Any], int], None] | None = getattr(self.clock, "observe", None)
        self._drop_history: deque[tuple[int, int]] = deque()

    # ---- the sink every sampler calls: stamp, count, queue ------------------------------------------------
    def sink(self, r: Reading) -> None:
        seq = self._seq.get(r.topic)
        if seq is None:
            seq = self._seq.setdefault(r.topic, itertools.count())
        payload = r.payload
        if self._observe is not None:
            self._observe(r.topic, payload, r.t_mono_ns)  # PPS edges and time messages steer the clock
        if r.stamped:
            stamp = self.clock.stamp(r.t_mono_ns)
            payload = {"t_mono_ns": r.t_mono_ns, **stamp.fields(), "seq": next(seq), **payload}
            log_ns = stamp.t_sync_ns
        else:
            log_ns = self.clock.stamp(r.t_mono_ns).t_sync_ns
        self.recorder.submit(r.topic, payload, log_ns, r.t_mono_ns)
        for tap in self.taps:
            tap.offer(r.topic, payload)

    # ---- life cycle ---------------------------------------------------------------------------------------
    def start(self) -> None:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.startup_lines = recover_unfinished(self.out_dir)
        for line in self.startup_lines:
            log.warning(line)
        self._started_mono = self.tb.monotonic_ns()
        path = self.recorder.start()
        log.info("recording to %s", path or self.recorder.status().detail)
        for plan in self.plans:
            s = Sampler(plan.source, self.sink, self.tb, plan.rate_hz, self.stop_event, plan.expected_hz)
            self.samplers.append(s)
        for s in self.samplers:
            s.start()
        self._start_thread("health", self._health_loop)
        for period, fn in self.extras.periodic:
            self._start_thread("sim-truth", self._periodic_loop, period, fn)
        from logger.status import StatusServer

        try:
            self.status_server = StatusServer(self.status_socket, self.snapshot)
            self.status_server.start()
        except OSError as exc:
            log.error("status socket %s unavailable (%s); `logger status` will not work", self.status_socket,
                      exc.strerror or exc)

    def _start_thread(self, name: str, target: Callable[..., None], *args: Any) -> None:
        t = threading.Thread(target=target, args=args, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def stop(self) -> None:
        self.stop_event.set()
        for s in self.samplers:
            s.join(5.0)
            if s.is_alive():
                log.error("%s did not stop within 5 s", s.name)
        for t in self._threads:
            t.join(2.0)
        if self.status_server is not None:
            self.status_server.close()
        self.recorder.stop()
        for fn in self.extras.close:
            try:
                fn()
            except Exception:
                log.debug("closing a simulated device failed", exc_info=True)

    def run(self, duration_s: float | None = None) -> int:
        """Run until SIGTERM/SIGINT or ``duration_s`` of drive time; returns the process exit code."""
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
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
        sensors = [s.health.snapshot(now) for s in self.samplers]
        rec = self.recorder.status()
        problems: list[str] = []
        critical = False
        if rec.state != "recording":
            problems.append(f"recorder: {rec.detail}")
            critical = True
        for s, snap in zip(self.samplers, sensors, strict=True):
            if snap["state"] != "ok":
                problems.append(f"{snap['name']}: {snap['state']}: {snap['last_error']}")
            elif (now - s.health.heartbeat_mono_ns) / 1e9 > HEARTBEAT_STALE_S:
                problems.append(f"{snap['name']}: thread not responding")
            elif snap["rate_hz"] and snap["last_sample_age_s"] is not None and \
                    snap["last_sample_age_s"] > 3.0 / snap["rate_hz"] + 1.0:
                problems.append(f"{snap['name']}: no sample for {snap['last_sample_age_s']:.1f} s")
        if self.samplers and all(s["state"] != "ok" for s in sensors):
            critical = True
        dropped = sum(rec.dropped.values())
        self._drop_history.append((now, dropped))
        while len(self._drop_history) > 2 and now - self._drop_history[0][0] > DROP_WINDOW_NS:
            self._drop_history.popleft()
        recent = dropped - self._drop_history[0][1]
        if recent:
            problems.append(f"recorder: {recent} records dropped in the last minute (queue full: writer too slow)")
        verdict = "critical" if critical else ("degraded" if problems else "ok")
        sync = getattr(self.clock, "report", None)
        return {
            "verdict": verdict, "problems": problems, "mode": self.mode, "pid": os.getpid(), "t_mono_ns": now,
            "uptime_s": (now - self._started_mono) / 1e9, "sensors": sensors,
            "sync": sync(now) if callable(sync) else {"state": self.clock.stamp(now).state,
                                                      "err_ns": self.clock.stamp(now).err_ns},
            "recorder": rec.__dict__,
            **{name: fn() for name, fn in self.extras.sections.items()},
        }

    def _health_loop(self) -> None:
        while not self.tb.wait(self.stop_event, 1.0):
            snap = self.snapshot()
            now = self.tb.monotonic_ns()
            report = getattr(self.clock, "report", None)
            if callable(report):
                self.sink(Reading("/sync", report(now), now, stamped=False))
            payload = {"t_mono_ns": now, "verdict": snap["verdict"], "problems": snap["problems"],
                       "sensors": snap["sensors"],
                       "recorder": {k: snap["recorder"][k] for k in ("state", "queue_depth", "written", "dropped",
                                                                     "free_bytes")}}
            self.sink(Reading("/health", payload, now, stamped=False))

    def _periodic_loop(self, period_s: float, fn: Callable[[], list[Reading]]) -> None:
        start = self.tb.monotonic_ns()
        n = 0
        while not self.stop_event.is_set():
            n += 1
            due = start + int(n * period_s * 1e9)
            if self.tb.wait(self.stop_event, (due - self.tb.monotonic_ns()) / 1e9):
                return
            for r in fn():
                self.sink(r)

