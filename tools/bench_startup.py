"""Start-up time: from starting the process to the first sample the recorder has written, per sensor.

    python tools/bench_startup.py --runs 5 --json out.json

Each run is a new process (``--worker``) that does what ``logger run --sim`` does: imports, builds the
simulated vehicle and the daemon, runs it. Times are on CLOCK_MONOTONIC, which parent and child share, from
just before the parent starts the child. The worker notes when each topic's first record left the recorder's
writer thread (written into the open chunk; it is on disk at the next flush, within ``flush_interval_s``),
when the daemon was ready (what systemd's READY=1 waits for), and its own CPU time at the first IMU record.
Building the simulated vehicle (the drive, ptys, device models) is timed on its own: a board does not do it,
so it is also taken out of the board figure. The GNSS fix and PPS times are the simulated receiver's own
start-up (time to first fix), not the daemon's. The worker imports the logger's modules from bytecode compiled
beforehand, as a board's pip-installed logger does (tools/bytecode.py): a checkout run with PYTHONDONTWRITEBYTECODE
would otherwise compile them at every start.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from bench_daemon import sim_config  # noqa: E402  (the tool's own: imported before the worker's clock starts)
from bytecode import compile_tree  # noqa: E402

SENSOR_TOPICS = ("/imu", "/baro", "/obd/speed", "/gnss/fix", "/pps")
AS_SAMPLES = {"/imu/batch": "/imu"}  # the IMU's first FIFO read is its first samples' record
NS = 1_000_000_000


def worker(spawn_ns: int, out: Path) -> dict[str, Any]:
    t_main = time.monotonic_ns()
    import sensors.sim.vehicle as sim_vehicle
    from logger.compose import build
    from logger.runtime import logs

    t_imported = time.monotonic_ns()
    logs.setup(False)
    marks: dict[str, Any] = {}
    original_build = sim_vehicle.build_vehicle

    def build_vehicle(*args: Any, **kwargs: Any) -> Any:
        t0, c0 = time.monotonic_ns(), time.process_time()
        vehicle = original_build(*args, **kwargs)
        marks["vehicle_s"] = (time.monotonic_ns() - t0) / NS
        marks["vehicle_cpu_s"] = time.process_time() - c0
        return vehicle

    sim_vehicle.build_vehicle = build_vehicle  # type: ignore[assignment]
    daemon, _vehicle = build(sim_config(out), 120.0)
    daemon.attachments.periodic.clear()  # no /truth/* topics, as on a board
    t_built = time.monotonic_ns()
    first: dict[str, tuple[int, float]] = {}
    all_seen = threading.Event()
    def note_first(topic: str) -> None:  # the writer thread wrote this topic's first record
        first.setdefault(AS_SAMPLES.get(topic, topic), (time.monotonic_ns(), time.process_time()))
        if all(t in first for t in SENSOR_TOPICS):
            all_seen.set()

    daemon.recorder.on_first_record = note_first

    def watch() -> None:
        daemon.ready.wait(90.0)
        marks["ready_ns"] = time.monotonic_ns()
        all_seen.wait(90.0)
        daemon.stop_event.set()

    threading.Thread(target=watch, name="bench-startup", daemon=True).start()
    daemon.run(None)
    since = {t: (ns - spawn_ns) / NS for t, (ns, _) in first.items() if t in SENSOR_TOPICS}
    return {"interpreter_s": (t_main - spawn_ns) / NS, "imports_s": (t_imported - t_main) / NS,
            "vehicle_s": marks.get("vehicle_s", 0.0), "vehicle_cpu_s": marks.get("vehicle_cpu_s", 0.0),
            "build_s": (t_built - t_imported) / NS - marks.get("vehicle_s", 0.0),
            "ready_s": (marks["ready_ns"] - spawn_ns) / NS if "ready_ns" in marks else None,
            "first_s": since, "cpu_at_first_imu_s": first["/imu"][1] if "/imu" in first else None}


def run(runs: int) -> dict[str, Any]:
    compile_tree()  # the worker imports bytecode, as an installed logger does
    results = []
    for _ in range(runs):
        with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
            result_path = Path(tmp) / "result.json"
            spawn = time.monotonic_ns()
            proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", str(spawn), "--out",
                                   str(Path(tmp) / "drive"), "--json", str(result_path)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=300)
            if proc.returncode:
                raise SystemExit(f"bench_startup: worker failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
            results.append(json.loads(result_path.read_text()))
    return {"runs": results}


def _median(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return statistics.median(vals) if vals else None


def summary(result: dict[str, Any]) -> dict[str, Any]:
    runs = result["runs"]
    s: dict[str, Any] = {k: _median([r[k] for r in runs]) for k in
                         ("interpreter_s", "imports_s", "vehicle_s", "vehicle_cpu_s", "build_s", "ready_s",
                          "cpu_at_first_imu_s")}
    s["first_s"] = {t: _median([r["first_s"].get(t) for r in runs]) for t in SENSOR_TOPICS}
    s["first_imu_max_s"] = max((r["first_s"].get("/imu") or 0.0) for r in runs)
    if s["first_s"]["/imu"] is not None:
        s["first_imu_board_s"] = s["first_s"]["/imu"] - (s["vehicle_s"] or 0.0)
    return s


def render(result: dict[str, Any]) -> list[str]:
    s = summary(result)
    f = s["first_s"]

    def sec(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f} s"

    lines = [f"Median of {len(result['runs'])} starts, from starting the process:", "",
             "| step | time |", "| --- | --- |",
             f"| interpreter up (the tool's own imports) | {sec(s['interpreter_s'])} |",
             f"| the logger's imports | +{sec(s['imports_s'])} |",
             f"| simulated vehicle built (not on a board) | +{sec(s['vehicle_s'])} |",
             f"| daemon built (configuration, clock, drivers' plans) | +{sec(s['build_s'])} |",
             "| **first IMU samples written by the recorder** (the first FIFO read) | "
             f"**{sec(f['/imu'])}** (slowest run "
             f"{s['first_imu_max_s']:.2f} s); without the simulated vehicle's build "
             f"**{sec(s.get('first_imu_board_s'))}** |",
             f"| first barometer sample | {sec(f['/baro'])} |",
             f"| first OBD speed | {sec(f['/obd/speed'])} |",
             f"| ready (READY=1: every sensor's first open returned, the first file open) | {sec(s['ready_s'])} |",
             f"| first PPS edge (the simulated receiver's time pulse) | {sec(f['/pps'])} |",
             f"| first GNSS fix (the simulated receiver's time to first fix) | {sec(f['/gnss/fix'])} |",
             "", f"Process CPU time at the first IMU record: {sec(s['cpu_at_first_imu_s'])}, of which building the "
             f"simulated vehicle {sec(s['vehicle_cpu_s'])}."]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="starts to time; the median counts (default 5)")
    ap.add_argument("--json", type=Path, help="write the result here as JSON")
    ap.add_argument("--worker", type=int, metavar="SPAWN_NS", help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker is not None:
        result = worker(args.worker, args.out)
    else:
        if args.runs < 1:
            ap.error("--runs must be at least 1")
        result = run(args.runs)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    else:
        print("\n".join(render(result)) if args.worker is None else json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
