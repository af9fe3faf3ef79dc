"""The evidence rules: measurements refused in a row that agree say the filter is off, not the sensor.

The chi-square gate refuses a measurement that disagrees with the filter beyond its covariance. One refusal says
nothing about who is wrong; a run of them that agree with each other (the same few metres off, fix after fix)
does: a scattering receiver in a street canyon does not agree with itself, a filter that drifted away does. Three
rules act on such runs, each with its own thresholds:

- positions (:class:`PositionEvidence`): good fixes refused in a row after a spell without any widen the
  position (a re-anchor); refused for long enough, the filter restarts from the receiver (it lost itself);
- velocities (:class:`VelocityEvidence`): trusted velocities (a stop the OBD confirms, a good receiver's Doppler,
  the OBD speed) refused in a row reopen velocity, attitude and IMU offsets;
- heights (:class:`HeightEvidence`): barometer heights refused in a row widen the height or the barometer's
  offset, whichever the receiver's heights say moved.

:class:`RefusalRun` is the one type that keeps such a run and judges whether it agrees.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from logger.nav.core import FilterCore, PreparedFix
from logger.nav.measurements import GnssPosition, Observation
from logger.nav.state import DH_ID, P_ID, V_ID

NS = 1_000_000_000
REFUSALS_KEPT = 64  # a run of refusals is judged on its latest: a 10 Hz sensor's over 6 s, bounded while they scatter
DIVERGENCE_REJECTS = 10  # consecutive rejected GNSS fixes with a good receiver accuracy...
DIVERGENCE_SPAN_NS = 8 * NS  # ... spanning this long: the filter has lost itself, start again from GNSS
DIVERGENCE_SIGMA_M = 1000.0
GOOD_FIX_H_ACC_M = 10.0  # a fix whose receiver claims better than this can tell a filter that lost itself
REANCHOR_REJECTS = 3  # consecutive refused fixes that agree, from a receiver this sure of itself...
REANCHOR_H_ACC_M = 2.0  # ...make the filter admit its position is less certain than it thought, when they
REANCHOR_AFTER_NS = 5 * NS  # come after this long without an accepted fix (a tunnel) or after worse ones only
VELOCITY_REFUSALS = 3  # trusted velocities (a stop the OBD confirms, a good receiver's, OBD's) refused in a row
VELOCITY_REFUSAL_SPAN_NS = NS  # ... over at least this long, agreeing: the filter's velocity is off, not theirs
BARO_REFUSALS = 5  # barometer heights refused in a row (at least this many)...
BARO_REFUSAL_SPAN_NS = 4 * NS  # ... over at least this long, agreeing: the filter's height is off, not the sensor's
GNSS_ARBITER_NS = 3 * NS  # a good 3D fix this recent can tell a wrong height from a moved barometer offset


def agree(refused: list[tuple[float, ...]]) -> bool:
    """Refused measurements (time, innovation...) whose innovations agree within a quarter of their mean: a
    shifted solution, not a scattering receiver."""
    width = min(len(r) for r in refused)
    inno = np.array([r[1:width] for r in refused])
    mean = inno.mean(axis=0)
    return float(np.linalg.norm(inno - mean, axis=1).max()) < 0.25 * float(np.linalg.norm(mean))


class RefusalRun:
    """Refusals in a row of one kind of measurement: (time, innovation...) each, oldest first.

    ``keep`` bounds the run to its latest refusals (None: the whole run, for a rule that measures from its first).
    """

    __slots__ = ("_items", "keep")

    def __init__(self, keep: int | None = REFUSALS_KEPT) -> None:
        self._items: list[tuple[float, ...]] = []
        self.keep = keep

    def add(self, t_ns: int, innovation: Iterable[float]) -> None:
        self._items.append((t_ns, *innovation))
        if self.keep is not None:
            del self._items[:-self.keep]  # only the latest are judged: bounded while they scatter

    def clear(self) -> None:
        self._items.clear()

    def __len__(self) -> int:
        return len(self._items)

    @property
    def first_ns(self) -> float:
        return self._items[0][0]

    @property
    def latest(self) -> tuple[float, ...]:
        return self._items[-1]

    def span_ns(self, last: int | None = None) -> float:
        """Time from the ``last``-th latest refusal (the first with None) to the latest."""
        return self._items[-1][0] - self._items[-last if last is not None else 0][0]

    def agrees(self, last: int) -> bool:
        """The latest ``last`` refusals agree among themselves."""
        return agree(self._items[-last:])

    def agrees_over(self, at_least: int, span_ns: int) -> bool:
        """At least ``at_least`` refusals over at least ``span_ns``, and the shortest run of the latest that spans
        it agrees: the same judgement whatever the sensor's rate."""
        items = self._items
        if len(items) < at_least or items[-1][0] - items[0][0] < span_ns:
            return False
        k = at_least
        while k < len(items) and items[-1][0] - items[-k][0] < span_ns:
            k += 1
        return agree(items[-k:])


