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
on when fixes arrive, its period the least of the last intervals between them (an epoch lost on the line does not
move it), and always holds the whole seconds: a post-processed solution is checked against the
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
from collections import deque

from logger.nav.gnss_noise import MAX_GAP_S

NS = 1_000_000_000
MS = 1_000_000
RATE_MARGIN = 0.25  # a receiver this much (of gnss_max_hz) faster than it is taken whole: 12.5 Hz at 10
PERIODS_KEPT = 8  # the receiver's period is the least of its last this many intervals between epochs


class FixThinner:
    """Which fixes of a receiver go into the filter: all at up to ``max_hz`` (and RATE_MARGIN over it), those on a
    grid of ``step`` epochs through the whole seconds of a faster one. Its period is the least of its last
    intervals between epochs (GNSS time, to the millisecond): an epoch lost on the line (a sentence with a bad
    checksum) makes one interval longer, never shorter, so the grid holds through it. (A mean of the intervals, as
    the noise model keeps, moved off the period at each loss: with one epoch in fifty lost, three in four of a 25 Hz
    receiver's fixes taken were off the 5 Hz grid.)"""

    def __init__(self, max_hz: float) -> None:
        self.max_hz = max_hz
        self._last_ms: int | None = None  # the last epoch seen (GNSS time, ms)
        self._intervals: deque[int] = deque(maxlen=PERIODS_KEPT)  # the last intervals between epochs, ms
        self._passed = 0  # fixes left out since the last one taken (what the count goes by where there is no grid)
        self._taken_ms: int | None = None  # the last epoch taken

    @property
    def period_ms(self) -> int:
        """The receiver's period, ms (0 until two epochs have come)."""
        return min(self._intervals, default=0)

    @property
    def step(self) -> int:
        """One epoch taken of this many: 1 until the receiver shows itself faster than ``max_hz``. Where the
        period divides the second, a divisor of the second's epochs, so that the grid holds the whole seconds."""
        period = self.period_ms
        if self.max_hz <= 0.0 or period <= 0:
            return 1
        least = max(1, math.ceil(1000.0 / (period * self.max_hz) - RATE_MARGIN - 1e-6))
        if least == 1 or 1000 % period:
            return least
        n = 1000 // period
        return next(k for k in range(least, n + 1) if n % k == 0)

    def take(self, gnss_time_ns: int | None) -> bool:
        """Whether the fix of this epoch (its GNSS time; None: a fix without one) goes in. The time is taken to the
        millisecond: a u-blox NAV-PVT's epoch lies some nanoseconds off the nominal one (its ``nano``)."""
        if gnss_time_ns is None:
            return True
        t_ms = round(gnss_time_ns / MS)
        last, self._last_ms = self._last_ms, t_ms
        dt_ms = None if last is None else t_ms - last
        gap = dt_ms is None or not 0 < dt_ms < MAX_GAP_S * 1000
        if not gap:
            self._intervals.append(dt_ms)
        if self._decide(t_ms, gap):
            self._taken_ms, self._passed = t_ms, 0
            return True
        self._passed += 1
        return False

    def _decide(self, t_ms: int, gap: bool) -> bool:
        step, period = self.step, self.period_ms
        if step == 1:
            return True
        if self._taken_ms is None or t_ms - self._taken_ms > 2 * step * period:
            return True  # none taken for two grid spacings: the receiver slowed down (its grid not yet forgotten)
        if 1000 % period == 0:
            return t_ms % 1000 % (step * period) == 0
        # No grid: every step-th by count from each whole second, and the first after a gap.
        return gap or t_ms % 1000 == 0 or self._passed + 1 >= step
