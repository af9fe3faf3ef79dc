"""``logger export --format ubx`` and ``--format rinex``: the receiver's bytes out of a drive, and RTKLIB's reading.

The real NEO-M8T capture of the GPSD project (39 complete RXM-RAWX epochs, and a 40th cut off by the end of the
capture) goes through a pty into the daemon's own receiver adapter (the real reader: ``GnssSource`` over
``GnssReceiver``), its ``/gnss/raw`` records into the real recorder, rotating files; the export must give back the
capture byte for byte, and Debian's RTKLIB ``convbin`` must find every RAWX epoch in it. Then the whole daemon on
the simulated vehicle with raw observations asked for: against the simulated receiver's own log of what it sent,
the export holds every byte the host read after the set-up, and the status says raw observations are coming (an
M8T) or that they are not (an M8N, which refuses them with one warning).
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_gnss_decode_gpsd import load_capture, random_pieces
from test_raw_observations import rawx

from logger.compose import build
from logger.config import defaults
from logger.exports.raw_stream import count_epochs
from logger.exports.whole import STAGE_PREFIX, remove_stale_stages, stage_prefix
from logger.recording.recorder import Recorder
from logger.recording.records import raw_bytes_record
from logger.recording.settings import RecorderSettings
from logger.recording.topics import GNSS_RAW, TOPICS
from logger.runtime.sources import GnssSource
from logger.runtime.timebase import host_timebase
from sensors.sim.pty import PtyPort
from sensors.ublox_frames import UbxNmeaFramer

ROOT = Path(__file__).resolve().parents[1]
CAPTURE = "ublox-neo-m8t.log"
START_NS = 1_540_500_963_000_000_000  # log times near the capture's own date (2018-10-25)
IN_CI = os.environ.get("LOGGER_TESTS_NO_SKIP") == "1" or os.environ.get("CI") == "true"


def need_convbin() -> str:
    """RTKLIB's convbin; a skip where it is not installed, a failure in CI, which installs it (.ci/run)."""
    path = shutil.which("convbin")
    if path is None:
        if IN_CI:
            pytest.fail("convbin is missing in CI: .ci/run installs Debian's rtklib")
        pytest.skip("convbin is not installed (apt-get install rtklib)")
    return path


def run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "logger.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=env)


def record_through_the_reader(folder: Path, data: bytes, config: dict[str, str] | None = None) -> list[Path]:
    """``data`` written into a pty in serial-port-like pieces, read by the daemon's receiver adapter, its
    ``/gnss/raw`` records recorded into small rotating files."""
    port = PtyPort()
    source = GnssSource(port.path, 115200, False, host_timebase())
    source.open()
    settings = RecorderSettings(out_dir=folder, flush_interval_s=0.01, rotate_size_bytes=6000, min_free_bytes=0)
    rec = Recorder(settings, TOPICS, metadata={"config": config} if config else None)
    rec.start()
    try:
        for piece in random_pieces(data, seed=15):
            port.write(piece)
            target = source.offset + len(piece)
            while source.offset < target:
                for r in source.read():
                    if r.topic == GNSS_RAW:
                        assert rec.submit(GNSS_RAW, r.payload, START_NS + r.payload["offset"] * 10_000, r.t_mono_ns)
            time.sleep(0.001)  # the writer flushes (and rotates) between pieces
    finally:
        rec.stop()
        source.close()
        port.close()
    return sorted(folder.glob("*.mcap"))


@pytest.fixture(scope="module")
def m8t_drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, list[Path]]:
    data = load_capture(CAPTURE)
    files = record_through_the_reader(tmp_path_factory.mktemp("m8t") / "rec", data,
                                      {"gnss.antenna_height_m": "1.234", "gnss.receiver_name": "7/NEO-M8T/TIM 1.10"})
    return data, files


