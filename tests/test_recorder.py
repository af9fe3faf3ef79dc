"""The recorder: flush cadence, a cut file recovered, drops counted, disk-full handled."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from logger.recording.files import is_finished, recover, walk
from logger.recording.recorder import Recorder
from logger.recording.settings import RecorderSettings
from logger.recording.topics import TopicSpec
from logger.runtime.sampler import wait_until

TOPICS = {"/a": TopicSpec("/a", "test.A", {"type": "object", "properties": {"x": {"type": "integer"}}}, "test")}


class FsyncFails:
    """The ``os`` module as the recorder sees it, with every fsync failing (a dying card, a full disk)."""

    def __init__(self, code: int, text: str) -> None:
        self._error = (code, text)

    def __getattr__(self, name: str):
        return getattr(os, name)

    def fsync(self, fd: int) -> None:
        raise OSError(*self._error)


def _read_all(path: Path) -> list[tuple[str, int]]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        return [(ch.topic, m.log_time) for _, ch, m in reader.iter_messages()]


def test_clean_stop_leaves_a_finished_indexed_file(tmp_path: Path) -> None:
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS)
    path = rec.start()
    for i in range(500):
        assert rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, i)
    rec.stop()
    assert path is not None and is_finished(path)
    got = _read_all(path)
    assert len(got) == 500
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count == 500
    assert rec.status().state == "stopped"


def test_a_cut_file_keeps_what_was_flushed_and_is_recovered(tmp_path: Path) -> None:
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.02), TOPICS)
    path = rec.start()
    assert path is not None
    for i in range(200):
        rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, i)
    # Simulate kill -9: copy the bytes as they are on disk, while the writer still holds the file open, once a
    # copy holds every message in closed chunks (the writer flushes every 0.02 s, but a loaded host may run it late;
    # a writer that never flushes fails at the deadline).
    cut = tmp_path / "cut.mcap"
    deadline = time.monotonic() + 5
    while True:
        cut.write_bytes(path.read_bytes())
        if len(walk(cut).messages) == 200 or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    rec.stop()
    assert not is_finished(cut)
    assert len(walk(cut).messages) == 200
    report = recover(cut)
    assert report.messages == 200 and report.chunks_bad == 0
    assert is_finished(cut)
    assert [t for t, _ in _read_all(cut)] == ["/a"] * 200


@pytest.mark.parametrize("library", ["vehicle-logger replay", "this"])
def test_a_recovered_file_keeps_its_writers_name(tmp_path: Path, library: str) -> None:
    """Recovery writes the header's profile and library again: a cut replay output (`logger replay`'s
    trajectory.mcap) is still told from a live recording after it is recovered, this release's (its version in
    the name) and 0.1.0's (none)."""
    from logger.recording.drive import REPLAY_LIBRARY, open_drive
    from logger.recording.mcap_writer import McapWriter

    path = tmp_path / "trajectory.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start("", REPLAY_LIBRARY if library == "this" else library)
        cid = w.register_channel("/nav/fix", "json", 0)
        for i in range(10):
            w.add_message(cid, 1_700_000_000_000_000_000 + i, b"{}", i)
        w.flush()
    assert not is_finished(path)
    recover(path)
    assert is_finished(path) and [d.origin for d in open_drive([path])] == ["replay"]


def test_truncation_in_the_middle_of_a_chunk_loses_only_that_chunk(tmp_path: Path) -> None:
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=3600), TOPICS)
    path = rec.start()
    assert path is not None
    for i in range(100):
        rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, i)
    rec.stop()
    data = path.read_bytes()
    first = walk(path)
    assert first.chunks_ok >= 1 and len(first.messages) == 100
    # One chunk holds all 100 messages: a cut inside it loses them, a cut in the summary loses none.
    for cut_at, expected in ((len(data) - 40, 100), (60, 0)):
        p = tmp_path / f"t{cut_at}.mcap"
        p.write_bytes(data[:cut_at])
        found = walk(p)
        assert found.stopped_at  # the walk notices the cut instead of raising
        report = recover(p)
        assert is_finished(p)
        assert report.messages == expected


def test_full_queue_is_a_counted_drop_not_a_block(tmp_path: Path) -> None:
    rec = Recorder(RecorderSettings(out_dir=tmp_path, queue_size=10), TOPICS)
    # Not started: nothing drains the queue, so the 11th record must be refused at once.
    accepted = sum(rec.submit("/a", {"x": i}, i, i) for i in range(25))
    assert accepted == 10
    assert rec.status().dropped == {"/a": 15}


