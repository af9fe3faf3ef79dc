"""``logger export`` on a drive recorded by the real daemon, checked against the messages read back from it.

The drive: the simulated vehicle through the whole daemon (drivers, device models, recorder, live navigator),
with a short GNSS outage near its end and the recorder rotating files every minute, then ``logger replay`` over
it. Also here: the Python reading example of docs/foxglove.md (run as written on a recorded file) and the
Foxglove message paths that guide gives (checked against the topic schemas).
"""

from __future__ import annotations

import contextlib
import csv
import datetime as dt
import io
import itertools
import json
import os
import re
import subprocess
import sys
import threading
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import pytest
from helpers_drive import drive_timeout
from mcap.reader import make_reader
from mcap.writer import Writer

from logger.cli.outputs import drive_name
from logger.compose import build
from logger.config import defaults
from logger.recording.drive import open_drive
from logger.recording.files import is_finished, walk
from logger.recording.topics import TOPICS

ROOT = Path(__file__).resolve().parents[1]
GPX = "{http://www.topografix.com/GPX/1/1}"
KML = "{http://www.opengis.net/kml/2.2}"
GX = "{http://www.google.com/kml/ext/2.2}"
XSI = "{http://www.w3.org/2001/XMLSchema-instance}"
# GPX 1.1 wptType: its children in the order the schema's <xsd:sequence> requires
WPT_ORDER = ("ele", "time", "magvar", "geoidheight", "name", "cmt", "desc", "src", "link", "sym", "type", "fix",
             "sat", "hdop", "vdop", "pdop", "ageofdgpsdata", "dgpsid", "extensions")
DURATION_S, OUTAGE_S, TIME_SCALE = 155.0, 8.0, 12.0  # the outage starts about 138 s into the drive


@dataclass
class Drive:
    files: list[Path]  # finished, rotated
    cut: Path  # a copy of the last file as a power cut leaves it
    replay: Path  # logger replay's trajectory.mcap


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Drive:
    base = tmp_path_factory.mktemp("export")
    cfg = defaults(sim=True)
    cfg.values["logger"].update(out_dir=str(base / "rec"), status_socket=str(base / "status.sock"),
                                state_dir=str(base / "state"))
    cfg.values["sim"].update(scenario="outage-60s", seed=3, time_scale=TIME_SCALE)
    cfg.values["recorder"]["rotate_duration_s"] = 60.0
    daemon, _ = build(cfg, DURATION_S, scenario_options={"outage_s": OUTAGE_S})
    runner = threading.Thread(target=daemon.run, args=(DURATION_S,), daemon=True)  # no signal handlers off main
    runner.start()
    runner.join(drive_timeout(DURATION_S))
    assert not runner.is_alive()
    files = sorted((base / "rec").glob("*.mcap"))
    assert len(files) >= 3 and all(is_finished(f) for f in files)
    cut = base / "cut" / files[-1].name
    cut.parent.mkdir()
    data = files[-1].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    r = run("replay", *map(str, files), "--out", str(base / "replay"))
    assert r.returncode == 0, r.stderr
    return Drive(files, cut, base / "replay" / "trajectory.mcap")


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "logger.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)


def recorded(paths: list[Path], topic: str) -> list[tuple[int, dict]]:
    """(log_time, message) of a topic: the mcap package's reader for finished files, recovery's walk for a cut."""
    out = []
    for p in paths:
        if is_finished(p):
            with open(p, "rb") as f:
                out += [(m.log_time, json.loads(m.data)) for _, _, m in make_reader(f).iter_messages(topics=[topic])]
        else:
            found = walk(p)
            ids = {cid for cid, ch in found.channels.items() if ch.topic == topic}
            out += [(m.log_time, json.loads(m.data)) for m in found.messages if m.channel_id in ids]
    return sorted(out, key=lambda x: x[0])


def valid_fix(m: dict) -> bool:
    return bool(m["fix_ok"]) and m["fix_mode"] == 3


def epoch_ns(m: dict) -> int:
    return m["timestamp"]["sec"] * 1_000_000_000 + m["timestamp"]["nsec"]


