"""The navigator in the daemon, its configuration and status lines, and `logger replay` on a recorded drive."""

from __future__ import annotations

import csv
import json
import math
import re
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from helpers_drive import drive_timeout
from test_nav_synth import records

from logger.cli.status_view import render
from logger.config import ConfigError, parse
from logger.nav.params import NavParams
from logger.runtime.daemon import Attachments
from logger.runtime.navigator import STALE_S, Navigator, attach_navigator
from logger.runtime.sampler import Reading
from logger.runtime.timebase import TimeBase
from sensors.sim.scenarios import make_drive

ROOT = Path(__file__).resolve().parents[1]


def test_offer_never_blocks_and_counts_what_it_drops():
    nav = Navigator(NavParams(queue_size=10))  # no thread started: nothing drains the queue
    msg = {"t_sync_ns": 1, "t_mono_ns": 1, "accel_mps2": [0, 0, -9.8], "gyro_rps": [0, 0, 0]}
    took: list[float] = []

    def offer_all() -> None:
        for _ in range(1000):
            t0 = time.perf_counter()
            nav.offer("/imu", msg)
            took.append(time.perf_counter() - t0)

    # In a thread of its own, so that an offer waiting for room fails the test instead of hanging it.
    worker = threading.Thread(target=offer_all, daemon=True)
    worker.start()
    worker.join(30.0)
    assert not worker.is_alive(), f"offer() blocked on a full queue after {len(took)} records"
    # An offer that waited even a millisecond for room would make the median call that long; a busy host
    # preempts only a few of the calls and leaves the median alone.
    assert statistics.median(took) < 1e-3, sorted(took)[-5:]
    assert nav.dropped == 990
    nav.offer("/truth/nav", msg)  # topics the filter does not use are not even queued
    nav.offer("/nav/fix", msg)  # nor its own output coming back through the daemon's sink
    assert nav.dropped == 990 and nav.queued == 10
    assert "navigator behind: 990 records skipped" in nav.section()["verdicts"]


def test_a_quarter_filled_queue_wakes_the_filter_thread():
    """The filter thread takes its queue every WAKE_S, and at once when offers fill a quarter of it: a
    fast simulated drive or a burst of reads is taken before the queue overflows."""
    nav = Navigator(NavParams(queue_size=40))  # no thread started: the wake-up is looked at, not acted on
    msg = {"t_sync_ns": 1, "t_mono_ns": 1, "accel_mps2": [0, 0, -9.8], "gyro_rps": [0, 0, 0]}
    for _ in range(9):
        nav.offer("/imu", msg)
        nav.offer("/truth/nav", msg)  # not queued, so not counted
    assert not nav._wake.is_set()
    nav.offer("/imu", msg)
    assert nav._wake.is_set() and nav.queued == 10


def run_through(nav: Navigator, recs: list[tuple[str, dict]]) -> None:
    """The navigator's thread fed these records, and stopped once it has taken them all."""
    nav.start()
    try:
        for topic, msg in recs:
            nav.offer(topic, msg)
        deadline = time.monotonic() + 20.0
        while nav.queued and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
    finally:
        nav.stop()


def test_navigator_thread_publishes_fixes_state_and_status():
    drive = make_drive("outage-60s", seed=1, duration_s=80.0)
    published: list[Reading] = []
    lock = threading.Lock()

    def publish(r: Reading) -> None:
        with lock:
            published.append(r)

    nav = Navigator(NavParams(publish_hz=2.0), publish=publish)
    jitter = iter(np.random.default_rng(7).integers(-5_000, 5_000, 10_000))
    recs = []
    for _, topic, msg in records(drive, 80.0, seed=1):
        if topic == "/imu":  # a board's samples: 50 ms apart to a few microseconds, either side
            msg = {**msg, "t_sync_ns": msg["t_sync_ns"] + int(next(jitter))}
        recs.append((topic, msg))
    run_through(nav, recs)
    fixes = [r for r in published if r.topic == "/nav/fix"]
    states = [r for r in published if r.topic == "/nav/state"]
    assert fixes and states and nav.dropped == 0
    assert all(not r.stamped for r in published)
    last = fixes[-1].payload
    assert last["frame_id"] == "nav" and last["source"] == "ins 17-state"
    truth = drive.state(80.0)
    assert abs(last["latitude"] - truth.lat_rad * 57.29577951308232) * 111_000 < 3.0
    # Published at about publish_hz of drive time, not per IMU sample.
    span_s = (fixes[-1].payload["t_sync_ns"] - fixes[0].payload["t_sync_ns"]) / 1e9
    assert len(fixes) <= 2.0 * span_s + 2
    # ... and at it: on a grid of the period, not a period after each (solutions a hair less than 0.5 s apart were
    # passed over for the next one, 50 ms later: 5 Hz published as 4.83 Hz).
    gaps = np.diff([r.payload["t_sync_ns"] for r in fixes]) / 1e9
    assert np.mean(np.abs(gaps - 0.5) < 0.01) > 0.95, np.unique(np.round(gaps, 3), return_counts=True)
    sec = nav.section()
    assert sec["lat_deg"] is not None and sec["sigma_h_m"] < 5.0 and sec["cpu_s"] > 0.0
    assert any(v.startswith("GNSS consistent with the IMU") for v in sec["verdicts"])
    assert any(v.startswith("OBD speed reads") for v in sec["verdicts"])
    text = render({"verdict": "ok", "nav": sec})
    assert f"nav     {sec['lat_deg']:.7f} " in text and "\n        GNSS consistent with the IMU" in text
    # Bound to a daemon whose board clock has gone on without IMU samples (the IMU unplugged): the position is
    # shown as the past it is, without the verdicts drawn with it (they read as the present before). A daemon at
    # 4x drive time: judged in real seconds.
    last_mono = fixes[-1].payload["t_mono_ns"]
    for scale, ahead_s, stale in ((1.0, 3.0, False), (1.0, STALE_S + 1.0, True), (4.0, 4 * STALE_S - 2.0, False)):
        # As bind() leaves it, without starting the thread again.
        nav._timebase = TimeBase(lambda a=ahead_s: last_mono + int(a * 1e9), scale=scale)
        sec = nav.section()
        assert sec["age_s"] == pytest.approx(ahead_s, abs=0.6)
        said_old = [v for v in sec["verdicts"] if v.startswith("no new solution for")]
        assert bool(said_old) == stale and (not stale or len(sec["verdicts"]) == 1), sec["verdicts"]
        # ... on the position's own row, which a full 80x24 screen keeps (the verdict is the first it drops).
        row = next(line for line in render({"verdict": "ok", "nav": sec}, width=80, height=3).split("\n")
                   if line.startswith("nav "))
        assert row.endswith("s old: not current") == stale and len(row) <= 79, row


