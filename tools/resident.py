"""A process's resident memory, also when it runs under qemu-user (the emulated board root of tools/board-check.sh).

Natively it is /proc/self/status's VmRSS (and VmHWM, its peak). Under qemu-user the process is qemu's: its status
and smaps describe the host process, whose resident set holds the translator and its code cache (about 24 MB at an
interpreter's start) beside the program's memory: 90 MB where the program held about half of it. qemu answers
/proc/self/maps with the guest's own mappings at guest addresses, and keeps the guest's memory as one window of
its own address space, at guest_base + guest address. So the guest's first file mapping, found in both (the same
file at the same offset), gives guest_base, and the Rss of the host's mappings inside the 4 GB window is the
guest's resident set: the 32-bit board's own pages, with its binaries and libraries (Debian's armhf numpy) and
4-byte pointers. The kernel keeps no peak for it: callers take the largest of their samples.

This rests on qemu passing /proc/self/smaps through, as Debian 12's qemu 7.2 does. qemu 8.1 and later emulate it
too (guest addresses, no Rss): :func:`emulated` then sees no mapping above 4 GB, and the figure falls back to
VmRSS, qemu's whole process, which the reports label as qemu's (``source``).
"""

from __future__ import annotations

import sys

GUEST_SPAN = 1 << 32  # a 32-bit guest's address space
NATIVE = "VmRSS"  # :func:`source` for a program that is not emulated
_emulated: bool | None = None


def _status_kb(key: str) -> int:
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            name, _, rest = line.partition(":")
            if name == key:
                return int(rest.split()[0])
    return 0


def host_mappings(smaps: str = "/proc/self/smaps") -> list[tuple[int, str, int, int]]:
    """(start, path, file offset, Rss kB) of each mapping ``smaps`` lists."""
    out: list[tuple[int, str, int, int]] = []
    start, path, offset = 0, "", 0
    with open(smaps, encoding="utf-8", errors="replace") as f:
        for line in f:
            head = line.split(None, 5)
            if head[0].endswith(":"):
                if head[0] == "Rss:":
                    out.append((start, path, offset, int(head[1])))
            else:
                start = int(head[0].partition("-")[0], 16)
                offset = int(head[2], 16)
                path = head[5].strip() if len(head) > 5 else ""
    return out


def emulated() -> bool:
    """Whether this is a 32-bit program whose smaps lists mappings above 4 GB: a 64-bit host's qemu-user."""
    global _emulated
    if _emulated is None:
        try:
            _emulated = sys.maxsize < GUEST_SPAN and any(start >= GUEST_SPAN for start, *_ in host_mappings())
        except OSError:  # a kernel without smaps: no qemu window to find, VmRSS it is
            _emulated = False
    return _emulated


def guest_base(host: list[tuple[int, str, int, int]], maps: str = "/proc/self/maps") -> int:
    """Where the guest's address 0 lies in qemu's own address space (see the module's docstring)."""
    with open(maps, encoding="utf-8", errors="replace") as f:
        for line in f:
            fields = line.split(None, 5)
            if len(fields) > 5 and fields[5].startswith("/"):
                start, path, offset = int(fields[0].partition("-")[0], 16), fields[5].strip(), int(fields[2], 16)
                break
        else:
            raise OSError("no file mapping in /proc/self/maps")
    for host_start, host_path, host_offset, _ in host:
        if host_path == path and host_offset == offset:
            return host_start - start
    raise OSError(f"qemu's mappings do not show {path}")


def rss_kb() -> int:
    """The program's resident set, kB: VmRSS natively, the guest's window under qemu-user."""
    if not emulated():
        return _status_kb("VmRSS")
    return guest_rss_kb()


def guest_rss_kb(smaps: str = "/proc/self/smaps", maps: str = "/proc/self/maps") -> int:
    """The Rss of qemu's mappings inside the guest's window, kB."""
    host = host_mappings(smaps)
    base = guest_base(host, maps)
    return sum(rss for start, _, _, rss in host if base <= start < base + GUEST_SPAN)


def peak_kb() -> int | None:
    """The resident set's peak (VmHWM), kB, natively; None under qemu-user, whose peak is the translator's too."""
    return None if emulated() else _status_kb("VmHWM")


def source() -> str:
    """Where :func:`rss_kb` reads from, for a report."""
    return "the guest's pages under qemu-user" if emulated() else NATIVE
