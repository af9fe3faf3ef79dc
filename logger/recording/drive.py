"""The one drive reader: a drive's messages for post-processing, over several files, finished or cut short.

A drive is rotated into several files, and its last file may be unfinished (power cut, ``kill -9``). A finished
file is read by walking its records with ``struct`` and keeping only the wanted channels: the ``mcap`` package's
reader handles every corner of the format but costs some 15 us per message in Python, as much as the filter's
own work per IMU sample, and the logger's own files are simple (chunked, zstd/lz4/none, JSON messages). Anything
the walk does not expect sends that file back to the package's reader, so a file written by another tool still
reads. An unfinished file is read the way recovery reads it (:func:`logger.recording.files.walk`: every CRC-valid
chunk up to the cut), so exporting, plotting or replaying a drive never needs ``logger recover`` first.

Every chunk's CRC is checked, whichever way the file is read: a flipped byte in a cleanly closed file otherwise
decompresses into other numbers in valid JSON, read without a word. A chunk whose CRC fails (or that does not
decompress, or holds a record that does not parse) is skipped whole and the rest of the file read; a file whose
records themselves are damaged falls back to recovery's walk. What was skipped (chunks, the messages they held,
when) is kept per file for :func:`damage_notes`, one line each, which the commands print once they have read.

Each file also says who wrote it: the daemon's recorder (``live``) or ``logger replay`` (``replay``), so that
the live ``/nav/fix`` and a replayed one are kept apart even though they share the topic name.
"""

from __future__ import annotations

import bisect
import functools
import json
import os
import re
import struct
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from logger import __version__
from logger.recording.files import (
    LIVE_NAME,
    MAGIC,
    REPLAY_NAME,
    RUN_METADATA,
    Loss,
    McapFileError,
    Statistics,
    being_written,
    chunk_fault,
    describe_losses,
    head_span_plausible,
    is_finished,
    summary_statistics,
    walk,
)
from logger.recording.mcap_writer import (
    CHUNK_HEAD,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_HEADER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_METADATA,
    RECORD_HEAD,
)
from logger.recording.topics import IMU as IMU_TOPIC
from logger.recording.topics import IMU_BATCH
from logger.words import plural

REPLAY_LIBRARY = f"{REPLAY_NAME} {__version__}"  # what logger replay writes into the MCAP header
# The metadata record a replay's trajectory.mcap begins with: the run id of the drive it was made from, so that it
# is never read beside another drive's files as if it were theirs.
REPLAY_OF_METADATA = "replay_of"

_MSG = struct.Struct("<HIQQ")
_H = struct.Struct("<H")
_I = struct.Struct("<I")
_Q = struct.Struct("<Q")
# An IMU record as the daemon writes it: the four fields the filter needs, pulled out without decoding the
# whole JSON object (json.loads of an IMU record costs more than the strapdown step it feeds). Anything that
# does not match, written by another tool or another version, is decoded in full.
_IMU = re.compile(rb'"t_mono_ns":\s*(-?\d+),\s*"t_sync_ns":\s*(-?\d+),.*?"accel_mps2":\s*\[([^\]]*)\],\s*'
                  rb'"gyro_rps":\s*\[([^\]]*)\](?:,\s*"temp_degc":\s*(-?[0-9.eE+-]+))?')


class UnexpectedLayout(Exception):
    pass


@dataclass
class _Walk:
    """What the struct walk of one file keeps as it goes."""

    wanted: set[str]
    out: list[tuple[int, int, str, bytes]] = field(default_factory=list)
    channels: dict[int, str] = field(default_factory=dict)
    seen: int = 0  # messages in the chunks read, all topics: the file's statistics count the same
    known: set[int] = field(default_factory=set)  # every channel id whose record was read, wanted or not
    orphans: int = 0  # messages of a channel whose record was not read (it was in a damaged chunk)
    losses: list[Loss] = field(default_factory=list)
    good: list[tuple[int, int, int]] = field(default_factory=list)  # (offset, first, last log time) of good chunks
    last_bad: Loss | None = None  # the chunk just skipped, whose message index records may follow


