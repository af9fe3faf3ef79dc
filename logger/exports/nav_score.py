"""Score a navigation trajectory against the truth of a simulated drive, or against a reference trajectory.

    logger nav-score DIR/trajectory.csv [DRIVE.mcap...] [--reference REF.csv|REF.mcap] [--plots DIR] [--json]

Prints, per north/east/down, the RMSE, mean, minimum and maximum error (the paper's Table 9), the horizontal
drift in every GNSS outage of the drive, and how often the error stays within 3 sigma of the filter's own
uncertainty. Each row is compared with the truth at the true time of its IMU sample (the row's t_mono_ns
through /truth/clock), so a free-running or disciplined logger clock scores the same. A reference trajectory has
no board clock of its own: its times are GNSS time, joined to the rows' t_sync_ns. Rows outside what they are
scored against (a drive cut short, another drive) are left out and counted, never placed at its nearest end.
With matplotlib installed (``pip install -e '.[plots]'``), ``--plots`` writes a map view and the error over time
as PNG.
"""

from __future__ import annotations

import csv
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from logger.exports.plotting import PlotsUnavailable, local_en, pyplot
from logger.exports.whole import save_figure, written_together
from logger.nav import earth
from logger.recording.drive import read_messages
from logger.recording.topics import GNSS_FIX, NAV_FIX, TRUTH_CLOCK, TRUTH_NAV

OUTAGE_MIN_S = 5.0
FOREIGN_M = 500.0
"""A trajectory whose rows lie a median this far from the drive's own GNSS fixes at the same board times is likely
not the drive's (its filter fused those fixes, which a receiver puts within metres; two drives of the simulator can
share their clocks' span, so time alone cannot tell), or its filter lost them: warned about, scored all the same."""


TRAJECTORY_COLUMNS = ("t_sync_ns", "lat_deg", "lon_deg", "height_m", "sn_m", "se_m", "sd_m")
"""The columns of ``logger replay``'s trajectory.csv that a score reads (``t_mono_ns`` too where it is there)."""
REFERENCE_COLUMNS = TRAJECTORY_COLUMNS[:4]
"""What a reference trajectory needs: its time and position (its own uncertainty is not scored)."""


class ScoreError(Exception):
    """Nothing can be scored: the message is one line for the user (naming the file where there is one)."""


class NoTruth(ScoreError):
    """The files are not a simulated drive: there is nothing to score against."""


class NoOverlap(ScoreError):
    """No row of a trajectory falls within what it is scored against: another drive's, or a drive cut short."""


def _utc(t_ns: float) -> str:
    return np.datetime_as_string(np.datetime64(int(t_ns), "ns"), unit="s") + "Z"