def iso_ns(text: str) -> int:
    assert text.endswith("Z") and re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", text), text
    t = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    return int(t.timestamp()) * 1_000_000_000 + t.microsecond * 1000


def gpx_tracks(path: Path) -> dict[str, list[list[ET.Element]]]:
    """Track name -> segments -> trkpt elements, after checking the document's frame."""
    root = ET.parse(path).getroot()
    assert root.tag == f"{GPX}gpx" and root.get("version") == "1.1" and root.get("creator")
    assert root.get(f"{XSI}schemaLocation") == "http://www.topografix.com/GPX/1/1 http://www.topografix.com/GPX/1/1/gpx.xsd"
    assert next(iter(root)).tag == f"{GPX}metadata"
    out = {}
    for trk in root.findall(f"{GPX}trk"):
        out[trk.findtext(f"{GPX}name")] = [seg.findall(f"{GPX}trkpt") for seg in trk.findall(f"{GPX}trkseg")]
        for seg in out[trk.findtext(f"{GPX}name")]:
            for pt in seg:
                names = [c.tag.removeprefix(GPX) for c in pt]
                assert [WPT_ORDER.index(n) for n in names] == sorted(WPT_ORDER.index(n) for n in names), names
    bounds = root.find(f"{GPX}metadata/{GPX}bounds")
    pts = [p for segs in out.values() for s in segs for p in s]
    assert bounds is not None and pts
    assert float(bounds.get("minlat")) == min(float(p.get("lat")) for p in pts)
    assert float(bounds.get("maxlon")) == max(float(p.get("lon")) for p in pts)
    return out


