"""The paper's adaptive counters (Lim et al. 2018, section 2, Eq. 1), kept beside the better clock.

An IMU counter ticks once per IMU sample and is reset by each PPS rising edge; when an edge is overdue the
count is carried into a timer counter, which only PPS resets. The paper's synchronisation time of a sample is
GPS time(k) + (IMU_CNT + Timer_CNT) / Fs, with k the last edge. Every record carries both counters so a drive
can be re-timed by the paper's method and compared with the regression clock.

The counters are a function of a sample's monotonic time (how many IMU samples since the last edge), so the OBD
and altimeter threads get exactly the values the IMU thread would hand them, and the order in which threads
report does not matter.
"""

from __future__ import annotations

import bisect
from collections import deque
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
    """IMU sample times since the last PPS edge, and the counters they give at any instant."""

    KEEP_NS = 3_000_000_000  # sample times kept after an edge; later samples only add to a count

    def __init__(self, imu_rate_hz: float) -> None:
        self.rate = max(1, round(imu_rate_hz))
        self.last_edge_ns: int | None = None
        self._times: list[int] = []  # IMU sample times after the last edge, while they are few
        self._beyond = 0  # samples after the last edge (or ever, before the first) no longer in _times
        self._recent: deque[int] = deque(maxlen=4 * self.rate)  # last samples, to re-count a late-reported edge

    def on_imu(self, t_ns: int) -> None:
        self._recent.append(t_ns)
        if self.last_edge_ns is None:
            self._beyond += 1  # no edge yet: the counter has never been reset
            return
        if t_ns <= self.last_edge_ns:
            return
        self._times.append(t_ns)
        if len(self._times) > 4 * self.rate and self._times[0] - self.last_edge_ns > self.KEEP_NS:
            cut = len(self._times) - 2 * self.rate
            self._beyond += cut
            del self._times[:cut]

    def on_imu_many(self, times_ns: Sequence[int]) -> None:
        """:meth:`on_imu` for a FIFO read's samples (oldest first) at once; the counts are the same, only the
        trimming of old times is looked at once per read."""
        self._recent.extend(times_ns)
        edge = self.last_edge_ns
        if edge is None:
            self._beyond += len(times_ns)
            return
        if times_ns and times_ns[0] > edge:
            self._times.extend(times_ns)
        else:
            self._times.extend(t for t in times_ns if t > edge)
        if len(self._times) > 4 * self.rate and self._times[0] - edge > self.KEEP_NS:
            cut = len(self._times) - 2 * self.rate
            self._beyond += cut
            del self._times[:cut]

    def on_edge(self, t_ns: int) -> None:
        """A PPS edge resets both counters; samples already seen after it (threads report late) are re-counted."""
        if self.last_edge_ns is not None and t_ns <= self.last_edge_ns:
            return
        self.last_edge_ns = t_ns
        self._times = sorted(t for t in self._recent if t > t_ns)
        self._beyond = 0

    def counters_many(self, times_ns: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`counters` at each of several instants, as arrays (a FIFO read's samples)."""
        t = np.asarray(times_ns, dtype=np.int64)
        k = len(t)
        ts = self._times
        if (k and self.last_edge_ns is not None and len(ts) >= k and ts[-1] == times_ns[-1]
                and (len(ts) == k or ts[-k - 1] < times_ns[0]) and ts[-k:] == list(times_ns)
                and (k == 1 or bool((t[1:] > t[:-1]).all()))):
            # A read just registered (on_imu_many, as the daemon does before stamping it): the newest times after
            # the edge, strictly increasing, so each one's count is its place among them, what the search finds.
            n = np.arange(len(ts) - k + 1 + self._beyond, len(ts) + 1 + self._beyond)
            if n[-1] <= self.rate + 1:  # no carry (with PPS, always)
                return n, np.zeros(k, dtype=np.int64)
        elif self.last_edge_ns is None:
            n = np.full(k, self._beyond, dtype=np.int64)
        else:
            # Only the registered times between the first and the last instant can tell them apart: search those.
            lo = bisect.bisect_right(ts, times_ns[0]) if k else 0
            hi = bisect.bisect_right(ts, times_ns[-1]) if k else 0
            n = np.searchsorted(np.asarray(ts[lo:hi], dtype=np.int64), t, side="right") + (lo + self._beyond)
            n[t <= self.last_edge_ns] = 0
        limit = self.rate + 1
        carries = np.where(n > limit, -(-(n - limit) // self.rate), 0) * self.rate
        return n - carries, carries

    def counters(self, t_ns: int) -> tuple[int, int]:
        if self.last_edge_ns is None:
            return split_count(self._beyond, self.rate)
        if t_ns <= self.last_edge_ns:
            return 0, 0
        n = self._beyond + bisect.bisect_right(self._times, t_ns)
        return split_count(n, self.rate)
