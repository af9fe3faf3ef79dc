"""u-blox GNSS receiver: epochs decoded from a mixed UBX + NMEA (+ RTCM3) serial stream.

API first; the decoding follows in this module.
"""

from __future__ import annotations

from dataclasses import dataclass

import serial

from sensors.ublox_frames import Frame, UbxNmeaFramer

__all__ = [
    "Frame",
    "GnssDecoder",
    "GnssFix",
    "GnssItem",
    "GnssRead",
    "GnssReceiver",
    "GnssTime",
    "TimePulse",
    "UbxNmeaFramer",
]


@dataclass(frozen=True, slots=True)
class GnssFix:
    """One navigation solution (one epoch) as the receiver reported it."""

    source: str
    itow_ms: int | None
    week: int | None
    time_utc_ns: int | None
    time_valid: bool
    fix_mode: int
    fix_ok: bool
    lat_deg: float | None
    lon_deg: float | None
    height_hae_m: float | None
    height_msl_m: float | None
    vel_ned_mps: tuple[float, float, float] | None
    h_acc_m: float | None
    v_acc_m: float | None
    s_acc_mps: float | None
    num_sv: int | None
    pdop: float | None


@dataclass(frozen=True, slots=True)
class TimePulse:
    """UBX TIM-TP: the time of the NEXT time pulse (PPS edge)."""

    tow_ms: int
    tow_sub_ms: float
    week: int
    qerr_ps: int
    qerr_valid: bool
    time_base: str
    utc_available: bool
    gnss: str | None


@dataclass(frozen=True, slots=True)
class GnssTime:
    """UBX NAV-TIMEGPS / NAV-TIMEUTC: GNSS time, leap seconds and their validity."""

    source: str
    itow_ms: int
    week: int | None
    leap_s: int | None
    time_utc_ns: int | None
    tow_valid: bool
    week_valid: bool
    leap_valid: bool
    utc_valid: bool
    t_acc_ns: int | None


GnssItem = GnssFix | TimePulse | GnssTime


@dataclass(frozen=True, slots=True)
class GnssRead:
    """What one read returned: every byte (for the raw log) and what they decoded to."""

    raw: bytes
    items: list[GnssItem]


class GnssDecoder:
    def push(self, frame: Frame) -> list[GnssItem]:
        raise NotImplementedError

    def flush(self) -> list[GnssItem]:
        raise NotImplementedError


class GnssReceiver:
    def __init__(self, port: serial.Serial) -> None:
        self._port = port

    @classmethod
    def open(cls, path: str, baud: int = 9600) -> GnssReceiver:
        raise NotImplementedError

    def read(self, timeout_s: float) -> GnssRead:
        raise NotImplementedError

    def write(self, data: bytes) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError
