"""The daemon records while it recovers the last run's cut files, and says so.

Recovering an hour's cut file takes minutes on the board's one core. The daemon used to do it before the recorder,
the sensors and the status server started: nothing was recorded meanwhile and `logger status` said "not running".
Now the file is listed first, everything starts, and a thread recovers it; the status names it, systemd's
watchdog goes on being pinged, its line reaches the log, and a stop gives it up with the file kept as it was.
The recovery is held back by a gate here, standing in for a long one.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from test_notify import FakeSystemd, TickSource, make_daemon, wait_until
from test_recovery_memory import cut_file

import logger.runtime.daemon as daemon_module
from logger.cli.status_view import render
from logger.recording.files import RecoveryCancelled, is_finished
from logger.runtime.daemon import recover_file
from logger.runtime.status_socket import fetch


@pytest.fixture
def systemd(tmp_path: Path) -> Any:
    fake = FakeSystemd(str(tmp_path / "notify.sock"))
    yield fake, str(tmp_path / "notify.sock")
    fake.close()


class GatedRecovery:
    """``recover`` held until ``gate`` is set (or the stop cancels it); the paths it was asked for. It gives up
    waiting after ``hold_s``, so that a daemon that recovers before starting (the old order) fails the test
    instead of hanging it."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, hold_s: float = 8.0) -> None:
        self.gate = threading.Event()
        self.asked: list[Path] = []
        self.hold_s = hold_s
        self.real = daemon_module.recover
        monkeypatch.setattr(daemon_module, "recover", self)

    def __call__(self, path: Path, *args: Any, cancel: Callable[[], bool] | None = None, **kw: Any) -> Any:
        self.asked.append(Path(path))
        give_up = time.monotonic() + self.hold_s
        while not self.gate.wait(0.02) and time.monotonic() < give_up:
            if cancel is not None and cancel():
                raise RecoveryCancelled()
        return self.real(path, *args, cancel=cancel, **kw)