def test_the_status_counts_an_outage_up_to_the_moment_it_is_asked():
    """The verdicts are drawn as the navigator publishes, and the navigator wakes every 2 s: the outage's age in
    the status is counted up to the moment asked (the time since the last solution added), as the receiver's own
    row beside it counts its silence; before, it lagged that row by a wake and a publish period."""
    drive = make_drive("outage-60s", seed=1, duration_s=70.0)
    nav = Navigator(NavParams(publish_hz=1.0), publish=lambda r: None)
    run_through(nav, [(topic, msg) for _, topic, msg in records(drive, 70.0, seed=1, gnss_off=[(50.0, 80.0)])])
    sol = nav.engine.current()
    assert sol is not None
    drawn = [v for v in nav._verdicts if v.startswith("no GNSS fix for ")]
    assert len(drawn) == 1, nav._verdicts
    drawn_age = int(re.match(r"no GNSS fix for (\d+) s", drawn[0]).group(1))
    assert 15 <= drawn_age <= 21, drawn  # the last fix's epoch at 49 s, the last solution published at 65-70 s
    for ahead_s in (0.0, 2.0, STALE_S - 1.0):  # the status between two wakes; a later one calls it stale
        nav._timebase = TimeBase(lambda a=ahead_s: sol.t_mono_ns + int(a * 1e9))
        sec = nav.section()
        (line,) = [v for v in sec["verdicts"] if v.startswith("no GNSS fix for ")]
        age = int(re.match(r"no GNSS fix for (\d+) s", line).group(1))
        assert age == round((sol.t_ns - nav.engine.last_readings.fix.t_ns) / 1e9 + ahead_s), (line, ahead_s)
        assert line.endswith(drawn[0].split(":", 1)[1]), (line, drawn)  # the same aids named


