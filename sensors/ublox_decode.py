"""u-blox GNSS decoding: navigation epochs from the frames of a mixed UBX + NMEA (+ RTCM3) stream.

One receiver speaks several dialects over its life: Antaris 4 and u-blox 5/6 send NAV-SOL, NAV-POSLLH
and NAV-VELNED as separate messages, u-blox 7 and later NAV-PVT, timing firmware NAV-TIMEUTC and TIM-TP,
and a receiver left at factory settings only NMEA. :class:`GnssDecoder` turns all of them into the same
:class:`GnssFix` per epoch, so nothing above it cares which receiver is fitted.

A receiver sends one epoch as a burst of messages that share a time tag (UBX iTOW, NMEA time of day).
The decoder collects a burst and reports the epoch when the burst is over: at UBX NAV-EOE, at the
message that closed the previous burst (learned, because which messages are enabled differs per
receiver), or at the first message of the next epoch. UBX solutions win over NMEA ones when a
receiver sends both, because they carry more digits and explicit validity flags.

Units are SI; times are integer nanoseconds (``*_ns``) or milliseconds of GPS week (``itow_ms``).
"""

from __future__ import annotations

import calendar
import datetime as dt
import math
import re
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import Any

from sensors.geodesy import (
    GPS_EPOCH_UNIX_S,
    NS_PER_S,
    WEEK_S,
    ecef_to_geodetic,
    ecef_velocity_to_ned,
    gps_to_unix_ns,
)
from sensors.ublox_frames import KIND_NMEA, KIND_UBX, Frame

NS_PER_MS = 1_000_000
KNOT_MPS = 1852.0 / 3600.0
# A speed reported without a course (the receiver's heading invalid) is a standing receiver's noise up to this: a
# velocity of nought then, within it of the truth. Faster without a course, no velocity (its direction unknown).
# Measured: in the 36 GPSD u-blox captures every RMC with a fix and an empty course had at most 0.20 m/s (lea-5h;
# 0.13 ublox-8, 0.08 neo-m8n, the F9s under 0.06).
NO_COURSE_SPEED_MPS = 0.25
# A receiver's GST (its accuracies) stands this long for the epochs after it that have none of their own: one sent
# once a second with fixes at 5 or 10 Hz, or after the burst's learnt end.
GST_HOLD_S = 1.0
NMEA_EPOCHS_KEPT = 4  # the last NMEA epochs whose sentences tell a burst's regular end and tail


@dataclass(frozen=True, slots=True)
class GnssFix:
    """One navigation solution (one epoch) as the receiver reported it.

    ``fix_mode`` follows gpsd: 1 no fix, 2 2D, 3 3D, and 0 when the receiver sent a position without
    saying what kind of fix it is (NAV-POSLLH alone). Dead-reckoning-only fixes count as 2D and
    time-only (surveyed-in) fixes as 3D, as gpsd does. ``fix_ok`` is the receiver's own verdict (UBX
    gnssFixOK, NMEA status A): a fix outside its DOP/accuracy masks has a mode but is not OK.

    ``time_utc_ns`` is set when the receiver says date and time are valid; ``time_valid`` additionally
    requires the time to be fully resolved (UBX) or the fix to be valid (NMEA), i.e. fit for clock
    discipline. ``vel_ned_mps[2]`` is NaN when the source has no vertical velocity (NMEA, HNR-PVT).
    Accuracies are the receiver's estimates (UBX hAcc/vAcc/sAcc, NAV-SOL's 3D pAcc for both when no
    NAV-POSLLH came with it, NMEA GST standard deviations).
    """

    source: str
    itow_ms: int | None
    week: int | None
    time_utc_ns: int | None
    time_valid: bool
    fix_mode: int
    fix_ok: bool
    lat_deg: float | None
    lon_deg: float | None
    height_hae_m: float | None
    height_msl_m: float | None
    vel_ned_mps: tuple[float, float, float] | None
    h_acc_m: float | None
    v_acc_m: float | None
    s_acc_mps: float | None
    num_sv: int | None
    pdop: float | None
    hdop: float | None = None  # horizontal and vertical DOPs, where the receiver gives them (NAV-DOP, GGA, GSA)
    vdop: float | None = None
    # The epoch is 23:59:60 UTC, an inserted leap second (the receiver's second field read 60). Unix time has no
    # such second: ``time_utc_ns`` is then POSIX's value for it, that of the 00:00:00 that follows, so the flag is
    # what tells the two epochs (and the clock, which second a PPS edge marks) apart.
    leap_second: bool = False
    # The decoder's ``read_mark`` when the epoch's first message came (GnssReceiver: the read of the port it came
    # in): the reader knows when that read was, which is when the epoch began to arrive. A receiver at 9600 baud
    # sending u-blox's factory NMEA finishes an epoch more than a second after its pulse, so the time it ends says
    # nothing of which pulse it follows; the time it begins does. None where nobody marks the reads.
    opened_mark: int | None = None
    # Whether the receiver's leap-second count is the broadcast one (UBX NAV-TIMEGPS leapSValid, NAV-TIMEUTC
    # validUTC in the same epoch); False: its UTC uses the firmware's default count, until the almanac brings it
    # (a cold start's first 12.5 min at most), and may be whole seconds off. None: the receiver did not say (NMEA).
    leap_known: bool | None = None


