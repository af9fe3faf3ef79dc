"""A post-processed GNSS solution (RTKLIB's .pos) into the filter: the parser on files the real ``rnx2rtkp`` wrote in
every layout it has, the join through GNSS time, the noise per quality, and ``logger replay --gnss-solution``."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_nav_filter import errors, run
from test_nav_synth import NS, T0_NS, records

from logger.nav import earth
from logger.nav.engine import NavEngine
from logger.nav.inputs import GnssObservation, SolutionEpoch
from logger.nav.measurements import Observation
from logger.nav.params import NavParams
from logger.nav.solution import solution_covariance, whitened
from logger.recording.records import feed_record, nav_feeder
from logger.recording.rtklib_pos import SolutionFileError, read_pos, unix_ns_utc
from sensors.sim.scenarios import make_drive

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "rtklib"
sys.path.insert(0, str(ROOT / "tools"))

import ppk_synth  # noqa: E402

KINEMATIC = ["kinematic-llh-gpst.pos", "kinematic-llh-utc-d1.pos", "kinematic-llh-jst.pos", "kinematic-llh-tow.pos",
             "kinematic-xyz-gpst.pos", "kinematic-enu-gpst.pos", "kinematic-dms-gpst.pos"]


def truth_ecef() -> dict[int, tuple[float, float, float]]:
    """The rover's true position per epoch of the fixtures (Unix ns UTC: GPST less 18 s in 2018)."""
    out = {}
    for line in (DATA / "truth.csv").read_text().splitlines()[1:]:
        week, tow, x, y, z = line.split(",")
        gps_s = int(week) * 604800 + round(float(tow))
        out[(gps_s + 315964800 - 18) * NS] = (float(x), float(y), float(z))
    return out


def error_ned(ep: SolutionEpoch, truth: dict[int, tuple[float, float, float]]) -> tuple[float, float, float]:
    lat, lon, h = earth.llh_from_ecef(*truth[ep.gnss_time_ns])
    return earth.ned_offset_m(lat, lon, h, math.radians(ep.lat_deg), math.radians(ep.lon_deg), ep.height_m)


