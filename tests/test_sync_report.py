"""``logger sync-report`` reads a drive through the project's drive reader: a file cut short up to the cut, with
the line every command prints, and refuses in one line naming the file what it cannot report on."""

from __future__ import annotations

import json
from pathlib import Path

import extras
import pytest
from mcap.writer import Writer

from logger.cli import sync_report as cli
from logger.recording.files import is_finished
from logger.recording.topics import IMU, NAV_FIX, PPS, TOPICS

NS = 1_000_000_000
T0 = 1_796_463_760 * NS
MONO0 = 100 * NS
SECONDS = 60
RATE_HZ = 20


def write_mcap(path: Path, topics: dict[str, list[dict]]) -> Path:
    """The messages in time order, in chunks of about 4 kB (a cut leaves whole chunks before it)."""
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=4096)
        w.start()
        w.add_metadata("config", {"imu.rate_hz": str(RATE_HZ)})
        channels = {t: w.register_channel(t, "json", w.register_schema(TOPICS[t].schema_name, "jsonschema", b"{}"))
                    for t in topics}
        for m, topic in sorted(((m, t) for t, msgs in topics.items() for m in msgs), key=lambda x: x[0]["t_sync_ns"]):
            w.add_message(channels[topic], log_time=m["t_sync_ns"], publish_time=m["t_sync_ns"],
                          data=json.dumps(m).encode())
        w.finish()
    return path


def locked_drive(path: Path) -> Path:
    """A minute of a locked clock: a PPS edge a second, 20 IMU samples between, counted from each edge."""
    period = NS // RATE_HZ
    imu = [{"t_mono_ns": MONO0 + k * period, "t_sync_ns": T0 + k * period, "sync_state": "locked",
            "sync_err_ns": 1000, "imu_cnt": k % RATE_HZ, "timer_cnt": 0} for k in range(SECONDS * RATE_HZ)]
    pps = [{"t_mono_ns": MONO0 + s * NS, "t_sync_ns": T0 + s * NS, "sync_state": "locked", "sync_err_ns": 1000}
           for s in range(SECONDS)]
    return write_mcap(path, {IMU: imu, PPS: pps})


def run(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str, str]:
    code = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


def test_a_file_cut_short_is_reported_up_to_the_cut(tmp_path: Path, capsys) -> None:
    whole = locked_drive(tmp_path / "drive_20261205T094239Z_0001.mcap")
    code, out, err = run(capsys, whole, "--json")
    assert code == 0 and err == "", err
    assert json.loads(out)["table7_synchronised"]["n"] == SECONDS - 1
    cut_dir = tmp_path / "cut"
    cut_dir.mkdir()
    cut = cut_dir / whole.name
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    assert not is_finished(cut)
    code, out, err = run(capsys, cut_dir, "--json")
    assert code == 0, err
    assert err == f"logger sync-report: {cut} was not closed cleanly: read up to where it was cut\n"
    t7 = json.loads(out)["table7_synchronised"]
    assert 5 < t7["n"] < SECONDS - 5 and t7["mean_s"] == pytest.approx(1.0)


def test_what_it_cannot_report_on_is_one_line_naming_the_file(tmp_path: Path, capsys) -> None:
    notes = tmp_path / "notes.txt"
    notes.write_text("hello\n")
    trajectory = write_mcap(tmp_path / "trajectory.mcap", {NAV_FIX: [
        {"t_mono_ns": MONO0 + s * NS, "t_sync_ns": T0 + s * NS, "latitude": 37.5, "longitude": 127.0,
         "altitude": 50.0} for s in range(10)]})
    cases = [
        (notes, f"{notes}: not an MCAP file"),
        (trajectory, f"{trajectory}: no /imu or /pps records: not a recorded drive's time sync"),
        (tmp_path / "none.mcap", "no such file"),
    ]
    for path, words in cases:
        code, out, err = run(capsys, path)
        assert code == 2 and out == "" and err.startswith(f"logger sync-report: {words}"), err
        assert err.count("\n") == 1, err


def test_a_figures_folder_that_cannot_be_one_is_said_before_the_work(tmp_path, capsys) -> None:
    """--png-dir (sync-report) and --plots (nav-score) naming a file: a traceback once the report was printed."""
    from logger.cli import main

    afile = tmp_path / "afile"
    afile.write_text("")
    assert main(["sync-report", str(tmp_path / "drive.mcap"), "--png-dir", str(afile)]) == 2
    assert capsys.readouterr().err == f"logger sync-report: --png-dir {afile}: exists and is not a folder\n"
    assert main(["nav-score", str(tmp_path / "t.csv"), "--plots", str(afile / "sub")]) == 2
    assert capsys.readouterr().err == (f"logger nav-score: --plots {afile / 'sub'}: cannot be made, {afile} is a "
                                       "file and not a folder\n")


def test_the_figures_into_a_closed_pipe_end_quietly(tmp_path: Path) -> None:
    """``logger sync-report D --png-dir DIR | head -1``: the reader gone, the command ends as every other does (141,
    no line), not as a failure to write the figures ("[Errno 32] Broken pipe", exit 2)."""
    import subprocess
    import sys

    extras.need("matplotlib")  # the figures need it: a board's suite may lack the optional extra
    drive = locked_drive(tmp_path / "drive_20261205T094239Z_0001.mcap")
    p = subprocess.Popen([sys.executable, "-m", "logger.cli", "sync-report", str(drive), "--png-dir",
                          str(tmp_path / "png")], cwd=Path(__file__).resolve().parents[1], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    assert p.stdout is not None
    p.stdout.readline()
    p.stdout.close()
    _, err = p.communicate(timeout=120)
    assert p.returncode == 141 and b"Broken pipe" not in err and b"Traceback" not in err, err


def test_a_damaged_chunk_is_said_and_the_rest_reported(tmp_path: Path, capsys) -> None:
    """A chunk that does not decompress is skipped whole and said, one line naming the file, as every reader of a
    drive says it (the report came without a word, its counts short of the file's)."""
    from mcap.reader import make_reader

    p = locked_drive(tmp_path / "drive_20261205T094239Z_0001.mcap")
    with open(p, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 4
    chunk = summary.chunk_indexes[2]
    data = bytearray(p.read_bytes())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle:middle + 8] = bytes(b ^ 0xFF for b in data[middle:middle + 8])
    p.write_bytes(bytes(data))
    code, out, err = run(capsys, p, "--json")
    assert code == 0 and json.loads(out)["table7_synchronised"]["n"] > 0
    (line,) = err.splitlines()
    assert line.startswith(f"logger sync-report: {p}: 1 damaged chunk skipped") and "messages lost" in line, err
