"""Reading, checking and recovering the logger's MCAP files.

A file is *finished* when it ends with the footer and the closing magic that ``McapWriter.finish()`` writes. An
unfinished file (power cut, ``kill -9``, full disk) still holds every chunk that was flushed before the cut; the
index-based readers see nothing in it, so recovery walks the records from the start, keeps every chunk whose CRC
checks out, and writes them again into a finished, indexed file. Recovery writes beside the original and
renames over it only once the copy is complete and synced, so a crash during recovery loses nothing either.

Recovery holds no message: its walk keeps where each good chunk lies (and the schema, channel and metadata
records), and the copy reads the chunks again one at a time. An hour's cut file at 500 Hz (178 MB, 2 million
messages) took 1.2 GB when the walk kept every message, more than the board has, so the daemon died at every
start recovering it; now recovery's memory is one source chunk, one chunk of the copy and a few bytes a chunk.

What the walk could not keep is kept as :class:`Loss` records (where, how many chunks, how many messages, when),
so recovery and the readers say what damage cost: a lost chunk's message index records (written right after it)
count its messages, and a finished file's statistics count everything its damage hid.
"""

from __future__ import annotations

import bisect
import contextlib
import fcntl
import io
import itertools
import mmap
import os
import struct
import time
import zlib
from array import array
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lz4.frame
import zstandard
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from logger.recording.mcap_writer import (
    CHUNK_HEAD,
    MAGIC,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE_INDEX,
    OP_STATISTICS,
    RECORD_HEAD,
    McapWriter,
)
from logger.recording.topics import TOPICS

# Metadata the recorder writes outside the chunks: channel id -> topic, so recovery can name the messages of a
# channel whose record was in a damaged chunk.
CHANNEL_TABLE = "vehicle-logger.channels"
# Every file carries this metadata record, written at open before any chunk (so a file cut short has it too):
# {"run": a random id per recorder start, "part": its part number}. The drive reader groups files by run, so two
# starts are two drives whatever their names say (logger.recording.drive.run_identity).
RUN_METADATA = "drive"
# The MCAP header's library: the program, then its version (logger.__version__): "vehicle-logger 0.2.0" for the
# daemon's files, "vehicle-logger replay 0.2.0" for a replay's. Files of 0.1.0 have the bare names.
LIVE_NAME = "vehicle-logger"
REPLAY_NAME = "vehicle-logger replay"

FOOTER_LEN = 1 + 8 + 8 + 8 + 4  # opcode, record length, summary start, summary offset start, summary crc


class McapFileError(Exception):
    """A file is not an MCAP file at all, or cannot be read; the message names the file."""


class RecoveryCancelled(Exception):
    """A walk or recovery stopped when its ``cancel`` said so (the daemon stopping while it recovers in the
    background): nothing was replaced and no partial copy is left, so the next start does it again."""


def is_finished(path: str | os.PathLike[str]) -> bool:
    """True when the file ends with a footer and the closing magic, as a clean ``finish()`` leaves it."""
    try:
        state = file_state(path)
    except OSError:
        return False
    return state is not None and state[1]


def file_state(path: str | os.PathLike[str]) -> tuple[int, bool] | None:
    """A file's size and whether it is finished (:func:`is_finished`), from one open; None when it is not there."""
    try:
        with open(path, "rb") as f:
            size = f.seek(0, os.SEEK_END)
            if size < 2 * len(MAGIC) + FOOTER_LEN:
                return size, False
            f.seek(size - len(MAGIC) - FOOTER_LEN)
            tail = f.read()
    except FileNotFoundError:
        return None
    return size, tail[-len(MAGIC):] == MAGIC and tail[0] == OP_FOOTER


