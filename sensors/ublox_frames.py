"""Framing of the byte stream a u-blox receiver sends: UBX binary, NMEA text and RTCM3, interleaved.

A serial port hands over bytes in arbitrary pieces, a receiver may emit all three protocols on one port,
and a line can be noisy or plugged in mid-message. The framer therefore works incrementally: it keeps
the bytes of an unfinished frame until the rest arrives, and never trusts a length field further than
the protocol allows, so a corrupt header costs a bounded number of bytes instead of a stalled reader.

Checksums and message decoding are done by pyubx2 and pynmeagps, except the few UBX messages of every
epoch, which ``ublox_epoch`` unpacks in one call each under pyubx2's names. RTCM3 frames are checked (CRC-24Q)
and passed on undecoded: they are corrections meant for another receiver, and recognising them keeps
the framer from hunting for sync bytes inside their binary payload.

Whatever cannot be framed is skipped one byte at a time, so a frame that starts inside garbage, or
inside a frame that failed its checksum, is still found.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pynmeagps import NMEAReader
from pynmeagps.nmeahelpers import calc_checksum as nmea_checksum
from pyubx2 import UBXReader

from sensors.ublox_epoch import decode_epoch_message

UBX_SYNC = b"\xb5\x62"
UBX_HEADER_LEN = 6
UBX_MAX_PAYLOAD = 8192
"""Largest payload accepted. The longest regular output (RXM-RAWX with 255 measurements) is 8176 bytes;
anything longer is a corrupt length field, not a message worth waiting for."""

NMEA_MAX_LEN = 128
"""Longest sentence accepted, from '$' to the line feed. NMEA 0183 allows 82 characters; u-blox
high-precision and proprietary sentences run a little longer."""

RTCM3_PREAMBLE = 0xD3
RTCM3_MAX_PAYLOAD = 1023
RTCM3_CHECK_PER_BYTE = 32
RTCM3_CHECK_BURST = 64 * 1024
"""CRC-24Q in Python costs about a millisecond per kilobyte, and every candidate header is checked over the
length it claims: a stream of forged headers ('D3 03 FF' repeated) would cost 50 us per byte, more than a
fast line leaves. Checking is therefore paid from a budget that each byte passing through earns
(``RTCM3_CHECK_PER_BYTE`` bytes of CRC, saved up to ``RTCM3_CHECK_BURST``); real RTCM3 frames never exhaust
it, and a candidate that finds it empty counts as garbage (``rtcm3_unchecked``)."""

KIND_UBX = "UBX"
KIND_NMEA = "NMEA"
KIND_RTCM3 = "RTCM3"


@dataclass(frozen=True, slots=True)
class Frame:
    """One complete frame whose checksum is good.

    ``message`` is the pyubx2 ``UBXMessage`` (or for an epoch's NAV-PVT, NAV-TIMEGPS, NAV-DOP, NAV-EOE and TIM-TP
    a :class:`~sensors.ublox_epoch.UbxEpochMessage` with the same attributes) or pynmeagps ``NMEAMessage``
    decoded from ``raw``, or None for RTCM3 and for well-formed frames the library has no definition for.
    """

    kind: str
    raw: bytes
    message: object | None


def _crc24q_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 16
        for _ in range(8):
            crc <<= 1
            if crc & 0x1000000:
                crc ^= 0x1864CFB
        table.append(crc & 0xFFFFFF)
    return tuple(table)


_CRC24Q = _crc24q_table()


def ubx_fletcher(body: bytes) -> bytes:
    """The UBX checksum (8-bit Fletcher) of class, id, length and payload, computed in numpy.

    Every candidate header in the stream is checked against its checksum, and a forged header claims up to
    8 kB; a Python loop took a millisecond for that, numpy a few microseconds. CK_A is the byte sum and
    CK_B the sum of the running CK_A values, both modulo 256.
    """
    running = np.cumsum(np.frombuffer(body, dtype=np.uint8), dtype=np.uint64)
    if running.size == 0:
        return b"\x00\x00"
    return bytes((int(running[-1]) & 0xFF, int(running.sum()) & 0xFF))


def crc24q(data: bytes) -> int:
    """CRC-24Q (RTCM 10403, Qualcomm polynomial 0x1864CFB) of ``data``."""
    crc = 0
    for byte in data:
        crc = ((crc << 8) & 0xFFFFFF) ^ _CRC24Q[((crc >> 16) ^ byte) & 0xFF]
    return crc


_NEED_MORE = -1
_NOT_A_FRAME = 0


class UbxNmeaFramer:
    """Incremental framer: ``feed(bytes) -> list[Frame]``.

    Counters (never reset, so a caller can difference them):

    - ``frames_ok``: frames with a good checksum (decoded or not),
    - ``bad_checksum``: UBX, NMEA or RTCM3 frames whose checksum failed (their bytes are then
      rescanned and counted as garbage unless a good frame starts inside them),
    - ``garbage_bytes``: bytes that belong to no good frame,
    - ``undecoded``: good frames the decoding library could not turn into a message,
    - ``rtcm3_unchecked``: RTCM3 candidates skipped unchecked because the check budget was spent,
    - ``nmea_without_checksum``: NMEA sentences that came without their ``*hh`` (an old receiver's, from before
      NMEA 2.3 made it mandatory), refused: counted so that the refusal can be named (they count as bad too).

    ``decode_nmea`` False frames and checks NMEA sentences but leaves their ``message`` None (not counted as
    undecoded): for a reader that takes its solutions from UBX and ignores NMEA, as ``GnssDecoder`` does once it
    has seen UBX solutions. Parsing the sentences it would throw away is most of a receiver thread's CPU.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.frames_ok = 0
        self.bad_checksum = 0
        self.garbage_bytes = 0
        self.undecoded = 0
        self.rtcm3_unchecked = 0
        self.nmea_without_checksum = 0
        self.decode_nmea = True
        self._consumed = 0  # bytes of the stream before the buffer
        self._rtcm3_credit = RTCM3_CHECK_BURST
        self._rtcm3_credited_at = 0

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Add bytes; return every frame they complete. Never raises on any input."""
        self._buf += data
        return self._scan(final=False)

    def finish(self) -> list[Frame]:
        """End of stream: frames still hidden inside an unfinished one, the rest counted as garbage."""
        return self._scan(final=True)

    def _scan(self, final: bool) -> list[Frame]:
        frames: list[Frame] = []
        buf = self._buf
        pos = 0
        end = len(buf)
        while pos < end:
            lead = buf[pos]
            if lead == 0xB5:
                size = self._ubx_size(buf, pos, end)
            elif lead == 0x24:  # '$'
                size = self._nmea_size(buf, pos, end)
            elif lead == RTCM3_PREAMBLE:
                size = self._rtcm3_size(buf, pos, end)
            else:
                nxt = self._next_sync(buf, pos + 1, end)
                self.garbage_bytes += nxt - pos
                pos = nxt
                continue
            if size == _NEED_MORE:
                if not final:
                    break
                size = _NOT_A_FRAME  # the stream ended inside it: not a frame after all
            if size == _NOT_A_FRAME:
                self.garbage_bytes += 1
                pos += 1
                continue
            if lead == RTCM3_PREAMBLE and not self._rtcm3_affordable(self._consumed + pos, size):
                self.rtcm3_unchecked += 1
                self.garbage_bytes += 1
                pos += 1
                continue
            raw = bytes(buf[pos : pos + size])
            frame = self._check(raw)
            if frame is None:
                if lead == 0x24 and b"*" not in raw:
                    self.nmea_without_checksum += 1
                self.bad_checksum += 1
                self.garbage_bytes += 1
                pos += 1
                continue
            frames.append(frame)
            self.frames_ok += 1
            pos += size
        del buf[:pos]
        self._consumed += pos
        return frames

    def _rtcm3_affordable(self, at: int, size: int) -> bool:
        """Pay for checking a ``size``-byte RTCM3 candidate at stream offset ``at``; False when broke.

        The credit depends only on the stream's bytes, not on how the port cut them into reads.
        """
        earned = (at - self._rtcm3_credited_at) * RTCM3_CHECK_PER_BYTE
        self._rtcm3_credit = min(RTCM3_CHECK_BURST, self._rtcm3_credit + earned)
        self._rtcm3_credited_at = at
        if self._rtcm3_credit < size:
            return False
        self._rtcm3_credit -= size
        return True

    @staticmethod
    def _next_sync(buf: bytearray, start: int, end: int) -> int:
        """Index of the next byte that could start a frame, or ``end``."""
        best = end
        for lead in (b"\xb5", b"$", b"\xd3"):
            i = buf.find(lead, start, best)
            if i >= 0:
                best = i
        return best

    @staticmethod
    def _ubx_size(buf: bytearray, pos: int, end: int) -> int:
        if end - pos < 2:
            return _NEED_MORE
        if buf[pos + 1] != 0x62:
            return _NOT_A_FRAME
        if end - pos < UBX_HEADER_LEN:
            return _NEED_MORE
        length = buf[pos + 4] | (buf[pos + 5] << 8)
        if length > UBX_MAX_PAYLOAD:
            return _NOT_A_FRAME
        size = UBX_HEADER_LEN + length + 2
        return size if end - pos >= size else _NEED_MORE

    @staticmethod
    def _nmea_size(buf: bytearray, pos: int, end: int) -> int:
        limit = min(end, pos + NMEA_MAX_LEN)
        for i in range(pos + 1, limit):
            c = buf[i]
            if c == 0x0A:  # line feed ends the sentence
                return i + 1 - pos
            if c == 0x0D:
                continue
            if c < 0x20 or c > 0x7E or c == 0x24:
                return _NOT_A_FRAME  # a sentence is printable ASCII; '$' starts the next one
        if limit == pos + NMEA_MAX_LEN:
            return _NOT_A_FRAME
        return _NEED_MORE

    @staticmethod
    def _rtcm3_size(buf: bytearray, pos: int, end: int) -> int:
        if end - pos < 3:
            return _NEED_MORE
        if buf[pos + 1] & 0xFC:
            return _NOT_A_FRAME  # six reserved bits must be zero
        length = ((buf[pos + 1] & 0x03) << 8) | buf[pos + 2]
        size = 3 + length + 3
        return size if end - pos >= size else _NEED_MORE

    def _check(self, raw: bytes) -> Frame | None:
        """The frame if its checksum is good, else None. Decoding failures leave ``message`` None."""
        lead = raw[0]
        if lead == 0xB5:
            if ubx_fletcher(raw[2:-2]) != raw[-2:]:
                return None
            return Frame(KIND_UBX, raw, self._decode_ubx(raw))
        if lead == RTCM3_PREAMBLE:
            if crc24q(raw[:-3]) != int.from_bytes(raw[-3:], "big"):
                return None
            return Frame(KIND_RTCM3, raw, None)
        return self._check_nmea(raw)

    def _check_nmea(self, raw: bytes) -> Frame | None:
        text = raw.rstrip(b"\r\n")
        star = text.rfind(b"*")
        if star < 0 or len(text) - star != 3:
            return None  # u-blox always sends a checksum; without one the line cannot be trusted
        sentence = text.decode("ascii")  # the scanner let only printable ASCII through
        if nmea_checksum(sentence[1:star]) != sentence[star + 1 :].upper():
            return None
        if not self.decode_nmea:
            return Frame(KIND_NMEA, raw, None)
        try:
            message = NMEAReader.parse(sentence)
        except Exception:
            message = None
        if message is None:
            self.undecoded += 1
        return Frame(KIND_NMEA, raw, message)

    def _decode_ubx(self, raw: bytes) -> object | None:
        epoch = decode_epoch_message(raw)  # the messages of every epoch, in one struct call each
        if epoch is not None:
            return epoch
        try:
            return UBXReader.parse(raw)
        except Exception:
            # A message the library has no (or another) definition for: still a frame.
            self.undecoded += 1
            return None
