"""Reading, checking and recovering the logger's MCAP files.

A file is *finished* when it ends with the footer and the closing magic that ``Writer.finish()`` writes. An
unfinished file (power cut, ``kill -9``, full disk) still holds every chunk that was flushed before the cut; the
index-based readers see nothing in it, so recovery walks the records from the start, keeps every chunk whose CRC
checks out, and writes them again into a finished, indexed file. Recovery writes beside the original and
renames over it only once the copy is complete and synced, so a crash during recovery loses nothing either.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

MAGIC = b"\x89MCAP0\r\n"
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
    return tail[-len(MAGIC):] == MAGIC and tail[0] == 0x02  # 0x02: footer opcode


@dataclass
class Salvage:
    """What a record walk of a possibly truncated file found."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    metadata: list[Metadata] = field(default_factory=list)
    chunks_ok: int = 0
    chunks_bad: int = 0
    stopped_at: str = ""  # why the walk ended early, empty if it reached the footer
    profile: str = ""


def walk(path: str | os.PathLike[str]) -> Salvage:
    """Collect every complete, CRC-valid record of a file, stopping at the first cut or corruption."""
    found = Salvage()
    try:
        size = os.path.getsize(path)
        f = open(path, "rb")  # noqa: SIM115 - closed in finally, the generator below needs it open
    except OSError as exc:
        raise McapFileError(f"{path}: cannot open ({exc.strerror or exc})") from exc
    try:
        head = f.read(len(MAGIC))
        if head != MAGIC:
            raise McapFileError(f"{path}: not an MCAP file (no MCAP magic at the start)")
        f.seek(0)
        reader = StreamReader(f, emit_chunks=True, validate_crcs=False, record_size_limit=max(size, 1))
        for record in _records_until_cut(reader, found):
            if isinstance(record, Chunk):
                try:
                    inner = breakup_chunk(record, validate_crc=True)
                except Exception:
                    found.chunks_bad += 1
                    continue
                found.chunks_ok += 1
                for r in inner:
                    _keep(found, r)
            else:
                _keep(found, record)
    finally:
        f.close()
    return found


def _records_until_cut(reader: StreamReader, found: Salvage) -> Iterator[object]:
    it = iter(reader.records)
    while True:
        try:
            record = next(it)
        except StopIteration:
            return
        except (EOFError, struct.error, ValueError, MemoryError, Exception) as exc:
            found.stopped_at = f"{type(exc).__name__}: {exc}"[:200]
            return
        yield record


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


@dataclass(frozen=True)
class RecoveryReport:
    path: Path
    messages: int
    chunks_ok: int
    chunks_bad: int
    dropped_orphans: int  # messages whose channel record was lost with the cut
    reason: str


def recover(path: str | os.PathLike[str], out: str | os.PathLike[str] | None = None,
            compression: CompressionType = CompressionType.ZSTD) -> RecoveryReport:
    """Rewrite what survives of ``path`` into a finished file (``out``, or in place)."""
    src = Path(path)
    found = walk(src)
    dst = Path(out) if out is not None else src
    tmp = dst.with_name(dst.name + ".recovering")
    orphans = 0
    with open(tmp, "wb") as f:
        writer = Writer(f, compression=compression, chunk_size=4 * 1024 * 1024)
        writer.start(profile=found.profile)
        schema_ids: dict[int, int] = {}
        for sid, schema in sorted(found.schemas.items()):
            schema_ids[sid] = writer.register_schema(schema.name, schema.encoding, schema.data)
        channel_ids: dict[int, int] = {}
        for cid, ch in sorted(found.channels.items()):
            channel_ids[cid] = writer.register_channel(ch.topic, ch.message_encoding,
                                                       schema_ids.get(ch.schema_id, 0), dict(ch.metadata))
        for m in found.metadata:
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
    os.replace(tmp, dst)
    _fsync_dir(dst.parent)
    return RecoveryReport(dst, len(found.messages) - orphans, found.chunks_ok, found.chunks_bad, orphans,
                          found.stopped_at)


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
