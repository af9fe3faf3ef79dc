"""The IMU offsets' temperature drift as process noise: what the die temperature adds, and what its noise must not."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
from test_nav_synth import SynthErrors, records

from logger.nav.engine import NavEngine
from logger.nav.imu_noise import OffsetWander
from logger.nav.params import NavParams
from logger.nav.state import BA_ID, BG_ID
from logger.nav.thermal import SMOOTH_S, STEP_DEGC, TempcoLearner, TemperatureSpan
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


def run(temp_of_t, gyro_tempco_rps_degc: tuple[float, float, float] = (0.0, 0.0, 0.0), duration_s: float = 150.0,
        setup=None, **params) -> NavEngine:
    """The synthetic drive with a die temperature ``temp_of_t`` (s from the first sample), the gyro's offsets
    following it by ``gyro_tempco_rps_degc`` from where they start; ``setup`` sees the engine before the drive."""
    drive = make_drive("outage-60s", seed=1, duration_s=duration_s)
    engine = NavEngine(NavParams(**{**DATASHEET, **params}))
    if setup is not None:
        setup(engine)
    t0 = None
    feed = nav_feeder(engine)
    k = np.array(gyro_tempco_rps_degc)
    for _, topic, msg in records(drive, duration_s, seed=2):
        if topic == "/imu":
            t0 = msg["t_sync_ns"] if t0 is None else t0
            temp = temp_of_t((msg["t_sync_ns"] - t0) / 1e9)
            gyro = np.array(msg["gyro_rps"]) + k * (temp - temp_of_t(0.0))
            msg = {**msg, "temp_degc": temp, "gyro_rps": gyro.tolist()}
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


def learner_on(k_true: np.ndarray, temps: np.ndarray, sigma: float, seed: int = 3) -> TempcoLearner:
    rng = np.random.default_rng(seed)
    learner = TempcoLearner([0.16] * 6)
    for i, temp in enumerate(temps):
        offsets = 0.01 + k_true * (temp - temps[0]) + rng.standard_normal(6) * sigma
        learner.add(30.0 * i, float(temp), offsets.tolist(), [sigma**2] * 6, [0.0] * 6, aided=True)
    return learner


def test_the_learner_finds_a_coefficient_the_temperature_range_shows() -> None:
    k_true = np.array([0.0, 0.01, -0.02, 0.05, -0.08, 0.0])
    learner = learner_on(k_true, np.linspace(20.0, 28.0, 40), sigma=0.02)
    k, sigma = map(np.array, learner.coefficients())  # the levels: quick, what narrows the covariance
    assert np.all(sigma < 0.01) and np.all(np.abs(k - k_true) < 3.0 * sigma), (k, sigma)
    kp, sp = map(np.array, learner.proven())  # the steps: slower (0.02-0.026 here), what is applied
    assert np.all(sp > sigma) and np.all(np.abs(kp - k_true) < 3.0 * sp), (kp, sp)
    applied = np.array(learner.applied())
    assert np.all((applied != 0.0) == (np.abs(k_true) >= 0.05))  # beyond 2 sigma of the steps' fit
    residual = np.array(learner.residual_sigma())
    assert np.all(residual < 0.16)
    assert np.allclose(residual[applied != 0.0], sp[applied != 0.0])


def test_without_a_temperature_range_the_configured_bound_stands() -> None:
    learner = learner_on(np.full(6, 0.05), np.full(40, 24.0), sigma=0.02)
    k, sigma = learner.coefficients()
    assert np.allclose(k, 0.0) and np.allclose(sigma, 0.16)
    assert not any(learner.applied()) and np.allclose(learner.residual_sigma(), 0.16)
    fresh = TempcoLearner([0.16] * 6)
    fresh.add(0.0, 24.0, [0.0] * 6, [1e-4] * 6, [0.0] * 6, aided=False)  # not aided: not taken
    assert fresh.coefficients() == ([0.0] * 6, [0.16] * 6)


def test_noisy_estimates_and_their_wander_count_for_less() -> None:
    temps = np.linspace(20.0, 22.0, 10)
    sharp = learner_on(np.zeros(6), temps, sigma=0.005)
    loose = learner_on(np.zeros(6), temps, sigma=0.05)
    assert max(sharp.coefficients()[1]) < min(loose.coefficients()[1])
    wandering = TempcoLearner([0.16] * 6)
    for i, temp in enumerate(temps):
        wandering.add(30.0 * i, float(temp), [0.0] * 6, [0.005**2] * 6, [1e-4] * 6, aided=True)
    assert min(wandering.coefficients()[1]) > max(sharp.coefficients()[1])


def test_turned_axes_turn_the_learnt_coefficients() -> None:
    k_true = np.array([0.0, 0.0, 0.0, 0.06, 0.0, 0.0])
    learner = learner_on(k_true, np.linspace(20.0, 28.0, 40), sigma=0.01)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 deg about z: x goes to y
    learner.turn(turn)
    k, sigma = learner.coefficients()
    assert abs(k[4] - 0.06) < 3.0 * sigma[4] and abs(k[3]) < 3.0 * sigma[3]


def warming(t: float) -> float:
    """A phone's die warming after power-up, degC."""
    return 25.0 + 6.0 * (1.0 - math.exp(-t / 200.0))


