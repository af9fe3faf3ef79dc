"""GNSS measurement noise from the receiver's own accuracy figures, with its degraded part taken as correlated.

A receiver's accuracy figure (u-blox ``hAcc``, ``vAcc``, ``sAcc``) is the spread of its error, not how long
that error lasts. In open sky its floor is the receiver's own (atmosphere, orbits, code noise); in a street
canyon it grows with multipath and reflected signals, and those last as long as the same facades are in the
way: seconds, many epochs at 1 Hz. A filter that takes such epochs as independent adds their shared error up
instead of averaging it out (ten epochs off by the same 2 m pull as hard as one epoch good to 0.6 m).

So the variance a fix reports is split into the receiver's floor, the lowest it reported recently, and the
excess over it; the excess is multiplied by (1 + rho) / (1 - rho), rho = exp(-dt / tau), the factor by which a
first-order correlated error sampled every dt shrinks more slowly under averaging than a white one
(``gnss_multipath_corr_s`` = tau). In open sky the excess is near zero and the receiver's figure is used as
is; a canyon's fixes count, together, about as much as one fix per correlation time.

The floor itself (atmosphere, orbits) changes over minutes, not between two epochs a tenth of a second apart:
a receiver giving fixes at 5, 10 or 25 Hz does not know the position 10 or 25 times better than at 1 Hz, it
reports the same error more often (its own navigation filter even smooths one epoch into the next). The floor's
variance is therefore multiplied by the fix rate over ``gnss_independent_hz`` (1 Hz by default, what the
figures of a receiver's data sheet are stated at), so a second of fixes weighs what one independent fix does,
whatever the rate.

Receivers that give no accuracy figure at all (an NMEA-only receiver without GST, a u-blox set to RMC and GGA)
are not uninformative: :class:`AccuracyModel` gives them a documented error model (below), and learns from
the fixes' own scatter how good this receiver on this drive is: its positions over minutes (:class:`ScatterLearner`),
its speeds over seconds (:class:`SpeedScatter`), since a reflection spoils a Doppler for as long as it lasts.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

FLOOR_WINDOW = 300  # fixes (5 min at 1 Hz) over which the receiver's floor is the lowest figure it gave
MAX_GAP_S = 10.0  # epochs further apart than this are taken as independent


class RunningMin:
    """Minimum of the last ``window`` values, amortised O(1) (a monotonic queue)."""

    def __init__(self, window: int = FLOOR_WINDOW) -> None:
        self.window = window
        self._q: deque[tuple[int, float]] = deque()
        self._i = 0

    def add(self, value: float) -> float:
        q = self._q
        while q and q[-1][1] >= value:
            q.pop()
        q.append((self._i, value))
        while q[0][0] <= self._i - self.window:
            q.popleft()
        self._i += 1
        return q[0][1]


class UsualFigure:
    """A receiver's usual figure: the ``quantile`` of each second's lowest figure over the last ``window_s`` of
    fixes. Not the lowest: one unusually good figure (a moment of RTK or SBAS) would make every ordinary one look
    several times worse for as long as it is remembered. Per second of fixes, not per fix: a 10 Hz receiver's
    window is as long as a 1 Hz receiver's."""

    def __init__(self, window_s: int = 300, quantile: float = 0.2) -> None:
        self.window_s = window_s
        self.quantile = quantile
        self._seconds: deque[tuple[int, float]] = deque()  # (second, its lowest figure), oldest first
        self._sorted: list[float] = []  # the same figures in order

    def add(self, t_ns: int, value: float) -> float:
        """Takes the figure of a fix at ``t_ns``; returns the usual figure with it."""
        sec = t_ns // 1_000_000_000
        secs, order = self._seconds, self._sorted
        if secs and sec <= secs[-1][0]:  # the same second (or a fix placed a little earlier): its lowest
            if value < secs[-1][1]:
                del order[bisect.bisect_left(order, secs[-1][1])]
                bisect.insort(order, value)
                secs[-1] = (secs[-1][0], value)
        else:
            secs.append((sec, value))
            bisect.insort(order, value)
            while secs[0][0] <= sec - self.window_s:
                del order[bisect.bisect_left(order, secs.popleft()[1])]
        return order[int(self.quantile * (len(order) - 1))]


