"""Soak: a long simulated drive at a high time scale with faults injected at random, then the figures that say
whether the logger can be left alone in a car for months.

    python tools/soak.py                       # 8 h of drive at 60x, about 10 minutes here
    python tools/soak.py --hours 1 --time-scale 10 --out /tmp/soak

The drive runs in worker processes (``--worker``), each a whole daemon on the simulated vehicle, so that the
process faults are real: a SIGTERM ends the first worker and a ``kill -9`` the second, and each time a new one
starts on the same folder (it must recover the cut file). Inside each worker a fault injector picks faults at
random, one at a time, through the device models: I2C chips unplugged, restarted and bus errors, the receiver's
USB serial vanishing, garbage on its line, the receiver restarting under the open port, the ELM327 resetting or
reporting bus errors, PPS outages, the disk nearly full.
While a fault lasts, the injector reads the status socket (what `logger status` shows) until the fault is
visible there; the orchestrator stamps every log line the worker writes, to check the journal as well.

Figures: threads alive at the end of each worker, RSS growth after warm-up, records lost outside the faults
(sequence numbers, and time gaps not explained by a fault, the start-up, or the receiver losing its time fix),
files recovered after ``kill -9``, and for every fault whether it showed in the status and in the log. The
report is printed and written as JSON next to the files.
"""

from __future__ import annotations

import argparse
import bisect
import contextlib
import itertools
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import resident  # tools/, beside this file

from logger.recording.topics import GAP_PERIODS  # the daemon's own definition of a gap
from sensors.sim.governor import FLOOR

NS = 1_000_000_000
SENSOR_TOPICS = {"/imu": 20.0, "/baro": 1.0, "/obd/speed": 2.0, "/gnss/fix": 1.0, "/pps": 1.0}
WARM_UP_S = 120.0  # drive seconds after a start: receiver's first fix, clock lock, first opens
RECOVERY_S = 25.0  # drive seconds after a fault ends for the sensor to come back (back-off up to 10 s, reopen)
# The sampler logs one message per distinct text per real minute: faults of one kind must be further apart
# than that to show in the log each time (the figures would otherwise blame the rate limit, not the fault).
SAME_KIND_COOLDOWN_REAL_S = 65.0
COUNTER_LAG_S = 30.0  # drive seconds after a silence within which the daemon's counters must show it
# Drive seconds: a silence that ends closer than this before the counters' last reading (a kill -9 leaves no
# later one) may not show in it yet, since the read that ends it counts it only when it returns (83 ms at 60x).
LAST_READING_MARGIN_S = 5.0
# The MCAP writer keeps the index of every chunk (one per flush, each drive second) until the file is finished,
# about 0.7 MB for the hour a file lasts (14 MB with mcap's own Writer, the recorder's until 2026-12-05); after the
# first rotation that memory is reused. Growth is measured from then on, in the workers that run long enough.
RSS_WARM_UP_S = 4500.0
POLL_REAL_S = 0.1  # how often the injector reads the status socket while a fault lasts (it costs CPU too)
SENSOR_OF_TOPIC = {"/imu": "imu", "/baro": "baro", "/obd/speed": "obd", "/gnss/fix": "gnss", "/pps": "pps"}

FAULT_TOPICS = {
    "imu_unplugged": {"/imu"},
    "imu_restarted": {"/imu"},
    "baro_unplugged": {"/baro"},
    "i2c_errors": {"/imu", "/baro"},
    "gnss_vanished": {"/gnss/fix", "/gnss/raw", "/gnss/timepulse"},
    "gnss_garbage": {"/gnss/fix", "/gnss/timepulse"},
    "gnss_restarted": {"/gnss/fix", "/gnss/timepulse", "/pps"},  # no fix, so no pulse, until its first fix again
    "elm327_reset": {"/obd/speed"},
    "elm327_can_error": {"/obd/speed"},
    "pps_outage": {"/pps"},
    "disk_nearly_full": set(SENSOR_TOPICS) | {"/gnss/raw", "/gnss/timepulse"},
}
FAULT_SENSOR = {"imu_unplugged": "imu", "imu_restarted": "imu", "baro_unplugged": "baro", "i2c_errors": "imu|baro",
                "gnss_vanished": "gnss",
                "gnss_garbage": "gnss", "gnss_restarted": "gnss", "elm327_reset": "obd", "elm327_can_error": "obd",
                "pps_outage": "pps", "disk_nearly_full": "recorder"}


# ================================================================================================================
# worker: one daemon on the simulated vehicle, with the fault injector
# ================================================================================================================

class Journal:
    """JSON lines, flushed one by one: a worker killed with -9 leaves everything it wrote before."""

    def __init__(self, path: Path) -> None:
        self._f = open(path, "a", buffering=1, encoding="utf-8")  # noqa: SIM115 - lives as long as the worker
        self._lock = threading.Lock()

    def write(self, **event: Any) -> None:
        with self._lock:
            self._f.write(json.dumps(event, default=str) + "\n")


