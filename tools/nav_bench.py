"""Speed of the navigation filter: replay throughput and the live navigator's share of one core.

    python tools/nav_bench.py DRIVE.mcap... [--live-s 60] [--repeat 3] [--batch]

Replay: the whole ``logger replay`` pipeline (read, decode, filter, no output files) over the drive, timed as
process CPU time and as wall time, per IMU sample and as a multiple of real time. Filter alone: the drive's
records read and decoded first (not timed), then the engine fed from memory as replay feeds it, per mode, the
best of ``--repeat`` runs (a shared machine only ever adds time); with ``--batch`` also with every run of
consecutive IMU samples handed over at once through ``NavEngine.imu_batch`` (its arrays built beforehand, as a
FIFO read's are). Live: the drive's records
are offered to a running :class:`~logger.runtime.navigator.Navigator` paced at the drive's own rate for ``--live-s``
seconds of real time, and the CPU time of the navigator thread plus that of every ``offer`` call (the part
the sampler threads pay) is divided by the elapsed time. Figures go to stdout; no test asserts on them.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from logger.exports.trajectory import read_drive, run_filter
from logger.nav.engine import NavEngine
from logger.nav.params import MODES, NavParams
from logger.recording.drive import read_messages
from logger.recording.records import NAV_INPUT_TOPICS, feed_record, nav_feeder
from logger.recording.topics import IMU
from logger.runtime.navigator import INPUT_TOPICS, Navigator


def bench_replay(files: list[Path], mode: str, smooth: bool) -> dict[str, float | int | str | bool]:
    """Time one replay, print the line and return the figures (``tools/bench.py`` tabulates them)."""
    p = NavParams(mode=mode)
    c0, w0 = time.process_time(), time.perf_counter()
    engine, rows = run_filter(files, p, smooth)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    n = engine.counters.imu or len(rows)
    span = (rows[-1][0] - rows[0][0]) / 1e9 if len(rows) > 1 else 0.0
    what = "fixes" if mode == "gnss" else "IMU samples"
    print(f"replay mode {mode}{' + smoother' if smooth else ''}: {n} {what}, {span:.0f} s of drive: "
          f"CPU {cpu:.2f} s ({cpu / max(n, 1) * 1e6:.1f} us per sample, {span / max(cpu, 1e-9):.0f}x real time), "
          f"wall {wall:.2f} s ({wall / max(n, 1) * 1e6:.1f} us per sample)")
    return {"mode": mode, "smooth": smooth, "samples": n, "what": what, "drive_s": span, "cpu_s": cpu,
            "wall_s": wall, "cpu_us_per_sample": cpu / max(n, 1) * 1e6, "x_real_time_cpu": span / max(cpu, 1e-9),
            "x_real_time_wall": span / max(wall, 1e-9)}


def imu_runs(msgs: list[tuple[str, dict[str, Any]]]) -> list[tuple[str, Any]]:
    """The records with each run of consecutive IMU records as one ``("batch", imu_batch arguments)`` item."""
    out: list[tuple[str, Any]] = []
    run: list[dict[str, Any]] = []

    def close() -> None:
        if run:
            out.append(("batch", (np.array([m["t_sync_ns"] for m in run], np.int64),
                                  np.array([m["t_mono_ns"] for m in run], np.int64),
                                  np.array([m["accel_mps2"] for m in run], float),
                                  np.array([m["gyro_rps"] for m in run], float), run[-1].get("temp_degc"))))
            run.clear()

    for topic, m in msgs:
        if topic == IMU:
            run.append(m)
            continue
        close()
        out.append((topic, m))
    close()
    return out


def bench_filter_alone(msgs: list[tuple[str, dict[str, Any]]], mode: str, repeat: int,
                       batches: list[tuple[str, Any]] | None = None) -> float:
    """CPU per IMU sample of the engine fed decoded records from memory (``batches``: through imu_batch), the best
    of ``repeat`` runs; prints the line."""
    best, n = float("inf"), 0
    for _ in range(repeat):
        engine = NavEngine(NavParams(mode=mode), record=True)
        feed = nav_feeder(engine)
        gc.collect()
        c0 = time.process_time()
        if batches is None:
            for topic, m in msgs:
                feed_record(feed, topic, m)
        else:
            batch = engine.imu_batch
            for topic, item in batches:
                if topic == "batch":
                    batch(*item)
                else:
                    feed_record(feed, topic, item)
        best = min(best, time.process_time() - c0)
        n = engine.counters.imu
    how = "IMU runs through imu_batch" if batches is not None else "sample by sample"
    print(f"filter alone, mode {mode}, {how}: {n} IMU samples, CPU {best / max(n, 1) * 1e6:.2f} us per sample "
          f"(best of {repeat})")
    return best / max(n, 1) * 1e6


def bench_live(files: list[Path], seconds: float, start_s: float) -> None:
    msgs = [(m["t_sync_ns"], t, m) for t, m in read_messages(files, tuple(INPUT_TOPICS))]
    nav = Navigator(NavParams(), publish=lambda r: None)
    # Everything before start_s goes in at once (levelling, heading), then the paced part is measured.
    skip = msgs[0][0] + int(start_s * 1e9)
    head = [m for m in msgs if m[0] < skip]
    msgs = msgs[len(head):]
    feed = nav_feeder(nav.engine)
    for _, topic, m in head:
        feed_record(feed, topic, m)
    nav.start()
    offer_cpu = 0.0
    t_first = msgs[0][0]
    start = time.perf_counter()
    i = 0
    try:
        while i < len(msgs):
            elapsed = time.perf_counter() - start
            if elapsed >= seconds:
                break
            due = t_first + elapsed * 1e9
            c0 = time.thread_time()
            while i < len(msgs) and msgs[i][0] <= due:
                nav.offer(msgs[i][1], msgs[i][2])
                i += 1
            offer_cpu += time.thread_time() - c0
            time.sleep(0.005)
        wall = time.perf_counter() - start
        time.sleep(0.5)  # let the navigator finish its last batch before reading its CPU time
    finally:
        nav.stop()
    drive_s = (msgs[i - 1][0] - t_first) / 1e9
    total = nav.cpu_s + offer_cpu
    print(f"live navigator, from {start_s:g} s: {drive_s:.0f} s of drive at real time "
          f"({nav.processed} records, {nav.dropped} dropped): thread {nav.cpu_s * 1e3:.0f} ms + offer "
          f"{offer_cpu * 1e3:.0f} ms of CPU in {wall:.0f} s = {total / wall * 100:.3f} % of one core")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", type=Path, nargs="+")
    ap.add_argument("--live-s", type=float, default=60.0, help="real seconds of the paced live run (0: skip)")
    ap.add_argument("--live-from", type=float, default=60.0, help="drive second where the paced run starts")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--repeat", type=int, default=3, help="runs of the filter alone per mode (the best is shown)")
    ap.add_argument("--batch", action="store_true", help="also time the filter alone fed through imu_batch")
    args = ap.parse_args(argv)
    msgs = list(read_drive(args.files, NAV_INPUT_TOPICS))
    batches = imu_runs(msgs) if args.batch else None
    for mode in args.modes:
        if mode != "gnss":
            bench_filter_alone(msgs, mode, args.repeat)
            if batches is not None:
                bench_filter_alone(msgs, mode, args.repeat, batches)
    del msgs, batches
    for mode in args.modes:
        bench_replay(args.files, mode, False)
    bench_replay(args.files, "17", True)
    if args.live_s > 0:
        bench_live(args.files, args.live_s, args.live_from)
    return 0


if __name__ == "__main__":
    sys.exit(main())
