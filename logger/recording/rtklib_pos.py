"""RTKLIB solution files (``.pos``, the output of ``rnx2rtkp`` and ``rtkpost``) as the filter's typed inputs.

A survey engineer processes the receiver's raw observations at the office against a base station (PPK) and
gets a ``.pos``: ``%`` header lines (the program, the input files, ``% ref pos`` for a relative solution, the
legend, and the column header, whose first word is the time system), then one line per epoch. Every layout
``rnx2rtkp`` writes is read:

- time: ``yyyy/mm/dd hh:mm:ss.sss`` (any number of decimals, ``-d``) or ``week tow`` (``out-timeform=tow``), in
  ``GPST`` (the default), ``UTC`` (``-u``) or ``JST`` (``out-timesys=jst``, UTC + 9 h);
- position: latitude / longitude / height in degrees (the default) or as ``ddd mm ss.sss`` (``-g``), ECEF
  x / y / z (``-e``), or east / north / up from the base (``-a``, with the header's ``% ref pos``);
- then ``Q ns``, three standard deviations, three signed cross terms, ``age`` and ``ratio`` (and, with
  ``out-outvel``, a velocity block, which is not used: it is the solution's Doppler velocity, which the receiver's
  own fixes carry already).

A cross term is written as sign(c) * sqrt(|c|) of the covariance c (RTKLIB's ``sqvar``): squared back with its
sign here. The epochs come out in UTC (Unix ns), the scale of the receiver's epoch times in ``/gnss/fix``: GPST
runs ahead of UTC by the leap seconds since 1980 (18 s since 2017).

A file that is not such a solution, or a line that cannot be read, raises :class:`SolutionFileError` naming the
file and the line, so ``logger replay`` can say it in one line.
"""

from __future__ import annotations

import datetime as dt
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from logger.nav import earth
from logger.nav.inputs import SolutionEpoch

NS = 1_000_000_000
GPS_EPOCH = dt.datetime(1980, 1, 6, tzinfo=dt.UTC)
# GPST - UTC from each date on (IERS Bulletin C); RTKLIB carries the same table (rtkcmn.c leaps[]).
LEAP_SECONDS: tuple[tuple[dt.datetime, int], ...] = tuple(
    (dt.datetime(y, m, 1, tzinfo=dt.UTC), s) for y, m, s in (
        (1981, 7, 1), (1982, 7, 2), (1983, 7, 3), (1985, 7, 4), (1988, 1, 5), (1990, 1, 6), (1991, 1, 7),
        (1992, 7, 8), (1993, 7, 9), (1994, 7, 10), (1996, 1, 11), (1997, 7, 12), (1999, 1, 13), (2006, 1, 14),
        (2009, 1, 15), (2012, 7, 16), (2015, 7, 17), (2017, 1, 18)))
TIME_SYSTEMS = ("GPST", "UTC", "JST")
QUALITIES = {1: "fix", 2: "float", 3: "sbas", 4: "dgps", 5: "single", 6: "ppp"}
LLH, DMS, XYZ, ENU = "llh", "dms", "xyz", "enu"
_YMD = re.compile(r"^\s*(\d{4})/(\d{1,2})/(\d{1,2})\s+(\d{1,2}):(\d{1,2}):(\d{1,2}(?:\.\d*)?)(\s|$)")
_REF_POS = re.compile(r"^%\s*ref pos\s*:\s*(\S+)\s+(\S+)\s+(\S+)")


class SolutionFileError(ValueError):
    """The file is not an RTKLIB position solution, or one of its lines cannot be read (the message names both)."""


@dataclass
class SolutionFile:
    """A parsed ``.pos``: its epochs in time order, and what its header said."""

    path: Path
    time_system: str  # GPST, UTC or JST
    position_format: str  # llh, dms, xyz or enu
    epochs: list[SolutionEpoch] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        """Epochs per quality, by RTKLIB's names (fix, float, sbas, dgps, single, ppp)."""
        out: dict[str, int] = {}
        for e in self.epochs:
            name = QUALITIES.get(e.quality, f"Q{e.quality}")
            out[name] = out.get(name, 0) + 1
        return out


def gpst_minus_utc_s(utc: dt.datetime) -> int:
    """Leap seconds between GPS time and UTC at a UTC instant."""
    n = 0
    for since, s in LEAP_SECONDS:
        if utc >= since:
            n = s
    return n