def test_a_write_stuck_on_a_stalled_card_blocks_neither_the_status_nor_the_sensors(tmp_path: Path) -> None:
    """A frozen filesystem holds the writer in write(), and the stream's lock with it: status() asked the stream
    for its size while holding the recorder's lock, and submit() needs that lock to count a drop, so the status
    socket and every sensor thread stopped with the card (fsfreeze for 50 s: the whole daemon silent). The size is
    the writer's own count now."""
    import threading

    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05, queue_size=20), TOPICS)
    rec.start()
    stuck, release = threading.Event(), threading.Event()
    try:
        assert rec.submit("/a", {"x": 0}, 1, 1)
        assert wait_until(lambda: rec.status().file_bytes > 0, 10.0)
        stream = rec._stream
        write, tell = stream.write, stream.tell

        def frozen_write(data: bytes) -> int:
            stuck.set()
            release.wait(30)
            return write(data)

        def frozen_tell() -> int:  # the BufferedWriter's own lock, held by the write above
            release.wait(30)
            return tell()
        stream.write, stream.tell = frozen_write, frozen_tell
        for i in range(1, 200):  # enough to close a chunk and reach the stream
            rec.submit("/a", {"x": i, "pad": "x" * 200}, i + 1, i + 1)
            if stuck.is_set():
                break
            time.sleep(0.002)
        assert stuck.wait(10)
        done = threading.Event()

        def ask() -> None:
            rec.status()
            for i in range(50):  # the queue fills: each a counted drop, never a wait
                rec.submit("/a", {"x": i}, 10_000 + i, 10_000 + i)
            done.set()
        threading.Thread(target=ask, daemon=True).start()
        assert done.wait(5), "status() or submit() waited for the stuck write"
        assert rec.status().dropped.get("/a", 0) > 0
    finally:
        release.set()
        rec.stop()


def test_writer_takes_records_in_batches_without_waiting_for_the_flush(tmp_path: Path) -> None:
    from logger.recording.recorder import BATCH_WAIT_S

    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=3600, queue_size=400), TOPICS)
    rec.start()
    try:
        rec.submit("/a", {"x": 0}, 1, 1)  # wakes nobody: written at the writer's next batch, long before a flush
        # Handed to the writer (buffered), not yet on disk: "written" waits for an fsync.
        assert wait_until(lambda: rec.status().buffered.get("/a") == 1, 10 * BATCH_WAIT_S + 5.0)
        assert rec.status().written == {}
        # A quarter of the queue waiting wakes the writer before the batch interval: nothing is refused.
        for i in range(1, 1001):
            rec.submit("/a", {"x": i}, i + 1, i + 1)
            if i % 100 == 0:
                wait_until(lambda: rec.status().queue_depth < 200, 10.0)
        assert rec.status().dropped == {}
        assert wait_until(lambda: rec.status().buffered.get("/a") == 1001, 10.0)
    finally:
        rec.stop()
    assert rec.status().state == "stopped" and rec.status().written == {"/a": 1001}  # on disk once finished
    (path,) = tmp_path.glob("*.mcap")
    assert len(_read_all(path)) == 1001


def test_disk_below_minimum_free_stops_recording_with_a_clear_state(tmp_path: Path) -> None:
    free = os.statvfs(tmp_path).f_bavail * os.statvfs(tmp_path).f_frsize
    rec = Recorder(RecorderSettings(out_dir=tmp_path, min_free_bytes=free * 2), TOPICS)
    assert rec.start() is None
    st = rec.status()
    assert st.state == "disk-full" and st.detail.startswith("not recording: disk full (") and "minimum" in st.detail
    assert not rec.submit("/a", {"x": 1}, 1, 1)
    rec.stop()
    assert list(tmp_path.glob("*.mcap")) == []


def test_rotation_by_duration_of_board_time(tmp_path: Path) -> None:
    """A new file every rotate_duration_s of the board's clock, whatever the log times do: before GNSS time is known
    a board without RTC logs at its boot date, and the log time jumps at the lock (by log time, decades forward cut
    the file there; a clock a day ahead rotated no file for a day)."""
    rec = Recorder(RecorderSettings(out_dir=tmp_path, rotate_duration_s=10.0, flush_interval_s=0.05), TOPICS)
    rec.start()
    t0 = 1_700_000_000_000_000_000
    for i in range(35):
        rec.submit("/a", {"x": i}, t0 + i * 1_000_000_000, i * 1_000_000_000)
    rec.stop()
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) == 4
    assert all(is_finished(f) for f in files)
    assert sum(len(_read_all(f)) for f in files) == 35
    for name, jump in (("behind", 50 * 365 * 86_400 * 10**9), ("ahead", -86_400 * 10**9)):
        out = tmp_path / name
        rec = Recorder(RecorderSettings(out_dir=out, rotate_duration_s=10.0, flush_interval_s=0.05), TOPICS)
        rec.start()
        for i in range(25):  # the lock at 5 s: the log time jumps, the board's clock goes on
            rec.submit("/a", {"x": i}, t0 + i * 1_000_000_000 - (jump if i < 5 else 0), i * 1_000_000_000)
        rec.stop()
        parts = sorted(out.glob("*.mcap"), key=lambda f: f.name[-9:])
        assert [len(_read_all(f)) for f in parts] == [11, 11, 3], name  # not cut at the lock


