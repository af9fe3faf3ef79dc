"""Small array helpers for the filter's block forms (a FIFO read's samples at once).

A block form pays its numpy calls once per block, so the calls themselves are the cost at the rates it serves: a
1 kHz IMU goes through them about ten times a second, per bookkeeping step. ``np.diff(x, prepend=v)`` builds its
result through broadcasting and a concatenation, eight microseconds here for forty samples where a subtraction
into a preallocated array takes under two.
"""

from __future__ import annotations

import numpy as np


def diff_from(before: int | float, x: np.ndarray) -> np.ndarray:
    """``np.diff(x, prepend=before)`` for a 1-D array: each element less the one before it, the first less
    ``before``."""
    d = np.empty(len(x), dtype=np.result_type(x, np.asarray(before)))
    if len(x):
        d[0] = x[0] - before
        np.subtract(x[1:], x[:-1], out=d[1:])
    return d
