"""Statistics of clock samples: a robust straight-line fit of offset against time (chrony's sourcestats idea).

Each PPS edge paired with its GNSS second gives one sample: board time x, offset y = GNSS time - board time.
Over a minute the board's crystal is well described by a line (offset and frequency), but samples can be
outliers (a late interrupt, a mislabelled edge) and old samples become stale when the temperature moves the
frequency. So the fit rejects outliers by their distance in robust standard deviations, and drops the oldest
samples until the residuals' signs change often enough (a runs test): a trend left in the residuals means the
line no longer fits the old part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_SAMPLES_FOR_SLOPE = 3
OUTLIER_SIGMAS = 5.0


@dataclass(frozen=True, slots=True)
class LineFit:
    """offset(x) = offset_at_ref + slope * (x - x_ref), with the statistics of how well it is known."""

    x_ref: float
    offset_at_ref: float
    slope: float  # frequency error of the board clock (dimensionless: +30e-6 is 30 ppm... of the offset trend)
    sigma_offset: float  # standard error of offset_at_ref
    skew: float  # standard error of slope
    rms: float  # residual RMS of the samples used
    n_used: int
    n_dropped_old: int
    n_outliers: int

    def offset(self, x: float) -> float:
        return self.offset_at_ref + self.slope * (x - self.x_ref)

    def sigma_at(self, x: float) -> float:
        """Standard error of the fitted offset at ``x`` (extrapolation grows with the slope's uncertainty)."""
        return math.hypot(self.sigma_offset, self.skew * (x - self.x_ref))


def critical_runs(n: int) -> int:
    """Fewest runs of residual signs acceptable for ``n`` samples of noise (one-sided 5 % of the runs test)."""
    if n < 4:
        return 1
    mean = (n + 1) / 2.0
    sd = math.sqrt((n - 1) / 4.0)
    return max(1, math.floor(mean - 1.645 * sd))


def count_runs(residuals: np.ndarray) -> int:
    signs = residuals >= 0.0
    return 1 + int(np.count_nonzero(signs[1:] != signs[:-1])) if len(signs) else 0


def _wls(x: np.ndarray, y: np.ndarray, w: np.ndarray, x_ref: float,
         slope_prior: float | None) -> tuple[float, float, np.ndarray, float, float]:
    """Weighted least squares; with ``slope_prior`` (too few samples for a slope) only the offset is fitted."""
    dx = x - x_ref
    if slope_prior is not None:
        a = float(np.sum(w * (y - slope_prior * dx)) / np.sum(w))
        res = y - (a + slope_prior * dx)
        return a, slope_prior, res, 0.0, float(np.sum(w))
    sw = np.sum(w)
    mx = np.sum(w * dx) / sw
    my = np.sum(w * y) / sw
    sxx = np.sum(w * (dx - mx) ** 2)
    b = float(np.sum(w * (dx - mx) * (y - my)) / sxx) if sxx > 0 else 0.0
    a = float(my - b * mx)
    res = y - (a + b * dx)
    return a, b, res, float(sxx), float(sw)


def fit_line(x: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None, slope_prior: float | None = None,
             min_sigma: float = 0.0) -> LineFit:
    """Robust line through (x, y): outliers out, stale head dropped by the runs test, errors estimated.

    ``x`` must be increasing (oldest first). ``slope_prior`` is used while there are too few samples to estimate
    a slope (e.g. the frequency saved at the last run). ``min_sigma`` is a floor for the noise estimate, so that
    a few lucky samples do not claim nanosecond precision.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    w = np.ones_like(x) if weights is None else np.asarray(weights, dtype=np.float64)
    n = len(x)
    if n == 0:
        raise ValueError("no samples to fit")
    x_ref = float(x[-1])
    keep = np.ones(n, dtype=bool)
    outliers = 0
    # Outliers: iterate fit -> reject beyond OUTLIER_SIGMAS robust sigmas (MAD) while something is rejected.
    for _ in range(3):
        idx = np.flatnonzero(keep)
        if len(idx) < MIN_SAMPLES_FOR_SLOPE + 1:
            break
        prior = slope_prior if len(idx) < MIN_SAMPLES_FOR_SLOPE else None
        _, _, res, _, _ = _wls(x[idx], y[idx], w[idx], x_ref, prior)
        # Distances from the residuals' median, not from zero: an outlier shifts the least-squares line by its
        # share, so every good sample's residual is that shift (31 us for an edge 2 ms late among 64), which the
        # noise's MAD of a few microseconds would call an outlier too: all of them went, and the fit with them.
        # Measured from the median, fewer than half can ever be beyond a multiple of the MAD.
        med = float(np.median(res))
        mad = float(np.median(np.abs(res - med)))
        scale = max(1.4826 * mad, min_sigma)
        bad = np.abs(res - med) > OUTLIER_SIGMAS * scale if scale > 0 else np.zeros(len(idx), dtype=bool)
        if not bad.any():
            break
        keep[idx[bad]] = False
        outliers += int(bad.sum())
    idx = np.flatnonzero(keep)
    # Runs test: drop the oldest samples (in steps) until the residual signs look like noise.
    dropped = 0
    start = 0
    while True:
        use = idx[start:]
        prior = slope_prior if len(use) < MIN_SAMPLES_FOR_SLOPE else None
        a, b, res, sxx, sw = _wls(x[use], y[use], w[use], x_ref, prior)
        if len(use) < 8 or count_runs(res) >= critical_runs(len(use)):
            break
        step = max(1, len(use) // 8)
        start += step
        dropped += step
    m = len(use)
    dof = m - (1 if prior is not None else 2)
    var = float(np.sum(w[use] * res**2) / max(dof, 1) / (sw / m)) if m > 1 else 0.0
    var = max(var, min_sigma**2)
    if prior is not None or sxx <= 0:
        sigma_a = math.sqrt(var / m)
        skew = 0.0 if prior is None else float("nan")
    else:
        dx = x[use] - x_ref
        mx = float(np.sum(w[use] * dx) / sw)
        sigma_a = math.sqrt(var * (1.0 / m + mx * mx / (sxx / (sw / m))))
        skew = math.sqrt(var / (sxx / (sw / m)))
    rms = float(math.sqrt(np.mean(res**2))) if m else 0.0
    return LineFit(x_ref, a, b, sigma_a, skew, rms, m, dropped, outliers)