class CorrelatedGnssNoise:
    """Per-fix variances for position (per axis, from hAcc and vAcc) and velocity (from sAcc)."""

    def __init__(self, corr_s: float, independent_hz: float = 1.0, floor_corr_s: float = 0.0,
                 floor_corr_v_s: float | None = None, floor_corr_speed_s: float | None = None) -> None:
        self.corr_s = corr_s
        self.floor_corr_s = floor_corr_s
        # The vertical's and the speed's floor errors last their own times (None: the horizontal's).
        self.floor_corr_v_s = floor_corr_s if floor_corr_v_s is None else floor_corr_v_s
        self.floor_corr_speed_s = floor_corr_s if floor_corr_speed_s is None else floor_corr_speed_s
        self.independent_s = 1.0 / independent_hz if independent_hz > 0.0 else 0.0
        self._floors = (RunningMin(), RunningMin(), RunningMin())
        self._t_last_ns: int | None = None
        self._dt_last = 0.0
        self.interval_s = 0.0  # the receiver's usual interval between fixes (0 until two have come)

    def factor(self, t_ns: int) -> float:
        """How much more slowly a correlated error averages out than a white one at this fix spacing."""
        last, self._t_last_ns = self._t_last_ns, t_ns
        dt = 0.0 if last is None else (t_ns - last) / 1e9
        self._dt_last = dt
        if 0.0 < dt < MAX_GAP_S:
            # The usual interval, not this one: a fix that came late does not make the next one worth less.
            self.interval_s = dt if self.interval_s == 0.0 else self.interval_s + 0.1 * (dt - self.interval_s)
        if self.corr_s <= 0.0 or not 0.0 < dt < MAX_GAP_S:
            return 1.0
        rho = math.exp(-dt / self.corr_s)
        return (1.0 + rho) / (1.0 - rho)

    def floor_factor(self, corr_s: float | None = None) -> float:
        """How much more slowly the floor's own error (atmosphere, orbits: minutes) averages out than a white one
        at the receiver's usual interval, the error lasting ``corr_s`` (the horizontal's ``floor_corr_s`` unless
        given); 1 when that is 0 (the floor taken as white)."""
        corr = self.floor_corr_s if corr_s is None else corr_s
        if corr <= 0.0 or self.interval_s <= 0.0 or not 0.0 < self._dt_last < MAX_GAP_S:
            return 1.0
        rho = math.exp(-self.interval_s / corr)
        return (1.0 + rho) / (1.0 - rho)

    def rate_factor(self) -> float:
        """The fix rate over the rate of independent fixes: how many epochs report one error (1 at 1 Hz)."""
        if self.interval_s <= 0.0 or not 0.0 < self._dt_last < MAX_GAP_S:
            return 1.0
        return max(1.0, self.independent_s / self.interval_s)

    def sigmas(self, t_ns: int, h_acc: float, v_acc: float, s_acc: float,
               floor_correlated: bool = True, scale: tuple[float, float] = (1.0, 1.0)) -> tuple[float, float, float]:
        """1-sigma horizontal per axis, vertical and speed, with the excess over the floor widened (and the floor
        too, as lasting ``floor_corr_s``, the vertical's ``floor_corr_v_s`` and the speed's ``floor_corr_speed_s``,
        unless ``floor_correlated`` is False).

        ``scale``: the variance scale (horizontal, vertical) learnt of guessed figures, which the figures given here
        do not include. It is this receiver's figures all being that much worse, its floor as well: applied to floor
        and excess alike, and the floor is the lowest unscaled figure. (Kept in the figures, a scale learnt in a
        canyon would read as excess over a floor remembered from before it, and be widened again as multipath for
        as long as that floor is remembered.)"""
        c = self.factor(t_ns)
        rate = self.rate_factor()
        corrs = (self.floor_corr_s, self.floor_corr_v_s, self.floor_corr_speed_s)
        out = []
        for value, floor, k, corr in zip((h_acc, v_acc, s_acc), self._floors, (*scale, 1.0), corrs, strict=True):
            rr = max(rate, self.floor_factor(corr) if floor_correlated else 1.0)
            low = floor.add(value)
            out.append(math.sqrt(k * (rr * low * low + c * (value * value - low * low))))
        return out[0] / math.sqrt(2.0), out[1], out[2]


