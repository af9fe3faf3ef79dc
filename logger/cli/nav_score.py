"""``logger nav-score TRAJECTORY.csv... [DRIVE.mcap...] [--reference REF] [--plots DIR] [--json]``.

Scores ``logger replay``'s trajectories against the truth a simulated drive recorded (or a reference trajectory):
the paper's Table 9 per axis, the drift in each GNSS outage, the share within 3 sigma
(:mod:`logger.exports.nav_score`). Exit 0 scored, 1 a trajectory with no row inside what it is scored against,
2 a file that cannot be read or is not what its place asks for (one line naming it).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from logger.cli.outputs import os_error_line, out_folder_problem
from logger.exports.nav_score import (
    FOREIGN_M,
    NoOverlap,
    ScoreError,
    Truth,
    fix_distance,
    format_score,
    load_reference,
    load_truth,
    plots,
    read_trajectory,
    reference_outages,
    score,
)
from logger.recording.drive import (
    DriveFileError,
    cut_notes,
    damage_notes,
    drive_paths,
    open_drive,
    replay_mismatch,
    replay_source,
    run_identity,
)

PROG = "logger nav-score"
TRAJECTORY_MCAP = "trajectory.mcap"  # logger replay's, beside its trajectory.csv: no drive's file


def expand(paths: list[Path]) -> list[Path]:
    """Folders as a user has them: ``logger replay``'s output folder stands for its trajectory.csv, a drive's
    folder for its MCAP files (:func:`logger.recording.drive.drive_paths`), a drive's folder that a replay wrote
    into (``logger replay DIR --out DIR``) for both; files as named."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir() and (p / "trajectory.csv").is_file():
            if p / "trajectory.csv" not in out:
                out.append(p / "trajectory.csv")
            if any(f.name != TRAJECTORY_MCAP for f in p.glob("*.mcap")):
                out += [f for f in drive_paths([p]) if f.name != TRAJECTORY_MCAP]
        else:
            out += drive_paths([p])
    return out


def sort_inputs(paths: list[Path]) -> tuple[list[Path], list[Path]]:
    """Trajectory CSVs and the drive's MCAP files; ScoreError for anything else (a file silently left out would
    be a score of less than was asked for, or of nothing)."""
    csvs = [p for p in paths if p.suffix.lower() == ".csv"]
    drives = [p for p in paths if p.suffix.lower() == ".mcap"]
    other = [p for p in paths if p not in csvs and p not in drives]
    if other:
        raise ScoreError(f"{other[0]}: neither a trajectory CSV (logger replay's trajectory.csv) nor a drive's "
                         "MCAP file")
    if not csvs:
        raise ScoreError("no trajectory to score: name logger replay's trajectory.csv (or its --out folder) "
                         "before the drive")
    return csvs, drives


def same_drive(csvs: list[Path], drives: list[Path], reference: Path | None = None) -> None:
    """ScoreError for a trajectory replayed from another drive than the one named, or a reference of another drive
    than the trajectories' or the drive's: a replay's trajectory.mcap, beside its CSV, names the run it was made
    from, and a drive's files name theirs (every urban drive starts at the same place, so the distance to the fixes
    does not tell two of them apart; a reference of another drive was scored without a word, 1.1 km "RMSE")."""
    runs = {ident[0] for ident in map(run_identity, drives) if ident is not None}
    for csv_path in csvs:
        foreign = replay_mismatch(csv_path, replay_source(csv_path.with_name("trajectory.mcap")) if runs else None,
                                  runs)
        if foreign:
            raise ScoreError(foreign)
    ref_run = reference_run(reference) if reference is not None else None
    if ref_run is None:
        return
    if runs and ref_run not in runs:
        raise ScoreError(f"{reference}: a reference of another drive (run {ref_run}), not of the one named "
                         f"(run {', '.join(sorted(runs))})")
    for csv_path in csvs:
        made_from = replay_source(csv_path.with_name("trajectory.mcap"))
        if made_from is not None and made_from != ref_run:
            raise ScoreError(f"{reference}: a reference of another drive (run {ref_run}) than {csv_path}'s "
                             f"(run {made_from})")


