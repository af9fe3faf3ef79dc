"""The navigation engine: recorded or live messages in time order in, a navigation solution at the IMU rate out.

One engine serves the live navigator and ``logger replay``, so what the operator sees on the road is what a
post-processing run computes. Per IMU sample it runs the strapdown mechanization (cheap, plain floats); the
covariance is propagated at most every ``cov_interval_s`` and always before an update. Measurements are
applied in the order they arrive, each at its own time: a GNSS fix is evaluated against the solution at its
epoch (kept in a short history, corrected for every feedback since), the others against the latest one.

Modes: ``17`` the paper's filter (GNSS, OBD with its scale factor, baro with its offset, zero motion at stops,
non-holonomic constraint), ``15`` the paper's baseline (GNSS position and velocity only), ``gnss`` the
receiver's own fixes passed through, for comparison on the same data.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

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
from logger.nav.dynamics import ProcessNoise, discretize, error_dynamics
from logger.nav.ekf import ErrorStateEkf
from logger.nav.gnss_noise import CorrelatedGnssNoise
from logger.nav.gnss_time import GnssEpochClock
from logger.nav.measurements import (
    BaroHeight,
    GnssPosition,
    GnssVelocity,
    NonHolonomic,
    ObdVelocity,
    Observation,
    ZeroMotion,
    repeat_variance,
)
from logger.nav.params import MODES, NavParams
from logger.nav.rotations import dcm_from_euler, euler_from_dcm, quat_from_euler, quat_from_rotvec, quat_mul
from logger.nav.state import BA_ID, BG_ID, DH_ID, N_FULL, N_INS, P_ID, PHI_ID, SF_ID, V_ID, NavState
from logger.nav.stops import StopDetector
from logger.nav.strapdown import Strapdown
from logger.nav.thermal import TemperatureSpan

NS = 1_000_000_000
IMU_GAP_S = 0.5  # samples further apart than this are a gap: counted, and still integrated across
MAX_IMU_GAP_S = 5.0  # beyond this the rates at both ends say nothing about the gap: coast on the velocity
UPDATE_STALE_S = 0.2  # an update uses the covariance as last propagated if that is less than this old
CONING_MAX_DT_S = 0.0105  # mean sample interval below which coning/sculling corrections are applied
OBD_FRESH_NS = int(1.2 * NS)
OBD_MIN_SPEED_MPS = 0.5  # below this the 1 km/h steps of PID 0x0D say little
OBD_STEP_MPS = 1.0 / 3.6  # PID 0x0D's resolution, whatever the interface
OBD_ROUNDING_HOLD_NS = 10 * NS  # how long one rounding error is taken to last: a speed leaves its step by then
NHC_MIN_SPEED_MPS = 1.0
NHC_INTERVAL_NS = NS // 2
DIVERGENCE_REJECTS = 10  # consecutive rejected GNSS fixes with a good receiver accuracy...
DIVERGENCE_SPAN_NS = 8 * NS  # ... spanning this long: the filter has lost itself, start again from GNSS
DIVERGENCE_SIGMA_M = 1000.0
REANCHOR_REJECTS = 3  # consecutive refused fixes that agree, from a receiver this sure of itself...
REANCHOR_H_ACC_M = 2.0  # ...make the filter admit its position is less certain than it thought, when they
REANCHOR_AFTER_NS = 5 * NS  # come after this long without an accepted fix (a tunnel) or after worse ones only
VELOCITY_REFUSALS = 3  # trusted velocities (a stop the OBD confirms, a good receiver's, OBD's) refused in a row
VELOCITY_REFUSAL_SPAN_NS = NS  # ... over at least this long, agreeing: the filter's velocity is off, not theirs
BARO_REFUSALS = 5  # barometer heights refused in a row (at least this many)...
BARO_REFUSAL_SPAN_NS = 4 * NS  # ... over at least this long, agreeing: the filter's height is off, not the sensor's
REFUSALS_KEPT = 64  # a run of refusals is judged on its latest: a 10 Hz sensor's over 6 s, bounded while they scatter
GNSS_ARBITER_NS = 3 * NS  # a good 3D fix this recent can tell a wrong height from a moved barometer offset
UNINFORMATIVE_RATIO = 16.0  # fix variance over the filter's own, on every axis: the update would gain < 6 %


@dataclass
class Epoch:
    """A covariance time step, kept for the backward smoother."""

    t_ns: int
    phi: np.ndarray | None  # transition from the previous epoch
    p_minus: np.ndarray
    p_plus: np.ndarray | None = None
    dx: np.ndarray | None = None  # sum of the corrections fed back at this epoch


@dataclass
class EngineCounters:
    imu: int = 0
    imu_gaps: int = 0
    imu_out_of_order: int = 0
    gnss_fixes: int = 0
    gnss_no_fix: int = 0
    gnss_few_sv: int = 0  # fixes left out for too few satellites
    gnss_skipped: int = 0  # GNSS rows (axes) that would add almost nothing but their bias
    obd: int = 0
    baro: int = 0
    zupt: int = 0
    resets: int = 0
    reanchors: int = 0  # times good fixes or baro heights, refused in a row, made it widen its position uncertainty
    reopens: int = 0  # times trusted velocities, refused in a row, made it reopen velocity, attitude and offsets
    initialised_ns: int | None = None
    init_method: str = ""


@dataclass
class Solution:
    """The latest output, for the live navigator and tests."""

    t_ns: int
    t_mono_ns: int
    lat_rad: float
    lon_rad: float
    h_m: float
    vel_ned: tuple[float, float, float]
    rpy_rad: tuple[float, float, float]
    sigma_ned: tuple[float, float, float]
    source: str


@dataclass
class _Fix:
    t_ns: int
    t_mono_ns: int
    lat: float
    lon: float
    h: float
    vel: np.ndarray | None
    sigma: tuple[float, float, float]
    s_vel: float
    fix_3d: bool
    h_acc: float


@dataclass
class NavEngine:
    params: NavParams = field(default_factory=NavParams)
    record: bool = False  # keep rows and covariance epochs (replay and the smoother)

    def __post_init__(self) -> None:
        p = self.params
        if p.mode not in MODES:
            raise ValueError(f"unknown navigation mode {p.mode!r}: choose one of {', '.join(MODES)}")
        self.mode = p.mode
        self.n = N_FULL if p.mode == "17" else N_INS
        m = dcm_from_euler(*(math.radians(a) for a in p.mounting_rpy_deg))
        self._mount = None if np.allclose(m, np.eye(3)) else tuple(tuple(float(v) for v in row) for row in m)
        self.lever = np.array(p.lever_arm_m, float)
        self.mech = Strapdown(coning=False)
        self.stops = StopDetector(p.still_accel_mps2)
        self.align = StaticAlignment()
        self.epoch_clock = GnssEpochClock()
        self._gnss_noise = CorrelatedGnssNoise(p.gnss_multipath_corr_s)
        self.noise = ProcessNoise(p.accel_vrw, p.gyro_arw, p.accel_bias_walk, p.gyro_bias_walk, p.obd_scale_walk_rts,
                                  p.baro_offset_walk_m_rts)
        self.q_diag = self.noise.diagonal(self.n)
        self.thermal = TemperatureSpan()  # die temperature since the offsets were calibrated
        self.state: NavState | None = None
        self.ekf: ErrorStateEkf | None = None
        self.counters = EngineCounters()
        self.rows: list[tuple[Any, ...]] = []
        self.epochs: list[Epoch] = []
        self.solution: Solution | None = None
        self._t_last: int | None = None
        self._dt_mean = 0.05
        self._t_mono_last = 0
        self._w_last = (0.0, 0.0, 0.0)  # last bias-corrected rate, body
        self._gyro_raw = (0.0, 0.0, 0.0)  # last raw rate, body
        self._raw: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.0, 0.0, -earth.G0),
                                                                                    (0.0, 0.0, 0.0))
        self._f_last = (0.0, 0.0, 0.0)
        self._hist: deque[tuple[Any, ...]] = deque(maxlen=4096)  # 4 s at 1 kHz: late fixes arrive within 1 s
        self._corr: tuple[float, ...] = (0.0,) * 6  # position (NED m) and velocity fed back so far
        self._cov_dt = 0.0
        self._f_acc = [0.0, 0.0, 0.0]
        self._sig = (math.inf, math.inf, math.inf)
        self._prov_q: tuple[float, float, float, float] | None = None  # attitude before the heading is known
        self._prov_hist: deque[tuple[int, tuple[float, float, float, float]]] = deque(maxlen=4096)
        self._levelled: tuple[float, float, tuple[float, float, float], tuple[float, float, float]] | None = None
        self._level_span = (0, 0.0)  # end (ns) and length (s) of the standstill the levelling averaged
        self._accel_bias_var = self.params.accel_bias_sigma**2  # prior of the accelerometer offset, per axis
        self._level_yaw = 0.0  # heading at the end of levelling, once the GNSS course (or config) tells it
        self._last_fix: _Fix | None = None
        self._baro_last: tuple[int, float] | None = None
        self._prov_w: tuple[float, float, float] | None = None
        self._obd: tuple[int, float] | None = None  # (t_ns, speed) of the last OBD reading
        self._obd_run = 0  # readings in a row with the same value (within OBD_ROUNDING_HOLD_NS of the first)
        self._obd_run_t0 = 0
        self._w_stop = [0.0, 0.0, 0.0, 0]  # gyro sum and count since the last zero-motion update
        self._w_stop_t0 = 0
        self._next_idle_check_ns = 0
        self._last_nhc_ns = 0
        self._last_pos_ok = (0, math.inf)  # time and accuracy of the last fix whose position went in
        self._rejects: list[tuple[float, ...]] = []  # consecutive refused fixes: time, then N, E (and D) innovation
        self._baro_refusals: list[tuple[float, ...]] = []  # the same for barometer heights: time, innovation
        self._last_good_fix_ns = 0  # epoch of the last 3D fix from a receiver sure of itself, whether it went in
        self._last_height_in_ns = 0  # ... and of the last one whose height went in
        self._vel_refusals: dict[str, list[tuple[int, float, float]]] = {}  # the same for trusted velocities
        self.stopped = False
        self.mount_yaw_stat = [0.0, 0.0]  # sum of lateral/forward velocity ratios and weights (mounting check)

    # ---- dispatch ---------------------------------------------------------------------------------------
    def feed(self, topic: str, msg: dict[str, Any]) -> None:
        """One recorded or live message; topics the filter does not use are ignored."""
        if topic == "/imu":
            a, g = msg["accel_mps2"], msg["gyro_rps"]
            temp = msg.get("temp_degc")
            if temp is not None:
                self.thermal.add(msg["t_sync_ns"], float(temp))
            self.imu(msg["t_sync_ns"], msg["t_mono_ns"], (a[0], a[1], a[2]), (g[0], g[1], g[2]))
        elif topic == "/gnss/fix":
            self.gnss(msg)
        elif topic == "/obd/speed":
            self.obd(msg["t_sync_ns"], float(msg["speed_mps"]))
        elif topic == "/baro":
            self.baro(msg["t_sync_ns"], float(msg["altitude_m"]))
        elif topic == "/pps":
            self.epoch_clock.pps(msg["t_sync_ns"])

    # ---- IMU ---------------------------------------------------------------------------------------------
    def imu(self, t_ns: int, t_mono_ns: int, acc: tuple[float, float, float], gyro: tuple[float, float, float]) -> None:
        if self.mode == "gnss":
            return
        mt = self._mount
        if mt is not None:
            acc = (mt[0][0] * acc[0] + mt[0][1] * acc[1] + mt[0][2] * acc[2],
                   mt[1][0] * acc[0] + mt[1][1] * acc[1] + mt[1][2] * acc[2],
                   mt[2][0] * acc[0] + mt[2][1] * acc[1] + mt[2][2] * acc[2])
            gyro = (mt[0][0] * gyro[0] + mt[0][1] * gyro[1] + mt[0][2] * gyro[2],
                    mt[1][0] * gyro[0] + mt[1][1] * gyro[1] + mt[1][2] * gyro[2],
                    mt[2][0] * gyro[0] + mt[2][1] * gyro[1] + mt[2][2] * gyro[2])
        c = self.counters
        t_last = self._t_last
        if t_last is not None and t_ns <= t_last:
            c.imu_out_of_order += 1
            return
        c.imu += 1
        self._raw = (acc, gyro)
        self.stops.add(t_ns, acc, gyro)
        dt = 0.0 if t_last is None else (t_ns - t_last) / NS
        if 0.0 < dt < IMU_GAP_S:
            # Coning and sculling corrections pay off once the IMU runs fast (100 Hz and up, FIFO reads): they
            # need consecutive increments of one sampling clock, which a slow polled IMU does not give.
            self._dt_mean += 0.02 * (dt - self._dt_mean)
            self.mech.coning = self._dt_mean < CONING_MAX_DT_S
        self._t_last = t_ns
        self._t_mono_last = t_mono_ns
        if dt > IMU_GAP_S:
            c.imu_gaps += 1
        if dt > MAX_IMU_GAP_S:
            self.mech.reset()
        s = self.state
        if s is None:
            self._pre_init(t_ns, acc, gyro, dt)
            return
        ba, bg = s.ba, s.bg
        f = (acc[0] - ba[0], acc[1] - ba[1], acc[2] - ba[2])
        w = (gyro[0] - bg[0], gyro[1] - bg[1], gyro[2] - bg[2])
        self._f_last, self._w_last, self._gyro_raw = f, w, gyro
        if dt <= MAX_IMU_GAP_S:
            # A late sample (a loaded host, a slow bus) still closes its interval: the vehicle moved meanwhile.
            self.mech.step(s, w, f, dt)
        else:
            s.lat, s.lon, s.h = earth.offset_llh(s.lat, s.lon, s.h, s.vn * dt, s.ve * dt, s.vd * dt)
            self.mech.prime(w, f)
        fn = self.mech.f_ned
        self._cov_dt += dt
        acc_ = self._f_acc
        acc_[0] += fn[0] * dt
        acc_[1] += fn[1] * dt
        acc_[2] += fn[2] * dt
        if self.stopped:
            ws = self._w_stop
            ws[0] += gyro[0]
            ws[1] += gyro[1]
            ws[2] += gyro[2]
            ws[3] += 1
        if self.mode == "17" and t_ns >= self._next_idle_check_ns and (
                self._obd is None or t_ns - self._obd[0] > OBD_FRESH_NS):
            # No speed from the vehicle (engine off, adapter gone): standing still is then told by a quiet IMU
            # and a solution that already stands, so a parked car does not drift on its IMU alone.
            self._next_idle_check_ns = t_ns + NHC_INTERVAL_NS
            self._stop_update(self.stops.still and math.sqrt(s.vn * s.vn + s.ve * s.ve + s.vd * s.vd) < 0.5)
        self._hist.append((t_ns, s.lat, s.lon, s.h, s.vn, s.ve, s.vd, s.q, self._corr))
        if self.record:
            self.rows.append((t_ns, t_mono_ns, s.lat, s.lon, s.h, s.vn, s.ve, s.vd, s.q, self._sig,
                              len(self.epochs) - 1))
        if self._cov_dt >= self.params.cov_interval_s:
            self._propagate()

    def _pre_init(self, t_ns: int, acc: tuple[float, float, float], gyro: tuple[float, float, float],
                  dt: float) -> None:
        """Before the heading is known: level while still, then carry the attitude on the gyro alone."""
        still = self.stops.still and (self._obd is None or self._obd[1] == 0.0)
        fix = self._last_fix
        if fix is not None and fix.vel is not None and math.hypot(fix.vel[0], fix.vel[1]) > 1.0:
            still = False
        if still and self._prov_q is None:
            self.align.add(t_ns, acc, gyro)
            return
        if self._prov_q is None:
            if self.align.n == 0 or self.align.duration_s < self.params.align_min_s:
                self.align.reset()
                return
            lat = fix.lat if fix is not None else None
            roll, pitch = self.align.level()
            bg = self.align.gyro_bias(lat)
            self._levelled = (roll, pitch, bg, self.align.mean_force())
            self._level_span = (self.align.t1_ns, self.align.duration_s)
            self._prov_q = quat_from_euler(roll, pitch, 0.0)
            self._prov_w = None
            if self.params.heading_source == "config" and fix is not None:
                self._level_yaw = math.radians(self.params.initial_heading_deg)
                self._initialise(t_ns, math.radians(self.params.initial_heading_deg), "config heading", fix)
                return
        bg = self._levelled[2] if self._levelled else (0.0, 0.0, 0.0)
        w = (gyro[0] - bg[0], gyro[1] - bg[1], gyro[2] - bg[2])
        if 0.0 < dt <= MAX_IMU_GAP_S:
            pw = self._prov_w or w
            self._prov_q = quat_mul(self._prov_q, quat_from_rotvec(0.5 * (pw[0] + w[0]) * dt,
                                                                   0.5 * (pw[1] + w[1]) * dt,
                                                                   0.5 * (pw[2] + w[2]) * dt))
        self._prov_w = w
        self._prov_hist.append((t_ns, self._prov_q))

    def _initialise(self, t_ns: int, yaw_or_none: float | None, method: str, fix: _Fix,
                    heading_var: float = math.radians(2.0) ** 2) -> None:
        """Start the filter: levelled attitude turned to the heading, position and velocity from the fix."""
        p = self.params
        if self._levelled is not None and self._prov_q is not None:
            roll, pitch, bg, _ = self._levelled
            q = self._prov_q
            if yaw_or_none is not None and method == "config heading":
                q = quat_from_euler(roll, pitch, yaw_or_none)
            att_var = math.radians(0.3) ** 2
            # With the heading known, the horizontal earth rate comes out of the standstill's gyro mean, and
            # what is left of the offset is what that mean could not average out.
            e = horizontal_earth_rate_body(roll, pitch, self._level_yaw, fix.lat)
            bg = (bg[0] - e[0], bg[1] - e[1], bg[2] - e[2])
            end_ns, span_s = self._level_span
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
        arm = c_bn @ self.lever
        s.lat, s.lon, s.h = earth.offset_llh(s.lat, s.lon, s.h, -arm[0], -arm[1], -arm[2])
        if self.n > SF_ID:
            s.dh = self._baro_offset_guess(s.h)
        self.state = s
        n = self.n
        p0 = np.zeros((n, n))
        for i in range(3):
            p0[P_ID + i, P_ID + i] = fix.sigma[i] ** 2 + (abs(vel[i]) * 0.05) ** 2
            p0[V_ID + i, V_ID + i] = max(fix.s_vel, 0.1) ** 2 + 0.1
            p0[BG_ID + i, BG_ID + i] = bg_var
        self._accel_bias_var = p.accel_bias_sigma**2
        if self._levelled is not None and c_level is not None:
            self._accel_bias_var = accel_offset_variance(self._levelled[3], earth.gravity(fix.lat, fix.h),
                                                         self._accel_bias_var)
        pphi, pphiba, pba = tilt_bias_covariance(c_bn if c_level is None else c_level, self._accel_bias_var,
                                                 earth.G0)
        p0[PHI_ID:PHI_ID + 3, PHI_ID:PHI_ID + 3] = pphi + np.diag((att_var, att_var, heading_var))
        p0[PHI_ID:PHI_ID + 3, BA_ID:BA_ID + 3] = pphiba
        p0[BA_ID:BA_ID + 3, PHI_ID:PHI_ID + 3] = pphiba.T
        p0[BA_ID:BA_ID + 3, BA_ID:BA_ID + 3] = pba
        if n > SF_ID:
            p0[SF_ID, SF_ID] = p.obd_scale_sigma**2
            p0[DH_ID, DH_ID] = fix.sigma[2] ** 2 + p.baro_sigma_m**2 + 1.0
        self.ekf = ErrorStateEkf(np.ones(n), p.gate_probability)
        self.ekf.p = p0
        self.thermal.restart()
        self._sig = tuple(math.sqrt(p0[P_ID + i, P_ID + i]) for i in range(3))
        self.mech.reset()
        acc, gyro = self._raw  # the latest sample starts the integration, corrected as the state now says
        self.mech.prime((gyro[0] - bg[0], gyro[1] - bg[1], gyro[2] - bg[2]), acc)
        self._hist.clear()
        self._corr = (0.0,) * 6
        self.counters.initialised_ns = t_ns
        self.counters.init_method = method
        if self.record:
            self.epochs.append(Epoch(t_ns, None, p0.copy(), dx=np.zeros(n)))

    def _baro_offset_guess(self, h: float) -> float:
        return 0.0 if self._baro_last is None else h - self._baro_last[1]

    # ---- covariance ------------------------------------------------------------------------------------
    def _propagate(self) -> None:
        dt = self._cov_dt
        if dt <= 0.0 or self.ekf is None or self.state is None:
            return
        s = self.state
        fa = self._f_acc
        f_mean = (fa[0] / dt, fa[1] / dt, fa[2] / dt)
        phi, qd = discretize(error_dynamics(s, s.dcm(), f_mean, self.n), self.q_diag, dt)
        if self.record:
            self.epochs[-1].p_plus = self.ekf.p.copy()
        self.ekf.propagate(phi, qd)
        owed = self.thermal.take()
        if owed > 0.0:
            # The offsets follow the die temperature through a fixed, unknown coefficient (thermal.py).
            pk = self.ekf.p
            for i in range(3):
                pk[BA_ID + i, BA_ID + i] += self.params.accel_bias_tempco**2 * owed
                pk[BG_ID + i, BG_ID + i] += self.params.gyro_bias_tempco**2 * owed
        if self.record:
            self.epochs.append(Epoch(self._t_last or 0, phi.astype(np.float32), self.ekf.p.copy(), dx=np.zeros(self.n)))
        self._cov_dt = 0.0
        self._f_acc = [0.0, 0.0, 0.0]
        self._refresh_sigma()

    def _refresh_sigma(self) -> None:
        p = self.ekf.p if self.ekf is not None else None
        if p is not None:
            self._sig = (math.sqrt(max(p[0, 0], 0.0)), math.sqrt(max(p[1, 1], 0.0)), math.sqrt(max(p[2, 2], 0.0)))

    def _apply(self, obs: Observation, gated: bool = True) -> bool:
        """Bring the covariance to now, update, and feed the estimate back into the nominal state."""
        if self.ekf is None or self.state is None:
            return False
        if self._cov_dt >= UPDATE_STALE_S:
            self._propagate()  # a covariance a few IMU samples old serves the update as well, and costs nothing
        dx = self.ekf.update(obs, gated)
        if dx is None:
            return False
        self._feedback(dx)
        return True

    def _feedback(self, dx: np.ndarray) -> None:
        assert self.state is not None
        self.state.correct(dx)
        c, d = self._corr, dx[:6].tolist()
        self._corr = (c[0] + d[0], c[1] + d[1], c[2] + d[2], c[3] + d[3], c[4] + d[4], c[5] + d[5])
        if self.record and self.epochs:
            ep = self.epochs[-1]
            ep.dx = dx if ep.dx is None else ep.dx + dx
        self._refresh_sigma()

    # ---- the solution at a past instant (for a fix that arrives late) ------------------------------------
    def _state_at(self, t_ns: int) -> NavState:
        s = self.state
        assert s is not None
        entry = None
        for e in reversed(self._hist):
            if e[0] <= t_ns:
                entry = e
                break
        if entry is None:
            entry = self._hist[0] if self._hist else None
        out = s.copy()
        if entry is None:
            return out
        t_e, lat, lon, h, vn, ve, vd, q, corr = entry
        c = self._corr
        d = [c[i] - corr[i] for i in range(6)]
        vn, ve, vd = vn - d[3], ve - d[4], vd - d[5]
        dt = (t_ns - t_e) / NS
        lat, lon, h = earth.offset_llh(lat, lon, h, -d[0] + vn * dt, -d[1] + ve * dt, -d[2] + vd * dt)
        out.lat, out.lon, out.h, out.vn, out.ve, out.vd, out.q = lat, lon, h, vn, ve, vd, q
        return out

    # ---- GNSS --------------------------------------------------------------------------------------------
    def gnss(self, msg: dict[str, Any]) -> None:
        c = self.counters
        if not msg.get("fix_ok") or (msg.get("fix_mode") or 1) < 2:
            c.gnss_no_fix += 1
            return
        c.gnss_fixes += 1
        p = self.params
        t_sync = int(msg["t_sync_ns"])
        t_e = self.epoch_clock.epoch_time(t_sync, msg.get("gnss_time_ns"), msg.get("sync_state", ""))
        h_acc, v_acc = msg.get("h_acc_m"), msg.get("v_acc_m")
        if h_acc is None or v_acc is None:
            pdop = msg.get("pdop") or 99.0
            h_acc = p.gnss_uere_m * pdop * 0.6 * math.sqrt(2.0)
            v_acc = p.gnss_uere_m * pdop * 0.8
        k = p.gnss_acc_scale
        s_acc = msg.get("s_acc_mps")
        sig_h, sig_v, s_vel = self._gnss_noise.sigmas(t_e, float(h_acc), float(v_acc),
                                                      float(s_acc) if s_acc is not None else 0.5)
        sig_h, sig_v, s_vel = max(0.1, k * sig_h), max(0.2, k * sig_v), max(0.03, k * s_vel)
        vel = msg.get("vel_ned_mps")
        vel_arr = None if vel is None or any(v is None for v in vel) else np.array(vel, float)
        fix_3d = (msg.get("fix_mode") or 0) >= 3
        fix = _Fix(t_e, int(msg["t_mono_ns"]) + (t_e - t_sync), math.radians(msg["latitude"]),
                   math.radians(msg["longitude"]), float(msg["altitude"]), vel_arr, (sig_h, sig_h, sig_v), s_vel,
                   fix_3d, float(h_acc))
        self._last_fix = fix
        if self.mode == "gnss":
            self._gnss_row(fix)
            return
        if self.state is None:
            self._try_heading_init(fix)
            return
        num_sv = msg.get("num_sv")
        if num_sv is not None and num_sv < p.gnss_min_sv:
            # Four or five satellites leave the receiver nothing to check its solution against: a reflection
            # shifts the fix by tens of metres while its accuracy figure stays small. Counted, not used.
            c.gnss_few_sv += 1
            return
        # Rows of a fix far worse than what the filter already knows would move it by a few percent per epoch,
        # and a receiver's errors in a street canyon persist for many epochs: those percents add up to its
        # bias, not to information. Such rows are left out (counted); the others go in.
        snap = self._state_at(t_e)
        full_pos = GnssPosition(fix.lat, fix.lon, fix.h, fix.sigma, self.lever, not fix_3d).observe(
            snap, snap.dcm(), self.n)
        obs = self._informative(full_pos, P_ID)
        ok = True if obs is None else self._apply(obs)
        if obs is not None and ok:
            self._last_pos_ok = (t_e, fix.h_acc)
            if fix_3d and len(obs.z) == 3 and fix.h_acc < 10.0:
                self._last_height_in_ns = t_e
        if vel_arr is not None:
            snap = self._state_at(t_e)
            full = GnssVelocity(vel_arr, s_vel, self.lever, np.array(self._gyro_raw), not fix_3d).observe(
                snap, snap.dcm(), self.n)
            obs = self._informative(full, V_ID)
            if obs is not None:
                self._velocity_evidence(obs, self._apply(obs), t_e,
                                        fix_3d and len(obs.z) == len(full.z) and fix.h_acc < 10.0)
        self._divergence_check(ok, fix, full_pos.z.tolist())

    def _informative(self, obs: Observation, block: int) -> Observation | None:
        """The observation without its rows whose variance exceeds the filter's own by UNINFORMATIVE_RATIO."""
        assert self.ekf is not None
        p = self.ekf.p
        keep = [i for i in range(min(2, len(obs.z)))
                if obs.r[i] <= UNINFORMATIVE_RATIO * float(p[block + i, block + i])]
        # The height row stays while the fix is any good horizontally: the barometer's offset is learnt from the
        # GNSS height over minutes. A fix useless horizontally is a canyon's, and its height goes with it.
        if len(obs.z) > 2 and keep:
            keep.append(2)
        if len(keep) < len(obs.z):
            self.counters.gnss_skipped += len(obs.z) - len(keep)
            if not keep:
                return None
            obs = Observation(obs.name, obs.z[keep], obs.h[keep], obs.r[keep])
        return obs

    def _gnss_row(self, fix: _Fix) -> None:
        v = fix.vel if fix.vel is not None else np.zeros(3)
        yaw = math.atan2(v[1], v[0])
        self.solution = Solution(fix.t_ns, fix.t_mono_ns, fix.lat, fix.lon, fix.h, (float(v[0]), float(v[1]),
                                 float(v[2])), (0.0, 0.0, yaw), fix.sigma, "gnss")
        if self.record:
            self.rows.append((fix.t_ns, fix.t_mono_ns, fix.lat, fix.lon, fix.h, float(v[0]), float(v[1]), float(v[2]),
                              quat_from_euler(0.0, 0.0, yaw), fix.sigma, -1))

    def _try_heading_init(self, fix: _Fix) -> None:
        p = self.params
        if fix.vel is None or not fix.fix_3d:
            return
        speed = math.hypot(fix.vel[0], fix.vel[1])
        if speed < p.heading_min_speed_mps or fix.s_vel > 0.2 * speed:
            return
        course = math.atan2(fix.vel[1], fix.vel[0])
        heading_var = (fix.s_vel / speed) ** 2 + math.radians(1.5) ** 2
        if self._prov_q is not None and self._levelled is not None:
            q_then = self._prov_q
            for t, q in reversed(self._prov_hist):
                if t <= fix.t_ns:
                    q_then = q
                    break
            _, _, yaw_then = euler_from_dcm(_dcm(q_then))
            self._prov_q = rotate_heading(self._prov_q, course - yaw_then)
            self._level_yaw = course - yaw_then  # the provisional attitude began at yaw 0 when levelling ended
            self._initialise(self._t_last or fix.t_ns, None, "gnss course", fix, heading_var)
        else:
            self._initialise(self._t_last or fix.t_ns, course, "gnss course, no levelling", fix,
                             heading_var + math.radians(3.0) ** 2)

    def _divergence_check(self, accepted: bool, fix: _Fix, innovation: list[float]) -> None:
        """Good fixes refused again and again that agree among themselves (the filter, not the receiver, is
        off), or a covariance gone wild: start again from the receiver. A street canyon's fixes are refused
        too, but they scatter: they do not trigger it."""
        assert self.ekf is not None and self.state is not None
        if fix.h_acc < 10.0 and fix.fix_3d:  # a 2D fix has no height of its own to settle anything with
            self._last_good_fix_ns = fix.t_ns
        if accepted:
            self._rejects.clear()
        elif fix.h_acc < 10.0 and len(innovation) >= 2:
            # On every axis the fix had (its whole innovation, also the rows left out as uninformative): a height
            # gone off behind a confident covariance is refused as surely as a position off sideways, and only
            # its vertical innovations agree.
            self._rejects.append((fix.t_ns, *innovation))
        sig = max(self._sig)
        lost = False
        rj = self._rejects
        last_t, last_acc = self._last_pos_ok
        if (not accepted and REANCHOR_REJECTS <= len(rj) < DIVERGENCE_REJECTS and fix.h_acc <= REANCHOR_H_ACC_M
                and (rj[0][0] - last_t >= REANCHOR_AFTER_NS or last_acc > 2.0 * fix.h_acc)
                and self._agree(rj[-REANCHOR_REJECTS:])):
            # Good fixes after a spell without any (or with worse ones only), all off by the same few metres: the
            # solution drifted further than its covariance says (a long dead reckoning on a speed sensor whose
            # steps do not average out). Admit the uncertainty of the position, counted, and let this fix in;
            # velocity and attitude are kept.
            inno = np.array((*rj[-1][1:], 0.0, 0.0)[:3])
            self.ekf.inflate(slice(P_ID, P_ID + 3), [float(self.ekf.p[P_ID + i, P_ID + i]) + inno[i] ** 2
                                                      + fix.sigma[i] ** 2 for i in range(3)])
            self.counters.reanchors += 1
            self._baro_refusals.clear()  # judged against the height just widened
            snap = self._state_at(fix.t_ns)
            if self._apply(GnssPosition(fix.lat, fix.lon, fix.h, fix.sigma, self.lever, not fix.fix_3d)
                           .observe(snap, snap.dcm(), self.n)):
                self._rejects.clear()
            return
        if len(rj) >= DIVERGENCE_REJECTS and rj[-1][0] - rj[0][0] >= DIVERGENCE_SPAN_NS:
            lost = self._agree(rj[-DIVERGENCE_REJECTS:])
        if not (lost or not math.isfinite(sig) or sig > DIVERGENCE_SIGMA_M):
            return
        s = self.state
        snap = self._state_at(fix.t_ns)
        dn, de, dd = earth.ned_offset_m(fix.lat, fix.lon, fix.h, snap.lat, snap.lon, snap.h)
        dx = np.zeros(self.n)
        dx[P_ID:P_ID + 3] = (dn, de, dd)
        if fix.vel is not None:
            dx[V_ID:V_ID + 3] = (s.vn - fix.vel[0], s.ve - fix.vel[1], s.vd - fix.vel[2])
        self._feedback(dx)
        self.ekf.inflate(slice(P_ID, V_ID + 3), [fix.sigma[0] ** 2, fix.sigma[1] ** 2, fix.sigma[2] ** 2,
                                                  fix.s_vel**2 + 0.1, fix.s_vel**2 + 0.1, fix.s_vel**2 + 0.1])
        self._reopen_attitude_and_offsets()
        self.counters.resets += 1
        # Refusals judged against the lost solution say nothing of the new one.
        self._rejects.clear()
        self._baro_refusals.clear()
        self._vel_refusals.clear()
        self._refresh_sigma()

    def _velocity_evidence(self, obs: Observation, accepted: bool, t_ns: int, trusted: bool,
                           body_to_ned: np.ndarray | None = None) -> bool:
        """Trusted velocities refused in a row that agree with each other: reopen the filter's velocity, attitude
        and offsets (counted as ``reopens``) and let the last one in. Returns whether it went in.

        A stop the OBD confirms is zero velocity beyond doubt, and a good receiver's Doppler velocity has no
        canyon bias worth metres per second; when the gate refuses them again and again, the filter's velocity
        is off by more than its covariance admits, and it got there through a tilt or an offset it holds too
        firmly (a chip worse than configured). The same holds for the OBD speed with its non-holonomic rows
        (innovations in vehicle axes: ``body_to_ned`` turns them). Refusing them further would leave it dead
        reckoning on that error until a divergence restart; a canyon's scattered velocities do not agree and do
        not trigger it. Each source keeps its own run of refusals."""
        rv = self._vel_refusals.setdefault(obs.name, [])
        if accepted:
            rv.clear()
            return True
        if not trusted:
            return False
        rv.append((t_ns, float(obs.z[0]), float(obs.z[1])))
        del rv[:-REFUSALS_KEPT]  # only the latest are judged: bounded while they scatter
        if (len(rv) < VELOCITY_REFUSALS or rv[-1][0] - rv[-VELOCITY_REFUSALS][0] < VELOCITY_REFUSAL_SPAN_NS
                or not self._agree(rv[-VELOCITY_REFUSALS:])):
            return False
        assert self.ekf is not None
        zv = obs.z[:3] if body_to_ned is None else body_to_ned @ obs.z[:3]
        z, r = zv.tolist(), obs.r.tolist()
        if body_to_ned is not None:  # the rows' noise, turned the same way (per axis, upper bound)
            r = (np.abs(body_to_ned) @ np.asarray(obs.r[:3])).tolist()
        old = self.ekf.p.diagonal().copy()
        # The velocity was off by up to this much since the first refusal: so was the position's drift.
        span_s = (rv[-1][0] - rv[0][0]) / NS
        self.ekf.inflate(slice(P_ID, V_ID + 3),
                         [float(old[P_ID + i]) + (z[i] * span_s) ** 2 if i < len(z) else float(old[P_ID + i])
                          for i in range(3)]
                         + [float(old[V_ID + i]) + z[i] ** 2 + r[i] if i < len(z) else float(old[V_ID + i])
                            for i in range(3)])
        self._reopen_attitude_and_offsets()
        self.counters.reopens += 1
        rv.clear()
        return self._apply(obs)

    def _reopen_attitude_and_offsets(self) -> None:
        """After a restart, forget what the filter believed of its attitude and IMU offsets, not only of its position.

        A filter that lost itself did so because its attitude or offsets were further off than their covariance
        said (a tilt taken for an accelerometer offset, a gyro offset the standstill mis-read): keeping that
        covariance would lock the same error in and restart again. Tilt and accelerometer offset get back their
        priors (the tilt an offset of the prior would cause, in the body axes as they stand now), but not the
        correlation levelling gave them: levelling measured their sum (the horizontal specific force was zero), a
        reopening is the evidence that the sum is off, so a prior that pins it again would admit none of the drift
        that caused it, and the next velocities would be refused and reopen again (every few seconds, for as long
        as the car drives straight). Heading and gyro offset get what the start-up gave them; none shrinks below
        what the filter holds now. The gyro offset's also covers the die temperature's change since the start
        (thermal.py)."""
        assert self.ekf is not None and self.state is not None
        p = self.params
        ekf = self.ekf
        old = ekf.p.diagonal().copy()
        pphi, _, pba = tilt_bias_covariance(self.state.dcm(), self._accel_bias_var, earth.G0)
        end_ns, span_s = self._level_span
        since_s = ((self._t_last or 0) - end_ns) / NS
        bg_var = (gyro_calibration_variance(p.gyro_arw, p.gyro_bias_walk, span_s, since_s) if span_s > 0.0
                  else p.gyro_bias_sigma**2)
        ekf.inflate(slice(PHI_ID, BG_ID + 3), np.zeros(9))
        att = np.diag((math.radians(0.3) ** 2, math.radians(0.3) ** 2, math.radians(5.0) ** 2))
        ekf.p[PHI_ID:PHI_ID + 3, PHI_ID:PHI_ID + 3] = pphi + att
        ekf.p[BA_ID:BA_ID + 3, BA_ID:BA_ID + 3] = pba  # uncorrelated with the tilt: their sum was just shown off
        bg_var += p.gyro_bias_tempco**2 * self.thermal.range_degc**2
        for i in range(3):
            ekf.p[BG_ID + i, BG_ID + i] = max(bg_var, float(old[BG_ID + i]))
            ekf.p[PHI_ID + i, PHI_ID + i] = max(float(ekf.p[PHI_ID + i, PHI_ID + i]), float(old[PHI_ID + i]))

    @staticmethod
    def _agree(refused: list[tuple[float, ...]]) -> bool:
        """Refused measurements (time, innovation...) whose innovations agree within a quarter of their mean: a
        shifted solution, not a scattering receiver."""
        width = min(len(r) for r in refused)
        inno = np.array([r[1:width] for r in refused])
        mean = inno.mean(axis=0)
        return float(np.linalg.norm(inno - mean, axis=1).max()) < 0.25 * float(np.linalg.norm(mean))

    # ---- OBD, baro, stops --------------------------------------------------------------------------------
    def obd(self, t_ns: int, speed_mps: float) -> None:
        if self.mode != "17":  # the baseline and GNSS-only modes know nothing of the vehicle's speed sensor
            return
        self.counters.obd += 1
        if self._obd is None or self._obd[1] != speed_mps:
            self._obd_run, self._obd_run_t0 = 1, t_ns
        elif t_ns - self._obd_run_t0 <= OBD_ROUNDING_HOLD_NS:
            self._obd_run += 1
        self._obd = (t_ns, speed_mps)
        if self.state is None:
            return
        p = self.params
        if self._stop_update(speed_mps == 0.0 and self.stops.still, learn=True):
            return
        if speed_mps < OBD_MIN_SPEED_MPS:
            return
        # The speed the ECU reported belongs to its own instant: evaluated against the solution then.
        # At a steady speed the reading stays on one 1 km/h step and its rounding error stays the same: the
        # repeats say little new about it, so they weigh less and less (a run of equal readings is not many
        # independent ones: 40 of them would otherwise pull the solution to the rounded speed). A real speed
        # does not stay within one step for long, and the IMU drifts meanwhile: past OBD_ROUNDING_HOLD_NS the
        # repeats keep the weight they had then, and hold the speed again.
        sigma = math.sqrt(repeat_variance(p.obd_speed_sigma_mps, OBD_STEP_MPS, self._obd_run))
        snap = self._state_at(t_ns)
        obs = ObdVelocity(speed_mps, sigma, p.nhc_sigma_mps).observe(snap, snap.dcm(), self.n)
        if self._velocity_evidence(obs, self._apply(obs), t_ns, True, snap.dcm()):
            self._last_nhc_ns = t_ns
            if speed_mps > 5.0:  # a mounting turned about the vertical shows as a steady side slip
                self.mount_yaw_stat[0] += float(obs.z[1]) / speed_mps
                self.mount_yaw_stat[1] += 1.0

    def _stop_update(self, stopped_now: bool, learn: bool = False) -> bool:
        """Zero velocity and zero rate (Eq. 12) over the stop so far; returns whether the vehicle stands."""
        assert self.state is not None
        p, s = self.params, self.state
        was = self.stopped
        self.stopped = stopped_now
        ws = self._w_stop
        if stopped_now:
            if learn:
                self.stops.learn()
            span_s = ((self._t_last or 0) - self._w_stop_t0) / NS
            if was and ws[3] > 0 and span_s > 0.0:
                w_mean = np.array((ws[0] / ws[3], ws[1] / ws[3], ws[2] / ws[3]))
                # The mean over the window: the gyro's white noise averages down with its length.
                sigma_w = max(math.radians(p.zaru_sigma_dps), p.gyro_arw) / math.sqrt(span_s)
                obs = ZeroMotion(w_mean, p.zupt_sigma_mps, sigma_w).observe(s, s.dcm(), self.n)
                self._velocity_evidence(obs, self._apply(obs), self._t_last or 0, learn)
                self.counters.zupt += 1
        self._w_stop = [0.0, 0.0, 0.0, 0]
        self._w_stop_t0 = self._t_last or 0
        return stopped_now

    def baro(self, t_ns: int, altitude_m: float) -> None:
        if self.mode != "17":
            return
        self.counters.baro += 1
        self._baro_last = (t_ns, altitude_m)
        if self.state is None:
            return
        s = self.state
        self._height_evidence(BaroHeight(altitude_m, self.params.baro_sigma_m).observe(s, s.dcm(), self.n), t_ns)
        # No fresh OBD speed: the vehicle still cannot slide sideways or lift off.
        if (self.stopped is False and self._obd is not None and t_ns - self._obd[0] > OBD_FRESH_NS
                and t_ns - self._last_nhc_ns > NHC_INTERVAL_NS and math.hypot(s.vn, s.ve) > NHC_MIN_SPEED_MPS
                and self._apply(NonHolonomic(self.params.nhc_sigma_mps).observe(s, s.dcm(), self.n))):
            self._last_nhc_ns = t_ns

    def _height_evidence(self, obs: Observation, t_ns: int) -> bool:
        """Barometer heights refused in a row that agree (the same few metres off, second after second): the
        filter's height went further off than its covariance admits (a vertical channel dead reckoned on too
        firm a belief), and refusing the sensor would keep it off for the rest of the drive, with every later
        GNSS fix refused on its height as well. Or the barometer's offset moved (a sensor replaced, a pressure
        port knocked). Which of the two is widened (counted as ``reanchors``) before the barometer goes in:
        - the receiver's heights are going in: the filter's height agrees with them, so the offset moved;
        - good 3D fixes come but are refused too: both, and the receiver's heights settle which one moved;
        - no receiver: the height, since the offset, which weather moves by centimetres a minute, is the
          firmer of the two (the height follows the barometer until fixes come back).
        The refusals are judged over at least BARO_REFUSALS readings and BARO_REFUSAL_SPAN_NS, whatever the
        barometer's rate. Returns whether the height went in."""
        if self._apply(obs):
            self._baro_refusals.clear()
            return True
        rb = self._baro_refusals
        rb.append((t_ns, float(obs.z[0])))
        del rb[:-REFUSALS_KEPT]
        if len(rb) < BARO_REFUSALS or rb[-1][0] - rb[0][0] < BARO_REFUSAL_SPAN_NS:
            return False
        k = BARO_REFUSALS  # the shortest run of the latest refusals that spans the time
        while k < len(rb) and rb[-1][0] - rb[-k][0] < BARO_REFUSAL_SPAN_NS:
            k += 1
        if not self._agree(rb[-k:]):
            return False
        assert self.ekf is not None
        old = self.ekf.p.diagonal().copy()
        grow = float(obs.z[0]) ** 2 + float(obs.r[0])
        receiver_heights_in = t_ns - self._last_height_in_ns <= GNSS_ARBITER_NS
        if not receiver_heights_in:
            self.ekf.inflate(slice(P_ID + 2, P_ID + 3), [float(old[P_ID + 2]) + grow])
        if receiver_heights_in or t_ns - self._last_good_fix_ns <= GNSS_ARBITER_NS:
            self.ekf.inflate(slice(DH_ID, DH_ID + 1), [float(old[DH_ID]) + grow])
        self.counters.reanchors += 1
        rb.clear()
        return self._apply(obs)

    # ---- output ------------------------------------------------------------------------------------------
    def current(self) -> Solution | None:
        s = self.state
        if self.mode == "gnss" or s is None:
            return self.solution
        roll, pitch, yaw = euler_from_dcm(s.dcm())
        return Solution(self._t_last or 0, self._t_mono_last, s.lat, s.lon, s.h, (s.vn, s.ve, s.vd),
                        (roll, pitch, yaw), self._sig, f"ins {self.mode}-state")


def _dcm(q: tuple[float, float, float, float]) -> np.ndarray:
    from logger.nav.rotations import dcm_from_quat

    return dcm_from_quat(q)
