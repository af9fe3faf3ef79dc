"""How regularly a topic's messages came: the one rate and gap rule of ``logger info``, ``logger plot`` and the
run summary, so two tools never give one file two rates.

The rate is what the topic delivered over its own span, (n - 1) / (last - first): a sensor that fell silent for
a minute reads low, as it should, instead of the rate of its good stretches. A gap is an interval longer than
:data:`GAP_FACTOR` times the usual (median) one. Pure Python over log times, so ``logger info`` needs no numpy and
stays quick on the board.
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


def regularity(times_ns: Sequence[int]) -> Regularity:
    """Rate, usual interval and gaps of message times (ns, in order)."""
    n = len(times_ns)
    if n < 2:
        return Regularity(n, 0.0, 0.0, 0.0)
    span_s = (times_ns[-1] - times_ns[0]) / 1e9
    intervals = [b - a for a, b in itertools.pairwise(times_ns)]
    median = statistics.median(intervals)
    limit = GAP_FACTOR * median
    gaps = [(times_ns[i], times_ns[i + 1]) for i, d in enumerate(intervals) if median > 0 and d > limit]
    return Regularity(n, (n - 1) / span_s if span_s > 0 else 0.0, median / 1e9, max(intervals) / 1e9, gaps)
