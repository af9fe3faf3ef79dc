"""The recorder's MCAP writer: the records of the MCAP specification, an index that stays small for hours.

mcap's own ``Writer`` keeps, until its file is finished, a ``ChunkIndex`` object for every chunk with a dict of
per-channel offsets: about 1.3 KB a chunk, 4.5 MB by the end of an hour's file at the recorder's chunk a second
(``flush_interval_s``) on a board with 512 MB and a daemon budget of 50 MB; and ``mcap.writer`` imports
``importlib.metadata`` (with email, zipfile, csv: 1.4 MB more in the daemon's imports, unless python-can's CAN
interfaces load it anyway) to name its own version. This writer writes the same records (https://mcap.dev/spec,
version 0: header, schema and channel records in the chunk open when they are registered, chunks with their
CRC, a message index per channel after each chunk, metadata outside the chunks, and a summary with schemas,
channels, statistics, chunk and metadata indexes, summary offsets and the footer's CRC) and keeps each chunk's
index as the bytes of its ChunkIndex record, about 0.2 KB. For the same calls its file is byte for byte the one
mcap's Writer writes (tests/test_mcap_writer.py), read by mcap's reader, ``@mcap/core`` and Foxglove like any
other.

Compression is imported only for the codec asked for. The offsets are counted, not asked of the stream, so the
writer starts wherever the stream stands and costs no ``lseek`` a record; the stream must take every write whole
(a file opened in buffered mode, as the recorder's is; a raw stream's short writes are not retried).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable, Mapping
from typing import BinaryIO

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
OP_CHUNK, OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_ATTACHMENT_INDEX = 0x06, 0x07, 0x08, 0x0A
OP_STATISTICS, OP_METADATA, OP_METADATA_INDEX, OP_SUMMARY_OFFSET, OP_DATA_END = 0x0B, 0x0C, 0x0D, 0x0E, 0x0F

COMPRESSIONS = ("zstd", "lz4", "none")  # the recorder's configuration words; "none" is "" in a chunk record
DEFAULT_CHUNK_SIZE = 1024 * 1024  # uncompressed bytes that close a chunk (mcap's Writer's default)

# Layouts the readers share (files.py's walk, drive.py's reader).
RECORD_HEAD = struct.Struct("<BQ")  # opcode, length of the record's body
CHUNK_HEAD = struct.Struct("<QQQI")  # a chunk's message start, message end, uncompressed size, uncompressed CRC
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel id, sequence, log time, publish time
_MESSAGE_FIXED = 2 + 4 + 8 + 8
_MESSAGE_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, length, channel id, length of the entries
_INDEX_ENTRY = struct.Struct("<QQ")  # log time, offset of the message in the chunk's records
_CHANNEL_U64 = struct.Struct("<HQ")  # channel id and an offset (chunk index) or a count (statistics)
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


def _compressor(name: str) -> tuple[str, Callable[[bytes], bytes]]:
    """The chunk record's compression name and its function, for a configuration word."""
    if name == "zstd":
        import zstandard

        return "zstd", zstandard.compress
    if name == "lz4":
        import lz4.frame

        return "lz4", lz4.frame.compress
    if name == "none":
        return "", bytes
    raise ValueError(f"MCAP compression must be one of {', '.join(COMPRESSIONS)}, not {name!r}")


def _string(value: str) -> bytes:
    data = value.encode()
    return _U32.pack(len(data)) + data


def _string_map(values: Mapping[str, str]) -> bytes:
    body = b"".join(_string(k) + _string(v) for k, v in values.items())
    return _U32.pack(len(body)) + body


def _record(opcode: int, body: bytes) -> bytes:
    return RECORD_HEAD.pack(opcode, len(body)) + body


