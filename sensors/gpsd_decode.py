"""gpsd's JSON reports (gpsd_json(5)) as the same navigation fixes the serial receiver gives.

gpsd describes one navigation epoch in several objects: a TPV (time, position, velocity and their error
estimates), a SKY (satellites and dilutions of precision) before or after it, and, for receivers that dribble
their epoch in several sentences, more than one TPV with the same ``time``, each repeating and completing the
last. :class:`GpsdEpochs` collects the objects of one epoch and turns them into one
:class:`~sensors.ublox_decode.GnssFix`, so the record on ``/gnss/fix`` does not depend on whether the receiver
was read on its serial port or through gpsd. What gpsd cannot tell (GPS time of week, week number) stays None.

An epoch is reported when an object of a later epoch arrives, or when its objects have stopped coming for a
settle time; a TPV of an epoch already reported is counted and dropped, never reported twice. A SKY goes with
the epoch of its time, or, when gpsd left its time behind (it keeps a sky view's time until the receiver
sends a new one), with the next epoch that has none.
Times are integer nanoseconds, Unix UTC for GNSS times and the caller's monotonic clock for arrival times:
this module reads no clock itself.
"""

from __future__ import annotations

import calendar
import collections
import math
import re
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from sensors.ublox_decode import NO_COURSE_SPEED_MPS, GnssFix

NS_PER_S = 1_000_000_000
SOURCE = "gpsd"

# gpsd prints ISO 8601 UTC with up to millisecond digits ("2023-06-28T14:52:12.000Z"); accept up to ns.
_ISO = re.compile(r"(\d{4})-(\d\d)-(\d\d)T(\d\d):(\d\d):(\d\d)(?:\.(\d{1,9}))?Z")


def number(value: object) -> float | None:
    """A finite JSON number, else None (gpsd omits unknown values; a bool or a string is not a number)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    result = float(value)
    return result if math.isfinite(result) else None


def integer(value: object) -> int | None:
    """A JSON number that is a whole number, else None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    if isinstance(value, float) and not (math.isfinite(value) and value.is_integer()):
        return None
    return int(value)


def parse_time_ns(value: object) -> int | None:
    """gpsd's ``time``: ISO 8601 UTC (protocol 3.10 and later) or Unix seconds (older daemons) -> Unix ns."""
    if isinstance(value, str):
        m = _ISO.fullmatch(value)
        if m is None:
            return None
        year, month, day, hour, minute, second = (int(g) for g in m.groups()[:6])
        if not (1 <= month <= 12 and 1 <= day <= 31 and hour < 24 and minute < 60 and second <= 60):
            return None
        try:
            whole = calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0))
        except (OverflowError, ValueError):
            return None
        frac = m.group(7) or ""
        return whole * NS_PER_S + int(frac.ljust(9, "0") or "0")
    seconds = number(value)
    if seconds is None or not 0 <= seconds < 1e11:
        return None
    return round(seconds * 1e6) * 1000  # a float of Unix seconds holds microseconds, not nanoseconds


@dataclass(frozen=True, slots=True)
class PpsReport:
    """gpsd's PPS object: one edge, stamped on the host's CLOCK_REALTIME and named in GNSS time.

    ``clock_ns`` is when the system clock saw the edge, ``real_ns`` the GNSS second the edge marks, and
    ``qerr_ps`` the receiver's quantisation error of that pulse when gpsd knows it (u-blox TIM-TP).
    """

    device: str | None
    real_ns: int
    clock_ns: int
    qerr_ps: int | None
    precision: int | None

    @property
    def edge_gnss_ns(self) -> int:
        """GNSS time of the edge itself: the pulse leaves qErr early of the second it marks (u-blox's sign)."""
        return self.real_ns - round((self.qerr_ps or 0) / 1000)


def pps_report(msg: Mapping[str, Any]) -> PpsReport | None:
    """A PPS object with all four time fields as whole numbers, else None (TOFF and others too)."""
    if msg.get("class") != "PPS":
        return None
    fields = [integer(msg.get(k)) for k in ("real_sec", "real_nsec", "clock_sec", "clock_nsec")]
    if any(f is None for f in fields):
        return None
    real_s, real_ns, clock_s, clock_ns = (int(f) for f in fields)  # type: ignore[arg-type]
    if not (0 <= real_ns < NS_PER_S and 0 <= clock_ns < NS_PER_S and real_s > 0 and clock_s > 0):
        return None
    device = msg.get("device")
    return PpsReport(device if isinstance(device, str) else None, real_s * NS_PER_S + real_ns,
                     clock_s * NS_PER_S + clock_ns, integer(msg.get("qErr")), integer(msg.get("precision")))


