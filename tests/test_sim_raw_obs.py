"""Raw GPS observations of the simulator (sensors/sim/raw_obs.py): orbits, navigation file, RXM-RAWX, tracking, and
RTKLIB's real tools end to end (``convbin`` to RINEX, ``rnx2rtkp`` single point and kinematic against a base).

The RTKLIB tests skip where Debian's ``rtklib`` is not installed (CI installs it); the rest run everywhere.
"""

from __future__ import annotations

import io
import math
import statistics
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from pyubx2 import UBXReader
from test_ublox_config import Bench, identities

from sensors.sim import earth
from sensors.sim.gnss_errors import Constellation, SkyGeometry
from sensors.sim.gnss_time import NS_PER_S, GnssTimeline
from sensors.sim.raw_obs import (
    LAMBDA_L1,
    GpsBroadcast,
    RawObservations,
    ReceiverClock,
    klobuchar_m,
    read_rinex_nav,
    record_raw_drive,
    rxm_rawx,
    saastamoinen_m,
    write_rinex_nav,
)
from sensors.sim.scenarios import make_drive
from sensors.sim.truth import ParkedTrajectory, StraightTrajectory
from sensors.ublox_config import ReceiverSetup, configure_receiver

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import sim_raw  # tools/sim_raw.py: the RTKLIB runs and the scoring against the truth

C = 299_792_458.0
OMGE = 7.2921151467e-5
# A start 30 min before a GPS week ends (Saturday 23:59:42 UTC): orbits and clocks across the week boundary.
WEEK_END = GnssTimeline(datetime(2018, 3, 17, 23, 30, tzinfo=UTC))
needs_rtklib = pytest.mark.skipif(bool(sim_raw.rtklib_missing()),
                                  reason="convbin/rnx2rtkp is not installed (apt-get install rtklib)")


def quiet(broadcast: GpsBroadcast, **kw: object) -> RawObservations:
    """A receiver without measurement noise, so formulas can be checked to the millimetre."""
    return RawObservations(broadcast, code_sigma_m=0.0, carrier_sigma_m=0.0, doppler_sigma_hz=0.0, **kw)


@pytest.mark.parametrize("timeline", [GnssTimeline(), WEEK_END], ids=["default", "week-end"])
def test_broadcast_orbits_put_the_satellites_where_the_simulated_sky_has_them(timeline: GnssTimeline) -> None:
    sky = Constellation(epoch_s=33_286.0)
    b = GpsBroadcast(sky, timeline, seed=1)
    assert b.prns == tuple(range(1, 25))  # the Walker 24/6/1 GPS of the sky, PRN = its name
    worst = 0.0
    for t in (0.0, 1799.5, 1800.5, 3600.0, 5399.0, 7300.0):  # across toe switches and the week's end
        gps_ns = timeline.gps_ns(round(t * NS_PER_S))
        ref = sky.ecef(t)
        for prn in b.prns:
            pos, _ = b.position(prn, gps_ns)
            worst = max(worst, float(np.linalg.norm(pos - ref[b.index[prn]])))
    assert worst < 1e-3
    # The set in use has the toe nearest in time, in the week that toe falls in.
    eph = b.current(5, timeline.gps_ns(round(2400 * NS_PER_S)))
    week, tow_ns = GnssTimeline.week_tow(timeline.gps_ns(round(2400 * NS_PER_S)))
    assert abs((eph.week - week) * 604_800 + eph.toe_s - tow_ns / NS_PER_S) <= 3600


