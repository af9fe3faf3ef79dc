"""Receivers faster than the filter needs: their fixes thinned to at most ``gnss_max_hz``.

A u-blox M9 or F9R navigates at up to 25 Hz. Its fixes report one error many times over (the receiver's own filter
carries each epoch into the next, and the atmosphere's and a facade's errors last seconds to minutes), so
:class:`logger.nav.gnss_noise.CorrelatedGnssNoise` weighs a second of them as one independent fix: at 25 Hz, with the
floor's error lasting 5 s, each fix's variance is 249 times its figure's. Judged one by one, every such row is then
far weaker than what the filter already knows, and :meth:`logger.nav.policies.GnssPolicy._informative`, which leaves
out rows that would move the solution by a few percent each (a canyon's share one error, and the percents add up to
its bias), left out nearly all of them: on the simulated outage drive with a 25 Hz receiver's own figures the filter
coasted between the few it took (RMSE 3.6 / 2.2 / 2.9 m against 0.8-1.3 m at 1 to 10 Hz).

What a second of fixes says is not more at 25 Hz than at 10 Hz, so the filter takes every ``step``-th fix of a
receiver faster than ``gnss_max_hz`` (by count, not by time: an epoch placed by its arrival jitters by tens of
milliseconds), the others counted as thinned: at 25 Hz every third (8.3 Hz), at 20 Hz every second (10 Hz), at
16 Hz every second (8 Hz). A receiver up to a fifth faster than ``gnss_max_hz`` (a 10 Hz one whose intervals
jitter) is not thinned at all, so receivers at 1 to 12 Hz go in whole as before. The noise model sees only the fixes
taken, and weighs them at their own spacing.
"""

from __future__ import annotations

import math

from logger.nav.gnss_noise import MAX_GAP_S

RATE_MARGIN = 0.2  # a receiver this much (of gnss_max_hz) faster than it is taken whole: jitter, not speed
INTERVAL_GAIN = 0.1  # the usual interval follows each new one by this much (as CorrelatedGnssNoise's)


class FixThinner:
    """Which fixes of a receiver go into the filter: all at up to ``max_hz`` (and RATE_MARGIN over it), every
    ``step``-th of a faster one, the receiver's rate taken from its usual interval between epochs."""

    def __init__(self, max_hz: float) -> None:
        self.max_hz = max_hz
        self.interval_s = 0.0  # the receiver's usual interval between epochs (0 until two have come)
        self._t_last_ns: int | None = None
        self._passed = 0  # fixes left out since the last one taken

    @property
    def step(self) -> int:
        """One fix taken of this many: 1 until the receiver shows itself faster than ``max_hz``."""
        if self.max_hz <= 0.0 or self.interval_s <= 0.0:
            return 1
        return max(1, math.ceil(1.0 / (self.interval_s * self.max_hz) - RATE_MARGIN))

    def take(self, t_ns: int) -> bool:
        """Whether the fix of epoch ``t_ns`` goes in. The first fix does, and the first after a gap (an outage,
        the receiver restarted): the count starts again from it."""
        last, self._t_last_ns = self._t_last_ns, t_ns
        dt = None if last is None else (t_ns - last) / 1e9
        if dt is None or not 0.0 < dt < MAX_GAP_S:
            self._passed = 0
            return True
        self.interval_s = dt if self.interval_s == 0.0 else self.interval_s + INTERVAL_GAIN * (dt - self.interval_s)
        if self._passed + 1 >= self.step:
            self._passed = 0
            return True
        self._passed += 1
        return False
