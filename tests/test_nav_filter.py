"""The filter on synthetic drives: outages, scale factor, gating, resets, mounting, lever arm, smoother, modes.

Each drive is a scenario's truth sampled with simple errors chosen here (tests/test_nav_synth.py), not the
simulator's device models, so these also check that the filter holds on data the simulator did not make.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
import pytest
from test_nav_synth import NS, T0_NS, SynthErrors, records

from logger.nav import earth
from logger.nav.engine import NavEngine
from logger.nav.health import noise_verdict
from logger.nav.params import NavParams
from logger.nav.rotations import dcm_from_euler
from logger.nav.smoother import smooth_rows
from logger.recording.records import feed_record, gnss_observation, nav_feeder, nav_state_record
from sensors.sim.scenarios import INTRO_S, make_drive

# A phone-grade IMU on the synthetic drives: ten times the MPU-6050's noise densities, over its 100 Hz band.
PHONE_HZ = 100.0
PHONE_NOISE = SynthErrors(accel_noise=4000e-6 * 9.80665 * math.sqrt(PHONE_HZ / 2.0),
                          gyro_noise=math.radians(0.05) * math.sqrt(PHONE_HZ / 2.0))


def run(recs, **params) -> NavEngine:
    engine = NavEngine(NavParams(**params), record=True)
    feed = nav_feeder(engine)
    for _, topic, msg in recs:
        feed_record(feed, topic, msg)
    return engine


def errors(drive, rows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (s), NED errors and sigmas of trajectory rows against the drive's truth."""
    t, err, sig = [], [], []
    for row in rows:
        ts = (row[0] - T0_NS) / 1e9
        s = drive.state(ts)
        t.append(ts)
        err.append(earth.ned_offset_m(s.lat_rad, s.lon_rad, s.height_m, row[2], row[3], row[4]))
        sig.append(row[9])
    return np.array(t), np.array(err), np.array(sig)


@pytest.fixture(scope="module")
def outage():
    drive = make_drive("outage-60s", seed=1, duration_s=270.0)
    (span,) = drive.spans_of("outage")
    recs = records(drive, 270.0, seed=2, gnss_off=[(span.start_s, span.end_s)],
                   errors=SynthErrors(obd_factor=1.02))
    return drive, span, recs


def test_a_minute_without_gnss_is_bridged_by_obd_and_baro_and_not_by_the_imu_alone(outage):
    drive, span, recs = outage
    full, base = run(recs), run(recs, mode="15")
    for engine in (full, base):
        assert engine.counters.init_method == "gnss course" and engine.counters.resets == 0
    t, e17, _ = errors(drive, full.rows)
    _, e15, _ = errors(drive, base.rows)
    inside = (t >= span.start_s) & (t <= span.end_s)
    h17 = np.hypot(e17[inside, 0], e17[inside, 1]).max()
    h15 = np.hypot(e15[inside, 0], e15[inside, 1]).max()
    assert h17 < 5.0
    assert h15 > 3.0 * h17
    assert np.abs(e17[inside, 2]).max() < 2.0  # the barometer holds the height
    assert {"gnss_pos", "gnss_vel", "obd", "baro"} <= set(full.ekf.stats)
    assert set(base.ekf.stats) == {"gnss_pos", "gnss_vel"}  # the baseline knows nothing of OBD or baro


@pytest.mark.parametrize("seed", [2, 3])
def test_a_cruises_rounding_learnt_before_an_outage_carries_through_it(seed):
    """OBD speed comes in whole km/h, so a cruise's every reading carries one rounding error: here 55.45 km/h is
    read as 55 (the true speed 0.12 m/s faster than the reading says, scale apart: 7.3 m over the minute). The
    rounding is a state of the run of equal readings (RQ_ID, ``obd_rounding_state``): the fixes before the outage
    teach it, and the dead reckoning through the outage goes at the true speed. The paper's model (the readings'
    rounding as their noise, repeats weighing less) goes at the reading's speed: 3.3 / 2.0 m on these seeds."""
    from logger.nav.state import RQ_ID, SF_ID

    factor = 1.0269
    drive = make_drive("outage-60s", seed=1, duration_s=200.0)
    (span,) = drive.spans_of("outage")
    kmh = drive.state(span.start_s).forward_speed_mps * 3.6 * factor  # what the ECU would send unrounded
    rounding = (kmh - round(kmh)) / 3.6  # true = (1 + s) (reading + rounding), 1 + s = 1 / factor
    assert abs(rounding) > 0.1 and drive.state(span.end_s).forward_speed_mps * 3.6 * factor == pytest.approx(kmh)
    recs = records(drive, 200.0, seed=seed, gnss_off=[(span.start_s, span.end_s)],
                   errors=SynthErrors(obd_factor=factor))
    engine = NavEngine(NavParams(obd_rounding_state=True), record=True)
    feed = nav_feeder(engine)
    speed = None  # what the filter takes the reading to mean when the outage begins: (1 + s) (reading + rounding)
    reading = 0.0
    for ts, topic, msg in recs:
        if speed is None and (ts - T0_NS) / NS >= span.start_s:
            st, p = engine.state, engine.ekf.p
            j = np.array((reading + st.rq, 1.0 + st.sf))  # the speed's derivatives in the scale and the rounding
            cov = p[np.ix_((SF_ID, RQ_ID), (SF_ID, RQ_ID))]
            speed = ((1.0 + st.sf) * (reading + st.rq), math.sqrt(float(j @ cov @ j)), reading)
        if topic == "/obd/speed":
            reading = msg["speed_kmh"] / 3.6
        feed_record(feed, topic, msg)
    true = drive.state(span.start_s).forward_speed_mps
    assert speed is not None and speed[2] == round(kmh) / 3.6
    assert abs(speed[0] - true) < 0.03 and speed[1] < 0.03  # the rounding's 0.12 m/s learnt to a few cm/s
    bound = 0.2 * abs(rounding) * (span.end_s - span.start_s)
    t, e, _ = errors(drive, engine.rows)
    inside = (t >= span.start_s) & (t <= span.end_s)
    assert np.hypot(e[inside, 0], e[inside, 1]).max() < bound
    t, e, _ = errors(drive, run(recs).rows)
    inside = (t >= span.start_s) & (t <= span.end_s)
    assert np.hypot(e[inside, 0], e[inside, 1]).max() > bound


