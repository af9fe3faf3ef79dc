"""What every PNG plot of a drive shares: matplotlib on the file-only backend, and a local metric frame.

matplotlib is an optional extra (``plots``): it is not on the board, and the logger never needs it to record.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from logger.nav import earth

INSTALL_HINT = ("matplotlib is not installed: pip install matplotlib (from a source tree: pip install -e '.[plots]'; "
                "on Debian: apt install python3-matplotlib)")


class PlotsUnavailable(Exception):
    """matplotlib cannot be imported; the message says how to install it."""


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (PNG files, no display needed, works over SSH)."""
    try:
        import matplotlib
    except ImportError as exc:
        raise PlotsUnavailable(INSTALL_HINT) from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def local_en(lat_rad: np.ndarray, lon_rad: np.ndarray, lat0_rad: float, lon0_rad: float,
             h0_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """East and north in metres from an origin, on the plane tangent there: a map in equal-aspect metres
    instead of degrees (whose aspect changes with latitude). The error grows with the square of the distance,
    about 0.1 m at 1 km: ample for a map, not for measuring."""
    rm, rn = earth.radii(lat0_rad)
    east = (np.asarray(lon_rad) - lon0_rad) * (rn + h0_m) * math.cos(lat0_rad)
    north = (np.asarray(lat_rad) - lat0_rad) * (rm + h0_m)
    return east, north
