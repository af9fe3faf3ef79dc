"""Speed of the navigation filter: replay throughput and the live navigator's share of one core.

    python tools/nav_bench.py DRIVE.mcap... [--live-s 60] [--repeat 3] [--batch] [--only filter|decode]
    python tools/nav_bench.py --fifo-s 60 [--fifo-feed per-read|merged|none]

Replay: the whole ``logger replay`` pipeline (read, decode, filter, no output files) over the drive, timed as
process CPU time and as wall time, per IMU sample and as a multiple of real time. Filter alone: the drive's
records read and decoded first (not timed), then the engine fed from memory as replay feeds it, per mode, the
best of ``--repeat`` runs (a shared machine only ever adds time); with ``--batch`` also with every run of
consecutive IMU samples handed over at once through ``NavEngine.imu_batch`` (its arrays built beforehand, as a
FIFO read's are). ``--only filter`` stops after the filter alone; ``--only decode`` only reads and decodes the
drive: under ``valgrind --tool=callgrind`` the difference of the two runs' instruction totals, divided by the IMU
samples, is the filter's instructions per sample (GNSS, OBD and barometer updates included). Live: the drive's records
are offered to a running :class:`~logger.runtime.navigator.Navigator` paced at the drive's own rate for ``--live-s``
seconds of real time, and the CPU time of the navigator thread plus that of every ``offer`` call (the part
the sampler threads pay) is divided by the elapsed time. Figures go to stdout; no test asserts on them.

FIFO reads (``--fifo-s``, no drive needed): a simulated drive (the ``outage-60s`` scenario) as the daemon queues it
for the navigator with a 1 kHz FIFO IMU, 40-sample ``/imu/batch`` reads with a die temperature each between GNSS
fixes (1 Hz), OBD speeds (2 Hz) and barometer readings (1 Hz); after ``--fifo-head`` seconds fed untimed (the
filter levels and starts), ``--fifo-s`` seconds go to a :class:`~logger.runtime.navigator.Navigator` (no thread,
publishing into nothing) either read by read with a publish check after each, as the navigator fed them before
runs were merged (``per-read``: ``Navigator.take(records, merge=False)``), or as its wake-ups take them
(``merged``: :meth:`Navigator.take` per ``WAKE_S`` of records); ``none`` only builds the stream and feeds the
head. CPU time depends on what else the
machine runs; instruction counts do not: run each under ``valgrind --tool=callgrind`` and subtract the ``none``
run's total from the others', divided by the samples the line reports::

    PYTHONHASHSEED=0 valgrind --tool=callgrind --callgrind-out-file=/tmp/cg.%p python tools/nav_bench.py \
        --fifo-s 60 --fifo-feed merged
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
from logger.recording.records import NAV_INPUT_TOPICS, feed_record, imu_batch_payload, nav_feeder
from logger.recording.topics import BARO, GNSS_FIX, IMU, IMU_BATCH, OBD_SPEED
from logger.runtime.navigator import INPUT_TOPICS, WAKE_S, Navigator, in_offer_order
from sensors.sim.scenarios import make_drive

NS = 1_000_000_000
T0_NS = 1_700_000_000 * NS


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
    msgs = in_offer_order(read_messages(files, tuple(INPUT_TOPICS)))
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
        time.sleep(WAKE_S + 0.5)  # its next wake-up takes the last records: let it finish before reading its CPU
    finally:
        nav.stop()
    drive_s = (msgs[i - 1][0] - t_first) / 1e9
    total = nav.cpu_s + offer_cpu
    print(f"live navigator, from {start_s:g} s: {drive_s:.0f} s of drive at real time "
          f"({nav.processed} records, {nav.dropped} dropped): thread {nav.cpu_s * 1e3:.0f} ms + offer "
          f"{offer_cpu * 1e3:.0f} ms of CPU in {wall:.0f} s = {total / wall * 100:.3f} % of one core")


def fifo_stream(seconds: float, imu_hz: float = 1000.0, per_read: int = 40,
                seed: int = 1) -> list[tuple[int, str, dict[str, Any]]]:
    """(time queued, topic, record) of ``seconds`` of the ``outage-60s`` drive as the daemon offers it to the
    navigator with a FIFO IMU: reads of ``per_read`` samples queued at their last sample, each with one die
    temperature (warming slowly, read with noise); GNSS fixes arriving 0.2 s after their epoch, OBD speeds,
    barometric altitudes. The truth is taken at 100 Hz and interpolated: a bench's stream, not a test's."""
    drive = make_drive("outage-60s", seed=seed, duration_s=seconds + 1.0)
    rng = np.random.default_rng(seed)
    tk = np.arange(0.0, seconds + 0.5, 0.01)
    truth = [drive.state(float(t)) for t in tk]
    t = np.arange(int(seconds * imu_hz)) / imu_hz
    f = np.array([np.interp(t, tk, [s.f_body_mps2[i] for s in truth]) for i in range(3)]).T
    w = np.array([np.interp(t, tk, [s.w_body_rps[i] for s in truth]) for i in range(3)]).T
    f += np.array((0.2, -0.15, 0.1)) + rng.normal(0.0, 0.012, f.shape)
    w += np.radians((1.5, -2.0, 0.8)) + rng.normal(0.0, 3e-4, w.shape)
    times = (t * NS).round().astype(np.int64)
    out: list[tuple[int, str, dict[str, Any]]] = []
    for lo in range(0, len(t), per_read):
        sl = slice(lo, lo + per_read)
        temp = 30.0 + 0.01 * t[lo] + rng.normal(0.0, 0.03)
        m = imu_batch_payload(times[sl].tolist(), f[sl], w[sl], temp, 1.0 / imu_hz, 0)
        m["t_sync_ns"] = [T0_NS + x for x in m["t_mono_ns"]]
        m["seq"] = lo  # the first sample's number, as the daemon's stamped record has it (records.stamped_batch)
        out.append((m["t_sync_ns"][-1], IMU_BATCH, m))
    for k in range(int(seconds)):
        s = drive.state(float(k))
        ts = T0_NS + (k * 1000 + 200) * 1_000_000
        dn, de, dd = rng.normal(0.0, (0.5, 0.5, 1.0))
        out.append((ts, GNSS_FIX, {
            "t_sync_ns": ts, "t_mono_ns": ts - T0_NS, "sync_state": "locked", "gnss_time_ns": T0_NS + k * NS,
            "fix_ok": True, "fix_mode": 3, "latitude": np.degrees(s.lat_rad + dn / 6.37e6),
            "longitude": np.degrees(s.lon_rad + de / (6.37e6 * np.cos(s.lat_rad))), "altitude": s.height_m - dd,
            "vel_ned_mps": (np.asarray(s.vel_ned_mps) + rng.normal(0.0, 0.05, 3)).tolist(), "h_acc_m": 0.7,
            "v_acc_m": 1.0, "s_acc_mps": 0.05, "pdop": 1.2, "num_sv": 18}))
        tb = ts + 100_000_000
        out.append((tb, BARO, {"t_sync_ns": tb, "t_mono_ns": tb - T0_NS,
                               "altitude_m": s.height_m - 27.0 + rng.normal(0.0, 0.25)}))
        for half in (0, 1):
            to = T0_NS + (k * 1000 + half * 500 + 100) * 1_000_000
            kmh = round(max(0.0, drive.state((to - T0_NS) / NS).forward_speed_mps) * 3.6)
            out.append((to, OBD_SPEED, {"t_sync_ns": to, "t_mono_ns": to - T0_NS, "speed_kmh": kmh,
                                        "speed_mps": kmh / 3.6}))
    out.sort(key=lambda r: r[0])
    return out


def bench_fifo(seconds: float, head_s: float, feed: str) -> None:
    """The navigator's filter over ``seconds`` of 1 kHz FIFO reads after ``head_s`` (see the module's text)."""
    items = fifo_stream(head_s + seconds)
    start = T0_NS + int(head_s * NS)
    head = [r for r in items if r[0] < start]
    items = items[len(head):]
    nav = Navigator(NavParams(), publish=lambda r: None)

    def read_by_read(part: list[tuple[int, str, dict[str, Any]]]) -> None:
        nav.take([(topic, m) for _, topic, m in part], merge=False)

    read_by_read(head)
    n0 = nav.engine.counters.imu
    gc.collect()
    c0 = time.process_time()
    if feed == "per-read":
        read_by_read(items)
    elif feed == "merged":
        wake = int(WAKE_S * NS)
        chunk: list[tuple[str, dict[str, Any]]] = []
        end = start + wake
        for t, topic, m in items:
            while t >= end:
                nav.take(chunk)
                chunk, end = [], end + wake
            chunk.append((topic, m))
        nav.take(chunk)
    cpu = time.process_time() - c0
    n = nav.engine.counters.imu - n0
    started = nav.engine.counters.initialised_ns
    print(f"FIFO reads, {feed}: {n} IMU samples in {seconds:g} s after {head_s:g} s (filter started at "
          f"{(started - T0_NS) / NS if started else float('nan'):.1f} s)"
          + (f", CPU {cpu / n * 1e6:.2f} us per sample" if n else ""))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", type=Path, nargs="*")
    ap.add_argument("--live-s", type=float, default=60.0, help="real seconds of the paced live run (0: skip)")
    ap.add_argument("--live-from", type=float, default=60.0, help="drive second where the paced run starts")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--repeat", type=int, default=3, help="runs of the filter alone per mode (the best is shown)")
    ap.add_argument("--batch", action="store_true", help="also time the filter alone fed through imu_batch")
    ap.add_argument("--only", choices=("filter", "decode"),
                    help="filter: the filter alone and nothing after it (no replays, no live run); decode: only read "
                         "and decode the drive (the baseline to subtract from a filter-only instruction count)")
    ap.add_argument("--fifo-s", type=float, default=0.0,
                    help="instead of a drive: seconds of simulated 1 kHz FIFO reads through the navigator")
    ap.add_argument("--fifo-head", type=float, default=20.0, help="seconds fed untimed before (the start)")
    ap.add_argument("--fifo-feed", choices=("per-read", "merged", "none"), nargs="+",
                    default=["per-read", "merged"], help="how the reads go to the filter")
    args = ap.parse_args(argv)
    if args.fifo_s > 0:
        for feed in args.fifo_feed:
            bench_fifo(args.fifo_s, args.fifo_head, feed)
        return 0
    if not args.files:
        ap.error("a drive (DRIVE.mcap...) or --fifo-s")
    msgs = list(read_drive(args.files, NAV_INPUT_TOPICS))
    if args.only == "decode":
        print(f"read and decoded {len(msgs)} records, {sum(t == IMU for t, _ in msgs)} IMU samples")
        return 0
    batches = imu_runs(msgs) if args.batch else None
    for mode in args.modes:
        if mode != "gnss":
            bench_filter_alone(msgs, mode, args.repeat)
            if batches is not None:
                bench_filter_alone(msgs, mode, args.repeat, batches)
    del msgs, batches
    if args.only == "filter":
        return 0
    for mode in args.modes:
        bench_replay(args.files, mode, False)
    bench_replay(args.files, "17", True)
    if args.live_s > 0:
        bench_live(args.files, args.live_s, args.live_from)
    return 0


if __name__ == "__main__":
    sys.exit(main())
