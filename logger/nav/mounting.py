"""Automatic IMU-mount alignment: the chip's roll, pitch and yaw against the vehicle, from what the drive shows.

Automotive dead-reckoning receivers (u-blox ADR/UDR, ESF-ALG) do not ask the installer how the box sits: they
compare what the IMU measures with what the vehicle must be doing. So does this module. A car has no side slip
and no vertical velocity through its floor (the non-holonomic constraint), so over a window between two GNSS
velocities (at least WINDOW_S apart; the receiver's Doppler owes nothing to the IMU whose mounting is in doubt)
its specific force and rate in its own forward-right-down axes follow from its speed, its course and the road:

    f_vehicle = (a + g sin(theta), v w, -g cos(theta)),    w_vehicle = w (-sin(theta), 0, cos(theta))

with ``a`` the change of speed, ``v`` the speed, ``theta`` the grade atan2(-v_down, v_horizontal), ``w`` the turn
rate (the gyro's, signed as the course turned), both vectors then turned by the body's lean out of the turn
(ROLL_GRADIENT). The chip measures ``f_chip = R f_vehicle + b`` and ``w_chip = R w_vehicle`` (R the mounting, chip
from vehicle, ``b`` the accelerometer's offset). Wahba's problem over the windows, with ``b`` free beside R, is one
SVD of the pairs' cross-covariance about their means (Markley). Gravity's mean is taken up by the offset, so the
angles come from the forces' spread and the turns: speeding up and braking tell the yaw, turns (the lateral force
and the turn axis) the roll and pitch. A drive without turns tells no roll. Windows slower than MIN_SPEED_MPS
(the grade is noise), sharper than MAX_TURN_DPS or harder than MAX_ACCEL_MPS2 are left out. A road's bank is not
modelled: it averages out over roads, and is in the residuals, hence in the uncertainty.

The configured mounting is a prior of PRIOR_SIGMA_DEG on every axis (pairs of its own axes in the same
problem), so an axis the drive does not show stays at the guess while the others are estimated: on a straight
road the forward axis (the yaw and the pitch of the chip's view of the car's forward direction) is known within a
minute of driving, the roll only after turns. What the filter needs first is that forward axis (the OBD speed and
the non-holonomic rows hold the body on it); an error about the forward axis itself is a roll the filter's
attitude takes up. The uncertainty is the fit's: the residuals' scatter over the information the pairs' spread
gives, widened by the windows' correlation (a grade or a bank lasts several windows), and the prior's. The
estimate is ``forward`` once pitch and yaw are known to USABLE_SIGMA_DEG (the roll still the guess), complete
(``learning``) once every angle is, and ``settled`` once roll and pitch are known to SETTLED_TILT_DEG and the yaw
to SETTLED_YAW_DEG over at least MIN_WINDOWS windows. A second, short-memory fit over the last minutes of windows
watches for a mounting that moved (the board knocked): when it disagrees with the long one by more than both its
uncertainty and MOVED_DEG (compared every MOVED_CHECK_WINDOWS windows), the long fit starts again from the recent
windows (counted in ``moves``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from logger.nav.arrays import diff_from
from logger.nav.deferred import BlockKeeper
from logger.nav.ekf import inverse3
from logger.nav.rotations import dcm_from_euler, euler_from_dcm, rotvec_from_dcm

# Standard gravity: the local value differs by a few hundredths of a m/s^2, a constant the free accelerometer
# offset takes up (it is the pairs' mean force along the vertical).
G0 = 9.80665
WINDOW_S = 1.0  # at least this long between the two fixes of a window
SUM_SAMPLES = 8192  # running sums kept at most: 8 s at 1 kHz, more than a fix's latency plus a window
# One running sum kept per this much time (the first sample of each step): a window's ends then fall within 10 ms
# of the fixes' epochs, a hundredth of a window, whatever the IMU's rate; a sum per sample at 1 kHz held 4000
# tuples (1.4 MB) for the same windows. Below 100 Hz two samples hardly ever share a step: every sum is kept.
SUM_STEP_NS = 10_000_000
SUM_KEEP_NS = int((3 * WINDOW_S + 1.0) * 1e9)  # ... and no older than the longest window before a fix's epoch
MIN_SPEED_MPS = 4.0  # slower, the grade from the velocity is noise
MAX_TURN_DPS = 30.0  # sharper turns (a roundabout): the speed's and course's change over a window is not smooth
# A passenger car's body roll per m/s^2 of lateral acceleration (a roll gradient of 3-7 deg per g; 4.5 taken).
ROLL_GRADIENT = math.radians(0.45)
MIN_TURN_DPS = 2.0  # below this a window is taken as straight: its rate is the gyro's noise and offset
MAX_ACCEL_MPS2 = 4.0  # harder than this (a bump, a pothole) is not the car's own acceleration
CORRELATION_WINDOWS = 3.0  # a window's grade and bank error lasts about this many windows (roads, not noise)
USABLE_SIGMA_DEG = 5.0  # an estimate less sure than this on any axis is not shown
SETTLED_TILT_DEG = 0.5
SETTLED_YAW_DEG = 1.0
MIN_WINDOWS = 60
RECENT_WINDOWS = 120  # the short memory that notices a mounting that moved
MOVED_DEG = 2.0
MOVED_CHECK_WINDOWS = 10  # the two fits are compared every this many windows: a knock shows over minutes anyway
# The configured mounting's weight: a board is fixed by hand to within a few degrees of what its installer wrote,
# and a guess 30 deg off is still a 1.5-sigma one. Against a minute of driving (3 deg) it pulls an estimate by 2 %.
PRIOR_SIGMA_DEG = 20.0

# ``forward``: the car's forward axis on the chip is known (pitch, yaw), the roll is still the guess.
LEARNING, FORWARD, SETTLED = "learning", "forward", "settled"


@dataclass(frozen=True)
class MountEstimate:
    """The mounting as estimated: roll, pitch, yaw of the chip against the vehicle (nav.mounting_rpy_deg's
    convention), 1-sigma, how many windows, and whether it is settled."""

    rpy_deg: tuple[float, float, float]
    sigma_deg: tuple[float, float, float]
    windows: int
    state: str

    def words(self) -> str:
        r, p, y = self.rpy_deg
        state = "forward axis only, roll not yet known" if self.state == FORWARD else self.state
        return f"mount alignment: {r:.1f} / {p:.1f} / {y:.1f} deg, {state}"


CHI2_FLOOR = 0.25  # the residuals may show the windows better than their nominal sigmas, by this much at most
ACCEL_SIGMA_MPS2 = 0.2  # a window's specific force against the model: a road's bank, bumps, the speed's change
GYRO_SIGMA_RPS = math.radians(0.5)  # a window's rate against the course's: pitch and roll rates of the body, slip


# The fit's running sums, packed into one vector so that forgetting is one product and a window one sum.
_B_ACC, _S_FC, _S_FV, _VV_ACC, _B_GYRO, _VV_GYRO = (slice(0, 9), slice(9, 12), slice(12, 15), slice(15, 24),
                                                    slice(24, 33), slice(33, 42))
_CC_ACC, _CC_GYRO, _N, _SIZE = 42, 43, 44, 45
_IJ = [(3 * i + j, i, j) for i in range(3) for j in range(3)]  # flat index, row, column of a 3x3 matrix


def _window_sums(fc: list[float], fv: list[float], wc: list[float], wv: list[float]) -> np.ndarray:
    """What one window adds to a fit's sums (see :class:`_Fit`), from plain floats."""
    return np.array([fc[i] * fv[j] for _, i, j in _IJ] + fc + fv + [fv[i] * fv[j] for _, i, j in _IJ]
                    + [wc[i] * wv[j] for _, i, j in _IJ] + [wv[i] * wv[j] for _, i, j in _IJ]
                    + [fc[0] * fc[0] + fc[1] * fc[1] + fc[2] * fc[2] + (fv[0] * fv[0] + fv[1] * fv[1] + fv[2] * fv[2]),
                       wc[0] * wc[0] + wc[1] * wc[1] + wc[2] * wc[2] + (wv[0] * wv[0] + wv[1] * wv[1] + wv[2] * wv[2]),
                       1.0])


