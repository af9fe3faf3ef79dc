"""The u-blox receiver model: its bytes decode with pyubx2 / pynmeagps and say truth + the error applied.

Every test drives the model with a ManualClock over a real pty opened with pyserial; ``Rig.step`` advances
drive time and waits for the model to catch up, so nothing depends on how fast the host is.
"""

from __future__ import annotations

import io
import math
import time
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime

import numpy as np
import pytest
import serial
from pynmeagps import NMEAMessage
from pyubx2 import ERR_RAISE, NMEA_PROTOCOL, POLL, SET, UBX_PROTOCOL, UBXMessage, UBXReader

from logger.recording.topics import GNSS_FIX
from logger.runtime.sampler import Reading
from logger.runtime.sources import GnssSource
from logger.runtime.timebase import TimeBase
from sensors.errors import BusError, ProtocolError, SensorError
from sensors.sim import earth
from sensors.sim.clock import ManualClock
from sensors.sim.gnss_errors import (
    GaussMarkov,
    GnssErrorModel,
    dops_for,
    fix_type_for,
    has_time_fix,
    satellites_tracked,
)
from sensors.sim.gnss_time import GnssTimeline, PulseQuantisation
from sensors.sim.oscillator import Oscillator
from sensors.sim.pps import PpsSignal
from sensors.sim.pty import PtyPort
from sensors.sim.truth import ParkedTrajectory, StraightTrajectory, Trajectory, TruthState
from sensors.sim.uart_line import resample
from sensors.sim.ublox import FACTORY_MESSAGES, UbloxReceiverModel
from sensors.sim.ublox_commands import mon_ver
from sensors.ublox import GnssReceiver
from sensors.ublox_frames import UbxNmeaFramer

NS = 1_000_000_000


@dataclass
class SkySchedule:
    """A trajectory whose sky closes and opens at given times: (from t_s, sky_open) in order."""

    base: Trajectory
    sky: list[tuple[float, float]]
    duration_s: float = math.inf

    def state(self, t_s: float) -> TruthState:
        value = 1.0
        for start, sky in self.sky:
            if t_s >= start:
                value = sky
        return replace(self.base.state(t_s), sky_open=value)


@dataclass
class Rig:
    """A model on a pty, a pyserial port on the other end, and a clock only the test moves."""

    clock: ManualClock = field(default_factory=ManualClock)
    port: PtyPort = field(default_factory=PtyPort)
    models: list[UbloxReceiverModel] = field(default_factory=list)
    serials: list[serial.Serial] = field(default_factory=list)
    arrivals: list[tuple[int, int]] = field(default_factory=list)  # (stream offset at end of chunk, drive ns)
    stream: bytearray = field(default_factory=bytearray)

    def start(self, trajectory: Trajectory | None = None, host_baud: int | None = None,
              **kw: object) -> tuple[UbloxReceiverModel, serial.Serial]:
        kw.setdefault("time_to_first_fix_s", 0.0)
        model = UbloxReceiverModel(self.port, self.clock, trajectory or StraightTrajectory(), **kw)  # type: ignore[arg-type]
        self.models.append(model.start())
        ser = serial.Serial(self.port.path, host_baud or model.baud, timeout=0)
        self.serials.append(ser)
        return model, ser

    def step(self, seconds: float) -> None:
        self.clock.advance(seconds)
        for m in self.models:
            m.sync()

    def read(self, ser: serial.Serial) -> bytes:
        data = ser.read(ser.in_waiting or 0)
        if data:
            self.stream += data
            self.arrivals.append((len(self.stream), self.clock.now_ns()))
        return data

    def drain(self, ser: serial.Serial, quiet_s: float = 0.05) -> bytes:
        """Everything already written: the pty hands bytes over asynchronously, so wait for a quiet line."""
        out = b""
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            ser.timeout = quiet_s
            chunk = ser.read(4096)
            if not chunk:
                break
            out += chunk
        ser.timeout = 0
        if out:
            self.stream += out
            self.arrivals.append((len(self.stream), self.clock.now_ns()))
        return out

    def run(self, ser: serial.Serial, seconds: float, step_s: float = 0.1) -> bytes:
        start = len(self.stream)
        for _ in range(round(seconds / step_s)):
            self.step(step_s)
            self.read(ser)
        self.drain(ser)
        return bytes(self.stream[start:])

    def arrival_ns(self, end_offset: int) -> int:
        for offset, t in self.arrivals:
            if offset >= end_offset:
                return t
        raise AssertionError("byte never arrived")

    def close(self) -> None:
        for m in self.models:
            m.stop()
            assert m.error is None
        for s in self.serials:
            s.close()
        self.port.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def decode(data: bytes) -> list[tuple[bytes, object]]:
    """Every message, checksums enforced: a bad frame raises."""
    reader = UBXReader(io.BytesIO(data), protfilter=NMEA_PROTOCOL | UBX_PROTOCOL, quitonerror=ERR_RAISE)
    return list(reader)


