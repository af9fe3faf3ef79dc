"""Progress of the long office commands: a line on a terminal's stderr, nothing in a pipe, wiped at the end."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

from logger.cli.progress import Progress
from logger.recording.drive import PROGRESS_EVERY, _counted

ROOT = Path(__file__).resolve().parents[1]


def test_the_reader_tells_how_far_it_got_and_the_meter_wipes_its_line() -> None:
    told: list[tuple[int, int]] = []
    items = list(range(3 * PROGRESS_EVERY + 5))
    assert list(_counted(items, lambda done, total, what: told.append((done, total)))) == items
    assert told == [(0, len(items)), (PROGRESS_EVERY, len(items)), (2 * PROGRESS_EVERY, len(items)),
                    (3 * PROGRESS_EVERY, len(items)), (len(items), len(items))]
    out = io.StringIO()
    meter = Progress("logger replay", out, on=True)
    meter(50, 200)
    meter(200, 200)  # the end is always drawn, however soon after the last redraw
    meter.stage("writing the trajectory")
    meter.end()
    text = out.getvalue()
    assert "\rlogger replay: 25 % (50 of 200 messages)" in text and "100 % (200 of 200" in text
    assert "writing the trajectory" in text and text.endswith("\r") and text.rsplit("\r", 2)[-2].strip() == ""
    quiet = io.StringIO()  # not a terminal: nothing at all
    for done in (0, 100, 200):
        Progress("logger replay", quiet)(done, 200)
    assert quiet.getvalue() == ""


def test_on_a_terminal_replay_shows_progress_and_in_a_pipe_it_does_not(tmp_path: Path) -> None:
    """A real pty as the command's stderr: the meter draws there; the same command into a pipe prints none."""
    import test_nav_live

    drive = tmp_path / "drive"
    test_nav_live.write_parked_drive(drive, 30.0)
    files = [str(p) for p in sorted(drive.glob("*.mcap"))]
    master, slave = os.openpty()
    try:
        r = subprocess.run([sys.executable, "-m", "logger.cli", "replay", *files, "--out", str(tmp_path / "o")],
                           cwd=ROOT, stdout=subprocess.PIPE, stderr=slave, timeout=120)
        os.close(slave)
        slave = -1
        seen = b""
        while True:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # the other side closed: all read
                break
            if not chunk:
                break
            seen += chunk
    finally:
        if slave >= 0:
            os.close(slave)
        os.close(master)
    assert r.returncode == 1  # a parked drive: no solution, said on stderr after the meter's line was wiped
    text = seen.decode()
    assert "logger replay: 100 % (" in text and "logger replay: no solution from" in text
    piped = subprocess.run([sys.executable, "-m", "logger.cli", "replay", *files, "--out", str(tmp_path / "p")],
                           cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert piped.returncode == 1 and "%" not in piped.stderr and piped.stderr.startswith("logger replay: no solution")