# ---- receivers without accuracy figures -------------------------------------------------------------------
RECEIVER = "receiver"  # the fix's own figures (UBX hAcc/vAcc/sAcc, NMEA GST, gpsd's eph/epv)
DOP = "dop"  # a DOP (NMEA GSA, NAV-DOP) times a range error
NOMINAL = "nominal"  # nothing from the receiver: the configured nominal figures, scaled by what was learnt
LEARN_TAU_S = 120.0  # the scatter is averaged over this much drive time
LEARN_MIN_S = 30.0  # ... and used once this much has been seen
LEARN_SCALE = (1.0, 25.0)  # the learnt variance stays between the nominal sigma and 5 times it (see below)
PDOP_SPLIT = (0.6, 0.8)  # HDOP and VDOP over PDOP for satellites spread over the sky
BIAS_TAU_S = 10.0  # the guessed fixes' innovations are averaged over this much drive time to see a lasting offset
BIAS_MIN_FIXES = 5  # ... and their mean used once this many went in since it (re)started
SPEED_KNOWN_S = 4.0  # the guessed speeds' scatter is known once it spans this much drive (five fixes at 1 Hz)
LEARN_CLIP = 16.0  # an innovation counts for at most 4 sigma of its prediction (one reflection is not scatter)


@dataclass(frozen=True, slots=True)
class FixFigures:
    """A fix's accuracy (1 sigma: horizontal as hAcc, the 2D RMS; vertical; speed) and where it came from: the
    receiver's or the error model's figures, and the variance scale learnt of this receiver's scatter."""

    h_model: float  # before the learnt scale (the receiver's own figure, or the DOP or nominal model's)
    v_model: float
    s_acc: float
    source: str  # RECEIVER, DOP or NOMINAL
    scale: tuple[float, float]  # learnt variance scale (horizontal, vertical); 1.0 when not learnt
    speed_guessed: bool = False  # s_acc is guessed (nominal, by the DOP or SpeedScatter), not the receiver's

    @property
    def h_acc(self) -> float:
        """The horizontal figure to use, learnt scale included."""
        return self.h_model * math.sqrt(self.scale[0])

    @property
    def v_acc(self) -> float:
        return self.v_model * math.sqrt(self.scale[1])


class ScatterLearner:
    """The variance of a receiver's fixes about the truth, learnt from the filter's innovations (Mehra's rule).

    An innovation z (fix minus the filter's prediction) has E[z^2] = P + R: the filter's own variance plus the
    fix's. Averaged over a couple of minutes, mean(z^2) - mean(P) is this receiver's R on this drive, and its
    ratio to the nominal R is the scale the nominal figures need. Bounded (a nominal model that is wrong by more
    than 5x is a configuration to fix, not something to learn) and clipped per innovation, so a reflection or the
    end of an outage (when P is large, which the subtraction takes out) does not teach it that the receiver is bad.

    It only ever widens the nominal figures. Mehra's rule assumes white errors; a receiver's are correlated over
    seconds to minutes, the filter's prediction follows them, and the innovations then read smaller than the
    errors are (on the simulated 10 Hz fixes with a 20 s correlation it learnt a quarter of the true variance, and
    the filter was inside its 3 sigma half the time). A scatter larger than the nominal figure admits is proof
    that the receiver is worse; a smaller one is not proof that it is better.
    """

    def __init__(self, tau_s: float = LEARN_TAU_S) -> None:
        self.tau_s = tau_s
        self.seen_s = 0.0
        self._z2 = [0.0, 0.0]  # horizontal (per axis), vertical: mean innovation squared
        self._p = [0.0, 0.0]  # mean filter variance
        self._r = [0.0, 0.0]  # mean nominal variance
        self._t_last_ns: int | None = None
        self._n = 0

    def add(self, t_ns: int, z: list[float], p: list[float], r_nominal: list[float], gated: bool = True) -> None:
        """One fix's innovation (N, E[, D], m), the filter's variances and the nominal variances it was given.
        ``gated`` False: a fix too weak to reach the gate, which nothing vetted: it may teach that the scale is
        smaller than learnt, never that it is larger (its innovation counts for at most what the scale predicts)."""
        dt = 0.0 if self._t_last_ns is None else (t_ns - self._t_last_ns) / 1e9
        self._t_last_ns = t_ns
        if not 0.0 <= dt < MAX_GAP_S:
            dt = 0.0
        self.seen_s += dt
        self._n += 1
        # A plain mean while short, then an exponential one over tau of drive time (whatever the fix rate).
        a = max(1.0 / self._n, 1.0 - math.exp(-dt / self.tau_s))
        groups = [(0, 1)] + ([(2,)] if len(z) > 2 else [])
        k = self._current()
        for g, axes in enumerate(groups):
            # Clipped at 4 sigma of what is expected with the scale learnt so far, so that the scale can grow.
            clip = LEARN_CLIP if gated else 1.0
            z2 = sum(min(z[i] ** 2, clip * (p[i] + k[g] * r_nominal[i])) for i in axes) / len(axes)
            pm = sum(p[i] for i in axes) / len(axes)
            rm = sum(r_nominal[i] for i in axes) / len(axes)
            self._z2[g] += a * (z2 - self._z2[g])
            self._p[g] += a * (pm - self._p[g])
            self._r[g] += a * (rm - self._r[g])

    def scale(self) -> tuple[float, float]:
        """Variance scale for the nominal horizontal and vertical figures (1.0 until enough was seen)."""
        if self.seen_s < LEARN_MIN_S:
            return 1.0, 1.0
        return self._current()

    def _current(self) -> tuple[float, float]:
        lo, hi = LEARN_SCALE
        out = []
        for g in range(2):
            if self._r[g] <= 0.0:
                out.append(1.0)
                continue
            out.append(min(hi, max(lo, (self._z2[g] - self._p[g]) / self._r[g])))
        return out[0], out[1]


