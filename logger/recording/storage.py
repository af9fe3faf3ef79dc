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

Under the service the mount point is always in the mount table: the unit's drop-in ``ReadWritePaths=`` (README)
binds the folder onto itself in the service's own mount namespace, so a card not mounted shows there as a mount of
the root filesystem's own folder. A mount point counts as mounted only when what is mounted there last is another
filesystem than the one holding its parent folder (as ``os.path.ismount`` tells a mount point by its device), or
when fstab itself lists it as a bind mount.
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


def _fstab_entries(text: str) -> list[tuple[Path, bool]]:
    """(mount point, whether it is a bind mount) of each fstab entry, but the root and swap (which are no storage of
    their own)."""
    entries = []
    for line in text.splitlines():
        fields = line.split()
        if len(fields) < 3 or fields[0].startswith("#"):
            continue
        where, kind = _unescape(fields[1]), fields[2]
        if kind == "swap" or not where.startswith("/") or where == "/":
            continue
        options = fields[3].split(",") if len(fields) > 3 else []
        entries.append((Path(os.path.normpath(where)), "bind" in options or "rbind" in options))
    return entries


def fstab_mount_points(text: str) -> list[Path]:
    """The mount points an fstab lists, but the root and swap (which are no storage of their own)."""
    return [point for point, _ in _fstab_entries(text)]


def _mounts(text: str) -> list[tuple[Path, str]]:
    """(mount point, device MAJ:MIN) of each line of ``/proc/self/mountinfo`` (its fifth and third fields), in its
    order: a later mount on the same point covers an earlier one."""
    mounts = []
    for line in text.splitlines():
        fields = line.split()
        if len(fields) >= 5:
            mounts.append((Path(os.path.normpath(_unescape(fields[4]))), fields[2]))
    return mounts


def mounted_points(text: str) -> set[Path]:
    """The mount points of ``/proc/self/mountinfo`` (its fifth field)."""
    return {point for point, _ in _mounts(text)}


def _storage_mounted(point: Path, mounts: list[tuple[Path, str]]) -> bool:
    """Whether another filesystem than its parent folder's is mounted on ``point`` (the last mount there counts)."""
    on_point = [device for where, device in mounts if where == point]
    if not on_point:
        return False
    holding_parent = [(len(where.parts), k) for k, (where, _) in enumerate(mounts)
                      if where == point.parent or where in point.parent.parents]
    if not holding_parent:
        return True
    parent_device = mounts[max(holding_parent)[1]][1]
    return on_point[-1] != parent_device


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
    holding = [(m, bind) for m, bind in _fstab_entries(tab) if here == m or m in here.parents]
    if not holding:
        return None
    point, bind = max(holding, key=lambda entry: len(entry[0].parts))
    info = _read(mountinfo or MOUNTINFO)
    if info is None:
        return None
    mounts = _mounts(info)
    if any(where == point for where, _ in mounts) if bind else _storage_mounted(point, mounts):
        return None
    # Short: the status screen's problem line (80 columns). The recorder's log line says what is not done.
    return f"{point} is not mounted (listed in /etc/fstab); waiting for it"