def named(messages: list[tuple[bytes, object]], identity: str) -> list:
    """UBX messages by identity ("NAV-PVT"), NMEA sentences by id whatever the talker ("GGA")."""
    return [m for _, m in messages
            if m.identity == identity or (isinstance(m, NMEAMessage) and m.msgID == identity)]


def lat_lon_of(truth: TruthState, err_ned: np.ndarray) -> tuple[float, float]:
    rn, re = earth.radii(truth.lat_rad)
    lat = truth.lat_rad + err_ned[0] / (rn + truth.height_m)
    lon = truth.lon_rad + err_ned[1] / ((re + truth.height_m) * math.cos(truth.lat_rad))
    return math.degrees(lat), math.degrees(lon)


# ---------------------------------------------------------------------------------------- pure parts


def test_timeline_maps_drive_time_to_gps_week_and_tow() -> None:
    tl = GnssTimeline(datetime(2018, 3, 14, 1, 30, tzinfo=UTC))
    gps = tl.gps_ns(0)
    week, tow_ns = GnssTimeline.week_tow(gps)
    # GPS week 1992 began on Sunday 2018-03-11; add three days, 01:30 and the 18 leap seconds.
    assert week == 1992
    assert tow_ns == (3 * 86_400 + 5_400 + 18) * NS
    assert tl.utc_unix_ns(gps) == int(datetime(2018, 3, 14, 1, 30, tzinfo=UTC).timestamp()) * NS
    assert tl.pulse_drive_ns(0) == NS and tl.pulse_drive_ns(NS) == 2 * NS
    with pytest.raises(ValueError):
        GnssTimeline(datetime(2018, 3, 14))  # naive datetimes are refused


def test_pulse_quantisation_is_a_saw_tooth_within_half_a_tick() -> None:
    q = PulseQuantisation.from_seed(3)
    offsets = np.array([q.edge_offset_ns(1_200_000_000 + k) for k in range(200)])
    assert np.all(np.abs(offsets) <= q.tick_ns / 2 + 1e-9)
    # consecutive pulses slide by the same fraction of a tick, modulo the tick
    steps = np.mod(np.diff(offsets), q.tick_ns)
    assert np.allclose(steps, steps[0], atol=1e-6)
    assert q.qerr_ps(1_200_000_007) == round(-q.edge_offset_ns(1_200_000_007) * 1000)


def test_satellites_fix_and_time_fix_follow_the_sky() -> None:
    assert satellites_tracked(1.0) == 18 and satellites_tracked(0.0) == 0
    assert [fix_type_for(n) for n in (0, 2, 3, 4, 12)] == [0, 0, 2, 3, 3]
    base = ParkedTrajectory().state(0.0)
    assert has_time_fix(replace(base, sky_open=0.17))  # three satellites: a 2D fix solves the clock
    assert not has_time_fix(replace(base, sky_open=0.1))
    assert dops_for(18).pdop < dops_for(6).pdop < dops_for(4).pdop < 99


def test_gauss_markov_keeps_unit_variance_and_its_correlation_time() -> None:
    gm = GaussMarkov(10.0, np.random.default_rng(1))
    xs = np.array([float(gm.step(1.0)[0]) for _ in range(40_000)])
    assert np.var(xs) == pytest.approx(1.0, rel=0.1)
    lag = 10
    r = np.corrcoef(xs[:-lag], xs[lag:])[0, 1]
    assert r == pytest.approx(math.exp(-1.0), abs=0.05)


def test_reported_accuracies_are_the_sigmas_of_the_errors_applied() -> None:
    """Over many correlation times, the RMS error equals the reported accuracy: neither inflated nor hidden."""
    model = GnssErrorModel(np.random.default_rng(7), tau_s=20.0)
    errs = [model.step(1.0, 1.0, 18) for _ in range(20_000)]
    pos = np.array([e.pos_ned_m for e in errs])
    h_acc = errs[0].h_acc_m
    assert math.sqrt(np.mean(pos[:, 0] ** 2 + pos[:, 1] ** 2)) == pytest.approx(h_acc, rel=0.12)
    assert math.sqrt(np.mean(pos[:, 2] ** 2)) == pytest.approx(errs[0].v_acc_m, rel=0.12)
    vel = np.array([e.vel_ned_mps for e in errs])
    assert np.std(vel, axis=0) == pytest.approx([errs[0].s_acc_mps] * 3, rel=0.05)
    assert errs[0].s_acc_mps == pytest.approx(0.05)
    assert 0.3 < h_acc < 2.0  # decimetres to metres under an open sky
    assert not any(np.any(e.multipath_ned_m) for e in errs)  # no reflections under an open sky


