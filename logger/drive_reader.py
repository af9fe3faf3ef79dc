"""The messages of one drive for post-processing: several files, finished or cut short, in log-time order.

A drive is rotated into several files, and its last file may be unfinished (power cut, ``kill -9``). Finished
files are read with the struct-level walk of :mod:`logger.nav.recording` (fast, only the wanted channels);
an unfinished one is read the way recovery reads it (:func:`logger.mcap_files.walk`: every CRC-valid chunk
up to the cut), so exporting or plotting a drive never needs ``logger recover`` first.

Each file also says who wrote it: the daemon's recorder (``live``) or ``logger replay`` (``replay``), so that
the live ``/nav/fix`` and a replayed one are kept apart even though they share the topic name.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from logger.mcap_files import MAGIC, McapFileError, is_finished, walk
from logger.nav.recording import raw_messages

REPLAY_LIBRARY = "vehicle-logger replay"  # what logger replay writes into the MCAP header


class DriveFileError(Exception):
    """A file that cannot be read as part of a drive; the message is one line naming the file."""


@dataclass(frozen=True)
class DriveFile:
    path: Path
    origin: str  # "live": written by the daemon; "replay": written by logger replay
    finished: bool


@dataclass(frozen=True)
class DriveMessage:
    log_time: int  # MCAP log time, Unix ns
    topic: str
    file: int  # index into the list of DriveFile
    msg: dict[str, Any]


def _header_library(path: Path) -> str:
    """The ``library`` string of the MCAP header record (the first record after the magic)."""
    with open(path, "rb") as f:
        head = f.read(4096)
    try:
        op, _length = struct.unpack_from("<BQ", head, len(MAGIC))
        if op != 0x01:
            return ""
        pos = len(MAGIC) + 9
        n = struct.unpack_from("<I", head, pos)[0]
        pos += 4 + n
        n = struct.unpack_from("<I", head, pos)[0]
        return head[pos + 4:pos + 4 + n].decode("utf-8", "replace")
    except struct.error:
        return ""


def open_drive(paths: Iterable[str | Path]) -> list[DriveFile]:
    """Check every file and say who wrote it; raises DriveFileError for a missing or non-MCAP file."""
    files = []
    for p in map(Path, paths):
        if not p.is_file():
            raise DriveFileError(f"{p}: no such file")
        try:
            with open(p, "rb") as f:
                magic = f.read(len(MAGIC))
        except OSError as exc:
            raise DriveFileError(f"{p}: cannot open ({exc.strerror or exc})") from exc
        if magic != MAGIC:
            raise DriveFileError(f"{p}: not an MCAP file (no MCAP magic at the start)")
        origin = "replay" if _header_library(p) == REPLAY_LIBRARY else "live"
        files.append(DriveFile(p, origin, is_finished(p)))
    return files


def cut_notes(files: list[DriveFile]) -> list[str]:
    """One line per file that was not closed cleanly, for the user: such a file is read up to its cut."""
    return [f"{f.path} was not closed cleanly: read up to where it was cut" for f in files if not f.finished]


def _raw(f: DriveFile, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    """(log_time, order, topic, data) of the wanted topics in one file."""
    if f.finished:
        try:
            return raw_messages(f.path, wanted)
        except Exception as exc:  # the mcap package's reader raises its own kinds for a damaged file
            raise DriveFileError(f"{f.path}: cannot be read ({type(exc).__name__}: {exc}); "
                                 "`logger recover` may save what is left") from exc
    try:
        found = walk(f.path)
    except McapFileError as exc:
        raise DriveFileError(str(exc)) from exc
    topics = {cid: ch.topic for cid, ch in found.channels.items() if ch.topic in wanted}
    return [(m.log_time, i, topics[m.channel_id], m.data) for i, m in enumerate(found.messages)
            if m.channel_id in topics]


def iter_messages(files: list[DriveFile], topics: Iterable[str]) -> Iterator[DriveMessage]:
    """Every message of the given topics over the files, decoded, in log-time order (ties: file order)."""
    wanted = set(topics)
    raw: list[tuple[int, int, int, str, bytes]] = []
    for index, f in enumerate(files):
        raw.extend((t, index, order, topic, data) for t, order, topic, data in _raw(f, wanted))
    raw.sort(key=lambda r: (r[0], r[1], r[2]))
    loads = json.loads
    for t, index, _, topic, data in raw:
        try:
            msg = loads(data)
        except ValueError as exc:  # UnicodeDecodeError and JSONDecodeError alike
            raise DriveFileError(f"{files[index].path}: a {topic} message at log time {t} is not JSON "
                                 f"({exc})") from exc
        yield DriveMessage(t, topic, index, msg)
