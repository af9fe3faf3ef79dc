"""Receiver setup against the receiver model over a real pty with pyserial.

The setup's ``sleep`` advances the ManualClock and waits for the model to catch up, so every timeout is
drive time and a test never waits for real.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import serial

from sensors.errors import BusError, NoData, ProtocolError
from sensors.sim import earth
from sensors.sim.clock import ManualClock
from sensors.sim.pty import PtyPort
from sensors.sim.truth import StraightTrajectory
from sensors.sim.ublox import FACTORY_MESSAGES, UbloxReceiverModel
from sensors.ublox import GnssFix, GnssReceiver, GnssTime, TimePulse
from sensors.ublox_config import ReceiverSetup, SetupResult, configure_receiver, message_id
from sensors.ublox_frames import UbxNmeaFramer


class Bench:
    """A receiver model on a pty and the host's pyserial port, both on one ManualClock."""

    def __init__(self) -> None:
        self.clock = ManualClock()
        self.port = PtyPort()
        self.model: UbloxReceiverModel | None = None
        self.serials: list[serial.Serial] = []

    def receiver(self, **kw: object) -> UbloxReceiverModel:
        kw.setdefault("time_to_first_fix_s", 0.0)
        kw.setdefault("messages", FACTORY_MESSAGES)
        self.model = UbloxReceiverModel(self.port, self.clock, StraightTrajectory(), **kw).start()  # type: ignore[arg-type]
        return self.model

    def host(self, baud: int) -> serial.Serial:
        ser = serial.Serial(self.port.path, baud, timeout=0)
        self.serials.append(ser)
        return ser

    def sleep(self, seconds: float) -> None:
        self.clock.advance(seconds)
        if self.model is not None:
            self.model.sync()

    def listen(self, ser: serial.Serial, seconds: float) -> UbxNmeaFramer:
        """Frames arriving over ``seconds`` of drive time, through the reader's framer."""
        framer = UbxNmeaFramer()
        framer.frames = []  # type: ignore[attr-defined]
        for _ in range(round(seconds / 0.1)):
            self.sleep(0.1)
            framer.frames += framer.feed(ser.read(ser.in_waiting or 0))  # type: ignore[attr-defined]
        ser.timeout = 0.05
        framer.frames += framer.feed(ser.read(8192))  # type: ignore[attr-defined]
        ser.timeout = 0
        return framer

    def close(self) -> None:
        if self.model is not None:
            self.model.stop()
            assert self.model.error is None
        for s in self.serials:
            s.close()
        self.port.close()


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def identities(framer: UbxNmeaFramer) -> list[str]:
    out = []
    for f in framer.frames:  # type: ignore[attr-defined]
        msg = f.message
        out.append(msg.identity if f.kind == "UBX" else msg.msgID)
    return out


def test_message_names_map_to_class_and_id() -> None:
    assert message_id("NAV-PVT") == (0x01, 0x07)
    assert message_id("TIM-TP") == (0x0D, 0x01)
    assert message_id("GGA") == (0xF0, 0x00)
    with pytest.raises(ValueError, match="unknown u-blox message"):
        message_id("NAV-XYZ")
    with pytest.raises(ValueError, match="baud"):
        ReceiverSetup(baud=12345)


def test_factory_m8_is_configured_by_legacy_messages_each_acknowledged(bench: Bench) -> None:
    model = bench.receiver(generation=8, seed=1)
    ser = bench.host(9600)
    result = configure_receiver(ser, ReceiverSetup(disable=("GGA",)), sleep=bench.sleep)
    assert isinstance(result, SetupResult)
    # NMEA stays on beside the UBX messages: more than 9600 baud carries with room for an epoch's burst.
    assert result.interface == "legacy" and result.baud == 19200 == model.baud == ser.baudrate
    assert result.software == "ROM CORE 3.01 (107888)" and "PROTVER=18.00" in result.extensions
    assert result.acknowledged == (
        "UBX-CFG-RATE (navigation rate 1000 ms x 1 on GPS time)",
        "UBX-CFG-MSG (NAV-PVT on)",
        "UBX-CFG-MSG (TIM-TP on)",
        "UBX-CFG-MSG (NAV-TIMEGPS on)",
        "UBX-CFG-MSG (GGA off)",
        "UBX-CFG-PRT (UART1 at 19200 baud)",
    )
    assert (model.counters.acks, model.counters.naks) == (7, 0)  # the CFG-PRT poll is acknowledged too
    assert [model.rate(m) for m in ("NAV-PVT", "TIM-TP", "NAV-TIMEGPS", "GGA", "RMC")] == [1, 1, 1, 0, 1]
    seen = identities(bench.listen(ser, 3.0))
    assert seen.count("NAV-PVT") == seen.count("NAV-TIMEGPS") == seen.count("RMC") == 3
    assert seen.count("TIM-TP") == 3 and "GGA" not in seen


