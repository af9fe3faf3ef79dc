"""``logger replay``'s two files: ``trajectory.csv`` with every row, written by the block, and ``trajectory.mcap``
with ``/nav/fix`` at a map's rate (``--fix-hz``, the live ``nav.publish_hz`` by default), its JSON filled into one
template. The values are held to what the row-at-a-time writers gave, to the byte."""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_nav_synth import records

from logger.exports.trajectory import BLOCK_ROWS, CSV_HEADER, columns, fix_rows, nav_fix_json, write_csv, write_mcap
from logger.nav.engine import TrajectoryRow
from logger.nav.params import NavParams
from logger.nav.rotations import dcm_from_quat, euler_from_dcm
from logger.recording.drive import read_messages
from logger.recording.intervals import GRID_TOLERANCE
from logger.recording.records import nav_fix_record
from sensors.sim.scenarios import make_drive

ROOT = Path(__file__).resolve().parents[1]
INF = math.inf


def random_rows(n: int, seed: int = 1) -> list[TrajectoryRow]:
    """Rows as the engine and the smoother give them: unit and not quite unit attitudes, numpy and Python
    floats, sigmas unknown (infinite) at the start."""
    rnd = random.Random(seed)
    rows = []
    t, t_mono = 1_796_210_195_239_415_122, 2_107_206_854_226
    for i in range(n):
        q = np.array([rnd.gauss(0, 1) for _ in range(4)])
        q = q / np.linalg.norm(q) * (1.0 + rnd.uniform(-1e-9, 1e-9))
        sig = (INF, INF, INF) if i < 3 else (rnd.uniform(0.01, 30), rnd.uniform(0.01, 30), rnd.uniform(0.01, 50))
        lat = math.radians(rnd.uniform(-89, 89))
        rows.append(TrajectoryRow(t, t_mono, np.float64(lat) if i % 2 else lat, math.radians(rnd.uniform(-180, 180)),
                                  rnd.uniform(-400, 4000), rnd.uniform(-40, 40), np.float64(rnd.uniform(-40, 40)),
                                  rnd.uniform(-3, 3), tuple(q.tolist()) if i % 3 else tuple(q), sig, i // 10))
        step = 50_000_000 + rnd.randint(-3_000_000, 3_000_000)
        t, t_mono = t + step, t_mono + step
    return rows


def csv_a_row_at_a_time(rows: list[TrajectoryRow]) -> str:
    """trajectory.csv as it was written before the block writer: csv.writer, a row and its f-strings at a time."""
    out = io.StringIO(newline="")
    w = csv.writer(out)
    w.writerow(CSV_HEADER)
    for t, t_mono, lat, lon, h, vn, ve, vd, q, sig, _ in rows:
        roll, pitch, yaw = euler_from_dcm(dcm_from_quat(q))
        w.writerow([t, t_mono, f"{math.degrees(lat):.9f}", f"{math.degrees(lon):.9f}", f"{h:.3f}", f"{vn:.3f}",
                    f"{ve:.3f}", f"{vd:.3f}", f"{math.degrees(roll):.3f}", f"{math.degrees(pitch):.3f}",
                    f"{math.degrees(yaw):.3f}", f"{sig[0]:.3f}", f"{sig[1]:.3f}", f"{sig[2]:.3f}"])
    return out.getvalue()


def record_json(row: TrajectoryRow, source: str, mode: str) -> bytes:
    """A /nav/fix message as the record layer builds it, a row at a time."""
    t, t_mono, lat, lon, h, vn, ve, vd, q, sig, _ = row
    return json.dumps(nav_fix_record(t, t_mono, lat, lon, h, (vn, ve, vd), euler_from_dcm(dcm_from_quat(q)), sig,
                                     source, mode)).encode()


def test_columns_hold_the_values_a_row_at_a_time_gives_to_the_bit() -> None:
    rows = random_rows(500)
    cols = columns(rows)
    assert len(cols) == len(rows)
    for k, (t, t_mono, lat, lon, h, vn, ve, vd, q, sig, _) in enumerate(rows):
        roll, pitch, yaw = euler_from_dcm(dcm_from_quat(q))
        expect = [t, t_mono, math.degrees(lat), math.degrees(lon), h, vn, ve, vd, math.degrees(roll),
                  math.degrees(pitch), math.degrees(yaw), *sig]
        got = [col[k] for col in cols.table()]
        assert [float(v) for v in got] == [float(v) for v in expect] and got[:2] == [t, t_mono], k
    assert len(columns([])) == 0


@pytest.mark.parametrize("n", [0, 1, BLOCK_ROWS, 2 * BLOCK_ROWS + 17])
def test_the_csv_written_by_the_block_is_the_one_written_by_the_row(tmp_path: Path, n: int) -> None:
    rows = random_rows(n, seed=n)
    write_csv(tmp_path / "trajectory.csv", rows)
    data = (tmp_path / "trajectory.csv").read_bytes()
    assert data == csv_a_row_at_a_time(rows).encode()
    assert data.count(b"\r\n") == n + 1
    if n:
        assert b",inf,inf,inf\r\n" in data  # a sigma not yet known stays as it was written


def test_nav_fix_json_is_the_record_layers_json_to_the_byte() -> None:
    rows = random_rows(300, seed=7)
    # A filter gone astray: values JSON writes as NaN and Infinity, built the same as the record layer builds them.
    t, t_mono, _, lon, h, _, ve, vd, q, _, e = rows[-1]
    rows[-1] = TrajectoryRow(t, t_mono, math.nan, lon, h, INF, ve, vd, q, (math.nan, 2.0, INF), e)
    for source, mode in (("ins 17-state", "17"), ("gnss", "gnss")):
        got = nav_fix_json(columns(rows), source, mode)
        assert got == [record_json(r, source, mode) for r in rows]
    assert b'"latitude": NaN' in got[-1] and b'"sigma_ned_m": [1000000.0, 2.0, 1000000.0]' in got[-1]
    assert nav_fix_json(columns([]), "gnss", "gnss") == []


def test_fix_rows_keep_the_rate_asked() -> None:
    """One row per tick of a grid of the period: 20 Hz rows microseconds either side of 50 ms apart give /nav/fix at
    the rate asked, every interval a period (the rule "a period after the last written" made one in six 0.25 s at
    5 Hz); with jitter of milliseconds still one row per tick, each the first that is due."""
    rnd = random.Random(3)
    for jitter_ns in (2_000, 2_000_000):
        t = [0]
        for _ in range(2000):  # 20 Hz
            t.append(50_000_000 * len(t) + rnd.randint(-jitter_ns, jitter_ns))
        assert fix_rows(t, 0.0) == list(range(len(t)))
        for hz in (5.0, 10.0, 1.0, 0.3):
            period = round(1e9 / hz)
            tol = int(period * GRID_TOLERANCE)
            keep = fix_rows(t, hz)
            assert keep[0] == 0
            ticks = [(t[i] + tol) // period for i in keep]
            assert ticks == list(range(len(keep)))  # every tick once: the rate asked
            assert (t[-1] + tol) // period == ticks[-1]
            for a, b in itertools.pairwise(keep):
                assert all((t[i] + tol) // period == (t[a] + tol) // period for i in range(a + 1, b))  # first due
                if jitter_ns < tol and period % 50_000_000 == 0:  # ticks on rows: every interval a period
                    assert abs(t[b] - t[a] - period) <= 2 * jitter_ns
    sparse = list(range(0, 60 * 10**9, 10**9))  # GNSS-only rows, 1 Hz: every one is kept at 5 Hz
    assert fix_rows(sparse, 5.0) == list(range(len(sparse)))
    assert fix_rows([], 5.0) == []


# ---- the command on a drive ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    """A minute of urban drive written through the real recorder (no daemon: as fast as it can be written)."""
    from logger.recording.recorder import Recorder
    from logger.recording.settings import RecorderSettings
    from logger.recording.topics import TOPICS

    folder = tmp_path_factory.mktemp("drive")
    rec = Recorder(RecorderSettings(out_dir=folder), TOPICS)
    rec.start()
    for t, topic, msg in records(make_drive("urban", seed=2, duration_s=60.0), 60.0, seed=2):
        assert rec.submit(topic, msg, t, msg["t_mono_ns"])
    rec.stop()
    return [str(p) for p in sorted(folder.glob("*.mcap"))]


def replay(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "logger.cli", "replay", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def trajectory(out: Path) -> tuple[list[dict[str, str]], list[dict], list[dict]]:
    with open(out / "trajectory.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    msgs = list(read_messages([out / "trajectory.mcap"], ("/nav/fix", "/nav/state")))
    return rows, [m for t, m in msgs if t == "/nav/fix"], [m for t, m in msgs if t == "/nav/state"]


def test_replay_writes_nav_fix_at_the_live_rate_and_every_row_when_asked(drive: list[str], tmp_path: Path) -> None:
    r = replay(*drive, "--out", str(tmp_path / "default"))
    assert r.returncode == 0, r.stderr
    rows, fixes, states = trajectory(tmp_path / "default")
    times = [int(row["t_sync_ns"]) for row in rows]
    hz = NavParams().publish_hz
    keep = fix_rows(times, hz)
    assert len(rows) > 600 and len(keep) < len(rows) / 3  # 20 Hz rows, /nav/fix at 5 Hz
    assert [f["t_sync_ns"] for f in fixes] == [times[i] for i in keep]
    assert f"trajectory.mcap: /nav/fix at {hz:g} Hz, {len(keep)} of {len(rows)} solutions (--fix-hz 0: every one)" \
        in r.stdout
    # /nav/state once a second: the first solution of every whole second of the rows (one a second after the last
    # drifted by how late each came, 0.87-0.91 a second on recorded drives)
    seconds = [m["t_sync_ns"] // 1_000_000_000 for m in states]
    assert len(states) >= 40 and seconds == list(range(seconds[0], seconds[0] + len(seconds)))
    assert seconds[-1] == times[-1] // 1_000_000_000
    for i, f in zip(keep, fixes, strict=True):  # the values the CSV row has, at full precision
        row = rows[i]
        assert abs(f["latitude"] - float(row["lat_deg"])) <= 5e-10 and abs(f["altitude"] - float(row["height_m"])) \
            <= 5e-4
        assert [round(v, 3) for v in f["rpy_deg"]] == [float(row[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg")]
        assert f["source"] == "ins 17-state" and f["mode"] == "17"

    r = replay(*drive, "--out", str(tmp_path / "full"), "--fix-hz", "0")
    assert r.returncode == 0, r.stderr
    assert "trajectory.mcap: /nav/fix for every solution" in r.stdout
    _, full, full_states = trajectory(tmp_path / "full")
    assert (tmp_path / "full" / "trajectory.csv").read_bytes() == (tmp_path / "default" / "trajectory.csv").read_bytes()
    assert [f["t_sync_ns"] for f in full] == times and full_states == states
    assert [full[i] for i in keep] == fixes  # the thinned messages are the full rate's, unchanged

    r = replay(*drive, "--out", str(tmp_path / "fast"), "--fix-hz", "50")  # above the 20 Hz rows: every one
    assert r.returncode == 0, r.stderr
    assert "trajectory.mcap: /nav/fix for every solution (50 Hz is the solutions' own rate or more)" in r.stdout

    r = replay(*drive, "--out", str(tmp_path / "one"), "--fix-hz", "1", "--mode", "15")
    assert r.returncode == 0, r.stderr
    _, one, _ = trajectory(tmp_path / "one")
    assert 40 <= len(one) <= 60 and one[0]["mode"] == "15"


def test_replay_refuses_a_rate_that_is_none(drive: list[str], tmp_path: Path) -> None:
    for bad in ("-1", "fast", "nan", "1e-300"):  # 1e-300 passed and its period overflowed: a traceback
        r = replay(*drive, "--out", str(tmp_path / "x"), "--fix-hz", bad)
        assert r.returncode == 2 and "--fix-hz" in r.stderr and not (tmp_path / "x").exists()
        assert "Traceback" not in r.stderr, r.stderr


def test_an_output_path_that_cannot_be_a_folder_is_refused_before_the_run(drive: list[str], tmp_path: Path) -> None:
    """Said in one line before the filter runs (it was a traceback once the whole drive had been filtered)."""
    afile = tmp_path / "afile"
    afile.write_text("")
    for out, words in ((afile, f"--out {afile}: exists and is not a folder"),
                       (afile / "sub", f"--out {afile / 'sub'}: cannot be made, {afile} is a file and not a folder")):
        r = replay(*drive, "--out", str(out))
        assert r.returncode == 2 and r.stderr == f"logger replay: {words}\n" and r.stdout == "", r.stderr


def test_write_mcap_takes_the_engines_publish_rate_unless_told(tmp_path: Path) -> None:
    from logger.nav.engine import NavEngine

    rows = random_rows(400, seed=4)  # 20 s at 20 Hz
    times = [r.t_ns for r in rows]
    engine = NavEngine(NavParams(publish_hz=2.0))
    assert write_mcap(tmp_path / "a.mcap", rows, engine, []) == len(fix_rows(times, 2.0))
    got = [m["t_sync_ns"] for _, m in read_messages([tmp_path / "a.mcap"], ("/nav/fix",))]
    assert got == [times[i] for i in fix_rows(times, 2.0)]
    assert write_mcap(tmp_path / "b.mcap", rows, engine, [], fix_hz=0) == 400
    got = [m for _, m in read_messages([tmp_path / "b.mcap"], ("/nav/fix",))]
    assert [json.dumps(m).encode() for m in got] == [record_json(r, f"ins {engine.mode}-state", engine.mode)
                                                     for r in rows]


def test_the_cycle_collector_is_paused_only_for_the_work() -> None:
    import gc

    from logger.cli.replay import no_cycle_collector

    assert gc.isenabled()
    with pytest.raises(RuntimeError), no_cycle_collector():
        assert not gc.isenabled()
        raise RuntimeError("the filter failed")
    assert gc.isenabled()
    gc.disable()
    try:
        with no_cycle_collector():
            pass
        assert not gc.isenabled()  # left as the caller had it
    finally:
        gc.enable()


def test_a_replay_names_its_drive_and_is_never_read_beside_another(drive: list[str], tmp_path: Path) -> None:
    """trajectory.mcap begins with the run id of the drive it was made from: named beside another drive's files
    (export, plot), it is refused in one line instead of being drawn as that drive's; replay itself leaves a
    replay's output out, and says so."""
    from logger.recording.drive import replay_source, run_identity
    from logger.recording.recorder import Recorder
    from logger.recording.settings import RecorderSettings
    from logger.recording.topics import TOPICS

    r = replay(*drive, "--out", str(tmp_path / "r"))
    assert r.returncode == 0, r.stderr
    ours = tmp_path / "r" / "trajectory.mcap"
    run = run_identity(Path(drive[0]))
    assert run is not None and replay_source(ours) == run[0]

    rec = Recorder(RecorderSettings(out_dir=tmp_path / "other"), TOPICS)
    rec.start()
    for t, topic, msg in records(make_drive("urban", seed=3, duration_s=5.0), 5.0, seed=3):
        rec.submit(topic, msg, t, msg["t_mono_ns"])
    rec.stop()
    (other,) = sorted((tmp_path / "other").glob("*.mcap"))

    def export(*files: Path | str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "logger.cli", "export", *map(str, files), "--out",
                               str(tmp_path / "ex"), "--format", "csv"], cwd=ROOT, capture_output=True, text=True,
                              timeout=120)

    bad = export(other, ours)
    assert bad.returncode == 2, bad.stdout + bad.stderr
    assert bad.stderr == (f"logger export: {ours}: the replay of another drive (run {run[0]}), not of the one named "
                          f"(run {run_identity(other)[0]})\n")
    good = export(*drive, ours)
    assert good.returncode == 0, good.stderr
    again = replay(*drive, str(ours), "--out", str(tmp_path / "r2"))
    assert again.returncode == 0 and f"{ours} is a replay's output: left out" in again.stderr, again.stderr
    # nav-score: the replay's folder stands for its CSV, scored against the drive named
    score = subprocess.run([sys.executable, "-m", "logger.cli", "nav-score", str(tmp_path / "r"), str(other)],
                           cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert score.returncode == 2 and score.stderr == (
        f"logger nav-score: {tmp_path / 'r' / 'trajectory.csv'}: the replay of another drive (run {run[0]}), not "
        f"of the one named (run {run_identity(other)[0]})\n"), score.stderr

    def nav_score(*args: Path | str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "logger.cli", "nav-score", *map(str, args)], cwd=ROOT,
                              capture_output=True, text=True, timeout=120)

    # ... and a reference of another drive than the trajectory's or the drive's is refused too (it was scored
    # without a word: a kilometre's "RMSE", exit 0), whether the other drive's file or a replay's folder.
    other_run = run_identity(other)[0]
    score = nav_score(tmp_path / "r", "--reference", other)
    assert score.returncode == 2 and score.stderr == (
        f"logger nav-score: {other}: a reference of another drive (run {other_run}) than "
        f"{tmp_path / 'r' / 'trajectory.csv'}'s (run {run[0]})\n"), score.stderr
    score = nav_score(tmp_path / "r", *drive, "--reference", other)
    assert score.returncode == 2 and score.stderr == (
        f"logger nav-score: {other}: a reference of another drive (run {other_run}), not of the one named "
        f"(run {run[0]})\n"), score.stderr
    score = nav_score(tmp_path / "r", *drive, "--reference", tmp_path / "r2")  # the same drive's: scored
    assert score.returncode == 0, score.stderr