def test_each_new_speed_reading_starts_a_new_rounding(outage):
    """A reading unlike the last begins a run whose rounding owes nothing to the last one's: the covariance step
    there forgets the state (its row in the transition zero, its variance a step's uniform spread), and the smoother's
    epoch holds the same transition."""
    from logger.nav.measurements import ROUNDING_VAR
    from logger.nav.state import RQ_ID

    _, _, recs = outage
    engine = run(recs, obd_rounding_state=True)
    readings = [m["speed_kmh"] for ts, topic, m in recs
                if topic == "/obd/speed" and ts >= (engine.counters.initialised_ns or 0)]
    changes = sum(1 for a, b in itertools.pairwise(readings) if a != b)
    resets = [ep for ep in engine.epochs if ep.phi is not None and ep.phi[RQ_ID, RQ_ID] == 0.0]
    assert changes > 10 and abs(len(resets) - changes) <= 1
    for ep in resets:
        assert ep.p_minus[RQ_ID, RQ_ID] == pytest.approx(ROUNDING_VAR)
        assert not np.any(np.delete(ep.p_minus[RQ_ID], RQ_ID)) and not np.any(np.delete(ep.phi[RQ_ID], RQ_ID))


@pytest.mark.parametrize("mode", ["15", "17"])
def test_a_fast_imus_wider_bandwidth_still_reads_as_standing(mode, monkeypatch):
    """At 200 Hz the MPU-6050 runs its 94 Hz low-pass (the widest under half the rate: sensors/mpu6050.py), so each
    sample carries the 400 ug/sqrt(Hz) noise over ~100 Hz, 0.039 m/s^2 per axis: a standing car's samples vary by
    0.0046 (m/s^2)^2, over the stop detector's 0.0025. It looks at 20 Hz means of them (stops.MEAN_S), so the
    start levels, and the 15-state filter, which has no OBD speed to learn the threshold from, does not lose itself.
    Read sample by sample, it never levelled (the check below)."""
    from logger.nav import stops

    rate = 200.0
    noise = SynthErrors(accel_noise=400e-6 * 9.80665 * math.sqrt(rate / 2.0),
                        gyro_noise=math.radians(0.005) * math.sqrt(rate / 2.0))
    drive = make_drive("outage-60s", seed=1, duration_s=60.0)
    recs = records(drive, 60.0, seed=3, imu_hz=rate, errors=noise)
    engine = run(recs, mode=mode)
    assert engine.startup.levelled is not None and engine.counters.init_method == "gnss course"
    assert engine.counters.resets == 0 and engine.stops.group == 10
    _, e, _ = errors(drive, engine.rows)
    assert np.hypot(e[:, 0], e[:, 1]).max() < 2.0
    monkeypatch.setattr(stops, "MEAN_S", 0.0)  # each sample on its own, as before
    monkeypatch.setattr(stops, "HELD_NS", 10**15)  # and no held stop to teach it otherwise
    assert run(recs, mode=mode).startup.levelled is None


def test_a_phone_grade_imu_is_taught_its_standstill_by_a_stop_the_obd_speed_holds(monkeypatch):
    """A phone-grade IMU (ten times the MPU-6050's noise densities, 100 Hz) never reads still by the configured
    thresholds: its standing car's 20 Hz means vary by ~0.05 (m/s^2)^2, five times the most a learnt threshold could
    reach, and only a stop it reads still in teaches it. So it never levelled and never took a zero-velocity update.
    A stop the OBD speed holds at zero for stops.HELD_S teaches it all the same: it levels and stops (the fixes'
    speed, which could hold the stop too, left out here)."""
    from logger.nav import engine as engine_module
    from logger.nav import policies, stops

    monkeypatch.setattr(engine_module, "GNSS_STANDING_MPS", 0.0)

    drive = make_drive("urban", seed=1, duration_s=150.0)  # parked at the start, stands again from 131 s
    recs = records(drive, 150.0, seed=3, imu_hz=PHONE_HZ, errors=PHONE_NOISE)
    rate_sigmas = []

    class Seen(policies.ZeroMotion):
        def __init__(self, gyro_mean, sigma_v, sigma_w) -> None:
            super().__init__(gyro_mean, sigma_v, sigma_w)
            rate_sigmas.append(sigma_w)

    monkeypatch.setattr(policies, "ZeroMotion", Seen)
    engine = run(recs)
    assert engine.stops.held_learned >= 1 and engine.stops.thr_a > 4 * 0.05**2
    assert engine.startup.levelled is not None and engine.counters.zupt > 0 and engine.counters.resets == 0
    # Its zero-rate updates know the gyro's noise as the drive measured it (five times the datasheet's here),
    # not as configured: the stop's mean rate is no surer than the chip's noise makes it.
    assert engine.noise.gyro_arw > 3.0 * engine.params.gyro_arw
    assert max(rate_sigmas) * math.sqrt(0.5) > engine.params.gyro_arw * 3.0
    # `logger status` says so (on the logger's own board a chip that noisy shakes).
    verdict = noise_verdict(engine)
    assert verdict is not None and "the configured noise" in verdict and verdict.endswith("stops told by speed")
    state = nav_state_record(engine, engine.t_last_ns or 0, 0)  # and /nav/state, for the office
    assert min(state["imu_noise_x"]) > 3.0 and state["held_stops"] == engine.stops.held_learned >= 1
    monkeypatch.setattr(stops, "HELD_NS", 10**15)  # only stops it reads still in teach it, as before
    before = run(recs)
    assert before.startup.levelled is None and before.counters.zupt == 0 and before.stops.learned == 0


def test_a_held_stop_teaches_only_an_imu_that_never_read_still_in_it():
    """The rule of a held stop (stops.HeldStop): readings that say the car stands for HELD_S with the IMU never
    still at any of them. A car that stood still by the IMU and pulls away while the reading still says it stands
    (the IMU unstill at the stop's last reading) teaches nothing: on the simulated urban drives that moment would
    have taught the detector the pull-away."""
    from logger.nav.stops import HELD_NS, HeldStop

    held = HeldStop()
    step = NS // 2
    said = [held.holds(k * step, False) for k in range(10)]  # standing from t = 0, the IMU never still
    assert said == [k * step >= HELD_NS for k in range(10)]
    held.end()  # moving: a new stop starts afresh
    # Still at its second reading, unstill from the seventh on (pulling away): never held.
    assert not any(held.holds(k * step, k == 12) for k in range(11, 21))