def test_multipath_jumps_only_under_a_partly_closed_sky_and_widen_the_accuracy() -> None:
    model = GnssErrorModel(np.random.default_rng(11))
    errs = [model.step(1.0, 0.4, satellites_tracked(0.4)) for _ in range(3000)]
    jumping = [e for e in errs if np.any(e.multipath_ned_m)]
    calm = [e for e in errs if not np.any(e.multipath_ned_m)]
    assert 0.05 < len(jumping) / len(errs) < 0.4  # ~0.03 jumps/s lasting ~5 s
    lengths = [math.hypot(*e.multipath_ned_m[:2]) for e in jumping]
    assert min(lengths) >= 2.0 and max(lengths) <= 10.0
    assert min(e.h_acc_m for e in jumping) > max(e.h_acc_m for e in calm)
    for e in jumping:  # the widened accuracy covers the jump
        assert math.hypot(*e.pos_ned_m[:2]) < 3 * e.h_acc_m


def test_resample_matches_a_hand_worked_uart_frame() -> None:
    # 0xFF at 9600 read at 19200: the start bit lasts two rx bits, so rx data bit 0 reads it low -> 0xFE.
    assert resample(b"\xff", 9600, 19200) == b"\xfe"
    # the same rate passes bytes through; no listener gets nothing
    assert resample(b"\xb5\x62abc", 115200, 115200) == b"\xb5\x62abc"
    assert resample(b"abc", 9600, None) == b""
    # a long stream at a rate twelve times too slow arrives as fewer, different bytes
    data = bytes(range(256)) * 4
    slow = resample(data, 9600, 115200)
    fast = resample(data, 115200, 9600)
    assert slow != data and fast != data
    assert len(fast) < len(data) // 4


# ---------------------------------------------------------------------------------------- the model on a pty


def test_output_decodes_with_valid_checksums_and_says_truth_plus_error(rig: Rig) -> None:
    traj = StraightTrajectory(speed_mps=12.0, heading_deg=30.0)
    model, ser = rig.start(traj, seed=5, messages=("NAV-PVT", "NAV-TIMEGPS", "TIM-TP", "GGA", "RMC"))
    data = rig.run(ser, 10.0)
    msgs = decode(data)
    pvts = named(msgs, "NAV-PVT")
    assert len(pvts) >= 9
    # frame lengths of the M8 protocol: NAV-PVT 92 payload bytes, TIM-TP and NAV-TIMEGPS 16
    sizes = {m.identity: len(raw) for raw, m in msgs if not isinstance(m, NMEAMessage)}
    assert sizes == {"NAV-PVT": 100, "TIM-TP": 24, "NAV-TIMEGPS": 24}
    assert len(named(msgs, "GGA")) == len(named(msgs, "RMC")) == len(pvts)
    for pvt in pvts:
        rec = model.solution_for_itow(pvt.iTOW)
        assert rec is not None and rec.fix_type == 3 == pvt.fixType and pvt.gnssFixOk == 1
        lat, lon = lat_lon_of(rec.truth, rec.pos_error_ned_m)
        assert pvt.lat == pytest.approx(lat, abs=1e-7)
        assert pvt.lon == pytest.approx(lon, abs=1e-7)
        assert pvt.height / 1000 == pytest.approx(rec.truth.height_m - rec.pos_error_ned_m[2], abs=1e-3)
        v = rec.truth.vel_ned_mps + rec.vel_error_ned_mps
        assert [pvt.velN, pvt.velE, pvt.velD] == pytest.approx(list(v * 1000), abs=0.51)
        assert pvt.gSpeed / 1000 == pytest.approx(math.hypot(v[0], v[1]), abs=1e-3)
        assert pvt.headMot == pytest.approx(math.degrees(math.atan2(v[1], v[0])) % 360, abs=1e-4)
        assert pvt.numSV == 18 and pvt.pDOP == pytest.approx(rec.error.dops.pdop, abs=0.01)
        assert pvt.validDate == pvt.validTime == pvt.fullyResolved == 1
        # the truth lies within the accuracy the receiver reports
        assert math.hypot(*rec.pos_error_ned_m[:2]) < 3 * pvt.hAcc / 1000
        assert abs(rec.pos_error_ned_m[2]) < 3 * pvt.vAcc / 1000
    for gga in named(msgs, "GGA"):
        rec = next(r for r in model.history if r.itow_ms % 86_400_000 == _nmea_ms_of_day(gga.time) + 18_000)
        assert gga.lat == pytest.approx(rec.lat_deg, abs=2e-7)  # 1e-5 minute in the sentence
        assert gga.numSV == 12  # NMEA 4.10 counts at most twelve
    for rmc in named(msgs, "RMC"):
        assert rmc.status == "A" and rmc.date == datetime(2018, 3, 14).date()


