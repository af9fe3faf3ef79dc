"""The daemon's notion of 'now' and 'wait': the host's clocks, or a simulated drive's scaled ones.

Sampler threads read the monotonic clock and sleep only through a :class:`TimeBase`, so the same threads run
a drive at 60x speed under ``--time-scale 60`` and every ``*_ns`` field is in drive time. A simulated drive's
scale may change while it runs (its governor slows it when the daemon falls behind), so ``scale`` is read each
time, waits follow the drive clock, and the threads tell ``late`` how far behind their schedule they ran.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

PACED_STEP_S = 0.05  # longest host wait on a paced drive between looks at its clock


class TimeBase:
    def __init__(self, monotonic_ns: Callable[[], int] = time.monotonic_ns,
                 scale: float | Callable[[], float] = 1.0,
                 late: Callable[[int, int], None] | None = None,
                 pace: Callable[[], dict[str, Any]] | None = None) -> None:
        self.monotonic_ns = monotonic_ns
        self._scale = scale if callable(scale) else (lambda fixed=float(scale): fixed)
        self._late = late
        self._pace = pace

    @property
    def paced(self) -> bool:
        """A simulated drive whose pace follows the daemon: worth measuring lateness for."""
        return self._late is not None

    @property
    def scale(self) -> float:
        """Drive seconds per host second now."""
        return self._scale()

    def late(self, lateness_ns: int, tolerance_ns: int) -> None:
        """A thread ran ``lateness_ns`` of drive time behind a schedule that loses data at ``tolerance_ns``:
        a simulated drive slows down before that happens; the host's own clock cannot, and ignores it."""
        if self._late is not None:
            self._late(lateness_ns, tolerance_ns)

    def pace(self) -> dict[str, Any] | None:
        """How fast a simulated drive runs against its ceiling (None on the host's clock or a fixed scale)."""
        return self._pace() if self._pace is not None else None

    def wait(self, event: threading.Event, seconds: float) -> bool:
        """Wait ``seconds`` of drive time, or until ``event`` is set (returns True then). On a paced drive in short
        host steps, each against the drive clock: a wait begun at real time ends on time when the pace rises."""
        if seconds <= 0:
            return event.is_set()
        if not self.paced:
            return event.wait(seconds / self.scale)
        end = self.monotonic_ns() + round(seconds * 1e9)
        while (left := end - self.monotonic_ns()) > 0:
            if event.wait(min(left / 1e9 / self.scale, PACED_STEP_S)):
                return True
        return event.is_set()

    def wait_until(self, event: threading.Event, t_ns: int) -> bool:
        """Wait until the drive clock reads ``t_ns``, or until ``event`` is set (returns True then)."""
        while (left := t_ns - self.monotonic_ns()) > 0:
            if self.wait(event, left / 1e9):
                return True
        return event.is_set()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.wait(threading.Event(), seconds)


def host_timebase() -> TimeBase:
    return TimeBase(time.monotonic_ns, 1.0)