def _records(buf: bytes | memoryview, start: int, end: int, w: _Walk) -> None:
    """Collect wanted messages from the message and channel records in buf[start:end] (a chunk's records, or an
    unchunked file's)."""
    pos = start
    out = w.out
    channels = w.channels
    while pos + 9 <= end:
        op, length = RECORD_HEAD.unpack_from(buf, pos)
        body = pos + 9
        nxt = body + length
        if nxt > end:
            raise UnexpectedLayout("record runs past its container")
        if op == OP_MESSAGE:
            w.seen += 1
            cid, _seq, log_time, _pub = _MSG.unpack_from(buf, body)
            topic = channels.get(cid)
            if topic is not None:
                out.append((log_time, len(out), topic, bytes(buf[body + 22:nxt])))
            elif cid not in w.known:
                w.orphans += 1
        elif op == OP_CHANNEL:
            cid = _H.unpack_from(buf, body)[0]
            w.known.add(cid)
            n = _I.unpack_from(buf, body + 4)[0]
            topic = bytes(buf[body + 8:body + 8 + n]).decode()
            if topic in w.wanted:
                channels[cid] = topic
        pos = nxt


def _chunk(buf: memoryview, pos: int, body: int, nxt: int, w: _Walk) -> None:
    """Read one chunk record into ``w``, or skip it whole as a loss: its CRC (over the decompressed records, when
    the writer set one), its decompression and its records must all hold, or none of its messages is kept (a
    flipped byte that still decompresses gives other numbers in valid JSON; only the CRC tells)."""
    start_t, end_t, size, crc = CHUNK_HEAD.unpack_from(buf, body)
    n = _I.unpack_from(buf, body + 28)[0]
    fault = ""
    raw = None
    if n > 16 or body + 40 + n > nxt:
        fault = "its head is damaged"
    else:
        try:
            compression = bytes(buf[body + 32:body + 32 + n]).decode()
        except UnicodeDecodeError:
            compression = "?"
        rec_len = _Q.unpack_from(buf, body + 32 + n)[0]
        if body + 40 + n + rec_len != nxt:
            fault = "its head is damaged"
        elif compression not in ("zstd", "lz4", ""):
            raise UnexpectedLayout(f"compression {compression!r}")
        else:
            fault, raw = chunk_fault(compression, buf[body + 40 + n:nxt], size, crc)
    if raw is not None:
        mark, seen, orphans, channels = len(w.out), w.seen, w.orphans, dict(w.channels)
        try:
            _records(raw, 0, len(raw), w)
        except (UnexpectedLayout, struct.error, UnicodeDecodeError):
            del w.out[mark:]
            w.seen, w.orphans, w.channels = seen, orphans, channels
            fault = "a record in it does not parse"
        else:
            w.good.append((pos, start_t, end_t))
            w.last_bad = None
            return
    loss = Loss(pos, chunks=1, exact=False, reason=fault, first_ns=start_t, last_ns=end_t)
    w.losses.append(loss)
    w.last_bad = loss


def walk_records(path: Path, wanted: set[str], losses: list[Loss] | None = None) -> list[tuple[int, int, str, bytes]]:
    """(log_time, order, topic, data) of the wanted topics in one finished file of the expected layout, by the
    struct walk; raises :class:`UnexpectedLayout` for anything else. A chunk whose CRC, decompression or records
    fail is skipped whole and put in ``losses`` (with the messages its index records, or the file's statistics,
    say it held), and the walk goes on with the next. Checking the CRCs costs about 2 ms of a 33 ms walk of a 600 s
    drive (zlib.crc32 over its 10.6 MB of decompressed records; the decompression itself, 16 ms, was always paid)."""
    buf = path.read_bytes()
    if not buf.startswith(MAGIC):
        raise UnexpectedLayout("not an MCAP file")
    view = memoryview(buf)
    w = _Walk(wanted)
    pos, end = len(MAGIC), len(buf)
    ended = False
    while pos + 9 <= end:
        op, length = RECORD_HEAD.unpack_from(view, pos)
        body = pos + 9
        nxt = body + length
        if nxt > end:
            raise UnexpectedLayout("record runs past its container")
        if op == OP_CHUNK:
            _chunk(view, pos, body, nxt, w)
        elif op == OP_MESSAGE_INDEX:
            if w.last_bad is not None and length >= 6:
                w.last_bad.messages += _I.unpack_from(view, body + 2)[0] // 16
                w.last_bad.exact = True
        elif op in (OP_MESSAGE, OP_CHANNEL):
            _records(view, pos, nxt, w)
        elif op == OP_DATA_END:
            ended = True
            break
        if op != OP_MESSAGE_INDEX and op != OP_CHUNK:
            w.last_bad = None
        pos = nxt
    if not ended:
        raise UnexpectedLayout("no data end record: an unfinished file")
    if w.orphans:  # a channel record went with a damaged chunk: recovery's walk names them from the channel table
        raise UnexpectedLayout(f"{w.orphans} messages of channels whose record was not read")
    _settle(w, summary_statistics(view))
    if losses is not None:
        losses.extend(w.losses)
    return w.out


