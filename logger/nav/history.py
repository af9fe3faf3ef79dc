"""The solution at each recent IMU sample, so a measurement that arrives late is judged at its own instant.

A GNSS fix reaches the filter some hundreds of ms after its epoch (and the OBD speed belongs to the moment the
ECU sampled it), while the solution has moved on. The history keeps the nominal solution of the last few seconds
of IMU samples together with the corrections fed back up to each, so the solution at a past instant is the one
of that time, corrected for every feedback since and carried to the instant on its velocity.
"""

from __future__ import annotations

from collections import deque

from logger.nav import earth
from logger.nav.state import NavState

NS = 1_000_000_000
HISTORY_SAMPLES = 4096  # 4 s at 1 kHz: late fixes arrive within 1 s


class SolutionHistory:
    """(time, lat, lon, h, vn, ve, vd, q, corrections so far) per IMU sample, oldest first."""

    __slots__ = ("corr", "entries")

    def __init__(self, samples: int = HISTORY_SAMPLES) -> None:
        self.entries: deque[tuple[object, ...]] = deque(maxlen=samples)
        self.corr: tuple[float, ...] = (0.0,) * 6  # position (NED m) and velocity fed back so far

    def add(self, t_ns: int, s: NavState) -> None:
        self.entries.append((t_ns, s.lat, s.lon, s.h, s.vn, s.ve, s.vd, s.q, self.corr))

    def fed_back(self, d: list[float]) -> None:
        """A correction of position and velocity (the first six error states) went into the nominal state."""
        c = self.corr
        self.corr = (c[0] + d[0], c[1] + d[1], c[2] + d[2], c[3] + d[3], c[4] + d[4], c[5] + d[5])

    def clear(self) -> None:
        self.entries.clear()
        self.corr = (0.0,) * 6

    def state_at(self, t_ns: int, current: NavState) -> NavState:
        """The solution at ``t_ns``: the newest entry not after it (or the oldest), corrected and carried on."""
        entry = None
        for e in reversed(self.entries):
            if e[0] <= t_ns:
                entry = e
                break
        if entry is None:
            entry = self.entries[0] if self.entries else None
        out = current.copy()
        if entry is None:
            return out
        t_e, lat, lon, h, vn, ve, vd, q, corr = entry
        c = self.corr
        d = [c[i] - corr[i] for i in range(6)]
        vn, ve, vd = vn - d[3], ve - d[4], vd - d[5]
        dt = (t_ns - t_e) / NS
        lat, lon, h = earth.offset_llh(lat, lon, h, -d[0] + vn * dt, -d[1] + ve * dt, -d[2] + vd * dt)
        out.lat, out.lon, out.h, out.vn, out.ve, out.vd, out.q = lat, lon, h, vn, ve, vd, q
        return out