def test_info_and_recover_commands(tmp_path: Path, capsys) -> None:
    from logger.cli import main

    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.02), TOPICS)
    path = rec.start()
    assert path is not None
    t0 = 1_700_000_000_000_000_000
    for i in range(50):
        # 10 Hz with one missing second between samples 19 and 20
        rec.submit("/a", {"x": i}, t0 + i * 100_000_000 + (1_000_000_000 if i >= 20 else 0), i)
    rec.stop()
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "Closed:    cleanly" in out and "/a" in out and "1.100" in out  # the gap, in seconds
    assert "before the file's end" not in out

    # A sensor that stopped 40 s before the recording did: its own span's rate and gaps do not show it; a line does.
    rec = Recorder(RecorderSettings(out_dir=tmp_path / "stopped", flush_interval_s=0.02), TOPICS)
    stopped = rec.start()
    assert stopped is not None
    for i in range(600):  # /a at 10 Hz for 60 s, /b at 2 Hz for its first 20 s
        rec.submit("/a", {"x": i}, t0 + i * 100_000_000, i)
        if i % 5 == 0 and i < 200:
            rec.submit("/b", {"x": i}, t0 + i * 100_000_000, i)
    rec.stop()
    assert main(["info", str(stopped)]) == 0
    out = capsys.readouterr().out
    assert "  /b: its last message 40.4 s before the file's end" in out and "  /a: its last" not in out
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-100])
    assert main(["info", str(cut)]) == 0
    out = capsys.readouterr().out
    assert "NO (cut short)" in out and "Writer:    vehicle-logger " in out  # from the record walk's header
    # Just written, not closed: it may be a logger's open file (an older logger holds no lock on it): refused
    assert main(["recover", str(cut)]) == 1
    assert "a logger may still be recording it" in capsys.readouterr().err and not is_finished(cut)
    os.utime(cut, (time.time() - 60, time.time() - 60))  # a minute since its last write: a crash's
    assert main(["recover", str(cut)]) == 0
    assert "recovered 50 messages" in capsys.readouterr().out
    assert is_finished(cut)
    assert main(["info", "/nonexistent.mcap"]) == 1
    assert "No such file" in capsys.readouterr().err
    assert main(["info", str(tmp_path)]) == 0  # a folder: every file in it, whichever drive
    out = capsys.readouterr().out
    assert out.count("File:") == len(list(tmp_path.glob("*.mcap"))) >= 2 and f"File:      {cut}" in out
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello world" * 10)
    assert main(["recover", str(junk)]) == 1
    assert "not an MCAP file" in capsys.readouterr().err


def test_info_names_the_version_that_wrote_a_file_and_leaves_a_boot_dates_stamps_out_of_its_span(
        tmp_path: Path, capsys) -> None:
    """A board booted at its image's 1970 records its first seconds on its own clock, then GNSS time: the file's
    Duration was the 56 years between. Undated stamps (before 2020) beside dated ones are now counted in their
    topics and left out of the span and rates, and said so. The header names the release that wrote the file, and
    a 0.1.0 file, which names none, is told as such."""
    from mcap.writer import Writer

    from logger import __version__
    from logger.cli import main

    topics = {**TOPICS, "/b": TopicSpec("/b", "test.A", TOPICS["/a"].schema, "test")}
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.02), topics)
    path = rec.start()
    assert path is not None
    boot, t0 = 3_000_000_000, 1_700_000_000_000_000_000  # 1970-01-01 00:00:03, then GNSS time
    for i in range(30):  # 3 s on the board's clock, then 10 s locked, at 10 Hz
        rec.submit("/a", {"x": i}, boot + i * 100_000_000, i)
        rec.submit("/b", {"x": i}, boot + i * 100_000_000, i)  # a sensor that went silent before the time came
    for i in range(100):
        rec.submit("/a", {"x": i}, t0 + i * 100_000_000, 3_000_000_000 + i)
    rec.stop()
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"Writer:    vehicle-logger {__version__}" in out
    assert "Duration:  9.9 s" in out and "Start:     2023-11-14" in out and "Messages:  160" in out
    assert "Undated:   60 messages stamped before 2020" in out and "left out of Start, End, Duration" in out
    assert " 130 " in out and "10.00" in out  # /a counts every message; its rate is the dated span's
    # /b's 30 messages all came before the time was known: said so (it said nothing, as a topic that ran to the end)
    assert "/b: every message undated: none after the time was known" in out and "/a: every" not in out
    old = tmp_path / "old" / "old.mcap"
    old.parent.mkdir()
    with open(old, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="vehicle-logger")
        sid = w.register_schema("test.A", "jsonschema", b"{}")
        cid = w.register_channel("/a", "json", sid)
        for i in range(5):  # a board that never learnt the time: every stamp undated, kept as they are
            w.add_message(cid, log_time=boot + i * 1_000_000_000, data=b'{"x":1}',
                          publish_time=boot + i * 1_000_000_000)
        w.finish()
    assert main(["info", str(old)]) == 0
    out = capsys.readouterr().out
    assert "Writer:    vehicle-logger (0.1.0: its files name no version)" in out
    assert "Duration:  4.0 s" in out and "Undated:   5 messages stamped before 2020" in out
    assert "left out" not in out


