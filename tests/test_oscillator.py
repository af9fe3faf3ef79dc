"""The board crystal model: exact inverse mappings, offset, temperature coefficient, wander, the daemon clock."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensors.sim.oscillator import Oscillator, OscillatorClock
from sensors.sim.scenarios import make_drive
from sensors.sim.truth import ParkedTrajectory

NS = 1_000_000_000


def test_pure_offset_is_exactly_30_ppm():
    osc = Oscillator(wander_ppm_per_sqrt_s=0.0, board_start_ns=5 * NS, duration_s=100.0)
    for t in (0, 1, NS, 37 * NS + 123, 100 * NS, 250 * NS, -3 * NS):
        assert osc.board_ns(t) == 5 * NS + t + round(30e-6 * t)
    assert osc.ppm(50.0) == pytest.approx(30.0, abs=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mappings_invert_each_other_to_the_nanosecond(seed):
    osc = Oscillator.for_trajectory(make_drive("outage-60s", seed=seed), seed=seed, wander_ppm_per_sqrt_s=0.05)
    rng = np.random.default_rng(seed)
    span = int(osc.duration_s * NS)
    trues = [int(t) for t in rng.integers(-5 * NS, span + 50 * NS, 3000)] + [0, 1, span, span + 1]
    assert all(osc.true_ns(osc.board_ns(t)) == t for t in trues)
    boards = [int(b) for b in rng.integers(osc.board_start_ns - 5 * NS, osc.board_start_ns + span + 50 * NS, 3000)]
    # The board clock ticks about 1.00003 ns per true ns, so an integer board time may fall between two.
    assert all(abs(osc.board_ns(osc.true_ns(b)) - b) <= 1 for b in boards)


def test_board_time_is_strictly_increasing_and_rate_matches_ppm():
    osc = Oscillator(seed=4, wander_ppm_per_sqrt_s=0.01, duration_s=600.0)
    t = np.sort(np.random.default_rng(4).integers(0, 600 * NS, 5000))
    b = np.array([osc.board_ns(int(x)) for x in t])
    assert np.all(np.diff(b) >= np.diff(t))  # a fast clock (y > 0) never falls behind
    for ts in (10.5, 200.25, 599.0):
        t0 = int(ts * NS)
        rate_ppm = (osc.board_ns(t0 + 10_000_000) - osc.board_ns(t0 - 10_000_000)) / 20_000_000 * 1e6 - 1e6
        assert rate_ppm == pytest.approx(osc.ppm(ts), abs=0.06)


def test_temperature_coefficient_follows_the_drive_ambient():
    drive = make_drive("urban", seed=2, duration_s=5 * 3600.0)  # long enough for the cabin's whole warming
    osc = Oscillator.for_trajectory(drive, wander_ppm_per_sqrt_s=0.0, seed=2)
    t_end = drive.duration_s
    swing_degc = drive.state(t_end).ambient_degc - drive.state(0.0).ambient_degc
    assert swing_degc == pytest.approx(20.0, abs=1e-6)
    assert osc.ppm(t_end) - osc.ppm(0.0) == pytest.approx(swing_degc * 1.0, abs=1e-3)
    assert osc.ppm(0.0) == pytest.approx(30.0 + drive.state(0.0).ambient_degc - 25.0, abs=1e-9)
    # The accumulated offset is the integral of the rate: between 10 and 40 ppm times the drive's length.
    dev_ns = osc.board_ns(int(t_end * NS)) - osc.board_start_ns - int(t_end * NS)
    avg_ppm = dev_ns / (t_end * NS) * 1e6
    assert min(osc.ppm(0.0), osc.ppm(t_end)) < avg_ppm < max(osc.ppm(0.0), osc.ppm(t_end))


def test_wander_is_a_seeded_random_walk():
    a = Oscillator(seed=7, duration_s=3600.0)
    b = Oscillator(seed=7, duration_s=3600.0)
    c = Oscillator(seed=8, duration_s=3600.0)
    times = [int(x * NS) for x in (0.0, 100.0, 1800.0, 3599.0)]
    assert [a.board_ns(t) for t in times] == [b.board_ns(t) for t in times]
    assert a.board_start_ns != c.board_start_ns or a.board_ns(times[-1]) != c.board_ns(times[-1])
    walks = np.array([[Oscillator(seed=s, duration_s=3600.0, board_start_ns=0).ppm(3600.0) - 30.0]
                      for s in range(200)])
    # sigma = 0.002 ppm/sqrt(s) * sqrt(3600 s) = 0.12 ppm after an hour.
    assert float(np.std(walks)) == pytest.approx(0.12, rel=0.2)
    assert abs(float(np.mean(walks))) < 0.03


def test_parked_trajectory_uses_a_finite_horizon():
    osc = Oscillator.for_trajectory(ParkedTrajectory(extras={"ambient_degc": 35.0}), horizon_s=120.0,
                                    wander_ppm_per_sqrt_s=0.0)
    assert osc.duration_s == 120.0
    assert osc.ppm(60.0) == pytest.approx(40.0)
    assert osc.true_ns(osc.board_ns(10 * 3600 * NS)) == 10 * 3600 * NS  # beyond the grid: same rate on


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="finite"):
        Oscillator(duration_s=math.inf)
    with pytest.raises(ValueError, match="backwards"):
        Oscillator(offset_ppm=-600_000.0, duration_s=10.0)


class FakeHost:
    """A host monotonic clock that moves only when slept on."""

    def __init__(self) -> None:
        self.ns = 1_000 * NS

    def monotonic_ns(self) -> int:
        return self.ns

    def sleep(self, seconds: float) -> None:
        self.ns += round(seconds * NS)


@pytest.mark.parametrize("scale", [1.0, 10.0, 60.0])
def test_oscillator_clock_runs_the_board_at_the_time_scale(scale):
    osc = Oscillator(seed=1, duration_s=3600.0)
    host = FakeHost()
    clock = OscillatorClock(osc, time_scale=scale, host_monotonic_ns=host.monotonic_ns, host_sleep=host.sleep)
    assert clock.monotonic_ns() == osc.board_start_ns
    assert clock.now_ns() == 0
    host.ns += NS
    assert clock.monotonic_ns() == osc.board_start_ns + round(scale * NS)
    assert clock.now_ns() == osc.true_ns(clock.monotonic_ns())
    before = clock.now_ns()
    clock.sleep(12.5)
    assert abs(clock.now_ns() - before - 12_500_000_000) <= math.ceil(scale)  # host ns rounding only
    # Over true time the board gains its ppm: that is what the sync must estimate.
    gained = clock.monotonic_ns() - osc.board_start_ns - clock.now_ns()
    assert gained == pytest.approx(osc.ppm(7.0) * 1e-6 * clock.now_ns(), rel=0.05)


def test_oscillator_clock_at_scale_one_can_be_the_host_clock():
    host = FakeHost()
    osc = Oscillator(seed=1, board_start_ns=host.ns, duration_s=60.0)
    clock = OscillatorClock(osc, host_monotonic_ns=host.monotonic_ns, host_sleep=host.sleep)
    host.sleep(3.25)
    assert clock.monotonic_ns() == host.monotonic_ns()
