"""Stop detection: the IMU is still (small variance of specific force and angular rate over the last second)
and, where the vehicle gives one, the OBD speed reads zero.

The variance thresholds adapt to the installation: a car's idling engine shakes the IMU more than the
datasheet noise, and differently in every car. Each stop that the OBD speed confirms teaches the detector
the variance of standing still here (a slow running mean of its logarithm, so one long stop does not
dominate), and the threshold is a fixed factor above it, bounded on both sides.

An IMU far noisier than the configured thresholds (a phone-grade part: its standing car reads 0.03-0.05
(m/s^2)^2 as 20 Hz means, ten times the configured threshold) never reads still, so no stop would ever teach it.
A stop held for HELD_S by the OBD speed at zero, or by fixes whose speed is under GNSS_STANDING_MPS (a car without
an OBD adapter, and the GNSS + IMU mode, which reads none), teaches the detector all the same (:class:`HeldStop`,
:meth:`StopDetector.learn` with ``held``), and lifts the bounds to HELD_CEILING_A / HELD_CEILING_W: a car that has
read 0 km/h, or a few centimetres a second, for that long stands or creeps, so what its IMU shows then is this
installation's standstill. A datasheet-grade IMU reads still well within HELD_S of a stop, and is taught as before.
"""

from __future__ import annotations

import copy
import math
from collections import deque

import numpy as np

from logger.nav.deferred import PENDING_MAX, BlockKeeper, Deferred
from logger.nav.params import NavParams

WINDOW_S = 1.0
WINDOW_NS = int(WINDOW_S * 1e9)
# The detector looks at means over this long (20 Hz, the rate its thresholds were set at): a faster IMU's samples
# are averaged down to it, so that the noise of its wider bandwidth does not read as motion (at 200 Hz a standing
# car's samples varied by 0.006 (m/s^2)^2, over twice the threshold: the start-up never levelled, and the 15-state
# filter, which has no OBD speed to teach the threshold, restarted seven times on the simulated urban drive). The
# number of samples a mean takes is fixed by the first interval between two samples the detector is given.
MEAN_S = 0.05
THRESHOLD_FACTOR = 9.0  # three standard deviations of the standing-still signal, in variance
LEARN_RATE = 0.05
HELD_S = 3.0  # readings that say the car stands (HeldStop) this long: it does, whatever the IMU's variance says
HELD_NS = int(HELD_S * 1e9)
# The learnt thresholds' bound once a held stop taught the detector: (0.7 m/s^2)^2 summed over the axes, about
# what a car pulling away at 1.5 m/s^2 within the one-second window shows, and (3 deg/s)^2.
HELD_CEILING_A = 0.7**2
HELD_CEILING_W = math.radians(3.0) ** 2
# A fix's horizontal speed under this says the car stands. The simulated receiver standing under an open sky reads
# 0.05 m/s (median) and 0.14 m/s (99 %, 123 fixes of outage-60s seed 1); at a stop in a street canyon 0.08 m/s and
# 0.76 m/s (95 %), so such a stop is seldom held by the fixes, which errs on the side of teaching nothing
# (/var/tmp/b43/standspeed.py). Stricter than nav_rerun.STANDING_MPS (0.3 m/s, OBD or fix), which only decides how
# much of a standstill the re-run's tape keeps: this one teaches the stop detector.
GNSS_STANDING_MPS = 0.15


class HeldStop:
    """A run of readings that each say the car stands (an OBD speed of zero, or a fix's speed under
    GNSS_STANDING_MPS), and whether the IMU read still at any of them. The run holds once it has lasted HELD_NS with
    the IMU never still: an IMU noisier than the thresholds, which only such a run can teach. A stop the IMU read
    still in is not one: the car pulling away while the readings still say it stands reads unstill at their end (on
    every simulated urban drive, after 34-60 s of zero: it would have taught the detector the pull-away)."""

    def __init__(self) -> None:
        self.since_ns: int | None = None  # the first reading of the run
        self.still_seen = False

    def end(self) -> None:
        """A reading that says the car moves (or says nothing of it)."""
        self.since_ns = None

    def holds(self, t_ns: int, still: bool) -> bool:
        """A reading at ``t_ns`` that says the car stands, the IMU ``still`` or not then: whether the run holds."""
        if self.since_ns is None:
            self.since_ns, self.still_seen = t_ns, still
        else:
            self.still_seen = self.still_seen or still
        return not self.still_seen and t_ns - self.since_ns >= HELD_NS
