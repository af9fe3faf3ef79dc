"""A post-processed GNSS solution (PPK: RTKLIB's ``.pos``) as position updates, joined through GNSS time.

At the office the receiver's raw observations, processed against a base station, give positions to a few
centimetres where the carrier phase's ambiguities are fixed, decimetres where they float, metres where only the
code is left. The filter takes them as it takes the receiver's fixes, with two differences:

- **The join.** A solution epoch carries its GNSS time and nothing else: no arrival. The receiver's fixes
  (``/gnss/fix``, ``gnss_time_ns``) arrive at known instants on the logger's clock, and
  :class:`logger.nav.gnss_time.GnssEpochClock` places each at its epoch (as is while the clock is locked to PPS,
  through the PPS phase or the shortest delay otherwise): that placement, epoch on the logger's clock minus GNSS
  epoch, is the offset between the two time scales. A solution epoch is placed with the offset of the latest
  receiver fix, so both land at the same instant whatever the clock's state, and it goes in as soon as the
  IMU reaches it: at its epoch, not a fix's latency (0.2-0.3 s) later. A forward filter that waited for the
  receiver's fix to arrive kept the rows between the epoch and the arrival on the solution dead reckoned from the
  second before: on the simulated urban drive 3.3-3.9 cm of error per horizontal axis in the 0.3 s after each
  epoch against 2.1-2.4 cm for the rest of the second. Epochs before any receiver fix had a time, or with none
  within :data:`MAP_STALE_S`, wait for the next one; those it would place more than :data:`MAX_LATE_S` behind
  the filter are not used (counted): the solution history reaches back 4 s at most.
- **The noise.** Each quality has its own (:data:`QUALITY_NOISE`). RTKLIB's standard deviations are the
  formal ones of its least squares: a fixed solution says 5-8 mm where its error (multipath on the phase, the
  base's coordinates, antenna phase centres) is 1-2 cm, so every quality has a floor per axis; the full 3x3
  covariance with its cross terms goes in (whitened: the EKF's rows stay independent). Float and code solutions
  carry errors that last (ambiguities converging over tens of seconds, the atmosphere over minutes), which 1 Hz
  epochs taken as white would add up: their variance is widened by (1 + rho) / (1 - rho), rho = exp(-dt / tau),
  as :mod:`logger.nav.gnss_noise` widens a receiver's canyon fixes.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from logger.nav import earth
from logger.nav.core import FilterCore, PreparedFix
from logger.nav.evidence import GOOD_FIX_H_ACC_M, PositionEvidence
from logger.nav.gnss_noise import FixFigures
from logger.nav.inputs import SolutionEpoch
from logger.nav.measurements import GnssPosition, Observation
from logger.nav.policies import LastReadings

NS = 1_000_000_000
MAP_STALE_S = 300.0  # the offset of a receiver fix older than this is not used (a free-running board clock drifts)
MAX_LATE_S = 2.0  # an epoch placed further behind the filter's latest IMU sample than this is not used
MAX_CORR_GAP_S = 10.0  # epochs further apart than this are independent
SOURCE = "solution"  # FixFigures.source of a solution epoch
NEVER = 2**63 - 1
# A solution whose positions lie further than this (median, horizontal) from the receiver's own fixes at the same
# GNSS epochs is not this drive's: another vehicle's of the same day, a mixed-up file. A receiver's single-point
# fixes are metres off a PPK solution (street canyons tens of metres, for minutes, not for a median); fused,
# another vehicle's track passed the time check, the gate refused 826 of its 836 epochs, the filter reset twice onto
# it and its 480 m error replaced the folder's trajectory with exit 0.
FOREIGN_SOLUTION_M = 30.0
# A fix whose receiver said its leap count is not yet the broadcast one (a cold start's first 12.5 min) is compared
# with the solution's epochs this many whole seconds either side too, the nearest kept: it labels its epochs seconds
# off, and at 33 m/s a second is 33 m (GPS-UTC moved 3 s since 2010: sync.pairing.LEAP_UNKNOWN_NS). Other fixes
# are compared at their own epoch only: another car on the same road a second or two behind is another track.
FOREIGN_LABEL_SLACK_S = 3
RESTART_SPEED_SIGMA_MPS = 1.0  # a filter restarted from a solution epoch (which has no velocity) keeps its own


@dataclass(frozen=True, slots=True)
class QualityNoise:
    """What a solution of one quality is worth: a floor per axis on its standard deviations and how long its
    error lasts; ``code``: a code solution, left out on fewer satellites than ``gnss_min_sv`` as the receiver's."""

    name: str
    floor_h_m: float  # per horizontal axis, 1 sigma
    floor_v_m: float
    corr_s: float  # 0: white
    code: bool


