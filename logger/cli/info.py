"""``logger info FILE``: what is in a recorded file, at a glance (like ``ros2 bag info``).

Per-topic counts, rates and gaps (by :mod:`logger.recording.intervals`, the rule ``logger plot`` uses too) come
from the message indexes, so the chunks need not be
decompressed for them: a day's file is summarised in seconds on the board. Each chunk is still decompressed once to
check its CRC, since a damaged chunk in a cleanly closed file is one every reader skips (``Damaged:``, with the
messages it held and when). A file that was not closed cleanly is walked record by record instead, and says so.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

from mcap.records import Channel, Chunk, Header, MessageIndex, Metadata
from mcap.stream_reader import StreamReader

from logger.recording.drive import DriveFileError, describe_writer, drive_paths
from logger.recording.files import (
    Loss,
    McapFileError,
    being_written,
    chunk_fault,
    describe_losses,
    is_finished,
    walk,
)
from logger.recording.intervals import GAP_FACTOR, regularity
from logger.recording.topics import BARO, GNSS_FIX, IMU, IMU_BATCH, OBD_SPEED, PPS
from sync.stamp import FLOOR_YEAR, GNSS_TIME_FLOOR_NS

SENSOR_TOPIC = {"imu": IMU, "baro": BARO, "obd": OBD_SPEED, "gnss": GNSS_FIX, "pps": PPS}  # each sensor's samples
ALSO_SAMPLES = {IMU: IMU_BATCH}  # a FIFO-read IMU's samples are in batches


def silent_sensors(config: dict[str, str], counts: dict[str, int]) -> list[str]:
    """The sensors the recording's configuration enabled that left no sample in the file (their topic absent)."""
    return [f"{name} (no {topic})" for name, topic in SENSOR_TOPIC.items()
            if config.get(f"{name}.source", "none") != "none"
            and counts.get(topic, 0) + counts.get(ALSO_SAMPLES.get(topic, ""), 0) == 0]


@dataclass
class TopicInfo:
    topic: str
    schema: str
    count: int
    rate_hz: float
    largest_gap_s: float  # the longest interval between two messages (the name scripts reading --json know)
    gaps: int  # intervals over GAP_FACTOR times the usual one (logger plot shades the same ones)
    # From its last message to the file's last: a sensor that stopped before the recording did (its rate and gaps,
    # taken over its own span, do not show it)
    ended_before_end_s: float = 0.0
    # Every message of it stamped before any time was known (a file whose other topics are dated): a sensor that
    # delivered in the first seconds and not after the clock was set; its rate and its end are not known
    undated_only: bool = False


@dataclass
class FileInfo:
    path: str
    size_bytes: int
    closed_cleanly: bool
    start_ns: int | None
    end_ns: int | None
    duration_s: float
    messages: int
    topics: list[TopicInfo]
    note: str = ""
    silent: list[str] = field(default_factory=list)  # configured sensors of which the file holds no record
    damaged_chunks: int = 0  # chunks whose CRC (or decompression) fails: every reader skips them whole
    lost_messages: int = 0  # the messages they held (counted in no topic above)
    damage: str = ""  # the two above, and when, in words; empty for a file whose chunks all hold
    recording: bool = False  # a running logger has it open: unfinished because it is being written, not cut
    # Messages logged at a time before FLOOR_YEAR: the board's own clock before any time was known (a board booted at
    # its image's 1970). Beside dated ones they are left out of start, end, duration and rates (a span from 1970 said
    # nothing); counted in their topics.
    undated_messages: int = 0
    writer: str = ""  # the MCAP header's library: the program and version that wrote the file


# A topic whose last message lies more than this (and GAP_FACTOR of its usual interval) before the file's last is
# said to have ended early. The sensor topics of a stopping logger ended at most 1.8 s before its last message in
# five simulated runs' files (/var/tmp/b49/lat, lat9600, soak: `logger info --json`, ended_before_end_s).
ENDED_EARLY_MIN_S = 5.0


