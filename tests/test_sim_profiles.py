"""The simulator's hardware variety (``[sim]`` receiver, gnss_rate_hz, gnss_latency_s, imu, mounting_rpy_deg): each
model is driven by the real driver at the bus, and the whole daemon records a drive with each kind of hardware.

The logger's own board (u-blox at 1 Hz, datasheet MPU-6050, square mounting) is only one of the installations it
meets; these tests hold the others to what the real parts do: an NMEA-only receiver that ignores UBX, fixes at
5 and 10 Hz arriving late, a phone-grade IMU, a board mounted at an angle the filter is not told.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import serial
from helpers_drive import read_messages, run_logger
from mcap.reader import make_reader
from pyubx2 import POLL, SET, UBXMessage
from sync_streams import NS, START_UTC_NS, feed, make_stream

from logger.config import ConfigError, defaults, parse
from logger.exports.trajectory import run_filter
from logger.nav.params import NavParams
from logger.nav.rotations import dcm_from_euler
from logger.recording.drive import iter_messages, open_drive
from logger.recording.topics import GNSS_FIX
from logger.runtime.sources import GnssSource
from logger.runtime.timebase import TimeBase
from sensors.mpu6050 import Mpu6050
from sensors.sim.clock import ManualClock
from sensors.sim.earth import gravity_ned
from sensors.sim.i2c import SimI2cAdapter, SimI2cBus
from sensors.sim.mpu6050 import Mpu6050Errors, Mpu6050Model, chip_from_body
from sensors.sim.profile import PHONE_IMU_RATE_HZ, SimProfile
from sensors.sim.pty import PtyPort
from sensors.sim.truth import ParkedTrajectory, StraightTrajectory, TruthState
from sensors.sim.ublox import NMEA_ONLY_MESSAGES, UbloxReceiverModel
from sensors.ublox import GnssFix, GnssReceiver
from sensors.ublox_config import NoUbxAnswer, ReceiverSetup, configure_receiver
from sensors.ublox_frames import KIND_NMEA, KIND_UBX, UbxNmeaFramer
from sync.clock import PpsClock
from sync.settings import SyncSettings

ROOT = Path(__file__).resolve().parents[1]
G0 = 9.80665


# ---- the [sim] keys -------------------------------------------------------------------------------------------
def test_the_sim_keys_defaults_are_the_profiles_and_each_key_reaches_its_field() -> None:
    assert SimProfile.from_config(defaults()["sim"]) == SimProfile()
    cfg = parse('[sim]\nreceiver = "nmea"\ngnss_rate_hz = 10\ngnss_latency_s = 0.25\nimu = "phone"\n'
                "mounting_rpy_deg = [5, -4, 30]\n", "sim.toml", sim=True)
    assert SimProfile.from_config(cfg["sim"]) == SimProfile("nmea", 10.0, 0.25, "phone", (5.0, -4.0, 30.0))


@pytest.mark.parametrize(("line", "complaint"), [
    ('receiver = "sirf"', "sim.receiver = 'sirf' must be one of 'ubx', 'nmea'"),
    ("gnss_rate_hz = 3", "sim.gnss_rate_hz = 3 must be one of 1, 2, 4, 5, 8, 10"),
    ("gnss_latency_s = 0.9", "sim.gnss_latency_s = 0.9 must be between 0 and 0.6"),
    ('imu = "bmi160"', "sim.imu = 'bmi160' must be one of 'mpu6050', 'phone'"),
    ("mounting_rpy_deg = [0, 0]", "sim.mounting_rpy_deg = [0, 0] must be three numbers"),
])
def test_a_wrong_sim_key_is_named_with_its_line(line: str, complaint: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse(f"[sim]\n{line}\n", "sim.toml", sim=True)
    assert err.value.problems[0].startswith(f"sim.toml:2: {complaint}")


def test_a_file_for_replay_or_a_simulated_run_needs_no_serial_port() -> None:
    """A board's file names the ELM327's and the receiver's ports; one for replay or ``--sim`` need not."""
    with pytest.raises(ConfigError, match=r"obd\.port is required"):
        parse("[nav]\nmode = \"15\"\n", "nav.toml")
    assert parse("[nav]\nmode = \"15\"\n", "nav.toml", devices=False)["nav"]["mode"] == "15"
    with pytest.raises(ConfigError, match=r"unknown key nav\.mod"):  # every key is still checked
        parse("[nav]\nmod = \"15\"\n", "nav.toml", devices=False)


