"""The IMU's noise as the drive shows it: a datasheet figure is a bench's, a car shakes the chip.

The filter's process noise (velocity and angle random walk) starts at the configured densities, from the
datasheet. A car adds vibration (engine, road) and a phone-grade chip is ten times noisier than an MPU-6050;
with the datasheet's figures the filter is too sure of its dead reckoning and refuses the measurements that
would set it right. So the white part of the samples is measured as they come: second differences
x[k] - 2 x[k-1] + x[k-2] take out whatever the vehicle does smoothly (its accelerations and turns change slowly
against the sample rate) and leave the noise, whose variance they carry six times. Averaged over about half a
minute of samples, per sensor over its three axes, the variance per sample times the sample interval is the
random walk's density squared (velocity or angle error variance per second): what the filter's process noise
is. A datasheet's density is one-sided over the Nyquist band, so a chip exactly as noisy as its datasheet
measures 1/sqrt(2) of it here. The filter uses the larger of the two, so the measurement only ever widens what
the datasheet says.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from logger.nav.deferred import PENDING_MAX, BlockKeeper, Deferred

TAU_S = 30.0  # the average's memory, drive time
# A chip measured this many times noisier than its datasheet is not of the datasheet's grade: a car's vibration
# adds less on a bolted board (the simulated MPU-6050 of the matrix's tunnel drive read up to 1.9x while starting
# off, then 1.0x; the simulated phone 6.6x).
CONSUMER_NOISE_RATIO = 3.0
MIN_S = 5.0  # before this much has been seen, the datasheet stands


def consumer_grade(ratio: Sequence[float]) -> bool:
    """Whether measured noise over the configured densities (accelerometer, gyro: ``NavEngine.imu_noise_ratio``)
    says a part CONSUMER_NOISE_RATIO times noisier or more on either: what lets a held stop teach the stop detector
    and what ``logger status`` then says of the IMU."""
    return max(ratio) >= CONSUMER_NOISE_RATIO


class ImuNoiseMonitor(Deferred, BlockKeeper):
    """Running white-noise densities of the accelerometer (m/s^2/sqrt(Hz)) and gyro (rad/s/sqrt(Hz))."""

    __slots__ = ("_a1", "_a2", "_blocks", "_g1", "_g2", "_k", "_pending", "_seen_s", "_var_a", "_var_g")

    def __init__(self) -> None:
        self._a1: tuple[float, float, float] | None = None
        self._a2: tuple[float, float, float] | None = None
        self._g1: tuple[float, float, float] | None = None
        self._g2: tuple[float, float, float] | None = None
        self._var_a = 0.0  # mean over axes of (second difference)^2 / 6
        self._var_g = 0.0
        self._k = 0
        self._seen_s = 0.0
        self._pending: list[tuple[tuple[float, float, float], tuple[float, float, float], float]] = []
        self._blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # blocks not yet taken, oldest first

    @property
    def seen_s(self) -> float:
        """Drive time the average has seen, s."""
        self._take_all()
        return self._seen_s

    def _take_all(self) -> None:
        """Everything kept, in order: blocks come before any single sample kept (:meth:`add` takes them first)."""
        self.take_kept()
        self.flush_pending()

    def add(self, acc: tuple[float, float, float], gyro: tuple[float, float, float], dt: float) -> None:
        """One sample and the interval since the previous one (a gap restarts the differences). Kept until a figure
        is asked for, then taken in order in one loop: a call per sample cost more than the arithmetic."""
        self.take_kept()
        pending = self._pending
        pending.append((acc, gyro, dt))
        if len(pending) >= PENDING_MAX:
            self.flush_pending()

    def take_pending(self, pending: list[tuple[tuple[float, float, float], tuple[float, float, float], float]]) -> None:
        a1, a2, g1, g2 = self._a1, self._a2, self._g1, self._g2
        k, va, vg, seen = self._k, self._var_a, self._var_g, self._seen_s
        for acc, gyro, dt in pending:
            if not 0.0 < dt < 0.5:
                a1 = a2 = g1 = g2 = None
            if a2 is not None and a1 is not None and g1 is not None and g2 is not None:
                x, y, z = acc
                ex, ey, ez = x - 2.0 * a1[0] + a2[0], y - 2.0 * a1[1] + a2[1], z - 2.0 * a1[2] + a2[2]
                x, y, z = gyro
                gx, gy, gz = x - 2.0 * g1[0] + g2[0], y - 2.0 * g1[1] + g2[1], z - 2.0 * g1[2] + g2[2]
                k += 1
                w = max(1.0 / k, dt / TAU_S)
                # variance per sample times the interval: the density squared, whatever the rate
                va += w * ((ex * ex + ey * ey + ez * ez) / 18.0 * dt - va)
                vg += w * ((gx * gx + gy * gy + gz * gz) / 18.0 * dt - vg)
                seen += dt
            a2, a1 = a1, acc
            g2, g1 = g1, gyro
        self._a1, self._a2, self._g1, self._g2 = a1, a2, g1, g2
        self._k, self._var_a, self._var_g, self._seen_s = k, va, vg, seen

    def add_block(self, acc: np.ndarray, gyro: np.ndarray, dt: np.ndarray) -> None:
        """Samples at once (``acc``, ``gyro``: n x 3, ``dt``: the interval before each): what :meth:`add` one by
        one leaves, the running average in closed form (the product of the forgetting factors after each term).
        Kept until a figure is asked for (the filter asks at each covariance step, twice a second) and then taken
        as one block: most of a block's cost is the same whatever its length, and a 1 kHz IMU's run of reads is
        cut into several by the measurements between them."""
        self.flush_pending()
        if len(dt):
            self.keep_block(acc, gyro, dt)

    def take_block(self, acc: np.ndarray, gyro: np.ndarray, dt: np.ndarray) -> None:
        n = len(dt)
        nan = (math.nan,) * 3
        a = np.concatenate((np.array((self._a2 or nan, self._a1 or nan)), acc))
        g = np.concatenate((np.array((self._g2 or nan, self._g1 or nan)), gyro))
        ok = (dt > 0.0) & (dt < 0.5)
        # A sample's second difference needs its own interval and the one before it good (a bad one restarts the
        # differences) and two samples before it.
        valid = ok.copy()
        valid[1:] &= ok[:-1]
        da = a[2:] - 2.0 * a[1:-1] + a[:-2]
        dg = g[2:] - 2.0 * g[1:-1] + g[:-2]
        va, vg = (da * da).sum(axis=1) / 18.0, (dg * dg).sum(axis=1) / 18.0
        valid &= np.isfinite(va) & np.isfinite(vg)
        m = int(valid.sum())
        if m:
            d = dt[valid]
            k = self._k + np.arange(1, m + 1)
            w = np.maximum(1.0 / k, d / TAU_S)
            keep = np.cumprod((1.0 - w)[::-1])[::-1]  # what is left of the value before each term after the rest
            after = np.append(keep[1:], 1.0)
            wa = w * after
            self._var_a = float(keep[0] * self._var_a + (wa * va[valid] * d).sum())
            self._var_g = float(keep[0] * self._var_g + (wa * vg[valid] * d).sum())
            self._k += m
            self._seen_s += float(d.sum())
        last_a, last_g = tuple(acc[-1].tolist()), tuple(gyro[-1].tolist())
        if not ok[-1]:
            self._a2 = self._g2 = None
        elif n >= 2:
            self._a2, self._g2 = tuple(acc[-2].tolist()), tuple(gyro[-2].tolist())
        else:
            self._a2, self._g2 = self._a1, self._g1
        self._a1, self._g1 = last_a, last_g

    def densities(self) -> tuple[float, float] | None:
        """(accelerometer, gyro) white-noise densities measured, None before enough was seen."""
        self._take_all()
        if self._seen_s < MIN_S:
            return None
        return math.sqrt(self._var_a), math.sqrt(self._var_g)


WANDER_EVERY_S = 10.0  # the filter's offset estimate is sampled this often...
WANDER_LAG_S = 35.0  # ... and its change taken from the first sample older than this (about 40 s back)
WANDER_MIN = 4  # changes seen before the wander is used
WANDER_KEPT = 30  # the latest changes kept (five minutes)


class OffsetWander:
    """How fast the gyro's offset wanders, from how the filter's own estimate of it moves while it is aided.

    The estimate follows the true offset (GNSS courses tell it the heading's drift), so its change over some
    40 s is the offset's: (change)^2 / time is the walk's variance per second. With the walk too small for the chip,
    the estimate follows late and the figure reads low; taken as the new walk, the next minutes read closer, so
    it converges from below. A phone-grade gyro wanders tens of times more than the MPU-6050 datasheet's walk,
    and no white-noise figure says so: in a tunnel the heading then drifts far beyond what the filter believes
    (on the simulated phone drive, 318 m off in a 131 s tunnel with a 22 m sigma)."""

    __slots__ = ("_hist", "_next_s", "_q")

    def __init__(self) -> None:
        self._hist: deque[tuple[float, tuple[float, float, float]]] = deque()
        self._q: deque[float] = deque(maxlen=WANDER_KEPT)
        self._next_s = 0.0

    def add(self, t_s: float, offset: tuple[float, float, float], aided: bool) -> None:
        """The filter's gyro offset estimate at ``t_s``; ``aided``: GNSS fixes are going in (not a tunnel)."""
        if t_s < self._next_s:
            return
        self._next_s = t_s + WANDER_EVERY_S
        if not aided:
            self._hist.clear()  # an outage's changes are what the walk let through, not what the gyro did
            return
        self._hist.append((t_s, offset))
        while self._hist and t_s - self._hist[0][0] > WANDER_LAG_S:
            t0, b0 = self._hist.popleft()
            d2 = sum((offset[i] - b0[i]) ** 2 for i in range(3)) / 3.0
            self._q.append(d2 / (t_s - t0))

    def restart(self) -> None:
        """Forget the estimates seen so far (the learnt changes stay): after a new mounting the offset is on other
        axes, and a change across it is the turn, not a wander (a 30 deg remount read as a walk 200 times the
        chip's)."""
        self._hist.clear()

    def walk(self) -> float | None:
        """The offset's random walk, rad/s/sqrt(s), once WANDER_MIN changes were seen: the median of the recent
        ones, since the first minutes hold the estimate's convergence from its start, not the chip's wander."""
        if len(self._q) < WANDER_MIN:
            return None
        q = sorted(self._q)
        return math.sqrt(q[len(q) // 2])