def unix_ns_utc(t: dt.datetime, time_system: str) -> int:
    """A calendar time of the file's time system (naive) as Unix ns UTC."""
    if time_system == "JST":
        utc = t.replace(tzinfo=dt.UTC) - dt.timedelta(hours=9)
    elif time_system == "UTC":
        utc = t.replace(tzinfo=dt.UTC)
    else:  # GPST: the leap seconds at the UTC instant, which is within 18 s of the GPST one
        g = t.replace(tzinfo=dt.UTC)
        utc = g - dt.timedelta(seconds=gpst_minus_utc_s(g - dt.timedelta(seconds=gpst_minus_utc_s(g))))
    delta = utc - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
    return (delta.days * 86400 + delta.seconds) * NS + delta.microseconds * 1000


def _seconds_ns(text: str) -> tuple[int, int]:
    """Whole seconds and the nanoseconds of a decimal field, exactly (no float rounding at 1e-9)."""
    whole, _, frac = text.partition(".")
    return int(whole), int((frac + "000000000")[:9])


def read_pos(path: Path) -> SolutionFile:
    """Parse an RTKLIB ``.pos`` file; :class:`SolutionFileError` names the file and the line of any problem."""
    try:
        text = path.read_text(encoding="ascii", errors="strict")
    except UnicodeDecodeError as exc:
        raise SolutionFileError(f"{path}: not a text file (byte {exc.start}): not an RTKLIB .pos") from None
    except OSError as exc:
        raise SolutionFileError(f"{path}: {exc.strerror}") from None
    time_system = fmt = ""
    ref: tuple[float, float, float] | None = None
    out: SolutionFile | None = None
    for no, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        if line.startswith("%"):
            m = _REF_POS.match(line)
            if m:
                ref = _ref_position(path, no, m.groups())
            words = line[1:].split()
            if words and words[0] in TIME_SYSTEMS and len(words) > 1:
                time_system, fmt = words[0], _position_format(line)
            continue
        if line.startswith("$"):
            raise SolutionFileError(f"{path}:{no}: an NMEA sentence: this is rnx2rtkp's -n output, not a .pos "
                                    "(write it without -n)")
        if out is None:
            if not time_system:
                raise SolutionFileError(f"{path}:{no}: a solution line before the column header ('%  GPST  "
                                        "latitude(deg) ...'): not an RTKLIB .pos, or written without its header "
                                        "(out-outhead=on)")
            if fmt == ENU and ref is None:
                raise SolutionFileError(f"{path}:{no}: e/n/u baselines without '% ref pos' in the header: the base "
                                        "position is needed to place them")
            out = SolutionFile(path, time_system, fmt)
        out.epochs.append(_epoch(path, no, line, time_system, fmt, ref))
    if out is None or not out.epochs:
        raise SolutionFileError(f"{path}: no solution epochs (an RTKLIB .pos has '%' header lines, then one line "
                                "per epoch)")
    out.epochs.sort(key=lambda e: e.gnss_time_ns)
    return out


def _position_format(header: str) -> str:
    if "latitude(deg)" in header:
        return LLH
    if "latitude(d'\")" in header:
        return DMS
    if "x-ecef(m)" in header:
        return XYZ
    if "e-baseline(m)" in header:
        return ENU
    return ""


def _ref_position(path: Path, no: int, fields: tuple[str, ...]) -> tuple[float, float, float]:
    try:
        lat, lon, h = (float(v) for v in fields)
    except ValueError:
        raise SolutionFileError(f"{path}:{no}: '% ref pos' is not latitude longitude height") from None
    return math.radians(lat), math.radians(lon), h


