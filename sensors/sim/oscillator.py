"""The board's crystal: how the board's CLOCK_MONOTONIC runs against the true time of the drive.

A time-sync algorithm is only tested if the clock it disciplines is wrong in the ways a real one is: a
fixed frequency offset of tens of ppm, a temperature coefficient that turns a warming cabin into a drifting
rate, and a slow random walk. The fractional frequency error is drawn on a grid and taken as piecewise
linear in true time, so the board time is its exact integral (piecewise quadratic) and the inverse is the
root of a quadratic: both directions agree to well under a nanosecond, at any time of a long drive.

:class:`OscillatorClock` is the :class:`~sensors.sim.clock.DriveClock` a simulated daemon runs on: the host's
monotonic clock, scaled, stands for the board's, and true drive time is read back through the oscillator,
so the board stamps PPS edges and samples exactly where the models put them.
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from sensors.sim.truth import Trajectory

NS_PER_S = 1_000_000_000


class Oscillator:
    """True drive time <-> board monotonic time, for one seeded crystal.

    ``board_ns(true_ns) = board_start_ns + true_ns + integral of y(t) dt``, with the fractional frequency
    error ``y = offset + tempco * (T - ref) + random walk``, T the ambient temperature at the board. Beyond
    the grid (before 0, after ``duration_s``) the rate of the nearest grid end carries on.
    """

    def __init__(
        self,
        *,
        offset_ppm: float = 30.0,
        tempco_ppm_per_degc: float = 1.0,
        reference_degc: float = 25.0,
        wander_ppm_per_sqrt_s: float = 0.002,
        ambient_degc: Callable[[float], float] | None = None,
        duration_s: float = 3600.0,
        grid_s: float = 1.0,
        board_start_ns: int | None = None,
        seed: int | np.random.Generator = 0,
    ) -> None:
        if not (math.isfinite(duration_s) and duration_s > 0.0):
            raise ValueError("the oscillator needs a finite, positive duration to draw its wander over")
        if grid_s <= 0.0:
            raise ValueError("grid step must be positive")
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        n = math.ceil(duration_s / grid_s) + 1
        self._step_ns = round(grid_s * NS_PER_S)
        t_s = np.arange(n) * (self._step_ns / NS_PER_S)
        temp = np.full(n, reference_degc)
        if ambient_degc is not None:
            temp = np.array([ambient_degc(float(t)) for t in t_s])
        steps = rng.standard_normal(n)
        steps[0] = 0.0
        wander = np.cumsum(steps) * wander_ppm_per_sqrt_s * math.sqrt(grid_s)
        y = (offset_ppm + tempco_ppm_per_degc * (temp - reference_degc) + wander) * 1e-6
        if np.any(y <= -0.5):
            raise ValueError("a frequency error that large would run the clock backwards")
        # Phase deviation (board - true, ns) at the nodes: trapezoids of the piecewise linear y are exact.
        dev = np.concatenate(([0.0], np.cumsum(0.5 * (y[:-1] + y[1:]) * self._step_ns)))
        if board_start_ns is None:
            # A board is up for a while before a drive starts: boot, then waiting for the receiver.
            board_start_ns = int(rng.integers(40 * NS_PER_S, 100 * NS_PER_S))
        self.board_start_ns = int(board_start_ns)
        self.duration_s = (n - 1) * self._step_ns / NS_PER_S
        self._n = n
        self._y = y.tolist()
        self._dev = dev.tolist()
        # true time + deviation at the nodes, relative to the start: increasing, searched by the inverse.
        self._u = (np.arange(n, dtype=np.float64) * self._step_ns + dev).tolist()

    @classmethod
    def for_trajectory(cls, trajectory: Trajectory, *, horizon_s: float = 3600.0, **kwargs: Any) -> Oscillator:
        """A crystal following the trajectory's ambient temperature over the drive (or ``horizon_s``)."""
        duration = trajectory.duration_s if math.isfinite(trajectory.duration_s) else horizon_s
        return cls(ambient_degc=lambda t: trajectory.state(t).ambient_degc, duration_s=duration, **kwargs)

    def ppm(self, true_s: float) -> float:
        """Fractional frequency error at a true time, in ppm (positive: the board clock runs fast)."""
        t_ns = true_s * NS_PER_S
        i, tau = self._cell(t_ns)
        if i < 0:
            return self._y[0] * 1e6
        if i >= self._n - 1:
            return self._y[-1] * 1e6
        return (self._y[i] + (self._y[i + 1] - self._y[i]) * tau / self._step_ns) * 1e6

    def _cell(self, t_ns: float) -> tuple[int, float]:
        i = math.floor(t_ns / self._step_ns)
        if i < 0:
            return -1, t_ns
        if i >= self._n - 1:
            return self._n - 1, t_ns - (self._n - 1) * self._step_ns
        return i, t_ns - i * self._step_ns

    def _deviation_ns(self, true_ns: int) -> float:
        i, tau = self._cell(true_ns)
        if i < 0:
            return self._y[0] * tau
        if i >= self._n - 1:
            return self._dev[-1] + self._y[-1] * tau
        y0 = self._y[i]
        return self._dev[i] + y0 * tau + (self._y[i + 1] - y0) * tau * tau / (2.0 * self._step_ns)

    def board_ns(self, true_ns: int) -> int:
        """The board's CLOCK_MONOTONIC reading at a true drive time."""
        true_ns = int(true_ns)
        return self.board_start_ns + true_ns + round(self._deviation_ns(true_ns))

    def true_ns(self, board_ns: int) -> int:
        """The true drive time at which the board's CLOCK_MONOTONIC reads ``board_ns``."""
        u = int(board_ns) - self.board_start_ns  # = true + deviation(true)
        if u < 0:
            return round(u / (1.0 + self._y[0]))
        j = bisect.bisect_right(self._u, u) - 1
        if j >= self._n - 1:
            base = (self._n - 1) * self._step_ns
            return base + round((u - base - self._dev[-1]) / (1.0 + self._y[-1]))
        base = j * self._step_ns
        # Solve r * (1 + y0) + a * r^2 = c for the offset r into the cell; the stable root form avoids
        # cancellation when a (the change of rate over the cell) is tiny.
        c = (u - base) - self._dev[j]
        y0 = self._y[j]
        a = (self._y[j + 1] - y0) / (2.0 * self._step_ns)
        b = 1.0 + y0
        r = 2.0 * c / (b + math.sqrt(b * b + 4.0 * a * c))
        return base + round(r)


