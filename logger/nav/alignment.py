"""Initialisation a real drive needs: levelling and gyro bias at standstill, heading from the GNSS course.

A MEMS gyro cannot find north (the earth's rate is a thousandth of the MPU-6050's offset), so the heading
comes from the direction of travel the receiver reports once the vehicle moves fast enough for it to mean
something, or from the configuration. Roll and pitch come from the mean specific force at standstill, and the
mean gyro output there is the gyro offset. The accelerometer offset cannot be told from a tilt at
standstill: levelling absorbs its horizontal part, so the initial covariance correlates the two.
"""

from __future__ import annotations

import math

import numpy as np

from logger.nav import earth
from logger.nav.rotations import dcm_from_euler, quat_from_euler, quat_from_rotvec, quat_mul


class StaticAlignment:
    """Averages specific force and angular rate while the vehicle stands still."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.n = 0
        self.t0_ns = 0
        self.t1_ns = 0
        self._f = [0.0, 0.0, 0.0]
        self._w = [0.0, 0.0, 0.0]

    def add(self, t_ns: int, f: tuple[float, float, float], w: tuple[float, float, float]) -> None:
        if self.n == 0:
            self.t0_ns = t_ns
        self.t1_ns = t_ns
        self.n += 1
        for i in range(3):
            self._f[i] += f[i]
            self._w[i] += w[i]

    def add_block(self, t_ns: np.ndarray, f: np.ndarray, w: np.ndarray) -> None:
        """Samples in time order at once (``f``, ``w``: n x 3): the sums :meth:`add` would leave."""
        if len(t_ns) == 0:
            return
        if self.n == 0:
            self.t0_ns = int(t_ns[0])
        self.t1_ns = int(t_ns[-1])
        self.n += len(t_ns)
        fs, ws = f.sum(axis=0).tolist(), w.sum(axis=0).tolist()
        for i in range(3):
            self._f[i] += fs[i]
            self._w[i] += ws[i]

    @property
    def duration_s(self) -> float:
        return (self.t1_ns - self.t0_ns) / 1e9

    def mean_force(self) -> tuple[float, float, float]:
        return self._f[0] / self.n, self._f[1] / self.n, self._f[2] / self.n

    def level(self) -> tuple[float, float]:
        """Roll and pitch (rad) from the mean specific force: at rest it is minus gravity in body axes."""
        fx, fy, fz = self.mean_force()
        return math.atan2(-fy, -fz), math.atan2(fx, math.hypot(fy, fz))

    def gyro_bias(self, lat_rad: float | None = None) -> tuple[float, float, float]:
        """Mean gyro output less the part of the earth's rate along the local vertical (known without heading)."""
        wx, wy, wz = (self._w[i] / self.n for i in range(3))
        if lat_rad is not None:
            roll, pitch = self.level()
            down = (-math.sin(pitch), math.sin(roll) * math.cos(pitch), math.cos(roll) * math.cos(pitch))
            wd = -earth.OMEGA_IE * math.sin(lat_rad)  # earth rate along NED down
            wx, wy, wz = wx - wd * down[0], wy - wd * down[1], wz - wd * down[2]
        return wx, wy, wz


def horizontal_earth_rate_body(roll: float, pitch: float, yaw: float, lat_rad: float) -> tuple[float, float, float]:
    """The horizontal part of the earth's rate (Omega cos(lat), due north) in body axes at this attitude.

    Levelling cannot take it out of the mean gyro output (it needs the heading), so it stays in the gyro offset
    found at standstill: 3 millidegrees/s at mid latitudes, which tilts the solution by 0.2 deg a minute once the
    mechanization subtracts the earth's rate itself. Once the heading is known it is taken out with this."""
    c = dcm_from_euler(roll, pitch, yaw)
    wn = earth.OMEGA_IE * math.cos(lat_rad)
    return float(c[0, 0] * wn), float(c[0, 1] * wn), float(c[0, 2] * wn)


def gyro_calibration_variance(gyro_arw: float, gyro_bias_walk: float, duration_s: float, since_s: float) -> float:
    """Variance per axis of the gyro offset found as the mean rate over ``duration_s`` of standstill, ``since_s``
    after its end: the white noise averaged over the window, the bias walk's spread about its mean within the
    window (q T / 3), and its walk since."""
    t = max(duration_s, 1e-3)
    return gyro_arw**2 / t + gyro_bias_walk**2 * (t / 3.0 + max(since_s, 0.0))


def accel_offset_variance(mean_force: tuple[float, float, float], gravity: float, prior_var: float) -> float:
    """Variance per axis of the accelerometer offset, widened by what levelling measured.

    At standstill the specific force's magnitude is normal gravity; what the mean differs by is the offset along
    the vertical (its horizontal part adds only its square over 2 g), a draw from the same distribution as the
    horizontal parts, which levelling cannot see. A residual beyond the configured prior says the chip is worse
    than configured: the prior becomes that residual, so the tilt the horizontal offsets may have caused is
    covered too. One draw is weak evidence, so the prior is only ever widened by it, never narrowed."""
    r = math.sqrt(mean_force[0] ** 2 + mean_force[1] ** 2 + mean_force[2] ** 2) - gravity
    return max(prior_var, r * r)


def attitude(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    return quat_from_euler(roll, pitch, yaw)


def rotate_heading(q: tuple[float, float, float, float], dpsi: float) -> tuple[float, float, float, float]:
    """Turn an attitude about the local vertical by ``dpsi`` (rad): keeps roll and pitch, shifts yaw."""
    return quat_mul(quat_from_rotvec(0.0, 0.0, dpsi), q)


def tilt_bias_covariance(c_bn: np.ndarray, accel_bias_var: float, g: float) -> tuple[np.ndarray, np.ndarray,
                                                                                        np.ndarray]:
    """Joint covariance of the horizontal attitude error and the accelerometer bias after levelling.

    Levelling makes the specific force it measured vertical, so f x phi = C dba in the horizontal: with
    f = (0, 0, -g), g phi_E = (C dba)_N and -g phi_N = (C dba)_E. Returns P_phi (3x3), P_phi_ba (3x3) and
    P_ba (3x3) for independent bias errors of variance ``accel_bias_var`` per axis.
    """
    m = np.zeros((3, 3))
    m[0] = -c_bn[1] / g
    m[1] = c_bn[0] / g
    pba = np.eye(3) * accel_bias_var
    return m @ pba @ m.T, m @ pba, pba
