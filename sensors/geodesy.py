"""WGS-84 and the GPS time scale: what turns a GNSS receiver's numbers into positions and UTC.

Tiny pure functions. NAV-SOL reports ECEF only, so the decoder needs ECEF -> geodetic and the ECEF
velocity rotated into north-east-down; GPS week + time of week become Unix time with the leap seconds.
"""

from __future__ import annotations

import math

NS_PER_S = 1_000_000_000
GPS_EPOCH_UNIX_S = 315_964_800  # 1980-01-06T00:00:00Z
WEEK_S = 604_800

WGS84_A_M = 6_378_137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)


def ecef_to_geodetic(x_m: float, y_m: float, z_m: float) -> tuple[float, float, float]:
    """WGS-84 ECEF -> (lat_rad, lon_rad, height_hae_m), iterated to well below a millimetre."""
    lon = math.atan2(y_m, x_m)
    p = math.hypot(x_m, y_m)
    if p < 1e-3:  # on the polar axis
        lat = math.copysign(math.pi / 2.0, z_m)
        return lat, lon, abs(z_m) - WGS84_B_M
    lat = math.atan2(z_m, p * (1.0 - WGS84_E2))
    height = 0.0
    for _ in range(10):
        sin_lat = math.sin(lat)
        n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
        height = p / math.cos(lat) - n
        new_lat = math.atan2(z_m, p * (1.0 - WGS84_E2 * n / (n + height)))
        if abs(new_lat - lat) < 1e-14:
            lat = new_lat
            break
        lat = new_lat
    sin_lat = math.sin(lat)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    height = p / math.cos(lat) - n if abs(lat) < math.radians(80.0) else z_m / sin_lat - n * (1.0 - WGS84_E2)
    return lat, lon, height


def ecef_velocity_to_ned(
    vx: float, vy: float, vz: float, lat_rad: float, lon_rad: float
) -> tuple[float, float, float]:
    """Rotate an ECEF velocity into the local north-east-down frame at (lat, lon)."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    so, co = math.sin(lon_rad), math.cos(lon_rad)
    north = -sl * co * vx - sl * so * vy + cl * vz
    east = -so * vx + co * vy
    down = -cl * co * vx - cl * so * vy - sl * vz
    return north, east, down


def gps_to_unix_ns(week: int, tow_ns: int, leap_s: int) -> int:
    """GPS week + time of week -> Unix ns UTC, given GPS-UTC leap seconds."""
    return (GPS_EPOCH_UNIX_S + week * WEEK_S - leap_s) * NS_PER_S + tow_ns
