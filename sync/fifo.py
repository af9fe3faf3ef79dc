"""Time stamps for MPU-6050 FIFO samples, which carry none.

The chip fills its FIFO on its own clock (nominally the configured rate, good to about 1 %); the board only
learns, at each poll, how many frames are waiting. Anchoring every batch to its own read time puts each batch's
frames behind that read at the nominal period, and a poll whose thread was preempted between taking the time and
reading FIFO_COUNT then stamps its older frames before the previous batch's newest: time going backwards, and gaps
that are not there.

Instead the frames are counted: each batch continues the previous one at the estimated period, and the read
times only steer that count-based time, slowly (a fraction of the difference per batch, spread over the batch's
intervals so that no single one carries it), within what the read bounds allow: the newest frame cannot have
arrived after the count was read (before ``t_after``), nor more than a period before the poll began
(``t_before``). The period is learned from frames counted over at least
``PERIOD_SPAN_S``, so a chip running 1 % fast does not pull the stamps against the bounds at every poll. A
prediction far outside the bounds (frames destroyed by an overflow the chip did not flag, a stalled bus) restarts
the count from the read time. Stamps are strictly increasing whatever the reads do.
"""

from __future__ import annotations

import numpy as np

STEER_GAIN = 0.1  # share of the read-time difference taken per batch: read jitter averages over ~10 polls
PERIOD_SPAN_S = 5.0  # frames counted over at least this long before the period estimate replaces the nominal
PERIOD_WINDOW_S = 60.0  # ... and over at most about twice this
PERIOD_TOLERANCE = 0.03  # a learned period further than this from the nominal one is not believed
RESTART_PERIODS = 3.0  # a prediction this many periods outside the read bounds restarts the count


class FifoClock:
    """Stamps for each batch of FIFO frames, oldest first, in the board's monotonic ns."""

    def __init__(self, nominal_period_ns: float) -> None:
        self.nominal_ns = float(nominal_period_ns)
        self.period_ns = float(nominal_period_ns)
        self.restarts = 0  # count restarts from the read time (after the first batch)
        self._last: float | None = None  # stamp of the newest frame delivered
        self._anchor: tuple[float, int] | None = None  # (stamp, frames counted up to it) for the period
        self._frames = 0
        self._window_ns: float | None = None  # a typical poll's duration, from the short ones

    def reset(self) -> None:
        """The FIFO was emptied (overflow, reopen): the next batch starts a new count."""
        self._last = None
        self._anchor = None
        self._frames = 0

    def stamps(self, n: int, t_before_ns: int, t_after_ns: int, backlog_frames: int = 0) -> list[int]:
        """Times of ``n`` frames read by a poll that began at ``t_before_ns`` and ended at ``t_after_ns``;
        ``backlog_frames`` were already in the FIFO behind them but left for the next poll."""
        if n <= 0:
            return []
        p = self.period_ns
        hi = t_after_ns - backlog_frames * p  # the count was read before t_after
        lo = t_before_ns - (backlog_frames + 1) * p  # ... and after t_before: the newest frame is younger than p
        measured = min(hi, t_before_ns - backlog_frames * p - p / 2)  # middle of its period, as if read at once
        steered = False
        if self._last is None:
            newest = measured
        else:
            predicted = self._last + n * p
            if lo - RESTART_PERIODS * p <= predicted <= hi + RESTART_PERIODS * p:
                # A poll preempted between its time and FIFO_COUNT measures too early, and its window
                # (t_after - t_before) is long: such polls steer less, and no poll by more than a period.
                window = t_after_ns - t_before_ns
                self._window_ns = window if self._window_ns is None else min(
                    window, 0.99 * self._window_ns + 0.01 * window)
                gain = STEER_GAIN * p / (p + max(0.0, window - self._window_ns))
                innovation = min(p, max(-p, measured - predicted))
                newest = min(hi, max(lo, predicted + gain * innovation))
                steered = True
            else:
                self.restarts += 1
                self._anchor = None
                newest = measured
        # A steered batch is spread evenly over the time since the last one: what the steering moved (the period's
        # residual error piled up over the polls since, or the bounds' clamp) goes into each of its intervals
        # rather than into the one between two batches, which a read's timing alone would otherwise stretch by up
        # to STEER_GAIN of a period. After a restart the frames keep the period behind the read time (at most the
        # time since the last batch: frames were lost between them).
        if self._last is None:
            step = p
        elif steered:
            step = (newest - self._last) / n
        else:
            step = min(p, (newest - self._last) / n)
        if self._last is not None and newest <= self._last:  # only with a clock going back: keep order anyway
            newest, step = self._last + n, 1.0
        # The same arithmetic as round(newest - (n - 1 - i) * step) per frame (rint rounds half to even as round does).
        out = np.rint(newest - np.arange(n - 1, -1, -1) * step).astype(np.int64).tolist()
        self._last = newest
        self._learn_period(newest, n)
        return out

    def _learn_period(self, newest: float, n: int) -> None:
        self._frames += n
        if self._anchor is None:
            self._anchor = (newest, self._frames)
            return
        t0, f0 = self._anchor
        frames = self._frames - f0
        if frames > 0 and newest - t0 >= PERIOD_SPAN_S * 1e9:
            estimate = (newest - t0) / frames
            if abs(estimate / self.nominal_ns - 1) <= PERIOD_TOLERANCE:
                self.period_ns = estimate
            if newest - t0 >= PERIOD_WINDOW_S * 1e9:  # follow the chip's clock as it warms: a sliding window
                self._anchor = (newest, self._frames)
