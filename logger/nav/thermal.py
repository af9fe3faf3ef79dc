"""How far the IMU offsets may have moved with the die temperature, as process noise on the offset states.

A MEMS offset follows the die temperature through a coefficient k that is fixed for the part but unknown to the
filter (the MPU-6050 datasheet bounds it only as a variation over the operating range). That is not a random
walk: warming by D moves the offset by k D, with a variance k^2 D^2 that grows with the square of the excursion,
and cooling back undoes it. The filter carries no state for k (the drive rarely sweeps enough temperature to
learn it), so the covariance must instead cover, over any interval, the square of what the offset can have moved
in it. :class:`TemperatureSpan` turns the smoothed die temperature into that variance, in degC^2 per unit k^2:

- a step d that widens the range R of temperatures seen since the offsets were calibrated adds
  d (2 R_after - d) = R_after^2 - R_before^2, so a steady warming by D adds exactly D^2 (k^2 D^2 in all);
- a step inside the range adds |d| (2 R - |d|) >= |d| R, so any back-and-forth of size a <= R, which moves the
  offset by k a, adds at least a R >= a^2.

The bound is conservative once the temperature wanders inside a range it has already seen (the filter has by
then learnt part of the offset from GNSS), and exact on the monotonic warm-up after a start, which is the case
that matters. The reading is averaged first (time constant ``SMOOTH_S``) and counted in steps of ``STEP_DEGC``:
the sensor's noise (a few hundredths of a degree per sample) would otherwise add up as if the die swung.
"""

from __future__ import annotations

import math

import numpy as np

SMOOTH_S = 20.0  # die temperature follows the board within minutes; its sensor's noise is white per sample
STEP_DEGC = 0.05  # smallest change counted: above the averaged noise, below any tempco worth modelling


class TemperatureSpan:
    """Smoothed die temperature, its range since :meth:`restart`, and the variance (degC^2) owed since last taken."""

    def __init__(self) -> None:
        self.restart()

    def restart(self) -> None:
        """The offsets were (re)calibrated: temperature changes count from here."""
        self._t_ns: int | None = None
        self._smooth = math.nan
        self._counted = math.nan
        self._lo = math.inf
        self._hi = -math.inf
        self._owed = 0.0

    @property
    def range_degc(self) -> float:
        return max(self._hi - self._lo, 0.0)

    def add(self, t_ns: int, temp_degc: float) -> None:
        """One die-temperature reading (from the IMU record it came with)."""
        if temp_degc - temp_degc != 0.0:  # not finite (NaN or infinite): the cheapest test of the hot path
            return
        t0 = self._t_ns
        if t0 is None:
            self._t_ns, self._smooth, self._counted = t_ns, temp_degc, temp_degc
            self._lo = self._hi = temp_degc
            return
        if t_ns <= t0:
            return
        self._t_ns = t_ns
        a = (t_ns - t0) / 1e9 / SMOOTH_S
        smooth = self._smooth
        smooth += (a if a < 1.0 else 1.0) * (temp_degc - smooth)
        self._smooth = smooth
        d = smooth - self._counted
        if -STEP_DEGC < d < STEP_DEGC:
            return
        self._count(smooth)

    def add_block(self, t_ns: np.ndarray, temp_degc: float) -> None:
        """One reading for samples at ``t_ns`` (in time order; a FIFO read has one temperature): what :meth:`add`
        at each leaves, the average in closed form."""
        if temp_degc - temp_degc != 0.0 or len(t_ns) == 0:
            return
        if self._t_ns is None:
            self.add(int(t_ns[0]), temp_degc)
            t_ns = t_ns[1:]
        t = t_ns[t_ns > self._t_ns]
        if len(t) == 0:
            return
        a = np.minimum(np.diff(t, prepend=self._t_ns) / 1e9 / SMOOTH_S, 1.0)
        smooth = temp_degc - np.cumprod(1.0 - a) * (temp_degc - self._smooth)
        self._t_ns, self._smooth = int(t[-1]), float(smooth[-1])
        i = 0
        while True:  # the steps counted: few if any in a block
            hit = np.flatnonzero(np.abs(smooth[i:] - self._counted) >= STEP_DEGC)
            if len(hit) == 0:
                return
            i += int(hit[0])
            self._count(float(smooth[i]))
            i += 1

    def _count(self, smooth: float) -> None:
        """A change of at least STEP_DEGC since the last one counted: the span widens and its variance is owed."""
        step = abs(smooth - self._counted)
        self._counted = smooth
        self._lo = min(self._lo, smooth)
        self._hi = max(self._hi, smooth)
        self._owed += step * (2.0 * self.range_degc - step)

    def take(self) -> float:
        """Variance per unit k^2 (degC^2) owed since the last call; the caller adds k^2 times it to the offsets."""
        owed, self._owed = self._owed, 0.0
        return owed
