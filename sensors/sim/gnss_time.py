"""GPS time of a simulated drive, shared by the receiver model and the PPS line model.

The receiver stamps its solutions and announces its time pulses in GPS time, while every device model
runs on the true drive time of a :class:`~sensors.sim.clock.DriveClock`. Both models must agree on the
mapping between the two, down to the nanosecond, or a test of the time synchronisation would measure the
simulation instead of the logger: hence one small object that both are handed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

import numpy as np

NS_PER_S = 1_000_000_000
NS_PER_MS = 1_000_000
SECONDS_PER_WEEK = 604_800
GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)
UNIX_NS_AT_GPS_EPOCH = 315_964_800 * NS_PER_S
GPS_UTC_LEAP_S = 18  # GPS - UTC since 2017-01-01, still in force


def _delta_ns(delta: timedelta) -> int:
    return (delta.days * 86_400 + delta.seconds) * NS_PER_S + delta.microseconds * 1_000


@dataclass(frozen=True, slots=True)
class GnssTimeline:
    """Maps true drive time (ns since the drive started) to GPS and UTC time.

    ``start_utc`` is the UTC instant at drive time zero; ``leap_s`` the GPS-UTC offset in force, which a
    receiver learns from the navigation message. A start before 2017 needs the leap second of its day.
    """

    start_utc: datetime = datetime(2018, 3, 14, 1, 30, tzinfo=UTC)
    leap_s: int = GPS_UTC_LEAP_S
    start_gps_ns: int = field(init=False)

    def __post_init__(self) -> None:
        if self.start_utc.tzinfo is None:
            raise ValueError("the start epoch must be a timezone-aware UTC datetime")
        start = _delta_ns(self.start_utc - GPS_EPOCH) + self.leap_s * NS_PER_S
        if start < 0:
            raise ValueError("the start epoch lies before the GPS epoch (1980-01-06)")
        object.__setattr__(self, "start_gps_ns", start)

    def gps_ns(self, drive_ns: int) -> int:
        """Nanoseconds of GPS time since the GPS epoch at a drive time."""
        return self.start_gps_ns + int(drive_ns)

    def drive_ns(self, gps_ns: int) -> int:
        return int(gps_ns) - self.start_gps_ns

    def utc_unix_ns(self, gps_ns: int) -> int:
        """Unix nanoseconds (UTC) of a GPS instant: what a log's wall-clock stamp should read."""
        return int(gps_ns) - self.leap_s * NS_PER_S + UNIX_NS_AT_GPS_EPOCH

    def utc_datetime(self, gps_ns: int) -> tuple[datetime, int]:
        """The UTC calendar second of a GPS instant and the nanoseconds past it."""
        utc_ns = int(gps_ns) - self.leap_s * NS_PER_S
        seconds, nano = divmod(utc_ns, NS_PER_S)
        return GPS_EPOCH + timedelta(seconds=seconds), nano

    @staticmethod
    def week_tow(gps_ns: int) -> tuple[int, int]:
        """GPS week number and nanoseconds into the week."""
        week, tow_ns = divmod(int(gps_ns), SECONDS_PER_WEEK * NS_PER_S)
        return week, tow_ns

    def pulse_drive_ns(self, after_drive_ns: int) -> int:
        """Drive time of the first whole GPS second strictly after ``after_drive_ns``: the next PPS edge.

        A u-blox time pulse aligned to UTC falls on the same instants, the leap offset being whole seconds.
        """
        gps = self.gps_ns(after_drive_ns)
        return self.drive_ns((gps // NS_PER_S + 1) * NS_PER_S)


@dataclass(frozen=True, slots=True)
class PulseQuantisation:
    """The saw-tooth error of a u-blox time pulse, reported ahead of each pulse as TIM-TP qErr.

    The receiver can only put its pulse on an edge of its 48 MHz core clock (a 20.8 ns grid), and that
    clock runs off a free TCXO: the grid slides past the true second by the oscillator's offset each second,
    so the error is a saw-tooth, not noise. The convention measured on an F9T (A. Wallin, 2019): the pulse
    leaves at the ideal second minus qErr, so adding qErr to a measured edge gives the ideal second.
    """

    tick_ns: float = 1e9 / 48e6
    oscillator_offset_ppb: float = 287.0
    phase0: float = 0.31

    @classmethod
    def from_seed(cls, seed: int | np.random.Generator) -> PulseQuantisation:
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        # A TCXO within +-0.5 ppm of nominal, which is what u-blox modules specify.
        return cls(oscillator_offset_ppb=float(rng.uniform(-500.0, 500.0)), phase0=float(rng.uniform(0.0, 1.0)))

    def edge_offset_ns(self, gps_second: int) -> float:
        """Actual minus ideal time of the pulse at a whole GPS second, in ns (within +-tick/2)."""
        slip_ticks = self.oscillator_offset_ppb * 1e-9 * NS_PER_S / self.tick_ns  # grid slip per second
        frac = math.fmod(self.phase0 + int(gps_second) * (slip_ticks % 1.0), 1.0)
        return (frac - 0.5) * self.tick_ns

    def qerr_ps(self, gps_second: int) -> int:
        """The qErr field of the TIM-TP that announces this pulse (ps)."""
        return round(-self.edge_offset_ns(gps_second) * 1000.0)