class McapWriter:
    """Writes one MCAP file into ``stream`` (opened for binary writing; the caller closes it).

    The same calls as mcap's ``Writer`` for what the logger uses: ``start``, ``register_schema``,
    ``register_channel``, ``add_message``, ``add_metadata``, ``flush`` (closes the open chunk and hands the bytes to
    the stream, which the caller fsyncs) and ``finish`` (the summary and footer).
    """

    def __init__(self, stream: BinaryIO, *, chunk_size: int = DEFAULT_CHUNK_SIZE, compression: str = "zstd") -> None:
        self._compression, self._compress = _compressor(compression)
        self._stream = stream
        self._chunk_size = chunk_size
        self._pos = 0  # the stream's offset of the next byte written
        # The open chunk: its records, their count, times and per-channel message index entries.
        self._chunk = bytearray()
        self._chunk_messages = 0
        self._chunk_start_ns = 0
        self._chunk_end_ns = 0
        self._message_index: dict[int, bytearray] = {}
        # The summary, kept as the records it will hold.
        self._schemas: list[bytes] = []
        self._channels: list[bytes] = []
        self._chunk_indexes = bytearray()
        self._metadata_indexes = bytearray()
        self._channel_counts: dict[int, int] = {}
        self._start_ns: int | None = None
        self._end_ns = 0
        self._chunk_count = 0
        self._metadata_count = 0

    # ---- the data section ---------------------------------------------------------------------------------
    def start(self, profile: str, library: str) -> None:
        self._pos = self._stream.tell()
        self._write(MAGIC + _record(OP_HEADER, _string(profile) + _string(library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = len(self._schemas) + 1
        record = _record(OP_SCHEMA, struct.pack("<H", schema_id) + _string(name) + _string(encoding)
                         + _U32.pack(len(data)) + data)
        self._schemas.append(record)
        self._add_to_chunk(record)
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: Mapping[str, str] | None = None) -> int:
        channel_id = len(self._channels) + 1
        record = _record(OP_CHANNEL, struct.pack("<HH", channel_id, schema_id) + _string(topic)
                         + _string(message_encoding) + _string_map(metadata or {}))
        self._channels.append(record)
        self._add_to_chunk(record)
        return channel_id

    def _add_to_chunk(self, record: bytes) -> None:
        self._chunk += record
        if len(self._chunk) > self._chunk_size:
            self._close_chunk()

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        chunk = self._chunk
        head = _MESSAGE_HEAD.pack(OP_MESSAGE, _MESSAGE_FIXED + len(data), channel_id, sequence, log_time,
                                  publish_time)  # first: a value out of range leaves nothing half added
        entries = self._message_index.get(channel_id)
        if entries is None:
            entries = self._message_index[channel_id] = bytearray()
        entries += _INDEX_ENTRY.pack(log_time, len(chunk))
        chunk += head
        chunk += data
        if self._chunk_messages:
            if log_time < self._chunk_start_ns:
                self._chunk_start_ns = log_time
            elif log_time > self._chunk_end_ns:
                self._chunk_end_ns = log_time
        else:
            self._chunk_start_ns = self._chunk_end_ns = log_time
        self._chunk_messages += 1
        self._channel_counts[channel_id] = self._channel_counts.get(channel_id, 0) + 1
        if len(chunk) > self._chunk_size:
            self._close_chunk()

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """A metadata record between chunks (the open chunk stays open), indexed in the summary."""
        record = _record(OP_METADATA, _string(name) + _string_map(data))
        self._metadata_indexes += _record(OP_METADATA_INDEX, struct.pack("<QQ", self._pos, len(record)) + _string(name))
        self._metadata_count += 1
        self._write(record)

    def flush(self) -> None:
        """Close the open chunk (if it holds a message) and hand everything to the stream; fsync is the caller's."""
        self._close_chunk()
        self._stream.flush()

    def _close_chunk(self) -> None:
        if not self._chunk_messages:
            return  # schema and channel records wait for the chunk of their first message, as in mcap's Writer
        raw = bytes(self._chunk)
        packed = self._compress(raw)
        start_ns, end_ns = self._chunk_start_ns, self._chunk_end_ns
        head = (CHUNK_HEAD.pack(start_ns, end_ns, len(raw), zlib.crc32(raw)) + _string(self._compression)
                + _U64.pack(len(packed)))
        chunk_record = RECORD_HEAD.pack(OP_CHUNK, len(head) + len(packed)) + head
        chunk_offset = self._pos
        chunk_length = len(chunk_record) + len(packed)
        index_offset = pos = chunk_offset + chunk_length
        offsets = bytearray()
        indexes = []
        for channel_id, entries in self._message_index.items():
            record = _MESSAGE_INDEX_HEAD.pack(OP_MESSAGE_INDEX, 6 + len(entries), channel_id, len(entries)) + entries
            offsets += _CHANNEL_U64.pack(channel_id, pos)
            indexes.append(record)
            pos += len(record)
        self._write(b"".join((chunk_record, packed, *indexes)))
        self._chunk_indexes += _record(OP_CHUNK_INDEX, struct.pack("<QQQQ", start_ns, end_ns, chunk_offset,
                                                                   chunk_length)
                                       + _U32.pack(len(offsets)) + offsets + _U64.pack(pos - index_offset)
                                       + _string(self._compression) + struct.pack("<QQ", len(packed), len(raw)))
        if self._start_ns is None or start_ns < self._start_ns:
            self._start_ns = start_ns
        self._end_ns = max(self._end_ns, end_ns)
        self._chunk_count += 1
        self._chunk = bytearray()
        self._chunk_messages = 0
        self._message_index = {}

    def _write(self, data: bytes) -> None:
        self._stream.write(data)
        self._pos += len(data)

    # ---- the summary --------------------------------------------------------------------------------------
    def finish(self) -> None:
        """Close the open chunk, end the data section and write the summary and footer (the stream stays open and
        unflushed: its owner flushes and fsyncs, or closes it). The summary is written group by group, so finishing
        needs little more memory than the index holds."""
        self._close_chunk()
        self._write(_record(OP_DATA_END, _U32.pack(0)))  # no data section CRC, as mcap's Writer by default
        summary_start = self._pos
        # mcap's Writer's groups in its order, an empty one (attachments: the logger writes none) included, so
        # that the two writers' files are the same bytes (tests/test_mcap_writer.py). Each group goes to the
        # stream as it is (the chunk index, the one that grows, without a copy) and the CRC runs along.
        groups: list[tuple[int, bytes | bytearray]] = [
            (OP_SCHEMA, b"".join(self._schemas)),
            (OP_CHANNEL, b"".join(self._channels)),
            (OP_STATISTICS, self._statistics()),
            (OP_CHUNK_INDEX, self._chunk_indexes),
            (OP_ATTACHMENT_INDEX, b""),
            (OP_METADATA_INDEX, self._metadata_indexes),
        ]
        crc = 0
        offsets = bytearray()
        for opcode, group in groups:
            offsets += _record(OP_SUMMARY_OFFSET, struct.pack("<BQQ", opcode, self._pos, len(group)))
            crc = zlib.crc32(group, crc)
            self._write(group)
        footer_head = struct.pack("<BQQQ", OP_FOOTER, 8 + 8 + 4, summary_start, self._pos)
        crc = zlib.crc32(footer_head, zlib.crc32(offsets, crc))
        self._write(bytes(offsets) + footer_head + _U32.pack(crc) + MAGIC)

    def _statistics(self) -> bytes:
        counts = b"".join(_CHANNEL_U64.pack(cid, n) for cid, n in self._channel_counts.items())
        return _record(OP_STATISTICS, struct.pack(
            "<QHIIIIQQ", sum(self._channel_counts.values()), len(self._schemas), len(self._channels), 0,
            self._metadata_count, self._chunk_count, self._start_ns or 0, self._end_ns)
            + _U32.pack(len(counts)) + counts)
