"""systemd's service notification protocol (sd_notify), spoken directly: no libsystemd binding on the board.

A ``Type=notify`` unit gives the service a datagram socket in ``NOTIFY_SOCKET``; each message is one datagram
of newline-separated ``KEY=VALUE`` assignments (``READY=1``, ``WATCHDOG=1``, ``STOPPING=1``, ``STATUS=...``).
A path starting with ``@`` names a socket in the abstract namespace (the ``@`` stands for a leading NUL byte).
The watchdog is armed when ``WATCHDOG_USEC`` is set and ``WATCHDOG_PID``, if present, is this process: a
child started by the service must not ping on its behalf.

Without ``NOTIFY_SOCKET`` (a terminal, a test, another init) every call is a cheap no-op, so the daemon
talks the same way everywhere. A failed send is never fatal: logging must go on even if systemd cannot
hear it, and systemd's own watchdog timeout is what catches a service that cannot report.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Mapping

log = logging.getLogger(__name__)

STATUS_MAX = 1024  # systemctl status shows one line; a long STATUS is cut rather than sent as a huge datagram


def _address(value: str) -> str | bytes | None:
    """The socket address of a ``NOTIFY_SOCKET`` value, or None for a kind this module does not speak."""
    if value.startswith("/"):
        return value
    if value.startswith("@") and len(value) > 1:
        return b"\0" + value[1:].encode()  # abstract namespace: no file, the name lives in the kernel
    return None  # "vsock:..." (systemd 254+, virtual machines) or garbage: not ours to guess


class Notifier:
    """Sends notifications to the service manager named in the environment (``from_env``)."""

    def __init__(self, socket_path: str | None, watchdog_usec: int | None = None) -> None:
        self.address = _address(socket_path) if socket_path else None
        if socket_path and self.address is None:
            log.warning("NOTIFY_SOCKET=%r is not a Unix socket address; not notifying", socket_path)
        self.watchdog_usec = watchdog_usec if watchdog_usec and watchdog_usec > 0 else None
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._failed_once = False

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None, pid: int | None = None) -> Notifier:
        """Read ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` as sd_notify(3) and sd_watchdog_enabled(3)."""
        env = os.environ if env is None else env
        pid = os.getpid() if pid is None else pid
        usec: int | None = None
        raw = env.get("WATCHDOG_USEC", "")
        if raw.isdigit():
            owner = env.get("WATCHDOG_PID", "")
            if not owner or (owner.isdigit() and int(owner) == pid):
                usec = int(raw)
        return cls(env.get("NOTIFY_SOCKET") or None, usec)

    @property
    def enabled(self) -> bool:
        return self.address is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """How often to ping: half the watchdog timeout, as sd_watchdog_enabled(3) recommends; None if unarmed."""
        return self.watchdog_usec / 2e6 if self.watchdog_usec else None

    def send(self, **fields: str | int) -> bool:
        """Send one datagram of ``KEY=VALUE`` lines; True when it left. Keys are upper-cased, values one line."""
        if self.address is None:
            return False
        lines = []
        for key, value in fields.items():
            text = " ".join(str(value).split())  # a newline would start a new assignment
            if key.upper() == "STATUS":
                text = text[:STATUS_MAX]
            lines.append(f"{key.upper()}={text}")
        data = "\n".join(lines).encode()
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.sendto(data, self.address)
                return True
            except OSError as exc:
                if not self._failed_once:  # once: a dead manager socket would otherwise log every second
                    log.warning("cannot notify systemd on %s: %s", self.address, exc.strerror or exc)
                    self._failed_once = True
                return False

    def ready(self, status: str | None = None) -> bool:
        return self.send(READY=1, **({"STATUS": status} if status else {}))

    def watchdog(self) -> bool:
        return self.send(WATCHDOG=1)

    def stopping(self, status: str | None = None) -> bool:
        return self.send(STOPPING=1, **({"STATUS": status} if status else {}))

    def status(self, text: str) -> bool:
        return self.send(STATUS=text)

    def extend_timeout(self, seconds: float) -> bool:
        """Ask for more start/stop time (a long recovery of a crashed file at start)."""
        return self.send(EXTEND_TIMEOUT_USEC=int(seconds * 1e6))

    def close(self) -> None:
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None
