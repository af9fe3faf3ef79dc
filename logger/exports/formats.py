"""Writers of position tracks: GPX 1.1, KML 2.2 and CSV.

GPX: one ``<trk>`` per track, one ``<trkseg>`` per segment, ``<time>`` the point's GNSS time in UTC (ISO 8601,
milliseconds), ``<ele>`` the height the caller chose (ellipsoidal by default: it is what every topic records;
MSL through the receiver's geoid separation on request), and for receiver fixes ``<fix>``, ``<sat>`` and
``<pdop>``. Elements follow the order of the GPX 1.1 schema's ``wptType``, so strict readers accept them.

KML: per track one Placemark whose ``gx:MultiTrack`` holds a ``gx:Track`` per segment: every point with its own
``<when>`` (Google Earth's time slider plays the drive as it was driven, and readers need not invent times
between the ends), clamped to the ground, not interpolated across the gaps; optionally a Placemark at the start
of every gap.

CSV: one file per track, a header with the unit in every column name, empty cells for what a topic lacks.
"""

from __future__ import annotations

import csv
import datetime as dt
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

from logger.exports.tracks import Gap, Track, TrackPoint
from logger.exports.whole import written_whole
from logger.recording.topics import GNSS_FIX, NAV_FIX
from logger.words import plural

GPX_NS = "http://www.topografix.com/GPX/1/1"
GPX_SCHEMA = "http://www.topografix.com/GPX/1/1/gpx.xsd"
KML_NS = "http://www.opengis.net/kml/2.2"
GX_NS = "http://www.google.com/kml/ext/2.2"  # Google's extension namespace: gx:Track, gx:MultiTrack, gx:coord
HEIGHTS = ("ellipsoid", "msl")
HEIGHT_TEXT = {"ellipsoid": "height above the WGS-84 ellipsoid, m",
               "msl": "height above mean sea level (the receiver's geoid), m"}
TIME_TEXT = {GNSS_FIX: "the receiver's epoch time of the fix, UTC",
             NAV_FIX: "the synchronised (GNSS) time of the filter's IMU sample, UTC"}
# KML colours are aabbggrr
KML_COLOURS = ("ff1f77b4", "ff0e7fff", "ff2ca02c", "ff2827d6", "ffbd6794")
CSV_COLUMNS = ("time_utc", "t_unix_ns", "segment", "lat_deg", "lon_deg", "height_ellipsoid_m", "height_msl_m",
               "speed_mps", "course_deg", "vel_down_mps", "h_sigma_m", "v_sigma_m", "fix_mode", "num_sv", "pdop",
               "sync_state", "sync_err_ns")


