"""Process noise from what the drive shows: a noisier chip (phone-grade, a shaking car) is measured from its own
samples and the filter's dead reckoning is widened to it; a chip as good as its datasheet changes nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_nav_filter import errors, run
from test_nav_synth import SynthErrors, records

from logger.nav.imu_noise import CONSUMER_NOISE_RATIO, ImuNoiseMonitor
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
    # and it wanders as much more: the offsets' walks grow by the same ratio at least (by what the offset
    # estimate's own moves read, once read; less than the ratio squared given before, this chip's offset being
    # constant)
    ratio = widened.noise.gyro_arw / widened.params.gyro_arw
    walk = widened.params.gyro_bias_walk
    assert ratio > 5.0 and ratio * walk * (1.0 - 1e-9) <= widened.noise.gyro_bias_walk < ratio**2 * walk

    def sigma_at_outage_end(engine) -> np.ndarray:
        t, _, s = errors(drive, engine.rows)
        inside = (t >= span.start_s) & (t < span.end_s)
        return s[inside][-1]

    # What it trusts its dead reckoning with through the minute without GNSS is wider, and it holds.
    assert (sigma_at_outage_end(widened)[:2] > sigma_at_outage_end(datasheet)[:2]).all()
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


def test_a_consumer_grade_gyro_is_given_a_pessimistic_wander_until_its_own_is_read(outage):
    """Before the filter has seen the offset move (a few minutes of aided driving), a chip far noisier than its
    datasheet is taken to wander as the pessimistic side of consumer parts, the ratio squared; one within
    CONSUMER_NOISE_RATIO of its datasheet keeps the ratio."""
    drive, _ = outage
    early = {}
    for times in (1.0, 2.0, 10.0):
        engine = run(records(drive, 45.0, seed=5, imu_hz=RATE_HZ, errors=_errors(times)))
        assert engine.offset_wander.walk() is None  # not yet read
        early[times] = engine
    phone = early[10.0]
    ratio = phone.noise.gyro_arw / phone.params.gyro_arw
    assert ratio > CONSUMER_NOISE_RATIO
    assert phone.noise.gyro_bias_walk == pytest.approx(ratio**2 * phone.params.gyro_bias_walk)
    for times in (1.0, 2.0):
        e = early[times]
        r = e.noise.gyro_arw / e.params.gyro_arw
        assert r <= CONSUMER_NOISE_RATIO and e.noise.gyro_bias_walk == pytest.approx(r * e.params.gyro_bias_walk)
