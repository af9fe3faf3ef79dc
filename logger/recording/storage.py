"""Whether the output folder is on the storage it was meant to be on, before anything is made or written there.

A board records onto a card or a disk of its own, listed in ``/etc/fstab`` (usually with ``nofail``, so that the
board still boots without it). When that storage is not mounted (the card left out, a failed mount, a lazy unmount
of a card that died), its mount point is an empty folder of the root filesystem: a daemon that made its output
folder there again and recorded would fill the root filesystem (journald, apt and the logger's own state live
there) while ``logger status`` said "recording" under the very path the operator expects on the card. So a
folder beneath a mount point that ``/etc/fstab`` lists and ``/proc/self/mountinfo`` does not show mounted is no
place to record: the recorder says so and tries again, and starts recording once the storage is there.

Mounts that ``/etc/fstab`` does not list (a USB stick mounted by a desktop's automounter, a systemd ``.mount``
unit of its own) are not known here.
"""

from __future__ import annotations

import os
from pathlib import Path

FSTAB = Path("/etc/fstab")
MOUNTINFO = Path("/proc/self/mountinfo")


def _unescape(field: str) -> str:
    r"""A path as fstab and mountinfo write it: octal escapes for space, tab, newline and backslash (``\040``)."""
    if "\\" not in field:
        return field
    out, i = [], 0
    while i < len(field):
        if field[i] == "\\" and i + 3 < len(field) and all(c in "01234567" for c in field[i + 1:i + 4]):
            out.append(chr(int(field[i + 1:i + 4], 8)))
            i += 4
        else:
            out.append(field[i])
            i += 1
    return "".join(out)


def fstab_mount_points(text: str) -> list[Path]:
    """The mount points an fstab lists, but the root and swap (which are no storage of their own)."""
    points = []
    for line in text.splitlines():
        fields = line.split()
        if len(fields) < 3 or fields[0].startswith("#"):
            continue
        where, kind = _unescape(fields[1]), fields[2]
        if kind == "swap" or not where.startswith("/") or where == "/":
            continue
        points.append(Path(os.path.normpath(where)))
    return points


def mounted_points(text: str) -> set[Path]:
    """The mount points of ``/proc/self/mountinfo`` (its fifth field)."""
    points = set()
    for line in text.splitlines():
        fields = line.split()
        if len(fields) >= 5:
            points.add(Path(os.path.normpath(_unescape(fields[4]))))
    return points


def _read(path: Path) -> str | None:
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return None


def storage_problem(out_dir: Path, fstab: Path | None = None, mountinfo: Path | None = None) -> str | None:
    """Why nothing may be made or recorded in ``out_dir`` now, in a short line naming its mount point;
    None when it may (the folder is on the storage fstab gives it, or on none that fstab lists). A board without
    an fstab or without /proc (not Linux) is taken as one where nothing is known against the folder."""
    tab = _read(fstab or FSTAB)
    if not tab:
        return None
    here = Path(os.path.abspath(out_dir))  # normalised too
    # The innermost listed mount point holding the folder: a card mounted under a disk mounted in turn.
    holding = [m for m in fstab_mount_points(tab) if here == m or m in here.parents]
    if not holding:
        return None
    point = max(holding, key=lambda m: len(m.parts))
    info = _read(mountinfo or MOUNTINFO)
    if info is None or point in mounted_points(info):
        return None
    # Short: the status screen's problem line (80 columns). The recorder's log line says what is not done.
    return f"{point} is not mounted (listed in /etc/fstab); waiting for it"
