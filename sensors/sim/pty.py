"""A serial port played by a device model: the master side of a pty, under a stable path.

The driver opens :attr:`PtyPort.path` with pyserial exactly as it would open ``/dev/ttyUSB0``. The path is
a symlink, like the ones udev makes under ``/dev/serial/by-id``, so that a port can vanish (the master
closes, the driver sees an I/O error) and come back on a new pty under the same name.

Our own slave fd stays open while the port exists: without it, the master reads EIO whenever the driver
closes its side, which a real adapter never does.
"""

from __future__ import annotations

import os
import pty
import select
import shutil
import tempfile
import threading
import tty

TMP_PREFIX = "sim-tty-"  # then the owning process's pid and "-": a folder a killed run left is told by its pid
_swept: set[str] = set()  # the temporary folders this process has swept of folders killed runs left (once each)


class PtyPort:
    """The device end of a serial line."""

    def __init__(self, link_path: str | None = None) -> None:
        if link_path is None:
            _remove_left_behind(tempfile.gettempdir())
            self._tmpdir: str | None = tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{os.getpid()}-")
            link_path = os.path.join(self._tmpdir, "tty")
        else:
            self._tmpdir = None
        self.path = link_path
        self._lock = threading.Lock()
        self._master = -1
        self._slave = -1
        self.reappear()

    @property
    def present(self) -> bool:
        return self._master >= 0

    def reappear(self) -> None:
        """Plug the device (back) in: a fresh pty under the same path."""
        with self._lock:
            if self._master >= 0:
                return
            master, slave = pty.openpty()
            tty.setraw(slave)
            tty.setraw(master)
            tmp = self.path + ".new"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(os.ttyname(slave), tmp)
            os.replace(tmp, self.path)
            self._master, self._slave = master, slave

    def vanish(self) -> None:
        """Unplug the device: the driver's next read or write fails, the path disappears."""
        with self._lock:
            if self._master < 0:
                return
            master, slave = self._master, self._slave
            self._master = self._slave = -1
            if os.path.lexists(self.path):
                os.unlink(self.path)
            os.close(master)
            os.close(slave)

    def write(self, data: bytes) -> None:
        """Send bytes to the driver; dropped silently while the device is unplugged."""
        fd = self._master
        if fd < 0 or not data:
            return
        view = memoryview(data)
        try:
            while view:
                n = os.write(fd, view)
                view = view[n:]
        except OSError:
            pass

    def read(self, timeout_s: float = 0.1, max_bytes: int = 4096) -> bytes:
        """Bytes the driver sent, waiting up to ``timeout_s``; empty when none or unplugged."""
        fd = self._master
        if fd < 0:
            return b""
        try:
            ready, _, _ = select.select([fd], [], [], timeout_s)
            return os.read(fd, max_bytes) if ready else b""
        except (OSError, ValueError):
            return b""

    def close(self) -> None:
        self.vanish()
        if self._tmpdir is not None:
            try:
                os.rmdir(self._tmpdir)
            except OSError:
                pass

    def __enter__(self) -> PtyPort:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _remove_left_behind(tmp: str) -> None:
    """Remove the port folders of simulated runs whose process is gone (a run killed with SIGKILL, a test run
    stopped hard): each held only a symlink to a pty that went with its process, and hundreds of them filled
    the temporary folder of a development machine or a CI host. Folders of live processes, and any other, stay.
    Once per process and folder: a run's later ports find nothing new left there."""
    if tmp in _swept:
        return
    _swept.add(tmp)
    try:
        names = os.listdir(tmp)
    except OSError:
        return
    for name in names:
        pid = name[len(TMP_PREFIX):].partition("-")[0]
        if not name.startswith(TMP_PREFIX) or not pid.isdigit() or _alive(int(pid)):
            continue
        shutil.rmtree(os.path.join(tmp, name), ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process
        pass
    return True