def _nmea_ms_of_day(t) -> int:
    return ((t.hour * 60 + t.minute) * 60 + t.second) * 1000 + t.microsecond // 1000


def test_time_fields_and_time_pulse_announce_the_next_edge(rig: Rig) -> None:
    model, ser = rig.start(ParkedTrajectory(), seed=2, messages=("NAV-PVT", "NAV-TIMEGPS", "TIM-TP"))
    rig.run(ser, 6.0, step_s=0.05)
    stream = bytes(rig.stream)
    offset = 0
    tps, pvts = [], []
    for raw, msg in decode(stream):
        offset = stream.index(raw, offset) + len(raw)
        if msg.identity == "TIM-TP":
            tps.append((msg, rig.arrival_ns(offset)))
        elif msg.identity == "NAV-PVT":
            pvts.append((msg, rig.arrival_ns(offset)))
        elif msg.identity == "NAV-TIMEGPS":
            assert msg.leapS == 18 and msg.leapSValid == msg.weekValid == msg.towValid == 1
            assert msg.week == 1992
    tl = model.timeline
    assert len(tps) >= 5
    for tp, arrived_ns in tps:
        # UTC time base (M8 default): towMS counts UTC; the pulse is the next whole second
        gps_second = (tp.week * 604_800_000 + tp.towMS) // 1000 + 18
        pulse_drive_ns = tl.drive_ns(gps_second * NS)
        assert tp.timeBase == 1 and tp.utc == 1 and tp.towMS % 1000 == 0
        assert tp.qErr == model.pulse_quantisation.qerr_ps(gps_second)
        assert pulse_drive_ns - 1 * NS < arrived_ns < pulse_drive_ns  # sent during the second before it
    for pvt, arrived_ns in pvts:
        rec = model.solution_for_itow(pvt.iTOW)
        latency = arrived_ns - rec.drive_ns
        assert 0.04 * NS <= latency <= 0.5 * NS  # tens to a few hundred ms, as a receiver does
        utc = datetime(pvt.year, pvt.month, pvt.day, pvt.hour, pvt.min, pvt.second, tzinfo=UTC)
        reported_ns = int(utc.timestamp()) * NS + pvt.nano
        assert reported_ns - tl.utc_unix_ns(rec.gps_ns) == round(rec.time_error_ns)
        assert abs(rec.time_error_ns) < 4 * pvt.tAcc