RESUM_EVERY = 4096


class _Block:
    """A block of samples in the stop detector's window: their times, their forces and rates (n x 6), and the
    first not yet gone out of the window. Indexed [0] it gives that sample's time, as a sample's tuple does."""

    __slots__ = ("head", "lo", "t", "v")

    def __init__(self, t: np.ndarray, v: np.ndarray) -> None:
        self.t, self.v, self.lo, self.head = t, v, 0, int(t[0])

    def __getitem__(self, i: int) -> int:
        assert i == 0
        return self.head


def _moved_sums(sums: tuple[float, ...], v: np.ndarray, sign: float) -> tuple[float, ...]:
    """The window's twelve sums (per axis, then of squares per axis) with the samples ``v`` (n x 6) added
    (``sign`` 1) or taken out (-1)."""
    return tuple((np.array(sums) + sign * np.concatenate((v.sum(axis=0), (v * v).sum(axis=0)))).tolist())


class StopDetector(Deferred, BlockKeeper):
    def __init__(self, still_accel_mps2: float = NavParams.still_accel_mps2,
                 still_gyro_rps: float = math.radians(0.5)) -> None:
        self.thr_a = still_accel_mps2**2
        self.thr_w = still_gyro_rps**2
        self._ceil_a, self._ceil_w = 4.0 * self.thr_a, 4.0 * self.thr_w
        self._floor_a, self._floor_w = 1e-8, 1e-12
        # The window's samples, oldest first: (t, f x y z, w x y z) one by one, or a block's as a _Block.
        self._win: deque[tuple[int, float, float, float, float, float, float] | _Block] = deque()
        self._n = 0  # samples in the window
        self._sums = (0.0,) * 12  # sum per axis (force x, y, z, rate x, y, z), then sum of squares per axis
        self._var_a = math.inf
        self._var_w = math.inf
        self._dirty = False
        self._adds = 0
        self._pending: list[tuple[int, tuple[float, float, float], tuple[float, float, float]]] = []
        self._blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # blocks not yet taken, oldest first
        self._log_a: float | None = None
        self._log_w: float | None = None
        self.learned = 0
        self.held_learned = 0  # of those, held stops (HeldStop: the OBD speed or the fixes) the IMU never read still in
        self.group = 0  # samples per mean, 0 until the first interval sizes it (taken as 1 meanwhile)
        self._t_first: int | None = None  # the first sample's time, while the group is not sized
        self._carry: list[tuple[int, tuple[float, float, float], tuple[float, float, float]]] = []  # a mean's so far

    def set_interval(self, dt_s: float) -> None:
        """The IMU's sample interval: how many samples make one of the detector's means (MEAN_S). A new count drops
        the samples of the mean under way."""
        group = max(1, round(MEAN_S / dt_s)) if dt_s > 0.0 else 1
        if group != self.group:
            self.group = group
            self._carry = []

    def _lead(self, t_ns: np.ndarray) -> int:
        """How many of these samples come before the group is sized (they go in one by one, as :meth:`add` takes
        them); sizes it on the way."""
        for i, t in enumerate(t_ns.tolist()):
            self._size(t)
            if self.group:
                return i
        return len(t_ns)

    def _size(self, t_ns: int) -> None:
        """Before the sample at ``t_ns`` while the group is not sized: the interval from the first sample sizes it
        (an interval of a window or more says nothing of the rate), whichever way the samples come (one by one,
        blocks, flags asked), so every path groups the same samples."""
        t0 = self._t_first
        if t0 is None:
            self._t_first = t_ns
        elif 0 < t_ns - t0 < WINDOW_NS:
            self.set_interval((t_ns - t0) / 1e9)
        else:
            self._t_first = t_ns

    def _grouped(self, t_ns: np.ndarray, f: np.ndarray, w: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[tuple[int, tuple, tuple]]]:
        """These samples after the mean under way, as means of ``group``: their times (each mean's last sample's),
        forces and rates; for each of these samples the number of means complete with it; and the samples left
        for the next mean."""
        k = self.group
        carry = self._carry
        if carry:
            t_ns = np.concatenate((np.array([c[0] for c in carry], dtype=np.int64), t_ns))
            f = np.concatenate((np.array([c[1] for c in carry], dtype=float), f))
            w = np.concatenate((np.array([c[2] for c in carry], dtype=float), w))
        m = len(t_ns) // k
        means_f = f[:m * k].reshape(m, k, 3).mean(axis=1)
        means_w = w[:m * k].reshape(m, k, 3).mean(axis=1)
        done = np.arange(len(carry) + 1, len(t_ns) + 1) // k  # means complete after each of these samples
        left = list(zip(t_ns[m * k:].tolist(), map(tuple, f[m * k:].tolist()), map(tuple, w[m * k:].tolist()),
                        strict=True))
        return t_ns[k - 1:m * k:k], means_f, means_w, done, left

    def add(self, t_ns: int, f: tuple[float, float, float], w: tuple[float, float, float]) -> None:
        """One sample into the one-second window. Kept until the variances are asked for, then taken in order in one
        loop (running sums: a call per sample cost more than the arithmetic). Of a fast IMU, the means of
        ``group`` samples go in."""
        if self.group == 0:
            self._size(t_ns)
        if self.group > 1:
            carry = self._carry
            carry.append((t_ns, f, w))
            if len(carry) < self.group:
                return
            k = 1.0 / len(carry)
            f = (sum(c[1][0] for c in carry) * k, sum(c[1][1] for c in carry) * k, sum(c[1][2] for c in carry) * k)
            w = (sum(c[2][0] for c in carry) * k, sum(c[2][1] for c in carry) * k, sum(c[2][2] for c in carry) * k)
            self._carry = []
        self.take_kept()
        pending = self._pending
        pending.append((t_ns, f, w))
        self._dirty = True
        if len(pending) >= PENDING_MAX:
            self.flush_pending()

    def take_pending(self, pending: list[tuple[int, tuple[float, float, float], tuple[float, float, float]]]) -> None:
        win = self._win
        a0, a1, a2, a3, a4, a5, b0, b1, b2, b3, b4, b5 = self._sums
        adds = self._adds
        n = self._n
        for t_ns, (fx, fy, fz), (wx, wy, wz) in pending:
            win.append((t_ns, fx, fy, fz, wx, wy, wz))
            n += 1
            a0 += fx
            a1 += fy
            a2 += fz
            a3 += wx
            a4 += wy
            a5 += wz
            b0 += fx * fx
            b1 += fy * fy
            b2 += fz * fz
            b3 += wx * wx
            b4 += wy * wy
            b5 += wz * wz
            limit = t_ns - WINDOW_NS
            while win[0][0] < limit:
                head = win[0]
                if head.__class__ is _Block:
                    self._sums, self._n = (a0, a1, a2, a3, a4, a5, b0, b1, b2, b3, b4, b5), n
                    self._expire_block(head, limit)
                    a0, a1, a2, a3, a4, a5, b0, b1, b2, b3, b4, b5 = self._sums
                    n = self._n
                    continue
                _, ox, oy, oz, ux, uy, uz = win.popleft()
                n -= 1
                a0 -= ox
                a1 -= oy
                a2 -= oz
                a3 -= ux
                a4 -= uy
                a5 -= uz
                b0 -= ox * ox
                b1 -= oy * oy
                b2 -= oz * oz
                b3 -= ux * ux
                b4 -= uy * uy
                b5 -= uz * uz
            adds += 1
            if adds >= RESUM_EVERY:  # running sums lose a little to round-off: start them afresh now and then
                self._n = n
                self._resum()
                a0, a1, a2, a3, a4, a5, b0, b1, b2, b3, b4, b5 = self._sums
                adds = 0
        self._sums = (a0, a1, a2, a3, a4, a5, b0, b1, b2, b3, b4, b5)
        self._adds = adds
        self._n = n

    def _expire_block(self, block: _Block, limit: int) -> None:
        """The samples of a block at the window's old end that are older than ``limit`` leave it (their sums at
        once); the block leaves when none is left."""
        cut = int(np.searchsorted(block.t, limit, side="left"))  # samples before limit: [lo, cut)
        self._sums = _moved_sums(self._sums, block.v[block.lo:cut], -1.0)
        self._n -= cut - block.lo
        if cut >= len(block.t):
            self._win.popleft()
        else:
            block.lo = cut
            block.head = int(block.t[cut])

    def add_block(self, t_ns: np.ndarray, f: np.ndarray, w: np.ndarray) -> None:
        """Samples in time order at once (``f``, ``w``: n x 3): the window and sums :meth:`add` would leave, the
        sums taken with numpy and the block kept whole in the window. Kept until the variances are asked for (a
        moving car with an OBD speed asks none) or BLOCKS_KEPT wait, then taken as one block: most of a block's
        cost is the same whatever its length, and a 1 kHz IMU's run of reads is cut into several by the
        measurements between them."""
        self.flush_pending()
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if self.group == 0 and len(t_ns):
            lead = self._lead(t_ns)
            if lead:
                self._dirty = True
                self.keep_block(t_ns[:lead], f[:lead], w[:lead])
                t_ns, f, w = t_ns[lead:], f[lead:], w[lead:]
        if self.group > 1 and len(t_ns):
            t_ns, f, w, _, self._carry = self._grouped(np.asarray(t_ns, dtype=np.int64), f, w)
        if len(t_ns):
            self._dirty = True
            self.keep_block(t_ns, f, w)

    def take_block(self, t_ns: np.ndarray, f: np.ndarray, w: np.ndarray) -> None:
        fw = np.concatenate((f, w), axis=1)
        self._win.append(_Block(np.asarray(t_ns, dtype=np.int64), fw))
        self._n += len(fw)
        self._sums = _moved_sums(self._sums, fw, 1.0)
        limit = int(t_ns[-1]) - WINDOW_NS
        win = self._win
        while win[0][0] < limit:
            head = win[0]
            if head.__class__ is _Block:
                self._expire_block(head, limit)
                continue
            o = win.popleft()
            self._n -= 1
            sq = [v * v for v in o[1:]]
            self._sums = tuple(a - b for a, b in zip(self._sums, (*o[1:], *sq), strict=True))
        self._dirty = True
        self._adds += len(fw)
        if self._adds >= RESUM_EVERY:
            self._resum()

    def still_flags(self, t_ns: np.ndarray, f: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Whether the vehicle reads still after each of these samples (time order, ``f``, ``w``: n x 3), as
        :attr:`still` would say after each were :meth:`add` ed in turn (to round-off); nothing is added.

        Before the filter starts, the start-up asks after every sample (levelling ends with the first that moves):
        one call per sample cost a 1 kHz IMU 10 us each. Here the window's sums at each sample come from cumulative
        sums of the samples that leave the window during these (its oldest) and of these themselves. Of a fast IMU,
        the word changes with each mean complete (``group``; sized here as :meth:`add_block` would, from the times
        alone)."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if self.group == 0 and len(t_ns):
            # Not sized yet (the first samples): on a copy, as add and add_block would size it and take them.
            probe = copy.deepcopy(self)
            lead = probe._lead(t_ns)
            head = probe._flags(t_ns[:lead], f[:lead], w[:lead]) if lead else np.zeros(0, bool)
            if lead == len(t_ns):
                return head
            if lead:
                probe.keep_block(t_ns[:lead], f[:lead], w[:lead])
                probe._dirty = True
            return np.concatenate((head, probe.still_flags(t_ns[lead:], f[lead:], w[lead:])))
        if self.group > 1:
            tm, fm, wm, done, _ = self._grouped(np.asarray(t_ns, dtype=np.int64), f, w)
            before = self.still
            if not len(tm):
                return np.full(len(done), before)
            flags = self._flags(tm, fm, wm)
            return np.where(done > 0, flags[np.maximum(done - 1, 0)], before)
        return self._flags(t_ns, f, w)

    def _flags(self, t_ns: np.ndarray, f: np.ndarray, w: np.ndarray) -> np.ndarray:
        """:meth:`still_flags` of the window's own entries (samples, or a fast IMU's means)."""
        self.take_kept()
        self.flush_pending()
        t = np.asarray(t_ns, dtype=np.int64)
        n = len(t)
        limit_last = int(t[-1]) - WINDOW_NS
        old_t: list[np.ndarray] = []
        old_v: list[np.ndarray] = []
        for item in self._win:  # oldest first: those that leave before the last of these comes
            if item.__class__ is _Block:
                bt = item.t[item.lo:]
                cut = int(np.searchsorted(bt, limit_last, side="left"))
                old_t.append(bt[:cut])
                old_v.append(item.v[item.lo:item.lo + cut])
                if cut < len(bt):
                    break
            else:
                if item[0] >= limit_last:
                    break
                old_t.append(np.array(item[:1], dtype=np.int64))
                old_v.append(np.array([item[1:]], dtype=float))
        m = sum(len(x) for x in old_t)
        xt = np.concatenate((*old_t, t))
        xv = np.concatenate((*old_v, np.concatenate((f, w), axis=1)))
        c = np.zeros((m + n + 1, 12))
        np.cumsum(np.concatenate((xv, xv * xv), axis=1), axis=0, out=c[1:])
        # The samples that stay in the window through these; if these span more than the window, none do.
        base, n_base = np.array(self._sums) - c[m], self._n - m
        lo = np.searchsorted(xt, t - WINDOW_NS, side="left")  # the first sample in each one's window
        end = np.arange(m + 1, m + n + 1)
        sums = base + c[end] - c[lo]
        count = (n_base + end - lo).astype(float)
        mean = sums[:, :6] / count[:, None]
        var = np.maximum(0.0, sums[:, 6:] / count[:, None] - mean * mean)
        return (count >= 4) & (var[:, :3].sum(axis=1) < self.thr_a) & (var[:, 3:].sum(axis=1) < self.thr_w)

    def _resum(self) -> None:
        self._adds = 0
        rows = [r for r in self._win if r.__class__ is not _Block]
        sums = (tuple(sum(r[i + 1] for r in rows) for i in range(6))
                + tuple(sum(r[i + 1] * r[i + 1] for r in rows) for i in range(6)))
        blocks = [b.v[b.lo:] for b in self._win if b.__class__ is _Block]
        if blocks:
            sums = _moved_sums(sums, np.concatenate(blocks), 1.0)
        self._sums = sums

    def _variances(self) -> None:
        if not self._dirty:
            return
        self._dirty = False
        self.take_kept()  # before the single samples kept: add() takes the blocks first
        self.flush_pending()
        n = self._n
        if n < 4:
            self._var_a = self._var_w = math.inf
            return
        s = self._sums
        var = [max(0.0, s[i + 6] / n - (s[i] / n) ** 2) for i in range(6)]
        self._var_a = var[0] + var[1] + var[2]
        self._var_w = var[3] + var[4] + var[5]

    @property
    def var_a(self) -> float:
        """Sum of the three accelerometer axes' variances over the window, (m/s^2)^2."""
        self._variances()
        return self._var_a

    @property
    def var_w(self) -> float:
        """Sum of the three gyro axes' variances over the window, (rad/s)^2."""
        self._variances()
        return self._var_w

    @property
    def still(self) -> bool:
        return self.var_a < self.thr_a and self.var_w < self.thr_w

    def learn(self, held: bool = False) -> None:
        """Called while the OBD speed confirms a stop: adapt the thresholds to this vehicle's standstill.

        ``held``: a :class:`HeldStop` (the OBD speed, or the fixes, saying the car stands for HELD_S) the IMU never
        read still in by the thresholds so far (a noisier part than configured): taught all the same, within the
        wider bounds from then on."""
        if not (0.0 < self.var_a < math.inf and 0.0 < self.var_w < math.inf):
            return
        if held:
            self._ceil_a = max(self._ceil_a, HELD_CEILING_A)
            self._ceil_w = max(self._ceil_w, HELD_CEILING_W)
            self.held_learned += 1
        la, lw = math.log(self.var_a), math.log(self.var_w)
        if self._log_a is None or self._log_w is None:
            self._log_a, self._log_w = la, lw
        else:
            self._log_a += LEARN_RATE * (la - self._log_a)
            self._log_w += LEARN_RATE * (lw - self._log_w)
        self.learned += 1
        self.thr_a = min(self._ceil_a, max(self._floor_a, THRESHOLD_FACTOR * math.exp(self._log_a)))
        self.thr_w = min(self._ceil_w, max(self._floor_w, THRESHOLD_FACTOR * math.exp(self._log_w)))
