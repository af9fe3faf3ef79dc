"""The measurement policies: how much each sensor's reading is worth, and when it goes in at all.

One class per source of updates, each with the little state its policy needs, acting on the filter through
:class:`logger.nav.core.FilterCore` and the evidence rules it is given:

- :class:`GnssPolicy`: a fix's noise from the receiver's accuracy (or its DOP), correlated over the multipath
  time; fixes with too few satellites left out; rows far worse than what the filter knows left out; a street
  canyon's heights left out while a barometer holds the height; position and velocity updates, with the position
  and velocity evidence;
- :class:`ObdPolicy`: the 1 km/h steps of PID 0x0D (repeats of one value weigh less and less) and the
  non-holonomic rows that go with the speed;
- :class:`StopPolicy`: zero velocity and zero rate at a stop (Eq. 12), over the stop so far;
- :class:`BaroPolicy`: barometric heights, with the height evidence, and the non-holonomic constraint when no
  fresh speed comes from the vehicle.

:class:`LastReadings` is what the sensors said last, which more than one policy (and the start-up) goes by.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from logger.nav.core import EngineCounters, FilterCore, PreparedFix
from logger.nav.evidence import GOOD_FIX_H_ACC_M, HeightEvidence, PositionEvidence, VelocityEvidence
from logger.nav.gnss_noise import RECEIVER, AccuracyModel, CorrelatedGnssNoise, UsualFigure
from logger.nav.gnss_rate import FixThinner
from logger.nav.gnss_time import GnssEpochClock
from logger.nav.inputs import GnssObservation
from logger.nav.measurements import (
    OBD_STEP_MPS,
    ROUNDING_VAR,
    BaroHeight,
    GnssPosition,
    GnssVelocity,
    NonHolonomic,
    ObdVelocity,
    Observation,
    ZeroMotion,
    repeat_variance,
)
from logger.nav.params import NavParams
from logger.nav.state import P_ID, RQ_ID, V_ID
from logger.nav.stops import StopDetector

NS = 1_000_000_000
OBD_FRESH_NS = int(1.2 * NS)
BARO_FRESH_NS = 5 * NS  # a barometer heard from within this long still holds the height (it runs at 1-2 Hz)
OBD_MIN_SPEED_MPS = 0.5  # below this the 1 km/h steps of PID 0x0D say little
OBD_ROUNDING_HOLD_NS = 10 * NS  # how long one rounding error is taken to last: a speed leaves its step by then
MIN_WHITE_VAR = 0.02**2  # (m/s)^2: the least white noise of a reading besides its rounding
NHC_MIN_SPEED_MPS = 1.0
NHC_INTERVAL_NS = NS // 2
UNINFORMATIVE_RATIO = 16.0  # fix variance over the filter's own, on every axis: the update would gain < 6 %
# A fix whose vertical figure is this many times its receiver's usual one (gnss_noise.UsualFigure) is a street
# canyon's: reflections make its height wrong one way for as long as the canyon lasts (the simulated receiver's
# canyon heights ran 1.2-5.3 times their figure, high by 1.0-1.5 of it on average, docs/nav.md). While a
# barometer holds the height its row is left out, for at most CANYON_HEIGHT_HOLD_NS since a fix's height last
# went in: the barometer's offset, which weather moves, is then checked against the receiver again.
CANYON_HEIGHT_RATIO = 3.0
CANYON_HEIGHT_HOLD_NS = 120 * NS
# A 2D fix measures no height: the one it carries is a stand-in (the last 3D fix's), good to that fix's figure
# widened by what a car can climb since (a 12 % grade at 60 km/h is 2 m/s). Before any 3D fix there is nothing to
# stand in: the receiver's own assumption if it gives one (u-blox holds a height it was told or guessed), else 0 m,
# either known only to the span of road heights on Earth. Only a start, a restart or a GNSS-only row takes a 2D
# fix's height (its update is horizontal): each then carries a sigma it can stand behind.
CLIMB_MPS = 2.0
UNKNOWN_HEIGHT_SIGMA_M = 1000.0


@dataclass
class LastReadings:
    """What the sensors said last."""

    fix: PreparedFix | None = None
    obd: tuple[int, float] | None = None  # (t_ns, speed) of the last OBD reading
    baro: tuple[int, float] | None = None  # (t_ns, altitude) of the last barometer reading
    nhc_ns: int = 0  # the last non-holonomic update
    pos_ok: tuple[int, float] = (0, math.inf)  # time and accuracy of the last fix whose position went in
    good_fix_ns: int = 0  # epoch of the last 3D fix from a receiver sure of itself, whether it went in
    height_in_ns: int = 0  # ... and of the last one whose height went in
    height_held_ns: int = 0  # ... and of the last whose height was left to the barometer as a canyon's

    def obd_fresh(self, t_ns: int) -> bool:
        return self.obd is not None and t_ns - self.obd[0] <= OBD_FRESH_NS

    def baro_fresh(self, t_ns: int) -> bool:
        return self.baro is not None and t_ns - self.baro[0] <= BARO_FRESH_NS


class GnssPolicy:
    """Receiver fixes: their noise, which of their rows go in, and what refusals of good ones say."""

    def __init__(self, params: NavParams, epoch_clock: GnssEpochClock, last: LastReadings,
                 position: PositionEvidence, velocity: VelocityEvidence, height: HeightEvidence) -> None:
        self.params = params
        self.epoch_clock = epoch_clock
        self.last_readings = last
        self.position, self.velocity, self.height = position, velocity, height
        self._noise = CorrelatedGnssNoise(params.gnss_multipath_corr_s, params.gnss_independent_hz,
                                          params.gnss_floor_corr_s, params.gnss_floor_corr_v_s,
                                          params.gnss_floor_corr_speed_s)
        # A GNSS-only solution is the fixes themselves: every one is a row.
        self._thinner = FixThinner(params.gnss_max_hz if params.mode != "gnss" else 0.0)
        self.accuracy = AccuracyModel(params.gnss_uere_m, (params.gnss_nominal_h_acc_m, params.gnss_nominal_v_acc_m,
                                                           params.gnss_nominal_s_acc_mps), params.gnss_learn_scatter)
        # The epoch of the last fix whose height went in, whatever its accuracy (LastReadings.height_in_ns counts
        # a receiver's sure ones only): what the canyon hold is measured from.
        self._height_in_ns: int | None = None
        self._usual_v = UsualFigure()  # the receiver's usual vertical figure, which a canyon's is measured against
        # The last 3D fix's epoch, height and vertical sigma: a 2D fix's stand-in for its height.
        self._last_height: tuple[int, float, float] | None = None

    def prepare(self, msg: GnssObservation, counters: EngineCounters) -> PreparedFix | None:
        """The fix at its epoch with the noise to use; None (counted) when the receiver has no fix."""
        fix_3d = (msg.fix_mode or 0) >= 3 and msg.height_m is not None
        if not msg.fix_ok or (msg.fix_mode or 1) < 2 or msg.lat_deg is None or msg.lon_deg is None:
            counters.gnss_no_fix += 1
            return None
        # A 2D fix (a held height, or none recorded: an epoch without GGA) goes in horizontally; its height is the
        # radius of the north/east offsets, for which the last 3D fix's (or 0 m, a few ppm of it) does, and only
        # where the filter takes a height from it whole its sigma (CLIMB_MPS).
        last_3d = self._last_height
        if fix_3d:
            height = msg.height_m
        elif last_3d is not None:
            height = last_3d[1]
        else:
            height = msg.height_m if msg.height_m is not None else 0.0
        p = self.params
        t_sync = msg.t_sync_ns
        began = None if msg.opened_mono_ns is None else t_sync - (msg.t_mono_ns - msg.opened_mono_ns)
        t_e = self.epoch_clock.epoch_time(t_sync, msg.gnss_time_ns, msg.sync_state, began)
        if not self._thinner.take(msg.gnss_time_ns):
            counters.gnss_thinned += 1  # a receiver faster than gnss_max_hz (gnss_rate.py)
            return None
        counters.gnss_fixes += 1
        fig = self.accuracy.figures(msg.h_acc_m, msg.v_acc_m, msg.s_acc_mps, msg.pdop, msg.hdop, msg.vdop, t_e)
        k = p.gnss_acc_scale
        # The receiver's own figures describe the error of the moment, which lasts: its floor is taken as
        # correlated. Guessed figures are a data sheet's broad spread already (and widened by the scatter).
        sig_h, sig_v, s_vel = self._noise.sigmas(t_e, fig.h_model, fig.v_model, fig.s_acc, fig.source == RECEIVER,
                                                 fig.scale)
        sig_h, sig_v, s_vel = max(0.1, k * sig_h), max(0.2, k * sig_v), max(0.03, k * s_vel)
        vel = msg.vel_ned_mps
        vel_arr, vel_3d = None, False
        if vel is not None and vel[0] is not None and vel[1] is not None:
            # North and east without down (NMEA's speed and course): a horizontal velocity, nothing made up.
            vel_3d = vel[2] is not None
            vel_arr = np.array((vel[0], vel[1], vel[2] if vel_3d else 0.0), float)
        tu = self.epoch_clock.uncertainty_s
        if tu > 0.0:
            # An epoch placed by its arrival is uncertain by the latency's spread: so is where the car was then.
            moving = vel_arr if vel_arr is not None else (self.last_readings.fix.vel if self.last_readings.fix
                                                          is not None else None)
            if moving is not None:
                d = tu * float(np.hypot(moving[0], moving[1]))
                sig_h, sig_v = math.hypot(sig_h, d), math.hypot(sig_v, tu * abs(float(moving[2])))
        if fix_3d:
            self._last_height = (t_e, height, sig_v)
        elif last_3d is not None:
            sig_v = math.hypot(last_3d[2], CLIMB_MPS * max(0.0, (t_e - last_3d[0]) / NS))
        else:
            sig_v = UNKNOWN_HEIGHT_SIGMA_M
        usual_v = self._usual_v.add(t_e, fig.v_model)
        return PreparedFix(t_e, msg.t_mono_ns + (t_e - t_sync), math.radians(msg.lat_deg),
                           math.radians(msg.lon_deg), height, vel_arr, vel_3d, (sig_h, sig_h, sig_v), s_vel,
                           fix_3d, fig, fig.v_model / usual_v if usual_v > 0.0 else 1.0)

    def update(self, core: FilterCore, fix: PreparedFix, num_sv: int | None, gyro_raw: np.ndarray,
               position: bool = True) -> str:
        """Position and velocity updates of a running filter; returns what the position evidence said ("",
        "reanchor" or "reset": the caller restarts the filter from the fix). ``position`` False: the velocity
        only (a post-processed solution gives the positions, :mod:`logger.nav.solution`)."""
        p = self.params
        if num_sv is not None and num_sv < p.gnss_min_sv:
            # Four or five satellites leave the receiver nothing to check its solution against: a reflection
            # shifts the fix by tens of metres while its accuracy figure stays small. Counted, not used.
            core.counters.gnss_few_sv += 1
            return ""
        if not position:
            self._velocity(core, fix, gyro_raw)
            return ""
        # Rows of a fix far worse than what the filter already knows would move it by a few percent per epoch,
        # and a receiver's errors in a street canyon persist for many epochs: those percents add up to its
        # bias, not to information. Such rows are left out (counted); the others go in.
        t_e = fix.t_ns
        snap = core.state_at(t_e)
        full_pos = GnssPosition(fix.lat, fix.lon, fix.h, fix.sigma, core.lever, not fix.fix_3d).observe(
            snap, snap.dcm(), core.n)
        assert core.ekf is not None
        p_prior = [float(core.ekf.p[P_ID + i, P_ID + i]) for i in range(len(full_pos.z))]
        last = self.last_readings
        canyon = (fix.v_over_usual >= CANYON_HEIGHT_RATIO and last.baro_fresh(t_e) and self._height_in_ns is not None
                  and t_e - self._height_in_ns <= CANYON_HEIGHT_HOLD_NS)
        obs, rows = self._informative(core, full_pos, P_ID, fix.figures.source != RECEIVER, t_e if canyon else None)
        ok = True if obs is None else core.apply(obs)
        # The height went in, with both horizontal rows, one (a fix whose east is too weak still gives its north and
        # height) or none (guessed figures' height judged on its own): the canyon's hold counts from it.
        height_in = ok and 2 in rows
        if height_in:
            self._height_in_ns = t_e
        if ok:
            # Learnt from fixes the gate let in, and from those too weak to reach it (which nothing vetted: they may
            # only lower the scale, ScatterLearner.add). A filter that lost itself must not teach the model that the
            # receiver scatters by hundreds of metres (its fixes' figures would then be too poor to restart it), but
            # a scale learnt from accepted fixes only cannot come down once it makes every fix too weak to go in.
            # After the simulated 130 s tunnel at 10 Hz (NMEA, seed 1) its first fixes (3-7 satellites, HDOP 4-15)
            # taught a horizontal scale of 14; every open-sky fix after them was then left out, the scale never
            # relearnt, and the filter stayed 6 m off for the 200 s left of the drive (north RMSE while moving
            # 5.01 m; 1.35 m now, with SpeedScatter's DOP prior for the exit's speeds as well).
            self.accuracy.observe(t_e, fix.figures, full_pos.z.tolist(), p_prior, obs is not None)
        if obs is not None and ok:
            last.pos_ok = (t_e, fix.h_acc)
            if fix.fix_3d and height_in and fix.h_acc < GOOD_FIX_H_ACC_M:
                last.height_in_ns = t_e
        if ok:
            # Position and velocity are one solution of the receiver's: one whose position the gate refuses is in
            # trouble (the first after a tunnel: 12.8 m off in height on the simulated urban drive, its velocity
            # 0.9 m/s off behind a 0.49 m/s figure), and its velocity, taken alone, moved the position a metre
            # through the outage's correlations. Urban east RMSE while moving 0.58 -> 0.54 m (the matrix's 600 s
            # default drive, seed 1, a quarter of it parked and left out).
            self._velocity(core, fix, gyro_raw)
        if fix.h_acc < GOOD_FIX_H_ACC_M and fix.fix_3d:  # a 2D fix has no height of its own to settle anything
            last.good_fix_ns = fix.t_ns
        sigma_max = max(core.sigma)
        verdict = self.position.judge(core, ok, fix, full_pos.z.tolist(), last.pos_ok, sigma_max)
        if verdict == "reanchor":
            self.height.run.clear()  # judged against the height just widened
        return verdict

    def _velocity(self, core: FilterCore, fix: PreparedFix, gyro_raw: np.ndarray) -> None:
        """The fix's velocity update, with the velocity evidence."""
        if fix.vel is None:
            return
        snap = core.state_at(fix.t_ns)
        full = GnssVelocity(fix.vel, fix.s_vel, core.lever, gyro_raw,
                            not (fix.fix_3d and fix.vel_3d)).observe(snap, snap.dcm(), core.n)
        if fix.figures.speed_guessed:  # whatever the gate says of it: a refused speed is the receiver's too
            assert core.ekf is not None
            p_prior = [float(core.ekf.p[V_ID + i, V_ID + i]) for i in range(2)]
            self.accuracy.observe_speed(fix.t_ns, fix.figures, full.z[:2].tolist(), p_prior, fix.figures.s_acc**2)
        obs, _ = self._informative(core, full, V_ID)
        if obs is not None:
            self.velocity.judge(core, obs, core.apply(obs), fix.t_ns,
                                fix.fix_3d and len(obs.z) == len(full.z) and fix.h_acc < GOOD_FIX_H_ACC_M)

    def _informative(self, core: FilterCore, obs: Observation, block: int, height_on_its_own: bool = False,
                     canyon_ns: int | None = None) -> tuple[Observation | None, list[int]]:
        """The observation without its rows whose variance exceeds the filter's own by UNINFORMATIVE_RATIO, and the
        rows of ``obs`` it keeps; with ``canyon_ns`` (a street canyon's fix, of that epoch) without its height, which
        the barometer holds instead."""
        assert core.ekf is not None
        p = core.ekf.p
        keep = [i for i in range(min(2, len(obs.z)))
                if obs.r[i] <= UNINFORMATIVE_RATIO * float(p[block + i, block + i])]
        # The height row stays while the fix is any good horizontally: the barometer's offset is learnt from the
        # GNSS height over minutes. A fix useless horizontally is a canyon's (its receiver's figures say so), and
        # its height goes with it. A fix with guessed figures (no accuracy from the receiver) says nothing of a
        # canyon: a filter held tight horizontally by its speeds leaves its height to the fixes, judged alone
        # (the 15-state filter, without a barometer, drifted 64 m in height when it went with the horizontal).
        # A canyon's height the barometer holds better is left out by the caller (CANYON_HEIGHT_RATIO).
        held = 0
        if len(obs.z) > 2 and (keep or (height_on_its_own
                                        and obs.r[2] <= UNINFORMATIVE_RATIO * float(p[block + 2, block + 2]))):
            if canyon_ns is None:
                keep.append(2)
            else:  # a canyon's height that would have gone in: the barometer holds the height instead
                held = 1
                core.counters.gnss_canyon_heights += 1
                self.last_readings.height_held_ns = canyon_ns
        if len(keep) < len(obs.z):
            core.counters.gnss_skipped += len(obs.z) - len(keep) - held
            if not keep:
                return None, []
            obs = Observation(obs.name, obs.z[keep], obs.h[keep], obs.r[keep])
        return obs, keep


