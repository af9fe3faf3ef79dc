"""Start-up: level while the vehicle stands, carry the attitude on the gyro, and start once the heading is known.

Before the filter runs it needs an attitude. Standing still, the accelerometer gives roll and pitch and the gyro
mean its offset (:mod:`logger.nav.alignment`); the heading then comes from the GNSS course once the vehicle moves
fast enough (or from the configuration). In between, a provisional attitude is carried on the gyro alone, and
kept per sample, so the course of a fix is matched with the attitude of its own epoch. A vehicle moving from the
start has no levelling: it starts level, its heading from the course with a wider uncertainty.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from logger.nav import earth
from logger.nav.alignment import (
    StaticAlignment,
    accel_offset_variance,
    gyro_calibration_variance,
    horizontal_earth_rate_body,
    rotate_heading,
    tilt_bias_covariance,
)
from logger.nav.core import PreparedFix
from logger.nav.measurements import ROUNDING_VAR
from logger.nav.params import NavParams
from logger.nav.rotations import (
    dcm_from_euler,
    dcm_from_quat,
    euler_from_dcm,
    quat_chain,
    quat_from_euler,
    quat_from_rotvec,
    quat_mul,
    quats_from_rotvecs,
)
from logger.nav.state import BA_ID, BG_ID, DH_ID, P_ID, PHI_ID, RQ_ID, SF_ID, V_ID, NavState

NS = 1_000_000_000
MAX_IMU_GAP_S = 5.0  # beyond this the rates at both ends say nothing about the gap: coast on the velocity
CONFIG_HEADING = "config heading"


def height_offset_variance(p: NavParams, fix_v_sigma: float = 0.0) -> float:
    """The barometer's offset (ellipsoidal height minus barometric altitude) before GNSS heights have told it: the
    fix's vertical error, the barometer's own and a metre more. The start's prior, and a remount's (the offset learnt
    through a wrong mounting is learnt again)."""
    return fix_v_sigma**2 + p.baro_sigma_m**2 + 1.0


class Startup:
    """The levelling, the provisional attitude, and the initial state and covariance built from them."""

    def __init__(self, params: NavParams) -> None:
        self.params = params
        self.align = StaticAlignment()
        self.prov_q: tuple[float, float, float, float] | None = None  # attitude before the heading is known
        self._prov_w: tuple[float, float, float] | None = None
        self._prov_hist: deque[tuple[int, tuple[float, float, float, float]]] = deque(maxlen=4096)
        # roll, pitch, gyro mean and mean specific force of the standstill the levelling averaged, once levelled
        self.levelled: tuple[float, float, tuple[float, float, float], tuple[float, float, float]] | None = None
        self.level_span = (0, 0.0)  # end (ns) and length (s) of the standstill the levelling averaged
        self.accel_bias_var = params.accel_bias_sigma**2  # prior of the accelerometer offset, per axis
        self._level_yaw = 0.0  # heading at the end of levelling, once the GNSS course (or config) tells it

    def step(self, t_ns: int, acc: tuple[float, float, float], gyro: tuple[float, float, float], dt: float,
             still: bool, fix: PreparedFix | None) -> str:
        """One IMU sample before the start: level while still, then carry the attitude on the gyro alone.

        Returns :data:`CONFIG_HEADING` when the configuration gives the heading and levelling just ended: the
        filter starts now, at that heading. Otherwise "".
        """
        if fix is not None and fix.vel is not None and math.hypot(fix.vel[0], fix.vel[1]) > 1.0:
            still = False
        if still and self.prov_q is None:
            self.align.add(t_ns, acc, gyro)
            return ""
        if self.prov_q is None:
            if self.align.n == 0 or self.align.duration_s < self.params.align_min_s:
                self.align.reset()
                return ""
            lat = fix.lat if fix is not None else None
            roll, pitch = self.align.level()
            bg = self.align.gyro_bias(lat)
            self.levelled = (roll, pitch, bg, self.align.mean_force())
            self.level_span = (self.align.t1_ns, self.align.duration_s)
            self.prov_q = quat_from_euler(roll, pitch, 0.0)
            self._prov_w = None
            if self.params.heading_source == "config" and fix is not None:
                self._level_yaw = math.radians(self.params.initial_heading_deg)
                return CONFIG_HEADING
        bg = self.levelled[2] if self.levelled else (0.0, 0.0, 0.0)
        w = (gyro[0] - bg[0], gyro[1] - bg[1], gyro[2] - bg[2])
        if 0.0 < dt <= MAX_IMU_GAP_S:
            pw = self._prov_w or w
            self.prov_q = quat_mul(self.prov_q, quat_from_rotvec(0.5 * (pw[0] + w[0]) * dt,
                                                                 0.5 * (pw[1] + w[1]) * dt,
                                                                 0.5 * (pw[2] + w[2]) * dt))
        self._prov_w = w
        self._prov_hist.append((t_ns, self.prov_q))
        return ""

    def step_block(self, t_ns: np.ndarray, acc: np.ndarray, gyro: np.ndarray, dts: np.ndarray, still: np.ndarray,
                   fix: PreparedFix | None) -> int | None:
        """:meth:`step` for consecutive samples at once (``acc``, ``gyro``: n x 3; ``dts``: each one's interval,
        none over :data:`MAX_IMU_GAP_S`; ``still``: the stop detector's word after each), to round-off: the
        standstill's runs summed at once, the provisional attitude's steps computed at once. Returns the index
        of the sample at which :meth:`step` returned :data:`CONFIG_HEADING` (the filter starts there: the samples
        after it are not taken), or None when all were taken."""
        n = len(t_ns)
        if fix is not None and fix.vel is not None and math.hypot(fix.vel[0], fix.vel[1]) > 1.0:
            still = np.zeros(n, dtype=bool)
        i = 0
        while i < n and self.prov_q is None:
            changes = np.flatnonzero(still[i + 1:] != still[i])
            j = i + 1 + int(changes[0]) if len(changes) else n  # the run of samples judged as sample i is
            if still[i]:
                self.align.add_block(t_ns[i:j], acc[i:j], gyro[i:j])
                i = j
                continue
            if self.align.n == 0 or self.align.duration_s < self.params.align_min_s:
                self.align.reset()  # what each sample of the run does
                i = j
                continue
            if self.step(int(t_ns[i]), tuple(acc[i].tolist()), tuple(gyro[i].tolist()), float(dts[i]), False,
                         fix) == CONFIG_HEADING:
                return i
            i += 1
        if i >= n or self.prov_q is None:
            return None
        bg = self.levelled[2] if self.levelled else (0.0, 0.0, 0.0)
        w = gyro[i:] - np.asarray(bg)
        pw = np.concatenate(((self._prov_w or w[0].tolist(),), w[:-1]))
        dt = dts[i:]
        turn = np.where(((dt > 0.0) & (dt <= MAX_IMU_GAP_S))[:, None], 0.5 * (pw + w) * dt[:, None], 0.0)
        qs = quat_chain(self.prov_q, quats_from_rotvecs(turn).tolist())
        self.prov_q = qs[-1]
        wl = w[-1].tolist()
        self._prov_w = (wl[0], wl[1], wl[2])
        self._prov_hist.extend(zip(t_ns[i:].tolist(), qs, strict=True))
        return None

    def late_config_heading(self) -> bool:
        """With ``heading_source = "config"``, a levelling that ended before any fix: turn the provisional attitude
        (yaw 0 when levelling ended) to the configured heading, so the next fix can start the filter. True when
        done; the filter then starts from the provisional attitude."""
        if self.params.heading_source != "config" or self.prov_q is None or self.levelled is None:
            return False
        self._level_yaw = math.radians(self.params.initial_heading_deg)
        self.prov_q = rotate_heading(self.prov_q, self._level_yaw)
        return True

    def heading_from_course(self, fix: PreparedFix) -> tuple[float | None, str, float] | None:
        """A fix fast and sure enough to give the heading: (yaw, or None for the provisional attitude's; how the
        filter starts; heading variance), or None to wait for a better one."""
        p = self.params
        if fix.vel is None or not fix.fix_3d:
            return None
        speed = math.hypot(fix.vel[0], fix.vel[1])
        if speed < p.heading_min_speed_mps or fix.s_vel > 0.2 * speed:
            return None
        course = math.atan2(fix.vel[1], fix.vel[0])
        heading_var = (fix.s_vel / speed) ** 2 + math.radians(1.5) ** 2
        if self.prov_q is not None and self.levelled is not None:
            q_then = self.prov_q
            for t, q in reversed(self._prov_hist):
                if t <= fix.t_ns:
                    q_then = q
                    break
            _, _, yaw_then = euler_from_dcm(dcm_from_quat(q_then))
            self.prov_q = rotate_heading(self.prov_q, course - yaw_then)
            self._level_yaw = course - yaw_then  # the provisional attitude began at yaw 0 when levelling ended
            return None, "gnss course", heading_var
        return course, "gnss course, no levelling", heading_var + math.radians(3.0) ** 2

    def started(self) -> None:
        """The filter has started (it never goes back to the start-up): the provisional attitudes kept for a late
        fix's course are not needed any more. At 1 kHz they are 4096 entries, about 1 MB held for the drive."""
        self._prov_hist.clear()

    def initial(self, t_ns: int, yaw_or_none: float | None, method: str, fix: PreparedFix, heading_var: float,
                n: int, lever: np.ndarray, baro_last: tuple[int, float] | None) -> tuple[NavState, np.ndarray]:
        """The state and covariance the filter starts with: levelled attitude turned to the heading, position and
        velocity from the fix (carried to ``t_ns``, at the IMU), the barometer's offset from its last reading."""
        p = self.params
        if self.levelled is not None and self.prov_q is not None:
            roll, pitch, bg, _ = self.levelled
            q = self.prov_q
            if yaw_or_none is not None and method == CONFIG_HEADING:
                q = quat_from_euler(roll, pitch, yaw_or_none)
            att_var = math.radians(0.3) ** 2
            # With the heading known, the horizontal earth rate comes out of the standstill's gyro mean, and
            # what is left of the offset is what that mean could not average out.
            e = horizontal_earth_rate_body(roll, pitch, self._level_yaw, fix.lat)
            bg = (bg[0] - e[0], bg[1] - e[1], bg[2] - e[2])
            end_ns, span_s = self.level_span
            bg_var = gyro_calibration_variance(p.gyro_arw, p.gyro_bias_walk, span_s, (t_ns - end_ns) / NS)
            # Levelling made the specific force it measured vertical in the attitude of that moment: the tilt
            # it took for the accelerometer offset is tied to the body axes as they were then.
            c_level = dcm_from_euler(roll, pitch, self._level_yaw)
        else:  # moving from the start: no levelling, no gyro calibration
            bg = (0.0, 0.0, 0.0)
            q = quat_from_euler(0.0, 0.0, yaw_or_none or 0.0)
            att_var = math.radians(3.0) ** 2
            bg_var = p.gyro_bias_sigma**2
            c_level = None
        dt_e = (t_ns - fix.t_ns) / NS
        vel = fix.vel if fix.vel is not None else np.zeros(3)
        lat, lon, h = earth.offset_llh(fix.lat, fix.lon, fix.h, vel[0] * dt_e, vel[1] * dt_e, vel[2] * dt_e)
        s = NavState(lat, lon, h, float(vel[0]), float(vel[1]), float(vel[2]), q, (0.0, 0.0, 0.0), bg)
        c_bn = s.dcm()
        arm = c_bn @ lever
        s.lat, s.lon, s.h = earth.offset_llh(s.lat, s.lon, s.h, -arm[0], -arm[1], -arm[2])
        if n > SF_ID:
            s.dh = 0.0 if baro_last is None else s.h - baro_last[1]
        p0 = np.zeros((n, n))
        for i in range(3):
            p0[P_ID + i, P_ID + i] = fix.sigma[i] ** 2 + (abs(vel[i]) * 0.05) ** 2
            p0[V_ID + i, V_ID + i] = max(fix.s_vel, 0.1) ** 2 + 0.1
            p0[BG_ID + i, BG_ID + i] = bg_var
        if fix.vel is None or not fix.vel_3d:  # no vertical velocity given: a car on a road climbs a few m/s at most
            p0[V_ID + 2, V_ID + 2] = max(float(p0[V_ID + 2, V_ID + 2]), 1.0)
        self.accel_bias_var = p.accel_bias_sigma**2
        if self.levelled is not None and c_level is not None:
            self.accel_bias_var = accel_offset_variance(self.levelled[3], earth.gravity(fix.lat, fix.h),
                                                        self.accel_bias_var)
        pphi, pphiba, pba = tilt_bias_covariance(c_bn if c_level is None else c_level, self.accel_bias_var,
                                                 earth.G0)
        p0[PHI_ID:PHI_ID + 3, PHI_ID:PHI_ID + 3] = pphi + np.diag((att_var, att_var, heading_var))
        p0[PHI_ID:PHI_ID + 3, BA_ID:BA_ID + 3] = pphiba
        p0[BA_ID:BA_ID + 3, PHI_ID:PHI_ID + 3] = pphiba.T
        p0[BA_ID:BA_ID + 3, BA_ID:BA_ID + 3] = pba
        if n > SF_ID:
            p0[SF_ID, SF_ID] = p.obd_scale_sigma**2
            p0[DH_ID, DH_ID] = height_offset_variance(p, fix.sigma[2])
        if n > RQ_ID:
            p0[RQ_ID, RQ_ID] = ROUNDING_VAR
        return s.plain(), p0