@pytest.mark.slow_on_board
def test_gpx_holds_every_valid_fix_split_at_the_outage(drive: Drive, tmp_path: Path) -> None:
    r = run("export", *map(str, drive.files), drive.replay.as_posix(), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    name = drive_name(open_drive(drive.files))
    tracks = gpx_tracks(tmp_path / f"{name}.gpx")
    assert list(tracks) == ["/gnss/fix", "/nav/fix", f"/nav/fix (replay: {drive.replay.name})"]

    fixes = recorded(drive.files, "/gnss/fix")
    valid = [i for i, (_, m) in enumerate(fixes) if valid_fix(m)]
    assert len(valid) < len(fixes) - 3, "the drive should hold a GNSS outage"
    segs = tracks["/gnss/fix"]
    pts = [p for s in segs for p in s]
    assert len(pts) == len(valid)
    for pt, i in zip(pts, valid, strict=True):
        m = fixes[i][1]
        assert abs(float(pt.get("lat")) - m["latitude"]) < 1e-9 and abs(float(pt.get("lon")) - m["longitude"]) < 1e-9
        assert abs(float(pt.findtext(f"{GPX}ele")) - m["altitude"]) < 1e-3  # ellipsoidal by default
        assert abs(iso_ns(pt.findtext(f"{GPX}time")) - epoch_ns(m)) <= 500_000  # the receiver's epoch, to 1 ms
        assert pt.findtext(f"{GPX}fix") == "3d" and int(pt.findtext(f"{GPX}sat")) == m["num_sv"]
        assert (float(pt.get("lat")), float(pt.get("lon"))) != (0.0, 0.0)
    # Within a segment: consecutive epochs, no invalid one between; between segments: an invalid one or 3 s.
    pos = 0
    for k, seg in enumerate(segs):
        idx = valid[pos:pos + len(seg)]
        assert all(b - a == 1 for a, b in itertools.pairwise(idx)), "a segment joins across a bad fix"
        if k:
            before, after = fixes[valid[pos - 1]][1], fixes[idx[0]][1]
            assert idx[0] - valid[pos - 1] > 1 or epoch_ns(after) - epoch_ns(before) > 3e9
        pos += len(seg)
    assert len(segs) >= 2

    live = [m for _, m in recorded(drive.files, "/nav/fix")]
    nav = [p for s in tracks["/nav/fix"] for p in s]
    assert len(live) > 50 and len(nav) == len(live)
    for p, m in zip(nav, live, strict=True):
        assert abs(iso_ns(p.findtext(f"{GPX}time")) - m["t_sync_ns"]) <= 500_000
    replayed = recorded([drive.replay], "/nav/fix")
    assert sum(len(s) for s in tracks[f"/nav/fix (replay: {drive.replay.name})"]) == len(replayed) > 50
    assert (tmp_path / f"{name}_nav_fix_replay.csv").exists()


def test_kml_and_csv_agree_with_the_gpx(drive: Drive, tmp_path: Path) -> None:
    r = run("export", *map(str, drive.files), "--out", str(tmp_path), "--gap-marks", "--topic", "/gnss/fix")
    assert r.returncode == 0, r.stderr
    name = drive_name(open_drive(drive.files))
    segs = gpx_tracks(tmp_path / f"{name}.gpx")["/gnss/fix"]
    root = ET.parse(tmp_path / f"{name}.kml").getroot()
    assert root.tag == f"{KML}kml"
    (folder,) = root.findall(f"{KML}Document/{KML}Folder")
    assert folder.findtext(f"{KML}name") == "/gnss/fix"
    track, *gaps = folder.findall(f"{KML}Placemark")
    multi = track.find(f"{GX}MultiTrack")
    assert multi.findtext(f"{GX}interpolate") == "0"  # a gap is not drawn as driven
    geoms = multi.findall(f"{GX}Track")
    assert len(geoms) == len(segs) and len(gaps) == len(segs) - 1
    for geom, seg in zip(geoms, segs, strict=True):
        # Every point with its own time, the GPX's, in order: gx:Track's <when> list and <gx:coord> list pair up.
        whens = [w.text for w in geom.findall(f"{KML}when")]
        coords = [c.text.split() for c in geom.findall(f"{GX}coord")]
        assert whens == [p.findtext(f"{GPX}time") for p in seg] and len(coords) == len(seg)
        assert [(c[0], c[1]) for c in coords] == [(p.get("lon"), p.get("lat")) for p in seg]
        assert [float(c[2]) for c in coords] == [float(p.findtext(f"{GPX}ele")) for p in seg]
    for g in gaps:
        assert re.fullmatch(r"gap \d+\.\d s", g.findtext(f"{KML}name"))
        # OGC KML 2.2 (ogckml22.xsd, AbstractFeatureType): the time primitive comes before styleUrl.
        assert [c.tag.removeprefix(KML) for c in g] == ["name", "description", "TimeStamp", "styleUrl", "Point"]
    with open(tmp_path / f"{name}_gnss_fix.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {"lat_deg", "lon_deg", "height_ellipsoid_m", "height_msl_m", "speed_mps", "h_sigma_m",
            "sync_err_ns"} <= set(rows[0])
    pts = [(n, p) for n, s in enumerate(segs, 1) for p in s]
    assert len(rows) == len(pts)
    for row, (n, p) in zip(rows, pts, strict=True):
        assert int(row["segment"]) == n and row["lat_deg"] == p.get("lat")
        assert row["time_utc"] == p.findtext(f"{GPX}time")
        assert float(row["height_ellipsoid_m"]) == float(p.findtext(f"{GPX}ele"))
    assert not (tmp_path / f"{name}_nav_fix.csv").exists()  # --topic /gnss/fix only


def test_msl_heights_use_the_receivers_geoid(drive: Drive, tmp_path: Path) -> None:
    r = run("export", *map(str, drive.files), "--out", str(tmp_path), "--format", "gpx", "--height", "msl")
    assert r.returncode == 0, r.stderr
    tracks = gpx_tracks(tmp_path / f"{drive_name(open_drive(drive.files))}.gpx")
    fixes = [m for _, m in recorded(drive.files, "/gnss/fix") if valid_fix(m)]
    gnss = [p for s in tracks["/gnss/fix"] for p in s]
    for p, m in zip(gnss, fixes, strict=True):
        assert abs(float(p.findtext(f"{GPX}ele")) - m["height_msl_m"]) < 1e-3
        assert abs(float(p.findtext(f"{GPX}geoidheight")) - (m["altitude"] - m["height_msl_m"])) < 2e-3
    sep = [m["altitude"] - m["height_msl_m"] for m in fixes]
    live = [m for _, m in recorded(drive.files, "/nav/fix")]
    for p, m in zip((p for s in tracks["/nav/fix"] for p in s), live, strict=True):
        assert min(sep) - 1e-3 <= m["altitude"] - float(p.findtext(f"{GPX}ele")) <= max(sep) + 1e-3


def test_a_file_cut_short_is_read_up_to_the_cut(drive: Drive, tmp_path: Path) -> None:
    files = [*drive.files[:-1], drive.cut]
    assert not is_finished(drive.cut)
    r = run("export", *map(str, files), "--out", str(tmp_path), "--format", "csv")
    assert r.returncode == 0, r.stderr
    assert f"{drive.cut} was not closed cleanly" in r.stderr
    from_cut = [m for _, m in recorded([drive.cut], "/gnss/fix") if valid_fix(m)]
    whole = [m for _, m in recorded(drive.files[-1:], "/gnss/fix") if valid_fix(m)]
    assert 0 < len(from_cut) < len(whole)
    expected = [m for _, m in recorded(files, "/gnss/fix") if valid_fix(m)]
    with open(tmp_path / f"{drive_name(open_drive(files))}_gnss_fix.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["lat_deg"]) for r in rows] == pytest.approx([m["latitude"] for m in expected], abs=1e-9)


def write_mcap(path: Path, topic: str, messages: list[dict]) -> None:
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        cid = w.register_channel(topic, "json", w.register_schema(TOPICS[topic].schema_name, "jsonschema", b"{}"))
        for i, m in enumerate(messages):
            w.add_message(cid, log_time=i + 1, publish_time=i + 1, data=json.dumps(m).encode())
        w.finish()


def test_what_cannot_be_exported_is_one_line_and_exit_2(drive: Drive, tmp_path: Path) -> None:
    imu_only = tmp_path / "imu.mcap"
    write_mcap(imu_only, "/imu", [{"t_mono_ns": 1}])
    no_fix = tmp_path / "nofix.mcap"
    fix = recorded(drive.files[:1], "/gnss/fix")[0][1]
    write_mcap(no_fix, "/gnss/fix", [{**fix, "fix_ok": False, "fix_mode": 1, "latitude": 0.0, "longitude": 0.0}] * 3)
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    cases = [
        ((str(tmp_path / "missing.mcap"),), "no such file"),
        ((str(text),), "not an MCAP file"),
        ((str(imu_only),), "no /gnss/fix or /nav/fix messages in"),
        ((str(no_fix),), "no valid position to export"),
        ((str(drive.files[0]), "--format", "gpx,shp"), "--format"),
        ((str(drive.files[0]), "--topic", "/imu"), "only /gnss/fix and /nav/fix hold positions"),
    ]
    for args, words in cases:
        r = run("export", *args, "--out", str(tmp_path / "out"))
        assert r.returncode == 2, (args, r.stderr)
        assert words in r.stderr and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_the_guides_python_example_runs_as_written(drive: Drive) -> None:
    guide = (ROOT / "docs" / "foxglove.md").read_text()
    code = re.search(r"```python\n(.*?)```", guide, re.S).group(1)
    assert '"drive.mcap"' in code
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code.replace('"drive.mcap"', repr(str(drive.files[0]))), "foxglove.md", "exec"), {})
    lines = out.getvalue().splitlines()
    fixes = [(t, m) for t, m in recorded(drive.files[:1], "/gnss/fix") if valid_fix(m)]
    assert len(lines) == len(fixes) + 1 and len(fixes) > 10
    for line, (t, m) in zip(lines, fixes, strict=False):
        assert line.split() == [str(t), str(m["latitude"]), str(m["longitude"]), str(m["altitude"]), str(m["h_acc_m"])]
    assert lines[-1] == "h_acc_m: " + TOPICS["/gnss/fix"].schema["properties"]["h_acc_m"]["description"]