def test_nav_configuration_is_checked_and_reaches_the_filter():
    cfg = parse("[nav]\nmode = '15'\nlever_arm_m = [0.3, 0, -1.1]\nmounting_rpy_deg = [180, 0, 90]\n"
                "accel_noise_ug_rthz = 800\n", "logger.toml", sim=True)
    p = NavParams.from_config(cfg["nav"])
    assert p.mode == "15" and p.lever_arm_m == (0.3, 0.0, -1.1) and p.mounting_rpy_deg == (180.0, 0.0, 90.0)
    assert p.accel_noise_ug_rthz == 800.0 and p.gyro_noise_dps_rthz == 0.005
    with pytest.raises(ConfigError) as e:
        parse("[nav]\nmode = '16'\nlever_arm_m = [1, 2]\nmounting_rpy_deg = 'flat'\n", "logger.toml", sim=True)
    assert e.value.problems == [
        "logger.toml:2: nav.mode = '16' must be one of '17', '15', 'gnss'",
        "logger.toml:3: nav.lever_arm_m = [1, 2] must be three numbers [x, y, z]",
        "logger.toml:4: nav.mounting_rpy_deg must be a list, not 'flat'",
    ]
    attachments = Attachments()
    assert attach_navigator(parse("[nav]\nenabled = false\n", "x", sim=True)["nav"], attachments) is None
    assert not attachments.taps
    nav = attach_navigator(cfg["nav"], attachments)
    assert attachments.taps == [nav] and attachments.sections["nav"] == nav.section and nav.stop in attachments.close


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short simulated drive through the real daemon: idling, levelling, pulling away."""
    out = tmp_path_factory.mktemp("drive")
    r = subprocess.run([sys.executable, "-m", "logger.cli", "run", "--sim", "--scenario", "outage-60s",
                        "--duration", "70", "--time-scale", "5", "--out", str(out), "--status-socket",
                        str(out / "status.sock")], cwd=ROOT, capture_output=True, text=True,
                       timeout=drive_timeout(70))
    assert r.returncode == 0, r.stderr
    return out


def _replay(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "logger.cli", "replay", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


@pytest.mark.slow_on_board
def test_the_daemon_records_the_live_solution(recorded: Path):
    from logger.recording.drive import read_messages

    msgs = list(read_messages(sorted(recorded.glob("*.mcap")), ("/nav/fix", "/nav/state")))
    fixes = [m for t, m in msgs if t == "/nav/fix"]
    states = [m for t, m in msgs if t == "/nav/state"]
    assert len(fixes) > 20 and len(states) > 5
    assert fixes[-1]["t_sync_ns"] - fixes[0]["t_sync_ns"] > 20e9
    assert {"latitude", "longitude", "altitude", "position_covariance", "sigma_ned_m"} <= set(fixes[-1])
    assert states[-1]["status"] == "navigating" and len(states[-1]["p_diag"]) == 17
    # Logged at their own time, as replay logs them: stamped again at the sink they were off by microseconds.
    from mcap.reader import make_reader

    for path in sorted(recorded.glob("*.mcap")):
        with open(path, "rb") as f:
            off = [m.log_time - json.loads(m.data)["t_sync_ns"]
                   for _, _, m in make_reader(f).iter_messages(topics=["/nav/fix", "/nav/state"])]
        assert off and not any(off), (path, min(off), max(off))


def test_replay_writes_the_trajectory_in_every_mode(recorded: Path, tmp_path: Path):
    files = [str(p) for p in sorted(recorded.glob("*.mcap"))]
    for mode, smooth in (("17", False), ("17", True), ("15", False), ("gnss", False)):
        out = tmp_path / f"{mode}{'s' if smooth else ''}"
        r = _replay(*files, "--out", str(out), "--mode", mode, *(["--smooth"] if smooth else []))
        assert r.returncode == 0, r.stderr
        assert f"wrote {out / 'trajectory.csv'}\nwrote {out / 'trajectory.mcap'}\n" in r.stdout  # every file it wrote
        # The start's height: the fixes before it, brought to it by the barometer (which only mode 17 reads).
        pooled = re.search(r"initialised by gnss course \(its height from \d+ fixes and the barometer", r.stdout)
        assert bool(pooled) == (mode == "17"), r.stdout
        with open(out / "trajectory.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        assert {"t_sync_ns", "lat_deg", "lon_deg", "height_m", "vn_mps", "ve_mps", "vd_mps", "roll_deg", "pitch_deg",
                "yaw_deg", "sn_m", "se_m", "sd_m"} <= set(rows[0])
        assert len(rows) > (30 if mode == "gnss" else 300)
        assert (out / "trajectory.mcap").stat().st_size > 0
    score = subprocess.run([sys.executable, "-m", "logger.cli", "nav-score", str(tmp_path / "17" / "trajectory.csv"),
                            *files, "--json"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert score.returncode == 0, score.stderr
    import json

    rmse = json.loads(score.stdout)["17"]["rmse"]
    assert max(rmse) < 3.0


def test_replay_refuses_what_it_cannot_read(tmp_path: Path):
    r = _replay(str(tmp_path / "none.mcap"), "--out", str(tmp_path))
    assert r.returncode == 2 and "no such file" in r.stderr
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording")
    r = _replay(str(text), "--out", str(tmp_path))
    assert r.returncode == 2 and "not an MCAP file" in r.stderr
    # A file whose head is all a cut left: read up to the cut (nothing), said, and nothing written.
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(b"\x89MCAP0\r\n" + b"\x01" * 50)
    r = _replay(str(cut), "--out", str(tmp_path / "out"))
    assert r.returncode == 1 and "was not closed cleanly" in r.stderr and "no solution from 0 IMU samples" in r.stderr
    assert not (tmp_path / "out").exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    r = _replay(str(empty), "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and "a folder without recorded MCAP files" in r.stderr and "Traceback" not in r.stderr
    # Another tool's file with an /imu of other fields: its messages are skipped and counted, not a traceback.
    from mcap.writer import Writer

    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        w = Writer(f)
        w.start("x", "another tool")
        cid = w.register_channel("/imu", "json", w.register_schema("foo", "jsonschema", b"{}"))
        for i in range(10):
            w.add_message(cid, log_time=i * 10**9, publish_time=i * 10**9, data=b'{"a": 1}')
        w.finish()
    r = _replay(str(foreign), "--out", str(tmp_path / "out"))
    assert r.returncode == 1 and "Traceback" not in r.stderr and not (tmp_path / "out").exists(), r.stderr
    assert r.stderr.startswith("logger replay: 10 /imu messages skipped: not the logger's records (no field "
                               "'accel_mps2')\n"), r.stderr


def test_a_failure_of_the_filter_on_the_loggers_own_records_is_not_taken_for_a_foreign_file(recorded: Path,
                                                                                             monkeypatch):
    """A message the feeding raised on is skipped and counted as "not the logger's records" only when it is not
    one: the recorded drive's own records, on which the filter itself raises a ValueError (math.sqrt of a negative
    variance; numpy 2's LinAlgError is one too, 1.24's is not), the exception a foreign message's wrong field
    raises, stop the replay with the filter named. Before, the drive's 70 barometer readings were "skipped: not the
    logger's records (math domain error)"."""
    from logger.exports.trajectory import FilterFailed, run_filter
    from logger.nav.engine import NavEngine

    files = sorted(recorded.glob("*.mcap"))

    def domain(self: NavEngine, t_ns: int, altitude_m: float) -> None:
        raise ValueError("math domain error")

    monkeypatch.setattr(NavEngine, "baro", domain)
    with pytest.raises(FilterFailed, match=r"failed on a well-formed /baro record .*ValueError: math domain error"):
        run_filter(files, NavParams(), skipped=[])

    def broken(self: NavEngine, *args: object) -> None:  # the FIFO reads, fed in runs of reads
        raise np.linalg.LinAlgError("Singular matrix")  # not a ValueError in numpy 1.24 (Debian 12's)

    monkeypatch.undo()
    monkeypatch.setattr(NavEngine, "imu_batch", broken)
    with pytest.raises(FilterFailed, match=r"well-formed /imu/batch record .*LinAlgError: Singular matrix"):
        run_filter(files, NavParams(), skipped=[])


