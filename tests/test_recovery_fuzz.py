"""Recovery after damage keeps every chunk that is intact: cuts, flipped bytes and zeroed pages, at random places.

A file written by the real recorder (many small chunks, the channel table written after every flush) is damaged
in a copy; the chunks whose bytes the damage did not touch are known from the original's chunk index, and every
message they hold must come out of ``recover`` under its own topic, whatever came before them.
"""

from __future__ import annotations

import io
import random
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader, breakup_chunk

import logger.recording.recorder as recorder_module
from logger.recording.files import MAGIC, McapFileError, is_finished, recover, walk
from logger.recording.recorder import Recorder
from logger.recording.settings import RecorderSettings
from logger.recording.topics import TopicSpec

TOPICS = {t: TopicSpec(t, f"test{t.replace('/', '.')}", {"type": "object"}, "test") for t in ("/a", "/b")}
PAGE = 4096


@pytest.fixture(scope="module")
def original(tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, list[tuple[int, int, set]]]:
    """A finished file of about 40 chunks, and per chunk (start offset, length, {(topic, log time)})."""
    folder = tmp_path_factory.mktemp("fuzz")
    mp = pytest.MonkeyPatch()
    mp.setattr(recorder_module, "CHANNEL_TABLE_S", 0.0)  # the table after every flush: some copy always survives
    try:
        rec = Recorder(RecorderSettings(out_dir=folder, flush_interval_s=0.01), TOPICS)
        path = rec.start()
        for burst in range(40):
            for i in range(30):
                k = burst * 30 + i
                rec.submit("/a" if k % 3 else "/b", {"x": k, "pad": "." * 40}, 1_700_000_000_000_000_000 + k, k)
            deadline = time.monotonic() + 5
            while rec.status().on_disk_mono_ns.get("/a", -1) < k - 2 and time.monotonic() < deadline:
                time.sleep(0.005)
        rec.stop()
    finally:
        mp.undo()
    assert path is not None and is_finished(path)
    data = path.read_bytes()
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {cid: ch.topic for cid, ch in summary.channels.items()}
        chunks = []
        for ci in summary.chunk_indexes:
            raw = data[ci.chunk_start_offset:ci.chunk_start_offset + ci.chunk_length]
            chunk = next(iter(StreamReader(io.BytesIO(raw), skip_magic=True, emit_chunks=True).records))
            msgs = {(topics[r.channel_id], r.log_time) for r in breakup_chunk(chunk) if isinstance(r, Message)}
            chunks.append((ci.chunk_start_offset, ci.chunk_length, msgs))
    assert len(chunks) >= 20 and sum(len(m) for *_, m in chunks) == 1200
    return data, chunks


def _recovered(path: Path) -> set[tuple[str, int]]:
    recover(path)
    with open(path, "rb") as f:
        return {(ch.topic, m.log_time) for _, ch, m in make_reader(f).iter_messages()}


def _intact(chunks: list[tuple[int, int, set]], lo: int, hi: int) -> set[tuple[str, int]]:
    """Messages of the chunks that lie wholly outside the damaged bytes [lo, hi)."""
    return set().union(*(m for start, length, m in chunks if start + length <= lo or start >= hi))


def test_flipped_bytes_lose_only_the_chunk_they_hit(original, tmp_path: Path) -> None:
    data, chunks = original
    rng = random.Random(7)
    for trial in range(40):
        at = rng.randrange(len(MAGIC), len(data))
        damaged = bytearray(data)
        damaged[at] ^= 1 << rng.randrange(8)
        p = tmp_path / f"flip{trial}.mcap"
        p.write_bytes(damaged)
        expected = _intact(chunks, at, at + 1)
        got = _recovered(p)
        assert expected <= got, (at, len(expected - got))
        assert is_finished(p)


def test_zeroed_pages_lose_only_the_chunks_in_them_even_the_first_page(original, tmp_path: Path) -> None:
    data, chunks = original
    rng = random.Random(11)
    for trial, page in enumerate([0, *rng.sample(range(1, len(data) // PAGE), 8)]):
        lo, hi = page * PAGE, min(len(data), (page + 1) * PAGE)
        damaged = bytearray(data)
        damaged[lo:hi] = bytes(hi - lo)
        p = tmp_path / f"zero{trial}.mcap"
        p.write_bytes(damaged)
        expected = _intact(chunks, lo, hi)
        got = _recovered(p)
        assert expected <= got, (page, len(expected - got))


def test_a_cut_keeps_every_chunk_before_it(original, tmp_path: Path) -> None:
    data, chunks = original
    rng = random.Random(3)
    for trial in range(15):
        cut = rng.randrange(PAGE, len(data))
        p = tmp_path / f"cut{trial}.mcap"
        p.write_bytes(data[:cut])
        found = walk(p)
        assert found.stopped_at.startswith("cut at byte"), found.stopped_at
        expected = _intact(chunks, cut, len(data) + 1)
        assert expected <= _recovered(p), cut


def test_a_file_with_nothing_readable_is_still_not_an_mcap_file(tmp_path: Path) -> None:
    p = tmp_path / "noise.mcap"
    p.write_bytes(random.Random(1).randbytes(20_000))
    with pytest.raises(McapFileError, match="not an MCAP file"):
        walk(p)


@pytest.fixture
def small_disk(tmp_path: Path):
    """A 1 MiB tmpfs of its own (root only, as CI and the board's service run): a disk this test can fill."""
    import os
    import subprocess

    if os.geteuid() != 0:
        pytest.skip("needs root to mount a tmpfs")
    mnt = tmp_path / "disk"
    mnt.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], check=True)
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def test_the_next_start_on_a_full_disk_keeps_the_cut_file_and_says_why(original, small_disk: Path) -> None:
    import os

    from logger.runtime.daemon import recover_unfinished

    data, chunks = original
    cut_at = chunks[len(chunks) // 2][0] + 10  # halfway, mid-chunk
    cut = small_disk / "drive_20261202T000000Z_0001.mcap"
    cut.write_bytes(data[:cut_at])
    filler = small_disk / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)  # another program fills the disk
    try:
        while os.write(fd, b"\0" * 4096):
            pass
    except OSError:
        pass
    finally:
        os.close(fd)
    (line,) = recover_unfinished(small_disk)
    assert line.startswith(f"could not recover {cut.name}: no space left on the disk"), line
    assert cut.read_bytes() == data[:cut_at]  # untouched, and no half copy left to take the space
    assert not list(small_disk.glob("*.recovering"))
    filler.unlink()  # room again: the next start recovers it
    (line,) = recover_unfinished(small_disk)
    assert line.startswith(f"recovered {cut.name}"), line
    assert "cut at byte" in line  # what was lost said, as `logger recover` says it (a bad-chunk count before)
    with open(cut, "rb") as f:
        kept = {(ch.topic, m.log_time) for _, ch, m in make_reader(f).iter_messages()}
    assert _intact(chunks, cut_at, len(data) + 1) <= kept
