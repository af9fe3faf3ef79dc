"""``logger nav-score TRAJECTORY.csv... DRIVE.mcap... [--reference REF.csv] [--plots DIR] [--json]``.

Scores ``logger replay``'s trajectories against the truth a simulated drive recorded (or a reference trajectory):
the paper's Table 9 per axis, the drift in each GNSS outage, the share within 3 sigma
(:mod:`logger.exports.nav_score`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from logger.exports.nav_score import NoTruth, format_score, load_reference, load_truth, plots, read_trajectory, score
from logger.recording.drive import DriveFileError, drive_paths


def expand(paths: list[Path]) -> list[Path]:
    """Folders as a user has them: ``logger replay``'s output folder stands for its trajectory.csv, a drive's
    folder for its MCAP files (:func:`logger.recording.drive.drive_paths`); files as named."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir() and (p / "trajectory.csv").is_file():
            out.append(p / "trajectory.csv")
        else:
            out += drive_paths([p])
    return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="logger nav-score",
                                 description="score trajectories against a simulated drive's truth (Table 9)")
    ap.add_argument("trajectory", type=Path, nargs="+",
                    help="trajectory.csv files (or logger replay's --out folders), then the drive's MCAP files (or "
                         "the folder holding them)")
    ap.add_argument("--reference", type=Path, help="score against this trajectory CSV instead of /truth")
    ap.add_argument("--plots", type=Path, help="folder for map.png and error.png")
    ap.add_argument("--json", action="store_true", help="print the scores as JSON")
    args = ap.parse_args(argv)
    try:
        named_paths = expand(args.trajectory)
    except DriveFileError as exc:
        print(f"logger nav-score: {exc}", file=sys.stderr)
        return 2
    missing = [str(p) for p in [*named_paths, *([args.reference] if args.reference else [])] if not p.is_file()]
    if missing:
        print(f"logger nav-score: no such file: {', '.join(missing)}", file=sys.stderr)
        return 2
    csvs = [p for p in named_paths if p.suffix == ".csv"]
    drives = [p for p in named_paths if p.suffix == ".mcap"]
    try:
        truth = load_reference(args.reference) if args.reference else load_truth(drives)
    except NoTruth as exc:
        print(f"logger nav-score: {exc}", file=sys.stderr)
        return 2
    named = {}
    for p in csvs:
        traj = read_trajectory(p)
        named[p.parent.name or p.stem] = (traj, score(traj, truth))
    if args.json:
        print(json.dumps({k: {**s.table(), "max_h": s.max_h, "coverage": s.coverage, "outages": s.outages,
                              "within_3sigma": s.within_3sigma} for k, (_, s) in named.items()}, indent=1))
    else:
        for k, (_, s) in named.items():
            print(format_score(k, s))
    if args.plots:
        for p in plots(args.plots, named, truth):
            print(f"wrote {p}")
    return 0
