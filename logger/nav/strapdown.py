"""Strapdown mechanization in a local-level NED frame on WGS-84 (Titterton & Weston ch. 3; KF-GINS insmech).

The inner loop of the filter: it runs once per IMU sample, so it is written with plain floats (a 3x3 numpy
product costs more than the whole step here). Each step integrates the interval between two samples:

- increments by the trapezoid rule on the bias-corrected rates of both ends (the MPU-6050 delivers point
  samples of rate, not increments);
- rotation compensation of the velocity increment (1/2 theta x dv), and, when the IMU runs fast enough for
  it to matter (``coning``), the two-sample coning and sculling corrections with the previous interval;
- velocity with gravity (Somigliana), Coriolis and transport-rate terms, and the rotation of the navigation
  frame over the step;
- position with the mean velocity on the radii of curvature, attitude as a quaternion rotated by the body
  increment on the right and by the navigation frame's rotation on the left, renormalised.
"""

from __future__ import annotations

import math

from logger.nav import earth
from logger.nav.state import NavState

_OMEGA = earth.OMEGA_IE


class Strapdown:
    """Integrates IMU samples into a :class:`NavState`; remembers the previous sample and increments."""

    def __init__(self, coning: bool = False) -> None:
        self.coning = coning
        self._w: tuple[float, float, float] | None = None  # previous bias-corrected rate, rad/s
        self._f: tuple[float, float, float] = (0.0, 0.0, 0.0)  # previous bias-corrected specific force
        self._th = (0.0, 0.0, 0.0)  # previous angle increment
        self._dv = (0.0, 0.0, 0.0)  # previous velocity increment
        self.f_ned = (0.0, 0.0, -earth.G0)  # last specific force in NED: what the error dynamics need
        self._geo: tuple[float, ...] | None = None

    def reset(self) -> None:
        self._w = None

    def prime(self, w: tuple[float, float, float], f: tuple[float, float, float]) -> None:
        """Start from a sample without integrating (the first one, or after a gap)."""
        self._w, self._f = w, f
        self._th = self._dv = (0.0, 0.0, 0.0)

    def step(self, s: NavState, w: tuple[float, float, float], f: tuple[float, float, float], dt: float) -> None:
        """Advance ``s`` by ``dt`` seconds to the sample whose bias-corrected rate is ``w`` and force ``f``."""
        if self._w is None:
            self.prime(w, f)
            return
        pw, pf = self._w, self._f
        h2 = 0.5 * dt
        tx, ty, tz = (pw[0] + w[0]) * h2, (pw[1] + w[1]) * h2, (pw[2] + w[2]) * h2
        ux, uy, uz = (pf[0] + f[0]) * h2, (pf[1] + f[1]) * h2, (pf[2] + f[2]) * h2
        # Rotation compensation: the velocity increment is taken in the body frame as it turns.
        dx = ux + 0.5 * (ty * uz - tz * uy)
        dy = uy + 0.5 * (tz * ux - tx * uz)
        dz = uz + 0.5 * (tx * uy - ty * ux)
        rx, ry, rz = tx, ty, tz
        if self.coning:
            (px, py, pz), (qx, qy, qz) = self._th, self._dv
            # Two-sample coning and sculling with the previous interval (Savage, Strapdown Analytics 7.1).
            rx += (py * tz - pz * ty) / 12.0
            ry += (pz * tx - px * tz) / 12.0
            rz += (px * ty - py * tx) / 12.0
            dx += ((py * uz - pz * uy) + (qy * tz - qz * ty)) / 12.0
            dy += ((pz * ux - px * uz) + (qz * tx - qx * tz)) / 12.0
            dz += ((px * uy - py * ux) + (qx * ty - qy * tx)) / 12.0
        self._w, self._f, self._th, self._dv = w, f, (tx, ty, tz), (ux, uy, uz)

        lat, h, vn, ve, vd = s.lat, s.h, s.vn, s.ve, s.vd
        geo = self._geo
        if geo is None or abs(lat - geo[0]) > 1e-6 or abs(h - geo[1]) > 1.0:
            # Radii, earth rate and gravity change by parts per million over 6 m of latitude or 1 m of height:
            # computed again only then (a third of the step's cost otherwise).
            geo = self._geo = _geometry(lat, h)
        _, _, sl, cl, rn, rm, g = geo
        rnh, rmh = rn + h, rm + h
        wie_n, wie_d = _OMEGA * cl, -_OMEGA * sl
        wen_n, wen_e, wen_d = ve / rnh, -vn / rmh, -ve * sl / cl / rnh
        zn, ze, zd = (wie_n + wen_n) * dt, wen_e * dt, (wie_d + wen_d) * dt  # rotation of NED over the step

        qw, qx_, qy_, qz_ = s.q
        # C_bn from the quaternion (rows), for the specific force.
        c11 = qw * qw + qx_ * qx_ - qy_ * qy_ - qz_ * qz_
        c12 = 2.0 * (qx_ * qy_ - qw * qz_)
        c13 = 2.0 * (qx_ * qz_ + qw * qy_)
        c21 = 2.0 * (qx_ * qy_ + qw * qz_)
        c22 = qw * qw - qx_ * qx_ + qy_ * qy_ - qz_ * qz_
        c23 = 2.0 * (qy_ * qz_ - qw * qx_)
        c31 = 2.0 * (qx_ * qz_ - qw * qy_)
        c32 = 2.0 * (qy_ * qz_ + qw * qx_)
        c33 = qw * qw - qx_ * qx_ - qy_ * qy_ + qz_ * qz_
        fn = c11 * dx + c12 * dy + c13 * dz
        fe = c21 * dx + c22 * dy + c23 * dz
        fd = c31 * dx + c32 * dy + c33 * dz
        # (I - 1/2 [zeta x]) applied to the NED increment: the frame turned under it by zeta.
        fn, fe, fd = (fn - 0.5 * (ze * fd - zd * fe), fe - 0.5 * (zd * fn - zn * fd), fd - 0.5 * (zn * fe - ze * fn))
        if dt > 0.0:
            self.f_ned = (fn / dt, fe / dt, fd / dt)
        cx, cy, cz = 2.0 * wie_n + wen_n, wen_e, 2.0 * wie_d + wen_d
        vn2 = vn + fn - (cy * vd - cz * ve) * dt
        ve2 = ve + fe - (cz * vn - cx * vd) * dt
        vd2 = vd + fd + (g - (cx * ve - cy * vn)) * dt
        h2_ = h - 0.5 * (vd + vd2) * dt
        hm = 0.5 * (h + h2_)
        lat2 = lat + 0.5 * (vn + vn2) * dt / (rm + hm)
        lm = 0.5 * (lat + lat2)
        s.lon += 0.5 * (ve + ve2) * dt / ((rn + hm) * math.cos(lm))
        s.lat, s.h, s.vn, s.ve, s.vd = lat2, h2_, vn2, ve2, vd2
        # q <- q(-zeta) * q * q(r); the body increment through its exact quaternion, the navigation frame's
        # (a few 1e-5 rad per step) to first order, which is exact to 1e-10 rad.
        a2 = rx * rx + ry * ry + rz * rz
        if a2 < 1e-8:
            cq, sq = 1.0 - a2 / 8.0 + a2 * a2 / 384.0, 0.5 - a2 / 48.0
        else:
            an = math.sqrt(a2)
            cq, sq = math.cos(0.5 * an), math.sin(0.5 * an) / an
        bx, by, bz = sq * rx, sq * ry, sq * rz
        aw = qw * cq - qx_ * bx - qy_ * by - qz_ * bz
        ax = qw * bx + qx_ * cq + qy_ * bz - qz_ * by
        ay = qw * by - qx_ * bz + qy_ * cq + qz_ * bx
        az = qw * bz + qx_ * by - qy_ * bx + qz_ * cq
        hn, he, hd = -0.5 * zn, -0.5 * ze, -0.5 * zd
        w_ = aw - hn * ax - he * ay - hd * az
        x_ = ax + hn * aw + he * az - hd * ay
        y_ = ay - hn * az + he * aw + hd * ax
        z_ = az + hn * ay - he * ax + hd * aw
        k = 1.0 / math.sqrt(w_ * w_ + x_ * x_ + y_ * y_ + z_ * z_)
        s.q = (w_ * k, x_ * k, y_ * k, z_ * k)


def _geometry(lat: float, h: float) -> tuple[float, ...]:
    """(lat, h, sin lat, cos lat, R_N, R_M, gravity) at a point: the slowly varying part of a step."""
    sl, cl = math.sin(lat), math.cos(lat)
    w2 = 1.0 - earth.E2 * sl * sl
    rn = earth.A / math.sqrt(w2)
    return lat, h, sl, cl, rn, rn * (1.0 - earth.E2) / w2, earth.gravity(lat, h)
