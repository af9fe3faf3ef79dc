"""What every sample carries from the clock, and the simplest clock that can give it.

The daemon asks a :class:`StampClock` to turn the monotonic acquisition time of a sample into synchronised
time. The PPS-disciplined clock of this package implements the same protocol; :class:`FreeRunClock` is what a
board without GNSS time has: the system's wall clock at start, carried on by the monotonic clock.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

FREERUN = "freerun"
LOCKED = "locked"
HOLDOVER = "holdover"


@dataclass(frozen=True, slots=True)
class Stamp:
    t_sync_ns: int  # synchronised time, Unix ns UTC
    state: str  # FREERUN, LOCKED or HOLDOVER
    err_ns: int  # bound on |t_sync_ns - true time|
    imu_cnt: int  # the paper's IMU counter (reset by PPS)
    timer_cnt: int  # the paper's timer counter (carries on without PPS)

    def fields(self) -> dict[str, int | str]:
        """The stamp as the record fields every sensor message carries."""
        return {"t_sync_ns": self.t_sync_ns, "sync_state": self.state, "sync_err_ns": self.err_ns,
                "imu_cnt": self.imu_cnt, "timer_cnt": self.timer_cnt}


class StampClock(Protocol):
    def stamp(self, t_mono_ns: int) -> Stamp:
        ...


class FreeRunClock:
    """Unix time = wall clock read once at start + monotonic time elapsed since.

    Reading the wall clock once keeps stamps monotonic when NTP steps the system clock. Its error bound is
    large on purpose: a board without an RTC may boot with a wrong date.
    """

    def __init__(self, monotonic_ns: Callable[[], int] = time.monotonic_ns,
                 wall_ns: Callable[[], int] = time.time_ns, imu_rate_hz: float = 20.0,
                 err_ns: int = 1_000_000_000) -> None:
        self._lock = threading.Lock()
        mono = monotonic_ns()
        self._offset_ns = wall_ns() - mono
        self._mono0 = mono
        self._period_ns = round(1e9 / imu_rate_hz)
        self._err_ns = err_ns

    def stamp(self, t_mono_ns: int) -> Stamp:
        # Without PPS the paper's IMU counter is never reset: the timer counter carries every tick.
        ticks = max(0, (t_mono_ns - self._mono0) // self._period_ns)
        return Stamp(t_mono_ns + self._offset_ns, FREERUN, self._err_ns, 0, int(ticks))