def test_m10_naks_the_legacy_message_and_is_configured_by_keys(bench: Bench) -> None:
    model = bench.receiver(generation=10, seed=2)
    ser = bench.host(38400)
    result = configure_receiver(ser, sleep=bench.sleep)
    assert result.interface == "keys"
    assert model.counters.naks == 1  # only the first legacy message: the keys are used from then on
    assert result.acknowledged[0] == "UBX-CFG-VALSET CFG-RATE-MEAS, CFG-RATE-NAV, CFG-RATE-TIMEREF"
    assert [model.rate(m) for m in ("NAV-PVT", "TIM-TP", "NAV-TIMEGPS")] == [1, 1, 1]
    assert "NAV-PVT" in identities(bench.listen(ser, 2.0))


def test_f9_still_takes_the_legacy_messages(bench: Bench) -> None:
    model = bench.receiver(generation=9, seed=3)
    result = configure_receiver(bench.host(38400), sleep=bench.sleep)
    assert result.interface == "legacy" and model.counters.naks == 0
    assert "MOD=ZED-F9P" in result.extensions


def test_a_setting_refused_by_both_interfaces_names_itself(bench: Bench) -> None:
    # A NEO-M8N running two constellations manages 10 Hz; 20 Hz is refused, and an M8 has no VALSET.
    model = bench.receiver(generation=8, seed=4, min_meas_period_ms=100)
    with pytest.raises(ProtocolError) as err:
        configure_receiver(bench.host(9600), ReceiverSetup(meas_period_ms=50), sleep=bench.sleep)
    text = str(err.value)
    assert "\n" not in text
    assert "rejected navigation rate 50 ms" in text and "ACK-NAK" in text and "UBX-CFG-RATE" in text
    assert model.counters.naks == 2 and model.meas_period_ms == 1000


def test_silence_is_a_timeout_in_drive_time(bench: Bench) -> None:
    ser = bench.host(9600)  # nothing plays the receiver
    with pytest.raises(NoData) as err:
        configure_receiver(ser, sleep=bench.sleep, reply_timeout_s=0.5, tries=3)
    assert "did not answer UBX-MON-VER within 0.5 s (3 tries)" in str(err.value)
    assert "wrong baud rate" in str(err.value)
    assert bench.clock.now_ns() == pytest.approx(3 * 0.5e9, rel=0.1)


def test_a_receiver_sending_nmea_without_checksums_is_told_so(bench: Bench) -> None:
    """A receiver older than NMEA 2.3 sends its sentences without '*hh': they are refused, and the set-up said
    "sent no NMEA either: wrong baud rate, or nothing on the line" with the NMEA there at the right speed."""
    ser = bench.host(9600)
    line = b"$GPGGA,120000.00,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,\r\n"

    def sleep(seconds: float) -> None:
        bench.port.write(line)  # the receiver's talk while the poll waits
        bench.sleep(seconds)

    with pytest.raises(NoData) as err:
        configure_receiver(ser, sleep=sleep, reply_timeout_s=0.5, tries=2)
    text = str(err.value)
    assert "NMEA sentences without a checksum, which the logger refuses" in text and "wrong baud rate" not in text

    # The daemon's GNSS source, which tries the next speed when nothing is understood at one, says it too (it said
    # "sent no NMEA at 9600, 19200 baud: wrong baud rate").
    from logger.runtime.sources import GnssSource
    from logger.runtime.timebase import TimeBase

    class Talking(TimeBase):
        def sleep(self, seconds: float) -> None:
            sleep(seconds)

    source = GnssSource(bench.port.path, 9600, True, Talking(bench.clock.now_ns, 1.0))
    with pytest.raises(NoData) as err:
        source.open()
    text = str(err.value)
    assert "NMEA sentences without a checksum, which the logger refuses" in text and "wrong baud rate" not in text


def test_a_receiver_at_another_baud_rate_is_silence_too(bench: Bench) -> None:
    model = bench.receiver(generation=8, seed=5, baud=38400)
    with pytest.raises(NoData, match="at 9600 baud"):
        configure_receiver(bench.host(9600), sleep=bench.sleep, reply_timeout_s=0.3)
    assert model.counters.input_frames == 0  # it never understood a byte of it