class Injector:
    """Picks faults at random through the device models and watches each in the status while it lasts."""

    def __init__(self, daemon: Any, vehicle: Any, journal: Journal, rng: random.Random, mean_gap_s: float,
                 kinds: list[str]) -> None:
        self.d, self.v, self.j, self.rng = daemon, vehicle, journal, rng
        self.mean_gap_s = mean_gap_s
        self.kinds = kinds
        self.sock = daemon.status_socket
        self.last_of_kind: dict[str, float] = {}

    # -- time
    def now(self) -> int:
        return int(self.d.tb.monotonic_ns())

    def wait(self, drive_s: float) -> bool:
        """Wait drive seconds; True if the daemon is stopping."""
        return bool(self.d.tb.wait(self.d.stop_event, drive_s))

    def snapshot(self) -> dict[str, Any] | None:
        from logger.runtime.status_socket import fetch

        try:
            return fetch(self.sock, timeout_s=5.0)
        except ConnectionError:
            return None

    # -- the loop
    def run(self) -> None:
        if self.wait(WARM_UP_S):
            return
        while not self.d.stop_event.is_set():
            if self.wait(self.rng.expovariate(1.0 / self.mean_gap_s)):
                return
            ready = [k for k in self.kinds
                     if time.monotonic() - self.last_of_kind.get(k, -1e9) > SAME_KIND_COOLDOWN_REAL_S]
            if not ready:
                continue
            kind = self.rng.choice(ready)
            self.last_of_kind[kind] = time.monotonic()
            try:
                getattr(self, kind)()
            except Exception as exc:  # the soak must report a broken injection, not die of it
                self.j.write(ev="injector_error", kind=kind, error=repr(exc))

    def _fault(self, kind: str, start: Callable[[], None], end: Callable[[], None] | None, drive_s: float,
               visible: Callable[[dict[str, Any]], str | None], settle: Callable[[dict[str, Any]], bool] | None = None,
               **extra: Any) -> None:
        """Run one fault: start it, watch the status until it shows (or the fault is over), end it, and for a
        fault that ends by itself wait until the status has settled; then journal the window."""
        t0, h0 = self.now(), time.monotonic_ns()
        start()
        # Its start goes into the journal at once: a stop of the daemon can end the process before this thread
        # journals the whole window (faults_of then closes it at the segment's last word).
        self.j.write(ev="fault_start", kind=kind, start_ns=t0, start_host_ns=h0)
        seen: str | None = None
        seen_after = None
        status_text = ""
        deadline = t0 + int(drive_s * NS)
        while self.now() < deadline and not self.d.stop_event.is_set():
            if seen is None:
                snap = self.snapshot()
                if snap is not None:
                    seen = visible(snap)
                    if seen is not None:
                        seen_after = (self.now() - t0) / NS
                        from logger.cli.status_view import render

                        status_text = render(snap)
            time.sleep(POLL_REAL_S)
        if end is not None:
            end()
        if settle is not None:  # the window closes when the sensor is back
            limit = self.now() + int(RECOVERY_S * NS)
            while self.now() < limit and not self.d.stop_event.is_set():
                snap = self.snapshot()
                if seen is None and snap is not None:
                    seen = visible(snap)
                    if seen is not None:
                        seen_after = (self.now() - t0) / NS
                if snap is not None and settle(snap):
                    break
                time.sleep(POLL_REAL_S)
        self.j.write(ev="fault", kind=kind, start_ns=t0, end_ns=self.now(), start_host_ns=h0,
                     end_host_ns=time.monotonic_ns(), seen_in_status=seen, seen_after_s=seen_after,
                     cut_short=self.d.stop_event.is_set(),
                     status_excerpt="\n".join(line for line in status_text.splitlines()
                                              if any(s in line for s in FAULT_SENSOR[kind].split("|"))
                                              or line.lstrip().startswith("!"))[:600], **extra)

    # -- helpers for visibility
    @staticmethod
    def sensor(snap: dict[str, Any], name: str) -> dict[str, Any]:
        return next(s for s in snap["sensors"] if s["name"] == name)

    def problem(self, snap: dict[str, Any], prefix: str) -> str | None:
        return next((p for p in snap.get("problems", []) if p.startswith(prefix)), None)

    def duration(self) -> float:
        return self.rng.uniform(30.0, 120.0)

    # -- the faults
    def imu_unplugged(self) -> None:
        self._unplug("imu_unplugged", "imu", 0x68)

    def baro_unplugged(self) -> None:
        self._unplug("baro_unplugged", "baro", 0x77)

    def _unplug(self, kind: str, name: str, address: int) -> None:
        self._fault(kind, lambda: self.v.i2c.unplug(address), lambda: self.v.i2c.replug(address), self.duration(),
                    lambda s: self.problem(s, f"{name}:"), lambda s: self.sensor(s, name)["state"] == "ok")

    def imu_restarted(self) -> None:
        # A dip in the chip's own supply: it restarts asleep at its reset values while every transfer succeeds.
        # Found and set up again within about a second: the status may show it only as one more reconnect.
        snap = self.snapshot()
        before = self.sensor(snap, "imu")["reconnects"] if snap else 0

        def visible(s: dict[str, Any]) -> str | None:
            grew = self.sensor(s, "imu")["reconnects"] > before
            return self.problem(s, "imu:") or (f"imu reconnects {before} -> {self.sensor(s, 'imu')['reconnects']}"
                                               if grew else None)

        self._fault("imu_restarted", lambda: self.v.i2c.chip(0x68).power_on_reset(), None, 15.0, visible,
                    lambda s: self.sensor(s, "imu")["state"] == "ok")

    def i2c_errors(self) -> None:
        snap = self.snapshot()
        before = {n: self.sensor(snap, n)["errors"] if snap else 0 for n in ("imu", "baro")}

        def visible(s: dict[str, Any]) -> str | None:
            grew = [n for n in ("imu", "baro") if self.sensor(s, n)["errors"] > before[n]]
            return f"errors counted on {', '.join(grew)}" if grew else None

        self._fault("i2c_errors", lambda: self.v.i2c.fail_next(count=3), None, 5.0, visible,
                    lambda s: all(self.sensor(s, n)["state"] == "ok" for n in ("imu", "baro")))

    def gnss_vanished(self) -> None:
        self._fault("gnss_vanished", self.v.gnss.vanish, self.v.gnss.reappear, self.duration(),
                    lambda s: self.problem(s, "gnss:"), lambda s: self.sensor(s, "gnss")["state"] == "ok")

    def gnss_garbage(self) -> None:
        def burst() -> None:
            for _ in range(3):
                self.v.gnss.inject_garbage(400)

        # The bytes wait in the line until the receiver's thread reads them: the fault lasts until then.
        self._fault("gnss_garbage", burst, None, 5.0, lambda s: self.problem(s, "gnss:"),
                    lambda s: self.problem(s, "gnss:") is not None)

    def gnss_restarted(self) -> None:
        # A voltage dip while the engine cranks: the receiver restarts under the open port, back at its flash's
        # speed and messages (NMEA only), so the GNSS thread must notice and set it up again.
        self._fault("gnss_restarted", lambda: self.v.gnss.reappear(power_cycle=True), None, 10.0,
                    lambda s: self.problem(s, "gnss:"),
                    lambda s: self.problem(s, "gnss:") is None and self.sensor(s, "gnss")["state"] == "ok")

    def elm327_reset(self) -> None:
        self._fault("elm327_reset", self.v.elm327.reset, None, 5.0, lambda s: self.problem(s, "obd:"),
                    lambda s: self.sensor(s, "obd")["state"] == "ok")

    def elm327_can_error(self) -> None:
        from sensors.sim.elm327 import ElmFault

        seconds = self.duration()
        self._fault("elm327_can_error", lambda: self.v.elm327.inject(ElmFault.CAN_ERROR, count=int(seconds * 2)),
                    None, seconds, lambda s: self.problem(s, "obd:"), lambda s: self.sensor(s, "obd")["state"] == "ok")

    def pps_outage(self) -> None:
        seconds = self.duration()

        def start() -> None:
            k = self.v.pps.pulse_index(self.v.oscillator.true_ns(self.now())) + 1
            for i in range(int(seconds) + 1):
                self.v.pps.inject_missed(k + i)

        self._fault("pps_outage", start, None, seconds, lambda s: self.problem(s, "pps:"),
                    lambda s: self.problem(s, "pps:") is None)

    def disk_nearly_full(self) -> None:
        settings = self.d.recorder.settings
        normal = settings.min_free_bytes

        def fill() -> None:
            settings.min_free_bytes = 1 << 62  # as if the card had less free space than the minimum

        def free() -> None:
            settings.min_free_bytes = normal

        self._fault("disk_nearly_full", fill, free, self.duration(), lambda s: self.problem(s, "recorder:"),
                    lambda s: s["recorder"]["state"] == "recording")