def test_the_export_is_the_capture_byte_for_byte_over_rotated_files(m8t_drive: tuple[bytes, list[Path]],
                                                                     tmp_path: Path) -> None:
    data, files = m8t_drive
    assert len(files) >= 3  # rotated: the .ubx joins them
    r = run("export", *map(str, reversed(files)), "--out", str(tmp_path), "--format", "ubx")  # any order
    assert r.returncode == 0, r.stderr
    ubx = next(tmp_path.glob("*.ubx"))
    assert ubx.read_bytes() == data and len(data) == 25904
    notes = json.loads((tmp_path / f"{ubx.name}.json").read_text())
    assert notes["bytes"] == 25904 and notes["gaps"] == [] and notes["bad_checksum"] == notes["garbage_bytes"] == 0
    assert notes["messages"]["RXM-RAWX"] == 39 and notes["messages"]["NAV-SOL"] == 39
    assert notes["unfinished_tail_bytes"] == 314  # the 40th RAWX, cut off by the end of the capture
    assert f"{GNSS_RAW}: 25904 bytes from " in r.stdout and "39 RXM-RAWX" in r.stdout and "no gaps" in r.stdout
    assert "ends inside a frame (314 bytes of it)" in r.stdout


def test_convbin_reads_every_rawx_epoch_of_the_export(m8t_drive: tuple[bytes, list[Path]], tmp_path: Path) -> None:
    need_convbin()
    data, files = m8t_drive
    r = run("export", *map(str, files), "--out", str(tmp_path), "--format", "rinex")
    assert r.returncode == 0, r.stderr
    obs = next(tmp_path.glob("*.obs"))
    complete_rawx = sum(1 for f in UbxNmeaFramer().feed(data) if f.message is not None
                        and f.message.identity == "RXM-RAWX")
    assert complete_rawx == 39 and count_epochs(obs) == 39
    assert "rinex: 39 observation epochs from 39 RXM-RAWX\n" in r.stdout
    header = obs.read_text().split("END OF HEADER")[0]
    # the antenna height and receiver the drive recorded in its configuration
    assert "        1.2340        0.0000        0.0000                  ANTENNA: DELTA H/E/N" in header
    assert "7                   NEO-M8T             TIM 1.10            REC # / TYPE / VERS" in header
    # Doppler and C/N0 as RXM-RAWX carries them, beside code and phase (RTKLIB's SNR mask works on S1C)
    obs_types = [line[:60].split() for line in header.splitlines() if line[60:].strip() == "SYS / # / OBS TYPES"]
    assert obs_types and all(t[1:] == ["4", "C1C", "L1C", "D1C", "S1C"] for t in obs_types), obs_types  # GPS, SBAS
    assert next(tmp_path.glob("*.ubx")).read_bytes() == data  # the .ubx keeps the unfinished tail
    # The capture holds no RXM-SFRBX: convbin writes no navigation file, and the command says what is missing.
    assert not list(tmp_path.glob("*.nav"))
    assert r.stderr == (f"logger export: no {obs.stem}.nav: the stream holds no navigation data (0 RXM-SFRBX); "
                        "rnx2rtkp needs the day's broadcast ephemerides from elsewhere (an IGS BRDC file)\n")


def test_a_failed_rinex_export_leaves_an_earlier_export_as_it_was(m8t_drive: tuple[bytes, list[Path]],
                                                                  tmp_path: Path) -> None:
    """convbin failing (here a stand-in that exits 3) after the stream was joined: the folder keeps what an earlier
    export of the drive put there, byte for byte (a failed export deleted the earlier .ubx, notes and .obs by name),
    and nothing of the failed one (no staging folder, no partial file)."""
    need_convbin()
    _, files = m8t_drive
    out = tmp_path / "out"
    r = run("export", *map(str, files), "--out", str(out), "--format", "ubx,rinex")
    assert r.returncode == 0, r.stderr
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(Path(n).suffix for n in before) == [".json", ".obs", ".ubx"]
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "convbin").write_text("#!/bin/sh\necho 'input file : broken' >&2\nexit 3\n")
    (fake / "convbin").chmod(0o755)
    env = {**os.environ, "PATH": f"{fake}:{os.environ['PATH']}"}
    for formats in ("rinex", "ubx,rinex"):
        r = run("export", *map(str, files), "--out", str(out), "--format", formats, env=env)
        assert r.returncode == 2 and "convbin wrote no observations from " in r.stderr, r.stderr
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before, formats
    ubx = next(out.glob("*.ubx"))
    assert r.stderr.endswith(f"; wrote only {ubx} and {ubx}.json\n") and f"from {ubx} (exit status 3" in r.stderr