@dataclass(frozen=True, slots=True)
class TimePulse:
    """UBX TIM-TP: the time of the NEXT time pulse (PPS edge), sent ahead of the edge.

    ``time_base`` is "gnss" (``tow_ms``/``week`` count in the GNSS time scale ``gnss`` names) or
    "utc" (they count UTC weeks). ``qerr_ps`` is the quantisation error of that pulse: the edge comes
    ``qerr_ps`` early or late against the ideal instant, which a sawtooth-corrected sync removes.
    """

    tow_ms: int
    tow_sub_ms: float
    week: int
    qerr_ps: int
    qerr_valid: bool
    time_base: str
    utc_available: bool
    gnss: str | None

    @property
    def tow_ns(self) -> int:
        """Time of week of the pulse in ns, sub-millisecond part included."""
        return self.tow_ms * NS_PER_MS + round(self.tow_sub_ms * NS_PER_MS)


@dataclass(frozen=True, slots=True)
class GnssTime:
    """UBX NAV-TIMEGPS / NAV-TIMEUTC: GNSS time of an epoch, leap seconds and their validity.

    ``time_utc_ns`` is the epoch in Unix ns UTC when the receiver knows it (NAV-TIMEUTC validUTC, or
    NAV-TIMEGPS with valid week, time of week and leap seconds).
    """

    source: str
    itow_ms: int
    ftow_ns: int
    week: int | None
    leap_s: int | None
    time_utc_ns: int | None
    tow_valid: bool
    week_valid: bool
    leap_valid: bool
    utc_valid: bool
    t_acc_ns: int | None


GnssItem = GnssFix | TimePulse | GnssTime


# --------------------------------------------------------------------------------------------------
# Small helpers: library objects carry '' for empty NMEA fields and differ in names between versions.


def _num(value: object) -> float | None:
    if isinstance(value, bool) or value is None or value == "":
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


def _int(value: object) -> int | None:
    number = _num(value)
    return None if number is None else int(number)


def _attr(msg: object, *names: str, default: object = None) -> object:
    for name in names:
        if hasattr(msg, name):
            return getattr(msg, name)
    return default


def _flag(msg: object, *names: str) -> bool:
    return bool(_int(_attr(msg, *names, default=0)) or 0)


def _unix_ns(year: int, month: int, day: int, hour: int, minute: int, second: int, nano: int) -> int | None:
    """UTC calendar time -> Unix ns; None for a date that does not exist (a receiver still starting)."""
    try:
        dt.datetime(year, month, day, hour, minute, min(second, 59))
    except ValueError:
        return None
    return calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0)) * NS_PER_S + nano


def _ubx_utc_ns(msg: Any) -> int | None:
    """The UTC fields of NAV-PVT, NAV-PVAT, HNR-PVT or NAV-TIMEUTC -> Unix ns (pyubx2 names the second
    ``second`` in some messages, ``sec`` in others)."""
    return _unix_ns(
        int(msg.year), int(msg.month), int(msg.day),
        int(msg.hour), int(msg.min), int(_attr(msg, "second", "sec")),
        int(msg.nano),
    )


def _ubx_leap(msg: Any) -> bool:
    """Whether a UBX message's UTC second is 60: the epoch is an inserted leap second (23:59:60)."""
    return _int(_attr(msg, "second", "sec")) == 60


_LEAP_TOD = re.compile(r"(\d\d)(\d\d)60(\.\d+)?")


def _leap_time_of_day(raw: bytes, kind: str) -> float | None:
    """The time of day (s, 86400 and up) of an NMEA sentence stamped hhmm60: an inserted leap second, which
    pynmeagps cannot parse (it gives no time at all), so the sentence would be lost with its epoch. Only 23:59:60
    is one (a leap second ends a UTC day); anything else stays a garbled time."""
    fields = raw.split(b"*", 1)[0].decode("ascii", "replace").split(",")
    index = 5 if kind == "GLL" else 1
    m = _LEAP_TOD.fullmatch(fields[index]) if len(fields) > index else None
    if m is None or (m.group(1), m.group(2)) != ("23", "59"):
        return None
    return 86_400.0 + (float(m.group(3)) if m.group(3) else 0.0)


def _ubx_llh(msg: Any) -> tuple[float, float, float, float]:
    """(lat_deg, lon_deg, height_hae_m, height_msl_m) of a UBX message with lat, lon, height, hMSL (mm)."""
    return float(msg.lat), float(msg.lon), msg.height / 1000.0, msg.hMSL / 1000.0


def _zda_date(msg: Any) -> dt.date | None:
    """The date of an NMEA ZDA sentence; None when a field is empty or the date does not exist."""
    year, month, day = _int(_attr(msg, "year")), _int(_attr(msg, "month")), _int(_attr(msg, "day"))
    try:
        return dt.date(year, month, day) if year and month and day else None
    except ValueError:
        return None


def _same_itow(a: float | None, b: float | None) -> bool:
    """Same epoch: u-blox iTOW can jitter by a millisecond or two inside one burst (gpsd allows 10)."""
    if a is None or b is None:
        return False
    diff = abs(a - b) % (WEEK_S * 1000)
    return min(diff, WEEK_S * 1000 - diff) <= 10


def _fix_mode_from_ubx(fix_type: int | None) -> int:
    """UBX fixType/gpsFix -> gpsd mode: DR-only counts as 2D, GNSS+DR and time-only as 3D."""
    return {0: 1, 1: 2, 2: 2, 3: 3, 4: 3, 5: 3}.get(fix_type if fix_type is not None else -1, 1)


_TP_GNSS = {0: "gps", 1: "glonass", 2: "beidou", 3: "galileo", 4: "navic"}

# What decoding a checksum-valid but nonsensical message can raise.
_CONTENT_ERRORS = (ArithmeticError, AttributeError, LookupError, TypeError, ValueError)