class StopPolicy:
    """Zero velocity and zero rate while the vehicle stands, over the stop so far."""

    def __init__(self, params: NavParams, stops: StopDetector, velocity: VelocityEvidence) -> None:
        self.params = params
        self.stops = stops
        self.velocity = velocity
        self.stopped = False
        self.w_sum = [0.0, 0.0, 0.0, 0]  # gyro sum and count since the last zero-motion update (the IMU loop adds)
        self._t0 = 0

    def update(self, core: FilterCore, stopped_now: bool, t_last_ns: int, learn: bool = False) -> bool:
        """Zero velocity and zero rate (Eq. 12) over the stop so far; returns whether the vehicle stands.

        ``learn``: the OBD confirms the stop, so the stop detector may adapt its threshold and the updates count
        as trusted evidence."""
        assert core.state is not None
        p, s = self.params, core.state
        was = self.stopped
        self.stopped = stopped_now
        ws = self.w_sum
        if stopped_now:
            if learn:
                self.stops.learn()
            span_s = (t_last_ns - self._t0) / NS
            if was and ws[3] > 0 and span_s > 0.0:
                w_mean = np.array((ws[0] / ws[3], ws[1] / ws[3], ws[2] / ws[3]))
                # The mean over the window: the gyro's white noise averages down with its length.
                sigma_w = max(math.radians(p.zaru_sigma_dps), core.noise.gyro_arw) / math.sqrt(span_s)
                obs = ZeroMotion(w_mean, p.zupt_sigma_mps, sigma_w).observe(s, s.dcm(), core.n)
                self.velocity.judge(core, obs, core.apply(obs), t_last_ns, learn)
                core.counters.zupt += 1
        self.w_sum = [0.0, 0.0, 0.0, 0]
        self._t0 = t_last_ns
        return stopped_now


