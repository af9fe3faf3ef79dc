"""``logger replay FILE... --out DIR [--mode 17|15|gnss] [--smooth] [--gnss-solution FILE.pos]``: the navigation filter
over recorded drives.

The work is :mod:`logger.exports.trajectory`'s; this is the command line around it. Writes ``DIR/trajectory.csv``
(one row per IMU sample once the filter runs; per fix in GNSS-only mode) and ``DIR/trajectory.mcap`` with
``/nav/fix`` at the live navigator's rate (``nav.publish_hz``, 5 Hz by default; ``--fix-hz HZ`` another, ``--fix-hz
0`` every row) and ``/nav/state`` once a second, so Foxglove draws it next to the recording. A drive the filter
could not start on writes nothing and exits 1, with what the start waited for.

``--gnss-solution FILE.pos`` fuses a post-processed solution (RTKLIB's ``rnx2rtkp``/``rtkpost`` output, read by
:mod:`logger.recording.rtklib_pos`): instead of the receiver's positions (``--gnss-solution-mode replace``, the
default; its velocities still go in) or beside them (``add``). A file that cannot be read is one line naming it
and the line, exit 2; so is a solution none of whose epochs the filter used (another drive's or day's: the line
gives both time spans), or whose positions lie a median 30 m or more from the receiver's own fixes at the same
epochs (another vehicle's of the same hours: ``logger.nav.solution.FOREIGN_SOLUTION_M``), and nothing is
written. An ``--out`` that cannot be a folder is refused before the run.
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from logger.cli.outputs import os_error_line, out_folder_problem
from logger.cli.progress import Progress
from logger.exports.trajectory import run_filter, write_csv, write_mcap
from logger.exports.whole import retire, written_together
from logger.nav.params import MODES, NavParams
from logger.nav.solution import MAX_LATE_S, SolutionPolicy
from logger.recording.drive import DriveFileError, cut_notes, damage_notes, open_drive
from logger.words import plural

if TYPE_CHECKING:
    from logger.nav.core import EngineCounters
    from logger.nav.smoother import SmoothingReport
    from logger.recording.rtklib_pos import SolutionFile

# Imported where used: the configuration file's reader (--config), RTKLIB's .pos reader (--gnss-solution) and the
# smoother's report (--smooth), which a plain replay does without.

SOLUTION_MODES = ("replace", "add")


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="logger replay", description="run the navigation filter over recorded drives")
    p.add_argument("files", nargs="+", type=Path,
                   help="MCAP files of one drive (several when it was rotated), or the folder holding them")
    p.add_argument("--out", required=True, type=Path, help="folder for trajectory.csv and trajectory.mcap")
    p.add_argument("--mode", choices=MODES, default=None, help="17 (default), 15 (GNSS + IMU) or gnss (fixes only)")
    p.add_argument("--smooth", action="store_true", help="add the Rauch-Tung-Striebel backward pass")
    p.add_argument("--config", type=Path, help="take the [nav] tuning from this configuration file")
    p.add_argument("--no-mcap", action="store_true", help="write only the CSV")
    p.add_argument("--one-pass", action="store_true",
                   help="as the live filter saw the drive: no second pass with the IMU mounting the drive showed "
                        "(by default a drive that showed one other than [nav] mounting_rpy_deg is filtered again "
                        "from the start with it)")
    p.add_argument("--fix-hz", type=rate_hz, default=None, metavar="HZ",
                   help="rate of /nav/fix in trajectory.mcap (default: nav.publish_hz, the live rate, 5 Hz unless "
                        "--config says otherwise); 0: one per row, as trajectory.csv")
    p.add_argument("--gnss-solution", type=Path, metavar="FILE.pos",
                   help="fuse a post-processed (PPK) solution: RTKLIB rnx2rtkp/rtkpost output")
    p.add_argument("--gnss-solution-mode", choices=SOLUTION_MODES, default="replace",
                   help="replace: the solution's positions instead of the receiver's (its velocities stay); "
                        "add: both (default: replace)")
    return p.parse_args(argv)


def rate_hz(text: str) -> float:
    """``--fix-hz``: a rate in Hz, 0 for every row."""
    try:
        hz = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(hz) and (hz == 0.0 or hz >= MIN_FIX_HZ)):
        raise argparse.ArgumentTypeError(f"a rate is 0 (every row) or {MIN_FIX_HZ:g} Hz or more: {text!r}")
    return hz


MIN_FIX_HZ = 1e-3  # one /nav/fix in about 17 minutes; a smaller rate's period overflowed a time in ns (a traceback)


@contextmanager
def no_cycle_collector() -> Iterator[None]:
    """Python's cyclic garbage collector paused. The filter's and the writers' objects are freed by reference
    counting (a whole replay leaves a few hundred objects in cycles, from its start), while every collection
    would walk the rows the trajectory keeps: on a 20-minute drive about 300 collections, some 5 % of the CPU."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def start_height(c: EngineCounters) -> str:
    """Where the start's height came from, as the replay line says it (logger/nav/start_height.py)."""
    if not c.init_height_fixes:
        return ""
    return f" (its height from {plural(c.init_height_fixes, 'fix', 'fixes')} and the barometer)"


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    problem = out_folder_problem(args.out)  # before the filter run, which the folder would otherwise end
    if problem:
        print(f"logger replay: {problem}", file=sys.stderr)
        return 2
    try:
        files = open_drive(args.files)
    except DriveFileError as exc:
        print(f"logger replay: {exc}", file=sys.stderr)
        return 2
    for line in cut_notes(files):  # a file cut short is read up to its cut, as export and plot read it
        print(f"logger replay: {line}", file=sys.stderr)
    for f in files:
        if f.origin == "replay":  # the filter runs on the drive's own records: a replay's output is not one
            print(f"logger replay: {f.path} is a replay's output: left out (the filter runs on the drive's own "
                  "records)", file=sys.stderr)
    if args.config is not None:
        from logger.config import ConfigError, load

        try:
            # Only [nav] is used: a file with that section alone will do (no serial port is demanded).
            params = NavParams.from_config(load(args.config, devices=False)["nav"])
        except ConfigError as exc:
            for line in exc.problems:
                print(f"logger replay: {line}", file=sys.stderr)
            return 2
    else:
        params = NavParams()
    if args.mode is not None:
        params.mode = args.mode
    # GNSS-only mode passes the receiver's fixes through: no filter to fuse a solution with or to smooth.
    needs_filter = "--gnss-solution" if args.gnss_solution is not None else "--smooth" if args.smooth else ""
    if params.mode == "gnss" and needs_filter:
        print(f"logger replay: {needs_filter} needs the filter (mode 15 or 17); mode gnss passes the receiver's "
              f"fixes through{' (the mode of ' + str(args.config) + ')' if args.mode is None else ''}",
              file=sys.stderr)
        return 2
    solution: SolutionFile | None = None
    if args.gnss_solution is not None:
        from logger.recording.rtklib_pos import SolutionFileError, read_pos

        try:
            solution = read_pos(args.gnss_solution)
        except SolutionFileError as exc:
            print(f"logger replay: {exc}", file=sys.stderr)
            return 2
    t0 = time.perf_counter()
    notes: list[str] = []
    skipped: list[str] = []
    states: list[dict[str, Any]] | None = None if args.no_mcap else []
    progress = Progress("logger replay")
    smoothing: SmoothingReport | None = None
    if args.smooth:
        from logger.nav.smoother import SmoothingReport

        smoothing = SmoothingReport()
    try:
        with no_cycle_collector():
            engine, rows = run_filter([f.path for f in files], params, args.smooth, states, progress, smoothing,
                                      solution.epochs if solution is not None else (),
                                      args.gnss_solution_mode == "replace", refilter=not args.one_pass, notes=notes,
                                      skipped=skipped)
    except DriveFileError as exc:  # a file that turned out unreadable once read: one line, nothing written
        progress.end()
        print(f"logger replay: {exc}", file=sys.stderr)
        return 2
    t1 = time.perf_counter()
    c = engine.counters
    progress.end()
    # Damaged chunks were skipped whole and the rest filtered: said before the result, which is still written
    # (exit 0), since the drive's other minutes are worth as much as before.
    for line in damage_notes(files) + skipped:
        print(f"logger replay: {line}", file=sys.stderr)
    if not rows:
        # An empty trajectory is no result: say what the start waited for, write nothing, fail.
        why = engine.waiting_for() or "the filter produced no solution"
        print(f"logger replay: no solution from {plural(c.imu, 'IMU sample')} and "
              f"{plural(c.gnss_fixes, 'GNSS fix', 'GNSS fixes')}: {why}; nothing written to {args.out}",
              file=sys.stderr)
        return 1
    if solution is not None and (engine.solution is None or not engine.solution.used):
        # Fused with nothing: in replace mode without any position update at all (the receiver's are left out), in
        # add mode the receiver's alone. Either is not what was asked, and written it would replace a folder's
        # trajectory from an earlier run: an error, nothing written.
        print(f"logger replay: {unused_solution(solution, engine.solution, rows)}; nothing written to {args.out}",
              file=sys.stderr)
        return 2
    foreign = engine.solution.foreign() if solution is not None and engine.solution is not None else None
    if foreign is not None:
        # Another vehicle's solution of the same hours passes the time check: its positions do not pass this one.
        print(f"logger replay: --gnss-solution {solution.path}: {foreign}; nothing written to {args.out}",
              file=sys.stderr)
        return 2
    progress.stage("writing the trajectory")
    fix_hz = params.publish_hz if args.fix_hz is None else args.fix_hz
    fixes = 0
    stale_mcap = False
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        with no_cycle_collector(), written_together():  # the CSV and the MCAP of one run, or neither
            stale_mcap = states is None and (args.out / "trajectory.mcap").is_file()
            if stale_mcap:
                retire(args.out / "trajectory.mcap")  # --no-mcap: an earlier run's MCAP is not this run's
            write_csv(args.out / "trajectory.csv", rows)
            if states is not None:
                source_run = next((f.run[0] for f in files if f.run is not None), None)
                fixes = write_mcap(args.out / "trajectory.mcap", rows, engine, states, fix_hz, source_run)
    except OSError as exc:  # checked before the run; what is left: a disk full, a folder changed meanwhile
        progress.end()
        print(f"logger replay: {os_error_line(exc)}", file=sys.stderr)
        return 2
    progress.end()
    span = (rows[-1][0] - rows[0][0]) / 1e9 if len(rows) > 1 else 0.0
    if engine.mode == "gnss":
        work = f"the receiver's fixes passed through in {t1 - t0:.2f} s"
    else:
        # Notes say when run_filter filtered the drive more than once (the live filter's re-run of its first minutes;
        # a second pass with the mounting found, after a GNSS + IMU pass that refines it): the time is all of them.
        work = (f"{plural(c.imu, 'IMU sample')} in {t1 - t0:.2f} s ({(t1 - t0) / max(c.imu, 1) * 1e6:.1f} us per "
                f"sample{', every pass below' if notes else ''}), initialised by {c.init_method}{start_height(c)}, "
                f"{plural(c.resets, 'reset')}")
    print(f"mode {engine.mode}{' smoothed' if args.smooth else ''}: {plural(len(rows), 'solution')} over "
          f"{span:.0f} s, {work}")
    for line in notes:
        print(line)
    if engine.ekf is not None:
        stats = ", ".join(f"{k} {v.accepted}/{v.accepted + v.rejected}" for k, v in engine.ekf.stats.items())
        print(f"updates accepted: {stats}")
    if solution is not None and engine.solution is not None:
        print(solution_summary(solution, engine.solution, args.gnss_solution_mode))
    if smoothing is not None and smoothing.epochs:
        print(smoothing.summary())
    if states is not None:
        if fix_hz == 0:
            print("trajectory.mcap: /nav/fix for every solution")
        elif fixes >= len(rows):  # a rate at or above the rows' own: every row, which "at 50 Hz" did not say
            print(f"trajectory.mcap: /nav/fix for every solution ({fix_hz:g} Hz is the solutions' own rate or more)")
        else:
            print(f"trajectory.mcap: /nav/fix at {fix_hz:g} Hz, {fixes} of {plural(len(rows), 'solution')} "
                  "(--fix-hz 0: every one)")
    print(f"wrote {args.out / 'trajectory.csv'}")
    if states is not None:
        print(f"wrote {args.out / 'trajectory.mcap'}")
    elif stale_mcap:
        print(f"removed {args.out / 'trajectory.mcap'}: an earlier run's (--no-mcap writes none)")
    return 0


