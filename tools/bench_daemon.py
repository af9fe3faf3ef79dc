"""Daemon CPU and memory on the simulated vehicle, thread by thread, and whether every IMU sample kept its time.

    python tools/bench_daemon.py --imu-rate 20 --seconds 300 --json out.json [--profile]

``logger run --sim`` holds the daemon and the simulated vehicle in one process, so the process's CPU time
overstates what a board would spend: the ELM327, u-blox and PPS models run on their own threads, and the I2C
chip models even run inside the daemon's sampler threads (a register read goes through smbus2 into the
simulated i2c-dev ioctl, where the MPU-6050 model generates its samples). So CPU is taken per thread, from
``/proc/self/task/<tid>/stat``, and split by thread name into the daemon's threads (samplers, recorder,
navigator, health, service, status, main) and the simulator's (``sim-*``, ``ublox-model``); the CPU a daemon
thread spends inside the simulated kernel (I2C ioctl, GPIO edge FIFO) is measured with that thread's own CPU
clock and moved to the simulator's side. The kernel work a board does for the same transfers (i2c-omap, the
serial and GPIO drivers) is not in either figure; the I2C transfer count is reported so it can be estimated.
Each thread's wake-ups a second (voluntary context switches, ``wakes_per_s`` in the JSON) come with it: a quiet
thread's share is its work per wake-up times their number, and they tell which of the two to cut.

The run is real time (time scale 1) with the default configuration except the IMU rate, as on a board: the
navigation filter runs live, and the drive is not paced (a paced drive's threads wait in short steps to follow
its pace, wake-ups a board does not have; at real time a governor has nothing to slow). The simulation's truth
topics (``/truth/*``, recorded only by ``--sim``) are left out, as the soak does: they would make the recorder
write about twice the records a board writes. After start-up and a warm-up the counters are read, again after
``--seconds``, and the difference is the figure.
From the recorded file, within that window: IMU records against the rate, sequence gaps (records lost in the
daemon), FIFO overflow losses, silences longer than 2.5 periods; from the daemon: late and missed sampler
periods and recorder drops. ``--profile`` runs the same with cProfile on every thread (on the thread's CPU
clock, so waiting does not count) and reports where the daemon threads' CPU goes; profiled runs are slower,
so they give the ranking, not the figure. ``--nice`` lowers the niceness (as root): on a machine shared with
other jobs they then delay the sampler threads less, as nothing would on the board; CPU time is CPU time
either way. Threads a library starts without Python's ``threading`` (numpy's BLAS workers) appear as
``native:`` with their kernel name.
"""

from __future__ import annotations

import argparse
import cProfile
import functools
import itertools
import json
import os
import pstats
import sys
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(1, str(ROOT / "tools"))  # run by path from elsewhere too (runpy, the board root)

import resident  # noqa: E402

from logger.recording.topics import GAP_PERIODS  # noqa: E402  the daemon's own definition of a gap

NS = 1_000_000_000
DAEMON_PREFIXES = ("sampler-", "recorder", "health", "service", "status", "navigator", "MainThread")
SIM_PREFIXES = ("sim-", "ublox-model")
BENCH_PREFIX = "bench-"


def thread_class(name: str) -> str:
    """daemon, sim or bench, by the thread's name (the daemon and the device models name every thread)."""
    if name.startswith(BENCH_PREFIX):
        return "bench"
    if name.startswith(SIM_PREFIXES):
        return "sim"
    if name.startswith(DAEMON_PREFIXES):
        return "daemon"
    return "other"


def sim_config(out: Path) -> Any:
    """``logger run --sim``'s configuration with every file, socket and saved state inside ``out``."""
    from logger.config import defaults

    cfg = defaults(sim=True)
    cfg.values["logger"].update(out_dir=str(out), state_dir=str(out / ".state"), status_socket=str(out / "status.sock"))
    return cfg


# ---- /proc readers -------------------------------------------------------------------------------------------
def task_cpu_s() -> dict[int, float]:
    """CPU seconds (user + system) of every thread of this process, by thread id."""
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[int, float] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            text = Path(f"/proc/self/task/{tid}/stat").read_text(encoding="ascii")
        except OSError:  # the thread ended meanwhile
            continue
        fields = text.rsplit(")", 1)[1].split()  # the name may hold spaces and parentheses
        out[int(tid)] = (int(fields[11]) + int(fields[12])) / tick
    return out


def task_wakes() -> dict[int, int]:
    """Voluntary context switches of every thread of this process, by thread id: each is a wait that ended (a
    sleep, a lock, a read), so their rate is how often a thread wakes, a cost the CPU share of a quiet thread is
    mostly made of."""
    out: dict[int, int] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/status", encoding="ascii") as f:
                for line in f:
                    if line.startswith("voluntary_ctxt_switches:"):
                        out[int(tid)] = int(line.split()[1])
                        break
        except OSError:  # the thread ended meanwhile
            continue
    return out


UNIT = ROOT / "systemd" / "vehicle-logger.service"
SIM_MODULES = "sensors.sim"
_MODULES_RSS_CHILD = """
import importlib, json, sys
sys.path.insert(0, "tools")
from resident import rss_kb as rss
names = json.loads(sys.stdin.read())
def load(group):
    for name in group:
        try:
            importlib.import_module(name)
        except BaseException:
            pass
load(names["rest"])
before = rss()
load(names["built"])
built = rss()
load(names["sim"])
print(json.dumps({"before": before, "built": built, "after": rss()}))
"""


def unit_environment(unit: Path = UNIT) -> dict[str, str]:
    """The ``Environment=`` assignments of the service unit: the benchmark runs the daemon with them, as systemd
    does on the board (glibc reads MALLOC_ARENA_MAX once, at the process's start)."""
    env: dict[str, str] = {}
    for line in unit.read_text(encoding="utf-8").splitlines():
        key, _, value = line.strip().partition("=")
        if key == "Environment":
            for item in value.split():
                name, eq, val = item.strip('"').partition("=")
                if eq:
                    env[name] = val
    return env


