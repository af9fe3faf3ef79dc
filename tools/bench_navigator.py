"""The live navigator's CPU at an IMU rate, side by side with another checkout of this project.

    python tools/bench_navigator.py --imu-rate 1000 --seconds 120 [--against /path/to/other/checkout]

``Navigator.take`` over a synthetic urban drive (``tests/test_nav_synth.records``: the drive's standing start,
then driving; OBD at 2 Hz, barometer and fixes at 1 Hz) as the daemon feeds it: FIFO reads of max(10, rate / 25)
samples, a wake-up every ``WAKE_S`` of drive, /nav/fix and /nav/state published. No threads, no simulator, no
recorder: the thread's CPU clock around ``take`` alone, best of ``--repeat`` runs, each checkout in its own process
and the runs alternated, so the ratio between two checkouts is measured in one go on the same host. The daemon
benchmark (tools/bench_daemon.py) gives the navigator thread's share in the running daemon; this one isolates it
from the host's noise (its other threads, the simulated devices) to compare two versions of the filter.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_once(root: Path, rate_hz: float, seconds: float) -> dict[str, float]:
    """One run in this process, importing the project from ``root``."""
    sys.path[:0] = [str(root), str(root / "tests")]
    from test_nav_batch import _runs, _with_temperature
    from test_nav_synth import records
    from test_navigator_merge import _read

    from logger.nav.params import NavParams
    from logger.recording.topics import IMU_BATCH
    from logger.runtime.navigator import WAKE_S, Navigator
    from sensors.sim.scenarios import make_drive

    per_read = max(10, int(rate_hz / 25))
    recs = _with_temperature(records(make_drive("urban", seed=1, duration_s=seconds), seconds, seed=4,
                                     imu_hz=rate_hz))
    items = []
    for topic, item in _runs(recs, per_read):
        if topic == "batch":
            items.append((item[-1]["t_sync_ns"], IMU_BATCH, _read(item, item[-1]["temp_degc"], period_s=1 / rate_hz)))
        else:
            items.append((item["t_sync_ns"], topic, item))
    published: list[object] = []
    nav = Navigator(NavParams(), publish=published.append)
    chunk: list[tuple[str, dict[str, object]]] = []
    wake_ns = int(WAKE_S * 1e9)
    end = items[0][0] + wake_ns
    c0 = time.thread_time()
    for t, topic, m in items:
        if t >= end:
            nav.take(chunk)
            chunk, end = [], end + wake_ns
        chunk.append((topic, m))
    nav.take(chunk)
    cpu = time.thread_time() - c0
    return {"cpu_s": cpu, "pct": cpu / seconds * 100.0, "published": len(published),
            "started": nav.engine.state is not None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--imu-rate", type=float, default=1000.0, help="IMU rate, Hz (default 1000)")
    ap.add_argument("--seconds", type=float, default=120.0, help="length of the synthetic drive, s (default 120)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per checkout, the best taken (default 3)")
    ap.add_argument("--against", type=Path, help="another checkout of this project, measured alternately")
    ap.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(run_once(args.child, args.imu_rate, args.seconds)))
        return
    roots = [ROOT] + ([args.against.resolve()] if args.against else [])
    best: dict[Path, dict[str, float]] = {}
    for _ in range(args.repeat):
        for root in roots:
            out = subprocess.run([sys.executable, __file__, "--child", str(root), "--imu-rate", str(args.imu_rate),
                                  "--seconds", str(args.seconds)], capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            if root not in best or r["cpu_s"] < best[root]["cpu_s"]:
                best[root] = r
    for root in roots:
        r = best[root]
        print(f"{root}: navigator {r['pct']:.3f} % of a core at {args.imu_rate:.0f} Hz over a {args.seconds:.0f} s "
              f"drive ({r['published']} records published, filter started: {r['started']})")
    if args.against:
        print(f"ratio this / other: {best[ROOT]['cpu_s'] / best[roots[1]]['cpu_s']:.3f}")


if __name__ == "__main__":
    main()