@dataclass
class Loss:
    """One place a reader could not read: a damaged chunk skipped whole, damaged bytes walked past up to the next
    good chunk, or the cut at the end. Kept so that what was lost is told (chunks, messages, when), not only that
    something was."""

    at: int  # the byte where it starts
    chunks: int = 0  # chunks known lost in it
    messages: int = 0  # messages they held, all topics (their message indexes, or the file's statistics, tell)
    exact: bool = True  # ``messages`` is all that was lost here; False: at least that many (nothing told the rest)
    cut: bool = False  # the file ends in it (a power loss), rather than going on past damage
    reason: str = ""  # why a chunk was skipped: its CRC, its compression, a record in it
    first_ns: int | None = None  # the log-time span lost: no later than this ...
    last_ns: int | None = None  # ... and no earlier than this (the chunk's own times, or its good neighbours')


def utc_text(t_ns: int | None) -> str:
    """A log time as the loss lines print it (to the tenth of a second: chunks span about one)."""
    if t_ns is None:
        return "?"
    return time.strftime("%H:%M:%S", time.gmtime(t_ns // 1_000_000_000)) + f".{(t_ns // 100_000_000) % 10}"


SPANS_SHOWN = 3


def describe_losses(losses: list[Loss]) -> str:
    """What the losses cost, in one clause: ``2 damaged chunks skipped (CRC mismatch), 130 messages lost, at
    09:44:50.1-09:44:51.1, 09:50:02.0-09:50:03.0 UTC``; empty for none."""
    if not losses:
        return ""
    chunks = sum(x.chunks for x in losses)
    messages = sum(x.messages for x in losses)
    exact = all(x.exact for x in losses)
    reasons = sorted({x.reason for x in losses if x.reason})
    what = (f"{'' if exact else 'at least '}{chunks} damaged chunk{'s' if chunks != 1 else ''} skipped" if chunks
            else f"damaged bytes skipped at byte {losses[0].at}")
    if reasons:
        what += f" ({', '.join(reasons)})"
    if messages or exact:
        what += f", {'' if exact else 'at least '}{messages} message{'s' if messages != 1 else ''} lost"
    else:
        what += ", messages lost: unknown"
    spans = [f"{utc_text(x.first_ns)}-{utc_text(x.last_ns)}" for x in losses]
    shown = ", ".join(spans[:SPANS_SHOWN]) + (", ..." if len(spans) > SPANS_SHOWN else "")
    return f"{what}, at {shown} UTC"


def chunk_fault(compression: str, data: bytes | memoryview, size: int, crc: int) -> tuple[str, bytes | None]:
    """A chunk's records decompressed and checked against its CRC (MCAP: ``uncompressed_crc`` over the
    decompressed records, 0 when the writer did not compute one): ("", records) when they hold, (why, None) when
    not. The CRC is what tells a flipped byte from a value: without it a damaged chunk that still decompresses
    (zstd's frames carry no checksum by default; lz4's none either) gives other numbers in valid JSON."""
    try:
        if compression == "zstd":
            raw = zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=size)
        elif compression == "lz4":
            raw = lz4.frame.decompress(bytes(data))
        elif compression == "":
            raw = bytes(data)
        else:
            return f"compression {compression!r}", None
    except Exception:  # whatever a damaged frame makes the decompressor raise
        return "does not decompress", None
    if len(raw) != size:
        return "wrong size", None
    if crc and zlib.crc32(raw) != crc:
        return "CRC mismatch", None
    return "", raw


def indexed_messages(buf: bytes | memoryview | mmap.mmap, pos: int) -> int | None:
    """Messages listed by the message index records at ``pos`` (the writer puts them right after their chunk):
    how many a lost chunk held. None when no index record is there."""
    n = 0
    seen = False
    while pos + 9 + 6 <= len(buf) and buf[pos] == OP_MESSAGE_INDEX:
        _, length = RECORD_HEAD.unpack_from(buf, pos)
        (entries,) = struct.unpack_from("<I", buf, pos + 9 + 2)
        if length != 6 + entries or entries % 16 or pos + 9 + length > len(buf):
            break
        n += entries // 16
        seen = True
        pos += 9 + length
    return n if seen else None


@dataclass(frozen=True)
class Statistics:
    messages: int
    chunks: int


def summary_statistics(buf: bytes | memoryview | mmap.mmap) -> Statistics | None:
    """The message and chunk counts of a finished file's statistics record, when its summary's CRC holds (or the
    writer left it 0): what a reader compares its count with, to know what damage cost even where a lost chunk's
    own index went with it. None for an unfinished file or a damaged summary."""
    size = len(buf)
    foot = size - len(MAGIC) - FOOTER_LEN
    if foot < len(MAGIC) or bytes(buf[size - len(MAGIC):]) != MAGIC or buf[foot] != OP_FOOTER:
        return None
    start, _offsets, crc = struct.unpack_from("<QQI", buf, foot + 9)
    if not len(MAGIC) <= start <= foot:
        return None
    if crc and zlib.crc32(buf[start:foot + 9 + 16]) != crc:
        return None
    pos = start
    while pos + 9 <= foot:
        op, length = RECORD_HEAD.unpack_from(buf, pos)
        if pos + 9 + length > foot:
            return None
        if op == OP_STATISTICS and length >= 38:
            messages, _s, _c, _a, _m, chunks = struct.unpack_from("<QHIIII", buf, pos + 9)
            return Statistics(messages, chunks)
        pos += 9 + length
    return None


@dataclass
class Salvage:
    """What a record walk of a possibly truncated file found."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)  # only when the walk keeps them (``keep_messages``)
    keep_messages: bool = True
    message_count: int = 0  # messages in the good chunks (and outside chunks), kept or not
    metadata: list[Metadata] = field(default_factory=list)
    chunks_ok: int = 0
    chunks_bad: int = 0
    stopped_at: str = ""  # the first cut or damage the walk met, empty if it reached the footer
    profile: str = ""
    library: str = ""  # the header's writer: a recovered file keeps it (a replay's output stays a replay's)
    magic: bool = True
    losses: list[Loss] = field(default_factory=list)  # every damage and cut the walk met, in file order
    good_chunks: list[tuple[int, int, int]] = field(default_factory=list)  # (offset, first, last log time)
    # Where the walk found messages, in file order: each good chunk's (and each message outside a chunk's) start
    # and end offset, flat, 16 bytes a record: what recovery copies from, reading each again in turn.
    pieces: array[int] = field(default_factory=lambda: array("q"))
    statistics: Statistics | None = None  # the finished file's own counts, when its summary holds

    def damage(self) -> list[Loss]:
        """The losses other than the cut at the end: what a reader of an unfinished file has to tell besides
        the cut it tells anyway."""
        return [x for x in self.losses if not x.cut]


OP_MAX = 0x11  # the walk's bound on an opcode byte that can start a record
RESYNC_LIMIT = 1 << 16  # candidate records tried after a damage before the walk gives up on the rest


def walk(path: str | os.PathLike[str], keep_messages: bool = True,
         cancel: Callable[[], bool] | None = None) -> Salvage:
    """Collect every complete, CRC-valid record of a file: past a flipped byte or a zeroed page it looks for the
    next chunk that parses with its CRC right and goes on from there; a cut ends it.

    ``keep_messages=False`` (recovery) counts the messages and notes where they lie (``pieces``) instead of keeping
    them: a reader wants the messages, recovery only their place, and on the board the messages of an hour at
    500 Hz do not fit. ``cancel`` is asked now and then; when it says so the walk raises
    :class:`RecoveryCancelled`.

    The file is mapped, not read: a day's file on a 512 MB board stays in the page cache, not on the heap, and the
    pages behind the walk are let go of as it goes (they stay cached), so they do not count in its resident set."""
    found = Salvage(keep_messages=keep_messages)
    try:
        with open(path, "rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                raise McapFileError(f"{path}: not an MCAP file (empty)")
            buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except OSError as exc:
        raise McapFileError(f"{path}: cannot open ({exc.strerror or exc})") from exc
    try:
        _walk_mapped(buf, found, cancel)
        found.statistics = summary_statistics(buf)
    finally:
        buf.close()
    _account(found)
    _name_orphans(found)
    if not found.magic and found.chunks_ok == 0:
        raise McapFileError(f"{path}: not an MCAP file (no MCAP magic at the start, and no readable chunk)")
    return found


RELEASE_BYTES = 16 << 20  # the walk lets go of the mapped pages behind it every this many bytes
CANCEL_EVERY = 64  # records walked (chunks, mostly) between two questions to ``cancel``


def _release(buf: mmap.mmap, upto: int) -> int:
    """Drop the mapping's pages before ``upto`` from the process (they stay in the page cache, and come back if
    touched again); returns where the next release starts from. Without it a walk's resident set grows by the
    whole file, which is no memory the kernel cannot take back, but is what the board's figures and a cgroup's
    accounting show."""
    end = upto - upto % mmap.PAGESIZE
    if end > 0 and hasattr(mmap, "MADV_DONTNEED"):
        with contextlib.suppress(OSError, ValueError):
            buf.madvise(mmap.MADV_DONTNEED, 0, end)
    return upto


def _walk_mapped(buf: mmap.mmap, found: Salvage, cancel: Callable[[], bool] | None = None) -> None:
    size = len(buf)
    found.magic = buf[:len(MAGIC)] == MAGIC
    pos = len(MAGIC) if found.magic else 0
    record = None
    released = 0
    for n in itertools.count():
        if pos + 9 > size:
            break
        if n % CANCEL_EVERY == 0 and cancel is not None and cancel():
            raise RecoveryCancelled()
        if pos - released >= RELEASE_BYTES:
            released = _release(buf, pos)
        record = _record_at(buf, pos, found) if pos > 0 else None
        if record is None:
            _, length = RECORD_HEAD.unpack_from(buf, pos)
            loss = Loss(pos, cut=pos + 9 + length > size and 0 < buf[pos] <= OP_MAX)
            found.losses.append(loss)
            if loss.cut:
                found.stopped_at = found.stopped_at or f"cut at byte {size} in a record from byte {pos}"
            else:
                found.stopped_at = found.stopped_at or f"damaged at byte {pos}"
            if buf[pos] == OP_CHUNK and pos + 9 + CHUNK_HEAD.size + 12 <= size and \
                    _chunk_lengths_agree(buf, pos, length):
                _count_lost_chunk(buf, pos, length, loss)
            elif pos > 0:
                loss.exact = False  # bytes that were not a chunk's: a chunk whose head they hid may be gone too
            nxt = _next_chunk(buf, pos + 1, found, loss)
            if nxt is None:
                if not loss.cut and pos + 9 + length < size:
                    loss.exact = False  # nothing readable after it: what followed is lost, uncounted
                return
            if not loss.exact:
                _scan_indexes(buf, pos + 1, nxt, found, loss)
            pos = nxt
            continue
        op, pos = record
        if op in (OP_DATA_END, OP_FOOTER):
            if buf[size - len(MAGIC):] != MAGIC:  # the data are whole; the summary after them was cut
                found.stopped_at = found.stopped_at or f"cut at byte {size}, after the data"
                found.losses.append(Loss(size, cut=True, reason="after the data"))
            return
    if not found.stopped_at:  # no DataEnd, no footer: cut, even exactly at a record's end (pos == size)
        found.stopped_at = f"cut at byte {size}"
        found.losses.append(Loss(pos, cut=True))


def _count_lost_chunk(buf: mmap.mmap, pos: int, length: int, loss: Loss) -> None:
    """Add the chunk at ``pos`` (whose lengths agree, but whose records fail) to ``loss``: one chunk, and the
    messages its index records list when they follow it whole."""
    loss.chunks += 1
    if pos + 9 + CHUNK_HEAD.size <= len(buf):  # its own times, checked against its neighbours' in _account
        first, last, _, _ = CHUNK_HEAD.unpack_from(buf, pos + 9)
        loss.first_ns = first if loss.first_ns is None else min(loss.first_ns, first)
        loss.last_ns = last if loss.last_ns is None else max(loss.last_ns, last)
    end = pos + 9 + length
    n = indexed_messages(buf, end) if end <= len(buf) else None
    if n is None:
        loss.exact = False
    else:
        loss.messages += n


def _scan_indexes(buf: mmap.mmap, lo: int, hi: int, found: Salvage, loss: Loss) -> None:
    """Damaged bytes between ``lo`` and the next good chunk at ``hi`` whose chunk heads were hit (a zeroed page):
    the message index records the writer put after each of those chunks often survive, and tell what they held.
    A candidate counts only when it parses whole, names a known channel and lists rising offsets; each run of
    them is one chunk. The count stays a lower bound (``exact`` false): an index may have gone with the damage."""
    pos = buf.find(bytes([OP_MESSAGE_INDEX]), lo, hi)
    messages, runs, last_end = 0, 0, -1
    while 0 <= pos < hi:
        step = 1
        if pos + 9 + 6 <= hi:
            _, length = RECORD_HEAD.unpack_from(buf, pos)
            cid, entries = struct.unpack_from("<HI", buf, pos + 9)
            if length == 6 + entries and entries and entries % 16 == 0 and pos + 9 + length <= hi and \
                    cid in found.channels:
                offsets = struct.unpack_from(f"<{entries // 8}Q", buf, pos + 15)[1::2]
                if all(a < b for a, b in itertools.pairwise(offsets)):
                    messages += entries // 16
                    runs += pos != last_end
                    last_end = pos + 9 + length
                    step = 9 + length
        pos = buf.find(bytes([OP_MESSAGE_INDEX]), pos + step, hi)
    loss.messages += messages
    loss.chunks = max(loss.chunks, runs)


# How far a chunk's messages may reach before its predecessor's first or after its successor's last: a message is
# logged at its own time (a solution's, a sample's) but written when it comes, and the navigator's come up to a
# few seconds late, so chunks overlap in time. A damaged head's times (not under the CRC) are garbage, far off.
CHUNK_OVERLAP_NS = 60 * 1_000_000_000


def head_span_plausible(first: int | None, last: int | None, prev: tuple[int, int, int] | None,
                        nxt: tuple[int, int, int] | None) -> bool:
    """Whether a skipped chunk's own head times (``first``, ``last``) can be its messages' span, against its good
    neighbours (offset, first, last): in order, and within CHUNK_OVERLAP_NS of them. Held to the neighbours'
    own first and last exactly, the late /nav/fix messages of a drive made every head look damaged, and a 4.7 s
    loss was said as the 0.7 s gap between its neighbours."""
    if first is None or last is None or first > last:
        return False
    if prev is not None and first < prev[1] - CHUNK_OVERLAP_NS:
        return False
    return nxt is None or last <= nxt[2] + CHUNK_OVERLAP_NS


def _account(found: Salvage) -> None:
    """Each loss's time span from the good chunks around it, and, for a finished file whose statistics hold, the
    exact count: the statistics know every chunk and message written, whatever the damage hid."""
    starts = [c[0] for c in found.good_chunks]
    for loss in found.losses:
        i = bisect.bisect_left(starts, loss.at)
        prev = found.good_chunks[i - 1] if i > 0 else None
        nxt = found.good_chunks[i] if i < len(found.good_chunks) else None
        # The lost chunks' own times when their heads were read and fit among their good neighbours'
        # (head_span_plausible), else the gap between the neighbours.
        if loss.chunks > 1 or not head_span_plausible(loss.first_ns, loss.last_ns, prev, nxt):
            loss.first_ns = prev[2] if prev is not None else None
            loss.last_ns = nxt[1] if nxt is not None else None
    stats = found.statistics
    if stats is None:
        return
    missing_chunks = stats.chunks - found.chunks_ok
    missing_messages = stats.messages - found.message_count
    if missing_chunks <= 0 and missing_messages <= 0:
        return
    if not found.losses:  # a damage the walk passed over without noticing (a record it could skip)
        found.losses.append(Loss(len(MAGIC), exact=False))
    if len(found.losses) == 1:
        only = found.losses[0]
        only.chunks = max(only.chunks, missing_chunks)
        only.messages, only.exact = missing_messages, True
    else:  # the statistics give the total, not where: the last loss takes what the indexes did not place
        rest = missing_messages - sum(x.messages for x in found.losses)
        last = found.losses[-1]
        last.messages += max(rest, 0)
        last.chunks += max(missing_chunks - sum(x.chunks for x in found.losses), 0)
        for x in found.losses:
            x.exact = True


def _parse_record(raw: bytes) -> object:
    """The one record in ``raw`` (opcode, length, body), its CRCs checked; raises whatever a damaged record makes
    the parser raise."""
    # One record on its own: the reader raises at the end of the slice after it, so only the first is taken.
    return next(iter(StreamReader(io.BytesIO(raw), skip_magic=True, emit_chunks=True, validate_crcs=True,
                                  record_size_limit=len(raw)).records))


def _record_at(buf: mmap.mmap, pos: int, found: Salvage) -> tuple[int, int] | None:
    """Parse the record at ``pos`` into ``found``; (opcode, end) or None when it does not parse (or a chunk's CRC
    is wrong: counted as a bad chunk)."""
    op, length = RECORD_HEAD.unpack_from(buf, pos)
    end = pos + 9 + length
    if not 0 < op <= OP_MAX or end > len(buf):
        return None
    try:
        record = _parse_record(buf[pos:end])
    except Exception:  # whatever a damaged record makes the parser raise
        if op == OP_CHUNK:
            found.chunks_bad += 1
        return None
    if isinstance(record, Chunk):
        try:
            inner = breakup_chunk(record, validate_crc=True)
        except Exception:
            found.chunks_bad += 1
            return None
        found.chunks_ok += 1
        found.good_chunks.append((pos, record.message_start_time, record.message_end_time))
        if any(isinstance(r, Message) for r in inner):
            found.pieces.extend((pos, end))
        for r in inner:
            _keep(found, r)
    else:
        if isinstance(record, Message):
            found.pieces.extend((pos, end))
        _keep(found, record)
    return op, end


def _next_chunk(buf: mmap.mmap, start: int, found: Salvage, loss: Loss) -> int | None:
    """The offset of the next chunk record that parses with its CRC right, from ``start`` on. A chunk met on the
    way whose lengths add up but whose CRC fails is a damaged chunk, counted (bad, and in ``loss``)."""
    tries = 0
    pos = buf.find(bytes([OP_CHUNK]), start)
    while pos >= 0 and pos + 9 + CHUNK_HEAD.size <= len(buf) and tries < RESYNC_LIMIT:
        _, length = RECORD_HEAD.unpack_from(buf, pos)
        if pos + 9 + length <= len(buf) and length >= CHUNK_HEAD.size + 12 and \
                _chunk_lengths_agree(buf, pos, length):
            tries += 1
            probe = Salvage(keep_messages=False)
            if _record_at(buf, pos, probe) is not None:
                return pos
            found.chunks_bad += 1
            _count_lost_chunk(buf, pos, length, loss)
        pos = buf.find(bytes([OP_CHUNK]), pos + 1)
    return None


def _chunk_lengths_agree(buf: mmap.mmap, pos: int, length: int) -> bool:
    """A cheap test before parsing: a chunk's compression name and records length add up to its record length."""
    at = pos + 9 + CHUNK_HEAD.size
    (n,) = struct.unpack_from("<I", buf, at)
    if n > 16 or at + 4 + n + 8 > len(buf):
        return False
    (records_len,) = struct.unpack_from("<Q", buf, at + 4 + n)
    return CHUNK_HEAD.size + 4 + n + 8 + records_len == length


