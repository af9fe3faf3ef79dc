"""``logger replay FILE... --out DIR [--mode 17|15|gnss] [--smooth]``: the navigation filter over recorded drives.

The same engine as the live navigator, as fast as the files can be read, optionally followed by the
Rauch-Tung-Striebel backward pass. Writes ``DIR/trajectory.csv`` (one row per IMU sample once the filter
runs; per fix in GNSS-only mode) and ``DIR/trajectory.mcap`` with ``/nav/fix`` per row and ``/nav/state``
once a second, so Foxglove draws it next to the recording.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from logger.config import ConfigError, load
from logger.nav.engine import NavEngine
from logger.nav.params import MODES, NavParams
from logger.nav.rotations import dcm_from_quat, euler_from_dcm

NAV_INPUT_TOPICS = ("/imu", "/gnss/fix", "/obd/speed", "/baro", "/pps")
CSV_HEADER = ("t_sync_ns", "t_mono_ns", "lat_deg", "lon_deg", "height_m", "vn_mps", "ve_mps", "vd_mps", "roll_deg",
              "pitch_deg", "yaw_deg", "sn_m", "se_m", "sd_m")


def read_drive(paths: list[Path], topics: tuple[str, ...] = NAV_INPUT_TOPICS) -> Iterator[tuple[str, dict[str, Any]]]:
    """(topic, message) of the given topics over several files (a rotated drive), in log-time order."""
    from logger.nav.recording import read_messages

    return read_messages(paths, topics)


def run_filter(paths: list[Path], params: NavParams, smooth: bool = False,
               states: list[dict[str, Any]] | None = None) -> tuple[NavEngine, list[tuple[Any, ...]]]:
    """Run the engine over the files; returns it and its rows (smoothed when asked). With ``states``, a
    ``/nav/state`` record is appended to it for every second of drive."""
    from logger.nav.live import state_message

    engine = NavEngine(params, record=True)
    feed = engine.feed
    next_state = 0
    for topic, msg in read_drive(paths):
        feed(topic, msg)
        if states is not None and topic == "/imu" and msg["t_sync_ns"] >= next_state and engine.state is not None:
            next_state = msg["t_sync_ns"] + 1_000_000_000
            states.append(state_message(engine, msg["t_sync_ns"], msg["t_mono_ns"]))
    rows = engine.rows
    if smooth and engine.mode != "gnss" and engine.ekf is not None and engine.epochs:
        from logger.nav.smoother import smooth_rows

        engine._propagate()
        engine.epochs[-1].p_plus = engine.ekf.p.copy()
        rows = smooth_rows(rows, engine.epochs, engine.ekf.p)
    return engine, rows


def row_fields(row: tuple[Any, ...]) -> list[Any]:
    t, t_mono, lat, lon, h, vn, ve, vd, q, sig, _ = row
    roll, pitch, yaw = euler_from_dcm(dcm_from_quat(q))
    return [t, t_mono, f"{math.degrees(lat):.9f}", f"{math.degrees(lon):.9f}", f"{h:.3f}", f"{vn:.3f}", f"{ve:.3f}",
            f"{vd:.3f}", f"{math.degrees(roll):.3f}", f"{math.degrees(pitch):.3f}", f"{math.degrees(yaw):.3f}",
            f"{sig[0]:.3f}", f"{sig[1]:.3f}", f"{sig[2]:.3f}"]


def write_csv(path: Path, rows: list[tuple[Any, ...]]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_HEADER)
        for row in rows:
            w.writerow(row_fields(row))


def write_mcap(path: Path, rows: list[tuple[Any, ...]], engine: NavEngine, states: list[dict[str, Any]]) -> None:
    from mcap.writer import CompressionType, Writer

    from logger.nav.live import fix_message
    from logger.topics import TOPICS

    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="vehicle-logger replay")
        ids = {}
        for topic in ("/nav/fix", "/nav/state"):
            spec = TOPICS[topic]
            sid = w.register_schema(spec.schema_name, "jsonschema", json.dumps(spec.schema).encode())
            ids[topic] = w.register_channel(topic, "json", sid)
        for row in rows:
            t, t_mono, lat, lon, h, vn, ve, vd, q, sig, _ = row
            roll, pitch, yaw = euler_from_dcm(dcm_from_quat(q))
            msg = fix_message(t, t_mono, lat, lon, h, (vn, ve, vd), (roll, pitch, yaw), sig,
                              "gnss" if engine.mode == "gnss" else f"ins {engine.mode}-state", engine.mode)
            w.add_message(ids["/nav/fix"], log_time=t, publish_time=t_mono, data=json.dumps(msg).encode())
        for st in states:
            w.add_message(ids["/nav/state"], log_time=st["t_sync_ns"], publish_time=st["t_mono_ns"],
                          data=json.dumps(st).encode())
        w.finish()


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="logger replay", description="run the navigation filter over recorded drives")
    p.add_argument("files", nargs="+", type=Path, help="MCAP files of one drive (several when it was rotated)")
    p.add_argument("--out", required=True, type=Path, help="folder for trajectory.csv and trajectory.mcap")
    p.add_argument("--mode", choices=MODES, default=None, help="17 (default), 15 (GNSS + IMU) or gnss (fixes only)")
    p.add_argument("--smooth", action="store_true", help="add the Rauch-Tung-Striebel backward pass")
    p.add_argument("--config", type=Path, help="take the [nav] tuning from this configuration file")
    p.add_argument("--no-mcap", action="store_true", help="write only the CSV")
    return p.parse_args(argv)


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    missing = [str(f) for f in args.files if not f.exists()]
    if missing:
        print(f"logger replay: no such file: {', '.join(missing)}", file=sys.stderr)
        return 2
    from logger.mcap_files import is_finished

    unfinished = [str(f) for f in args.files if not is_finished(f)]
    if unfinished:
        print(f"logger replay: not a finished recording (still being written, or cut short: "
              f"`logger recover FILE`): {', '.join(unfinished)}", file=sys.stderr)
        return 2
    if args.config is not None:
        try:
            params = NavParams.from_config(load(args.config)["nav"])
        except ConfigError as exc:
            for line in exc.problems:
                print(f"logger replay: {line}", file=sys.stderr)
            return 2
    else:
        params = NavParams()
    if args.mode is not None:
        params.mode = args.mode
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    states: list[dict[str, Any]] | None = None if args.no_mcap else []
    engine, rows = run_filter(args.files, params, args.smooth, states)
    t1 = time.perf_counter()
    write_csv(args.out / "trajectory.csv", rows)
    if states is not None:
        write_mcap(args.out / "trajectory.mcap", rows, engine, states)
    c = engine.counters
    span = (rows[-1][0] - rows[0][0]) / 1e9 if len(rows) > 1 else 0.0
    print(f"mode {engine.mode}{' smoothed' if args.smooth else ''}: {len(rows)} solutions over {span:.0f} s, "
          f"{c.imu} IMU samples in {t1 - t0:.2f} s "
          f"({(t1 - t0) / max(c.imu, 1) * 1e6:.1f} us per sample), "
          f"initialised by {c.init_method or 'nothing'}, {c.resets} resets")
    if engine.ekf is not None:
        stats = ", ".join(f"{k} {v.accepted}/{v.accepted + v.rejected}" for k, v in engine.ekf.stats.items())
        print(f"updates accepted: {stats}")
    print(f"wrote {args.out / 'trajectory.csv'}")
    return 0
