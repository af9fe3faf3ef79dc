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


class SocketInUse(OSError):
    """Another logger answers on the status socket: it is not taken over (its operator would lose it)."""

    def __init__(self, path: Path, pid: object) -> None:
        super().__init__(f"in use by another logger (pid {pid})")
        self.strerror = f"in use by another logger (pid {pid})"
        self.path, self.pid = path, pid


def answering_pid(path: str | os.PathLike[str], timeout_s: float = 1.0) -> object | None:
    """The pid of the logger answering on ``path``, or None when nobody does (a socket left by a crash)."""
    try:
        return fetch(path, timeout_s).get("pid", "?")
    except ConnectionError:
        return None


def free_sim_socket(default: Path) -> Path:
    """``default`` unless another simulated run answers on it; then a socket of this process's own beside it, which
    ``logger status`` also looks for (:func:`sim_sockets`)."""
    if default.exists() and answering_pid(default) is not None:
        return default.with_name(f"{default.stem}-{os.getpid()}{default.suffix}")
    return default


def sim_sockets(default: Path) -> list[Path]:
    """Every socket a simulated run may be answering on: the default, then the per-run ones, newest first."""
    others = sorted(default.parent.glob(f"{default.stem}-*{default.suffix}"), key=_mtime, reverse=True)
    return [default, *others]


def _mtime(p: Path) -> float:
    try:
        return p.stat().st_mtime
    except OSError:
        return 0.0


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
            pid = answering_pid(self.path)
            if pid is not None:
                raise SocketInUse(self.path, pid)
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
