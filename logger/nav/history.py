"""The solution at each recent IMU sample, so a measurement that arrives late is judged at its own instant.

A GNSS fix reaches the filter some hundreds of ms after its epoch (and the OBD speed belongs to the moment the
ECU sampled it), while the solution has moved on. The history keeps the nominal solution of the last few seconds
of IMU samples together with the corrections fed back up to each, so the solution at a past instant is the one
of that time, corrected for every feedback since and interpolated to the instant between the entries around it.
"""

from __future__ import annotations

from collections import deque

from logger.nav import earth
from logger.nav.state import NavState

NS = 1_000_000_000
HISTORY_SAMPLES = 4096  # at most: 4 s of a 1 kHz IMU integrated per sample
HISTORY_S = 10.0  # and no older than this: fixes arrive within 1 s of their epoch, OBD speeds sooner


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

    def trim(self, newest_ns: int) -> None:
        """Forget entries more than HISTORY_S before ``newest_ns``: at 20 Hz the sample bound alone would keep
        three minutes (1.8 MB) that no late measurement asks for."""
        entries = self.entries
        cutoff = newest_ns - int(HISTORY_S * NS)
        while entries and entries[0][0] < cutoff:
            entries.popleft()

    def clear(self) -> None:
        self.entries.clear()
        self.corr = (0.0,) * 6

    def _since(self, corr: tuple[float, ...]) -> list[float]:
        """The position and velocity fed back since an entry that had seen ``corr``."""
        c = self.corr
        return [c[i] - corr[i] for i in range(6)]

    def state_at(self, t_ns: int, current: NavState) -> NavState:
        """The solution at ``t_ns``, corrected for every feedback since: between the two entries around it, the
        point on the straight line between their positions and velocities (the mechanisation's own path, 50 ms
        apart at 20 Hz); after the newest entry (or before the oldest) the nearest one carried on its velocity.

        Carrying the entry before on its velocity alone would place a fix up to a sample's interval of
        acceleration off, and at an entry's own time both agree."""
        entries = self.entries
        entry = after = None
        for e in reversed(entries):
            if e[0] <= t_ns:
                entry = e
                break
            after = e
        if entry is None:
            entry, after = (entries[0] if entries else None), None
        out = current.copy()
        if entry is None:
            return out
        t_e, lat, lon, h, vn, ve, vd, q, corr = entry
        d = self._since(corr)
        vn, ve, vd = vn - d[3], ve - d[4], vd - d[5]
        if after is not None and after[0] > t_e:
            t_a, lat_a, lon_a, h_a, vn_a, ve_a, vd_a, _, corr_a = after
            da = self._since(corr_a)
            lat, lon, h = earth.offset_llh(lat, lon, h, -d[0], -d[1], -d[2])
            lat_a, lon_a, h_a = earth.offset_llh(lat_a, lon_a, h_a, -da[0], -da[1], -da[2])
            k = (t_ns - t_e) / (t_a - t_e)
            out.lat, out.lon, out.h = lat + (lat_a - lat) * k, lon + (lon_a - lon) * k, h + (h_a - h) * k
            out.vn = vn + (vn_a - da[3] - vn) * k
            out.ve = ve + (ve_a - da[4] - ve) * k
            out.vd = vd + (vd_a - da[5] - vd) * k
            out.q = q
            return out
        dt = (t_ns - t_e) / NS
        lat, lon, h = earth.offset_llh(lat, lon, h, -d[0] + vn * dt, -d[1] + ve * dt, -d[2] + vd * dt)
        out.lat, out.lon, out.h, out.vn, out.ve, out.vd, out.q = lat, lon, h, vn, ve, vd, q
        return out
