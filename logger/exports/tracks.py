"""Position tracks of a drive: the valid points of ``/gnss/fix`` and ``/nav/fix``, split into segments at gaps.

What a valid point is, is decided here once for every output (GPX, KML, CSV, the map plot): a GNSS epoch
counts only when the receiver flags a 3D fix as OK (``fix_ok``, ``fix_mode`` 3, or 0 when the receiver did not
say the kind), and a position of exactly 0, 0 is what the logger records when the receiver gave none. A
track never joins two points across a skipped message or a silence longer than ``gap_s``: it starts a new
segment instead, so a tunnel or a cold start shows as a break, never as a straight jump.

Point times are GNSS time in UTC: a fix's own epoch (``timestamp``, the receiver's time of the solution) and
a filter solution's ``t_sync_ns`` (the synchronised stamp of its IMU sample), never the board's wall clock.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from logger.recording.drive import DriveFile, DriveMessage
from logger.recording.intervals import next_due_ns
from logger.recording.topics import GNSS_FIX, NAV_FIX

EXPORT_TOPICS = (GNSS_FIX, NAV_FIX)
SIGMA_UNKNOWN_M = 1e6  # what /nav/fix carries for a sigma the filter does not have yet


@dataclass(slots=True)
class TrackPoint:
    t_ns: int  # GNSS time of the position, Unix ns UTC
    lat_deg: float
    lon_deg: float
    h_ell_m: float | None  # above the WGS-84 ellipsoid (None: a receiver that sent no geoid separation)
    h_msl_m: float | None  # above mean sea level (the receiver's geoid)
    speed_mps: float | None  # horizontal
    course_deg: float | None  # over ground, from north, 0..360
    vel_down_mps: float | None
    h_sigma_m: float | None  # horizontal 1-sigma (receiver: hAcc; filter: from sigma north and east)
    v_sigma_m: float | None
    fix_mode: int | None = None
    num_sv: int | None = None
    pdop: float | None = None
    sync_state: str | None = None
    sync_err_ns: int | None = None


@dataclass
class Gap:
    before: TrackPoint  # last point before the gap
    after: TrackPoint  # first point after it
    skipped: int  # messages in between that were not valid positions
    reason: str

    @property
    def duration_s(self) -> float:
        return (self.after.t_ns - self.before.t_ns) / 1e9


@dataclass
class Track:
    key: str  # safe in a file name: gnss_fix, nav_fix, nav_fix_replay, nav_fix_replay_2
    topic: str
    origin: str  # live or replay
    label: str  # for people: "/gnss/fix", "/nav/fix (replay: trajectory.mcap)"
    segments: list[list[TrackPoint]] = field(default_factory=list)
    gaps: list[Gap] = field(default_factory=list)
    messages: int = 0
    skipped: Counter[str] = field(default_factory=Counter)

    @property
    def points(self) -> list[TrackPoint]:
        return [p for seg in self.segments for p in seg]

    @property
    def n_points(self) -> int:
        return sum(len(seg) for seg in self.segments)


def _finite(*values: object) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in values)


def _no_position(lat: object, lon: object) -> bool:
    if not (isinstance(lat, int | float) and isinstance(lon, int | float) and _finite(lat, lon)):
        return True
    return (lat == 0.0 and lon == 0.0) or abs(lat) > 90.0 or abs(lon) > 180.0


def fix_time_ns(msg: dict) -> int:
    """The time a LocationFix is for: its ``timestamp`` ({sec, nsec}), else its ``t_sync_ns``."""
    ts = msg.get("timestamp") or {}
    t = int(ts.get("sec", 0)) * 1_000_000_000 + int(ts.get("nsec", 0))
    return t if t > 0 else int(msg.get("t_sync_ns", 0))


def _velocity(vel: object) -> tuple[float | None, float | None, float | None]:
    if not isinstance(vel, list) or len(vel) != 3:
        return None, None, None
    vn, ve, vd = vel
    if not _finite(vn, ve):
        return None, None, vd if _finite(vd) else None
    course = math.degrees(math.atan2(ve, vn)) % 360.0
    return math.hypot(vn, ve), course, vd if _finite(vd) else None


def gnss_point(msg: dict) -> TrackPoint | str:
    """A /gnss/fix message as a point, or why it is not one."""
    mode, ok = msg.get("fix_mode"), msg.get("fix_ok")
    if mode == 1:
        return "no fix"
    if mode == 2:
        return "2D fix"
    if not ok:
        return "fix not flagged valid"
    lat, lon, alt = msg.get("latitude"), msg.get("longitude"), msg.get("altitude")
    msl = msg.get("height_msl_m")
    # A receiver without a geoid model sends GGA without its separation: a height above sea level and none above
    # the ellipsoid. The point stands with the height it has (it was dropped as "no position").
    if _no_position(lat, lon) or not (_finite(alt) or _finite(msl)):
        return "no position"
    speed, course, vd = _velocity(msg.get("vel_ned_mps"))
    return TrackPoint(fix_time_ns(msg), float(lat), float(lon), float(alt) if _finite(alt) else None,
                      float(msl) if _finite(msl) else None,
                      speed, course, vd, msg.get("h_acc_m"), msg.get("v_acc_m"), mode, msg.get("num_sv"),
                      msg.get("pdop"), msg.get("sync_state"), msg.get("sync_err_ns"))


def nav_point(msg: dict) -> TrackPoint | str:
    """A /nav/fix message as a point, or why it is not one."""
    lat, lon, alt = msg.get("latitude"), msg.get("longitude"), msg.get("altitude")
    if _no_position(lat, lon) or not _finite(alt):
        return "no position"
    sig = msg.get("sigma_ned_m")
    if not isinstance(sig, list) or len(sig) != 3:
        sig = [None, None, None]
    sn, se, sd = (s if _finite(s) and s < SIGMA_UNKNOWN_M else None for s in sig)
    speed, course, vd = _velocity(msg.get("vel_ned_mps"))
    return TrackPoint(fix_time_ns(msg), float(lat), float(lon), float(alt), None, speed, course, vd,
                      math.hypot(sn, se) if sn is not None and se is not None else None, sd)


def _label(topic: str, origin: str, f: DriveFile) -> str:
    return topic if origin == "live" else f"{topic} (replay: {f.path.name})"


class _Builder:
    """One track, point by point: segments broken at gaps, points thinned to ``every_ns``.

    Gaps are judged on every valid point, kept or thinned: a point thinned away is still a position the receiver
    (or the filter) had, so the time since it, not since the last kept point, says whether the track broke. The
    thinning is on a grid of ``every_ns`` anchored at each segment's first point
    (:func:`logger.recording.intervals.next_due_ns`)."""

    def __init__(self, track: Track, gap_ns: int, every_ns: int) -> None:
        self.track, self.gap_ns, self.every_ns = track, gap_ns, every_ns
        self.last: TrackPoint | None = None  # the last valid point, kept or thinned
        self.anchor_ns = 0  # the thinning grid's origin: the segment's first point
        self.due_ns = 0  # the earliest time the next kept point may have
        self.between: Counter[str] = Counter()

    def add(self, point: TrackPoint | str) -> None:
        t = self.track
        t.messages += 1
        if isinstance(point, str):
            t.skipped[point] += 1
            if self.last is not None:
                self.between[point] += 1
            return
        last = self.last
        if last is None:
            self._start(point)
        else:
            dt = point.t_ns - last.t_ns
            if dt <= 0:
                t.skipped["repeated or out-of-order time"] += 1
                return
            if self.between or dt > self.gap_ns:
                n = sum(self.between.values())
                reason = (f"{n} message{'s' if n > 1 else ''} without a valid position "
                          f"({', '.join(self.between)})" if n else f"no message for {dt / 1e9:.1f} s")
                t.gaps.append(Gap(last, point, n, reason))
                self._start(point)
            elif point.t_ns < self.due_ns:
                t.skipped["thinned out (--every)"] += 1
            else:
                t.segments[-1].append(point)
                self._kept(point)
        self.last = point
        self.between = Counter()

    def _start(self, point: TrackPoint) -> None:
        self.track.segments.append([point])
        self.anchor_ns = point.t_ns
        self._kept(point)

    def _kept(self, point: TrackPoint) -> None:
        if self.every_ns > 0:
            self.due_ns = next_due_ns(point.t_ns, self.anchor_ns, self.every_ns)


def build_tracks(messages: Iterable[DriveMessage], files: list[DriveFile], gap_s: float = 3.0,
                 every_s: float = 0.0) -> list[Track]:
    """The tracks of /gnss/fix and /nav/fix in the messages: the live ones over all files, a replayed
    /nav/fix per replay file (each is a whole trajectory of its own)."""
    builders: dict[tuple[str, str, int], _Builder] = {}
    gap_ns, every_ns = int(gap_s * 1e9), int(every_s * 1e9)
    replay_files = sorted({i for i, f in enumerate(files) if f.origin == "replay"})
    for m in messages:
        if m.topic not in EXPORT_TOPICS:
            continue
        f = files[m.file]
        group = (m.topic, f.origin, m.file if f.origin == "replay" else -1)
        b = builders.get(group)
        if b is None:
            key = m.topic.strip("/").replace("/", "_")
            if f.origin == "replay":
                n = replay_files.index(m.file)
                key += "_replay" + (f"_{n + 1}" if n else "")
            b = builders[group] = _Builder(Track(key, m.topic, f.origin, _label(m.topic, f.origin, f)), gap_ns,
                                           every_ns)
        b.add(gnss_point(m.msg) if m.topic == GNSS_FIX else nav_point(m.msg))
    tracks = [b.track for _, b in sorted(builders.items(), key=lambda kv: (kv[0][0], kv[0][1] != "live", kv[0][2]))]
    fill_msl(tracks)
    return tracks


def fill_msl(tracks: list[Track]) -> None:
    """Give filter points a height above sea level from the receiver's own geoid separation (ellipsoidal
    minus MSL height of its fixes, interpolated in time); left None without GNSS fixes that carry one."""
    ref = [(p.t_ns, p.h_ell_m - p.h_msl_m) for t in tracks if t.topic == GNSS_FIX for p in t.points
           if p.h_msl_m is not None and p.h_ell_m is not None]
    if not ref:
        return
    ref.sort()
    t_ref = np.array([r[0] for r in ref], dtype=float)
    n_ref = np.array([r[1] for r in ref], dtype=float)
    for t in tracks:
        if t.topic == GNSS_FIX:
            continue
        pts = t.points
        if not pts:
            continue
        sep = np.interp(np.array([p.t_ns for p in pts], dtype=float), t_ref, n_ref)
        for p, n in zip(pts, sep, strict=True):
            p.h_msl_m = None if p.h_ell_m is None else p.h_ell_m - float(n)