def test_the_navigation_file_gives_the_model_s_orbits_and_clocks(tmp_path: Path) -> None:
    b = GpsBroadcast(Constellation(epoch_s=1234.0), WEEK_END, seed=2)
    start = WEEK_END.start_gps_ns
    ephs = b.ephemerides(start, start + 3600 * NS_PER_S)
    assert {e.week for e in ephs} == {1992, 1993}  # the week's last toe and the next week's first
    assert len(ephs) == 24 * len({(e.week, e.toe_s) for e in ephs})
    buf = io.StringIO()
    write_rinex_nav(buf, ephs, leap_s=18)
    text = buf.getvalue()
    assert text.startswith("     3.04           N: GNSS NAV DATA    G: GPS              RINEX VERSION / TYPE\n")
    assert all(len(line) <= 80 for line in text.splitlines())
    path = tmp_path / "nav.rnx"
    path.write_text(text)
    back, alpha, beta = read_rinex_nav(path)
    assert len(back) == len(ephs)
    assert alpha == (1.1176e-08, -7.4506e-09, -5.9605e-08, 1.1921e-07)
    assert beta == (1.1674e05, -2.2938e05, -1.3107e05, 1.0486e06)
    worst_pos = worst_clock = 0.0
    for e in back:
        ref = b.ephemeris(e.prn, e.week, int(e.toe_s))
        assert (e.toc_s, e.iode, e.health, e.sv_accuracy_m) == (ref.toc_s, ref.iode, 0, 2.0)
        for dt in (-7200.0, -1.0, 0.0, 3599.0, 7200.0):
            p1, c1 = e.position(e.week, e.toe_s + dt)
            p2, c2 = ref.position(ref.week, ref.toe_s + dt)
            worst_pos = max(worst_pos, float(np.linalg.norm(p1 - p2)))
            worst_clock = max(worst_clock, abs(c1 - c2) * C)
    assert worst_pos < 1e-3 and worst_clock < 1e-3


def test_rawx_frames_decode_to_the_measurements() -> None:
    drive = make_drive("urban", seed=1)
    raw = RawObservations(GpsBroadcast(drive.gnss_sky.constellation, GnssTimeline(), 1), sky=drive.gnss_sky, seed=3)
    gps_ns = GnssTimeline().gps_ns(0) + 2 * NS_PER_S
    epoch = raw.measure(gps_ns, drive.state(2.0))
    frame = rxm_rawx(epoch)
    assert frame[:4] == b"\xb5\x62\x02\x15" and int.from_bytes(frame[4:6], "little") == 16 + 32 * 7
    msg = UBXReader.parse(frame, validate=True)  # the checksum holds
    assert msg.identity == "RXM-RAWX"
    week, tow_ns = GnssTimeline.week_tow(gps_ns)
    assert (msg.rcvTow, msg.week, msg.leapS, msg.numMeas, msg.leapSec) == (tow_ns / NS_PER_S, week, 18, 7, 1)
    assert frame[6 + 13] == 1  # version
    for i, m in enumerate(epoch.measurements, start=1):
        assert getattr(msg, f"prMes_{i:02d}") == m.pseudorange_m
        assert getattr(msg, f"cpMes_{i:02d}") == m.carrier_cycles
        assert getattr(msg, f"doMes_{i:02d}") == pytest.approx(m.doppler_hz, abs=1e-3)  # R4
        block = frame[6 + 16 + 32 * (i - 1):6 + 16 + 32 * i]
        assert (block[20], block[21], block[22], block[23]) == (0, m.prn, 0, 0)  # GPS, L1 C/A
        assert getattr(msg, f"svId_{i:02d}") == m.prn
        assert getattr(msg, f"locktime_{i:02d}") == m.locktime_ms == 0  # the first epoch of every lock
        assert (getattr(msg, f"prValid_{i:02d}"), getattr(msg, f"cpValid_{i:02d}")) == (1, 1)
        assert getattr(msg, f"halfCyc_{i:02d}") == int(m.half_cycle_valid) == 0
        assert 36 <= getattr(msg, f"cno_{i:02d}") <= 48
        assert 1 <= getattr(msg, f"cpStd_{i:02d}") <= 5  # 0.004 cycles a step: RTKLIB takes the phase up to 5
        assert 0.01 * 2 ** getattr(msg, f"prStd_{i:02d}") >= m.pr_std_m
        assert 20e6 < m.pseudorange_m - C * epoch.clock_bias_s < 26e6


