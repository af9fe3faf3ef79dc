"""gpsd as a source of fixes and PPS edges: the adapters that turn its reports into the same records.

The counterpart of :class:`logger.runtime.sources.GnssSource` and :class:`logger.runtime.sources.PpsSource` for a
receiver that gpsd owns. Each adapter has its own connection and its own sampler thread, so PPS edges are recorded
at once while fixes wait for the rest of their epoch, and each shows in ``logger status`` under its usual name with
``gpsd HOST:PORT`` as its source. gpsd's stream gives no receiver bytes (no ``/gnss/raw``) and no time pulse
announcements (no ``/gnss/timepulse``): a PPS report names its own second instead.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from logger.recording.records import location_fix, pps_record
from logger.recording.topics import GNSS_FIX, PPS
from logger.runtime.sampler import Reading, Source
from logger.runtime.timebase import TimeBase
from sensors.errors import BusError, NoData
from sensors.gpsd import GpsdClient
from sensors.gpsd_decode import GpsdEpochs, pps_report, toff_real_ns
from sync.realtime import RealtimeMap

NS = 1_000_000_000
DAY_S = 86_400
LEAP_EDGE_GAP_NS = 500_000_000  # a midnight second's repeat this long after its first edge is the next edge
READ_WAIT_S = 0.2  # longest wait for gpsd per read, host seconds: the thread's heartbeat and stop latency
SETTLE_S = 0.3  # an epoch is complete when its reports stopped coming for this long (drive time)
QUIET_S = 3.0  # this long without a record, gpsd's own word on a missing receiver becomes the sensor's state
TOFF_KEEP = 64  # TOFF arrivals kept until their fix completes (gpsd sends one a second: a minute's)


def _origin(host: str, port: int, device: str | None) -> str:
    return f"gpsd {host}:{port}" + (f" {device}" if device else "")


class _GpsdConnection(Source):
    """What both adapters share: the connection, its counters, and gpsd's word on a missing receiver."""

    def __init__(self, host: str, port: int, device: str | None, tb: TimeBase) -> None:
        self.host, self.port, self.device, self.tb = host, port, device or None, tb
        self.origin = _origin(host, port, self.device)
        self.client: Any = None
        self._last_record_ns = 0
        self._last_nodata_ns: int | None = None

    def _connect(self) -> None:
        self.client = GpsdClient.connect(self.host, self.port, self.device)
        self._last_record_ns = self.tb.monotonic_ns()
        self._last_nodata_ns = None

    def _quiet(self, t_ns: int, produced: bool) -> None:
        """After a quiet while, say why when gpsd told (no receiver, not the configured one, an ERROR reply);
        at most once a second, as the sampler counts each as an error."""
        if produced:
            self._last_record_ns = t_ns
            return
        if t_ns - self._last_record_ns < QUIET_S * NS:
            return
        reason = self.client.missing_device()
        if reason is None and self.client.error:
            reason = f"gpsd at {self.client.where}: {self.client.error}"
        if reason is None or (self._last_nodata_ns is not None and t_ns - self._last_nodata_ns < NS):
            return
        self._last_nodata_ns = t_ns
        raise NoData(reason)

    def incidents(self) -> dict[str, int]:
        if self.client is None:
            return {}
        c = self.client.counters
        return {"lines of garbage from gpsd": c.garbage, "overlong lines from gpsd": c.oversized}

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
        self.client = None


