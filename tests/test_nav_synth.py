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
            latency_s: float = 0.2, gnss_hz: float = 1.0, receiver: str = "ubx", epoch_time: bool = True,
            gnss_corr_s: float = 0.0) -> list[tuple[int, str, dict[str, Any]]]:
    """(log time, topic, message) sorted by time: IMU at ``imu_hz``, GNSS at ``gnss_hz`` (arriving ``latency_s``
    late, with its epoch time unless ``epoch_time`` is False), OBD 2 Hz in whole km/h, baro 1 Hz; ``gnss_off``
    lists (start, end) s without fix.

    ``receiver``: "ubx" reports accuracy figures, PDOP and a 3D velocity (NAV-PVT); "nmea" what RMC and GGA
    give: position, height, speed and course (no vertical velocity), satellites, no accuracy, no DOP; "gsa" the
    same with GSA's PDOP. ``gnss_corr_s``: the position error is first-order Gauss-Markov with this correlation
    time (0: white), as a receiver's errors are once fixes come faster than its error changes."""
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
    sig = np.array((e.gnss_h_sigma, e.gnss_h_sigma, e.gnss_v_sigma))
    err = rng.standard_normal(3) * sig if gnss_corr_s > 0.0 else sig * 0.0
    baro_with_fix = gnss_hz == 1.0  # one loop for both, in the order the 1 Hz tests' random draws were made
    for k in range(int(duration_s * gnss_hz) + 1):
        t = k / gnss_hz
        s = trajectory.state(t)
        ts = T0_NS + round((t + latency_s) * NS)
        ok = not any(a <= t < b for a, b in (gnss_off or []))
        rm, rn = _radii(s.lat_rad)
        if gnss_corr_s > 0.0:
            rho = math.exp(-1.0 / (gnss_hz * gnss_corr_s))
            err = rho * err + math.sqrt(1.0 - rho * rho) * rng.standard_normal(3) * sig
        else:
            err = rng.standard_normal(3) * sig
        dn, de, dd = err
        vel = s.vel_ned_mps + rng.standard_normal(3) * e.gnss_vel_sigma
        msg = {
            "t_sync_ns": ts, "t_mono_ns": ts - T0_NS, "sync_state": "locked",
            "gnss_time_ns": T0_NS + round(t * NS) if epoch_time else None,
            "fix_ok": ok, "fix_mode": 3 if ok else 1,
            "latitude": math.degrees(s.lat_rad + dn / (rm + s.height_m)),
            "longitude": math.degrees(s.lon_rad + de / ((rn + s.height_m) * math.cos(s.lat_rad))),
            "altitude": s.height_m - dd, "vel_ned_mps": vel.tolist() if ok else None,
            "h_acc_m": e.gnss_h_sigma * math.sqrt(2.0), "v_acc_m": e.gnss_v_sigma, "s_acc_mps": e.gnss_vel_sigma,
            "pdop": 1.2, "num_sv": 18 if ok else 0}
        if receiver in ("nmea", "gsa"):
            msg.update(h_acc_m=None, v_acc_m=None, s_acc_mps=None, pdop=1.2 if receiver == "gsa" else None,
                       vel_ned_mps=[vel[0], vel[1], None] if ok else None, source="NMEA")
        out.append((ts, "/gnss/fix", msg))
        if baro_with_fix:
            _baro(out, trajectory, t, e, rng)
    for k in range(0 if baro_with_fix else int(duration_s) + 1):
        _baro(out, trajectory, float(k), e, rng)
    for k in range(int(duration_s * 2) + 1):
        t = k / 2.0 + 0.1
        s = trajectory.state(t)
        ts = T0_NS + round(t * NS)
        kmh = round(max(0.0, s.forward_speed_mps) * e.obd_factor * 3.6)
        out.append((ts, "/obd/speed", {"t_sync_ns": ts, "t_mono_ns": ts - T0_NS, "speed_kmh": kmh,
                                       "speed_mps": kmh / 3.6}))
    out.sort(key=lambda r: r[0])
    return out


def _baro(out: list[tuple[int, str, dict[str, Any]]], trajectory: Any, t: float, e: SynthErrors,
          rng: np.random.Generator) -> None:
    s = trajectory.state(t)
    ts_b = T0_NS + round((t + 0.3) * NS)
    out.append((ts_b, "/baro", {"t_sync_ns": ts_b, "t_mono_ns": ts_b - T0_NS,
                                "altitude_m": s.height_m + e.baro_offset + rng.standard_normal() * e.baro_sigma}))


def _radii(lat: float) -> tuple[float, float]:
    e2 = 6.69437999014e-3
    w = math.sqrt(1.0 - e2 * math.sin(lat) ** 2)
    return 6378137.0 * (1.0 - e2) / w**3, 6378137.0 / w


def truth_at(trajectory: Any, t_ns: int) -> Any:
    return trajectory.state((t_ns - T0_NS) / NS)