def _epoch(path: Path, no: int, line: str, time_system: str, fmt: str,
           ref: tuple[float, float, float] | None) -> SolutionEpoch:
    where = f"{path}:{no}"
    if not fmt:
        raise SolutionFileError(f"{where}: the column header names no position layout rnx2rtkp writes "
                                "(latitude(deg), latitude(d'\"), x-ecef(m) or e-baseline(m))")
    m = _YMD.match(line)
    try:
        if m:
            y, mo, d, hh, mi = (int(v) for v in m.groups()[:5])
            s, ns = _seconds_ns(m.group(6))
            t = dt.datetime(y, mo, d, hh, mi) + dt.timedelta(seconds=s)
            t_ns = unix_ns_utc(t, time_system) + ns
            rest = line[m.end():].split()
        else:
            words = line.split()
            week, (s, ns) = int(words[0]), _seconds_ns(words[1])
            if not 0 <= s < 604800:
                raise ValueError
            t = GPS_EPOCH.replace(tzinfo=None) + dt.timedelta(weeks=week, seconds=s)
            t_ns = unix_ns_utc(t, time_system) + ns
            rest = words[2:]
    except (ValueError, IndexError, OverflowError):
        raise SolutionFileError(f"{where}: the time is neither 'yyyy/mm/dd hh:mm:ss.sss' nor 'week tow'") from None
    n_pos = 7 if fmt == DMS else 3
    if len(rest) < n_pos + 2:
        raise SolutionFileError(f"{where}: {len(rest)} fields after the time, a {fmt} solution line has at least "
                                f"{n_pos + 2} (position, Q, ns)")
    try:
        v = [float(x) for x in rest]
    except ValueError as exc:
        raise SolutionFileError(f"{where}: not a number: {str(exc).split(': ', 1)[-1]}") from None
    pos, q, nsat = v[:n_pos], v[n_pos], v[n_pos + 1]
    if q != int(q) or int(q) not in QUALITIES:
        raise SolutionFileError(f"{where}: quality Q {rest[n_pos]} is none of RTKLIB's 1 fix, 2 float, 3 SBAS, "
                                "4 DGPS, 5 single, 6 PPP")
    sd = v[n_pos + 2:n_pos + 8]
    if len(sd) not in (0, 3, 6):
        raise SolutionFileError(f"{where}: {len(sd)} standard deviation fields, a solution line has 3 or 6")
    sd += [0.0] * (6 - len(sd))
    tail = v[n_pos + 8:n_pos + 10]
    age, ratio = [*tail, 0.0, 0.0][:2]
    lat, lon, h, cov = _position(fmt, pos, sd, ref)
    if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(h) and abs(lat) <= math.pi / 2):
        raise SolutionFileError(f"{where}: the position is not on the earth")
    if any(x < 0.0 for x in sd[:3]):
        raise SolutionFileError(f"{where}: a negative standard deviation")
    return SolutionEpoch(t_ns, math.degrees(lat), math.degrees(lon), h, cov, int(q), int(nsat), age, ratio)


def _sq(signed_sqrt: float) -> float:
    """A covariance back from RTKLIB's sign(c) * sqrt(|c|)."""
    return math.copysign(signed_sqrt * signed_sqrt, signed_sqrt)


def _position(fmt: str, pos: list[float], sd: list[float], ref: tuple[float, float, float] | None
              ) -> tuple[float, float, float, tuple[tuple[float, float, float], ...]]:
    """Latitude, longitude (rad), height and the NED covariance of a line's position fields."""
    a, b, c = sd[0] ** 2, sd[1] ** 2, sd[2] ** 2
    x, y, z = _sq(sd[3]), _sq(sd[4]), _sq(sd[5])
    if fmt in (LLH, DMS):
        if fmt == LLH:
            lat, lon = math.radians(pos[0]), math.radians(pos[1])
            h = pos[2]
        else:  # ddd mm ss.sss: the sign is the degrees' (a "-0" included)
            lat, lon = (math.radians(math.copysign(abs(d) + mi / 60.0 + sec / 3600.0, d))
                        for d, mi, sec in (pos[0:3], pos[3:6]))
            h = pos[6]
        # sdn sde sdu, sdne sdeu sdun: the down axis is minus up.
        return lat, lon, h, ((a, x, -z), (x, b, -y), (-z, -y, c))
    if fmt == ENU:
        assert ref is not None
        e, n, u = pos
        r0 = earth.ecef_from_llh(*ref)
        rows = earth.ned_rows(ref[0], ref[1])
        d = (n, e, -u)
        p = tuple(r0[k] + sum(rows[i][k] * d[i] for i in range(3)) for k in range(3))
        lat, lon, h = earth.llh_from_ecef(*p)
        # sde sdn sdu, sden sdnu sdue (in the base's frame, which is the rover's to a few arc-seconds)
        return lat, lon, h, ((b, x, -y), (x, a, -z), (-y, -z, c))
    lat, lon, h = earth.llh_from_ecef(*pos)
    # sdx sdy sdz, sdxy sdyz sdzx: rotated into the solution's own north, east, down.
    p = ((a, x, z), (x, b, y), (z, y, c))
    rows = earth.ned_rows(lat, lon)
    cov = tuple(tuple(sum(rows[i][k] * p[k][m] * rows[j][m] for k in range(3) for m in range(3)) for j in range(3))
                for i in range(3))
    return lat, lon, h, cov