def test_on_disk_tells_only_what_an_fsync_kept(tmp_path: Path, monkeypatch) -> None:
    """`logger status` says how far each topic is on disk: a record handed over before a failed fsync (a dying
    card) is not counted as kept, neither then nor after the recorder has reopened on a new file."""
    import errno

    import logger.recording.recorder as recorder_module

    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.02), TOPICS)
    rec.start()
    try:
        rec.submit("/a", {"x": 1}, 1_700_000_000_000_000_001, 1000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 1000, 20.0), "the first record on disk"
        monkeypatch.setattr(recorder_module, "os", FsyncFails(errno.EIO, "Input/output error"))
        rec.submit("/a", {"x": 2}, 1_700_000_000_000_000_002, 2000)
        assert wait_until(lambda: rec.status().state == "failed", 20.0), "the failed fsync noticed"
        assert rec.status().on_disk_mono_ns == {"/a": 1000}
        monkeypatch.undo()  # the card answers again: the recorder reopens on a new file after its back-off
        assert wait_until(lambda: rec.status().state == "recording", 20.0), "recording again"
        time.sleep(0.1)  # a few flushes of the new file
        assert rec.status().on_disk_mono_ns == {"/a": 1000}
        rec.submit("/a", {"x": 3}, 1_700_000_000_000_000_003, 3000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 3000, 20.0), "the new record on disk"
    finally:
        rec.stop()


def test_first_record_of_each_topic_is_announced_once_when_written(tmp_path: Path) -> None:
    topics = {**TOPICS, "/b": TopicSpec("/b", "test.B", {"type": "object"}, "test")}
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), topics)
    firsts: list[tuple[str, int]] = []
    rec.on_first_record = lambda topic: firsts.append((topic, sum(rec.status().buffered.values())))
    path = rec.start()
    for i in range(50):
        rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, i)
    rec.submit("/b", {}, 1_700_000_000_000_000_100, 100)
    rec.stop()
    assert path is not None
    # Each topic once, and only after its record was handed to the writer (counted written once an fsync keeps it).
    assert firsts == [("/a", 1), ("/b", 51)]


def _records_on_disk(folder: Path) -> int:
    return sum(len(walk(p).messages) for p in sorted(folder.glob("*.mcap")))


def test_a_deleted_file_is_noticed_at_the_next_flush_and_a_new_one_started(tmp_path: Path) -> None:
    """Writes and fsyncs into an unlinked file succeed: the recorder looks at the link count at every flush."""
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS)
    first = rec.start()
    assert first is not None
    try:
        rec.submit("/a", {"x": 1}, 1_700_000_000_000_000_001, 1000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 1000, 20.0)
        first.unlink()
        rec.submit("/a", {"x": 2}, 1_700_000_000_000_000_002, 2000)
        assert wait_until(lambda: rec.status().file not in (None, str(first)), 20.0), rec.status()
        assert rec.alive and rec.status().state == "recording"
        rec.submit("/a", {"x": 3}, 1_700_000_000_000_000_003, 3000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 3000, 20.0)
    finally:
        rec.stop()
    (second,) = sorted(tmp_path.glob("*.mcap"))
    assert is_finished(second) and [m[1] for m in _read_all(second)] == [1_700_000_000_000_000_003]
    # The status counts on disk only what is: the first record went with its file (the second, handed to the
    # writer around the deletion, is lost with it or in the new file, whichever the flush's timing gave).
    st = rec.status()
    assert st.deleted == {"/a": 1} and st.written == {"/a": _records_on_disk(tmp_path)}, st
    assert st.written["/a"] + st.deleted["/a"] + st.lost.get("/a", 0) == 3, st