# Floors from what such solutions achieve on a moving vehicle against their formal sigmas: a fixed RTK/PPK
# solution 1-2 cm horizontally and about twice that vertically (RTKLIB's own sigmas for it are 5-8 mm); float
# decimetres; DGPS and SBAS a few decimetres to a metre; single point metres. PPP after convergence: a few cm.
QUALITY_NOISE: dict[int, QualityNoise] = {
    1: QualityNoise("fix", 0.015, 0.03, 0.0, False),
    2: QualityNoise("float", 0.10, 0.20, 10.0, False),
    3: QualityNoise("sbas", 0.50, 1.00, 5.0, True),
    4: QualityNoise("dgps", 0.30, 0.60, 5.0, True),
    5: QualityNoise("single", 1.00, 2.00, 5.0, True),
    6: QualityNoise("ppp", 0.05, 0.10, 10.0, False),
}


def solution_covariance(epoch: SolutionEpoch, dt_s: float) -> np.ndarray:
    """The epoch's NED covariance as the filter takes it: floored per axis by its quality, widened for errors
    that last ``corr_s`` when the previous epoch came ``dt_s`` before."""
    q = QUALITY_NOISE[epoch.quality]
    r = np.array(epoch.cov_ned_m2, float)
    for i, floor in enumerate((q.floor_h_m, q.floor_h_m, q.floor_v_m)):
        # Raising a diagonal element keeps a covariance positive definite; the cross terms stay as stated.
        r[i, i] = max(float(r[i, i]), floor * floor)
    if q.corr_s > 0.0 and 0.0 < dt_s < MAX_CORR_GAP_S:
        rho = math.exp(-dt_s / q.corr_s)
        r *= (1.0 + rho) / (1.0 - rho)
    return r


def whitened(obs: Observation, r: np.ndarray) -> Observation:
    """The observation with covariance ``r`` as independent unit-variance rows (z and H through L^-1, R = L L^T),
    the form the EKF takes; a covariance its cross terms leave not positive definite keeps its diagonal only."""
    try:
        chol = np.linalg.cholesky(r)
    except np.linalg.LinAlgError:
        chol = np.diag(np.sqrt(np.diag(r)))
    return Observation(obs.name, np.linalg.solve(chol, obs.z), np.linalg.solve(chol, obs.h), np.ones(len(obs.z)))