def _altered(drive: Path, out: Path, changes: dict[tuple[str, int], Callable[[dict], None]]) -> list[Path]:
    """A copy of a recorded drive's files with the n-th message of a topic (counted over the files) changed."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    counts: dict[str, int] = {}
    paths = []
    for src in sorted(drive.glob("*.mcap")):
        dst = out / src.name
        with open(src, "rb") as f, open(dst, "wb") as g:
            w = Writer(g)
            w.start("x", "another tool")
            channels: dict[int, int] = {}
            for schema, channel, msg in make_reader(f).iter_messages():
                if channel.id not in channels:
                    sid = w.register_schema(schema.name, schema.encoding, schema.data) if schema else 0
                    channels[channel.id] = w.register_channel(channel.topic, channel.message_encoding, sid)
                counts[channel.topic] = n = counts.get(channel.topic, 0) + 1
                data = msg.data
                change = changes.get((channel.topic, n))
                if change is not None:
                    m = json.loads(data)
                    change(m)
                    data = json.dumps(m).encode()
                w.add_message(channels[channel.id], log_time=msg.log_time, publish_time=msg.publish_time, data=data)
            w.finish()
        paths.append(dst)
    return paths


def test_a_drive_with_messages_no_logger_writes_is_replayed_without_them(recorded: Path, tmp_path: Path,
                                                                         monkeypatch):
    """Values no logger record holds (times in floats, JSON's Infinity and NaN, a position off the globe, an empty
    FIFO read, a rate beyond any IMU's) are each their message's fault: skipped and counted, the rest replayed. Some
    of them the filter took in and failed on later, on a good record (an Infinity in a sample ended in an SVD that
    did not converge, blamed on an /obd/speed record); some raised only after the filter had taken them."""
    from logger.exports.trajectory import run_filter
    from logger.nav.engine import NavEngine
    from logger.recording import nav_rerun, records

    def setter(key: str, value: object, index: int | None = None) -> Callable[[dict], None]:
        def change(m: dict) -> None:
            if index is None:
                m[key] = value
            else:
                m[key][index] = value
        return change

    def floats(m: dict) -> None:
        m["t_sync_ns"] = [float(t) for t in m["t_sync_ns"]]

    def empty(m: dict) -> None:
        for k in ("t_sync_ns", "t_mono_ns", "accel_x_mps2", "accel_y_mps2", "accel_z_mps2", "gyro_x_rps",
                  "gyro_y_rps", "gyro_z_rps"):
            m[k] = []

    changes = {("/imu/batch", 40): setter("accel_x_mps2", math.inf, 0), ("/imu/batch", 60): floats,
               ("/imu/batch", 80): empty, ("/imu/batch", 100): setter("gyro_x_rps", 1e300, 0),
               ("/gnss/fix", 50): setter("longitude", math.inf), ("/gnss/fix", 52): setter("latitude", 91.0),
               ("/gnss/fix", 54): setter("gnss_time_ns", 1e30), ("/obd/speed", 100): setter("speed_mps", math.inf),
               ("/baro", 50): setter("altitude_m", math.nan)}
    left_out: list[int] = []  # the samples of the FIFO reads changed

    def counting(change: Callable[[dict], None]) -> Callable[[dict], None]:
        def counted_change(m: dict) -> None:
            left_out.append(len(m["t_sync_ns"]))
            change(m)
        return counted_change

    changes = {k: counting(c) if k[0] == "/imu/batch" else c for k, c in changes.items()}
    files = _altered(recorded, tmp_path, changes)
    assert len(left_out) == 4
    fed = [0]  # the samples of the FIFO reads the filter took
    take = records.feed_reads

    def counted(engine: NavEngine, msgs) -> None:
        take(engine, msgs)
        fed[0] += sum(len(m["t_sync_ns"]) for m in msgs)

    monkeypatch.setattr(records, "feed_reads", counted)
    monkeypatch.setattr(nav_rerun, "feed_reads", counted)
    skipped: list[str] = []
    _, rows = run_filter(files, NavParams(), skipped=skipped)
    fed_altered, fed[0] = fed[0], 0
    # Each message counted once: a FIFO read the replay cut where another topic's message falls in it (replay's
    # order, as live) is one message of the file, however many of its pieces are left out.
    counts = {line.split(" ", 2)[1]: line.split(" ", 1)[0] for line in skipped}
    assert counts == {"/baro": "1", "/gnss/fix": "3", "/imu/batch": "4", "/obd/speed": "1"}, skipped
    _, clean_rows = run_filter(sorted(recorded.glob("*.mcap")), NavParams())
    # None of a good read's samples left out with the bad ones (a read the replay cut in pieces loses only the piece
    # that holds the bad value); the float-timed read and the emptied one's wholly.
    assert fed[0] - sum(left_out) <= fed_altered <= fed[0] - 20 and fed[0] > 1000
    assert len(rows) > 0.9 * len(clean_rows)
    assert all(math.isfinite(r.lat_rad) and math.isfinite(r.h_m) for r in rows)


def test_what_is_wrong_with_a_message_that_is_not_a_record_of_its_topic(recorded: Path):
    """record_fault finds nothing wrong with any record the daemon wrote, and names the field of one that is not
    the logger's."""
    from logger.recording.drive import read_messages
    from logger.recording.records import NAV_INPUT_TOPICS, record_fault

    seen: dict[str, dict] = {}
    for topic, msg in read_messages(sorted(recorded.glob("*.mcap")), (*NAV_INPUT_TOPICS, "/imu/batch")):
        assert record_fault(topic, msg) is None, (topic, msg)
        seen.setdefault(topic, msg)
    assert {"/imu/batch", "/gnss/fix", "/obd/speed", "/baro"} <= set(seen)
    batch = dict(seen["/imu/batch"], accel_y_mps2=seen["/imu/batch"]["accel_y_mps2"][:-1])
    assert record_fault("/imu/batch", batch) == "a FIFO read's columns hold different numbers of samples"
    assert record_fault("/imu/batch", {"a": 1}) == "no field 't_sync_ns'"
    floats = dict(seen["/imu/batch"], t_mono_ns=[float(t) for t in seen["/imu/batch"]["t_mono_ns"]])
    assert record_fault("/imu/batch", floats) == "a FIFO read's times are not integer nanoseconds"
    nan = dict(seen["/imu/batch"], gyro_z_rps=[math.nan] * len(seen["/imu/batch"]["gyro_z_rps"]))
    assert record_fault("/imu/batch", nan) == "a sample's acceleration or rate is not a number a sensor gives"
    assert record_fault("/imu/batch", dict(seen["/imu/batch"], t_sync_ns=[])) == "a FIFO read without samples"
    assert record_fault("/imu/batch", dict(seen["/imu/batch"], period_s="0.05")) == "period_s is not a number"
    assert record_fault("/imu", {"a": 1}) == "t_sync_ns is not a time in integer nanoseconds"
    assert record_fault("/imu", {"t_sync_ns": 1, "t_mono_ns": 1, "accel_mps2": [0, 0], "gyro_rps": [0, 0, 0]}) \
        == "accel_mps2 is not three numbers a sensor gives"
    assert record_fault("/gnss/fix", dict(seen["/gnss/fix"], latitude="52.1")) == "latitude is not a number"
    assert record_fault("/gnss/fix", dict(seen["/gnss/fix"], vel_ned_mps=[1.0, 2.0, None])) is None
    assert record_fault("/obd/speed", dict(seen["/obd/speed"], speed_mps=None)) == "speed_mps is not a number"
    assert record_fault("/baro", [1, 2]) == "not an object"


def test_replay_takes_the_drive_folder_and_a_file_cut_short(recorded: Path, tmp_path: Path):
    """The daemon's --out folder stands for its files (what a user has at hand after a drive); a drive cut short by
    a power loss is replayed up to the cut without `logger recover` first, as export and plot read it."""
    files = sorted(recorded.glob("*.mcap"))
    by_files, by_folder = tmp_path / "files", tmp_path / "folder"
    # --one-pass as well: a board mounted as configured gets no second pass, so the trajectories are the same.
    assert _replay(*map(str, files), "--out", str(by_files), "--no-mcap", "--one-pass").returncode == 0
    r = _replay(str(recorded), "--out", str(by_folder), "--no-mcap")
    assert r.returncode == 0, r.stderr
    whole = (by_files / "trajectory.csv").read_text()
    assert (by_folder / "trajectory.csv").read_text() == whole
    # nav-score takes the same folders: replay's --out for its trajectory.csv, the drive's for its files.
    score = subprocess.run([sys.executable, "-m", "logger.cli", "nav-score", str(by_folder), str(recorded), "--json"],
                           cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert score.returncode == 0, score.stderr
    import json

    assert max(json.loads(score.stdout)["folder"]["rmse"]) < 3.0
    cut_dir = tmp_path / "cut"
    cut_dir.mkdir()
    for f in files:
        (cut_dir / f.name).write_bytes(f.read_bytes())
    last = cut_dir / files[-1].name
    last.write_bytes(last.read_bytes()[: last.stat().st_size * 7 // 10])
    r = _replay(str(cut_dir), "--out", str(tmp_path / "from-cut"), "--no-mcap")
    assert r.returncode == 0, r.stderr
    assert f"{last} was not closed cleanly: read up to where it was cut" in r.stderr
    rows = (tmp_path / "from-cut" / "trajectory.csv").read_text().splitlines()
    assert 300 < len(rows) < len(whole.splitlines())
    assert whole.startswith("\n".join(rows[:300]))  # the same solution up to the cut
    # Two drives in one folder (the daemon started twice) are not one trajectory.
    (cut_dir / "drive_20990101T000000Z_0001.mcap").write_bytes(files[0].read_bytes())
    r = _replay(str(cut_dir), "--out", str(tmp_path / "two"))
    assert r.returncode == 2 and "a folder of 2 drives" in r.stderr and "name the files of one drive" in r.stderr


def test_fast_reader_agrees_with_the_mcap_package(recorded: Path, tmp_path: Path):
    """The struct-level reader (and its IMU shortcut, for compact and spaced JSON alike) gives what mcap gives."""
    import json as _json

    from mcap.writer import Writer

    from logger.recording.drive import imu_samples, read_messages, read_with_mcap

    files = sorted(recorded.glob("*.mcap"))
    # Both IMU topics asked for: the FIFO reads come as recorded, not as their samples.
    topics = ("/imu", "/imu/batch", "/gnss/fix", "/obd/speed", "/baro", "/pps")
    fast = list(read_messages(files, topics))
    slow = sorted(r for f in files for r in read_with_mcap(f, set(topics)))
    assert len(fast) == len(slow) > 100
    assert any(topic == "/imu/batch" for topic, _ in fast)
    for (topic, msg), (_, _, topic2, data) in zip(fast, slow, strict=True):
        full = _json.loads(data)
        assert topic == topic2 and all(full[k] == v for k, v in msg.items())
    # The same samples as records of their own (as a drive read a register burst per sample records them), written
    # with json.dumps' default separators: the reader's /imu shortcut takes spaced JSON too.
    samples = [m for _, _, topic, data in slow if topic == "/imu/batch" for m in imu_samples(_json.loads(data))]
    spaced = tmp_path / "spaced.mcap"
    with open(spaced, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        cid = w.register_channel("/imu", "json", sid)
        for msg in samples[:50]:
            w.add_message(cid, log_time=msg["t_sync_ns"], publish_time=0, data=_json.dumps(
                {"t_mono_ns": msg["t_mono_ns"], "t_sync_ns": msg["t_sync_ns"], "sync_state": "locked",
                 "accel_mps2": msg["accel_mps2"], "gyro_rps": msg["gyro_rps"], "temp_degc": 20.0}).encode())
        w.finish()
    again = [m for _, m in read_messages([spaced], ("/imu",))]
    assert again and all(set(m) == {"t_mono_ns", "t_sync_ns", "accel_mps2", "gyro_rps", "temp_degc"} for m in again)


def write_parked_drive(folder: Path, seconds: float) -> None:
    """A drive that never moves, written through the real recorder into ``folder``."""
    from logger.recording.recorder import Recorder
    from logger.recording.settings import RecorderSettings
    from logger.recording.topics import TOPICS

    parked = make_drive("urban", seed=1, duration_s=seconds, intro_s=seconds + 20.0)
    rec = Recorder(RecorderSettings(out_dir=folder), TOPICS)
    rec.start()
    for t, topic, msg in records(parked, seconds, seed=1):
        assert rec.submit(topic, msg, t, msg["t_mono_ns"])
    rec.stop()


def test_replay_of_a_drive_that_never_moves_says_why_and_fails(tmp_path: Path) -> None:
    """A parked drive: the filter levels but never learns its heading, so there is no trajectory to write."""
    write_parked_drive(tmp_path / "drive", 40.0)
    out = tmp_path / "out"
    r = _replay(*map(str, sorted((tmp_path / "drive").glob("*.mcap"))), "--out", str(out))
    assert r.returncode == 1, r.stdout + r.stderr
    assert r.stderr.strip().startswith("logger replay: no solution from 801 IMU samples and 41 GNSS fixes: ")
    assert "waiting for the car to move to find the heading" in r.stderr and "Traceback" not in r.stderr
    assert f"nothing written to {out}" in r.stderr and not out.exists() and r.stdout == ""


def test_a_gnss_only_navigator_publishes_its_fixes_live():
    """nav.mode = "gnss" integrates no IMU sample: its solution is the last fix's, and goes out as such."""
    drive = make_drive("outage-60s", seed=1, duration_s=40.0)
    published: list[Reading] = []
    nav = Navigator(NavParams(mode="gnss", publish_hz=2.0), publish=published.append)
    nav.take([(topic, msg) for _, topic, msg in records(drive, 40.0, seed=1)])
    fixes = [r.payload for r in published if r.topic == "/nav/fix"]
    states = [r.payload for r in published if r.topic == "/nav/state"]
    assert len(fixes) >= 30 and len(states) >= 30, (len(fixes), len(states))
    assert all(f["source"] == "gnss" and f["mode"] == "gnss" for f in fixes)
    times = [f["t_sync_ns"] for f in fixes]
    assert times == sorted(set(times))  # one per fix at most, in order
    truth = drive.state(40.0)
    assert abs(fixes[-1]["latitude"] - math.degrees(truth.lat_rad)) * 111_000 < 10.0


def test_the_benchmarks_filter_from_memory_what_replay_filters_from_the_files(recorded: Path, capsys):
    """tools/bench_kfgins.py times the filter fed from memory and tools/nav_bench.py's live run offers the drive to
    a navigator: both must do the work replay does on the same drive (a FIFO drive's /imu/batch blocks included),
    or their figures measure something else (or, as happened, nothing: they stopped with a TypeError)."""
    sys.path.insert(0, str(ROOT / "tools"))
    import bench_kfgins
    import nav_bench

    from logger.exports.trajectory import read_drive, run_filter

    files = sorted(recorded.glob("*.mcap"))
    params = NavParams(mode="17")
    _, rows = run_filter(files, params)
    msgs = list(read_drive(files, runs=True))
    assert any(t == "/imu/batch" for t, _ in msgs)
    with bench_kfgins.from_memory(msgs):
        _, again = run_filter(files, NavParams(mode="17"))
    assert len(rows) > 100 and again == rows

    nav_bench.bench_live(files, seconds=1.0, start_s=40.0)
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("live navigator, from 40 s:") and " 0 dropped" in line
    assert int(line.split("(")[1].split(" records")[0]) > 0

    # Its 1 kHz stream of FIFO reads (no seq numbers: the navigator cuts reads at the measurements between them).
    nav_bench.bench_fifo(1.0, 16.0, "merged")
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("FIFO reads, merged: 1000 IMU samples in 1 s") and "us per sample" in line


def test_live_check_scores_the_recorded_and_the_offered_live_solution(recorded: Path, capsys):
    sys.path.insert(0, str(ROOT / "tools"))
    import live_check

    assert live_check.main([str(recorded)]) == 0
    out = capsys.readouterr().out
    for name in ("recorded live /nav/fix", "navigator, as offered", "replay, forward"):
        assert name in out

    def rmse(name: str) -> list[float]:
        text = next(x for x in out.splitlines() if name in x).split("V ")[1].split(" m,")[0]
        return [float(v) for v in text.split(" / ")]

    # The daemon's order gives replay's solution (scored at the five fixes a second against every row).
    assert max(abs(a - b) for a, b in zip(rmse("navigator, as offered"), rmse("replay, forward"), strict=True)) < 0.05


def test_a_filter_failing_batch_after_batch_is_a_problem_said_once_a_minute(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A filter that fails on every batch (restarted each time) showed `logger OK`, its row saying "initialising:
    waiting for the IMU: no sample yet" while the IMU delivered, and logged a traceback every 2 s. Now the row says
    it fails, the daemon's status counts it as a problem, and the traceback is logged once a minute at most."""
    import logging

    from test_notify import make_daemon

    from logger.runtime import navigator as navmod

    caplog.set_level(logging.INFO)
    nav = Navigator(NavParams(), publish=lambda r: None)

    def broken(batch: list) -> None:
        raise FloatingPointError("singular covariance")

    nav.take = broken  # type: ignore[method-assign]
    nav.start()
    try:
        drive = make_drive("urban", seed=3, duration_s=20.0)
        for _, topic, msg in records(drive, 20.0, seed=3):
            nav.offer(topic, msg)
            if nav.queued >= 200:
                nav._wake.set()
                deadline = time.monotonic() + 10.0
                while nav.queued and time.monotonic() < deadline:
                    time.sleep(0.01)
        deadline = time.monotonic() + 20.0
        while nav.failures < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        nav.stop()
    assert nav.failures >= 3
    line = (f"filter failing: FloatingPointError: singular covariance (restarted after each of {nav.failures} "
            "failures)")
    sec = nav.section()
    assert sec["verdicts"] == [line] and sec["problems"] == [f"nav: {line}"], sec
    logged = [r for r in caplog.records if r.getMessage().startswith("navigation filter failed")]
    assert len(logged) == 1 and logged[0].exc_info is not None, [r.getMessage() for r in logged]
    # In the daemon's status: one of its problems (this daemon is not started: its recorder's is there too).
    d = make_daemon(tmp_path, [], "")
    d._started_mono = d.tb.monotonic_ns()
    without = d.snapshot()["problems"]
    d.attachments.sections["nav"] = nav.section
    assert d.snapshot()["problems"] == [*without, f"nav: {line}"]
    # Once it no longer fails (FAILING_S since the last failure), a restart after an error is only noted.
    nav._failed_at -= navmod.FAILING_S
    sec = nav.section()
    assert "problems" not in sec and sec["verdicts"][-1] == "filter restarted after an error: FloatingPointError: " \
        "singular covariance", sec


def test_before_its_first_turn_the_filter_does_not_say_the_imu_is_silent():
    """At start the IMU delivers and its row says ok while the filter thread has not had its first turn (it wakes
    every WAKE_S): the nav row said "waiting for the IMU: no sample yet"; it says the records wait for it."""
    nav = Navigator(NavParams())  # no thread started: the records wait
    assert nav.section()["verdicts"] == ["initialising: waiting for the IMU: no sample yet"]
    msg = {"t_sync_ns": 1, "t_mono_ns": 1, "accel_mps2": [0, 0, -9.8], "gyro_rps": [0, 0, 0]}
    nav.offer("/imu", msg)
    nav.offer("/imu", {**msg, "t_sync_ns": 2, "t_mono_ns": 2})
    assert nav.section()["verdicts"] == ["initialising: 2 records waiting for the filter's first turn"]


def test_after_its_first_turn_records_waiting_do_not_stand_for_a_silent_imu():
    """An IMU that never delivers (the chip on another bus) beside a receiver that does: after the filter's first
    turn, the GNSS records waiting for the next one kept "records waiting for the filter's first turn" up for the
    whole run, over the IMU's silence."""
    nav = Navigator(NavParams())  # no thread started: turns by hand
    fix = {"t_sync_ns": 1_700_000_000 * 10**9, "t_mono_ns": 10**9, "gnss_time_ns": None, "sync_state": "locked",
           "fix_ok": True, "fix_mode": 3, "latitude": 48.1, "longitude": 11.5, "altitude": 520.0,
           "vel_ned_mps": [10.0, 0.0, None], "h_acc_m": 2.0, "v_acc_m": 3.0}
    with nav._lock:
        nav.take([("/gnss/fix", fix)])
    nav.offer("/gnss/fix", {**fix, "t_sync_ns": fix["t_sync_ns"] + 10**9, "t_mono_ns": 2 * 10**9})
    assert nav.section()["verdicts"] == ["initialising: waiting for the IMU: no sample yet"]


def test_records_stamped_before_gnss_time_on_a_clock_with_no_bound_never_reach_the_filter() -> None:
    """A board without RTC or network boots in 1970 (or at its image's date) and the receiver's cold start takes
    30 s: until the lock every record is stamped free-running with no bound. The filter levelled on those stamps,
    then crossed the jump of 56 years at the lock: /nav/fix latitudes up to 207281 deg behind a status 'logger OK'
    (or an OverflowError and a restart). Now such records are not offered (live) or fed (replay); the filter
    starts on GNSS time."""
    from logger.exports.trajectory import NavEngine
    from logger.recording.nav_rerun import NavRerun
    from sync.stamp import NO_BOUND_NS

    drive = make_drive("urban", seed=1, duration_s=90)
    recs = records(drive, 90, seed=4)
    t0 = recs[0][0]
    shift = 1_796_000_000 * 1_000_000_000 - 30 * 1_000_000_000  # the board's 1970 against GNSS time
    for t, _, msg in recs:
        if t - t0 < 30 * 1_000_000_000:
            msg["t_sync_ns"] -= shift
            msg["sync_state"], msg["sync_err_ns"] = "freerun", NO_BOUND_NS
    before = sum(1 for t, _, _ in recs if t - t0 < 30 * 1_000_000_000)
    nav = Navigator(NavParams())
    nav.take([(topic, msg) for _, topic, msg in recs[:before]])
    assert nav.unplaced == before and nav.engine.t_last_ns is None  # not one reached the filter
    # The status says so, not "waiting for the IMU: no sample yet" beside an IMU row that says ok
    assert nav.section()["verdicts"] == [f"initialising: waiting for GNSS time (the clock's first lock): {before} "
                                         "records stamped without it left out"]
    # Once a record with GNSS time comes, that is not what the filter waits for: an IMU that never delivers is
    # (the line said "waiting for GNSS time" for the whole run after one unbound record)
    fix = next(msg for _, topic, msg in recs[before:] if topic == "/gnss/fix")
    with nav._lock:
        nav.take([("/gnss/fix", fix)])
    assert nav.section()["verdicts"] == ["initialising: waiting for the IMU: no sample yet"]
    rerun = NavRerun(NavParams(), lambda p: NavEngine(p))
    for _, topic, msg in recs:  # replay's feeding, record by record
        rerun.feed(topic, msg)
    assert rerun.unplaced == before
    s = rerun.engine.state
    assert s is not None
    truth = drive.state(90.0)
    north_m = (s.lat - truth.lat_rad) * 6.37e6
    east_m = (s.lon - truth.lon_rad) * 6.37e6 * math.cos(truth.lat_rad)
    assert math.hypot(north_m, east_m) < 10.0, (north_m, east_m)
