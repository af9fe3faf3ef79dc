"""The nominal navigation state and the layout of the error state (the paper's Eq. 6), with named offsets.

Error states are *estimated minus true*, as in the paper (delta V = V_hat - V): position error in metres
north, east, down (the paper's latitude/longitude/height errors scaled by the radii of curvature, which keeps
the covariance well conditioned), velocity error NED, the attitude error phi of the computed navigation frame
(C_hat = (I - [phi x]) C), accelerometer and gyro bias errors in body axes, then the OBD scale factor error and
the baro/GNSS height offset error. The 15-state mode (the paper's baseline) keeps the first fifteen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from logger.nav import earth
from logger.nav.rotations import dcm_from_quat, euler_from_dcm, quat_from_rotvec, quat_mul

P_ID = 0  # position error, m, NED
V_ID = 3  # velocity error, m/s, NED
PHI_ID = 6  # attitude error, rad, NED
BA_ID = 9  # accelerometer bias error, m/s^2, body
BG_ID = 12  # gyro bias error, rad/s, body
SF_ID = 15  # OBD speed scale factor error (true speed = (1 + s) x OBD speed)
DH_ID = 16  # height offset error, m (ellipsoidal height minus baro pressure altitude)
RQ_ID = 17  # error of the current OBD reading's rounding, m/s (true speed = (1 + s) x (OBD speed + r))
N_INS = 15
N_FULL = 17  # the paper's filter
N_ROUNDING = 18  # with the OBD reading's rounding (NavParams.obd_rounding_state)

STATE_NAMES = ("pn", "pe", "pd", "vn", "ve", "vd", "phin", "phie", "phid", "bax", "bay", "baz", "bgx", "bgy",
               "bgz", "sf", "dh", "rq")


@dataclass
class NavState:
    """Position (rad, rad, m above the ellipsoid), NED velocity, attitude quaternion body->NED, sensor biases,
    OBD scale factor and height offset: the whole nominal state, as plain floats for a fast inner loop."""

    lat: float
    lon: float
    h: float
    vn: float = 0.0
    ve: float = 0.0
    vd: float = 0.0
    q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    ba: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sf: float = 0.0
    dh: float = 0.0
    rq: float = 0.0

    def plain(self) -> NavState:
        """Every field as a plain Python float, in place (and returned). The inner loop's arithmetic on numpy
        scalars, which a state built from arrays would carry, costs several times as much for the same result."""
        self.lat, self.lon, self.h = float(self.lat), float(self.lon), float(self.h)
        self.vn, self.ve, self.vd = float(self.vn), float(self.ve), float(self.vd)
        self.q = (float(self.q[0]), float(self.q[1]), float(self.q[2]), float(self.q[3]))
        self.ba = (float(self.ba[0]), float(self.ba[1]), float(self.ba[2]))
        self.bg = (float(self.bg[0]), float(self.bg[1]), float(self.bg[2]))
        self.sf, self.dh, self.rq = float(self.sf), float(self.dh), float(self.rq)
        return self

    def dcm(self) -> np.ndarray:
        return dcm_from_quat(self.q)

    def rpy(self) -> tuple[float, float, float]:
        return euler_from_dcm(self.dcm())

    def vel(self) -> np.ndarray:
        return np.array((self.vn, self.ve, self.vd))

    def copy(self) -> NavState:
        return NavState(self.lat, self.lon, self.h, self.vn, self.ve, self.vd, self.q, self.ba, self.bg, self.sf,
                        self.dh, self.rq)

    def correct(self, dx: np.ndarray) -> None:
        """Feed an estimated error back into the nominal state (closed loop): x_true = x_hat - dx."""
        d = dx.tolist()  # plain floats at once: indexing the array element by element costs more than the rest
        rm, rn = earth.radii(self.lat)
        self.lat -= d[P_ID] / (rm + self.h)
        self.lon -= d[P_ID + 1] / ((rn + self.h) * math.cos(self.lat))
        self.h += d[P_ID + 2]
        self.vn -= d[V_ID]
        self.ve -= d[V_ID + 1]
        self.vd -= d[V_ID + 2]
        # C_true = (I + [phi x]) C_hat: rotate the computed frame back by phi, in NED.
        w, x, y, z = quat_mul(quat_from_rotvec(d[PHI_ID], d[PHI_ID + 1], d[PHI_ID + 2]), self.q)
        n = math.sqrt(w * w + x * x + y * y + z * z)
        self.q = (w / n, x / n, y / n, z / n)
        self.ba = (self.ba[0] - d[BA_ID], self.ba[1] - d[BA_ID + 1], self.ba[2] - d[BA_ID + 2])
        self.bg = (self.bg[0] - d[BG_ID], self.bg[1] - d[BG_ID + 1], self.bg[2] - d[BG_ID + 2])
        if len(d) > SF_ID:
            self.sf -= d[SF_ID]
            self.dh -= d[DH_ID]
        if len(d) > RQ_ID:
            self.rq -= d[RQ_ID]