def test_a_corrupted_reply_is_retried_and_too_many_are_an_error(bench: Bench) -> None:
    model = bench.receiver(generation=8, seed=6, messages=())  # nothing periodic: only replies are sent
    model.corrupt_checksums(1)  # the first MON-VER answer is damaged on the line
    quiet = ReceiverSetup(enable=(), nmea_output=False)  # still nothing periodic afterwards (so no speed change)
    result = configure_receiver(bench.host(9600), quiet, sleep=bench.sleep, reply_timeout_s=0.3)
    assert result.software.startswith("ROM CORE")
    assert model.counters.sent["MON-VER"] == 2 and model.counters.acks == 2  # CFG-RATE, the CFG-PRT poll

    model.corrupt_checksums(3)  # every answer to three tries
    with pytest.raises(NoData, match=r"UBX-MON-VER within 0.3 s \(3 tries\)"):
        configure_receiver(bench.serials[0], sleep=bench.sleep, reply_timeout_s=0.3, tries=3)
    assert model.counters.corrupted == 4


@pytest.mark.parametrize("generation, start_baud, interface", [(8, 9600, "legacy"), (10, 38400, "keys")])
def test_baud_change_is_followed_by_the_host(bench: Bench, generation: int, start_baud: int,
                                             interface: str) -> None:
    model = bench.receiver(generation=generation, seed=7)
    ser = bench.host(start_baud)
    result = configure_receiver(ser, ReceiverSetup(baud=115200), sleep=bench.sleep)
    assert result.interface == interface
    assert result.baud == ser.baudrate == model.baud == 115200
    assert result.acknowledged[-1].endswith("115200") or "115200 baud" in result.acknowledged[-1]
    framer = bench.listen(ser, 2.0)
    assert identities(framer).count("NAV-PVT") == 2 and framer.bad_checksum == 0


def test_a_host_that_does_not_follow_the_baud_change_hears_garbage(bench: Bench) -> None:
    model = bench.receiver(generation=8, seed=8)
    ser = bench.host(9600)
    configure_receiver(ser, ReceiverSetup(baud=57600), sleep=bench.sleep)
    ser.baudrate = 9600  # as if the host had not switched
    framer = bench.listen(ser, 2.0)
    assert model.baud == 57600 and framer.frames_ok == 0 and framer.garbage_bytes > 0


def test_an_unplugged_port_is_a_bus_error(bench: Bench) -> None:
    model = bench.receiver(generation=8, seed=9)
    ser = bench.host(9600)
    model.vanish()
    with pytest.raises(BusError, match="serial port failed"):
        configure_receiver(ser, sleep=bench.sleep)


def test_end_to_end_through_the_gnss_receiver_driver(bench: Bench) -> None:
    model = bench.receiver(generation=8, seed=10)
    receiver = GnssReceiver.open(bench.port.path, 9600)
    bench.serials.append(receiver._port)
    result = configure_receiver(receiver, ReceiverSetup(baud=115200, disable=("GGA", "RMC")),
                                sleep=bench.sleep)
    assert result.baud == 115200
    items = []
    for _ in range(40):
        bench.sleep(0.1)
        items += receiver.read(0.0).items
    bench.sleep(0.0)
    items += receiver.read(0.05).items
    fixes = [i for i in items if isinstance(i, GnssFix)]
    pulses = [i for i in items if isinstance(i, TimePulse)]
    times = [i for i in items if isinstance(i, GnssTime)]
    assert len(fixes) >= 3 and len(pulses) >= 3 and len(times) >= 3
    for fix in fixes:
        assert fix.source and fix.fix_ok and fix.fix_mode == 3 and fix.time_valid
        rec = model.solution_for_itow(fix.itow_ms)
        assert rec is not None
        assert fix.lat_deg == pytest.approx(rec.lat_deg, abs=1e-7)
        assert fix.lon_deg == pytest.approx(rec.lon_deg, abs=1e-7)
        rn, re = earth.radii(rec.truth.lat_rad)
        north = math.radians(fix.lat_deg - math.degrees(rec.truth.lat_rad)) * rn
        east = math.radians(fix.lon_deg - math.degrees(rec.truth.lon_rad)) * re * math.cos(rec.truth.lat_rad)
        assert math.hypot(north, east) < 3 * fix.h_acc_m  # the truth is inside the reported accuracy
        assert fix.time_utc_ns == pytest.approx(model.timeline.utc_unix_ns(rec.gps_ns), abs=1e3)
    tl = model.timeline
    for tp in pulses:
        assert tp.time_base == "utc" and tp.utc_available
        gps_second = (tp.week * 604_800_000 + tp.tow_ms) // 1000 + tl.leap_s
        assert tp.qerr_ps == model.pulse_quantisation.qerr_ps(gps_second)
    assert {t.leap_s for t in times} == {18}