def test_a_datasheet_grade_chip_shaken_at_a_stop_is_not_taught_the_shaking(monkeypatch):
    """People getting into a standing car shake it for the whole of the first seconds (here 0.3 m/s^2 at 1 Hz): the
    IMU never reads still while the OBD speed says zero. Such a stop teaches only a chip the noise monitor measures
    noisier than its grade (white noise, which a slow shake is not): a datasheet-grade one waits for a stop it
    reads still in, and its thresholds stay where they were."""
    from logger.nav.engine import NavEngine as Engine

    drive = make_drive("urban", seed=1, duration_s=40.0)

    def shaken(m: dict) -> dict:
        t = (m["t_sync_ns"] - T0_NS) / NS
        if t >= 7.5:
            return m
        a = list(m["accel_mps2"])
        a[2] += 0.3 * math.sin(2.0 * math.pi * t)
        a[0] += 0.2 * math.sin(2.0 * math.pi * 0.7 * t)
        return {**m, "accel_mps2": a}

    recs = [(ts, tp, shaken(m) if tp == "/imu" else m) for ts, tp, m in records(drive, 40.0, seed=3)]
    engine = run(recs)
    assert engine.stops.held_learned == 0 and engine.stops.thr_a == pytest.approx(0.05**2)
    assert noise_verdict(engine) is None  # a datasheet-grade chip: no word of its noise in `logger status`
    state = nav_state_record(engine, engine.t_last_ns or 0, 0)
    assert max(state["imu_noise_x"]) < 1.0 and state["held_stops"] == 0  # it measures under its datasheet's density
    monkeypatch.setattr(Engine, "_noisy_chip", lambda self: True)  # any chip taught by a held stop
    assert run(recs).stops.held_learned >= 1


@pytest.mark.parametrize("mode", ["15", "17"])
def test_fixes_that_say_the_car_stands_teach_a_phone_grade_imu_without_an_obd_speed(mode, monkeypatch):
    """No OBD adapter (or the GNSS + IMU mode, which reads none): fixes whose speed stays under
    stops.GNSS_STANDING_MPS for HELD_S hold the stop instead, so the phone-grade IMU levels at the start. Before,
    the 15-state mode never levelled it, and replay's boresight pass (that mode) read side slips of tens of degrees
    on a phone in a holder."""
    from logger.nav import stops

    drive = make_drive("urban", seed=1, duration_s=60.0)
    recs = [r for r in records(drive, 60.0, seed=3, imu_hz=PHONE_HZ, errors=PHONE_NOISE) if r[1] != "/obd/speed"]
    engine = run(recs, mode=mode)
    assert engine.stops.held_learned >= 1 and engine.startup.levelled is not None
    assert engine.counters.resets == 0 and engine.counters.init_method == "gnss course"
    monkeypatch.setattr(stops, "HELD_NS", 10**15)  # no held stop: as before
    assert run(recs, mode=mode).startup.levelled is None


def test_smoothing_shrinks_the_outage_error(outage):
    drive, span, recs = outage
    # The synthetic fixes' errors are white: told so
    engine = run(recs, gnss_floor_corr_s=0.0, gnss_floor_corr_v_s=0.0, gnss_floor_corr_speed_s=0.0)
    engine.close_epochs()
    smoothed = smooth_rows(engine.rows, engine.epochs, engine.ekf.p)
    t, ef, sf = errors(drive, engine.rows)
    _, es, ss = errors(drive, smoothed)
    inside = (t >= span.start_s) & (t <= span.end_s)
    assert np.hypot(es[inside, 0], es[inside, 1]).max() < 0.5 * np.hypot(ef[inside, 0], ef[inside, 1]).max()
    assert np.all(ss[inside, 0] <= sf[inside, 0] + 1e-9)  # the smoother knows more, never less


def test_obd_scale_factor_is_learnt_before_a_tunnel():
    drive = make_drive("tunnel-130s", seed=1, duration_s=240.0)
    (tunnel,) = drive.spans_of("tunnel")
    recs = records(drive, tunnel.start_s, seed=3, errors=SynthErrors(obd_factor=1.03))
    engine = run(recs)
    reads_high = 1.0 / (1.0 + engine.state.sf) - 1.0
    assert reads_high == pytest.approx(0.03, abs=0.005)
    assert engine.ekf.sigma(15) < 0.005


def test_a_multipath_jump_is_refused_counted_and_harmless():
    drive = make_drive("outage-60s", seed=2, duration_s=140.0)

    def jump(m: dict) -> dict:  # 40 m north for five epochs, the reported accuracy unchanged
        return {**m, "latitude": m["latitude"] + 40.0 / 111_000}

    recs = [(ts, tp, jump(m) if tp == "/gnss/fix" and 100 <= (m["gnss_time_ns"] - T0_NS) / 1e9 < 105 else m)
            for ts, tp, m in records(drive, 140.0, seed=4)]
    engine = run(recs)
    assert engine.ekf.stats["gnss_pos"].rejected == 5
    t, e, _ = errors(drive, engine.rows)
    after = t > 100
    assert np.hypot(e[after, 0], e[after, 1]).max() < 2.0


def fed_with_upset(recs, at_s: float, upset, **params) -> tuple[NavEngine, bool]:
    """The records through a filter, with ``upset(engine)`` applied once, ``at_s`` into the drive."""
    engine = NavEngine(NavParams(**params), record=True)
    done = False
    feed = nav_feeder(engine)
    for _, topic, msg in recs:
        feed_record(feed, topic, msg)
        if not done and engine.state is not None and (msg["t_sync_ns"] - T0_NS) / 1e9 > at_s:
            upset(engine)
            done = True
    return engine, done


def upset_at_90_s(duration_s: float, records_seed: int, upset) -> tuple[Any, NavEngine, bool]:
    """The outage-60s drive (seed 3) through the default filter, with ``upset(engine)`` applied once, 90 s in."""
    drive = make_drive("outage-60s", seed=3, duration_s=duration_s)
    return drive, *fed_with_upset(records(drive, duration_s, seed=records_seed), 90.0, upset)