_TIMED_SENTENCES = {"GGA", "RMC", "GLL", "GNS", "GST", "ZDA", "GBS"}

# Shortest payload of each message the decoder reads (u-blox interface descriptions). pyubx2 zero-fills
# a short payload, so a runt with a good checksum would otherwise become a fix at 0 N 0 E.
_MIN_PAYLOAD = {
    "NAV-PVT": 84, "NAV-PVAT": 116, "NAV-SOL": 52, "NAV-POSLLH": 28, "NAV-HPPOSLLH": 36,
    "NAV-VELNED": 36, "NAV-STATUS": 16, "NAV-DOP": 18, "NAV-TIMEGPS": 16, "NAV-TIMEUTC": 20,
    "NAV-TIMELS": 24, "NAV-EOE": 4, "TIM-TP": 16, "HNR-PVT": 72, "RXM-RAWX": 16,
}

# NAV messages that carry an iTOW and belong to the navigation epoch of that iTOW.
_NAV_CLASS = 0x01


# --------------------------------------------------------------------------------------------------
# Epoch assembly


@dataclass
class _Burst:
    """Messages of one epoch, by identity; the last one of each kind wins.

    ``key`` is the epoch's time tag: UBX iTOW in ms, NMEA time of day in s (None until a sentence with
    a time arrives).
    """

    key: float | None
    parts: dict[str, Any] = field(default_factory=dict)
    order: list[str] = field(default_factory=list)
    opened: int | None = None  # the decoder's read_mark when its first message came
    # NMEA, a burst begun with a time-less sentence (GSA, VTG): whether that came first in a read begun after a quiet
    # line (a head) or not (the previous epoch's tail, more likely). None: begun with a timed sentence, or not known.
    quiet_head: bool | None = None

    def add(self, ident: str, msg: Any) -> None:
        self.parts[ident] = msg
        self.order.append(ident)


def _marked(fix: GnssFix | None, burst: _Burst) -> list[GnssItem]:
    """A burst's fix (none: nothing) with the read its burst opened in, where the reads are marked."""
    if fix is None:
        return []
    return [fix if burst.opened is None else replace(fix, opened_mark=burst.opened)]