def daemon_named_modules(roots: tuple[str, ...] = ("logger", "sync", "sensors")) -> set[str]:
    """Every module name the daemon's own code imports, at the top of a file or inside a function (the simulator's
    ``sensors.sim`` left out): a library the simulator happened to load first is still the daemon's if these
    name it."""
    import ast

    names: set[str] = set()
    for root in roots:
        for path in (ROOT / root).rglob("*.py"):
            if path.is_relative_to(ROOT / SIM_MODULES.replace(".", "/")):
                continue
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    names.update(a.name for a in node.names)
                elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                    names.add(node.module)
    return names


def sim_modules_rss_mb(loaded: list[str], while_building: list[str] | None = None) -> tuple[float, float]:
    """Resident memory the simulator's modules add to an interpreter that holds every other module the run loaded,
    measured in a child, which imports the others, then those: (what the libraries first loaded while the drive was
    built add, what they and ``sensors.sim`` add).

    ``while_building``: the modules that appeared while the simulated drive was built. Those the daemon's code does
    not name (:func:`daemon_named_modules`) are the simulator's: with numpy 2, ``numpy.random`` (and ``secrets``,
    ``hashlib`` and OpenSSL's library behind it), which the daemon never imports; with numpy 1.24.2 (Debian 12's,
    the board's) ``import numpy`` loads it, so it is there before the drive is built and counts for the daemon. The
    part the build's libraries add is inside the RSS measured across the build: :func:`run` takes it out of the
    drive's figure, so that the drive is its data only. A library only the simulator imports from elsewhere counts
    for the daemon: the estimate errs on the daemon's side."""
    import subprocess

    sim = sorted(n for n in loaded if n == SIM_MODULES or n.startswith(SIM_MODULES + "."))
    named = daemon_named_modules()
    present = set(loaded)
    built = sorted(n for n in (while_building or []) if n not in sim and n not in named and n in present)
    rest = sorted(n for n in loaded
                  if n not in sim and n not in built and n != "__main__" and not n.startswith("bench"))
    try:
        out = subprocess.run([sys.executable, "-c", _MODULES_RSS_CHILD],
                             input=json.dumps({"rest": rest, "built": built, "sim": sim}),
                             capture_output=True, text=True, cwd=ROOT, timeout=120, check=True)
        got = json.loads(out.stdout)
    except (OSError, subprocess.SubprocessError, ValueError):
        return 0.0, 0.0
    return round((got["built"] - got["before"]) / 1024, 1), round((got["after"] - got["before"]) / 1024, 1)


def set_niceness(nice: int) -> int:
    """Ask for a niceness; returns the one in force (unchanged when not permitted)."""
    if nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except (PermissionError, OSError) as exc:
            print(f"bench_daemon: cannot set niceness {nice} ({exc.strerror or exc}); running at the default",
                  file=sys.stderr)
    return os.getpriority(os.PRIO_PROCESS, 0)


def thread_names(tids: Any) -> dict[int, str]:
    """Python's name for each thread id; a thread Python did not start gets its kernel name (comm)."""
    names = {t.native_id: t.name for t in threading.enumerate() if t.native_id}
    for tid in tids:
        if tid not in names:
            try:
                names[tid] = "native:" + Path(f"/proc/self/task/{tid}/comm").read_text(encoding="ascii").strip()
            except OSError:
                names[tid] = f"tid-{tid}"
    return names


# ---- CPU the daemon's threads spend inside the simulated kernel --------------------------------------------
class SimMeter:
    """Thread CPU time spent inside methods of the simulated kernel, per thread name (outermost call only)."""

    def __init__(self) -> None:
        self._local = threading.local()
        self._lock = threading.Lock()
        self.by_thread: dict[str, float] = defaultdict(float)
        self.profiles: ThreadProfiles | None = None  # paused inside the simulation, so they show the daemon only

    def wrap(self, owner: type, name: str) -> None:
        original: Callable[..., Any] = getattr(owner, name)
        meter = self

        @functools.wraps(original)
        def metered(*args: Any, **kwargs: Any) -> Any:
            local = meter._local
            if getattr(local, "inside", False):
                return original(*args, **kwargs)
            local.inside = True
            profile = meter.profiles.current() if meter.profiles is not None else None
            if profile is not None:
                profile.disable()
            t0 = time.thread_time()
            try:
                return original(*args, **kwargs)
            finally:
                spent = time.thread_time() - t0
                local.inside = False
                if profile is not None:
                    profile.enable()
                who = threading.current_thread().name
                with meter._lock:
                    meter.by_thread[who] += spent

        setattr(owner, name, metered)

    def install(self) -> None:
        """The seams where a daemon thread enters the simulation: the i2c-dev ioctl (chip models behind it)
        and the GPIO character device's edge FIFO (the PPS line's edges are produced when it is read)."""
        from sensors.sim import gpiod_ext, i2c

        self.wrap(i2c.SimI2cAdapter, "ioctl")
        self.wrap(gpiod_ext.SimLineRequest, "_catch_up")
        self.wrap(gpiod_ext.SimLineRequest, "read_edge_events")

    def snapshot(self) -> dict[str, float]:
        with self._lock:
            return dict(self.by_thread)


