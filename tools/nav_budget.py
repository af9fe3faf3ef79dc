"""Where the filter's position uncertainty comes from through a drive's longest GNSS outage: an error budget.

    python tools/nav_budget.py drives/drive_*.mcap [--mode 17|15]

The filter is run over the recording as ``logger replay`` runs it. From the outage's start (its last fix plus
half a second) to its first fix, every covariance step is kept: each propagation (its transition and process
noise), each accepted update (its rows, their noise and the gain the filter used), and any change made outside
both (the offsets' temperature terms, a widening). With those gains held, the covariance is a sum of parts that
each follow the same linear recursion (P = (I - KH) P (I - KH)^T + K R K^T after an update, Phi P Phi^T + Q over a
step): the covariance at the start, split by state group (its cross terms together), each group's process noise,
each measurement row's noise, and the changes from outside. The parts add up to the filter's own covariance (the
report says how closely), and each part's share of the horizontal variance at the outage's end says what made
the position's sigma grow: in the simulated outage-60s drives the OBD speed readings' noise, in the tunnel the
gyro offsets (docs/nav.md).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from logger.nav.engine import NavEngine  # noqa: E402
from logger.nav.params import NavParams  # noqa: E402
from logger.nav.state import BA_ID, BG_ID, DH_ID, P_ID, PHI_ID, RQ_ID, SF_ID, V_ID  # noqa: E402
from logger.recording.records import nav_feeder  # noqa: E402
from logger.recording.topics import GNSS_FIX  # noqa: E402

NS = 1_000_000_000
START_AFTER_NS = NS // 2  # after the outage's last fix: its update is in the starting covariance
GROUPS = {"position": range(P_ID, P_ID + 3), "velocity": range(V_ID, V_ID + 3), "attitude": range(PHI_ID, PHI_ID + 3),
          "accel offset": range(BA_ID, BA_ID + 3), "gyro offset": range(BG_ID, BG_ID + 3), "OBD scale": (SF_ID,),
          "height offset": (DH_ID,), "OBD rounding": (RQ_ID,)}


@dataclass
class Budget:
    """The parts of the covariance at the outage's end (name -> n x n), and what the filter itself held."""

    outage_s: float
    parts: dict[str, np.ndarray]
    p_start: np.ndarray
    p_end: np.ndarray
    counts: dict[str, int] = field(default_factory=dict)

    def total(self) -> np.ndarray:
        return sum(self.parts.values(), np.zeros_like(self.p_end))

    def horizontal_shares(self) -> list[tuple[str, float, float, float]]:
        """(part, share of the horizontal variance, its sigma north, east; negative where the part's variance is),
        largest first."""
        tot = self.total()
        hv = float(tot[0, 0] + tot[1, 1])
        out = []
        for name, c in self.parts.items():
            v = float(c[0, 0] + c[1, 1])
            out.append((name, v / hv if hv > 0 else 0.0, _signed_sqrt(c[0, 0]), _signed_sqrt(c[1, 1])))
        return sorted(out, key=lambda r: -r[1])


def _signed_sqrt(v: float) -> float:
    return math.copysign(math.sqrt(abs(float(v))), float(v))


def _time_ns(msg: dict[str, Any]) -> int:
    t = msg["t_sync_ns"]
    return int(t[0]) if isinstance(t, list) else int(t)


def longest_outage(records: list[tuple[str, dict[str, Any]]]) -> tuple[int, int] | None:
    """(last fix before, first fix after) of the longest interval between fixes with a position, or None."""
    fixes = [_time_ns(m) for topic, m in records
             if topic == GNSS_FIX and m.get("fix_ok", True) and m.get("latitude") is not None]
    if len(fixes) < 2:
        return None
    k = int(np.argmax(np.diff(fixes)))
    return fixes[k], fixes[k + 1]


class _Steps:
    """Records the filter's covariance steps from the moment it is attached (wraps the filter's own methods)."""

    def __init__(self, ekf: Any) -> None:
        self.ekf = ekf
        self.events: list[tuple[Any, ...]] = []
        self.last = ekf.p.copy()
        prop, upd = ekf.propagate_trapezoid, ekf.update

        def propagate_trapezoid(phi: np.ndarray, half_q: np.ndarray) -> None:
            self._outside()
            prop(phi, half_q)
            self.events.append(("propagate", np.array(phi, float), np.array(half_q, float)))
            self.last = ekf.p.copy()

        def update(obs: Any, gated: bool = True) -> Any:
            self._outside()
            p0 = ekf.p.copy()
            dx = upd(obs, gated)
            if dx is not None:
                h, r = np.asarray(obs.h, float), np.asarray(obs.r, float)
                gain = p0 @ h.T @ np.linalg.inv(h @ p0 @ h.T + np.diag(r))
                self.events.append(("update", obs.name, h, r, gain))
            self.last = ekf.p.copy()
            return dx

        ekf.propagate_trapezoid, ekf.update = propagate_trapezoid, update

    def _outside(self) -> None:
        d = self.ekf.p - self.last
        if np.any(d):
            self.events.append(("outside", d))

    def finish(self) -> None:
        self._outside()


