"""How far the IMU offsets may have moved with the die temperature, as process noise on the offset states.

A MEMS offset follows the die temperature through a coefficient k that is fixed for the part but unknown to the
filter (the MPU-6050 datasheet bounds it only as a variation over the operating range). That is not a random
walk: warming by D moves the offset by k D, with a variance k^2 D^2 that grows with the square of the excursion,
and cooling back undoes it. The filter carries no state for k (learnt beside it, below, where the drive shows
it), so the covariance must cover, over any interval, the square of what the offset can have moved in it.
:class:`TemperatureSpan` turns the smoothed die temperature into that variance, in degC^2 per unit k^2:

- a step d that widens the range R of temperatures seen since the offsets were calibrated adds
  d (2 R_after - d) = R_after^2 - R_before^2, so a steady warming by D adds exactly D^2 (k^2 D^2 in all);
- a step inside the range adds |d| (2 R - |d|) >= |d| R, so any back-and-forth of size a <= R, which moves the
  offset by k a, adds at least a R >= a^2.

The bound is conservative once the temperature wanders inside a range it has already seen (the filter has by
then learnt part of the offset from GNSS), and exact on the monotonic warm-up after a start, which is the case
that matters. The reading is averaged first (time constant ``SMOOTH_S``) and counted in steps of ``STEP_DEGC``:
the sensor's noise (a few hundredths of a degree per sample) would otherwise add up as if the die swung.

k itself is learnt from the drive where the drive shows it (:class:`TempcoLearner`), as phones and
automotive dead-reckoning receivers calibrate their gyros over temperature: while fixes go in, the filter's own
offset estimates are regressed on the die temperature, with the configured bound as the prior of k. The
posterior narrows the bound in the variance above, and a coefficient the data prove (beyond twice its sigma)
moves the offsets with the temperature, in an outage too, where nothing else would. With the MPU-6050's bound
of 0.16 deg/s/degC taken as it stands, the simulated phone's gyro offset sigma grew 0.24 deg/s in its first
1.5 degC of warming and 0.2 deg/s more in a minute's outage, and the weak constraints of an outage (speed, no
side slip) moved the estimate where nothing moved the chip's: 23.0 m the largest error in that outage, 19.0 m
with the learner, 5.9 m with the bound set by hand to the simulated part's 0.05.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from logger.nav.arrays import diff_from
from logger.nav.deferred import BlockKeeper

SMOOTH_S = 20.0  # die temperature follows the board within minutes; its sensor's noise is white per sample
STEP_DEGC = 0.05  # smallest change counted: above the averaged noise, below any tempco worth modelling


class TemperatureSpan(BlockKeeper):
    """Smoothed die temperature, its range since :meth:`restart`, and the variance (degC^2) owed since last taken."""

    def __init__(self) -> None:
        self.restart()

    def restart(self) -> None:
        """The offsets were (re)calibrated: temperature changes count from here (blocks kept from before would
        only be forgotten)."""
        self._blocks: list[tuple[np.ndarray, ...]] = []  # times of blocks not yet taken, all of one reading ...
        self._kept_degc = math.nan  # ... this one
        self._t_ns: int | None = None
        self._smooth = math.nan
        self._counted = math.nan
        self._lo = math.inf
        self._hi = -math.inf
        self._owed = 0.0

    @property
    def smoothed(self) -> float:
        """The averaged die temperature, degC (NaN before the first reading)."""
        self.take_kept()
        return self._smooth

    @property
    def range_degc(self) -> float:
        self.take_kept()
        return max(self._hi - self._lo, 0.0)

    def add(self, t_ns: int, temp_degc: float) -> None:
        """One die-temperature reading (from the IMU record it came with)."""
        if temp_degc - temp_degc != 0.0:  # not finite (NaN or infinite): the cheapest test of the hot path
            return
        self.take_kept()
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
        at each leaves, the average in closed form. Kept until a figure is asked for (at each covariance step) or
        BLOCKS_KEPT wait; consecutive blocks of one reading are taken as one, the same average (another reading
        takes those kept first)."""
        if temp_degc - temp_degc != 0.0 or len(t_ns) == 0:
            return
        if temp_degc != self._kept_degc:
            self.take_kept()
            self._kept_degc = temp_degc
        self.keep_block(t_ns)

    def take_block(self, t_ns: np.ndarray) -> None:
        temp_degc = self._kept_degc
        if self._t_ns is None:
            self.add(int(t_ns[0]), temp_degc)
            t_ns = t_ns[1:]
        t = t_ns[t_ns > self._t_ns]
        if len(t) == 0:
            return
        a = np.minimum(diff_from(self._t_ns, t) / 1e9 / SMOOTH_S, 1.0)
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
        self.take_kept()
        owed, self._owed = self._owed, 0.0
        return owed