def test_a_gyro_offset_that_follows_the_warming_die_is_learnt_and_followed() -> None:
    """The synthetic drive with the die warming by 4.7 degC and the gyro's z offset following it at
    0.15 deg/s/degC (a part at the data sheet's bound): learnt from the aided driving, the coefficient moves the
    offset with the temperature, and the covariance covers what is left of it instead of the bound."""
    k = math.radians(0.15)
    seen: list[tuple[float, float]] = []  # what the wander reader got, and the offset less what the learner moved

    def spy(engine: NavEngine) -> None:
        class Seen(OffsetWander):
            __slots__ = ()

            def add(self, t_s, offset, aided):
                seen.append((offset[2], engine.state.bg[2] - engine._tempco_moved[2]))
                super().add(t_s, offset, aided)
        engine.offset_wander = Seen()

    follows = run(warming, gyro_tempco_rps_degc=(0.0, 0.0, k), duration_s=330.0, setup=spy)
    # The levels' fit is quick and optimistic (0.165 +- 0.004 here): it only narrows the covariance.
    kz, sz = follows.tempco.coefficients()[0][5], follows.tempco.coefficients()[1][5]
    assert abs(kz - k) < 0.2 * k and sz < math.radians(0.03), (math.degrees(kz), math.degrees(sz))
    kp, sp = follows.tempco.proven()[0][5], follows.tempco.proven()[1][5]
    assert abs(kp - k) < 3.0 * sp and follows.tempco.applied()[5] == kp
    assert math.sqrt(follows.tempco.residual_var()[5]) == pytest.approx(sp) and sp < math.radians(0.16) / 3.0
    # It moved the offset by its share of the warming once proven (0.15 x 4.7 degC at most), and that is kept
    # apart from the wander read from the estimates.
    assert 0.1 < math.degrees(follows._tempco_moved[2]) < 0.15 * (warming(330.0) - warming(0.0))
    assert seen and all(a == b for a, b in seen) and seen[-1][0] != follows.state.bg[2]
    # The offset estimate at the end is where the die temperature put the chip's.
    true_bg = SynthErrors().gyro_bias[2] + k * (warming(330.0) - warming(0.0))
    assert abs(follows.state.bg[2] - true_bg) < 3.0 * math.sqrt(follows.ekf.p[BG_ID + 2, BG_ID + 2])