def test_a_lost_filter_restarts_from_gnss_and_says_so():
    def teleport(engine: NavEngine) -> None:
        engine.state.lat += 300.0 / 6.36e6  # 300 m off, with the covariance still confident

    drive, engine, teleported = upset_at_90_s(160.0, 5, teleport)
    assert teleported and engine.counters.resets == 1 and engine.counters.reanchors == 0
    _, e, _ = errors(drive, engine.rows)
    assert np.hypot(e[-1, 0], e[-1, 1]) < 2.0


def test_a_restart_from_a_2d_fix_keeps_the_height_the_filter_held():
    """A 2D fix's height is a stand-in (the last 3D fix's, its sigma widened by the climb since): a restart from it
    takes its position and velocity, and its height only where the filter claims its own height less well."""
    import dataclasses

    from logger.nav.state import P_ID

    seen: dict[str, Any] = {}

    def restart_2d(engine: NavEngine) -> None:
        fix = engine.last_readings.fix
        h0, var0 = engine.state.h, float(engine.ekf.p[P_ID + 2, P_ID + 2])
        stand_in = dataclasses.replace(fix, fix_3d=False, h=fix.h + 30.0, sigma=(fix.sigma[0], fix.sigma[1], 40.0))
        engine._restart_from(stand_in)
        seen["kept"] = (engine.state.h - h0, float(engine.ekf.p[P_ID + 2, P_ID + 2]), var0)
        engine._restart_from(dataclasses.replace(stand_in, sigma=(fix.sigma[0], fix.sigma[1], 1e-3)))
        seen["taken"] = (engine.state.h - h0, float(engine.ekf.p[P_ID + 2, P_ID + 2]))

    _, engine, done = upset_at_90_s(100.0, 5, restart_2d)
    assert done and engine.counters.resets == 2
    dh, var, var0 = seen["kept"]
    assert abs(dh) < 0.05 and var == pytest.approx(var0) and var0 < 40.0**2
    dh, var = seen["taken"]  # a stand-in surer than the filter (a 3D fix a moment ago, on level road): taken
    assert abs(dh - 30.0) < 1.0 and var == pytest.approx(1e-6)


def test_mounting_rotation_from_the_configuration():
    drive = make_drive("outage-60s", seed=4, duration_s=150.0)
    recs = records(drive, 150.0, seed=6)
    # The chip lies turned 90 deg about the vertical and 180 deg about x (face up): chip = R^T vehicle.
    rpy = (180.0, 0.0, 90.0)
    r = dcm_from_euler(*(math.radians(a) for a in rpy))
    turned = [(ts, tp, {**m, "accel_mps2": (r.T @ np.array(m["accel_mps2"])).tolist(),
                        "gyro_rps": (r.T @ np.array(m["gyro_rps"])).tolist()}) if tp == "/imu" else (ts, tp, m)
              for ts, tp, m in recs]
    # The mounting as configured, the alignment off (tests/test_nav_mounting.py has the estimated one).
    straight, mounted = run(recs), run(turned, mounting_rpy_deg=rpy, mount_align=False)
    _, e1, _ = errors(drive, straight.rows)
    _, e2, _ = errors(drive, mounted.rows)
    assert np.sqrt(np.mean(e2**2)) == pytest.approx(np.sqrt(np.mean(e1**2)), rel=0.05, abs=0.02)
    from logger.nav.health import mounting_verdict

    assert mounting_verdict(mounted).startswith("IMU mounting plausible")
    wrong = run(turned, mount_align=False)  # the same data with the mounting left out of the configuration
    assert wrong.state is None or mounting_verdict(wrong).startswith("IMU mounting implausible")


def test_the_offsets_verdict_says_beyond_or_within_only_as_far_as_the_filter_knows():
    """A chip whose accelerometer y offset (65 mg) is beyond the datasheet's 50: said once the filter knows it to a
    few mg; while its sigma is tens of mg, neither "within" nor "beyond" (it said "within" on nothing before)."""
    from logger.nav.health import offsets_verdict
    from logger.nav.state import BA_ID

    drive = make_drive("urban", seed=2, duration_s=200.0)
    engine = run(records(drive, 200.0, seed=4, errors=SynthErrors(accel_bias=(0.0, -0.065 * 9.80665, 0.0))))
    sigma_y = engine.ekf.sigma(BA_ID + 1) / 9.80665 * 1e3
    assert sigma_y < 7.0 and abs(abs(engine.state.ba[1]) / 9.80665 * 1e3 - 65.0) < 3 * sigma_y
    assert offsets_verdict(engine).startswith("IMU offsets beyond the datasheet: accelerometer y offset")
    engine.ekf.p[BA_ID + 1, BA_ID + 1] = (0.05 * 9.80665) ** 2  # as unsure as a minute after the start
    assert offsets_verdict(engine).startswith("IMU offsets not yet known against the datasheet (accelerometer y)")
    engine.state.ba = (engine.state.ba[0], 0.0, engine.state.ba[2])
    assert offsets_verdict(engine).startswith("IMU offsets not yet known")  # 0 +- 50 mg: no verdict either
    engine.ekf.p[BA_ID + 1, BA_ID + 1] = (0.005 * 9.80665) ** 2
    assert offsets_verdict(engine).startswith("IMU offsets within the datasheet")
    engine.state.ba = (engine.state.ba[0], float("nan"), engine.state.ba[2])
    assert offsets_verdict(engine).startswith("IMU offsets not yet known")  # not "within" on a NaN

    # The tolerances are the chip's: a board rolled 90 deg carries the chip's y (50 mg) on the vehicle's z (80).
    rolled = dcm_from_euler(math.radians(90.0), 0.0, 0.0)  # vehicle from chip
    ba_chip = np.array([0.0, -0.065 * 9.80665, 0.0])
    engine._mount_m = rolled
    engine.state.ba = tuple((rolled @ ba_chip).tolist())
    p = engine.ekf.p
    p[BA_ID:BA_ID + 3, BA_ID:BA_ID + 3] = np.eye(3) * (0.003 * 9.80665) ** 2
    assert abs(engine.state.ba[2]) / 9.80665 * 1e3 == pytest.approx(65.0)  # on the vehicle's z: under z's 80
    assert offsets_verdict(engine).startswith("IMU offsets beyond the datasheet: accelerometer y offset 65 mg")