def test_a_simulated_run_from_a_sim_only_file_writes_where_a_run_without_one_does(tmp_path: Path,
                                                                                   monkeypatch) -> None:
    """``logger run --sim --config FILE``: every sensor simulated, and files under ./drives as ``logger run --sim``
    puts them, unless the file says where (the board's /var/lib is not a user's to write)."""
    from logger.cli.run import parse_args, resolve_config

    monkeypatch.chdir(tmp_path)
    only_sim = tmp_path / "sim.toml"
    only_sim.write_text('[sim]\nreceiver = "nmea"\n[obd]\nsource = "elm327"\n')  # no port: --sim opens none
    placed = tmp_path / "placed.toml"
    placed.write_text(f'[logger]\nout_dir = "{tmp_path / "mine"}"\n[sim]\nimu = "phone"\n')
    for f in (only_sim, placed):
        f.chmod(0o644)
    cfg = resolve_config(parse_args(["--sim", "--config", str(only_sim)]))
    assert all(cfg[s]["source"] == "sim" for s in ("imu", "baro", "obd", "gnss", "pps"))
    assert cfg["sim"]["receiver"] == "nmea"
    assert cfg["logger"]["out_dir"] == str(tmp_path / "drives")
    assert cfg["logger"]["state_dir"] == str(tmp_path / "drives" / ".state")
    cfg = resolve_config(parse_args(["--sim", "--config", str(placed)]))
    assert cfg["logger"]["out_dir"] == str(tmp_path / "mine")
    assert cfg["logger"]["state_dir"] == str(tmp_path / "mine" / ".state")
    with pytest.raises(ConfigError, match=r"obd\.port is required"):  # without --sim the file names a device
        resolve_config(parse_args(["--config", str(only_sim)]))


# ---- the receiver: an NMEA-only one, its rate and its latency -------------------------------------------------
class Bench:
    """A receiver model on a pty and the host's port, both on a ManualClock the test (or the setup's sleep) moves."""

    def __init__(self, **kw: object) -> None:
        self.clock = ManualClock()
        self.port = PtyPort()
        kw.setdefault("time_to_first_fix_s", 0.0)
        self.model = UbloxReceiverModel(self.port, self.clock, StraightTrajectory(), **kw).start()  # type: ignore[arg-type]
        self.ser = serial.Serial(self.port.path, self.model.baud, timeout=0)

    def sleep(self, seconds: float) -> None:
        self.clock.advance(seconds)
        self.model.sync()

    def listen(self, seconds: float, step_s: float = 0.01) -> list[tuple[int, object]]:
        """(drive ns when read, frame) of everything the receiver sends over ``seconds``."""
        framer = UbxNmeaFramer()
        out = []
        for _ in range(round(seconds / step_s)):
            self.sleep(step_s)
            out += [(self.clock.now_ns(), f) for f in framer.feed(self.ser.read(self.ser.in_waiting or 0))]
        return out

    def close(self) -> None:
        self.model.stop()
        assert self.model.error is None
        self.ser.close()
        self.port.close()


@pytest.fixture
def bench():
    made: list[Bench] = []

    def make(**kw: object) -> Bench:
        made.append(Bench(**kw))
        return made[-1]

    yield make
    for b in made:
        b.close()


def nmea_epoch_ns(frame: object, day_ns: int) -> int:
    """The UTC time of day of an NMEA sentence with a time field, as ns after ``day_ns``."""
    t = frame.message.time  # type: ignore[attr-defined]
    return day_ns + ((t.hour * 60 + t.minute) * 60 + t.second) * NS + t.microsecond * 1000


