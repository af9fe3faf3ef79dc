"""``logger export FILE... --out DIR``: a drive's positions as GPX, KML and CSV, for maps and spreadsheets, and
the receiver's byte stream for RTKLIB (``ubx``, ``rinex``).

Takes the files of one drive (rotated files in any order, a last file cut short by a power failure) and the
``trajectory.mcap`` of ``logger replay``; exports the receiver's ``/gnss/fix``, the live ``/nav/fix`` the daemon
recorded, and each replayed ``/nav/fix`` as tracks of their own. Only valid positions are written, and a
track is split wherever fixes were missing or invalid (see :mod:`logger.exports.tracks`). ``ubx`` joins ``/gnss/raw``
into one ``.ubx`` with its gaps noted beside it, ``rinex`` converts that with RTKLIB's convbin (see
:mod:`logger.exports.raw_stream`).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections import Counter
from pathlib import Path

from logger.cli.outputs import drive_name, os_error_line, out_folder_problem
from logger.cli.progress import Progress
from logger.config import SCHEMA, ConfigError, load
from logger.exports.formats import HEIGHT_TEXT, HEIGHTS, write_csv, write_gpx, write_kml
from logger.exports.formats import height as point_height
from logger.exports.raw_stream import (
    ConvbinError,
    StreamReport,
    convbin_path,
    recorded_config,
    to_rinex,
    write_notes,
    write_ubx,
)
from logger.exports.tracks import EXPORT_TOPICS, Track, build_tracks
from logger.exports.whole import STAGE_PREFIX, adopt, remove_stale_stages, stage_prefix, written_together
from logger.recording.drive import (
    DriveFile,
    DriveFileError,
    cut_notes,
    damage_notes,
    iter_messages,
    open_drive,
)
from logger.recording.topics import GNSS_RAW
from logger.words import plural
from sensors.ublox_config import RAW_MESSAGES

TRACK_FORMATS = ("gpx", "kml", "csv")
STREAM_FORMATS = ("ubx", "rinex")  # the receiver's bytes: as they came, and through RTKLIB's convbin
FORMATS = TRACK_FORMATS + STREAM_FORMATS
RINEX_HEADER_KEYS = ("antenna_height_m", "receiver_name")  # [gnss] keys that go into the RINEX header


class UsageError(Exception):
    """Bad arguments, or a drive without what they ask for: one line for the user."""


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="logger export", description="export a drive's positions to GPX, KML and CSV")
    p.add_argument("files", nargs="+", type=Path, metavar="FILE",
                   help="MCAP files of one drive (rotated files, a cut file) or the folder holding them, and/or "
                        "logger replay's trajectory.mcap")
    p.add_argument("--out", required=True, type=Path, help="folder for the exported files")
    p.add_argument("--format", action="append", metavar="FORMATS",
                   help="comma-separated, or repeated: gpx, kml, csv (default: these three); ubx (the receiver's "
                        "bytes from /gnss/raw, gaps noted in NAME.ubx.json), rinex (that through RTKLIB's convbin)")
    p.add_argument("--config", type=Path, metavar="FILE",
                   help="rinex: take [gnss] antenna_height_m and receiver_name from FILE instead of the drive's "
                        "recorded configuration")
    p.add_argument("--topic", action="append", dest="topics", metavar="TOPIC",
                   help="/gnss/fix or /nav/fix; repeat for both (default: both)")
    p.add_argument("--height", choices=HEIGHTS, default="ellipsoid",
                   help="GPX <ele> and KML altitude: ellipsoid (as recorded, default) or msl (through the "
                        "receiver's geoid separation)")
    p.add_argument("--gap", type=float, default=3.0, metavar="S",
                   help="start a new segment after this many seconds without a position (default 3)")
    p.add_argument("--every", type=float, default=0.0, metavar="S",
                   help="keep one point per S seconds of each track, on a grid of S from each segment's start "
                        "(default: every point)")
    p.add_argument("--gap-marks", action="store_true", help="KML: a placemark where each gap starts")
    return p.parse_args(argv)


def check_args(args: argparse.Namespace) -> tuple[list[str], list[str]]:
    # Repeated, the formats add up (the last one alone was written, silently): --format gpx --format kml is both.
    given = ",".join(args.format) if args.format else "gpx,kml,csv"
    formats = list(dict.fromkeys(f.strip().lower() for f in given.split(",") if f.strip()))
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise UsageError(f"--format {given!r}: choose from {', '.join(FORMATS)} (comma-separated)")
    topics = args.topics or list(EXPORT_TOPICS)
    bad = [t for t in topics if t not in EXPORT_TOPICS]
    if bad:
        raise UsageError(f"--topic {bad[0]}: only {' and '.join(EXPORT_TOPICS)} hold positions")
    if not 0 < args.gap < 1e6:
        raise UsageError(f"--gap {args.gap:g}: must be a positive number of seconds")
    if not 0 <= args.every < 1e6:
        raise UsageError(f"--every {args.every:g}: must be zero or a positive number of seconds")
    problem = out_folder_problem(args.out)
    if problem:
        raise UsageError(problem)
    if args.config is not None and "rinex" not in formats:
        raise UsageError("--config is for --format rinex (the RINEX header's antenna height and receiver)")
    return formats, topics


def summary(t: Track) -> str:
    longest = max((g.duration_s for g in t.gaps), default=0.0)
    skipped = ", ".join(f"{reason} {n}" for reason, n in t.skipped.most_common())
    return (f"{t.label}: {plural(t.n_points, 'point')} in {plural(len(t.segments), 'segment')} from "
            f"{plural(t.messages, 'message')}"
            + (f", {plural(len(t.gaps), 'gap')} (longest {longest:.1f} s)" if t.gaps else "")
            + (f"; skipped: {skipped}" if skipped else ""))


def export(files: list[DriveFile], out: Path, formats: list[str], topics: list[str], height: str,
           gap_s: float, every_s: float, gap_marks: bool) -> tuple[list[Track], list[Path]]:
    """Read, build and write; returns the tracks written and the files made."""
    progress = Progress("logger export")
    try:
        tracks = build_tracks(iter_messages(files, EXPORT_TOPICS, progress), files, gap_s, every_s)
    finally:
        progress.end()
    chosen = [t for t in tracks if t.topic in topics and t.n_points]
    if not chosen:
        return [t for t in tracks if t.topic in topics], []
    out.mkdir(parents=True, exist_ok=True)
    name = drive_name(files)
    written = []
    with written_together():  # one run's tracks: a GPX beside another run's CSV would disagree without a word
        if "gpx" in formats:
            written.append(out / f"{name}.gpx")
            write_gpx(written[-1], chosen, height, name)
        if "kml" in formats:
            written.append(out / f"{name}.kml")
            write_kml(written[-1], chosen, height, name, gap_marks)
        if "csv" in formats:
            for t in chosen:
                written.append(out / f"{name}_{t.key}.csv")
                write_csv(written[-1], t)
    return chosen, written


def rinex_header(files: list[DriveFile], config: Path | None) -> tuple[float, str]:
    """Antenna height and receiver name: from ``config`` when given, else as the drive recorded its configuration,
    else the schema's defaults (a drive from before these keys)."""
    if config is not None:
        gnss = load(config, devices=False)["gnss"]
        return float(gnss["antenna_height_m"]), str(gnss["receiver_name"])
    recorded = recorded_config(files)
    values = [recorded.get(f"gnss.{k}", SCHEMA["gnss"][k].default) for k in RINEX_HEADER_KEYS]
    try:
        return float(values[0]), str(values[1])
    except ValueError:
        raise UsageError(f"the drive's recorded gnss.antenna_height_m {values[0]!r} is not a number: give "
                         "--config FILE") from None