class VelocityEvidence:
    """Trusted velocities refused in a row that agree with each other: reopen the filter's velocity, attitude
    and offsets (counted as ``reopens``) and let the last one in.

    A stop the OBD confirms is zero velocity beyond doubt, and a good receiver's Doppler velocity has no canyon
    bias worth metres per second; when the gate refuses them again and again, the filter's velocity is off by
    more than its covariance admits, and it got there through a tilt or an offset it holds too firmly (a chip
    worse than configured). The same holds for the OBD speed with its non-holonomic rows (innovations in vehicle
    axes: ``body_to_ned`` turns them). Refusing them further would leave it dead reckoning on that error until a
    divergence restart; a canyon's scattered velocities do not agree and do not trigger it. Each source keeps
    its own run of refusals.
    """

    def __init__(self) -> None:
        self.runs: dict[str, RefusalRun] = {}

    def clear(self) -> None:
        self.runs.clear()

    def judge(self, core: FilterCore, obs: Observation, accepted: bool, t_ns: int, trusted: bool,
              body_to_ned: np.ndarray | None = None) -> bool:
        """After the gate's answer on ``obs``: returns whether it went in (now or after a reopening)."""
        rv = self.runs.get(obs.name)
        if rv is None:
            rv = self.runs[obs.name] = RefusalRun()
        if accepted:
            rv.clear()
            return True
        if not trusted:
            return False
        rv.add(t_ns, (float(obs.z[0]), float(obs.z[1])))
        if (len(rv) < VELOCITY_REFUSALS or rv.span_ns(VELOCITY_REFUSALS) < VELOCITY_REFUSAL_SPAN_NS
                or not rv.agrees(VELOCITY_REFUSALS)):
            return False
        ekf = core.ekf
        assert ekf is not None
        zv = obs.z[:3] if body_to_ned is None else body_to_ned @ obs.z[:3]
        z, r = zv.tolist(), obs.r.tolist()
        if body_to_ned is not None:  # the rows' noise, turned the same way (per axis, upper bound)
            r = (np.abs(body_to_ned) @ np.asarray(obs.r[:3])).tolist()
        # The velocity was off by up to this much since the first refusal: so was the position's drift. Added to
        # what the filter held, as the process noise it had missed (correlations kept: the height stays tied to the
        # barometer's offset, which the velocities say nothing about).
        span_s = rv.span_ns() / NS
        ekf.widen(slice(P_ID, V_ID + 3),
                  [(z[i] * span_s) ** 2 if i < len(z) else 0.0 for i in range(3)]
                  + [z[i] ** 2 + r[i] if i < len(z) else 0.0 for i in range(3)])
        core.reopen_attitude_and_offsets()
        core.counters.reopens += 1
        rv.clear()
        return core.apply(obs)


