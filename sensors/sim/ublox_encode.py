"""The periodic output of the simulated u-blox receiver: one navigation solution as UBX and NMEA messages.

The counterpart of :mod:`sensors.ublox_decode` on the device side. :class:`EpochRecord` is what the
receiver model computed for one epoch; the encoders turn it into NAV-PVT, NAV-TIMEGPS, GGA, RMC, GSA and the
rest of the factory NMEA set (GLL, VTG, GSV: what fills a slow line), and a pulse second into TIM-TP, with the
fields, scalings and "no estimate" conventions of the u-blox M8 protocol specification. They are plain functions
of their arguments, so the receiver model decides what it knows (a time solution, a position since power-on) and
the encoders only say it as the firmware would.

Messages are built with pyubx2 and pynmeagps and serialised by the caller, which also labels them by
the names in :data:`MESSAGE_IDS`.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass

import numpy as np
from pynmeagps import NMEAMessage
from pyubx2 import GET, UBXMessage

from sensors.sim.gnss_errors import NO_DOP, EpochError
from sensors.sim.gnss_time import NS_PER_MS, NS_PER_S, GnssTimeline
from sensors.sim.truth import TruthState

__all__ = ["MESSAGE_IDS", "EpochRecord", "gga", "gll", "gsa", "gsv", "nav_pvt", "nav_timegps", "rmc", "tim_tp", "vtg"]

# Class and id of the output messages the model produces (u-blox M8 protocol spec; NMEA class 0xF0).
MESSAGE_IDS: dict[str, tuple[int, int]] = {
    "NAV-PVT": (0x01, 0x07),
    "NAV-TIMEGPS": (0x01, 0x20),
    "TIM-TP": (0x0D, 0x01),
    "GGA": (0xF0, 0x00),
    "RMC": (0xF0, 0x04),
    "GSA": (0xF0, 0x02),
    "GLL": (0xF0, 0x01),
    "GSV": (0xF0, 0x03),
    "VTG": (0xF0, 0x05),
    # Raw observations: the receiver model puts out what its raw_frames hook gives (sensors.sim.ublox).
    "RXM-RAWX": (0x02, 0x15),
    "RXM-SFRBX": (0x02, 0x13),
}

_U4_MAX = 0xFFFF_FFFF


@dataclass(frozen=True, slots=True)
class EpochRecord:
    """One navigation solution as computed: the truth, the error applied and what was reported."""

    drive_ns: int  # true drive time of the epoch
    gps_ns: int  # true GPS time of the epoch
    itow_ms: int
    truth: TruthState
    fix_type: int
    num_sv: int
    lat_deg: float  # reported, before the 1e-7 deg quantisation of NAV-PVT
    lon_deg: float
    height_m: float  # reported ellipsoidal height
    vel_ned_mps: np.ndarray  # reported
    pos_error_ned_m: np.ndarray  # reported minus true, metres north-east-down
    vel_error_ned_mps: np.ndarray
    time_error_ns: float  # reported minus true epoch time
    error: EpochError  # the error model's draw (accuracies, DOPs, multipath part)
    h_acc_m: float
    v_acc_m: float
    s_acc_mps: float
    t_acc_ns: float
    head_mot_deg: float = 0.0  # heading of motion; kept from the last epoch with enough speed
    head_acc_deg: float = 180.0
    # Satellites in view as (constellation name such as "G07", elevation deg, azimuth deg, C/N0 dB-Hz), for GSV;
    # empty where the model has no sky geometry (a bare trajectory): GSV then lists ``num_sv`` satellites by number.
    satellites: tuple[tuple[str, float, float, int], ...] = ()


def nav_pvt(rec: EpochRecord, utc_ns: int, *, time_known: bool, position_known: bool,
            generation: int) -> UBXMessage:
    """UBX-NAV-PVT of one solution; ``utc_ns`` is the epoch as the receiver states it (Unix ns, error included).

    Without a time solution the date and time fields are still filled from ``utc_ns`` but flagged invalid
    (validDate, validTime, confirmed*), so a decoder has to honour the flags. hMSL stays 0 until the first
    fix since power-on (``position_known``), and from protocol 27 (generation 9 on) invalidLlh says so too.
    """
    second_ns, nano = _nearest_second(utc_ns)
    day = _unix_to_calendar(second_ns)
    fix_ok = rec.fix_type >= 2
    vn, ve, vd = (float(v) for v in rec.vel_ned_mps)
    g_speed = math.hypot(vn, ve)
    return UBXMessage(
        "NAV", "NAV-PVT", GET,
        iTOW=rec.itow_ms,
        year=day[0], month=day[1], day=day[2], hour=day[3], min=day[4], second=day[5],
        validDate=int(time_known), validTime=int(time_known), fullyResolved=int(time_known), validMag=0,
        tAcc=_acc(rec.t_acc_ns, 1.0),
        nano=int(nano) if time_known else 0,
        fixType=rec.fix_type,
        gnssFixOk=int(fix_ok), diffSoln=0, psmState=0, headVehValid=0, carrSoln=0,
        confirmedAvai=1, confirmedDate=int(time_known), confirmedTime=int(time_known),
        numSV=rec.num_sv,
        lon=_scaled(round(rec.lon_deg * 1e7), 1e-7),
        lat=_scaled(round(rec.lat_deg * 1e7), 1e-7),
        height=round(rec.height_m * 1000),
        hMSL=round((rec.height_m - rec.truth.geoid_m) * 1000) if position_known else 0,
        hAcc=_acc(rec.h_acc_m, 1e3),
        vAcc=_acc(rec.v_acc_m, 1e3),
        velN=round(vn * 1000), velE=round(ve * 1000), velD=round(vd * 1000),
        gSpeed=round(g_speed * 1000),
        headMot=_scaled(round(rec.head_mot_deg * 1e5) % 36_000_000, 1e-5),
        sAcc=_acc(rec.s_acc_mps, 1e3),
        headAcc=_scaled(round(rec.head_acc_deg * 1e5), 1e-5),
        pDOP=_scaled(round(rec.error.dops.pdop * 100), 0.01),
        invalidLlh=int(generation >= 9 and not position_known),
    )


def nav_timegps(rec: EpochRecord, *, leap_s: int, time_known: bool, leap_known: bool | None = None) -> UBXMessage:
    """UBX-NAV-TIMEGPS: the epoch's week and the clock error as fTOW (clamped to the field's +-0.5 ms);
    ``leap_known`` False: the leap count is the firmware's (leapSValid clear), as before the almanac's UTC page."""
    week, _ = GnssTimeline.week_tow(rec.gps_ns)
    f_tow = max(-500_000, min(500_000, round(rec.time_error_ns)))
    return UBXMessage(
        "NAV", "NAV-TIMEGPS", GET,
        iTOW=rec.itow_ms, fTOW=f_tow if time_known else 0, week=week if time_known else 0,
        leapS=leap_s if time_known else 0,
        towValid=int(time_known), weekValid=int(time_known),
        leapSValid=int(time_known if leap_known is None else time_known and leap_known),
        tAcc=_acc(rec.t_acc_ns, 1.0),
    )


def tim_tp(pulse_gps_second: int, *, leap_s: int, utc_base: bool, qerr_ps: int, utc_known: bool) -> UBXMessage:
    """UBX-TIM-TP announcing the pulse at whole GPS second ``pulse_gps_second``.

    The time of week is given in the pulse's time base (UTC or GPS), so a UTC-based pulse names the same
    instant ``leap_s`` seconds lower; ``qerr_ps`` is the quantisation error of that edge.
    """
    base_ns = (pulse_gps_second - (leap_s if utc_base else 0)) * NS_PER_S
    week, tow_ns = GnssTimeline.week_tow(base_ns)
    return UBXMessage(
        "TIM", "TIM-TP", GET,
        towMS=tow_ns // NS_PER_MS, towSubMS=0,
        qErr=qerr_ps,
        week=week,
        timeBase=int(utc_base), utc=int(utc_known), raim=2, qErrInvalid=0,
        timeRefGnss=0, utcStandard=3 if utc_base else 0,  # GPS; UTC(USNO) as GPS broadcasts it
    )


def gga(rec: EpochRecord, utc_ns: int | None, *, talker: str) -> NMEAMessage:
    """NMEA GGA; ``utc_ns`` None while the receiver has no time (the time field is then empty)."""
    hhmmss, _ = _nmea_time(utc_ns) if utc_ns is not None else ("", "")
    if rec.fix_type >= 2:
        lat, lon = rec.lat_deg, rec.lon_deg
        fields = [
            hhmmss, _nmea_coordinate(lat, 2), "N" if lat >= 0 else "S", _nmea_coordinate(lon, 3),
            "E" if lon >= 0 else "W", "1", f"{min(rec.num_sv, 12):02d}", f"{rec.error.dops.hdop:.2f}",
            f"{rec.height_m - rec.truth.geoid_m:.1f}", "M", f"{rec.truth.geoid_m:.1f}", "M", "", "",
        ]
    else:
        fields = [hhmmss, "", "", "", "", "0", f"{min(rec.num_sv, 12):02d}", "99.99", "", "", "", "", "", ""]
    return NMEAMessage(talker, "GGA", GET, payload=fields)


def rmc(rec: EpochRecord, utc_ns: int | None, *, talker: str) -> NMEAMessage:
    """NMEA RMC; ``utc_ns`` None while the receiver has no time (time and date fields are then empty)."""
    hhmmss, ddmmyy = _nmea_time(utc_ns) if utc_ns is not None else ("", "")
    if rec.fix_type >= 2:
        lat, lon = rec.lat_deg, rec.lon_deg
        vn, ve = float(rec.vel_ned_mps[0]), float(rec.vel_ned_mps[1])
        knots = math.hypot(vn, ve) * 3600.0 / 1852.0
        fields = [
            hhmmss, "A", _nmea_coordinate(lat, 2), "N" if lat >= 0 else "S", _nmea_coordinate(lon, 3),
            "E" if lon >= 0 else "W", f"{knots:.3f}", f"{rec.head_mot_deg:.2f}", ddmmyy, "", "", "A", "V",
        ]
    else:
        fields = [hhmmss, "V", "", "", "", "", "", "", ddmmyy, "", "", "N", "V"]
    return NMEAMessage(talker, "RMC", GET, payload=fields)


def gsa(rec: EpochRecord, *, talker: str) -> NMEAMessage:
    """NMEA GSA: the fix's dimension (1 none, 2 2D, 3 3D) and its DOPs, in automatic 2D/3D mode.

    The satellite fields are left empty: the error model knows how many satellites a solution used, not which
    (NMEA allows null fields, and a reader of GSA wants the mode and the DOPs). Without a fix the DOPs are
    99.99, as u-blox sends them."""
    mode = rec.fix_type if rec.fix_type in (2, 3) else 1
    d = rec.error.dops
    dops = (d.pdop, d.hdop, d.vdop) if mode >= 2 else (NO_DOP,) * 3
    return NMEAMessage(talker, "GSA", GET, payload=["A", str(mode), *[""] * 12,
                                                     *(f"{min(x, NO_DOP):.2f}" for x in dops)])


def gll(rec: EpochRecord, utc_ns: int | None, *, talker: str) -> NMEAMessage:
    """NMEA GLL: the position again, with its time and status (a factory-default sentence)."""
    hhmm, _ = _nmea_time(utc_ns) if utc_ns is not None else ("", "")
    if rec.fix_type >= 2:
        lat, lon = rec.lat_deg, rec.lon_deg
        fields = [_nmea_coordinate(lat, 2), "N" if lat >= 0 else "S", _nmea_coordinate(lon, 3),
                  "E" if lon >= 0 else "W", hhmm, "A", "A"]
    else:
        fields = ["", "", "", "", hhmm, "V", "N"]
    return NMEAMessage(talker, "GLL", GET, payload=fields)


def vtg(rec: EpochRecord, *, talker: str) -> NMEAMessage:
    """NMEA VTG: course and speed over ground, in knots and km/h (a factory-default sentence)."""
    if rec.fix_type < 2:
        return NMEAMessage(talker, "VTG", GET, payload=["", "T", "", "M", "", "N", "", "K", "N"])
    speed = math.hypot(float(rec.vel_ned_mps[0]), float(rec.vel_ned_mps[1]))
    return NMEAMessage(talker, "VTG", GET, payload=[
        f"{rec.head_mot_deg:.2f}", "T", "", "M", f"{speed * 3600.0 / 1852.0:.3f}", "N", f"{speed * 3.6:.3f}", "K",
        "A"])


# GSV talker and satellite number of each constellation (NMEA 4.10 as u-blox M8 numbers them: GLONASS 65-96).
_GSV_SYSTEMS = {"G": ("GP", 0), "R": ("GL", 64), "E": ("GA", 0)}


def gsv(rec: EpochRecord) -> list[NMEAMessage]:
    """NMEA GSV: the satellites in view, four to a sentence, one series per constellation (GPGSV, GLGSV, GAGSV).

    It is the bulk of a factory receiver's output (56 % of the simulated M8's 649 bytes a second with 21 satellites
    in view), which is why the line speed the logger sets up depends on whether NMEA stays on."""
    series: dict[str, list[list[str]]] = {}
    if rec.satellites:
        for name, el, az, cno in rec.satellites:
            talker, base = _GSV_SYSTEMS.get(name[:1], ("GP", 0))
            series.setdefault(talker, []).append([f"{base + int(name[1:]):02d}", f"{round(el):02d}",
                                                  f"{round(az) % 360:03d}", f"{cno:02d}"])
    elif rec.num_sv:
        series["GP"] = [[f"{n:02d}", "", "", ""] for n in range(1, rec.num_sv + 1)]
    else:
        series["GP"] = []
    out = []
    for talker, sats in series.items():
        count = max(1, math.ceil(len(sats) / 4))
        for i in range(count):
            group = sats[i * 4:(i + 1) * 4]
            out.append(NMEAMessage(talker, "GSV", GET, payload=[
                str(count), str(i + 1), f"{len(sats):02d}", *[f for sat in group for f in sat]]))
    return out


def _nearest_second(utc_ns: int) -> tuple[int, int]:
    """(whole second as Unix ns, nano) with the second rounded to nearest, as NAV-PVT splits its time."""
    second = (utc_ns + NS_PER_S // 2) // NS_PER_S * NS_PER_S
    return second, utc_ns - second


def _scaled(n: int, resolution: float) -> float:
    """A float that pyubx2 turns back into exactly the integer ``n`` at ``resolution``.

    pyubx2 truncates value / resolution; a quarter of a step away from the integer survives both
    truncation and rounding whatever the binary representation of the resolution.
    """
    return (n + math.copysign(0.25, n)) * resolution


def _acc(value: float, scale: float) -> int:
    """An accuracy field (U4), saturated as u-blox does when there is no estimate."""
    if not math.isfinite(value):
        return _U4_MAX
    return min(_U4_MAX, max(0, round(value * scale)))


def _nmea_coordinate(deg: float, width: int) -> str:
    """(d)ddmm.mmmmm as u-blox prints it, rounded once to the 1e-5 minute the sentence carries."""
    units = round(abs(deg) * 60 * 100_000)  # 1e-5 minutes
    whole, minutes = divmod(units, 60 * 100_000)
    return f"{whole:0{width}d}{minutes // 100_000:02d}.{minutes % 100_000:05d}"


def _nmea_time(utc_ns: int) -> tuple[str, str]:
    """hhmmss.ss and ddmmyy of a UTC instant (Unix ns)."""
    cs = round(utc_ns / 10_000_000)
    seconds, cs = divmod(cs, 100)
    days, sod = divmod(seconds, 86_400)
    hh, rem = divmod(sod, 3600)
    mm, ss = divmod(rem, 60)
    d = dt.date(1970, 1, 1) + dt.timedelta(days=days)
    return f"{hh:02d}{mm:02d}{ss:02d}.{cs:02d}", f"{d.day:02d}{d.month:02d}{d.year % 100:02d}"


def _unix_to_calendar(unix_ns: int) -> tuple[int, int, int, int, int, int]:
    t = dt.datetime(1970, 1, 1) + dt.timedelta(seconds=unix_ns // NS_PER_S)
    return t.year, t.month, t.day, t.hour, t.minute, t.second
