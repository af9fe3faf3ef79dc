"""The mount alignment kept from one drive to the next, like the clock's drift file.

A board screwed into a car stays as it was: the mounting the last drive settled on is the next start's first
guess, so the filter starts aligned instead of learning it again for minutes. It is used only while the
configuration still says what it said when it was saved (a changed ``nav.mounting_rpy_deg`` is the installer's
word that the board was moved, and wins) and for the same installation: a board, or a simulated board mounted at
given angles (simulated drives with other profiles share a state folder). The drive still estimates it (a
knocked board is noticed anew).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from logger.nav.mounting import SETTLED, MountEstimate
from logger.runtime.state_file import save_json

log = logging.getLogger(__name__)
SAVE_INTERVAL_S = 60.0
BOARD = "board"  # the installation of a real IMU; a simulated one is named by its mounting (simulated())


def simulated(mounting_rpy_deg: tuple[float, float, float]) -> str:
    """The installation of a simulated IMU mounted at these angles."""
    return "simulated board at " + " / ".join(f"{a:g}" for a in mounting_rpy_deg) + " deg"


def load(path: Path, configured: tuple[float, float, float], installation: str) -> tuple[float, float, float] | None:
    """The saved mounting when it was learnt under the same configured one and installation; None otherwise (or
    unreadable)."""
    if not path.exists():
        return None
    try:
        st = json.loads(path.read_text())
        saved_for = tuple(float(a) for a in st["configured_rpy_deg"])
        rpy = tuple(float(a) for a in st["rpy_deg"])
        saved_on = str(st.get("installation", ""))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("ignoring the saved mount alignment %s: %s", path, exc)
        return None
    if saved_on != installation:
        # Learnt on another (simulated) installation: says nothing of this one. A file without the key is an older
        # logger's, which kept none: said, rather than dropped without a word after an upgrade.
        if "installation" not in st:
            log.info("the saved mount alignment %s was written by an older version of the logger (it does not say "
                     "which installation it was learnt on): learning the mounting again", path)
        return None
    if len(rpy) != 3 or any(abs(a - b) > 1e-6 for a, b in zip(saved_for, configured, strict=True)):
        log.info("the configured mounting changed since the mount alignment was saved: starting from the "
                 "configuration")
        return None
    log.info("starting from the mount alignment of the last drive: %.1f / %.1f / %.1f deg", *rpy)
    return rpy  # type: ignore[return-value]


def save(path: Path, configured: tuple[float, float, float], installation: str, est: MountEstimate) -> None:
    """Keep a settled estimate (written to a temporary file and renamed: a power cut leaves the old one)."""
    if est.state != SETTLED:
        return
    state = {"installation": installation, "configured_rpy_deg": list(configured), "rpy_deg": list(est.rpy_deg),
             "sigma_deg": list(est.sigma_deg), "windows": est.windows, "saved_unix_s": round(time.time())}
    save_json(path, state, "the mount alignment")
