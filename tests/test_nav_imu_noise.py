"""Process noise from what the drive shows: a noisier chip (phone-grade, a shaking car) is measured from its own
samples and the filter's dead reckoning is widened to it; a chip as good as its datasheet changes nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_nav_filter import errors, run
from test_nav_synth import SynthErrors, records

from logger.nav.imu_noise import ImuNoiseMonitor
from logger.nav.params import NavParams
from sensors.sim.scenarios import make_drive

BASE = SynthErrors(obd_factor=1.02)
RATE_HZ = 100.0


def _errors(times: float) -> SynthErrors:
    """The synthetic IMU at 100 Hz with ``times`` the datasheet's noise density (its per-sample sigma is the
    density times the square root of the 10 Hz bandwidth the 20 Hz default stands for; here of 50 Hz)."""
    k = times * math.sqrt(RATE_HZ / 2.0 / 10.0)
    return SynthErrors(obd_factor=1.02, accel_noise=BASE.accel_noise * k, gyro_noise=BASE.gyro_noise * k)


@pytest.fixture(scope="module")
def outage():
    drive = make_drive("outage-60s", seed=1, duration_s=270.0)
    (span,) = drive.spans_of("outage")
    return drive, span


def test_the_densities_measured_while_driving_are_the_chips(outage):
    drive, _ = outage
    p = NavParams()
    for times in (1.0, 10.0):
        monitor = ImuNoiseMonitor()
        for _, topic, m in records(drive, 120.0, seed=3, imu_hz=RATE_HZ, errors=_errors(times)):
            if topic == "/imu":
                monitor.add(tuple(m["accel_mps2"]), tuple(m["gyro_rps"]), 1.0 / RATE_HZ)
        acc, gyro = monitor.densities()
        # White noise of one-sided density N over the Nyquist band random-walks at N / sqrt(2) per sqrt(s).
        assert acc == pytest.approx(times * p.accel_vrw / math.sqrt(2.0), rel=0.1)
        assert gyro == pytest.approx(times * p.gyro_arw / math.sqrt(2.0), rel=0.1)


def test_a_phone_grade_chip_widens_the_dead_reckoning_it_is_trusted_with(outage):
    drive, span = outage
    recs = records(drive, 270.0, seed=2, imu_hz=RATE_HZ, gnss_off=[(span.start_s, span.end_s)],
                   errors=_errors(10.0))
    widened, datasheet = run(recs), run(recs, imu_noise_from_drive=False)
    assert widened.noise.accel_vrw == pytest.approx(10.0 / math.sqrt(2.0) * widened.params.accel_vrw, rel=0.1)
    # and it wanders as much more: the offsets' walks grow by the same ratio
    ratio = widened.noise.gyro_arw / widened.params.gyro_arw
    assert ratio > 5.0 and widened.noise.gyro_bias_walk == pytest.approx(ratio * widened.params.gyro_bias_walk)

    def worst_in_outage(engine) -> float:
        t, e, _ = errors(drive, engine.rows)
        inside = (t >= span.start_s) & (t < span.end_s)
        return float(np.hypot(e[inside, 0], e[inside, 1]).max())

    assert worst_in_outage(widened) < worst_in_outage(datasheet)
    _, e, s = errors(drive, widened.rows)
    assert ((np.abs(e) <= 3.0 * s).mean(axis=0) >= 0.95).all()


def test_a_chip_as_good_as_its_datasheet_changes_nothing(outage):
    drive, _ = outage
    recs = records(drive, 120.0, seed=4, imu_hz=RATE_HZ, errors=_errors(1.0))
    engine = run(recs)
    assert engine.noise.accel_vrw == engine.params.accel_vrw and engine.noise.gyro_arw == engine.params.gyro_arw


def test_the_gyro_offsets_wander_is_read_from_how_the_filters_estimate_moves():
    from logger.nav.imu_noise import OffsetWander

    rng = np.random.default_rng(5)
    walk = math.radians(0.03)  # rad/s/sqrt(s): a phone-grade gyro's
    wander = OffsetWander()
    b = np.zeros(3)
    assert wander.walk() is None
    for k in range(600):  # ten minutes, the estimate following the offset, sampled every second
        b += rng.standard_normal(3) * walk
        wander.add(float(k), tuple(b), aided=True)
    assert wander.walk() == pytest.approx(walk, rel=0.3)
    # An outage's changes are what the filter let through, not what the gyro did: nothing is learnt from them.
    before = wander.walk()
    for k in range(600, 700):
        wander.add(float(k), (1.0, 1.0, 1.0), aided=False)
    assert wander.walk() == before