class _Fit:
    """Running sums of one fit (with exponential forgetting when ``memory`` is set): Wahba's problem over pairs of
    specific forces, with the accelerometer's offset estimated beside the rotation, and over pairs of rates.

    Sums, packed in one vector: f_chip f_vehicle^T, f_chip, f_vehicle, f_vehicle f_vehicle^T, w_chip w_vehicle^T,
    w_vehicle w_vehicle^T, |f_chip|^2 + |f_vehicle|^2, |w_chip|^2 + |w_vehicle|^2 and the count. The information
    of a vector v about the rotation, |v|^2 I - v v^T, is a linear function of v v^T: taken from the sum at the
    solve."""

    def __init__(self, prior: np.ndarray, memory: float | None = None) -> None:
        self.memory = memory
        self.prior = prior  # chip from vehicle: the configured mounting, weighed PRIOR_SIGMA_DEG per axis
        self.sums = np.zeros(_SIZE)
        self._solved: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._fresh = False  # _solved is the solution of the sums as they are

    @property
    def n(self) -> float:
        return float(self.sums[_N])

    def add_sums(self, window: np.ndarray) -> None:
        """One window's sums (:func:`_window_sums`), after forgetting a little of the older ones."""
        if self.memory is not None:
            self.sums *= 1.0 - 1.0 / self.memory
        self.sums += window
        self._fresh = False

    def add(self, fc: np.ndarray, fv: np.ndarray, wc: np.ndarray, wv: np.ndarray) -> None:
        self.add_sums(_window_sums(*(np.asarray(v, float).tolist() for v in (fc, fv, wc, wv))))

    def copy_from(self, other: _Fit) -> None:
        self.sums = other.sums.copy()
        self._solved, self._fresh = other._solved, other._fresh

    def solve(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(R chip from vehicle, covariance of its small-angle error in vehicle axes, accelerometer offset on the
        chip's axes), None without enough."""
        if self._fresh:
            return self._solved
        self._solved, self._fresh = self._solve(), True
        return self._solved

    def _solve(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        # In plain floats around the one SVD: a 3x3 problem costs numpy more in calls than in arithmetic.
        sums = self.sums.tolist()
        n = sums[_N]
        if n < 3:
            return None
        wa, wg = 1.0 / ACCEL_SIGMA_MPS2**2, 1.0 / GYRO_SIGMA_RPS**2
        b_acc, s_fc, s_fv, b_gyro = sums[_B_ACC], sums[_S_FC], sums[_S_FV], sums[_B_GYRO]
        m_fv = [v / n for v in s_fv]
        # With the offset b free, its best value is the mean of fc - R fv, and what is left to fit is the pairs'
        # cross-covariance about their means (the term R sum fv sum fv^T / n adds a constant, R^T R = I):
        # one SVD, for the rotation and the offset together.
        cross = [wa * (b_acc[k] - s_fc[i] * m_fv[j]) + wg * b_gyro[k] for k, i, j in _IJ]
        r = _wahba(cross)
        bias = [(s_fc[i] - (r[3 * i] * s_fv[0] + r[3 * i + 1] * s_fv[1] + r[3 * i + 2] * s_fv[2])) / n
                for i in range(3)]
        # sum |fc - b - R fv|^2 = sum |fc|^2 - 2 b.sum fc + n |b|^2 + sum |fv|^2 - 2 trace(R^T sum (fc - b) fv^T)
        sse_acc = (sums[_CC_ACC] - 2.0 * sum(bias[i] * s_fc[i] for i in range(3)) + n * sum(b * b for b in bias)
                   - 2.0 * sum(r[k] * (b_acc[k] - bias[i] * s_fv[j]) for k, i, j in _IJ))
        sse_gyro = sums[_CC_GYRO] - 2.0 * sum(r[k] * b_gyro[k] for k in range(9))
        chi2 = (wa * max(sse_acc, 0.0) + wg * max(sse_gyro, 0.0)) / max(6.0 * n - 6.0, 1.0)
        # The windows' information counts 1 / scale of its nominal (their correlation, and the scatter of their
        # residuals about the windows' own best rotation, the one just found, before the prior);
        # the prior is added as pairs of the configured mounting's axes, sum_i (R0 e_i) e_i^T = R0, whose
        # information is 2 w I: w = 1 / (2 sigma^2) gives sigma per axis.
        scale = max(chi2, CHI2_FLOOR) * CORRELATION_WINDOWS
        w_prior = 0.5 / math.radians(PRIOR_SIGMA_DEG) ** 2
        r0 = self.prior.ravel().tolist()
        r = _wahba([c / scale + w_prior * r0[k] for k, c in enumerate(cross)])
        bias = [(s_fc[i] - (r[3 * i] * s_fv[0] + r[3 * i + 1] * s_fv[1] + r[3 * i + 2] * s_fv[2])) / n
                for i in range(3)]
        # The offset takes up the pairs' mean force (gravity, mostly): only their spread about it tells the angles.
        # Information of a vector v: |v|^2 I - v v^T; summed, trace(V) I - V with V = sum v v^T.
        vv_acc, vv_gyro = sums[_VV_ACC], sums[_VV_GYRO]
        m = [-(wa * (vv_acc[k] - s_fv[i] * m_fv[j]) + wg * vv_gyro[k]) / scale for k, i, j in _IJ]
        tr = (wa * sum(vv_acc[4 * i] - s_fv[i] * m_fv[i] for i in range(3))
              + wg * (vv_gyro[0] + vv_gyro[4] + vv_gyro[8])) / scale + 2.0 * w_prior
        m[0] += tr
        m[4] += tr
        m[8] += tr
        inv = inverse3(m)
        if inv is None:
            return None
        return np.array(r).reshape(3, 3), inv, np.array(bias)


def _wahba(cross: list[float]) -> list[float]:
    """The rotation (row-major, 9 floats) that best turns the second vectors of the pairs onto the first, from
    their weighted cross-covariance sum a b^T (row-major): one SVD, its sign kept a rotation (Markley)."""
    u, _, vt = np.linalg.svd(np.array(cross).reshape(3, 3))
    u9, v9 = u.ravel().tolist(), vt.ravel().tolist()
    sign = _det3(u9) * _det3(v9)
    us = [u9[0], u9[1], u9[2] * sign, u9[3], u9[4], u9[5] * sign, u9[6], u9[7], u9[8] * sign]
    return [us[3 * i] * v9[j] + us[3 * i + 1] * v9[3 + j] + us[3 * i + 2] * v9[6 + j] for _, i, j in _IJ]


def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation nearest the 3 x 3 matrix ``m``: Wahba's problem with ``m`` as the cross-covariance."""
    return np.array(_wahba(np.asarray(m, dtype=float).ravel().tolist())).reshape(3, 3)


def _det3(m: list[float]) -> float:
    a, b, c, d, e, f, g, h, i = m
    return a * (e * i - f * h) + b * (f * g - d * i) + c * (d * h - e * g)


class MountAlignment(BlockKeeper):
    """The mounting from windows of one second of the drive; ``configured`` is the starting guess (degrees)."""

    def __init__(self, configured_rpy_deg: tuple[float, float, float]) -> None:
        self.configured = tuple(float(a) for a in configured_rpy_deg)
        prior = mount_matrix(self.configured).T  # chip from vehicle
        self._long = _Fit(prior)
        self._recent = _Fit(prior, memory=RECENT_WINDOWS)
        self.moves = 0
        self._unchecked = 0  # windows since the fits were last compared
        self._estimate: MountEstimate | None = None  # the last estimate, until the next window changes it
        # Running sums of the chip's samples: (time, sum of specific force, sum of rate, count) at the first sample
        # of each SUM_STEP_NS, so a window between two fix epochs is a difference of two entries whenever the later
        # fix arrives.
        self._sums: deque[tuple[int, float, float, float, float, float, float, int]] = deque(maxlen=SUM_SAMPLES)
        self._last: tuple[int, float, float, float, float, float, float, int] = (0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0)
        self._step = -1  # the SUM_STEP_NS step of the last sum kept
        self._blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # blocks not yet summed, oldest first
        self._fix0: tuple[int, tuple[float, float, float]] | None = None  # the window's first fix: epoch, velocity
        # The filter's gyro offset on the chip's axes (from the standstills: the mounting does not enter), removed
        # from each window's mean rate. The accelerometer's offset is estimated here: the filter's own took up
        # part of the mounting's tilt while the mounting was wrong.
        self.gyro_offset_source: tuple[np.ndarray, tuple[float, float, float]] | None = None

    @property
    def gyro_offset(self) -> np.ndarray:
        """The filter's gyro offset on the chip's axes, from what it last gave (:meth:`offsets`): mounting and offset
        are kept as given and turned only when a window needs them."""
        src = self.gyro_offset_source
        return np.zeros(3) if src is None else src[0].T @ np.array(src[1])

    def offsets(self, mount: np.ndarray, gyro_offset_body: tuple[float, float, float]) -> None:
        """The filter's gyro offset in the vehicle's axes and the mounting (vehicle from chip) it applies."""
        self.gyro_offset_source = (mount, gyro_offset_body)

    # ---- windows ---------------------------------------------------------------------------------------
    def sample(self, t_ns: int, acc_chip: tuple[float, float, float], gyro_chip: tuple[float, float, float]) -> None:
        """One IMU sample on the chip's axes, as read."""
        self.take_kept()
        _, a0, a1, a2, w0, w1, w2, n = self._last
        ax, ay, az = acc_chip
        wx, wy, wz = gyro_chip
        row = self._last = (t_ns, a0 + ax, a1 + ay, a2 + az, w0 + wx, w1 + wy, w2 + wz, n + 1)
        step = t_ns // SUM_STEP_NS
        if step != self._step:
            self._step = step
            self._sums.append(row)

    def sample_block(self, t_ns: np.ndarray, acc_chip: np.ndarray, gyro_chip: np.ndarray) -> None:
        """Samples at once (n x 3 each): the same running sums as :meth:`sample` one by one. Kept until a fix asks
        for the sums (or BLOCKS_KEPT wait), then summed as one block: the same sums (a cumulative sum goes on where
        it stopped), at the cost of one block's numpy calls for the several a run of reads is cut into."""
        if len(t_ns):
            self.keep_block(t_ns, acc_chip, gyro_chip)

    def take_block(self, t_ns: np.ndarray, acc_chip: np.ndarray, gyro_chip: np.ndarray) -> None:
        last = self._last
        run = np.cumsum(np.concatenate((np.array((last[1:7],)), np.concatenate((acc_chip, gyro_chip), axis=1))),
                        axis=0)[1:]
        steps = t_ns // SUM_STEP_NS
        first = np.flatnonzero(diff_from(self._step, steps) != 0)  # each step's first sample
        counts = np.arange(last[7] + 1, last[7] + 1 + len(t_ns))
        self._sums.extend(zip(t_ns[first].tolist(), *run[first].T.tolist(), counts[first].tolist(), strict=True))
        self._step = int(steps[-1])
        self._last = (int(t_ns[-1]), *run[-1].tolist(), int(counts[-1]))

    def _sum_at(self, t_ns: int) -> tuple[float, ...] | None:
        """The running sums at the last sample not after ``t_ns`` (None when it is no longer kept)."""
        self.take_kept()
        sums = self._sums
        if not sums or sums[0][0] > t_ns:
            return None
        lo, hi = 0, len(sums) - 1
        while lo < hi:  # the last entry with time <= t_ns
            mid = (lo + hi + 1) // 2
            if sums[mid][0] <= t_ns:
                lo = mid
            else:
                hi = mid - 1
        return sums[lo]

    def fix(self, t_epoch_ns: int, vel_ned: tuple[float, float, float]) -> None:
        """A GNSS velocity at its epoch (the receiver's Doppler: it owes nothing to the IMU, whose mounting is
        being estimated; the down element may come from the filter when the receiver gives none). Once a window
        of WINDOW_S is complete, its pair goes into the fits if the car was moving."""
        self.take_kept()
        sums = self._sums
        cutoff = t_epoch_ns - SUM_KEEP_NS  # at 20 Hz the sample bound alone would keep seven minutes (2 MB)
        while len(sums) > 1 and sums[1][0] <= cutoff:
            sums.popleft()
        if self._fix0 is None or t_epoch_ns <= self._fix0[0] or t_epoch_ns - self._fix0[0] > 3 * WINDOW_S * 1e9:
            self._fix0 = (t_epoch_ns, vel_ned)
            return
        t0, v0 = self._fix0
        dt = (t_epoch_ns - t0) / 1e9
        if dt < WINDOW_S * 0.999:
            return
        self._fix0 = (t_epoch_ns, vel_ned)
        a, b = self._sum_at(t0), self._sum_at(t_epoch_ns)
        if a is None or b is None or b[7] - a[7] < 2:
            return
        k = b[7] - a[7]
        go = self.gyro_offset.tolist()
        fc = [(b[1] - a[1]) / k, (b[2] - a[2]) / k, (b[3] - a[3]) / k]
        wc = [(b[4] - a[4]) / k - go[0], (b[5] - a[5]) / k - go[1], (b[6] - a[6]) / k - go[2]]
        v1 = vel_ned
        h0, h1 = math.hypot(v0[0], v0[1]), math.hypot(v1[0], v1[1])
        if min(h0, h1) < MIN_SPEED_MPS:
            return
        accel = (h1 - h0) / dt
        turn = math.remainder(math.atan2(v1[1], v1[0]) - math.atan2(v0[1], v0[0]), math.tau) / dt  # FRD yaw rate
        if abs(accel) > MAX_ACCEL_MPS2 or abs(math.degrees(turn)) > MAX_TURN_DPS:
            return
        speed = 0.5 * (h0 + h1)
        theta = math.atan2(-0.5 * (v0[2] + v1[2]), speed)
        g0 = G0
        # The car turns about its own vertical: the chip's rate is that axis, at the gyro's rate (more exact than
        # the course's change between two velocities), turning the way the course turned.
        rate = (math.copysign(math.sqrt(wc[0] * wc[0] + wc[1] * wc[1] + wc[2] * wc[2]), turn)
                if abs(math.degrees(turn)) > MIN_TURN_DPS else 0.0)
        # Forward: the change of speed and the grade; right: the centripetal force of the turn; down: gravity.
        fx, fy, fz = accel + g0 * math.sin(theta), speed * rate, -g0 * math.cos(theta)
        # The turn is about the vertical: on a grade, that axis leans back in the car's axes by the grade.
        wx, wy, wz = -rate * math.sin(theta), 0.0, rate * math.cos(theta)
        # And the body leans out of the turn on its springs (roll = -gradient x lateral acceleration): both are in
        # the body's axes turned by that roll. Left out, the leaning of a drive that turns one way more than the
        # other came out as a mounting roll (1 deg on the simulated urban lap).
        phi = -ROLL_GRADIENT * fy
        c, s_ = math.cos(phi), math.sin(phi)
        fv = [fx, c * fy + s_ * fz, -s_ * fy + c * fz]
        wv = [wx, c * wy + s_ * wz, -s_ * wy + c * wz]
        self._add_window(_window_sums(fc, fv, wc if rate else [0.0, 0.0, 0.0], wv))

    def add(self, f_chip: np.ndarray, f_vehicle: np.ndarray, w_chip: np.ndarray, w_vehicle: np.ndarray) -> None:
        """One window: the chip's mean specific force and rate, and the vehicle's."""
        self._add_window(_window_sums(*(np.asarray(v, float).tolist() for v in (f_chip, f_vehicle, w_chip, w_vehicle))))

    def _add_window(self, window: np.ndarray) -> None:
        self._long.add_sums(window)
        self._recent.add_sums(window)
        self._estimate = None
        self._unchecked += 1
        if (self._unchecked >= MOVED_CHECK_WINDOWS and self._long.n >= MIN_WINDOWS
                and self._recent.n >= 0.5 * RECENT_WINDOWS):
            # Solving both fits costs two SVDs each: once a second it was a tenth of the filter's time at 20 Hz.
            self._unchecked = 0
            if self._moved():
                self.moves += 1
                self._long.copy_from(self._recent)

    def _moved(self) -> bool:
        a, b = self._long.solve(), self._recent.solve()
        if a is None or b is None:
            return False
        angle = math.degrees(float(np.linalg.norm(rotvec_from_dcm(a[0].T @ b[0]))))
        sigma = math.degrees(math.sqrt(float(np.trace(b[1])) + float(np.trace(a[1]))))
        return angle > max(MOVED_DEG, 4.0 * sigma)

    # ---- the estimate ----------------------------------------------------------------------------------
    def estimate(self) -> MountEstimate:
        """The current estimate; the configured mounting (sigma unknown) until the drive has shown enough. Solved
        once per window however often it is asked (the status, /nav/state and the engine each ask)."""
        if self._estimate is None:
            self._estimate = self._solve()
        return self._estimate

    def _solve(self) -> MountEstimate:
        sol = self._long.solve() if self._long.n >= 3 else None
        if sol is None:
            return MountEstimate(self.configured, (math.inf, math.inf, math.inf), int(self._long.n), LEARNING)
        r, cov, _ = sol
        sig = tuple(math.degrees(math.sqrt(max(float(cov[i, i]), 0.0))) for i in range(3))
        if not max(sig[1], sig[2]) < USABLE_SIGMA_DEG:
            # Not even the forward axis yet (the car has hardly sped up or braked): no estimate.
            return MountEstimate(self.configured, (math.inf, math.inf, math.inf), int(self._long.n), LEARNING)
        m = r.T  # vehicle from chip: what the engine applies to a sample (dcm_from_euler(mounting_rpy_deg))
        rpy = tuple(math.degrees(a) for a in euler_from_dcm(m))
        if not sig[0] < USABLE_SIGMA_DEG:
            # A drive without turns tells no roll (the offset takes it): the roll is the guess's, about the forward
            # axis the drive has shown.
            return MountEstimate(rpy, sig, int(self._long.n), FORWARD)
        settled = (self._long.n >= MIN_WINDOWS and max(sig[0], sig[1]) <= SETTLED_TILT_DEG
                   and sig[2] <= SETTLED_YAW_DEG)
        return MountEstimate(rpy, sig, int(self._long.n), SETTLED if settled else LEARNING)


def forward_axis_deg(rpy_a_deg: tuple[float, ...], rpy_b_deg: tuple[float, ...]) -> float:
    """Angle between the car's forward axis on the chip under two mountings (roll about that axis left out)."""
    a, b = mount_matrix(rpy_a_deg)[0], mount_matrix(rpy_b_deg)[0]  # vehicle x on the chip's axes
    return math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b)))))


def mount_matrix(rpy_deg: tuple[float, ...]) -> np.ndarray:
    """Vehicle from chip, as the engine applies ``nav.mounting_rpy_deg``."""
    return dcm_from_euler(*(math.radians(a) for a in rpy_deg))