def test_antenna_lever_arm_from_the_configuration():
    drive = make_drive("outage-60s", seed=5, duration_s=150.0)
    arm = np.array([1.5, 0.4, -1.3])  # antenna forward, right and above the IMU
    recs = records(drive, 150.0, seed=7, errors=SynthErrors(gnss_h_sigma=0.1, gnss_v_sigma=0.1))
    moved = []
    for ts, tp, m in recs:
        if tp == "/gnss/fix" and m["fix_ok"]:
            s = drive.state((m["gnss_time_ns"] - T0_NS) / 1e9)
            dn, de, dd = dcm_from_euler(*s.rpy_rad) @ arm
            lat, lon, h = earth.offset_llh(math.radians(m["latitude"]), math.radians(m["longitude"]), m["altitude"],
                                           dn, de, dd)
            m = {**m, "latitude": math.degrees(lat), "longitude": math.degrees(lon), "altitude": h}
        moved.append((ts, tp, m))
    with_arm, without = run(moved, lever_arm_m=tuple(arm)), run(moved)
    _, e1, _ = errors(drive, with_arm.rows)
    _, e2, _ = errors(drive, without.rows)
    assert np.sqrt(np.mean(np.sum(e1**2, axis=1))) < 0.4
    assert np.sqrt(np.mean(np.sum(e2**2, axis=1))) > 1.0


def test_heading_from_the_configuration_starts_at_standstill():
    drive = make_drive("outage-60s", seed=6, duration_s=60.0)
    recs = records(drive, 60.0, seed=8)
    heading = math.degrees(drive.state(0.0).rpy_rad[2])
    engine = run(recs, heading_source="config", initial_heading_deg=heading)
    assert engine.counters.init_method == "config heading"
    # Levelled over the idling, started as soon as the vehicle moves (OBD speed above 0.5 km/h).
    assert INTRO_S < (engine.counters.initialised_ns - T0_NS) / 1e9 < INTRO_S + 4.0
    assert abs(math.degrees(math.remainder(engine.state.rpy()[2] - drive.state(60.0).rpy_rad[2], 2 * math.pi))) < 1.0


def test_a_configured_heading_still_starts_the_filter_when_the_first_fix_comes_after_levelling() -> None:
    """No fix yet when the car moves off (a receiver still finding its first fix): the configured heading belongs
    to the moment levelling ended, the gyro carries it on, and the first fix starts the filter with it."""
    drive = make_drive("outage-60s", seed=6, duration_s=60.0)
    recs = records(drive, 60.0, seed=8, gnss_off=[(0.0, 20.0)])
    heading = math.degrees(drive.state(0.0).rpy_rad[2])
    engine = run(recs, heading_source="config", initial_heading_deg=heading)
    assert engine.counters.init_method == "config heading"
    assert 20.0 < (engine.counters.initialised_ns - T0_NS) / 1e9 < 22.0
    assert abs(math.degrees(math.remainder(engine.state.rpy()[2] - drive.state(60.0).rpy_rad[2], 2 * math.pi))) < 1.0


def test_standstill_calibration_leaves_the_gyro_offset_and_not_the_earths_rate():
    """The mean rate at standstill holds the gyro offset and the earth's rate. Its vertical part is taken out at
    levelling, its horizontal part (3 millidegrees/s here, 0.2 deg of tilt a minute) once the GNSS course gives
    the heading; the offset's uncertainty is then what averaging left, not the datasheet's spread."""
    drive = make_drive("outage-60s", seed=6, duration_s=45.0)
    e = SynthErrors(gyro_noise=0.0)
    engine = NavEngine(NavParams())
    feed = nav_feeder(engine)
    for _, topic, msg in records(drive, 45.0, seed=8, errors=e):
        feed_record(feed, topic, msg)
        if engine.state is not None:  # as the calibration left it, before any update
            break
    assert engine.counters.init_method == "gnss course"
    bg_err = np.degrees(np.array(engine.state.bg) - np.array(e.gyro_bias)) * 1000.0  # millidegrees/s
    horizontal = math.degrees(earth.OMEGA_IE * math.cos(engine.state.lat)) * 1000.0
    assert horizontal > 2.0 and np.all(np.abs(bg_err) < 0.1 * horizontal)
    sigma_bg = math.degrees(engine.ekf.sigma(12)) * 1000.0
    assert sigma_bg < 20.0  # the standstill's average, with the configured walk since: not 0.05 deg/s


def test_gnss_only_mode_passes_the_fixes_through(outage):
    recs = outage[2]
    engine = run(recs, mode="gnss")
    fixes = [m for _, tp, m in recs if tp == "/gnss/fix" and m["fix_ok"]]
    assert len(engine.rows) == len(fixes) and engine.ekf is None
    assert math.degrees(engine.rows[10][2]) == pytest.approx(fixes[10]["latitude"], abs=1e-12)


def test_imu_errors_twice_what_the_configuration_assumes_keep_the_filter_consistent(outage):
    drive, span, _ = outage
    p = NavParams()
    worse = SynthErrors(accel_noise=2 * SynthErrors.accel_noise, gyro_noise=2 * SynthErrors.gyro_noise,
                        obd_factor=1.02)
    noisy = records(drive, 270.0, seed=9, gnss_off=[(span.start_s, span.end_s)], errors=worse)
    engine = run(noisy, **{k: v for k, v in p.__dict__.items() if k != "extra"})
    assert engine.counters.resets == 0 and engine.ekf.repairs == 0
    _, e, s = errors(drive, engine.rows)
    assert np.mean(np.abs(e) <= 3.0 * s) > 0.9


def test_a_parked_car_without_speed_or_gnss_does_not_drift():
    """Engine off at the end of a drive: no OBD answer, and here no GNSS either. A quiet IMU and a solution that
    already stands keep the zero-velocity updates going."""
    drive = make_drive("outage-60s", seed=7)
    (parked,) = drive.spans_of("parked")
    recs = [(ts, tp, m) for ts, tp, m in records(drive, drive.duration_s, seed=10)
            if not ((ts - T0_NS) / 1e9 >= parked.start_s and tp in ("/obd/speed", "/gnss/fix"))]
    engine = run(recs)
    t, e, _ = errors(drive, engine.rows)
    at_park = np.argmin(np.abs(t - parked.start_s))
    drift = np.hypot(*(e[-1, :2] - e[at_park, :2]))
    assert drift < 0.3
    assert engine.counters.zupt > 30