class CoarseTrajectory:
    """The drive's state on a 50 ms grid, cached: what the MPU-6050 model asks for at its 1 kHz chip rate.

    At 60x the model would evaluate the trajectory 120 000 times per real second, far more than one core can;
    the soak then measures the host, not the logger. Samples between grid points repeat the nearest state
    (sensor noise, bias and filtering are still the model's own), which is immaterial for a soak.
    """

    def __init__(self, trajectory: Any, step_s: float = 0.05) -> None:
        self._trajectory = trajectory
        self._step_s = step_s
        self._cache: dict[int, Any] = {}

    def state(self, t_s: float) -> Any:
        k = round(t_s / self._step_s)
        got = self._cache.get(k)
        if got is None:
            if len(self._cache) > 256:
                self._cache.clear()
            got = self._cache[k] = self._trajectory.state(k * self._step_s)
        return got

    def __getattr__(self, name: str) -> Any:
        return getattr(self._trajectory, name)


def pps_off_watch(daemon: Any, vehicle: Any, journal: Journal) -> None:
    """Journal the windows in which the receiver has no time fix, so it sends no PPS: not a fault of ours."""
    off_since: int | None = None
    while not daemon.tb.wait(daemon.stop_event, 1.0):
        now = int(daemon.tb.monotonic_ns())
        locked = vehicle.gnss.time_pulse_locked(vehicle.oscillator.true_ns(now) / NS)
        if not locked and off_since is None:
            off_since = now
        elif locked and off_since is not None:
            journal.write(ev="pps_off", start_ns=off_since, end_ns=now)
            off_since = None
    if off_since is not None:
        journal.write(ev="pps_off", start_ns=off_since, end_ns=int(daemon.tb.monotonic_ns()))