def test_the_daemon_records_and_answers_while_it_recovers_a_cut_file(
        tmp_path: Path, systemd: Any, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    fake, notify = systemd
    drives = tmp_path / "drives"
    drives.mkdir()
    cut = drives / "drive_20261206T040000Z_0001.mcap"
    kept = cut_file(cut, 500)
    (drives / "drive_20261206T040000Z_0001.mcap.recovering").write_bytes(b"a copy cut short")
    gated = GatedRecovery(monkeypatch)
    caplog.set_level(logging.INFO)
    d = make_daemon(tmp_path, [TickSource("a")], notify, watchdog_usec=200_000)
    d.heartbeat_bound_s = 5.0
    d.start()
    try:
        fake.wait_for("READY", timeout_s=5)
        ready_at = time.monotonic()
        assert not gated.gate.is_set() and gated.asked == [cut]  # the recorder's new file is never recovered
        snap = fetch(tmp_path / "status.sock")  # answers: not "not running"
        assert snap["recorder"]["recovering"].startswith(f"{cut.name} ("), snap["recorder"]
        assert not any("recover" in p for p in snap["problems"]), snap["problems"]  # no problem of this run's
        assert f"recovering {cut.name} (" in render(snap)
        assert snap["recorder"]["state"] == "recording" and Path(snap["recorder"]["file"]) != cut
        assert not list(drives.glob("*.recovering")), "the stale copy was not removed before recovering"
        wait_until(lambda: fake.pings_between(ready_at, time.monotonic()) >= 5, "pings during the recovery")
        wait_until(lambda: d.recorder.status().written.get("/test/a", 0) >= 5, "records written meanwhile")
        assert "RecoveryCancelled" not in caplog.text
        gated.gate.set()
        wait_until(lambda: any(r.getMessage().startswith(f"recovered {cut.name}: {len(kept)} messages")
                               for r in caplog.records), "the recovered file's line in the log")
        assert is_finished(cut) and d.startup_lines[0].startswith(f"recovered {cut.name}")
        wait_until(lambda: not any(p.startswith("recovery:") for p in d.snapshot()["problems"]),
                   "the recovery's problem cleared")
        done_at = time.monotonic()
        wait_until(lambda: fake.pings_between(done_at, time.monotonic()) >= 3, "pings once the recovery ended")
        assert d.recorder.status().state == "recording"
    finally:
        gated.gate.set()
        d.stop()


def test_a_stop_gives_the_recovery_up_and_keeps_the_file(
        tmp_path: Path, systemd: Any, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    _, notify = systemd
    drives = tmp_path / "drives"
    drives.mkdir()
    first, second = drives / "drive_20261206T040000Z_0001.mcap", drives / "drive_20261206T050000Z_0001.mcap"
    cut_file(first, 200)
    cut_file(second, 200)
    before = first.read_bytes()
    gated = GatedRecovery(monkeypatch, hold_s=30.0)
    caplog.set_level(logging.INFO)
    d = make_daemon(tmp_path, [TickSource("a")], notify)
    d.start()
    try:
        wait_until(lambda: gated.asked == [first], "the recovery on the first file")
    finally:
        t0 = time.monotonic()
        d.stop()
    assert time.monotonic() - t0 < 15  # not the 30 s the recovery would have held it
    assert first.read_bytes() == before and not is_finished(first) and not is_finished(second)
    assert not list(drives.glob("*.recovering"))
    text = caplog.text
    assert f"recovery of {first.name} stopped with the daemon" in text
    assert f"1 cut file left unrecovered by the stop, for the next start: {second.name}" in text


def test_a_recovery_that_would_take_the_recordings_room_waits(tmp_path: Path) -> None:
    """Beside a live recording, the copy must leave the recorder's minimum free: the new drive comes first, and
    the cut file is readable as it is."""
    cut = tmp_path / "drive_20261206T040000Z_0001.mcap"
    cut_file(cut, 100)
    before = cut.read_bytes()
    line = recover_file(cut, reserve_bytes=1 << 60)
    assert line.startswith(f"did not recover {cut.name}: its copy (up to "), line
    assert cut.read_bytes() == before and not list(tmp_path.glob("*.recovering"))
    assert recover_file(cut).startswith(f"recovered {cut.name}: 100 messages")


def test_a_second_logger_on_the_same_configuration_is_refused_and_the_file_being_written_is_never_recovered(
        tmp_path: Path, systemd: tuple[FakeSystemd, str]) -> None:
    """A second `logger run` with the service's configuration (the README's command, while the service runs): it
    logged "in use by another logger", went on, took the running logger's open file for a crash's and rewrote it
    under it. Now it is refused before anything is opened; and the file being written is never recovered, by a
    logger with another socket in the same folder or by `logger recover` by hand."""
    import subprocess
    import sys

    from logger.recording.files import being_written
    from logger.runtime.daemon import unfinished_files

    _, path = systemd
    first = make_daemon(tmp_path, [TickSource("steady")], path)
    first.start()
    try:
        wait_until(lambda: first.recorder.status().on_disk_mono_ns, "the first logger's records on disk")
        (open_file,) = first.recorder.files()
        assert being_written(open_file) and not is_finished(open_file)
        second = make_daemon(tmp_path, [TickSource("other")], path)
        with pytest.raises(OSError, match=r"in use by another logger \(pid \d+\): one logger records at a time"):
            second.start()
        second.stop()
        assert fetch(tmp_path / "status.sock")["pid"]  # the first still answers on its socket
        assert unfinished_files(tmp_path / "drives") == []  # what another start would recover: not the open file
        r = subprocess.run([sys.executable, "-m", "logger.cli", "recover", str(open_file)], capture_output=True,
                           text=True, timeout=60, cwd=Path(__file__).resolve().parents[1])
        assert r.returncode == 1 and "a running logger is writing it" in r.stderr, r.stderr
        # `info` and the office commands say it is being recorded, not that it was cut (and to recover it)
        r = subprocess.run([sys.executable, "-m", "logger.cli", "info", str(open_file)], capture_output=True,
                           text=True, timeout=60, cwd=Path(__file__).resolve().parents[1])
        assert r.returncode == 0 and "Closed:    not yet (being recorded)" in r.stdout, r.stdout + r.stderr
        assert "logger recover" not in r.stdout and "cut short" not in r.stdout
        from logger.recording.drive import cut_notes, open_drive

        assert cut_notes(open_drive([open_file])) == [f"{open_file} is being recorded: read up to its last chunk "
                                                       "on disk"]
        newest = max(first.recorder.status().on_disk_mono_ns.values())
        wait_until(lambda: max(first.recorder.status().on_disk_mono_ns.values()) > newest, "more records on disk")
        assert first.recorder.status().deleted == {} and first.recorder.status().state == "recording"
    finally:
        first.stop()
    assert not being_written(open_file) and is_finished(open_file)


def test_recover_names_its_output_and_leaves_no_half_copy(tmp_path: Path) -> None:
    """`logger recover FILE -o OUT`: a folder as OUT takes the file under its name (it said "FILE: Is a directory"
    of the input and left OUT.recovering beside it); OUT in a folder that does not exist is said of OUT (it said
    "FILE: no such file" of an input that was there). The recovered file keeps the source's permissions."""
    import subprocess
    import sys

    cut = tmp_path / "drive_0001.mcap"
    cut_file(cut, 400)
    cut.chmod(0o640)
    os.utime(cut, (time.time() - 60, time.time() - 60))  # cut a minute ago: no logger's open file
    folder = tmp_path / "out"
    folder.mkdir()

    def recover(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "logger.cli", "recover", str(cut), *args], capture_output=True,
                              text=True, timeout=60, cwd=Path(__file__).resolve().parents[1])

    r = recover("-o", str(tmp_path / "missing" / "x.mcap"))
    assert r.returncode == 1 and r.stderr == (f"logger recover: -o {tmp_path / 'missing' / 'x.mcap'}: the folder "
                                              f"{tmp_path / 'missing'} does not exist\n"), r.stderr
    # A folder named with its slash is a folder even before it exists: said to be missing, not made a file.
    r = recover("-o", str(tmp_path / "new") + "/")
    assert r.returncode == 1 and r.stderr == (f"logger recover: -o {tmp_path / 'new'}/: the folder "
                                              f"{tmp_path / 'new'} does not exist\n"), r.stderr
    assert not (tmp_path / "new").exists()
    r = recover("-o", str(folder))
    assert r.returncode == 0, r.stderr
    assert is_finished(folder / cut.name) and sorted(os.listdir(folder)) == [cut.name]
    assert sorted(os.listdir(tmp_path)) == [cut.name, "out"]  # no .recovering left anywhere
    assert (folder / cut.name).stat().st_mode & 0o777 == 0o640
    # Another recording named as OUT (a wrong completion) is never replaced; naming FILE itself replaces FILE.
    other = tmp_path / "drive_other.mcap"
    other.write_bytes(b"another drive's file")
    r = recover("-o", str(other))
    assert r.returncode == 2 and other.read_bytes() == b"another drive's file"
    assert r.stderr == f"logger recover: -o {other} already exists and is not {cut}: name a new file or a folder\n"
    r = recover("-o", str(folder))  # the folder already holds the earlier output under FILE's name
    assert r.returncode == 2 and "already exists" in r.stderr
    # A copy that fills its disk (a write past the size limit fails as on a full card) is said of the copy.
    import resource
    import signal

    def small_disk() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1000, 1000))

    r = subprocess.run([sys.executable, "-m", "logger.cli", "recover", str(cut), "-o", str(tmp_path / "big.mcap")],
                       capture_output=True, text=True, timeout=60, cwd=Path(__file__).resolve().parents[1],
                       preexec_fn=small_disk)
    assert r.returncode == 1 and r.stderr == f"logger recover: {tmp_path / 'big.mcap'}: File too large\n", r.stderr
    assert not list(tmp_path.glob("big.mcap*"))
    r = recover("-o", str(cut))
    assert r.returncode == 0 and is_finished(cut), r.stderr