class GpsdSource(_GpsdConnection):
    """Fixes from gpsd's TPV and SKY reports, one ``/gnss/fix`` record per epoch (see sensors.gpsd_decode).

    A fix's acquisition time is the arrival of its epoch's last TPV, as a serial fix's is the read that
    completed its epoch; when gpsd's TOFF for the epoch came in an earlier read, that read's time is the fix's
    ``opened_mono_ns``, as a serial epoch spread over several reads has it: gpsd reports a TPV only once the
    cycle's last sentence is in, which on a slow line (u-blox's factory NMEA at 9600 baud) is after the next pulse.
    """

    name = "gnss"
    sample_topic = GNSS_FIX

    def __init__(self, host: str, port: int, device: str | None, tb: TimeBase, settle_s: float = SETTLE_S) -> None:
        super().__init__(host, port, device, tb)
        self.settle_ns = round(settle_s * NS)
        self.epochs: Any = None
        # Epochs still being collected when the connection ended (gpsd restarted, the socket closed): complete as
        # far as gpsd got, so they are recorded with the next read instead of lost with the old assembler.
        self._carried: list[Reading] = []
        self._toff: dict[int, int] = {}  # epoch time (Unix ns, as gpsd names it) -> the read its TOFF came in

    def open(self) -> None:
        self._connect()
        self.epochs = GpsdEpochs(self.settle_ns)
        self._toff = {}

    def read(self) -> list[Reading]:
        carried, self._carried = self._carried, []
        wait_s = 0.0 if carried else READ_WAIT_S
        due = self.epochs.due_ns()
        if due is not None:  # wake up when the open epoch is due, not a whole wait later
            wait_s = min(wait_s, max(0.0, (due - self.tb.monotonic_ns()) / NS / self.tb.scale))
        try:
            messages = self.client.read(wait_s)
        except BusError:
            self._carried = carried  # close() adds the open epoch; the next connection's first read records them
            raise
        t = self.tb.monotonic_ns()
        done = []
        for msg in messages:
            real = toff_real_ns(msg)
            if real is not None:
                self._toff.setdefault(real, t)
                if len(self._toff) > TOFF_KEEP:
                    del self._toff[next(iter(self._toff))]
            done += self.epochs.push(msg, t)
        done += self.epochs.poll(t)
        out = carried + self._readings(done)
        self._quiet(t, bool(out))
        return out

    def close(self) -> None:
        if self.epochs is not None:
            self._carried += self._readings(self.epochs.flush())
            self.epochs = None
        super().close()

    def _readings(self, done: list[tuple[Any, int]]) -> list[Reading]:
        return [Reading(GNSS_FIX, location_fix(fix, t_fix, opened_mono_ns=self._opened_at(fix, t_fix)), t_fix)
                for fix, t_fix in done]

    def _opened_at(self, fix: Any, t_fix: int) -> int | None:
        """The read the epoch's TOFF came in, where that was an earlier read than the one that completed it."""
        opened = self._toff.pop(fix.time_utc_ns, None) if fix.time_utc_ns is not None else None
        return opened if opened is not None and opened < t_fix else None


class GpsdPpsSource(_GpsdConnection):
    """PPS edges from gpsd's PPS reports: the edge's system-clock stamp mapped to the monotonic clock, and the
    GNSS second gpsd says it marks, which the sync clock takes as the edge's label.

    The mapping (:class:`sync.realtime.RealtimeMap`) refuses an edge when the system clock was stepped between
    the edge and its report; such refusals are this sensor's incidents. ``realtime_ns`` is the system clock
    gpsd stamps with (a simulated board's, under ``--sim``).
    """

    name = "pps"

    def __init__(self, host: str, port: int, device: str | None, tb: TimeBase,
                 realtime_ns: Callable[[], int] = time.time_ns) -> None:
        super().__init__(host, port, device, tb)
        self.realtime_ns = realtime_ns
        self.map: Any = None
        self._seqno = 0  # across reconnects, like a kernel line's sequence number
        self._last_second: int | None = None
        self._last_mono: int | None = None  # the last edge recorded, monotonic ns

    def open(self) -> None:
        self._connect()
        self.map = RealtimeMap(self.realtime_ns, self.tb.monotonic_ns)
        self.map.sample()

    def read(self) -> list[Reading]:
        messages = self.client.read(READ_WAIT_S)
        self.map.sample()  # right after the read: the reports in it arrived before this sample
        out: list[Reading] = []
        for msg in messages:
            rep = pps_report(msg)
            if rep is None:
                continue
            second = rep.real_ns // NS
            repeat = self._last_second is not None and second == self._last_second
            if self._last_second is not None and second < self._last_second:
                continue  # a second already reported
            if repeat and second % DAY_S:
                continue  # the same edge reported again
            mono = self.map.to_monotonic(rep.clock_ns)
            if mono is None:
                continue  # counted by the map; a step shows as this sensor's incident
            if repeat and (self._last_mono is None or mono - self._last_mono < LEAP_EDGE_GAP_NS):
                continue  # the same edge again, not the next second's
            # A midnight second reported again for an edge a second later is a leap second: gpsd names 23:59:60 and
            # the 00:00:00 after it by one Unix second (POSIX). Both edges go to the clock, which knows the second
            # from the first (its prediction) and takes the repeat for what it is (sync.pairing).
            self._last_mono = mono
            lost = second - self._last_second - 1 if self._last_second is not None else 0
            self._last_second = second
            out.append(Reading(PPS, pps_record(self._seqno, lost if 0 < lost <= 3600 else 0, rep.edge_gnss_ns),
                               mono))
            self._seqno += 1
        self._quiet(self.tb.monotonic_ns(), bool(out))
        return out

    def incidents(self) -> dict[str, int]:
        counts = super().incidents()
        if self.map is not None:
            counts["edges left out: system clock stepped"] = self.map.refused_step
        return counts
