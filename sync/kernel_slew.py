"""How far NTP has moved CLOCK_MONOTONIC, measured against CLOCK_MONOTONIC_RAW, which nothing adjusts.

Linux slews CLOCK_MONOTONIC with the system clock: chronyd's frequency and offset corrections (up to 83 333 ppm by
chronyd's default ``maxslewrate``, 500 ppm under ntpd) move every stamp this daemon takes, the PPS edges' too.
While edges come, the clock's fit follows them. In holdover it carries on at the rate the edges last showed, which
holds the kernel's rate of then: a slew that begins meanwhile (chronyd turning to NTP servers over a mobile network
when the PPS it was fed stops, in a tunnel) moved stamps 1 ms off behind a 34 us bound. CLOCK_MONOTONIC_RAW runs on
the board's oscillator alone, so ``K = MONOTONIC - MONOTONIC_RAW`` is the sum of the kernel's adjustments, and what
K did beyond the rate it had over the fit's edges is what a holdover must take out (:meth:`KernelSlew.excess`).
Reading both clocks needs no privilege: the unit's ProtectClock= forbids adjtimex, not clock_gettime.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import numpy as np

from sync.realtime import OffsetSample, read_offset

MIN_GAP_NS = 5_000_000  # K is read at most this often (200 Hz): a stamp is then at most this far past a read of it
LINEAR_SPAN_NS = 40_000_000  # a read this short takes K as a line between its ends (excess_many)
MIN_EDGES_FOR_RATE = 3  # as the fit's slope (sync.regress.MIN_SAMPLES_FOR_SLOPE): fewer, and the prior stands


def raw_clock_ns() -> int:
    return time.clock_gettime_ns(time.CLOCK_MONOTONIC_RAW)


def _k(sample: OffsetSample) -> int:
    """K = MONOTONIC - MONOTONIC_RAW of a read of the raw clock against the monotonic one."""
    return -sample.offset_ns


class KernelSlew:
    """K sampled when asked (the clock asks at every stamp and edge), and K at the clock's samples (its edges).

    Between samples K is taken as linear (a FIFO read's samples, stamped up to half a second back, fall between the
    reads that sample K); past the newest it carries on at the last rate seen.
    """

    def __init__(self, monotonic_ns: Callable[[], int] = time.monotonic_ns,
                 raw_ns: Callable[[], int] = raw_clock_ns, keep: int = 256, keep_edges: int = 256) -> None:
        self._mono = monotonic_ns
        self._raw = raw_ns
        self._samples: deque[OffsetSample] = deque(maxlen=keep)  # raw - mono: -K
        self._edges: deque[tuple[int, float]] = deque(maxlen=keep_edges)  # (board ns of an edge, K there)
        # Between two samples K is taken as linear; where its rate changed in between (chronyd changes it at its
        # updates) the line is off by up to a quarter of the change times the gap. The largest such since the
        # newest edge, with the samples' read windows, is what the bound adds (margin_ns).
        self._margin_ns = 0.0
        self._segment_ns = 0.0  # the newest sample's part of it
        self._rate_key: tuple[int, int, bool] | None = None
        self._rate = 0.0
        self._prior_rate: float | None = None  # K's rate over the last window of enough edges, or a restored one

    def sample(self) -> OffsetSample:
        """Read K now (sync.realtime's window: monotonic, raw, monotonic); kept when later than the last. Within
        MIN_GAP_NS of the last one that one stands (every sensor thread stamps through here: the samples stay
        sparse enough that a FIFO read's span, half a second back, covers a few of them)."""
        s = self._samples
        if s and self._mono() - s[-1].mono_ns < MIN_GAP_NS:
            return s[-1]
        new = read_offset(self._mono, self._raw)
        if len(s) >= 2:
            a, b = s[-2], s[-1]
            before = (_k(b) - _k(a)) / (b.mono_ns - a.mono_ns)
            after = (_k(new) - _k(b)) / (new.mono_ns - b.mono_ns)
            gap = max(b.mono_ns - a.mono_ns, new.mono_ns - b.mono_ns)
            self._segment_ns = abs(after - before) * gap / 4 + 2 * (new.spread_ns + b.spread_ns)
            self._margin_ns = max(self._margin_ns, self._segment_ns)
        s.append(new)
        return new

    def at(self, t_ns: int) -> float:
        """K at a board time, from the samples around it (a sample is taken first when there is none)."""
        if not self._samples:
            self.sample()
        s = self._samples
        newest = s[-1]
        if t_ns >= newest.mono_ns:
            if len(s) < 2:
                return float(_k(newest))
            prev = s[-2]
            return _k(newest) + (_k(newest) - _k(prev)) * (t_ns - newest.mono_ns) / (newest.mono_ns - prev.mono_ns)
        i = len(s) - 1  # from the newest back: the times asked about are the latest reads'
        while i > 0 and s[i - 1].mono_ns > t_ns:
            i -= 1
        if i == 0:
            return float(_k(s[0]))
        a, b = s[i - 1], s[i]
        return _k(a) + (_k(b) - _k(a)) * (t_ns - a.mono_ns) / (b.mono_ns - a.mono_ns)

    def at_many(self, t_ns: np.ndarray) -> np.ndarray:
        """:meth:`at` for an array of board times."""
        if not self._samples:
            self.sample()
        s = self._samples
        earliest = int(t_ns.min()) if len(t_ns) else 0
        n = 2  # the newest samples back to the first before the earliest time: a read's span, not the whole deque
        while n < len(s) and s[-n].mono_ns > earliest:
            n += 1
        tail = [s[-i] for i in range(min(n, len(s)), 0, -1)]
        times = np.fromiter((a.mono_ns for a in tail), dtype=np.float64, count=len(tail))
        ks = np.fromiter((_k(a) for a in tail), dtype=np.float64, count=len(tail))
        out = np.interp(t_ns.astype(np.float64), times, ks)
        if len(s) >= 2:
            rate = (ks[-1] - ks[-2]) / (times[-1] - times[-2])
            beyond = t_ns > times[-1]
            out = np.where(beyond, ks[-1] + rate * (t_ns - times[-1]), out)
        return out

    def mark_edge(self, edge_ns: int) -> None:
        """An edge the clock took as a sample: K there (sampled now, interpolated back to the edge)."""
        self.sample()
        if not self._edges or edge_ns > self._edges[-1][0]:
            self._edges.append((edge_ns, self.at(edge_ns)))
        self._margin_ns = self._segment_ns  # K at the edge is interpolated in the newest segment

    @property
    def margin_ns(self) -> float:
        """How far K between samples since the newest edge may be from the lines through them, and the samples'
        own read windows: ns for an error bound."""
        return self._margin_ns

    def edge_rate(self, first_edge_ns: int, use_prior: bool = False) -> tuple[int, float, float] | None:
        """(newest edge, K there, K's mean rate from the edge at or after ``first_edge_ns`` to it), or None. The
        rate is the prior (the last one measured over MIN_EDGES_FOR_RATE edges or more, or a restored one) where
        the clock's fit takes its slope from its prior (``use_prior``: too few edges), as a fit of fewer edges does:
        the slope it extrapolates then holds the kernel's rate of then, which a rate of 0 took out a second time
        (20 ppm of steady NTP: 111 us off behind 69 us after a relock)."""
        if not self._edges:
            return None
        last_t, last_k = self._edges[-1]
        key = (first_edge_ns, last_t, use_prior)
        if self._rate_key != key:  # once per edge: every stamp between two edges asks the same
            window = [(t, k) for t, k in self._edges if t >= first_edge_ns]
            if not use_prior and len(window) >= MIN_EDGES_FOR_RATE and last_t > window[0][0]:
                self._rate = self._prior_rate = (last_k - window[0][1]) / (last_t - window[0][0])
            else:
                self._rate = self._prior_rate if self._prior_rate is not None else 0.0
            self._rate_key = key
        return last_t, last_k, self._rate

    def restore(self, edge_ns: int, k_ns: float, rate: float) -> None:
        """K at the newest edge of a previous run on this boot and its rate then (the clock's state file): a
        restart's holdover from that run's mapping takes out what NTP did while the logger was down."""
        self._edges.append((edge_ns, float(k_ns)))
        self._prior_rate = float(rate)
        self._rate_key = None

    def excess(self, t_ns: int, first_edge_ns: int, use_prior: bool = False) -> float:
        """What the kernel moved CLOCK_MONOTONIC by between the newest edge and ``t_ns`` beyond the rate it moved it
        at over the fit's edges (from ``first_edge_ns``): ns that board time gained with no time passing."""
        edge = self.edge_rate(first_edge_ns, use_prior)
        if edge is None or t_ns <= edge[0]:
            return 0.0
        last_t, last_k, rate = edge
        return (self.at(t_ns) - last_k) - rate * (t_ns - last_t)

    def excess_many(self, t_ns: np.ndarray, first_edge_ns: int, use_prior: bool = False) -> np.ndarray | float:
        """:meth:`excess` for an array of board times (0 where a time is not after the newest edge). A short read
        (a fast FIFO's, LINEAR_SPAN_NS or less) takes K as a line between its ends: it holds at most one read of K
        inside, and the bound's margin has what a change of rate there does; a longer one is interpolated between
        every read of K it spans."""
        edge = self.edge_rate(first_edge_ns, use_prior)
        if edge is None or not len(t_ns):
            return 0.0
        last_t, last_k, rate = edge
        t0, t1 = max(int(t_ns[0]), last_t), int(t_ns[-1])
        if t1 <= last_t:
            return 0.0
        if t1 - t0 <= LINEAR_SPAN_NS:
            e0, e1 = self.excess(t0, first_edge_ns, use_prior), self.excess(t1, first_edge_ns, use_prior)
            if abs(e1 - e0) < 0.5 and t0 > last_t:
                return e0  # one number for the read (stamps are whole ns): no arrays
            slope = (e1 - e0) / (t1 - t0) if t1 > t0 else 0.0
            line = e0 + slope * (t_ns - t0)
            return line if t0 > last_t else np.where(t_ns > last_t, line, 0.0)
        return np.where(t_ns > last_t, (self.at_many(t_ns) - last_k) - rate * (t_ns - last_t), 0.0)