LEARN_EVERY_S = 30.0  # the offset estimates are sampled this often while aided (closer ones repeat each other)
WANDER_MEMORY_S = 120.0  # fitting the levels: the walk over this long counts as each sample's error beside its sigma
MAX_RHO = 0.95  # fitting the levels: the residuals' lag-one correlation counted at most (a factor of 39)
LEARN_KEPT = 240  # samples kept: the last two hours
SIGNIFICANT = 2.0  # a coefficient this many sigmas from zero moves the offsets with the temperature
PRIOR_FLOOR = 0.05  # an earlier drive's sigma is taken at no less than this share of the configured bound


class TempcoLearner:
    """The offsets' temperature coefficients (accelerometer x y z, gyro x y z), learnt from the filter's own
    offset estimates against the die temperature while it is aided.

    The offset is a random walk (the filter's own model of it) plus k times the die temperature, so from one
    sample to the next, per axis, d(offset) = k dT + the walk's step, with a variance of q dt (q the walk's
    density squared) plus the two estimates' variances (an upper bound: the filter's errors a sample apart are
    much alike). The steps are independent, so k is a weighted regression of the offset's steps on the
    temperature's, through zero: a drift of the offset that happens to run with a warm-up is a walk the
    variance expects, not a slope (fitting the levels instead, a pure walk over a 30 min warming passed for a
    coefficient on 40 % of the axes). Where the steps scatter more than that variance says, the data's variance
    is scaled by their reduced chi-square. That fit, with the walk the drive showed, is what is applied and
    kept (:meth:`proven`). The covariance is narrowed by a quicker fit of the levels at the chip grade's walk
    (:meth:`coefficients`, :meth:`_solve_levels`), which covers k^2 + sigma^2 of what it finds. k's prior is the
    configured bound around zero, or what an earlier drive learnt of the part (:meth:`set_prior`), so with no
    temperature change seen the prior stands, and the posterior narrows only as far as the drive's warming and
    the estimates' quality allow. An axis whose bound is 0 is off: no coefficient, whatever the prior."""

    __slots__ = ("_bound_var", "_fit", "_next_s", "_prior_mean", "_prior_var", "_samples")
    _fit: tuple[list[float], ...] | None

    def __init__(self, bound: Sequence[float]) -> None:
        self._bound_var = [s * s for s in bound]  # the configured bound: never more uncertain than that
        self._prior_var = list(self._bound_var)
        self._prior_mean = [0.0] * len(bound)
        # (time s, temperature, offsets, their variances, walk density^2 at the grade, and as the drive showed)
        self._samples: list[tuple[float, float, tuple[float, ...], tuple[float, ...], tuple[float, ...],
                                  tuple[float, ...]]] = []
        self._next_s = -math.inf
        self._fit = None

    def set_prior(self, mean: Sequence[float], sigma: Sequence[float]) -> None:
        """Start from what an earlier drive learnt of this part (its coefficients are the part's, not the
        drive's): each sigma between PRIOR_FLOOR of the configured bound and the bound; an axis whose bound is
        0 stays off."""
        self._prior_mean = [m if b > 0.0 else 0.0 for m, b in zip(mean, self._bound_var, strict=True)]
        self._prior_var = [min(max(s * s, PRIOR_FLOOR**2 * b), b) for s, b in zip(sigma, self._bound_var, strict=True)]
        self._fit = None

    @property
    def bound(self) -> list[float]:
        """The configured bounds of the six coefficients (the prior's sigma with nothing learnt)."""
        return [math.sqrt(v) for v in self._bound_var]

    @property
    def due_s(self) -> float:
        """Drive time (s) from which the next sample is taken."""
        return self._next_s

    def restart(self) -> None:
        """New offsets or new axes (a restart, a remount): the estimates so far no longer line up with the next."""
        self._samples.clear()
        self._next_s = -math.inf
        self._fit = None

    def turn(self, d: np.ndarray) -> None:
        """The body axes turned by ``d`` (new from old; a refined mounting): the estimates so far turn with them,
        each sensor's axes taking the largest of its three variances; the prior turns too, its variances weighted
        by the squared direction cosines (correlations dropped: a turn and its inverse widen an unequal pair)."""
        def widest(v: tuple[float, ...]) -> tuple[float, ...]:
            return (max(v[:3]),) * 3 + (max(v[3:]),) * 3

        for i, (t, temp, off, var, q, q_drive) in enumerate(self._samples):
            ba, bg = d @ np.array(off[:3]), d @ np.array(off[3:])
            self._samples[i] = (t, temp, (*ba.tolist(), *bg.tolist()), widest(var), widest(q), widest(q_drive))
        self._prior_mean, sigma = turned(d, self._prior_mean, [math.sqrt(v) for v in self._prior_var])
        self._prior_var = [v * v for v in sigma]
        self._fit = None

    def add(self, t_s: float, temp_degc: float, offsets: Sequence[float], variances: Sequence[float],
            wander_var_per_s: Sequence[float], aided: bool,
            drive_wander_var_per_s: Sequence[float] | None = None) -> None:
        """The filter's offset estimates and their variances at ``t_s``, taken when ``aided`` (fixes going in) and
        at most every LEARN_EVERY_S; ``wander_var_per_s`` the offsets' random walk squared at the chip's grade,
        ``drive_wander_var_per_s`` the one the drive showed (the filter's own, when larger; default the grade's)."""
        if not aided or t_s < self._next_s or temp_degc - temp_degc != 0.0:
            return
        self._next_s = t_s + LEARN_EVERY_S
        drive = wander_var_per_s if drive_wander_var_per_s is None else drive_wander_var_per_s
        self._samples.append((t_s, temp_degc, tuple(offsets), tuple(variances), tuple(wander_var_per_s),
                              tuple(max(w, d) for w, d in zip(wander_var_per_s, drive, strict=True))))
        if len(self._samples) > LEARN_KEPT:
            del self._samples[0]
        self._fit = None

    def coefficients(self) -> tuple[list[float], list[float]]:
        """Posterior mean and sigma of k per axis, each estimate's error at the chip's grade: what the covariance
        is narrowed by."""
        fit = self._solved()
        return fit[0], fit[1]

    def proven(self) -> tuple[list[float], list[float]]:
        """Posterior mean and sigma of k per axis with the offsets' wander as the drive showed it (the filter's
        walk, when larger than the grade's): what moves the offsets and what is kept for the next drive. A
        wander the grade does not know would otherwise pass for a coefficient over a monotonic warm-up."""
        fit = self._solved()
        return fit[3], fit[4]

    def data_sigma(self) -> list[float]:
        """Per axis, the sigma of k from this drive's estimates alone (infinite before two), the wander as the
        drive showed it: what the drive taught."""
        return self._solved()[5]

    def _solved(self) -> tuple[list[float], ...]:
        if self._fit is None:
            self._fit = (*self._solve_levels(), *self._solve_steps())
        return self._fit

    def _prior_only(self) -> tuple[list[float], list[float], list[float]]:
        return list(self._prior_mean), [math.sqrt(v) for v in self._prior_var], [math.inf] * len(self._prior_var)

    def _posterior(self, sxx: np.ndarray, sxy: np.ndarray) -> tuple[list[float], list[float], list[float]]:
        """k's posterior from the data's normal equations and the prior; and the data's sigma alone."""
        prior, mean = np.array(self._prior_var), np.array(self._prior_mean)
        with np.errstate(divide="ignore", invalid="ignore"):
            prior_info = np.where(prior > 0.0, 1.0 / prior, np.inf)
            precision = sxx + prior_info
            k = np.where(np.isfinite(precision), (sxy + mean * prior_info) / precision, mean)
            data_sigma = np.where(sxx > 0.0, 1.0 / np.sqrt(sxx), np.inf)
        sigma = np.where(np.isfinite(precision), 1.0 / np.sqrt(precision), 0.0)
        return k.tolist(), sigma.tolist(), data_sigma.tolist()

    def _solve_levels(self) -> tuple[list[float], list[float], list[float]]:
        """The offsets' levels regressed on the temperature, at the chip grade's walk: each estimate weighted by
        1 / (its variance + the walk over WANDER_MEMORY_S) and counted for LEARN_EVERY_S / WANDER_MEMORY_S of an
        independent one (estimates minutes apart share most of their error), less where the residuals scatter
        more (reduced chi-square) or run together longer ((1 + rho) / (1 - rho), rho their lag-one
        correlation). Quick to narrow; a walk that runs with a warm-up passes for a slope here, so this only
        narrows the covariance, which then covers k^2 + sigma^2."""
        n_axes = len(self._prior_var)
        if len(self._samples) < 2:
            return self._prior_only()
        temp = np.array([s[1] for s in self._samples])
        b = np.array([s[2] for s in self._samples])
        err = np.array([s[3] for s in self._samples]) + np.array([s[4] for s in self._samples]) * WANDER_MEMORY_S
        w = 1.0 / err
        sw = w.sum(axis=0)
        dt = temp[:, None] - (w * temp[:, None]).sum(axis=0) / sw
        db = b - (w * b).sum(axis=0) / sw
        sxx, sxy = (w * dt * dt).sum(axis=0), (w * dt * db).sum(axis=0)
        inflation = np.full(n_axes, WANDER_MEMORY_S / LEARN_EVERY_S)
        n = len(self._samples)
        if n > 2:
            with np.errstate(divide="ignore", invalid="ignore"):
                k_data = np.where(sxx > 0.0, sxy / sxx, 0.0)
                r = (db - k_data * dt) * np.sqrt(w)
                rr = (r * r).sum(axis=0)
                rho = np.where(rr > 0.0, (r[1:] * r[:-1]).sum(axis=0) / rr, 0.0)
            rho = np.clip(rho, 0.0, MAX_RHO)
            inflation = np.maximum(1.0, rr / (n - 2)) * np.maximum(inflation, (1.0 + rho) / (1.0 - rho))
        return self._posterior(sxx / inflation, sxy / inflation)

    def _solve_steps(self) -> tuple[list[float], list[float], list[float]]:
        """The offsets' steps regressed on the temperature's, at the walk the drive showed (see the class)."""
        if len(self._samples) < 2:
            return self._prior_only()
        t = np.array([s[0] for s in self._samples])
        temp = np.array([s[1] for s in self._samples])
        b = np.array([s[2] for s in self._samples])
        var = np.array([s[3] for s in self._samples])
        q = np.array([s[5] for s in self._samples])
        d_temp = np.diff(temp)[:, None]
        d_b = np.diff(b, axis=0)
        w = 1.0 / (q[1:] * np.diff(t)[:, None] + var[1:] + var[:-1])
        sxx, sxy = (w * d_temp * d_temp).sum(axis=0), (w * d_temp * d_b).sum(axis=0)
        m = len(d_b)
        if m > 1:
            with np.errstate(divide="ignore", invalid="ignore"):
                k_data = np.where(sxx > 0.0, sxy / sxx, 0.0)
            chi2 = (w * (d_b - k_data * d_temp) ** 2).sum(axis=0) / (m - 1)
            inflation = np.maximum(1.0, chi2)
            sxx, sxy = sxx / inflation, sxy / inflation
        return self._posterior(sxx, sxy)

    def applied(self) -> list[float]:
        """The coefficients that move the offsets with the temperature: those proven (:meth:`proven`) beyond
        SIGNIFICANT sigmas, else 0."""
        k, sigma = self.proven()
        return [kj if abs(kj) > SIGNIFICANT * sj else 0.0 for kj, sj in zip(k, sigma, strict=True)]

    def residual_var(self) -> list[float]:
        """Per axis, the variance of the coefficient the covariance must still cover (:meth:`residual_sigma`)."""
        return [r * r for r in self.residual_sigma()]

    def residual_sigma(self) -> list[float]:
        """Per axis, the coefficient the covariance must still cover: the proven sigma where a coefficient is
        applied, else sqrt(k^2 + sigma^2) at the chip's grade, never above the configured bound."""
        k, sigma = self.coefficients()
        kp, sp = self.proven()
        return [min(spj if abs(kpj) > SIGNIFICANT * spj else math.sqrt(sj * sj + kj * kj), math.sqrt(bv))
                for kj, sj, kpj, spj, bv in zip(k, sigma, kp, sp, self._bound_var, strict=True)]


def turned(m: np.ndarray, k: Sequence[float], sigma: Sequence[float]) -> tuple[list[float], list[float]]:
    """Coefficients (accelerometer x y z, gyro x y z) and their sigmas on axes turned by ``m`` (new from old):
    each sensor's three turned as a vector, the variances weighted by the squared direction cosines (the axes
    taken as independent: a turn and its inverse widen an unequal pair)."""
    m2 = m * m
    k_new = [*(m @ np.asarray(k[:3], float)).tolist(), *(m @ np.asarray(k[3:], float)).tolist()]
    sigma_new = [*np.sqrt(m2 @ np.square(sigma[:3])).tolist(), *np.sqrt(m2 @ np.square(sigma[3:])).tolist()]
    return k_new, sigma_new
