"""The whole daemon on the simulated vehicle: real threads, drivers, device models and recorder.

A drive runs at a time scale so that tens of seconds of driving take a few seconds here; every figure below
is in drive time (the board's monotonic clock as the simulation runs it).
"""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from extras import need
from helpers_drive import drive_timeout, read_messages, run_logger
from mcap.reader import make_reader

from logger.recording.files import is_finished
from logger.recording.topics import IMU_BATCH
from logger.runtime.status_socket import fetch

SENSOR_TOPICS = ("/imu", "/baro", "/obd/speed", "/gnss/fix", "/pps")
STAMP_FIELDS = ("t_mono_ns", "t_sync_ns", "sync_state", "sync_err_ns", "imu_cnt", "timer_cnt", "seq")


@pytest.fixture(scope="module")
def minute_drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("drive")
    # What README's run command does: a minute of drive in real time (no time scale, so the check of gaps
    # does not magnify the host's scheduling jitter).
    r = run_logger("--sim", "--duration", "60", "--out", str(out), "--status-socket", str(out / "status.sock"))
    assert r.returncode == 0, r.stderr
    files = sorted(out.glob("*.mcap"))
    assert len(files) == 1
    return files[0], read_messages(files[0], imu_samples=True)


@pytest.mark.slow_on_board
def test_a_minute_of_drive_is_complete(minute_drive: tuple[Path, dict]) -> None:
    path, msgs = minute_drive
    assert is_finished(path)
    expected_hz = {"/imu": 20.0, "/baro": 1.0, "/obd/speed": 2.0, "/gnss/fix": 1.0, "/pps": 1.0}
    # What the daemon said of its polled sensors in its last health report (about a second before the end).
    last_health = msgs["/health"][-1][2]
    polled = {"imu": "/imu", "baro": "/baro", "obd": "/obd/speed"}
    health = {polled[h["name"]]: h for h in last_health["sensors"] if h["name"] in polled}
    gnss_health = next(h for h in last_health["sensors"] if h["name"] == "gnss")
    for topic, hz in expected_hz.items():
        t = [m["t_mono_ns"] for _, _, m in msgs[topic]]
        span = (t[-1] - t[0]) / 1e9
        # A fix's arrival wanders with the receiver's solution latency (40-390 ms): its rate is that of the
        # epochs it reports. Every other topic is sampled by the board, on the board's clock.
        if topic == "/gnss/fix":
            when = [m["gnss_time_ns"] for _, _, m in msgs[topic] if m["gnss_time_ns"] is not None]
            assert len(when) >= len(t) - 2  # only the receiver's first second may come without a valid time
        else:
            when = t
        # A period the host let pass unsampled is counted as missed, not shifted: it counts in the schedule. The
        # IMU's FIFO keeps sampling while a read waits: only an overflow loses samples, and it counts them.
        if topic == "/imu":
            missed = sum(m["lost"] for _, _, m in msgs[topic])
        else:
            missed = health[topic]["missed"] if topic in health else 0
        rate = (len(when) - 1 + missed) / ((when[-1] - when[0]) / 1e9)
        assert abs(rate / hz - 1) < 0.01, (topic, rate, missed)
        assert span > 56, (topic, span)  # started within the first seconds, ran to the end
        seq = [m["seq"] for _, _, m in msgs[topic]]
        assert seq == list(range(len(seq))), topic  # nothing lost between sensor and file
        gaps = [b - a for a, b in itertools.pairwise(t)]
        if topic == "/imu":
            # Stamped by the chip's sample clock, read a batch at a time: a sample's interval is the chip's period
            # whenever the host reads, longer only after samples the FIFO lost (and counted).
            assert all(abs(g * hz / 1e9 - 1) < 0.01 for g, (_, _, m) in zip(gaps, msgs[topic][1:], strict=True)
                       if not m["lost"]), (topic, min(gaps), max(gaps))
        elif topic in health:
            # The board's scheduling: an interval over 1.5 periods can only touch a sample the daemon counted as
            # delayed (finished more than half a period after its deadline) or late (after the next deadline: a
            # read stalled mid-way makes both its intervals long), and none may reach 2.5 periods (a gap)
            # unless the daemon counted a gap.
            h = health[topic]
            counted_by = last_health["t_mono_ns"] - 100_000_000  # samples the last report had seen
            long_ones = sum(1 for g, end in zip(gaps, t[1:], strict=True) if g >= 1.5e9 / hz and end < counted_by)
            assert long_ones <= h["delayed"] + h["late"], (topic, long_ones, h)
            assert max(gaps) < 2.5e9 / hz or h["gaps"] > 0, (topic, max(gaps))
        elif topic == "/gnss/fix":
            # Arrival wanders with the receiver's latency and the host's scheduling; the epochs' own regularity
            # is checked below. A silence of 2.5 periods is a gap the daemon must have counted.
            assert max(gaps) < 2.5e9 / hz or gnss_health["gaps"] > 0, (topic, max(gaps))
        else:
            assert max(gaps) < 1.5e9 / hz, (topic, max(gaps))
    # The receiver's epochs follow each other second by second, and every PPS edge is there.
    epochs = [m["gnss_time_ns"] for _, _, m in msgs["/gnss/fix"] if m["gnss_time_ns"] is not None]
    # (the solution's UTC carries the receiver's time error of some ns: compare whole milliseconds)
    assert len(epochs) >= 55 and all(round((b - a) / 1e6) == 1000 for a, b in itertools.pairwise(epochs))
    seqnos = [m["seqno"] for _, _, m in msgs["/pps"]]
    assert seqnos == list(range(seqnos[0], seqnos[0] + len(seqnos)))