def _settle(w: _Walk, stats: Statistics | None) -> None:
    """Each skipped chunk's span: its own head's times, unless they do not fit among its good neighbours'
    (:func:`~logger.recording.files.head_span_plausible`: the head is not under the CRC, a damaged one gives any
    times), then the gap between them; and the messages lost counted
    against the file's statistics where its summary holds. Raises UnexpectedLayout when they count messages no
    skipped chunk explains (a damaged record the walk passed over: the caller reads the file another way)."""
    starts = [g[0] for g in w.good]
    for loss in w.losses:
        i = bisect.bisect_left(starts, loss.at)
        prev, nxt = (w.good[i - 1] if i > 0 else None), (w.good[i] if i < len(w.good) else None)
        if not head_span_plausible(loss.first_ns, loss.last_ns, prev, nxt):
            loss.first_ns = prev[2] if prev is not None else None
            loss.last_ns = nxt[1] if nxt is not None else None
    if stats is None:
        return
    missing = stats.messages - w.seen
    if missing == sum(x.messages for x in w.losses) and stats.chunks == len(w.good) + len(w.losses):
        for x in w.losses:
            x.exact = True
        return
    if not w.losses:
        raise UnexpectedLayout(f"the statistics count {stats.messages} messages, the walk found {w.seen}")
    rest = missing - sum(x.messages for x in w.losses if x.exact)
    unplaced = [x for x in w.losses if not x.exact] or w.losses[-1:]
    unplaced[-1].messages += max(rest, 0)
    for x in w.losses:
        x.exact = True


def read_with_mcap(path: Path, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    """The same as :func:`walk_records` through the ``mcap`` package's reader: any layout, at its cost. Every
    chunk's CRC is checked (the package's reader does not by default): a damaged chunk raises here, and the caller
    then salvages the file chunk by chunk."""

    out: list[tuple[int, int, str, bytes]] = []
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f, validate_crcs=True).iter_messages(topics=list(wanted),
                                                                                    log_time_order=False):
            out.append((message.log_time, len(out), channel.topic, message.data))
    return out


def raw_messages(path: Path, wanted: set[str], losses: list[Loss] | None = None) -> list[tuple[int, int, str, bytes]]:
    """(log_time, order, topic, data) of the wanted topics in one finished file: the record walk above; the mcap
    package's reader for a layout the walk does not expect; and when that fails too (damage in the records
    themselves, not only in a chunk's data), recovery's walk, which reads every chunk whose CRC holds past the
    damage. What was skipped goes into ``losses``; :class:`McapFileError` when nothing can be read."""
    tried: list[Loss] = []
    try:
        out = walk_records(path, wanted, tried)
    except UnexpectedLayout:
        pass
    else:
        if losses is not None:
            losses.extend(tried)
        return out
    try:
        return read_with_mcap(path, wanted)
    except Exception:  # a damaged chunk or record, whatever the package raises for it: salvage below
        pass
    found = walk(path)
    if losses is not None:
        losses.extend(found.losses)
    topics = {cid: ch.topic for cid, ch in found.channels.items() if ch.topic in wanted}
    return [(m.log_time, i, topics[m.channel_id], m.data) for i, m in enumerate(found.messages)
            if m.channel_id in topics]


@dataclass
class FileDamage:
    """What a read of one file skipped: damaged chunks (whole) and messages that were not JSON (one by one)."""

    path: Path
    losses: list[Loss] = field(default_factory=list)
    undecodable: int = 0

    def line(self) -> str:
        """One line for the user: the file, what was skipped and lost, when; that the rest was read."""
        parts = [describe_losses(self.losses)] if self.losses else []
        if self.undecodable:
            parts.append(f"{plural(self.undecodable, 'message')} that {'is' if self.undecodable == 1 else 'are'} "
                         "not JSON skipped")
        return f"{self.path}: " + "; ".join(parts) + "; read the rest"


# What the last read of each file skipped, by the path it was read by: the commands tell it once they have read
# (damage_notes), whichever reader read it and however often (replay reads a drive up to three times).
_DAMAGE: dict[Path, FileDamage] = {}


def damage_notes(files: Iterable[DriveFile | Path]) -> list[str]:
    """One line per file whose last read skipped something (:class:`FileDamage`), in the order given."""
    paths = [f.path if isinstance(f, DriveFile) else Path(f) for f in files]
    return [_DAMAGE[p].line() for p in dict.fromkeys(paths) if p in _DAMAGE]


def damage_spans(path: Path) -> list[tuple[int | None, int | None]]:
    """The log-time spans (first, last; None where unknown) of the chunks the last read of ``path`` skipped as
    damaged, not its cut: where a stream read from it may lack what the file once held."""
    d = _DAMAGE.get(path)
    return [] if d is None else [(loss.first_ns, loss.last_ns) for loss in d.losses if not loss.cut]


