"""How the board's crystal frequency follows temperature, learned while PPS is there (chrony's tempcomp idea).

A quartz crystal drifts by about a part per million per degree; over an hour in a tunnel while the cabin warms
that is milliseconds. While locked, each new frequency estimate is paired with the temperature then (the
MPU-6050's die sits on the same board); a straight line through those pairs gives the coefficient that holdover
uses to bend its frequency with the temperature. Until the temperature has moved enough to tell, there is no
coefficient, and the error bound assumes a typical crystal's instead.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

MIN_SPACING_NS = 20_000_000_000  # one pair per 20 s: neighbouring fits share most of their samples
MIN_SPAN_DEGC = 1.5
MIN_POINTS = 12
MIN_FIT_SAMPLES = 16  # frequency estimates from shorter fits are too noisy to learn from


class TempcoEstimator:
    def __init__(self, max_points: int = 360) -> None:
        self._pts: deque[tuple[float, float]] = deque(maxlen=max_points)  # (degC, fractional frequency)
        self._last_ns: int | None = None
        self._prior: float | None = None
        # The fit, or None when the points do not allow one, until the next point: asked at every IMU sample,
        # and "no fit yet" (a car whose cabin temperature holds still) must not refit 360 points each time.
        self._cache: tuple[float, float] | None = None
        self._cached = False

    def prior(self, coefficient: float) -> None:
        """A coefficient saved by the previous run: used until this run has learned its own."""
        if math.isfinite(coefficient) and abs(coefficient) < 1e-5:
            self._prior = coefficient

    def add(self, t_ns: int, freq: float, temp_degc: float | None, n_used: int) -> None:
        if temp_degc is None or n_used < MIN_FIT_SAMPLES:
            return
        if self._last_ns is not None and t_ns - self._last_ns < MIN_SPACING_NS:
            return
        self._last_ns = t_ns
        self._pts.append((temp_degc, freq))
        self._cached = False

    def _fit(self) -> tuple[float, float] | None:
        if not self._cached:
            self._cache = self._compute_fit()
            self._cached = True
        return self._cache

    def _compute_fit(self) -> tuple[float, float] | None:
        if len(self._pts) < MIN_POINTS:
            return None
        pts = np.array(self._pts)
        temp, freq = pts[:, 0], pts[:, 1]
        if np.ptp(temp) < MIN_SPAN_DEGC:
            return None
        tm = temp - temp.mean()
        sxx = float(np.sum(tm**2))
        k = float(np.sum(tm * (freq - freq.mean())) / sxx)
        res = freq - freq.mean() - k * tm
        sigma = math.sqrt(float(np.sum(res**2)) / max(len(pts) - 2, 1) / sxx)
        return k, sigma

    def coefficient(self) -> float | None:
        """d(frequency)/d(temperature) per degC (1e-6 is 1 ppm/degC), or None while unknown."""
        fit = self._fit()
        return fit[0] if fit is not None else self._prior

    def sigma(self) -> float | None:
        fit = self._fit()
        return fit[1] if fit is not None else None
