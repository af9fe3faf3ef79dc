"""Synthetic sensor records for navigation tests: a trajectory sampled straight into message dicts.

No daemon, no device models, no buses: the truth of a trajectory plus simple white noise and constant biases,
in the same record layout as a recording, so a test of the filter runs in a fraction of a second and on
errors it chooses (a drive 'the simulator did not make').
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

NS = 1_000_000_000
T0_NS = 1_700_000_000 * NS


@dataclass
class SynthErrors:
    accel_noise: float = 400e-6 * 9.80665 * math.sqrt(10.0)  # per sample: density x sqrt(bandwidth)
    gyro_noise: float = math.radians(0.005) * math.sqrt(10.0)
    accel_bias: tuple[float, float, float] = (0.2, -0.15, 0.1)
    gyro_bias: tuple[float, float, float] = (math.radians(1.5), math.radians(-2.0), math.radians(0.8))
    gnss_h_sigma: float = 0.5
    gnss_v_sigma: float = 1.0
    gnss_vel_sigma: float = 0.05
    obd_factor: float = 1.03
    baro_sigma: float = 0.25
    baro_offset: float = -27.0


def records(trajectory: Any, duration_s: float, seed: int = 0, imu_hz: float = 20.0,
            errors: SynthErrors | None = None, gnss_off: list[tuple[float, float]] | None = None,
            latency_s: float = 0.2) -> list[tuple[int, str, dict[str, Any]]]:
    """(log time, topic, message) sorted by time: IMU at ``imu_hz``, GNSS 1 Hz (arriving ``latency_s`` late,
    with its epoch time), OBD 2 Hz in whole km/h, baro 1 Hz; ``gnss_off`` lists (start, end) s without fix."""
    e = errors or SynthErrors()
    rng = np.random.default_rng(seed)
    out: list[tuple[int, str, dict[str, Any]]] = []
    n = int(duration_s * imu_hz)
    ba, bg = np.array(e.accel_bias), np.array(e.gyro_bias)
    for k in range(n + 1):
        t = k / imu_hz
        s = trajectory.state(t)
        a = s.f_body_mps2 + ba + rng.standard_normal(3) * e.accel_noise
        w = s.w_body_rps + bg + rng.standard_normal(3) * e.gyro_noise
        ts = T0_NS + round(t * NS)
        out.append((ts, "/imu", {"t_sync_ns": ts, "t_mono_ns": ts - T0_NS, "sync_state": "locked",
                                 "accel_mps2": a.tolist(), "gyro_rps": w.tolist()}))
    for k in range(int(duration_s) + 1):
        t = float(k)
        s = trajectory.state(t)
        ts = T0_NS + round((t + latency_s) * NS)
        ok = not any(a <= t < b for a, b in (gnss_off or []))
        rm, rn = _radii(s.lat_rad)
        dn, de, dd = rng.standard_normal(3) * (e.gnss_h_sigma, e.gnss_h_sigma, e.gnss_v_sigma)
        vel = s.vel_ned_mps + rng.standard_normal(3) * e.gnss_vel_sigma
        out.append((ts, "/gnss/fix", {
            "t_sync_ns": ts, "t_mono_ns": ts - T0_NS, "sync_state": "locked", "gnss_time_ns": T0_NS + round(t * NS),
            "fix_ok": ok, "fix_mode": 3 if ok else 1,
            "latitude": math.degrees(s.lat_rad + dn / (rm + s.height_m)),
            "longitude": math.degrees(s.lon_rad + de / ((rn + s.height_m) * math.cos(s.lat_rad))),
            "altitude": s.height_m - dd, "vel_ned_mps": vel.tolist() if ok else None,
            "h_acc_m": e.gnss_h_sigma * math.sqrt(2.0), "v_acc_m": e.gnss_v_sigma, "s_acc_mps": e.gnss_vel_sigma,
            "pdop": 1.2, "num_sv": 18 if ok else 0}))
        ts_b = T0_NS + round((t + 0.3) * NS)
        out.append((ts_b, "/baro", {"t_sync_ns": ts_b, "t_mono_ns": ts_b - T0_NS,
                                    "altitude_m": s.height_m + e.baro_offset + rng.standard_normal() * e.baro_sigma}))
    for k in range(int(duration_s * 2) + 1):
        t = k / 2.0 + 0.1
        s = trajectory.state(t)
        ts = T0_NS + round(t * NS)
        kmh = round(max(0.0, s.forward_speed_mps) * e.obd_factor * 3.6)
        out.append((ts, "/obd/speed", {"t_sync_ns": ts, "t_mono_ns": ts - T0_NS, "speed_kmh": kmh,
                                       "speed_mps": kmh / 3.6}))
    out.sort(key=lambda r: r[0])
    return out


def _radii(lat: float) -> tuple[float, float]:
    e2 = 6.69437999014e-3
    w = math.sqrt(1.0 - e2 * math.sin(lat) ** 2)
    return 6378137.0 * (1.0 - e2) / w**3, 6378137.0 / w


def truth_at(trajectory: Any, t_ns: int) -> Any:
    return trajectory.state((t_ns - T0_NS) / NS)
