"""Sampler threads: one per sensor, owning timing, retries and reconnects; drivers stay simple.

A periodic sampler keeps deadlines on the monotonic clock (period n is due at start + n * period), so sleeping
after slow work never makes it drift; a sample taken after its deadline is counted late and periods that
passed unsampled are counted as missed, never silently shifted. Any :class:`SensorError` closes the source
and retries it with a growing back-off while every other thread goes on.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from bisect import bisect_left, bisect_right
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from logger.recording.topics import GAP_PERIODS
from logger.runtime.journal import PROBLEM_LOG_REPEAT_S, RateLimiter, problem_key
from logger.runtime.timebase import TimeBase
from sensors.errors import DeviceNotFound, NoData, SensorError

log = logging.getLogger(__name__)


@dataclass(slots=True)
class Reading:
    """One message for the recorder: the source fills topic, payload and the acquisition time."""

    topic: str
    payload: dict[str, Any]
    t_mono_ns: int
    stamped: bool = True  # False for messages that carry no sensor time (e.g. raw receiver bytes)
    # A batch (one FIFO read): each sample's acquisition time, oldest first; t_mono_ns is then the first's. The
    # record is one message whatever the count, which is what keeps a 1 kHz IMU cheap.
    times: list[int] | None = None


class Source(ABC):
    """A sensor as a sampler sees it: the adapters in :mod:`logger.runtime.sources` wrap each driver.

    The whole contract is here, its optional parts with their defaults (as python-can's ``BusABC`` does), so a
    sampler never probes a source for what it might have.
    """

    name: str = ""
    origin: str = ""  # where the samples come from, for sensors with more than one kind of source ("gpsd ...")
    sample_topic: str | None = None  # the topic whose records are this sensor's samples; None: every stamped one

    @abstractmethod
    def open(self) -> None:
        """Open and set up the device; raises :class:`SensorError` (``DeviceNotFound`` when it is absent)."""

    @abstractmethod
    def read(self) -> list[Reading]:
        """One sample (periodic sensors) or what arrived (event sensors, waiting at most a short while)."""

    @abstractmethod
    def close(self) -> None:
        """Release the device; never raises for a device that is already gone."""

    def incidents(self) -> dict[str, int]:
        """Cumulative counts of what the device recovered from by itself, for the device opened now.

        An adapter that reset itself and was set up again, bytes on a serial line that framed as nothing: the
        device misbehaves without failing a read. Keys are what a person would call them ("ELM327 resets"); the
        sampler turns increases into journal lines and a status problem, so the fault is seen while it lasts
        although every read succeeded. Most devices have none.
        """
        return {}


INCIDENT_SHOW_S = 30.0  # how long an incident stays among the status problems after it last grew


Sink = Callable[[Reading], None]


@dataclass
class SensorHealth:
    """Counters a sensor thread keeps for ``logger status`` and ``/health``; read from other threads."""

    name: str
    rate_hz: float | None  # configured; None for event-driven sensors
    state: str = "starting"  # starting, ok, no-data, retrying, missing, stopped
    samples: int = 0
    errors: int = 0
    late: int = 0
    missed: int = 0
    # Of those, periods missed after a read the host made late by half a period or more (a simulated drive only:
    # paced, it measures that): what a faster host, or a slower pace, would have sampled.
    missed_host: int = 0
    # A FIFO's samples an overflow destroyed (the driver's count, from the time since the last read): a FIFO read
    # late loses nothing until then, so these, not its missed reads, are what it did not deliver.
    samples_lost: int = 0
    delayed: int = 0  # samples finished more than half a period after their deadline (host scheduling)
    gaps: int = 0
    reconnects: int = 0
    last_error: str = ""
    origin: str = ""  # where the samples come from, for sensors with more than one kind of source
    last_sample_mono_ns: int | None = None
    first_sample_mono_ns: int | None = None
    heartbeat_mono_ns: int = 0
    ok_since_mono_ns: int = 0  # when the device was last opened (a silence is counted from there before any sample)
    incidents: dict[str, int] = field(default_factory=dict)  # totals since start, by kind
    last_incident: str = ""
    last_incident_mono_ns: int | None = None
    _recent: deque[int] = field(default_factory=lambda: deque(maxlen=2048))

    def measured_rate_hz(self, now_ns: int, window_s: float = 10.0) -> float | None:
        """Samples a second over the last ``window_s``, or over three of the configured intervals when those are
        longer (a barometer at 0.1 Hz has one sample in 10 s, and a rate needs two). 0.0 when none came in it; None
        when one did (the first after an open): no rate can be measured from one time, and it is not none. The
        times arrive in order (a FIFO read's stamp the clock steered back moves the window's edge by a sample or
        so), so the window's first one is found by bisection in a copy taken at once (the sampler thread appends
        meanwhile): at 1 kHz the 2048 kept times were walked one by one at every snapshot."""
        if self.rate_hz:
            window_s = max(window_s, 3.0 / self.rate_hz)
        recent = list(self._recent)
        first = bisect_left(recent, now_ns - int(window_s * 1e9))
        n = len(recent) - first
        if n == 0:
            return 0.0
        # Samples read together share their time: those at the window's first time start it as one, since the
        # rate is of the intervals after it (a receiver's first two fixes came in one read: 2.1/1 Hz at start,
        # 1.0 only after the 10 s window had passed them).
        first = bisect_right(recent, recent[first]) - 1
        n = len(recent) - first
        span = recent[-1] - recent[first]
        return (n - 1) / (span / 1e9) if n > 1 and span > 0 else None

    def snapshot(self, now_ns: int) -> dict[str, Any]:
        age = (now_ns - self.last_sample_mono_ns) / 1e9 if self.last_sample_mono_ns is not None else None
        return {"name": self.name, "state": self.state, "rate_hz": self.rate_hz,
                "measured_rate_hz": None if (rate := self.measured_rate_hz(now_ns)) is None else round(rate, 3),
                "last_sample_age_s": age,
                "samples": self.samples, "errors": self.errors, "late": self.late, "missed": self.missed,
                "delayed": self.delayed, "gaps": self.gaps, "reconnects": self.reconnects,
                "samples_lost": self.samples_lost,
                "last_error": self.last_error, "origin": self.origin,
                "incidents": dict(self.incidents), "last_incident": self.last_incident,
                "last_incident_age_s": (now_ns - self.last_incident_mono_ns) / 1e9
                if self.last_incident_mono_ns is not None else None}

    def recent_incident(self, now_ns: int) -> str | None:
        """The last incident while it is fresh enough to be a present problem."""
        if self.last_incident_mono_ns is None or now_ns - self.last_incident_mono_ns > INCIDENT_SHOW_S * 1e9:
            return None
        return self.last_incident


class Sampler(threading.Thread):
    """Runs one source: periodic at ``rate_hz``, or as its events arrive when ``rate_hz`` is None."""

    BACKOFF_START_S = 0.5
    BACKOFF_MAX_S = 10.0
    # A device that worked this long (drive time) before an error is opened again at once, the first time: one NACK
    # on the I2C bus otherwise cost the IMU the back-off's half second of samples (500 at 1 kHz) on top of the
    # reopening. A device that fails again sooner backs off as usual.
    QUICK_RETRY_AFTER_S = 5.0
    LOG_REPEAT_S = PROBLEM_LOG_REPEAT_S

    def __init__(self, source: Source, sink: Sink, timebase: TimeBase, rate_hz: float | None,
                 stop: threading.Event, expected_hz: float | None = None, gap_factor: float = GAP_PERIODS) -> None:
        super().__init__(name=f"sampler-{source.name}", daemon=True)
        self.source = source
        self.sink = sink
        self.tb = timebase
        self.rate_hz = rate_hz
        self.stop_event = stop
        expected_hz = expected_hz or rate_hz
        self.health = SensorHealth(source.name, expected_hz, origin=source.origin)
        self._gap_ns = int(gap_factor * 1e9 / expected_hz) if expected_hz else None
        self._log_limiter = RateLimiter(1, self.LOG_REPEAT_S, max_keys=64)
        # Which readings are this sensor's samples for rates and gaps (a receiver also sends time pulses).
        self._sample_topic = source.sample_topic
        self._incident_base: dict[str, int] | None = None  # counts of the device opened now, at its first read
        self._delivered_ns: int | None = None  # when the device opened now first delivered (None: not yet)
        self._back_after: str | None = None  # the error a reopened device is back after, once it delivers
        self._incidents_of = source.incidents

    # The thread body: open, sample until an error, back off, reopen.
    def run(self) -> None:
        backoff = self.BACKOFF_START_S
        opened_once = False
        while not self.stop_event.is_set():
            self.health.heartbeat_mono_ns = self.tb.monotonic_ns()
            try:
                self.source.open()
            except Exception as exc:  # drivers raise SensorError; anything else must not end the thread either
                if not isinstance(exc, SensorError):
                    log.debug("%s: unexpected error while opening", self.source.name, exc_info=True)
                    exc = SensorError(f"cannot open: {type(exc).__name__}: {exc}")
                self._close()
                self._failed(exc, missing=not opened_once or isinstance(exc, DeviceNotFound))
                if self.tb.wait(self.stop_event, backoff):
                    break
                backoff = min(backoff * 2, self.BACKOFF_MAX_S)
                continue
            # Opened is not yet back: an ELM327 opens with the ignition off (its set-up keeps the vehicle's silence
            # for the reads), a CAN interface opens while the bus is off. The reconnection is counted and logged,
            # and the back-off starts over, once the device delivers (_read_once); until then a device that
            # fails again backs off further instead of being set up again every half second, "back after" each time.
            self._back_after = (self.health.last_error or "an error") if opened_once else None
            self.health.last_error = ""  # open again: no error now (a PPS line without a fix delivers nothing for
            # long, and kept showing the read error it was opened again after, as if present)
            self._delivered_ns = None
            opened_once = True
            self._incident_base = None
            self.health.state = "ok"
            self.health.ok_since_mono_ns = self.tb.monotonic_ns()
            try:
                if self.rate_hz:
                    self._periodic()
                else:
                    self._events()
            except SensorError as exc:
                self._failed(exc, missing=isinstance(exc, DeviceNotFound))
                self._close()
                delivered = self._delivered_ns
                if delivered is None:
                    wait_s, backoff = backoff, min(backoff * 2, self.BACKOFF_MAX_S)
                else:
                    worked_s = (self.tb.monotonic_ns() - delivered) / 1e9
                    wait_s = backoff = self.BACKOFF_START_S  # it delivered: a new fault, backed off from the start
                    if worked_s >= self.QUICK_RETRY_AFTER_S:
                        wait_s = 0.0
                if self.tb.wait(self.stop_event, wait_s):
                    break
                continue
            except Exception as exc:  # a bug in a driver must not take the daemon down: log it, retry
                log.exception("%s: unexpected error", self.source.name)
                self._failed(SensorError(f"internal error: {type(exc).__name__}: {exc}"), missing=False)
                self._close()
                if self.tb.wait(self.stop_event, self.BACKOFF_MAX_S):
                    break
                continue
        self._close()
        self.health.state = "stopped"

    def _periodic(self) -> None:
        assert self.rate_hz
        period_ns = round(1e9 / self.rate_hz)
        start = self.tb.monotonic_ns()
        n = 0
        while not self.stop_event.is_set():
            due = start + n * period_ns
            now = self.tb.monotonic_ns()
            woke = due  # already overdue: the previous read's overrun, counted below, is no late wake-up
            if due > now:
                if self.tb.wait_until(self.stop_event, due):
                    return
                woke = self.tb.monotonic_ns()
            host_late = 0
            if self.tb.paced:
                cpu0 = time.thread_time_ns()
                self._read_once()
                host_late = self._report_lateness(woke - due, time.thread_time_ns() - cpu0, period_ns)
            else:
                self._read_once()
            n += 1
            after = self.tb.monotonic_ns()
            if after - due > period_ns // 2:
                # Its stamp may then sit more than 1.5 periods after the previous one: say so, so that the
                # irregularity a loaded host causes is counted rather than found later in the file.
                self.health.delayed += 1
            if after > start + n * period_ns:
                # This sample ended after the next one was due: count it late; skip periods already gone.
                self.health.late += 1
                next_n = int((after - start) // period_ns) + 1  # first deadline still ahead
                self.health.missed += next_n - n
                if 2 * host_late >= period_ns:
                    self.health.missed_host += next_n - n
                n = next_n

    def _report_lateness(self, woke_late_ns: int, cpu_ns: int, period_ns: int) -> int:
        """What the host made this sample late by, for a paced simulated drive: how late the thread woke, or the
        processor time its read took (host ns, so at the drive's scale), whichever is more. Not the read's whole
        duration: a device's own waits (a conversion, an adapter's answer) are drive time, which no pace shortens.
        A period of either loses the next sample. Returns that lateness (drive ns)."""
        late = max(woke_late_ns, round(cpu_ns * self.tb.scale))
        self.tb.late(late, period_ns)
        return late

    def _events(self) -> None:
        while not self.stop_event.is_set():
            self._read_once()

    def _read_once(self) -> None:
        """One read; 'no data now' (engine off, no answer yet) keeps the device open and the schedule going."""
        try:
            readings = self.source.read()
        except NoData as exc:
            self._failed(exc, missing=False, state="no-data")
            self._check_incidents()
            return
        self._check_incidents()
        if self.health.state != "ok":  # data again after 'no data': recovered, the error is no present one
            self.health.state, self.health.last_error = "ok", ""
            self.health.ok_since_mono_ns = self.tb.monotonic_ns()
        if readings and self._delivered_ns is None:
            self._delivered_ns = self.tb.monotonic_ns()
            if self._back_after is not None:
                self.health.reconnects += 1
                self._log(f"back after: {self._back_after}")
                self._back_after = None
        self._deliver(readings)

    def _deliver(self, readings: list[Reading]) -> None:
        h = self.health
        h.heartbeat_mono_ns = self.tb.monotonic_ns()
        for r in readings:
            if r.stamped and (self._sample_topic is None or r.topic == self._sample_topic):
                times = r.times
                if times is not None and not times:
                    continue  # an empty FIFO read (after an overflow): nothing to count or record
                first, last_t = (r.t_mono_ns, r.t_mono_ns) if times is None else (times[0], times[-1])
                last = h.last_sample_mono_ns
                # Within a batch the samples sit one chip period apart by construction: a gap is between reads.
                if last is not None and self._gap_ns and first - last > self._gap_ns:
                    h.gaps += 1
                h.last_sample_mono_ns = last_t
                if h.first_sample_mono_ns is None:
                    h.first_sample_mono_ns = first
                if times is None:
                    h._recent.append(first)
                    h.samples += 1
                else:
                    h._recent.extend(times)
                    h.samples += len(times)
                    h.samples_lost += r.payload.get("lost") or 0
            self.sink(r)

    def _check_incidents(self) -> None:
        """Count what the device recovered from by itself; the first read after an open sets the base, since
        a line opened mid-frame or an adapter's start-up is not a fault."""
        counts = self._incidents_of()
        base = self._incident_base
        if not counts and base is not None and not base:
            return  # a device with nothing to count (most): no work per read on the sensor thread
        self._incident_base = dict(counts)
        if base is None:
            return
        h = self.health
        for kind, count in counts.items():
            new = count - base.get(kind, 0)
            if new <= 0:
                continue
            total = h.incidents[kind] = h.incidents.get(kind, 0) + new
            h.last_incident = f"{kind}: {new} more ({total} since start)"
            h.last_incident_mono_ns = self.tb.monotonic_ns()
            self._log(h.last_incident)

    def _failed(self, exc: SensorError, missing: bool, state: str | None = None) -> None:
        h = self.health
        h.errors += 1
        message = str(exc) or type(exc).__name__
        self._log(message)
        h.last_error = message
        h.state = state or ("missing" if missing else "retrying")
        h.heartbeat_mono_ns = self.tb.monotonic_ns()

    def _log(self, message: str) -> None:
        """Warn once per distinct message per ``LOG_REPEAT_S``: a flapping sensor must not flood the journal. The
        line that gets through says how many repeats of that message were held back since it was last logged."""
        key, now = problem_key(message), time.monotonic()
        allowed, held = self._log_limiter.allow(key, now)
        if not allowed:
            return
        self._log_limiter.prune(now, {key})
        extra = f" ({held} repeats not logged)" if held else ""
        log.warning("%s: %s%s", self.source.name, message, extra)

    def _close(self) -> None:
        try:
            self.source.close()
        except Exception:  # closing a broken device must not raise out of the thread
            log.debug("%s: error while closing", self.source.name, exc_info=True)


def wait_until(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.01) -> bool:
    """Poll ``predicate`` on the host clock; for tests and start-up checks."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(poll_s)
    return predicate()