def sample_loop(daemon: Any, journal: Journal, every_real_s: float) -> None:
    """RSS, threads and counters: once the daemon is ready (a short worker still gets one), then periodically."""
    daemon.ready.wait(120)
    while not daemon.stop_event.is_set():
        threads = sorted(t.name for t in threading.enumerate() if t.is_alive())
        snap = daemon.snapshot()
        if daemon.stop_event.is_set():
            # The stop came while this sample was taken: its threads may be the stopping ones (the service loop
            # ends at once), which read as a thread missing at the end. The sample before is the last.
            return
        journal.write(ev="sample", host_ns=time.monotonic_ns(), drive_ns=int(daemon.tb.monotonic_ns()),
                      rss_kb=resident.rss_kb(), threads=threads,
                      stale=daemon.stale_threads(), verdict=snap["verdict"], problems=snap["problems"],
                      recorder=snap["recorder"]["state"], queue=snap["recorder"]["queue_depth"],
                      sensors={s["name"]: {k: s[k] for k in ("state", "samples", "errors", "late", "missed", "gaps")}
                               for s in snap["sensors"]})
        if daemon.stop_event.wait(every_real_s):
            return


def end_at(daemon: Any, drive_s: float, how: str) -> None:
    """Send this process SIGTERM (a service stop) or SIGKILL (a power cut, as kill -9) once ``drive_s`` of drive
    time have passed since the recording started."""
    daemon.ready.wait()
    end = daemon.tb.monotonic_ns() + int(drive_s * NS)
    while (left := end - daemon.tb.monotonic_ns()) > 0:
        if daemon.tb.wait(daemon.stop_event, left / NS):
            return
    os.kill(os.getpid(), signal.SIGTERM if how == "sigterm" else signal.SIGKILL)


def worker(args: argparse.Namespace) -> int:
    from logger.compose import build
    from logger.config import defaults
    from logger.runtime import logs

    logs.setup(False)
    out = Path(args.out)
    cfg = defaults(sim=True)
    cfg.values["logger"]["out_dir"] = str(out)
    cfg.values["logger"]["state_dir"] = str(out / ".state")
    cfg.values["logger"]["status_socket"] = str(out / "status.sock")
    cfg.values["sim"].update(time_scale=args.time_scale, seed=args.seed, scenario=args.scenario)
    cfg.values["nav"]["enabled"] = args.nav
    # Smaller min_free so that the 'disk nearly full' fault is the only disk-full this host's disk causes.
    cfg.values["recorder"]["min_free_mb"] = 64
    daemon, vehicle = build(cfg, args.duration)
    if args.light_imu and vehicle.imu is not None:
        import sensors.sim.mpu6050 as mpu_model

        vehicle.imu.trajectory = CoarseTrajectory(vehicle.imu.trajectory)
        # A read that comes late makes the model generate every chip sample since the last one; beyond a
        # period's worth (50 at 20 Hz) they are never seen by a register read, so only their noise is advanced.
        mpu_model.MAX_SAMPLES_PER_CATCH_UP = 60
    if not args.truth:
        # The truth topics score the navigation filter; the soak does not need them, and at 60x their 30
        # records per drive second cost the recorder as much as all the sensors together.
        daemon.attachments.periodic.clear()
    journal = Journal(Path(args.journal))
    journal.write(ev="start", pid=os.getpid(), seed=args.seed, host_ns=time.monotonic_ns(),
                  drive_ns=int(daemon.tb.monotonic_ns()))
    rng = random.Random(args.seed)
    kinds = [k for k in args.faults.split(",") if k]
    injector = Injector(daemon, vehicle, journal, rng, args.mean_fault_gap_s, kinds)
    for target in (injector.run, lambda: pps_off_watch(daemon, vehicle, journal),
                   lambda: sample_loop(daemon, journal, args.sample_real_s)):
        threading.Thread(target=target, daemon=True, name="soak").start()
    if args.end_by:
        threading.Thread(target=end_at, args=(daemon, args.end_at, args.end_by), daemon=True, name="soak").start()
    code = daemon.run(args.duration)
    # The counters once every sampler has stopped: the last /health record comes before the samplers' last
    # records, and only these can tell whether a silence in that tail was counted.
    now = int(daemon.tb.monotonic_ns())
    counters = {c["name"]: {k: c[k] for k in ("late", "missed", "gaps")}
                for c in (s.health.snapshot(now) for s in daemon.samplers)}
    journal.write(ev="end", host_ns=time.monotonic_ns(), drive_ns=now, code=code, sensors=counters,
                  threads_left=sorted(t.name for t in threading.enumerate()
                                      if t.is_alive() and not t.daemon and t is not threading.main_thread()))
    return code


# ================================================================================================================
# orchestrator: segments ended by SIGTERM and kill -9, log stamping, analysis
# ================================================================================================================

@dataclass
class Segment:
    index: int
    drive_s: float
    ends_by: str  # "sigterm", "kill9" or "duration"
    seed: int
    pid: int = 0
    exit_code: int | None = None
    log_lines: list[tuple[int, str]] = field(default_factory=list)


