"""A PPK-grade RTKLIB solution (``.pos``) of a simulated drive, and what ``logger replay --gnss-solution`` makes of it.

    python tools/ppk_synth.py DRIVE_DIR --out FILE.pos [--seed 1]           # write the solution
    python tools/ppk_synth.py DRIVE_DIR... --evaluate [--work DIR] [--seed 1] # and score the replays

A survey receiver's raw observations processed against a base station (``rnx2rtkp -p 2``) give, epoch by epoch,
a fixed solution (Q=1) where the sky is open and the ambiguities have been resolved, a float one (Q=2) in a street
canyon and for a while after the satellites come back, a code solution (Q=5) with only four or so satellites, and
nothing where the sky is closed. This writes that, in ``rnx2rtkp``'s exact ``.pos`` layout (GPST, latitude /
longitude / height, its header), from a simulated drive's truth (``/truth/nav``) and its sky (the drive's own
satellite geometry, ``sensors.sim.gnss_errors.SkyGeometry``):

- per GPST second, the satellites seen directly (reflections do not count: a phase solution needs the direct
  path); under 4 no line; 4 a single-point line;
- fixed once the sky is open (no canyon, 8 or more satellites) and the phase has been tracked without a break for
  a time to fix drawn after each break (10-30 s after an outage, 3-10 s after a canyon); float before that and in
  canyons;
- errors per quality, first-order Gauss-Markov per axis: fixed 2 cm horizontal / 4 cm vertical (10 s), float
  0.3 m / 0.5 m (20 s), single 1.5 m / 3 m (30 s); the standard deviations written are RTKLIB's kind (its
  formal ones: a fixed solution's a third of its true error), with signed cross terms (sign(c) sqrt(|c|)).

``--evaluate`` writes the solution of each drive, runs ``logger replay`` on it (the command a user runs: 17-state,
forward and ``--smooth``, the solution instead of the receiver's positions) and on the receiver's fixes alone,
and prints the RMSE north / east / vertical where the solution is fixed, float, and over the whole drive while
moving, and the largest horizontal error in each GNSS outage.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from logger.recording.rtklib_pos import LEAP_SECONDS  # noqa: E402

NS = 1_000_000_000
HEADER_COLUMNS = ("%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)"
                  "  sdne(m)  sdeu(m)  sdun(m) age(s)  ratio")
LEGEND = ("% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,"
          "ns=# of satellites)")
# True error (1 sigma horizontal per axis, vertical) and its correlation time per quality; RTKLIB's formal
# sigma as a share of it.
ERRORS = {1: (0.02, 0.04, 10.0), 2: (0.30, 0.50, 20.0), 5: (1.5, 3.0, 30.0)}
FORMAL_SHARE = {1: 0.35, 2: 0.6, 5: 1.5}
FIX_MIN_SV = 8
TIME_TO_FIX_AFTER_OUTAGE_S = (10.0, 30.0)
TIME_TO_FIX_AFTER_CANYON_S = (3.0, 10.0)
OUTAGE_S = 5.0  # a break at least this long is an outage: the receiver reacquires from scratch


@dataclass(frozen=True)
class PosRow:
    """One line of a .pos: the epoch (Unix ns UTC) and the fields rnx2rtkp writes after it."""

    t_utc_ns: int
    lat_deg: float
    lon_deg: float
    height_m: float
    q: int
    ns: int
    sd: tuple[float, float, float, float, float, float]  # sdn sde sdu sdne sdeu sdun, the cross terms signed
    age_s: float = 0.0
    ratio: float = 0.0


def leap_s(utc: dt.datetime) -> int:
    return max((s for since, s in LEAP_SECONDS if utc >= since), default=0)


def gpst_text(t_utc_ns: int) -> str:
    """The epoch as rnx2rtkp writes it in GPST: yyyy/mm/dd hh:mm:ss.sss."""
    utc = dt.datetime.fromtimestamp(t_utc_ns // NS, dt.UTC)
    g = utc + dt.timedelta(seconds=leap_s(utc))
    ms = round((t_utc_ns % NS) / 1e6)
    return g.strftime("%Y/%m/%d %H:%M:%S") + f".{ms:03d}"


def write_pos(path: Path, rows: list[PosRow], ref_llh: tuple[float, float, float] | None = None,
              inputs: tuple[str, ...] = ("rover.obs", "base.obs", "rover.nav")) -> None:
    """``rows`` in rnx2rtkp's llh / GPST layout, header included (as ``rnx2rtkp -p 2 -o FILE`` writes them)."""
    def week(t_ns: int) -> str:
        utc = dt.datetime.fromtimestamp(t_ns // NS, dt.UTC)
        g = (utc + dt.timedelta(seconds=leap_s(utc)) - dt.datetime(1980, 1, 6, tzinfo=dt.UTC)).total_seconds()
        return f"week{int(g // 604800)} {g % 604800:.1f}s"

    head = ["% program   : RTKLIB ver.2.4.3", *(f"% inp file  : {f}" for f in inputs),
            f"% obs start : {gpst_text(rows[0].t_utc_ns)[:-2]} GPST ({week(rows[0].t_utc_ns)})",
            f"% obs end   : {gpst_text(rows[-1].t_utc_ns)[:-2]} GPST ({week(rows[-1].t_utc_ns)})"]
    if ref_llh is not None:
        head.append(f"% ref pos   :{ref_llh[0]:14.9f}{ref_llh[1]:15.9f}{ref_llh[2]:11.4f}")
    head += ["%", LEGEND, HEADER_COLUMNS]
    lines = [f"{gpst_text(r.t_utc_ns)} {r.lat_deg:14.9f} {r.lon_deg:14.9f} {r.height_m:10.4f} {r.q:3d} {r.ns:3d}"
             + "".join(f" {v:8.4f}" for v in r.sd) + f" {r.age_s:6.2f} {r.ratio:6.1f}" for r in rows]
    path.write_text("\n".join(head + lines) + "\n")


def signed_sqrt(c: float) -> float:
    return math.copysign(math.sqrt(abs(c)), c)


def pos_row(t_ns: int, lat: float, lon: float, h: float, err_ned: np.ndarray, q: int, ns: int,
            formal: tuple[float, float, float], rho_ne: float, ratio: float) -> PosRow:
    """A line for the truth (rad, m) moved by ``err_ned``, with the formal sigmas and a north-east correlation."""
    rm = 6378137.0 * (1 - 6.69437999014e-3) / (1 - 6.69437999014e-3 * math.sin(lat) ** 2) ** 1.5
    rn = 6378137.0 / math.sqrt(1 - 6.69437999014e-3 * math.sin(lat) ** 2)
    sn, se, su = formal
    return PosRow(t_ns, math.degrees(lat + err_ned[0] / (rm + h)),
                  math.degrees(lon + err_ned[1] / ((rn + h) * math.cos(lat))), h - err_ned[2], q, ns,
                  (sn, se, su, signed_sqrt(rho_ne * sn * se), signed_sqrt(0.1 * se * su),
                   signed_sqrt(-0.15 * su * sn)), 0.0, ratio)


def drive_of(files: list[Path]) -> tuple[Any, float]:
    """The simulated drive behind a recording and its start (Unix s), as ``sensors.sim.vehicle`` built it."""
    from nav_eval import drive_segments

    from logger.recording.drive import read_messages
    from logger.recording.topics import TRUTH_NAV

    t = [m["t_true_ns"] for _, m in read_messages(files, [TRUTH_NAV])]
    found = drive_segments(files, (max(t) - min(t)) / 1e9)
    if found is None:
        raise SystemExit(f"ppk_synth: {files[0]} is not a simulated drive (no 'simulation' metadata)")
    return found


def synthesize(files: list[Path], seed: int = 1) -> list[PosRow]:
    """A PPK solution of a recorded simulated drive, one line per GPST second the drive spans."""
    from logger.recording.drive import read_messages
    from logger.recording.topics import TRUTH_NAV

    drive, start_s = drive_of(files)
    truth = sorted((m["t_true_ns"], m["lat_deg"], m["lon_deg"], m["height_m"])
                   for _, m in read_messages(files, [TRUTH_NAV]))
    tt = np.array([r[0] for r in truth], float)
    llh = np.array([r[1:] for r in truth], float)
    rng = np.random.default_rng(seed)
    err = {q: np.zeros(3) for q in ERRORS}
    rows: list[PosRow] = []
    tracked_s = 0.0  # phase tracked without a break so far
    since_break_s = math.inf  # how long the last break lasted (an outage or a canyon's)
    to_fix = rng.uniform(*TIME_TO_FIX_AFTER_OUTAGE_S)
    was_fixable = False
    for t_ns in range(math.ceil(tt[0] / NS) * NS, int(tt[-1]), NS):
        t_s = t_ns / NS - start_s
        state = drive.state(t_s)
        view = drive.gnss_sky.view(state)
        direct = int((~view.reflected).sum())
        for q, (sh, sv, tau) in ERRORS.items():
            a = math.exp(-1.0 / tau)
            err[q] = a * err[q] + math.sqrt(1.0 - a * a) * rng.standard_normal(3) * np.array((sh, sh, sv))
        if direct < 4:
            since_break_s = 0.0 if tracked_s > 0.0 else since_break_s + 1.0
            tracked_s = 0.0
            was_fixable = False
            continue
        fixable = not view.canyon and direct >= FIX_MIN_SV
        if tracked_s == 0.0:  # the satellites back: the time to fix starts again
            to_fix = rng.uniform(*(TIME_TO_FIX_AFTER_OUTAGE_S if since_break_s >= OUTAGE_S
                                   else TIME_TO_FIX_AFTER_CANYON_S))
        elif fixable and not was_fixable:  # out of a canyon: the ambiguities resolve again
            to_fix = tracked_s + rng.uniform(*TIME_TO_FIX_AFTER_CANYON_S)
        was_fixable = fixable
        tracked_s += 1.0
        q = 5 if direct < 5 else (1 if fixable and tracked_s >= to_fix else 2)
        sh, sv, _ = ERRORS[q]
        k = FORMAL_SHARE[q] * math.sqrt(8.0 / direct)
        lat, lon, h = (np.interp(t_ns, tt, llh[:, i]) for i in range(3))
        ratio = float(rng.uniform(3.5, 60.0)) if q == 1 else float(rng.uniform(1.0, 2.9)) if q == 2 else 0.0
        rows.append(pos_row(t_ns, math.radians(lat), math.radians(lon), float(h), err[q], q, direct,
                            (k * sh, k * sh * 0.9, k * sv), -0.2, ratio))
    return rows


# ---- evaluation -------------------------------------------------------------------------------------------------
def replay(files: list[Path], out: Path, solution: Path | None, smooth: bool) -> Path:
    """``logger replay`` as a user runs it; returns the trajectory."""
    cmd = [sys.executable, "-m", "logger.cli", "replay", *map(str, files), "--out", str(out), "--no-mcap"]
    if solution is not None:
        cmd += ["--gnss-solution", str(solution)]
    if smooth:
        cmd.append("--smooth")
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"ppk_synth: {' '.join(cmd)} failed: {r.stderr.strip()}")
    for line in r.stdout.splitlines():
        if line.startswith(("GNSS solution", "updates accepted", "mode")):
            print(f"    {line}")
    return out / "trajectory.csv"