def _damaged(path: Path) -> FileDamage:
    return _DAMAGE.setdefault(path, FileDamage(path))


class DriveFileError(Exception):
    """A file that cannot be read as part of a drive; the message is one line naming the file."""


@dataclass(frozen=True)
class DriveFile:
    path: Path
    origin: str  # "live": written by the daemon; "replay": written by logger replay
    finished: bool
    run: tuple[str, int] | None = None  # (run id, part number) of a daemon's file (:func:`run_identity`)
    replay_of: str | None = None  # a replay's file: the run id of the drive it was made from (:func:`replay_source`)


@dataclass(frozen=True)
class DriveMessage:
    log_time: int  # MCAP log time, Unix ns
    topic: str
    file: int  # index into the list of DriveFile
    msg: dict[str, Any]


def _header_library(path: Path) -> str:
    """The ``library`` string of the MCAP header record (the first record after the magic): who wrote the file."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return ""
    try:
        op, _length = RECORD_HEAD.unpack_from(head, len(MAGIC))
        if op != OP_HEADER:
            return ""
        pos = len(MAGIC) + 9
        n = struct.unpack_from("<I", head, pos)[0]
        pos += 4 + n
        n = struct.unpack_from("<I", head, pos)[0]
        return head[pos + 4:pos + 4 + n].decode("utf-8", "replace")
    except struct.error:
        return ""


def _writer_name(library: str) -> str:
    """The program part of a header's library, its version left off ("vehicle-logger replay 0.2.0")."""
    if library in (LIVE_NAME, REPLAY_NAME):  # 0.1.0's, with no version
        return library
    head = library.rpartition(" ")[0]
    return head if head in (LIVE_NAME, REPLAY_NAME) else library


def describe_writer(library: str) -> str:
    """A header's library for a person: which program wrote the file, and which version when it says."""
    if not library:
        return "unknown (no MCAP header library)"
    if library in (LIVE_NAME, REPLAY_NAME):
        return f"{library} (0.1.0: its files name no version)"
    return library


# The daemon's file names end in the drive's part number (recorder.default_file_name, boot_safe_file_name: 0001
# at each start, one more at each rotation).
_PART = re.compile(r"_(\d{4,})$")
FOLDER_DRIVES_SHOWN = 3


def part_number(path: Path) -> int | None:
    """The part number a daemon's file name ends in (``drive_20261204T142314Z_0002.mcap``: 2), or None."""
    m = _PART.search(path.stem)
    return int(m.group(1)) if m else None


def drive_stem(path: Path) -> str:
    """A file's name without its suffix and part number: the name of what is made of the drive."""
    return _PART.sub("", path.stem)


RUN_HEAD_BYTES = 16 * 1024  # the run record follows the header (a few dozen bytes) in the recorder's files


def _string_map(buf: bytes, pos: int, end: int) -> dict[str, str]:
    total = _I.unpack_from(buf, pos)[0]
    pos += 4
    stop = pos + total
    if stop > end:
        raise ValueError("map runs past its record")
    out = {}
    while pos < stop:
        n = _I.unpack_from(buf, pos)[0]
        key = buf[pos + 4:pos + 4 + n].decode()
        pos += 4 + n
        n = _I.unpack_from(buf, pos)[0]
        out[key] = buf[pos + 4:pos + 4 + n].decode()
        pos += 4 + n
    return out


def replay_source(path: Path) -> str | None:
    """The run id of the drive a replay's file was made from (its ``replay_of`` record); None for one that does not
    say (a replay written before it did)."""
    fields = _head_metadata(path, REPLAY_OF_METADATA) or {}
    return fields.get("run") or None


def run_identity(path: Path) -> tuple[str, int] | None:
    """(run id, part number) of a file the recorder wrote, from its ``drive`` metadata record; None for a file
    without one (written before run ids, by another tool, or unreadable).

    The recorder writes that record right after the header, outside any chunk, so it is in the first bytes of a
    file cut short as of a finished one, and recovery copies it into the rewritten file (before its first chunk):
    reading the file's head is enough, not its summary, and costs one small read per file. A command asks it of
    each file up to three times (a folder's drives, the files named, :func:`open_drive`): the answer is kept per
    file as it is on disk (its size and modification time), so the head is read once."""
    fields = _head_metadata(path, RUN_METADATA)
    if fields is None:
        return None
    run, part = fields.get("run", ""), fields.get("part", "")
    return (run, int(part)) if run and part.isdigit() else None