def test_pseudorange_and_carrier_are_range_clocks_and_atmosphere() -> None:
    """Against RTKLIB's way of modelling them, written out here from the simulated sky's own positions: the
    satellite at the transmission time the pseudorange gives, the Sagnac term, both clocks, Saastamoinen and
    Klobuchar. The carrier is the same range with the ionosphere advanced, plus a whole number of cycles."""
    timeline = GnssTimeline()
    sky = Constellation(epoch_s=5000.0)
    b = GpsBroadcast(sky, timeline, seed=4)
    car = StraightTrajectory(speed_mps=20.0, heading_deg=30.0, lat_deg=37.5, lon_deg=127.0, height_m=80.0)
    raw = quiet(b, seed=5, clock=ReceiverClock(offset_s=3e-4, rate=2e-7))
    for k in (0, 1, 7):  # the half cycle has settled by 7 s
        gps_ns = timeline.gps_ns(0) + k * NS_PER_S
        truth = car.state(k)
        epoch = raw.measure(gps_ns, truth)
        assert len(epoch.measurements) >= 6
        dtr = epoch.clock_bias_s
        assert dtr == pytest.approx(3e-4 + 2e-7 * k, abs=1e-12)
        # the antenna where it was when the receiver's clock read the epoch
        rr = earth.ecef(truth.lat_rad, truth.lon_rad, truth.height_m) - earth.dcm_ned_to_ecef(
            truth.lat_rad, truth.lon_rad) @ truth.vel_ned_mps * dtr
        assert np.linalg.norm(rr - epoch.receiver_ecef_m) < 1e-6
        tow_rcv = GnssTimeline.week_tow(gps_ns)[1] / NS_PER_S
        for m in epoch.measurements:
            eph = b.current(m.prn, gps_ns)
            tc = tow_rcv - m.pseudorange_m / C - eph.toc_s  # transmission by the satellite's clock, from toc
            for _ in range(2):
                tc -= eph.af0 + eph.af1 * tc
            dts = eph.af0 + eph.af1 * tc
            rs = sky.ecef(k - m.pseudorange_m / C - dts)[b.index[m.prn]]  # the sky at the true transmission
            rho = float(np.linalg.norm(rs - rr)) + OMGE * (rs[0] * rr[1] - rs[1] * rr[0]) / C
            d = earth.dcm_ned_to_ecef(truth.lat_rad, truth.lon_rad).T @ (rs - rr)
            az, el = math.atan2(d[1], d[0]), math.atan2(-d[2], math.hypot(d[0], d[1]))
            trop = saastamoinen_m(truth.lat_rad, truth.height_m, el)
            iono = klobuchar_m(truth.lat_rad, truth.lon_rad, az, el, GnssTimeline.week_tow(gps_ns)[1] / NS_PER_S)
            assert 2.3 < trop < 15.0 and 1.0 < iono < 30.0
            expected = rho + C * (dtr - dts) + trop + iono
            assert m.pseudorange_m == pytest.approx(expected, abs=2e-3)
            cycles = m.carrier_cycles - (m.pseudorange_m - 2.0 * iono) / LAMBDA_L1
            offset = 0.5 if (not m.half_cycle_valid and abs(cycles - round(cycles)) > 0.25) else 0.0
            assert abs(cycles - offset - round(cycles - offset)) < 1e-4
            if k == 7:
                assert m.half_cycle_valid and offset == 0.0


def test_doppler_is_the_carrier_phase_rate() -> None:
    timeline = GnssTimeline()
    b = GpsBroadcast(Constellation(epoch_s=100.0), timeline, seed=6)
    car = StraightTrajectory(speed_mps=25.0, heading_deg=100.0)
    raw = quiet(b, seed=7)
    epochs = [raw.measure(timeline.gps_ns(0) + k * NS_PER_S, car.state(k)) for k in range(8, 11)]
    for i in range(2):
        a, z = ({m.prn: m for m in e.measurements} for e in epochs[i:i + 2])
        for prn in a:
            # a carrier phase in cycles grows with the range; Doppler is positive for an approaching satellite
            phase_rate = z[prn].carrier_cycles - a[prn].carrier_cycles
            assert -phase_rate == pytest.approx(0.5 * (a[prn].doppler_hz + z[prn].doppler_hz), abs=0.01)
            assert 100.0 < abs(a[prn].doppler_hz) < 6000.0