def test_the_guides_message_paths_exist_in_the_schemas() -> None:
    guide = (ROOT / "docs" / "foxglove.md").read_text()
    paths = set(re.findall(r"`(/[a-z_/]+(?:\{[^}`]*\})?(?:\.[a-z][a-z_0-9]*(?:\[(?:\d+|:)\])?)+)`", guide))
    assert len(paths) > 25
    for path in paths:
        topic = max((t for t in TOPICS if path.startswith(t) and path[len(t)] in ".{"), key=len)
        props = TOPICS[topic].schema["properties"]
        rest = path[len(topic):]
        for field, _ in re.findall(r"\{([a-z_]+)==([^}]*)\}", rest):
            assert field in props, path
        for field, index in re.findall(r"\.([a-z][a-z_0-9]*)(?:\[(\d+|:)\])?", re.sub(r"\{[^}]*\}", "", rest)):
            assert field in props, path
            if index:  # [:] (every element, as Foxglove plots a batch's columns) or an index within a fixed size
                assert "array" in props[field]["type"], path
                assert index == ":" or int(index) < props[field].get("maxItems", int(index) + 1), path


def test_bad_epochs_split_the_track_and_never_become_points(drive: Drive) -> None:
    """Fixes built from a recorded one: every kind of bad epoch the receiver can give, between good ones."""
    from logger.exports.tracks import build_tracks
    from logger.recording.drive import DriveFile, DriveMessage

    good = next(m for _, m in recorded(drive.files[:1], "/gnss/fix") if valid_fix(m))
    t0 = epoch_ns(good)

    def at(k: float, **change: object) -> DriveMessage:
        t = t0 + int(k * 1e9)
        msg = {**good, "timestamp": {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000}, **change}
        return DriveMessage(t, "/gnss/fix", 0, msg)

    stream = [at(0), at(1), at(2, fix_mode=2), at(3), at(4, fix_ok=False), at(5), at(6, fix_mode=1, fix_ok=False,
              latitude=0.0, longitude=0.0), at(7), at(8, latitude=0.0, longitude=0.0), at(9), at(9), at(13), at(14),
              at(14.5), at(15)]
    files = [DriveFile(drive.files[0], "live", True)]
    (track,) = build_tracks(stream, files, gap_s=3.0)
    times = [[round((p.t_ns - t0) / 1e9, 1) for p in seg] for seg in track.segments]
    assert times == [[0, 1], [3], [5], [7], [9], [13, 14, 14.5, 15]]
    assert [round(g.duration_s) for g in track.gaps] == [2, 2, 2, 2, 4]
    assert track.skipped == {"2D fix": 1, "fix not flagged valid": 1, "no fix": 1, "no position": 1,
                             "repeated or out-of-order time": 1}
    (thin,) = build_tracks(stream, files, gap_s=3.0, every_s=1.0)
    assert [round((p.t_ns - t0) / 1e9, 1) for p in thin.segments[-1]] == [13, 14, 15]


