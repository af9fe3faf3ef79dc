"""The IMU offsets' temperature coefficients kept from one drive to the next, like the mount alignment.

A coefficient is the part's, not the drive's (a phone's or an automotive receiver's over-temperature gyro
calibration is kept the same way): what a drive learnt of it (:class:`logger.nav.thermal.TempcoLearner`) is the
next start's prior, so the first minutes' warming, which teach little, start from what earlier drives showed.
Kept on the chip's axes, so a new mounting turns it; only for the same part as far as the logger can tell (a
real IMU by its bus and address; a simulated one by its profile and seed, since simulated drives with other
profiles share a state folder) and the same configured bounds (a changed bound is the installer's word); and
only when the drive itself narrowed some coefficient to under half its bound (a drive that showed no warming
leaves the file as it was). The saved sigma is doubled on loading: a drive's posterior counts its estimates as
partly independent, and a part ages. A new IMU on the same bus and address cannot be told apart: delete
``imu_tempco.json`` from the state folder when the IMU is changed.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

from logger.runtime.state_file import save_json

log = logging.getLogger(__name__)
LEARNT_SHARE = 0.5  # saved once some coefficient's sigma is under this share of its configured bound
LOAD_WIDENING = 2.0  # the saved sigma times this is the next start's prior


def board(bus: str | int, address: int) -> str:
    """The installation of a real IMU: where it answers."""
    return f"IMU on I2C bus {bus} at 0x{address:02x}"


def simulated(imu: str, seed: int) -> str:
    """The installation of a simulated IMU: its profile and the seed its part was drawn with."""
    return f"simulated {imu} IMU, seed {seed}"


def load(path: Path, installation: str, bounds: list[float]) -> tuple[list[float], list[float]] | None:
    """The saved coefficients and sigmas (accelerometer x y z in m/s^2/degC, gyro x y z in rad/s/degC, chip
    axes), the sigmas widened by LOAD_WIDENING, when saved for the same installation under the same configured
    ``bounds``; None otherwise."""
    if not path.exists():
        return None
    try:
        st = json.loads(path.read_text())
        if isinstance(st, dict) and "k_chip" in st and ("bounds" not in st or "installation" not in st):
            log.info("the saved IMU temperature coefficients %s were written by an older version of the logger "
                     "(without %s): learning them again", path,
                     " and ".join(k for k in ("bounds", "installation") if k not in st))
            return None
        k = [float(v) for v in st["k_chip"]]
        sigma = [float(v) * LOAD_WIDENING for v in st["sigma_chip"]]
        saved_bounds = [float(v) for v in st["bounds"]]
        saved_on = str(st.get("installation", ""))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("ignoring the saved IMU temperature coefficients %s: %s", path, exc)
        return None
    if saved_on != installation:
        return None  # another part: says nothing of this one
    if (len(k) != 6 or len(sigma) != 6 or len(saved_bounds) != 6 or not all(math.isfinite(v) for v in (*k, *sigma))
            or any(sv <= 0.0 < b for sv, b in zip(sigma, saved_bounds, strict=True))):
        log.warning("ignoring the saved IMU temperature coefficients %s: not six finite coefficients and positive "
                    "sigmas (an axis whose bound is 0 has none)", path)
        return None
    if any(abs(a - b) > 1e-12 for a, b in zip(saved_bounds, bounds, strict=True)):
        log.info("the configured temperature coefficient bounds changed since the IMU's were saved: starting from "
                 "the configuration")
        return None
    log.info("starting from the IMU temperature coefficients of earlier drives: gyro %s deg/s/degC",
             " / ".join(f"{math.degrees(v):.3f}" for v in k[3:]))
    return k, sigma


def save(path: Path, installation: str, k_chip: list[float], sigma_chip: list[float], bounds: list[float],
         taught_sigma: list[float]) -> bool:
    """Keep coefficients a drive has learnt: written when this drive's estimates alone (``taught_sigma``) put
    some coefficient under LEARNT_SHARE of its bound, whole or not at all. Returns whether it was written."""
    if not any(s < LEARNT_SHARE * b for s, b in zip(taught_sigma, bounds, strict=True) if b > 0.0):
        return False
    state = {"installation": installation, "k_chip": list(k_chip), "sigma_chip": list(sigma_chip),
             "bounds": list(bounds),
             "units": "m/s^2/degC (accelerometer x y z), rad/s/degC (gyro x y z), chip axes",
             "saved_unix_s": round(time.time())}
    return save_json(path, state, "the IMU temperature coefficients")
