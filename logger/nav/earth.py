"""WGS-84 earth model: tiny pure functions (radii, normal gravity, earth and transport rates).

Kept apart from the simulator's own copy on purpose: the filter must not share code paths with the model
that makes the test data, or an error in one would hide in the other.
"""

from __future__ import annotations

import math

A = 6378137.0  # semi-major axis, m
F = 1.0 / 298.257223563  # flattening
E2 = F * (2.0 - F)  # first eccentricity squared
OMEGA_IE = 7.292115e-5  # earth rotation rate, rad/s
GM = 3.986004418e14  # m^3/s^2
GAMMA_E = 9.7803253359  # normal gravity at the equator, m/s^2
K_SOMIGLIANA = 0.00193185265241
M_RATIO = OMEGA_IE**2 * A**2 * (A * (1.0 - F)) / GM
G0 = 9.80665  # standard gravity, m/s^2: the g of datasheet figures in g and of the paper's Eq. 4


def radii(lat_rad: float) -> tuple[float, float]:
    """Meridian (north) radius R_M and prime-vertical (east) radius R_N of curvature, m."""
    s2 = math.sin(lat_rad) ** 2
    w = math.sqrt(1.0 - E2 * s2)
    return A * (1.0 - E2) / (w * w * w), A / w


def gravity(lat_rad: float, height_m: float) -> float:
    """Magnitude of normal gravity (Somigliana, with the free-air terms to second order in height), m/s^2."""
    s2 = math.sin(lat_rad) ** 2
    g0 = GAMMA_E * (1.0 + K_SOMIGLIANA * s2) / math.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 / A * (1.0 + F + M_RATIO - 2.0 * F * s2) * height_m + 3.0 * height_m**2 / A**2)


def earth_rate_ned(lat_rad: float) -> tuple[float, float, float]:
    """Earth rotation expressed in NED, rad/s."""
    return OMEGA_IE * math.cos(lat_rad), 0.0, -OMEGA_IE * math.sin(lat_rad)


def transport_rate_ned(lat_rad: float, height_m: float, vn: float, ve: float) -> tuple[float, float, float]:
    """Rotation of the NED frame over the ellipsoid as the vehicle moves, rad/s."""
    rm, rn = radii(lat_rad)
    return ve / (rn + height_m), -vn / (rm + height_m), -ve * math.tan(lat_rad) / (rn + height_m)


def ned_offset_m(lat0_rad: float, lon0_rad: float, h0_m: float, lat_rad: float, lon_rad: float,
                 h_m: float) -> tuple[float, float, float]:
    """North, east, down metres from point 0 to a nearby point, on the local curvature (good to ~1 ppm per km)."""
    rm, rn = radii(lat0_rad)
    return ((lat_rad - lat0_rad) * (rm + h0_m),
            math.remainder(lon_rad - lon0_rad, 2.0 * math.pi) * (rn + h0_m) * math.cos(lat0_rad),
            h0_m - h_m)


def offset_llh(lat_rad: float, lon_rad: float, h_m: float, dn: float, de: float,
               dd: float) -> tuple[float, float, float]:
    """The point ``dn, de, dd`` metres (NED) away from the given one."""
    rm, rn = radii(lat_rad)
    return lat_rad + dn / (rm + h_m), lon_rad + de / ((rn + h_m) * math.cos(lat_rad)), h_m - dd


def ecef_from_llh(lat_rad: float, lon_rad: float, h_m: float) -> tuple[float, float, float]:
    """Earth-centred, earth-fixed x, y, z of a geodetic point, m."""
    n = A / math.sqrt(1.0 - E2 * math.sin(lat_rad) ** 2)
    c = (n + h_m) * math.cos(lat_rad)
    return c * math.cos(lon_rad), c * math.sin(lon_rad), (n * (1.0 - E2) + h_m) * math.sin(lat_rad)


def llh_from_ecef(x: float, y: float, z: float) -> tuple[float, float, float]:
    """Geodetic latitude, longitude (rad) and height (m) of an ECEF point: the fixed-point iteration RTKLIB's
    ecef2pos uses (converged to 0.1 mm)."""
    r2 = x * x + y * y
    v, z_ = A, z
    for _ in range(20):
        zk = z_
        sinp = z_ / math.sqrt(r2 + z_ * z_)
        v = A / math.sqrt(1.0 - E2 * sinp * sinp)
        z_ = z + v * E2 * sinp
        if abs(z_ - zk) < 1e-4:
            break
    lat = math.atan(z_ / math.sqrt(r2)) if r2 > 1e-12 else (math.pi / 2.0 if z > 0.0 else -math.pi / 2.0)
    return lat, math.atan2(y, x) if r2 > 1e-12 else 0.0, math.sqrt(r2 + z_ * z_) - v


def ned_rows(lat_rad: float, lon_rad: float) -> tuple[tuple[float, float, float], ...]:
    """North, east and down as ECEF unit vectors (the rows of the ECEF-to-NED rotation)."""
    sp, cp, sl, cl = math.sin(lat_rad), math.cos(lat_rad), math.sin(lon_rad), math.cos(lon_rad)
    return (-sp * cl, -sp * sl, cp), (-sl, cl, 0.0), (-cp * cl, -cp * sl, -sp)
