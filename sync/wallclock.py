"""What the host tells of its clocks: whether the wall clock is synchronised (adjtimex(2), or timedated where the
service's sandbox forbids it), and which boot this is.

A board without RTC boots with a wrong date, so the wall clock is no reference in general. When the kernel says
it is synchronised, it is good to well under a second, which is enough to catch the one failure the PPS pairing
cannot see by itself: a whole chain of edges labelled with the wrong second at the first lock.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import subprocess
from pathlib import Path

TIME_ERROR = 5  # clock not synchronised (adjtimex return value)
TIMEDATECTL_TIMEOUT_S = 2.0  # a start waits at most this for timedated's answer


class _Timeval(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long)]


class _Timex(ctypes.Structure):
    _fields_ = [("modes", ctypes.c_uint), ("offset", ctypes.c_long), ("freq", ctypes.c_long),
                ("maxerror", ctypes.c_long), ("esterror", ctypes.c_long), ("status", ctypes.c_int),
                ("constant", ctypes.c_long), ("precision", ctypes.c_long), ("tolerance", ctypes.c_long),
                ("time", _Timeval), ("tick", ctypes.c_long), ("ppsfreq", ctypes.c_long),
                ("jitter", ctypes.c_long), ("shift", ctypes.c_int), ("stabil", ctypes.c_long),
                ("jitcnt", ctypes.c_long), ("calcnt", ctypes.c_long), ("errcnt", ctypes.c_long),
                ("stbcnt", ctypes.c_long), ("tai", ctypes.c_int), ("_pad", ctypes.c_int * 11)]


TIMESYNC_FLAG = Path("/run/systemd/timesync/synchronized")  # systemd-timesyncd's: present once it synchronised


def system_clock_synchronized() -> bool:
    """True when the kernel reports the wall clock synchronised; False when not, or when it cannot tell.

    The service's sandbox (``ProtectClock=yes``) refuses adjtimex() even read-only: then systemd-timesyncd's flag
    file, then timedated (``timedatectl``, which asks the kernel from outside the sandbox: chrony's clock too)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        tx = _Timex()  # modes = 0: read only
        state = libc.adjtimex(ctypes.byref(tx))
    except (OSError, AttributeError):
        state = -1
    if state >= 0:
        return state != TIME_ERROR
    if TIMESYNC_FLAG.exists():
        return True
    try:
        done = subprocess.run(["timedatectl", "show", "--property=NTPSynchronized", "--value"], capture_output=True,
                              text=True, timeout=TIMEDATECTL_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0 and done.stdout.strip() == "yes"


BOOT_ID_PATH = Path("/proc/sys/kernel/random/boot_id")


def boot_id() -> str | None:
    """The kernel's random id of this boot, or None where /proc does not tell it.

    CLOCK_MONOTONIC runs on within one boot and restarts at the next: a clock mapping saved under the same id
    still holds, and files named by it before time is known stay apart from every other boot's.
    """
    try:
        text = BOOT_ID_PATH.read_text(encoding="ascii").strip()
    except OSError:
        return None
    return text or None
