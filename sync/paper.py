"""The paper's adaptive counters (Lim et al. 2018, section 2, Eq. 1), kept beside the better clock.

An IMU counter ticks once per IMU sample and is reset by each PPS rising edge; when an edge is overdue the
count is carried into a timer counter, which only PPS resets. The paper's synchronisation time of a sample is
GPS time(k) + (IMU_CNT + Timer_CNT) / Fs, with k the last edge. Every record carries both counters so a drive
can be re-timed by the paper's method and compared with the regression clock.

The counters are a function of an instant's monotonic time (how many IMU samples since the last edge), so the
order in which threads report does not matter; an OBD speed or an altimeter reading stamped before the IMU's FIFO
has delivered the samples up to it counts those at the IMU's rate.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np


def split_count(n: int, rate_hz: int) -> tuple[int, int]:
    """(IMU_CNT, Timer_CNT) after ``n`` IMU samples since the last edge.

    The IMU counter carries into the timer once it passes Fs + 1: with PPS present an edge always comes before
    that (the count peaks at Fs or Fs + 1 with interrupt and sampling jitter: the paper's Table 6 maximum of 21 at
    20 Hz); without PPS the timer takes whole seconds of counts.
    """
    limit = rate_hz + 1
    if n <= limit:
        return n, 0
    carries = -(-(n - limit) // rate_hz)
    return n - carries * rate_hz, carries * rate_hz


class PaperCounters:
    """IMU sample times around the last PPS edges, and the counters they give at any instant.

    A sample's count is the number of samples taken since the last edge before it, counted from the start of the
    run until the first edge: a function of its time alone, whatever was reported first. The PPS thread reports
    an edge within milliseconds, while a FIFO read brings samples taken up to half a second earlier (20 Hz, two
    reads a second): the samples of a read that straddles an edge, taken before it, count from the edge before
    (up to Fs + 1 with PPS), as the paper's counter, ticking at each sample, had them. So the counters keep, for
    each recent edge, how many samples were taken up to it (``_at_edge``; a sample reported after an edge it
    preceded is added to it then), and the recent samples' times: a count is then a difference of two
    positions."""

    KEEP_S = 4  # seconds of sample times kept at least: a read's latency and a late-reported edge, with margin
    EDGES_KEPT = 16  # recent edges kept (with PPS, the last 16 s)

    def __init__(self, imu_rate_hz: float) -> None:
        self.rate = max(1, round(imu_rate_hz))
        self._total = 0  # samples registered since the start
        self._times: list[int] = []  # the latest registered sample times, oldest first (KEEP_S of them at least)
        self._keep = self.KEEP_S * self.rate
        self._edges: list[int] = []  # recent edges, oldest first ...
        self._at_edge: list[int] = []  # ... and the samples taken at or before each of them

    @property
    def last_edge_ns(self) -> int | None:
        return self._edges[-1] if self._edges else None

    def on_imu(self, t_ns: int) -> None:
        self.on_imu_many((t_ns,))

    def on_imu_many(self, times_ns: Sequence[int]) -> None:
        """Samples just read (oldest first): a FIFO read's, or one."""
        k = len(times_ns)
        if not k:
            return
        self._total += k
        ts = self._times
        late = bool(ts) and times_ns[0] < ts[-1]
        ts.extend(times_ns)
        if late:  # reported after later ones (never by the daemon's one IMU thread): the positions need order
            ts.sort()
        edges = self._edges
        if edges and times_ns[0] <= edges[-1]:
            # Taken before an edge already reported: they count before it (and before any later one).
            for j in range(len(edges) - 1, -1, -1):
                if edges[j] < times_ns[0]:
                    break
                self._at_edge[j] += bisect.bisect_right(times_ns, edges[j]) if k > 1 else 1
        if len(self._times) > 2 * self._keep:
            del self._times[:len(self._times) - self._keep]

    def on_edge(self, t_ns: int) -> None:
        """A PPS edge resets both counters (for the samples after it; those reported already are counted from it)."""
        if self._edges and t_ns <= self._edges[-1]:
            return
        self._edges.append(t_ns)
        self._at_edge.append(self._registered(t_ns))
        if len(self._edges) > self.EDGES_KEPT:
            del self._edges[0], self._at_edge[0]

    def _registered(self, t_ns: int) -> int:
        """Samples read so far that were taken at or before ``t_ns``, since the start (exact inside the kept span,
        KEEP_S at least; an older time counts every sample before the span as before it)."""
        ts = self._times
        return self._total - (len(ts) - bisect.bisect_right(ts, t_ns))

    def _unread(self, t_ns: int) -> int:
        """Samples taken after the newest one read and at or before ``t_ns``, at the IMU's rate: a FIFO holds up
        to half a second at 20 Hz, and an OBD speed or a fix stamped meanwhile counts them, as the paper's counter
        ticking at each sample would have."""
        ts = self._times
        return (t_ns - ts[-1]) * self.rate // 1_000_000_000 if ts and t_ns > ts[-1] else 0

    def _upto(self, t_ns: int) -> int:
        """Samples taken at or before ``t_ns`` since the start, read or not."""
        return self._registered(t_ns) + self._unread(t_ns)

    def _at(self, j: int) -> int:
        """Samples taken at or before edge ``j``: those read (counted as they came) and those not yet."""
        return self._at_edge[j] + self._unread(self._edges[j])

    def counters_many(self, times_ns: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`counters` at each of several instants, as arrays (a FIFO read's samples)."""
        t = np.asarray(times_ns, dtype=np.int64)
        k = len(t)
        ts, edges = self._times, self._edges
        limit = self.rate + 1
        fresh = (k and len(ts) >= k and ts[-1] == times_ns[-1] and (len(ts) == k or ts[-k - 1] < times_ns[0])
                 and ts[-k:] == list(times_ns) and (k == 1 or bool((t[1:] > t[:-1]).all())))
        if fresh and edges and times_ns[0] > edges[-1]:
            # A read just registered (on_imu_many, as the daemon does before stamping it) and wholly after the last
            # edge (most reads): the newest times, strictly increasing, so each one's count is its place among
            # them; with PPS the largest carries nothing.
            last = self._total - self._at(len(edges) - 1)
            if last <= limit:
                return np.arange(last - k + 1, last + 1), np.zeros(k, dtype=np.int64)
        if fresh:
            n = np.arange(self._total - k + 1, self._total + 1)
        else:
            n = np.array([self._upto(x) for x in times_ns], dtype=np.int64).reshape(k)
        if edges and k and times_ns[0] > edges[-1]:
            n = n - self._at(len(edges) - 1)
        elif edges:
            j = np.searchsorted(np.asarray(edges, dtype=np.int64), t, side="left") - 1  # the last edge before each
            at = np.array([self._at(i) for i in range(len(edges))], dtype=np.int64)
            n = n - np.where(j >= 0, at[np.maximum(j, 0)], 0)
        carries = np.where(n > limit, -(-(n - limit) // self.rate), 0) * self.rate
        return n - carries, carries

    def counters(self, t_ns: int) -> tuple[int, int]:
        """(IMU_CNT, Timer_CNT) at ``t_ns``: exact inside the kept span of sample times (KEEP_S, and edges reported
        within it), the unread samples counted at the IMU's rate after the newest one read."""
        n = self._upto(t_ns)
        j = bisect.bisect_left(self._edges, t_ns) - 1  # the last edge before this instant
        if j >= 0:
            n -= self._at(j)
        return split_count(n, self.rate)