class ThreadProfiles:
    """cProfile on every thread started after ``install``, timed by the thread's own CPU clock."""

    def __init__(self) -> None:
        self.profiles: list[tuple[str, cProfile.Profile]] = []
        self._lock = threading.Lock()
        self._local = threading.local()

    def install(self) -> None:
        threading.setprofile(self._first_event)

    def current(self) -> cProfile.Profile | None:
        return getattr(self._local, "profile", None)

    def _first_event(self, frame: Any, event: str, arg: Any) -> None:
        sys.setprofile(None)
        profile = cProfile.Profile(time.thread_time)
        self._local.profile = profile
        with self._lock:
            self.profiles.append((threading.current_thread().name, profile))
        profile.enable()

    def top(self, n: int = 20, thread: str | None = None, dump: Path | None = None) -> dict[str, Any]:
        """The daemon threads' functions by own CPU time (one thread's, if named), and the same summed per module;
        with ``dump``, the merged statistics are written there too (``python -m pstats FILE``: callers, cumulative
        times)."""
        stats: pstats.Stats | None = None
        for name, profile in self.profiles:
            if thread_class(name) != "daemon" or (thread is not None and name != thread):
                continue
            profile.disable()
            stats = pstats.Stats(profile) if stats is None else stats.add(profile)
        if stats is None:
            return {"functions": [], "modules": [], "total_s": 0.0}
        if dump is not None:
            stats.dump_stats(dump)
        raw = stats.stats  # type: ignore[attr-defined]
        total = sum(v[2] for v in raw.values()) or 1e-12
        rows = sorted(raw.items(), key=lambda kv: kv[1][2], reverse=True)
        functions = [{"function": f"{_short(f)}:{line}({fn})", "own_s": round(v[2], 3),
                      "share": round(v[2] / total, 4), "calls": v[1], "sim": _is_sim(f)}
                     for (f, line, fn), v in rows[:n]]
        modules: dict[str, float] = defaultdict(float)
        for (f, _line, _fn), v in raw.items():
            if f != "~" or not v[4]:
                modules[_short(f)] += v[2]
                continue
            for (caller_file, _l, _n), per_caller in v[4].items():  # a built-in counts for the module calling it
                modules[_short(caller_file)] += per_caller[2]
        mods = [{"module": m, "own_s": round(s, 3), "share": round(s / total, 4), "sim": _is_sim(m)}
                for m, s in sorted(modules.items(), key=lambda kv: kv[1], reverse=True)[:n]]
        return {"functions": functions, "modules": mods, "total_s": round(total, 3)}


def _short(path: str) -> str:
    """A file path as a reader knows it: this tree's files relative to it, libraries by package."""
    if path == "~":
        return "(built-in)"
    if path.startswith(str(ROOT)) and "site-packages" not in path:
        return os.path.relpath(path, ROOT)
    if "site-packages/" in path:
        return path.split("site-packages/", 1)[1]
    if "/lib/python3" in path:
        return "stdlib " + path.split("/lib/python3", 1)[1].split("/", 1)[1]
    return path


def _is_sim(path: str) -> bool:
    return "sensors/sim/" in path or path.startswith("sensors/sim")


# ---- the run ------------------------------------------------------------------------------------------------
@dataclass
class Snapshot:
    wall_s: float
    mono_ns: int
    process_cpu_s: float
    task_cpu_s: dict[int, float]
    task_wakes: dict[int, int]
    names: dict[int, str]
    sim_inside_s: dict[str, float]
    rss_kb: int
    hwm_kb: int
    sensors: dict[str, dict[str, int]]
    recorder_written: int
    recorder_dropped: int
    nav: dict[str, int]
    i2c_transfers: int


def take_snapshot(daemon: Any, vehicle: Any, meter: SimMeter) -> Snapshot:
    snap = daemon.snapshot()
    times = os.times()
    nav = snap.get("nav") or {}
    cpu = task_cpu_s()
    return Snapshot(
        wall_s=time.monotonic(), mono_ns=int(daemon.tb.monotonic_ns()), process_cpu_s=times.user + times.system,
        task_cpu_s=cpu, task_wakes=task_wakes(), names=thread_names(cpu),
        sim_inside_s=meter.snapshot(), rss_kb=resident.rss_kb(), hwm_kb=resident.peak_kb() or 0,
        sensors={s["name"]: {k: s[k] for k in ("samples", "late", "missed", "gaps", "errors", "reconnects")}
                 for s in snap["sensors"]},
        recorder_written=sum(snap["recorder"]["written"].values()),
        recorder_dropped=sum(snap["recorder"]["dropped"].values()),
        nav={k: int(nav.get(k) or 0) for k in ("processed", "dropped")},
        i2c_transfers=vehicle.i2c.transfer_count if vehicle is not None and vehicle.i2c is not None else 0)


def _by_name(a: dict[int, float], b: dict[int, float], names: dict[int, str]) -> dict[str, float]:
    """A per-thread counter's growth from ``a`` to ``b`` per thread name (threads of one name summed)."""
    out: dict[str, float] = defaultdict(float)
    for tid, value in b.items():
        out[names.get(tid, f"tid-{tid}")] += value - a.get(tid, 0)
    return dict(out)


def cpu_by_thread(a: Snapshot, b: Snapshot) -> dict[str, float]:
    """CPU seconds between two snapshots per thread name."""
    return _by_name(a.task_cpu_s, b.task_cpu_s, {**a.names, **b.names})


def wakes_by_thread(a: Snapshot, b: Snapshot) -> dict[str, float]:
    """Voluntary context switches between two snapshots per thread name."""
    return _by_name(dict(a.task_wakes), dict(b.task_wakes), {**a.names, **b.names})


@dataclass
class DaemonResult:
    imu_rate_hz: float
    window_s: float
    startup_s: float
    warmup_s: float
    profile: bool
    threads: dict[str, dict[str, float]] = field(default_factory=dict)  # name -> cpu_s, pct, class
    daemon_pct: float = 0.0
    sim_pct: float = 0.0
    sim_inside_daemon_pct: float = 0.0
    bench_pct: float = 0.0
    other_pct: float = 0.0
    process_pct: float = 0.0
    rss_start_mb: float = 0.0
    rss_end_mb: float = 0.0
    rss_growth_mb: float = 0.0
    hwm_mb: float = 0.0
    rss_source: str = resident.NATIVE  # or the guest's pages, inside the emulated board root (tools/resident.py)
    sim_build_rss_mb: float = 0.0
    sim_modules_rss_mb: float = 0.0
    sim_build_modules_mb: float = 0.0  # of which libraries the simulator alone loaded as it built the drive
    writer_index: dict[str, float] = field(default_factory=dict)  # what the MCAP writer keeps per chunk
    # The run's library versions (LIBRARIES): numpy 1 (Debian 12's 1.24.2) loads numpy.random and numpy.ma with
    # ``import numpy``, numpy 2 does not.
    libraries: dict[str, str] = field(default_factory=dict)
    environment: dict[str, str] = field(default_factory=dict)
    rss_series_mb: list[float] = field(default_factory=list)
    counters: dict[str, Any] = field(default_factory=dict)
    file: dict[str, Any] = field(default_factory=dict)
    i2c_transfers_per_s: float = 0.0
    sustained: bool = False
    profile_top: dict[str, Any] = field(default_factory=dict)


