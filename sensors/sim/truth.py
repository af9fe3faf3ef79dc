"""What the vehicle truly did: the interface every device model reads, and two simple trajectories.

Models sample a :class:`Trajectory` at the time they need (a 1 kHz IMU, a 1 Hz receiver), so the truth
must be a function of time rather than a fixed-rate table. Body axes are forward-right-down (FRD);
navigation axes are north-east-down (NED) on WGS-84.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from sensors.sim import earth


@dataclass(frozen=True, slots=True)
class TruthState:
    """The vehicle and its surroundings at one instant of true time."""

    t_s: float
    lat_rad: float
    lon_rad: float
    height_m: float  # above the WGS-84 ellipsoid
    vel_ned_mps: np.ndarray  # (3,)
    rpy_rad: np.ndarray  # (3,) roll, pitch, yaw of body FRD against NED
    f_body_mps2: np.ndarray  # (3,) specific force an ideal accelerometer senses, body FRD
    w_body_rps: np.ndarray  # (3,) inertial angular rate an ideal gyro senses, body FRD
    geoid_m: float = 0.0  # geoid undulation: height above mean sea level = height_m - geoid_m
    ambient_degc: float = 20.0
    sea_level_pa: float = 101325.0  # today's weather: pressure reduced to mean sea level
    sky_open: float = 1.0  # fraction of the sky a GNSS antenna sees: 0 in a tunnel
    engine_on: bool = True

    @property
    def forward_speed_mps(self) -> float:
        """Speed along the body x axis: what a wheel-speed sensor measures (negative when reversing)."""
        c = earth.dcm_body_to_ned(self.rpy_rad)
        return float(c[:, 0] @ self.vel_ned_mps)

    @property
    def height_msl_m(self) -> float:
        return self.height_m - self.geoid_m


class Trajectory(Protocol):
    """A drive, as a function of true time in seconds since its start."""

    duration_s: float

    def state(self, t_s: float) -> TruthState:
        ...


@dataclass
class ParkedTrajectory:
    """A level vehicle standing still: the case every sensor must get exactly right."""

    lat_deg: float = 37.6
    lon_deg: float = 126.87
    height_m: float = 40.0
    heading_deg: float = 0.0
    duration_s: float = math.inf
    extras: dict = field(default_factory=dict)

    def state(self, t_s: float) -> TruthState:
        lat = math.radians(self.lat_deg)
        rpy = np.array([0.0, 0.0, math.radians(self.heading_deg)])
        c_bn = earth.dcm_body_to_ned(rpy)
        g = earth.gravity_ned(lat, self.height_m)
        f_body = c_bn.T @ (-g)
        w_body = c_bn.T @ earth.earth_rate_ned(lat)
        return TruthState(t_s, lat, math.radians(self.lon_deg), self.height_m, np.zeros(3), rpy, f_body,
                          w_body, **self.extras)


@dataclass
class StraightTrajectory:
    """Constant speed on a level road along a constant heading: a moving case with a closed form."""

    speed_mps: float = 15.0
    heading_deg: float = 0.0
    lat_deg: float = 37.6
    lon_deg: float = 126.87
    height_m: float = 40.0
    duration_s: float = math.inf

    def state(self, t_s: float) -> TruthState:
        psi = math.radians(self.heading_deg)
        v = np.array([self.speed_mps * math.cos(psi), self.speed_mps * math.sin(psi), 0.0])
        lat0 = math.radians(self.lat_deg)
        rn, re = earth.radii(lat0)
        lat = lat0 + v[0] * t_s / (rn + self.height_m)
        lon = math.radians(self.lon_deg) + v[1] * t_s / ((re + self.height_m) * math.cos(lat))
        rpy = np.array([0.0, 0.0, psi])
        c_bn = earth.dcm_body_to_ned(rpy)
        w_ie = earth.earth_rate_ned(lat)
        w_en = earth.transport_rate_ned(lat, self.height_m, v)
        # Level flight on the ellipsoid: the vehicle turns with the navigation frame.
        a_ned = np.cross(2 * w_ie + w_en, v)
        f_body = c_bn.T @ (a_ned - earth.gravity_ned(lat, self.height_m))
        w_body = c_bn.T @ (w_ie + w_en)
        return TruthState(t_s, lat, lon, self.height_m, v, rpy, f_body, w_body)
