"""Strapdown mechanization in a local-level NED frame on WGS-84 (Titterton & Weston ch. 3; KF-GINS insmech).

The inner loop of the filter: it runs once per IMU sample (or once per step of several samples of a fast IMU's
FIFO block, :func:`preintegrate`), so it is written with plain floats (a 3x3 numpy product costs more than the
whole step here). Each step integrates the interval between two samples:

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
from collections.abc import Sequence

import numpy as np

from logger.nav import earth
from logger.nav.state import NavState

_OMEGA = earth.OMEGA_IE
_sqrt, _sin, _cos = math.sqrt, math.sin, math.cos  # module globals: one lookup where math.x takes two


class Strapdown:
    """Integrates IMU samples into a :class:`NavState`; remembers the previous sample and increments."""

    def __init__(self, coning: bool = False) -> None:
        self.coning = coning
        self._w: tuple[float, float, float] | None = None  # previous bias-corrected rate, rad/s
        self._f: tuple[float, float, float] = (0.0, 0.0, 0.0)  # previous bias-corrected specific force
        self._th = (0.0, 0.0, 0.0)  # previous angle increment
        self._dv = (0.0, 0.0, 0.0)  # previous velocity increment
        # Sum of the specific force's velocity increments in NED since the caller last cleared it: the mean
        # specific force of a covariance interval is this over its length (what the error dynamics need).
        self.dv_ned_sum = [0.0, 0.0, 0.0]
        self._dv_ned = (0.0, 0.0, -earth.G0)  # the last step's increment in NED, and its interval
        self._dt = 1.0
        self._geo: tuple[float, ...] = _NO_GEOMETRY

    @property
    def f_ned(self) -> tuple[float, float, float]:
        """The last step's specific force in NED, m/s^2."""
        dn, de, dd = self._dv_ned
        dt = self._dt
        return dn / dt, de / dt, dd / dt

    def reset(self) -> None:
        self._w = None

    @property
    def ready(self) -> bool:
        """Whether a previous sample is there to integrate the next interval from."""
        return self._w is not None

    @property
    def last_rate(self) -> tuple[float, float, float]:
        """The previous sample's bias-corrected rate (rad/s); meaningful when :attr:`ready`."""
        return self._w or (0.0, 0.0, 0.0)

    @property
    def last_force(self) -> tuple[float, float, float]:
        return self._f

    def prime(self, w: tuple[float, float, float], f: tuple[float, float, float]) -> None:
        """Start from a sample without integrating (the first one, or after a gap)."""
        self._w, self._f = w, f
        self._th = self._dv = (0.0, 0.0, 0.0)

    def step(self, s: NavState, w: tuple[float, float, float], f: tuple[float, float, float], dt: float) -> None:
        """Advance ``s`` by ``dt`` seconds to the sample whose bias-corrected rate is ``w`` and force ``f``."""
        pw = self._w
        if pw is None:
            self.prime(w, f)
            return
        # Locals and unpacking throughout: an attribute or an index costs as much as the arithmetic it feeds.
        pwx, pwy, pwz = pw
        pfx, pfy, pfz = self._f
        h2 = 0.5 * dt
        wx, wy, wz = w
        fx, fy, fz = f
        tx, ty, tz = (pwx + wx) * h2, (pwy + wy) * h2, (pwz + wz) * h2
        ux, uy, uz = (pfx + fx) * h2, (pfy + fy) * h2, (pfz + fz) * h2
        # Rotation compensation: the velocity increment is taken in the body frame as it turns.
        dx = ux + 0.5 * (ty * uz - tz * uy)
        dy = uy + 0.5 * (tz * ux - tx * uz)
        dz = uz + 0.5 * (tx * uy - ty * ux)
        if self.coning:
            (px, py, pz), (qx, qy, qz) = self._th, self._dv
            # Two-sample coning and sculling with the previous interval (Savage, Strapdown Analytics 7.1).
            rx = tx + (py * tz - pz * ty) / 12.0
            ry = ty + (pz * tx - px * tz) / 12.0
            rz = tz + (px * ty - py * tx) / 12.0
            dx += ((py * uz - pz * uy) + (qy * tz - qz * ty)) / 12.0
            dy += ((pz * ux - px * uz) + (qz * tx - qx * tz)) / 12.0
            dz += ((px * uy - py * ux) + (qx * ty - qy * tx)) / 12.0
        else:
            rx, ry, rz = tx, ty, tz
        self._w, self._f, self._th, self._dv = w, f, (tx, ty, tz), (ux, uy, uz)
        self._advance(s, rx, ry, rz, dx, dy, dz, dt)

    def step_increments(self, s: NavState, r: Sequence[float], d: Sequence[float], dt: float) -> None:
        """Advance ``s`` by one step of several samples (:func:`preintegrate`): ``r`` the body's rotation vector over
        it and ``d`` its velocity increment (rad, m/s; coning, sculling and rotation compensation included), ``dt``
        its length. :meth:`continue_from` then says which sample the next single-sample step starts from."""
        self._advance(s, r[0], r[1], r[2], d[0], d[1], d[2], dt)

    def continue_from(self, w: Sequence[float], f: Sequence[float], w_prev: Sequence[float],
                      f_prev: Sequence[float], dt: float) -> None:
        """The last sample integrated by steps (its bias-corrected rate and force), and the one before it ``dt``
        earlier: the next single-sample step integrates from them, its coning and sculling against their interval."""
        h = 0.5 * dt
        self._w, self._f = (w[0], w[1], w[2]), (f[0], f[1], f[2])
        self._th = ((w_prev[0] + w[0]) * h, (w_prev[1] + w[1]) * h, (w_prev[2] + w[2]) * h)
        self._dv = ((f_prev[0] + f[0]) * h, (f_prev[1] + f[1]) * h, (f_prev[2] + f[2]) * h)

    def _advance(self, s: NavState, rx: float, ry: float, rz: float, dx: float, dy: float, dz: float,
                 dt: float) -> None:
        """The navigation frame's half of a step: the body increments (rotation vector r, velocity increment d) over
        ``dt`` turned into attitude, velocity and position."""
        lat, h, vn, ve, vd = s.lat, s.h, s.vn, s.ve, s.vd
        glat, gh, tl, rn, rm, g, wie_n, wie_d, wie2_n, wie2_d = self._geo
        if abs(lat - glat) > 1e-6 or abs(h - gh) > 1.0:
            # Radii, earth rate and gravity change by parts per million over 6 m of latitude or 1 m of height:
            # computed again only then (a third of the step's cost otherwise).
            glat, gh, tl, rn, rm, g, wie_n, wie_d, wie2_n, wie2_d = self._geo = _geometry(lat, h)
        rnh = rn + h
        wen_n, wen_e = ve / rnh, -vn / (rm + h)
        wen_d = -wen_n * tl
        zn, ze, zd = (wie_n + wen_n) * dt, wen_e * dt, (wie_d + wen_d) * dt  # rotation of NED over the step

        qw, qx, qy, qz = s.q
        # The velocity increment turned to NED by the attitude quaternion: v + 2 qw (u x v) + 2 u x (u x v).
        ax_, ay_, az_ = 2.0 * (qy * dz - qz * dy), 2.0 * (qz * dx - qx * dz), 2.0 * (qx * dy - qy * dx)
        fn = dx + qw * ax_ + (qy * az_ - qz * ay_)
        fe = dy + qw * ay_ + (qz * ax_ - qx * az_)
        fd = dz + qw * az_ + (qx * ay_ - qy * ax_)
        # (I - 1/2 [zeta x]) applied to the NED increment: the frame turned under it by zeta.
        fn, fe, fd = (fn - 0.5 * (ze * fd - zd * fe), fe - 0.5 * (zd * fn - zn * fd), fd - 0.5 * (zn * fe - ze * fn))
        self._dv_ned = (fn, fe, fd)
        self._dt = dt
        acc = self.dv_ned_sum
        acc[0] += fn
        acc[1] += fe
        acc[2] += fd
        cx, cz = wie2_n + wen_n, wie2_d + wen_d
        vn2 = vn + fn - (wen_e * vd - cz * ve) * dt
        ve2 = ve + fe - (cz * vn - cx * vd) * dt
        vd2 = vd + fd + (g - (cx * ve - wen_e * vn)) * dt
        h2_ = h - 0.5 * (vd + vd2) * dt
        hm = 0.5 * (h + h2_)
        lat2 = lat + 0.5 * (vn + vn2) * dt / (rm + hm)
        s.lon += 0.5 * (ve + ve2) * dt / ((rn + hm) * _cos(0.5 * (lat + lat2)))
        s.lat, s.h, s.vn, s.ve, s.vd = lat2, h2_, vn2, ve2, vd2
        # q <- q(-zeta) * q * q(r); the body increment through its exact quaternion, the navigation frame's
        # (a few 1e-5 rad per step) to first order, which is exact to 1e-10 rad.
        a2 = rx * rx + ry * ry + rz * rz
        if a2 < 1e-8:
            cq, sq = 1.0 - a2 / 8.0 + a2 * a2 / 384.0, 0.5 - a2 / 48.0
        else:
            an = _sqrt(a2)
            cq, sq = _cos(0.5 * an), _sin(0.5 * an) / an
        bx, by, bz = sq * rx, sq * ry, sq * rz
        aw = qw * cq - qx * bx - qy * by - qz * bz
        ax = qw * bx + qx * cq + qy * bz - qz * by
        ay = qw * by - qx * bz + qy * cq + qz * bx
        az = qw * bz + qx * by - qy * bx + qz * cq
        hn, he, hd = -0.5 * zn, -0.5 * ze, -0.5 * zd
        w_ = aw - hn * ax - he * ay - hd * az
        x_ = ax + hn * aw + he * az - hd * ay
        y_ = ay - hn * az + he * aw + hd * ax
        z_ = az + hn * ay - he * ax + hd * aw
        k = 1.0 / _sqrt(w_ * w_ + x_ * x_ + y_ * y_ + z_ * z_)
        s.q = (w_ * k, x_ * k, y_ * k, z_ * k)


