"""The navigation engine: recorded or live messages in time order in, a navigation solution at the IMU rate out.

One engine serves the live navigator and ``logger replay``, so what the operator sees on the road is what a
post-processing run computes. Per IMU sample it runs the strapdown mechanization (cheap, plain floats); the
covariance is propagated at most every ``cov_interval_s`` and always before an update. Measurements are
applied in the order they arrive, each at its own time: a GNSS fix is evaluated against the solution at its
epoch (kept in a short history, corrected for every feedback since), the others against the latest one.

Modes: ``17`` the paper's filter (GNSS, OBD with its scale factor, baro with its offset, zero motion at stops,
non-holonomic constraint), ``15`` the paper's baseline (GNSS position and velocity only), ``gnss`` the
receiver's own fixes passed through, for comparison on the same data.

This module is the loop: the strapdown step per sample, the covariance, the updates and their feedback, and the
outputs. Its rooms are :mod:`logger.nav.startup` (levelling and the first heading), :mod:`logger.nav.policies`
(what each sensor's reading is worth), :mod:`logger.nav.evidence` (what refusals in a row say) and
:mod:`logger.nav.history` (the solution at a late measurement's instant); the policies and the evidence rules
act on the engine through :class:`logger.nav.core.FilterCore`, the start-up only hands back the initial state
and covariance. Inputs are typed (:mod:`logger.nav.inputs`): the engine knows no record.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from logger.nav import earth
from logger.nav.alignment import gyro_calibration_variance, tilt_bias_covariance
from logger.nav.arrays import diff_from
from logger.nav.core import EngineCounters, PreparedFix
from logger.nav.dynamics import ProcessNoise, error_dynamics, transition
from logger.nav.ekf import ErrorStateEkf
from logger.nav.evidence import HeightEvidence, PositionEvidence, VelocityEvidence
from logger.nav.gnss_time import GnssEpochClock
from logger.nav.history import SolutionHistory
from logger.nav.imu_noise import CONSUMER_NOISE_RATIO, ImuNoiseMonitor, OffsetWander, consumer_grade
from logger.nav.inputs import GnssObservation, SolutionEpoch
from logger.nav.measurements import ROUNDING_VAR, Observation
from logger.nav.mounting import SETTLED, MountAlignment, MountEstimate, forward_axis_deg, mount_matrix
from logger.nav.params import MODES, NavParams
from logger.nav.policies import (
    NHC_INTERVAL_NS,
    OBD_FRESH_NS,
    BaroPolicy,
    GnssPolicy,
    LastReadings,
    ObdPolicy,
    StopPolicy,
)
from logger.nav.rotations import (
    dcm_elements,
    dcm_from_euler,
    euler_from_dcm,
    quat_from_dcm,
    quat_from_euler,
    rotvec_from_dcm,
    twist_about_x,
)
from logger.nav.solution import SolutionPolicy
from logger.nav.start_height import StartHeight
from logger.nav.startup import CONFIG_HEADING, MAX_IMU_GAP_S, Startup, height_offset_variance
from logger.nav.state import BA_ID, BG_ID, DH_ID, N_FULL, N_INS, N_ROUNDING, P_ID, PHI_ID, RQ_ID, V_ID, NavState
from logger.nav.stops import GNSS_STANDING_MPS, HeldStop, StopDetector
from logger.nav.strapdown import Strapdown, preintegrate
from logger.nav.thermal import TempcoLearner, TemperatureSpan, turned

NS = 1_000_000_000
IMU_GAP_S = 0.5  # samples further apart than this are a gap: counted, and still integrated across
UPDATE_STALE_S = 0.2  # an update uses the covariance as last propagated if that is less than this old
CONING_MAX_DT_S = 0.0105  # mean sample interval below which coning/sculling corrections are applied
CONFIG_HEADING_VAR = math.radians(2.0) ** 2
REMOUNT_INTERVAL_NS = 10 * NS  # how often a settled alignment's estimate is compared with the mounting in use
REMOUNT_MIN_DEG = 0.5  # a settled estimate further from the mounting in use than this (and 2 sigma) replaces it
REOPEN_DEG = 2.0  # a new mounting this far from the old one reopens attitude and offsets; less is a refinement
PRE_INIT_BATCH_MIN = 50  # before the start, blocks from this size go through _pre_init_block (at 40 it is even)
BATCH_MIN = 64  # shorter batches go sample by sample: the block forms cost numpy calls worth tens of samples
DECIMATED_BATCH_MIN = 16  # ... unless integrated in steps of several samples: then a FIFO read of 40 gains
NEVER = 2**63 - 1
STANDING_MPS = 0.5  # a solution slower than this may stand (the idle check's, and a held stop's, bound)


class TrajectoryRow(NamedTuple):
    """One solution of the trajectory (replay keeps one per IMU sample; per fix in GNSS-only mode)."""

    t_ns: int  # synchronised time of the sample, Unix ns
    t_mono_ns: int
    lat_rad: float
    lon_rad: float
    h_m: float  # above the ellipsoid
    vn_mps: float
    ve_mps: float
    vd_mps: float
    q: tuple[float, float, float, float]  # attitude, body to NED
    sigma_ned_m: tuple[float, float, float]
    epoch: int  # index of the covariance epoch the sample follows (the smoother's), -1 for none


# A row made straight from its fields' tuple: TrajectoryRow(...) goes through a generated Python __new__, a frame per
# IMU sample for nothing.
_new_row = tuple.__new__


@dataclass
class Epoch:
    """A covariance time step, kept for the backward smoother."""

    t_ns: int
    phi: np.ndarray | None  # transition from the previous epoch
    p_minus: np.ndarray
    p_plus: np.ndarray | None = None
    dx: np.ndarray | None = None  # sum of the corrections fed back at this epoch
    cut: bool = False  # the filter forgot something here (a restart, a re-anchor, a reopening): see smoother.py
    # Corrections fed back after rows of this epoch were already recorded (an update on a covariance less than
    # UPDATE_STALE_S old does not open an epoch): (rows recorded by then, the correction). Those rows lie on the
    # solution before it.
    late: list[tuple[int, np.ndarray]] = field(default_factory=list)


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


def configured_tempco(p: NavParams) -> tuple[float, ...]:
    """The configured bounds of the offsets' temperature coefficients, accelerometer x y z then gyro x y z: the
    learner's prior (and what a saved one is checked against)."""
    return (p.accel_bias_tempco,) * 3 + (p.gyro_bias_tempco,) * 3


def forward_axis_turned(applied_rpy_deg: tuple[float, ...], est: MountEstimate) -> bool:
    """Whether an estimate puts the car's forward axis on the chip REOPEN_DEG and three of its sigmas (pitch, yaw)
    from the mounting in use: the rule for taking it (live, and for replay's second pass)."""
    return forward_axis_deg(applied_rpy_deg, est.rpy_deg) >= max(REOPEN_DEG, 3.0 * max(est.sigma_deg[1],
                                                                                        est.sigma_deg[2]))


