"""Hand PPS samples to chrony through its SOCK refclock, so the system clock is disciplined too.

While the logger owns the GPIO line, chrony cannot read the PPS itself. chronyd with
``refclock SOCK /run/chrony.vehicle-logger.sock refid GPS`` listens on a datagram socket for ``struct sock_sample``
(chrony's refclock_sock.c): the system time of the event, the offset of true time from it, a pulse flag, leap
status and a magic number. Each accepted edge becomes one such sample; a missing or restarted chronyd only costs
the samples sent meanwhile.
"""

from __future__ import annotations

import logging
import socket
import struct
import time

log = logging.getLogger(__name__)

SOCK_MAGIC = 0x534F434B
# struct timeval (long tv_sec, long tv_usec), double offset, int pulse, int leap, int _pad, int magic: native layout.
SAMPLE = struct.Struct("@lldiiii")
LEAP_NORMAL = 0


def pack_sample(system_ns: int, offset_s: float, pulse: bool = False, leap: int = LEAP_NORMAL) -> bytes:
    sec, ns = divmod(system_ns, 1_000_000_000)
    return SAMPLE.pack(sec, ns // 1000, offset_s, int(pulse), leap, 0, SOCK_MAGIC)


class ChronySock:
    def __init__(self, path: str) -> None:
        self.path = path
        self.sent = 0
        self.failed = 0
        # Why the last send failed, while it is the last send (a later one that worked clears it): what the status
        # shows, since a journal line once per outage was all an operator had (chrony's clock unfed for hours).
        self.error: str | None = None
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._warned = False

    def send_edge(self, edge_mono_ns: int, edge_true_unix_ns: int) -> None:
        """One PPS edge: its system time (realtime clock, mapped from the monotonic stamp) and the true offset."""
        real_now, mono_now = time.clock_gettime_ns(time.CLOCK_REALTIME), time.monotonic_ns()
        system_ns = real_now - (mono_now - edge_mono_ns)
        try:
            self._sock.sendto(pack_sample(system_ns, (edge_true_unix_ns - system_ns) / 1e9), self.path)
            self.sent += 1
            self._warned = False
            self.error = None
        except OSError as exc:
            self.failed += 1
            self.error = exc.strerror or str(exc)
            if not self._warned:
                if isinstance(exc, PermissionError):  # chronyd made it root's: the unit drop-in gives it our group
                    log.warning("chrony SOCK refclock %s refuses this user (%s): chronyd makes it root's; "
                                "systemd/chrony.service.d/vehicle-logger.conf gives it the logger's group",
                                self.path, exc.strerror or exc)
                else:
                    log.warning("chrony SOCK refclock %s not reachable (%s): is chronyd running with it "
                                "configured?", self.path, exc.strerror or exc)
                self._warned = True

    def section(self) -> dict[str, object]:
        """For ``logger status``: the socket, samples sent and failed, and why the last one failed if it did."""
        return {"path": self.path, "sent": self.sent, "failed": self.failed, "error": self.error}

    def close(self) -> None:
        self._sock.close()