def test_a_deleted_folder_is_reported_made_again_and_recording_goes_on(tmp_path: Path, caplog) -> None:
    out = tmp_path / "drives"
    rec = Recorder(RecorderSettings(out_dir=out, flush_interval_s=0.05), TOPICS)
    rec.start()
    seen: list[str] = []
    try:
        rec.submit("/a", {"x": 1}, 1_700_000_000_000_000_001, 1000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 1000, 20.0)
        for p in out.iterdir():
            p.unlink()
        out.rmdir()

        def failed_then_back() -> bool:
            st = rec.status()
            seen.append(st.detail)
            return st.state == "recording" and out.is_dir() and any(out.glob("*.mcap"))

        assert wait_until(failed_then_back, 20.0, poll_s=0.001), seen[-3:]
        rec.submit("/a", {"x": 2}, 1_700_000_000_000_000_002, 2000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 2000, 20.0)
    finally:
        rec.stop()
    assert f"the output folder {out} was deleted while recording" in caplog.text
    assert f"the output folder {out} was missing: made it again" in caplog.text
    assert _records_on_disk(out) == 1 and rec.alive is False
    st = rec.status()
    assert st.deleted == {"/a": 1} and st.written == {"/a": 1} and st.on_disk_mono_ns == {"/a": 2000}, st


def test_a_deleted_folder_takes_the_runs_earlier_files_from_the_count_on_disk(tmp_path: Path) -> None:
    """Every file of the run in the folder went with it, the finished ones too: none of their records is counted
    on disk any more, and the newest on disk is the new folder's."""
    import shutil

    out = tmp_path / "drives"
    rec = Recorder(RecorderSettings(out_dir=out, flush_interval_s=0.05, rotate_size_bytes=1), TOPICS)
    rec.start()
    try:
        for i in range(3):  # a file each (rotated at the first flush past one byte)
            rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, 1000 + i)
            assert wait_until(lambda i=i: rec.status().on_disk_mono_ns.get("/a") == 1000 + i, 20.0)
            assert wait_until(lambda i=i: rec.status().files_done >= i + 1, 20.0)
        assert rec.status().written == {"/a": 3} and len(list(out.glob("*.mcap"))) >= 3
        shutil.rmtree(out)
        assert wait_until(lambda: rec.status().deleted == {"/a": 3}, 20.0), rec.status()
        assert wait_until(lambda: rec.status().state == "recording" and out.is_dir(), 20.0), rec.status()
        rec.submit("/a", {"x": 9}, 1_700_000_000_000_000_009, 9000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 9000, 20.0)
    finally:
        rec.stop()
    st = rec.status()
    assert st.written == {"/a": 1} == {"/a": _records_on_disk(out)} and st.deleted == {"/a": 3}, st


@pytest.mark.parametrize("how", ["deleted", "moved"])
def test_a_folder_deleted_between_two_files_takes_its_files_from_the_count_on_disk(tmp_path: Path, how: str) -> None:
    """The folder deleted at a rotation, after one file closed and before the next opened: the flushes' check needs
    an open file, so the folder was made again with the run's earlier files still counted on disk (the emulated
    board's suite hit it: 264 rotations in 13 s). The folder held open tells deleted from moved away (its files
    still on the card, counted so)."""
    import shutil

    out = tmp_path / "drives"
    rec = Recorder(RecorderSettings(out_dir=out, flush_interval_s=0.05, rotate_size_bytes=1), TOPICS)
    closed: list[Path] = []

    def delete_once(path: Path) -> None:
        if not closed:
            shutil.rmtree(out) if how == "deleted" else out.rename(tmp_path / "moved")
        closed.append(path)

    rec.start()
    try:
        for i in range(2):
            rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, 1000 + i)
            assert wait_until(lambda i=i: rec.status().on_disk_mono_ns.get("/a") == 1000 + i, 20.0)
        rec.on_file_closed = delete_once  # at the next rotation, between the close and the open
        assert wait_until(lambda: bool(closed) and rec.status().state == "recording" and out.is_dir(), 20.0)
        rec.submit("/a", {"x": 9}, 1_700_000_000_000_000_009, 9000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 9000, 20.0)
    finally:
        rec.stop()
    st = rec.status()
    assert _records_on_disk(out) == 1
    if how == "deleted":
        assert st.written == {"/a": 1} and st.deleted == {"/a": 2}, st
    else:
        assert st.written == {"/a": 3} and st.deleted == {} and _records_on_disk(tmp_path / "moved") == 2, st