def _keep(found: Salvage, record: object) -> None:
    if isinstance(record, Schema):
        found.schemas[record.id] = record
    elif isinstance(record, Channel):
        found.channels[record.id] = record
    elif isinstance(record, Message):
        found.message_count += 1
        if found.keep_messages:
            found.messages.append(record)
    elif isinstance(record, Metadata):
        found.metadata.append(record)
    elif type(record).__name__ == "Header":
        found.profile = getattr(record, "profile", "")
        found.library = getattr(record, "library", "")


def _name_orphans(found: Salvage) -> None:
    """Channels whose record was in a damaged chunk, made again from the recorder's channel tables (outside the
    chunks) and the topic registry's schemas, so their messages keep their topic."""
    tables: dict[int, str] = {}
    for m in found.metadata:
        if m.name == CHANNEL_TABLE:
            tables.update((int(cid), topic) for cid, topic in m.metadata.items() if cid.isdigit())
    # By name and content: /gnss/fix and /nav/fix share a schema name, each with its own fields.
    known = {(schema.name, bytes(schema.data)): sid for sid, schema in found.schemas.items()}
    for cid, topic in sorted(tables.items()):
        if cid in found.channels:
            continue
        spec = TOPICS.get(topic)
        sid = 0
        if spec is not None:
            key = (spec.schema_name, spec.schema_data)
            sid = known.get(key, 0)
            if sid == 0:
                sid = max(found.schemas, default=0) + 1
                found.schemas[sid] = Schema(id=sid, name=spec.schema_name, encoding="jsonschema",
                                            data=spec.schema_data)
                known[key] = sid
        found.channels[cid] = Channel(id=cid, topic=topic, message_encoding="json", schema_id=sid, metadata={})


