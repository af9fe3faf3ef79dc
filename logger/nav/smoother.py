"""Rauch-Tung-Striebel backward pass for the closed-loop error-state filter (post-processing only).

The forward filter feeds every estimate back, so its error estimate after each epoch is zero and what it
keeps per covariance epoch j is: the transition Phi_j from epoch j-1, the covariances before (P-_j) and after
(P+_j) the updates at j, and the correction dx_j fed back there. The smoothed error e_j of the corrected
solution x+_j then follows backwards from e_M = 0 at the last epoch:

    e-_{j+1} = e_{j+1} + dx_{j+1}          (the same error, relative to the uncorrected solution at j+1)
    A_j      = P+_j Phi_{j+1}^T (P-_{j+1})^-1
    e_j      = A_j e-_{j+1}
    Ps_j     = P+_j + A_j (Ps_{j+1} - P-_{j+1}) A_j^T

Solutions between epochs lie on the mechanization from x+_j to x-_{j+1}; their error is interpolated between
e_j and e-_{j+1} in time. With covariance epochs every quarter second this costs one 17x17 solve per epoch.

The pass above assumes the forward filter's model held. Where it did not, the backward pass can make the
solution worse than the forward one (a restart's jump of a hundred metres spread back over the minute before
it). Two rules keep it from doing so:

- where the filter forgot something (``Epoch.cut``: a restart, a re-anchor, a reopening, a widened height),
  the covariances on either side do not describe one model, so nothing crosses back: the epoch before keeps
  its forward solution and the pass starts again from it, as from the last epoch;
- where the smoothed correction of the position is further from zero than the forward filter's covariance
  admits (its Mahalanobis distance over P+ - Ps beyond the chi-square 99.9 % point, 3 degrees of freedom), the
  backward and forward passes disagree beyond their covariances: the forward solution, the better supported
  (it never used the model the disagreement puts in doubt past that epoch), is kept there and the pass
  starts again from it. Both are counted in a :class:`SmoothingReport`, which ``logger replay`` prints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from logger.nav import earth
from logger.nav.engine import Epoch, TrajectoryRow
from logger.nav.rotations import quat_from_rotvec, quat_mul
from logger.nav.state import P_ID, PHI_ID, V_ID

DISAGREE_CHI2 = 16.27  # chi-square 99.9 % point, 3 degrees of freedom
_POS = slice(P_ID, P_ID + 3)


@dataclass
class SmoothingReport:
    """What the backward pass did: epochs smoothed, and where it kept the forward solution and why."""

    epochs: int = 0
    cuts: int = 0  # epochs where the filter forgot something: nothing crossed back
    disagreements: int = 0  # epochs where the passes disagreed beyond their covariances: forward kept

    def summary(self) -> str:
        if not self.cuts and not self.disagreements:
            return f"smoothed {self.epochs} covariance epochs"
        return (f"smoothed {self.epochs} covariance epochs; kept the forward solution at {self.cuts} where the "
                f"filter restarted or widened and at {self.disagreements} where the backward pass disagreed with "
                "it beyond their covariances")


def smooth_errors(epochs: list[Epoch], p_last: np.ndarray, report: SmoothingReport | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Smoothed errors e_j (M, n), e-_j = e_j + dx_j (M, n), smoothed sigmas (M, n) per epoch, and which epochs
    kept the forward solution (M,)."""
    report = report if report is not None else SmoothingReport()
    report.epochs = len(epochs)
    m = len(epochs)
    n = p_last.shape[0]
    e = np.zeros((m, n))
    e_minus = np.zeros((m, n))
    sig = np.zeros((m, n))
    kept = np.zeros(m, bool)
    ps = p_last.copy()
    dx_last = epochs[-1].dx if epochs[-1].dx is not None else np.zeros(n)
    e_minus[-1] = dx_last
    sig[-1] = np.sqrt(np.maximum(np.diag(ps), 0.0))
    for j in range(m - 2, -1, -1):
        nxt = epochs[j + 1]
        p_plus = epochs[j].p_plus if epochs[j].p_plus is not None else nxt.p_minus
        dx = epochs[j].dx if epochs[j].dx is not None else np.zeros(n)
        keep_forward = nxt.cut or nxt.phi is None
        if keep_forward:
            report.cuts += 1
        else:
            phi = np.asarray(nxt.phi, float)
            try:
                a = np.linalg.solve(nxt.p_minus, phi @ p_plus).T  # P+ Phi^T (P-)^-1, P symmetric
            except np.linalg.LinAlgError:
                a = np.zeros((n, n))
            ej = a @ e_minus[j + 1]
            ps_j = p_plus + a @ (ps - nxt.p_minus) @ a.T
            ps_j = 0.5 * (ps_j + ps_j.T)
            # The smoothed correction against what the forward filter admits of its own error, less what stays.
            c = p_plus[_POS, _POS] - ps_j[_POS, _POS] + np.eye(3) * 1e-9
            d = ej[_POS]
            try:
                keep_forward = float(d @ np.linalg.solve(c, d)) > DISAGREE_CHI2
            except np.linalg.LinAlgError:
                keep_forward = True
            if keep_forward:
                report.disagreements += 1
            else:
                e[j], ps = ej, ps_j
        if keep_forward:  # the forward solution here, and the pass starts again from it
            kept[j] = True
            e[j] = 0.0
            ps = p_plus.copy()
        sig[j] = np.sqrt(np.maximum(np.diag(ps), 0.0))
        e_minus[j] = e[j] + dx
    return e, e_minus, sig, kept