def test_an_unexpected_error_in_the_writer_is_a_reported_failure_not_a_dead_thread(tmp_path: Path,
                                                                                 monkeypatch) -> None:
    """A bug or an error nobody foresaw in the writer thread: status `failed` with the reason, the thread goes on,
    what was flushed stays readable, and a new file is started after the back-off."""
    import logger.recording.recorder as recorder_module

    real_encode = recorder_module.encode
    calls = {"n": 0}

    def encode_once_broken(payload):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("something nobody foresaw")
        return real_encode(payload)

    monkeypatch.setattr(recorder_module, "encode", encode_once_broken)
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS)
    first = rec.start()
    try:
        rec.submit("/a", {"x": 1}, 1_700_000_000_000_000_001, 1000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 1000, 20.0)
        rec.submit("/a", {"x": 2}, 1_700_000_000_000_000_002, 2000)
        assert wait_until(lambda: rec.status().state == "failed", 20.0)
        assert rec.alive and "RuntimeError: something nobody foresaw" in rec.status().detail
        assert wait_until(lambda: rec.status().state == "recording", 20.0), rec.status()  # after its back-off
        rec.submit("/a", {"x": 3}, 1_700_000_000_000_000_003, 3000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 3000, 20.0)
    finally:
        rec.stop()
    assert first is not None and len(walk(first).messages) == 1 and _records_on_disk(tmp_path) == 2


def test_a_disk_full_while_opening_leaves_no_empty_file(tmp_path: Path, monkeypatch) -> None:
    import errno

    import logger.recording.recorder as recorder_module

    monkeypatch.setattr(recorder_module, "os", FsyncFails(errno.ENOSPC, "No space left on device"))
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS)
    assert rec.start() is None
    try:
        st = rec.status()
        assert st.state == "disk-full" and st.detail.startswith("not recording: disk full ("), st
        assert list(tmp_path.glob("*.mcap")) == []
    finally:
        rec.stop()


def _run_file(path: Path, run: str, part: int) -> None:
    """A finished MCAP file holding only the recorder's run record."""
    from logger.recording.files import RUN_METADATA
    from logger.recording.mcap_writer import McapWriter

    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="", library="vehicle-logger")
        w.add_metadata(RUN_METADATA, {"run": run, "part": str(part)})
        w.finish()


def test_a_folder_stands_for_one_drive_and_several_are_told_apart(tmp_path: Path) -> None:
    """The daemon numbers a drive's files from 0001 at each start: in name order the numbers rise within a drive, and
    one that does not rise begins another, whether it is another start's 0001 or a later drive after the last parts
    of an earlier one whose first files are gone."""
    from logger.recording.drive import DriveFileError, drive_paths, drive_stem, part_number

    one = tmp_path / "one"
    one.mkdir()
    names = ["drive_20261204T100000Z_0001.mcap", "drive_20261204T110000Z_0002.mcap", "drive_20261204T120000Z_0003.mcap"]
    for n in names:
        (one / n).write_bytes(b"")
    assert [p.name for p in drive_paths([one])] == names
    # Named by two clocks that disagree (the system clock's 2026 at start, GNSS time's 2018 after): one drive by
    # the run id its files carry.
    two_clocks = tmp_path / "two-clocks"
    two_clocks.mkdir()
    for n, part in (("drive_20261204T100000Z_0001.mcap", 1), ("drive_20181025T205603Z_0002.mcap", 2)):
        _run_file(two_clocks / n, "5c0ffee1", part)
    assert len(drive_paths([two_clocks])) == 2
    # Without run ids (files of an older recorder) the names decide: a start killed before the clock locked left a
    # boot-named 0001, the next start's first file was numbered 0002 and dated; numbers in one unbroken run no
    # longer merge them.
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    for n in ("drive_boot-3a79384f_0001.mcap", "drive_20261206T051345Z_0002.mcap"):
        (crashed / n).write_bytes(b"")
    with pytest.raises(DriveFileError, match="a folder of 2 drives"):
        drive_paths([crashed])
    # Two runs whose names look like one drive's parts are two drives.
    runs = tmp_path / "runs"
    runs.mkdir()
    _run_file(runs / "drive_20261206T051345Z_0001.mcap", "aaaaaaaa", 1)
    _run_file(runs / "drive_20261206T052000Z_0002.mcap", "bbbbbbbb", 2)
    with pytest.raises(DriveFileError, match="a folder of 2 drives"):
        drive_paths([runs])
    assert part_number(one / names[1]) == 2 and drive_stem(one / names[1]) == "drive_20261204T110000Z"
    for folder, files in (("restarted", ["drive_20261204T100000Z_0001.mcap", "drive_20261204T110000Z_0001.mcap"]),
                          ("pruned", ["drive_20261203T100000Z_0005.mcap", "drive_20261203T110000Z_0006.mcap",
                                      "drive_20261204T090000Z_0001.mcap", "drive_20261204T100000Z_0002.mcap"])):
        d = tmp_path / folder
        d.mkdir()
        for n in files:
            (d / n).write_bytes(b"")
        with pytest.raises(DriveFileError, match="a folder of 2 drives"):
            drive_paths([d])
        assert len(drive_paths([d], one_drive=False)) == len(files)  # logger info takes them all
    with pytest.raises(DriveFileError, match="without recorded MCAP files"):
        (tmp_path / "empty").mkdir()
        drive_paths([tmp_path / "empty"])