def stream_summary(r: StreamReport) -> str:
    kinds = Counter(g.kind for g in r.gaps)
    raw = [(name, r.messages.get(name, 0)) for name in RAW_MESSAGES]  # what RTKLIB needs: always said
    rest = sorted((kv for kv in r.messages.items() if kv[0] not in RAW_MESSAGES), key=lambda kv: -kv[1])[:3]
    found = ", ".join(f"{n} {name}" for name, n in raw + rest)
    return (f"{GNSS_RAW}: {plural(r.bytes, 'byte')} from {plural(r.records, 'record')} ({found or 'no frames'})"
            + (", gaps: " + ", ".join(f"{n} {k}" for k, n in kinds.items()) if kinds else ", no gaps")
            + (f"; {r.bad_checksum} bad checksums, {r.garbage_bytes} bytes outside frames"
               if r.bad_checksum or r.garbage_bytes else "")
            + (f"; ends inside a frame ({plural(r.unfinished_tail_bytes, 'byte')} of it)"
               if r.unfinished_tail_bytes else ""))


def export_stream(files: list[DriveFile], out: Path, name: str, rinex: bool, keep_ubx: bool,
                  config: Path | None) -> list[Path]:
    """``ubx`` (and ``rinex``): the stream, its notes, and RTKLIB's RINEX of it; [] when the drive has no raw bytes.

    RINEX needs the receiver's raw observations (RXM-RAWX): a stream without any (an M8N, the default, sends none;
    ``[gnss] raw_observations`` off) is refused before convbin is run, which would only fail with its progress
    output for a message. When RINEX cannot be made, the ``.ubx`` and its notes are kept only if ``keep_ubx`` (the
    user asked for ``ubx`` too), and the error says so; otherwise they were only convbin's input.

    Everything is made in a staging folder inside ``out`` (named with this process's id: an export killed outright
    leaves it, and the next one removes it, :func:`~logger.exports.whole.remove_stale_stages`) and moved into place
    only once it is complete, all of it together, so that a failure (no raw observations, convbin failing, a full
    disk) leaves the folder as it was: an earlier export's ``.ubx``, ``.obs`` and ``.nav`` of the same drive were
    deleted by a failed one. Without navigation data (no
    RXM-SFRBX in the stream: convbin writes no ``.nav``) the observations are written and a line says what is
    missing: rnx2rtkp needs broadcast ephemerides from elsewhere then."""
    header = rinex_header(files, config) if rinex else None
    progress = Progress("logger export")
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    ubx, notes, obs, nav = (out / f"{name}{ext}" for ext in (".ubx", ".ubx.json", ".obs", ".nav"))
    try:
        with tempfile.TemporaryDirectory(prefix=stage_prefix(), dir=out) as tmp:
            stage = Path(tmp)
            try:
                report = write_ubx(iter_messages(files, [GNSS_RAW], progress), files, stage / ubx.name)
            finally:
                progress.end()
            if not report.records:
                return []
            report.ubx = str(ubx)
            write_notes(stage / notes.name, report)
            print(stream_summary(report))
            made = [ubx, notes]
            failure: UsageError | ConvbinError | None = None
            if header is not None:
                try:
                    if not report.raw_epochs:
                        raise UsageError(f"no RINEX: {GNSS_RAW} holds no raw observations (0 RXM-RAWX; record them "
                                         "with [gnss] raw_observations = true on a receiver that has them: M8T, "
                                         "M8P, F9P, F9T)")
                    result = to_rinex(stage / ubx.name, stage / obs.name, stage / nav.name, *header,
                                      report.unfinished_tail_bytes, named=ubx)
                except (UsageError, ConvbinError) as exc:
                    failure = exc
                else:
                    print(f"rinex: {plural(result.epochs, 'observation epoch')} from {report.raw_epochs} RXM-RAWX")
                    made += [obs] + ([nav] if result.nav.is_file() else [])
                    if not result.nav.is_file():
                        print(f"logger export: no {nav.name}: the stream holds no navigation data (0 RXM-SFRBX); "
                              "rnx2rtkp needs the day's broadcast ephemerides from elsewhere (an IGS BRDC file)",
                              file=sys.stderr)
            if failure is not None and not keep_ubx:
                raise type(failure)(f"{failure}; nothing written") from None
            with written_together():  # every file of the stream's set, or none (a name taken by a folder)
                for final in made:
                    adopt(stage / final.name, final)
            if failure is not None:
                raise type(failure)(f"{failure}; wrote only {ubx} and {notes}") from None
            return made
    except OSError as exc:  # a full disk while staging: named as the output it was to be
        if exc.filename and Path(exc.filename).parent.name.startswith(STAGE_PREFIX):
            exc.filename = str(out / Path(exc.filename).name)
        raise
    finally:
        if created and not any(out.iterdir()):
            out.rmdir()


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    try:
        formats, topics = check_args(args)
        if "rinex" in formats:
            convbin_path()  # before any work: without RTKLIB the command cannot finish
        files = open_drive(args.files)
    except (UsageError, DriveFileError, ConvbinError) as exc:
        print(f"logger export: {exc}", file=sys.stderr)
        return 2
    for line in cut_notes(files):
        print(f"logger export: {line}", file=sys.stderr)
    if args.out.is_dir():
        for stage in remove_stale_stages(args.out):
            print(f"logger export: removed {stage}, left by an export that was killed", file=sys.stderr)
    streamed: list[Path] = []
    if any(f in STREAM_FORMATS for f in formats):
        try:
            streamed = export_stream(files, args.out, drive_name(files), "rinex" in formats,
                                     "ubx" in formats, args.config)
        except (DriveFileError, ConvbinError, UsageError) as exc:
            print(f"logger export: {exc}", file=sys.stderr)
            return 2
        except ConfigError as exc:
            print("\n".join(f"logger export: {p}" for p in exc.problems), file=sys.stderr)
            return 2
        except OSError as exc:  # the folder was checked first; what is left: a disk full, a folder changed meanwhile
            print(f"logger export: {os_error_line(exc)}", file=sys.stderr)
            return 2
        if not streamed:
            print(f"logger export: no {GNSS_RAW} messages in {', '.join(str(f) for f in args.files)}",
                  file=sys.stderr)
            return 2
        formats = [f for f in formats if f in TRACK_FORMATS]
        if not formats:
            for line in damage_notes(files):
                print(f"logger export: {line}", file=sys.stderr)
            for p in streamed:
                print(f"wrote {p}")
            return 0
    try:
        chosen, written = export(files, args.out, formats, topics, args.height, args.gap, args.every, args.gap_marks)
    except DriveFileError as exc:
        print(f"logger export: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"logger export: {os_error_line(exc)}", file=sys.stderr)
        return 2
    for line in damage_notes(files):  # damaged chunks skipped whole; what is written is the rest (exit 0)
        print(f"logger export: {line}", file=sys.stderr)
    names = ", ".join(str(f) for f in args.files)
    if not written:
        if not chosen:
            print(f"logger export: no {' or '.join(topics)} messages in {names}", file=sys.stderr)
        else:
            print(f"logger export: no valid position to export in {names} ("
                  + "; ".join(summary(t) for t in chosen) + ")", file=sys.stderr)
        return 2
    for topic in topics:
        if not any(t.topic == topic for t in chosen):
            print(f"logger export: note: no valid {topic} in these files", file=sys.stderr)
    for t in chosen:
        print(summary(t))
    if any(point_height(p, args.height) is None for t in chosen for p in t.points):
        why = ("no receiver fix to take the geoid from" if args.height == "msl" else
               "the receiver sent no geoid separation; --height msl has theirs")
        print(f"logger export: note: some points have no {HEIGHT_TEXT[args.height]} ({why}): written without a "
              "height", file=sys.stderr)
    for p in streamed + written:
        print(f"wrote {p}")
    return 0
