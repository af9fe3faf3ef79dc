"""Plain verdicts for ``logger status``, drawn from the filter: what an operator at a red light can act on.

Each verdict is one sentence with its figure: whether GNSS agrees with the IMU, how far the OBD speed reads
off, whether the barometer's offset holds, whether the IMU offsets are within the datasheet, whether the IMU is
far noisier than configured (a board that shakes), and whether the IMU is mounted the way the configuration says.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from logger.nav.earth import G0
from logger.nav.engine import NavEngine
from logger.nav.imu_noise import consumer_grade
from logger.nav.mounting import FORWARD
from logger.nav.state import BA_ID, BG_ID, DH_ID, SF_ID

ACCEL_LIMIT_MG = (50.0, 50.0, 80.0)  # MPU-6050 zero-g output tolerance, x y z
GYRO_LIMIT_DPS = 20.0  # MPU-6050 zero-rate output tolerance
BARO_DRIFT_M_PER_MIN = 0.5  # a front passing moves pressure ~1 hPa/h (0.14 m/min); more is the sensor or its vent
OFFSET_SIGMAS = 2.0  # an offset is beyond (or within) the datasheet's tolerance when this many sigmas past it
MOUNT_TILT_LIMIT_DEG = 10.0
MOUNT_SLIP_LIMIT_DEG = 2.0
OUTAGE_S = 5.0  # the filter's last fix older than this: dead reckoning is said (not for a few missed fixes)


class HealthJudge:
    """Keeps the little history the verdicts need (GNSS acceptance, baro offset over minutes)."""

    def __init__(self) -> None:
        # Where the last verdicts' outage line is (None: there is none), so that a status asked between two
        # publishes can say its age as of then (outage_verdict's ``later_s``).
        self.outage_line: int | None = None
        self._gnss: deque[bool] = deque(maxlen=60)
        self._seen_gnss = (0, 0)
        self._offset: deque[tuple[float, float]] = deque(maxlen=600)  # (t_s, offset m), one per call

    def verdicts(self, engine: NavEngine, t_s: float) -> list[str]:
        out: list[str] = []
        self.outage_line = None
        ekf, s = engine.ekf, engine.state
        if s is None or ekf is None:
            if engine.mode == "gnss":
                waiting = engine.waiting_for()
                return [f"GNSS-only mode: {waiting}" if waiting else
                        "GNSS-only mode: no filter, the receiver's fixes are passed through"]
            return [f"initialising: {engine.waiting_for()}"]
        st = ekf.stats.get("gnss_pos")
        if st is not None:
            acc, rej = st.accepted, st.rejected
            d_acc, d_rej = acc - self._seen_gnss[0], rej - self._seen_gnss[1]
            self._seen_gnss = (acc, rej)
            self._gnss.extend([True] * min(d_acc, 60) + [False] * min(d_rej, 60))
        n = len(self._gnss)
        refused = n - sum(self._gnss)
        outage = outage_verdict(engine)
        self.outage_line = len(out) if outage else None
        if outage:
            out.append(outage)
        elif n and refused > n // 5:
            out.append(f"GNSS disagrees with the IMU: {refused} of the last {n} fixes refused")
        elif n:
            out.append(f"GNSS consistent with the IMU ({n - refused} of the last {n} fixes accepted)")
        if engine.n > SF_ID:
            t_last = engine.t_last_ns
            sf_sigma = ekf.sigma(SF_ID)
            obd = engine.last_readings.obd
            if obd is None or not engine.last_readings.obd_fresh(t_last or 0):
                since = "" if obd is None or not t_last else f" for {(t_last - obd[0]) / 1e9:.0f} s"
                out.append(f"no OBD speed{since}: the filter runs without the vehicle's speed")
            elif sf_sigma < 0.01:
                high = (1.0 / (1.0 + s.sf) - 1.0) * 100.0
                word = "high" if high >= 0 else "low"
                out.append(f"OBD speed reads {abs(high):.1f} % {word} (+-{sf_sigma * 100:.1f} %)")
            else:
                out.append("OBD speed scale still being learned (needs GNSS velocity while driving)")
            out.append(self._baro_verdict(engine, t_s))
        out.append(offsets_verdict(engine))
        noisy = noise_verdict(engine)
        if noisy:
            out.append(noisy)
        out.append(mounting_verdict(engine))
        if engine.counters.resets:
            out.append(f"filter restarted from GNSS {engine.counters.resets} times (lost itself)")
        return out

    def _baro_verdict(self, engine: NavEngine, t_s: float) -> str:
        """The barometer's offset and its trend over a minute; without a barometer heard from, that there is none
        (an offset nothing moves stands still: no verdict on it, and its trend starts again with the readings)."""
        s, ekf, t_last = engine.state, engine.ekf, engine.t_last_ns
        assert s is not None and ekf is not None
        baro = engine.last_readings.baro
        if baro is None or not engine.last_readings.baro_fresh(t_last or 0):
            self._offset.clear()
            since = "" if baro is None or not t_last else f" for {(t_last - baro[0]) / 1e9:.0f} s"
            return f"no barometer{since}: the height runs without it"
        self._offset.append((t_s, s.dh))
        old = [(t, d) for t, d in self._offset if t_s - t >= 60.0]
        if not old:
            return f"barometer offset {s.dh:+.1f} m (+-{ekf.sigma(DH_ID):.1f} m), trend after a minute"
        t0, d0 = old[-1]
        rate = (s.dh - d0) / (t_s - t0) * 60.0
        state = "drifting" if abs(rate) > BARO_DRIFT_M_PER_MIN else "stable"
        return f"barometer offset {state}: {s.dh:+.1f} m (+-{ekf.sigma(DH_ID):.1f} m), {rate:+.2f} m/min"


def outage_verdict(engine: NavEngine, later_s: float = 0.0) -> str | None:
    """The line "no GNSS fix for N s: dead reckoning on ..." when the filter's last fix was over OUTAGE_S old at its
    last sample; None otherwise. ``later_s``: how long after that sample the line is read (the status between two of the
    navigator's wakes), counted into the age, as the receiver's own row counts its silence up to the moment asked."""
    fix = engine.last_readings.fix
    t_last = engine.t_last_ns
    age = (t_last - fix.t_ns) / 1e9 if fix is not None and t_last else math.inf
    if not age > OUTAGE_S:
        return None
    on = "the IMU"
    if engine.mode == "17":
        last = engine.last_readings
        aids = [name for name, fresh in (("OBD", last.obd_fresh(t_last or 0)),
                                         ("baro", last.baro_fresh(t_last or 0))) if fresh]
        on = "IMU" + "".join(f", {a}" for a in aids[:-1]) + (f" and {aids[-1]}" if aids else " alone")
    return f"no GNSS fix for {age + max(later_s, 0.0):.0f} s: dead reckoning on {on}"


def offsets_verdict(engine: NavEngine) -> str:
    """The IMU offsets against the datasheet's tolerances, as far as the filter knows them: beyond only when the
    estimate is OFFSET_SIGMAS of its sigmas past the limit, within only when as far inside it; otherwise not yet
    known (a minute after the start the accelerometer's offsets are known to tens of mg: the estimate alone said
    "within" or "beyond" then on nothing)."""
    s, ekf = engine.state, engine.ekf
    assert s is not None and ekf is not None
    # The filter holds the offsets on the vehicle's axes; the tolerances are the chip's (z is wider): turned back
    # through the mounting in use (vehicle from chip), with their covariance.
    m = engine.vehicle_from_chip
    p = ekf.p
    ba = m.T @ np.array(s.ba)
    bg = m.T @ np.array(s.bg)
    var_a = np.diag(m.T @ p[BA_ID:BA_ID + 3, BA_ID:BA_ID + 3] @ m)
    var_g = np.diag(m.T @ p[BG_ID:BG_ID + 3, BG_ID:BG_ID + 3] @ m)
    ba_mg = [abs(float(b)) / G0 * 1e3 for b in ba]
    ba_sig = [math.sqrt(max(float(v), 0.0)) / G0 * 1e3 for v in var_a]
    bg_dps = [abs(math.degrees(float(b))) for b in bg]
    bg_sig = [math.degrees(math.sqrt(max(float(v), 0.0))) for v in var_g]
    bad = [f"accelerometer {'xyz'[i]} offset {ba_mg[i]:.0f} mg (+-{ba_sig[i]:.0f}) beyond the datasheet's "
           f"{ACCEL_LIMIT_MG[i]:.0f}" for i in range(3) if ba_mg[i] - OFFSET_SIGMAS * ba_sig[i] > ACCEL_LIMIT_MG[i]]
    bad += [f"gyro {'xyz'[i]} offset {bg_dps[i]:.1f} deg/s (+-{bg_sig[i]:.1f}) beyond the datasheet's "
            f"{GYRO_LIMIT_DPS:.0f}" for i in range(3) if bg_dps[i] - OFFSET_SIGMAS * bg_sig[i] > GYRO_LIMIT_DPS]
    if bad:
        return "IMU offsets beyond the datasheet: " + "; ".join(bad)
    # Written so that a NaN (an estimate or a sigma gone bad) is not "within": only a comparison that holds is.
    unsure = ([f"accelerometer {'xyz'[i]}" for i in range(3)
               if not ba_mg[i] + OFFSET_SIGMAS * ba_sig[i] <= ACCEL_LIMIT_MG[i]]
              + [f"gyro {'xyz'[i]}" for i in range(3) if not bg_dps[i] + OFFSET_SIGMAS * bg_sig[i] <= GYRO_LIMIT_DPS])
    if unsure:
        return (f"IMU offsets not yet known against the datasheet ({', '.join(unsure)}): accel <= {max(ba_mg):.0f} mg "
                f"+-{max(ba_sig):.0f}, gyro <= {max(bg_dps):.2f} deg/s +-{max(bg_sig):.2f}")
    return f"IMU offsets within the datasheet: accel <= {max(ba_mg):.0f} mg, gyro <= {max(bg_dps):.2f} deg/s"


def noise_verdict(engine: NavEngine) -> str | None:
    """The IMU's white noise (imu_noise.py) when it measures CONSUMER_NOISE_RATIO times the configured densities or
    more: on the logger's own board it shakes, loose in its mount or on something that vibrates (what the operator
    can look at at the next stop: the noise alone cannot tell which); on a consumer-grade part what the part is.
    The filter has widened its process noise to it, and stops are told by the vehicle's speed or the fixes (held
    stops). None when it is not so."""
    ratio = engine.imu_noise_ratio()
    if ratio is None or not consumer_grade(ratio):
        return None
    ra, rg = ratio
    return (f"IMU {ra:.1f}x / {rg:.1f}x the configured noise (accel / gyro): the board shakes (loose, or on something"
            " that vibrates) or the part is consumer-grade"
            + ("; stops told by speed" if engine.stops.held_learned else ""))


def mounting_verdict(engine: NavEngine) -> str:
    al = engine.alignment
    if al is not None:
        est = al.estimate()
        if math.isfinite(est.sigma_deg[0]):
            moved = f"; the mounting moved {al.moves} times this drive" if al.moves else ""
            # Forward axis only: the roll's sigma is the guess's, what is known is the pitch and yaw's.
            sig, what = ((max(est.sigma_deg[1:]), "forward axis +-") if est.state == FORWARD
                         else (max(est.sigma_deg), "+-"))
            return f"{est.words()} ({what}{sig:.1f} deg, {est.windows} windows){moved}"
    lev = engine.startup.levelled
    slip_sum, slip_n = engine.mount_yaw_stat
    parts = []
    problems = []
    if lev is not None:
        roll, pitch = math.degrees(lev[0]), math.degrees(lev[1])
        parts.append(f"levelled at roll {roll:+.1f} deg, pitch {pitch:+.1f} deg")
        if max(abs(roll), abs(pitch)) > MOUNT_TILT_LIMIT_DEG:
            problems.append(f"the IMU stands tilted {max(abs(roll), abs(pitch)):.0f} deg at standstill")
    if slip_n >= 20:
        slip = math.degrees(slip_sum / slip_n)
        parts.append(f"mean side slip {slip:+.1f} deg")
        if abs(slip) > MOUNT_SLIP_LIMIT_DEG:
            problems.append(f"the vehicle seems to slide sideways {slip:+.1f} deg: IMU turned about the vertical")
    if problems:
        return "IMU mounting implausible: " + "; ".join(problems) + " (check nav.mounting_rpy_deg)"
    return "IMU mounting plausible" + (f" ({', '.join(parts)})" if parts else "")