def test_coning_and_sculling_switch_on_with_a_fast_imu():
    drive = make_drive("outage-60s", seed=8, duration_s=45.0)
    slow = run(records(drive, 45.0, seed=11, imu_hz=20.0))
    fast = run(records(drive, 45.0, seed=11, imu_hz=100.0))
    assert not slow.mech.coning and fast.mech.coning
    assert fast.state is not None and fast.counters.imu > 4000


def test_good_fixes_after_an_outage_that_all_disagree_the_same_way_widen_the_position(outage):
    """Out of a tunnel with the solution further off than its covariance admits, the first good fixes agree with
    each other and not with it: after three the position uncertainty is widened and they pull it back."""
    drive, span, recs = outage

    def east(engine: NavEngine) -> None:
        engine.state.lon += 25.0 / 5.0e6  # 25 m east, unknown to the covariance

    engine, moved = fed_with_upset(recs, span.start_s + 5.0, east)
    assert moved and engine.counters.reanchors == 1 and engine.counters.resets == 0
    t, e, _ = errors(drive, engine.rows)
    assert np.hypot(e[t > span.end_s + 8.0, 0], e[t > span.end_s + 8.0, 1]).max() < 1.5


def test_a_tilt_the_covariance_does_not_admit_reopens_attitude_and_offsets_instead_of_restarting():
    """A solution tilted 8 deg behind a covariance that claims a fraction of a degree (a chip worse than
    configured): the good receiver's velocities and the OBD speed are refused in a row and agree, so velocity,
    attitude and offsets are reopened (counted) and the filter re-converges without a restart. The reopened
    covariance admits the drift that was refused (the tilt is not tied to the accelerometer offset again), so it
    takes one reopening or two, not one every few seconds while the car drives straight."""
    from logger.nav.rotations import quat_from_rotvec, quat_mul

    def tilt(engine: NavEngine) -> None:
        engine.state.q = quat_mul(quat_from_rotvec(math.radians(8.0), 0.0, 0.0), engine.state.q)

    drive, engine, tilted = upset_at_90_s(200.0, 12, tilt)
    assert tilted and 1 <= engine.counters.reopens <= 3 and engine.counters.resets == 0
    t, e, s = errors(drive, engine.rows)
    late = t > 150.0
    assert np.hypot(e[late, 0], e[late, 1]).max() < 2.0
    assert np.mean(np.abs(e[late]) <= 3.0 * s[late]) > 0.9


def shifted_height(recs, at_s: float, metres: float, **params) -> NavEngine:
    """The records through a filter whose height is moved by ``metres`` at ``at_s``, unknown to its covariance."""

    def lift(engine: NavEngine) -> None:
        engine.state.h += metres

    engine, moved = fed_with_upset(recs, at_s, lift, **params)
    assert moved
    return engine