# ---- the parser on rnx2rtkp's own files ------------------------------------------------------------------------
@pytest.mark.skipif(shutil.which("rnx2rtkp") is None, reason="rnx2rtkp (Debian's rtklib) is not installed")
def test_the_fixtures_are_what_rnx2rtkp_writes_today(tmp_path: Path):
    """make.sh again with this machine's rnx2rtkp: the same files, byte for byte (the README's recipe holds)."""
    r = subprocess.run(["sh", str(DATA / "make.sh"), str(tmp_path)], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHON": sys.executable})
    assert r.returncode == 0, r.stderr
    made = sorted(p.name for p in tmp_path.iterdir())
    assert made == [*sorted(p.name for p in DATA.glob("*.pos")), "truth.csv"] and len(made) == 12
    for name in made:
        assert (tmp_path / name).read_bytes() == (DATA / name).read_bytes(), name


@pytest.mark.parametrize(("name", "quality", "bound_m"), [
    ("kinematic-llh-gpst.pos", 1, 0.02), ("float-llh-gpst.pos", 2, 1.5), ("dgps-llh-gpst.pos", 4, 2.0),
    ("single-llh-gpst.pos", 5, 5.0), ("single-xyz-utc.pos", 5, 5.0)])
def test_every_quality_rnx2rtkp_gave_is_read_at_the_true_position(name: str, quality: int, bound_m: float):
    sol = read_pos(DATA / name)
    truth = truth_ecef()
    assert len(sol.epochs) == 20 and set(truth) >= {e.gnss_time_ns for e in sol.epochs}
    assert sol.epochs[-1].quality == quality and all(e.num_sv == 8 for e in sol.epochs)
    worst = max(max(abs(v) for v in error_ned(e, truth)) for e in sol.epochs if e.quality == quality)
    assert worst < bound_m
    sd = math.sqrt(sol.epochs[-1].cov_ned_m2[0][0])
    assert {1: 0.005 < sd < 0.01, 2: 0.05 < sd < 0.5, 4: 0.3 < sd < 1.5, 5: 5.0 < sd < 15.0}[quality]


def test_the_kinematic_solution_fixes_after_one_float_epoch_and_carries_its_ratio():
    sol = read_pos(DATA / "kinematic-llh-gpst.pos")
    assert sol.counts() == {"float": 1, "fix": 19} and sol.time_system == "GPST" and sol.position_format == "llh"
    assert sol.epochs[0].quality == 2 and sol.epochs[0].ratio == 2.9 and sol.epochs[1].ratio == 7.1
    assert sol.epochs[0].age_s == 0.0


@pytest.mark.parametrize("name", KINEMATIC[1:])
def test_every_time_system_and_layout_gives_the_same_epochs(name: str):
    """GPST, UTC, JST, week/tow; llh in degrees or d m s, ECEF xyz, e/n/u from the base: one solution."""
    ref = read_pos(DATA / KINEMATIC[0]).epochs
    sol = read_pos(DATA / name)
    assert [e.gnss_time_ns for e in sol.epochs] == [e.gnss_time_ns for e in ref]
    for a, b in zip(sol.epochs, ref, strict=True):
        d = earth.ned_offset_m(math.radians(b.lat_deg), math.radians(b.lon_deg), b.height_m,
                               math.radians(a.lat_deg), math.radians(a.lon_deg), a.height_m)
        assert max(abs(v) for v in d) < 2e-4 and a.quality == b.quality and a.num_sv == b.num_sv
        # Four decimals of a standard deviation (+-5e-5 m): the covariances agree to what the files print.
        scale = math.sqrt(max(b.cov_ned_m2[i][i] for i in range(3)))
        assert np.allclose(a.cov_ned_m2, b.cov_ned_m2, rtol=0.0, atol=2.5e-4 * scale)


def test_time_systems_and_leap_seconds():
    import datetime as dt

    t = dt.datetime(2018, 10, 25, 20, 56, 13)
    utc = unix_ns_utc(t, "UTC")
    assert unix_ns_utc(t, "GPST") == utc - 18 * NS
    assert unix_ns_utc(t, "JST") == utc - 9 * 3600 * NS
    assert unix_ns_utc(dt.datetime(2016, 6, 1), "GPST") == unix_ns_utc(dt.datetime(2016, 6, 1), "UTC") - 17 * NS
    # The leap second at the end of 2016: GPST 2017-01-01 00:00:17 was UTC 2016-12-31 23:59:60, which Unix
    # time folds onto 2017-01-01 00:00:00; a second later GPST is 18 s ahead.
    assert unix_ns_utc(dt.datetime(2017, 1, 1, 0, 0, 18), "GPST") == unix_ns_utc(dt.datetime(2017, 1, 1), "UTC")
    assert read_pos(DATA / "kinematic-llh-gpst.pos").epochs[0].gnss_time_ns == utc - 18 * NS + 0


def test_cross_terms_are_squared_back_with_their_sign():
    """sdne -0.0041, sdeu 0.0054, sdun -0.0065 (RTKLIB's sign(c) sqrt(|c|)): c_ne < 0, and down is minus up."""
    line = (DATA / "kinematic-llh-gpst.pos").read_text().splitlines()
    assert "   0.0077   0.0061   0.0151  -0.0041   0.0054  -0.0065" in line[11]
    c = read_pos(DATA / "kinematic-llh-gpst.pos").epochs[1].cov_ned_m2
    assert c[0][0] == pytest.approx(0.0077**2) and c[2][2] == pytest.approx(0.0151**2)
    assert c[0][1] == c[1][0] == pytest.approx(-(0.0041**2))
    assert c[1][2] == pytest.approx(-(0.0054**2)) and c[0][2] == pytest.approx(0.0065**2)
    assert np.all(np.linalg.eigvalsh(np.array(c)) > 0.0)


# ---- files that are not a solution: one line naming the file and the line --------------------------------------
@pytest.mark.parametrize(("text", "says"), [
    ("2018/10/25 20:56:13.000   44.06 -121.31 1100.0 1 8\n", ":1: a solution line before the column header"),
    ("$GPGGA,205613.00,4403.6,N,12118.6,W,4,08,1.0,1100.0,M,0.0,M,,*5B\n", ":1: an NMEA sentence"),
    ("%  GPST  latitude(deg) longitude(deg) height(m) Q ns\n2018/10/25 20:56:13.000 44.06 -121.31 1100 9 8\n",
     ":2: quality Q 9 is none of RTKLIB's"),
    ("%  GPST  latitude(deg) longitude(deg) height(m) Q ns\n2018/13/45 20:56:13.000 44.06 -121.31 1100 1 8\n",
     ":2: the time is neither"),
    ("%  GPST  latitude(deg) longitude(deg) height(m) Q ns\n2018/10/25 20:56:13.000 44.06 -121.31\n",
     ":2: 2 fields after the time"),
    ("%  GPST  latitude(deg) longitude(deg) height(m) Q ns\n2018/10/25 20:56:13.000 44.06 x 1100 1 8\n",
     ":2: not a number: 'x'"),
    ("%  GPST  e-baseline(m) n-baseline(m) u-baseline(m) Q ns\n2018/10/25 20:56:13.000 1 2 3 1 8\n",
     ":2: e/n/u baselines without '% ref pos'"),
    ("% just a comment\n", ": no solution epochs"),
])
def test_a_bad_file_is_one_line_naming_the_file_and_the_line(tmp_path: Path, text: str, says: str):
    f = tmp_path / "bad.pos"
    f.write_text(text)
    with pytest.raises(SolutionFileError) as e:
        read_pos(f)
    assert str(e.value).startswith(f"{f}{says}") and "\n" not in str(e.value)


def test_a_binary_or_missing_file_is_one_line(tmp_path: Path):
    f = tmp_path / "drive.mcap"
    f.write_bytes(b"\x89MCAP0\r\n\xff\xfe")
    with pytest.raises(SolutionFileError, match=r"drive.mcap: not a text file"):
        read_pos(f)
    with pytest.raises(SolutionFileError, match=r"nothing.pos: No such file"):
        read_pos(tmp_path / "nothing.pos")


# ---- the join through GNSS time and the noise --------------------------------------------------------------
def fix_msg(gnss_s: float, arrival_s: float, state: str) -> GnssObservation:
    t = T0_NS + round(arrival_s * NS)
    return GnssObservation(t, t - T0_NS, T0_NS + round(gnss_s * NS), state, True, 3, 37.0, 127.0, 50.0,
                           (10.0, 0.0, 0.0), 1.0, 2.0, 0.1, 1.2, 18)


def epoch_at(gnss_s: float, q: int = 1) -> SolutionEpoch:
    return SolutionEpoch(T0_NS + round(gnss_s * NS), 37.0, 127.0, 50.0, ((1e-4, 0, 0), (0, 1e-4, 0), (0, 0, 4e-4)),
                         q, 12)


@pytest.mark.parametrize("state", ["locked", "freerun"])
def test_solution_epochs_are_placed_through_the_receiver_time_and_go_in_at_their_epoch(state: str):
    """Not by arrival: 5 Hz solution epochs between 1 Hz fixes land at their GNSS epoch on the logger's clock, with
    the offset the receiver's fix was placed with (locked: none; free-running: the shortest delay's), and are due
    as soon as the IMU reaches them, not when the receiver's fix arrives 0.3 s later."""
    engine = NavEngine(NavParams())
    engine.use_solution([epoch_at(k * 0.2) for k in range(16)] + [epoch_at(400.0)])
    sol = engine.solution
    assert sol is not None and sol.due(T0_NS + 10 * NS, 0) == []  # no receiver time yet: nothing placed
    engine.gnss(fix_msg(1.0, 1.3, state))
    offset_ms = 0 if state == "locked" else 200  # free-running: the shortest delay (0.3 s) less 0.1 s of latency
    assert engine.epoch_clock.offset_ns == offset_ms * 1_000_000
    placed = sol.due(T0_NS + round(1.3 * NS), 0)
    assert [round((t - T0_NS) / 1e6) for _, t, _ in placed] == list(range(offset_ms, 1301, 200))
    assert all(t_mono == t - T0_NS for _, t, t_mono in placed)
    assert sol.next_ns == T0_NS + (len(placed) * 200 + offset_ms) * 1_000_000  # the next one, in the IMU's time
    left = 16 - len(placed)
    assert sol.due(T0_NS + 6 * NS, T0_NS + round(3.5 * NS)) == [] and sol.before_start == left  # filter not started
    # Past the fix's offset's lifetime (MAP_STALE_S) nothing is placed until a receiver fix with a time comes.
    assert sol.due(T0_NS + 400 * NS, 0) == [] and sol.next_ns > T0_NS + 10**6 * NS
    engine.gnss(fix_msg(399.0, 399.3, state))
    assert [ep.gnss_time_ns for ep, _, _ in sol.due(T0_NS + 401 * NS, 0)] == [T0_NS + 400 * NS]


def test_each_quality_has_its_floor_and_float_errors_last():
    raw = ((1e-6, 0.0, 0.0), (0.0, 1e-6, 0.0), (0.0, 0.0, 1e-6))
    fixed = solution_covariance(SolutionEpoch(0, 0, 0, 0, raw, 1, 9), 1.0)
    assert np.sqrt(np.diag(fixed)).tolist() == pytest.approx([0.015, 0.015, 0.03])
    flt = solution_covariance(SolutionEpoch(0, 0, 0, 0, raw, 2, 9), 1.0)
    single = solution_covariance(SolutionEpoch(0, 0, 0, 0, raw, 5, 9), 1.0)
    assert np.sqrt(flt[0, 0]) > 0.1 * 4 and np.sqrt(single[0, 0]) > 1.0 * 3  # correlated: 1 Hz is not independent
    assert np.sqrt(solution_covariance(SolutionEpoch(0, 0, 0, 0, raw, 2, 9), 30.0)[0, 0]) == pytest.approx(0.1)


def test_a_whitened_update_is_the_update_with_the_full_covariance():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((3, 3))
    r = a @ a.T + 0.1 * np.eye(3)
    p = np.diag([4.0, 3.0, 2.0, 1.0])
    h = rng.standard_normal((3, 4))
    z = rng.standard_normal(3)
    w = whitened(Observation("x", z, h, np.ones(3)), r)
    k_full = p @ h.T @ np.linalg.inv(h @ p @ h.T + r)
    k_w = p @ w.h.T @ np.linalg.inv(w.h @ p @ w.h.T + np.diag(w.r))
    assert np.allclose(k_full @ z, k_w @ w.z) and np.allclose(k_full @ h @ p, k_w @ w.h @ p)


# ---- a short drive: the fixed solution against the receiver's fixes ----------------------------------------------
@pytest.fixture(scope="module")
def drive_with_ppk(tmp_path_factory: pytest.TempPathFactory):
    """Four minutes of the outage drive (before its outage) with u-blox-like fixes (0.5 m, 1 m), and a PPK
    solution from the truth with 2 cm errors, written by ppk_synth in rnx2rtkp's layout and read back."""
    drive = make_drive("outage-60s", seed=1, duration_s=110.0)
    recs = records(drive, 110.0, seed=4)
    pos = tmp_path_factory.mktemp("ppk") / "drive.pos"
    ppk_synth.write_pos(pos, ppk_rows(drive))
    return drive, recs, pos


def ppk_rows(drive, north_m: float = 0.0) -> list[str]:
    """A fixed solution of the drive's truth with 2 cm errors, in rnx2rtkp's layout; ``north_m``: that far north
    of it all the time (another vehicle's track at the same hours)."""
    rng = np.random.default_rng(8)
    rows = []
    for k in range(111):
        s = drive.state(float(k))
        err = rng.standard_normal(3) * (0.02, 0.02, 0.04) + (north_m, 0.0, 0.0)
        rows.append(ppk_synth.pos_row(T0_NS + k * NS, s.lat_rad, s.lon_rad, s.height_m, err, 1, 14,
                                      (0.007, 0.006, 0.014), -0.2, 12.0))
    return rows


def rms_moving(drive, rows) -> np.ndarray:
    t, e, _ = errors(drive, rows)
    moving = np.array([drive.state(v).forward_speed_mps > 1.0 for v in t])
    return np.sqrt(np.mean(e[moving & (t > 40.0)] ** 2, axis=0))


def test_the_fixed_solution_beats_the_receiver_fixes(drive_with_ppk):
    drive, recs, pos = drive_with_ppk
    sol = read_pos(pos)
    assert sol.counts() == {"fix": 111} and sol.time_system == "GPST"
    live = rms_moving(drive, run(recs).rows)
    engine = NavEngine(NavParams(), record=True)
    engine.use_solution(sol.epochs)
    feed = nav_feeder(engine)
    for _, topic, msg in recs:
        feed_record(feed, topic, msg)
    ppk = rms_moving(drive, engine.rows)
    assert engine.ekf is not None and engine.ekf.stats["solution_pos"].accepted > 60
    assert "gnss_pos" not in engine.ekf.stats  # replaced: the receiver's positions stay out
    assert np.all(ppk < 0.05) and np.all(ppk < live / 3), (ppk, live)


def test_replay_fuses_the_solution_and_says_so(drive_with_ppk, tmp_path: Path):
    from logger.recording.recorder import Recorder
    from logger.recording.settings import RecorderSettings
    from logger.recording.topics import TOPICS

    drive, recs, pos = drive_with_ppk
    rec = Recorder(RecorderSettings(out_dir=tmp_path / "drive"), TOPICS)
    rec.start()
    for t, topic, msg in recs:
        assert rec.submit(topic, msg, t, msg["t_mono_ns"])
    rec.stop()
    files = [str(f) for f in sorted((tmp_path / "drive").glob("*.mcap"))]

    def replay(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "logger.cli", "replay", *files, *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=120)

    # Beside the receiver's fixes, with 20 s of the solution missing: the receiver's positions, left out as
    # uninformative while 2 cm epochs come, fill the gap.
    lines = pos.read_text().splitlines()
    gapped = tmp_path / "gapped.pos"
    gapped.write_text("\n".join(lines[:9 + 60] + lines[9 + 80:]) + "\n")
    r = replay("--out", str(tmp_path / "out"), "--gnss-solution", str(gapped), "--gnss-solution-mode", "add",
               "--smooth", "--no-mcap")
    assert r.returncode == 0, r.stderr
    assert "GNSS solution gapped.pos (GPST, llh: 91 fix), beside the receiver's positions: used 75 fix" in r.stdout
    accepted = dict(w.split() for w in r.stdout.split("updates accepted: ")[1].splitlines()[0].split(", "))
    assert int(accepted["solution_pos"].split("/")[0]) >= 70 and int(accepted["gnss_pos"].split("/")[0]) >= 5
    bad = tmp_path / "bad.pos"
    bad.write_text(pos.read_text().replace(" 1  14 ", " 7  14 ", 1))
    r = replay("--out", str(tmp_path / "out2"), "--gnss-solution", str(bad))
    assert r.returncode == 2 and r.stdout == "" and not (tmp_path / "out2").exists()
    assert r.stderr.startswith(f"logger replay: {bad}:10: quality Q 7 is none of RTKLIB's") and \
        r.stderr.count("\n") == 1
    r = replay("--out", str(tmp_path / "out3"), "--gnss-solution", str(tmp_path / "missing.pos"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "missing.pos: No such file" in r.stderr
    # A solution of the next day: no epoch of it goes in (in replace mode not even the receiver's positions), which
    # is an error, not a trajectory; an earlier run's trajectory in the folder is left as it was.
    next_day = tmp_path / "next_day.pos"
    next_day.write_text("".join(line[:8] + f"{int(line[8:10]) + 1:02d}" + line[10:] if line[:1].isdigit() else line
                                for line in pos.read_text().splitlines(keepends=True)))
    for mode in ("replace", "add"):
        r = replay("--out", str(tmp_path / "out"), "--gnss-solution", str(next_day), "--gnss-solution-mode", mode,
                   "--no-mcap")
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
        assert r.stderr.startswith(f"logger replay: --gnss-solution {next_day}: none of its 111 epochs was used "
                                   "(111 after the drive's end): it spans "), r.stderr
        assert r.stderr.endswith(f"; nothing written to {tmp_path / 'out'}\n")
    assert (tmp_path / "out" / "trajectory.csv").stat().st_mtime_ns < next_day.stat().st_mtime_ns
    # Another vehicle's solution of the same minutes, 200 m north all along: its times pass, its positions do not
    # (fused, the gate refused most and the filter reset onto the rest, exit 0 and "used 111 fix").
    other = tmp_path / "other_vehicle.pos"
    ppk_synth.write_pos(other, ppk_rows(drive, north_m=200.0))
    r = replay("--out", str(tmp_path / "out"), "--gnss-solution", str(other), "--no-mcap")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    assert "its positions lie a median 200 m from the receiver's own fixes at the same GNSS epochs" in r.stderr
    assert (tmp_path / "out" / "trajectory.csv").stat().st_mtime_ns < other.stat().st_mtime_ns
    # Epochs on too few satellites are named among those not used (the summary's counts add up to the file's).
    few = tmp_path / "few_sv.pos"
    few_lines = pos.read_text().splitlines(keepends=True)
    data_at = [i for i, line in enumerate(few_lines) if line[:1].isdigit()]
    for i in data_at[40:60]:
        few_lines[i] = few_lines[i].replace(" 1  14 ", " 5   4 ", 1)  # single point, 4 satellites
    few.write_text("".join(few_lines))
    r = replay("--out", str(tmp_path / "out4"), "--gnss-solution", str(few), "--no-mcap")
    assert r.returncode == 0, r.stderr
    (said,) = [line for line in r.stdout.splitlines() if line.startswith("GNSS solution few_sv.pos")]
    assert "20 on fewer than 5 satellites" in said, said
    used = int(said.split(": used ")[1].split(" fix")[0])
    left = [int(part.split()[0]) for part in said.split("; not used: ")[1].split("; ")]
    assert used + sum(left) == 111, said
    # GNSS-only mode has no filter to fuse a solution with, or to smooth: one line, exit 2 (a traceback before).
    for extra in (("--gnss-solution", str(pos)), ("--smooth",)):
        r = replay("--out", str(tmp_path / "out5"), "--mode", "gnss", *extra)
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and "needs the filter (mode 15 or 17)" in r.stderr
    # --no-mcap into a folder holding an earlier run's trajectory.mcap: removed with the run's CSV, and said.
    r = replay("--out", str(tmp_path / "out6"))
    assert r.returncode == 0 and (tmp_path / "out6" / "trajectory.mcap").exists(), r.stderr
    r = replay("--out", str(tmp_path / "out6"), "--no-mcap", "--mode", "15")
    assert r.returncode == 0 and not (tmp_path / "out6" / "trajectory.mcap").exists(), r.stderr
    assert f"removed {tmp_path / 'out6' / 'trajectory.mcap'}: an earlier run's (--no-mcap writes none)" in r.stdout


def test_a_filter_lost_with_a_solution_restarts_from_its_epochs(drive_with_ppk):
    """300 m off with its covariance still confident: the solution's epochs, refused in a row and agreeing, restart
    the filter from them (velocity kept: a .pos has none), and it is back on the solution."""
    drive, recs, pos = drive_with_ppk
    engine = NavEngine(NavParams(), record=True)
    engine.use_solution(read_pos(pos).epochs)
    feed = nav_feeder(engine)
    done = False
    for _, topic, msg in recs:
        feed_record(feed, topic, msg)
        if not done and engine.state is not None and (msg["t_sync_ns"] - T0_NS) / 1e9 > 60.0:
            engine.state.lat += 300.0 / 6.36e6
            done = True
    assert done and engine.counters.resets == 1 and engine.ekf is not None
    t, e, sig = errors(drive, engine.rows)
    late = t > 90.0
    assert np.all(np.isfinite(sig)) and np.abs(e[late]).max() < 0.1


def test_the_foreign_check_takes_a_receiver_labelling_its_epochs_seconds_off_for_the_same_drive():
    """A cold start's receiver counts leap seconds by its firmware's default (and says so: leap_unknown): its
    epochs are labelled a second or more off the solution's (GPST, from the raw observations). At 33 m/s a second
    is 33 m, and the drive's own solution was refused as another vehicle's; for such fixes the nearest of the
    solution's epochs within 3 s is compared. Without the word, a track a second behind is another car's (on the
    same road: 33 m), and one 5 s behind is another whatever the receiver said."""
    from logger.nav.solution import FOREIGN_SOLUTION_M, SolutionPolicy

    lat0, speed = math.radians(48.0), 33.0
    epochs = [SolutionEpoch(T0_NS + k * NS, math.degrees(lat0 + k * speed / earth.A), 11.0, 300.0,
                            ((1e-4, 0.0, 0.0), (0.0, 1e-4, 0.0), (0.0, 0.0, 4e-4)), 1, 12) for k in range(120)]
    for labels_off_s, said, foreign in ((0, False, False), (1, True, False), (-3, True, False), (1, False, True),
                                        (5, True, True)):
        policy = SolutionPolicy(epochs, True, None, None)  # type: ignore[arg-type]  # map and foreign alone
        for k in range(10, 110):  # the receiver's fix of epoch k, labelled labels_off_s seconds off
            policy.map(T0_NS + (k + labels_off_s) * NS, 0, 0, lat0 + k * speed / earth.A, math.radians(11.0),
                       leap_unknown=said)
        assert len(policy.receiver_distances_m) == 100
        assert (policy.foreign() is not None) is foreign, (labels_off_s, said, policy.foreign())
    assert 5 * speed > FOREIGN_SOLUTION_M