def test_an_export_killed_outright_leaves_its_stage_and_the_next_export_removes_it(
        m8t_drive: tuple[bytes, list[Path]], tmp_path: Path) -> None:
    """SIGKILL during RINEX conversion (a stand-in convbin kills the export that runs it): the export cannot clean
    up, so its staging folder stays with the joined stream in it and nothing of it is in place. The next export
    into that folder says it removes the stage and finishes as usual."""
    need_convbin()
    _, files = m8t_drive
    out = tmp_path / "out"
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "convbin").write_text("#!/bin/sh\nkill -9 $PPID\nsleep 5\n")
    (fake / "convbin").chmod(0o755)
    env = {**os.environ, "PATH": f"{fake}:{os.environ['PATH']}"}
    r = run("export", *map(str, files), "--out", str(out), "--format", "rinex", env=env)
    assert r.returncode == -9, (r.returncode, r.stderr)
    (stage,) = out.iterdir()
    assert stage.name.startswith(".export-") and stage.is_dir() and list(stage.glob("*.ubx")), stage
    r = run("export", *map(str, files), "--out", str(out), "--format", "rinex")
    assert r.returncode == 0, r.stderr
    assert f"logger export: removed {stage}, left by an export that was killed\n" in r.stderr, r.stderr
    assert sorted(p.suffix for p in out.iterdir()) == [".json", ".obs", ".ubx"], list(out.iterdir())


def test_only_the_stages_of_ended_processes_are_removed(tmp_path: Path) -> None:
    """A stage whose process still runs (this one, or another) is another export at work; a name without a process
    id is not a stage this judges."""
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                           check=True)
    gone = tmp_path / f"{STAGE_PREFIX}{int(ended.stdout)}-abc"
    mine = tmp_path / f"{stage_prefix()}def"
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        other = tmp_path / f"{STAGE_PREFIX}{sleeper.pid}-ghi"
        unnamed = tmp_path / f"{STAGE_PREFIX}jkl"
        for d in (gone, mine, other, unnamed):
            d.mkdir()
            (d / "part.ubx").write_bytes(b"x")
        assert remove_stale_stages(tmp_path) == [gone]
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(d.name for d in (mine, other, unnamed))
    finally:
        sleeper.kill()
        sleeper.wait()
    assert remove_stale_stages(tmp_path) == [other]


def test_a_configuration_given_at_the_office_goes_into_the_rinex_header(m8t_drive: tuple[bytes, list[Path]],
                                                                        tmp_path: Path) -> None:
    need_convbin()
    _, files = m8t_drive
    cfg = tmp_path / "office.toml"
    cfg.write_text('[gnss]\nantenna_height_m = 2.05\nreceiver_name = "SN42/NEO-M8T"\n')
    r = run("export", *map(str, files), "--out", str(tmp_path / "out"), "--format", "rinex", "--config", str(cfg))
    assert r.returncode == 0, r.stderr
    header = next((tmp_path / "out").glob("*.obs")).read_text().split("END OF HEADER")[0]
    assert "        2.0500        0.0000        0.0000                  ANTENNA: DELTA H/E/N" in header
    assert "SN42                NEO-M8T" in header
    # convbin names its input in a COMMENT: the stream's own name, not the staging folder it was converted in
    (log,) = [line for line in header.splitlines() if line.startswith("log: ")]
    assert ".export-" not in log and "/" not in log[:60] and ".ubx" in log, log


def test_without_convbin_rinex_says_how_to_install_it(m8t_drive: tuple[bytes, list[Path]], tmp_path: Path) -> None:
    _, files = m8t_drive
    bare = tmp_path / "bin"
    bare.mkdir()
    env = {**os.environ, "PATH": str(bare)}
    r = run("export", *map(str, files), "--out", str(tmp_path / "out"), "--format", "rinex", env=env)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr == ("logger export: --format rinex needs RTKLIB's convbin, which is not installed "
                        "(apt-get install rtklib)\n")
    assert not (tmp_path / "out").exists()