def run_segment(seg: Segment, args: argparse.Namespace, out: Path, journal: Path) -> None:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--out", str(out), "--journal", str(journal),
           "--seed", str(seg.seed), "--time-scale", str(args.time_scale), "--scenario", args.scenario,
           "--mean-fault-gap-s", str(args.mean_fault_gap_s), "--faults", args.faults,
           "--sample-real-s", str(args.sample_real_s)] + (["--nav"] if args.nav else []) + \
        (["--truth"] if args.truth else []) + (["--light-imu"] if args.light_imu else [])
    # A worker ended by its duration gets exactly that; one ended by a signal sends it to itself at that drive
    # time (the drive's pace follows the host, so only the worker knows when its drive time has passed).
    cmd += ["--duration", str(seg.drive_s if seg.ends_by == "duration" else seg.drive_s * 2 + 600)]
    if seg.ends_by != "duration":
        cmd += ["--end-by", seg.ends_by, "--end-at", str(seg.drive_s)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, bufsize=1)
    seg.pid = proc.pid

    def pump() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            seg.log_lines.append((time.monotonic_ns(), line.rstrip("\n")))

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    started = time.monotonic()
    # At the slowest pace a drive is paced to (the governor's floor) plus start-up and the finish.
    seg.exit_code = proc.wait(seg.drive_s / FLOOR + 600)
    reader.join(10)
    print(f"segment {seg.index}: {seg.drive_s / 3600:.2f} h of drive, ended by {seg.ends_by}, exit {seg.exit_code}, "
          f"{time.monotonic() - started:.0f} s", flush=True)