def reference_run(reference: Path) -> str | None:
    """The run id of the drive a reference is of, when it says: a drive's file its own, a replay's output (its
    trajectory.mcap, or the one beside its CSV) the run it was made from."""
    if reference.is_dir():
        reference = reference / "trajectory.csv"
    if reference.suffix.lower() == ".csv":
        return replay_source(reference.with_name("trajectory.mcap"))
    ident = run_identity(reference)
    return ident[0] if ident is not None else replay_source(reference)


def load_against(reference: Path | None, drives: list[Path]) -> Truth:
    """What the trajectories are scored against: the reference (with the outages of the drive named beside it),
    or the drive's truth. A drive's file cut short is read up to the cut, said in a line."""
    for note in cut_notes(open_drive(drives)):
        print(note, file=sys.stderr)
    if reference is None:
        if not drives:
            raise ScoreError("nothing to score against: name the simulated drive's MCAP files (or its folder), "
                             "or a reference trajectory with --reference")
        return load_truth(drives)
    if reference.is_dir() and (reference / "trajectory.csv").is_file():
        reference = reference / "trajectory.csv"
    truth = load_reference(reference)
    if drives:
        truth.outages = reference_outages(drives)
    return truth


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog=PROG,
                                 description="score trajectories against a simulated drive's truth (Table 9)")
    ap.add_argument("trajectory", type=Path, nargs="+",
                    help="trajectory.csv files (or logger replay's --out folders), then the drive's MCAP files (or "
                         "the folder holding them)")
    ap.add_argument("--reference", type=Path,
                    help="score against this trajectory instead of /truth: a trajectory CSV (or replay's --out "
                         "folder) or an MCAP file's /nav/fix, joined on GNSS time (t_sync_ns); the drive, when "
                         "named too, gives the GNSS outages")
    ap.add_argument("--plots", type=Path, help="folder for map.png and error.png")
    ap.add_argument("--json", action="store_true", help="print the scores as JSON")
    args = ap.parse_args(argv)
    problem = out_folder_problem(args.plots, "--plots") if args.plots else None
    if problem:  # before the work, not a traceback after it
        print(f"{PROG}: {problem}", file=sys.stderr)
        return 2
    try:
        named_paths = expand(args.trajectory)
        missing = [str(p) for p in [*named_paths, *([args.reference] if args.reference else [])] if not p.exists()]
        if missing:
            raise ScoreError(f"no such file: {', '.join(missing)}")
        csvs, drives = sort_inputs(named_paths)
        same_drive(csvs, drives, args.reference)
        truth = load_against(args.reference, drives)
        trajectories = {p: read_trajectory(p) for p in csvs}
    except (ScoreError, DriveFileError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    for line in damage_notes(drives):  # damaged chunks of the truth skipped whole: scored on the rest
        print(f"{PROG}: {line}", file=sys.stderr)
    named = {}
    status = 0
    for p, traj in trajectories.items():
        away = fix_distance(traj, truth)
        if away is not None and away > FOREIGN_M:
            # Scored all the same: a filter that lost the fixes and drifted (a phone-grade IMU in mode 15: 269 m)
            # is what a score is for, and refusing it would hide it. The line says which reading is likelier.
            print(f"{PROG}: {p}: warning: its rows lie a median {away / 1000:.1f} km from the drive's own GNSS fixes "
                  "at the same times: another drive's trajectory, or a filter that lost the fixes", file=sys.stderr)
        try:
            named[p.parent.name or p.stem] = (traj, score(traj, truth))
        except NoOverlap as exc:
            print(f"{PROG}: {p}: {exc}", file=sys.stderr)
            status = 1
    if args.json:
        print(json.dumps({k: {**s.table(), "max_h": s.max_h, "coverage": s.coverage, "outages": s.outages,
                              "within_3sigma": s.within_3sigma, "rows": s.rows, "rows_scored": s.n}
                          for k, (_, s) in named.items()}, indent=1))
    else:
        for k, (_, s) in named.items():
            print(format_score(k, s))
    if args.plots and named:
        try:
            for p in plots(args.plots, named, truth):
                print(f"wrote {p}")
        except BrokenPipeError:
            raise  # the reader of stdout went away (| head): ended quietly by the command line
        except OSError as exc:  # a disk full, a folder changed meanwhile
            print(f"{PROG}: {os_error_line(exc)}", file=sys.stderr)
            return 2
    return status