def solution_summary(solution: SolutionFile, used: SolutionPolicy, mode: str) -> str:
    """What became of the solution's epochs, in one line."""
    counts = ", ".join(f"{n} {q}" for q, n in solution.counts().items())
    took = ", ".join(f"{n} {q}" for q, n in used.used.items()) or "none"
    offered = sum(used.used.values())
    left = not_used(used)
    return (f"GNSS solution {solution.path.name} ({solution.time_system}, {solution.position_format}: {counts}), "
            f"{'instead of' if mode == 'replace' else 'beside'} the receiver's positions: used {took}"
            + (f" (the filter's gate refused {offered - used.accepted})" if used.accepted < offered else "")
            + (f"; not used: {'; '.join(left)}" if left else "")
            + ("; not compared with the receiver's fixes (no epoch of theirs at its times)"
               if offered and not used.receiver_distances_m else ""))


def not_used(used: SolutionPolicy) -> list[str]:
    """The solution's epochs the filter did not take, by why: the one wording of the summary and of the error."""
    left = ([f"{used.unjoined} placed more than {MAX_LATE_S:g} s behind the filter (no receiver fix with a time "
             "near them)"] if used.unjoined else [])
    if used.before_start:
        left.append(f"{used.before_start} before the filter started")
    if used.few_sv:
        left.append(f"{used.few_sv} on fewer than {used.min_sv} satellites")
    if used.pending:
        left.append(f"{len(used.pending)} after the drive's end")
    return left


def unused_solution(solution: SolutionFile, used: SolutionPolicy | None, rows: list[Any]) -> str:
    """Why none of a solution's epochs went into the filter, with both time spans: a solution of another drive or
    day is the usual cause, which the spans show at once."""
    from logger.exports.formats import utc_iso

    n = len(solution.epochs)
    why = not_used(used) if used is not None else []
    span = (f"{utc_iso(solution.epochs[0].gnss_time_ns)} to {utc_iso(solution.epochs[-1].gnss_time_ns)}"
            if solution.epochs else "no epoch")
    return (f"--gnss-solution {solution.path}: none of its {plural(n, 'epoch')} was used"
            + (f" ({'; '.join(why)})" if why else "")
            + f": it spans {span}, the filter {utc_iso(rows[0][0])} to {utc_iso(rows[-1][0])}")