class DriveMean:
    """Running means of a few quantities over ``tau_s`` of drive time (whatever the fix rate), started again after a
    gap longer than tau, with the count and the span of the samples since then: what the guessed fixes' vertical
    offset and speed scatter are read from. ``plain_start``: a plain mean while short (the first n samples
    weigh 1/n each); otherwise the first sample after a start is the mean and the next ones move it by
    1 - exp(-dt / tau)."""

    def __init__(self, tau_s: float, size: int, plain_start: bool) -> None:
        self.tau_s = tau_s
        self.plain_start = plain_start
        self.mean = [0.0] * size
        self.t_ns: int | None = None  # the last sample's time
        self.start_ns = 0  # the first sample's since the mean (re)started
        self.n = 0  # samples since then

    def add(self, t_ns: int, values: Sequence[float]) -> None:
        dt = 0.0 if self.t_ns is None else max(0.0, (t_ns - self.t_ns) / 1e9)
        if self.t_ns is None or dt > self.tau_s:
            self.n, self.start_ns = 0, t_ns
        self.n += 1
        self.t_ns = t_ns
        a = 1.0 - math.exp(-dt / self.tau_s)
        a = max(1.0 / self.n, a) if self.plain_start else (1.0 if self.n == 1 else a)
        for i, v in enumerate(values):
            self.mean[i] += a * (v - self.mean[i])

    def fade(self, t_ns: int) -> float:
        """How much of the mean stands ``t_ns`` on, with no sample since the last: exp(-elapsed / tau)."""
        assert self.t_ns is not None
        return math.exp(-max(0.0, (t_ns - self.t_ns) / 1e9) / self.tau_s)


