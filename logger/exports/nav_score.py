"""Score a navigation trajectory against the truth of a simulated drive, or against a reference trajectory.

    logger nav-score DIR/trajectory.csv DRIVE.mcap... [--reference REF.csv] [--plots DIR] [--json]

Prints, per north/east/down, the RMSE, mean, minimum and maximum error (the paper's Table 9), the horizontal
drift in every GNSS outage of the drive, and how often the error stays within 3 sigma of the filter's own
uncertainty. Each row is compared with the truth at the true time of its IMU sample (the row's t_mono_ns
through /truth/clock), so a free-running or disciplined logger clock scores the same. With matplotlib
installed (``pip install -e '.[plots]'``), ``--plots`` writes a map view and the error over time as PNG.
"""

from __future__ import annotations

import csv
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from logger.exports.plotting import PlotsUnavailable, local_en, pyplot
from logger.nav import earth
from logger.recording.drive import read_messages
from logger.recording.topics import GNSS_FIX, TRUTH_CLOCK, TRUTH_NAV

OUTAGE_MIN_S = 5.0


@dataclass
class Truth:
    t_ns: np.ndarray  # true time, Unix ns
    lat: np.ndarray  # rad
    lon: np.ndarray
    h: np.ndarray
    clock_mono: np.ndarray  # /truth/clock pairs
    clock_true: np.ndarray
    outages: list[tuple[int, int]] = field(default_factory=list)  # true-time spans without a GNSS fix

    def true_time(self, t_mono_ns: np.ndarray) -> np.ndarray:
        return np.interp(t_mono_ns.astype(float), self.clock_mono.astype(float), self.clock_true.astype(float))


class NoTruth(Exception):
    """The files are not a simulated drive: there is nothing to score against."""


def load_truth(paths: list[Path]) -> Truth:
    nav: list[tuple[int, float, float, float]] = []
    clock: list[tuple[int, int]] = []
    fixes: list[tuple[int, bool]] = []
    for topic, d in read_messages(paths, (TRUTH_NAV, TRUTH_CLOCK, GNSS_FIX)):
        if topic == TRUTH_NAV:
            nav.append((d["t_true_ns"], d["lat_deg"], d["lon_deg"], d["height_m"]))
        elif topic == TRUTH_CLOCK:
            clock.append((d["t_mono_ns"], d["t_true_ns"]))
        else:
            fixes.append((d["t_mono_ns"], bool(d.get("fix_ok"))))
    if not nav or not clock:
        raise NoTruth("no /truth/nav or /truth/clock in these files: not a simulated drive (use --reference)")
    nav.sort()
    clock.sort()
    a = np.array(nav, dtype=float)
    c = np.array(clock, dtype=np.int64)
    truth = Truth(np.array([n[0] for n in nav], dtype=np.int64), np.radians(a[:, 1]), np.radians(a[:, 2]), a[:, 3],
                  c[:, 0], c[:, 1])
    fixes.sort()
    if fixes:
        t_true = truth.true_time(np.array([f[0] for f in fixes], dtype=np.int64))
        last_ok = None
        start = None
        for t, ok in zip(t_true, (f[1] for f in fixes), strict=True):
            if ok:
                if start is not None and last_ok is not None and (t - last_ok) / 1e9 >= OUTAGE_MIN_S:
                    truth.outages.append((int(last_ok), int(t)))
                start = None
                last_ok = t
            elif start is None:
                start = t
    return truth


def load_reference(path: Path) -> Truth:
    """A reference trajectory in the same CSV layout (its t_sync_ns is taken as true time)."""
    rows = read_trajectory(path)
    t = rows["t_sync_ns"].astype(np.int64)
    return Truth(t, np.radians(rows["lat_deg"]), np.radians(rows["lon_deg"]), rows["height_m"], t, t)


def read_trajectory(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as f:
        r = csv.reader(f)
        header = next(r)
        data = [row for row in r if row]
    cols: dict[str, np.ndarray] = {}
    for i, name in enumerate(header):
        kind = np.int64 if name.endswith("_ns") else float
        cols[name] = np.array([row[i] for row in data], dtype=kind) if data else np.zeros(0, dtype=kind)
    return cols


@dataclass
class Score:
    n: int
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
    t_s: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    err: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 3)))
    sig: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 3)))

    def table(self) -> dict[str, list[float]]:
        return {"max": self.max, "min": self.min, "mean": self.mean, "rmse": self.rmse}


def score(traj: dict[str, np.ndarray], truth: Truth, skip_s: float = 0.0) -> Score:
    t_mono = traj.get("t_mono_ns")
    t_true = truth.true_time(t_mono) if t_mono is not None and len(t_mono) else traj["t_sync_ns"].astype(float)
    keep = (t_true >= truth.t_ns[0]) & (t_true <= truth.t_ns[-1])
    if skip_s > 0 and keep.any():
        keep &= t_true >= t_true[keep][0] + skip_s * 1e9
    t_true = t_true[keep]
    tt = truth.t_ns.astype(float)
    lat_t = np.interp(t_true, tt, truth.lat)
    lon_t = np.interp(t_true, tt, truth.lon)
    h_t = np.interp(t_true, tt, truth.h)
    lat = np.radians(traj["lat_deg"][keep])
    lon = np.radians(traj["lon_deg"][keep])
    h = traj["height_m"][keep]
    rm, rn = np.vectorize(earth.radii)(lat_t) if len(lat_t) else (np.zeros(0), np.zeros(0))
    err = np.column_stack(((lat - lat_t) * (rm + h_t), (lon - lon_t) * (rn + h_t) * np.cos(lat_t), -(h - h_t)))
    sig = np.column_stack([traj[k][keep] for k in ("sn_m", "se_m", "sd_m")])
    n = len(t_true)
    if n == 0:
        raise SystemExit("no trajectory row falls within the truth's time span")
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
                 (t_true - tt[0]) / 1e9, err, sig)


def format_score(name: str, s: Score) -> str:
    lines = [f"{name}: {s.n} solutions over {s.span_s:.0f} s, covering {s.coverage * 100:.1f} % of the drive",
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
    fig.savefig(p, dpi=110)
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
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)
    return written
