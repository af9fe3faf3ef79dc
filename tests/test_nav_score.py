"""``logger nav-score`` on small synthetic drives: the time base a row is joined on, rows outside what they are
scored against, and inputs that are not what their place asks for (one line naming the file, no traceback)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
from mcap.writer import Writer

from logger.cli import nav_score as cli
from logger.recording.topics import GNSS_FIX, NAV_FIX, TOPICS, TRUTH_CLOCK, TRUTH_NAV

NS = 1_000_000_000
T0 = 1_796_463_760 * NS  # true time at board time MONO0
MONO0 = 100 * NS
DRIVE_S = 100  # the drive's truth covers board time 100-200 s
LAT0, LON0, H0 = 37.5, 127.0, 50.0
NORTH_DEG_PER_S = 1e-5  # about 1.1 m/s northwards


def lat_at(t_true_ns: int) -> float:
    return LAT0 + NORTH_DEG_PER_S * (t_true_ns - T0) / NS


def write_mcap(path: Path, topics: dict[str, list[dict]]) -> Path:
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        for topic, msgs in topics.items():
            cid = w.register_channel(topic, "json", w.register_schema(TOPICS[topic].schema_name, "jsonschema", b"{}"))
            for m in msgs:
                t = m.get("t_sync_ns", m.get("t_true_ns", 0))
                w.add_message(cid, log_time=t, publish_time=t, data=json.dumps(m).encode())
        w.finish()
    return path


def drive(folder: Path, lat_offset_deg: float = 0.0) -> Path:
    """A simulated drive's truth in one file: /truth/clock at 10 Hz, /truth/nav at 20 Hz, a valid /gnss/fix a second."""
    folder.mkdir()
    clock = [{"t_mono_ns": MONO0 + k * NS // 10, "t_true_ns": T0 + k * NS // 10} for k in range(DRIVE_S * 10 + 1)]
    nav = [{"t_true_ns": T0 + k * NS // 20, "lat_deg": lat_at(T0 + k * NS // 20) + lat_offset_deg,
            "lon_deg": LON0, "height_m": H0} for k in range(DRIVE_S * 20 + 1)]
    fixes = [{"t_mono_ns": MONO0 + k * NS, "t_sync_ns": T0 + k * NS, "fix_ok": True,
              "latitude": lat_at(T0 + k * NS) + lat_offset_deg, "longitude": LON0, "altitude": H0}
             for k in range(DRIVE_S + 1)]
    return write_mcap(folder / "drive_20261205T094239Z_0001.mcap", {TRUTH_CLOCK: clock, TRUTH_NAV: nav,
                                                                    GNSS_FIX: fixes})


def trajectory(path: Path, from_s: float, to_s: float, north_m: float = 1.0, mono_shift_ns: int = 0) -> Path:
    """logger replay's trajectory.csv at 10 Hz over board time from_s-to_s (true time = board time + T0 - MONO0),
    north_m north of the truth."""
    path.parent.mkdir(exist_ok=True)
    dlat = math.degrees(north_m / 6_378_137.0)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_sync_ns", "t_mono_ns", "lat_deg", "lon_deg", "height_m", "sn_m", "se_m", "sd_m"])
        for k in range(int(from_s * 10), int(to_s * 10) + 1):
            mono = k * NS // 10
            t = T0 + mono - MONO0
            w.writerow([t, mono + mono_shift_ns, f"{lat_at(t) + dlat:.10f}", f"{LON0:.10f}", H0, 1.0, 1.0, 2.0])
    return path


def run(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str, str]:
    code = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


def test_a_trajectory_against_itself_as_reference_scores_zero(tmp_path: Path, capsys) -> None:
    """The reference's times are GNSS time, joined to the rows' t_sync_ns: a reference's board clock (another
    board's, or none) plays no part, and nothing is clamped to one instant."""
    traj = trajectory(tmp_path / "rp" / "trajectory.csv", 110, 190)
    other_board = trajectory(tmp_path / "ref" / "trajectory.csv", 110, 190, mono_shift_ns=5000 * NS)
    for ref in (traj, other_board, tmp_path / "ref"):
        code, out, err = run(capsys, tmp_path / "rp", "--reference", ref, "--json")
        assert code == 0, err
        s = json.loads(out)["rp"]
        assert s["max_h"] == 0.0 and max(map(abs, s["rmse"])) == 0.0
        assert s["coverage"] == 1.0 and s["rows_scored"] == s["rows"] == 801
    # A reference 1 m south, as an MCAP file's /nav/fix (replay's trajectory.mcap): 1 m north everywhere.
    fixes = [{"t_mono_ns": 0, "t_sync_ns": T0 + k * NS // 5, "latitude": lat_at(T0 + k * NS // 5),
              "longitude": LON0, "altitude": H0} for k in range(50, 451)]
    ref_mcap = write_mcap(tmp_path / "trajectory.mcap", {NAV_FIX: fixes})
    code, out, err = run(capsys, tmp_path / "rp", "--reference", ref_mcap, "--json")
    assert code == 0, err
    assert json.loads(out)["rp"]["rmse"][0] == pytest.approx(1.0, abs=0.01)


def test_rows_outside_the_truth_are_left_out_and_counted(tmp_path: Path, capsys) -> None:
    """Half the trajectory lies after the drive's end (a drive cut short): those rows are not scored (the clock
    held at its end put them at its last instant: tens of metres here, kilometres on a real drive), and the
    score says how many were left out."""
    d = drive(tmp_path / "drive")
    traj = trajectory(tmp_path / "rp" / "trajectory.csv", 150, 250)
    code, out, err = run(capsys, traj, d, "--json")
    assert code == 0, err
    s = json.loads(out)["rp"]
    assert s["rows"] == 1001 and s["rows_scored"] == 501
    assert s["max_h"] == pytest.approx(1.0, abs=0.01)
    code, out, err = run(capsys, traj, d)
    assert code == 0 and "500 of its 1001 rows (50.0 %) lie outside it, not scored" in out


def test_a_trajectory_the_drive_does_not_cover_is_refused(tmp_path: Path, capsys) -> None:
    d = drive(tmp_path / "drive")
    after = trajectory(tmp_path / "after" / "trajectory.csv", 300, 400)
    code, out, err = run(capsys, after, d)
    assert code == 1 and out == ""
    assert err.count("\n") == 1 and f"{after}: none of its 1001 rows falls within the span of" in err
    assert "board time 100.0-200.0 s" in err
    # Against a reference that ends before the rows begin: the same.
    ref = trajectory(tmp_path / "ref" / "trajectory.csv", 0, 90)
    code, out, err = run(capsys, after, "--reference", ref)
    assert code == 1 and err.count("\n") == 1 and "none of its 1001 rows" in err


def test_a_trajectory_far_from_the_drives_fixes_is_scored_with_a_warning(tmp_path: Path, capsys) -> None:
    """Two simulated drives can share their clocks' span: a trajectory kilometres from the drive's own GNSS
    fixes is likely another drive's, and the user is told so; it is scored all the same (a filter that lost the
    fixes and drifted looks the same, and its score is what shows it)."""
    elsewhere = drive(tmp_path / "elsewhere", lat_offset_deg=0.03)
    traj = trajectory(tmp_path / "rp" / "trajectory.csv", 110, 190)
    code, out, err = run(capsys, traj, elsewhere)
    assert code == 0 and out
    assert err.count("\n") == 1 and "3.3 km from the drive's own GNSS fixes" in err and "warning" in err


@pytest.mark.parametrize(("content", "words"), [
    ("", "empty: not a trajectory"),
    ("time_utc,t_unix_ns,lat_deg,lon_deg,height_ellipsoid_m\n2026-12-05T09:42:41Z,1,37.5,127.0,50\n",
     "no column t_sync_ns, height_m, sn_m, se_m, sd_m: not a trajectory of logger replay"),
    ("t_sync_ns,t_mono_ns,lat_deg,lon_deg,height_m,sn_m,se_m,sd_m\n", "no rows under its header"),
    ("t_sync_ns,t_mono_ns,lat_deg,lon_deg,height_m,sn_m,se_m,sd_m\n1,2,north,4,5,6,7,8\n",
     "line 2: lat_deg 'north' is not a number"),
    ("t_sync_ns,t_mono_ns,lat_deg,lon_deg,height_m,sn_m,se_m,sd_m\n1,2,3\n", "line 2 has 3 fields, the header 8"),
])
def test_a_csv_that_is_not_a_trajectory_is_one_line(tmp_path: Path, capsys, content: str, words: str) -> None:
    d = drive(tmp_path / "drive")
    bad = tmp_path / "bad.csv"
    bad.write_text(content)
    code, out, err = run(capsys, bad, d)
    assert code == 2 and out == "" and err == f"logger nav-score: {bad}: {words}" + err[err.index(words) + len(words):]
    assert err.count("\n") == 1, err


def test_inputs_it_cannot_use_are_named(tmp_path: Path, capsys) -> None:
    """Nothing is silently left out: a file of another kind, no trajectory at all, nothing to score against."""
    d = drive(tmp_path / "drive")
    traj = trajectory(tmp_path / "rp" / "trajectory.csv", 110, 190)
    notes = tmp_path / "notes.txt"
    notes.write_text("hello\n")
    cases = [
        ((notes, d), f"{notes}: neither a trajectory CSV"),
        ((d,), "no trajectory to score"),
        ((traj,), "nothing to score against"),
        ((traj, d, "--reference", notes), f"{notes}: a reference is a trajectory CSV or an MCAP file"),
        ((traj, d, "--reference", d), "no /nav/fix messages: not a trajectory"),
        ((traj, notes.with_suffix(".mcap")), "no such file"),
    ]
    for args, words in cases:
        code, out, err = run(capsys, *args)
        assert code == 2 and out == "" and words in err and err.count("\n") == 1, (args, err)


def test_a_drive_folder_a_replay_wrote_into_is_the_drive_and_the_trajectory(tmp_path: Path, capsys) -> None:
    """``logger replay DRIVE --out DRIVE`` puts trajectory.csv and trajectory.mcap beside the drive's files; replay,
    export and plot take that folder as the drive still. nav-score took it for the CSV alone: "nothing to score
    against" for `nav-score DRIVE/trajectory.csv DRIVE`."""
    d = drive(tmp_path / "drive").parent
    trajectory(d / "trajectory.csv", 110, 190)
    write_mcap(d / "trajectory.mcap", {NAV_FIX: [{"t_mono_ns": 0, "t_sync_ns": T0 + k * NS, "latitude": lat_at(
        T0 + k * NS), "longitude": LON0, "altitude": H0} for k in range(10, 90)]})
    for args in ((d / "trajectory.csv", d), (d,)):
        code, out, err = run(capsys, *args, "--json")
        assert code == 0, (args, err)
        (score,) = json.loads(out).values()
        assert score["rmse"][0] == pytest.approx(1.0, abs=0.01) and score["rows_scored"] == 801, args