def test_files_of_two_drives_named_one_by_one_are_refused_as_a_folder_of_two_is(tmp_path: Path) -> None:
    """A shell's ``drives/drive_*.mcap`` over two cars' files was merged into one track and filtered as one drive:
    files named one by one are held to the folder's rule (part numbers rising in name order), in any order given."""
    from logger.recording.drive import DriveFileError, drive_paths

    a = [tmp_path / "a" / f"drive_20261204T10000{i}Z_000{i + 1}.mcap" for i in range(3)]
    b = [tmp_path / "b" / "drive_20261205T090000Z_0001.mcap"]
    for f in a + b:
        f.parent.mkdir(exist_ok=True)
        f.write_bytes(b"")
    assert drive_paths([a[2], a[0], a[1]]) == [a[2], a[0], a[1]]  # one drive's, in any order
    with pytest.raises(DriveFileError, match=r"^files of 2 drives \(files drive_20261204T100000Z_0001.mcap, "
                                             r"drive_20261205T090000Z_0001.mcap each begin one\): name the files"):
        drive_paths([*a, *b])
    with pytest.raises(DriveFileError, match="files of 2 drives"):
        drive_paths([tmp_path / "a", *b])  # a folder and a file of another drive
    with pytest.raises(DriveFileError, match="named twice"):
        drive_paths([a[0], a[1], tmp_path / "a" / ".." / "a" / a[0].name])
    assert len(drive_paths([*a, *b], one_drive=False)) == 4  # logger info takes any files


def test_a_failed_open_takes_no_part_number_and_every_file_says_its_run(tmp_path: Path, monkeypatch) -> None:
    """Opens that fail (a full disk) took part numbers: a restart's first file was _0005 and one run jumped from
    _0001 to _0011, which the drive reader took for one drive with an earlier start's files. Now a part number goes
    to a file actually started, and every file carries its run id and part in a metadata record written at open,
    so a file cut short (kill -9) has it too."""
    import errno

    import logger.recording.recorder as recorder_module
    from logger.recording.drive import run_identity

    monkeypatch.setattr(recorder_module, "os", FsyncFails(errno.ENOSPC, "No space left on device"))
    monkeypatch.setattr(recorder_module, "RETRY_S", 0.0)
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.02, rotate_duration_s=1.0), TOPICS)
    assert rec.start() is None
    try:
        for i in range(3):  # each record finds no file and makes the writer try again: three failed opens
            rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, i)
        assert wait_until(lambda: sum(rec.status().unrecorded.values()) == 3, 20.0)
        # The writer keeps trying (RETRY_S 0): a file exists for the instant between an attempt's open and its
        # removal, so the check is that none is left behind, which a file kept by each attempt would never give.
        assert wait_until(lambda: not list(tmp_path.glob("*.mcap")), 20.0), list(tmp_path.glob("*.mcap"))
        monkeypatch.undo()
        monkeypatch.setattr(recorder_module, "RETRY_S", 0.0)
        assert wait_until(lambda: rec.status().state == "recording", 20.0), rec.status()
        first = Path(rec.status().file or "")
        assert first.name.endswith("_0001.mcap"), first.name
        rec.submit("/a", {"x": 9}, 1_700_000_000_000_000_009, 9)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 9, 20.0)
        cut = tmp_path / "cut.bin"
        cut.write_bytes(first.read_bytes())  # as a kill -9 leaves it
        assert not is_finished(cut) and run_identity(cut) == (rec.run_id, 1)
        cut.unlink()
        rec.submit("/a", {"x": 10}, 1_700_000_000_000_000_009 + 2 * 10**9, 9 + 2 * 10**9)  # rotated: part 2, not 12
    finally:
        rec.stop()
    names = sorted((p.name for p in tmp_path.glob("*.mcap")), key=lambda n: n[-9:])  # the first named by the wall
    assert [n[-9:] for n in names] == ["0001.mcap", "0002.mcap"], names
    assert sorted(run_identity(tmp_path / n) for n in names) == [(rec.run_id, 1), (rec.run_id, 2)]
    recover(tmp_path / names[0], tmp_path / "recovered.mcap")  # recovery keeps the run record
    assert run_identity(tmp_path / "recovered.mcap") == (rec.run_id, 1)


