"""Measurement models: one small class per update type, each giving its innovation, Jacobian and noise.

The paper's Table 2 and Eq. 8-12, in the error convention of :mod:`logger.nav.state` (estimated minus true):

- :class:`GnssPosition` and :class:`GnssVelocity` (type 1), with the antenna lever arm;
- :class:`ObdVelocity` (type 2, Eq. 8): the INS velocity against the OBD speed along the vehicle's x axis
  with its scale factor; the paper's form also asks the lateral and vertical body velocity to be zero, which
  is the non-holonomic constraint, so those two rows carry its noise;
- :class:`BaroHeight` (type 3, Eq. 9): the INS height against the barometric altitude plus the estimated
  height offset, which makes the offset observable whenever the GNSS height is there too;
- :class:`ZeroMotion` (type 4, Eq. 12): zero velocity and zero angular rate while stopped;
- :class:`NonHolonomic`: the lateral and vertical rows alone, while moving without an OBD reading.

Each ``observe`` returns an :class:`Observation`, so the filter loop never changes when a type is added.
Innovations are *predicted minus measured*, so that ``z = H dx + noise``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from logger.nav import earth
from logger.nav.rotations import skew
from logger.nav.state import BG_ID, DH_ID, P_ID, PHI_ID, RQ_ID, SF_ID, V_ID, NavState

_I3 = np.arange(3)  # a 3x3 identity block set through its diagonal (np.eye costs more than the update's rows)


@dataclass
class Observation:
    name: str
    z: np.ndarray  # innovation, predicted minus measured
    h: np.ndarray  # (m, n) Jacobian of the innovation in the error state
    r: np.ndarray  # (m,) measurement noise variances (independent rows)


@dataclass
class GnssPosition:
    """Antenna position from the receiver; ``sigma_ned`` is the 1-sigma per axis, m."""

    lat_rad: float
    lon_rad: float
    h_m: float
    sigma_ned: tuple[float, float, float]
    lever_arm: np.ndarray  # antenna from IMU, vehicle axes, m
    horizontal_only: bool = False  # a 2D fix: the height is the receiver's held value

    def observe(self, s: NavState, c_bn: np.ndarray, n: int) -> Observation:
        arm_n = c_bn @ self.lever_arm
        dn, de, dd = earth.ned_offset_m(self.lat_rad, self.lon_rad, self.h_m, s.lat, s.lon, s.h)
        z = np.array((dn, de, dd)) + arm_n
        h = np.zeros((3, n))
        h[_I3, P_ID + _I3] = 1.0
        h[:, PHI_ID:PHI_ID + 3] = skew(arm_n)
        r = np.array(self.sigma_ned) ** 2
        if self.horizontal_only:
            return Observation("gnss_pos", z[:2], h[:2], r[:2])
        return Observation("gnss_pos", z, h, r)


@dataclass
class GnssVelocity:
    """Antenna velocity (NED, m/s) from the receiver's Doppler; ``gyro`` is the raw body rate, rad/s."""

    vel_ned: np.ndarray
    sigma: float
    lever_arm: np.ndarray
    gyro: np.ndarray
    horizontal_only: bool = False

    def observe(self, s: NavState, c_bn: np.ndarray, n: int) -> Observation:
        wx, wy, wz = (float(self.gyro[0]) - s.bg[0], float(self.gyro[1]) - s.bg[1], float(self.gyro[2]) - s.bg[2])
        lx, ly, lz = np.asarray(self.lever_arm, float).tolist()
        w_x_l = np.array((wy * lz - wz * ly, wz * lx - wx * lz, wx * ly - wy * lx))  # numpy's cross costs 50 us
        z = np.array((s.vn, s.ve, s.vd)) + c_bn @ w_x_l - self.vel_ned
        h = np.zeros((3, n))
        h[_I3, V_ID + _I3] = 1.0
        h[:, PHI_ID:PHI_ID + 3] = skew(c_bn @ w_x_l)
        h[:, BG_ID:BG_ID + 3] = c_bn @ skew(self.lever_arm)
        r = np.full(3, self.sigma**2)
        if self.horizontal_only:
            return Observation("gnss_vel", z[:2], h[:2], r[:2])
        return Observation("gnss_vel", z, h, r)