def utc_iso(t_ns: int) -> str:
    """Unix ns as ISO 8601 UTC with milliseconds, e.g. 2026-11-22T18:43:49.123Z."""
    ms = (t_ns + 500_000) // 1_000_000
    stamp = dt.datetime.fromtimestamp(ms // 1000, tz=dt.UTC).strftime("%Y-%m-%dT%H:%M:%S")
    return f"{stamp}.{ms % 1000:03d}Z"


def height(p: TrackPoint, which: str) -> float | None:
    return p.h_ell_m if which == "ellipsoid" else p.h_msl_m


def _num(v: float | None, digits: int) -> str:
    return "" if v is None else f"{v:.{digits}f}"


def _gpx_point(p: TrackPoint, which: str, gnss: bool) -> str:
    parts = [f'<trkpt lat="{p.lat_deg:.9f}" lon="{p.lon_deg:.9f}">']
    h = height(p, which)
    if h is not None:
        parts.append(f"<ele>{h:.3f}</ele>")
    parts.append(f"<time>{utc_iso(p.t_ns)}</time>")
    if which == "msl" and p.h_msl_m is not None and p.h_ell_m is not None:
        parts.append(f"<geoidheight>{p.h_ell_m - p.h_msl_m:.3f}</geoidheight>")
    if gnss:
        if p.fix_mode == 3:
            parts.append("<fix>3d</fix>")
        if p.num_sv is not None:
            parts.append(f"<sat>{int(p.num_sv)}</sat>")
        if p.pdop is not None:
            parts.append(f"<pdop>{p.pdop:.2f}</pdop>")
    parts.append("</trkpt>")
    return "".join(parts)


def write_gpx(path: Path, tracks: list[Track], which: str, title: str) -> None:
    pts = [p for t in tracks for p in t.points]
    with written_whole(path, "w", encoding="utf-8") as f:
        f.write('<?xml version="1.0" encoding="UTF-8"?>\n')
        f.write(f'<gpx version="1.1" creator="vehicle-logger export" xmlns="{GPX_NS}" '
                f'xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" '
                f'xsi:schemaLocation="{GPX_NS} {GPX_SCHEMA}">\n')
        f.write(f"<metadata><name>{escape(title)}</name>"
                f"<desc>{escape(f'<ele>: {HEIGHT_TEXT[which]}')}</desc>")
        if pts:
            f.write(f"<time>{utc_iso(min(p.t_ns for p in pts))}</time>")
            f.write(f'<bounds minlat="{min(p.lat_deg for p in pts):.9f}" minlon="{min(p.lon_deg for p in pts):.9f}" '
                    f'maxlat="{max(p.lat_deg for p in pts):.9f}" maxlon="{max(p.lon_deg for p in pts):.9f}"/>')
        f.write("</metadata>\n")
        for t in tracks:
            desc = (f"{plural(t.n_points, 'point')}, {plural(len(t.segments), 'segment')}; "
                    f"<time>: {TIME_TEXT[t.topic]}; <ele>: {HEIGHT_TEXT[which]}")
            f.write(f"<trk><name>{escape(t.label)}</name><desc>{escape(desc)}</desc>"
                    f"<src>vehicle-logger {escape(t.topic)} ({t.origin})</src><type>{escape(t.key)}</type>\n")
            for seg in t.segments:
                f.write("<trkseg>\n")
                for p in seg:
                    f.write(_gpx_point(p, which, t.topic == GNSS_FIX))
                    f.write("\n")
                f.write("</trkseg>\n")
            f.write("</trk>\n")
        f.write("</gpx>\n")


def _coord(p: TrackPoint, which: str) -> str:
    h = height(p, which)
    return f"{p.lon_deg:.9f},{p.lat_deg:.9f}" + ("" if h is None else f",{h:.3f}")


def _gx_track(seg: list[TrackPoint], which: str) -> str:
    """One segment as a gx:Track: all the ``<when>`` first, then the ``<gx:coord>`` (lon lat alt, by spaces)."""
    whens = "".join(f"<when>{utc_iso(p.t_ns)}</when>" for p in seg)
    # gx:coord is always three numbers; a point without the chosen height (no geoid separation) gets 0,
    # which the track's clampToGround does not use anyway.
    coords = "".join(f"<gx:coord>{p.lon_deg:.9f} {p.lat_deg:.9f} {_num(height(p, which), 3) or '0'}</gx:coord>"
                     for p in seg)
    return f"<gx:Track><altitudeMode>clampToGround</altitudeMode>{whens}\n{coords}</gx:Track>\n"


def _kml_gap(g: Gap, which: str) -> str:
    """A placemark where a gap starts, its elements in OGC KML 2.2's order (a feature's time before its style)."""
    text = (f"{g.reason}; stopped {utc_iso(g.before.t_ns)}, resumed {utc_iso(g.after.t_ns)} "
            f"at {g.after.lat_deg:.7f}, {g.after.lon_deg:.7f}")
    return (f"<Placemark><name>gap {g.duration_s:.1f} s</name><description>{escape(text)}</description>"
            f"<TimeStamp><when>{utc_iso(g.before.t_ns)}</when></TimeStamp><styleUrl>#gap</styleUrl>"
            f"<Point><coordinates>{_coord(g.before, which)}</coordinates></Point></Placemark>\n")


def write_kml(path: Path, tracks: list[Track], which: str, title: str, gap_marks: bool = False) -> None:
    with written_whole(path, "w", encoding="utf-8") as f:
        f.write('<?xml version="1.0" encoding="UTF-8"?>\n')
        f.write(f'<kml xmlns="{KML_NS}" xmlns:gx="{GX_NS}"><Document><name>{escape(title)}</name>\n')
        f.write(f"<description>{escape(f'altitudes: {HEIGHT_TEXT[which]} (lines are clamped to the ground)')}"
                "</description>\n")
        for i, t in enumerate(tracks):
            f.write(f'<Style id={quoteattr(t.key)}><LineStyle><color>{KML_COLOURS[i % len(KML_COLOURS)]}</color>'
                    "<width>3</width></LineStyle></Style>\n")
        f.write('<Style id="gap"><IconStyle><color>ff0000ff</color></IconStyle></Style>\n')
        for t in tracks:
            f.write(f"<Folder><name>{escape(t.label)}</name>\n")
            pts = t.points
            if pts:
                desc = ", ".join((plural(t.n_points, "point"), plural(len(t.segments), "segment"),
                                  plural(len(t.gaps), "gap")))
                f.write(f"<Placemark><name>{escape(t.label)}</name><description>{escape(desc)}</description>"
                        f"<styleUrl>#{t.key}</styleUrl><gx:MultiTrack><gx:interpolate>0</gx:interpolate>\n")
                for seg in t.segments:
                    f.write(_gx_track(seg, which))
                f.write("</gx:MultiTrack></Placemark>\n")
            if gap_marks:
                for g in t.gaps:
                    f.write(_kml_gap(g, which))
            f.write("</Folder>\n")
        f.write("</Document></kml>\n")


def write_csv(path: Path, track: Track) -> None:
    with written_whole(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for n, seg in enumerate(track.segments, 1):
            for p in seg:
                w.writerow([utc_iso(p.t_ns), p.t_ns, n, f"{p.lat_deg:.9f}", f"{p.lon_deg:.9f}", _num(p.h_ell_m, 3),
                            _num(p.h_msl_m, 3), _num(p.speed_mps, 3), _num(p.course_deg, 2),
                            _num(p.vel_down_mps, 3), _num(p.h_sigma_m, 3), _num(p.v_sigma_m, 3),
                            "" if p.fix_mode is None else p.fix_mode, "" if p.num_sv is None else p.num_sv,
                            _num(p.pdop, 2), p.sync_state or "", "" if p.sync_err_ns is None else p.sync_err_ns])
