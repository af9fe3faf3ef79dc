"""A board without a real-time clock: it boots with a wrong wall clock (1970, or whatever the last shutdown left)
until GNSS gives the time. File names must never come from that wall clock: a file started before the time is
known gets a boot-safe name and is renamed to its start time once the clock knows it; and a system clock that
steps (NTP arriving, an operator's `date -s`) changes nothing, because everything runs on the monotonic clock."""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from logger.config import defaults
from logger.recording.files import is_finished
from logger.recording.recorder import Recorder, boot_safe_file_name, read_boot_id
from logger.recording.settings import RecorderSettings
from logger.recording.topics import TopicSpec
from logger.runtime.daemon import Daemon
from sync.stamp import FREERUN, LOCKED, Stamp, StampClock

TOPICS = {"/a": TopicSpec("/a", "test.A", {"type": "object", "properties": {"x": {"type": "integer"}}}, "test")}
GNSS_OFFSET_NS = 1_795_000_000_000_000_000 - time.monotonic_ns()  # "GNSS time" = monotonic + this, in 2026
BOOT_NAME = re.compile(r"^drive_boot-[0-9a-f]{8}_(\d{4})\.mcap$")
DATED_NAME = re.compile(r"^drive_(\d{8}T\d{6}Z)_(\d{4})\.mcap$")


class GnssClock(StampClock):
    """A StampClock that free-runs on a 1970 wall clock until ``lock()``, then gives GNSS time."""

    def __init__(self) -> None:
        self.locked = threading.Event()

    def lock(self) -> None:
        self.locked.set()

    def stamp(self, t_mono_ns: int) -> Stamp:
        if self.locked.is_set():
            return Stamp(t_mono_ns + GNSS_OFFSET_NS, LOCKED, 100, 0, 0)
        return Stamp(t_mono_ns, FREERUN, 10**9, 0, 0)  # the wall clock of a board that booted in 1970

    def synced(self, t_mono_ns: int) -> int | None:
        s = self.stamp(t_mono_ns)
        return None if s.state == FREERUN else s.t_sync_ns


def wait_until(what: str, predicate, timeout_s: float = 10.0) -> None:  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out: {what}")


def messages(path: Path) -> list[int]:
    with open(path, "rb") as f:
        import json

        return [json.loads(m.data)["x"] for _, _, m in make_reader(f).iter_messages()]


@pytest.fixture
def wall_clock_in_1970(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(time, "time", lambda: 42.0)
    monkeypatch.setattr(time, "time_ns", lambda: 42_000_000_000)


def test_boot_safe_name_then_renamed_to_the_start_time_once_known(tmp_path: Path, wall_clock_in_1970: None) -> None:
    clock = GnssClock()
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS, synced_unix_ns=clock.synced)
    opened_at = time.monotonic_ns()
    first = rec.start()
    assert first is not None and BOOT_NAME.match(first.name), first.name
    assert first.name == boot_safe_file_name("drive", read_boot_id(), 1)
    for i in range(100):
        rec.submit("/a", {"x": i}, i, i)
    time.sleep(0.2)
    assert first.exists()  # still unknown: the name stays

    clock.lock()
    wait_until("renamed", lambda: not first.exists())
    (renamed,) = tmp_path.glob("*.mcap")
    m = DATED_NAME.match(renamed.name)
    assert m, renamed.name
    expected = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime((opened_at + GNSS_OFFSET_NS) / 1e9))
    started = time.strptime(m.group(1), "%Y%m%dT%H%M%SZ")
    assert abs(time.mktime(started) - time.mktime(time.strptime(expected, "%Y%m%dT%H%M%SZ"))) <= 1
    wait_until("status names the renamed file", lambda: rec.status().file == str(renamed))
    assert rec.status().detail == f"writing {renamed.name}"  # not the boot-time name it had
    for i in range(100, 200):  # the writer goes on writing into the renamed file
        rec.submit("/a", {"x": i}, i, i)
    rec.stop()
    assert is_finished(renamed) and messages(renamed) == list(range(200))
    assert not any("1970" in p.name for p in tmp_path.iterdir())


def test_files_rotated_before_the_time_was_known_are_renamed_too(tmp_path: Path, wall_clock_in_1970: None) -> None:
    clock = GnssClock()
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05, rotate_duration_s=1e-9), TOPICS,
                   synced_unix_ns=clock.synced)
    rec.start()
    for i in range(5):  # every second record is past the rotation duration: three files
        rec.submit("/a", {"x": i}, i * 10, i)
    wait_until("three files", lambda: len(list(tmp_path.glob("*.mcap"))) >= 3)
    assert all(BOOT_NAME.match(p.name) for p in tmp_path.glob("*.mcap"))
    clock.lock()
    wait_until("all dated", lambda: all(DATED_NAME.match(p.name) for p in tmp_path.glob("*.mcap")))
    rec.stop()
    names = sorted(p.name for p in tmp_path.glob("*.mcap"))
    assert [DATED_NAME.match(n).group(2) for n in names] == [f"{k:04d}" for k in range(1, len(names) + 1)]  # type: ignore[union-attr]
    assert len(names) == 3 and sum(len(messages(tmp_path / n)) for n in names) == 5


def test_a_file_started_after_the_time_is_known_is_dated_at_once(tmp_path: Path, wall_clock_in_1970: None) -> None:
    clock = GnssClock()
    clock.lock()
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS, synced_unix_ns=clock.synced)
    path = rec.start()
    rec.stop()
    assert path is not None and DATED_NAME.match(path.name) and path.name.startswith("drive_2026")


