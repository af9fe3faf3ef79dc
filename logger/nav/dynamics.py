"""Error dynamics and process noise: the transition matrix F_k and W_k of the paper's Eq. 7.

The INS block follows the psi-angle error model (Titterton & Weston, eq. 12.6 and 12.11) with the error
convention of :mod:`logger.nav.state` (estimated minus true):

    d(dr)/dt  = dv
    d(dv)/dt  = [f_n x] phi - C_bn dba - [(2 w_ie + w_en) x] dv + (2 g / R) dr_D e_D
    d(phi)/dt = -[w_in x] phi + dw_in(dr, dv) + C_bn dbg
    biases, scale factor and height offset: random walks

Terms of the order of v / R (transport-rate coupling of position errors) are dropped: a land vehicle's
speed makes them a few parts per million of what is kept. The covariance is propagated at a lower rate than
the mechanization, with a second-order transition matrix and the trapezoidal discrete process noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from logger.nav import earth
from logger.nav.state import BA_ID, BG_ID, DH_ID, P_ID, PHI_ID, RQ_ID, SF_ID, V_ID, NavState


@dataclass(frozen=True)
class ProcessNoise:
    """Continuous-time noise densities of the state's driving white noise (all SI, per sqrt(s))."""

    accel_vrw: float  # velocity random walk, m/s^2/sqrt(Hz) = m/s/sqrt(s)
    gyro_arw: float  # angle random walk, rad/s/sqrt(Hz) = rad/sqrt(s)
    accel_bias_walk: float  # m/s^2/sqrt(s)
    gyro_bias_walk: float  # rad/s/sqrt(s)
    scale_walk: float  # 1/sqrt(s)
    height_offset_walk: float  # m/sqrt(s)
    rounding_walk: float = 0.0  # m/s/sqrt(s): the true speed's drift inside one OBD reading's step

    def diagonal(self, n: int) -> np.ndarray:
        q = np.zeros(n)
        q[V_ID:V_ID + 3] = self.accel_vrw**2
        q[PHI_ID:PHI_ID + 3] = self.gyro_arw**2
        q[BA_ID:BA_ID + 3] = self.accel_bias_walk**2
        q[BG_ID:BG_ID + 3] = self.gyro_bias_walk**2
        if n > SF_ID:
            q[SF_ID] = self.scale_walk**2
            q[DH_ID] = self.height_offset_walk**2
        if n > RQ_ID:
            q[RQ_ID] = self.rounding_walk**2
        return q


def error_dynamics(s: NavState, c_bn: np.ndarray | tuple[float, ...], f_ned: tuple[float, float, float],
                   n: int) -> np.ndarray:
    """The continuous-time error dynamics matrix F (n x n) at the nominal state ``s``; ``c_bn`` the attitude as a
    matrix or its nine elements row by row (:func:`logger.nav.rotations.dcm_elements`).

    Built from a template holding the constant entries, the rest put in at their flat indices in one call (a
    slice assignment per block cost as much as the covariance propagation it serves)."""
    lat, h = s.lat, s.h
    rm, rn = earth.radii(lat)
    rmh, rnh = rm + h, rn + h
    sl, cl = math.sin(lat), math.cos(lat)
    tl = sl / cl
    om = earth.OMEGA_IE
    wie_n, wie_d = om * cl, -om * sl
    wen_n, wen_e, wen_d = s.ve / rnh, -s.vn / rmh, -s.ve * tl / rnh
    g = earth.gravity(lat, h)
    # -[(2 w_ie + w_en) x] on the velocity error
    a, b, c = 2.0 * wie_n + wen_n, wen_e, 2.0 * wie_d + wen_d
    fn, fe, fd = f_ned
    # -[w_in x] on the attitude error
    a2, b2, c2 = wie_n + wen_n, wen_e, wie_d + wen_d
    c11, c12, c13, c21, c22, c23, c31, c32, c33 = c_bn.ravel().tolist() if isinstance(c_bn, np.ndarray) else c_bn
    values = (
        c, -b, -c, a, b, -a,  # V, V
        -fd, fe, fd, -fn, -fe, fn,  # V, PHI: [f_n x]
        -c11, -c12, -c13, -c21, -c22, -c23, -c31, -c32, -c33,  # V, BA: -C_bn
        2.0 * g / math.sqrt(rmh * rnh),  # V_D, P_D
        c2, -b2, -c2, a2, b2, -a2,  # PHI, PHI
        # d(w_in)/d(dv): the transport rate's dependence on velocity.
        1.0 / rnh, -1.0 / rmh, -tl / rnh,
        # d(w_ie)/d(dr_N): a latitude error turns the earth rate vector.
        -om * sl / rmh, -om * cl / rmh,
        c11, c12, c13, c21, c22, c23, c31, c32, c33,  # PHI, BG: C_bn
    )
    template, index = _f_template(n)
    f = template.copy()
    f.put(index, values)
    return f


