"""The status socket: the daemon answers each connection with one JSON snapshot and closes it.

No network listener, and the socket is readable by the daemon's group only (mode 0660). The server runs in the
daemon (:class:`StatusServer`); ``logger status`` and the tools read it with :func:`fetch`. The verdict's exit
codes are part of the protocol, so scripts read the same numbers whoever asks.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

EXIT = {"ok": 0, "degraded": 1, "critical": 2}
NOT_RUNNING = 3
MAX_REPLY = 4 << 20


class StatusServer(threading.Thread):
    """Serves ``snapshot()`` as JSON to every client that connects."""

    def __init__(self, path: str | os.PathLike[str], snapshot: Callable[[], dict[str, Any]],
                 mode: int = 0o660) -> None:
        super().__init__(name="status", daemon=True)
        self.path = Path(path)
        self.snapshot = snapshot
        self._halt = threading.Event()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists() or self.path.is_symlink():
            self.path.unlink()  # a socket left by a crashed daemon
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o117)  # never world-accessible, not even between bind and chmod
        try:
            self._sock.bind(str(self.path))
        finally:
            os.umask(old)
        os.chmod(self.path, mode)
        self._sock.listen(8)
        self._sock.settimeout(0.5)

    def run(self) -> None:
        while not self._halt.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                if self._halt.is_set():
                    return
                continue
            with conn:
                try:
                    conn.settimeout(2.0)
                    data = json.dumps(self.snapshot(), default=str).encode() + b"\n"
                    conn.sendall(data)
                except Exception:  # a client that hangs up early, or a snapshot bug: never kill the server
                    log.debug("status client failed", exc_info=True)

    def close(self) -> None:
        self._halt.set()
        with contextlib.suppress(OSError):
            self._sock.close()
        with contextlib.suppress(OSError):
            self.path.unlink()
        if self.is_alive():
            self.join(2.0)


def fetch(path: str | os.PathLike[str], timeout_s: float = 3.0) -> dict[str, Any]:
    """One snapshot from the daemon; raises ConnectionError with a readable reason when it is not there."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(str(path))
        chunks, size = [], 0
        while True:
            part = s.recv(65536)
            if not part:
                break
            chunks.append(part)
            size += len(part)
            if size > MAX_REPLY:
                raise ConnectionError("status reply too large")
    except FileNotFoundError:
        raise ConnectionError(f"logger is not running (no status socket at {path})") from None
    except ConnectionRefusedError:
        raise ConnectionError(f"logger is not running (nobody answers on {path})") from None
    except PermissionError:
        raise ConnectionError(f"not allowed to read {path}: add yourself to the logger's group") from None
    except TimeoutError:
        raise ConnectionError(f"logger did not answer on {path} within {timeout_s:g} s") from None
    finally:
        s.close()
    try:
        return json.loads(b"".join(chunks))
    except ValueError:
        raise ConnectionError("logger sent an unreadable status") from None