@dataclass(frozen=True)
class RecoveryReport:
    path: Path
    messages: int
    chunks_ok: int
    chunks_bad: int
    dropped_orphans: int  # messages whose channel record was lost with the cut
    reason: str
    losses: tuple[Loss, ...] = ()  # what was lost, where and when (files.describe_losses says it)

    def lost(self) -> str:
        """What the recovery could not keep, in one clause, the cut told apart from the damage; empty: nothing."""
        damage = [x for x in self.losses if not x.cut]
        cut = [x for x in self.losses if x.cut]
        parts = [describe_losses(damage)] if damage else []
        for c in cut[:1]:
            if c.reason:
                parts.append(f"cut at byte {c.at}, {c.reason}: only the index was lost")
            else:
                parts.append(f"cut at byte {c.at}" + (f" (after {utc_text(c.first_ns)} UTC)" if c.first_ns else "")
                             + (", its unfinished last chunk lost" if c.chunks else ""))
        return "; ".join(parts)


RECOVERY_CHUNK_BYTES = 4 * 1024 * 1024  # the copy's chunks: few index records, each compressed well


def hold_for_writing(stream: Any) -> None:
    """Mark a file the recorder has open for writing: an exclusive advisory lock (``flock``) held until it is
    closed, by which :func:`being_written` tells that a logger still writes it. Best effort: a file system that
    refuses locks (ENOLCK) loses that protection, never the recording."""
    with contextlib.suppress(OSError):
        fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)


