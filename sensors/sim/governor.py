"""The pace of a simulated drive: as fast as asked, never faster than the daemon keeps up with.

``--time-scale 60`` is a ceiling, as a robotics simulator's real-time factor is: on a busy or slow host the
daemon's threads wake late, and at 60x a host millisecond is 60 ms of drive, enough to lose IMU samples and to
stamp fixes seconds off. A run that loses data that way measures the host, not the code. The governor reads how
late the daemon's threads and the device models run against their schedules (each report is a lateness and the
lateness its schedule tolerates before data are lost) and, every ``WINDOW_S`` of host time, sets the drive
clock's scale from the worst share seen: above ``SLOW_AT`` it slows the drive, below ``FAST_AT`` it speeds up
towards the ceiling, in between it holds. The drive starts at no more than real time and climbs, so the start
loses nothing either. It never goes below real time (``FLOOR``): a recording is to be as good as one made at
real time, not better, so a host that cannot keep up even then loses data as a board would, and the run says
so at its end. What it achieved is in :meth:`Governor.report`, shown by ``logger status`` and at the end of the
run.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from sensors.sim.oscillator import OscillatorClock

WINDOW_S = 0.25  # host seconds between decisions
SLOW_AT = 0.5  # worst lateness share of its tolerance above which the drive slows
FAST_AT = 0.25  # ... below which it speeds up
PLUNGE_AT = 1.0  # a share at which data were lost: slow hard
RISE, FALL, PLUNGE = 1.1, 0.75, 0.5  # factors on the scale per window
FLOOR = 1.0  # slowest pace: real time (what a board does, no better)


@dataclass(frozen=True)
class PaceReport:
    """The pace of the drive so far, for status and the run's summary."""

    ceiling: float  # the time scale asked for
    now: float  # the scale at this moment
    achieved: float  # board time run over host time since the drive started
    slowest: float  # the lowest scale set since the ramp first reached its limit
    held_back_s: float  # host seconds spent below the ceiling since the ramp first reached its limit

    def as_dict(self) -> dict[str, float]:
        return {"ceiling": self.ceiling, "now": self.now, "achieved": self.achieved, "slowest": self.slowest,
                "held_back_s": self.held_back_s}


class Governor:
    """Sets ``clock``'s time scale within ``[FLOOR, ceiling]`` from the lateness its reporters see."""

    def __init__(self, clock: OscillatorClock, ceiling: float,
                 host_monotonic_ns: Callable[[], int] = time.monotonic_ns) -> None:
        if not ceiling > 0.0:
            raise ValueError("time scale must be positive")
        self.clock = clock
        self.ceiling = float(ceiling)
        self.floor = min(FLOOR, self.ceiling)
        self._host_ns = host_monotonic_ns
        self._worst = 0.0
        self._host0 = host_monotonic_ns()
        self._board0 = clock.monotonic_ns()
        self._ramped = False  # the climb from the start reached the ceiling or was first held back
        self._slowest = self.ceiling
        self._held_back_ns = 0
        self._last_step_ns = self._host0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        clock.set_time_scale(min(self.ceiling, 1.0))
        clock.on_late = self.late

    def late(self, lateness_ns: int, tolerance_ns: int) -> None:
        """One thread or model ran ``lateness_ns`` behind a schedule that loses data at ``tolerance_ns``. Cheap and
        lock-free: a report lost to a race with another is one of many in the window."""
        if tolerance_ns > 0:
            share = lateness_ns / tolerance_ns
            if share > self._worst:
                self._worst = share

    def step(self) -> float:
        """One decision from the window's worst lateness; returns the new scale."""
        worst, self._worst = self._worst, 0.0
        now_ns = self._host_ns()
        x = self.clock.time_scale
        if self._ramped and x < self.ceiling:
            self._held_back_ns += now_ns - self._last_step_ns
        self._last_step_ns = now_ns
        if worst > PLUNGE_AT:
            new = x * PLUNGE
        elif worst > SLOW_AT:
            new = x * FALL
        elif worst < FAST_AT:
            new = x * RISE
        else:
            new = x
        new = min(self.ceiling, max(self.floor, new))
        if new < x or new >= self.ceiling:
            self._ramped = True
        if self._ramped:
            self._slowest = min(self._slowest, new)
        if new != x:
            self.clock.set_time_scale(new)
        return new

    def report(self) -> PaceReport:
        host_s = (self._host_ns() - self._host0) / 1e9
        board_s = (self.clock.monotonic_ns() - self._board0) / 1e9
        now = self.clock.time_scale
        return PaceReport(self.ceiling, now, board_s / host_s if host_s > 0 else now, self._slowest,
                          self._held_back_ns / 1e9)

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="sim-governor", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _run(self) -> None:
        while not self._stop.wait(WINDOW_S):
            self.step()