@dataclass
class Truth:
    """What trajectories are scored against: a simulated drive's truth, or a reference trajectory.

    A simulated drive's truth is in true time, which only its own /truth/clock links to the board's clock: a row is
    placed by its ``t_mono_ns`` through that clock, so that a free-running or disciplined logger clock scores the
    same. A reference trajectory (another solution of the drive: a smoothed replay, a reference receiver's) has no
    such clock: its times are GNSS time, as a trajectory's ``t_sync_ns`` is, and the two are joined on them
    (``clock_mono`` and ``clock_true`` are then None)."""

    t_ns: np.ndarray  # true time (a reference: its t_sync_ns), Unix ns
    lat: np.ndarray  # rad
    lon: np.ndarray
    h: np.ndarray
    clock_mono: np.ndarray | None  # /truth/clock pairs; None for a reference trajectory
    clock_true: np.ndarray | None
    outages: list[tuple[int, int]] = field(default_factory=list)  # true-time spans without a GNSS fix
    what: str = "the drive's truth"  # what it is, for the user's messages
    # The drive's valid /gnss/fix, a row each: board ns, lat, lon (rad); empty for a reference.
    fixes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def true_time(self, t_mono_ns: np.ndarray) -> np.ndarray:
        """True time at board times through /truth/clock, held at its ends outside it (for interpolating the
        truth's own states; which rows may be scored is :meth:`row_times`'s)."""
        if self.clock_mono is None or self.clock_true is None:
            raise ScoreError(f"{self.what} has no board clock: its times are GNSS time")
        return np.interp(t_mono_ns.astype(float), self.clock_mono.astype(float), self.clock_true.astype(float))

    def row_times(self, traj: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Each row's time on this truth's time base, and whether the truth covers it.

        Rows outside the truth's span are not scored: the clock's mapping held at its ends (or extrapolated) would
        put them at a moment they are not from, and compare them with where the car was then, which measures
        nothing (kilometres against the first half of a drive cut short)."""
        t_mono = traj.get("t_mono_ns")
        if self.clock_mono is not None and t_mono is not None and len(t_mono):
            t = self.true_time(t_mono)
            inside = (t_mono >= self.clock_mono[0]) & (t_mono <= self.clock_mono[-1])
        else:  # a reference in GNSS time, or a trajectory without board times: its synchronised time
            t = traj["t_sync_ns"].astype(float)
            inside = np.ones(len(t), dtype=bool)
        inside &= (t >= self.t_ns[0]) & (t <= self.t_ns[-1])
        return t, inside

    def span_note(self, traj: dict[str, np.ndarray]) -> str:
        """Where the truth and the rows lie in time, on the base they are joined on, for a refusal."""
        t_mono = traj.get("t_mono_ns")
        if self.clock_mono is not None and t_mono is not None and len(t_mono):
            return (f"board time {self.clock_mono[0] / 1e9:.1f}-{self.clock_mono[-1] / 1e9:.1f} s by /truth/clock, "
                    f"the rows {t_mono.min() / 1e9:.1f}-{t_mono.max() / 1e9:.1f} s")
        t = traj["t_sync_ns"]
        return f"{_utc(self.t_ns[0])} to {_utc(self.t_ns[-1])}, the rows {_utc(t.min())} to {_utc(t.max())}"


def fix_distance(traj: dict[str, np.ndarray], truth: Truth) -> float | None:
    """The median horizontal distance, m, of the trajectory from the drive's own valid GNSS fixes at their board
    times (within the rows' span); None where there is nothing to compare (a reference, no fix, no board time).
    Beyond FOREIGN_M the trajectory is likely another drive's, whatever its times say."""
    t_mono = traj.get("t_mono_ns")
    if truth.clock_mono is None or t_mono is None or len(t_mono) < 2 or not len(truth.fixes):
        return None
    order = np.argsort(t_mono)
    tm = t_mono[order].astype(float)
    f = truth.fixes[(truth.fixes[:, 0] >= tm[0]) & (truth.fixes[:, 0] <= tm[-1])]
    if not len(f):
        return None
    lat = np.interp(f[:, 0], tm, np.radians(traj["lat_deg"][order]))
    lon = np.interp(f[:, 0], tm, np.radians(traj["lon_deg"][order]))
    rm, rn = np.vectorize(earth.radii)(f[:, 1])
    return float(np.median(np.hypot((lat - f[:, 1]) * rm, (lon - f[:, 2]) * rn * np.cos(f[:, 1]))))


def _outages(t_ns: np.ndarray, ok: list[bool]) -> list[tuple[int, int]]:
    """Spans of at least OUTAGE_MIN_S between two fixes with a position, the fixes in time order."""
    out: list[tuple[int, int]] = []
    last_ok = None
    start = None
    for t, good in zip(t_ns, ok, strict=True):
        if good:
            if start is not None and last_ok is not None and (t - last_ok) / 1e9 >= OUTAGE_MIN_S:
                out.append((int(last_ok), int(t)))
            start = None
            last_ok = t
        elif start is None:
            start = t
    return out


def load_truth(paths: list[Path]) -> Truth:
    """A simulated drive's truth (/truth/nav, /truth/clock) and its GNSS outages (/gnss/fix), read through the
    project's drive reader (a file cut short is read up to the cut; DriveFileError for a file it cannot read)."""
    nav: list[tuple[int, float, float, float]] = []
    clock: list[tuple[int, int]] = []
    fixes: list[tuple[int, bool]] = []
    positions: list[tuple[int, float, float]] = []
    for topic, d in read_messages(paths, (TRUTH_NAV, TRUTH_CLOCK, GNSS_FIX)):
        if topic == TRUTH_NAV:
            nav.append((d["t_true_ns"], d["lat_deg"], d["lon_deg"], d["height_m"]))
        elif topic == TRUTH_CLOCK:
            clock.append((d["t_mono_ns"], d["t_true_ns"]))
        else:
            fixes.append((d["t_mono_ns"], bool(d.get("fix_ok"))))
            if d.get("fix_ok"):
                positions.append((d["t_mono_ns"], d["latitude"], d["longitude"]))
    if not nav or not clock:
        names = ", ".join(map(str, paths)) or "no drive named"
        raise NoTruth(f"{names}: no /truth/nav or /truth/clock: not a simulated drive (score against a reference "
                      "trajectory with --reference)")
    nav.sort()
    clock.sort()
    a = np.array(nav, dtype=float)
    c = np.array(clock, dtype=np.int64)
    truth = Truth(np.array([n[0] for n in nav], dtype=np.int64), np.radians(a[:, 1]), np.radians(a[:, 2]), a[:, 3],
                  c[:, 0], c[:, 1])
    if positions:
        f = np.array(sorted(positions), dtype=float)
        truth.fixes = np.column_stack((f[:, 0], np.radians(f[:, 1]), np.radians(f[:, 2])))
    fixes.sort()
    fixes = [f for f in fixes if c[0, 0] <= f[0] <= c[-1, 0]]  # outside the clock there is no true time
    if fixes:
        truth.outages = _outages(truth.true_time(np.array([f[0] for f in fixes], dtype=np.int64)),
                                 [f[1] for f in fixes])
    return truth


def reference_outages(paths: list[Path]) -> list[tuple[int, int]]:
    """The GNSS outages of a drive in its synchronised time, the time base of a reference trajectory: with
    --reference, the drive named beside it says where its receiver had no fix."""
    fixes = sorted((d["t_sync_ns"], bool(d.get("fix_ok"))) for _, d in read_messages(paths, (GNSS_FIX,)))
    return _outages(np.array([f[0] for f in fixes], dtype=np.int64), [f[1] for f in fixes])


def load_reference(path: Path) -> Truth:
    """A reference trajectory: ``logger replay``'s trajectory.csv layout, or an MCAP file's /nav/fix (replay's
    trajectory.mcap, or a drive's live solution). Its times are GNSS time (``t_sync_ns``); ScoreError or
    DriveFileError, naming the file, for one that holds no trajectory."""
    if path.suffix.lower() == ".mcap":
        fixes = [d for _, d in read_messages([path], (NAV_FIX,))]
        if not fixes:
            raise ScoreError(f"{path}: no /nav/fix messages: not a trajectory")
        rows = {"t_sync_ns": np.array([m["t_sync_ns"] for m in fixes], dtype=np.int64),
                "lat_deg": np.array([m["latitude"] for m in fixes], dtype=float),
                "lon_deg": np.array([m["longitude"] for m in fixes], dtype=float),
                "height_m": np.array([m["altitude"] for m in fixes], dtype=float)}
    elif path.suffix.lower() == ".csv":
        rows = read_trajectory(path, REFERENCE_COLUMNS)
    else:
        raise ScoreError(f"{path}: a reference is a trajectory CSV or an MCAP file with /nav/fix")
    # In time order, one position per instant: np.interp needs rising times.
    t, first = np.unique(rows["t_sync_ns"].astype(np.int64), return_index=True)
    return Truth(t, np.radians(rows["lat_deg"][first]), np.radians(rows["lon_deg"][first]), rows["height_m"][first],
                 None, None, what=f"the reference {path}")


def read_trajectory(path: Path, need: tuple[str, ...] = TRAJECTORY_COLUMNS) -> dict[str, np.ndarray]:
    """The columns of a trajectory CSV (``logger replay``'s layout), as arrays.

    ScoreError, one line naming the file and what is wrong, for a file that is not one: empty, without the columns
    ``need`` names (the CSV of ``logger export``, say), or with a row that does not parse; a column that is not
    needed and does not parse is left out."""
    try:
        with open(path, newline="") as f:
            r = csv.reader(f)
            header = next(r, None)
            data = [(r.line_num, row) for row in r if row]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ScoreError(f"{path}: cannot be read ({exc})") from exc
    if not header:
        raise ScoreError(f"{path}: empty: not a trajectory (logger replay's trajectory.csv)")
    missing = [c for c in need if c not in header]
    if missing:
        raise ScoreError(f"{path}: no column {', '.join(missing)}: not a trajectory of logger replay (its "
                         f"trajectory.csv has {', '.join(TRAJECTORY_COLUMNS)})")
    if not data:
        raise ScoreError(f"{path}: no rows under its header")
    for line, row in data:
        if len(row) != len(header):
            raise ScoreError(f"{path}: line {line} has {len(row)} fields, the header {len(header)}")
    cols: dict[str, np.ndarray] = {}
    for i, name in enumerate(header):
        kind = np.int64 if name.endswith("_ns") else float
        try:
            cols[name] = np.array([row[i] for _, row in data], dtype=kind)
        except (ValueError, OverflowError):
            if name not in need and name != "t_mono_ns":
                continue
            line, bad = next((line, row[i]) for line, row in data if not _parses(row[i], kind))
            raise ScoreError(f"{path}: line {line}: {name} {bad!r} is not a number") from None
    return cols


def _parses(text: str, kind: type) -> bool:
    try:
        np.array([text], dtype=kind)
    except (ValueError, OverflowError):
        return False
    return True


@dataclass
class Score:
    n: int  # rows scored
    span_s: float
    coverage: float  # fraction of the truth's time span with a solution within 1.5 s
    rmse: list[float]
    mean: list[float]
    min: list[float]
    max: list[float]
    max_h: float
    within_3sigma: list[float]
    within_3sigma_all: float
    outages: list[dict[str, float]]
    rows: int = 0  # rows of the trajectory in all (after skip_s); those outside the truth's span are not scored
    t_s: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    err: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 3)))
    sig: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 3)))

    def table(self) -> dict[str, list[float]]:
        return {"max": self.max, "min": self.min, "mean": self.mean, "rmse": self.rmse}