def test_the_one_minute_drive_shows_a_live_position_for_most_of_it(minute_drive: tuple[Path, dict]) -> None:
    """README's run: the car levels, moves off and the filter publishes its position for at least 40 of 60 s."""
    _, msgs = minute_drive
    fixes = [m for _, _, m in msgs["/nav/fix"]]
    assert fixes, "no /nav/fix in README's one-minute drive"
    span_s = (fixes[-1]["t_sync_ns"] - fixes[0]["t_sync_ns"]) / 1e9
    assert span_s >= 40.0, span_s
    assert fixes[-1]["source"] == "ins 17-state"


def test_every_sensor_message_is_stamped(minute_drive: tuple[Path, dict]) -> None:
    _, msgs = minute_drive
    # A FIFO read is logged at its first sample's stamps; each of its samples carries its own.
    batches = msgs["/imu/batch"]
    assert batches and all(log == m["t_sync_ns"][0] and pub == m["t_mono_ns"][0] for log, pub, m in batches)
    assert all(len(m[k]) == len(m["t_mono_ns"]) for _, _, m in batches for k in STAMP_FIELDS[1:5])
    for topic in SENSOR_TOPICS:
        for log_time, publish_time, m in msgs[topic]:
            assert all(k in m for k in STAMP_FIELDS), topic
            assert log_time == m["t_sync_ns"] and publish_time == m["t_mono_ns"]
            assert m["sync_state"] in ("freerun", "locked", "holdover") and m["sync_err_ns"] > 0
            assert 1.5e18 < log_time < 4e18  # a real date, not 1970