def test_written_counts_only_what_reached_the_disk_and_a_failed_write_is_counted_lost(tmp_path: Path,
                                                                                    monkeypatch) -> None:
    """After an I/O error (a read-only remount, a full disk) the summary and the status counted the lost chunk's
    records as written: a record is written once an fsync kept it, and lost when the write it was in failed."""
    import errno

    import logger.recording.recorder as recorder_module

    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.02), TOPICS)
    rec.start()
    try:
        rec.submit("/a", {"x": 1}, 1_700_000_000_000_000_001, 1000)
        assert wait_until(lambda: rec.status().written == {"/a": 1}, 20.0)
        monkeypatch.setattr(recorder_module, "os", FsyncFails(errno.EROFS, "Read-only file system"))
        rec.submit("/a", {"x": 2}, 1_700_000_000_000_000_002, 2000)
        rec.submit("/a", {"x": 3}, 1_700_000_000_000_000_003, 3000)
        assert wait_until(lambda: rec.status().state == "failed", 20.0)
        st = rec.status()
        assert st.written == {"/a": 1} and st.lost == {"/a": 2} and st.buffered == {}, st
        assert st.detail == "not recording: Read-only file system"  # no path, the same on every retry
        rec.submit("/a", {"x": 4}, 1_700_000_000_000_000_004, 4000)  # while down: not recorded
        assert wait_until(lambda: rec.status().unrecorded == {"/a": 1}, 20.0)
        assert wait_until(lambda: rec.status().down_s > 0.0, 20.0)
    finally:
        monkeypatch.undo()
        rec.stop()
    # (The fake fails only the fsync, so the page cache still held those bytes; a real failed write keeps nothing.)
    assert rec.status().written == {"/a": 1} and rec.status().lost == {"/a": 2}


def test_a_drive_with_a_part_missing_is_said_and_read_without_it(tmp_path: Path) -> None:
    """A part of a rotated drive deleted (or not copied from the card): the readers bridged its hole as if nothing
    were missing. ``cut_notes``, which every office command prints before reading, now names the missing parts;
    the first part missing is said too (the drive starts late), and a drive with all its parts says nothing."""
    from logger.recording.drive import cut_notes, open_drive

    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.02, rotate_size_bytes=1), TOPICS)
    rec.start()
    try:
        for i in range(4):  # a file each (rotated at the first flush past one byte)
            rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, 1000 + i)
            assert wait_until(lambda i=i: rec.status().files_done >= i + 1, 20.0)
    finally:
        rec.stop()
    files = sorted(tmp_path.glob("*.mcap"), key=lambda f: f.name[-9:])  # the first named by the wall clock
    assert [f.name[-9:] for f in files][:4] == ["0001.mcap", "0002.mcap", "0003.mcap", "0004.mcap"], files
    assert cut_notes(open_drive(files)) == []
    assert cut_notes(open_drive([files[0], files[1], files[3]])) == [
        f"the drive of {files[0].name} lacks 1 part (0003): read without them, its time there is a gap"]
    assert cut_notes(open_drive(files[2:4])) == [
        f"the drive of {files[2].name} lacks 2 parts (0001, 0002): read without them, its time there is a gap"]


def test_a_folder_moved_away_or_unmounted_while_recording_keeps_its_records_counted_on_disk(tmp_path: Path) -> None:
    """A card unmounted under the recorder (a lazy unmount) or its folder moved away: the path no longer leads to the
    open file, but the file was not deleted (it still has a link) and holds every record up to its last flush.
    Counted deleted and lost, they were said gone while they were on the card."""
    out = tmp_path / "drives"
    rec = Recorder(RecorderSettings(out_dir=out, flush_interval_s=0.05), TOPICS)
    rec.start()
    try:
        rec.submit("/a", {"x": 1}, 1_700_000_000_000_000_001, 1000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 1000, 20.0)
        out.rename(tmp_path / "moved")
        assert wait_until(lambda: out.is_dir() and rec.status().state == "recording", 20.0), rec.status()
        rec.submit("/a", {"x": 2}, 1_700_000_000_000_000_002, 2000)
        assert wait_until(lambda: rec.status().on_disk_mono_ns.get("/a") == 2000, 20.0)
    finally:
        rec.stop()
    st = rec.status()
    assert st.deleted == {} and st.lost == {} and st.written == {"/a": 2}, st
    assert _records_on_disk(tmp_path / "moved") + _records_on_disk(out) == 2


def test_a_recorder_stopped_on_an_error_lets_go_of_its_folder(tmp_path: Path) -> None:
    """The output folder is held open (to tell it deleted from moved): a stop whose last close failed (a card
    failing) left it open after the recorder had stopped, keeping the storage busy."""
    rec = Recorder(RecorderSettings(out_dir=tmp_path / "drives", flush_interval_s=0.05), TOPICS)
    rec.start()
    assert wait_until(lambda: rec._dir_fd is not None, 20.0)
    close = rec._close_file

    def failing_close() -> None:
        close()
        raise OSError(5, "Input/output error")

    rec._close_file = failing_close  # type: ignore[method-assign]
    rec.stop()
    assert rec.status().state == "stopped" and rec._dir_fd is None