def test_gnss_decode_reads_a_recordings_raw_receiver_bytes(drive: Drive) -> None:
    """A recording given to ``logger gnss-decode`` is decoded from its /gnss/raw bytes: the same navigation
    solutions the daemon recorded on /gnss/fix (read independently, by the mcap package), none taken for garbage."""
    r = run("gnss-decode", "--json", str(drive.files[0]))
    assert r.returncode == 0, r.stderr
    decoded = [json.loads(line) for line in r.stdout.splitlines()]
    ms = 1_000_000  # TPV times are to the millisecond
    epochs = {round(m["gnss_time_ns"] / ms) for _, m in recorded(drive.files[:1], "/gnss/fix")
              if m["gnss_time_ns"] is not None}
    assert decoded and epochs
    decoded_times = {round(iso_ns(t["time"]) / ms) for t in decoded if "time" in t}
    # Every recorded epoch was decoded again from the raw bytes (the first and last epochs of a rotated file may
    # have been cut between files, so at most one at each end may be missing).
    assert len(epochs - decoded_times) <= 2, sorted(epochs - decoded_times)[:5]
    assert " 0 garbage bytes" in r.stderr


def test_gnss_decode_says_what_a_damaged_or_cut_recording_lost(drive: Drive, tmp_path: Path) -> None:
    """A recording with a chunk that does not decompress, and one cut short: decoded from what is left, with the
    line every reader of a drive gives (it said nothing, one fix short of the file's)."""
    from mcap.reader import make_reader

    damaged = tmp_path / drive.files[0].name
    data = bytearray(drive.files[0].read_bytes())
    with open(drive.files[0], "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 4
    chunk = summary.chunk_indexes[2]
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle:middle + 8] = bytes(b ^ 0xFF for b in data[middle:middle + 8])
    damaged.write_bytes(bytes(data))
    r = run("gnss-decode", str(damaged))
    assert r.returncode == 0, r.stderr
    assert f"logger gnss-decode: {damaged}: 1 damaged chunk skipped" in r.stderr, r.stderr
    r = run("gnss-decode", str(drive.cut))
    assert r.returncode == 0, r.stderr
    assert f"logger gnss-decode: {drive.cut} was not closed cleanly: read up to where it was cut" in r.stderr


