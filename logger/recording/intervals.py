"""How regularly a topic's messages came: the one rate and gap rule of ``logger info`` and ``logger plot``, so
two tools never give one file two rates; and the one thinning rule (:func:`next_due_ns`) of what is written at a
rate of its own (``/nav/fix`` live and replayed, ``logger export --every``).

The rate is what the topic delivered over its own span, (n - 1) / (last - first): a sensor that fell silent for
a minute reads low, as it should, instead of the rate of its good stretches. A gap is an interval longer than
:data:`GAP_FACTOR` times the usual (median) one. Pure Python over log times, so ``logger info`` needs no numpy and
stays quick on the board; the usual interval of a long topic (a 1 kHz IMU over an hour) is the median of an
evenly spread sample of its intervals, so no list of millions of intervals is built on a 512 MB board.
"""

from __future__ import annotations

import itertools
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field

GAP_FACTOR = 3.0  # an interval this many times the median one is a gap


@dataclass(frozen=True)
class Regularity:
    count: int
    rate_hz: float  # (count - 1) / span; 0 with fewer than two messages
    median_interval_s: float
    largest_interval_s: float
    gaps: list[tuple[int, int]] = field(default_factory=list)  # (time before, time after) of each gap, ns


MEDIAN_SAMPLE = 100_000  # intervals the usual one is taken from, at most


def regularity(times_ns: Sequence[int]) -> Regularity:
    """Rate, usual interval and gaps of message times (ns, in order)."""
    n = len(times_ns)
    if n < 2:
        return Regularity(n, 0.0, 0.0, 0.0)
    span_s = (times_ns[-1] - times_ns[0]) / 1e9
    stride = max(1, (n - 1) // MEDIAN_SAMPLE)
    median = statistics.median(times_ns[i + 1] - times_ns[i] for i in range(0, n - 1, stride))
    limit = GAP_FACTOR * median
    largest = 0
    gaps: list[tuple[int, int]] = []
    for a, b in itertools.pairwise(times_ns):
        d = b - a
        if d > largest:
            largest = d
        if d > limit and median > 0:
            gaps.append((a, b))
    return Regularity(n, (n - 1) / span_s if span_s > 0 else 0.0, median / 1e9, largest / 1e9, gaps)


GRID_TOLERANCE = 0.01  # of the interval: how early a time may be and still count for the tick after it


def next_due_ns(t_ns: int, anchor_ns: int, period_ns: int) -> int:
    """The earliest time that is due after one kept at ``t_ns``, on a grid of ``period_ns`` from ``anchor_ns``.

    Why a grid and not "a period after the last kept time": samples come close to a multiple of the period apart
    but a hair either side of it (a receiver's epochs a few ns off whole seconds, IMU rows 50 ms +- us apart), and
    a sample a hair short of a period after the last kept one would be passed over for the next, a whole sample
    later: 1 Hz fixes thinned to 2 s kept one in 3 s, 20 Hz rows at 5 Hz one interval in six 0.25 s. On the grid
    each tick keeps the first sample at or after it, or up to ``GRID_TOLERANCE`` of a period before it, so the rate
    asked is the rate kept, whatever the jitter."""
    tol_ns = int(period_ns * GRID_TOLERANCE)
    tick = (t_ns - anchor_ns + tol_ns) // period_ns  # the tick t_ns counts for
    return anchor_ns + (tick + 1) * period_ns - tol_ns
