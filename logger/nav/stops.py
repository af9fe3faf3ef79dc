"""Stop detection: the IMU is still (small variance of specific force and angular rate over the last second)
and, where the vehicle gives one, the OBD speed reads zero.

The variance thresholds adapt to the installation: a car's idling engine shakes the IMU more than the
datasheet noise, and differently in every car. Each stop that the OBD speed confirms teaches the detector
the variance of standing still here (a slow running mean of its logarithm, so one long stop does not
dominate), and the threshold is a fixed factor above it, bounded on both sides.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from logger.nav.deferred import PENDING_MAX, Deferred

WINDOW_S = 1.0
WINDOW_NS = int(WINDOW_S * 1e9)
THRESHOLD_FACTOR = 9.0  # three standard deviations of the standing-still signal, in variance
LEARN_RATE = 0.05
RESUM_EVERY = 4096


class StopDetector(Deferred):
    def __init__(self, still_accel_mps2: float = 0.05, still_gyro_rps: float = math.radians(0.5)) -> None:
        self.thr_a = still_accel_mps2**2
        self.thr_w = still_gyro_rps**2
        self._ceil_a, self._ceil_w = 4.0 * self.thr_a, 4.0 * self.thr_w
        self._floor_a, self._floor_w = 1e-8, 1e-12
        self._win: deque[tuple[int, float, float, float, float, float, float]] = deque()
        self._sums = (0.0,) * 12  # sum per axis (force x, y, z, rate x, y, z), then sum of squares per axis
        self._var_a = math.inf
        self._var_w = math.inf
        self._dirty = False
        self._adds = 0
        self._pending: list[tuple[int, tuple[float, float, float], tuple[float, float, float]]] = []
        self._log_a: float | None = None
        self._log_w: float | None = None
        self.learned = 0

    def add(self, t_ns: int, f: tuple[float, float, float], w: tuple[float, float, float]) -> None:
        """One sample into the one-second window. Kept until the variances are asked for, then taken in order in one
        loop (running sums: a call per sample cost more than the arithmetic)."""
        pending = self._pending
        pending.append((t_ns, f, w))
        self._dirty = True
        if len(pending) >= PENDING_MAX:
            self.flush_pending()

    def take_pending(self, pending: list[tuple[int, tuple[float, float, float], tuple[float, float, float]]]) -> None:
        win = self._win
        a0, a1, a2, a3, a4, a5, b0, b1, b2, b3, b4, b5 = self._sums
        adds = self._adds
        for t_ns, (fx, fy, fz), (wx, wy, wz) in pending:
            win.append((t_ns, fx, fy, fz, wx, wy, wz))
            a0 += fx
            a1 += fy
            a2 += fz
            a3 += wx
            a4 += wy
            a5 += wz
            b0 += fx * fx
            b1 += fy * fy
            b2 += fz * fz
            b3 += wx * wx
            b4 += wy * wy
            b5 += wz * wz
            limit = t_ns - WINDOW_NS
            while win[0][0] < limit:
                _, ox, oy, oz, ux, uy, uz = win.popleft()
                a0 -= ox
                a1 -= oy
                a2 -= oz
                a3 -= ux
                a4 -= uy
                a5 -= uz
                b0 -= ox * ox
                b1 -= oy * oy
                b2 -= oz * oz
                b3 -= ux * ux
                b4 -= uy * uy
                b5 -= uz * uz
            adds += 1
            if adds >= RESUM_EVERY:  # running sums lose a little to round-off: start them afresh now and then
                self._resum()
                a0, a1, a2, a3, a4, a5, b0, b1, b2, b3, b4, b5 = self._sums
                adds = 0
        self._sums = (a0, a1, a2, a3, a4, a5, b0, b1, b2, b3, b4, b5)
        self._adds = adds

    def add_block(self, t_ns: np.ndarray, f: np.ndarray, w: np.ndarray) -> None:
        """Samples in time order at once (``f``, ``w``: n x 3): the window and sums :meth:`add` would leave, the
        sums taken with numpy."""
        self.flush_pending()
        if len(t_ns) == 0:
            return
        fw = np.concatenate((f, w), axis=1)
        win = self._win
        times = t_ns.tolist()
        win.extend(zip(times, *fw.T.tolist(), strict=True))
        sums = np.concatenate((fw.sum(axis=0), (fw * fw).sum(axis=0)))
        limit = times[-1] - WINDOW_NS
        old = []
        while win[0][0] < limit:
            old.append(win.popleft())
        if old:
            o = np.array(old, dtype=float)[:, 1:]
            sums -= np.concatenate((o.sum(axis=0), (o * o).sum(axis=0)))
        self._sums = tuple((np.array(self._sums) + sums).tolist())
        self._dirty = True
        self._adds += len(times)
        if self._adds >= RESUM_EVERY:
            self._resum()

    def _resum(self) -> None:
        self._adds = 0
        win = self._win
        self._sums = (tuple(sum(r[i + 1] for r in win) for i in range(6))
                      + tuple(sum(r[i + 1] * r[i + 1] for r in win) for i in range(6)))

    def _variances(self) -> None:
        if not self._dirty:
            return
        self._dirty = False
        self.flush_pending()
        n = len(self._win)
        if n < 4:
            self._var_a = self._var_w = math.inf
            return
        s = self._sums
        var = [max(0.0, s[i + 6] / n - (s[i] / n) ** 2) for i in range(6)]
        self._var_a = var[0] + var[1] + var[2]
        self._var_w = var[3] + var[4] + var[5]

    @property
    def var_a(self) -> float:
        """Sum of the three accelerometer axes' variances over the window, (m/s^2)^2."""
        self._variances()
        return self._var_a

    @property
    def var_w(self) -> float:
        """Sum of the three gyro axes' variances over the window, (rad/s)^2."""
        self._variances()
        return self._var_w

    @property
    def still(self) -> bool:
        return self.var_a < self.thr_a and self.var_w < self.thr_w

    def learn(self) -> None:
        """Called while the OBD speed confirms a stop: adapt the thresholds to this vehicle's standstill."""
        if not (0.0 < self.var_a < math.inf and 0.0 < self.var_w < math.inf):
            return
        la, lw = math.log(self.var_a), math.log(self.var_w)
        if self._log_a is None or self._log_w is None:
            self._log_a, self._log_w = la, lw
        else:
            self._log_a += LEARN_RATE * (la - self._log_a)
            self._log_w += LEARN_RATE * (lw - self._log_w)
        self.learned += 1
        self.thr_a = min(self._ceil_a, max(self._floor_a, THRESHOLD_FACTOR * math.exp(self._log_a)))
        self.thr_w = min(self._ceil_w, max(self._floor_w, THRESHOLD_FACTOR * math.exp(self._log_w)))