class GnssDecoder:
    """Frames -> epochs: ``push(frame)`` returns what the frame completes, ``flush()`` the rest.

    Items are :class:`GnssFix` (one per epoch and solution stream), :class:`TimePulse` (each TIM-TP, at
    once, because it announces an edge that is about to happen) and :class:`GnssTime` (each NAV-TIMEGPS
    and NAV-TIMEUTC, at once). ``rejected`` counts decoded messages whose content made no sense.
    """

    def __init__(self) -> None:
        self._ubx: _Burst | None = None
        self._ubx_done: float | None = None
        self._ubx_ender: str | None = None
        self._nmea: _Burst | None = None
        self._nmea_done: float | None = None
        self._nmea_ender: str | None = None
        # The sentences of the last NMEA epochs that ended (each burst's, and those that came after its end), newest
        # last, and the sentence each burst began with: what a receiver sends in (almost) every epoch tells a
        # burst's real end from a sentence sent at a lower rate, and an epoch's tail from the next one's head.
        self._nmea_epochs: deque[set[str]] = deque(maxlen=NMEA_EPOCHS_KEPT)
        self._nmea_heads: deque[str] = deque(maxlen=NMEA_EPOCHS_KEPT)
        self._gst: tuple[float, Any] | None = None  # the last GST (time of day, message): _gst_for
        self._nmea_read: int | None = None  # the read_mark of the last NMEA sentence
        self._first_in_read = False  # the sentence being pushed is its read's first NMEA sentence
        self._ubx_solutions = False
        self.leap_s: int | None = None
        self.week: int | None = None
        self._date: dt.date | None = None
        self._last_tod_s: float | None = None
        self.rejected = 0
        # The caller's number for what it is pushing now (GnssReceiver: one per read of the port); an epoch's fix
        # carries the one its first message came under (GnssFix.opened_mark). None: not marked.
        self.read_mark: int | None = None
        # Whether the line was quiet before the read being pushed (GnssReceiver.read: a burst's start); None: unknown.
        # A time-less sentence is taken as a burst's head only at the start of such a read.
        self.read_quiet: bool | None = None

    # ---- public

    def push(self, frame: Frame) -> list[GnssItem]:
        msg = frame.message
        if msg is None:
            return []
        try:
            if frame.kind == KIND_UBX:
                if len(frame.raw) - 8 < _MIN_PAYLOAD.get(str(_attr(msg, "identity", default="")), 0):
                    self.rejected += 1
                    return []
                return self._push_ubx(msg)
            if frame.kind == KIND_NMEA:
                return self._push_nmea(msg, frame.raw)
        except _CONTENT_ERRORS:
            self.rejected += 1  # checksum-valid nonsense; the decoder's state stays usable
        return []

    @property
    def ignores_nmea(self) -> bool:
        """True once UBX solutions were seen: from then on NMEA sentences give nothing (see ``_push_nmea``)."""
        return self._ubx_solutions

    def push_all(self, frames: Iterable[Frame]) -> list[GnssItem]:
        items: list[GnssItem] = []
        for frame in frames:
            items += self.push(frame)
        return items

    def flush(self) -> list[GnssItem]:
        """End of stream: report the epochs still being collected."""
        items: list[GnssItem] = []
        if self._ubx is not None:
            items += self._finish_ubx(learn=True)
        if self._nmea is not None:
            items += self._finish_nmea(learn=True)
        return items

    # ---- UBX

    def _push_ubx(self, msg: Any) -> list[GnssItem]:
        ident = str(_attr(msg, "identity", default=""))
        items: list[GnssItem] = []
        if ident == "TIM-TP":
            return [self._time_pulse(msg)]
        if ident == "HNR-PVT":
            fix = self._fix_from_hnr(msg)
            return [fix] if fix is not None else []
        if ident == "RXM-RAWX" and _flag(msg, "leapSec"):
            self.leap_s = _int(_attr(msg, "leapS"))
            return []
        msg_class = _attr(msg, "msg_cls", default=b"")
        if msg_class != bytes([_NAV_CLASS]) or not hasattr(msg, "iTOW"):
            return []
        itow = _int(msg.iTOW)
        if itow is None:
            return []
        if ident == "NAV-TIMEGPS":
            items.append(self._time_from_timegps(msg))
        elif ident == "NAV-TIMEUTC":
            items.append(self._time_from_timeutc(msg))
        elif ident == "NAV-TIMELS" and _flag(msg, "validCurrLs"):
            self.leap_s = _int(_attr(msg, "currLs"))
        if ident in ("NAV-PVT", "NAV-PVAT", "NAV-SOL"):  # a solution with its fix type and time (_fix_from_ubx)
            self._ubx_solutions = True
            if self._nmea is not None:
                items += self._finish_nmea(learn=False)
        if self._ubx is None and _same_itow(itow, self._ubx_done):
            self._ubx_ender = ident  # the burst went on after where we thought it ended
            return items
        if self._ubx is not None and not _same_itow(itow, self._ubx.key):
            items += self._finish_ubx(learn=True)
        if self._ubx is None:
            self._ubx = _Burst(itow, opened=self.read_mark)
        self._ubx.add(ident, msg)
        parts = self._ubx.parts
        if (not self._ubx_solutions and "NAV-STATUS" in parts
                and ("NAV-POSLLH" in parts or "NAV-HPPOSLLH" in parts)):
            # The older receivers' separate messages: a position with its fix type is the UBX solution, from the
            # moment both are in (a position alone, beside NMEA, is not: _fix_from_ubx).
            self._ubx_solutions = True
            if self._nmea is not None:
                items += self._finish_nmea(learn=False)
        if ident in ("NAV-EOE", self._ubx_ender):
            items += self._finish_ubx(learn=ident == "NAV-EOE")
        return items

    def _finish_ubx(self, learn: bool) -> list[GnssItem]:
        burst, self._ubx = self._ubx, None
        if burst is None:
            return []
        self._ubx_done = burst.key
        if learn and burst.order:
            self._ubx_ender = burst.order[-1]
        try:
            fix = self._fix_from_ubx(burst)
        except _CONTENT_ERRORS:
            self.rejected += 1  # only this epoch is lost, not the message that closed it
            return []
        return _marked(fix, burst)

    def _time_pulse(self, msg: Any) -> TimePulse:
        utc_base = _flag(msg, "timeBase")
        gnss_id = _int(_attr(msg, "timeRefGnss"))
        return TimePulse(
            tow_ms=int(msg.towMS),
            tow_sub_ms=float(msg.towSubMS),
            week=int(msg.week),
            qerr_ps=int(msg.qErr),
            qerr_valid=not _flag(msg, "qErrInvalid"),
            time_base="utc" if utc_base else "gnss",
            utc_available=_flag(msg, "utc"),
            gnss=None if utc_base else _TP_GNSS.get(gnss_id if gnss_id is not None else -1),
        )

    def _time_from_timegps(self, msg: Any) -> GnssTime:
        itow = int(msg.iTOW)
        ftow = int(msg.fTOW)
        tow_ok, week_ok, leap_ok = _flag(msg, "towValid"), _flag(msg, "weekValid"), _flag(msg, "leapSValid")
        week = int(msg.week) if week_ok else None
        leap = int(msg.leapS) if leap_ok else None
        if week is not None:
            self.week = week
        if leap is not None:
            self.leap_s = leap
        utc = None
        if tow_ok and week is not None and leap is not None:
            utc = gps_to_unix_ns(week, itow * NS_PER_MS + ftow, leap)
        return GnssTime(
            source="NAV-TIMEGPS",
            itow_ms=itow,
            ftow_ns=ftow,
            week=week,
            leap_s=leap,
            time_utc_ns=utc,
            tow_valid=tow_ok,
            week_valid=week_ok,
            leap_valid=leap_ok,
            utc_valid=utc is not None,
            t_acc_ns=_int(_attr(msg, "tAcc")),
        )

    def _time_from_timeutc(self, msg: Any) -> GnssTime:
        valid_utc = _flag(msg, "validUTC")
        utc = None
        if valid_utc:
            utc = _ubx_utc_ns(msg)
        return GnssTime(
            source="NAV-TIMEUTC",
            itow_ms=int(msg.iTOW),
            ftow_ns=0,
            week=None,
            leap_s=None,
            time_utc_ns=utc,
            tow_valid=_flag(msg, "validTOW"),
            week_valid=_flag(msg, "validWKN"),
            leap_valid=valid_utc,
            utc_valid=utc is not None,
            t_acc_ns=_int(_attr(msg, "tAcc")),
        )

    def _week_for(self, itow_ms: int, time_utc_ns: int | None) -> int | None:
        """GPS week of an epoch that does not carry one (NAV-PVT), from UTC and known leap seconds."""
        if time_utc_ns is None or self.leap_s is None:
            return None
        gps_s = time_utc_ns // NS_PER_S - GPS_EPOCH_UNIX_S + self.leap_s
        week, tow_s = divmod(gps_s, WEEK_S)
        # the UTC second and iTOW must name the same instant; near a week boundary trust the iTOW
        if abs(tow_s - itow_ms // 1000) > WEEK_S // 2:
            week += 1 if tow_s > itow_ms // 1000 else -1
        return int(week)

    def _fix_from_ubx(self, burst: _Burst) -> GnssFix | None:
        parts = burst.parts
        itow = int(burst.key)
        pvt = parts.get("NAV-PVT")
        if pvt is None:
            pvt = parts.get("NAV-PVAT")
        sol = parts.get("NAV-SOL")
        posllh = parts.get("NAV-POSLLH")
        hp = parts.get("NAV-HPPOSLLH")
        if hp is not None and _flag(hp, "invalidLlh"):
            hp = None
        if pvt is None and sol is None and posllh is None and hp is None:
            return None  # a burst without a position (time or satellite messages only)
        status = parts.get("NAV-STATUS")
        if pvt is None and sol is None and status is None:
            # A position without a fix type or a time (NAV-HPPOSLLH added by an owner to NMEA output): no fix of its
            # own. The NMEA beside it has both (it was ignored from then on: every record "no fix").
            return None
        velned = parts.get("NAV-VELNED")
        dop = parts.get("NAV-DOP")
        timegps = parts.get("NAV-TIMEGPS")
        timeutc = parts.get("NAV-TIMEUTC")

        source: str
        lat = lon = hae = msl = None
        vel: tuple[float, float, float] | None = None
        h_acc = v_acc = s_acc = pdop = None
        num_sv: int | None = None
        week: int | None = None
        time_utc: int | None = None
        time_valid = False
        leap = False
        mode = 0
        fix_ok = False

        if pvt is not None:
            source = str(_attr(pvt, "identity"))
            fix_type = _int(pvt.fixType)
            mode = _fix_mode_from_ubx(fix_type)
            fix_ok = _flag(pvt, "gnssFixOk", "gnssFixOK")
            if _flag(pvt, "validDate") and _flag(pvt, "validTime"):
                time_utc = _ubx_utc_ns(pvt)
                time_valid = time_utc is not None and _flag(pvt, "fullyResolved")
                leap = time_utc is not None and _ubx_leap(pvt)
            if mode >= 2:
                vel = (pvt.velN / 1000.0, pvt.velE / 1000.0, pvt.velD / 1000.0)
                if _flag(pvt, "invalidLlh"):
                    # u-blox 9 and later: the fix type stands but longitude, latitude and heights are invalid. No
                    # position is no fix to use (its record said a 3D fix at 0 N 0 E, which the filter took).
                    fix_ok = False
                else:
                    lat, lon, hae, msl = _ubx_llh(pvt)
            h_acc = pvt.hAcc / 1000.0
            v_acc = pvt.vAcc / 1000.0
            s_acc = pvt.sAcc / 1000.0
            num_sv = _int(pvt.numSV)
            pdop = _num(_attr(pvt, "pDOP"))
        elif sol is not None:
            source = "NAV-SOL"
            mode = _fix_mode_from_ubx(_int(sol.gpsFix))
            fix_ok = _flag(sol, "gpsfixOK", "gpsFixOk")
            if _flag(sol, "wknSet"):
                week = int(sol.week)
                self.week = week
            if mode >= 2:
                lat_r, lon_r, hae = ecef_to_geodetic(
                    sol.ecefX / 100.0, sol.ecefY / 100.0, sol.ecefZ / 100.0
                )
                lat, lon = math.degrees(lat_r), math.degrees(lon_r)
                vel = ecef_velocity_to_ned(
                    sol.ecefVX / 100.0, sol.ecefVY / 100.0, sol.ecefVZ / 100.0, lat_r, lon_r
                )
            s_acc = sol.sAcc / 100.0
            h_acc = v_acc = sol.pAcc / 100.0  # a 3D accuracy bounds both; NAV-POSLLH refines it below
            num_sv = _int(sol.numSV)
            pdop = _num(sol.pDOP)
            if week is not None and _flag(sol, "towSet") and self.leap_s is not None:
                time_utc = gps_to_unix_ns(week, itow * NS_PER_MS + int(sol.fTOW), self.leap_s)
                time_valid = True
        else:
            source = "NAV-POSLLH" if posllh is not None else "NAV-HPPOSLLH"
            if status is not None:
                mode = _fix_mode_from_ubx(_int(status.gpsFix))
                fix_ok = _flag(status, "gpsFixOk", "gpsfixOK")

        if source not in ("NAV-PVT", "NAV-PVAT") and mode != 1:
            # separate position, velocity and DOP messages of older receivers
            pos = hp if hp is not None else posllh
            if pos is not None:
                lat, lon, hae, msl = _ubx_llh(pos)
                h_acc = pos.hAcc / 1000.0
                v_acc = pos.vAcc / 1000.0
            if velned is not None:
                vel = (velned.velN / 100.0, velned.velE / 100.0, velned.velD / 100.0)
                s_acc = velned.sAcc / 100.0
        elif hp is not None and mode >= 2:
            lat, lon, hae, msl = _ubx_llh(hp)
        hdop = vdop = None
        if dop is not None:
            pdop = pdop if pdop is not None else _num(dop.pDOP)
            hdop, vdop = _num(_attr(dop, "hDOP")), _num(_attr(dop, "vDOP"))

        if timegps is not None:
            if week is None and _flag(timegps, "weekValid"):
                week = int(timegps.week)
            if time_utc is None and _flag(timegps, "towValid") and week is not None and self.leap_s is not None:
                tow_ns = int(timegps.iTOW) * NS_PER_MS + int(timegps.fTOW)
                time_utc = gps_to_unix_ns(week, tow_ns, self.leap_s)
                time_valid = True
        if timeutc is not None and time_utc is None and _flag(timeutc, "validUTC"):
            time_utc = _ubx_utc_ns(timeutc)
            time_valid = time_utc is not None
            leap = time_utc is not None and _ubx_leap(timeutc)
        leap_known = (_flag(timegps, "leapSValid") if timegps is not None
                      else _flag(timeutc, "validUTC") if timeutc is not None else None)
        if week is None:
            week = self._week_for(itow, time_utc)
        if mode == 1:
            lat = lon = hae = msl = None
            vel = None
        return GnssFix(
            source=source,
            itow_ms=itow,
            week=week,
            time_utc_ns=time_utc,
            time_valid=time_valid,
            fix_mode=mode,
            fix_ok=fix_ok,
            lat_deg=lat,
            lon_deg=lon,
            height_hae_m=hae,
            height_msl_m=msl,
            vel_ned_mps=vel,
            h_acc_m=h_acc,
            v_acc_m=v_acc,
            s_acc_mps=s_acc,
            num_sv=num_sv,
            pdop=pdop,
            hdop=hdop,
            vdop=vdop,
            leap_second=leap,
            leap_known=leap_known,
        )

    def _fix_from_hnr(self, msg: Any) -> GnssFix | None:
        """UBX HNR-PVT: the receiver's sensor-fused high-rate solution, reported as its own stream."""
        itow = int(msg.iTOW)
        mode = _fix_mode_from_ubx(_int(msg.gpsFix))
        time_utc = None
        time_valid = False
        if _flag(msg, "validDate") and _flag(msg, "validTime"):
            time_utc = _ubx_utc_ns(msg)
            time_valid = time_utc is not None and _flag(msg, "fullyResolved")
        lat = lon = hae = msl = None
        vel = None
        if mode >= 2:
            lat, lon, hae, msl = _ubx_llh(msg)
            ground = msg.gSpeed / 1000.0
            heading = math.radians(float(msg.headMot))
            vel = (ground * math.cos(heading), ground * math.sin(heading), math.nan)
        return GnssFix(
            source="HNR-PVT",
            itow_ms=itow,
            week=self._week_for(itow, time_utc),
            time_utc_ns=time_utc,
            time_valid=time_valid,
            fix_mode=mode,
            fix_ok=_flag(msg, "GPSfixOK", "gpsFixOk"),
            leap_second=time_utc is not None and _ubx_leap(msg),
            lat_deg=lat,
            lon_deg=lon,
            height_hae_m=hae,
            height_msl_m=msl,
            vel_ned_mps=vel,
            h_acc_m=msg.hAcc / 1000.0,
            v_acc_m=msg.vAcc / 1000.0,
            s_acc_mps=msg.sAcc / 1000.0,
            num_sv=None,
            pdop=None,
        )

    # ---- NMEA

    def _push_nmea(self, msg: Any, raw: bytes = b"") -> list[GnssItem]:
        if self._ubx_solutions:
            return []  # the same receiver also sends UBX solutions: those are the better copy
        kind = str(_attr(msg, "msgID", default=""))
        ident = str(_attr(msg, "talker", default="")) + kind
        self._first_in_read, self._nmea_read = self.read_mark != self._nmea_read, self.read_mark
        items: list[GnssItem] = []
        tod = _attr(msg, "time")
        key: float | None = None
        if isinstance(tod, dt.time):
            key = tod.hour * 3600 + tod.minute * 60 + tod.second + tod.microsecond / 1e6
        elif kind in _TIMED_SENTENCES:
            # 23:59:60 (a leap second) is the one time pynmeagps does not parse; its epoch is a fix like any other,
            # keyed past 23:59:59 (86400 s and up), which dates it on the day it ends and orders it before 00:00:00.
            key = _leap_time_of_day(raw, kind)
            if key is None:
                self.rejected += 1  # a garbled time field: the sentence cannot be placed in an epoch
                return items
        if key is not None:
            if kind == "GST":
                self._gst = (key, msg)  # the receiver's latest accuracies, for the fixes after it too (_gst_for)
            if key == self._nmea_done and (self._nmea is None or self._nmea.key is None):
                # The burst went on after where we thought it ended. A sentence the burst before it lacked too is one
                # the receiver sends at a lower rate (GST once a second at 5 Hz): the end stays (moved to it, every
                # burst without it ended only when the next began, a fix late, and the end flapped to and fro), and
                # its accuracies stand for the epochs of the next second (_gst_for). Time-less sentences collected
                # since are that epoch's too (an end learnt at a GSA when its burst's last sentence was lost: the
                # GSAs after the first and the GLL after them made the same epoch again, a fix of the GLL alone).
                if self._nmea_epochs:
                    self._nmea_epochs[-1].update(() if self._nmea is None else self._nmea.order)
                    self._nmea_epochs[-1].add(ident)
                self._nmea = None
                if len(self._nmea_epochs) >= 2 and ident in self._nmea_epochs[-2]:
                    self._nmea_ender = ident
                return items
            if self._nmea is not None and self._nmea.key is not None and self._nmea.key != key:
                if self._date is None:
                    self._bootstrap_date(msg, kind, self._nmea.key, key)
                items += self._finish_nmea(learn=True)
            if self._nmea is None:
                self._nmea = _Burst(key, opened=self.read_mark)
            elif self._nmea.key is None:
                # The burst's start is its first timed sentence's read: the time-less ones before it may be the last
                # epoch's tail (one GSA per constellation, the first of which was learnt as the burst's end), read a
                # second earlier, and an epoch dated from there is paired with the PPS edge a second early. Even a
                # head read after a quiet line is not trusted with the date: a tail after a pause of the receiver's,
                # the port opened in it, looks the same, and dating by it locked the clock a second off.
                self._nmea.key, self._nmea.opened = key, self.read_mark
        elif self._nmea is None:
            if kind not in ("GSA", "VTG"):
                return items
            if self._regular_tail(ident):
                # The end of the epoch just reported (RMC, GGA, GSA: one GSA lost to a bad checksum had its end
                # learnt at GGA for good, and every epoch carried the previous one's GSA, its fix mode and DOPs).
                self._nmea_ender = ident
                return items
            # a time-less sentence opens the burst; the next timed one names it and dates its start
            self._nmea = _Burst(None, opened=self.read_mark, quiet_head=self._read_begins())
        elif self._begins_next(ident):
            # A receiver that begins its bursts with this sentence: the next epoch's, not this one's tail. Taken into
            # this burst, it ended the first epoch, was learnt as every burst's end, and every fix came a read late
            # with the next epoch's GSA (its fix mode and DOPs) or VTG. The start is dated by the first timed
            # sentence's read all the same: a tail taken for a head (the receiver paused before it, longer than
            # a tenth of its period, the port opened in the pause) costs its epochs' GSA, not a second.
            items += self._finish_nmea(learn=True)
            self._nmea = _Burst(None, opened=self.read_mark, quiet_head=True)
        self._nmea.add(kind, msg)
        self._nmea.order[-1] = ident
        if ident == self._nmea_ender and self._nmea.key is not None:
            items += self._finish_nmea(learn=False)
        return items

    def _begins_next(self, ident: str) -> bool:
        """Whether a time-less sentence begins the next epoch's burst: the burst being collected has its time, began
        with this sentence after a quiet line, and this one comes first after a quiet line too (a receiver sends a
        burst back to back; its next burst a fix period later)."""
        b = self._nmea
        return (b is not None and b.key is not None and b.quiet_head is True and b.order[0] == ident
                and self._read_begins() is True)

    def _read_begins(self) -> bool | None:
        """Whether the sentence being pushed came first in a read begun after a quiet line: a burst's first (None:
        reads not marked, or their quiet not known)."""
        if self.read_mark is None or self.read_quiet is None:
            return None
        return self.read_quiet and self._first_in_read

    def _regular_tail(self, ident: str) -> bool:
        """Whether a time-less sentence come after the last epoch's end is that epoch's tail: one the receiver sends in
        all but one of the last epochs, never at a burst's head (a receiver that begins its bursts with GSA), and
        not the learnt end itself (one GSA per constellation: the first ends the burst, the others follow it)."""
        epochs = self._nmea_epochs
        if len(epochs) < NMEA_EPOCHS_KEPT - 1 or ident == self._nmea_ender or ident in self._nmea_heads:
            return False
        if 1 + sum(ident in seen for seen in list(epochs)[:-1]) < len(epochs) - 1:  # the last epoch with it now
            return False
        epochs[-1].add(ident)
        return True

    def _bootstrap_date(self, msg: Any, kind: str, prev_tod_s: float, tod_s: float) -> None:
        """Date the very first epoch from the sentence that opens the next one (a receiver that sends
        GGA before RMC would otherwise leave its first fix without a date)."""
        date = _attr(msg, "date") if kind == "RMC" else None
        if kind == "ZDA":
            date = _zda_date(msg)
        if isinstance(date, dt.date):
            self._date = date - dt.timedelta(days=1) if tod_s < prev_tod_s - 43_200 else date
            self._last_tod_s = prev_tod_s

    def _date_of(self, burst: _Burst, tod_s: float) -> dt.date | None:
        """UTC date of an NMEA epoch: its own RMC or ZDA, else the last one seen, rolled over at midnight."""
        date: dt.date | None = None
        rmc = burst.parts.get("RMC")
        zda = burst.parts.get("ZDA")
        if rmc is not None and isinstance(_attr(rmc, "date"), dt.date):
            date = rmc.date
        elif zda is not None:
            date = _zda_date(zda)
        if date is None and self._date is not None:
            date = self._date
            if self._last_tod_s is not None and tod_s < self._last_tod_s - 43_200:
                date += dt.timedelta(days=1)  # midnight passed since the date was last sent
        if date is not None:
            self._date = date
            self._last_tod_s = tod_s
        return date

    def _finish_nmea(self, learn: bool) -> list[GnssItem]:
        burst, self._nmea = self._nmea, None
        if burst is None or burst.key is None:
            return []
        self._nmea_done = burst.key
        self._nmea_epochs.append(set(burst.order))
        if burst.order:
            # A time-less sentence that did not come after a quiet line is no head: a receiver that ends its bursts
            # with it, first taken for a head, comes back to its real end (_regular_tail).
            self._nmea_heads.append("" if burst.quiet_head is False else burst.order[0])
        if learn and burst.order:
            self._nmea_ender = burst.order[-1]
        try:
            fix = self._fix_from_nmea(burst)
        except _CONTENT_ERRORS:
            self.rejected += 1
            return []
        return _marked(fix, burst)

    def _gst_for(self, gst: Any, tod_s: float | None) -> Any:
        """The GST of an epoch: its own, or the receiver's last within GST_HOLD_S before it (one sent at a lower
        rate than the fixes, or after the epoch's learnt end: its accuracies are the receiver's latest word)."""
        if gst is not None:
            return gst
        if self._gst is None or tod_s is None:
            return None
        since = tod_s - self._gst[0]
        if since < -43_200.0:  # across midnight (times of day; 23:59:60 is keyed 86400)
            since += 86_400.0
        return self._gst[1] if 0.0 <= since <= GST_HOLD_S else None

    def _fix_from_nmea(self, burst: _Burst) -> GnssFix | None:
        parts = burst.parts
        gga = parts.get("GGA")
        gns = parts.get("GNS")
        rmc = parts.get("RMC")
        gll = parts.get("GLL")
        gsa = parts.get("GSA")
        gst = self._gst_for(parts.get("GST"), float(burst.key) if burst.key is not None else None)
        vtg = parts.get("VTG")
        pos = next((m for m in (gga, gns, rmc, gll) if m is not None), None)
        if pos is None or burst.key is None:
            return None  # time-only sentences (ZDA, GST): no solution to report
        tod_s = float(burst.key)

        status_ok: bool | None = None
        if rmc is not None:
            status_ok = _attr(rmc, "status") == "A"
        elif gll is not None:
            status_ok = _attr(gll, "status") == "A"
        quality = _int(_attr(gga, "quality")) if gga is not None else None
        if gns is not None and quality is None:
            # posMode has a character per constellation (GPS, GLONASS, Galileo, BeiDou, ...): a fix by any of them is
            # a fix, not only one that GPS (the first character) takes part in ("NA": GLONASS alone).
            pos_mode = str(_attr(gns, "posMode", default=""))
            quality = 0 if not pos_mode.strip("N") else 1

        lat = _num(_attr(pos, "lat"))
        lon = _num(_attr(pos, "lon"))
        nav_mode = _int(_attr(gsa, "navMode")) if gsa is not None else None
        if nav_mode in (1, 2, 3):
            mode = int(nav_mode)
        elif quality == 0 or status_ok is False or lat is None:
            mode = 1
        else:
            # A height in GGA or in GNS (which NMEA 4 receivers send instead of GGA) makes it 3D.
            alt_known = any(m is not None and _num(_attr(m, "alt")) is not None for m in (gga, gns))
            mode = 3 if alt_known else 2
        fix_ok = bool(status_ok) if status_ok is not None else bool(quality)

        msl = sep = None
        src = gga if gga is not None else gns
        if src is not None:
            msl = _num(_attr(src, "alt"))
            sep = _num(_attr(src, "sep"))
        hae = msl + sep if msl is not None and sep is not None else None
        if mode == 3 and msl is None and hae is None and lat is not None:
            # GSA says 3D, but no height reached us (the epoch's GGA lost to a bad checksum, or a receiver that sends
            # RMC and GSA only): what we have is a position without a height, a 2D fix, and no height is made up.
            mode = 2

        speed = course = None
        if rmc is not None:
            knots = _num(_attr(rmc, "spd"))
            speed = knots * KNOT_MPS if knots is not None else None
            course = _num(_attr(rmc, "cog"))
        if speed is None and vtg is not None:
            kmh = _num(_attr(vtg, "sogk"))
            knots = _num(_attr(vtg, "sogn"))
            speed = kmh / 3.6 if kmh is not None else (knots * KNOT_MPS if knots is not None else None)
            course = _num(_attr(vtg, "cogt"))
        elif course is None and vtg is not None:
            course = _num(_attr(vtg, "cogt"))
        vel = None
        if speed is not None and course is not None:
            heading = math.radians(course)
            vel = (speed * math.cos(heading), speed * math.sin(heading), math.nan)
        elif speed is not None and speed <= NO_COURSE_SPEED_MPS:  # standing: within a receiver's noise of 0
            vel = (0.0, 0.0, math.nan)
        # A speed above that without a course (u-blox leaves it empty while its heading is invalid) is no velocity:
        # it was made one due north, which the filter took as a measurement.

        h_acc = v_acc = None
        if gst is not None:
            s_lat, s_lon = _num(_attr(gst, "stdLat")), _num(_attr(gst, "stdLong"))
            if s_lat is not None and s_lon is not None:
                h_acc = math.hypot(s_lat, s_lon)
            v_acc = _num(_attr(gst, "stdAlt"))

        date = self._date_of(burst, tod_s)
        time_utc = None
        leap = tod_s >= 86_400.0  # 23:59:60: POSIX gives it the Unix time of the 00:00:00 after it
        if date is not None:
            whole = int(tod_s)
            time_utc = (calendar.timegm(date.timetuple()) + whole) * NS_PER_S + round((tod_s - whole) * 1e9)

        if mode == 1:
            lat = lon = hae = msl = None
            vel = None
        num_sv = _int(_attr(src, "numSV")) if src is not None else None
        # GSA's HDOP is the solution's own; GGA's is the same, and the only DOP of a receiver sending GGA and RMC.
        hdop = _num(_attr(gsa, "HDOP")) if gsa is not None else None
        if hdop is None and gga is not None:
            hdop = _num(_attr(gga, "HDOP"))
        return GnssFix(
            source="NMEA",
            itow_ms=None,
            week=None,
            time_utc_ns=time_utc,
            time_valid=time_utc is not None and fix_ok,
            fix_mode=mode,
            fix_ok=fix_ok,
            lat_deg=lat,
            lon_deg=lon,
            height_hae_m=hae,
            height_msl_m=msl,
            vel_ned_mps=vel,
            h_acc_m=h_acc,
            v_acc_m=v_acc,
            s_acc_mps=None,
            num_sv=num_sv,
            pdop=_num(_attr(gsa, "PDOP")) if gsa is not None else None,
            hdop=hdop,
            vdop=_num(_attr(gsa, "VDOP")) if gsa is not None else None,
            leap_second=leap and time_utc is not None,
        )
