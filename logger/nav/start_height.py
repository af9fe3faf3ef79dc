"""The height the filter starts from: the fixes of the window before the start, carried to it by the barometer.

The filter starts on one fix (:meth:`logger.nav.startup.Startup.initial`), and the height of one fix is its
vertical error whole (0.8 m at 1 sigma for a good receiver; more for the first fixes after a cold start). Until
the next good fixes the filter has nothing better: a start followed by a street canyon kept that one fix's error
for minutes (the simulated urban drive of seed 2: 1.46 m at the start, about 1 m through the first 90 s). The fixes
before the start are not wasted if the barometer says how the height changed since each: ``h(t) = h_i + b(t) -
b(t_i)``, with ``b`` the barometric altitude, whose offset cancels and whose drift over a minute (weather: about
0.05 m) is far below a fix's error. Their weighted mean (weights the fixes' own vertical variances) is the
starting height, when it is the better guess: the barometer's noise enters it too (its reading at the start
whole, each fix's share of its own), and the fixes' errors are correlated over the multipath time, so its
variance is taken as the fixes' mean variance over the number of multipath times they span (at most their number)
plus the barometer's variance (1 + 1 / n) times. It replaces the start fix's height only below that fix's variance
and from two fixes on: a receiver sure of its height to a few centimetres (RTK) keeps its own, as does a single fix.
The starting variance stays the start fix's (the pooled one is never claimed better than it).

Which fixes: those of the last two multipath correlation times (``gnss_multipath_corr_s``, 5 s by default: ten
fixes at 1 Hz, more at a faster rate). That averages the fast part of the error (reflections, noise), which is
what the pooling is for; the slow part (atmosphere, orbits) is common to all of them and has moved less in ten
seconds than in a minute, so older fixes describe the start's error less well. Measured on 36 recorded drives
(docs/nav.md, Start-up): a minute's fixes took the vertical RMSE while moving of the drives whose single start fix
was off down by up to 0.06 m, and that of eleven others up by 0.005-0.009 m; ten seconds' kept most of the gain and
raised none by more than 0.005 m (chosen after seeing those figures, as the filter's own multipath time).

Only with a barometer (the 17-state mode): without one the fixes' heights cannot be brought to one instant.
"""

from __future__ import annotations

import dataclasses
from bisect import bisect_right
from collections import deque

from logger.nav.core import PreparedFix
from logger.nav.params import NavParams

NS = 1_000_000_000
MULTIPATH_TIMES = 2.0  # the fixes counted: this many multipath correlation times before the start ...
MIN_WINDOW_S = 5.0  # ... and at least this long (multipath configured as white: a few fixes still average)
MAX_BARO_GAP_S = 3.0  # readings further apart than this do not bring a fix between them to the start
_MAX_KEPT = 1600  # fixes (a minute at 25 Hz and more) and readings: memory bounded whatever the window


def window_s(params: NavParams) -> float:
    """How far before the start fixes count, s."""
    return max(MULTIPATH_TIMES * params.gnss_multipath_corr_s, MIN_WINDOW_S)


class StartHeight:
    """Fixes and barometer readings before the start; the start's height from all of them."""

    @classmethod
    def for_params(cls, params: NavParams) -> StartHeight:
        """The window, the barometer's noise and the multipath time the configuration gives."""
        return cls(window_s(params), params.baro_sigma_m, params.gnss_multipath_corr_s)

    def __init__(self, window_s: float, baro_sigma_m: float = NavParams.baro_sigma_m,
                 multipath_corr_s: float = NavParams.gnss_multipath_corr_s) -> None:
        self.window_ns = int(window_s * NS)
        self.baro_var = baro_sigma_m * baro_sigma_m
        self.corr_s = multipath_corr_s
        self._fixes: deque[tuple[int, float, float]] = deque(maxlen=_MAX_KEPT)  # (epoch, height, vertical sigma)
        self._baro: deque[tuple[int, float]] = deque(maxlen=_MAX_KEPT)
        self.used = 0  # fixes in the last start's height (0: the fix's own)

    def fix(self, fix: PreparedFix) -> None:
        """A fix before the start (3D fixes only: a 2D fix's height is the receiver's assumption)."""
        if fix.fix_3d and fix.sigma[2] > 0.0:
            self._fixes.append((fix.t_ns, fix.h, fix.sigma[2]))

    def baro(self, t_ns: int, altitude_m: float) -> None:
        if self._baro and t_ns <= self._baro[-1][0]:
            return  # out of order: the interpolation needs increasing times
        self._baro.append((t_ns, altitude_m))
        while len(self._baro) > 2 and t_ns - self._baro[1][0] > self.window_ns + MAX_BARO_GAP_S * NS:
            self._baro.popleft()

    def _baro_at(self, t_ns: int) -> float | None:
        """The barometric altitude at ``t_ns`` interpolated between the two readings around it, None outside."""
        b = self._baro
        if len(b) < 2 or not b[0][0] <= t_ns <= b[-1][0]:
            return None
        hi = min(bisect_right(b, t_ns, key=lambda r: r[0]), len(b) - 1)  # the readings are in time order
        (t0, a0), (t1, a1) = b[hi - 1], b[hi]
        if t1 - t0 > MAX_BARO_GAP_S * NS:
            return None
        return a0 if t1 == t0 else a0 + (a1 - a0) * (t_ns - t0) / (t1 - t0)

    def start_fix(self, fix: PreparedFix) -> PreparedFix:
        """``fix`` with its height replaced by the pooled one at its epoch, or as it is without what that needs or
        when the pooled one is no better (the module's docstring).

        The pooled height is anchored at the newest barometer reading and carried to the fix's epoch by the fix's
        vertical velocity when the receiver gives one (held otherwise: the newest reading is at most
        MAX_BARO_GAP_S from the fix, so a barometer read more slowly than that leaves the start to the fix)."""
        self.used = 0
        if not self._baro:
            return fix
        t_b, b_now = self._baro[-1]
        if abs(fix.t_ns - t_b) > MAX_BARO_GAP_S * NS:
            return fix  # the barometer has stopped (or not reached the fix): nothing carries a height to it
        total_w = total = 0.0
        n = 0
        first = last = fix.t_ns
        for t, h, sigma in self._fixes:
            if fix.t_ns - t > self.window_ns or t > fix.t_ns:
                continue
            b = self._baro_at(t)
            if b is None:
                continue
            w = 1.0 / (sigma * sigma)
            total_w += w
            total += w * (h - b)
            if n == 0:
                first = t
            last = t
            n += 1
        if n < 2:
            return fix
        span_s = (last - first) / NS
        independent = n if self.corr_s <= 0.0 else min(float(n), 1.0 + span_s / self.corr_s)
        var = n / total_w / independent + self.baro_var * (1.0 + 1.0 / n)
        if var >= fix.sigma[2] * fix.sigma[2]:
            return fix  # the start fix is surer of its height than the pool would be
        h0 = total / total_w + b_now
        if fix.vel is not None and fix.vel_3d:
            h0 -= float(fix.vel[2]) * (fix.t_ns - t_b) / NS
        self.used = n
        return dataclasses.replace(fix, h=h0)

    def clear(self) -> None:
        self._fixes.clear()
        self._baro.clear()
