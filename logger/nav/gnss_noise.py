"""GNSS measurement noise from the receiver's own accuracy figures, with its degraded part taken as correlated.

A receiver's accuracy figure (u-blox ``hAcc``, ``vAcc``, ``sAcc``) is the spread of its error, not how long
that error lasts. In open sky its floor is the receiver's own (atmosphere, orbits, code noise); in a street
canyon it grows with multipath and reflected signals, and those last as long as the same facades are in the
way: seconds, many epochs at 1 Hz. A filter that takes such epochs as independent adds their shared error up
instead of averaging it out (ten epochs off by the same 2 m pull as hard as one epoch good to 0.6 m).

So the variance a fix reports is split into the receiver's floor, the lowest it reported recently, and the
excess over it; the excess is multiplied by (1 + rho) / (1 - rho), rho = exp(-dt / tau), the factor by which a
first-order correlated error sampled every dt shrinks more slowly under averaging than a white one
(``gnss_multipath_corr_s`` = tau). In open sky the excess is near zero and the receiver's figure is used as
is; a canyon's fixes count, together, about as much as one fix per correlation time.
"""

from __future__ import annotations

import math
from collections import deque

FLOOR_WINDOW = 300  # fixes (5 min at 1 Hz) over which the receiver's floor is the lowest figure it gave
MAX_GAP_S = 10.0  # epochs further apart than this are taken as independent


class RunningMin:
    """Minimum of the last ``window`` values, amortised O(1) (a monotonic queue)."""

    def __init__(self, window: int = FLOOR_WINDOW) -> None:
        self.window = window
        self._q: deque[tuple[int, float]] = deque()
        self._i = 0

    def add(self, value: float) -> float:
        q = self._q
        while q and q[-1][1] >= value:
            q.pop()
        q.append((self._i, value))
        while q[0][0] <= self._i - self.window:
            q.popleft()
        self._i += 1
        return q[0][1]


class CorrelatedGnssNoise:
    """Per-fix variances for position (per axis, from hAcc and vAcc) and velocity (from sAcc)."""

    def __init__(self, corr_s: float) -> None:
        self.corr_s = corr_s
        self._floors = (RunningMin(), RunningMin(), RunningMin())
        self._t_last_ns: int | None = None

    def factor(self, t_ns: int) -> float:
        """How much more slowly a correlated error averages out than a white one at this fix spacing."""
        last, self._t_last_ns = self._t_last_ns, t_ns
        if self.corr_s <= 0.0 or last is None:
            return 1.0
        dt = (t_ns - last) / 1e9
        if not 0.0 < dt < MAX_GAP_S:
            return 1.0
        rho = math.exp(-dt / self.corr_s)
        return (1.0 + rho) / (1.0 - rho)

    def sigmas(self, t_ns: int, h_acc: float, v_acc: float, s_acc: float) -> tuple[float, float, float]:
        """1-sigma horizontal per axis, vertical and speed, with the excess over the floor widened."""
        c = self.factor(t_ns)
        out = []
        for value, floor in zip((h_acc, v_acc, s_acc), self._floors, strict=True):
            low = floor.add(value)
            out.append(math.sqrt(low * low + c * (value * value - low * low)))
        return out[0] / math.sqrt(2.0), out[1], out[2]