def test_a_satellite_hidden_and_seen_again_is_a_new_lock() -> None:
    """Through a tunnel every lock is lost: after it each satellite has a new ambiguity, its locktime restarts, and
    its half cycle is unresolved until the subframe preamble (then subtracted where it was wrong: subHalfCyc)."""
    timeline = GnssTimeline()
    sky = SkyGeometry(epoch_s=20_000.0)
    b = GpsBroadcast(sky.constellation, timeline, seed=8)
    raw = quiet(b, sky=sky, seed=9, clock=ReceiverClock(offset_s=1e-4, rate=0.0))

    def at(k: int, sky_open: float) -> dict[int, tuple[int, bool, bool, float]]:
        """PRN -> locktime, half cycle valid, subtracted, and carrier minus pseudorange in cycles."""
        state = ParkedTrajectory(extras={"sky_open": sky_open}).state(float(k))
        e = raw.measure(timeline.gps_ns(0) + k * NS_PER_S, state)
        return {m.prn: (m.locktime_ms, m.half_cycle_valid, m.half_cycle_subtracted,
                        m.carrier_cycles - m.pseudorange_m / LAMBDA_L1) for m in e.measurements}

    before = [at(k, 1.0) for k in range(10)]
    assert len(before[0]) >= 6
    assert [before[k][p][0] for p in before[0] for k in (0, 9)] == [0, 9000] * len(before[0])
    assert all(before[9][p][1] for p in before[0])  # resolved within 6 s
    for p in before[0]:  # where it had been wrong the half cycle comes off, once, when it is resolved
        k = next(k for k in range(10) if before[k][p][1])
        # the step of (carrier - pseudorange) less the next one: the ionosphere's slow drift taken out
        jump = (before[k][p][3] - before[k - 1][p][3]) - (before[k + 1][p][3] - before[k][p][3])
        assert jump == pytest.approx(-0.5 if before[k][p][2] else 0.0, abs=1e-3)
        assert all(before[j][p][2] == before[k][p][2] for j in range(k, 10))
    assert any(before[9][p][2] for p in before[0]) and not all(before[9][p][2] for p in before[0])
    assert at(10, 0.0) == {}  # the tunnel
    after = at(11, 1.0)
    assert set(after) == set(before[0])
    for p, (lock, half, sub, amb) in after.items():
        assert lock == 0 and not half and not sub
        assert abs(amb - before[9][p][3]) > 0.9  # another integer (a new draw of +-500 cycles)


def test_the_receiver_clock_steps_by_a_millisecond_and_says_so() -> None:
    clock = ReceiverClock(offset_s=4.9e-4, rate=1e-6)
    assert clock.bias(0.0) == (pytest.approx(4.9e-4), False)
    bias, stepped = clock.bias(20.0)  # 5.1e-4 s: past half a millisecond
    assert stepped and bias == pytest.approx(5.1e-4 - 1e-3)
    assert clock.bias(21.0)[1] is False
    timeline = GnssTimeline()
    b = GpsBroadcast(Constellation(), timeline)
    raw = quiet(b, clock=ReceiverClock(offset_s=4.9e-4, rate=1e-6))
    here = ParkedTrajectory()
    p0 = raw.measure(timeline.gps_ns(0), here.state(0.0))
    p1 = raw.measure(timeline.gps_ns(20 * NS_PER_S), here.state(20.0))
    assert not p0.clock_reset and p1.clock_reset
    assert UBXReader.parse(rxm_rawx(p1)).clkReset == 1
    # pseudoranges step with the clock: c * 1 ms shorter, the geometry's change aside
    m0, m1 = p0.measurements[0], p1.measurements[0]
    assert m0.prn == m1.prn and m1.pseudorange_m - m0.pseudorange_m == pytest.approx(-C * 1e-3, abs=2e4)


def test_the_simulated_receiver_sends_them_once_raw_observations_are_on() -> None:
    """The receiver model's raw_frames hook (the one sensors/sim/vehicle.py plugs in) over a real pty."""
    bench = Bench()
    try:
        m0 = bench.receiver(model="NEO-M8T", seed=3)  # to learn its timeline
        raw = RawObservations(GpsBroadcast(Constellation(epoch_s=777.0), m0.timeline, 1), seed=2)
        m0.raw_frames = raw.for_epoch
        ser = bench.host(m0.baud)
        result = configure_receiver(ser, ReceiverSetup(raw_observations=True), sleep=bench.sleep)
        assert result.raw_observations == "on"
        framer = bench.listen(ser, 3.0)
        assert identities(framer).count("RXM-RAWX") == 3
        ubx = [f.message for f in framer.frames if f.kind == "UBX"]  # type: ignore[attr-defined]
        rawx = [f for f in ubx if f.identity == "RXM-RAWX"]
        pvt = [f for f in ubx if f.identity == "NAV-PVT"]
        assert [round(f.rcvTow * 1000) for f in rawx] == [f.iTOW for f in pvt][:3]
        assert all(f.numMeas >= 5 for f in rawx)
    finally:
        bench.close()