def test_learnt_coefficients_are_kept_for_the_next_drive_of_the_same_part(tmp_path, caplog) -> None:
    """What a drive learnt of the part is saved on the chip's axes once it narrowed some coefficient to under half
    its bound, and is the next start's prior (its sigma doubled), whatever the mounting then; another part, an
    unreadable file or a drive that learnt nothing leave the configured bounds."""
    from logger.runtime import tempco_state
    from logger.runtime.navigator import Navigator

    k = math.radians(0.15)
    learnt = run(warming, gyro_tempco_rps_degc=(0.0, 0.0, k), duration_s=330.0)
    k_chip, sigma_chip = learnt.learnt_tempco()
    bounds = [NavParams(**DATASHEET).accel_bias_tempco] * 3 + [NavParams(**DATASHEET).gyro_bias_tempco] * 3
    path = tmp_path / "imu_tempco.json"
    board = tempco_state.board(2, 0x68)
    # A drive that taught nothing (a loaded prior alone) is not saved.
    assert not tempco_state.save(path, board, k_chip, sigma_chip, bounds, [math.inf] * 6) and not path.exists()
    assert tempco_state.save(path, board, k_chip, sigma_chip, bounds, learnt.tempco.data_sigma())
    assert tempco_state.load(path, tempco_state.simulated("phone", 3), bounds) is None  # another part
    assert tempco_state.load(path, tempco_state.board(2, 0x69), bounds) is None
    assert tempco_state.load(path, board, [b / 2.0 for b in bounds]) is None  # the bounds were changed
    saved = tempco_state.load(path, board, bounds)
    assert saved is not None and saved[0] == pytest.approx(k_chip) and saved[1] == pytest.approx(
        [2.0 * s for s in sigma_chip])

    # The next start: the prior is the saved coefficient, its sigma doubled (and at least 5 % of the bound).
    nav = Navigator(NavParams(**DATASHEET), tempco_path=path, imu_installation=board)
    for kz, sz in (nav.engine.tempco.coefficients(), nav.engine.tempco.proven()):
        assert kz[5] == pytest.approx(k_chip[5]) and sz[5] == pytest.approx(max(2 * sigma_chip[5], 0.05 * bounds[5]))
    assert math.sqrt(nav.engine.tempco.residual_var()[5]) <= bounds[5] + 1e-12
    # A bound of 0 turns the term off, whatever was saved.
    off = NavEngine(NavParams(gyro_bias_tempco_dps_degc=0.0, accel_bias_tempco_mg_degc=0.0))
    off.start_tempco_from(*saved)
    assert off.tempco.applied() == [0.0] * 6 and off.tempco.residual_var() == [0.0] * 6

    # Turned 90 deg in yaw: the chip's x is the body's y, and what the engine learns comes back on chip axes.
    turned = NavEngine(NavParams(**DATASHEET, mounting_rpy_deg=(0.0, 0.0, 90.0)))
    turned.start_tempco_from([0.0] * 3 + [0.001, 0.0, 0.0], [1e-4] * 6)
    body_k = turned.tempco.coefficients()[0]
    assert body_k[4] == pytest.approx(0.001) and abs(body_k[3]) < 1e-12
    assert turned.learnt_tempco()[0][3:] == pytest.approx([0.001, 0.0, 0.0], abs=1e-12)

    path.write_text(path.read_text().replace('"sigma_chip": [', '"sigma_chip": [0.0, '))  # seven, one of them 0
    assert tempco_state.load(path, board, bounds) is None and "not six finite" in caplog.text
    good = path.read_text()
    path.write_text(json.dumps({k: v for k, v in json.loads(good).items() if k != "bounds"}))  # an older logger's
    with caplog.at_level(logging.INFO, logger="logger.runtime.tempco_state"):
        assert tempco_state.load(path, board, bounds) is None
    assert "written by an older version of the logger (without bounds)" in caplog.text  # was: "...: 'bounds'"
    path.write_text("{not json")
    assert tempco_state.load(path, board, bounds) is None and "ignoring the saved IMU temperature" in caplog.text


def test_an_offset_that_wanders_during_a_warming_proves_no_coefficient() -> None:
    """Estimates of an offset that wanders (0.03 deg/s over 200 s, a walk of 0.003 deg/s/sqrt(s) as the filter
    reads it) while the die warms monotonically, with no temperature coefficient at all and a chip grade whose
    walk says far less: at the grade's errors many axes show a coefficient (the covariance then covers it as
    k^2 + sigma^2), but with the wander the drive showed none is proven, so none moves the offsets."""
    rng = np.random.default_rng(8)
    bound = math.radians(0.16)
    at_grade = proven = 0
    for _ in range(8):
        learner = TempcoLearner([bound] * 6)
        wander = rng.standard_normal(6) * math.radians(0.03)
        for i in range(20):  # ten minutes, a sample every 30 s
            phi = math.exp(-30.0 / 200.0)
            wander = phi * wander + math.sqrt(1 - phi * phi) * math.radians(0.03) * rng.standard_normal(6)
            learner.add(30.0 * i, warming(30.0 * i), wander.tolist(), [math.radians(0.002) ** 2] * 6,
                        [math.radians(0.0005) ** 2] * 6, True, [math.radians(0.003) ** 2] * 6)
        k, sigma = learner.coefficients()
        at_grade += sum(1 for kj, sj in zip(k, sigma, strict=True) if abs(kj) > 2.0 * sj)
        proven += sum(1 for k in learner.applied() if k != 0.0)
        residual = learner.residual_sigma()
        applied = learner.applied()
        assert all(r >= min(abs(kj), bound) or a != 0.0 for r, kj, a in zip(residual, k, applied, strict=True))
    # Of 48 axes a 2-sigma test lets 2.2 through by chance (5 or more in 7 % of such sets); at the grade, 12 here.
    assert proven <= 5 < at_grade, (at_grade, proven)
