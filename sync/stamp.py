"""What every sample carries from the clock, and the simplest clock that can give it.

The daemon asks a :class:`StampClock` to turn the monotonic acquisition time of a sample into synchronised
time. The PPS-disciplined clock of this package implements the same protocol; :class:`FreeRunClock` is what a
board without GNSS time has: the system's wall clock at start, carried on by the monotonic clock.
"""

from __future__ import annotations

import calendar
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from sync.chrony_sock import ChronySock
from sync.inputs import FixEpoch, TimeAnnouncement

FREERUN = "freerun"
# A free-running stamp's bound when the system clock was not synchronised at start: none the logger can stand
# behind. A board without RTC or network boots at the time it last saved (days or months behind) or at any date,
# so a fixed bound of seconds would be a claim; 2^62 ns (146 years) says "no bound" in an integer field.
NO_BOUND_NS = 2**62
# No time before this (2020-01-01 UTC) is a real one here: a receiver's is a GPS week rollover or no date yet (the
# clock does not pair it), a stamp's is the board's own clock before any time was known (an image's 1970 or build
# date), which `logger info` leaves out of a file's span.
FLOOR_YEAR = 2020
GNSS_TIME_FLOOR_NS = calendar.timegm((FLOOR_YEAR, 1, 1, 0, 0, 0)) * 1_000_000_000
LOCKED = "locked"
HOLDOVER = "holdover"


@dataclass(frozen=True, slots=True)
class Stamp:
    t_sync_ns: int  # synchronised time, Unix ns UTC
    state: str  # FREERUN, LOCKED or HOLDOVER
    err_ns: int  # bound on |t_sync_ns - true time|
    imu_cnt: int  # the paper's IMU counter (reset by PPS)
    timer_cnt: int  # the paper's timer counter (carries on without PPS)


@dataclass(frozen=True, slots=True)
class Stamps:
    """The stamps of several samples (a FIFO read) as columns, oldest first: what an ``/imu/batch`` record holds."""

    t_sync_ns: list[int]
    state: list[str]
    err_ns: list[int]
    imu_cnt: list[int]
    timer_cnt: list[int]

    @classmethod
    def of(cls, stamps: Sequence[Stamp]) -> Stamps:
        return cls([s.t_sync_ns for s in stamps], [s.state for s in stamps], [s.err_ns for s in stamps],
                   [s.imu_cnt for s in stamps], [s.timer_cnt for s in stamps])


@dataclass(frozen=True, slots=True)
class TrackingReport:
    """The clock's state as ``chronyc tracking`` shows it, in the units of the names (``/sync``, ``logger status``)."""

    t_mono_ns: int  # when, on the board's monotonic clock
    state: str  # FREERUN, LOCKED or HOLDOVER
    offset_ns: int | None  # at the last PPS edge, published time minus the edge's GNSS time
    freq_ppm: float | None  # the board clock's rate error (positive: it runs fast)
    skew_ppm: float | None  # uncertainty of freq_ppm
    rms_ns: float | None  # RMS of the regression residuals
    err_ns: int  # current error bound of stamps
    since_edge_s: float | None  # since the last PPS edge used
    samples: int  # edges in the regression
    tempco_ppm_per_degc: float | None  # learned temperature coefficient of the board clock
    edges: int  # PPS edges seen since start
    rejected: int  # edges or time messages refused by the pairing checks
    relocks: int  # returns from holdover to locked


class StampClock(ABC):
    """What the daemon asks of a clock: a stamp for a monotonic time, and what it may tell the clock.

    The whole contract is here, its optional parts with their defaults, as python-can's ``BusABC`` does: a clock
    that learns nothing from PPS edges or time messages ignores them, one with nothing to persist saves nothing,
    and every clock can report its state. Inputs arrive from any thread.
    """

    # What a clock may have found or feed, for the status: a pairing it found wrong lately, or GNSS time it would not
    # pair (board ns, what), and the chrony socket it hands its samples to (its counts and its last error). None for
    # a clock without them.
    last_mislabel: tuple[int, str] | None = None
    chrony: ChronySock | None = None

    def time_doubt(self) -> str | None:
        """What the receiver says now that keeps the clock's time from being trusted to the second (the status's
        clock problem while it lasts); None when nothing does."""
        return None

    @abstractmethod
    def stamp(self, t_mono_ns: int) -> Stamp:
        """The synchronised time, state and error bound of the instant ``t_mono_ns`` of the board's clock."""

    def stamp_many(self, times_ns: Sequence[int]) -> Stamps:
        """The stamps of several instants (a FIFO read's samples, oldest first): as :meth:`stamp` for each; a clock
        may do it cheaper, at the same values."""
        return Stamps.of([self.stamp(t) for t in times_ns])

    def on_imu_sample(self, t_mono_ns: int, temp_degc: float | None) -> None:  # noqa: B027 - optional input
        """An IMU sample was taken (the paper's counters; the die temperature)."""

    def on_imu_samples(self, times_ns: Sequence[int], temp_degc: float | None) -> None:
        """Several IMU samples (a FIFO read, oldest first) with one die temperature: as :meth:`on_imu_sample` for
        each, the temperature told with the last."""
        for t in times_ns[:-1]:
            self.on_imu_sample(t, None)
        if times_ns:
            self.on_imu_sample(times_ns[-1], temp_degc)

    def on_edge(self, t_mono_ns: int, gnss_time_ns: int | None = None) -> None:  # noqa: B027 - optional input
        """A PPS edge, at its kernel time stamp; ``gnss_time_ns`` when the source names its second."""

    def on_announcement(self, announcement: TimeAnnouncement, t_mono_ns: int) -> None:  # noqa: B027
        """The receiver announced the GNSS time of its next pulse."""

    def on_fix_epoch(self, epoch: FixEpoch, t_mono_ns: int) -> None:  # noqa: B027 - optional input
        """A navigation solution with a valid time arrived."""

    def report(self, now_ns: int) -> TrackingReport | None:
        """What ``chronyc tracking`` would show, for ``/sync`` and ``logger status``; None for a clock that tracks
        nothing (its stamps' state and bound are all there is to say)."""
        return None

    def save(self) -> None:  # noqa: B027 - optional: nothing to persist by default
        """Persist what should survive a restart (a frequency, a mapping); called when the daemon stops."""

    def recheck_wall(self, now_ns: int) -> None:  # noqa: B027 - optional: a clock without a wall clock to check
        """Look again whether the system clock became synchronised (the daemon's health loop, once a second)."""


class FreeRunClock(StampClock):
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