def toff_real_ns(msg: Mapping[str, Any]) -> int | None:
    """The epoch a TOFF object names (its ``real_sec``/``real_nsec``: the fix time gpsd latched), else None.

    gpsd sends a TOFF (to watchers that asked for ``pps``) when it latches an epoch's time, at the first sentence
    that carries it, and its TPV only when the cycle is over: 0.12 s against 0.92 s after the epoch for a receiver
    sending u-blox's factory NMEA at 9600 baud (gpsd 3.22, measured). The TOFF's arrival is when the epoch began
    to come in, which the clock's pairing needs (sync.pairing); gpsd sends none for its first fixes."""
    if msg.get("class") != "TOFF":
        return None
    sec, nsec = integer(msg.get("real_sec")), integer(msg.get("real_nsec"))
    if sec is None or nsec is None or sec <= 0 or not 0 <= nsec < NS_PER_S:
        return None
    return sec * NS_PER_S + nsec


def _first(tpv: Mapping[str, Any], *keys: str) -> float | None:
    for key in keys:
        value = number(tpv.get(key))
        if value is not None:
            return value
    return None


def sky_used(sky: Mapping[str, Any] | None) -> int | None:
    """Satellites in the solution: SKY's ``uSat``, else the satellites flagged ``used``."""
    if sky is None:
        return None
    used = integer(sky.get("uSat"))
    if used is not None and used >= 0:
        return used
    sats = sky.get("satellites")
    if isinstance(sats, list):
        return sum(1 for s in sats if isinstance(s, dict) and s.get("used") is True)
    return None


