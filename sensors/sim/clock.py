"""Clocks of the simulated drive.

Device models ask a :class:`DriveClock` what the true time of the drive is, so the same model serves a
test that steps time by hand and a daemon that runs the drive at a time scale. Drivers that must wait
(a conversion time, a slow adapter) take a ``sleep`` callable; handing them ``clock.sleep`` keeps a test
deterministic and lets a scaled drive wait scaled times.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol

NS_PER_S = 1_000_000_000


class DriveClock(Protocol):
    """True time of the simulated drive."""

    def now_ns(self) -> int:
        """Nanoseconds of true time since the drive started."""
        ...

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of drive time pass."""
        ...

    def late(self, lateness_ns: int, tolerance_ns: int) -> None:
        """A model ran ``lateness_ns`` behind its schedule, which loses data at ``tolerance_ns``: a paced drive
        slows down on it (:mod:`sensors.sim.governor`); a clock that is not paced ignores it."""
        ...


class ManualClock:
    """A clock that moves only when told to: ``sleep`` advances it instantly, so tests never wait."""

    def __init__(self, start_ns: int = 0) -> None:
        self._ns = int(start_ns)
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        with self._lock:
            return self._ns

    def advance(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError("a clock does not run backwards")
        with self._lock:
            self._ns += round(seconds * NS_PER_S)

    def sleep(self, seconds: float) -> None:
        self.advance(max(0.0, seconds))

    def late(self, lateness_ns: int, tolerance_ns: int) -> None:
        """Nothing to slow: this clock moves only when told to."""


class ScaledClock:
    """Drive time running ``time_scale`` times faster than the host's monotonic clock."""

    def __init__(self, time_scale: float = 1.0, start_ns: int = 0) -> None:
        if time_scale <= 0:
            raise ValueError("time scale must be positive")
        self.time_scale = float(time_scale)
        self._origin_ns = time.monotonic_ns()
        self._start_ns = int(start_ns)

    def now_ns(self) -> int:
        return self._start_ns + round((time.monotonic_ns() - self._origin_ns) * self.time_scale)

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds / self.time_scale)

    def late(self, lateness_ns: int, tolerance_ns: int) -> None:
        """A fixed scale: lateness is the test's to measure, not this clock's to act on."""
