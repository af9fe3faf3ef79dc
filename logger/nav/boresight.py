"""The IMU's mounting refined at the office: the side slip and climb of a solution without the car's constraints.

The mount alignment (``mounting.py``) finds the mounting from the drive's accelerations and velocities to a few
tenths of a degree in pitch and yaw (0.1-0.6 deg on the simulated urban drives with the board at (5, -4, 30) deg).
The 17-state filter is that sensitive to what is left: the OBD speed and the non-holonomic rows hold the vehicle's
lateral and vertical velocity at zero on the axes the mounting gives, so a mounting 0.6 deg off in yaw holds the
solution's heading 0.6 deg off too (its own side slip then reads zero whatever the error), and on those drives it
cost 1.2x the configured mounting's east RMSE, and a pitch 0.17 deg off 1.15x its vertical.

A GNSS + IMU solution (the 15-state mode: no speed sensor, no constraints on the body) knows its heading from the
accelerations alone. Its velocity, turned into the vehicle's axes with the mounting found, has a lateral and a
vertical part: on average over the drive, those are the mounting's residual, since a car neither slides sideways
nor climbs out of its own floor's plane on average (its side slip in turns goes both ways, and is small at the
speeds counted). That is also the mounting the constraints need: the axes on which the body's lateral and vertical
velocities average zero. With the velocity in the assumed axes v_a = (v, -e_z v, e_y v) for a residual rotation e
(small: true axes = (I + [e x]) x assumed axes), the mean side slip atan(v_y / v_x) is -e_z and the mean climb
atan(-v_z / v_x) is -e_y. A rotation about the direction of travel is not shown this way and stays the alignment's
(the car's forward axis on the chip is what is refined: with the board turned 30 deg, all three Euler angles may
move, the roll too).

The rows counted are the solution's at speed and while fixes hold it (MAX_SIGMA_M); the mean is taken once the drive
held MIN_MOVING_S of them and when it is small enough to be a residual. Its standard error is the scatter of its 30 s
means; that leaves out the solution's own attitude error, whose pitch trades with the forward accelerometer offset
(0.06 deg a mg). On the simulated urban drives (600 s, board at (5, -4, 30) deg) the alignment's 5.05 / -3.86 / 30.35
and 4.84 / -4.17 / 30.62 deg became 5.03 / -3.90 / 30.03 and 4.92 / -4.02 / 30.06 deg.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from logger.nav.engine import TrajectoryRow
from logger.nav.mounting import mount_matrix, nearest_rotation
from logger.nav.rotations import dcm_from_quat, euler_from_dcm, skew

MIN_SPEED_MPS = 5.0  # rows slower than this are left out: a heading is poorly held standing, a slip angle noisy
# Rows less sure of their position than this are left out: dead reckoning. Without fixes and without the car's
# constraints the velocity drifts, and its "side slip" with it (counted, a 130 s tunnel took one simulated drive's
# refined yaw from 29.88 to 28.87 deg, the truth 30). A street canyon's fixes still hold the velocity, and its rows
# count: bounded at 1.5 m instead, which leaves them out, the urban drives' pitch came 0.07-0.13 deg further off.
MAX_SIGMA_M = 5.0
MIN_MOVING_S = 120.0  # less drive than this at speed, and the mean is not taken (a short drive's turns may not cancel)
MAX_RESIDUAL_DEG = 2.0  # a residual larger than this is the GNSS + IMU solution's own heading, not the mounting's
BLOCK_S = 30.0  # the mean's spread is judged from blocks this long (neighbouring rows share their errors)


@dataclass(frozen=True, slots=True)
class Residual:
    """The mean side slip and climb of a solution's velocity in the vehicle axes (deg), their standard errors from
    the scatter of BLOCK_S means (deg), and how much drive at speed they stand on (s)."""

    slip_deg: float
    climb_deg: float
    slip_se_deg: float
    climb_se_deg: float
    moving_s: float

    def usable(self) -> bool:
        """Enough drive at speed, and small enough to be a mounting's residual."""
        return (self.moving_s >= MIN_MOVING_S and abs(self.slip_deg) <= MAX_RESIDUAL_DEG
                and abs(self.climb_deg) <= MAX_RESIDUAL_DEG)


def residual(rows: Sequence[TrajectoryRow]) -> Residual | None:
    """The residual of the mounting a constraint-free solution's rows were computed with; None when no row is at
    speed."""
    if not rows:
        return None
    t_all, _, _, _, _, vn, ve, vd, q, sig, _ = zip(*rows, strict=True)
    v = np.array((vn, ve, vd))  # 3 x rows
    sg = np.array(sig)
    keep = (np.hypot(v[0], v[1]) >= MIN_SPEED_MPS) & (np.maximum(sg[:, 0], sg[:, 1]) <= MAX_SIGMA_M)
    if not keep.any():
        return None
    qa = np.array(q)[keep]
    c = dcm_from_quat((qa[:, 0], qa[:, 1], qa[:, 2], qa[:, 3]))  # 3 x 3 x rows, body to NED
    vb = np.einsum("jin,jn->in", c, v[:, keep])  # C^T v, row by row
    slip, climb = np.arctan2(vb[1], vb[0]), np.arctan2(-vb[2], vb[0])
    t = np.array(t_all, dtype=np.int64)[keep]
    order = np.argsort(t, kind="stable")  # the engine's rows are in time order; a caller's need not be
    t, slip, climb = t[order], slip[order], climb[order]
    dt = np.diff(t) / 1e9
    # Time between rows at speed (rows come at the IMU's rate or its integration's, 20 Hz and up): gaps of a second
    # or more (stops, dead reckoning left out) do not count.
    moving_s = float(dt[(dt > 0.0) & (dt < 1.0)].sum())
    s, c = np.degrees(slip), np.degrees(climb)
    # As the platform's index type: np.bincount refuses int64 where that is 32 bits (the board's armhf numpy: a
    # TypeError out of every mount refinement of `logger replay`, found by tools/board-check.sh's suite).
    block = ((t - t[0]) // int(BLOCK_S * 1e9)).astype(np.intp)
    return Residual(float(s.mean()), float(c.mean()), _standard_error(s, block), _standard_error(c, block), moving_s)


def _standard_error(x: np.ndarray, block: np.ndarray) -> float:
    """The standard error of the mean of ``x`` from the scatter of its blocks' means (NaN with fewer than two)."""
    counts = np.bincount(block)
    keep = counts > 0
    means = np.bincount(block, weights=x)[keep] / counts[keep]
    if len(means) < 2:
        return math.nan
    return float(means.std(ddof=1) / math.sqrt(len(means)))


def refined(rpy_deg: Sequence[float], r: Residual) -> tuple[float, float, float]:
    """The mounting (roll, pitch, yaw deg, as ``nav.mounting_rpy_deg``) with the residual taken out."""
    e = (0.0, -math.radians(r.climb_deg), -math.radians(r.slip_deg))
    # I + [e x] is a rotation only to first order: the nearest one.
    roll, pitch, yaw = euler_from_dcm(nearest_rotation((np.eye(3) + skew(e)) @ mount_matrix(tuple(rpy_deg))))
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)