def fix_from_tpv(tpv: Mapping[str, Any], sky: Mapping[str, Any] | None = None, gst: Mapping[str, Any] | None = None,
                 receiver_figures: bool = False) -> GnssFix:
    """One epoch's TPV (and SKY and GST, when they came with it) as the fix the serial receiver would give.

    ``fix_mode`` is gpsd's ``mode`` (0 unknown, 1 no fix, 2 2D, 3 3D), and gpsd reports a position only
    with a 2D or 3D fix, so that is also the fix's validity; a 3D fix without any height is a 2D one to us (no
    height is made up). Heights: ``altHAE``, else ``altMSL`` plus ``geoidSep``; mean sea level from ``altMSL``,
    else the older ``alt``. Velocity: ``velN/E/D`` when gpsd has them, else speed and track over ground with
    ``climb`` upwards (down velocity NaN when there is none, as for NMEA).

    Accuracies are the receiver's own 1-sigma figures or nothing, as on the serial path, because the filter weighs
    a receiver's figures as they are and guesses by its own DOP model: a GST report's ``lat``, ``lon``, ``alt``
    (the NMEA GST standard deviations, as the serial path takes them); else, with ``receiver_figures`` (gpsd's
    u-blox driver, which passes hAcc, vAcc and sAcc on as ``eph``, ``epv``, ``eps``), those. Otherwise gpsd's
    figures are its own DOP x UERE model at 95 % (17 m for HDOP 0.9 where the receiver said 2.5 m): guesses,
    left out (None), so the filter's DOP model, which learns the receiver's scatter, takes the fix instead.
    """
    mode = integer(tpv.get("mode"))
    mode = mode if mode in (0, 1, 2, 3) else 0
    fixed = mode >= 2
    time_ns = parse_time_ns(tpv.get("time"))
    lat = number(tpv.get("lat"))
    lon = number(tpv.get("lon"))
    if (lat is not None and not -90.0 <= lat <= 90.0) or (lon is not None and not -180.0 <= lon <= 180.0):
        lat = lon = None
    sep = number(tpv.get("geoidSep"))
    hae = number(tpv.get("altHAE"))
    msl = _first(tpv, "altMSL", "alt")
    if hae is None and msl is not None and sep is not None:
        hae = msl + sep
    if msl is None and hae is not None and sep is not None:
        msl = hae - sep
    if mode == 3 and hae is None and msl is None and lat is not None:
        mode = 2  # a position, but no height came with it (gpsd's mode is the receiver's GSA)
    vel: tuple[float, float, float] | None = None
    vn, ve, vd = number(tpv.get("velN")), number(tpv.get("velE")), number(tpv.get("velD"))
    # The receiver's vertical velocity only: gpsd's ``climb`` without a ``velD`` is its own difference of altitudes,
    # repeated between epochs (+0.3 m/s for eight epochs of a receiver whose velD was within 0.04 of 0): no
    # measurement, and the filter took it as one. Missing, as NMEA's is.
    down = vd if vd is not None else math.nan
    if vn is not None and ve is not None:
        vel = (vn, ve, down)
    else:
        speed, track = number(tpv.get("speed")), number(tpv.get("track"))
        if speed is not None and track is not None:
            vel = (speed * math.cos(math.radians(track)), speed * math.sin(math.radians(track)), down)
        elif speed is not None and speed <= NO_COURSE_SPEED_MPS:  # standing: within a receiver's noise of 0
            vel = (0.0, 0.0, down)
        # A speed above that without a course (the receiver's heading invalid, gpsd leaves ``track`` out) is no
        # velocity: it was made one due north.
    h_acc = v_acc = s_acc = None
    g_lat, g_lon = (number(gst.get("lat")), number(gst.get("lon"))) if gst is not None else (None, None)
    if gst is not None and g_lat is not None and g_lon is not None:
        h_acc, v_acc = math.hypot(g_lat, g_lon), number(gst.get("alt"))
    elif receiver_figures:
        h_acc, v_acc, s_acc = number(tpv.get("eph")), number(tpv.get("epv")), number(tpv.get("eps"))
    if not fixed:
        lat = lon = hae = msl = None
        vel = None
    return GnssFix(
        source=SOURCE,
        itow_ms=None,
        week=None,
        time_utc_ns=time_ns,
        time_valid=time_ns is not None and fixed,
        fix_mode=mode,
        fix_ok=fixed and lat is not None and lon is not None,
        lat_deg=lat,
        lon_deg=lon,
        height_hae_m=hae,
        height_msl_m=msl,
        vel_ned_mps=vel,
        h_acc_m=h_acc,
        v_acc_m=v_acc,
        s_acc_mps=s_acc,
        num_sv=sky_used(sky),
        pdop=number(sky.get("pdop")) if sky is not None else None,
        hdop=number(sky.get("hdop")) if sky is not None else None,
        vdop=number(sky.get("vdop")) if sky is not None else None,
    )


@dataclass
class _Epoch:
    """The objects of one epoch so far: TPVs merged field by field (later ones win), the SKY and GST if any."""

    key: int | None  # TPV time, Unix ns; None for a TPV without time (no fix, time not known yet)
    tpv: dict[str, Any] = field(default_factory=dict)
    sky: dict[str, Any] | None = None
    last_ns: int = 0  # arrival of its latest object
    first_ns: int = 0  # arrival of its first TPV
    gst: dict[str, Any] | None = None

    def merge(self, tpv: Mapping[str, Any], t_ns: int, keep_first_figures: bool) -> None:
        """A later TPV of the epoch, field by field over the earlier ones (their accuracy figures kept if asked)."""
        kept = {k: self.tpv[k] for k in FIRST_FIGURES if k in self.tpv} if keep_first_figures else {}
        self.tpv.update(tpv)
        self.tpv.update(kept)
        self.last_ns = t_ns


@dataclass
class EpochCounters:
    """What the assembler did with the objects it was given."""

    tpv: int = 0
    sky: int = 0
    gst: int = 0
    epochs: int = 0
    late: int = 0  # TPVs of an epoch already reported
    lost_fix: int = 0  # no-fix TPVs under a fixed epoch's time: gpsd's word that the receiver lost it (dropped)
    stale_sky: int = 0  # SKYs with an older time than the epoch they went with
    other: int = 0  # objects of other classes (VERSION, DEVICES, TOFF, PPS, ATT, ...)