class SpeedScatter:
    """The variance of a receiver's speeds about the truth when it gives no speed figure, learnt over seconds from
    the filter's velocity innovations (Mehra's rule, as :class:`ScatterLearner`, per axis north and east).

    The nominal speed figure is an open sky's (``gnss_nominal_s_acc_mps``, a data sheet's 0.05-0.1 m/s). In a
    street canyon a reflected carrier puts a Doppler 0.3-1 m/s off for as long as the reflection lasts, seconds,
    while the receiver says nothing and its DOP barely moves (the simulated NMEA urban drives: 0.2-1.0 m/s errors
    at HDOP 0.8-1.0; elsewhere HDOP 2-5 with speeds good to 0.3 m/s). Taken at 0.1 m/s, such speeds outweighed
    the OBD speed (0.2 m/s) and led the filter 9 m off with a sigma of 1.4 m. So the mean of the innovations
    squared over BIAS_TAU_S, less the filter's own variance, is the speed's variance while it exceeds the nominal
    one. Every innovation counts, refused ones included: the gate refuses exactly the worst speeds, and learning
    from the rest alone would call a receiver good that is half the time off (each is clipped at LEARN_CLIP of
    its prediction, so one reflection is not scatter; a filter off in velocity is pulled back by the OBD speed
    within seconds, and what it taught fades as fast). Used once BIAS_MIN_FIXES went in over SPEED_KNOWN_S since
    it (re)started, a gap longer than BIAS_TAU_S restarting it; it never narrows the nominal figure. Until then
    (the drive's first fixes, the first after an outage) the nominal figure follows the DOP, as a Doppler's error
    does: a receiver reacquiring after the simulated 130 s tunnel at 10 Hz gave a second of speeds 0.6-1.3 m/s
    off from 6-9 satellites (HDOP 2-5), and one of them at the nominal 0.1 m/s moved the position 25 m through the
    outage's position-velocity correlation. Not while it is known: a canyon's DOP of 2-4 came with speeds good to
    0.3 m/s on other simulated drives, and the DOP-scaled figure let them go (urban north RMSE 0.71 -> 1.17 m).
    """

    def __init__(self, tau_s: float = BIAS_TAU_S) -> None:
        # Mean innovation squared north and east, and the filter's variance they were taken against.
        self._m = DriveMean(tau_s, 4, plain_start=True)

    def add(self, t_ns: int, z: list[float], p: list[float], r: float) -> None:
        """One fix's velocity innovation (north, east; m/s), the filter's variances and the speed variance used."""
        self._m.add(t_ns, (min(z[0] * z[0], LEARN_CLIP * (p[0] + r)), min(z[1] * z[1], LEARN_CLIP * (p[1] + r)),
                           p[0], p[1]))

    def known(self, t_ns: int) -> bool:
        """Whether the innovations since it (re)started are enough (BIAS_MIN_FIXES of them over SPEED_KNOWN_S: at
        10 Hz five are half a second of one error), the last within tau of ``t_ns``."""
        m = self._m
        return (m.t_ns is not None and m.n >= BIAS_MIN_FIXES and m.t_ns - m.start_ns >= SPEED_KNOWN_S * 1e9
                and t_ns - m.t_ns <= m.tau_s * 1e9)

    def variance(self, t_ns: int) -> float:
        """The speed variance the recent innovations show (m^2/s^2, the larger axis; 0 until enough were seen),
        fading over tau while no fix comes."""
        m = self._m
        if m.t_ns is None or m.n < BIAS_MIN_FIXES:
            return 0.0
        z2n, z2e, pn, pe = m.mean
        return m.fade(t_ns) * max(0.0, z2n - pn, z2e - pe)


def dops(pdop: float | None, hdop: float | None, vdop: float | None) -> tuple[float | None, float | None]:
    """The HDOP and VDOP to use: the receiver's own where it gives them (a DOP of 0 or less is none), else the split
    of PDOP a sky of satellites spread over it gives (HDOP 0.6, VDOP 0.8 of PDOP, as PDOP^2 = HDOP^2 + VDOP^2)."""
    h = hdop if hdop is not None and hdop > 0.0 else None
    v = vdop if vdop is not None and vdop > 0.0 else None
    if pdop is not None and pdop > 0.0:
        h = h if h is not None else PDOP_SPLIT[0] * pdop
        v = v if v is not None else PDOP_SPLIT[1] * pdop
    return h, v


