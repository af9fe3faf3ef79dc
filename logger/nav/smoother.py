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
  backward and forward passes disagree beyond their covariances. Before the forward solution is taken for the
  better supported, the pass looks back (up to LOOKBACK_NS) for an update the rest of the drive refuses: a fix
  taken whole by a forward pass wide open after an outage leaves the forward solution off, and over-confident,
  until later fixes pull it back; keeping it would carry the fix back into the outage. Where such an update is
  found (the smoothed solution moves by more without it than its information admits, and without it the forward
  prior agrees), the epochs from it to the disagreement, and those of the LOOKBACK_NS after the disagreement,
  which the forward pass still pulled towards it, are smoothed without it (:func:`_explain`). Otherwise
  the forward solution (it never used the model the disagreement puts in doubt past that epoch) is kept there
  and the pass starts again from it. All three are counted in a :class:`SmoothingReport`, which ``logger
  replay`` prints.

The smoothed covariance assumes the two passes' information independent: Ps^-1 = P+^-1 + Pb^-1, with Pb the
backward pass's covariance (every measurement after the epoch). A receiver's slow error (a minute of the same
few decimetres, more in a canyon) is in both: the fixes before an epoch and those after it share it, and Ps
halves a variance that the shared error does not let shrink (on simulated drives the smoothed position was
within 3 sigma only 83-95 % of the time on one axis, the forward one 99-100 %). So the sigmas the rows carry are
no smaller than the error of a fusion of two passes fully correlated on that axis: w sigma_f + (1 - w) sigma_b,
w = sigma_b^2 / (sigma_f^2 + sigma_b^2), the weights the fusion gives them (:func:`_fused_sigma`). Where the
backward pass knows nothing (the last epoch, a kept forward solution) that is the forward sigma; in an outage
(the passes' fixes a minute apart, nearly independent) it is pessimistic, the forward and backward sigmas being
about equal there. Never more than the forward sigma, though: the smoothed solution is never less sure than the
forward one it corrects, whose sigma holds by itself. The smoothed solution itself is unchanged.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from logger.nav import earth
from logger.nav.engine import Epoch, TrajectoryRow
from logger.nav.rotations import quat_from_rotvec, quat_mul
from logger.nav.state import P_ID, PHI_ID, V_ID

DISAGREE_CHI2 = 16.27  # chi-square 99.9 % point, 3 degrees of freedom
LOOKBACK_NS = 30 * 1_000_000_000  # how far before a disagreement the update it comes from is looked for
_POS = slice(P_ID, P_ID + 3)


@dataclass
class SmoothingReport:
    """What the backward pass did: epochs smoothed, and where it kept the forward solution and why."""

    epochs: int = 0
    cuts: int = 0  # epochs where the filter forgot something: nothing crossed back
    disagreements: int = 0  # epochs where the passes disagreed beyond their covariances: forward kept
    refused: int = 0  # epochs whose own updates the rest disagreed with: smoothed without them

    def summary(self) -> str:
        text = f"smoothed {self.epochs} covariance epochs"
        if self.cuts or self.disagreements:
            text += (f"; kept the forward solution at {self.cuts} where the filter restarted or widened and at "
                     f"{self.disagreements} where the backward pass disagreed with it beyond their covariances")
        if self.refused:
            text += (f"; smoothed without {self.refused} epochs' updates (a fix the forward pass took) that the rest "
                     "of the drive contradicted beyond their covariances")
        return text


def smooth_errors(epochs: list[Epoch], p_last: np.ndarray, report: SmoothingReport | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Smoothed errors e_j (M, n), e-_j = e_j + dx_j (M, n), smoothed sigmas (M, n) per epoch, and which epochs
    kept the forward solution (M,)."""
    report = report if report is not None else SmoothingReport()
    report.epochs = len(epochs)
    m = len(epochs)
    n = p_last.shape[0]
    zero = np.zeros(n)
    e = np.zeros((m, n))
    e_minus = np.zeros((m, n))
    sig = np.zeros((m, n))
    kept = np.zeros(m, bool)
    ps = p_last.copy()
    e_minus[-1] = _dx(epochs[-1], zero)
    sig[-1] = _fused_sigma(ps, p_last)
    # The epochs smoothed last (up to LOOKBACK_NS after the current one, latest first) with their smoothed
    # covariances and gains: an update refused further back still pulls them through the forward pass, and its
    # information is taken out of them too (_spread). Emptied where the chain of gains breaks; after a refusal, the
    # epochs it smoothed again (a second refusal within the window reaches past the first: the gains there are the
    # forward pass's, which took the first, so that is close, not exact).
    recent: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = deque()
    j = m - 2
    while j >= 0:
        while recent and epochs[recent[0][0]].t_ns - epochs[j].t_ns > LOOKBACK_NS:
            recent.popleft()
        step = _back(epochs, j, e_minus[j + 1], ps)
        if step is None:
            report.cuts += 1
        elif _disagree(step[0], step[1], _p_plus(epochs, j)):
            explained = _explain(epochs, j, step, recent)
            if explained is not None:  # an update before it that the rest refuses: smoothed without it
                report.refused += 1
                for i, ei, psi, _ in explained:
                    e[i], ps = ei, psi
                    sig[i] = _fused_sigma(ps, _p_plus(epochs, i))
                    e_minus[i] = ei + _dx(epochs[i], zero)
                j = explained[-1][0] - 1
                recent = deque(explained)
                continue
            report.disagreements += 1
            step = None
        if step is None:  # the forward solution here, and the pass starts again from it
            kept[j] = True
            e[j] = 0.0
            ps = _p_plus(epochs, j).copy()
            recent.clear()
        else:
            e[j], ps = step[0], step[1]
            recent.append((j, step[0], ps, step[2]))
        sig[j] = _fused_sigma(ps, _p_plus(epochs, j))
        e_minus[j] = e[j] + _dx(epochs[j], zero)
        j -= 1
    return e, e_minus, sig, kept


def _fused_sigma(ps: np.ndarray, p_plus: np.ndarray) -> np.ndarray:
    """Per state, the larger of the smoothed sigma and that of the two passes' fusion were they fully correlated
    on that state: w sigma_f + (1 - w) sigma_b with w = sigma_b^2 / (sigma_f^2 + sigma_b^2), the backward pass's
    covariance from its information Ps^-1 - P+^-1 (computed on the forward covariance's scale; a direction it
    does not inform has no backward variance: the forward sigma then)."""
    d = np.maximum(np.diag(p_plus), 1e-30)
    sig_s = np.sqrt(np.maximum(np.diag(ps), 0.0))
    sig_f = np.sqrt(d)
    s = 1.0 / sig_f
    sc = s[:, None] * s[None, :]
    try:
        info = np.linalg.inv(ps * sc) - np.linalg.inv(p_plus * sc)
        lam, v = np.linalg.eigh(0.5 * (info + info.T))
    except np.linalg.LinAlgError:
        return sig_s
    # Backward variance per state (scaled): sum over the information's directions of v^2 / lambda; a direction
    # without information (lambda not above round-off) makes it infinite.
    floor = 1e-9 * max(float(lam.max()), 1.0)
    informed = lam > floor
    var_b = (v[:, informed] ** 2 / lam[informed]).sum(axis=1)
    var_b = np.where((v[:, ~informed] ** 2).sum(axis=1) > 1e-6, np.inf, var_b) / (s * s)
    with np.errstate(invalid="ignore", over="ignore"):
        sig_b = np.sqrt(var_b)
        w = np.where(np.isinf(var_b), 1.0, var_b / (d + var_b))
        fused = w * sig_f + np.where(w < 1.0, (1.0 - w) * sig_b, 0.0)
    return np.maximum(sig_s, np.minimum(np.nan_to_num(fused, nan=0.0), sig_f))


def _dx(ep: Epoch, zero: np.ndarray) -> np.ndarray:
    return ep.dx if ep.dx is not None else zero


def _p_plus(epochs: list[Epoch], j: int) -> np.ndarray:
    p = epochs[j].p_plus
    return p if p is not None else epochs[j + 1].p_minus


def _back(epochs: list[Epoch], j: int, e_minus_next: np.ndarray, ps_next: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """One step of the backward pass, from epoch j+1 to j: e_j, Ps_j and the gain A_j; None where nothing crosses
    back (a cut)."""
    nxt = epochs[j + 1]
    if nxt.cut or nxt.phi is None:
        return None
    p_plus = _p_plus(epochs, j)
    n = p_plus.shape[0]
    try:
        a = np.linalg.solve(nxt.p_minus, np.asarray(nxt.phi, float) @ p_plus).T  # P+ Phi^T (P-)^-1, P symmetric
    except np.linalg.LinAlgError:
        a = np.zeros((n, n))
    ps_j = p_plus + a @ (ps_next - nxt.p_minus) @ a.T
    return a @ e_minus_next, 0.5 * (ps_j + ps_j.T), a


def _explain(epochs: list[Epoch], j: int, step: tuple[np.ndarray, np.ndarray, np.ndarray],
             after: Sequence[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = ()
             ) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] | None:
    """Where the passes disagree at epoch j: an update at j or up to LOOKBACK_NS before it that the rest of the
    drive refuses, and the smoothed errors and covariances (with the gains) from j back to it without it, and of
    the epochs ``after`` j (smoothed already, latest first, with their gains) too; None if there is none.

    A fix taken whole by a forward pass wide open after an outage leaves the forward solution off by more than its
    covariance, now small, admits, until later fixes pull it back: the passes disagree there, seconds after the
    fix. Keeping the forward solution there would carry the fix back into the outage; the fix, not the forward
    pass's model, is what the rest of the drive contradicts. An update is refused where (1) the smoothed solution
    moves by more without it than its information admits (the deleted-residual test, position, DISAGREE_CHI2) and
    (2) without it the forward prior agrees with the rest. The epochs between it and j are then smoothed without
    it too: their change is the refused epoch's through the smoothed cross-covariance, Ps_i (A_r ... A_{i-1})^T
    Ps_r^-1 (the updates' likelihood depends on that epoch's state only)."""
    zero = np.zeros(step[0].shape[0])
    t_j = epochs[j].t_ns
    out: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
    i, (ei, psi, ai) = j, step
    while True:
        ep = epochs[i]
        dx = _dx(ep, zero)
        if dx.any():
            without = _without_update(ei, psi, _p_plus(epochs, i), ep.p_minus, dx)
            if (without is not None and _disagree(ei - without[0], psi, without[1])
                    and not _disagree(without[0] + dx, without[1], ep.p_minus)):
                return _spread([*after, *out], i, ei, psi, ai, *without)
        out.append((i, ei, psi, ai))
        if i == 0 or t_j - epochs[i].t_ns > LOOKBACK_NS:
            return None
        prev = _back(epochs, i - 1, ei + dx, psi)
        if prev is None:
            return None
        i, (ei, psi, ai) = i - 1, prev


def _spread(later: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]], r: int, er: np.ndarray, psr: np.ndarray,
            ar: np.ndarray, er_without: np.ndarray, psr_without: np.ndarray
            ) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """The refused epoch r and the epochs after it (``later``: latest first, with their gains A_i) without r's
    updates, latest first, with their gains."""
    res = [(r, er_without, psr_without, ar)]
    try:
        inv = np.linalg.inv(psr)
    except np.linalg.LinAlgError:
        return [*later, *res]
    v = inv @ (er_without - er)
    d = inv @ (psr_without - psr) @ inv
    w = np.eye(len(er))
    a_prev = ar
    for i, ei, psi, ai in reversed(later):
        w = a_prev.T @ w  # (A_r ... A_{i-1})^T
        c = psi @ w  # the smoothed cross-covariance of epochs i and r
        ps_new = psi + c @ d @ c.T
        res.append((i, ei + c @ v, 0.5 * (ps_new + ps_new.T), ai))
        a_prev = ai
    return list(reversed(res))


def _disagree(e: np.ndarray, ps: np.ndarray, p: np.ndarray) -> bool:
    """Whether a smoothed correction ``e`` of a forward solution with covariance ``p`` lies beyond what that
    covariance admits of its own error, less what stays (``ps``): position, chi-square at DISAGREE_CHI2."""
    c = p[_POS, _POS] - ps[_POS, _POS] + np.eye(3) * 1e-9
    d = e[_POS]
    try:
        return float(d @ np.linalg.solve(c, d)) > DISAGREE_CHI2
    except np.linalg.LinAlgError:
        return True


def _without_update(e: np.ndarray, ps: np.ndarray, p_plus: np.ndarray, p_minus: np.ndarray, dx: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """The smoothed error and covariance at an epoch with the information of its own updates taken out.

    All three are Gaussians over the error of the corrected solution x+: the smoothed one N(e, Ps) (every
    measurement), the forward filter's N(0, P+) (those up to this epoch) and its prior N(-dx, P-) (those before
    it). The updates' likelihood is the forward posterior over the prior, so without them the information is
    Ps^-1 - P+^-1 + P-^-1 and its mean follows from Ps^-1 e - P-^-1 dx. Computed on the prior's scale (its
    states differ by ten orders of magnitude); None where that is not a covariance."""
    s = 1.0 / np.sqrt(np.maximum(np.diag(p_minus), 1e-30))
    sc = s[:, None] * s[None, :]
    try:
        i_s, i_p, i_m = (np.linalg.inv(m / sc) for m in (ps, p_plus, p_minus))
        info = i_s - i_p + i_m
        info = 0.5 * (info + info.T)
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    cov = 0.5 * (cov + cov.T)
    if not np.all(np.isfinite(cov)) or np.diag(cov).min() <= 0.0:
        return None
    mean = cov @ (i_s @ (e / s) - i_m @ (dx / s))
    return mean * s, cov * sc


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
        _, t_mono, lat, lon, h, vn, ve, vd, q, sig_f, jr = row
        ek = err[k]
        rm, rn = earth.radii(lat)
        q2 = quat_mul(quat_from_rotvec(float(ek[PHI_ID]), float(ek[PHI_ID + 1]), float(ek[PHI_ID + 2])), q)
        out.append(TrajectoryRow(row[0], t_mono, lat - float(ek[P_ID]) / (rm + h),
                                 lon - float(ek[P_ID + 1]) / ((rn + h) * math.cos(lat)), h + float(ek[P_ID + 2]),
                                 vn - float(ek[V_ID]), ve - float(ek[V_ID + 1]), vd - float(ek[V_ID + 2]), q2,
                                 # never less sure than the forward row (its sigma as of its epoch: between
                                 # two epochs the smoothed one is interpolated towards the next)
                                 (min(float(sg[k, P_ID]), sig_f[0]), min(float(sg[k, P_ID + 1]), sig_f[1]),
                                  min(float(sg[k, P_ID + 2]), sig_f[2])), jr))
    return out