def _geometry(lat: float, h: float) -> tuple[float, ...]:
    """(lat, h, tan lat, R_N, R_M, gravity, earth rate north and down, and twice those two) at a point: the slowly
    varying part of a step."""
    sl, cl = math.sin(lat), math.cos(lat)
    w2 = 1.0 - earth.E2 * sl * sl
    rn = earth.A / math.sqrt(w2)
    wie_n, wie_d = _OMEGA * cl, -_OMEGA * sl
    return lat, h, sl / cl, rn, rn * (1.0 - earth.E2) / w2, earth.gravity(lat, h), wie_n, wie_d, 2.0 * wie_n, \
        2.0 * wie_d


_NEXT, _AFTER = [1, 2, 0], [2, 0, 1]  # axis orders of a cross product's two terms

# No point yet: every latitude is further than the threshold from it.
_NO_GEOMETRY = (math.inf, math.inf, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def preintegrate(w: np.ndarray, f: np.ndarray, dts: np.ndarray, starts: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Body increments of consecutive groups of samples, for a strapdown step per group rather than per sample.

    ``w``, ``f``: (m + 1) x 3 bias-corrected rates and forces, the sample before the first interval first; ``dts``:
    the m intervals (s); ``starts``: the first interval of each group (0 first, increasing). Each interval's
    increments are the trapezoid of its two samples, as :meth:`Strapdown.step` takes them. Over a group, with
    alpha the angle summed since the group's start, the rotation vector is sum(theta) + 1/2 sum(alpha x theta)
    (Bortz's equation to second order: the coning of the samples inside the group) and the velocity increment in
    the group's starting body frame sum(u) + sum(alpha x u + 1/2 theta x u) (the body turning under the force:
    rotation compensation and sculling; Savage, Strapdown Analytics 7.2). One sample per group gives exactly the
    single step's rotation compensation. Returns (rotation vectors, velocity increments, group lengths in s)."""
    m = len(dts)
    h = 0.5 * dts[:, None]
    th = (w[:-1] + w[1:]) * h
    u = (f[:-1] + f[1:]) * h
    a = np.cumsum(th, axis=0)
    before = a[starts - 1]  # the angle summed up to each group's start
    before[0] = 0.0
    prev = a - th - np.repeat(before, np.diff(starts, append=m), axis=0)  # alpha before each interval
    # The three cross products at once (prev x theta, prev x u, theta x u), by columns: numpy's cross costs twice.
    x, y = np.concatenate((prev, prev, th)), np.concatenate((th, u, u))
    c = x[:, _NEXT] * y[:, _AFTER] - x[:, _AFTER] * y[:, _NEXT]
    rot = np.add.reduceat(th + 0.5 * c[:m], starts, axis=0)
    dv = np.add.reduceat(u + c[m:2 * m] + 0.5 * c[2 * m:], starts, axis=0)
    return rot, dv, np.add.reduceat(dts, starts)
