"""WGS-84 earth model and rotations: tiny pure functions the truth model and device models share."""

from __future__ import annotations

import math

import numpy as np

A = 6378137.0  # semi-major axis, m
F = 1 / 298.257223563
E2 = F * (2 - F)  # first eccentricity squared
OMEGA_IE = 7.292115e-5  # earth rotation rate, rad/s
GM = 3.986004418e14
# Somigliana normal gravity constants
GAMMA_E = 9.7803253359
K_SOMIGLIANA = 0.00193185265241
M_RATIO = OMEGA_IE**2 * A**2 * (A * (1 - F)) / GM


def radii(lat_rad: float) -> tuple[float, float]:
    """Meridian (north) and prime-vertical (east) radii of curvature, m."""
    s2 = math.sin(lat_rad) ** 2
    w = math.sqrt(1 - E2 * s2)
    return A * (1 - E2) / w**3, A / w


def ecef(lat_rad: float, lon_rad: float, height_m: float) -> np.ndarray:
    """Earth-centred earth-fixed position (m) of a point given on the WGS-84 ellipsoid."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    rn = A / math.sqrt(1 - E2 * sl * sl)
    return np.array(((rn + height_m) * cl * math.cos(lon_rad), (rn + height_m) * cl * math.sin(lon_rad),
                     (rn * (1 - E2) + height_m) * sl))


def dcm_ned_to_ecef(lat_rad: float, lon_rad: float) -> np.ndarray:
    """Rotation taking north-east-down vectors at a point into the earth-fixed frame (columns: N, E, D)."""
    sl, cl, so, co = math.sin(lat_rad), math.cos(lat_rad), math.sin(lon_rad), math.cos(lon_rad)
    return np.array([[-sl * co, -so, -cl * co], [-sl * so, co, -cl * so], [cl, 0.0, -sl]])


def gravity_ned(lat_rad: float, height_m: float) -> np.ndarray:
    """Normal gravity vector (NED, m/s^2) from Somigliana's formula with the free-air height term."""
    s2 = math.sin(lat_rad) ** 2
    g0 = GAMMA_E * (1 + K_SOMIGLIANA * s2) / math.sqrt(1 - E2 * s2)
    g = g0 * (1 - 2 / A * (1 + F + M_RATIO - 2 * F * s2) * height_m + 3 * height_m**2 / A**2)
    return np.array([0.0, 0.0, g])


def earth_rate_ned(lat_rad: float) -> np.ndarray:
    return np.array([OMEGA_IE * math.cos(lat_rad), 0.0, -OMEGA_IE * math.sin(lat_rad)])


def transport_rate_ned(lat_rad: float, height_m: float, vel_ned: np.ndarray) -> np.ndarray:
    rn, re = radii(lat_rad)
    vn, ve = float(vel_ned[0]), float(vel_ned[1])
    return np.array([ve / (re + height_m), -vn / (rn + height_m), -ve * math.tan(lat_rad) / (re + height_m)])


def dcm_body_to_ned(rpy_rad: np.ndarray) -> np.ndarray:
    """Direction cosine matrix C_b^n from roll, pitch, yaw (aerospace z-y-x order)."""
    r, p, y = (float(a) for a in rpy_rad)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([
        [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
        [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
        [-sp, sr * cp, cr * cp],
    ])