def inspect(path: str | os.PathLike[str]) -> FileInfo:
    """Summarise one file; raises McapFileError with a readable message for a file that is not MCAP."""
    p = Path(path)
    finished = is_finished(p)
    times: dict[int, list[int]] = defaultdict(list)
    channels: dict[int, Channel] = {}
    schemas: dict[int, str] = {}
    config: dict[str, str] = {}  # the daemon's configuration, as the file's "config" metadata keeps it
    note = ""
    writer = ""  # the header's library (who wrote the file), from whichever walk reads the file
    recording = False
    losses: list[Loss] = []
    if finished:
        try:
            with open(p, "rb") as f:
                bad: Loss | None = None  # the chunk just read, when it failed: its message indexes count its loss
                for record in StreamReader(f, emit_chunks=True, record_size_limit=max(p.stat().st_size, 1)).records:
                    if isinstance(record, Chunk):
                        # Each chunk decompressed and its CRC checked (the indexes alone cannot tell a damaged one):
                        # 16 ms more for a 600 s drive (44 -> 60 ms, 600 chunks): a cleanly closed file is not simply
                        # "cleanly" when readers will skip some of it.
                        fault, _ = chunk_fault(record.compression, record.data, record.uncompressed_size,
                                               record.uncompressed_crc)
                        bad = Loss(0, chunks=1, reason=fault, first_ns=record.message_start_time,
                                   last_ns=record.message_end_time) if fault else None
                        if bad is not None:
                            losses.append(bad)
                    elif isinstance(record, MessageIndex) and bad is not None:
                        bad.messages += len(record.records)  # in no topic's count: no reader gets them
                    elif isinstance(record, MessageIndex):
                        times[record.channel_id].extend(t for t, _ in record.records)
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif type(record).__name__ == "Schema":
                        schemas[record.id] = record.name  # type: ignore[attr-defined]
                    elif isinstance(record, Header):
                        writer = record.library  # the walk's record: the file is not opened again for it
                    elif isinstance(record, Metadata) and record.name == "config":
                        config = dict(record.metadata)
        except Exception as exc:  # a footer present but a broken body: fall back to the walk
            finished = False
            note = f"index unreadable ({type(exc).__name__}); walked the records instead"
            times.clear()
            losses.clear()
    if not finished:
        found = walk(p)
        writer = found.library
        channels = dict(found.channels)
        schemas = {sid: s.name for sid, s in found.schemas.items()}
        for m in found.messages:
            times[m.channel_id].append(m.log_time)
        config = next((dict(m.metadata) for m in found.metadata if m.name == "config"), config)
        losses = found.damage()
        recording = being_written(p)
        if recording:
            note = "being recorded: a running logger is writing it; read up to its last chunk on disk"
        elif found.stopped_at and not note:
            note = "not closed cleanly: run `logger recover` to make it a finished, indexed file"
    topics = []
    all_times = [t for ts in times.values() for t in ts]
    total = len(all_times)
    undated = sum(1 for t in all_times if t < GNSS_TIME_FLOOR_NS)
    floor = GNSS_TIME_FLOOR_NS if 0 < undated < total else None  # undated ones beside dated: left out
    if floor is not None:
        all_times = [t for t in all_times if t >= floor]
    start = min(all_times) if all_times else None
    end = max(all_times) if all_times else None
    for cid, ch in sorted(channels.items(), key=lambda kv: kv[1].topic):
        own = sorted(times.get(cid, []))
        count = len(own)
        if floor is not None:
            own = [t for t in own if t >= floor]
        reg = regularity(own)
        ended = (end - own[-1]) / 1e9 if own and end is not None else 0.0
        topics.append(TopicInfo(ch.topic, schemas.get(ch.schema_id, ""), count, reg.rate_hz,
                                reg.largest_interval_s, len(reg.gaps), round(ended, 3), bool(count and not own)))
    duration = (end - start) / 1e9 if start is not None and end is not None else 0.0
    silent = silent_sensors(config, {t.topic: t.count for t in topics})
    damage = ""
    if losses:
        damage = (f"{describe_losses(losses)}: every reader skips {'it' if len(losses) == 1 else 'them'} and reads the "
                  f"rest; `logger recover {p}` rewrites the file without {'it' if len(losses) == 1 else 'them'}")
    return FileInfo(str(p), p.stat().st_size, finished, start, end, duration, total, topics, note, silent,
                    sum(x.chunks for x in losses), sum(x.messages for x in losses), damage,
                    recording, undated, writer)


