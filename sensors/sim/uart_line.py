"""The wire between a serial device model and the host: baud rates and what a mismatch turns bytes into.

A pty carries bytes, not bits, so by itself it would let a host read a receiver at any baud rate. A real
UART at the wrong rate reads the line at the wrong instants and delivers other bytes, NULs for framing
errors, or nothing. Device models re-sample their output through :func:`resample` whenever the host's
termios speed (which pyserial sets on the pty slave) differs from the device's, so a driver that forgets
to follow a baud change sees exactly the garbage it would see on the bench.
"""

from __future__ import annotations

import fcntl
import os
import struct
import termios

STANDARD_BAUDS = (
    1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600,
)

_TERMIOS_TO_BAUD: dict[int, int] = {
    getattr(termios, f"B{b}"): b for b in (
        50, 75, 110, 134, 150, 200, 300, 600, 1200, 1800, 2400, 4800, 9600, 19200, 38400, 57600, 115200,
        230400, 460800, 500000, 576000, 921600, 1000000, 1152000, 1500000, 2000000, 2500000, 3000000,
        3500000, 4000000,
    ) if hasattr(termios, f"B{b}")
}


def termios_baud(code: int) -> int | None:
    """Baud rate of a termios speed code, or None for one outside the table (e.g. BOTHER)."""
    return _TERMIOS_TO_BAUD.get(code)


class HostSide:
    """Our own handle on the pty slave, to see what the host configured and how much it left unread.

    The slave's termios is shared by every file descriptor on it, so the speeds pyserial sets on the
    driver's descriptor are visible here. Re-opened when the port comes back on a new pty.
    """

    def __init__(self, path: str) -> None:
        self._path = path
        self._fd = -1
        self._target = ""

    def _ensure(self) -> int:
        try:
            target = os.path.realpath(self._path, strict=True)
        except OSError:
            self.close()
            return -1
        if target != self._target or self._fd < 0:
            self.close()
            try:
                self._fd = os.open(target, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            except OSError:
                return -1
            self._target = target
        return self._fd

    def speeds(self) -> tuple[int | None, int | None]:
        """(input, output) baud rates the host has set, None where unknown or unplugged."""
        fd = self._ensure()
        if fd < 0:
            return None, None
        try:
            attrs = termios.tcgetattr(fd)
        except termios.error:
            self.close()
            return None, None
        return termios_baud(attrs[4]), termios_baud(attrs[5])

    def unread(self) -> int:
        """Bytes waiting in the host's receive buffer; -1 when the port is gone."""
        fd = self._ensure()
        if fd < 0:
            return -1
        try:
            return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
        except OSError:
            self.close()
            return -1

    def close(self) -> None:
        if self._fd >= 0:
            try:
                os.close(self._fd)
            except OSError:
                pass
        self._fd = -1
        self._target = ""


def resample(data: bytes, tx_baud: int, rx_baud: int | None) -> bytes:
    """What a UART at ``rx_baud`` receives from ``data`` sent 8N1 at ``tx_baud`` on an idle line.

    The receiver waits for a falling edge, checks the start bit half a bit later, samples eight data bits
    and the stop bit in their middles, and then hunts for the next edge. A low stop bit is a framing
    error, which Linux (neither IGNPAR nor PARMRK set, as pyserial leaves it) delivers as a NUL byte.
    Times are kept in integer units of 1 / (2 tx rx) s so long bursts do not drift by rounding.
    """
    if rx_baud is None:
        rx_baud = 0
    if rx_baud == tx_baud:
        return bytes(data)
    if rx_baud <= 0 or not data:
        return b""
    bits: list[int] = []
    for byte in data:
        bits.append(0)
        bits.extend((byte >> i) & 1 for i in range(8))
        bits.append(1)
    n = len(bits)
    tx_bit = 2 * rx_baud  # one tx bit time in the integer unit
    rx_half = tx_baud  # half an rx bit time

    def level(t: int) -> int:
        i = t // tx_bit
        return bits[i] if i < n else 1

    out = bytearray()
    k = 0  # first tx bit index at which an edge may be taken
    while k < n:
        # next 1 -> 0 transition at or after bit k (the line is idle high before the burst)
        while k < n and not (bits[k] == 0 and (k == 0 or bits[k - 1] == 1)):
            k += 1
        if k >= n:
            break
        edge = k * tx_bit
        if level(edge + rx_half) != 0:  # a glitch shorter than half a bit: not a start bit
            k += 1
            continue
        value = 0
        for j in range(8):
            value |= level(edge + (3 + 2 * j) * rx_half) << j
        stop_t = edge + 19 * rx_half
        out.append(value if level(stop_t) == 1 else 0)
        k = -(-stop_t // tx_bit)  # the receiver hunts again from the middle of the stop bit
    return bytes(out)