def score(traj: dict[str, np.ndarray], truth: Truth, skip_s: float = 0.0) -> Score:
    """The errors of the rows the truth covers (:meth:`Truth.row_times`); NoOverlap when it covers none."""
    t_true, keep = truth.row_times(traj)
    rows = len(t_true)
    if skip_s > 0 and keep.any():
        rows = int(np.sum(t_true >= t_true[keep][0] + skip_s * 1e9))
        keep &= t_true >= t_true[keep][0] + skip_s * 1e9
    if not keep.any():
        raise NoOverlap(f"none of its {len(t_true)} rows falls within the span of {truth.what} "
                        f"({truth.span_note(traj)}): another drive's trajectory, or one cut short before it?")
    t_true = t_true[keep]
    tt = truth.t_ns.astype(float)
    lat_t = np.interp(t_true, tt, truth.lat)
    lon_t = np.interp(t_true, tt, truth.lon)
    h_t = np.interp(t_true, tt, truth.h)
    lat = np.radians(traj["lat_deg"][keep])
    lon = np.radians(traj["lon_deg"][keep])
    h = traj["height_m"][keep]
    rm, rn = np.vectorize(earth.radii)(lat_t)
    err = np.column_stack(((lat - lat_t) * (rm + h_t), (lon - lon_t) * (rn + h_t) * np.cos(lat_t), -(h - h_t)))
    err += 0.0  # no "-0.000" in the tables (a trajectory against itself)
    sig = np.column_stack([traj[k][keep] for k in ("sn_m", "se_m", "sd_m")])
    n = len(t_true)
    inside = np.abs(err) <= 3.0 * sig
    span = (truth.t_ns[-1] - truth.t_ns[0]) / 1e9
    gaps = np.diff(np.concatenate(([tt[0]], t_true, [tt[-1]]))) / 1e9
    covered = span - float(np.sum(gaps[gaps > 1.5]))
    outs = []
    horiz = np.hypot(err[:, 0], err[:, 1])
    for a, b in truth.outages:
        sel = (t_true >= a) & (t_true <= b)
        if sel.any():
            outs.append({"start_s": (a - tt[0]) / 1e9, "duration_s": (b - a) / 1e9,
                         "max_h_m": float(horiz[sel].max()), "end_h_m": float(horiz[sel][-1])})
    return Score(n, (t_true[-1] - t_true[0]) / 1e9, covered / span if span > 0 else 0.0,
                 [float(v) for v in np.sqrt(np.mean(err**2, axis=0))], [float(v) for v in err.mean(axis=0)],
                 [float(v) for v in err.min(axis=0)], [float(v) for v in err.max(axis=0)], float(horiz.max()),
                 [float(v) for v in inside.mean(axis=0)], float(inside.all(axis=1).mean()), outs,
                 rows, (t_true - tt[0]) / 1e9, err, sig)