def rmse(err: np.ndarray) -> str:
    if len(err) == 0:
        return "no rows"
    r = np.sqrt(np.mean(err**2, axis=0))
    return f"{r[0]:.3f} / {r[1]:.3f} / {r[2]:.3f} m ({len(err)} rows)"


def evaluate(files: list[Path], work: Path, seed: int) -> dict[str, Any]:
    from nav_eval import moving

    from logger.exports.nav_score import load_truth, read_trajectory, score

    work.mkdir(parents=True, exist_ok=True)
    rows = synthesize(files, seed)
    pos = work / "ppk.pos"
    write_pos(pos, rows)
    counts = {q: sum(1 for r in rows if r.q == q) for q in (1, 2, 5)}
    print(f"  {pos}: {len(rows)} epochs, fix {counts[1]}, float {counts[2]}, single {counts[5]}")
    truth = load_truth(files)
    t_q = {r.t_utc_ns // NS: r.q for r in rows}
    result: dict[str, Any] = {"epochs": counts}
    for name, sol, smooth in (("live fixes", None, False), ("live fixes smoothed", None, True),
                              ("ppk", pos, False), ("ppk smoothed", pos, True)):
        traj = read_trajectory(replay(files, work / name.replace(" ", "-"), sol, smooth))
        s = score(traj, truth)
        t_abs = truth.t_ns[0] + s.t_s * 1e9
        lo, hi = np.floor(t_abs / NS).astype(np.int64), np.ceil(t_abs / NS).astype(np.int64)
        q_lo = np.array([t_q.get(int(v), 0) for v in lo])
        q_hi = np.array([t_q.get(int(v), 0) for v in hi])
        mv = moving(files, s, truth)
        fixed, flt = (q_lo == 1) & (q_hi == 1), (q_lo == 2) & (q_hi == 2)
        print(f"  {name}: RMSE N / E / V where fixed {rmse(s.err[fixed])}; where float {rmse(s.err[flt])}; "
              f"while moving {rmse(s.err[mv])}")
        for o in s.outages:
            print(f"    outage at {o['start_s']:.0f} s ({o['duration_s']:.0f} s): max horizontal "
                  f"{o['max_h_m']:.2f} m, {o['end_h_m']:.2f} m at its end")
        result[name] = {"fixed": np.sqrt(np.mean(s.err[fixed] ** 2, axis=0)).tolist() if fixed.any() else None,
                        "float": np.sqrt(np.mean(s.err[flt] ** 2, axis=0)).tolist() if flt.any() else None,
                        "moving": np.sqrt(np.mean(s.err[mv] ** 2, axis=0)).tolist(), "outages": s.outages}
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("drives", nargs="+", type=Path, help="folders of recorded simulated drives (or their files)")
    ap.add_argument("--out", type=Path, help="write the solution of the (one) drive here")
    ap.add_argument("--evaluate", action="store_true", help="replay each drive with its solution and score it")
    ap.add_argument("--work", type=Path, default=Path("/tmp/ppk-eval"), help="folder for --evaluate's files")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="--evaluate's figures as JSON at the end")
    args = ap.parse_args(argv)

    def files_of(p: Path) -> list[Path]:
        return sorted(p.glob("*.mcap")) if p.is_dir() else [p]

    if args.out is not None:
        if len(args.drives) != 1:
            raise SystemExit("ppk_synth: --out takes one drive")
        rows = synthesize(files_of(args.drives[0]), args.seed)
        write_pos(args.out, rows)
        print(f"wrote {args.out}: {len(rows)} epochs, " + ", ".join(
            f"{name} {sum(1 for r in rows if r.q == q)}" for q, name in ((1, "fix"), (2, "float"), (5, "single"))))
    if args.evaluate:
        results = {}
        for d in args.drives:
            print(f"{d}:")
            results[str(d)] = evaluate(files_of(d), args.work / d.name, args.seed)
        if args.json:
            print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
