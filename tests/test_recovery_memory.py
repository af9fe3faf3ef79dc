"""Recovery's memory does not grow with the file: its walk keeps where the good chunks lie, not their messages,
and the copy reads them again one chunk at a time.

An hour's cut file at 500 Hz (178 MB, 2 million messages) took 1.2 GB to recover when the walk kept every
message: an out-of-memory kill at every start on the 512 MB board. The files here are small and built with the
project's own writer; what is measured is the growth of Python's allocations (tracemalloc) between a file and one
four times its size, which does not depend on the machine's speed.
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import pytest
from mcap.reader import make_reader

import logger.recording.files as files
from logger.recording.files import CHANNEL_TABLE, RecoveryCancelled, is_finished, recover, walk
from logger.recording.mcap_writer import McapWriter

PER_CHUNK = 50
T0 = 1_700_000_000_000_000_000


def cut_file(path: Path, messages: int) -> list[tuple[str, int, int, int, bytes]]:
    """A recorder-like file of ``messages`` (a multiple of PER_CHUNK) in chunks of PER_CHUNK, two topics, the
    channel table outside the chunks, cut short in one more chunk; returns (topic, log time, publish time,
    sequence, data) of every message before the cut."""
    written = []
    with open(path, "wb") as f:
        w = McapWriter(f, compression="zstd")
        w.start(profile="", library="vehicle-logger")
        sid = w.register_schema("test", "jsonschema", b"{}")
        chans = {t: w.register_channel(t, "json", sid, {}) for t in ("/a", "/b")}
        w.add_metadata(CHANNEL_TABLE, {str(cid): t for t, cid in chans.items()})
        for k in range(messages + PER_CHUNK // 2):
            if k == messages:
                kept, written = written, []
                whole = f.tell()
            topic = "/a" if k % 3 else "/b"
            data = b'{"k": %d, "pad": "%s"}' % (k, b"x" * (60 + k % 50))
            w.add_message(chans[topic], T0 + k * 1_000_000, data, T0 + k * 1_000_000 + 7, k)
            written.append((topic, T0 + k * 1_000_000, T0 + k * 1_000_000 + 7, k, data))
            if (k + 1) % PER_CHUNK == 0:
                w.flush()
        w.flush()
    with open(path, "r+b") as f:  # the power goes in the middle of the last chunk
        f.truncate(whole + 100)
    return kept


def read_back(path: Path) -> list[tuple[str, int, int, int, bytes]]:
    with open(path, "rb") as f:
        return [(ch.topic, m.log_time, m.publish_time, m.sequence, m.data)
                for _, ch, m in make_reader(f).iter_messages(log_time_order=False)]


def peak_of_recovery(src: Path, out: Path) -> int:
    tracemalloc.start()
    try:
        recover(src, out)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_recovery_memory_does_not_grow_with_the_messages(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The copy's chunks small (4 MB by default, more than these files hold): what remains is what grows.
    monkeypatch.setattr(files, "RECOVERY_CHUNK_BYTES", 64 * 1024)
    small, large = tmp_path / "small.mcap", tmp_path / "large.mcap"
    cut_file(small, 4_000)
    kept = cut_file(large, 16_000)
    peak_small = peak_of_recovery(small, tmp_path / "small.rec.mcap")
    peak_large = peak_of_recovery(large, tmp_path / "large.rec.mcap")
    # 12,000 more messages of ~100 bytes: 1.2 MB of data alone, some 4 MB as message objects. Only the walk's few
    # bytes a chunk (240 more chunks) may grow.
    assert peak_large - peak_small < 300_000, (peak_small, peak_large)
    assert read_back(tmp_path / "large.rec.mcap") == kept  # every flushed message, in order, as written


def test_the_recovery_walk_counts_the_messages_and_keeps_none(tmp_path: Path) -> None:
    p = tmp_path / "cut.mcap"
    kept = cut_file(p, 1_000)
    lean = walk(p, keep_messages=False)
    full = walk(p)
    assert lean.messages == [] and lean.message_count == len(full.messages) == len(kept)
    assert lean.losses == full.losses and lean.chunks_ok == full.chunks_ok and lean.stopped_at == full.stopped_at
    # The copy from the source chunk by chunk is the copy of the kept messages, byte for byte.
    report = recover(p, tmp_path / "lean.mcap", found=lean)
    recover(p, tmp_path / "full.mcap", found=full)
    assert (tmp_path / "lean.mcap").read_bytes() == (tmp_path / "full.mcap").read_bytes()
    assert report.messages == len(kept) and read_back(tmp_path / "lean.mcap") == kept


def test_an_orphan_is_counted_without_its_message_being_kept(tmp_path: Path) -> None:
    """A message whose channel nothing names (no channel record, no table entry) is dropped and counted, as when
    the walk kept the messages."""
    p = tmp_path / "orphan.mcap"
    with open(p, "wb") as f:
        w = McapWriter(f, compression="zstd")
        w.start(profile="", library="vehicle-logger")
        sid = w.register_schema("test", "jsonschema", b"{}")
        a = w.register_channel("/a", "json", sid, {})
        for k in range(10):
            w.add_message(a, T0 + k, b"{}", T0 + k)
            w.add_message(a + 1, T0 + k, b"{}", T0 + k)  # a channel never registered
        w.flush()
    report = recover(p, tmp_path / "out.mcap")
    assert (report.messages, report.dropped_orphans) == (10, 10)


def test_a_cancelled_recovery_leaves_the_file_as_it_was(tmp_path: Path) -> None:
    p = tmp_path / "cut.mcap"
    cut_file(p, 2_000)
    before = p.read_bytes()
    asked = [0]

    def cancel() -> bool:
        asked[0] += 1
        return asked[0] > 3  # during the copy, after a few chunks

    with pytest.raises(RecoveryCancelled):
        recover(p, cancel=cancel)
    assert p.read_bytes() == before and not is_finished(p)
    assert not list(tmp_path.glob("*.recovering"))
    recover(p)  # and the next time it goes through
    assert is_finished(p)