def format_score(name: str, s: Score) -> str:
    outside = s.rows - s.n
    lines = [f"{name}: {s.n} solutions over {s.span_s:.0f} s, covering {s.coverage * 100:.1f} % of the drive"
             + (f"; {outside} of its {s.rows} rows ({outside / s.rows * 100:.1f} %) lie outside it, not scored"
                if outside else ""),
             f"  {'':6} {'north m':>9} {'east m':>9} {'down m':>9}"]
    for k, v in s.table().items():
        lines.append(f"  {k:6} {v[0]:9.3f} {v[1]:9.3f} {v[2]:9.3f}")
    lines.append(f"  max horizontal error {s.max_h:.2f} m; within 3 sigma: N {s.within_3sigma[0] * 100:.1f} %, "
                 f"E {s.within_3sigma[1] * 100:.1f} %, D {s.within_3sigma[2] * 100:.1f} %")
    for o in s.outages:
        lines.append(f"  outage at {o['start_s']:.0f} s, {o['duration_s']:.0f} s long: max horizontal error "
                     f"{o['max_h_m']:.2f} m, {o['end_h_m']:.2f} m at its end")
    return "\n".join(lines)


def plots(out_dir: Path, named: dict[str, tuple[dict[str, np.ndarray], Score]], truth: Truth) -> list[Path]:
    """The score's figures into ``out_dir``: all of them, or none (an earlier run's left as they were)."""
    with written_together():
        return _plots(out_dir, named, truth)