class ObdPolicy:
    """The vehicle's speed sensor: a velocity along the vehicle's axis, in 1 km/h steps."""

    def __init__(self, params: NavParams, last: LastReadings, stop: StopPolicy, velocity: VelocityEvidence) -> None:
        self.params = params
        self.last_readings = last
        self.stop = stop
        self.velocity = velocity
        self._run = 0  # readings in a row with the same value (within OBD_ROUNDING_HOLD_NS of the first)
        self._run_t0 = 0
        self.mount_yaw_stat = [0.0, 0.0]  # sum of lateral/forward velocity ratios and weights (mounting check)

    def note(self, t_ns: int, speed_mps: float) -> bool:
        """Every reading, before the filter runs too: the rounding run and the latest speed. Whether the reading
        begins a new run of equal readings (a value unlike the last one)."""
        last = self.last_readings.obd
        new = last is None or last[1] != speed_mps
        if new:
            self._run, self._run_t0 = 1, t_ns
        elif t_ns - self._run_t0 <= OBD_ROUNDING_HOLD_NS:
            self._run += 1
        self.last_readings.obd = (t_ns, speed_mps)
        return new

    def update(self, core: FilterCore, t_ns: int, speed_mps: float, t_last_ns: int) -> None:
        p = self.params
        if self.stop.update(core, speed_mps == 0.0 and self.stop.stops.still, t_last_ns, learn=True):
            return
        if speed_mps < OBD_MIN_SPEED_MPS:
            return
        # The speed the ECU reported belongs to its own instant: evaluated against the solution then.
        # At a steady speed the reading stays on one 1 km/h step and its rounding error stays the same.
        if core.n > RQ_ID:
            # That rounding is a state of the run of equal readings (RQ_ID, ``obd_rounding_state``; started
            # again by the engine at each new value), so each reading adds only the rest of its error (latency,
            # wheel slip) as white noise: n readings of a run know the speed to the rounding's variance plus the
            # rest over n, and fixes during the run teach the rounding.
            var = p.obd_speed_sigma_mps**2
            sigma = math.sqrt(max(var - min(ROUNDING_VAR, var), MIN_WHITE_VAR))
        else:
            # The paper's model: the repeats say little new about the rounding, so they weigh less and less (a run
            # of equal readings is not many independent ones: 40 of them would otherwise pull the solution to the
            # rounded speed). A real speed does not stay within one step for long, and the IMU drifts meanwhile:
            # past OBD_ROUNDING_HOLD_NS the repeats keep the weight they had then, and hold the speed again.
            sigma = math.sqrt(repeat_variance(p.obd_speed_sigma_mps, OBD_STEP_MPS, self._run))
        snap = core.state_at(t_ns)
        c_bn = snap.dcm()
        obs = ObdVelocity(speed_mps, sigma, p.nhc_sigma_mps).observe(snap, c_bn, core.n)
        if self.velocity.judge(core, obs, core.apply(obs), t_ns, True, c_bn):
            self.last_readings.nhc_ns = t_ns
            if speed_mps > 5.0:  # a mounting turned about the vertical shows as a steady side slip
                self.mount_yaw_stat[0] += float(obs.z[1]) / speed_mps
                self.mount_yaw_stat[1] += 1.0


