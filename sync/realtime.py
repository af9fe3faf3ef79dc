"""CLOCK_REALTIME stamps of other processes (gpsd's PPS edges) on the board's CLOCK_MONOTONIC.

The clock of this package works on monotonic edge times; gpsd stamps an edge on the system clock. Linux slews
CLOCK_REALTIME and CLOCK_MONOTONIC alike (NTP's frequency and offset corrections apply to both), so their
difference changes only when the system clock is stepped: a settimeofday, chrony's makestep, a leap second.
:class:`RealtimeMap` samples that difference after every read of the stream that carries the stamps and maps
a stamp with the sample taken after its report arrived. It accepts the result only when the last sample taken
before the edge agrees: then no step fell between the edge and its report, and the mapping is as exact as the
sampling (a few microseconds on a loaded single core, best of three reads each time).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

NS = 1_000_000_000


@dataclass(frozen=True, slots=True)
class OffsetSample:
    """Another clock minus MONOTONIC (REALTIME here; MONOTONIC_RAW in sync.kernel_slew) at ``mono_ns``, known to
    within +-``spread_ns`` (half the read window)."""

    mono_ns: int
    offset_ns: int
    spread_ns: int


def read_offset(monotonic_ns: Callable[[], int], other_ns: Callable[[], int]) -> OffsetSample:
    """One monotonic-other-monotonic window: the other clock's reading at the window's middle."""
    m1 = monotonic_ns()
    r = other_ns()
    m2 = monotonic_ns()
    mid = (m1 + m2) // 2
    return OffsetSample(mid, r - mid, (m2 - m1 + 1) // 2)


class RealtimeMap:
    """Maps CLOCK_REALTIME stamps to the monotonic clock, refusing any a clock step may have crossed."""

    def __init__(self, realtime_ns: Callable[[], int] = time.time_ns,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns, tolerance_ns: int = 20_000,
                 keep: int = 256) -> None:
        self._real = realtime_ns
        self._mono = monotonic_ns
        self.tolerance_ns = tolerance_ns
        self._samples: deque[OffsetSample] = deque(maxlen=keep)
        self.mapped = 0
        self.refused_step = 0  # the system clock was stepped between an edge and its report
        self.refused_unverified = 0  # no sample before the edge (just connected, or a report far too late)

    def sample(self) -> OffsetSample:
        """Read the offset now: the tightest of three monotonic-realtime-monotonic windows."""
        best = min((read_offset(self._mono, self._real) for _ in range(3)), key=lambda s: s.spread_ns)
        self._samples.append(best)
        return best

    def to_monotonic(self, realtime_stamp_ns: int) -> int | None:
        """The monotonic time of a realtime stamp taken before the latest sample, or None when it cannot be
        vouched for (a step in between, or no sample before the stamp)."""
        if not self._samples:
            self.refused_unverified += 1
            return None
        now = self._samples[-1]
        mono = realtime_stamp_ns - now.offset_ns
        if mono > now.mono_ns + now.spread_ns:
            self.refused_step += 1  # a stamp from the future: the clock was stepped back meanwhile
            return None
        before = next((s for s in reversed(self._samples) if s.mono_ns <= mono), None)
        oldest = before if before is not None else self._samples[0]
        if abs(oldest.offset_ns - now.offset_ns) > self.tolerance_ns + oldest.spread_ns + now.spread_ns:
            self.refused_step += 1
            return None
        if before is None:
            self.refused_unverified += 1
            return None
        self.mapped += 1
        return mono
