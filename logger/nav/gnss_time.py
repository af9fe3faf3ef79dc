"""When a GNSS fix was valid, on the logger's clock.

A fix reaches the logger a quarter of a second or more after its epoch (solution latency plus the UART), so
its arrival stamp is useless as a measurement time at driving speed: 0.3 s at 15 m/s is 4.5 m. The receiver
states its epoch time (UTC), which is the measurement time once the logger's clock is known against UTC:

- a clock locked to the PPS already runs on UTC: the epoch time is used as it is;
- otherwise the PPS edges, which fall on whole UTC seconds, give the clock's offset modulo one second, and the
  read its first message came in (between zero and one second after its epoch) picks the whole second: not the
  fix's arrival, which at 9600 baud can come more than a second after its epoch (a burst of 0.9 s);
- without PPS either, the shortest arrival delay seen over the last minute stands for the offset, less a
  nominal solution latency: the best that can be done, and flagged as such.
"""

from __future__ import annotations

import itertools
from collections import deque

NS = 1_000_000_000
NOMINAL_LATENCY_NS = 100_000_000
ARRIVAL_SIGMA_S = 0.1  # spread of a receiver's solution and output latency (u-blox: some tens to 300 ms)
MIN_LATENCY_SIGMA_S = 0.02  # the least spread taken for latencies learnt while the time was valid
PPS_STALE_NS = 10 * NS
RECENT_DELAYS = 10  # the fixes whose shortest arrival delay (median first-read delay) picks the whole seconds


class GnssEpochClock:
    def __init__(self) -> None:
        self._pps: deque[tuple[int, int]] = deque(maxlen=5)  # (t_sync_ns, offset modulo 1 s)
        self._delays: deque[int] = deque(maxlen=60)  # from each fix's epoch to its arrival
        self._began: deque[int] = deque(maxlen=RECENT_DELAYS)  # ... to the read its first message came in, if earlier
        self._latencies: deque[int] = deque(maxlen=60)  # arrival delays while the clock was locked (on UTC)
        self.method = "none"
        self.offset_ns = 0
        self.uncertainty_s = 0.0  # 1 sigma of the last epoch placed, s: 0 when the receiver stated its epoch

    def pps(self, t_sync_ns: int) -> None:
        self._pps.append((t_sync_ns, (t_sync_ns + NS // 2) % NS - NS // 2))

    def epoch_time(self, t_sync_ns: int, gnss_time_ns: int | None, sync_state: str,
                   began_sync_ns: int | None = None) -> int:
        """The fix's epoch on the logger's clock (t_sync scale), ns: ``t_sync_ns`` when the fix was read whole,
        ``began_sync_ns`` when its first message was (earlier on a slow line; None: the same read)."""
        if gnss_time_ns is None:
            # No valid epoch time (a receiver without a date yet, GGA alone): the fix is placed by its arrival,
            # less the latency its predecessors showed while their time was valid and the clock on UTC, or less a
            # nominal solution latency when none ever had a time.
            if self._latencies and sync_state == "locked":
                lat = sorted(self._latencies)
                n = len(lat)
                # The spread of the latencies seen (their interquartile range / 1.35, a robust sigma).
                self.uncertainty_s = max(MIN_LATENCY_SIGMA_S, (lat[(3 * n) // 4] - lat[n // 4]) / 1.35e9)
                self.method = "arrival, usual latency"
                return t_sync_ns - lat[n // 2]
            self.method = "arrival"
            self.uncertainty_s = ARRIVAL_SIGMA_S
            return t_sync_ns - NOMINAL_LATENCY_NS
        self.uncertainty_s = 0.0
        delay = t_sync_ns - gnss_time_ns
        self._delays.append(delay)
        if began_sync_ns is not None:
            self._began.append(began_sync_ns - gnss_time_ns)
        if sync_state == "locked":
            self._latencies.append(delay)  # an epoch without time is placed by its arrival, less these
            self.method, self.offset_ns = "clock locked", 0
            return gnss_time_ns
        if self._pps and t_sync_ns - self._pps[-1][0] < PPS_STALE_NS:
            fracs = sorted(f for _, f in self._pps)
            frac = fracs[len(fracs) // 2]
            # delay = offset + latency with 0 <= latency < 1 s: the whole seconds of the offset follow, from the
            # shortest delay of the last few fixes (one held back past a second, an NMEA epoch sent with the next
            # burst, took a whole second too many and landed on its successor's time). A fix read over several reads
            # (a slow line) is measured from the first, whose delay stays under a second where its arrival's does
            # not: the median of the last few such, which one epoch misdated either way does not move.
            if began_sync_ns is not None:
                began = sorted(self._began)
                k = (began[len(began) // 2] - frac) // NS
            else:
                k = (min(itertools.islice(reversed(self._delays), RECENT_DELAYS)) - frac) // NS
            self.method, self.offset_ns = "pps", frac + k * NS
            return gnss_time_ns + self.offset_ns
        self.method = "shortest delay"
        self.offset_ns = min(self._delays) - NOMINAL_LATENCY_NS
        return gnss_time_ns + self.offset_ns