class OscillatorClock:
    """The drive clock of a simulated daemon: the host's monotonic clock, scaled, is the board's.

    At time scale X the board's CLOCK_MONOTONIC advances X ns per host ns from ``oscillator.board_start_ns``;
    true drive time is what the oscillator says that board time corresponds to. With X = 1 and an
    oscillator whose ``board_start_ns`` is the host's monotonic time at start, the board clock is the host's.

    The scale may change while the drive runs (:class:`sensors.sim.governor.Governor` slows the drive when the
    daemon falls behind): board time is then piecewise linear in host time, continuous and never backwards.
    """

    SLEEP_CHUNK_S = 0.05  # longest host sleep: a sleeper notices a new scale within this

    def __init__(self, oscillator: Oscillator, time_scale: float = 1.0,
                 host_monotonic_ns: Callable[[], int] = time.monotonic_ns,
                 host_sleep: Callable[[float], None] = time.sleep) -> None:
        if not time_scale > 0.0:
            raise ValueError("time scale must be positive")
        self.oscillator = oscillator
        self._host_ns = host_monotonic_ns
        self._host_sleep = host_sleep
        # (host ns, board ns, scale) of the current segment, replaced whole under the lock; a reader takes the
        # host time and the segment together, so a change of scale between the two cannot send time back.
        self._segment = (host_monotonic_ns(), oscillator.board_start_ns, float(time_scale))
        self._lock = threading.Lock()
        # Who to tell that a device model is late against its own schedule (the governor, when there is one).
        self.on_late: Callable[[int, int], None] | None = None

    @property
    def time_scale(self) -> float:
        """Board ns per host ns now."""
        return self._segment[2]

    def set_time_scale(self, time_scale: float) -> None:
        """Run at a new scale from now on; the board time so far is kept."""
        if not time_scale > 0.0:
            raise ValueError("time scale must be positive")
        with self._lock:
            host = self._host_ns()
            h0, b0, x = self._segment
            self._segment = (host, b0 + round((host - h0) * x), float(time_scale))

    def monotonic_ns(self) -> int:
        """The board's CLOCK_MONOTONIC now: what the daemon must read for acquisition stamps."""
        with self._lock:
            host = self._host_ns()
            h0, b0, x = self._segment
        return b0 + round((host - h0) * x)

    def now_ns(self) -> int:
        return self.oscillator.true_ns(self.monotonic_ns())

    def late(self, lateness_ns: int, tolerance_ns: int) -> None:
        """A device model ran ``lateness_ns`` of board time behind its schedule, which tolerates ``tolerance_ns``."""
        hook = self.on_late
        if hook is not None:
            hook(lateness_ns, tolerance_ns)

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of true drive time pass (the board clock runs a few ppm off meanwhile). Sleeps in
        short host chunks, so that a drive slowed or sped up meanwhile still wakes the sleeper on time."""
        if seconds <= 0.0:
            return
        target = self.oscillator.board_ns(self.now_ns() + round(seconds * NS_PER_S))
        while True:
            remaining = target - self.monotonic_ns()
            if remaining <= 0:
                return
            host_ns = math.ceil(remaining / self.time_scale)  # at least a host ns: a sleep that always moves on
            self._host_sleep(min(host_ns / NS_PER_S, self.SLEEP_CHUNK_S))
