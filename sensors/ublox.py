"""u-blox GNSS receiver: the serial driver, :class:`GnssReceiver`.

Framing lives in :mod:`sensors.ublox_frames`, epoch decoding in :mod:`sensors.ublox_decode`, WGS-84 and
GPS time in :mod:`sensors.geodesy`. Their public names are re-exported here, so that
``from sensors.ublox import GnssFix, GnssDecoder, UbxNmeaFramer, ...`` works as it always has.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import serial

from sensors.errors import BusError, DeviceNotFound
from sensors.geodesy import ecef_to_geodetic, ecef_velocity_to_ned, gps_to_unix_ns
from sensors.ublox_decode import GnssDecoder, GnssFix, GnssItem, GnssTime, TimePulse
from sensors.ublox_frames import KIND_UBX, Frame, UbxNmeaFramer

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
    "ecef_to_geodetic",
    "ecef_velocity_to_ned",
    "gps_to_unix_ns",
]


@dataclass(frozen=True, slots=True)
class GnssRead:
    """What one read returned: every byte read (garbage included, for the raw log) and its decoding."""

    raw: bytes
    items: list[GnssItem]
    mark: int = 0  # the receiver's number for this read (GnssReceiver.reads), which the fixes' opened_mark names


class GnssReceiver:
    """The receiver on a serial port: bytes in, decoded items out, every byte kept for the raw log.

    I/O and decoding only: the sampler thread owns timing, stamping and reconnecting. A port that
    goes away raises :class:`~sensors.errors.BusError`; the thread then opens the path again.
    """

    def __init__(self, port: serial.Serial, path: str | None = None) -> None:
        self._port = port
        self.path = path if path is not None else str(getattr(port, "port", "") or "")
        self.framer = UbxNmeaFramer()
        self.decoder = GnssDecoder()
        self.reads = 0  # reads that returned bytes: the read marks of GnssFix.opened_mark
        # Good UBX frames by (class, id) since the port was opened: which messages the receiver still sends (a
        # receiver restarted under the open port comes back without the ones the host's set-up turned on).
        self.ubx_counts: Counter[tuple[int, int]] = Counter()
        self._idle_from: int | None = None  # the caller's time from which nothing was waiting on the line (read)

    @property
    def port(self) -> serial.Serial:
        """The pyserial port the receiver is on (receiver setup talks through it, baud changes included)."""
        return self._port

    @classmethod
    def open(cls, path: str, baud: int = 9600) -> GnssReceiver:
        """Open ``path`` 8N1 without flow control (u-blox UARTs have none); 9600 is the factory rate.

        A missing path raises :class:`~sensors.errors.DeviceNotFound` (unplugged adapter, wrong name),
        any other failure :class:`~sensors.errors.BusError`.
        """
        try:
            port = serial.Serial(path, baudrate=baud, timeout=0.0)
        except (serial.SerialException, OSError) as err:
            if not os.path.exists(path):
                raise DeviceNotFound(f"GNSS receiver: no serial port at {path}") from err
            raise BusError(f"GNSS receiver: cannot open {path}: {_one_line(err)}") from err
        return cls(port, path)

    def read(self, timeout_s: float, settle: Callable[[], None] | None = None,
             now_ns: Callable[[], int] | None = None, quiet_ns: int = 0) -> GnssRead:
        """Wait up to ``timeout_s`` for bytes, take all that are waiting, decode them.

        ``settle``, called once the first byte is in, waits for the rest of the burst (the caller's clock): an
        epoch's messages come back to back, and a read that took each as it came would wake the reader once per
        message here and once per tty flush on a board's UART. Returns an empty read when the receiver stayed
        silent; that is not an error here.

        ``now_ns`` (the caller's clock) tells the decoder whether the line was quiet before this read: nothing was
        waiting, and the first byte came ``quiet_ns`` or more after the reader began to wait for it (less the line
        time of what came in while it woke up). A receiver's burst comes back to back, so such a read begins a
        burst (GnssDecoder.read_quiet); without a clock, not known.
        """
        timeout_s = max(0.0, timeout_s)  # a negative wait means 'do not wait', not an error
        try:
            if self._port.timeout != timeout_s:
                self._port.timeout = timeout_s
            if now_ns is not None:
                if self._port.in_waiting:
                    self._idle_from = None
                elif self._idle_from is None:
                    self._idle_from = now_ns()  # nothing waiting since (across reads that timed out)
            data = self._port.read(1)
            quiet: bool | None = None
            if now_ns is not None and data:
                # Bytes come in while a late reader wakes up (another thread holding the interpreter, a busy core):
                # the line's quiet ended that many byte times before the reader saw its first byte.
                baud = getattr(self._port, "baudrate", None) or 9600
                late_ns = self._port.in_waiting * 10_000_000_000 // baud  # 8N1: ten bits a byte
                quiet = self._idle_from is not None and now_ns() - self._idle_from - late_ns >= quiet_ns
                self._idle_from = None
            if data:
                if settle is not None:
                    settle()
                waiting = self._port.in_waiting
                if waiting:
                    data += self._port.read(waiting)
        except (serial.SerialException, OSError) as err:
            raise BusError(f"GNSS receiver on {self.path}: serial port lost: {_one_line(err)}") from err
        items: list[GnssItem] = []
        if data:
            # Each read its number: an epoch's fix names the read its first message came in (GnssFix.opened_mark),
            # which the caller dated (GnssRead.mark is this one).
            self.decoder.read_mark = self.reads = self.reads + 1
            self.decoder.read_quiet = quiet
            self.framer.decode_nmea = not self.decoder.ignores_nmea  # what the decoder would discard is not parsed
            for frame in self.framer.feed(data):
                if frame.kind == KIND_UBX:
                    self.ubx_counts[frame.raw[2], frame.raw[3]] += 1
                items += self.decoder.push(frame)
        return GnssRead(raw=bytes(data), items=items, mark=self.reads)

    def write(self, data: bytes) -> None:
        """Send bytes (UBX configuration) to the receiver."""
        try:
            self._port.write(data)
            self._port.flush()
        except (serial.SerialException, OSError) as err:
            raise BusError(f"GNSS receiver on {self.path}: write failed: {_one_line(err)}") from err

    def close(self) -> None:
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass

    def __enter__(self) -> GnssReceiver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__