def test_a_system_clock_step_changes_neither_cadence_nor_names(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    clock = GnssClock()
    clock.lock()
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS, synced_unix_ns=clock.synced)
    path = rec.start()
    assert path is not None
    for i in range(50):
        rec.submit("/a", {"x": i}, i, i)
    wait_until("written", lambda: rec.status().written.get("/a", 0) == 50)
    size_before = path.stat().st_size
    real_ns = time.time_ns()
    monkeypatch.setattr(time, "time_ns", lambda: real_ns - 86_400 * 10**9)  # chrony steps the clock a day back
    monkeypatch.setattr(time, "time", lambda: real_ns / 1e9 - 86_400)
    for i in range(50, 100):
        rec.submit("/a", {"x": i}, i, i)
    wait_until("flushed after the step", lambda: path.stat().st_size > size_before)  # chunks keep closing
    rec.stop()
    assert list(tmp_path.glob("*.mcap")) == [path] and messages(path) == list(range(100))


def test_the_daemon_names_files_from_its_clock_not_the_wall(tmp_path: Path, wall_clock_in_1970: None) -> None:
    cfg = defaults(sim=True)
    cfg.values["logger"]["out_dir"] = str(tmp_path / "drives")
    cfg.values["logger"]["status_socket"] = str(tmp_path / "status.sock")
    clock = GnssClock()
    d = Daemon(cfg, [], clock=clock)
    d.start()
    try:
        (boot_named,) = (tmp_path / "drives").glob("*.mcap")
        assert BOOT_NAME.match(boot_named.name)
        clock.lock()  # the receiver got its fix
        wait_until("dated", lambda: all(DATED_NAME.match(p.name) for p in (tmp_path / "drives").glob("*.mcap")),
                   timeout_s=15)
    finally:
        d.stop()
    (dated,) = (tmp_path / "drives").glob("*.mcap")
    assert dated.name.startswith("drive_2026") and is_finished(dated)


def test_a_restart_in_the_same_boot_begins_its_own_0001_and_is_another_drive(tmp_path: Path,
                                                                              wall_clock_in_1970: None) -> None:
    """A start killed before the clock locked leaves its boot-named 0001; the next start in the same boot found that
    name taken, took 0002 (later dated ..._0002), and the drive reader merged the two starts as one drive. Now the
    new start's first file is its own 0001, its name tagged with its run id while the boot name is taken, and each
    file carries its run id: two drives, whatever the names."""
    from logger.recording.drive import DriveFileError, drive_paths, part_number, run_identity

    clock = GnssClock()
    crashed = tmp_path / boot_safe_file_name("drive", read_boot_id(), 1)
    first = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS, synced_unix_ns=clock.synced)
    assert first.start() == crashed
    first.submit("/a", {"x": 1}, 1, 1)
    first.stop()  # stands for the kill: its boot-named file stays
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS, synced_unix_ns=clock.synced)
    path = rec.start()
    assert path is not None and path.name == f"drive_boot-{read_boot_id()}_run-{rec.run_id}_0001.mcap", path
    assert part_number(path) == 1 and run_identity(path) == (rec.run_id, 1)
    rec.submit("/a", {"x": 2}, 2, 2)
    clock.lock()
    wait_until("dated", lambda: not path.exists())
    rec.stop()
    (dated,) = [p for p in tmp_path.glob("*.mcap") if p != crashed]
    assert DATED_NAME.match(dated.name) and dated.name.endswith("_0001.mcap"), dated.name  # no tag needed now
    assert run_identity(dated) == (rec.run_id, 1) and run_identity(crashed) == (first.run_id, 1)
    with pytest.raises(DriveFileError, match="a folder of 2 drives"):
        drive_paths([tmp_path])


def test_the_clock_synchronised_state_is_read_where_the_sandbox_refuses_adjtimex(tmp_path, monkeypatch) -> None:
    """The service's ProtectClock=yes makes adjtimex() fail even read-only: the daemon then looked unsynchronised
    for ever. It asks systemd-timesyncd's flag, then timedated (timedatectl, which sees chrony's clock too)."""
    import ctypes
    import os

    import sync.wallclock as wallclock

    def refused(*_a, **_k):
        raise OSError(1, "Operation not permitted")

    monkeypatch.setattr(ctypes, "CDLL", refused)  # as under the sandbox: no answer from the kernel
    monkeypatch.setattr(wallclock, "TIMESYNC_FLAG", tmp_path / "synchronized")
    fake = tmp_path / "bin"
    fake.mkdir()
    answer = tmp_path / "answer"
    (fake / "timedatectl").write_text(f"#!/bin/sh\ncat {answer}\n")
    (fake / "timedatectl").chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake}:{os.environ['PATH']}")
    for said, synced in (("yes\n", True), ("no\n", False)):
        answer.write_text(said)
        assert wallclock.system_clock_synchronized() is synced
    (tmp_path / "synchronized").touch()  # timesyncd's flag: no need to ask
    assert wallclock.system_clock_synchronized() is True
    (tmp_path / "synchronized").unlink()
    monkeypatch.setenv("PATH", str(tmp_path / "nowhere"))  # no timedated either: it cannot tell
    assert wallclock.system_clock_synchronized() is False