DAY_NS = 86_400 * NS_PER_S
# gpsd (3.22) stamps a leap second, 23:59:60, with the Unix time of the 00:00:00 after it: two epochs, a second
# apart, under one time. A TPV of a midnight second arriving this long after the first of that time is the second.
LEAP_REPEAT_NS = 600_000_000
# ... and an epoch of such a second is held this long after its first TPV before the settle time reports it (the
# repeat, 1 s later, then finds it open and marks it 23:59:60), on the days a leap second may end: the first of
# January, April, July and October (ITU-R TF.460; every one so far ended June or December). A day without one
# reports that second's epoch when the next second's TPV comes, about 1 s late, four times a year.
LEAP_HOLD_NS = 1_500_000_000
LEAP_MONTHS = (1, 4, 7, 10)
UNTIMED_CYCLE_SHARE = 0.9  # of the receiver's cycle, TPVs without a time are one epoch (GpsdEpochs._untimed_ns)
# The receiver's cycle as its fixes show it: the least interval between consecutive timed epochs over the last this
# many (gpsd's DEVICE says 1.00 s for any NMEA receiver, 10 Hz included; an epoch gpsd skipped doubles one interval).
CYCLE_INTERVALS_KEPT = 8
FIRST_FIGURES = ("eph", "epv", "eps")  # an epoch's accuracy figures: its first TPV's (GpsdEpochs._tpv)
UBLOX_DRIVER = "u-blox"  # gpsd's driver that passes the receiver's hAcc, vAcc, sAcc on as eph, epv, eps


def _has_fix(tpv: Mapping[str, Any]) -> bool:
    """Whether a TPV reports a 2D or 3D fix (gpsd's ``mode``; 0 and 1 are none)."""
    mode = integer(tpv.get("mode"))
    return mode is not None and mode >= 2


def _midnight_second(key: int | None) -> bool:
    """Whether a time falls in the first second of a UTC day, the second a leap second's repeat lands in."""
    return key is not None and key % DAY_NS < NS_PER_S