def test_an_nmea_only_receiver_sends_gga_rmc_gsa_and_answers_no_ubx(bench) -> None:
    b = bench(ubx=False, messages=NMEA_ONLY_MESSAGES)
    for msg in (UBXMessage("MON", "MON-VER", POLL), UBXMessage("CFG", "CFG-RATE", SET, measRate=200, navRate=1,
                                                             timeRef=1)):
        b.ser.write(msg.serialize())
    frames = [f for _, f in b.listen(3.0)]
    assert frames and all(f.kind == KIND_NMEA for f in frames)
    assert {f.message.msgID for f in frames} == {"GGA", "RMC", "GSA"}  # no GST: no accuracy figures
    assert b.model.counters.input_frames == 2 and b.model.counters.acks == b.model.counters.naks == 0
    assert b.model.meas_period_ms == 1000  # the rate command was not taken either
    # What the reader makes of it: a 3D fix (GSA's mode) with DOPs, no vertical velocity, no accuracy.
    receiver = GnssReceiver(b.ser)
    fixes = []
    for _ in range(30):  # the reader learns where a burst ends from the first one, then reports each at its end
        b.sleep(0.1)
        fixes += [i for i in receiver.read(0.0).items if isinstance(i, GnssFix)]
    assert fixes and all(f.source == "NMEA" for f in fixes)
    f = fixes[-1]
    assert f.fix_mode == 3 and f.pdop is not None and f.h_acc_m is None and f.v_acc_m is None
    assert math.isnan(f.vel_ned_mps[2]) and math.hypot(*f.vel_ned_mps[:2]) == pytest.approx(15.0, abs=0.5)


def test_the_setup_of_an_nmea_only_receiver_says_so_and_its_nmea_is_recorded(bench, caplog) -> None:
    b = bench(ubx=False, messages=NMEA_ONLY_MESSAGES)
    with pytest.raises(NoUbxAnswer) as err:
        configure_receiver(b.ser, sleep=b.sleep)  # two polls a second apart: two epochs of NMEA heard meanwhile
    assert err.value.nmea_sentences > 0 and "though it sent" in str(err.value) and "not a u-blox" in str(err.value)

    class BenchTime(TimeBase):
        def sleep(self, seconds: float) -> None:
            b.sleep(seconds)

    source = GnssSource(b.port.path, b.model.baud, True, BenchTime(b.clock.now_ns))
    with caplog.at_level(logging.WARNING, logger="logger.runtime.sources"):
        source.open()  # the setup gets no answer, and the source keeps the receiver instead of failing
        source.close()
        source.open()  # the next open says nothing new
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and "recording its NMEA unconfigured" in warnings[0]
    assert source.nmea_only and source.setup is None
    b.sleep(2.0)
    fixes = [r.payload for r in source.read() if r.topic == GNSS_FIX]
    source.close()
    assert fixes and all(p["source"] == "NMEA" and p["vel_ned_mps"][2] is None and p["h_acc_m"] is None
                         for p in fixes)


@pytest.mark.parametrize(("meas_ms", "latency_s"), [(200, 0.3), (100, 0.0)])
def test_fixes_come_at_the_receivers_rate_in_epoch_order_after_their_latency(bench, meas_ms: int,
                                                                            latency_s: float) -> None:
    b = bench(ubx=False, messages=NMEA_ONLY_MESSAGES, meas_period_ms=meas_ms, baud=115200, latency_s=(latency_s, 0.06))
    day_ns = b.model.timeline.utc_unix_ns(b.model.timeline.gps_ns(0)) // (86_400 * NS) * 86_400 * NS
    drive_to_utc = b.model.timeline.utc_unix_ns(b.model.timeline.gps_ns(0))
    got = [(t, nmea_epoch_ns(f, day_ns)) for t, f in b.listen(5.0) if f.message.msgID == "GGA"]
    epochs = [e for _, e in got]
    assert all(round((y - x) / 1e6) == meas_ms for x, y in itertools.pairwise(epochs))  # every epoch, in order
    assert len(epochs) >= (5.0 - latency_s - 0.4) * 1000 // meas_ms  # all but those still on their way
    delays = [(t + drive_to_utc - e) / NS for t, e in got]
    # The least delay is the latency asked for (plus the line: a GGA is 7 ms at 115200 baud; reads every 10 ms).
    assert min(delays) >= latency_s and min(delays) < latency_s + 0.03
    # ... and its computing time never takes longer than the solution period (0.35 s at most, at 1 Hz).
    assert max(delays) <= latency_s + meas_ms / 1000 + 0.03


def test_the_setup_keeps_a_fast_receiver_at_its_rate(bench) -> None:
    """The daemon asks a simulated receiver for its own rate (``GnssSource(meas_period_ms=...)``): 10 Hz NAV-PVT."""
    b = bench(meas_period_ms=100, baud=115200)
    result = configure_receiver(b.ser, ReceiverSetup(meas_period_ms=100), sleep=b.sleep)
    assert "UBX-CFG-RATE (navigation rate 100 ms x 1 on GPS time)" in result.acknowledged
    pvt = [f for _, f in b.listen(2.0) if f.kind == KIND_UBX and f.message.identity == "NAV-PVT"]
    itow = [f.message.iTOW for f in pvt]
    assert len(itow) >= 19 and all(y - x == 100 for x, y in itertools.pairwise(itow))