def test_rinex_of_a_stream_without_raw_observations_is_one_line_before_convbin(tmp_path: Path) -> None:
    """A receiver that sent no RXM-RAWX (an M8N, the default): refused before convbin, whose only answer was its
    progress output as the error. Asked for RINEX alone nothing is left behind; asked for the .ubx too, it is kept
    and the line says so."""
    need_convbin()
    rec = Recorder(RecorderSettings(out_dir=tmp_path / "rec", min_free_bytes=0), TOPICS)
    rec.start()
    gga = b"$GPGGA,092725.00,4717.11399,N,00833.91590,E,1,08,1.01,499.6,M,48.0,M,,*5B\r\n"
    for k in range(5):
        rec.submit(GNSS_RAW, raw_bytes_record(k * 10**9, gga, k * len(gga)), START_NS + k * 10**9, k * 10**9)
    rec.stop()
    files = [str(p) for p in (tmp_path / "rec").glob("*.mcap")]
    why = ("logger export: no RINEX: /gnss/raw holds no raw observations (0 RXM-RAWX; record them with [gnss] "
           "raw_observations = true on a receiver that has them: M8T, M8P, F9P, F9T)")
    r = run("export", *files, "--out", str(tmp_path / "out"), "--format", "rinex")
    assert r.returncode == 2 and r.stderr == f"{why}; nothing written\n", r.stderr
    assert not (tmp_path / "out").exists()
    r = run("export", *files, "--out", str(tmp_path / "both"), "--format", "ubx,rinex")
    ubx = next((tmp_path / "both").glob("*.ubx"))
    assert r.returncode == 2 and r.stderr == f"{why}; wrote only {ubx} and {ubx}.json\n", r.stderr
    assert ubx.read_bytes() == gga * 5 and sorted(p.name for p in (tmp_path / "both").iterdir()) == [
        ubx.name, f"{ubx.name}.json"]
    # Into a folder holding an earlier export of another stream: RINEX alone touches nothing there.
    (tmp_path / "both" / f"{ubx.stem}.obs").write_text("an earlier export's observations\n")
    before = {p.name: p.read_bytes() for p in (tmp_path / "both").iterdir()}
    ubx.write_bytes(b"an earlier stream")
    before[ubx.name] = b"an earlier stream"
    r = run("export", *files, "--out", str(tmp_path / "both"), "--format", "rinex")
    assert r.returncode == 2 and r.stderr == f"{why}; nothing written\n", r.stderr
    assert {p.name: p.read_bytes() for p in (tmp_path / "both").iterdir()} == before


def test_lost_records_a_reopened_port_and_a_silence_are_noted_beside_the_stream(tmp_path: Path) -> None:
    rec = Recorder(RecorderSettings(out_dir=tmp_path / "rec", min_free_bytes=0), TOPICS)
    rec.start()
    chunks = [(0, b"A" * 100), (100, b"B" * 50), (400, b"C" * 10), (0, b"D" * 20), (20, b"E" * 5)]
    t_mono = [0, 1, 2, 8, 15]  # seconds: the port reopened after 6 s, then 7 s of silence
    for (offset, data), t in zip(chunks, t_mono, strict=True):
        rec.submit(GNSS_RAW, raw_bytes_record(t * 10**9, data, offset), START_NS + t * 10**9, t * 10**9)
    rec.stop()
    r = run("export", *map(str, (tmp_path / "rec").glob("*.mcap")), "--out", str(tmp_path / "out"), "--format", "ubx")
    assert r.returncode == 0, r.stderr
    ubx = next((tmp_path / "out").glob("*.ubx"))
    assert ubx.read_bytes() == b"A" * 100 + b"B" * 50 + b"C" * 10 + b"D" * 20 + b"E" * 5
    gaps = json.loads((tmp_path / "out" / f"{ubx.name}.json").read_text())["gaps"]
    assert [(g["kind"], g["at_byte"], g["bytes_lost"]) for g in gaps] == [
        ("lost", 150, 250), ("reopened", 160, None), ("silence", 180, None)]
    assert gaps[0]["detail"] == "250 bytes the port gave were not recorded (the recorder dropped records)"
    assert "gaps: 1 lost, 1 reopened, 1 silence" in r.stdout


