"""Reading, checking and recovering the logger's MCAP files.

A file is *finished* when it ends with the footer and the closing magic that ``McapWriter.finish()`` writes. An
unfinished file (power cut, ``kill -9``, full disk) still holds every chunk that was flushed before the cut; the
index-based readers see nothing in it, so recovery walks the records from the start, keeps every chunk whose CRC
checks out, and writes them again into a finished, indexed file. Recovery writes beside the original and
renames over it only once the copy is complete and synced, so a crash during recovery loses nothing either.
"""

from __future__ import annotations

import io
import mmap
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from logger.recording.mcap_writer import (
    CHUNK_HEAD,
    MAGIC,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    RECORD_HEAD,
    McapWriter,
)
from logger.recording.topics import TOPICS

# Metadata the recorder writes outside the chunks: channel id -> topic, so recovery can name the messages of a
# channel whose record was in a damaged chunk.
CHANNEL_TABLE = "vehicle-logger.channels"

FOOTER_LEN = 1 + 8 + 8 + 8 + 4  # opcode, record length, summary start, summary offset start, summary crc


class McapFileError(Exception):
    """A file is not an MCAP file at all, or cannot be read; the message names the file."""


def is_finished(path: str | os.PathLike[str]) -> bool:
    """True when the file ends with a footer and the closing magic, as a clean ``finish()`` leaves it."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            if size < 2 * len(MAGIC) + FOOTER_LEN:
                return False
            f.seek(size - len(MAGIC) - FOOTER_LEN)
            tail = f.read()
    except OSError:
        return False
    return tail[-len(MAGIC):] == MAGIC and tail[0] == OP_FOOTER


@dataclass
class Salvage:
    """What a record walk of a possibly truncated file found."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    metadata: list[Metadata] = field(default_factory=list)
    chunks_ok: int = 0
    chunks_bad: int = 0
    stopped_at: str = ""  # the first cut or damage the walk met, empty if it reached the footer
    profile: str = ""
    library: str = ""  # the header's writer: a recovered file keeps it (a replay's output stays a replay's)
    magic: bool = True


OP_MAX = 0x11  # the walk's bound on an opcode byte that can start a record
RESYNC_LIMIT = 1 << 16  # candidate records tried after a damage before the walk gives up on the rest


def walk(path: str | os.PathLike[str]) -> Salvage:
    """Collect every complete, CRC-valid record of a file: past a flipped byte or a zeroed page it looks for the
    next chunk that parses with its CRC right and goes on from there; a cut ends it.

    The file is mapped, not read: a day's file on a 512 MB board stays in the page cache, not on the heap."""
    found = Salvage()
    try:
        with open(path, "rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                raise McapFileError(f"{path}: not an MCAP file (empty)")
            buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except OSError as exc:
        raise McapFileError(f"{path}: cannot open ({exc.strerror or exc})") from exc
    try:
        _walk_mapped(buf, found)
    finally:
        buf.close()
    _name_orphans(found)
    if not found.magic and found.chunks_ok == 0:
        raise McapFileError(f"{path}: not an MCAP file (no MCAP magic at the start, and no readable chunk)")
    return found


def _walk_mapped(buf: mmap.mmap, found: Salvage) -> None:
    size = len(buf)
    found.magic = buf[:len(MAGIC)] == MAGIC
    pos = len(MAGIC) if found.magic else 0
    record = None
    while pos + 9 <= size:
        record = _record_at(buf, pos, found) if pos > 0 else None
        if record is None:
            _, length = RECORD_HEAD.unpack_from(buf, pos)
            if pos + 9 + length > size and 0 < buf[pos] <= OP_MAX:
                found.stopped_at = found.stopped_at or f"cut at byte {size} in a record from byte {pos}"
            else:
                found.stopped_at = found.stopped_at or f"damaged at byte {pos}"
            nxt = _next_chunk(buf, pos + 1)
            if nxt is None:
                return
            pos = nxt
            continue
        op, pos = record
        if op in (OP_DATA_END, OP_FOOTER):
            if buf[size - len(MAGIC):] != MAGIC:  # the data are whole; the summary after them was cut
                found.stopped_at = found.stopped_at or f"cut at byte {size}, after the data"
            return
    if pos < size and not found.stopped_at:
        found.stopped_at = f"cut at byte {size}"


def _record_at(buf: mmap.mmap, pos: int, found: Salvage) -> tuple[int, int] | None:
    """Parse the record at ``pos`` into ``found``; (opcode, end) or None when it does not parse (or a chunk's CRC
    is wrong: counted as a bad chunk)."""
    op, length = RECORD_HEAD.unpack_from(buf, pos)
    end = pos + 9 + length
    if not 0 < op <= OP_MAX or end > len(buf):
        return None
    try:
        # One record on its own: the reader raises at the end of the slice after it, so only the first is taken.
        records = [next(iter(StreamReader(io.BytesIO(buf[pos:end]), skip_magic=True, emit_chunks=True,
                                          validate_crcs=True, record_size_limit=length + 9).records))]
    except Exception:  # whatever a damaged record makes the parser raise
        if op == OP_CHUNK:
            found.chunks_bad += 1
        return None
    for record in records:
        if isinstance(record, Chunk):
            try:
                inner = breakup_chunk(record, validate_crc=True)
            except Exception:
                found.chunks_bad += 1
                return None
            found.chunks_ok += 1
            for r in inner:
                _keep(found, r)
        else:
            _keep(found, record)
    return op, end


def _next_chunk(buf: mmap.mmap, start: int) -> int | None:
    """The offset of the next chunk record that parses with its CRC right, from ``start`` on."""
    tries = 0
    pos = buf.find(bytes([OP_CHUNK]), start)
    while pos >= 0 and pos + 9 + CHUNK_HEAD.size <= len(buf) and tries < RESYNC_LIMIT:
        _, length = RECORD_HEAD.unpack_from(buf, pos)
        if pos + 9 + length <= len(buf) and length >= CHUNK_HEAD.size + 12 and \
                _chunk_lengths_agree(buf, pos, length):
            tries += 1
            probe = Salvage()
            if _record_at(buf, pos, probe) is not None:
                return pos
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


def recover(path: str | os.PathLike[str], out: str | os.PathLike[str] | None = None,
            compression: str = "zstd") -> RecoveryReport:
    """Rewrite what survives of ``path`` into a finished file (``out``, or in place)."""
    src = Path(path)
    found = walk(src)
    dst = Path(out) if out is not None else src
    tmp = dst.with_name(dst.name + ".recovering")
    try:
        orphans = _rewrite(found, src, tmp, compression)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a full disk: the source is untouched, and no half copy takes its space
        raise
    os.replace(tmp, dst)
    _fsync_dir(dst.parent)
    return RecoveryReport(dst, len(found.messages) - orphans, found.chunks_ok, found.chunks_bad, orphans,
                          found.stopped_at)


def _rewrite(found: Salvage, src: Path, tmp: Path, compression: str) -> int:
    """Write what the walk found into ``tmp`` as a finished file; returns the messages without a channel."""
    orphans = 0
    with open(tmp, "wb") as f:
        writer = McapWriter(f, compression=compression, chunk_size=4 * 1024 * 1024)
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
        for msg in found.messages:
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