def test_a_factory_receiver_under_a_simulated_sky_gets_a_line_that_carries_its_output(bench: Bench) -> None:
    """NMEA stays on after the set-up: with a GSV series per constellation it is most of a 9600-baud line, so the
    speed goes up to one where NMEA and the UBX messages fill at most LINE_USE of it, and nothing is dropped."""
    from sensors.sim.scenarios import make_drive
    from sensors.ublox_config import LINE_USE

    drive = make_drive("urban", seed=1, duration_s=200)
    bench.model = UbloxReceiverModel(bench.port, bench.clock, drive, time_to_first_fix_s=0.0,
                                     messages=FACTORY_MESSAGES, seed=3).start()
    model, ser = bench.model, bench.host(9600)
    bench.listen(ser, 2.0)
    sent0, bytes0 = dict(model.counters.sent), model.counters.bytes_written
    factory = bench.listen(ser, 10.0)
    factory_bps = (model.counters.bytes_written - bytes0) / 10.0
    in_view = {f.message.numSV for f in factory.frames if f.kind == "NMEA" and f.message.msgID == "GSV"}
    gsv_per_s = (model.counters.sent["GSV"] - sent0["GSV"]) / 10.0
    assert gsv_per_s >= 3 and max(in_view) >= 6  # several constellations, several sentences each

    result = configure_receiver(ser, ReceiverSetup(), sleep=bench.sleep)
    bench.listen(ser, 2.0)
    bytes0, drops0 = model.counters.bytes_written, model.counters.tx_overflow_drops
    seen = identities(bench.listen(ser, 30.0))
    out_bps = (model.counters.bytes_written - bytes0) / 30.0
    assert out_bps > factory_bps + 100  # NAV-PVT, TIM-TP and NAV-TIMEGPS on top of the factory NMEA
    assert out_bps > 9600 / 10 * LINE_USE  # what 9600 baud would have had to carry: more than its share
    assert result.baud == model.baud == ser.baudrate > 9600
    assert out_bps <= result.baud / 10 * LINE_USE
    assert model.counters.tx_overflow_drops == drops0
    assert 29 <= seen.count("NAV-PVT") <= 31 and 29 <= seen.count("TIM-TP") <= 31
    assert {"GGA", "GLL", "GSA", "GSV", "RMC", "VTG"} <= set(seen)


@pytest.mark.parametrize("generation", [8, 9])
def test_raising_the_speed_changes_nothing_else_of_the_port(bench: Bench, generation: int) -> None:
    """An RTK receiver takes its corrections on the same UART (RTCM 2 on an M8P, RTCM 3 on an F9P): the legacy
    CFG-PRT that raises the speed is the port's own settings, polled, with only the speed changed."""
    model = bench.receiver(generation=generation, seed=2)
    before = replace(model._cfg.port)
    assert before.in_rtcm and before.in_rtcm3 == (generation >= 9)
    ser = bench.host(model.baud)
    result = configure_receiver(ser, ReceiverSetup(baud=115200), sleep=bench.sleep)
    assert result.interface == "legacy" and result.baud == model.baud == 115200 != before.baud
    assert replace(model._cfg.port, baud=before.baud) == before


def test_a_factory_receiver_set_to_five_fixes_a_second_gets_a_line_for_them(bench: Bench) -> None:
    """At 5 Hz the output is five times a second's: at the factory's 9600 baud most of it would be dropped in the
    receiver (NAV-PVT and TIM-TP among it); the set-up raises the speed first, and every solution arrives."""
    model = bench.receiver(generation=8, seed=7)
    ser = bench.host(9600)
    result = configure_receiver(ser, ReceiverSetup(meas_period_ms=200), sleep=bench.sleep)
    assert model.meas_period_ms == 200 and result.baud == model.baud == 115200
    bench.listen(ser, 1.0)
    drops = model.counters.tx_overflow_drops
    seen = identities(bench.listen(ser, 10.0))
    assert model.counters.tx_overflow_drops == drops
    assert 49 <= seen.count("NAV-PVT") <= 51 and 9 <= seen.count("TIM-TP") <= 11