def every_half_second(recs, topic: str) -> list:
    """The records with ``topic`` at twice its rate: each reading repeated half a second later."""
    extra = [(ts + NS // 2, tp, {**m, "t_sync_ns": m["t_sync_ns"] + NS // 2, "t_mono_ns": m["t_mono_ns"] + NS // 2})
             for ts, tp, m in recs if tp == topic]
    return sorted(recs + extra, key=lambda r: r[0])


@pytest.mark.parametrize("baro_hz", [1, 2])
def test_a_height_gone_off_in_an_outage_is_given_back_by_the_barometer(outage, baro_hz):
    """A height 15 m off behind a covariance that claims decimetres: each barometer reading is refused, and
    refusing them all would keep it off for the rest of the drive (and every later GNSS height with it). Five
    that agree over 4 s, at whatever rate the barometer runs, widen the height (counted); with no receiver to say
    otherwise the barometer's offset, which moves by centimetres a minute, keeps its own, so the height follows
    the barometer within the outage."""
    drive, span, recs = outage
    engine = shifted_height(recs if baro_hz == 1 else every_half_second(recs, "/baro"), span.start_s + 5.0, 15.0)
    assert engine.counters.reanchors == 1 and engine.counters.resets == 0
    t, e, s = errors(drive, engine.rows)
    after = t > span.start_s + 15.0
    assert np.abs(e[after, 2]).max() < 1.0
    assert np.mean(np.abs(e[after, 2]) <= 3.0 * s[after, 2]) > 0.9


def test_a_moved_barometer_offset_is_settled_by_the_receiver(outage):
    """The barometer's reading steps 20 m (a sensor replaced, a pressure port knocked) while fixes come: its
    heights are refused in a row, and as the receiver's heights are going in, only the barometer's offset is
    widened: it takes the step, and the height does not move."""
    drive, _, recs = outage
    step_s = 60.0
    moved = [(ts, tp, {**m, "altitude_m": m["altitude_m"] + 20.0} if tp == "/baro" and ts - T0_NS > step_s * 1e9
              else m) for ts, tp, m in recs]
    engine = run(moved)
    assert engine.counters.reanchors >= 1 and engine.counters.resets == 0
    t, e, _ = errors(drive, engine.rows)
    assert np.abs(e[(t > step_s) & (t < 140.0), 2]).max() < 1.0
    # The offset took the step (height minus barometer: 20 m less than without it).
    assert engine.state.dh == pytest.approx(run(recs).state.dh - 20.0, abs=1.0)


def test_the_baseline_restarts_from_fixes_that_agree_only_in_height(outage):
    """Without a barometer, good fixes all refused on a height 15 m off agree among themselves only in their
    vertical innovation: that is a lost filter too, restarted from the receiver."""
    drive, _, recs = outage
    # The synthetic fixes' errors are white: the filter is told so, and trusts them as much as they deserve.
    engine = shifted_height(recs, 60.0, 15.0, mode="15", gnss_floor_corr_s=0.0, gnss_floor_corr_v_s=0.0,
                            gnss_floor_corr_speed_s=0.0)
    assert engine.counters.resets == 1
    t, e, _ = errors(drive, engine.rows)
    assert np.abs(e[(t > 100.0) & (t < 140.0), 2]).max() < 1.0


def test_levelling_widens_the_accelerometer_prior_by_what_gravity_says():
    from logger.nav.alignment import accel_offset_variance

    g = earth.gravity(math.radians(37.5), 60.0)
    prior = (0.05 * earth.G0) ** 2
    # A magnitude 100 mg short of normal gravity: the offset along the vertical is twice the 50 mg prior.
    wide = accel_offset_variance((0.0, 0.0, -(g - 0.1 * earth.G0)), g, prior)
    assert math.sqrt(wide) == pytest.approx(0.1 * earth.G0, rel=1e-6)
    # A chip within the prior leaves it as configured (one draw never narrows it).
    assert accel_offset_variance((0.3, 0.2, -g), g, prior) == prior


def test_a_fix_record_without_a_position_is_no_fix() -> None:
    """Whatever its flags say, a solution without latitude or longitude is not a fix: counted, not used. One
    without a height (an epoch whose GGA never came: the record's altitude null) is a 2D fix: its position goes in
    horizontally, and a GNSS-only row holds the last 3D fix's height, not 0 m."""
    engine = NavEngine(NavParams(mode="gnss"), record=True)
    full = {"t_sync_ns": 1_700_000_000 * 10**9, "t_mono_ns": 10**9, "gnss_time_ns": None, "sync_state": "locked",
            "fix_ok": True, "fix_mode": 3, "latitude": 48.1, "longitude": 11.5, "altitude": 520.0,
            "vel_ned_mps": [1.0, 0.0, None], "h_acc_m": 2.0, "v_acc_m": 3.0}
    for missing in ("latitude", "longitude"):
        engine.gnss(gnss_observation({k: v for k, v in full.items() if k != missing}))
    assert (engine.counters.gnss_no_fix, engine.counters.gnss_fixes, len(engine.rows)) == (2, 0, 0)
    engine.gnss(gnss_observation(full))
    assert (engine.counters.gnss_fixes, len(engine.rows)) == (1, 1)
    later = {**full, "t_sync_ns": full["t_sync_ns"] + 10**9, "t_mono_ns": 2 * 10**9, "latitude": 48.10001}
    engine.gnss(gnss_observation({k: v for k, v in later.items() if k != "altitude"}))
    assert (engine.counters.gnss_fixes, len(engine.rows)) == (2, 2)
    assert engine.rows[-1][4] == 520.0 and abs(math.degrees(engine.rows[-1][2]) - 48.10001) < 1e-9
    # ... with a sigma it can stand behind: the 3D fix's, widened by the 2 m/s a car climbs at most in that second
    # (10 s later, 20 m).
    assert engine.rows[-2][9][2] == pytest.approx(3.0) and engine.rows[-1][9][2] == pytest.approx(math.hypot(3.0, 2.0))
    ten = {**later, "t_sync_ns": full["t_sync_ns"] + 10 * 10**9, "t_mono_ns": 11 * 10**9, "fix_mode": 2}
    engine.gnss(gnss_observation(ten))
    assert engine.rows[-1][4] == 520.0 and engine.rows[-1][9][2] == pytest.approx(math.hypot(3.0, 20.0))


def test_a_2d_fix_before_any_3d_one_claims_no_height() -> None:
    """A receiver whose first fixes are 2D (three satellites: a street canyon at power-on) measures no height yet:
    the one its fix carries is its own assumption (u-blox: a height it was told or guessed) or none. A GNSS-only
    row took it, or 0 m, with the receiver's vertical figure: 63 m off behind a sigma of 0.65 m on the simulated
    urban drive with its first 40 fixes made 2D. It now says the height is unknown."""
    from logger.nav.policies import UNKNOWN_HEIGHT_SIGMA_M

    engine = NavEngine(NavParams(mode="gnss"), record=True)
    fix2d = {"t_sync_ns": 1_700_000_000 * 10**9, "t_mono_ns": 10**9, "gnss_time_ns": None, "sync_state": "locked",
             "fix_ok": True, "fix_mode": 2, "latitude": 48.1, "longitude": 11.5, "altitude": 0.0,
             "vel_ned_mps": [1.0, 0.0, None], "h_acc_m": 2.0, "v_acc_m": 3.0}
    engine.gnss(gnss_observation(fix2d))
    engine.gnss(gnss_observation({**fix2d, "t_sync_ns": fix2d["t_sync_ns"] + 10**9, "altitude": None}))
    assert [r[4] for r in engine.rows] == [0.0, 0.0]
    assert [r[9][2] for r in engine.rows] == [UNKNOWN_HEIGHT_SIGMA_M] * 2
    engine.gnss(gnss_observation({**fix2d, "t_sync_ns": fix2d["t_sync_ns"] + 2 * 10**9, "fix_mode": 3,
                                  "altitude": 520.0}))
    # Its figure, widened as the floor's error lasting gnss_floor_corr_v_s at one fix a second.
    rho = math.exp(-1.0 / NavParams().gnss_floor_corr_v_s)
    assert engine.rows[-1][4] == 520.0
    assert engine.rows[-1][9][2] == pytest.approx(3.0 * math.sqrt((1 + rho) / (1 - rho)))


def _reopening_core(p0: np.ndarray) -> Any:
    """The filter as the evidence rooms see it: a real covariance, updates through the gate, a reopening that
    (like the engine's) forgets attitude and offsets."""
    from types import SimpleNamespace

    from logger.nav.core import EngineCounters
    from logger.nav.ekf import ErrorStateEkf
    from logger.nav.state import BA_ID, PHI_ID

    ekf = ErrorStateEkf(np.diag(p0).copy())
    ekf.p = p0.copy()
    core = SimpleNamespace(ekf=ekf, counters=EngineCounters())
    core.apply = lambda obs: ekf.update(obs) is not None
    core.reopen_attitude_and_offsets = lambda: ekf.inflate(slice(PHI_ID, BA_ID + 3), np.full(6, 1e-2))
    return core


def test_reopening_on_refused_velocities_admits_more_uncertainty_and_never_gains_any():
    """Velocities refused in a row widen position and velocity by the drift they show. Widening is added
    variance: of the height and the barometer's offset, which every barometer reading ties together, neither
    may come out better known, and the next barometer reading may not then count their old values as two
    independent measurements (forgetting the correlation did: the offset's sigma fell 0.75 -> 0.55 m per
    reopening on the simulated NMEA urban drive, seed 2, with no height coming in, and the height sat 1.4 m off
    inside a 0.3 m sigma)."""
    from logger.nav.evidence import VELOCITY_REFUSALS, VelocityEvidence
    from logger.nav.measurements import BaroHeight, Observation
    from logger.nav.state import DH_ID, N_FULL, P_ID, V_ID, NavState

    p0 = np.diag(np.full(N_FULL, 0.04))
    sd, sh = 0.75, 0.79  # the offset's and the height's sigma, tied by the barometer's readings
    p0[DH_ID, DH_ID], p0[P_ID + 2, P_ID + 2] = sd**2, sh**2
    p0[DH_ID, P_ID + 2] = p0[P_ID + 2, DH_ID] = -0.95 * sd * sh  # down and up: their sum is what is known
    core = _reopening_core(p0)
    evidence = VelocityEvidence()
    h = np.zeros((2, N_FULL))
    h[0, V_ID], h[1, V_ID + 1] = 1.0, 1.0
    for k in range(VELOCITY_REFUSALS + 2):  # a receiver's horizontal velocity, 0.8 m/s off, refused each second
        evidence.judge(core, Observation("gnss_vel", np.array([0.8, 0.3]), h.copy(), np.full(2, 0.01)), False,
                       k * NS, True)
    assert core.counters.reopens == 1
    tied = [P_ID + 2, DH_ID]  # the height and the offset: horizontal velocities say nothing of them
    added = core.ekf.p[np.ix_(tied, tied)] - p0[np.ix_(tied, tied)]
    assert np.linalg.eigvalsh(added).min() > -1e-12  # no combination of them got better known
    assert core.ekf.p[P_ID, P_ID] > p0[P_ID, P_ID]  # the position widened by the drift the velocities show
    before_dh = math.sqrt(core.ekf.p[DH_ID, DH_ID])
    s = NavState(0.6, 2.2, 50.0, 0.0, 0.0, 0.0, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    s.dh = -10.0
    baro = BaroHeight(60.0, 0.5).observe(s, s.dcm(), N_FULL)
    core.apply(baro)
    assert math.sqrt(core.ekf.p[DH_ID, DH_ID]) > 0.97 * before_dh  # a reading of their difference: no news of it


def test_an_outages_covariance_is_the_sum_of_what_made_it(outage):
    """tools/nav_budget.py: the forward covariance through the outage, split into its sources (the starting
    covariance by state group, each group's process noise, each measurement row's noise) that each follow the
    filter's recursion with its gains held, adds up to the filter's own covariance; the position's growth is made by
    the dead reckoning's terms, not by the position it started from."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    import nav_budget

    _, span, recs = outage
    b = nav_budget.budget([(topic, msg) for _, topic, msg in recs], NavParams())
    assert abs(b.outage_s - (span.end_s - span.start_s)) < 2.0
    scale = np.sqrt(np.outer(np.diag(b.p_end), np.diag(b.p_end)))
    assert np.abs(b.total() - b.p_end).max() <= 1e-9 * scale.max()
    assert np.all(np.abs(b.total() - b.p_end) <= 1e-6 * scale + 1e-15)
    shares = {name: share for name, share, _, _ in b.horizontal_shares()}
    assert sum(shares.values()) == pytest.approx(1.0)
    assert b.counts["obd"] > 100 and b.counts["propagate"] > 100 and "gnss_pos" not in b.counts
    grew = math.sqrt(b.p_end[0, 0] + b.p_end[1, 1]) / math.sqrt(b.p_start[0, 0] + b.p_start[1, 1])
    assert grew > 3.0
    assert shares["start: position"] < 1.0 / grew**2 + 0.01  # carried through, not grown
    assert shares["noise: obd row 0"] > 0.05  # the speed readings' noise is one of the sources
    # With the reading's rounding a state, the rounding of the run the outage began in (a cruise stays on one 1 km/h
    # step) is the main source, with the rounding of each new run and the rest of the readings' noise.
    r = nav_budget.budget([(topic, msg) for _, topic, msg in recs], NavParams(obd_rounding_state=True))
    shares = {name: share for name, share, _, _ in r.horizontal_shares()}
    assert np.abs(r.total() - r.p_end).max() <= 1e-9 * scale.max()
    assert shares["start: OBD rounding"] + shares["process noise: OBD rounding"] + shares["noise: obd row 0"] > 0.3
    assert "start: OBD rounding" not in b.horizontal_shares()[0][0]


def test_the_start_ups_provisional_attitudes_are_let_go_once_the_filter_runs() -> None:
    """Before the heading is known the start-up keeps its provisional attitudes (a late fix's course is matched to
    the attitude at its epoch); the filter never goes back to the start-up, so they are not held for the drive
    (4096 entries, about 1 MB, at 1 kHz)."""
    drive = make_drive("outage-60s", seed=1, duration_s=60.0)
    engine = NavEngine(NavParams(), record=False)
    feed = nav_feeder(engine)
    held = 0
    for _, topic, msg in records(drive, 60.0, seed=1):
        feed_record(feed, topic, msg)
        if engine.state is None:
            held = max(held, len(engine.startup._prov_hist))
    assert engine.state is not None and held > 0
    assert len(engine.startup._prov_hist) == 0


def test_no_imu_sample_no_filter_whatever_the_fixes_say(outage) -> None:
    """An IMU that never delivers (a chip on the wrong bus) with fixes that give a course: the heading start-up took
    the course and started the filter with nothing to integrate, dated board time 0 (the status showed a position
    "16.0 h old", the host's uptime). It now waits for the IMU and says so."""
    _, _, recs = outage
    engine = run([r for r in recs if r[1] not in ("/imu", "/imu/batch")])
    assert engine.counters.gnss_fixes > 100 and engine.counters.imu == 0
    assert engine.state is None and engine.rows == [] and engine.current() is None
    assert engine.waiting_for() == "waiting for the IMU: no sample yet"
    assert run(recs).state is not None  # the same drive with its IMU starts
