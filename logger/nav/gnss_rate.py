"""Receivers faster than the filter needs: their fixes thinned to at most ``gnss_max_hz``.

A u-blox M9 or F9R navigates at up to 25 Hz. Its fixes report one error many times over (the receiver's own filter
carries each epoch into the next, and the atmosphere's and a facade's errors last seconds to minutes), so
:class:`logger.nav.gnss_noise.CorrelatedGnssNoise` weighs a second of them as one independent fix: at 25 Hz, with the
floor's error lasting 5 s, each fix's variance is 249 times its figure's. Judged one by one, every such row is then
far weaker than what the filter already knows, and :meth:`logger.nav.policies.GnssPolicy._informative`, which leaves
out rows that would move the solution by a few percent each (a canyon's share one error, and the percents add up to
its bias), left out nearly all of them.

What a second of fixes says is not more at 25 Hz than at 10 Hz, so the filter takes the fixes of a receiver faster
than ``gnss_max_hz`` as if the receiver ran at a lower rate of its own: every ``step``-th epoch on a grid through the
whole seconds, ``step`` the least that brings the rate to ``gnss_max_hz`` (a quarter over it allowed) and divides the
second's epochs, so that those taken are evenly spaced: at 20 Hz every second (10 Hz), at 25 Hz every fifth (5 Hz).
The rest are counted as thinned. The grid runs on the receiver's own epoch times (GNSS time, whole milliseconds), not
on when fixes arrive, and always holds the whole seconds: a post-processed solution is checked against the
receiver's fixes at the epochs both have (a 1 Hz ``.pos`` at whole seconds, :class:`logger.nav.solution.
SolutionPolicy`), and a live re-run (:mod:`logger.recording.nav_rerun`) thins the same fixes again. A receiver whose
second holds no whole number of epochs (a 60 ms period) has every ``step``-th taken by count from each whole second.
A receiver up to a quarter faster than ``gnss_max_hz`` (12.5 Hz) is not thinned, nor is a fix without an epoch time
(placed by its arrival, whose spacing jitters by tens of milliseconds and says little of the rate): receivers at 1
to 10 Hz, the simulator's and u-blox's usual rates, go in whole, as before. The noise model sees only the fixes
taken, and weighs them at their own spacing.
"""

from __future__ import annotations

import math

from logger.nav.gnss_noise import MAX_GAP_S

NS = 1_000_000_000
MS = 1_000_000
RATE_MARGIN = 0.25  # a receiver this much (of gnss_max_hz) faster than it is taken whole: 12.5 Hz at 10
INTERVAL_GAIN = 0.1  # the usual interval follows each new one by this much (as CorrelatedGnssNoise's)


class FixThinner:
    """Which fixes of a receiver go into the filter: all at up to ``max_hz`` (and RATE_MARGIN over it), those on a
    grid of ``step`` epochs through the whole seconds of a faster one, its rate taken from its usual interval
    between epochs (GNSS time)."""

    def __init__(self, max_hz: float) -> None:
        self.max_hz = max_hz
        self.interval_s = 0.0  # the receiver's usual interval between epochs (0 until two have come)
        self._last_ns: int | None = None  # the last epoch seen (GNSS time)
        self._passed = 0  # fixes left out since the last one taken, where the grid does not apply

    def _per_second(self) -> int | None:
        """The receiver's epochs in a second where its period is a whole number of nanoseconds dividing the second."""
        if self.interval_s <= 0.0:
            return None
        n = round(1.0 / self.interval_s)
        return n if n > 0 and abs(1.0 / self.interval_s - n) < 0.01 and NS % n == 0 else None

    @property
    def step(self) -> int:
        """One epoch taken of this many: 1 until the receiver shows itself faster than ``max_hz``."""
        if self.max_hz <= 0.0 or self.interval_s <= 0.0:
            return 1
        least = max(1, math.ceil(1.0 / (self.interval_s * self.max_hz) - RATE_MARGIN - 1e-6))
        n = self._per_second()
        if least == 1 or n is None:
            return least
        return next(k for k in range(least, n + 1) if n % k == 0)

    def take(self, gnss_time_ns: int | None) -> bool:
        """Whether the fix of this epoch (its GNSS time; None: a fix without one) goes in. The time is taken to the
        millisecond: a u-blox NAV-PVT's epoch lies some nanoseconds off the nominal one (its ``nano``)."""
        if gnss_time_ns is None:
            return True
        gnss_time_ns = round(gnss_time_ns / MS) * MS
        last, self._last_ns = self._last_ns, gnss_time_ns
        dt = None if last is None else (gnss_time_ns - last) / NS
        if dt is not None and 0.0 < dt < MAX_GAP_S:
            self.interval_s = dt if self.interval_s == 0.0 else self.interval_s + INTERVAL_GAIN * (dt - self.interval_s)
        step = self.step
        if step == 1:
            return True
        n = self._per_second()
        if n is not None:
            return gnss_time_ns % NS % (step * (NS // n)) == 0
        # No grid: every step-th by count from each whole second, and the first after a gap.
        if dt is None or not 0.0 < dt < MAX_GAP_S or gnss_time_ns % NS == 0 or self._passed + 1 >= step:
            self._passed = 0
            return True
        self._passed += 1
        return False