class SolutionPolicy:
    """The solution's epochs waiting to be placed, and their position updates once placed."""

    def __init__(self, epochs: Iterable[SolutionEpoch], replace: bool, last: LastReadings,
                 position: PositionEvidence) -> None:
        self.pending: deque[SolutionEpoch] = deque(sorted(epochs, key=lambda e: e.gnss_time_ns))
        self.replace = replace  # the receiver's positions are not used (its velocities are)
        self.last_readings = last
        self.position = position
        self.used: dict[str, int] = {}  # epochs that went to the filter, per quality name
        self.accepted = 0  # ... of which the filter's gate took
        # The epochs by GNSS time (ms), for the receiver's fixes at the same epochs to be compared with: the
        # horizontal distances found (m), to tell another drive's solution (FOREIGN_SOLUTION_M).
        self._at_ms = {round(e.gnss_time_ns / 1e6): (math.radians(e.lat_deg), math.radians(e.lon_deg))
                       for e in self.pending}
        self.receiver_distances_m: list[float] = []
        self.unjoined = 0  # epochs placed too late behind the filter, or with no receiver time near them
        self.before_start = 0  # epochs placed before the filter had started
        self.few_sv = 0  # epochs left out for too few satellites (gnss_min_sv): their figures are not trusted
        self.min_sv = 0  # ... that many at least (the filter's gnss_min_sv), once one was left out
        self.next_ns = NEVER  # where the next pending epoch falls on the logger's clock (NEVER: unknown)
        self._offset: tuple[int, int, int] | None = None  # (sync - GNSS time, mono - sync, at) of the last fix
        self._t_prev_ns: int | None = None

    def map(self, gnss_time_ns: int, t_ns: int, t_mono_ns: int, lat: float | None = None,
            lon: float | None = None, leap_unknown: bool = False) -> None:
        """A receiver fix with a GNSS time was placed at ``t_ns`` (``t_mono_ns``) on the logger's clock; its
        position (rad), where it has one, is compared with the solution's at the same epoch (within
        FOREIGN_LABEL_SLACK_S of it when ``leap_unknown``)."""
        self._offset = (t_ns - gnss_time_ns, t_mono_ns - t_ns, t_ns)
        self._schedule()
        if lat is not None and lon is not None:
            ms = round(gnss_time_ns / 1e6)
            slack = FOREIGN_LABEL_SLACK_S if leap_unknown else 0
            near = [math.hypot(*earth.ned_offset_m(there[0], there[1], 0.0, lat, lon, 0.0)[:2])
                    for k in range(-slack, slack + 1) if (there := self._at_ms.get(ms + 1000 * k)) is not None]
            if near:
                self.receiver_distances_m.append(min(near))

    def foreign(self) -> str | None:
        """Why the solution is not this drive's, when its positions lie a median FOREIGN_SOLUTION_M or more from
        the receiver's fixes at the same epochs; None when they agree (or no epoch is shared)."""
        d = self.receiver_distances_m
        if not d:
            return None
        median = float(np.median(d))
        if median < FOREIGN_SOLUTION_M:
            return None
        return (f"its positions lie a median {median:.0f} m from the receiver's own fixes at the same GNSS epochs "
                f"({len(d)} fixes; over {FOREIGN_SOLUTION_M:g} m: another vehicle's or drive's solution?)")

    def _schedule(self) -> None:
        off = self._offset
        self.next_ns = self.pending[0].gnss_time_ns + off[0] if self.pending and off is not None else NEVER

    def due(self, t_ns: int, start_ns: int) -> list[tuple[SolutionEpoch, int, int]]:
        """The epochs placed at or before ``t_ns`` (the latest IMU sample): (epoch, synchronised and monotonic
        time); those before the filter started (``start_ns``) or too far behind are counted and dropped."""
        off = self._offset
        if off is None or t_ns - off[2] > MAP_STALE_S * NS:
            self.next_ns = NEVER  # until a receiver fix brings a fresh offset
            return []
        out = []
        pend = self.pending
        while pend and pend[0].gnss_time_ns + off[0] <= t_ns:
            ep = pend.popleft()
            t_e = ep.gnss_time_ns + off[0]
            if t_e < start_ns:
                self.before_start += 1
            elif t_ns - t_e > MAX_LATE_S * NS:
                self.unjoined += 1
            else:
                out.append((ep, t_e, t_e + off[1]))
        self._schedule()
        return out

    def update(self, core: FilterCore, ep: SolutionEpoch, t_e: int, t_mono: int) -> tuple[str, PreparedFix | None]:
        """One epoch's position update; returns what the position evidence said ("", "reanchor" or "reset", for
        which the caller restarts the filter from the returned fix)."""
        q = QUALITY_NOISE[ep.quality]
        if q.code and ep.num_sv < core.params.gnss_min_sv:
            core.counters.gnss_few_sv += 1
            self.few_sv += 1
            self.min_sv = core.params.gnss_min_sv
            return "", None
        dt_s = 0.0 if self._t_prev_ns is None else (t_e - self._t_prev_ns) / NS
        self._t_prev_ns = t_e
        r = solution_covariance(ep, dt_s)
        lat, lon = math.radians(ep.lat_deg), math.radians(ep.lon_deg)
        sig = (math.sqrt(r[0, 0]), math.sqrt(r[1, 1]), math.sqrt(r[2, 2]))
        # No velocity: a restart from this epoch keeps the filter's, widened by RESTART_SPEED_SIGMA_MPS.
        fix = PreparedFix(t_e, t_mono, lat, lon, ep.height_m, None, False, sig, RESTART_SPEED_SIGMA_MPS, True,
                          FixFigures(math.hypot(sig[0], sig[1]), sig[2], RESTART_SPEED_SIGMA_MPS, SOURCE, (1.0, 1.0)))
        snap = core.state_at(t_e)
        full = GnssPosition(lat, lon, ep.height_m, (1.0, 1.0, 1.0), core.lever).observe(snap, snap.dcm(), core.n)
        ok = core.apply(whitened(Observation("solution_pos", full.z, full.h, full.r), r))
        self.used[q.name] = self.used.get(q.name, 0) + 1
        last = self.last_readings
        if ok:
            self.accepted += 1
            last.pos_ok = (t_e, fix.h_acc)
            last.height_in_ns = t_e
        if fix.h_acc < GOOD_FIX_H_ACC_M:
            last.good_fix_ns = t_e
        return self.position.judge(core, ok, fix, full.z.tolist(), last.pos_ok, max(core.sigma)), fix
