"""What the daemon keeps in its state folder from one drive to the next: written whole or not at all; and the
folder's lock, which lets one logger at a time use it."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def save_json(path: Path, state: dict[str, Any], what: str) -> bool:
    """Write ``state`` as JSON to a temporary file, flushed to the card, and rename it over ``path``, the folder
    flushed too: a power cut (how a car's logger stops) leaves the old file or the new one, never an empty one.
    A failure is a warning naming ``what``, never an error (the drive goes on). Returns whether it was
    written."""
    tmp = path.with_suffix(".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "w") as f:
            f.write(json.dumps(state))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("cannot save %s to %s: %s", what, path, exc.strerror or exc)
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass  # what stands in its way is not ours to remove
        return False
    try:  # the rename itself to the card; best effort (some file systems refuse a folder's fsync)
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass
    return True


LOCK_NAME = "lock"


class StateInUse(OSError):
    """Another logger holds the state folder: it is recording with this configuration's folders."""


def lock_state(folder: Path) -> int | None:
    """Hold ``folder``'s lock for as long as the returned descriptor stays open (the process's life, or
    :func:`unlock_state`): one logger per state folder, hence per recording folder and clock state.

    The status socket already refuses a second logger of the same configuration, but only where both look for
    it: a second simulated run beside a first takes a socket of its own, and recorded into the same folder (its
    start-up recovery rewriting the first one's open file as a crash's). The lock holds whatever the sockets, and
    is gone with its process, however that ends (no stale lock after a power cut). Raises :class:`StateInUse`
    when another process holds it; a folder that cannot be locked at all (made, written: the recorder says what
    it can of such a folder) is passed over (a debug line), and the run goes on as before the lock, its own
    errors for that folder said where they happen."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
    except OSError as exc:  # a folder that cannot be made: what uses it says so (the run's folders, the state)
        log.debug("cannot lock the state folder %s (%s)", folder, exc.strerror or exc)
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        try:
            pid = os.read(fd, 32).decode(errors="replace").strip() or "?"
        except OSError:
            pid = "?"
        os.close(fd)
        raise StateInUse(errno.EBUSY, f"in use by another logger (pid {pid}): one logger records at a time; stop "
                         "that one first", str(folder)) from None
    except OSError as exc:  # a file system without locks
        os.close(fd)
        log.warning("cannot lock the state folder %s (%s): a second logger on it would not be refused",
                    folder, exc.strerror or exc)
        return None
    with contextlib.suppress(OSError):  # who holds it, for the next one's line
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def unlock_state(fd: int | None) -> None:
    if fd is not None:
        with contextlib.suppress(OSError):
            os.close(fd)