class HeightEvidence:
    """Barometer heights refused in a row that agree (the same few metres off, second after second).

    The filter's height went further off than its covariance admits (a vertical channel dead reckoned on too firm
    a belief), and refusing the sensor would keep it off for the rest of the drive, with every later GNSS fix
    refused on its height as well. Or the barometer's offset moved (a sensor replaced, a pressure port knocked).
    Which of the two is widened (counted as ``reanchors``) before the barometer goes in:
    - the receiver's heights are going in: the filter's height agrees with them, so the offset moved (a street
      canyon's heights left to the barometer count as going in: the filter's height is the one the receiver's last
      heights left it, carried by the barometer and the IMU since, and a sudden disagreement is the offset's);
    - good 3D fixes come but are refused too: both, and the receiver's heights settle which one moved;
    - no receiver: the height, since the offset, which weather moves by centimetres a minute, is the firmer of
      the two (the height follows the barometer until fixes come back).
    The refusals are judged over at least BARO_REFUSALS readings and BARO_REFUSAL_SPAN_NS, whatever the
    barometer's rate.
    """

    def __init__(self) -> None:
        self.run = RefusalRun()

    def judge(self, core: FilterCore, obs: Observation, t_ns: int, last_height_in_ns: int,
              last_good_fix_ns: int) -> bool:
        """Applies ``obs``; returns whether the height went in (now or after a widening)."""
        if core.apply(obs):
            self.run.clear()
            return True
        rb = self.run
        rb.add(t_ns, (float(obs.z[0]),))
        if not rb.agrees_over(BARO_REFUSALS, BARO_REFUSAL_SPAN_NS):
            return False
        ekf = core.ekf
        assert ekf is not None
        grow = float(obs.z[0]) ** 2 + float(obs.r[0])
        receiver_heights_in = t_ns - last_height_in_ns <= GNSS_ARBITER_NS
        if not receiver_heights_in:
            ekf.widen(slice(P_ID + 2, P_ID + 3), [grow])
        if receiver_heights_in or t_ns - last_good_fix_ns <= GNSS_ARBITER_NS:
            ekf.widen(slice(DH_ID, DH_ID + 1), [grow])
        core.counters.reanchors += 1
        rb.clear()
        return core.apply(obs)


class PositionEvidence:
    """Good fixes refused again and again that agree among themselves (the filter, not the receiver, is off), or
    a covariance gone wild: widen the position (a re-anchor) or start again from the receiver (a reset). A street
    canyon's fixes are refused too, but they scatter: they do not trigger it."""

    def __init__(self) -> None:
        # Consecutive refused fixes: time, then N, E (and D) innovation. The whole run: the re-anchor rule
        # measures from its first refusal.
        self.run = RefusalRun(keep=None)

    def judge(self, core: FilterCore, accepted: bool, fix: PreparedFix, innovation: list[float],
              last_pos_ok: tuple[int, float], sigma_max: float) -> str:
        """What the run says after this fix: "" nothing, "reanchor" (position widened and the fix applied: height
        refusals judged against the old height say nothing now), or "reset" (the filter lost itself: the caller
        restarts it from the fix)."""
        rj = self.run
        if accepted:
            rj.clear()
        elif fix.h_acc < GOOD_FIX_H_ACC_M and len(innovation) >= 2:
            # On every axis the fix had (its whole innovation, also the rows left out as uninformative): a height
            # gone off behind a confident covariance is refused as surely as a position off sideways, and only
            # its vertical innovations agree.
            rj.add(fix.t_ns, innovation)
        lost = False
        last_t, last_acc = last_pos_ok
        if (not accepted and REANCHOR_REJECTS <= len(rj) < DIVERGENCE_REJECTS and fix.h_acc <= REANCHOR_H_ACC_M
                and (rj.first_ns - last_t >= REANCHOR_AFTER_NS or last_acc > 2.0 * fix.h_acc)
                and rj.agrees(REANCHOR_REJECTS)):
            # Good fixes after a spell without any (or with worse ones only), all off by the same few metres: the
            # solution drifted further than its covariance says (a long dead reckoning on a speed sensor whose
            # steps do not average out). Admit the uncertainty of the position, counted, and let this fix in;
            # velocity and attitude are kept.
            ekf = core.ekf
            assert ekf is not None
            inno = np.array((*rj.latest[1:], 0.0, 0.0)[:3])
            ekf.widen(slice(P_ID, P_ID + 3), [inno[i] ** 2 + fix.sigma[i] ** 2 for i in range(3)])
            core.counters.reanchors += 1
            snap = core.state_at(fix.t_ns)
            if core.apply(GnssPosition(fix.lat, fix.lon, fix.h, fix.sigma, core.lever, not fix.fix_3d)
                          .observe(snap, snap.dcm(), core.n)):
                rj.clear()
            return "reanchor"
        if len(rj) >= DIVERGENCE_REJECTS and rj.span_ns() >= DIVERGENCE_SPAN_NS:
            lost = rj.agrees(DIVERGENCE_REJECTS)
        if not (lost or not math.isfinite(sigma_max) or sigma_max > DIVERGENCE_SIGMA_M):
            return ""
        return "reset"