@dataclass
class NavEngine:
    """The filter's loop; implements :class:`logger.nav.core.FilterCore` for its rooms."""

    params: NavParams = field(default_factory=NavParams)
    record: bool = False  # keep rows and covariance epochs (replay and the smoother)

    def __post_init__(self) -> None:
        p = self.params
        if p.mode not in MODES:
            raise ValueError(f"unknown navigation mode {p.mode!r}: choose one of {', '.join(MODES)}")
        self.mode = p.mode
        self.n = (N_ROUNDING if p.obd_rounding_state else N_FULL) if p.mode == "17" else N_INS
        self._full, self._gnss_only = p.mode == "17", p.mode == "gnss"
        self._set_mount(dcm_from_euler(*(math.radians(a) for a in p.mounting_rpy_deg)))
        self.alignment = MountAlignment(p.mounting_rpy_deg) if p.mount_align and p.mode != "gnss" else None
        self.mount_applied: tuple[float, float, float] = tuple(float(a) for a in p.mounting_rpy_deg)
        self.mount_reopened_ns: int | None = None  # the first remount that reopened attitude and offsets (rerun.py)
        # Set on the engine that took a drive's first minutes again with that remount's mounting: how far into
        # them the remount came, s (recording/nav_rerun.py; /nav/state says it).
        self.rerun_at_s: float | None = None
        self._next_remount_ns = 0
        self.lever = np.array(p.lever_arm_m, float)
        self.mech = Strapdown(coning=False)
        self.stops = StopDetector(p.still_accel_mps2)
        self._obd_held, self._fix_held = HeldStop(), HeldStop()  # stops the OBD speed, or the fixes, hold
        self.startup = Startup(p)
        self.start_height = StartHeight.for_params(p)
        self.epoch_clock = GnssEpochClock()
        self.noise = ProcessNoise(p.accel_vrw, p.gyro_arw, p.accel_bias_walk, p.gyro_bias_walk, p.obd_scale_walk_rts,
                                  p.baro_offset_walk_m_rts, p.obd_rounding_walk_mps_rts)
        self.q_diag = self.noise.diagonal(self.n)
        self.imu_noise = ImuNoiseMonitor() if p.imu_noise_from_drive else None
        self.offset_wander = OffsetWander() if p.imu_noise_from_drive else None
        self.thermal = TemperatureSpan()  # die temperature since the offsets were calibrated
        # The offsets' temperature coefficients learnt from the drive, the configured bounds their prior.
        self.tempco = TempcoLearner(configured_tempco(p))
        self._tempco_at = math.nan  # the smoothed die temperature the offsets were last moved to
        self._tempco_moved = (0.0, 0.0, 0.0)  # how far that moved the gyro's offsets since the learner started
        self._tempco_saved: tuple[list[float], list[float]] | None = None  # an earlier drive's, chip axes
        # The offsets' walks at the chip's grade (the configured ones scaled by the noise measured), without the
        # wander read from the estimates (OffsetWander), which holds the temperature's drift the learner models.
        self._grade_walk = (p.accel_bias_walk, p.gyro_bias_walk)
        self.state: NavState | None = None
        self.ekf: ErrorStateEkf | None = None
        self.counters = EngineCounters()
        self.rows: list[TrajectoryRow] = []
        self.epochs: list[Epoch] = []
        self.solution: Solution | None = None
        self.sigma = (math.inf, math.inf, math.inf)  # 1-sigma position N, E, D as last propagated or updated
        self.history = SolutionHistory()
        self.last_readings = LastReadings()
        self.position_evidence = PositionEvidence()
        self.velocity_evidence = VelocityEvidence()
        self.height_evidence = HeightEvidence()
        self._stop = StopPolicy(p, self.stops, self.velocity_evidence)
        self._gnss = GnssPolicy(p, self.epoch_clock, self.last_readings, self.position_evidence, self.velocity_evidence,
                                self.height_evidence)
        self._obd = ObdPolicy(p, self.last_readings, self._stop, self.velocity_evidence)
        self._baro = BaroPolicy(p, self.last_readings, self._stop, self.height_evidence)
        self.solution: SolutionPolicy | None = None  # a post-processed solution's epochs (use_solution)
        self._t_last: int | None = None
        self._dt_mean = 0.05
        self._t_mono_last = 0
        self._w_last = (0.0, 0.0, 0.0)  # last bias-corrected rate, body
        self._gyro_raw = (0.0, 0.0, 0.0)  # last raw rate, body
        self._raw: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.0, 0.0, -earth.G0),
                                                                                    (0.0, 0.0, 0.0))
        self._f_last = (0.0, 0.0, 0.0)
        self._cov_dt = 0.0
        self._cov_interval_s = p.cov_interval_s
        self._next_idle_check_ns = 0
        self._inflations_seen = 0
        self._block: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float | None] | None = None  # imu_batch
        self._block_done = 0  # samples of _block whose bookkeeping is done
        # The live navigator's tap: the first step that ends at or after tap_ns hands its solution to tap, which
        # publishes it and says when it wants the next one. A run of FIFO reads then goes in whole rather than
        # cut at each publishing time (each cut a block's numpy calls again).
        self.tap: Callable[[Solution], int] | None = None
        self.tap_ns = NEVER

    # ---- IMU ---------------------------------------------------------------------------------------------
    def imu(self, t_ns: int, t_mono_ns: int, acc: tuple[float, float, float], gyro: tuple[float, float, float],
            temp_degc: float | None = None) -> None:
        """One IMU sample: specific force (m/s^2) and rate (rad/s) on the chip's axes, and its die temperature."""
        if temp_degc is not None:
            self.thermal.add(t_ns, float(temp_degc))
        if self._gnss_only:
            return
        al = self.alignment
        if al is not None:
            al.sample(t_ns, acc, gyro)
        mt = self._mount
        if mt is not None:
            (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = mt  # unpacked: 36 indexings fewer
            a0, a1, a2 = acc
            g0, g1, g2 = gyro
            acc = (m00 * a0 + m01 * a1 + m02 * a2, m10 * a0 + m11 * a1 + m12 * a2, m20 * a0 + m21 * a1 + m22 * a2)
            gyro = (m00 * g0 + m01 * g1 + m02 * g2, m10 * g0 + m11 * g1 + m12 * g2, m20 * g0 + m21 * g1 + m22 * g2)
        c = self.counters
        t_last = self._t_last
        if t_last is not None and t_ns <= t_last:
            c.imu_out_of_order += 1
            return
        c.imu += 1
        self._raw = (acc, gyro)
        self.stops.add(t_ns, acc, gyro)
        dt = 0.0 if t_last is None else (t_ns - t_last) / NS
        if self.imu_noise is not None:
            self.imu_noise.add(acc, gyro, dt)
        mech = self.mech
        if 0.0 < dt < IMU_GAP_S:
            # Coning and sculling corrections pay off once the IMU runs fast (100 Hz and up, FIFO reads): they
            # need consecutive increments of one sampling clock, which a slow polled IMU does not give.
            self._dt_mean += 0.02 * (dt - self._dt_mean)
            mech.coning = self._dt_mean < CONING_MAX_DT_S
        else:
            if dt > IMU_GAP_S:
                c.imu_gaps += 1
            if dt > MAX_IMU_GAP_S:
                mech.reset()
        self._t_last = t_ns
        self._t_mono_last = t_mono_ns
        s = self.state
        if s is None:
            self._pre_init(t_ns, acc, gyro, dt)
            return
        (bax, bay, baz), (bgx, bgy, bgz) = s.ba, s.bg
        ax, ay, az = acc
        gx, gy, gz = gyro
        f = (ax - bax, ay - bay, az - baz)
        w = (gx - bgx, gy - bgy, gz - bgz)
        self._f_last, self._w_last, self._gyro_raw = f, w, gyro
        if dt <= MAX_IMU_GAP_S:
            # A late sample (a loaded host, a slow bus) still closes its interval: the vehicle moved meanwhile.
            mech.step(s, w, f, dt)
        else:
            s.lat, s.lon, s.h = earth.offset_llh(s.lat, s.lon, s.h, s.vn * dt, s.ve * dt, s.vd * dt)
            mech.prime(w, f)
            fn, acc_ = mech.f_ned, mech.dv_ned_sum  # the interval counts at the last specific force
            acc_[0] += fn[0] * dt
            acc_[1] += fn[1] * dt
            acc_[2] += fn[2] * dt
        self._after_step(t_ns, t_mono_ns, s, gyro, dt)

    def imu_batch(self, t_ns: np.ndarray | list[int], t_mono_ns: np.ndarray | list[int], acc: np.ndarray,
                  gyro: np.ndarray, temp_degc: float | np.ndarray | None = None) -> None:
        """Consecutive IMU samples at once: a FIFO read, or a run of ``/imu`` records with nothing between them.

        ``t_ns`` and ``t_mono_ns``: each sample's synchronised and board times (n); ``acc`` and ``gyro``: n x 3
        specific force (m/s^2) and rate (rad/s) on the chip's axes; ``temp_degc``: the die temperature read with
        them (one per read), or None; or one per sample (n, NaN where none was read) when the block is several
        reads, each with its own. The result is what :meth:`imu` gives fed the samples one by one with their
        temperatures (to round-off): every sample is integrated at its own time, gets its row and its place in
        the late-fix history, and the covariance is propagated after the same samples. A fast IMU's samples (from
        ``integration_hz`` x 1.5) are integrated in steps of several instead (:meth:`_decimated_segment`): a row
        and a history entry per step, the same state at the steps' ends to the second order the steps leave out
        (8 um on a synthetic 1 kHz drive, 0.9 mm at most on a 200 s recording of the simulated daemon), the
        covariance still after the same samples. What is per-sample
        bookkeeping rather than integration (the mounting's rotation, the offsets, the stop detector's window, the
        noise monitor, the mount alignment's sums, the die temperature) is done for the whole block with numpy.
        Measurements between samples are not part of a batch: call this for the samples before a measurement,
        then the measurement, then the rest. Short blocks and blocks with a gap or a sample out of order go sample
        by sample; before the filter has started, blocks from ``PRE_INIT_BATCH_MIN`` go through the start-up's
        block form (:meth:`_pre_init_block`)."""
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        n = len(t)
        if n == 0:
            return
        acc = np.asarray(acc, dtype=float).reshape(n, 3)
        gyro = np.asarray(gyro, dtype=float).reshape(n, 3)
        mono = np.asarray(t_mono_ns, dtype=np.int64).reshape(n)
        if temp_degc is not None and np.ndim(temp_degc):
            temp_degc = np.asarray(temp_degc, dtype=float).reshape(n)  # one per sample: the reads' own
        t_last = self._t_last
        starting = self.state is None and not self._gnss_only
        least = PRE_INIT_BATCH_MIN if starting else BATCH_MIN if self._group_size() == 1 else DECIMATED_BATCH_MIN
        if n < least or t_last is None or (self.state is None and not starting):
            self._imu_each(t, mono, acc, gyro, temp_degc)
            return
        d = diff_from(t_last, t)
        if not bool(((d > 0) & (d < int(IMU_GAP_S * NS))).all()):  # out of order, or a gap
            self._imu_each(t, mono, acc, gyro, temp_degc)
            return
        dts = d / NS
        if starting:
            taken = self._pre_init_block(t, mono, acc, gyro, dts, temp_degc)
            if taken < n:  # the filter started at a sample of the block: the rest goes to it
                self.imu_batch(t[taken:], mono[taken:], acc[taken:], gyro[taken:],
                               temp_degc[taken:] if isinstance(temp_degc, np.ndarray) else temp_degc)
            return
        if self.alignment is not None:
            self.alignment.sample_block(t, acc, gyro)
        chip_acc, chip_gyro, mount = acc, gyro, self._mount_m
        if self._mount is not None:
            acc, gyro = acc @ mount.T, gyro @ mount.T
        self.counters.imu += n
        self._block = (t, acc, gyro, dts, temp_degc)  # the bookkeeping owed, done by _catch_up
        self._block_done = 0
        s = self.state
        mech, hist, record, rows = self.mech, self.history.entries, self.record, self.rows
        times, monos, dtl = t.tolist(), mono.tolist(), dts.tolist()
        interval = self._cov_interval_s
        i = 0
        while i < n:
            # A segment: the samples up to the next one that closes something besides its integration (the
            # covariance's interval, the idle check, a solution's epoch); nothing changes the offsets inside it.
            event_ns = self._event_ns()
            group = self._group_size()
            if group > 1 and mech.ready:
                last, due, cov_dt = self._decimated_segment(i, group, event_ns, t, acc, gyro, dts, times, monos)
            else:
                ba, bg = s.ba, s.bg
                f_rows = (acc[i:] - ba).tolist()
                w_rows = (gyro[i:] - bg).tolist()
                corr, sigma, epoch = self.history.corr, self.sigma, len(self.epochs) - 1
                cov_dt, dt_mean, tap_ns = self._cov_dt, self._dt_mean, self.tap_ns
                j = i
                due = False
                for f_, w_ in zip(f_rows, w_rows, strict=False):
                    dt = dtl[j]
                    dt_mean += 0.02 * (dt - dt_mean)
                    mech.coning = dt_mean < CONING_MAX_DT_S
                    mech.step(s, (w_[0], w_[1], w_[2]), (f_[0], f_[1], f_[2]), dt)
                    cov_dt += dt
                    t_j = times[j]
                    if cov_dt >= interval or t_j >= event_ns:
                        due = True
                        break
                    hist.append((t_j, s.lat, s.lon, s.h, s.vn, s.ve, s.vd, s.q, corr))
                    if record:
                        rows.append(_new_row(TrajectoryRow, (t_j, monos[j], s.lat, s.lon, s.h, s.vn, s.ve, s.vd,
                                                             s.q, sigma, epoch)))
                    if t_j >= tap_ns:
                        tap_ns = self._tapped(t_j, monos[j], s)
                    j += 1
                self._dt_mean = dt_mean
                last = j if due else n - 1
                f_, w_ = f_rows[last - i], w_rows[last - i]
                self._f_last, self._w_last = (f_[0], f_[1], f_[2]), (w_[0], w_[1], w_[2])
            a_, g_ = acc[last].tolist(), gyro[last].tolist()
            self._gyro_raw = (g_[0], g_[1], g_[2])
            self._raw = ((a_[0], a_[1], a_[2]), self._gyro_raw)
            self._t_last, self._t_mono_last = times[last], monos[last]
            self._catch_up(last + 1)
            if not due:
                self._cov_dt = cov_dt
                break
            # The bookkeeping came up to the closing sample: the rest of it runs as for a single sample.
            self._cov_dt = cov_dt - dtl[last]
            self._after_step(times[last], monos[last], s, self._gyro_raw, dtl[last], gyro_sum=False)
            i = last + 1
            if self._mount_m is not mount:
                # The covariance step took a new mounting: the rest of the block is turned the new way, as the
                # samples one by one would be.
                mount = self._mount_m
                acc = np.concatenate((acc[:i], chip_acc[i:] @ mount.T))
                gyro = np.concatenate((gyro[:i], chip_gyro[i:] @ mount.T))
                self._block = (t, acc, gyro, dts, temp_degc)
        self._block = None

    def _pre_init_block(self, t: np.ndarray, mono: np.ndarray, acc: np.ndarray, gyro: np.ndarray, dts: np.ndarray,
                        temp_degc: float | np.ndarray | None) -> int:
        """A block of samples before the filter has started (increasing times after the last sample, ``dts``
        their intervals, none a gap), as :meth:`imu` takes them one by one (to round-off): the stop detector's word
        after each sample (:meth:`~logger.nav.stops.StopDetector.still_flags`) and the start-up's levelling and
        provisional attitude (:meth:`~logger.nav.startup.Startup.step_block`) at once, the bookkeeping in blocks.
        Sample by sample, a 1 kHz IMU waiting for its first fix cost 9 us a sample here, a second's reads at once
        1 us (while waiting, the navigator feeds a wake-up's reads as one block). Returns how
        many samples it took: all, or up to the one at which the configured heading started the filter."""
        chip_acc, chip_gyro = acc, gyro
        if self._mount is not None:
            acc, gyro = acc @ self._mount_m.T, gyro @ self._mount_m.T
        still = self.stops.still_flags(t, acc, gyro)
        if self._obd_moving():
            still[:] = False
        fix = self.last_readings.fix
        k = self.startup.step_block(t, acc, gyro, dts, still, fix)
        end = len(t) if k is None else k + 1
        if self.alignment is not None:
            self.alignment.sample_block(t[:end], chip_acc[:end], chip_gyro[:end])
        self.counters.imu += end
        a_, g_ = acc[end - 1].tolist(), gyro[end - 1].tolist()
        self._raw = ((a_[0], a_[1], a_[2]), (g_[0], g_[1], g_[2]))
        self._bookkeeping(t[:end], acc[:end], gyro[:end], dts[:end],
                          temp_degc[:end] if isinstance(temp_degc, np.ndarray) else temp_degc)
        self._mean_interval_over(dts[:end])
        self._t_last, self._t_mono_last = int(t[end - 1]), int(mono[end - 1])
        if k is not None and fix is not None:
            self._initialise(self._t_last, math.radians(self.params.initial_heading_deg), CONFIG_HEADING, fix,
                             CONFIG_HEADING_VAR)
        return end

    def _mean_interval_over(self, dts: np.ndarray) -> None:
        """The mean sample interval after these intervals, as :meth:`imu` keeps it sample by sample (an
        exponential mean, weight 0.02 a sample), and whether it is short enough for coning corrections."""
        k = 0.98 ** np.arange(len(dts) - 1, -1, -1)
        self._dt_mean = 0.98 ** len(dts) * self._dt_mean + 0.02 * float(k @ dts)
        self.mech.coning = self._dt_mean < CONING_MAX_DT_S

    def _bookkeeping(self, t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, dts: np.ndarray,
                     temp: float | np.ndarray | None) -> None:
        """A block's per-sample bookkeeping on the body axes, what :meth:`imu` does sample by sample besides the
        integration: the stop detector's window, the noise monitor, the die temperature."""
        self.stops.add_block(t, acc, gyro)
        if self.imu_noise is not None:
            self.imu_noise.add_block(acc, gyro, dts)
        self._thermal_block(t, temp)

    def _thermal_block(self, t: np.ndarray, temp: float | np.ndarray | None) -> None:
        """The die temperatures of a block's samples: one for the block, or one per sample (NaN where none was
        read: unequal to its neighbours, and ignored as :meth:`imu` ignores it)."""
        if isinstance(temp, np.ndarray):
            # One temperature per read of a run of reads: a block for each read's samples.
            lo = 0
            for hi in (*(np.flatnonzero(temp[1:] != temp[:-1]) + 1).tolist(), len(temp)):
                self.thermal.add_block(t[lo:hi], float(temp[lo]))
                lo = hi
        elif temp is not None:
            self.thermal.add_block(t, float(temp))

    def _group_size(self) -> int:
        """Samples per strapdown step in a block: one up to ``integration_hz``; above it as many as make a step of
        about 1 / ``integration_hz`` (a 1 kHz FIFO at the default 100 Hz: ten)."""
        hz = self.params.integration_hz
        if hz <= 0.0 or self._dt_mean <= 0.0:
            return 1
        return max(1, round(1.0 / (hz * self._dt_mean)))

    def _decimated_segment(self, i: int, group: int, event_ns: int, t: np.ndarray, acc: np.ndarray,
                           gyro: np.ndarray, dts: np.ndarray, times: list[int], monos: list[int]
                           ) -> tuple[int, bool, float]:
        """The block's samples from ``i`` up to the next one that closes something (as the per-sample segment),
        integrated ``group`` at a time (:func:`~logger.nav.strapdown.preintegrate`, coning and sculling within each
        step), with a history entry and a row per step; the closing sample ends a step of its own, whose history
        and row :meth:`_after_step` adds. Returns the segment's last sample, whether it closes something, and the
        covariance's interval so far including it."""
        s, mech = self.state, self.mech
        assert s is not None
        n = len(times)
        cov = np.cumsum(np.concatenate(((self._cov_dt,), dts[i:])))[1:]
        hit = np.flatnonzero((cov >= self._cov_interval_s) | (t[i:] >= event_ns))
        due = len(hit) > 0
        end = i + int(hit[0]) if due else n - 1
        m = end + 1 - i
        w = np.concatenate(((mech.last_rate,), gyro[i:end + 1] - np.asarray(s.bg)))
        f = np.concatenate(((mech.last_force,), acc[i:end + 1] - np.asarray(s.ba)))
        starts = np.arange(0, m, group)
        rot, dv, lengths = preintegrate(w, f, dts[i:end + 1], starts)
        self._mean_interval_over(dts[i:end + 1])
        hist, record, rows = self.history.entries, self.record, self.rows
        corr, sigma, epoch = self.history.corr, self.sigma, len(self.epochs) - 1
        step, tap_ns = mech.step_increments, self.tap_ns
        ends = (np.append(starts[1:], m) - 1 + i).tolist()  # each step's last sample, in the block
        for r, d, dt, j in zip(rot.tolist(), dv.tolist(), lengths.tolist(), ends, strict=True):
            step(s, r, d, dt)
            if due and j == end:
                break
            t_j = times[j]
            hist.append((t_j, s.lat, s.lon, s.h, s.vn, s.ve, s.vd, s.q, corr))
            if record:
                rows.append(_new_row(TrajectoryRow, (t_j, monos[j], s.lat, s.lon, s.h, s.vn, s.ve, s.vd, s.q,
                                                     sigma, epoch)))
            if t_j >= tap_ns:
                tap_ns = self._tapped(t_j, monos[j], s)
        wl, fl = w[-2:].tolist(), f[-2:].tolist()  # the last sample and the one before it (or before the segment)
        mech.continue_from(wl[1], fl[1], wl[0], fl[0], float(dts[end]))
        self._f_last, self._w_last = mech.last_force, mech.last_rate
        return end, due, float(cov[end - i])

    def _event_ns(self) -> int:
        """The first instant from which a sample closes something besides its integration and the covariance's
        interval: the idle check (17-state, no fresh OBD speed) or a solution's next epoch."""
        at = NEVER
        if self.mode == "17":
            obd = self.last_readings.obd
            at = max(self._next_idle_check_ns, obd[0] + OBD_FRESH_NS + 1 if obd is not None else 0)
        if self.solution is not None:
            at = min(at, self.solution.next_ns)
        return at

    def _imu_each(self, t: np.ndarray, mono: np.ndarray, acc: np.ndarray, gyro: np.ndarray,
                  temp_degc: float | np.ndarray | None) -> None:
        """A batch sample by sample, through :meth:`imu` (each with its temperature when there is one per sample)."""
        sample = self.imu
        temps = temp_degc.tolist() if isinstance(temp_degc, np.ndarray) else [temp_degc] * len(t)
        for t_i, m_i, a, g, c in zip(t.tolist(), mono.tolist(), acc.tolist(), gyro.tolist(), temps, strict=True):
            sample(t_i, m_i, (a[0], a[1], a[2]), (g[0], g[1], g[2]), c)

    def _catch_up(self, upto: int) -> None:
        """The per-sample bookkeeping of the current batch's samples before ``upto``, in blocks: the stop detector,
        the noise monitor, the die temperature, the gyro sum of a stop."""
        t, acc, gyro, dts, temp = self._block
        sl = slice(self._block_done, upto)
        self._block_done = upto
        self._bookkeeping(t[sl], acc[sl], gyro[sl], dts[sl], temp[sl] if isinstance(temp, np.ndarray) else temp)
        if self._stop.stopped:
            ws = self._stop.w_sum
            g = gyro[sl].sum(axis=0).tolist()
            ws[0] += g[0]
            ws[1] += g[1]
            ws[2] += g[2]
            ws[3] += len(t[sl])

    def _after_step(self, t_ns: int, t_mono_ns: int, s: NavState, gyro: tuple[float, float, float],
                    dt: float, gyro_sum: bool = True) -> None:
        """What follows each integrated sample: the stop's gyro sum (unless a batch did it), the idle check, the
        history, the row, and the covariance when its interval is up."""
        self._cov_dt += dt
        stop = self._stop
        if stop.stopped and gyro_sum:
            ws = stop.w_sum
            ws[0] += gyro[0]
            ws[1] += gyro[1]
            ws[2] += gyro[2]
            ws[3] += 1
        if t_ns >= self._next_idle_check_ns and self._full and not self.last_readings.obd_fresh(t_ns):
            # No speed from the vehicle (engine off, adapter gone): standing still is then told by a quiet IMU
            # and a solution that already stands, so a parked car does not drift on its IMU alone.
            self._next_idle_check_ns = t_ns + NHC_INTERVAL_NS
            stop.update(self, self.stops.still and math.sqrt(s.vn * s.vn + s.ve * s.ve + s.vd * s.vd) < STANDING_MPS,
                        t_ns)
        hist = self.history
        hist.entries.append((t_ns, s.lat, s.lon, s.h, s.vn, s.ve, s.vd, s.q, hist.corr))  # SolutionHistory.add
        if self.solution is not None and t_ns >= self.solution.next_ns:
            self._solution_due(t_ns)
        if self.record:
            self.rows.append(_new_row(TrajectoryRow, (t_ns, t_mono_ns, s.lat, s.lon, s.h, s.vn, s.ve, s.vd, s.q,
                                                      self.sigma, len(self.epochs) - 1)))
        if self._cov_dt >= self._cov_interval_s:
            self.propagate()
        if t_ns >= self.tap_ns:
            self._tapped(t_ns, t_mono_ns, s)

    def _tapped(self, t_ns: int, t_mono_ns: int, s: NavState) -> int:
        """The solution at the end of a step that reached ``tap_ns``, handed to ``tap``; the next such instant."""
        self.tap_ns = NEVER if self.tap is None else self.tap(self._solution(t_ns, t_mono_ns, s))
        return self.tap_ns

    def _pre_init(self, t_ns: int, acc: tuple[float, float, float], gyro: tuple[float, float, float],
                  dt: float) -> None:
        """Before the heading is known: the start-up levels while still, then carries the attitude on the gyro."""
        still = self.stops.still and not self._obd_moving()
        fix = self.last_readings.fix
        if self.startup.step(t_ns, acc, gyro, dt, still, fix) == CONFIG_HEADING and fix is not None:
            self._initialise(t_ns, math.radians(self.params.initial_heading_deg), CONFIG_HEADING, fix,
                             CONFIG_HEADING_VAR)

    def _obd_moving(self) -> bool:
        """Whether the last OBD speed says the car moves (the start-up levels only while it reads 0)."""
        obd = self.last_readings.obd
        return obd is not None and obd[1] != 0.0

    def _try_heading_init(self, fix: PreparedFix) -> None:
        if self._t_last is None:
            return  # no IMU sample yet: nothing to integrate (a course alone started a filter dated 0, "16 h old")
        if self.startup.late_config_heading():  # levelled before the first fix: the configured heading now
            self._initialise(self._t_last, None, CONFIG_HEADING, fix, CONFIG_HEADING_VAR)
            return
        heading = self.startup.heading_from_course(fix)
        if heading is not None:
            yaw, method, heading_var = heading
            self._initialise(self._t_last, yaw, method, fix, heading_var)

    def _initialise(self, t_ns: int, yaw_or_none: float | None, method: str, fix: PreparedFix,
                    heading_var: float) -> None:
        """Start the filter from what the start-up built: state, covariance, and the integration primed."""
        n = self.n
        fix = self.start_height.start_fix(fix)
        self.counters.init_height_fixes = self.start_height.used
        self.start_height.clear()
        s, p0 = self.startup.initial(t_ns, yaw_or_none, method, fix, heading_var, n, self.lever,
                                     self.last_readings.baro)
        self.startup.started()
        self.state = s
        self.ekf = ErrorStateEkf(np.ones(n), self.params.gate_probability)
        self.ekf.p = p0
        self._inflations_seen = 0
        self.thermal.restart()
        self._restart_tempco()
        self.sigma = tuple(math.sqrt(p0[P_ID + i, P_ID + i]) for i in range(3))
        self.mech.reset()
        acc, gyro = self._raw  # the latest sample starts the integration, corrected as the state now says
        bg = s.bg
        self.mech.prime((gyro[0] - bg[0], gyro[1] - bg[1], gyro[2] - bg[2]), acc)
        self.history.clear()
        self.counters.initialised_ns = t_ns
        self.counters.init_method = method
        if self.record:
            self.epochs.append(Epoch(t_ns, None, p0.copy(), dx=np.zeros(n)))

    # ---- covariance ------------------------------------------------------------------------------------
    def propagate(self, new_rounding: bool = False) -> None:
        """Bring the covariance to the last IMU sample (an epoch for the smoother when recording); with
        ``new_rounding`` the OBD reading's rounding starts again at its end (:meth:`_new_rounding_run`)."""
        dt = self._cov_dt
        if (dt <= 0.0 and not new_rounding) or self.ekf is None or self.state is None:
            return
        s = self.state
        if dt > 0.0:
            fa = self.mech.dv_ned_sum  # the specific force's velocity increments in NED since the last propagation
            f_mean = (fa[0] / dt, fa[1] / dt, fa[2] / dt)
            phi = transition(error_dynamics(s, dcm_elements(s.q), f_mean, self.n), dt)
        else:  # no sample since the last step: a step of zero length, for the rounding's sake
            phi = np.eye(self.n)
        half_q = self.q_diag * (0.5 * dt)
        if new_rounding:
            phi[RQ_ID, :] = 0.0  # the new rounding owes nothing to the old one or to anything else
            half_q[RQ_ID] = ROUNDING_VAR  # P = phi (P + Q/2) phi^T + Q/2: the new variance, no correlation
        if self.record:
            self._close_epoch()
        self.ekf.propagate_trapezoid(phi, half_q)
        owed = self.thermal.take()
        if owed > 0.0:
            # The offsets follow the die temperature through a fixed coefficient, known as far as the drive showed
            # it (thermal.py).
            pk = self.ekf.p
            kv = self.tempco.residual_var()
            for i in range(3):
                pk[BA_ID + i, BA_ID + i] += kv[i] * owed
                pk[BG_ID + i, BG_ID + i] += kv[3 + i] * owed
        if self.record:
            self.epochs.append(Epoch(self._t_last or 0, phi.astype(np.float32), self.ekf.p.copy(), dx=np.zeros(self.n)))
        self._cov_dt = 0.0
        self.mech.dv_ned_sum = [0.0, 0.0, 0.0]
        self.refresh_sigma()
        if self._t_last is not None:
            self.history.trim(self._t_last)
        if new_rounding:
            return  # a step for the rounding's sake: what follows the covariance's own steps waits for the next one
        self._follow_temperature()
        if self.alignment is not None:
            self._follow_alignment()
        if self.imu_noise is not None:
            self._follow_imu_noise()

    def _restart_tempco(self) -> None:
        """New offsets or new axes: the coefficients are learnt again, from the configured bounds or from what an
        earlier drive learnt of this part (:meth:`start_tempco_from`), turned onto the body axes in use."""
        self.tempco.restart()
        if self._tempco_saved is not None:
            self.tempco.set_prior(*turned(self._mount_m, *self._tempco_saved))
        self._tempco_at = self.thermal.smoothed
        self._tempco_moved = (0.0, 0.0, 0.0)

    def start_tempco_from(self, k_chip: list[float], sigma_chip: list[float]) -> None:
        """Coefficients (accelerometer x y z in m/s^2/degC, gyro x y z in rad/s/degC, the chip's axes) and their
        sigmas that an earlier drive learnt of this part: the learner's prior from now on."""
        self._tempco_saved = (list(k_chip), list(sigma_chip))
        self._restart_tempco()

    def learnt_tempco(self) -> tuple[list[float], list[float]]:
        """The coefficients as learnt so far and their sigmas, on the chip's axes (what :meth:`start_tempco_from`
        takes at the next start, whatever the mounting then)."""
        return turned(self._mount_m.T, *self.tempco.proven())

    def _follow_temperature(self) -> None:
        """The offsets against the die temperature (thermal.py): the estimates go to the learner while fixes go
        in; a coefficient it proves moves the offsets with the temperature since the last propagation, and what
        it leaves unknown is what the covariance covers from here on."""
        s, ekf = self.state, self.ekf
        temp = self.thermal.smoothed
        if s is None or ekf is None or temp - temp != 0.0:
            return
        t = self._t_last or 0
        if t / NS >= self.tempco.due_s and 0 < t - self.last_readings.pos_ok[0] < 3 * NS:  # a sample due, aided
            wa, wg = self._grade_walk
            nz = self.noise
            self.tempco.add(t / NS, temp, (*s.ba, *s.bg), ekf.p.diagonal()[BA_ID:BG_ID + 3].tolist(),
                            (wa * wa,) * 3 + (wg * wg,) * 3, True,
                            (nz.accel_bias_walk**2,) * 3 + (nz.gyro_bias_walk**2,) * 3)
        k = self.tempco.applied()
        d = temp - self._tempco_at
        if d - d == 0.0 and d != 0.0 and any(k):
            ba, bg, m = s.ba, s.bg, self._tempco_moved
            s.ba = (ba[0] + k[0] * d, ba[1] + k[1] * d, ba[2] + k[2] * d)
            s.bg = (bg[0] + k[3] * d, bg[1] + k[4] * d, bg[2] + k[5] * d)
            self._tempco_moved = (m[0] + k[3] * d, m[1] + k[4] * d, m[2] + k[5] * d)
        self._tempco_at = temp

    def _follow_imu_noise(self) -> None:
        """Process noise from what the drive shows, never below the configured densities (imu_noise.py)."""
        assert self.imu_noise is not None
        measured = self.imu_noise.densities()
        if measured is None:
            return
        p = self.params
        s = self.state
        t = self._t_last or 0
        aided = 0 < t - self.last_readings.pos_ok[0] < 3 * NS
        if self.offset_wander is not None and s is not None:
            # What the temperature moved is the learner's (_follow_temperature), not a wander.
            m = self._tempco_moved
            self.offset_wander.add(t / NS, (s.bg[0] - m[0], s.bg[1] - m[1], s.bg[2] - m[2]), aided)
        vrw, arw = max(p.accel_vrw, measured[0]), max(p.gyro_arw, measured[1])
        # A chip noisier than its datasheet by some factor wanders by as much more too: consumer MEMS grades scale
        # noise and bias instability together (an MPU-6050 against a phone's IMU: about 10x both); and what the
        # filter's own offset estimate shows of the wander (OffsetWander) widens the gyro's walk further.
        ratio = arw / p.gyro_arw
        gyro_walk = p.gyro_bias_walk * ratio
        self._grade_walk = (p.accel_bias_walk * vrw / p.accel_vrw, gyro_walk)
        wander = self.offset_wander.walk() if self.offset_wander is not None else None
        if wander is not None:
            gyro_walk = max(gyro_walk, wander)
        elif ratio > CONSUMER_NOISE_RATIO:
            # Not the datasheet's grade at all, and its wander not yet read (OffsetWander wants a few minutes of
            # aided driving): until then the pessimistic side of consumer parts, ratio^2, so that the covariance
            # stays what the filter can stand behind. An earlier simulated phone (6.6x the noise, its offset
            # wandering 0.3 deg/s over 200 s, beyond any phone's data sheet) took the ratio alone, 0.0033
            # deg/s/sqrt(s), into a tunnel 85 s in and came out 402 m off with 73 % of the drive inside 3 sigma;
            # with ratio^2, 261 m and 100 %. The price, on a chip as noisy whose offset does not wander
            # (synthetic): a minute's outage 3.7 m off instead of 1.1 m. Taken only while no fixes came, that
            # phone's tunnel stayed 432 m off and 80 % inside 3 sigma.
            gyro_walk *= ratio
        if (abs(vrw / self.noise.accel_vrw - 1.0) > 0.1 or abs(arw / self.noise.gyro_arw - 1.0) > 0.1
                or abs(gyro_walk / self.noise.gyro_bias_walk - 1.0) > 0.1):
            self.noise = ProcessNoise(vrw, arw, p.accel_bias_walk * vrw / p.accel_vrw, gyro_walk,
                                      p.obd_scale_walk_rts, p.baro_offset_walk_m_rts, p.obd_rounding_walk_mps_rts)
            self.q_diag = self.noise.diagonal(self.n)

    # ---- the mounting ----------------------------------------------------------------------------------
    @property
    def vehicle_from_chip(self) -> np.ndarray:
        """The mounting in use: the rotation that turns the chip's axes into the vehicle's (the filter's body)."""
        return self._mount_m

    def _set_mount(self, m: np.ndarray) -> None:
        self._mount_m = m
        self._mount = None if np.allclose(m, np.eye(3)) else tuple(tuple(float(v) for v in row) for row in m)

    def _follow_alignment(self) -> None:
        """Give the alignment the offsets on the chip's axes, and take its estimate once it has settled."""
        al, s = self.alignment, self.state
        assert al is not None and s is not None
        al.offsets(self._mount_m, s.bg)
        t = self._t_last or 0
        if t < self._next_remount_ns:
            return
        self._next_remount_ns = t + REMOUNT_INTERVAL_NS
        est = al.estimate()
        if est.state != SETTLED:
            # Before it settles, the car's forward axis is taken as soon as it is shown (pitch and yaw within
            # USABLE_SIGMA_DEG) and three sigmas from the one in use: that axis is what the OBD speed and the
            # non-holonomic rows hold the body on, and a board turned 30 deg would otherwise be driven unaligned for
            # the minutes the roll takes to show (the whole drive, on roads without turns). The roll stays near the
            # guess until the estimate settles. On the synthetic outage drive with the board at (5, -4, 30) deg it
            # is taken 36 s in; waiting for 3 deg took it 30 s later, and the minute without GNSS after it ended
            # 3.0 m off instead of 1.1 m.
            if math.isfinite(est.sigma_deg[1]) and forward_axis_turned(self.mount_applied, est):
                self.remount(est, reopen=True)
            return
        d = mount_matrix(est.rpy_deg) @ self._mount_m.T  # new body from old body
        angle = math.degrees(float(np.linalg.norm(rotvec_from_dcm(d))))
        # Only a change the estimate is sure of: following its noise would turn the samples every ten seconds.
        if angle >= max(REMOUNT_MIN_DEG, 2.0 * max(est.sigma_deg)):
            self.remount(est, reopen=angle >= REOPEN_DEG)

    def remount(self, est: MountEstimate, reopen: bool = True) -> None:
        """Take a new mounting: the samples are turned the new way from now on.

        The filter's attitude keeps its forward axis: it is the vehicle's, since the GNSS course, the OBD speed and
        the non-holonomic rows pulled the body's forward axis onto the vehicle's while the samples came in turned
        the wrong way (that is where the mounting's error went: into the attitude the filter held of the chip, and
        into its offsets). Keeping the chip's attitude instead turned the body 30 deg off the road on a board
        mounted at 30 deg, and the filter refused its fixes for half a minute. About the forward axis the rows
        hold nothing (the car's lateral and vertical velocities are both nought, turned about it or not): there
        the body took the turn the old mounting left, as gravity showed it, so the change's twist about the forward
        axis turns the attitude (a phone in a holder, whose forward axis came first and the 70 deg turn about it
        minutes later, was 33 m off within two seconds with the attitude kept). The offsets, fitted through the wrong
        mounting, are reopened, as after a restart. A small change (``reopen`` False: under REOPEN_DEG) is a
        refinement: the offsets turn with the axes and nothing is reopened (reopening a phone-grade IMU's offsets
        for every half-degree refinement cost it eight restarts in ten minutes)."""
        assert self.state is not None and self.ekf is not None
        m_new = mount_matrix(est.rpy_deg)
        d = m_new @ self._mount_m.T  # new body from old body
        s = self.state
        s.q = quat_from_dcm(s.dcm() @ twist_about_x(d).T)
        # The gyro's offset came from standstills, where the mounting does not matter: it turns with the axes.
        # After a large change the accelerometer's, which took up the mounting's tilt, starts again from zero.
        s.bg = tuple(float(v) for v in d @ np.array(s.bg))
        s.ba = (0.0, 0.0, 0.0) if reopen else tuple(float(v) for v in d @ np.array(s.ba))
        self._set_mount(m_new)
        self.mount_applied = est.rpy_deg
        self._w_last = tuple(float(v) for v in d @ np.array(self._w_last))
        self._f_last = tuple(float(v) for v in d @ np.array(self._f_last))
        self.mech.prime(self._w_last, self._f_last)
        self._obd.mount_yaw_stat = [0.0, 0.0]
        if self.offset_wander is not None:
            self.offset_wander.restart()
        self.counters.remounts += 1
        if not reopen:
            self.tempco.turn(d)
            self._tempco_moved = tuple(float(v) for v in d @ np.array(self._tempco_moved))
            t = np.eye(self.n)
            t[BA_ID:BA_ID + 3, BA_ID:BA_ID + 3] = d
            t[BG_ID:BG_ID + 3, BG_ID:BG_ID + 3] = d
            self.ekf.p = t @ self.ekf.p @ t.T
            return
        if self.mount_reopened_ns is None:
            self.mount_reopened_ns = self._t_last or 0
        self.reopen_attitude_and_offsets()
        self._restart_tempco()  # after the variance owed to the temperature so far went into the reopening
        if self.n > DH_ID:
            # The barometer's offset was learnt against heights the wrong mounting bent (the non-holonomic rows
            # held a body pitched on the car): it is learnt again.
            old = float(self.ekf.p[DH_ID, DH_ID])
            self.ekf.inflate(slice(DH_ID, DH_ID + 1), np.array([max(old, height_offset_variance(self.params))]))
        self.velocity_evidence.clear()

    def refresh_sigma(self) -> None:
        p = self.ekf.p if self.ekf is not None else None
        if p is not None:
            self.sigma = (math.sqrt(max(p[0, 0], 0.0)), math.sqrt(max(p[1, 1], 0.0)), math.sqrt(max(p[2, 2], 0.0)))

    def apply(self, obs: Observation, gated: bool = True) -> bool:
        """Bring the covariance to now, update, and feed the estimate back into the nominal state."""
        if self.ekf is None or self.state is None:
            return False
        if self._cov_dt >= UPDATE_STALE_S:
            self.propagate()  # a covariance a few IMU samples old serves the update as well, and costs nothing
        dx = self.ekf.update(obs, gated)
        if dx is None:
            return False
        self.feedback(dx)
        return True

    def feedback(self, dx: np.ndarray) -> None:
        """Feed an error estimate back into the nominal state, the late-fix history and the smoother's epoch."""
        assert self.state is not None
        self.state.correct(dx)
        self.history.fed_back(dx[:6].tolist())
        if self.record and self.epochs:
            ep = self.epochs[-1]
            ep.dx = dx if ep.dx is None else ep.dx + dx
            if self.rows and self.rows[-1].epoch == len(self.epochs) - 1:
                ep.late.append((len(self.rows), dx))
        self.refresh_sigma()

    def state_at(self, t_ns: int) -> NavState:
        """The solution at a past instant (for a measurement that arrives late), corrected since."""
        assert self.state is not None
        return self.history.state_at(t_ns, self.state)

    def reopen_attitude_and_offsets(self) -> None:
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
        pphi, _, pba = tilt_bias_covariance(self.state.dcm(), self.startup.accel_bias_var, earth.G0)
        end_ns, span_s = self.startup.level_span
        since_s = ((self._t_last or 0) - end_ns) / NS
        bg_var = (gyro_calibration_variance(p.gyro_arw, p.gyro_bias_walk, span_s, since_s) if span_s > 0.0
                  else p.gyro_bias_sigma**2)
        ekf.inflate(slice(PHI_ID, BG_ID + 3), np.zeros(9))
        att = np.diag((math.radians(0.3) ** 2, math.radians(0.3) ** 2, math.radians(5.0) ** 2))
        ekf.p[PHI_ID:PHI_ID + 3, PHI_ID:PHI_ID + 3] = pphi + att
        ekf.p[BA_ID:BA_ID + 3, BA_ID:BA_ID + 3] = pba  # uncorrelated with the tilt: their sum was just shown off
        bg_var += max(self.tempco.residual_var()[3:]) * self.thermal.range_degc**2
        for i in range(3):
            ekf.p[BG_ID + i, BG_ID + i] = max(bg_var, float(old[BG_ID + i]))
            ekf.p[PHI_ID + i, PHI_ID + i] = max(float(ekf.p[PHI_ID + i, PHI_ID + i]), float(old[PHI_ID + i]))

    # ---- the sensors ---------------------------------------------------------------------------------------
    def pps(self, t_ns: int) -> None:
        """A PPS edge at its synchronised time: places fix epochs on the logger's clock while it is not locked."""
        self.epoch_clock.pps(t_ns)

    def use_solution(self, epochs: Iterable[SolutionEpoch], replace: bool = True) -> None:
        """Fuse a post-processed solution (PPK, :mod:`logger.nav.solution`): each epoch goes in once the IMU reaches
        it, placed on the logger's clock as the receiver's fixes are. ``replace``: the receiver's positions are
        left out (its velocities still go in: a ``.pos`` has none); otherwise both go in."""
        self.solution = SolutionPolicy(epochs, replace, self.last_readings, self.position_evidence)

    def gnss(self, msg: GnssObservation) -> None:
        """One navigation solution of the receiver."""
        fix = self._gnss.prepare(msg, self.counters)
        if fix is None:
            return
        sol = self.solution
        if sol is not None and msg.gnss_time_ns is not None and self.mode != "gnss":
            sol.map(msg.gnss_time_ns, fix.t_ns, fix.t_mono_ns, fix.lat, fix.lon, msg.leap_unknown)
        self.last_readings.fix = fix
        v = fix.vel
        # The fixes' speed holds stops too: a car without an OBD adapter, or this filter without its speed (the
        # GNSS + IMU mode).
        self._held_reading(self._fix_held, fix.t_ns, v is not None and self.mode != "gnss"
                           and v[0] * v[0] + v[1] * v[1] < GNSS_STANDING_MPS**2)
        if self.alignment is not None and v is not None and self.state is not None:
            self.alignment.fix(fix.t_ns, (float(v[0]), float(v[1]), float(v[2]) if fix.vel_3d else self.state.vd))
        if self.mode == "gnss":
            self._gnss_row(fix)
            return
        if self.state is None:
            self.start_height.fix(fix)
            self._try_heading_init(fix)
            return
        positions = sol is None or not sol.replace
        if self._gnss.update(self, fix, msg.num_sv, np.array(self._gyro_raw), positions) == "reset":
            self._restart_from(fix)

    def _solution_due(self, t_ns: int) -> None:
        """The solution's epochs the IMU has reached: their updates, at their epochs."""
        sol = self.solution
        assert sol is not None
        for ep, t_e, t_mono in sol.due(t_ns, self.counters.initialised_ns or 0):
            verdict, placed = sol.update(self, ep, t_e, t_mono)
            if verdict == "reset" and placed is not None:
                self._restart_from(placed)

    def _restart_from(self, fix: PreparedFix) -> None:
        """The filter lost itself: position and velocity from the fix, attitude and offsets reopened."""
        assert self.ekf is not None and self.state is not None
        s = self.state
        snap = self.state_at(fix.t_ns)
        dn, de, dd = earth.ned_offset_m(fix.lat, fix.lon, fix.h, snap.lat, snap.lon, snap.h)
        var_d = fix.sigma[2] ** 2
        if not fix.fix_3d and float(self.ekf.p[P_ID + 2, P_ID + 2]) < var_d:
            # A 2D fix's height is a stand-in (GnssPolicy.prepare): the filter's own, which the barometer held, is
            # kept where it claims better than the stand-in's sigma.
            dd, var_d = 0.0, float(self.ekf.p[P_ID + 2, P_ID + 2])
        dx = np.zeros(self.n)
        dx[P_ID:P_ID + 3] = (dn, de, dd)
        if fix.vel is not None:
            dx[V_ID:V_ID + 3] = (s.vn - fix.vel[0], s.ve - fix.vel[1], s.vd - fix.vel[2] if fix.vel_3d else 0.0)
        self.feedback(dx)
        self.ekf.inflate(slice(P_ID, V_ID + 3), [fix.sigma[0] ** 2, fix.sigma[1] ** 2, var_d,
                                                  fix.s_vel**2 + 0.1, fix.s_vel**2 + 0.1, fix.s_vel**2 + 0.1])
        self.reopen_attitude_and_offsets()
        self._restart_tempco()  # the offsets it estimated while losing itself teach nothing of the temperature
        if self.offset_wander is not None:
            self.offset_wander.restart()  # nor of the wander (what the learner had moved is no longer counted)
        self.counters.resets += 1
        # Refusals judged against the lost solution say nothing of the new one.
        self.position_evidence.run.clear()
        self.height_evidence.run.clear()
        self.velocity_evidence.clear()
        self.refresh_sigma()

    def _gnss_row(self, fix: PreparedFix) -> None:
        v = fix.vel if fix.vel is not None else np.zeros(3)
        yaw = math.atan2(v[1], v[0])
        self.solution = Solution(fix.t_ns, fix.t_mono_ns, fix.lat, fix.lon, fix.h, (float(v[0]), float(v[1]),
                                 float(v[2])), (0.0, 0.0, yaw), fix.sigma, "gnss")
        if self.record:
            self.rows.append(TrajectoryRow(fix.t_ns, fix.t_mono_ns, fix.lat, fix.lon, fix.h, float(v[0]), float(v[1]),
                                           float(v[2]), quat_from_euler(0.0, 0.0, yaw), fix.sigma, -1))

    def obd(self, t_ns: int, speed_mps: float) -> None:
        """A vehicle speed from the OBD-II port, m/s, at the instant the ECU was asked."""
        if self.mode != "17":  # the baseline and GNSS-only modes know nothing of the vehicle's speed sensor
            return
        self.counters.obd += 1
        new_run = self._obd.note(t_ns, speed_mps)
        self._held_reading(self._obd_held, t_ns, speed_mps == 0.0)
        if self.state is None:
            return
        if new_run and self.n > RQ_ID:
            self._new_rounding_run()
        self._obd.update(self, t_ns, speed_mps, self._t_last or 0)

    def _held_reading(self, held: HeldStop, t_ns: int, says_standing: bool) -> None:
        """A reading of the OBD speed or a fix, which ``says_standing`` or not: a stop it holds while the IMU never
        read still teaches the stop detector a noisier part's standstill (before the start too, so that it
        levels), if the solution agrees the car stands and the chip measures that noisy (:meth:`_noisy_chip`)."""
        if not says_standing:
            held.end()
        elif held.holds(t_ns, self.stops.still) and self._standing() and self._noisy_chip():
            self.stops.learn(held=True)

    def _standing(self) -> bool:
        """Whether the solution, or before the start the last fix's velocity, agrees that the car stands (no word:
        yes): an adapter that reads zero while the car drives teaches no threshold."""
        s = self.state
        if s is not None:
            return s.vn * s.vn + s.ve * s.ve + s.vd * s.vd < STANDING_MPS**2
        fix = self.last_readings.fix
        return fix is None or fix.vel is None or math.hypot(float(fix.vel[0]), float(fix.vel[1])) < STANDING_MPS

    def imu_noise_ratio(self) -> list[float] | None:
        """The IMU's white noise as measured (imu_noise.py) over the configured densities, accelerometer and gyro;
        None before it is measured or without the monitor."""
        d = self.imu_noise.densities() if self.imu_noise is not None else None
        if d is None:
            return None
        return [d[0] / self.params.accel_vrw, d[1] / self.params.gyro_arw]

    def _noisy_chip(self) -> bool:
        """Whether the IMU measures CONSUMER_NOISE_RATIO times noisier than its configured densities or more
        (imu_noise.consumer_grade: white noise, which a car shaken by people getting in or out does not add): a
        part whose standstill the configured thresholds cannot tell, which a held stop may teach. A datasheet-grade
        chip waits for a stop it reads still in, as before. Without the monitor (``imu_noise_from_drive`` off): yes."""
        if self.imu_noise is None:
            return True
        ratio = self.imu_noise_ratio()
        return ratio is not None and consumer_grade(ratio)

    def _new_rounding_run(self) -> None:
        """A reading unlike the last one: its rounding is a new unknown, independent of the last run's. The
        covariance is brought to now with a transition that forgets the state (its row zero, its variance the
        rounding's): the smoother's epoch then says the same."""
        assert self.state is not None
        self.state.rq = 0.0
        self.propagate(new_rounding=True)

    def baro(self, t_ns: int, altitude_m: float) -> None:
        """A barometric (pressure) altitude, m."""
        if self.mode != "17":
            return
        self.counters.baro += 1
        self.last_readings.baro = (t_ns, altitude_m)
        if self.state is None:
            self.start_height.baro(t_ns, altitude_m)
            return
        self._baro.update(self, t_ns, altitude_m)

    # ---- output ------------------------------------------------------------------------------------------
    @property
    def t_last_ns(self) -> int | None:
        """Synchronised time of the last IMU sample integrated, None before the first."""
        return self._t_last

    @property
    def stopped(self) -> bool:
        """The vehicle stands (zero-motion updates running)."""
        return self._stop.stopped

    @property
    def mount_yaw_stat(self) -> list[float]:
        """Sum of lateral/forward OBD velocity ratios and their count: a mounting turned about the vertical."""
        return self._obd.mount_yaw_stat

    def waiting_for(self) -> str:
        """What the start waits for, in words an operator can act on; "" once there is a solution.

        The same sentence for ``logger status``, the end of a run and ``logger replay``, so an empty trajectory
        always comes with its reason."""
        c, su, fix, p = self.counters, self.startup, self.last_readings.fix, self.params
        no_fix = ("no GNSS fix yet" if c.gnss_no_fix == 0 else
                  f"no GNSS fix yet ({c.gnss_no_fix} epochs without one)")
        if self.mode == "gnss":
            return "" if self.solution is not None else (
                "waiting for a GNSS fix" + (f" ({c.gnss_no_fix} epochs without one)" if c.gnss_no_fix else ""))
        if self.state is not None:
            return ""
        if c.imu == 0:
            return "waiting for the IMU: no sample yet"
        if su.prov_q is None:
            if su.align.n:
                return (f"levelling the IMU ({su.align.duration_s:.0f} s standing); waiting for the car to move "
                        "to find the heading")
            return ("waiting for the car to stand still to level the IMU (or to drive at "
                    f"{p.heading_min_speed_mps:g} m/s or more to start from the GNSS course without levelling)")
        if fix is None:
            return f"levelled; waiting for a GNSS fix to find the heading: {no_fix}"
        if p.heading_source == "config":
            return "levelled; starting at the configured heading with the next GNSS fix"
        if fix.vel is None or not fix.fix_3d:
            return ("levelled; waiting for a 3D GNSS fix with a velocity to find the heading (the last fix had "
                    + ("no velocity)" if fix.vel is None else "no 3D solution)"))
        speed = math.hypot(fix.vel[0], fix.vel[1])
        if speed >= p.heading_min_speed_mps:
            return (f"levelled; waiting for a GNSS course the receiver is sure of (the last: {speed:.1f} m/s, "
                    f"+-{fix.s_vel:.1f} m/s)")
        return (f"levelled; waiting for the car to move at {p.heading_min_speed_mps:g} m/s or more to find the "
                "heading from the GNSS course")

    def close_epochs(self) -> None:
        """Bring the covariance to the last sample and close the last epoch: the backward pass starts there."""
        if self.ekf is None or not self.epochs:
            return
        self.propagate()
        self._close_epoch()

    def _close_epoch(self) -> None:
        """The covariance after the last epoch's updates, and whether the filter forgot something meanwhile."""
        assert self.ekf is not None
        ep = self.epochs[-1]
        ep.p_plus = self.ekf.p.copy()
        if self.ekf.inflations != self._inflations_seen:
            self._inflations_seen = self.ekf.inflations
            ep.cut = True

    def current(self) -> Solution | None:
        s = self.state
        if self.mode == "gnss" or s is None:
            return self.solution
        return self._solution(self._t_last or 0, self._t_mono_last, s)

    def _solution(self, t_ns: int, t_mono_ns: int, s: NavState) -> Solution:
        roll, pitch, yaw = euler_from_dcm(s.dcm())
        return Solution(t_ns, t_mono_ns, s.lat, s.lon, s.h, (s.vn, s.ve, s.vd), (roll, pitch, yaw), self.sigma,
                        f"ins {self.mode}-state")
