"""Raw observations: the receiver set-up asks for RXM-RAWX and RXM-SFRBX, and the simulated u-blox answers as its
product would (the timing M8T and the high-precision F9P take them, a standard-precision M8N NAKs them by both
interfaces), over a real pty with pyserial on a ManualClock (``test_ublox_config.Bench``)."""

from __future__ import annotations

import io

import pytest
from pyubx2 import GET, UBXMessage
from test_ublox_config import Bench, identities

from sensors.sim.ublox_encode import EpochRecord
from sensors.ublox_config import RAW_MESSAGES, ReceiverSetup, baud_for, configure_receiver, line_budget


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def rawx(rec: EpochRecord) -> bytes:
    """A RXM-RAWX frame of one measurement for the epoch (enough for the set-up tests; no physics)."""
    tow = rec.gps_ns / 1e9 % (7 * 86400)
    return UBXMessage("RXM", "RXM-RAWX", GET, rcvTow=tow, week=2300, leapS=18, numMeas=1, leapSec=1, version=1,
                      prMes_01=2.2e7, cpMes_01=1.1e8, doMes_01=100.0, gnssId_01=0, svId_01=5, cno_01=40,
                      prValid_01=1, cpValid_01=1).serialize()


def sfrbx(rec: EpochRecord) -> bytes:
    words = {f"dwrd_{i:02d}": 0x22C00000 + i for i in range(1, 11)}
    return UBXMessage("RXM", "RXM-SFRBX", GET, gnssId=0, svId=5, numWords=10, version=2, **words).serialize()


@pytest.mark.parametrize("model", ["NEO-M8T", "ZED-F9P"])
def test_a_raw_capable_receiver_acknowledges_raw_observations_at_a_raised_speed(bench: Bench, model: str) -> None:
    m = bench.receiver(model=model, seed=3, raw_frames=lambda rec: [rawx(rec), sfrbx(rec)])
    ser = bench.host(m.baud)
    result = configure_receiver(ser, ReceiverSetup(raw_observations=True), sleep=bench.sleep)
    assert result.raw_observations == "on" and result.raw_refusal == ""
    assert result.interface == "legacy"  # both answer the legacy messages; the F9P takes them too
    assert "UBX-CFG-MSG (RXM-RAWX on)" in result.acknowledged and "UBX-CFG-MSG (RXM-SFRBX on)" in result.acknowledged
    # 1 Hz with raw observations needs about 5.6 kB/s: 115200 baud carries it within 75 %, 57600 does not
    assert result.baud == m.baud == 115200 == ser.baudrate
    assert m.counters.naks == 0 and m.rate("RXM-RAWX") == m.rate("RXM-SFRBX") == 1
    seen = identities(bench.listen(ser, 3.0))
    assert seen.count("RXM-RAWX") == seen.count("RXM-SFRBX") == seen.count("NAV-PVT") == 3
    assert seen.index("RXM-RAWX") < seen.index("NAV-PVT")  # measurements before the solution made of them


def test_an_m8n_naks_raw_observations_and_the_rest_of_the_setup_stands(bench: Bench) -> None:
    m = bench.receiver(model="NEO-M8N", seed=4, raw_frames=lambda rec: [rawx(rec)])
    ser = bench.host(9600)
    result = configure_receiver(ser, ReceiverSetup(raw_observations=True), sleep=bench.sleep)
    assert result.raw_observations == "refused"
    assert result.raw_refusal == ("RXM-RAWX on (ACK-NAK to UBX-CFG-MSG and UBX-CFG-VALSET "
                                  "CFG-MSGOUT-UBX-RXM-RAWX-UART1)")
    assert m.counters.naks == 2  # CFG-MSG, then the key the M8 does not know
    assert result.interface == "legacy"  # a NAK to a message it lacks does not turn the set-up to the keys
    assert m.rate("RXM-RAWX") == 0 and m.rate("NAV-PVT") == 1
    seen = identities(bench.listen(ser, 2.0))
    assert "RXM-RAWX" not in seen and seen.count("NAV-PVT") == 2


def test_without_raw_observations_asked_nothing_changes(bench: Bench) -> None:
    m = bench.receiver(model="NEO-M8T", seed=5, raw_frames=lambda rec: [rawx(rec)])
    ser = bench.host(9600)
    result = configure_receiver(ser, ReceiverSetup(), sleep=bench.sleep)
    # The speed is what the NMEA and UBX output needs (19200), not the 115200 that raw observations would.
    assert result.raw_observations == "off" and result.baud == 19200 == baud_for(ReceiverSetup())
    assert m.rate("RXM-RAWX") == 0
    assert not any("RXM" in a for a in result.acknowledged)
    assert "RXM-RAWX" not in identities(bench.listen(ser, 2.0))


def test_the_line_budget_picks_the_slowest_speed_that_carries_the_output() -> None:
    assert RAW_MESSAGES == ("RXM-RAWX", "RXM-SFRBX")
    one_hz = ReceiverSetup(raw_observations=True)
    # NAV-PVT 100 + TIM-TP 24 + NAV-TIMEGPS 24 + NMEA 1000 + RAWX (16 + 32 * 64 + 8) a solution, SFRBX 2400 a second
    assert line_budget(one_hz) == 100 + 24 + 24 + 1000 + 2072 + 2400
    assert baud_for(one_hz) == 115200
    assert baud_for(ReceiverSetup(meas_period_ms=200, raw_observations=True)) == 460800
    assert baud_for(ReceiverSetup(meas_period_ms=100, raw_observations=True)) == 921600
    assert baud_for(ReceiverSetup()) == 19200  # without raw: the logger's own messages fit a slow line


def test_the_sent_log_holds_every_byte_the_host_received(bench: Bench) -> None:
    log = io.BytesIO()
    m = bench.receiver(model="NEO-M8T", seed=6, raw_frames=lambda rec: [rawx(rec)], sent_log=log)
    ser = bench.host(m.baud)
    got = bytearray()
    for _ in range(25):
        bench.sleep(0.1)
        got += ser.read(ser.in_waiting or 0)
    ser.timeout = 0.05
    got += ser.read(65536)
    assert len(got) > 250 and bytes(got) == log.getvalue()