def test_on_usb_the_speed_is_left_alone_and_uart1_untouched(bench: Bench) -> None:
    """On USB (CDC-ACM) a baud rate means nothing, and the receiver's UART1 may carry an RTK radio: the set-up asks
    which port it is heard on (a CFG-PRT poll without a port number) and changes no port's speed."""
    model = bench.receiver(generation=8, seed=3, usb=True)
    ser = bench.host(9600)
    result = configure_receiver(ser, ReceiverSetup(meas_period_ms=200), sleep=bench.sleep)
    assert result.baud == ser.baudrate == 9600 and not any("CFG-PRT" in a for a in result.acknowledged)
    assert model.baud == 9600 and model.meas_period_ms == 200  # the model's UART1 speed, as it was
    bench.listen(ser, 1.0)
    seen = identities(bench.listen(ser, 4.0))
    assert 19 <= seen.count("NAV-PVT") <= 21 and model.counters.tx_overflow_drops == 0


def test_a_receiver_its_owner_set_to_ubx_only_is_not_given_nmea_again(bench: Bench) -> None:
    """NMEA output off in the port's settings (its owner's choice): the set-up neither turns it back on nor counts
    NMEA bytes when it judges the line, so 9600 baud carries the UBX messages and stays."""
    model = bench.receiver(generation=8, seed=4, messages=())
    ser = bench.host(9600)
    model._commands.ram.port.out_nmea = False
    result = configure_receiver(ser, ReceiverSetup(), sleep=bench.sleep)
    assert result.baud == model.baud == 9600 and not model._cfg.port.out_nmea
    assert not any("CFG-PRT" in a for a in result.acknowledged)
    seen = identities(bench.listen(ser, 3.0))
    assert seen.count("NAV-PVT") == 3 and not {"GGA", "RMC"} & set(seen)


def test_the_simulated_factory_nmea_is_what_gpsd_reads_of_it(bench: Bench) -> None:
    """The factory sentences the simulated receiver sends (GGA, GLL, GSA, GSV per constellation, RMC, VTG), read by
    gpsd's own decoder (gpsdecode, Debian's gpsd-clients): one epoch's whole sky from its GSV series, each
    satellite's elevation, azimuth and C/N0 under its constellation (gpsd's gnssid and PRN), and the fix."""
    import json
    import shutil
    import subprocess

    from sensors.sim.scenarios import make_drive

    if shutil.which("gpsdecode") is None:
        pytest.skip("gpsd's gpsdecode (gpsd-clients) is not installed")
    drive = make_drive("urban", seed=1, duration_s=60)
    model = bench.model = UbloxReceiverModel(bench.port, bench.clock, drive, time_to_first_fix_s=0.0,
                                             messages=FACTORY_MESSAGES, seed=3).start()
    ser = bench.host(9600)
    data = b""
    for _ in range(40):
        bench.sleep(0.1)
        data += ser.read(ser.in_waiting or 0)
    ser.timeout = 0.2
    data += ser.read(65536)
    decoded = subprocess.run(["gpsdecode", "-d"], input=data, capture_output=True, timeout=60)
    assert decoded.returncode == 0, decoded.stderr
    reports = [json.loads(line) for line in decoded.stdout.decode().splitlines() if line.startswith("{")]
    sky = [r for r in reports if r["class"] == "SKY"]
    tpv = [r for r in reports if r["class"] == "TPV" and r.get("mode") == 3]
    assert sky and tpv
    numbers = {"G": (0, 0), "R": (6, 64), "E": (2, 300)}  # our constellation letter -> gpsd's gnssid, PRN base
    recs = [rec for rec in model.history if rec.satellites]
    last_sky = max(sky, key=lambda r: len(r["satellites"]))
    seen = {(s["gnssid"], s["PRN"]): (s["el"], s["az"], s["ss"]) for s in last_sky["satellites"]}
    sent = [{(numbers[n[0]][0], numbers[n[0]][1] + int(n[1:])): (float(round(el)), float(round(az) % 360), float(cno))
             for n, el, az, cno in rec.satellites} for rec in recs]
    assert seen in sent and len(seen) >= 12  # one epoch's whole sky, every satellite as the receiver said it
    for r in tpv:  # each fix one of the receiver's, to the 1e-5 minute (1.7e-7 deg) NMEA carries
        assert min(max(abs(r["lat"] - rec.lat_deg), abs(r["lon"] - rec.lon_deg)) for rec in recs) < 1e-7, r