def smooth_rows(rows: list[TrajectoryRow], epochs: list[Epoch], p_last: np.ndarray,
                report: SmoothingReport | None = None) -> list[TrajectoryRow]:
    """The forward rows with the smoothed error removed (same layout as the engine's rows)."""
    if not epochs or not rows:
        return rows
    e, e_minus, sig, kept = smooth_errors(epochs, p_last, report)
    times = np.array([ep.t_ns for ep in epochs], dtype=np.int64)
    m = len(epochs)
    j = np.array([r[10] for r in rows])
    t = np.array([r[0] for r in rows], dtype=np.int64)
    valid = j >= 0
    jj = np.clip(j, 0, m - 1)
    nxt = np.minimum(jj + 1, m - 1)
    span = (times[nxt] - times[jj]).astype(float)
    a = np.where((jj + 1 < m) & (span > 0), (t - times[jj]) / np.where(span > 0, span, 1.0), 0.0)
    # Rows after an epoch that kept the forward solution stay on it until the next epoch: the correction the
    # next epoch's covariance would give them is the one that was not trusted.
    a = np.where(kept[jj], 0.0, np.clip(a, 0.0, 1.0))[:, None]
    err = (1.0 - a) * e[jj] + a * e_minus[nxt]
    # An update on a covariance less than UPDATE_STALE_S old does not open an epoch: the rows of the epoch recorded
    # before it lie on the solution it corrected, so their error is the smoothed one plus its correction (as e- is
    # e plus dx). Without this, the row before an outage's first fix took the whole exit correction as error: 10 m
    # on the simulated NMEA tunnel drive, where the solution was smoothed to 0.1 m on either side of it.
    for i, ep in enumerate(epochs):
        if ep.late and not kept[i]:
            first = int(np.searchsorted(j, i))  # rows follow their epochs in order
            for n_at, dx in ep.late:
                err[first:n_at] += dx
    sg = (1.0 - a) * sig[jj] + a * sig[nxt]
    out = []
    for k, row in enumerate(rows):
        if not valid[k]:
            out.append(row)
            continue
        _, t_mono, lat, lon, h, vn, ve, vd, q, _sig, jr = row
        ek = err[k]
        rm, rn = earth.radii(lat)
        q2 = quat_mul(quat_from_rotvec(float(ek[PHI_ID]), float(ek[PHI_ID + 1]), float(ek[PHI_ID + 2])), q)
        out.append(TrajectoryRow(row[0], t_mono, lat - float(ek[P_ID]) / (rm + h),
                                 lon - float(ek[P_ID + 1]) / ((rn + h) * math.cos(lat)), h + float(ek[P_ID + 2]),
                                 vn - float(ek[V_ID]), ve - float(ek[V_ID + 1]), vd - float(ek[V_ID + 2]), q2,
                                 (float(sg[k, P_ID]), float(sg[k, P_ID + 1]), float(sg[k, P_ID + 2])), jr))
    return out