def read_files(out: Path) -> dict[str, dict[str, Any]]:
    """Per file: its segment seed, whether it is finished, and per sensor topic the (t_mono_ns, seq) list."""
    from mcap.reader import make_reader

    from logger.recording.files import is_finished

    files: dict[str, dict[str, Any]] = {}
    for path in sorted(out.glob("*.mcap")):
        info: dict[str, Any] = {"finished": is_finished(path), "topics": defaultdict(list), "seed": None,
                                "health": []}
        with open(path, "rb") as f:
            reader = make_reader(f)
            for meta in reader.iter_metadata():
                if meta.name == "simulation":
                    info["seed"] = int(meta.metadata.get("seed", -1))
        with open(path, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
                if channel.topic in SENSOR_TOPICS:
                    m = json.loads(message.data)
                    info["topics"][channel.topic].append((m["t_mono_ns"], m["seq"]))
                elif channel.topic == "/imu/batch":  # a FIFO read: its samples, each with its own time and number
                    m = json.loads(message.data)
                    info["topics"]["/imu"].extend(zip(m["t_mono_ns"], itertools.count(m["seq"])))
                elif channel.topic == "/health":
                    m = json.loads(message.data)
                    info["health"].append((m["t_mono_ns"], {s["name"]: (s["late"] + s["missed"], s["gaps"])
                                                            for s in m["sensors"]}))
        files[path.name] = info
    return files


def faults_of(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """A segment's faults, each as journalled when it ended; one that started but never got that far (the
    daemon's stop ended the process first) lasts to the segment's last word and counts as cut short by the stop."""
    done = {(e["kind"], e["start_ns"]) for e in events if e["ev"] == "fault"}
    out = [e for e in events if e["ev"] == "fault"]
    last = max((e for e in events if "drive_ns" in e and "host_ns" in e), key=lambda x: x["drive_ns"], default=None)
    for e in events:
        if e["ev"] == "fault_start" and (e["kind"], e["start_ns"]) not in done:
            out.append({"ev": "fault", "kind": e["kind"], "start_ns": e["start_ns"],
                        "end_ns": max(e["start_ns"], last["drive_ns"]) if last else e["start_ns"],
                        "start_host_ns": e["start_host_ns"],
                        "end_host_ns": max(e["start_host_ns"], last["host_ns"]) if last else e["start_host_ns"],
                        "seen_in_status": None, "seen_after_s": None, "cut_short": True, "status_excerpt": ""})
    return sorted(out, key=lambda e: e["start_ns"])


def windows_for(events: list[dict[str, Any]], topic: str) -> list[tuple[int, int, str]]:
    """Drive-time windows in which a gap in ``topic`` is explained: its faults (plus recovery), disk full."""
    out = []
    for e in events:
        if e["ev"] == "fault" and topic in FAULT_TOPICS[e["kind"]]:
            out.append((e["start_ns"], e["end_ns"] + int(RECOVERY_S * NS), e["kind"]))
        elif e["ev"] == "pps_off" and topic == "/pps":
            out.append((e["start_ns"], e["end_ns"] + int(5 * NS), "receiver without time fix"))
    return sorted(out)


def explained(windows: list[tuple[int, int, str]], a: int, b: int) -> str | None:
    """The window that covers most of the silence (a, b): a gap that overlaps one is explained by it."""
    for start, end, why in windows:
        if start <= b and a <= end:
            return why
    return None


def analyse(args: argparse.Namespace, out: Path, segments: list[Segment]) -> dict[str, Any]:
    from logger.recording.files import is_finished

    report: dict[str, Any] = {"drive_hours": sum(s.drive_s for s in segments) / 3600, "time_scale": args.time_scale,
                              "segments": [], "faults": [], "gaps_outside_faults": {}, "seq_breaks_outside": {}}
    files = read_files(out)
    all_ok = True
    for seg in segments:
        journal = [json.loads(line) for line in (out / f"journal-{seg.index}.jsonl").read_text().splitlines()]
        faults = faults_of(journal)
        events = [e for e in journal if e["ev"] not in ("fault", "fault_start")] + faults
        start = next(e for e in events if e["ev"] == "start")
        samples = [e for e in events if e["ev"] == "sample"]
        end = next((e for e in events if e["ev"] == "end"), None)
        seg_files = sorted(n for n, f in files.items() if f["seed"] == seg.seed)
        # Threads alive at the end: the last sample before the stop (a kill -9 leaves no later word).
        last = samples[-1] if samples else {}
        expected = {"sampler-imu", "sampler-baro", "sampler-obd", "sampler-gnss", "sampler-pps", "recorder",
                    "health", "status", "service"}
        missing_threads = sorted(expected - set(last.get("threads", [])))
        # RSS after warm-up: the first sample after one file rotation, against the last one.
        rss = [(e["drive_ns"] - start["drive_ns"], e["rss_kb"]) for e in samples]
        warm = next((kb for t, kb in rss if t >= RSS_WARM_UP_S * NS), None)
        rss_growth_mb = (rss[-1][1] - warm) / 1024 if warm is not None and rss else None
        # Records: every seq of a topic in this segment's files, in order; breaks outside faults are losses.
        lost: dict[str, list[str]] = defaultdict(list)
        gaps: dict[str, list[str]] = defaultdict(list)
        counted: dict[str, int] = defaultdict(int)
        unjudged: dict[str, int] = defaultdict(int)
        health = sorted(h for n in seg_files for h in files[n]["health"])
        # The last /health record comes before the samplers' last records (the health loop ends first when the
        # daemon stops); a worker that stopped cleanly journals the counters once every sampler has ended.
        final = end is not None and "sensors" in end
        if final:
            health.append((end["drive_ns"], {n: (c["late"] + c["missed"], c["gaps"])
                                             for n, c in end["sensors"].items()}))
        health_t = [t for t, _ in health]

        def daemon_counted(sensor: str, a: int, b: int, health: list[Any] = health, health_t: list[int] = health_t,
                           final: bool = final) -> bool | None:
            """The daemon's own counters (late + missed periods, gaps) grew across the silence (a, b): it knew
            and reported it (/health, `logger status`); a silence nobody counted would be a silent loss. None
            when the counters were last read too soon after the silence to tell (the tail before a kill -9)."""
            if not health:
                return False
            # The counters move when the sampler's late read returns, which can be well after the silence ended
            # when the read itself was held up (a serial timeout is real time, 60 drive seconds at 60x).
            i = max(0, bisect.bisect_right(health_t, a) - 1)
            j = bisect.bisect_left(health_t, b + COUNTER_LAG_S * NS)
            if j == len(health):  # no reading that late: the last one, if read after every sampler had ended
                if not final and b > health_t[-1] - LAST_READING_MARGIN_S * NS:  # or long enough after the silence
                    return None
                j -= 1
            if i >= j:
                return False
            before, after = health[i][1].get(sensor), health[j][1].get(sensor)
            return before is not None and after is not None and (after[0] > before[0] or after[1] > before[1])

        for topic, hz in SENSOR_TOPICS.items():
            recs = sorted(r for n in seg_files for r in files[n]["topics"][topic])
            wins = windows_for(events, topic)
            disk = [w for w in windows_for(events, "/imu") if w[2] == "disk_nearly_full"]
            for (t0, s0), (t1, s1) in itertools.pairwise(recs):
                if s1 != s0 + 1 and not explained(disk, t0, t1):
                    lost[topic].append(f"seq {s0}->{s1} at drive {(t0 - start['drive_ns']) / NS:.0f} s")
                if t1 - t0 > GAP_PERIODS * NS / hz and t0 - start["drive_ns"] > WARM_UP_S * NS \
                        and not explained(wins, t0, t1):
                    verdict = daemon_counted(SENSOR_OF_TOPIC[topic], t0, t1)
                    if verdict is None:
                        unjudged[topic] += 1
                    elif verdict:
                        counted[topic] += 1
                    else:
                        gaps[topic].append(f"{(t1 - t0) / NS:.2f} s at drive {(t0 - start['drive_ns']) / NS:.0f} s")
        # Log lines in each fault's window that name its sensor or say what happened.
        for f in faults:
            words = FAULT_SENSOR[f["kind"]].split("|") + (["recording", "disk"] if f["kind"] == "disk_nearly_full"
                                                           else [])
            grace = 3 * NS
            hits = [line for t, line in seg.log_lines
                    if f["start_host_ns"] <= t <= f["end_host_ns"] + grace and any(w in line for w in words)]
            report["faults"].append({
                "segment": seg.index, "kind": f["kind"], "at_drive_s": round((f["start_ns"] - start["drive_ns"]) / NS),
                "lasted_s": round((f["end_ns"] - f["start_ns"]) / NS, 1), "status": f["seen_in_status"],
                "status_after_s": f["seen_after_s"], "log": hits[0][:160] if hits else None,
                "cut_short_by_the_stop": f.get("cut_short", False),
                "status_excerpt": f.get("status_excerpt", "")})
        recovered = []
        if seg.index > 0 and segments[seg.index - 1].ends_by == "kill9":
            recovered = [line for _, line in seg.log_lines if "recovered " in line]
        stopped_cleanly = seg.ends_by != "kill9" and seg.exit_code == 0 and end is not None and \
            end.get("threads_left") == []
        report["segments"].append({
            "index": seg.index, "drive_h": round(seg.drive_s / 3600, 2), "ended_by": seg.ends_by,
            "exit_code": seg.exit_code, "stopped_cleanly": stopped_cleanly if seg.ends_by != "kill9" else None,
            "files": seg_files, "threads_missing_at_end": missing_threads,
            "stale_threads_seen": sorted({s for e in samples for s in e.get("stale", [])}),
            "rss_warm_mb": round(warm / 1024, 1) if warm else None,
            "rss_end_mb": round(rss[-1][1] / 1024, 1) if rss else None,
            "rss_growth_mb": round(rss_growth_mb, 2) if rss_growth_mb is not None else None,
            "faults": len(faults), "injector_errors": [e for e in events if e["ev"] == "injector_error"],
            "records_lost_outside_faults": {k: v[:5] + ([f"... {len(v)} in all"] if len(v) > 5 else [])
                                            for k, v in lost.items() if v},
            "gaps_outside_faults_uncounted": {k: v[:5] + ([f"... {len(v)} in all"] if len(v) > 5 else [])
                                              for k, v in gaps.items() if v},
            "gaps_outside_faults_counted_by_daemon": dict(counted),
            "gaps_after_the_last_counters": dict(unjudged),
            "records": {t: sum(len(files[n]["topics"][t]) for n in seg_files) for t in SENSOR_TOPICS},
            "recovered_lines": recovered,
            "sensor_counters_at_end": last.get("sensors", {}),
        })
        seg_report = report["segments"][-1]
        # Every figure measured counts (the verdict said OK over a worker that exited 1, a fault neither the status
        # nor the log showed, an injector that failed or a thread seen stale); memory only where measured (below).
        all_ok &= (not missing_threads and not lost and not gaps and (rss_growth_mb is None or rss_growth_mb <= 5.0)
                   and seg_report["stopped_cleanly"] in (True, None) and not seg_report["injector_errors"]
                   and not seg_report["stale_threads_seen"])
    unfinished = [n for n in files if not is_finished(out / n)]
    report["files"] = {"count": len(files), "unfinished": unfinished}
    report["kill9_files_recovered"] = all(s["recovered_lines"] for s in report["segments"]
                                          if s["index"] > 0 and segments[s["index"] - 1].ends_by == "kill9")
    # A fault the worker's stop cut short may end before the status or the log could show it: not counted.
    whole = [f for f in report["faults"] if not f["cut_short_by_the_stop"]]
    report["faults_cut_short"] = len(report["faults"]) - len(whole)
    report["faults_seen_in_status"] = sum(1 for f in whole if f["status"])
    report["faults_seen_in_log"] = sum(1 for f in whole if f["log"])
    report["rss_measured"] = any(s["rss_growth_mb"] is not None for s in report["segments"])
    report["ok"] = bool(all_ok and not unfinished and report["kill9_files_recovered"]
                        and report["faults_seen_in_status"] == len(whole) == report["faults_seen_in_log"])
    return report


def summary(report: dict[str, Any]) -> str:
    lines = [f"soak: {report['drive_hours']:.2f} h of drive at {report['time_scale']:g}x, "
             f"{len(report['faults'])} faults injected, {report['files']['count']} files"]
    for s in report["segments"]:
        lines.append(f"  segment {s['index']}: {s['drive_h']} h, ended by {s['ended_by']} (exit {s['exit_code']}), "
                     f"threads missing at end: {s['threads_missing_at_end'] or 'none'}, "
                     f"RSS {s['rss_warm_mb']} -> {s['rss_end_mb']} MB (growth {s['rss_growth_mb']} MB)")
        lines.append(f"    records lost outside faults: {s['records_lost_outside_faults'] or 'none'}")
        lines.append(f"    records: {s['records']}")
        lines.append(f"    gaps outside faults nobody counted: {s['gaps_outside_faults_uncounted'] or 'none'}; "
                     f"counted by the daemon as late/missed samples or gaps (host too slow for the time scale): "
                     f"{s['gaps_outside_faults_counted_by_daemon'] or 'none'}")
        if s["gaps_after_the_last_counters"]:
            lines.append(f"    gaps too near the end to judge (counters last read before they could show them): "
                         f"{s['gaps_after_the_last_counters']}")
        if s["recovered_lines"]:
            lines.append(f"    after kill -9: {'; '.join(x.split(': ', 1)[-1] for x in s['recovered_lines'])}")
    lines.append(f"  files unfinished at the end: {report['files']['unfinished'] or 'none'}; files cut by kill -9 "
                 f"recovered: {report['kill9_files_recovered']}")
    n = len(report["faults"]) - report["faults_cut_short"]
    lines.append(f"  faults shown by the status: {report['faults_seen_in_status']}/{n}, "
                 f"in the log: {report['faults_seen_in_log']}/{n}"
                 + (f" ({report['faults_cut_short']} cut short by a worker's stop, not counted)"
                    if report["faults_cut_short"] else ""))
    by_kind: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for f in report["faults"]:
        if not f["cut_short_by_the_stop"]:
            by_kind[f["kind"]].append(f)
    for kind, fs in sorted(by_kind.items()):
        lines.append(f"    {kind:<18} x{len(fs)}: status {sum(1 for f in fs if f['status'])}/{len(fs)}, "
                     f"log {sum(1 for f in fs if f['log'])}/{len(fs)}")
    if not report.get("rss_measured", True):
        lines.append(f"  memory not judged: no segment ran past the {RSS_WARM_UP_S / 60:.0f} min of drive of the "
                     "warm-up (the RSS growth is measured after it)")
    lines.append(f"  verdict: {'OK' if report['ok'] else 'NOT OK'}"
                 + (" (memory not judged)" if report["ok"] and not report.get("rss_measured", True) else ""))
    return "\n".join(lines)


def plan_segments(args: argparse.Namespace) -> list[Segment]:
    """Three workers: the longest first (for the memory figure), ended by SIGTERM; then one ended by kill -9;
    the last runs to its planned end. Where each cut falls is random, from the seed."""
    rng = random.Random(args.seed)
    total = args.hours * 3600.0
    first = total * rng.uniform(0.55, 0.65)
    second = (total - first) * rng.uniform(0.4, 0.6)
    return [Segment(0, first, "sigterm", args.seed), Segment(1, second, "kill9", args.seed + 1),
            Segment(2, total - first - second, "duration", args.seed + 2)]


def reanalyse(out: Path) -> int:
    """The analysis again, on a folder a finished soak left (after changing the analysis, not the run)."""
    saved = json.loads((out / "segments.json").read_text())
    args = argparse.Namespace(**saved["args"])
    segments = [Segment(**s) for s in saved["segments"]]
    for seg in segments:
        for line in (out / f"log-{seg.index}.txt").read_text().splitlines():
            stamp, _, text = line.partition(" ")
            seg.log_lines.append((int(stamp), text))
    report = analyse(args, out, segments)
    (out / "soak-report.json").write_text(json.dumps(report, indent=1, default=str))
    print(summary(report))
    return 0 if report["ok"] else 1


def orchestrate(args: argparse.Namespace) -> int:
    out = Path(args.out).resolve()
    if out.exists() and any(out.glob("*.mcap")):
        print(f"soak: {out} already holds drives; give an empty folder", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    segments = plan_segments(args)
    t0 = time.monotonic()
    for seg in segments:
        journal = out / f"journal-{seg.index}.jsonl"
        journal.unlink(missing_ok=True)
        run_segment(seg, args, out, journal)
        (out / f"log-{seg.index}.txt").write_text("\n".join(f"{t} {line}" for t, line in seg.log_lines))
    (out / "segments.json").write_text(json.dumps(
        {"args": vars(args), "segments": [{k: v for k, v in asdict(s).items() if k != "log_lines"}
                                          for s in segments]}, indent=1))
    report = analyse(args, out, segments)
    report["wall_s"] = round(time.monotonic() - t0)
    (out / "soak-report.json").write_text(json.dumps(report, indent=1, default=str))
    print(summary(report))
    print(f"report: {out / 'soak-report.json'}  ({report['wall_s']} s)")
    return 0 if report["ok"] else 1


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hours", type=float, default=8.0, help="hours of drive in all (default 8)")
    p.add_argument("--time-scale", type=float, default=60.0,
                   help="drive seconds per real second at most (default 60): the drive runs as fast as the host allows")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--scenario", default="urban")
    p.add_argument("--out", default="soak-out", help="empty folder for files, journals, logs and the report")
    p.add_argument("--mean-fault-gap-s", type=float, default=420.0, help="mean drive seconds between faults")
    p.add_argument("--faults", default=",".join(FAULT_TOPICS), help="comma-separated fault kinds")
    p.add_argument("--nav", action="store_true", help="run the live navigation filter too (more CPU)")
    p.add_argument("--truth", action="store_true", help="record the simulation's truth topics too (more CPU)")
    p.add_argument("--light-imu", action=argparse.BooleanOptionalAction, default=None,
                   help="cache the IMU model's trajectory on a 50 ms grid (default: above 10x)")
    p.add_argument("--sample-real-s", type=float, default=2.0, help="RSS/thread sample period, real seconds")
    p.add_argument("--analyse", metavar="DIR", help="only analyse the folder of a finished soak again")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--journal", help=argparse.SUPPRESS)
    p.add_argument("--duration", type=float, help=argparse.SUPPRESS)
    p.add_argument("--end-by", choices=("sigterm", "kill9"), help=argparse.SUPPRESS)
    p.add_argument("--end-at", type=float, default=0.0, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    if args.light_imu is None:
        args.light_imu = args.time_scale > 10
    if args.worker:
        return worker(args)
    if args.analyse:
        return reanalyse(Path(args.analyse))
    with contextlib.suppress(KeyboardInterrupt):
        return orchestrate(args)
    return 130


if __name__ == "__main__":
    sys.exit(main())