def _head_metadata(path: Path, name: str) -> dict[str, str] | None:
    """The fields of the metadata record ``name`` among the records that open the file (before its first chunk);
    None when there is none. Kept per file as it is on disk (its size and modification time)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return _head_records(str(path), st.st_size, st.st_mtime_ns).get(name)


@functools.lru_cache(maxsize=1024)
def _head_records(path: str, _size: int, _mtime_ns: int) -> dict[str, dict[str, str]]:
    try:
        with open(path, "rb") as f:
            head = f.read(RUN_HEAD_BYTES)
    except OSError:
        return {}
    out: dict[str, dict[str, str]] = {}
    if not head.startswith(MAGIC):
        return out
    pos = len(MAGIC)
    while pos + 9 <= len(head):
        op, length = RECORD_HEAD.unpack_from(head, pos)
        body, nxt = pos + 9, pos + 9 + length
        if nxt > len(head) or op in (OP_DATA_END, OP_CHUNK):
            return out
        if op == OP_METADATA:
            try:
                n = _I.unpack_from(head, body)[0]
                out.setdefault(head[body + 4:body + 4 + n].decode(), _string_map(head, body + 4 + n, nxt))
            except (struct.error, UnicodeDecodeError, ValueError):
                return out
        pos = nxt
    return out


def drive_starts(files: list[Path]) -> list[Path]:
    """The files that begin a drive, in name order.

    Files that carry a run id (:func:`run_identity`, every file of a recorder since run ids) are grouped by it:
    a run is one daemon start, so one drive, whatever its files' names say (a board whose system clock and GNSS
    time disagree names its first file 2026 and the next 2018; a restart in the same boot may find its first
    name taken), and its lowest part begins it; a part met twice in a run (a copy) begins another, so that it
    is refused rather than read twice.

    Files without a run id go by their names: in name order, the first daemon file and every one whose part
    number does not rise over the one before it (another start's 0001, or a later drive after an earlier one's
    last parts) begin a drive. Such files are not merged when their names' order disagrees with their numbers:
    a start killed before the clock locked left a boot-named 0001, and the next start's first file was numbered
    0002 by an older recorder, so "numbers in one unbroken run" does not make one drive. Files without a part
    number (a replay's output) begin none."""
    named: list[tuple[Path, int]] = []
    runs: dict[str, set[int]] = {}
    starts: dict[str, tuple[int, Path]] = {}
    extra: list[Path] = []
    for f in sorted(files, key=lambda f: f.name):
        ident = run_identity(f)
        if ident is None:
            if (n := part_number(f)) is not None:
                named.append((f, n))
            continue
        run, part = ident
        if part in runs.setdefault(run, set()):
            extra.append(f)
            continue
        runs[run].add(part)
        if run not in starts or part < starts[run][0]:
            starts[run] = (part, f)
    out = [f for i, (f, n) in enumerate(named) if i == 0 or n <= named[i - 1][1]]
    out += [f for _, f in starts.values()] + extra
    return sorted(out, key=lambda f: f.name)


def _several(starts: list[Path]) -> str:
    shown = ", ".join(f.name for f in starts[:FOLDER_DRIVES_SHOWN]) + (", ..." if len(starts) > FOLDER_DRIVES_SHOWN
                                                                      else "")
    return f"{len(starts)} drives (files {shown} each begin one): name the files of one drive"


def drive_paths(paths: Iterable[str | Path], one_drive: bool = True) -> list[Path]:
    """The files a user named, a folder standing for the drive the daemon wrote into it (``logger run --out``).

    A folder gives its MCAP files in name order (a ``logger replay`` output among them is read as such). Files
    with a run id are one drive per run; for files without one, a drive's part numbers rise in name order and a
    file whose part number does not rise over the one before it (another start's 0001, or a later drive after an
    earlier one's last parts) begins another drive (:func:`drive_starts`).
    Mixing drives would join unrelated trajectories (two cars' tracks as one, filtered as one drive), so a folder
    of several is an error naming the files that begin them, and so are files named one by one (a shell's
    ``drives/drive_*.mcap`` over two drives) that are not one drive's by the same rule, or a file named twice
    (its messages would be read twice) -- unless ``one_drive`` is false: ``logger info`` takes any files. A folder
    without MCAP files is an error too.
    """
    out: list[Path] = []
    for p in map(Path, paths):
        if not p.is_dir():
            out.append(p)
            continue
        found = [f for f in sorted(p.glob("*.mcap")) if f.is_file()]
        if not found:
            raise DriveFileError(f"{p}: a folder without recorded MCAP files")
        starts = drive_starts(found)
        if one_drive and len(starts) > 1:
            raise DriveFileError(f"{p}: a folder of {_several(starts)}")
        out += found
    if one_drive:
        seen: set[Path] = set()
        for f in out:
            key = f.resolve() if f.exists() else f
            if key in seen:
                raise DriveFileError(f"{f}: named twice (its messages would be read twice)")
            seen.add(key)
        starts = drive_starts(out)
        if len(starts) > 1:
            raise DriveFileError(f"files of {_several(starts)}")
    return out


def open_drive(paths: Iterable[str | Path]) -> list[DriveFile]:
    """Check every file and say who wrote it (a folder: the drive in it, :func:`drive_paths`); raises
    DriveFileError for a missing or non-MCAP file."""
    files = []
    for p in drive_paths(paths):
        if not p.is_file():
            raise DriveFileError(f"{p}: no such file")
        try:
            with open(p, "rb") as f:
                magic = f.read(len(MAGIC))
        except OSError as exc:
            raise DriveFileError(f"{p}: cannot open ({exc.strerror or exc})") from exc
        if magic != MAGIC:
            raise DriveFileError(f"{p}: not an MCAP file (no MCAP magic at the start)")
        origin = "replay" if _writer_name(_header_library(p)) == REPLAY_NAME else "live"
        files.append(DriveFile(p, origin, is_finished(p), run_identity(p) if origin == "live" else None,
                               replay_source(p) if origin == "replay" else None))
    runs = {f.run[0] for f in files if f.run is not None}
    for f in files:
        if (foreign := replay_mismatch(f.path, f.replay_of, runs)):
            raise DriveFileError(foreign)
    return files


def replay_mismatch(path: Path, replay_of: str | None, runs: set[str]) -> str:
    """Why a replay's output (``path``, made from run ``replay_of``) is not of the drive of ``runs`` ("" when it is,
    or when either side does not say): one line, for every command that reads one beside a drive."""
    if not runs or replay_of is None or replay_of in runs:
        return ""
    named = ", ".join(sorted(runs))
    return f"{path}: the replay of another drive (run {replay_of}), not of the one named (run {named})"


def cut_notes(files: list[DriveFile]) -> list[str]:
    """One line per file that was not closed cleanly, for the user: such a file is read up to its cut; and one for
    a drive whose parts are not all there (:func:`missing_parts`)."""
    return ([f"{f.path} is being recorded: read up to its last chunk on disk" if being_written(f.path)
             else f"{f.path} was not closed cleanly: read up to where it was cut" for f in files if not f.finished]
            + missing_parts(files))


def missing_parts(files: list[DriveFile]) -> list[str]:
    """A line when the daemon's files given lack parts of their run: a part number skipped (a file deleted or not
    copied from the card) leaves a hole in the drive that the reader would bridge as if nothing were missing (a
    61 s hole replayed as dead reckoning, 25 m off), and a drive whose first part is not given starts late. The
    rest is read; the line names what is missing. Files without a run id go by the part numbers of their names,
    and only a hole between them counts (an older recorder could number a start's first file 0002)."""
    parts: dict[str, list[tuple[int, Path]]] = {}
    for f in files:
        if f.origin != "live":
            continue
        if f.run is not None:
            parts.setdefault(f.run[0], []).append((f.run[1], f.path))
        elif (n := part_number(f.path)) is not None:
            parts.setdefault("", []).append((n, f.path))
    out = []
    for run, found in parts.items():
        have = {n for n, _ in found}
        missing = sorted(set(range(1 if run else min(have), max(have) + 1)) - have)
        if missing:
            first = min(found)[1]
            shown = ", ".join(f"{n:04d}" for n in missing[:FOLDER_DRIVES_SHOWN]) + (
                ", ..." if len(missing) > FOLDER_DRIVES_SHOWN else "")
            out.append(f"the drive of {first.name} lacks {plural(len(missing), 'part')} ({shown}): read without "
                       "them, its time there is a gap")
    return out


def _raw(f: DriveFile, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    """(log_time, order, topic, data) of the wanted topics in one file; what damage skipped is kept for
    :func:`damage_notes` (an unfinished file's cut is :func:`cut_notes`' to tell)."""
    _DAMAGE.pop(f.path, None)
    losses: list[Loss] = []
    try:
        if f.finished:
            out = raw_messages(f.path, wanted, losses)
        else:
            found = walk(f.path)
            losses = found.damage()
            topics = {cid: ch.topic for cid, ch in found.channels.items() if ch.topic in wanted}
            out = [(m.log_time, i, topics[m.channel_id], m.data) for i, m in enumerate(found.messages)
                   if m.channel_id in topics]
    except McapFileError as exc:
        raise DriveFileError(str(exc)) from exc
    except OSError as exc:
        raise DriveFileError(f"{f.path}: cannot be read ({exc.strerror or exc})") from exc
    if losses:
        _damaged(f.path).losses = losses
    return out


def _collect(files: list[DriveFile], wanted: set[str],
             progress: ProgressFn | None = None) -> list[tuple[int, int, int, str, bytes]]:
    """(log_time, file index, order, topic, data) of the wanted topics over the files, in log-time order (ties:
    file order, then order within the file)."""
    raw: list[tuple[int, int, int, str, bytes]] = []
    for index, f in enumerate(files):
        if progress is not None:
            progress(index, len(files), "files read")
        raw.extend((t, index, order, topic, data) for t, order, topic, data in _raw(f, wanted))
    raw.sort()  # (log_time, index, order) is unique: the data are never compared
    return raw


# Told (done, in all, of what): once per file read, then every PROGRESS_EVERY messages handed on.
ProgressFn = Callable[[int, int, str], None]
PROGRESS_EVERY = 4096


def _counted(raw: list[Any], progress: ProgressFn | None) -> Iterator[Any]:
    """The collected messages, telling ``progress`` how far the caller has got through them."""
    if progress is None:
        yield from raw
        return
    total = len(raw)
    for i, item in enumerate(raw):
        if i % PROGRESS_EVERY == 0:
            progress(i, total, "messages")
        yield item
    progress(total, total, "messages")


def imu_samples(batch: dict[str, Any]) -> list[dict[str, Any]]:
    """An ``/imu/batch`` record as the ``/imu`` records of its samples (their layout, their values), so that every
    reader of samples reads both kinds of drive alike."""
    ax, ay, az = batch["accel_x_mps2"], batch["accel_y_mps2"], batch["accel_z_mps2"]
    gx, gy, gz = batch["gyro_x_rps"], batch["gyro_y_rps"], batch["gyro_z_rps"]
    mono, sync, state, err = batch["t_mono_ns"], batch["t_sync_ns"], batch["sync_state"], batch["sync_err_ns"]
    imu_cnt, timer_cnt, seq, temp, lost = (batch["imu_cnt"], batch["timer_cnt"], batch["seq"], batch["temp_degc"],
                                           batch["lost"])
    return [{"t_mono_ns": mono[i], "t_sync_ns": sync[i], "sync_state": state[i], "sync_err_ns": err[i],
             "imu_cnt": imu_cnt[i], "timer_cnt": timer_cnt[i], "seq": seq + i,
             "accel_mps2": [ax[i], ay[i], az[i]], "gyro_rps": [gx[i], gy[i], gz[i]], "temp_degc": temp,
             "fifo": True, "lost": lost if i == 0 else 0} for i in range(len(mono))]


def _wanted(topics: Iterable[str]) -> tuple[set[str], bool]:
    """The topics to read, and whether ``/imu/batch`` records are to be handed on as their ``/imu`` samples: a
    reader of samples asks for ``/imu`` and gets a FIFO drive's samples too, one record each."""
    wanted = set(topics)
    expand = IMU_TOPIC in wanted and IMU_BATCH not in wanted
    if expand:
        wanted.add(IMU_BATCH)
    return wanted, expand


class ImuSlice(dict):
    """Samples of an ``/imu/batch`` record as a record of their own, which knows the record it was cut from: the
    file's one message, however many pieces a reader cuts it in (what a count of messages counts)."""

    __slots__ = ("record",)

    def __init__(self, fields: dict[str, Any], record: dict[str, Any]) -> None:
        super().__init__(fields)
        self.record = record


def imu_slice(batch: dict[str, Any], lo: int, hi: int) -> ImuSlice:
    """Samples ``lo`` to ``hi - 1`` of an ``/imu/batch`` record as a record of its own (its lost count goes with
    its first sample, its number is its first sample's)."""
    out = ImuSlice({k: v[lo:hi] if isinstance(v, list) else v for k, v in batch.items()}, batch)
    if lo:
        out["lost"] = 0
        out["seq"] = batch["seq"] + lo
    return out


def record_of(msg: dict[str, Any]) -> dict[str, Any]:
    """The file's message ``msg`` is, or is a piece of (:class:`ImuSlice`)."""
    return msg.record if isinstance(msg, ImuSlice) else msg


def _in_time_order(items: Iterator[tuple[int, str, int, dict[str, Any]]],
                   expand: bool, runs: bool = False) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
    """(log time, topic, file index, message) with each ``/imu/batch`` replaced by its samples at their own times.

    A batch is logged at its first sample's time, so its later samples wait here until the messages logged before
    them have gone by: the samples and the other topics come out in time order, as per-sample records would.
    ``runs``: a batch's samples come as ``/imu/batch`` records of their own instead, each the batch's samples up
    to the next other message (one slice when nothing comes between), for a reader that takes blocks."""
    if runs:
        yield from in_runs(items)
        return
    if not expand:
        yield from items
        return
    pending: deque[tuple[int, int, dict[str, Any]]] = deque()
    for t, topic, index, msg in items:
        while pending and pending[0][0] <= t:
            pt, pi, pm = pending.popleft()
            yield pt, IMU_TOPIC, pi, pm
        if topic == IMU_BATCH:
            pending.extend((m["t_sync_ns"], index, m) for m in imu_samples(msg))
            continue
        yield t, topic, index, msg
    for pt, pi, pm in pending:
        yield pt, IMU_TOPIC, pi, pm


def in_runs(items: Iterator[tuple[int, str, int, dict[str, Any]]]) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
    """(log time, topic, file index, message) in log-time order, a batch logged at its first sample's time, with
    each batch cut where another message comes between its samples: replay's order, and the live navigator's
    (logger.runtime.navigator)."""
    pending: deque[tuple[int, dict[str, Any], int]] = deque()  # (file index, batch, first sample not yet out)

    def upto(t: int | None) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
        while pending:
            index, batch, lo = pending[0]
            times = batch["t_sync_ns"]
            hi = len(times) if t is None else bisect.bisect_right(times, t, lo)
            if hi > lo:
                yield times[lo], IMU_BATCH, index, batch if lo == 0 and hi == len(times) else imu_slice(batch, lo, hi)
            if hi < len(times):
                pending[0] = (index, batch, hi)
                return
            pending.popleft()

    for t, topic, index, msg in items:
        yield from upto(t)
        if topic == IMU_BATCH and msg["t_sync_ns"]:
            pending.append((index, msg, 0))
            continue
        yield t, topic, index, msg
    yield from upto(None)


def iter_messages(files: list[DriveFile], topics: Iterable[str],
                  progress: ProgressFn | None = None) -> Iterator[DriveMessage]:
    """Every message of the given topics over the files, decoded, in log-time order (ties: file order); a FIFO
    drive's ``/imu/batch`` records come as their ``/imu`` samples where ``/imu`` is asked for."""
    wanted, expand = _wanted(topics)
    for t, topic, index, msg in _in_time_order(_decoded(files, wanted, progress), expand):
        yield DriveMessage(t, topic, index, msg)


def _decoded(files: list[DriveFile], wanted: set[str],
             progress: ProgressFn | None) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
    loads = json.loads
    for t, index, _, topic, data in _counted(_collect(files, wanted, progress), progress):
        try:
            msg = loads(data)
        except ValueError:  # UnicodeDecodeError and JSONDecodeError alike: skipped, counted, told (damage_notes)
            _damaged(files[index].path).undecodable += 1
            continue
        yield t, topic, index, msg


def read_messages(paths: Iterable[Path], topics: Iterable[str],
                  progress: ProgressFn | None = None, runs: bool = False) -> Iterator[tuple[str, dict[str, Any]]]:
    """(topic, message) of the given topics over one drive's files, in log-time order, for the filter: as
    :func:`iter_messages`, with an IMU record's fields pulled out without decoding the whole JSON object.
    ``runs``: a FIFO drive's samples as ``/imu/batch`` records cut at the other messages (:func:`_in_time_order`)."""
    files = open_drive(paths)
    wanted, expand = _wanted(topics)
    for _, topic, _, msg in _in_time_order(_filter_inputs(files, wanted, progress), expand, runs):
        yield topic, msg


def _filter_inputs(files: list[DriveFile], wanted: set[str],
                   progress: ProgressFn | None) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
    loads = json.loads
    imu = _IMU.match
    for t, index, _, topic, data in _counted(_collect(files, wanted, progress), progress):
        if topic == IMU_TOPIC:
            m = imu(data, 1)
            if m is not None:
                a, g = m.group(3).split(b","), m.group(4).split(b",")
                if len(a) == 3 and len(g) == 3:
                    msg = {"t_mono_ns": int(m.group(1)), "t_sync_ns": int(m.group(2)),
                           "accel_mps2": [float(a[0]), float(a[1]), float(a[2])],
                           "gyro_rps": [float(g[0]), float(g[1]), float(g[2])]}
                    if m.group(5) is not None:  # die temperature: the offsets' thermal drift (thermal.py)
                        msg["temp_degc"] = float(m.group(5))
                    yield t, topic, index, msg
                    continue
        try:
            msg = loads(data)
        except ValueError:  # as in _decoded: skipped, counted, told
            _damaged(files[index].path).undecodable += 1
            continue
        yield t, topic, index, msg
