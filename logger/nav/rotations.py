"""Rotations: direction cosine matrices, quaternions, Euler angles and skew matrices as small pure functions.

Conventions (those of KF-GINS and of the simulator's truth): body axes forward-right-down, navigation axes
north-east-down, Euler angles roll-pitch-yaw in z-y-x order, ``C_bn`` maps body vectors into NED,
quaternions are scalar-first and rotate body into NED.
"""

from __future__ import annotations

import math

import numpy as np


def skew(v: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """The matrix ``[v x]`` with ``skew(a) @ b == cross(a, b)``."""
    x, y, z = v.tolist() if isinstance(v, np.ndarray) else v
    return np.array(((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0)))


def dcm_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """C_bn from roll, pitch, yaw (rad)."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), \
        math.sin(yaw)
    return np.array([
        [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
        [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
        [-sp, sr * cp, cr * cp],
    ])


def euler_from_dcm(c: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad) of C_bn; yaw in (-pi, pi]."""
    pitch = math.atan2(-c[2, 0], math.hypot(c[2, 1], c[2, 2]))
    return math.atan2(c[2, 1], c[2, 2]), pitch, math.atan2(c[1, 0], c[0, 0])


def quat_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy)


def dcm_elements(q: tuple[float, float, float, float]) -> tuple[float, ...]:
    """The nine elements of :func:`dcm_from_quat`, row by row, as plain floats (no array to build)."""
    w, x, y, z = q
    return (w * w + x * x - y * y - z * z, 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), w * w - x * x + y * y - z * z, 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z)


def dcm_from_quat(q: tuple[float, float, float, float]) -> np.ndarray:
    w, x, y, z = q
    return np.array([
        [w * w + x * x - y * y - z * z, 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), w * w - x * x + y * y - z * z, 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z],
    ])


def quat_from_dcm(c: np.ndarray) -> tuple[float, float, float, float]:
    """Scalar-first quaternion of a rotation matrix (Shepperd's method: stable for every rotation)."""
    tr = float(c[0, 0] + c[1, 1] + c[2, 2])
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (c[2, 1] - c[1, 2]) / s, (c[0, 2] - c[2, 0]) / s, (c[1, 0] - c[0, 1]) / s)
    elif c[0, 0] > c[1, 1] and c[0, 0] > c[2, 2]:
        s = 2.0 * math.sqrt(1.0 + c[0, 0] - c[1, 1] - c[2, 2])
        q = ((c[2, 1] - c[1, 2]) / s, 0.25 * s, (c[0, 1] + c[1, 0]) / s, (c[0, 2] + c[2, 0]) / s)
    elif c[1, 1] > c[2, 2]:
        s = 2.0 * math.sqrt(1.0 + c[1, 1] - c[0, 0] - c[2, 2])
        q = ((c[0, 2] - c[2, 0]) / s, (c[0, 1] + c[1, 0]) / s, 0.25 * s, (c[1, 2] + c[2, 1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + c[2, 2] - c[0, 0] - c[1, 1])
        q = ((c[1, 0] - c[0, 1]) / s, (c[0, 2] + c[2, 0]) / s, (c[1, 2] + c[2, 1]) / s, 0.25 * s)
    w, x, y, z = (float(v) for v in q)
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    return w, x, y, z


def quat_mul(a: tuple[float, float, float, float],
             b: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def twist_about_x(c: np.ndarray) -> np.ndarray:
    """The part of rotation ``c`` about the x axis: T in c = S T, with S a swing (a rotation about an axis
    perpendicular to x) applied after the twist T (the swing-twist decomposition of its quaternion)."""
    w, x, _, _ = quat_from_dcm(c)
    n = math.hypot(w, x)
    if n < 1e-12:  # a half turn about an axis perpendicular to x: no twist to speak of
        return np.eye(3)
    return dcm_from_quat((w / n, x / n, 0.0, 0.0))


def quat_from_rotvec(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """Quaternion of a rotation vector (axis times angle, rad); series near zero keeps it exact and cheap."""
    a2 = x * x + y * y + z * z
    if a2 < 1e-8:
        # cos(a/2) and sin(a/2)/a to fourth order: exact in double precision below 1e-4 rad.
        c = 1.0 - a2 / 8.0 + a2 * a2 / 384.0
        s = 0.5 - a2 / 48.0
    else:
        a = math.sqrt(a2)
        c = math.cos(0.5 * a)
        s = math.sin(0.5 * a) / a
    return c, s * x, s * y, s * z


def quats_from_rotvecs(r: np.ndarray) -> np.ndarray:
    """:func:`quat_from_rotvec` of each row of ``r`` (n x 3), with the same series near zero."""
    a2 = np.einsum("ij,ij->i", r, r)
    small = a2 < 1e-8
    a = np.sqrt(np.where(small, 1.0, a2))  # the exact forms only where they are used: no 0 / 0
    c = np.where(small, 1.0 - a2 / 8.0 + a2 * a2 / 384.0, np.cos(0.5 * a))
    s = np.where(small, 0.5 - a2 / 48.0, np.sin(0.5 * a) / a)
    return np.column_stack((c, s[:, None] * r))


def quat_chain(q0: tuple[float, float, float, float], steps: list[list[float]]) -> list[tuple[float, ...]]:
    """The running products q0 x steps[0] x ... x steps[k] for every k: :func:`quat_mul` in a loop, inlined (a
    call per sample was most of its cost; numpy's passes over a FIFO read's forty cost more than the loop)."""
    aw, ax, ay, az = q0
    out = []
    for bw, bx, by, bz in steps:
        aw, ax, ay, az = (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                          aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)
        out.append((aw, ax, ay, az))
    return out


def rotvec_from_dcm(c: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix."""
    w, x, y, z = quat_from_dcm(c)
    n = math.sqrt(x * x + y * y + z * z)
    if n < 1e-12:
        return np.array([x, y, z]) * 2.0
    angle = 2.0 * math.atan2(n, w)
    return np.array([x, y, z]) * (angle / n)


def wrap_pi(a: float) -> float:
    return math.remainder(a, 2.0 * math.pi)