def test_truth_topics_are_recorded(minute_drive: tuple[Path, dict]) -> None:
    _, msgs = minute_drive
    clock = [m for _, _, m in msgs["/truth/clock"]]
    assert len(clock) > 590  # 10 Hz
    nav = [m for _, _, m in msgs["/truth/nav"]]
    assert {"lat_deg", "lon_deg", "height_m", "vel_ned_mps", "rpy_deg"} <= set(nav[0])
    # One record every 50 ms of drive time, none lost. Counted against the drive time the records span, not the
    # minute of wall time: on a busy host the governor may slow the simulated drive (sensors/sim/governor.py), and
    # a minute then holds less of it (1186 records once, with two test runs sharing the machine).
    span_s = (nav[-1]["t_true_ns"] - nav[0]["t_true_ns"]) / 1e9
    assert span_s > 45.0 and len(nav) >= 20.0 * span_s - 1.0, (len(nav), span_s)
    # The simulated receiver's fixes sit within metres of the truth at the same instant.
    truth = {m["t_true_ns"] // 10**9: m for m in nav}
    near = 0
    for _, _, fix in msgs["/gnss/fix"]:
        if fix["gnss_time_ns"] is None or fix["fix_mode"] < 3:
            continue
        t = truth.get(fix["gnss_time_ns"] // 10**9)
        if t is not None:
            dlat_m = (fix["latitude"] - t["lat_deg"]) * 111_000
            assert abs(dlat_m) < 30
            near += 1
    assert near > 40


@pytest.mark.slow_on_board
def test_kill_9_loses_only_what_was_not_yet_flushed_and_the_next_start_recovers(tmp_path: Path) -> None:
    sock = tmp_path / "status.sock"
    cmd = [sys.executable, "-m", "logger.cli", "run", "--sim", "--duration", "3600", "--time-scale", "5",
           "--out", str(tmp_path), "--status-socket", str(sock)]
    proc = subprocess.Popen(cmd, cwd=Path(__file__).resolve().parents[1], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + drive_timeout(25)
        snap = None
        while time.monotonic() < deadline:
            try:
                snap = fetch(sock)
                if snap["uptime_s"] > 25 and all(s["state"] == "ok" for s in snap["sensors"]):
                    break
            except ConnectionError:
                pass
            time.sleep(0.1)
        assert snap is not None and snap["uptime_s"] > 25, snap
        snap = fetch(sock)
        os.kill(proc.pid, signal.SIGKILL)
        killed_at = snap["t_mono_ns"]
    finally:
        proc.kill()
        proc.wait(10)
    (cut,) = sorted(tmp_path.glob("*.mcap"))
    assert not is_finished(cut)
    r = run_logger("--sim", "--duration", "2", "--time-scale", "5", "--out", str(tmp_path), "--status-socket",
                   str(sock))
    assert r.returncode == 0, r.stderr
    assert f"recovered {cut.name}" in r.stderr
    assert is_finished(cut)
    msgs = read_messages(cut, imu_samples=True)
    # Everything the daemon had said was on disk before the kill is there after the recovery; what came after
    # the last flush is the loss (one flush interval, a second of drive, plus the writer's lag).
    on_disk = snap["recorder"]["on_disk_mono_ns"]
    losses = {}
    for topic in SENSOR_TOPICS:
        last = max(m["t_mono_ns"] for _, _, m in msgs[topic])
        # (the recorder counts a FIFO read by its first sample's time)
        written = on_disk["/imu/batch"] if topic == "/imu" else on_disk[topic]
        assert last >= written, (topic, last, written)
        losses[topic] = (killed_at - last) / 1e9
    # Flushes kept coming while it ran (a writer that had stopped flushing fails this): the newest record on
    # disk was under 10 s of drive (2 s real) old, against a flush every second of drive.
    assert killed_at - max(on_disk.values()) < 10e9, (killed_at, on_disk)
    print("kill -9 loss per topic (s of drive):", {k: round(v, 3) for k, v in losses.items()})
    # The loss bound: at most 2 s of each topic's data (a flush every second of drive, and the writer's lag),
    # beyond the wait for its next sample (a 1 Hz topic's last sample may be a second old at any moment; the IMU's
    # newest samples wait in its FIFO for the next read, four a second).
    periods = {"/imu": 0.25, "/baro": 1.0, "/obd/speed": 0.5, "/gnss/fix": 1.0, "/pps": 1.0}
    assert all(losses[t] <= 2.0 + periods[t] for t in SENSOR_TOPICS), losses


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_sigterm_and_a_hang_up_finish_the_file_cleanly(tmp_path: Path, sig: signal.Signals) -> None:
    """SIGTERM from systemd, SIGHUP from an SSH session dropped under a foreground run: both finish the file."""
    sock = tmp_path / "status.sock"
    proc = subprocess.Popen([sys.executable, "-m", "logger.cli", "run", "--sim", "--time-scale", "5", "--out",
                             str(tmp_path), "--status-socket", str(sock)], cwd=Path(__file__).resolve().parents[1],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + drive_timeout(5)
        while time.monotonic() < deadline:
            try:
                if fetch(sock)["uptime_s"] > 5:
                    break
            except ConnectionError:
                pass
            time.sleep(0.1)
        proc.send_signal(sig)
        assert proc.wait(30) == 0
    finally:
        proc.kill()
    (path,) = sorted(tmp_path.glob("*.mcap"))
    assert is_finished(path)
    assert len(read_messages(path, imu_samples=True)["/imu"]) > 50
    assert not sock.exists()


def load_report_tool():
    from logger.exports import sync_report

    return sync_report


def test_the_clock_locks_and_stamps_within_microseconds(minute_drive: tuple[Path, dict], tmp_path: Path) -> None:
    path, msgs = minute_drive
    tool = load_report_tool()
    drive = tool.Drive.load([path])
    out = tool.report(drive)
    assert out["table6"]["max_count_with_carry"] <= 21  # the paper's Table 6 with PPS present
    for key, s in out["stamp_error"].items():
        assert s["bound_covers"] == 1.0, key
        if key.endswith("locked"):
            assert s["rmse_us"] <= 20 and s["max_us"] <= 100, (key, s)
    assert out["table7_synchronised"]["rmse_s"] < 20e-6
    states = [m["state"] for _, _, m in msgs["/sync"]]
    assert states[-1] == "locked" and states.count("locked") > 50
    need("matplotlib")  # the figures are drawn with it; everything above holds without
    pngs = tool.plots(drive, tmp_path)
    assert all(p.stat().st_size > 10_000 for p in pngs)


@pytest.mark.slow_on_board
def test_a_minute_without_gnss_holds_time_and_relocks_without_going_back(tmp_path: Path) -> None:
    r = run_logger("--sim", "--scenario", "outage-60s", "--duration", "230", "--time-scale", "10", "--out",
                   str(tmp_path), "--status-socket", str(tmp_path / "status.sock"))
    assert r.returncode == 0, r.stderr
    (path,) = sorted(tmp_path.glob("*.mcap"))
    tool = load_report_tool()
    out = tool.report(tool.Drive.load([path]))
    held = {k: s for k, s in out["stamp_error"].items() if k.endswith("holdover")}
    assert held and all(s["max_us"] <= 200 and s["bound_covers"] == 1.0 for s in held.values()), held
    assert out["table6"]["longest_without_pps_s"] > 55
    msgs = read_messages(path, imu_samples=True)
    # What the status said meanwhile (its /health records): the receiver has no fix and its row says so, the PPS
    # line is silent and its row says so too, and the problems blame the sky, not the PPS wiring.
    health = [m for _, _, m in msgs["/health"]]
    outage = [m for m in health if any(p.startswith("gnss: no fix for ") for p in m["problems"])]
    assert len(outage) > 40, [m["problems"] for m in health]
    for m in outage:
        rows = {h["name"]: h for h in m["sensors"]}
        assert m["verdict"] == "degraded" and rows["gnss"]["state"] == "no fix", m
        assert rows["gnss"]["measured_rate_hz"] > 0.5  # the receiver still reports, without a position
    silent = [m for m in outage if any(p.startswith("pps: no pulse for ") for p in m["problems"])]
    assert len(silent) > 30 and all(p.endswith("(the receiver pulses only with a fix)")
                                    for m in silent for p in m["problems"] if p.startswith("pps:"))
    assert all({h["name"]: h["state"] for h in m["sensors"]}["pps"] == "silent" for m in silent)
    assert health[-1]["verdict"] == "ok" and not health[-1]["problems"], health[-1]  # over once the sky is back
    # The end of the run says how long: the receiver about the outage's minute without a fix, the PPS about as
    # long silent, the clock's share of holdover about that minute of the run's 230 s.
    # (A host that fell behind may add a silent second or two of its own: "(no fix 61 s, silent 1 s)".)
    no_fix = re.search(r"^  ! gnss was not ok for (\d+) s of the run \(no fix (\d+) s(?:, silent \d s)?\)$", r.stdout,
                       re.M)
    assert no_fix and 55 <= int(no_fix.group(2)) <= 66, r.stdout
    assert re.search(r"^  ! pps was not ok for (5\d|6\d) s of the run \(silent \d+ s\)$", r.stdout, re.M), r.stdout
    shares = re.search(r"^  clock locked at the end, .*\(locked (\d+)%, holdover (\d+)%(, freerun \d+%)? of the run\)$",
                       r.stdout, re.M)
    assert shares and 20 <= int(shares.group(2)) <= 32, r.stdout
    for topic in SENSOR_TOPICS:
        synced = [m for _, _, m in msgs[topic] if m["sync_state"] != "freerun"]
        states = {m["sync_state"] for m in synced}
        # Locked, then holdover, then locked again. The PPS line has no edge in the outage: the first one after it
        # is in holdover, or already locked when the host read it after the time message that labels it.
        assert states == {"locked", "holdover"} or (topic == "/pps" and states == {"locked"}), (topic, states)
        # Never back, and never equal unless read together: epochs a busy host let pile up in the receiver's
        # buffer come out of one read and share its time.
        stamps = [(m["t_sync_ns"], m["t_mono_ns"]) for m in synced]
        assert all(b[0] > a[0] or (b[0] == a[0] and b[1] == a[1]) for a, b in itertools.pairwise(stamps)), topic


@pytest.mark.slow_on_board
def test_the_end_of_a_run_says_what_it_recorded_and_what_never_came(tmp_path: Path) -> None:
    """The summary after a run: each file by its final name, per-topic counts the file itself holds (read by the
    mcap package), the sensor that never delivered with its error, the clock and the filter, the next commands."""
    cfg = tmp_path / "logger.toml"
    cfg.write_text('[imu]\nsource = "sim"\n[baro]\nsource = "sim"\n[gnss]\nsource = "sim"\n[pps]\nsource = "sim"\n'
                   f'[obd]\nsource = "elm327"\nport = "{tmp_path / "no-adapter"}"\n'
                   f'[logger]\nout_dir = "{tmp_path / "rec"}"\nstatus_socket = "{tmp_path / "status.sock"}"\n'
                   f'state_dir = "{tmp_path / "state"}"\n')
    r = run_logger("--config", str(cfg), "--duration", "8", umask=0)  # a caller who lets everybody read
    assert r.returncode == 0, r.stderr
    out = r.stdout
    (path,) = sorted((tmp_path / "rec").glob("*.mcap"))
    for made in (path, tmp_path / "rec", *(tmp_path / "state").iterdir()):
        assert made.stat().st_mode & 0o007 == 0, (made, oct(made.stat().st_mode))  # group-only, like the service
    assert f"  {path}  " in out and is_finished(path)  # the final (dated) name, not the boot-time one
    with open(path, "rb") as f:
        stats = make_reader(f).get_summary()
    assert stats is not None
    counts = {ch.topic: stats.statistics.channel_message_counts.get(cid, 0) for cid, ch in stats.channels.items()}
    with open(path, "rb") as f:  # a FIFO read's record holds several samples: the summary counts them too
        held = sum(len(json.loads(m.data)["t_sync_ns"])
                   for _, _, m in make_reader(f).iter_messages(topics=[IMU_BATCH]))
    assert counts[IMU_BATCH] > 0 and held > counts[IMU_BATCH]
    for topic, n in counts.items():
        samples = rf"  \({held} samples, \d+\.\d\d Hz\)" if topic == IMU_BATCH else ""
        assert re.search(rf"^  {re.escape(topic)} +{n} +\d+\.\d\d{samples}$", out, re.M), (topic, n, out)
    assert re.search(r"^  ! obd never delivered: .*no-adapter", out, re.M), out
    assert "never delivered" not in out.replace("! obd never delivered", "")  # the others did
    assert re.search(r"^  clock (locked|holdover) at the end, error bound [\d.]+ us", out, re.M), out
    assert re.search(r"^  navigation mode 17: ", out, re.M) and f"  logger info {path}" in out
    info = subprocess.run([sys.executable, "-m", "logger.cli", "info", str(path)], capture_output=True, text=True,
                          timeout=60, cwd=Path(__file__).resolve().parents[1])
    assert info.returncode == 0 and "Silent:    obd (no /obd/speed): configured, never delivered" in info.stdout
    assert "imu (" not in info.stdout.split("Silent:", 1)[1].splitlines()[0]  # the others delivered
