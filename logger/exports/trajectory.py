"""A drive through the navigation filter, and the trajectory it gives as CSV and MCAP (``logger replay``'s work).

The same engine as the live navigator, fed by the same record layer, as fast as the files can be read,
optionally followed by the Rauch-Tung-Striebel backward pass. ``trajectory.csv`` has one row per IMU sample once
the filter runs (per fix in GNSS-only mode); ``trajectory.mcap`` has ``/nav/fix`` per row and ``/nav/state`` once
a second, so Foxglove draws it next to the recording.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from logger.nav.engine import NavEngine, TrajectoryRow
from logger.nav.inputs import SolutionEpoch
from logger.nav.params import NavParams
from logger.nav.rotations import dcm_from_quat, euler_from_dcm
from logger.nav.smoother import SmoothingReport, smooth_rows
from logger.recording.drive import REPLAY_LIBRARY, ProgressFn, read_messages
from logger.recording.records import NAV_INPUT_TOPICS, nav_feeder, nav_fix_record, nav_state_record
from logger.recording.topics import IMU, NAV_FIX, NAV_STATE, TOPICS

CSV_HEADER = ("t_sync_ns", "t_mono_ns", "lat_deg", "lon_deg", "height_m", "vn_mps", "ve_mps", "vd_mps", "roll_deg",
              "pitch_deg", "yaw_deg", "sn_m", "se_m", "sd_m")


def read_drive(paths: list[Path], topics: tuple[str, ...] = NAV_INPUT_TOPICS,
               progress: ProgressFn | None = None) -> Iterator[tuple[str, dict[str, Any]]]:
    """(topic, message) of the given topics over several files (a rotated drive), in log-time order."""
    return read_messages(paths, topics, progress)


def run_filter(paths: list[Path], params: NavParams, smooth: bool = False,
               states: list[dict[str, Any]] | None = None,
               progress: ProgressFn | None = None,
               smoothing: SmoothingReport | None = None, solution: Sequence[SolutionEpoch] = (),
               solution_replaces: bool = True) -> tuple[NavEngine, list[TrajectoryRow]]:
    """Run the engine over the files; returns it and its rows (smoothed when asked). With ``states``, a
    ``/nav/state`` record is appended to it for every second of drive; ``progress`` hears how far it got;
    ``smoothing`` hears where the backward pass kept the forward solution; ``solution``: a post-processed
    solution's epochs fused (``solution_replaces``: instead of the receiver's positions)."""
    engine = NavEngine(params, record=True)
    if solution:
        engine.use_solution(solution, solution_replaces)
    feed = nav_feeder(engine)
    next_state = 0
    for topic, msg in read_drive(paths, progress=progress):
        feed[topic](msg)
        if states is not None and topic == IMU and msg["t_sync_ns"] >= next_state and engine.state is not None:
            next_state = msg["t_sync_ns"] + 1_000_000_000
            states.append(nav_state_record(engine, msg["t_sync_ns"], msg["t_mono_ns"]))
    rows = engine.rows
    if smooth and engine.mode != "gnss" and engine.ekf is not None and engine.epochs:
        engine.close_epochs()
        rows = smooth_rows(rows, engine.epochs, engine.ekf.p, smoothing)
    return engine, rows


def row_fields(row: TrajectoryRow) -> list[Any]:
    t, t_mono, lat, lon, h, vn, ve, vd, q, sig, _ = row
    roll, pitch, yaw = euler_from_dcm(dcm_from_quat(q))
    return [t, t_mono, f"{math.degrees(lat):.9f}", f"{math.degrees(lon):.9f}", f"{h:.3f}", f"{vn:.3f}", f"{ve:.3f}",
            f"{vd:.3f}", f"{math.degrees(roll):.3f}", f"{math.degrees(pitch):.3f}", f"{math.degrees(yaw):.3f}",
            f"{sig[0]:.3f}", f"{sig[1]:.3f}", f"{sig[2]:.3f}"]


def write_csv(path: Path, rows: list[TrajectoryRow]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_HEADER)
        for row in rows:
            w.writerow(row_fields(row))


def write_mcap(path: Path, rows: list[TrajectoryRow], engine: NavEngine, states: list[dict[str, Any]]) -> None:
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library=REPLAY_LIBRARY)
        ids = {}
        for topic in (NAV_FIX, NAV_STATE):
            spec = TOPICS[topic]
            sid = w.register_schema(spec.schema_name, "jsonschema", spec.schema_data)
            ids[topic] = w.register_channel(topic, "json", sid)
        for row in rows:
            t, t_mono, lat, lon, h, vn, ve, vd, q, sig, _ = row
            roll, pitch, yaw = euler_from_dcm(dcm_from_quat(q))
            msg = nav_fix_record(t, t_mono, lat, lon, h, (vn, ve, vd), (roll, pitch, yaw), sig,
                              "gnss" if engine.mode == "gnss" else f"ins {engine.mode}-state", engine.mode)
            w.add_message(ids[NAV_FIX], log_time=t, publish_time=t_mono, data=json.dumps(msg).encode())
        for st in states:
            w.add_message(ids[NAV_STATE], log_time=st["t_sync_ns"], publish_time=st["t_mono_ns"],
                          data=json.dumps(st).encode())
        w.finish()