class AccuracyModel:
    """A fix's accuracy figures, from the receiver when it gives them and from the error model when not.

    In order: the receiver's own figures (UBX hAcc/vAcc/sAcc, NMEA GST's standard deviations, gpsd's eph/epv);
    DOPs (NMEA GSA or GGA, UBX NAV-DOP, gpsd SKY) times ``gnss_uere_m``, the user range error; and with neither, the
    nominal figures ``gnss_nominal_h_acc_m`` / ``gnss_nominal_v_acc_m`` / ``gnss_nominal_s_acc_mps`` (see
    :class:`logger.nav.params.NavParams` for where their defaults come from). By the DOPs' definition the
    horizontal 2D RMS is UERE x HDOP and the vertical sigma UERE x VDOP; a receiver's own HDOP and VDOP are used
    where it gives them (GGA carries an HDOP even where no GSA comes), else the usual split of PDOP (HDOP 0.6,
    VDOP 0.8 of it, :func:`dops`). A missing vertical figure is the horizontal one times the nominal ratio.
    DOP-based and nominal figures are guesses about this receiver, so their variance is scaled by what
    :class:`ScatterLearner` learnt of the fixes' scatter (``gnss_learn_scatter``). A missing speed figure is the
    nominal one, widened to what :class:`SpeedScatter` learnt of the last seconds' speeds.
    """

    def __init__(self, uere_m: float, nominal: tuple[float, float, float], learn: bool) -> None:
        self.uere_m = uere_m
        self.nominal = nominal
        self.learn = learn
        self.learner = ScatterLearner()
        self.speeds = SpeedScatter()
        # The guessed fixes' vertical innovations (m, down) and the filter's vertical variance they were taken against.
        self._offset = DriveMean(BIAS_TAU_S, 2, plain_start=False)

    def figures(self, h_acc: float | None, v_acc: float | None, s_acc: float | None,
                pdop: float | None, hdop: float | None = None, vdop: float | None = None,
                t_ns: int | None = None) -> FixFigures:
        nh, nv, ns = self.nominal
        if h_acc is not None:
            source = RECEIVER
            v = v_acc if v_acc is not None else h_acc * nv / nh
            scale = (1.0, 1.0)
            h = h_acc
        else:
            hd, vd = dops(pdop, hdop, vdop)
            if hd is not None:
                source, h = DOP, self.uere_m * hd
                v = self.uere_m * vd if vd is not None else h * nv / nh
            else:
                source, h, v = NOMINAL, nh, nv
            scale = self.learner.scale() if self.learn else (1.0, 1.0)
            if self.learn and t_ns is not None:
                v = math.sqrt(v * v + self.offset_excess(t_ns))
        if s_acc is not None:
            return FixFigures(h, v, s_acc, source, scale)
        if not self.learn or t_ns is None:
            s = ns
        elif self.speeds.known(t_ns):
            s = math.sqrt(max(ns * ns, self.speeds.variance(t_ns)))
        else:
            # Nothing seen of the speeds' scatter yet (the drive's first fixes, the first after an outage): the
            # geometry is all there is, and a Doppler's error grows with the DOP as a position's does. The nominal
            # figures describe an open sky's DOP (gnss_uere_m x HDOP = nominal hAcc: 0.75 with the defaults).
            hd = dops(pdop, hdop, vdop)[0]
            s = ns * max(1.0, self.uere_m * hd / nh) if hd is not None else ns
        return FixFigures(h, v, s, source, scale, speed_guessed=True)

    def offset_excess(self, t_ns: int) -> float:
        """The variance (m^2) a lasting vertical offset of the recent guessed fixes adds to the next one's figure
        (horizontally the filter's own drift in a canyon reads as the fixes' offset: not done there).

        A DOP knows no multipath: in a street canyon an NMEA receiver's heights ran 10-30 m high for 80 s (the
        simulated urban drive, seed 2) behind a DOP figure of 6-10 m, each fix passing the gate, together moving
        the height 2.4 m with a sigma of 0.8. Their innovations then keep one sign: their mean over BIAS_TAU_S,
        beyond what the filter's own variance explains (after an outage the filter is the one off), is an offset
        the fixes share, and it counts as variance on top of the DOP's. Noise alone leaves the mean small against
        the DOP figure (a fifth of it at 1 Hz), so an open sky's fixes keep their weight; the excess fades with
        the mean once the fixes agree with the filter again, and with time while none come."""
        m = self._offset
        if m.t_ns is None or m.n < BIAS_MIN_FIXES:
            return 0.0  # a mean of a few innovations is one innovation's noise, not an offset
        offset, p = m.mean
        return max(0.0, (m.fade(t_ns) * offset) ** 2 - p)

    def observe_speed(self, t_ns: int, figures: FixFigures, innovation: list[float], p_diag: list[float],
                      r: float) -> None:
        """A running filter's velocity innovation (north, east) of a fix whose speed figure was guessed, with the
        filter's variances before it and the speed variance it was given."""
        if self.learn and figures.speed_guessed:
            self.speeds.add(t_ns, innovation, p_diag, r)

    def observe(self, t_ns: int, figures: FixFigures, innovation: list[float], p_diag: list[float],
                gated: bool = True) -> None:
        """A running filter's innovation of a fix whose figures were guessed: what the learner learns from.
        ``gated`` False: the fix was too weak to reach the gate (:meth:`ScatterLearner.add`)."""
        if not self.learn or figures.source == RECEIVER:
            return
        rh = figures.h_model**2 / 2.0
        rv = figures.v_model**2
        self.learner.add(t_ns, innovation, p_diag, [rh, rh, rv][:len(innovation)], gated)
        if len(innovation) < 3:
            return  # a 2D fix has no height of its own: the vertical mean waits for the next 3D one
        self._offset.add(t_ns, (innovation[2], p_diag[2]))  # after a gap it starts again (DriveMean)