def budget(records: Iterable[tuple[str, dict[str, Any]]], params: NavParams,
           span_ns: tuple[int, int] | None = None) -> Budget:
    """The covariance budget over ``span_ns`` (default: the records' longest outage, from half a second after its
    last fix to its first fix)."""
    recs = list(records)
    span = span_ns or longest_outage(recs)
    if span is None:
        raise SystemExit("nav_budget: the drive has fewer than two fixes with a position: no outage to explain")
    t_a, t_b = span
    engine = NavEngine(params)
    feed = nav_feeder(engine)
    steps: _Steps | None = None
    p_start = None
    for topic, msg in recs:
        t = _time_ns(msg)
        if t >= t_b and topic == GNSS_FIX:
            break
        if steps is None and t > t_a + START_AFTER_NS and engine.ekf is not None:
            p_start = engine.ekf.p.copy()
            steps = _Steps(engine.ekf)
        handler = feed.get(topic)
        if handler is not None:
            handler(msg)
    if steps is None or p_start is None or engine.ekf is None:
        raise SystemExit("nav_budget: the filter was not running when the outage began")
    steps.finish()
    return Budget((t_b - t_a) / NS, _parts(p_start, steps.events), p_start, engine.ekf.p.copy(),
                  _counts(steps.events))


def _counts(events: list[tuple[Any, ...]]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for e in events:
        key = e[1] if e[0] == "update" else e[0]
        counts[key] = counts.get(key, 0) + 1
    return counts


def _parts(p_start: np.ndarray, events: list[tuple[Any, ...]]) -> dict[str, np.ndarray]:
    n = p_start.shape[0]
    groups = {g: list(r) for g, r in GROUPS.items() if max(r) < n}
    parts: dict[str, np.ndarray] = {}
    block = np.zeros((n, n), bool)
    for g, idx in groups.items():
        c = np.zeros((n, n))
        c[np.ix_(idx, idx)] = p_start[np.ix_(idx, idx)]
        parts[f"start: {g}"] = c
        block[np.ix_(idx, idx)] = True
    parts["start: cross terms"] = np.where(block, 0.0, p_start)
    for g in groups:
        parts[f"process noise: {g}"] = np.zeros((n, n))
    parts["changes outside the steps"] = np.zeros((n, n))
    for e in events:
        if e[0] == "propagate":
            phi, half_q = e[1], e[2]
            for name in parts:
                parts[name] = phi @ parts[name] @ phi.T
            for g, idx in groups.items():
                q = np.zeros(n)
                q[idx] = half_q[idx]
                parts[f"process noise: {g}"] += (phi * q) @ phi.T + np.diag(q)  # as propagate_trapezoid adds it
        elif e[0] == "update":
            _, obs_name, h, r, gain = e
            a = np.eye(n) - gain @ h
            for name in parts:
                parts[name] = a @ parts[name] @ a.T
            for i in range(len(r)):
                key = f"noise: {obs_name} row {i}"
                parts[key] = parts.get(key, np.zeros((n, n))) + r[i] * np.outer(gain[:, i], gain[:, i])
        else:
            parts["changes outside the steps"] += e[1]
    return parts


def render(b: Budget) -> list[str]:
    tot = b.total()
    lines = [f"outage {b.outage_s:.1f} s; " + ", ".join(f"{k} {v}" for k, v in sorted(b.counts.items())),
             f"position sigma at its end: filter N {math.sqrt(b.p_end[0, 0]):.2f} E {math.sqrt(b.p_end[1, 1]):.2f} m, "
             f"sum of the parts N {math.sqrt(max(tot[0, 0], 0.0)):.2f} E {math.sqrt(max(tot[1, 1], 0.0)):.2f} m "
             f"(largest difference of any element {float(np.abs(tot - b.p_end).max()):.1e})",
             "| part | share of the horizontal variance | sigma N, m | sigma E, m |", "| --- | --- | --- | --- |"]
    lines += [f"| {name} | {share * 100:.1f} % | {sn:.2f} | {se:.2f} |"
              for name, share, sn, se in b.horizontal_shares() if abs(share) >= 0.001]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", type=Path, help="the drive's MCAP files (or its folder)")
    ap.add_argument("--mode", default="17", choices=("17", "15"), help="the filter's mode (default 17)")
    args = ap.parse_args(argv)
    from logger.exports.trajectory import read_drive
    from logger.recording.drive import DriveFileError, drive_paths

    try:
        files = drive_paths(args.files)
    except DriveFileError as exc:
        raise SystemExit(f"nav_budget: {exc}") from None
    params = NavParams()
    params.mode = args.mode
    print("\n".join(render(budget(read_drive(files, runs=True), params))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