def _leap_may_end(key: int | None) -> bool:
    """Whether a time falls in the first second of a day a leap second may end before (LEAP_MONTHS' first)."""
    if not _midnight_second(key):
        return False
    assert key is not None
    day = time.gmtime(key // NS_PER_S)
    return day.tm_mday == 1 and day.tm_mon in LEAP_MONTHS


class GpsdEpochs:
    """TPV, SKY and GST objects -> one fix per epoch: ``push`` returns what an object completes, ``poll`` what the
    settle time completes, ``flush`` the rest. Each fix comes with the arrival time of its epoch's last TPV.

    DEVICE and DEVICES objects say which gpsd driver reads each receiver (whose accuracy figures are the
    receiver's own only with the u-blox driver, :func:`fix_from_tpv`) and its cycle. TPVs without a time (gpsd
    without a fix) carry nothing to tell epochs apart but their arrival: one record per cycle, as the serial path
    records one per epoch, never one for a whole outage."""

    def __init__(self, settle_ns: int = 300_000_000) -> None:
        self.settle_ns = settle_ns
        self._open: _Epoch | None = None
        self._sky: tuple[int | None, dict[str, Any]] | None = None  # a SKY waiting for its TPV: (time, object)
        self._gst: tuple[int | None, dict[str, Any]] | None = None  # a GST waiting for its TPV
        self._done: int | None = None  # time of the last epoch reported
        self._done_first_ns = 0  # arrival of its first TPV
        self._drivers: dict[str, str] = {}  # device path -> gpsd driver
        self._cycles: dict[str, float] = {}  # device path -> the receiver's cycle, s
        self._last_timed: int | None = None  # time of the last timed epoch reported ...
        self._intervals: collections.deque[int] = collections.deque(maxlen=CYCLE_INTERVALS_KEPT)  # ... and before
        self.counters = EpochCounters()

    def push(self, msg: Mapping[str, Any], t_ns: int) -> list[tuple[GnssFix, int]]:
        kind = msg.get("class")
        if kind == "TPV":
            self.counters.tpv += 1
            return self._tpv(msg, t_ns)
        if kind == "SKY":
            self.counters.sky += 1
            return self._skyview(msg)
        if kind == "GST":
            self.counters.gst += 1
            self._noise(msg)
            return []
        self.counters.other += 1
        if kind == "DEVICE":
            self._device(msg)
        elif kind == "DEVICES" and isinstance(msg.get("devices"), list):
            for device in msg["devices"]:
                if isinstance(device, Mapping):
                    self._device(device)
        return []

    def poll(self, t_ns: int) -> list[tuple[GnssFix, int]]:
        """The open epoch, once nothing was added to it for the settle time (a possible leap second's, once
        LEAP_HOLD_NS passed too)."""
        due = self.due_ns()
        if due is not None and t_ns >= due:
            return self._finish()
        return []

    def due_ns(self) -> int | None:
        """When ``poll`` will report the open epoch (arrival clock), or None with nothing open."""
        open_ = self._open
        if open_ is None:
            return None
        due = open_.last_ns + self.settle_ns
        if _leap_may_end(open_.key):  # its repeat, if it comes, must find it open
            due = max(due, open_.first_ns + LEAP_HOLD_NS)
        return due

    def flush(self) -> list[tuple[GnssFix, int]]:
        return self._finish()

    def _device(self, device: Mapping[str, Any]) -> None:
        path, driver, cycle = device.get("path"), device.get("driver"), number(device.get("cycle"))
        if not isinstance(path, str):
            return
        if isinstance(driver, str) and driver:
            self._drivers[path] = driver
        if cycle is not None and cycle > 0:
            self._cycles[path] = cycle

    def _of_device(self, table: Mapping[str, Any], tpv: Mapping[str, Any]) -> Any:
        """A TPV's device's entry: by its ``device``, else the one gpsd has when it has one (old or replayed logs)."""
        device = tpv.get("device")
        if isinstance(device, str) and device in table:
            return table[device]
        values = set(table.values())
        return values.pop() if len(values) == 1 else None

    def _untimed_ns(self, tpv: Mapping[str, Any]) -> int:
        """How long TPVs without a time may still belong to one epoch: nine tenths of the receiver's cycle (else
        the settle time). gpsd reports such a TPV per sentence, and a burst may fill the cycle (u-blox's factory
        NMEA at 9600 baud: 0.9 s of a second); at half the cycle, at most the settle time, a second's burst was
        cut in two records (gpsd 3.22, 1 Hz: a no-fix record at .23 and another at .30 of every second).

        The cycle is gpsd's DEVICE figure or, where shorter, the one the receiver's timed epochs showed: gpsd 3.22
        gives 1.00 s for a 10 Hz NMEA receiver, and a loss of fix and time there was one record a second."""
        cycle = self._of_device(self._cycles, tpv)
        cycle_ns = None if cycle is None else cycle * NS_PER_S
        if self._intervals:
            seen = min(self._intervals)
            cycle_ns = seen if cycle_ns is None else min(cycle_ns, seen)
        return self.settle_ns if cycle_ns is None else round(cycle_ns * UNTIMED_CYCLE_SHARE)

    def _learn_cycle(self, key: int | None) -> None:
        """An epoch reported: with the last timed one before it, an interval of the receiver's cycle (only those
        up to a second, or up to gpsd's cycle where it has one: a loss between them is no cycle)."""
        if key is None:
            return
        last, self._last_timed = self._last_timed, key
        if last is None or key <= last:
            return
        longest = max(self._cycles.values(), default=1.0) * NS_PER_S
        if key - last <= longest:
            self._intervals.append(key - last)

    def _tpv(self, msg: Mapping[str, Any], t_ns: int) -> list[tuple[GnssFix, int]]:
        key = parse_time_ns(msg.get("time"))
        out: list[tuple[GnssFix, int]] = []
        open_ = self._open
        leap = False
        if open_ is not None and open_.key == key:
            if key is None and t_ns - open_.first_ns >= self._untimed_ns(msg):
                pass  # another cycle's report without a time: an epoch of its own
            elif _has_fix(open_.tpv) and not _has_fix(msg):
                # gpsd's first report after the receiver's time fields went empty carries the last epoch's time
                # with mode 1 and no position (gpsd 3.22 at 5-10 Hz, 89 ms after that epoch's 3D report): merged,
                # it turned the epoch's fix into a no-fix without a time. The fix stands; the loss is the next
                # epoch's to say (gpsd's next report, without a time). Before the leap test: no leap repeats
                # a fix as a no-fix.
                self.counters.lost_fix += 1
                return out
            elif _midnight_second(key) and t_ns - open_.first_ns >= LEAP_REPEAT_NS:
                leap = True  # the open epoch was 23:59:60 under 00:00:00's time; this is 00:00:00
            else:
                # The epoch's first TPV carries the receiver's own figures (u-blox driver: NAV-PVT's hAcc, vAcc,
                # sAcc); gpsd's later report of the same epoch (at 5 Hz, after its cycle's NMEA) carries its own
                # model's, 80 times the receiver's sAcc: the first ones stand.
                open_.merge(msg, t_ns, keep_first_figures=True)
                return out
        elif key is not None and self._done == key and not (
                _midnight_second(key) and t_ns - self._done_first_ns >= LEAP_REPEAT_NS):
            self.counters.late += 1  # a TPV completing an epoch that was already reported
            return out
        elif open_ is not None and open_.key is None and key is not None and _has_fix(open_.tpv) and \
                _has_fix(msg) and t_ns - open_.first_ns < self._untimed_ns(msg):
            # The same burst, its time known now: gpsd's first report of an NMEA receiver comes at its GGA, before
            # any RMC gave the date, so without a time (gpsd 3.22: a 3D fix 67 ms before the timed TPV of the
            # same epoch). Reported apart, it was an epoch of its own: a fix without a time, then the same again.
            # The timed report's figures, and its arrival as the epoch's first (the leap test counts from it); a
            # no-fix report without a time stays a record of its own.
            open_.merge(msg, t_ns, keep_first_figures=False)
            open_.key, open_.first_ns = key, t_ns
            if self._gst is not None and self._gst[0] == key:
                open_.gst, self._gst = self._gst[1], None
            return out
        out += self._finish(leap_second=leap)
        epoch = _Epoch(key, dict(msg), None, t_ns, t_ns)
        pending = self._sky
        if pending is not None and (pending[0] is None or key is None or pending[0] <= key):
            epoch.sky = pending[1]
        self._sky = None
        if self._gst is not None and self._gst[0] == key:
            epoch.gst = self._gst[1]
        self._gst = None
        self._open = epoch
        return out

    def _noise(self, msg: Mapping[str, Any]) -> None:
        """A GST report (the receiver's NMEA GST): it goes with the epoch of its time, before or after its TPV."""
        key = parse_time_ns(msg.get("time"))
        if self._open is not None and key is not None and key == self._open.key:
            self._open.gst = dict(msg)
        else:
            self._gst = (key, dict(msg))

    def _skyview(self, msg: Mapping[str, Any]) -> list[tuple[GnssFix, int]]:
        key = parse_time_ns(msg.get("time"))
        open_ = self._open
        if open_ is not None and (key is None or key == open_.key):
            open_.sky = {**open_.sky, **msg} if open_.sky is not None else dict(msg)
            return []
        if open_ is not None and key is not None and (open_.key is None or key > open_.key):
            out = self._finish()  # the next epoch has begun: this one is complete
            self._sky = (key, dict(msg))
            return out
        # Older than the open epoch, or nothing open: gpsd keeps a sky view's time until the receiver updates it,
        # so even an old one is the latest sky there is; the epoch that has none takes it.
        if open_ is not None or (key is not None and self._done is not None and key <= self._done):
            self.counters.stale_sky += 1
        if open_ is not None and open_.sky is None:
            open_.sky = dict(msg)
        else:
            self._sky = (key, dict(msg))
        return []

    def _finish(self, leap_second: bool = False) -> list[tuple[GnssFix, int]]:
        epoch, self._open = self._open, None
        if epoch is None:
            return []
        self._done = epoch.key
        self._done_first_ns = epoch.first_ns
        self.counters.epochs += 1
        self._learn_cycle(epoch.key)
        fix = fix_from_tpv(epoch.tpv, epoch.sky, epoch.gst,
                           receiver_figures=self._of_device(self._drivers, epoch.tpv) == UBLOX_DRIVER)
        if leap_second and fix.time_utc_ns is not None:
            fix = replace(fix, leap_second=True)
        return [(fix, epoch.last_ns)]
