"""The recorder's MCAP writer against mcap's own Writer: the same calls give the same file, byte for byte.

mcap's Writer is the specification's Python implementation that the readers (mcap's, ``@mcap/core``, Foxglove) are
tested against; a file equal to its file is read as its file is. The calls are drawn at random (hypothesis):
schemas and channels registered between messages, messages of any size and time order, metadata, flushes, chunk
sizes small enough that chunks close on size as well as on flush, every compression.
"""

from __future__ import annotations

import io
import json
import tracemalloc
from typing import Any

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from logger.recording.mcap_writer import COMPRESSIONS, McapWriter

# Any text UTF-8 can hold: text()'s own alphabet leaves out the surrogates (as Debian 12's Hypothesis 6.67 has it,
# which knows no characters(codec=...): the board's suite stopped while collecting this file).
_text = st.text(max_size=12)
_op = st.one_of(
    st.tuples(st.just("schema"), _text, st.binary(max_size=40)),
    st.tuples(st.just("channel"), _text, st.dictionaries(_text, _text, max_size=3)),
    st.tuples(st.just("message"), st.integers(0, 7), st.integers(0, 2**63), st.binary(max_size=300),
              st.integers(0, 2**32 - 1)),
    st.tuples(st.just("metadata"), _text, st.dictionaries(_text, _text, max_size=3)),
    st.tuples(st.just("flush")),
)


def _play(writer: Any, ops: list[tuple[Any, ...]], library: str) -> None:
    writer.start(profile="test", library=library)
    schemas = channels = 0
    for op in ops:
        if op[0] == "schema":
            schemas = writer.register_schema(op[1], "jsonschema", op[2])
        elif op[0] == "channel":
            channels = writer.register_channel(f"/t{op[1]}", "json", schemas, op[2])
        elif op[0] == "message":
            _, k, log_ns, data, seq = op  # k past the channels registered: an id the file never declares
            writer.add_message(1 + k % (channels + 2), log_ns, data, log_ns // 2, seq)
        elif op[0] == "metadata":
            writer.add_metadata(op[1], op[2])
        elif op[0] == "flush":
            writer.flush()
    writer.finish()


def _files(ops: list[tuple[Any, ...]], chunk_size: int, compression: str, before: bytes = b"",
           library: str = "same") -> tuple[bytes, bytes]:
    """Both writers' files, each written after ``before`` in its stream (offsets count from the stream's start)."""
    ours, theirs = io.BytesIO(before), io.BytesIO(before)
    ours.seek(0, io.SEEK_END)
    theirs.seek(0, io.SEEK_END)
    _play(McapWriter(ours, chunk_size=chunk_size, compression=compression), ops, library)
    _play(Writer(theirs, chunk_size=chunk_size, compression=CompressionType[compression.upper()]), ops, library)
    return ours.getvalue(), theirs.getvalue()


@settings(max_examples=150, deadline=None)
@given(ops=st.lists(_op, max_size=60), chunk_size=st.sampled_from([1, 200, 1000, 1 << 20]),
       compression=st.sampled_from(COMPRESSIONS), before=st.binary(max_size=20), library=_text)
# A channel registered while a chunk holds messages, taking it over its size: it closes there, as in mcap's Writer.
@example(ops=[("schema", "s", b""), ("channel", "a", {}), ("message", 0, 5, b"x" * 100, 0),
              ("channel", "b" * 12, {"k" * 12: "v" * 12}), ("message", 1, 6, b"y", 0)], chunk_size=200,
         compression="none", before=b"", library="same")
def test_the_same_calls_write_the_same_file_as_mcaps_writer(ops: list[tuple[Any, ...]], chunk_size: int,
                                                            compression: str, before: bytes, library: str) -> None:
    ours, theirs = _files(ops, chunk_size, compression, before, library)
    assert ours == theirs


def test_a_recorders_hour_in_small_reads_back_with_its_index() -> None:
    """A file of many flushed chunks on several channels: mcap's reader checks every CRC, finds each message by its
    topic through the indexes, and the statistics count what was written."""
    buf = io.BytesIO()
    w = McapWriter(buf)
    w.start("", "test")
    sid = w.register_schema("s", "jsonschema", b'{"type": "object"}')
    ids = [w.register_channel(f"/c{i}", "json", sid, {"description": f"channel {i}"}) for i in range(1, 5)]
    for second in range(300):
        for i in ids[: 1 + second % 4]:
            t = 10**18 + second * 10**9 + i
            w.add_message(i, t, json.dumps({"s": second, "c": i}).encode(), t)
        w.flush()
        if second % 60 == 0:
            w.add_metadata("table", {str(i): f"/c{i}" for i in ids})
    w.finish()
    reader = make_reader(io.BytesIO(buf.getvalue()), validate_crcs=True)
    summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.chunk_count == len(summary.chunk_indexes) == 300
    assert summary.statistics.message_count == 75 * (1 + 2 + 3 + 4)
    assert [m.name for m in reader.iter_metadata()] == ["table"] * 5
    got = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/c4"])]
    assert [g["s"] for g in got] == [s for s in range(300) if s % 4 == 3]
    assert all(g["c"] == 4 for g in got)


def test_its_index_stays_small_over_an_hours_chunks() -> None:
    """What the writer keeps per chunk until the file is finished: the bytes of one ChunkIndex record (about 200 B
    for eleven channels), where mcap's Writer keeps objects of about 1.3 KB; an hour of one chunk a second is then
    under a megabyte."""
    sink = io.BytesIO()
    w = McapWriter(sink, compression="none")
    w.start("", "test")
    sid = w.register_schema("s", "jsonschema", b"{}")
    ids = [w.register_channel(f"/c{i}", "json", sid) for i in range(11)]
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        for second in range(1000):
            for i in ids:
                w.add_message(i, second * 10**9 + i, b"{}", 0)
            w.flush()
            sink.seek(0)
            sink.truncate()  # the file's bytes are the disk's, not the writer's
        held = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert held / 1000 * 3600 < 1 << 20


def test_finishing_needs_little_more_than_the_index() -> None:
    """The summary goes out group by group: finishing an hour's file does not copy its index several times over
    (a peak at every rotation)."""
    class Disk(io.RawIOBase):
        """A file whose bytes go to the disk, not to this process's memory."""

        def __init__(self) -> None:
            self.size = 0

        def write(self, data: Any) -> int:
            self.size += len(data)
            return len(data)

        def tell(self) -> int:
            return self.size

    disk = Disk()
    w = McapWriter(disk, compression="none")  # type: ignore[arg-type]
    w.start("", "test")
    sid = w.register_schema("s", "jsonschema", b"{}")
    ids = [w.register_channel(f"/c{i}", "json", sid) for i in range(11)]
    for second in range(3600):
        for i in ids:
            w.add_message(i, second * 10**9 + i, b"{}", 0)
        w.flush()
    index = disk.size
    tracemalloc.start()
    try:
        w.finish()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    index = disk.size - index  # the summary: the chunk index and a few records
    assert index > 600_000 and peak < index / 4, (peak, index)


def test_an_unknown_compression_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"zstd, lz4, none.*'brotli'"):
        McapWriter(io.BytesIO(), compression="brotli")
