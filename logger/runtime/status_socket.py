"""The status socket: the daemon answers each connection with one JSON snapshot and closes it.

No network listener, and the socket is readable by the daemon's group only (mode 0660). The server runs in the
daemon (:class:`StatusServer`); ``logger status`` and the tools read it with :func:`fetch`. The verdict's exit
codes are part of the protocol, so scripts read the same numbers whoever asks.

Clients cannot hurt recording: a snapshot is taken at most every :data:`CACHE_S` whoever asks how often, and the
server answers at most :data:`MAX_ANSWERS_PER_S` connections a second, so a script polling in a loop or four
``watch`` sessions cost the sensor threads a bounded share of the one core. A client that finds the queue full
waits and tries again (:func:`fetch`); one that still gets no answer is told the logger is busy, not that it is
not running.
"""

from __future__ import annotations

import contextlib
import grp
import json
import logging
import os
import pwd
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

EXIT = {"ok": 0, "degraded": 1, "critical": 2}
NOT_RUNNING = 3
UNKNOWN = 4  # running but not answering in time, or not allowed to ask: nobody can say whether it is well (LSB's
# "status unknown")
MAX_REPLY = 4 << 20
CACHE_S = 0.25  # a snapshot is this fresh at most: the daemon computes at most four a second
MAX_ANSWERS_PER_S = 50.0
BACKLOG = 16


class StatusBusy(ConnectionError):
    """The daemon is there but did not answer in time (its queue full, or it is stalled)."""


class StatusDenied(ConnectionError):
    """The status socket (or the folder it is in) may not be read by this user: nothing says whether the daemon
    runs or how it is."""


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
        self._sock.listen(BACKLOG)
        self._sock.settimeout(0.5)
        self._cached: tuple[float, bytes] | None = None  # (monotonic time taken, the snapshot's JSON)
        self.snapshots = 0  # taken since start (how often the daemon did the work)
        self.answered = 0

    def _reply(self) -> bytes:
        now = time.monotonic()
        if self._cached is None or now - self._cached[0] >= CACHE_S:
            self._cached = (now, json.dumps(self.snapshot(), default=str).encode() + b"\n")
            self.snapshots += 1
        return self._cached[1]

    def run(self) -> None:
        next_answer = 0.0
        while not self._halt.is_set():
            wait = next_answer - time.monotonic()
            if wait > 0 and self._halt.wait(wait):  # pace the answers; the rest wait in the queue
                return
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                if self._halt.is_set():
                    return
                continue
            next_answer = time.monotonic() + 1.0 / MAX_ANSWERS_PER_S
            with conn:
                try:
                    conn.settimeout(2.0)
                    conn.sendall(self._reply())
                    self.answered += 1
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


def denied(path: Path) -> StatusDenied:
    """Not allowed to read ``path`` (the socket, or its folder): what to do about it, by the group that owns it, on a
    line of its own (together they ran to 120 columns and more on a phone's 80)."""
    return StatusDenied(f"not allowed to read {path}:\n  {group_advice(path)}")


def group_advice(path: Path) -> str:
    """How to get the right to read ``path``: join the group that owns it (or its folder, if it cannot be looked
    at), or, for a member added since this login (install-board.sh --operator), log in again: a session keeps the
    groups it started with."""
    gid = None
    for p in (path, path.parent):
        try:
            gid = p.stat().st_gid
            break
        except OSError:
            continue
    try:
        group = grp.getgrgid(gid) if gid is not None else None
        user = pwd.getpwuid(os.getuid()).pw_name
    except KeyError:
        group = None
    if group is None:
        return "add yourself to the logger's group"
    name = group.gr_name
    if user in group.gr_mem and gid not in os.getgroups():
        return f"you were added to the group {name} after this login: log in again (or run `newgrp {name}`)"
    return f"add yourself to the logger's group, then log in again:\n  sudo usermod -a -G {name} $USER"


def _connect_error(exc: OSError, path: str | os.PathLike[str], timeout_s: float) -> ConnectionError:
    """Why a connection to the status socket failed, in words."""
    if isinstance(exc, FileNotFoundError):
        return ConnectionError(f"logger is not running (no status socket at {path})")
    if isinstance(exc, ConnectionRefusedError):
        return ConnectionError(f"logger is not running (nobody answers on {path})")
    if isinstance(exc, PermissionError):
        return denied(Path(path))
    if isinstance(exc, TimeoutError):
        return StatusBusy(f"logger did not answer on {path} within {timeout_s:g} s")
    return ConnectionError(f"cannot reach the logger on {path}: {exc.strerror or exc}")


def fetch(path: str | os.PathLike[str], timeout_s: float = 3.0) -> dict[str, Any]:
    """One snapshot from the daemon; raises ConnectionError with a readable reason when it is not there."""
    deadline = time.monotonic() + timeout_s
    pause = 0.01
    while True:  # a full queue (other clients polling) refuses at once: wait and try again until the deadline
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(timeout_s)
        try:
            s.connect(str(path))
            break
        except BlockingIOError:
            s.close()
            if time.monotonic() + pause > deadline:
                raise StatusBusy(f"logger is running but busy: its status queue at {path} stayed full for "
                                 f"{timeout_s:g} s") from None
            time.sleep(pause)
            pause = min(pause * 2, 0.2)
        except OSError as exc:
            s.close()
            raise _connect_error(exc, path, timeout_s) from None
    try:
        chunks, size = [], 0
        while True:
            part = s.recv(65536)
            if not part:
                break
            chunks.append(part)
            size += len(part)
            if size > MAX_REPLY:
                raise ConnectionError("status reply too large")
    except TimeoutError:
        raise StatusBusy(f"logger did not answer on {path} within {timeout_s:g} s") from None
    except OSError as exc:
        raise ConnectionError(f"logger closed the status connection on {path}: {exc.strerror or exc}") from None
    finally:
        s.close()
    try:
        return json.loads(b"".join(chunks))
    except ValueError:
        raise ConnectionError("logger sent an unreadable status") from None