def _body_velocity_rows(s: NavState, c_bn: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame velocity C^T v and its Jacobian: d(C_hat^T v_hat) = C^T dv - C^T [v x] phi."""
    v = np.array((s.vn, s.ve, s.vd))
    ct = c_bn.T
    h = np.zeros((3, n))
    h[:, V_ID:V_ID + 3] = ct
    h[:, PHI_ID:PHI_ID + 3] = -ct @ skew(v)
    return ct @ v, h


@dataclass
class ObdVelocity:
    """Eq. 8 in the vehicle frame: [C^T v]_x - (1 + s) u, and the lateral and vertical rows held at zero."""

    speed_mps: float
    sigma: float
    nhc_sigma: float

    def observe(self, s: NavState, c_bn: np.ndarray, n: int) -> Observation:
        vb, h = _body_velocity_rows(s, c_bn, n)
        z = vb.copy()
        u = self.speed_mps + s.rq if n > RQ_ID else self.speed_mps
        z[0] -= (1.0 + s.sf) * u
        if n > SF_ID:
            h[0, SF_ID] = -u
        if n > RQ_ID:
            h[0, RQ_ID] = -(1.0 + s.sf)
        return Observation("obd", z, h, np.array((self.sigma**2, self.nhc_sigma**2, self.nhc_sigma**2)))


OBD_STEP_MPS = 1.0 / 3.6  # PID 0x0D's resolution, whatever the interface
ROUNDING_VAR = OBD_STEP_MPS**2 / 12.0  # a reading's rounding to it: uniform over one step
NO_WEIGHT_VAR = 1.0e6  # a row's variance that leaves the state as it is, yet keeps the update's algebra finite


def repeat_variance(sigma: float, step: float, n: int) -> float:
    """Forward-row variance of the ``n``-th of equal speed readings in a row, so that the run weighs as it should
    (without the rounding state, ``obd_rounding_state`` off).

    A reading's error is its rounding to ``step`` (variance step^2 / 12, part of ``sigma``) plus the rest
    (latency, wheel slip), taken as white. At a steady speed the rounding error is the same in every reading
    of a run: n readings then know the speed to var_q + var_w / n, not to sigma^2 / n. The n-th reading gets
    the variance that makes the information of the run add up to exactly that, so the first counts in full
    and the repeats less and less, however long the run.
    """
    var = sigma * sigma
    var_q = min(step * step / 12.0, var)
    var_w = var - var_q
    if n <= 1:
        return var
    gain = 0.0 if var_w <= 0.0 else 1.0 / (var_q + var_w / n) - 1.0 / (var_q + var_w / (n - 1))
    return min(1.0 / gain, NO_WEIGHT_VAR) if gain > 0.0 else NO_WEIGHT_VAR


@dataclass
class NonHolonomic:
    """No side slip and no vertical motion of the vehicle body: zero lateral and vertical body velocity."""

    sigma: float

    def observe(self, s: NavState, c_bn: np.ndarray, n: int) -> Observation:
        vb, h = _body_velocity_rows(s, c_bn, n)
        return Observation("nhc", vb[1:], h[1:], np.full(2, self.sigma**2))


@dataclass
class BaroHeight:
    """Eq. 9: INS height against barometric altitude plus the estimated offset: z = dh - d(offset)."""

    altitude_m: float
    sigma: float

    def observe(self, s: NavState, c_bn: np.ndarray, n: int) -> Observation:
        h = np.zeros((1, n))
        h[0, P_ID + 2] = -1.0  # dh = -dr_D
        h[0, DH_ID] = -1.0
        return Observation("baro", np.array((s.h - (self.altitude_m + s.dh),)), h, np.array((self.sigma**2,)))


@dataclass
class ZeroMotion:
    """Eq. 12 while stopped: the velocity is zero and the gyro (its raw mean over the stop so far, less the
    estimated offset) senses only the earth's rotation."""

    gyro_mean: np.ndarray
    sigma_v: float
    sigma_w: float

    def observe(self, s: NavState, c_bn: np.ndarray, n: int) -> Observation:
        w_ie_b = c_bn.T @ np.array(earth.earth_rate_ned(s.lat))
        z = np.concatenate(((s.vn, s.ve, s.vd), self.gyro_mean - np.array(s.bg) - w_ie_b))
        h = np.zeros((6, n))
        h[_I3, V_ID + _I3] = 1.0
        h[3 + _I3, BG_ID + _I3] = -1.0  # w_hat = w - dbg
        r = np.array([self.sigma_v**2] * 3 + [self.sigma_w**2] * 3)
        return Observation("zupt", z, h, r)


@functools.lru_cache(maxsize=64)
def chi2_gate(m: int, probability: float) -> float:
    """Chi-square quantile with ``m`` degrees of freedom, by bisection on the regularised incomplete gamma
    function (kept per dimension and probability: a filter started again, as at each restart, asks for the same
    six, and the bisection costs a millisecond each)."""
    lo, hi = 0.0, 10.0 * m + 100.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if _lower_gamma_regularised(0.5 * m, 0.5 * mid) < probability:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _lower_gamma_regularised(a: float, x: float) -> float:
    """P(a, x) by its power series (converges for every x; a few hundred terms at most here)."""
    if x <= 0.0:
        return 0.0
    term = 1.0 / a
    total = term
    k = 0
    while term > total * 1e-16 and k < 10000:
        k += 1
        term *= x / (a + k)
        total += term
    return min(1.0, total * math.exp(-x + a * math.log(x) - math.lgamma(a)))