def being_written(path: Path) -> bool:
    """Whether a running logger has ``path`` open for writing (:func:`hold_for_writing`). An unfinished file looks
    the same whether a crash cut it or a logger is writing it: recovering the one being written (a second `logger
    run`'s start-up, a `logger recover` by hand) rewrote it under the logger, which then lost it."""
    try:
        with open(path, "rb") as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
    except OSError:
        return False
    return False


def recover(path: str | os.PathLike[str], out: str | os.PathLike[str] | None = None,
            compression: str = "zstd", found: Salvage | None = None,
            cancel: Callable[[], bool] | None = None) -> RecoveryReport:
    """Rewrite what survives of ``path`` into a finished file (``out``, or in place); ``found``: the file's walk,
    when the caller has made it already (``logger recover`` walks a cleanly closed file to see whether it is
    damaged). ``cancel`` is asked between chunks: :class:`RecoveryCancelled` then, with the source untouched and
    no copy left.

    The walk keeps no message (``keep_messages=False``); the copy takes the good chunks from the source again,
    one at a time, so what recovery holds does not grow with the file."""
    src = Path(path)
    if found is None:
        found = walk(src, keep_messages=False, cancel=cancel)
    dst = Path(out) if out is not None else src
    tmp = dst.with_name(dst.name + ".recovering")
    try:
        orphans = _rewrite(found, src, tmp, compression, cancel)
        with contextlib.suppress(OSError):  # the source's permissions (the logger's 0640), not the caller's umask
            os.chmod(tmp, src.stat().st_mode & 0o777)
        os.replace(tmp, dst)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)  # a full disk, a folder as OUT: the source is untouched, no half copy left
        if isinstance(exc, OSError) and (not exc.filename or Path(exc.filename) == tmp):
            exc.filename, exc.filename2 = str(dst), None  # a write names no file: the copy's disk, not the source's
        raise
    _fsync_dir(dst.parent)
    return RecoveryReport(dst, found.message_count - orphans, found.chunks_ok, found.chunks_bad, orphans,
                          found.stopped_at, tuple(found.losses))


