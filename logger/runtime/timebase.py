"""The daemon's notion of 'now' and 'wait': the host's clocks, or a simulated drive's scaled ones.

Sampler threads read the monotonic clock and sleep only through a :class:`TimeBase`, so the same threads run
a drive at 60x speed under ``--time-scale 60`` and every ``*_ns`` field is in drive time.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass
class TimeBase:
    monotonic_ns: Callable[[], int] = time.monotonic_ns
    scale: float = 1.0

    def wait(self, event: threading.Event, seconds: float) -> bool:
        """Wait ``seconds`` of drive time, or until ``event`` is set (returns True then)."""
        if seconds <= 0:
            return event.is_set()
        return event.wait(seconds / self.scale)

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds / self.scale)


def host_timebase() -> TimeBase:
    return TimeBase(time.monotonic_ns, 1.0)