_F_TEMPLATES: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _f_template(n: int) -> tuple[np.ndarray, np.ndarray]:
    """F's constant entries for ``n`` states, and the flat indices of the entries :func:`error_dynamics` fills."""
    t = _F_TEMPLATES.get(n)
    if t is None:
        f = np.zeros((n, n))
        f[P_ID, V_ID] = f[P_ID + 1, V_ID + 1] = f[P_ID + 2, V_ID + 2] = 1.0
        v, ph, ba, bg, p = V_ID, PHI_ID, BA_ID, BG_ID, P_ID
        cells = [(v, v + 1), (v, v + 2), (v + 1, v), (v + 1, v + 2), (v + 2, v), (v + 2, v + 1),
                 (v, ph + 1), (v, ph + 2), (v + 1, ph), (v + 1, ph + 2), (v + 2, ph), (v + 2, ph + 1)]
        cells += [(v + i, ba + j) for i in range(3) for j in range(3)]
        cells += [(v + 2, p + 2)]
        cells += [(ph, ph + 1), (ph, ph + 2), (ph + 1, ph), (ph + 1, ph + 2), (ph + 2, ph), (ph + 2, ph + 1)]
        cells += [(ph, v + 1), (ph + 1, v), (ph + 2, v + 1), (ph, p), (ph + 2, p)]
        cells += [(ph + i, bg + j) for i in range(3) for j in range(3)]
        t = _F_TEMPLATES[n] = (f, np.array([i * n + j for i, j in cells]))
    return t


def transition(f: np.ndarray, dt: float) -> np.ndarray:
    """Transition matrix over ``dt``, second order in F dt."""
    fdt = f * dt
    phi = np.dot(fdt, fdt)  # the same product as @ with less of the ufunc machinery's dispatch
    phi *= 0.5
    phi += fdt
    phi += _eye(f.shape[0])  # the identity added whole: one call, where indexing the diagonal took three
    return phi


def discretize(f: np.ndarray, q_diag: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition matrix (second order in F dt) and discrete process noise (trapezoid) over ``dt``:
    Q_d = (Phi Q Phi^T + Q) dt / 2. (:meth:`logger.nav.ekf.ErrorStateEkf.propagate_trapezoid` applies the same
    without forming Q_d.)"""
    phi = transition(f, dt)
    d = _diag(f.shape[0])
    qd = (phi * q_diag) @ phi.T
    qd[d, d] += q_diag
    qd *= 0.5 * dt
    return phi, qd


_DIAG: dict[int, np.ndarray] = {}
_EYE: dict[int, np.ndarray] = {}


def _eye(n: int) -> np.ndarray:
    """The n x n identity, made once (read only: it is shared)."""
    e = _EYE.get(n)
    if e is None:
        e = _EYE[n] = np.eye(n)
        e.flags.writeable = False
    return e


def _diag(n: int) -> np.ndarray:
    """Indices of a diagonal (numpy's own helper costs more than the 17x17 product it serves)."""
    d = _DIAG.get(n)
    if d is None:
        d = _DIAG[n] = np.arange(n)
    return d
