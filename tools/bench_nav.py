"""The navigation filter's cost per IMU sample, and ``logger replay``'s speed as a multiple of real time.

    python tools/bench_nav.py DRIVE.mcap... --json out.json

The filter alone: ``tools/nav_bench.py``'s replay timing (read, decode and filter, no output files) in each
mode, and the 17-state mode with the smoother; its drive length is the span of the filter's output (from the
first solution on), its CPU per sample counts every IMU sample fed. The whole command: ``logger replay DRIVE
--out DIR`` as a user runs it, interpreter start (its modules from bytecode, as pip installs them:
tools/bytecode.py) and the trajectory's CSV and MCAP included, timed from outside
as wall time and as the child's CPU time, against the drive's length from its first to its last IMU record.
The live navigator's share of a core at the IMU rate is in the daemon benchmark.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from bytecode import compile_tree  # noqa: E402
from nav_bench import bench_replay  # noqa: E402


def time_cli(files: list[Path]) -> dict[str, float]:
    """``logger replay`` (17-state, no smoother) as a separate process, its modules from bytecode as installed
    (tools/bytecode.py): wall and CPU seconds."""
    compile_tree()
    with tempfile.TemporaryDirectory(prefix="bench-replay-") as out:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "logger.cli", "replay", *map(str, files), "--out", out], cwd=ROOT,
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"wall_s": wall, "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)}


def drive_span_s(files: list[Path]) -> float:
    """Seconds from the first to the last IMU record: the drive the whole command goes through."""
    from logger.recording.drive import read_messages

    first = last = None
    for _, m in read_messages(files, ("/imu",)):
        first = m["t_sync_ns"] if first is None else first
        last = m["t_sync_ns"]
    return (last - first) / 1e9 if first is not None and last is not None else 0.0


def run(files: list[Path]) -> dict[str, Any]:
    modes = [bench_replay(files, mode, False) for mode in ("17", "15", "gnss")]
    modes.append(bench_replay(files, "17", True))
    cli = time_cli(files)
    span = drive_span_s(files)
    cli.update(drive_s=span, x_real_time_wall=span / max(cli["wall_s"], 1e-9),
               x_real_time_cpu=span / max(cli["cpu_s"], 1e-9))
    return {"replays": modes, "cli": cli}


def render(result: dict[str, Any]) -> list[str]:
    lines = ["| filter | samples | drive | CPU per sample | x real time (CPU) | x real time (wall) |",
             "| --- | --- | --- | --- | --- | --- |"]
    for r in result["replays"]:
        name = {"17": "17-state", "15": "15-state", "gnss": "GNSS only"}[r["mode"]] + (" + smoother" if r["smooth"]
                                                                                        else "")
        lines.append(f"| {name} | {r['samples']} {r['what']} | {r['drive_s']:.0f} s | {r['cpu_us_per_sample']:.1f} us "
                     f"| {r['x_real_time_cpu']:.0f}x | {r['x_real_time_wall']:.0f}x |")
    c = result["cli"]
    lines += ["", f"`logger replay` (17-state, whole command with interpreter start and output files) over "
              f"{c['drive_s']:.0f} s of drive: {c['wall_s']:.1f} s wall, {c['cpu_s']:.1f} s CPU: "
              f"**{c['x_real_time_wall']:.0f}x real time** ({c['x_real_time_cpu']:.0f}x per CPU second)."]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", type=Path, nargs="+", help="a recorded drive")
    ap.add_argument("--json", type=Path, help="write the result here as JSON")
    args = ap.parse_args(argv)
    missing = [str(f) for f in args.files if not f.is_file()]
    if missing:
        ap.error(f"no such file: {', '.join(missing)}")
    result = run(args.files)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