def test_gnss_decode_says_when_a_recording_has_no_raw_bytes(drive: Drive, tmp_path: Path) -> None:
    r = run("gnss-decode", str(drive.replay))  # logger replay's trajectory: no /gnss/raw
    assert r.returncode == 1 and "without /gnss/raw" in r.stderr and "Traceback" not in r.stderr


def test_every_thins_on_a_grid_and_never_breaks_the_track() -> None:
    """``--every``: 1 Hz fixes stamped a few ns either side of whole seconds (as a receiver stamps them), one real
    outage of 10 s. Thinned to 2 s and 5 s they keep one point per 2 s and 5 s and the track keeps its two segments
    and its one gap: a point thinned away is no gap (it was one segment per point at 5 s, one per 3 s at 2 s)."""
    from logger.exports.tracks import build_tracks
    from logger.recording.drive import DriveFile, DriveMessage

    t0 = 1_780_000_000 * 10**9
    seconds = [k for k in range(120) if not 60 <= k < 70]

    def fix(k: int) -> DriveMessage:
        t = t0 + k * 10**9 + (3 if k % 2 else -4)
        msg = {"fix_mode": 3, "fix_ok": True, "latitude": 37.5 + k * 1e-5, "longitude": 127.0, "altitude": 50.0,
               "timestamp": {"sec": t // 10**9, "nsec": t % 10**9}}
        return DriveMessage(t, "/gnss/fix", 0, msg)

    def nav(k: int) -> DriveMessage:  # 5 Hz rows a microsecond either side of 200 ms apart
        t = t0 + k * 200_000_000 + (1000 if k % 3 else -1000)
        return DriveMessage(t, "/nav/fix", 0, {"latitude": 37.5, "longitude": 127.0, "altitude": 50.0, "t_sync_ns": t})

    stream = sorted([fix(k) for k in seconds] + [nav(k) for k in range(300)], key=lambda m: m.log_time)
    files = [DriveFile(Path("drive_0001.mcap"), "live", True)]
    (whole, nav_whole) = build_tracks(stream, files, gap_s=3.0)
    assert [len(s) for s in whole.segments] == [60, 50] and len(whole.gaps) == 1
    for every in (2, 5):
        (thin, nav_thin) = build_tracks(stream, files, gap_s=3.0, every_s=every)
        assert len(thin.segments) == 2 and [round(g.duration_s) for g in thin.gaps] == [11]
        assert [len(s) for s in thin.segments] == [60 // every, 50 // every]
        for seg in thin.segments:
            assert {round((b.t_ns - a.t_ns) / 1e9, 6) for a, b in itertools.pairwise(seg)} == {every}
        assert thin.skipped["thinned out (--every)"] == 110 - 110 // every
        assert len(nav_thin.segments) == 1 and len(nav_thin.points) == 60 // every
        assert nav_whole.n_points == 300


def test_an_output_path_that_cannot_be_a_folder_is_one_line_before_the_work(tmp_path: Path) -> None:
    """``--out`` a file, or a folder under a file: said at once in one line, exit 2, not a traceback after the drive
    was read."""
    drive = tmp_path / "drive.mcap"
    write_mcap(drive, "/gnss/fix", [{"fix_mode": 3, "fix_ok": True, "latitude": 37.5, "longitude": 127.0,
                                     "altitude": 50.0, "timestamp": {"sec": 1_780_000_000 + k, "nsec": 0}}
                                    for k in range(3)])
    afile = tmp_path / "afile"
    afile.write_text("")
    for out, words in ((afile, f"--out {afile}: exists and is not a folder"),
                       (afile / "sub", f"--out {afile / 'sub'}: cannot be made, {afile} is a file and not a folder")):
        for fmt in ("gpx", "ubx"):
            r = run("export", str(drive), "--out", str(out), "--format", fmt)
            assert r.returncode == 2 and r.stderr == f"logger export: {words}\n" and r.stdout == "", r.stderr
    r = run("export", str(drive), "--out", str(tmp_path / "new" / "deeper"))
    assert r.returncode == 0 and (tmp_path / "new" / "deeper").is_dir(), r.stderr


def _with_file_size_limit(limit_bytes: int):
    """A child whose writes past ``limit_bytes`` fail with EFBIG, as a full card fails them (ENOSPC): a real
    write error from the kernel, without mounting a small file system (SIGXFSZ ignored, so the write returns it)."""
    import resource
    import signal

    def child() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return child


def test_an_output_that_fails_part_way_leaves_the_earlier_one_whole(drive: Drive, tmp_path: Path) -> None:
    """The same drive exported and replayed again into the same folder, the second time with a write failing
    part-way (a full card): the earlier GPX, CSV and trajectory files stay as they were, byte for byte, where a
    truncated file had replaced them, no partial file is left, and the line names the output that failed."""
    out = tmp_path / "out"
    r = run("export", *map(str, drive.files), "--out", str(out), "--format", "gpx,csv", "--every", "20")
    assert r.returncode == 0, r.stderr
    r = run("replay", *map(str, drive.files), "--out", str(out))
    assert r.returncode == 0, r.stderr
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    gpx = next(out.glob("*.gpx"))
    limit = 2 * len(before[gpx.name])  # the thinned GPX fits, every fix's does not
    for args, failed in ((("export", "--format", "gpx,csv"), gpx),
                         (("replay", "--fix-hz", "0"), out / "trajectory.csv")):
        r = subprocess.run([sys.executable, "-m", "logger.cli", args[0], *map(str, drive.files), "--out", str(out),
                            *args[1:]], cwd=ROOT, capture_output=True, text=True, timeout=300,
                           preexec_fn=_with_file_size_limit(limit))
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert r.stderr.endswith(f"{failed}: File too large\n"), r.stderr
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before, args


def test_one_runs_outputs_go_in_together_or_not_at_all(drive: Drive, tmp_path: Path) -> None:
    """A later output of a run failing (a full card after the first file fitted; a folder where an output goes):
    none of the run's outputs replaces the earlier run's, so the folder never holds one run's CSV beside another
    run's MCAP, or one run's GPX beside another's CSV; the line names the output that failed, not its hidden
    partial file."""
    out, full = tmp_path / "out", tmp_path / "full"
    r = run("replay", *map(str, drive.files), "--out", str(out), "--mode", "15")
    assert r.returncode == 0, r.stderr
    r = run("export", *map(str, drive.files), "--out", str(out), "--format", "gpx,csv", "--every", "20")
    assert r.returncode == 0, r.stderr
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    r = run("replay", *map(str, drive.files), "--out", str(full), "--fix-hz", "0")
    assert r.returncode == 0, r.stderr
    size = {p.name: p.stat().st_size for p in full.iterdir()}
    # trajectory.csv is written first: it fits under the limit, trajectory.mcap after it does not.
    assert size["trajectory.csv"] < size["trajectory.mcap"], size
    r = subprocess.run([sys.executable, "-m", "logger.cli", "replay", *map(str, drive.files), "--out", str(out),
                        "--fix-hz", "0"], cwd=ROOT, capture_output=True, text=True, timeout=300,
                       preexec_fn=_with_file_size_limit(size["trajectory.csv"]))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.endswith(f"logger replay: {out / 'trajectory.mcap'}: File too large\n"), r.stderr
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    # An output's name taken by a folder: found before anything is replaced, and named as the output.
    (csv_path,) = list(out.glob("*gnss_fix.csv"))
    csv_path.unlink()
    csv_path.mkdir()
    r = run("export", *map(str, drive.files), "--out", str(out), "--format", "gpx,csv")
    assert r.returncode == 2 and r.stderr.endswith(f"logger export: {csv_path}: Is a directory\n"), r.stderr
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert after == {k: v for k, v in before.items() if k != csv_path.name}


def test_any_export_removes_a_killed_exports_stage(drive: Drive, tmp_path: Path) -> None:
    """A staging folder left by a killed export (its process gone) is removed by the next export into the folder,
    whatever it writes, and the command says so; a stage whose process runs is left to it."""
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                           check=True)
    out = tmp_path / "out"
    stale, live = out / f".export-{int(ended.stdout)}-abc", out / f".export-{os.getpid()}-def"
    for stage in (stale, live):
        stage.mkdir(parents=True)
        (stage / "drive.ubx").write_bytes(b"\xb5b" * 1000)
    r = run("export", *map(str, drive.files), "--out", str(out), "--format", "gpx")
    assert r.returncode == 0, r.stderr
    assert f"logger export: removed {stale}, left by an export that was killed\n" in r.stderr, r.stderr
    assert not stale.exists() and (live / "drive.ubx").exists()


def test_the_outputs_are_named_for_the_drive_whatever_order_its_files_come_in(drive: Drive, tmp_path: Path) -> None:
    """A drive's parts are named by the times they began: given last part first, the outputs were named for the last
    part and sat beside the ones named for the first."""
    assert len(drive.files) >= 2
    for order, out in ((drive.files, tmp_path / "forward"), (drive.files[::-1], tmp_path / "backward")):
        r = run("export", *map(str, order), "--out", str(out), "--format", "gpx")
        assert r.returncode == 0, r.stderr
    first = re.sub(r"_\d{4}$", "", drive.files[0].stem)
    assert [p.name for p in (tmp_path / "backward").iterdir()] == [f"{first}.gpx"]
    assert [p.name for p in (tmp_path / "forward").iterdir()] == [f"{first}.gpx"]


def test_a_fix_without_a_geoid_separation_keeps_its_point_and_its_height_above_sea_level(tmp_path: Path) -> None:
    """A receiver without a geoid model sends GGA with an empty separation: its fixes have a height above sea level
    and none above the ellipsoid. Every one was dropped as "no position"; the point stands, written with the
    height it has (--height msl) or without one (the ellipsoid's), never with a made-up one."""
    from logger.exports.formats import write_csv, write_gpx, write_kml
    from logger.exports.tracks import Track, gnss_point

    fix = {"timestamp": {"sec": 1_796_000_000, "nsec": 0}, "latitude": 48.1173, "longitude": 11.5167,
           "altitude": None, "height_msl_m": 545.4, "fix_mode": 3, "fix_ok": True, "vel_ned_mps": [1.0, 0.0, None]}
    p = gnss_point(fix)
    assert not isinstance(p, str)
    assert (p.h_ell_m, p.h_msl_m) == (None, 545.4)
    track = Track("gnss_fix", "/gnss/fix", "live", "/gnss/fix", [[p]])
    write_csv(tmp_path / "t.csv", track)
    with open(tmp_path / "t.csv", newline="") as f:
        (row,) = list(csv.DictReader(f))
    assert (row["height_ellipsoid_m"], row["height_msl_m"]) == ("", "545.400")
    for which, ele in (("msl", "545.400"), ("ellipsoid", None)):
        write_gpx(tmp_path / f"{which}.gpx", [track], which, "t")
        (pt,) = ET.parse(tmp_path / f"{which}.gpx").getroot().iter(f"{GPX}trkpt")
        assert pt.findtext(f"{GPX}ele") == ele and pt.find(f"{GPX}geoidheight") is None
        write_kml(tmp_path / f"{which}.kml", [track], which, "t")
        ET.parse(tmp_path / f"{which}.kml")


def test_repeated_formats_add_up() -> None:
    """`--format gpx --format kml` wrote only the KML, exit 0 (the last one won, silently); --topic adds up."""
    from logger.cli.export import check_args, parse_args

    formats, _ = check_args(parse_args(["d.mcap", "--out", "o", "--format", "gpx", "--format", "kml,gpx"]))
    assert formats == ["gpx", "kml"]
    assert check_args(parse_args(["d.mcap", "--out", "o"]))[0] == ["gpx", "kml", "csv"]
