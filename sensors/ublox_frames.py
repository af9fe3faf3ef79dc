"""Framing of a mixed UBX / NMEA / RTCM3 byte stream (API first; implementation follows)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Frame:
    """One complete, checksum-valid frame."""

    kind: str
    raw: bytes
    message: object | None


class UbxNmeaFramer:
    def __init__(self) -> None:
        self.frames_ok = 0
        self.bad_checksum = 0
        self.garbage_bytes = 0

    def feed(self, data: bytes) -> list[Frame]:
        raise NotImplementedError