def analyse_file(files: list[Path], rate_hz: float, t0_ns: int, t1_ns: int) -> dict[str, Any]:
    """/imu in [t0, t1], in the order the daemon numbered the records: records against the rate, sequence gaps
    (records lost inside the daemon), FIFO overflow losses, and how regular the stamps are (a stamp more than
    2.5 periods after the one before is what the daemon counts as a gap; one before it is a stamp that went back)."""
    from logger.recording.drive import iter_messages, open_drive

    # A FIFO rate records batches (/imu/batch); the reader hands on their samples as /imu records.
    imu: list[tuple[int, int, int]] = [(m.msg["seq"], m.msg["t_mono_ns"], m.msg.get("lost", 0))
                                       for m in iter_messages(open_drive(files), ["/imu"])]
    imu.sort()
    inside = [r for r in imu if t0_ns <= r[1] <= t1_ns]
    pairs = list(itertools.pairwise(inside))
    period_ns = NS / rate_hz
    steps = [b[1] - a[1] for a, b in pairs if b[0] == a[0] + 1]
    return {"imu_records": len(inside), "expected": round((t1_ns - t0_ns) / NS * rate_hz),
            "seq_missing": sum(max(0, b[0] - a[0] - 1) for a, b in pairs),
            "fifo_lost": sum(r[2] for r in inside),
            "stamp_gaps": sum(1 for d in steps if d > GAP_PERIODS * period_ns),
            "stamp_backwards": sum(1 for d in steps if d < 0),
            "stamp_step_error_max_ms": round(max((abs(d - period_ns) for d in steps), default=0.0) / 1e6, 2),
            "imu_records_whole_run": len(imu)}


# The libraries the daemon runs on: the report's machine table and each run's versions (what --board-python changes).
LIBRARIES = ("numpy", "mcap", "pyserial", "smbus2", "python-can", "zstandard", "lz4", "ujson", "pyubx2", "pynmeagps",
             "gpiod")


def library_versions() -> dict[str, str]:
    """The installed versions of :data:`LIBRARIES` ("not installed" for one that is not)."""
    import importlib.metadata

    out = {}
    for name in LIBRARIES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _writer_bytes_per_chunk(counts: list[int], t0_ns: int, chunks: int = 1000) -> float:
    """What the recorder's MCAP writer keeps per chunk, measured on the writer itself: ``chunks`` chunks a second
    apart written to a temporary file (real offsets: mcap's Writer, the recorder's until 2026-12-05, kept them as
    Python integers, which /dev/null's zeros would have hidden), chunk i with a message on ``counts[i %
    len(counts)]`` channels (the recorded file's own mix), and Python's allocations that stay (tracemalloc) divided
    by the chunks."""
    import gc
    import tracemalloc

    from logger.recording.mcap_writer import McapWriter

    most = max(counts)
    with tempfile.TemporaryFile() as sink:
        writer = McapWriter(sink)
        writer.start("bench", "writer index")
        schema = writer.register_schema("s", "jsonschema", b"{}")
        ids = [writer.register_channel(f"/c{j}", "json", schema) for j in range(most)]
        tracing = tracemalloc.is_tracing()
        if not tracing:
            tracemalloc.start()
        gc.collect()
        base = tracemalloc.get_traced_memory()[0]
        for i in range(chunks):
            t = t0_ns + i * NS
            for c in ids[:counts[i % len(counts)]]:
                writer.add_message(c, log_time=t + c, data=b"{}", publish_time=t)
            writer.flush()
        gc.collect()
        held = tracemalloc.get_traced_memory()[0] - base
        if not tracing:
            tracemalloc.stop()
        writer.finish()
    return held / chunks


def writer_index(files: list[Path]) -> dict[str, float]:
    """What the recorder's MCAP writer keeps per chunk until its file rotates: a chunk index (the chunk's times,
    place and sizes, and the offset of each channel's message index in it), one per chunk, one chunk per flush. From the
    recorded file: chunks a second (over the chunks' starts) and channels a chunk; the memory the writer keeps per
    chunk of that mix (:func:`_writer_bytes_per_chunk`; Python's allocations, not pages); hence the memory the index
    holds at the end of a file of ``rotate_duration_s`` (the configuration's default, an hour), and how much of it
    the file did not yet hold when it was read (the run's RSS already has the rest). Empty without a readable
    summary of at least two chunks."""
    from mcap.reader import make_reader

    from logger.recording.settings import RecorderSettings

    chunks: list[Any] = []
    for path in files:
        try:
            with open(path, "rb") as fh:
                summary = make_reader(fh).get_summary()
        except Exception:  # whatever the reader refuses (a file cut short): this file gives no figure
            continue
        if summary is not None:
            chunks += summary.chunk_indexes
    starts = sorted(c.message_start_time for c in chunks)
    if len(starts) < 2 or starts[-1] <= starts[0]:
        return {}
    per_s = (len(starts) - 1) / ((starts[-1] - starts[0]) / NS)
    held_s = (max(c.message_end_time for c in chunks) - starts[0]) / NS  # the file's age when it was read
    counts = [len(c.message_index_offsets) for c in chunks]  # each chunk's channels, as the file has them
    channels = sum(counts) / len(counts)
    per_chunk = _writer_bytes_per_chunk(counts, starts[0])
    rotate_s = RecorderSettings.rotate_duration_s
    mib = 1 << 20
    return {"writer": "McapWriter", "chunks_per_s": round(per_s, 2), "channels_per_chunk": round(channels, 1),
            "bytes_per_chunk": round(per_chunk), "rotate_s": rotate_s, "held_s": round(held_s),
            "at_rotation_mb": round(per_chunk * per_s * rotate_s / mib, 1),
            "beyond_window_mb": round(per_chunk * per_s * max(0.0, rotate_s - held_s) / mib, 1)}