def _messages_at(source: io.BufferedReader, src: Path, at: int, end: int) -> list[Message]:
    """The messages of the good chunk (or the message) the walk found at ``at``, read again from the source and
    checked again as the walk checked it: a file that changed since (which nothing should write to) is refused
    rather than copied as it is now."""
    source.seek(at)
    raw = source.read(end - at)
    try:
        if len(raw) != end - at:
            raise ValueError("shorter")
        record = _parse_record(raw)
        inner = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
    except Exception as exc:  # whatever the parser raises for bytes that are no longer what the walk read
        raise McapFileError(f"{src}: changed while it was recovered (the record at byte {at} no longer "
                            "reads as it did)") from exc
    return [r for r in inner if isinstance(r, Message)]


def _rewrite(found: Salvage, src: Path, tmp: Path, compression: str,
             cancel: Callable[[], bool] | None = None) -> int:
    """Write what the walk found into ``tmp`` as a finished file; returns the messages without a channel. The
    messages come from ``found.messages`` when the walk kept them, else from the source, a chunk at a time."""
    orphans = 0
    with open(tmp, "wb") as f, open(src, "rb") as source:
        writer = McapWriter(f, compression=compression, chunk_size=RECOVERY_CHUNK_BYTES)
        writer.start(profile=found.profile, library=found.library)
        schema_ids: dict[int, int] = {}
        for sid, schema in sorted(found.schemas.items()):
            schema_ids[sid] = writer.register_schema(schema.name, schema.encoding, schema.data)
        channel_ids: dict[int, int] = {}
        for cid, ch in sorted(found.channels.items()):
            channel_ids[cid] = writer.register_channel(ch.topic, ch.message_encoding,
                                                       schema_ids.get(ch.schema_id, 0), dict(ch.metadata))
        for m in found.metadata:
            if m.name != CHANNEL_TABLE:
                writer.add_metadata(m.name, dict(m.metadata))
        if found.keep_messages:
            batches: Iterator[list[Message]] = iter([found.messages])
        else:
            pieces = found.pieces
            batches = (_messages_at(source, src, pieces[i], pieces[i + 1]) for i in range(0, len(pieces), 2))
        for batch in batches:
            if cancel is not None and cancel():
                raise RecoveryCancelled()
            for msg in batch:
                cid = channel_ids.get(msg.channel_id)
                if cid is None:
                    orphans += 1
                    continue
                writer.add_message(cid, msg.log_time, msg.data, msg.publish_time, msg.sequence)
        writer.add_metadata("recovery", {
            "source": src.name, "chunks_recovered": str(found.chunks_ok),
            "chunks_corrupt": str(found.chunks_bad), "cut": found.stopped_at or "none"})
        writer.finish()
        f.flush()
        os.fsync(f.fileno())
    return orphans


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