# ---- the clock: fixes between the seconds -----------------------------------------------------------------------
@pytest.mark.parametrize("latency_s", [0.04, 0.6])
def test_fixes_between_whole_seconds_do_not_confuse_the_pps_pairing(latency_s: float) -> None:
    """Ten NMEA fixes a second (no TIM-TP, no iTOW), each arriving after its epoch, in order: only the whole
    second's fix labels an edge, and every edge gets its own second."""
    stream = make_stream(300, seed=4, timepulse=False, fixes=False)
    rng = np.random.default_rng(4)
    arrival = 0
    for k in range(1, 300 * 10):
        epoch_true_ns = k * NS // 10
        arrival = max(epoch_true_ns + round((latency_s + min(rng.exponential(0.06), 0.35)) * NS), arrival)
        stream.events.append((stream.osc.board_ns(arrival), "/gnss/fix",
                              {"gnss_time_ns": START_UTC_NS + epoch_true_ns, "itow_ms": None}))
    stream.events.sort(key=lambda e: e[0])
    now = [0]
    clock = PpsClock(SyncSettings(), monotonic_ns=lambda: now[0], wall_ns=lambda: 0)
    errors = []
    for board, topic, _ in feed(clock, stream.events):
        now[0] = board
        if topic == "/pps":
            s = clock.stamp(board + 17_000_000)
            if s.state == "locked":
                errors.append(s.t_sync_ns - stream.true_unix_ns(board + 17_000_000))
    assert clock.labeller.rejected == 0 and clock.counts["mislabels"] == 0
    assert len(errors) > 280 and max(abs(e) for e in errors) <= 100_000