def run(imu_rate: float, seconds: float, warmup_s: float, out: Path, profile: bool,
        profile_thread: str | None = None, pstats_path: Path | None = None) -> DaemonResult:
    from logger.compose import build
    from logger.runtime import logs

    logs.setup(False)
    cfg = sim_config(out)
    cfg.values["imu"]["rate_hz"] = imu_rate
    meter = SimMeter()
    meter.install()
    profiles = ThreadProfiles()
    if profile:
        profiles.install()
        meter.profiles = profiles
    # The simulated drive is generated for the run's length; the RSS it adds is not the daemon's.
    import sensors.sim.vehicle as sim_vehicle

    built: dict[str, int] = {}
    while_building: list[str] = []
    original_build = sim_vehicle.build_vehicle

    def build_vehicle(*args: Any, **kwargs: Any) -> Any:
        # Real time and unpaced, as a board runs: a governor only ever slows a drive the host cannot keep (never
        # below real time), and a paced drive's waits go in 50 ms steps to follow its pace, wake-ups that every
        # daemon thread would pay here and none pays on a board. Lateness is still counted by the samplers.
        kwargs["paced"] = False
        built["before"] = resident.rss_kb()
        modules = set(sys.modules)
        vehicle = original_build(*args, **kwargs)
        built["after"] = resident.rss_kb()
        while_building.extend(set(sys.modules) - modules)
        return vehicle

    sim_vehicle.build_vehicle = build_vehicle  # type: ignore[assignment]
    t_start = time.monotonic()
    daemon, vehicle = build(cfg, 120.0 + warmup_s + seconds)
    daemon.attachments.periodic.clear()  # no /truth/* topics: a board records none
    result = DaemonResult(imu_rate, seconds, 0.0, warmup_s, profile)
    snaps: list[Snapshot] = []
    rss: list[float] = []

    def monitor() -> None:
        try:
            if not daemon.ready.wait(90.0):
                print("bench_daemon: the daemon did not become ready within 90 s", file=sys.stderr)
                return
            result.startup_s = time.monotonic() - t_start
            if daemon.stop_event.wait(warmup_s):
                return
            snaps.append(take_snapshot(daemon, vehicle, meter))
            end = time.monotonic() + seconds
            while (left := end - time.monotonic()) > 0:
                rss.append(resident.rss_kb() / 1024)
                if daemon.stop_event.wait(min(5.0, left)):
                    return
            snaps.append(take_snapshot(daemon, vehicle, meter))
        finally:
            daemon.stop_event.set()

    watcher = threading.Thread(target=monitor, name="bench-monitor", daemon=True)
    watcher.start()
    daemon.run(None)
    watcher.join(10.0)
    if len(snaps) != 2:
        raise SystemExit("bench_daemon: the run ended before the measurement window closed")
    a, b = snaps
    wall = b.wall_s - a.wall_s
    per_thread = cpu_by_thread(a, b)
    wakes = wakes_by_thread(a, b)
    inside = {k: b.sim_inside_s.get(k, 0.0) - a.sim_inside_s.get(k, 0.0) for k in b.sim_inside_s}
    sums: dict[str, float] = defaultdict(float)
    for name, cpu in per_thread.items():
        kind = thread_class(name)
        sums[kind] += cpu
        result.threads[name] = {"cpu_s": round(cpu, 3), "pct": round(cpu / wall * 100, 3), "class": kind,
                                "sim_inside_pct": round(inside.get(name, 0.0) / wall * 100, 3),
                                "wakes_per_s": round(wakes.get(name, 0) / wall, 1)}
    moved = sum(v for k, v in inside.items() if thread_class(k) == "daemon")
    result.daemon_pct = round((sums["daemon"] - moved) / wall * 100, 3)
    result.sim_inside_daemon_pct = round(moved / wall * 100, 3)
    result.sim_pct = round((sums["sim"] + moved) / wall * 100, 3)
    result.bench_pct = round(sums["bench"] / wall * 100, 3)
    result.other_pct = round(sums["other"] / wall * 100, 3)
    result.process_pct = round((b.process_cpu_s - a.process_cpu_s) / wall * 100, 3)
    result.window_s = round(wall, 1)
    result.rss_start_mb = round(a.rss_kb / 1024, 1)
    result.rss_end_mb = round(b.rss_kb / 1024, 1)
    result.rss_growth_mb = round((b.rss_kb - a.rss_kb) / 1024, 2)
    # Under qemu-user the kernel keeps no peak of the guest's pages alone: the largest sample stands for it.
    result.hwm_mb = round(max(b.hwm_kb / 1024, a.rss_kb / 1024, b.rss_kb / 1024, *rss), 1)
    result.rss_source = resident.source()
    result.sim_build_modules_mb, result.sim_modules_rss_mb = sim_modules_rss_mb(list(sys.modules), while_building)
    result.sim_build_rss_mb = round((built.get("after", 0) - built.get("before", 0)) / 1024
                                    - result.sim_build_modules_mb, 1)
    result.environment = {k: os.environ.get(k, "") for k in unit_environment()}
    result.libraries = library_versions()
    result.rss_series_mb = [round(x, 1) for x in rss[:: max(1, len(rss) // 12)]]
    result.i2c_transfers_per_s = round((b.i2c_transfers - a.i2c_transfers) / wall, 1)
    result.counters = {
        "sensors": {n: {k: b.sensors[n][k] - a.sensors.get(n, {}).get(k, 0) for k in b.sensors[n]}
                    for n in b.sensors},
        "recorder_written": b.recorder_written - a.recorder_written,
        "recorder_dropped": b.recorder_dropped - a.recorder_dropped,
        "nav": {k: b.nav[k] - a.nav.get(k, 0) for k in b.nav},
        "whole_run_imu_late": b.sensors.get("imu", {}).get("late", 0),
        "whole_run_imu_missed": b.sensors.get("imu", {}).get("missed", 0)}
    result.file = analyse_file(sorted(out.glob("*.mcap")), imu_rate, a.mono_ns, b.mono_ns)
    result.writer_index = writer_index(sorted(out.glob("*.mcap")))
    imu = result.counters["sensors"].get("imu", {})
    # Sustained: no sample lost anywhere and no sampler period late or missed. Irregular stamps are reported
    # beside it (stamp_gaps, stamp_backwards): every sample is there, but its time is off.
    result.sustained = not any((imu.get("late", 1), imu.get("missed", 1), result.counters["recorder_dropped"],
                                result.file["seq_missing"], result.file["fifo_lost"]))
    if profile:
        result.profile_top = profiles.top(thread=profile_thread, dump=pstats_path)
    return result


# ---- report -------------------------------------------------------------------------------------------------
def why_not(r: dict[str, Any]) -> str:
    """What kept a run from being sustained, in a few words."""
    imu = r["counters"]["sensors"].get("imu", {})
    f = r["file"]
    parts = [f"{what} {n}" for n, what in ((imu.get("late", 0), "late polls"), (imu.get("missed", 0), "missed polls"),
                                          (f["seq_missing"], "records lost"), (f["fifo_lost"], "lost to FIFO overflow"),
                                          (r["counters"]["recorder_dropped"], "recorder drops")) if n]
    return ", ".join(parts) or "nothing counted"


def live_costs(r: dict[str, Any]) -> dict[str, float]:
    """CPU per record of the recorder thread and per IMU sample of the navigator thread, in live operation."""
    window = r["window_s"]
    written = r["counters"]["recorder_written"] / window
    samples = r["counters"]["sensors"].get("imu", {}).get("samples", 0) / window
    cpu = {n: t["cpu_s"] / window for n, t in r["threads"].items()}
    return {"records_per_s": written, "imu_per_s": samples,
            "recorder_us_per_record": cpu.get("recorder", 0.0) / max(written, 1e-9) * 1e6,
            "navigator_us_per_sample": cpu.get("navigator", 0.0) / max(samples, 1e-9) * 1e6}


def daemon_alone_mb(r: dict[str, Any]) -> float | None:
    """The process's RSS at the window's end less what the simulator holds: its drive and its modules (None for
    figures saved before the modules were measured)."""
    if "sim_modules_rss_mb" not in r:
        return None
    return r["rss_end_mb"] - r["sim_build_rss_mb"] - r["sim_modules_rss_mb"]


def had_unit_environment(runs: list[dict[str, Any]]) -> bool:
    """Whether every run had the service unit's environment values (a run records the variables' values it had,
    empty for one that was not set)."""
    unit = unit_environment()
    return all(r.get("environment") == unit for r in runs)


def _mb(value: float | None, bold: bool = False) -> str:
    if value is None:
        return "-"
    return f"**{value:.1f} MB**" if bold else f"{value:.1f} MB"


def numpy_version(r: dict[str, Any]) -> str:
    """The numpy a run had ("?" for figures saved before the runs listed their libraries)."""
    return r.get("libraries", {}).get("numpy", "?")


def mb_span(values: list[float]) -> str:
    """"3.9 MB", or "1.1 to 3.4 MB"."""
    low, high = f"{min(values):.1f}", f"{max(values):.1f}"
    return f"{low} MB" if low == high else f"{low} to {high} MB"


def _memory_row(r: dict[str, Any]) -> str:
    return (f"| {r['rss_start_mb']:.1f} -> {r['rss_end_mb']:.1f} MB ({r['rss_growth_mb']:+.2f}) "
            f"| {r['hwm_mb']:.1f} MB | {r['sim_build_rss_mb']:.1f} MB "
            f"| {_mb(r.get('sim_modules_rss_mb'))} | {_mb(daemon_alone_mb(r), bold=True)} |")


def render(results: list[dict[str, Any]], board_runs: list[dict[str, Any]] | None = None) -> list[str]:
    """Markdown: CPU and memory per IMU rate, the per-thread split, and the sustained-rate verdicts; ``board_runs``,
    the same benchmark run with Debian 12's library versions (``tools/bench.py --board-python``): their memory."""
    from logger.runtime.navigator import WAKE_S

    plain = [r for r in results if not r["profile"]]
    lines = ["| IMU rate | window | niceness | daemon threads | simulator (threads + inside daemon threads) "
             "| whole process | RSS at start -> end (growth) | peak RSS | of which the simulated drive "
             "| and the simulator's modules | daemon alone at the end, estimated |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in plain:
        lines.append(f"| {r['imu_rate_hz']:g} Hz | {r['window_s']:.0f} s | {r.get('nice', 0)} "
                     f"| **{r['daemon_pct']:.2f} %** "
                     f"| {r['sim_pct']:.2f} % ({r['sim_inside_daemon_pct']:.2f} % inside) | {r['process_pct']:.2f} % "
                     + _memory_row(r))
    if board_runs:
        libs = board_runs[0]["libraries"]
        numpy1 = all(numpy_version(r).startswith("1.") for r in board_runs)
        lines += ["", "The same with Debian 12's library versions, which the board installs (`.ci/floors.txt`; "
                  "`tools/bench.py --board-python`; this run's: "
                  + ", ".join(f"{k} {v}" for k, v in libs.items()) + ")"
                  + (": numpy 1's `import numpy` loads `numpy.random` and `numpy.ma` too, and OpenSSL's library "
                     "behind `secrets` with them, which numpy 2 leaves until asked for" if numpy1 else "") + ":", "",
                  "| IMU rate | window | daemon threads | RSS at start -> end (growth) | peak RSS "
                  "| of which the simulated drive | and the simulator's modules | daemon alone at the end, estimated |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        lines += [f"| {r['imu_rate_hz']:g} Hz | {r['window_s']:.0f} s | {r['daemon_pct']:.2f} % " + _memory_row(r)
                  for r in board_runs]
    lines += ["", "Per thread, % of one core of this machine (the simulator's share inside a daemon thread in "
              "brackets, already moved out of the daemon figure):", ""]
    names = sorted({n for r in plain for n in r["threads"]}, key=lambda n: (thread_class(n) != "daemon", n))
    lines.append("| thread | class | " + " | ".join(f"{r['imu_rate_hz']:g} Hz" for r in plain) + " |")
    lines.append("| --- | --- | " + " | ".join("---" for _ in plain) + " |")
    for n in names:
        cells = []
        for r in plain:
            t = r["threads"].get(n)
            if t is None:
                cells.append("-")
            else:
                cells.append(f"{t['pct']:.3f}" + (f" ({t['sim_inside_pct']:.3f})" if t["sim_inside_pct"] else ""))
        lines.append(f"| {n} | {thread_class(n)} | " + " | ".join(cells) + " |")
    lines += ["", "Wake-ups a second per daemon thread (voluntary context switches: every wait that ended, a sleep, a "
              "read, a lock or the interpreter's lock handed over): a quiet thread's share above is its work per "
              "wake-up times these:", ""]
    lines.append("| thread | " + " | ".join(f"{r['imu_rate_hz']:g} Hz" for r in plain) + " |")
    lines.append("| --- | " + " | ".join("---" for _ in plain) + " |")
    for n in (n for n in names if thread_class(n) == "daemon"):
        cells = [f"{r['threads'][n]['wakes_per_s']:.1f}" if "wakes_per_s" in r["threads"].get(n, {}) else "-"
                 for r in plain]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines += ["", "Live, the recorder and navigator threads cost more per record than the throughput benchmarks "
              f"below show: the recorder wakes about once a second, the navigator every {WAKE_S:g} s, each takes what "
              "has arrived in one go, and a chunk is closed and fsynced every second whatever the rate, so at low "
              "rates those fixed costs dominate:",
              ""]
    for r in plain:
        c = live_costs(r)
        lines.append(f"- {r['imu_rate_hz']:g} Hz: recorder thread {c['recorder_us_per_record']:.0f} us per record "
                     f"({c['records_per_s']:.0f} records/s), navigator thread {c['navigator_us_per_sample']:.0f} us "
                     f"per IMU sample ({c['imu_per_s']:.0f}/s).")
    if had_unit_environment(plain):
        lines += ["", "The runs have the service unit's environment (`Environment=` in systemd/vehicle-logger.service: "
                  "glibc's malloc arenas at 2, its own limit on the board's one 32-bit core, where this 64-bit host "
                  "with two cores would allow 16)."]
    else:
        lines += ["", "Not every run had the service unit's environment (run without it, or before the benchmark "
                  "took it): those had glibc's default malloc arenas (16 on this 64-bit host with two cores, 2 on the "
                  "board's one 32-bit core)."]
    if plain and all("sim_build_modules_mb" in r for r in plain):
        libs = [r["sim_build_modules_mb"] for r in plain]
        drive = [r["sim_build_rss_mb"] for r in plain]
        lines += ["The daemon alone (where the run measured it) is the process's RSS at the window's end less the "
                  "simulated drive (the growth measured across its building, less the libraries first loaded then "
                  f"that the daemon's code never imports: {mb_span(libs)} in these runs, with numpy 2 `numpy.random` "
                  "and OpenSSL's library behind `secrets`) and the simulator's modules (those libraries and "
                  "`sensors.sim`, measured in a child interpreter that first imports every other module the run "
                  "loaded): an estimate, since the simulator's objects and threads stay in it, the drive's growth "
                  f"depends on what the heap had free ({mb_span(drive)} in these runs), and the board's 32-bit "
                  "interpreter has smaller objects. A library that the daemon's code does not import by name (one "
                  "that numpy or another library loads by itself when first used) counts for the simulator if it "
                  "first appeared while the drive was built."]
    else:
        lines += ["The daemon alone (where the run measured it) is the process's RSS at the window's end less the "
                  "simulated drive (measured as it was built, with any library first loaded then: with numpy 2, "
                  "`numpy.random`) and the simulator's modules (`sensors.sim`, measured in a child interpreter that "
                  "first imports every other module the run loaded): an estimate, since the simulator's objects and "
                  "threads stay in it, and the board's 32-bit interpreter has smaller objects."]
    growth = [r["rss_growth_mb"] for r in plain]
    if growth:
        lines += ["", f"RSS grew by {min(growth):+.1f} to {max(growth):+.1f} MB over each window, by about the same "
                  "whatever the number of records; the growth is not split between the daemon and the simulator, "
                  "and both keep things that grow: the daemon's MCAP writer an index entry per chunk (one a second, "
                  "per-channel offsets) until the file rotates (`rotate_duration_s`, an hour by default); the "
                  "simulated u-blox its last 3600 epochs and the simulated ELM327 its last 2048-4096 command lines, "
                  "for the tests; the filter's history and the mount alignment's running sums are bounded to their "
                  "last 10 s and 4 s. `tools/soak.py` measures growth over hours."]
        idx = [r for r in plain if r.get("writer_index")]
        if idx:
            w = [r["writer_index"] for r in idx]
            who = ("the recorder's writer (`logger/recording/mcap_writer.py`) keeps per chunk of that mix, measured on "
                   "the writer itself" if all(x.get("writer") == "McapWriter" for x in w) else
                   "mcap's Writer (the recorder's until 2026-12-05) keeps per chunk of that mix, measured on the "
                   "Writer itself")
            lines += ["", "The writer's index by the end of an hour's file, from each run's recorded chunks (chunks a "
                      f"second, channels a chunk) and what {who} (Python's allocations, not pages): "
                      + "; ".join(f"{r['imu_rate_hz']:g} Hz {x['chunks_per_s']:.2f} chunks/s x "
                                  f"{x['channels_per_chunk']:.1f} channels, {x['bytes_per_chunk']:.0f} B a chunk, "
                                  f"{x['at_rotation_mb']:.1f} MB at {x['rotate_s'] / 3600:g} h"
                                  + (f" (**{x['beyond_window_mb']:.1f} MB** of it after the window, which ended "
                                     f"{x['held_s']:.0f} s into the file)" if "beyond_window_mb" in x else "")
                                  for r, x in zip(idx, w, strict=True))
                      + ". By the end of each file the daemon holds about that much more than the table says; the "
                      "index is freed as the file rotates (whether its memory is then reused or the RSS keeps "
                      "growing from file to file is what `tools/soak.py`'s RSS growth over hours tells)."]
    lines += ["", "Sustained IMU rate, in the measured window. Sustained means every sample recorded (no sequence "
              "gap, no FIFO overflow, no recorder drop) and no sampler period late or missed; the last three columns "
              "say how regular the samples' stamps are (every sample is there, but its time may be off):", "",
              "| IMU rate | window | IMU records (expected) | late polls | missed polls | records lost (seq) "
              "| FIFO overflow lost | recorder drops | navigator skipped | I2C transfers/s | sustained "
              "| stamp gaps > 2.5 periods | stamps going back | largest stamp step error |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in plain:
        imu = r["counters"]["sensors"].get("imu", {})
        f = r["file"]
        lines.append(f"| {r['imu_rate_hz']:g} Hz | {r['window_s']:.0f} s | {f['imu_records']} ({f['expected']}) "
                     f"| {imu.get('late', '?')} | {imu.get('missed', '?')} | {f['seq_missing']} | {f['fifo_lost']} "
                     f"| {r['counters']['recorder_dropped']} | {r['counters']['nav']['dropped']} "
                     f"| {r['i2c_transfers_per_s']:.0f} | {'yes' if r['sustained'] else '**no**'} "
                     f"| {f['stamp_gaps']} | {f['stamp_backwards']} | {f['stamp_step_error_max_ms']:.2f} ms |")
    ok = [r["imu_rate_hz"] for r in plain if r["sustained"]]
    lines += ["", f"Highest IMU rate sustained without a late, missed, lost or dropped sample: **{max(ok):g} Hz**."
              if ok else "No tried IMU rate was sustained without a late, missed, lost or dropped sample."]
    lines += [f"- {r['imu_rate_hz']:g} Hz not sustained: {why_not(r)}." for r in plain if not r["sustained"]]
    for r in results:
        if r["profile"] and r["profile_top"].get("functions"):
            top = r["profile_top"]
            lines += ["", f"Where the daemon threads' CPU goes at {r['imu_rate_hz']:g} Hz: cProfile on each thread's "
                      f"CPU clock over {r['window_s']:.0f} s, {top['total_s']:.2f} s of profiled CPU (the profiler "
                      "pauses while a daemon thread is inside the simulated kernel, so this is the daemon's own work; "
                      "profiling slows calls down, so read shares, not times):", "",
                      "| module (built-ins counted for the module calling them) | own CPU share | |",
                      "| --- | --- | --- |"]
            lines += [f"| {m['module']} | {m['share'] * 100:.1f} % | {'sim' if m['sim'] else ''} |"
                      for m in top["modules"][:12]]
            lines += ["", "| function | own CPU share | calls | |", "| --- | --- | --- | --- |"]
            lines += [f"| `{fn['function']}` | {fn['share'] * 100:.1f} % | {fn['calls']} "
                      f"| {'sim' if fn['sim'] else ''} |" for fn in top["functions"][:15]]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--imu-rate", type=float, default=20.0, help="IMU rate, Hz (default 20, the configuration's)")
    ap.add_argument("--seconds", type=float, default=120.0, help="length of the measured window, s")
    ap.add_argument("--warmup", type=float, default=15.0, help="seconds after READY before the window opens")
    ap.add_argument("--profile", action="store_true", help="cProfile every thread (slower: ranking only)")
    ap.add_argument("--profile-thread", metavar="NAME", help="with --profile, rank only this thread's functions "
                    "(sampler-imu, recorder, navigator, ...)")
    ap.add_argument("--pstats", type=Path, metavar="FILE",
                    help="with --profile, write the merged statistics there (python -m pstats FILE)")
    ap.add_argument("--nice", type=int, default=0,
                    help="run at this niceness (negative needs root): on a shared machine, keeps other jobs from "
                    "delaying the sampler threads as nothing would on the board")
    ap.add_argument("--out", type=Path, help="folder for the recorded files (default: a temporary one)")
    ap.add_argument("--json", type=Path, help="write the result here as JSON")
    args = ap.parse_args(argv)
    if args.seconds <= 0 or args.warmup < 0:
        ap.error("--seconds must be positive and --warmup not negative")
    from logger.config import SCHEMA

    problem = SCHEMA["imu"]["rate_hz"].check(args.imu_rate)  # type: ignore[misc]
    if problem:
        ap.error(f"--imu-rate {args.imu_rate:g} {problem}")
    nice = set_niceness(args.nice)
    with tempfile.TemporaryDirectory(prefix="bench-daemon-") as tmp:
        out = args.out or Path(tmp)
        result = asdict(run(args.imu_rate, args.seconds, args.warmup, out, args.profile, args.profile_thread,
                                   args.pstats))
    result["nice"] = nice
    text = json.dumps(result, indent=1)
    if args.json:
        args.json.write_text(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    wanted = {k: v for k, v in unit_environment().items() if os.environ.get(k) != v}
    if wanted:  # the unit's environment, read by glibc and Python at start: a fresh process with it
        os.execve(sys.executable, [sys.executable, str(Path(__file__).resolve()), *sys.argv[1:]],
                  {**os.environ, **wanted})
    sys.exit(main())