def test_a_drive_without_raw_bytes_says_so(tmp_path: Path) -> None:
    rec = Recorder(RecorderSettings(out_dir=tmp_path / "rec", min_free_bytes=0), TOPICS)
    rec.start()
    rec.submit("/baro", {"x": 1}, START_NS, 0)
    rec.stop()
    files = [str(p) for p in (tmp_path / "rec").glob("*.mcap")]
    r = run("export", *files, "--out", str(tmp_path / "out"), "--format", "ubx")
    assert r.returncode == 2 and r.stderr == f"logger export: no {GNSS_RAW} messages in {files[0]}\n"
    assert not list((tmp_path / "out").glob("*.ubx"))


# ---------------------------------------------------------------------------------------------------------------
# The whole daemon on the simulated vehicle


def simulated_drive(base: Path, model: str, duration_s: float) -> tuple[bytes, list[Path], list[str], dict, int]:
    """A drive with raw observations asked for of a simulated ``model``, its receiver's log of what it sent, the
    log lines of the run, a status snapshot three quarters into it and the baud rate the receiver ran at."""
    cfg = defaults(sim=True)
    cfg.values["logger"].update(out_dir=str(base / "rec"), status_socket=str(base / "status.sock"),
                                state_dir=str(base / "state"))
    cfg.values["sim"].update(scenario="urban", seed=4, time_scale=4.0, receiver_model=model)
    cfg.values["gnss"]["raw_observations"] = True
    cfg.values["nav"]["enabled"] = False
    daemon, vehicle = build(cfg, duration_s)
    sent = io.BytesIO()
    vehicle.gnss.raw_frames = lambda rec: [rawx(rec)]  # one measurement an epoch: enough to count
    vehicle.gnss.sent_log = sent  # before the daemon opens the port: everything from here on
    lines: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: lines.append(record.getMessage())  # type: ignore[method-assign]
    watched = logging.getLogger("logger")
    level = watched.level
    watched.addHandler(handler)
    watched.setLevel(logging.INFO)
    snapshots: list[dict] = []
    runner = threading.Thread(target=daemon.run, args=(duration_s,), daemon=True)
    try:
        runner.start()
        while runner.is_alive():
            time.sleep(0.5)
            if daemon.ready.is_set():
                snapshots.append(daemon.snapshot())
        runner.join(120)
    finally:
        watched.removeHandler(handler)
        watched.setLevel(level)
    assert not runner.is_alive()
    return sent.getvalue(), sorted((base / "rec").glob("*.mcap")), lines, snapshots[len(snapshots) * 3 // 4], \
        vehicle.gnss.baud


@pytest.mark.slow_on_board
def test_the_export_holds_every_byte_the_simulated_m8t_sent_after_the_setup(tmp_path: Path) -> None:
    sent, files, lines, snap, baud = simulated_drive(tmp_path, "NEO-M8T", 30.0)
    assert baud == 115200  # raised for the raw observations
    assert any("raw observations (RXM-RAWX, RXM-SFRBX) on at 115200 baud" in line for line in lines)
    assert not any("refused" in line for line in lines)
    gnss_line = gnss_row(snap)
    # The rate over the status window: 1 Hz, or a hair under it where a loaded host read an epoch late.
    raw_hz = re.search(r", raw ([\d.]+) Hz, ", gnss_line)
    assert raw_hz and 0.9 <= float(raw_hz.group(1)) <= 1.1 and len(gnss_line) < 80, gnss_line
    assert not any("raw observations" in p for p in snap["problems"])
    out = tmp_path / "out"
    r = run("export", *map(str, files), "--out", str(out), "--format", "ubx")
    assert r.returncode == 0, r.stderr
    exported = next(out.glob("*.ubx")).read_bytes()
    notes = json.loads(next(out.glob("*.ubx.json")).read_text())
    # Nothing lost and the port never reopened (a host loaded by other work may read late enough for a silence).
    assert [g for g in notes["gaps"] if g["kind"] != "silence"] == [], notes["gaps"]
    assert notes["bad_checksum"] == 0 and notes["garbage_bytes"] == 0
    assert notes["messages"]["RXM-RAWX"] >= 25 and notes["messages"]["NAV-PVT"] >= 25
    # The host read everything the receiver sent from the end of its set-up on: the export is one run of the
    # receiver's own log, starting right after the set-up's last answer (the ACK of RXM-SFRBX on, after the
    # MON-VER that confirmed the new speed; at most the rest of one epoch's output read by the set-up with it)
    # and ending within the last second of the drive (what came after the daemon's last read).
    start = sent.find(exported)
    assert start >= 0, "the export is not a contiguous run of what the receiver sent"
    setup_part, tail = sent[:start], sent[start + len(exported):]
    ack_sfrbx = bytes.fromhex("b562050102000601") + b"\x0f\x38"  # ACK-ACK of CFG-MSG, as the log shows it
    assert setup_part.rfind(b"\xb5\x62\x0a\x04") < setup_part.rfind(ack_sfrbx)
    assert len(setup_part) - (setup_part.rfind(ack_sfrbx) + len(ack_sfrbx)) < 600
    per_s = len(exported) / notes["messages"]["NAV-PVT"]  # the receiver's output a second
    assert len(tail) < 8 * per_s, (len(tail), per_s)  # what came while the daemon stopped: seconds, not more


def gnss_row(snap: dict) -> str:
    """The receiver's line of ``logger status`` on an 80-column terminal (not its row in the sensor table)."""
    from logger.cli.status_view import render

    return next(line for line in render(snap, width=80).splitlines()
                if line.startswith("gnss    ") and "reported" in line)


@pytest.mark.slow_on_board
def test_a_simulated_m8n_refuses_raw_observations_with_one_warning(tmp_path: Path) -> None:
    sent, _, lines, snap, baud = simulated_drive(tmp_path, "NEO-M8N", 25.0)
    assert baud == 115200  # the speed goes up before they are asked for, so it does for a receiver that refuses
    refusals = [line for line in lines if "refused raw observations" in line]
    assert refusals == ["gnss: the receiver refused raw observations, RXM-RAWX on (ACK-NAK to UBX-CFG-MSG and "
                        "UBX-CFG-VALSET CFG-MSGOUT-UBX-RXM-RAWX-UART1): its firmware has none (an M8N; M8T, M8P, "
                        "F9P and F9T do); recording without them"]
    assert b"\xb5\x62\x02\x15" not in sent  # nothing raw ever left the receiver
    assert any(p.startswith("gnss: no raw observations (RXM-RAWX) in ") for p in snap["problems"]), snap["problems"]
    gnss_line = gnss_row(snap)
    assert ", raw none yet, " in gnss_line
    assert snap["verdict"] == "degraded"


def test_bytes_in_a_damaged_chunk_are_not_blamed_on_the_recorder(m8t_drive: tuple[bytes, list[Path]],
                                                                 tmp_path: Path) -> None:
    """A chunk of the drive damaged at the office (a flipped byte: its CRC fails, the reader skips it): the bytes it
    held are missing from the .ubx, and the notes said "the recorder dropped records", which it did not."""
    _, files = m8t_drive
    copies = []
    for f in files:
        shutil.copy(f, tmp_path / f.name)
        copies.append(tmp_path / f.name)
    victim = copies[len(copies) // 2]
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside a chunk's compressed records
    victim.write_bytes(bytes(data))
    r = run("export", *map(str, copies), "--out", str(tmp_path / "out"), "--format", "ubx")
    assert r.returncode == 0 and f"{victim}: " in r.stderr, r.stderr  # the read's note names the damage
    notes = json.loads(next((tmp_path / "out").glob("*.ubx.json")).read_text())
    kinds = [g["kind"] for g in notes["gaps"]]
    assert kinds and set(kinds) == {"damaged"}, notes["gaps"]
    assert all("damaged chunk" in g["detail"] and "recorder" not in g["detail"] for g in notes["gaps"])
