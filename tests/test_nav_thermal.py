"""The IMU offsets' temperature drift as process noise: what the die temperature adds, and what its noise must not."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_nav_synth import records

from logger.nav.engine import NavEngine
from logger.nav.params import NavParams
from logger.nav.state import BA_ID, BG_ID
from logger.nav.thermal import SMOOTH_S, STEP_DEGC, TemperatureSpan
from logger.recording.records import feed_record, nav_feeder
from sensors.sim.scenarios import make_drive


def owed(temps: np.ndarray, hz: float = 20.0) -> float:
    span = TemperatureSpan()
    total = 0.0
    for k, temp in enumerate(temps):
        span.add(int(k / hz * 1e9), float(temp))
        total += span.take()
    return total


def test_a_steady_warming_owes_the_square_of_its_span() -> None:
    # 2 degC over 20 minutes: a fixed coefficient k moves the offset by 2k, variance k^2 * 4 degC^2.
    temps = np.linspace(20.0, 22.0, 20 * 60 * 20)
    got = owed(temps)
    lag = 2.0 / (20 * 60) * SMOOTH_S  # the smoothed temperature trails the ramp by this much
    assert (2.0 - lag - STEP_DEGC) ** 2 <= got <= 2.0**2


def test_sensor_noise_at_a_steady_temperature_owes_nothing() -> None:
    rng = np.random.default_rng(3)
    assert owed(25.0 + 0.02 * rng.standard_normal(20 * 600)) == 0.0


def test_a_swing_back_inside_the_range_seen_owes_at_least_its_square() -> None:
    up = np.linspace(20.0, 23.0, 20 * 600)
    hold = np.full(20 * 200, 23.0)
    down = np.linspace(23.0, 21.0, 20 * 400)
    span = TemperatureSpan()
    k = 0
    for temp in np.concatenate([up, hold]):
        span.add(int(k / 20 * 1e9), float(temp))
        k += 1
    span.take()
    for temp in np.concatenate([down, np.full(20 * 200, 21.0)]):
        span.add(int(k / 20 * 1e9), float(temp))
        k += 1
    assert span.take() >= (2.0 - STEP_DEGC) ** 2


DATASHEET = {"gyro_bias_tempco_dps_degc": 0.16, "accel_bias_tempco_mg_degc": 0.5}


def run(temp_of_t, **params) -> NavEngine:
    drive = make_drive("outage-60s", seed=1, duration_s=150.0)
    engine = NavEngine(NavParams(**{**DATASHEET, **params}))
    t0 = None
    feed = nav_feeder(engine)
    for _, topic, msg in records(drive, 150.0, seed=2):
        if topic == "/imu":
            t0 = msg["t_sync_ns"] if t0 is None else t0
            msg = {**msg, "temp_degc": temp_of_t((msg["t_sync_ns"] - t0) / 1e9)}
        feed_record(feed, topic, msg)
    assert engine.ekf is not None
    return engine


@pytest.fixture(scope="module")
def steady() -> NavEngine:
    return run(lambda t: 25.0)


def offset_sigmas(engine: NavEngine) -> tuple[np.ndarray, np.ndarray]:
    p = engine.ekf.p
    return (np.sqrt(np.diag(p)[BA_ID:BA_ID + 3]), np.sqrt(np.diag(p)[BG_ID:BG_ID + 3]))


def test_a_warming_die_widens_the_offsets_by_the_configured_tempco(steady: NavEngine) -> None:
    warm = run(lambda t: 25.0 + 3.0 * t / 150.0)  # 3 degC in the drive: a cabin heating up
    ba0, bg0 = offset_sigmas(steady)
    ba1, bg1 = offset_sigmas(warm)
    # The gyro offset's tempco (0.16 deg/s/degC) over more than a degree dwarfs what GNSS learns meanwhile.
    assert np.all(bg1 > 3.0 * bg0)
    assert np.all(ba1 > ba0)
    assert math.degrees(float(bg1.max())) < 0.16 * 3.0  # never more than the whole warming's worth


def test_without_a_tempco_the_temperature_changes_nothing(steady: NavEngine) -> None:
    warm = run(lambda t: 25.0 + 3.0 * t / 150.0, gyro_bias_tempco_dps_degc=0.0, accel_bias_tempco_mg_degc=0.0)
    assert np.allclose(np.diag(warm.ekf.p), np.diag(steady.ekf.p))