# ---- RTKLIB end to end ------------------------------------------------------------------------------------
DRIVE_S = 150.0  # urban seed 1: open sky to 37 s, a street canyon (3 GPS satellites) to 116 s, open again


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory) -> dict:
    if sim_raw.rtklib_missing():
        pytest.skip("convbin/rnx2rtkp is not installed (apt-get install rtklib)")
    out = tmp_path_factory.mktemp("raw")
    drive = make_drive("urban", seed=1, duration_s=DRIVE_S)
    timeline = GnssTimeline()
    files = record_raw_drive(drive, drive.gnss_sky, out, duration_s=DRIVE_S, timeline=timeline, seed=1)
    rover_obs, base_obs = sim_raw.convbin(files.rover_ubx), sim_raw.convbin(files.base_ubx)
    single = sim_raw.score(sim_raw.rnx2rtkp(files, rover_obs, None, out / "single.pos"), drive, timeline)
    kinematic = sim_raw.score(sim_raw.rnx2rtkp(files, rover_obs, base_obs, out / "kinematic.pos"), drive, timeline)
    return {"files": files, "rover_obs": rover_obs, "base_obs": base_obs, "single": single, "kinematic": kinematic}


@needs_rtklib
def test_convbin_reads_every_rawx_epoch(processed: dict) -> None:
    files = processed["files"]
    frames = [msg for _, msg in UBXReader(io.BytesIO(files.rover_ubx.read_bytes()), validate=True)]
    assert len(frames) == files.epochs == 151 and all(f.identity == "RXM-RAWX" for f in frames)
    with_meas = [f for f in frames if f.numMeas > 0]
    assert sim_raw.rinex_epochs(processed["rover_obs"]) == len(with_meas) == files.rover_epochs_with_measurements
    assert sim_raw.rinex_epochs(processed["base_obs"]) == files.epochs
    body = processed["rover_obs"].read_text().split("END OF HEADER")[1].splitlines()
    first = {line[:3]: line for line in body[2:2 + frames[0].numMeas]}
    for i in range(1, frames[0].numMeas + 1):
        line = first[f"G{getattr(frames[0], f'svId_{i:02d}'):02d}"]
        assert float(line[3:17]) == pytest.approx(getattr(frames[0], f"prMes_{i:02d}"), abs=1e-3)
        assert float(line[19:33]) == pytest.approx(getattr(frames[0], f"cpMes_{i:02d}"), abs=1e-3)
        assert line[33] == "3"  # LLI: a new lock (slip) with its half cycle unresolved


@needs_rtklib
def test_rnx2rtkp_single_point_is_within_metres_under_an_open_sky(processed: dict) -> None:
    open_sky = [e for e in processed["single"] if e.sky_open >= 1.0]
    assert len(open_sky) >= 70  # every open-sky epoch solved (37 s before the canyon, 35 after)
    h = [e.horizontal_m for e in open_sky]
    assert math.sqrt(statistics.fmean(x * x for x in h)) < 1.0 and max(h) < 2.5
    assert max(abs(e.enu_m[2]) for e in open_sky) < 3.0


@needs_rtklib
def test_rnx2rtkp_kinematic_fixes_to_centimetres_against_the_base(processed: dict) -> None:
    kin = processed["kinematic"]
    open_sky = [e for e in kin if e.sky_open >= 1.0]
    fixed = [e for e in open_sky if e.row.quality == 1]
    assert len(fixed) >= 0.8 * len(open_sky)
    h = sorted(e.horizontal_m for e in fixed)
    assert statistics.median(h) < 0.015
    assert sum(x < 0.05 for x in h) >= 0.95 * len(h)
    # After the canyon: the satellites that came back are new locks, and the solution fixes again.
    later = [e for e in fixed if e.row.gps_ns >= processed["files"].first_gps_ns + 126 * NS_PER_S]
    assert len(later) >= 20 and max(e.horizontal_m for e in later) < 0.05
