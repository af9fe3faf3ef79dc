"""When a GNSS fix was valid, on the logger's clock.

A fix reaches the logger a quarter of a second or more after its epoch (solution latency plus the UART), so
its arrival stamp is useless as a measurement time at driving speed: 0.3 s at 15 m/s is 4.5 m. The receiver
states its epoch time (UTC), which is the measurement time once the logger's clock is known against UTC:

- a clock locked to the PPS already runs on UTC: the epoch time is used as it is;
- otherwise the PPS edges, which fall on whole UTC seconds, give the clock's offset modulo one second, and the
  fix's own arrival (between zero and one second after its epoch) picks the whole second;
- without PPS either, the shortest arrival delay seen over the last minute stands for the offset, less a
  nominal solution latency: the best that can be done, and flagged as such.
"""

from __future__ import annotations

from collections import deque

NS = 1_000_000_000
NOMINAL_LATENCY_NS = 100_000_000
PPS_STALE_NS = 10 * NS


class GnssEpochClock:
    def __init__(self) -> None:
        self._pps: deque[tuple[int, int]] = deque(maxlen=5)  # (t_sync_ns, offset modulo 1 s)
        self._delays: deque[int] = deque(maxlen=60)
        self.method = "none"
        self.offset_ns = 0

    def pps(self, t_sync_ns: int) -> None:
        self._pps.append((t_sync_ns, (t_sync_ns + NS // 2) % NS - NS // 2))

    def epoch_time(self, t_sync_ns: int, gnss_time_ns: int | None, sync_state: str) -> int:
        """The fix's epoch on the logger's clock (t_sync scale), ns."""
        if gnss_time_ns is None:
            self.method = "arrival"
            return t_sync_ns - NOMINAL_LATENCY_NS
        delay = t_sync_ns - gnss_time_ns
        self._delays.append(delay)
        if sync_state == "locked":
            self.method, self.offset_ns = "clock locked", 0
            return gnss_time_ns
        if self._pps and t_sync_ns - self._pps[-1][0] < PPS_STALE_NS:
            fracs = sorted(f for _, f in self._pps)
            frac = fracs[len(fracs) // 2]
            # delay = offset + latency with 0 <= latency < 1 s: the whole seconds of the offset follow.
            k = (delay - frac) // NS
            self.method, self.offset_ns = "pps", frac + k * NS
            return gnss_time_ns + self.offset_ns
        self.method = "shortest delay"
        self.offset_ns = min(self._delays) - NOMINAL_LATENCY_NS
        return gnss_time_ns + self.offset_ns