def _plots(out_dir: Path, named: dict[str, tuple[dict[str, np.ndarray], Score]], truth: Truth) -> list[Path]:
    try:
        plt = pyplot()
    except PlotsUnavailable as exc:
        print(f"{exc}: no plots", file=sys.stderr)
        return []
    out_dir.mkdir(parents=True, exist_ok=True)
    lat0, lon0, h0 = float(truth.lat[0]), float(truth.lon[0]), float(truth.h[0])
    written = []
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.plot(*local_en(truth.lat, truth.lon, lat0, lon0, h0), "k-", lw=2.5, alpha=0.35, label="truth")
    for name, (traj, _) in named.items():
        ax.plot(*local_en(np.radians(traj["lat_deg"]), np.radians(traj["lon_deg"]), lat0, lon0, h0),
                "." if name.startswith("gnss") else "-", ms=2, lw=0.8, label=name)
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.set_aspect("equal")
    ax.legend()
    ax.set_title("map view")
    p = out_dir / "map.png"
    save_figure(fig, p, 110)
    plt.close(fig)
    written.append(p)
    fig, axes = plt.subplots(3, 1, figsize=(11, 8), sharex=True)
    for name, (_, s) in named.items():
        for i, axn in enumerate(("north", "east", "down")):
            axes[i].plot(s.t_s, s.err[:, i], "." if name.startswith("gnss") else "-", ms=2, lw=0.8, label=name)
            axes[i].set_ylabel(f"{axn} error, m")
    for a, b in truth.outages:
        for axx in axes:
            axx.axvspan((a - truth.t_ns[0]) / 1e9, (b - truth.t_ns[0]) / 1e9, color="0.85")
    axes[0].legend()
    axes[-1].set_xlabel("drive time, s (grey: no GNSS fix)")
    p = out_dir / "error.png"
    save_figure(fig, p, 110)
    plt.close(fig)
    written.append(p)
    return written
