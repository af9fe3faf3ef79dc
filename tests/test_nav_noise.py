"""Measurement noise of the navigation filter: correlated GNSS errors above the receiver's floor, and runs of
equal OBD speed readings. Each model must give a run of epochs the weight its shared error leaves it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from logger.nav.ekf import ErrorStateEkf
from logger.nav.engine import NavEngine
from logger.nav.gnss_noise import CorrelatedGnssNoise, RunningMin
from logger.nav.measurements import OBD_STEP_MPS, ROUNDING_VAR, Observation, repeat_variance
from logger.nav.params import NavParams

NS = 1_000_000_000


def test_running_minimum_matches_a_brute_force_window():
    rng = np.random.default_rng(1)
    values = rng.gamma(2.0, 1.0, 2000)
    rm = RunningMin(window=37)
    for i, v in enumerate(values):
        assert rm.add(float(v)) == values[max(0, i - 36): i + 1].min()


def test_open_sky_figures_pass_unchanged():
    noise = CorrelatedGnssNoise(corr_s=5.0)
    for k in range(20):
        h, v, s = noise.sigmas(k * NS, 0.5, 0.8, 0.05)
        assert (h, v, s) == pytest.approx((0.5 / math.sqrt(2.0), 0.8, 0.05))


def _belief_and_truth(corr_s: float, tau_s: float, n: int, runs: int = 400) -> tuple[float, float]:
    """Variance the filter would believe of n epochs' mean, and the true one, for AR(1) errors over a floor."""
    floor, excess = 0.5, 3.0  # the receiver's open-sky figure and a canyon's extra error, DRMS
    rho = math.exp(-1.0 / tau_s)
    rng = np.random.default_rng(7)
    e = np.zeros((runs, n))
    x = rng.standard_normal(runs) * excess / math.sqrt(2.0)
    for k in range(n):
        e[:, k] = x + rng.standard_normal(runs) * floor / math.sqrt(2.0)
        x = rho * x + rng.standard_normal(runs) * excess / math.sqrt(2.0) * math.sqrt(1.0 - rho**2)
    noise = CorrelatedGnssNoise(corr_s)
    for k in range(30):  # open sky first: the receiver's floor is known
        noise.sigmas(k * NS, floor, 1.0, 0.05)
    h_acc = math.hypot(floor, excess)
    info = sum(1.0 / noise.sigmas((30 + k) * NS, h_acc, 1.0, 0.05)[0] ** 2 for k in range(n))
    return 1.0 / info, float(e.mean(axis=1).var())


def test_a_canyons_correlated_fixes_weigh_what_their_shared_error_leaves_them():
    believed, true = _belief_and_truth(corr_s=5.0, tau_s=5.0, n=60)
    assert 0.5 < believed / true < 2.0
    white, true = _belief_and_truth(corr_s=0.0, tau_s=5.0, n=60)  # taken as independent: far too sure
    assert white / true < 0.2


def test_the_verticals_floor_error_lasts_its_own_time():
    """gnss_floor_corr_v_s widens the vertical's floor by its own time, gnss_floor_corr_speed_s the speed's; the
    horizontal's keeps floor_corr_s's, and without them the vertical and the speed keep the horizontal's."""
    def widened(rho: float) -> float:
        return math.sqrt((1 + rho) / (1 - rho))

    both = CorrelatedGnssNoise(corr_s=5.0, floor_corr_s=5.0, floor_corr_v_s=8.0, floor_corr_speed_s=3.5)
    same = CorrelatedGnssNoise(corr_s=5.0, floor_corr_s=5.0)
    for k in range(20):
        h, v, s = both.sigmas(k * NS, 0.5, 0.8, 0.05)
        h1, v1, s1 = same.sigmas(k * NS, 0.5, 0.8, 0.05)
    assert h == pytest.approx(0.5 / math.sqrt(2.0) * widened(math.exp(-1 / 5.0))) and h1 == pytest.approx(h)
    assert s == pytest.approx(0.05 * widened(math.exp(-1 / 3.5)))
    assert s1 == pytest.approx(0.05 * widened(math.exp(-1 / 5.0)))
    assert v == pytest.approx(0.8 * widened(math.exp(-1 / 8.0)))
    assert v1 == pytest.approx(0.8 * widened(math.exp(-1 / 5.0)))
    p = NavParams()
    assert (p.gnss_floor_corr_v_s, p.gnss_floor_corr_s, p.gnss_floor_corr_speed_s) == (8.0, 5.0, 3.5)
    noise = NavEngine(NavParams(gnss_floor_corr_speed_s=2.0))._gnss._noise  # the filter's fixes take the key
    assert (noise.floor_corr_s, noise.floor_corr_v_s, noise.floor_corr_speed_s) == (5.0, 8.0, 2.0)