def _utc(ns: int | None) -> str:
    if ns is None:
        return "-"
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(ns / 1e9)) + f".{(ns // 1_000_000) % 1000:03d} UTC"


def render(info: FileInfo) -> str:
    lines = [
        f"File:      {info.path}",
        f"Size:      {info.size_bytes / 1e6:.1f} MB",
        "Closed:    " + ("cleanly" if info.closed_cleanly else "not yet (being recorded)" if info.recording
                            else "NO (cut short)")
        + (f", but {info.damaged_chunks} chunk{'s' if info.damaged_chunks != 1 else ''} damaged"
           if info.damaged_chunks else ""),
        f"Start:     {_utc(info.start_ns)}",
        f"End:       {_utc(info.end_ns)}",
        f"Duration:  {info.duration_s:.1f} s",
        f"Messages:  {info.messages}",
        f"Writer:    {describe_writer(info.writer)}",
    ]
    if info.undated_messages:
        some = info.undated_messages < info.messages
        lines.append(f"Undated:   {info.undated_messages} message{'s' if info.undated_messages != 1 else ''} stamped "
                     f"before {FLOOR_YEAR}, by the board's own clock before any time was known"
                     + ("; left out of Start, End, Duration and the rates" if some else ""))
    if info.damage:
        lines.append(f"Damaged:   {info.damage}")
    if info.note:
        lines.append(f"Note:      {info.note}")
    if info.silent:
        lines.append(f"Silent:    {', '.join(info.silent)}: configured, never delivered in this file")
    width = max([len(t.topic) for t in info.topics] + [5])
    lines.append("")
    lines.append(f"  {'topic':<{width}}  {'count':>8}  {'rate Hz':>8}  {'gaps':>5}  {'longest s':>9}  schema")
    for t in info.topics:
        lines.append(f"  {t.topic:<{width}}  {t.count:>8}  {t.rate_hz:>8.2f}  {t.gaps:>5}  "
                     f"{t.largest_gap_s:>9.3f}  {t.schema}")
    lines.append(f"  (rate over each topic's span; a gap: an interval over {GAP_FACTOR:g}x the usual one)")
    for t in info.topics:
        usual = 1.0 / t.rate_hz if t.rate_hz > 0 else 0.0
        if t.undated_only:
            lines.append(f"  {t.topic}: every message undated: none after the time was known")
        elif t.count and t.ended_before_end_s > max(ENDED_EARLY_MIN_S, GAP_FACTOR * usual):
            lines.append(f"  {t.topic}: its last message {t.ended_before_end_s:.1f} s before the file's end")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="logger info", description="summarise a recorded MCAP file")
    parser.add_argument("files", nargs="+", metavar="FILE", help="MCAP files, or folders of them")
    parser.add_argument("--json", action="store_true", help="one JSON object per file")
    args = parser.parse_args(argv)
    status = 0
    try:
        paths = drive_paths(args.files, one_drive=False)
    except DriveFileError as exc:
        print(f"logger info: {exc}", file=sys.stderr)
        return 1
    for f in paths:
        try:
            info = inspect(f)
        except McapFileError as exc:
            print(f"logger info: {exc}", file=sys.stderr)
            status = 1
            continue
        except FileNotFoundError:
            print(f"logger info: {f}: no such file", file=sys.stderr)
            status = 1
            continue
        print(json.dumps(asdict(info)) if args.json else render(info))
    return status
