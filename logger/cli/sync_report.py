"""``logger sync-report DRIVE.mcap... [--png-dir DIR] [--json]``: the paper's time-sync tables for a drive.

The report is :mod:`logger.exports.sync_report`'s: Tables 6 and 7 for the paper's counters and this logger's
clock, the stamp error against the truth on a simulated drive, and Figures 18 and 19 as PNG (with matplotlib).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from logger.cli.outputs import os_error_line, out_folder_problem
from logger.exports.plotting import PlotsUnavailable
from logger.exports.sync_report import Drive, plots, render, report
from logger.recording.drive import DriveFileError, cut_notes, damage_notes, drive_paths


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="logger sync-report",
                                 description="the paper's Tables 6 and 7 and the stamp error of a recorded drive")
    ap.add_argument("files", nargs="+", type=Path, help="MCAP files of one drive, or the folder holding them")
    ap.add_argument("--png-dir", type=Path, help="write Figures 18 and 19 as PNG here")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)
    problem = out_folder_problem(args.png_dir, "--png-dir") if args.png_dir else None
    if problem:  # before the report, not a traceback after it
        print(f"logger sync-report: {problem}", file=sys.stderr)
        return 2
    try:
        paths = drive_paths(args.files)
    except DriveFileError as exc:
        print(f"logger sync-report: {exc}", file=sys.stderr)
        return 2
    missing = [str(f) for f in paths if not f.is_file()]
    if missing:
        print(f"logger sync-report: no such file: {', '.join(missing)}", file=sys.stderr)
        return 2
    try:
        drive = Drive.load(paths)
    except DriveFileError as exc:
        print(f"logger sync-report: {exc}", file=sys.stderr)
        return 2
    for note in cut_notes(drive.files) + damage_notes(drive.files):  # Drive.load has read them: damage is known
        print(f"logger sync-report: {note}", file=sys.stderr)
    out = report(drive)
    print(json.dumps(out, indent=1) if args.json else render(out))
    if args.png_dir:
        try:
            for p in plots(drive, args.png_dir):
                print(f"wrote {p}")
        except PlotsUnavailable as exc:
            print(exc, file=sys.stderr)
            return 1
        except BrokenPipeError:
            raise  # the reader of stdout went away (| head): ended quietly by the command line
        except OSError as exc:  # a disk full, a folder changed meanwhile
            print(f"logger sync-report: {os_error_line(exc)}", file=sys.stderr)
            return 2
    return 0