def test_fixes_far_apart_are_taken_as_independent():
    noise = CorrelatedGnssNoise(corr_s=5.0)
    noise.sigmas(0, 0.5, 0.8, 0.05)
    assert noise.factor(60 * NS) == 1.0
    assert noise.factor(61 * NS) == pytest.approx((1 + math.exp(-0.2)) / (1 - math.exp(-0.2)))


@pytest.mark.parametrize("n", [1, 2, 5, 40, 400])
def test_a_run_of_equal_speed_readings_adds_up_to_what_its_rounding_leaves(n):
    sigma, step = 0.2, 1.0 / 3.6
    var_q = step**2 / 12.0
    info = sum(1.0 / repeat_variance(sigma, step, k) for k in range(1, n + 1))
    assert 1.0 / info == pytest.approx(var_q + (sigma**2 - var_q) / n, rel=1e-6)


def test_rounded_steady_speeds_are_consistent_with_the_weight_of_their_run():
    sigma, step, n = 0.2, 1.0 / 3.6, 40
    rng = np.random.default_rng(3)
    v = rng.uniform(5.0, 25.0, 5000)
    err = np.round(v / step) * step - v  # the same in every reading of the run
    believed = 1.0 / sum(1.0 / repeat_variance(sigma, step, k) for k in range(1, n + 1))
    assert float(np.mean(err**2 / believed)) < 1.2
    assert float(np.mean(err**2 / (sigma**2 / n))) > 4.0  # taken as independent: far too sure


def test_no_white_part_leaves_the_repeats_without_weight_but_finite():
    assert repeat_variance(0.05, 1.0 / 3.6, 1) == pytest.approx(0.0025)
    assert math.isfinite(repeat_variance(0.05, 1.0 / 3.6, 2)) and repeat_variance(0.05, 1.0 / 3.6, 2) >= 1e5


def _run_of_readings(n: int, sigma: float) -> float:
    """With the rounding a state (``obd_rounding_state``): the speed's variance after ``n`` equal readings, by the
    filter's own update: the speed error and the run's rounding error as states (the speed unknown at first), each
    reading's row speed - rounding with the white part of ``sigma`` as the policy gives it."""
    var_w = sigma**2 - ROUNDING_VAR
    ekf = ErrorStateEkf(np.array((100.0, ROUNDING_VAR)))
    for _ in range(n):
        obs = Observation("obd", np.zeros(1), np.array(((1.0, -1.0),)), np.array((var_w,)))
        assert ekf.update(obs, gated=False) is not None
    return float(ekf.p[0, 0])


@pytest.mark.parametrize("n", [1, 2, 5, 40, 400])
def test_the_rounding_state_knows_a_runs_speed_as_the_repeats_weights_do(n):
    """The two models of a run agree on what it knows: the rounding's variance plus the rest over n."""
    sigma = 0.2
    info = sum(1.0 / repeat_variance(sigma, OBD_STEP_MPS, k) for k in range(1, n + 1))
    assert _run_of_readings(n, sigma) == pytest.approx(1.0 / info, rel=1e-3)