def test_a_second_simulated_run_into_the_same_folder_is_refused(tmp_path: Path) -> None:
    """`logger run --sim --out DIR` twice: the second took a status socket of its own (so as not to take the
    first's) and recorded into DIR beside the first, two drives in one folder and one clock state. The state
    folder's lock refuses it, whatever the sockets; a run into another folder beside it goes on."""
    import signal
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "drives"

    def logger_run(folder: Path, seconds: str) -> subprocess.Popen[str]:
        return subprocess.Popen([sys.executable, "-m", "logger.cli", "run", "--sim", "--out", str(folder),
                                 "--duration", seconds], cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, start_new_session=True)

    first = logger_run(out, "600")
    try:
        lock = out / ".state" / "lock"
        wait_until(lambda: lock.exists() and lock.read_text().strip() == str(first.pid), "the first run's lock")
        second = logger_run(out, "5")
        _, err = second.communicate(timeout=60)
        assert second.returncode == 1, err
        assert err == (f"logger: {out / '.state'}: in use by another logger (pid {first.pid}): one logger records "
                       "at a time; stop that one first\n"), err
        beside = logger_run(tmp_path / "other", "2")
        _, err = beside.communicate(timeout=120)
        assert beside.returncode == 0, err
    finally:
        os.killpg(first.pid, signal.SIGTERM)
        first.communicate(timeout=60)
    assert first.returncode == 0
    assert len(list(out.glob("drive_*.mcap"))) == 1