# ---- the IMU: phone grade and mounting ---------------------------------------------------------------------------
def imu_samples(trajectory, errors: Mpu6050Errors, seconds: float, rate_hz: float = 100.0, seed: int = 5,
                mounting: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Specific force and rate (chip axes) the real driver reads from the model through its FIFO."""
    clock = ManualClock()
    model = Mpu6050Model(clock, trajectory, seed=seed, errors=errors, chip_from_body=mounting)
    bus = SimI2cBus(SimI2cAdapter({0x68: model}))
    try:
        drv = Mpu6050(bus, rate_hz=rate_hz, fifo=True, sleep=clock.sleep)
        drv.configure()
        clock.advance(0.2)
        drv.read_fifo(clock.now_ns())
        acc, gyro = [], []
        for _ in range(round(seconds / 0.25)):
            clock.advance(0.25)
            batch = drv.read_fifo(clock.now_ns())
            acc.append(batch.accel_mps2)
            gyro.append(batch.gyro_rps)
        return np.vstack(acc), np.vstack(gyro)
    finally:
        bus.close()


def test_a_phone_grade_imu_is_about_ten_times_noisier_at_rest() -> None:
    a0, g0 = imu_samples(ParkedTrajectory(), Mpu6050Errors(), 8.0)
    a1, g1 = imu_samples(ParkedTrajectory(), Mpu6050Errors.phone_grade(), 8.0)
    assert len(a0) == len(a1) == 800  # 100 Hz
    ratio_a, ratio_g = a1.std(axis=0) / a0.std(axis=0), g1.std(axis=0) / g0.std(axis=0)
    # The engine's idle tone adds a little on y and z (0.04 m/s^2 against 0.26 m/s^2 of noise).
    assert np.all((ratio_a > 8.5) & (ratio_a < 12)), ratio_a
    assert np.all((ratio_g > 8.5) & (ratio_g < 12)), ratio_g


def test_a_phone_grade_gyro_offset_wanders() -> None:
    """Ten-second means of the rate over ten minutes at rest, with the warming off: the Gauss-Markov wander
    (0.03 deg/s over 200 s) shows against what the random walk and the noise alone leave."""
    def spread(errors: Mpu6050Errors) -> float:
        _, gyro = imu_samples(ParkedTrajectory(), errors, 600.0, rate_hz=20.0, seed=9)
        means = np.degrees(gyro.reshape(60, -1, 3).mean(axis=1))
        return float(means.std(axis=0).mean())

    phone = replace(Mpu6050Errors.phone_grade(), accel_tempco_mg_per_degc=0.0, gyro_tempco_dps_per_degc=0.0)
    steady = spread(replace(phone, gyro_bias_gm_dps=0.0, gyro_bias_walk_dps_per_rts=0.0))
    wandering = spread(phone)
    assert steady < 0.013 and wandering > 0.018, (steady, wandering)  # noise alone: 0.05/sqrt(2 x 10 s)


def test_a_phone_grade_chip_warms_and_its_offsets_follow_the_die_temperature() -> None:
    """Parked for half an hour from power-up: the die warms by most of its 8 degC, and the offsets move with
    what the temperature sensor reads by the coefficients drawn at power-up."""
    phone = replace(Mpu6050Errors.phone_grade(), gyro_bias_gm_dps=0.0, gyro_bias_walk_dps_per_rts=0.0,
                    accel_bias_walk_mg_per_rts=0.0)
    clock = ManualClock()
    model = Mpu6050Model(clock, ParkedTrajectory(), seed=4, errors=phone)
    bus = SimI2cBus(SimI2cAdapter({0x68: model}))
    try:
        drv = Mpu6050(bus, rate_hz=20.0, fifo=True, sleep=clock.sleep)
        drv.configure()
        temps, acc, gyro = [], [], []
        for _ in range(3600):  # half-second reads (the FIFO holds 2.5 s at 20 Hz) over 30 min
            clock.advance(0.5)
            batch = drv.read_fifo(clock.now_ns())
            temps.append(batch.temp_degc)
            acc.append(batch.accel_mps2.mean(axis=0))
            gyro.append(batch.gyro_rps.mean(axis=0))
    finally:
        bus.close()
    temps_a = np.array(temps).reshape(180, 20).mean(axis=1)  # 10 s means
    acc = np.array(acc).reshape(180, 20, 3).mean(axis=1)
    gyro = np.array(gyro).reshape(180, 20, 3).mean(axis=1)
    assert 6.5 < temps_a[-1] - temps_a[0] < 8.0  # 8 (1 - e^-3) less the first 10 s
    slope = np.polyfit(temps_a, np.hstack((np.array(acc), np.array(gyro))), 1)[0]
    # Within the noise of a slope fitted to 180 ten-second means (accelerometer 3e-4 m/s^2/K, gyro 6e-6 rad/s/K).
    assert np.allclose(slope[:3], model._tempco[:3], rtol=0.0, atol=1e-3), (slope, model._tempco)
    assert np.allclose(slope[3:], model._tempco[3:], rtol=0.0, atol=3e-5), (slope, model._tempco)
    assert np.all(model._tempco != 0.0)


def test_a_phone_grade_imu_shakes_while_moving_and_the_mpu6050_does_not() -> None:
    def vertical_std(trajectory, errors: Mpu6050Errors) -> float:
        acc, _ = imu_samples(trajectory, errors, 6.0)
        return float(acc[:, 2].std())

    for errors, low, high in ((Mpu6050Errors.phone_grade(), 1.25, 2.0), (Mpu6050Errors(), 0.9, 1.1)):
        moving, parked = vertical_std(StraightTrajectory(speed_mps=15.0), errors), vertical_std(ParkedTrajectory(),
                                                                                               errors)
        assert low < moving / parked < high, (errors.engine_vibration_mps2, moving, parked)


class Turning:
    """A level vehicle standing still but turning on the spot with a fixed body rate: gravity and a rotation."""

    duration_s = math.inf

    def state(self, t_s: float) -> TruthState:
        g = gravity_ned(math.radians(37.6), 40.0)
        return TruthState(t_s, math.radians(37.6), math.radians(126.9), 40.0, np.zeros(3), np.zeros(3), -g,
                          np.array([0.2, -0.1, 0.3]))


def test_nav_told_the_simulated_mounting_undoes_it_exactly() -> None:
    """The sim's ``mounting_rpy_deg`` and ``[nav] mounting_rpy_deg`` share one convention: the filter's transform
    of the chip's readings (``dcm_from_euler`` of the configured angles, as ``NavEngine`` applies it) gives back
    the vehicle's specific force and rate; left unconfigured, the readings are those of a turned board."""
    rpy = (5.0, -4.0, 30.0)
    acc, gyro = imu_samples(Turning(), Mpu6050Errors.ideal(), 1.0, mounting=chip_from_body(rpy))
    f_body = -gravity_ned(math.radians(37.6), 40.0)
    nav = dcm_from_euler(*np.radians(rpy))
    lsb_a, lsb_w = G0 / 8192, math.radians(1 / 65.5)  # the driver's default ranges: 4 g, 500 deg/s
    assert nav @ acc.mean(axis=0) == pytest.approx(f_body, abs=3 * lsb_a)
    assert nav @ gyro.mean(axis=0) == pytest.approx([0.2, -0.1, 0.3], abs=3 * lsb_w)
    # The chip itself reads a turned board: gravity off its z axis, the rates mixed between axes.
    assert np.abs(acc.mean(axis=0) - f_body).max() > 0.5
    assert np.abs(gyro.mean(axis=0) - [0.2, -0.1, 0.3]).max() > 0.05
    # ... and the opposite convention would not undo it.
    assert np.abs(nav.T @ acc.mean(axis=0) - f_body).max() > 0.5


# ---- the daemon on each kind of hardware ------------------------------------------------------------------------
def simulation_metadata(path: Path) -> dict[str, str]:
    with open(path, "rb") as f:
        return next(dict(m.metadata) for m in make_reader(f).iter_metadata() if m.name == "simulation")


def run_with_profile(tmp: Path, sim: str, duration_s: float) -> tuple[subprocess.CompletedProcess[str], Path]:
    """``logger run --sim --config FILE`` with a file holding only ``[sim]``: no device port is demanded."""
    cfg = tmp / "sim.toml"
    cfg.write_text("[sim]\n" + sim)
    cfg.chmod(0o644)
    r = run_logger("--sim", "--config", str(cfg), "--duration", f"{duration_s:g}", "--time-scale", "4",
                   "--out", str(tmp / "out"), "--status-socket", str(tmp / "status.sock"))
    assert r.returncode == 0, r.stderr
    files = sorted((tmp / "out").glob("*.mcap"))
    assert len(files) == 1
    return r, files[0]


@pytest.mark.slow_on_board
def test_the_daemon_records_an_nmea_only_receiver_at_5_hz(tmp_path: Path) -> None:
    r, path = run_with_profile(tmp_path, 'receiver = "nmea"\ngnss_rate_hz = 5\ngnss_latency_s = 0.3\n', 25.0)
    assert "did not answer UBX-MON-VER" in r.stderr and "recording its NMEA unconfigured" in r.stderr
    msgs = read_messages(path)
    assert "/gnss/timepulse" not in msgs  # no UBX: no TIM-TP
    fixes = [m for _, _, m in msgs["/gnss/fix"]]
    valid = [m for m in fixes if m["fix_ok"]]
    assert len(valid) > 0.9 * len(fixes)
    for m in valid:
        assert m["source"] == "NMEA" and m["itow_ms"] is None
        assert m["vel_ned_mps"][2] is None and m["h_acc_m"] is None and m["v_acc_m"] is None
        assert m["s_acc_mps"] is None and m["position_covariance_type"] == 0 and m["pdop"] is not None
    epochs = [m["gnss_time_ns"] for m in valid]
    assert all(round((b - a) / 1e6) == 200 for a, b in itertools.pairwise(epochs))  # 5 a second, none lost
    assert len(epochs) >= 5 * 20  # the setup's two unanswered polls cost the first 2 s
    # The clock locks on NMEA time alone, and each fix is stamped at least its latency after its epoch.
    locked = [m for m in valid if m["sync_state"] == "locked"]
    assert len(locked) > 0.8 * len(valid)
    assert min(m["t_sync_ns"] - m["gnss_time_ns"] for m in locked) >= 0.3e9 - 1e6
    assert msgs["/sync"][-1][2]["state"] == "locked" and msgs["/sync"][-1][2]["rejected"] == 0
    meta = simulation_metadata(path)
    assert (meta["receiver"], meta["gnss_rate_hz"], meta["gnss_latency_s"]) == ("nmea", "5", "0.3")
    assert SimProfile.from_metadata(meta) == SimProfile(receiver="nmea", gnss_rate_hz=5, gnss_latency_s=0.3)
    # logger replay takes a file with only [nav] (no serial port demanded).
    nav = tmp_path / "nav.toml"
    nav.write_text('[nav]\nmode = "17"\n')
    nav.chmod(0o644)
    rp = subprocess.run([sys.executable, "-m", "logger.cli", "replay", str(path), "--out", str(tmp_path / "replay"),
                         "--config", str(nav), "--no-mcap"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert rp.returncode != 2 and "is required" not in rp.stderr, rp.stderr


@pytest.mark.slow_on_board
@pytest.mark.parametrize("receiver", ["ubx", "nmea"])
def test_the_daemon_records_a_25_hz_receiver_and_the_filter_takes_every_fifth_fix(tmp_path: Path,
                                                                                 receiver: str) -> None:
    """A receiver at its fastest (a u-blox M9's 25 Hz), with its UBX set-up or NMEA only: every epoch recorded 40 ms
    after the last, the clock locked on them, and the filter taking every fifth, on a grid through the whole seconds
    (gnss_max_hz)."""
    _, path = run_with_profile(tmp_path, f'gnss_rate_hz = 25\nreceiver = "{receiver}"\n', 25.0)
    msgs = read_messages(path)
    valid = [m for _, _, m in msgs["/gnss/fix"] if m["fix_ok"]]
    epochs = [m["gnss_time_ns"] for m in valid]
    assert all(round((b - a) / 1e6) == 40 for a, b in itertools.pairwise(epochs)) and len(epochs) > 25 * 20
    assert {m["source"] for m in valid} == ({"NAV-PVT"} if receiver == "ubx" else {"NMEA"})
    assert sum(m["sync_state"] == "locked" for m in valid) > 0.7 * len(valid)
    gnss = next(h for h in msgs["/health"][-1][2]["sensors"] if h["name"] == "gnss")
    assert gnss["rate_hz"] == 25.0
    engine, rows = run_filter([path], NavParams())
    c = engine.counters
    assert c.init_method == "gnss course" and c.resets == 0 and rows
    assert c.gnss_fixes + c.gnss_thinned == len(valid)
    assert c.gnss_fixes == pytest.approx(0.2 * len(valid), abs=3)  # every fifth, on the whole seconds' grid


@pytest.mark.slow_on_board
def test_the_daemon_records_a_phone_grade_imu_and_a_10_hz_receiver(tmp_path: Path) -> None:
    _, path = run_with_profile(tmp_path, 'gnss_rate_hz = 10\nimu = "phone"\nmounting_rpy_deg = [5, -4, 30]\n', 20.0)
    msgs = read_messages(path)
    epochs = [m["gnss_time_ns"] for _, _, m in msgs["/gnss/fix"] if m["gnss_time_ns"] is not None]
    assert all(round((b - a) / 1e6) == 100 for a, b in itertools.pairwise(epochs)) and len(epochs) > 150
    assert {m["source"] for _, _, m in msgs["/gnss/fix"]} == {"NAV-PVT"}
    # The daemon expects ten a second (how they arrive, and so its count of silences, is the host's: every epoch
    # is in the file, above).
    gnss = next(h for h in msgs["/health"][-1][2]["sensors"] if h["name"] == "gnss")
    assert gnss["rate_hz"] == 10.0
    assert "/imu" not in msgs and msgs["/imu/batch"]  # 100 Hz is read through the FIFO: a record per read
    imu = [m.msg for m in iter_messages(open_drive([path]), ["/imu"])]
    t = [m["t_mono_ns"] for m in imu]
    assert (len(t) - 1) / ((t[-1] - t[0]) / 1e9) == pytest.approx(PHONE_IMU_RATE_HZ, rel=0.02)
    assert all(m["fifo"] for m in imu)
    # At rest (the car stands 8 s before it moves off): ten times the datasheet's noise, 4000 ug/sqrt(Hz) through
    # the 44 Hz filter the driver picks for 100 Hz.
    rest = np.array([m["accel_mps2"] for m in imu if m["t_mono_ns"] < t[0] + 6e9])
    pole = math.exp(-2 * math.pi * 44 / 100)
    sigma = 4000e-6 * G0 * math.sqrt(100 * (1 - pole) / (2 * (1 + pole)))
    assert rest[:, 0].std() == pytest.approx(sigma, rel=0.15)
    meta = simulation_metadata(path)
    assert (meta["imu"], meta["gnss_rate_hz"], json.loads(meta["mounting_rpy_deg"])) == ("phone", "10", [5, -4, 30])
    assert SimProfile.from_metadata(meta) == SimProfile(gnss_rate_hz=10, imu="phone", mounting_rpy_deg=(5, -4, 30))
    assert json.loads(meta["imu_errors"])["gyro_bias_gm_dps"] == Mpu6050Errors.phone_grade().gyro_bias_gm_dps