def test_blockage_takes_satellites_then_the_fix_then_the_time_pulse(rig: Rig) -> None:
    sky = SkySchedule(StraightTrajectory(speed_mps=10.0),
                      [(0.0, 1.0), (3.5, 0.3), (6.5, 0.17), (9.5, 0.1), (12.5, 0.0), (15.5, 1.0)])
    model, ser = rig.start(sky, seed=9)
    msgs = decode(rig.run(ser, 18.0, step_s=0.25))
    by_second = {}
    for pvt in named(msgs, "NAV-PVT"):
        rec = model.solution_for_itow(pvt.iTOW)
        by_second[round(rec.drive_ns / NS)] = (pvt, rec)
    expect = {2: (18, 3), 5: (5, 3), 8: (3, 2), 11: (2, 0), 14: (0, 0), 17: (18, 3)}
    for second, (num_sv, fix_type) in expect.items():
        pvt, rec = by_second[second]
        assert (pvt.numSV, pvt.fixType, pvt.gnssFixOk) == (num_sv, fix_type, int(fix_type >= 2))
        assert pvt.validTime == 1  # the time stays known through the tunnel
    pvt8, rec8 = by_second[8]
    assert pvt8.height == by_second[7][0].height  # 2D: the height is held
    assert pvt8.vAcc / 1000 >= abs(rec8.pos_error_ned_m[2])
    pvt14, rec14 = by_second[14]
    assert pvt14.lat == by_second[10][0].lat  # no fix: the last position stays, its accuracy bounds it
    assert math.hypot(*rec14.pos_error_ned_m[:2]) <= pvt14.hAcc / 1000
    assert pvt14.tAcc > by_second[10][0].tAcc
    # no pulse is announced while the clock is not solved
    pulses = {(tp.towMS // 1000 + 18 - 1) % 86_400 for tp in named(msgs, "TIM-TP")}
    tod0 = (model.timeline.gps_ns(0) // NS) % 86_400
    seconds_with_pulse = {(s - tod0) % 86_400 for s in pulses}
    assert {11, 12, 13, 14, 15}.isdisjoint(seconds_with_pulse)
    assert {1, 2, 5, 8, 16, 17} <= seconds_with_pulse
    ggas = {_nmea_ms_of_day(g.time) // 1000: g for g in named(msgs, "GGA")}
    assert ggas[(tod0 + 14 - 18) % 86_400].quality == 0 and ggas[(tod0 + 14 - 18) % 86_400].lat == ""


def test_before_the_first_fix_nothing_is_valid(rig: Rig) -> None:
    _, ser = rig.start(ParkedTrajectory(), seed=1, time_to_first_fix_s=2.5)
    msgs = decode(rig.run(ser, 4.0))
    first, *rest = named(msgs, "NAV-PVT")
    assert (first.fixType, first.validTime, first.validDate, first.lat, first.numSV) == (0, 0, 0, 0, 0)
    assert first.hAcc == 0xFFFF_FFFF
    assert named(msgs, "GGA")[0].time == "" and named(msgs, "RMC")[0].status == "V"
    assert rest[-1].fixType == 3 and rest[-1].validTime == 1
    assert len(named(msgs, "TIM-TP")) == 1  # only once the clock is solved (t = 3 s)


def test_disabled_messages_stop_and_polls_are_answered(rig: Rig) -> None:
    model, ser = rig.start(seed=3)
    rig.run(ser, 2.0)
    for cls, mid in ((0x01, 0x07), (0xF0, 0x00)):  # NAV-PVT and GGA off on this port (short form)
        ser.write(UBXMessage("CFG", "CFG-MSG", SET, payload=bytes((cls, mid, 0))).serialize())
    ser.write(UBXMessage("CFG", "CFG-MSG", POLL, msgClass=0x01, msgID=0x07).serialize())
    ser.write(UBXMessage("MON", "MON-VER", POLL).serialize())
    start = len(rig.stream)
    rig.run(ser, 4.0)
    msgs = decode(bytes(rig.stream[start:]))
    acks = [(m.clsID, m.msgID) for m in named(msgs, "ACK-ACK")]
    assert acks == [(0x06, 0x01)] * 3
    assert named(msgs, "CFG-MSG")[0].rateUART1 == 0
    assert named(msgs, "MON-VER")[0].swVersion.rstrip(b"\0") == b"ROM CORE 3.01 (107888)"
    assert model.rate("NAV-PVT") == model.rate("GGA") == 0
    late = decode(rig.run(ser, 3.0))
    assert not named(late, "NAV-PVT") and not named(late, "GGA")
    assert len(named(late, "RMC")) == 3 and len(named(late, "TIM-TP")) == 3


@pytest.mark.parametrize("baud, expect_drops", [(9600, True), (115200, False)])
def test_cfg_rate_is_honoured_and_a_slow_line_overflows(rig: Rig, baud: int, expect_drops: bool) -> None:
    model, ser = rig.start(seed=4, baud=baud)
    ser.write(UBXMessage("CFG", "CFG-RATE", SET, measRate=100, navRate=1, timeRef=1).serialize())
    rig.run(ser, 1.0)
    msgs = decode(rig.run(ser, 3.0, step_s=0.05))
    pvts, tps = named(msgs, "NAV-PVT"), named(msgs, "TIM-TP")
    assert model.meas_period_ms == 100
    if expect_drops:  # ~270 bytes ten times a second do not fit through 960 bytes/s: whatever comes, goes
        assert model.counters.tx_overflow_drops > 0 and len(pvts) < 15 and len(tps) <= 3
    else:
        assert model.counters.tx_overflow_drops == 0 and 29 <= len(pvts) <= 31
        assert len(tps) == 3  # the pulse stays at 1 Hz
        assert all(p.iTOW % 100 == 0 for p in pvts)


def test_generations_answer_their_own_configuration_interface(rig: Rig) -> None:
    m8, ser = rig.start(seed=1, messages=(), generation=8)
    ser.write(UBXMessage.config_set(1, 0, [("CFG_RATE_MEAS", 200)]).serialize())
    ser.write(UBXMessage("CFG", "CFG-NAV5", POLL).serialize())  # exists on an M8, not modelled: NAK
    ser.write(UBXMessage("CFG", "CFG-RATE", POLL).serialize())
    msgs = decode(rig.run(ser, 0.5))
    assert [(m.clsID, m.msgID) for m in named(msgs, "ACK-NAK")] == [(0x06, 0x8A), (0x06, 0x24)]
    assert named(msgs, "CFG-RATE")[0].measRate == 1000
    m8.stop()
    rig.models.remove(m8)
    rig.serials.remove(ser)
    ser.close()

    m10, ser = rig.start(seed=1, messages=(), generation=10)
    assert ser.baudrate == 38400
    ser.write(UBXMessage("CFG", "CFG-RATE", SET, measRate=200, navRate=1, timeRef=1).serialize())
    ser.write(UBXMessage.config_set(1, 0, [("CFG_RATE_MEAS", 200), ("CFG_MSGOUT_UBX_NAV_PVT_UART1", 1)]).serialize())
    ser.write(UBXMessage.config_set(1, 0, [("CFG_NAVSPG_DYNMODEL", 4)]).serialize())  # not modelled
    msgs = decode(rig.run(ser, 0.5))
    assert [(m.clsID, m.msgID) for m in named(msgs, "ACK-NAK")] == [(0x06, 0x08), (0x06, 0x8A)]
    assert [(m.clsID, m.msgID) for m in named(msgs, "ACK-ACK")] == [(0x06, 0x8A)]
    assert m10.meas_period_ms == 200 and m10.rate("NAV-PVT") == 1
    assert b"PROTVER=34.10" in mon_ver(m10.generation).serialize()


def test_a_host_at_the_wrong_baud_rate_reads_only_garbage(rig: Rig) -> None:
    model, ser = rig.start(seed=1, baud=9600, host_baud=115200)
    framer = UbxNmeaFramer()
    framer.feed(rig.run(ser, 3.0))
    assert framer.frames_ok == 0 and framer.garbage_bytes > 0
    # and what it sends is not understood either
    ser.write(UBXMessage("MON", "MON-VER", POLL).serialize())
    rig.run(ser, 0.5)
    assert model.counters.input_frames == 0


def test_faults_garbage_corruption_unplug_and_power_cycle(rig: Rig) -> None:
    model, ser = rig.start(seed=8)
    rig.run(ser, 2.0)
    framer = UbxNmeaFramer()
    model.inject_garbage(300)
    model.corrupt_checksums(3)
    framer.feed(rig.run(ser, 3.0))
    assert model.counters.garbage_bytes == 300 and model.counters.corrupted == 3
    assert framer.bad_checksum >= 3 and framer.garbage_bytes >= 300
    assert framer.frames_ok >= 4 * 3 - 3  # the rest still decodes

    receiver = GnssReceiver(ser, rig.port.path)
    model.vanish()
    rig.step(1.0)
    with pytest.raises(BusError, match="serial port lost"):
        receiver.read(0.05)
    assert model.counters.unplugged_drops > 0
    rig.serials.remove(ser)
    ser.close()

    model.reappear()  # plugged back in: open again, as the sampler thread would
    ser2 = serial.Serial(rig.port.path, model.baud, timeout=0)
    rig.serials.append(ser2)
    assert named(decode(rig.run(ser2, 2.0)), "NAV-PVT")

    ser2.write(UBXMessage("CFG", "CFG-MSG", SET, payload=bytes((0x01, 0x07, 0))).serialize())
    rig.run(ser2, 1.0)
    assert model.rate("NAV-PVT") == 0
    model.vanish()
    model.reappear(power_cycle=True)  # the receiver lost power too: RAM configuration is gone
    rig.serials.remove(ser2)
    ser2.close()
    ser3 = serial.Serial(rig.port.path, model.baud, timeout=0)
    rig.serials.append(ser3)
    rig.step(0.1)
    assert model.rate("NAV-PVT") == 1
    assert named(decode(rig.run(ser3, 2.0)), "NAV-PVT")


def test_a_host_that_stops_reading_loses_data_but_never_stalls_the_receiver(rig: Rig) -> None:
    model, ser = rig.start(seed=6, baud=115200)
    for _ in range(40):
        rig.step(1.0)  # nobody reads: the host's buffer fills up
    assert model.counters.host_overrun_drops > 0
    ser.reset_input_buffer()
    rig.stream.clear()
    rig.arrivals.clear()
    msgs = decode(rig.run(ser, 3.0))
    assert len(named(msgs, "NAV-PVT")) >= 2


def test_same_seed_same_errors_whatever_the_command_timing() -> None:
    def errors(poll_first: bool) -> np.ndarray:
        r = Rig()
        try:
            model, ser = r.start(seed=42)
            if poll_first:  # commands draw their own random delays: they must not shift the GNSS errors
                for _ in range(5):
                    ser.write(UBXMessage("MON", "MON-VER", POLL).serialize())
                    r.step(0.3)
            while len(model.history) < 12:
                r.step(1.0)
                r.read(ser)
            return np.array([rec.pos_error_ned_m for rec in list(model.history)[:12]])
        finally:
            r.close()

    assert np.array_equal(errors(False), errors(True))


def test_the_pps_line_model_puts_its_edges_where_tim_tp_says(rig: Rig) -> None:
    """Wired as the simulated vehicle wires them, receiver and PPS line agree on second, offset and fix."""
    sky = SkySchedule(ParkedTrajectory(), [(0.0, 1.0), (4.5, 0.1), (6.5, 1.0)])
    model, ser = rig.start(sky, seed=12, time_to_first_fix_s=1.5, messages=("TIM-TP",))
    signal = PpsSignal(Oscillator(duration_s=100.0, seed=3), model.time_pulse_locked, seed=4,
                       gnss_ns_at_start=model.timeline.start_gps_ns,
                       pulse_offset_ns=model.pulse_quantisation.edge_offset_ns)
    tps = named(decode(rig.run(ser, 9.0)), "TIM-TP")
    announced = {(tp.week * 604_800_000 + tp.towMS) // 1000 + 18: tp.qErr for tp in tps}
    for k in range(signal.first_pulse, 9):
        gps_second = signal.pulse_gnss_ns(k) // NS
        t_s = signal.pulse_true_ns(k) / NS
        edge_offset_ns = signal.pulse_edge_true_ns(k) - signal.pulse_true_ns(k)
        if model.time_pulse_locked(t_s) and model.time_pulse_locked(t_s - 1.0):
            assert gps_second in announced  # announced during the second before, while locked
            assert edge_offset_ns == round(-announced[gps_second] / 1000)  # edge = ideal - qErr
        if not model.time_pulse_locked(t_s - 1.0):  # nothing to announce from: no message for that edge
            assert gps_second not in announced
    # announced at 4 s, lost at 4.5 s: the host must live with an announced edge that never comes
    assert any(not model.time_pulse_locked(s - model.timeline.start_gps_ns / NS) for s in announced)
    assert not model.time_pulse_locked(1.0) and model.time_pulse_locked(2.0)  # time to first fix
    assert not model.time_pulse_locked(5.0)  # two satellites: no time solution


def test_a_read_that_holds_two_seconds_says_its_messages_were_read_late() -> None:
    """A host that reads the port a second late gets two seconds of messages in one read: their stamps say nothing
    of when they came, so the receiver's source marks them ``late_read`` and the clock pairs no PPS edge with them.
    Read on time, nothing is marked."""
    from logger.recording.topics import TIMEPULSE

    rig = Rig()
    model = UbloxReceiverModel(rig.port, rig.clock, StraightTrajectory(), time_to_first_fix_s=0.0).start()
    rig.models.append(model)
    source = GnssSource(rig.port.path, model.baud, configure=False, tb=TimeBase(rig.clock.now_ns, 1.0))
    source.open()
    try:
        def read_all() -> list:
            out = []
            while True:
                got = source.read()
                out += [r for r in got if r.topic in (GNSS_FIX, TIMEPULSE)]
                if not got:
                    return out
        rig.step(2.5)  # the first solutions (start-up) come out together
        read_all()
        on_time = []
        for _ in range(3):  # each second read as it comes
            rig.step(1.0)
            on_time += read_all()
        assert on_time and not any(r.payload["late_read"] for r in on_time), [r.payload for r in on_time]
        rig.step(2.0)  # two seconds without a read
        backlog = read_all()
        fixes = [r for r in backlog if r.topic == GNSS_FIX and r.payload["gnss_time_ns"] is not None]
        assert len({r.payload["gnss_time_ns"] for r in fixes}) >= 2
        assert all(r.payload["late_read"] for r in backlog), [r.payload for r in backlog]
    finally:
        source.close()
        model.stop()


class _RigTime(TimeBase):
    """The rig's clock as the GNSS thread's time base: its waits move the drive (and the model) on."""

    def __init__(self, rig: Rig) -> None:
        super().__init__(rig.clock.now_ns, 1.0)
        self.rig = rig

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.rig.step(seconds)


def _gnss_reads(rig: Rig, source: GnssSource, seconds: float) -> list:
    """The GNSS thread's reads over ``seconds`` of drive time; a SensorError ends them (returned, not raised)."""
    out: list = []
    end = rig.clock.now_ns() + round(seconds * 1e9)
    while rig.clock.now_ns() < end:
        rig.step(0.25)
        try:
            out += source.read()
        except SensorError as exc:
            out.append(exc)
            break
    return out


def _pvt_fixes(reads: list) -> list:
    return [r for r in reads if isinstance(r, Reading) and r.topic == GNSS_FIX and r.payload["source"] == "NAV-PVT"]


@pytest.mark.parametrize("generation, speeds", [(8, (9600, 19200)), (10, (38400, 38400))])
def test_a_receiver_that_restarts_under_the_logger_is_set_up_again(generation: int, speeds: tuple[int, int]) -> None:
    """A voltage dip while the engine cranks restarts the receiver: it comes back at its flash's speed and with its
    factory messages, NMEA only. An M8 whose set-up raised the line to 19200 then sends bytes the port reads as
    garbage; an M10 at 38400 sends NMEA without NAV-PVT. Either way the GNSS thread stops (one line saying why) and
    the port opened again sets the receiver up again: NAV-PVT comes back within seconds."""
    rig = Rig()
    flash, raised = speeds
    model = UbloxReceiverModel(rig.port, rig.clock, StraightTrajectory(), time_to_first_fix_s=0.0,
                               messages=FACTORY_MESSAGES, generation=generation).start()
    rig.models.append(model)
    source = GnssSource(rig.port.path, flash, configure=True, tb=_RigTime(rig))
    try:
        source.open()
        assert model.baud == source.port_baud == raised
        assert len(_pvt_fixes(_gnss_reads(rig, source, 4.0))) >= 3

        model.reappear(power_cycle=True)  # the port stays: a UART on the board, the receiver restarted
        rig.step(0.1)
        reads = _gnss_reads(rig, source, 15.0)
        stop = reads[-1]
        assert isinstance(stop, ProtocolError), reads[-3:]
        expected = f"only garbage at {raised} baud" if raised != flash else "messages but no NAV-PVT"
        assert expected in str(stop) and "Setting it up again" in str(stop) and "\n" not in str(stop)
        assert not _pvt_fixes(reads)
        source.close()

        source.open()  # what the sampler does after its back-off
        assert model.baud == source.port_baud == raised and model.rate("NAV-PVT") == 1
        assert len(_pvt_fixes(_gnss_reads(rig, source, 4.0))) >= 3
    finally:
        source.close()
        model.stop()


def test_a_logger_restarted_while_the_receiver_kept_its_raised_speed_finds_it() -> None:
    """The service restarted (a watchdog, an upgrade) while the receiver kept the 19200 baud of the last set-up in
    RAM: the new logger opens at the configured 9600, hears garbage, and tries the speed a set-up gives next."""
    rig = Rig()
    model = UbloxReceiverModel(rig.port, rig.clock, StraightTrajectory(), time_to_first_fix_s=0.0,
                               messages=FACTORY_MESSAGES, generation=8).start()
    rig.models.append(model)
    first = GnssSource(rig.port.path, 9600, configure=True, tb=_RigTime(rig))
    second = GnssSource(rig.port.path, 9600, configure=True, tb=_RigTime(rig))
    try:
        first.open()
        assert model.baud == first.port_baud == 19200
        first.close()
        second.open()
        assert second.port_baud == 19200 == model.baud
        assert len(_pvt_fixes(_gnss_reads(rig, second, 4.0))) >= 3
    finally:
        first.close()
        second.close()
        model.stop()


def test_damaged_frames_at_the_right_speed_are_not_taken_for_a_restart() -> None:
    """Interference (an engine cranking, a loose connector) damages frames for longer than the restart watch's
    limit: their checksums fail, but they are frames, so the speed is right and nothing is opened again."""
    rig = Rig()
    model = UbloxReceiverModel(rig.port, rig.clock, StraightTrajectory(), time_to_first_fix_s=0.0,
                               messages=FACTORY_MESSAGES, generation=8).start()
    rig.models.append(model)
    source = GnssSource(rig.port.path, 9600, configure=True, tb=_RigTime(rig))
    try:
        source.open()
        _gnss_reads(rig, source, 2.0)
        model.corrupt_checksums(10_000)  # every frame for a while
        reads = _gnss_reads(rig, source, 8.0)
        assert not any(isinstance(r, SensorError) for r in reads) and source.port_baud == 19200
        assert source.receiver.framer.bad_checksum > 20
    finally:
        source.close()
        model.stop()


def test_a_receiver_restarted_with_its_own_saved_setup_is_still_set_up_again() -> None:
    """A ZED-F9P whose owner saved NAV-PVT at 115200 to flash: restarted, it sends NAV-PVT at the same speed but
    none of the raw observations or NAV-TIMEGPS the logger's set-up turned on. The watch covers every message of
    every epoch the set-up asked for, and the read that shows it is recorded before the port is opened again."""
    from test_raw_observations import rawx

    rig = Rig()
    model = UbloxReceiverModel(rig.port, rig.clock, StraightTrajectory(), time_to_first_fix_s=0.0, model="ZED-F9P",
                               baud=115200, messages=("NAV-PVT", "GGA", "RMC"), raw_frames=lambda rec: [rawx(rec)],
                               ).start()
    rig.models.append(model)
    source = GnssSource(rig.port.path, 115200, configure=True, tb=_RigTime(rig), raw_observations=True)
    try:
        source.open()
        assert source.setup.raw_observations == "on" and model.rate("RXM-RAWX") == 1
        assert len(_pvt_fixes(_gnss_reads(rig, source, 3.0))) >= 2
        model.reappear(power_cycle=True)
        rig.step(0.1)
        reads = _gnss_reads(rig, source, 15.0)
        stop = reads[-1]
        assert isinstance(stop, ProtocolError), reads[-3:]
        assert "no NAV-TIMEGPS, RXM-RAWX for" in str(stop), stop
        assert _pvt_fixes(reads)  # the restarted receiver's own NAV-PVT kept coming, and was recorded
        before = reads[-2]
        assert isinstance(before, Reading)  # the read that tripped the watch went out before the error
        source.close()
        source.open()
        assert model.rate("RXM-RAWX") == 1 == model.rate("NAV-TIMEGPS")
    finally:
        source.close()
        model.stop()
