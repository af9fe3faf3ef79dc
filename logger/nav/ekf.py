"""The filter engine: covariance propagation and gated sequential updates of a closed-loop error-state EKF.

The nominal state lives outside (it is corrected after every accepted update and the error estimate goes
back to zero), so this class holds only the covariance and the bookkeeping an operator wants to see:
accepted and rejected updates per type, the last normalised innovations, and covariance repairs.

Covariance hygiene: P is symmetrised after every step, and a diagonal that goes non-positive or non-finite
is repaired and counted (the Joseph form would cost twice as much per update on a one-core board, and in
double precision with a symmetrised P the short form has not needed it: the repair count says so).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from logger.nav.measurements import Observation, chi2_gate
from logger.nav.params import NavParams


@dataclass
class UpdateStats:
    accepted: int = 0
    rejected: int = 0
    last_nis: float = 0.0  # normalised innovation squared of the last update of this type
    last_innovation: list[float] = field(default_factory=list)


class ErrorStateEkf:
    def __init__(self, p0_diag: np.ndarray, gate_probability: float = NavParams.gate_probability) -> None:
        self.n = len(p0_diag)
        self.p = np.diag(np.asarray(p0_diag, float))
        self.gate_probability = gate_probability
        self._gates = {m: chi2_gate(m, gate_probability) for m in range(1, 7)}
        self.stats: dict[str, UpdateStats] = {}
        self.repairs = 0
        self.inflations = 0  # times the covariance was reset (inflate) or widened (widen): the smoother's cuts
        self._work: _Scratch | None = None  # propagate_trapezoid's arrays, made on its first call

    def propagate(self, phi: np.ndarray, qd: np.ndarray) -> None:
        p = phi @ self.p @ phi.T + qd
        self.p = 0.5 * (p + p.T)

    def propagate_trapezoid(self, phi: np.ndarray, half_q: np.ndarray) -> None:
        """:meth:`propagate` with the trapezoidal discrete noise Q_d = (Phi Q Phi^T + Q) dt / 2 of a diagonal Q,
        given as ``half_q`` = Q dt / 2: Phi P Phi^T + Q_d = Phi (P + Q dt / 2) Phi^T + Q dt / 2, one product of
        Phi fewer."""
        w = self._work
        if w is None:
            w = self._work = _Scratch(self.n)
        m, s = w.m, w.s
        np.copyto(m, self.p)
        w.m_diag += half_q
        s = np.dot(np.dot(phi, m, out=w.t), phi.T, out=s)  # np.dot: the same product as @, less dispatch
        w.s_diag += half_q
        # The symmetrised sum into a fresh array: P is handed out (the smoother's epochs keep copies, callers read it).
        p = np.add(s, w.s_t)
        p *= 0.5
        self.p = p

    def gate(self, m: int) -> float:
        g = self._gates.get(m)
        if g is None:
            g = self._gates[m] = chi2_gate(m, self.gate_probability)
        return g

    def update(self, obs: Observation, gated: bool = True) -> np.ndarray | None:
        """Apply one observation; returns the error estimate to feed back, or None when gated out."""
        st = self.stats.get(obs.name)
        if st is None:
            st = self.stats[obs.name] = UpdateStats()
        h, z = obs.h, obs.z
        p0 = self.p
        ph = p0 @ h.T
        s = h @ ph
        m = len(z)
        if m == 1:
            s_inv = np.array(((1.0 / (float(s[0, 0]) + float(obs.r[0])),),))
        else:
            s.ravel()[::m + 1] += obs.r  # the diagonal (s is a fresh contiguous product)
            s_inv = _inverse(s)
            if s_inv is None:
                st.rejected += 1
                return None
        nis = float(z @ s_inv @ z)
        st.last_nis = nis
        st.last_innovation = z.tolist()
        if gated and not nis <= self.gate(m):  # also catches NaN
            st.rejected += 1
            return None
        k = ph @ s_inv
        dx = k @ z
        # P - K S K^T written as P - K (H P): symmetric by construction up to round-off, which the
        # symmetrisation removes; a diagonal that still fails is repaired and counted.
        p = k @ ph.T
        np.subtract(p0, p, out=p)
        p += p.T
        p *= 0.5
        self.p = p
        self._repair()
        st.accepted += 1
        return dx

    def _repair(self) -> None:
        d = self.p.diagonal()
        low = float(d.min())
        if low > 0.0 and math.isfinite(float(d.sum())):
            return
        self.repairs += 1
        bad = ~(np.isfinite(d) & (d > 0.0))
        self.p[bad, :] = 0.0
        self.p[:, bad] = 0.0
        self.p[bad, bad] = 1e-12

    def sigma(self, i: int) -> float:
        return math.sqrt(max(float(self.p[i, i]), 0.0))

    def widen(self, indices: slice, added: list[float]) -> None:
        """Admit more uncertainty in some states than the filter held (an unmodelled error found): add ``added`` to
        their variances as independent process noise, keeping what is known of how they go with the others.

        Unlike :meth:`inflate`, never a gain of information: P + Q >= P. Zeroing the correlations of a state while
        keeping its variance is not a widening; of two states tied by a measurement (the height and the barometer's
        offset, held together by every barometer reading) it makes their sum better known than it was, and the next
        reading of their difference then counts the old values of both as two independent measurements."""
        self.inflations += 1
        idx = range(*indices.indices(self.n))
        for i, v in zip(idx, added, strict=True):
            self.p[i, i] += max(0.0, float(v))

    def inflate(self, indices: slice, variances: np.ndarray) -> None:
        """Forget what is known about some states (a divergence reset): zero their correlations, set P."""
        self.inflations += 1
        self.p[indices, :] = 0.0
        self.p[:, indices] = 0.0
        idx = range(*indices.indices(self.n))
        for i, v in zip(idx, variances, strict=True):
            self.p[i, i] = float(v)


class _Scratch:
    """Preallocated n x n arrays of :meth:`ErrorStateEkf.propagate_trapezoid`, with views of their diagonals and
    of a transpose made once: a numpy call per product instead of an allocation, an index and a view each."""

    def __init__(self, n: int) -> None:
        self.m, self.t, self.s = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
        self.m_diag = self.m.reshape(-1)[::n + 1]
        self.s_diag = self.s.reshape(-1)[::n + 1]
        self.s_t = self.s.T

    def __deepcopy__(self, memo: dict[int, object]) -> _Scratch:
        return _Scratch(self.m.shape[0])  # fresh views on fresh arrays (a copied view would not be one)


def _inverse(s: np.ndarray) -> np.ndarray | None:
    """Inverse of an innovation covariance, None when singular. Most updates have two or three rows, where the
    adjugate in plain floats costs a fifth of ``numpy.linalg.inv``'s checks and dispatch."""
    m = s.shape[0]
    if m == 2:
        a, b, c, d = s.ravel().tolist()
        det = a * d - b * c
        if det == 0.0 or not math.isfinite(det):
            return None
        return np.array(((d / det, -b / det), (-c / det, a / det)))
    if m == 3:
        return inverse3(s)
    try:
        return np.linalg.inv(s)
    except np.linalg.LinAlgError:
        return None


def inverse3(s: np.ndarray | list[float]) -> np.ndarray | None:
    """Inverse of a 3x3 matrix (or its nine elements row by row) by its adjugate in plain floats, None when
    singular."""
    a, b, c, d, e, f, g, h, i = s.ravel().tolist() if isinstance(s, np.ndarray) else s
    ca, cb, cc = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * ca + b * cb + c * cc
    if det == 0.0 or not math.isfinite(det):
        return None
    r = 1.0 / det
    return np.array(((ca * r, (c * h - b * i) * r, (b * f - c * e) * r),
                     (cb * r, (a * i - c * g) * r, (c * d - a * f) * r),
                     (cc * r, (b * g - a * h) * r, (a * e - b * d) * r)))