class BaroPolicy:
    """Barometric heights (with the barometer's offset in the 17-state filter)."""

    def __init__(self, params: NavParams, last: LastReadings, stop: StopPolicy, height: HeightEvidence) -> None:
        self.params = params
        self.last_readings = last
        self.stop = stop
        self.height = height

    def update(self, core: FilterCore, t_ns: int, altitude_m: float) -> None:
        s = core.state
        assert s is not None
        last = self.last_readings
        # A canyon's height held by the barometer counts as the receiver's going in: the filter's height is the one
        # the receiver's last heights left it, carried by the barometer and the IMU since (HeightEvidence).
        self.height.judge(core, BaroHeight(altitude_m, self.params.baro_sigma_m).observe(s, s.dcm(), core.n), t_ns,
                          max(last.height_in_ns, last.height_held_ns), last.good_fix_ns)
        # No fresh OBD speed: the vehicle still cannot slide sideways or lift off.
        if (self.stop.stopped is False and last.obd is not None and t_ns - last.obd[0] > OBD_FRESH_NS
                and t_ns - last.nhc_ns > NHC_INTERVAL_NS and math.hypot(s.vn, s.ve) > NHC_MIN_SPEED_MPS
                and core.apply(NonHolonomic(self.params.nhc_sigma_mps).observe(s, s.dcm(), core.n))):
            last.nhc_ns = t_ns
