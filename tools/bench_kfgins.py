"""Side by side: this project's navigation filter against KF-GINS (i2Nav-WHU's C++ GNSS/INS EKF) on the same drives.

    python tools/bench_kfgins.py DRIVE... --kfgins /var/tmp/kf-gins/bin/KF-GINS [--kfgins-bench PATH]
        [--repeat 3] [--json FILE] [--keep DIR]

A DRIVE is a folder of one recording's MCAP files (``logger run --sim --out DIR``) or one MCAP file; it must be a
simulated drive (``/truth/nav``). KF-GINS is not part of this repository: build it outside (its CMake Release
build, -O3) and give its binary. For each drive:

Conversion into KF-GINS's inputs (a temporary folder, ``--keep`` to keep it): the IMU text file has, per /imu sample
from the start on, the GNSS seconds of week of its t_sync_ns and the angle and velocity increments over the interval
from the previous sample (trapezoid of the two samples' rates, as this filter's strapdown integrates them), turned
from the chip's axes to the vehicle's forward-right-down by ``[nav] mounting_rpy_deg`` (mounting.mount_matrix, as
the engine applies it); an interval of ``MAX_LINE_S`` or more (a polled sample read late) is written as equal parts,
since KF-GINS's loader takes 0.1 s and more as a gap of 1 / imudatarate. The GNSS file has each valid fix (fix_ok)
at its epoch time (gnss_time_ns), with sigma north = east = h_acc / sqrt(2) and down = v_acc (as gnss_noise takes
the receiver's figures). The configuration starts KF-GINS from /truth/nav one second before the car first moves
(after the clock has locked and a first fix), its gyro offset the mean rate of the standstill before that (a static
calibration; less the earth's rate), its noise from :class:`NavParams`: angle and velocity random walk from the
noise densities, the offsets' first-order Gauss-Markov (KF-GINS's model) with a correlation time of ``CORR_TIME_H``
and the steady-state sigma that makes its driving noise this filter's random walk, its six scale-factor states held
at ``SCALE_PPM`` (this filter has no scale factors; the simulated chip has none), its lever arm
``[nav] lever_arm_m``. KF-GINS uses the GNSS positions only: no velocity, OBD speed, barometer, non-holonomic or
zero-velocity update.

Timing, each ``--repeat`` times in turn (KF-GINS, then this filter, then ``logger replay``; the median of the
runs is shown, or the least with ``--stat best``; every run is in the JSON), as CPU time (user + system) per IMU
sample filtered:

- KF-GINS whole process: the unmodified binary as a child (os.wait4), reading the files and writing its three
  outputs (navresult, IMU errors, std) at every IMU sample, as its main() does.
- KF-GINS filter alone (with ``--kfgins-bench``, by default ``kfgins-bench`` beside the binary): a harness that
  links KF-GINS's own engine, loaders and savers and runs its main loop in three timed phases: the text files
  read into memory; GIEngine over those samples without output (the filter alone); the same with its outputs.
  Without the harness the filter alone is not separated and only the whole process is shown.
- This filter alone: ``logger.exports.trajectory.run_filter`` per mode, its input messages read and decoded
  first (timed apart) and handed over from memory (kept out of the garbage collector's passes, gc.freeze, as the
  file pipeline's raw bytes are); and ``run_filter`` on the files (read + decode + filter, as nav_bench times it).
- This project's whole process: ``logger replay DRIVE --out DIR --mode M`` as a child: interpreter start, imports
  (from bytecode compiled beforehand, as a pip install has it: tools/bytecode.py), reading, filtering,
  trajectory.csv and trajectory.mcap.

Per IMU sample the two scale differently with the IMU's rate: KF-GINS propagates its covariance at every sample,
this filter every ``cov_interval_s`` and at its updates, which come at the other sensors' rates (fixes, OBD speed,
barometer) whatever the IMU's, and a FIFO drive's runs of reads go in strapdown steps of ``integration_hz`` (a drive
named ``-imu-200hz`` is the same simulated drive with the IMU at 200 Hz, read through its FIFO).

Accuracy, each against /truth/nav with :func:`logger.exports.nav_score.score` (KF-GINS's navresult and std turned
into the same columns), over the rows from KF-GINS's start on while the car moves (``nav_eval.moving``), and the
largest horizontal error in the drive's longest GNSS outage. Prints a markdown table ready to paste, per drive,
and ``--json FILE`` has every figure.
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from bench import cpu_model, loadavg, machine_busy, tree_state  # noqa: E402
from bytecode import compile_tree  # noqa: E402
from nav_eval import MOVING_MPS, moving  # noqa: E402
from nav_eval import trajectory as engine_columns  # noqa: E402

import logger.exports.trajectory as trajectory_module  # noqa: E402
from logger.exports.nav_score import Score, Truth, load_truth, score  # noqa: E402
from logger.exports.trajectory import read_drive, run_filter  # noqa: E402
from logger.nav.earth import OMEGA_IE  # noqa: E402
from logger.nav.mounting import mount_matrix  # noqa: E402
from logger.nav.params import NavParams  # noqa: E402
from logger.nav.rotations import dcm_from_euler  # noqa: E402
from logger.recording.drive import read_messages  # noqa: E402
from logger.recording.topics import GNSS_FIX, IMU, TRUTH_NAV  # noqa: E402

NS = 1_000_000_000
WEEK_NS = 604_800 * NS
GPS_EPOCH_UNIX_NS = 315_964_800 * NS
GPS_LEAP_S = 18  # GPS - UTC since 2017, used only when no fix carries its time of week
CORR_TIME_H = 1.0  # KF-GINS's Gauss-Markov correlation time of the offsets (and of its scale factors)
SCALE_PPM = 1.0  # its scale-factor states' sigma, initial and steady: held near zero (not modelled here)
INIT_POS_STD_M = (0.5, 0.5, 0.5)  # KF-GINS starts from the truth: its initial sigmas
INIT_VEL_STD_MPS = (0.05, 0.05, 0.05)
INIT_ATT_STD_DEG = (0.5, 0.5, 1.0)
INIT_GYRO_BIAS_STD_DPS = 0.1  # the standstill's mean rate as its gyro offset: what that leaves (offsets wander)
LEAD_S = 1.0  # KF-GINS starts this long before the car first moves
STILL_MPS = 0.05  # the standstill whose mean rate is the gyro offset
MAX_LINE_S = 0.095  # longest interval of an IMU line (KF-GINS's loader takes 0.1 s and more as a gap)
MODES = ("15", "17")


@dataclass
class Converted:
    """A drive in KF-GINS's files, and what maps its rows back to this project's time stamps."""

    work: Path
    config: Path
    bench_config: Path
    out: Path
    bench_out: Path
    week_start_ns: int
    start_ns: int  # t_sync_ns of the sample KF-GINS starts at
    imu_sow: np.ndarray  # seconds of week of the IMU lines written
    imu_t_sync: np.ndarray  # their t_sync_ns and t_mono_ns (a split interval's parts: interpolated)
    imu_t_mono: np.ndarray
    fixes: int
    gaps: int  # IMU intervals over MAX_LINE_S, written as several lines
    gyro_bias_dph: list[float]
    notes: list[str] = field(default_factory=list)


# ---- conversion ----------------------------------------------------------------------------------------------
def sow_text(t_ns: int, week_start_ns: int) -> str:
    d = t_ns - week_start_ns
    return f"{d // NS}.{d % NS:09d}"


def truth_states(files: list[Path]) -> dict[str, np.ndarray]:
    """/truth/nav as arrays in true time order: position, velocity, attitude."""
    rows = [(m["t_true_ns"], m["lat_deg"], m["lon_deg"], m["height_m"], *m["vel_ned_mps"], *m["rpy_deg"])
            for _, m in read_messages(files, [TRUTH_NAV])]
    rows.sort()
    a = np.array([r[1:] for r in rows], dtype=float)
    return {"t_ns": np.array([r[0] for r in rows], dtype=np.int64), "llh": a[:, 0:3], "vel": a[:, 3:6],
            "rpy_deg": a[:, 6:9]}


def convert(files: list[Path], work: Path, params: NavParams, truth: Truth) -> Converted:
    """Write KF-GINS's IMU file, GNSS file and configuration for the drive into ``work``."""
    t_sync, t_mono, acc, gyro, locked = [], [], [], [], []
    fixes = []
    for topic, m in read_messages(files, (IMU, GNSS_FIX)):
        if topic == IMU:
            t_sync.append(m["t_sync_ns"])
            t_mono.append(m["t_mono_ns"])
            acc.append(m["accel_mps2"])
            gyro.append(m["gyro_rps"])
            locked.append(m.get("sync_state", "locked") == "locked")
        elif m.get("fix_ok") and m.get("gnss_time_ns") is not None and (m.get("fix_mode") or 0) >= 2:
            fixes.append(m)
    if len(t_sync) < 100 or not fixes:
        raise SystemExit(f"bench_kfgins: {files[0].parent}: too few IMU samples or no valid fix")
    ts = np.array(t_sync, dtype=np.int64)
    order = np.argsort(ts, kind="stable")
    ts, tm = ts[order], np.array(t_mono, dtype=np.int64)[order]
    mount = mount_matrix(params.mounting_rpy_deg)  # vehicle from chip
    f_b = (np.array(acc, float)[order]) @ mount.T
    w_b = (np.array(gyro, float)[order]) @ mount.T
    locked_a = np.array(locked)[order]
    fixes.sort(key=lambda m: m["gnss_time_ns"])

    with_tow = next((m for m in fixes if m.get("itow_ms") is not None), None)
    if with_tow is not None:
        week_start_ns = round((with_tow["gnss_time_ns"] - with_tow["itow_ms"] * 1_000_000) / NS) * NS
    else:
        gps_ns = fixes[0]["gnss_time_ns"] + GPS_LEAP_S * NS - GPS_EPOCH_UNIX_NS
        week_start_ns = fixes[0]["gnss_time_ns"] - gps_ns % WEEK_NS

    # Where KF-GINS starts: LEAD_S before the car first moves, once the clock is locked and a fix is in.
    states = truth_states(files)
    t_true = truth.true_time(tm)
    tt = states["t_ns"].astype(float)
    speed = np.interp(t_true, tt, np.hypot(states["vel"][:, 0], states["vel"][:, 1]))
    first_ok = int(np.argmax(locked_a)) if locked_a.any() else 0
    first_ok = max(first_ok, int(np.searchsorted(ts, fixes[0]["gnss_time_ns"])), 1)
    moves = np.nonzero(speed[first_ok:] > MOVING_MPS)[0]
    notes = []
    if len(moves):
        move_i = first_ok + int(moves[0])
        start_i = max(first_ok, int(np.searchsorted(ts, ts[move_i] - int(LEAD_S * NS))))
    else:
        start_i = first_ok
        notes.append("the car never moves")
    if ts[-1] - week_start_ns >= WEEK_NS:
        raise SystemExit("bench_kfgins: the drive crosses a GPS week: KF-GINS's time of week would wrap")

    # The gyro offset from the standstill before the start (less the earth's rate in the body).
    lat0 = math.radians(float(np.interp(t_true[start_i], tt, states["llh"][:, 0])))
    k = int(np.argmin(np.abs(tt - t_true[start_i])))
    rpy0 = states["rpy_deg"][k]
    c_bn = dcm_from_euler(*np.radians(rpy0))
    wie_b = c_bn.T @ np.array([OMEGA_IE * math.cos(lat0), 0.0, -OMEGA_IE * math.sin(lat0)])
    still = np.nonzero(speed[first_ok:start_i + 1] < STILL_MPS)[0] + first_ok
    if len(still) >= 20:
        bg = w_b[still].mean(axis=0) - wie_b
    else:
        bg = np.zeros(3)
        notes.append("no standstill before the start: KF-GINS's gyro offset starts at zero")
    bg_dph = [float(v) for v in np.degrees(bg) * 3600.0]

    # IMU file: increments over (t[k-1], t[k]] by the trapezoid rule, from the start sample on. KF-GINS's loader
    # takes an interval of 0.1 s or more as one of 1 / imudatarate (a gap in a regular record), so a polled
    # sample read that late is written as equal parts under 0.1 s each (counted in ``gaps``).
    dt = np.diff(ts).astype(float) / NS
    dth = (w_b[1:] + w_b[:-1]) * 0.5 * dt[:, None]
    dvel = (f_b[1:] + f_b[:-1]) * 0.5 * dt[:, None]
    gaps = 0
    line_t, line_mono = [], []
    imu_path, gnss_path = work / "imu.txt", work / "gnss.txt"
    with open(imu_path, "w") as f:
        for k in range(start_i, len(ts)):  # sample k's line holds interval k-1 -> k (row k-1 of the diffs)
            parts = max(1, math.ceil(dt[k - 1] / MAX_LINE_S))
            gaps += parts > 1
            a, v = dth[k - 1] / parts, dvel[k - 1] / parts
            incs = f"{a[0]:.10e} {a[1]:.10e} {a[2]:.10e} {v[0]:.10e} {v[1]:.10e} {v[2]:.10e}\n"
            for j in range(1, parts + 1):
                t = int(ts[k - 1]) + (int(ts[k]) - int(ts[k - 1])) * j // parts
                line_t.append(t)
                line_mono.append(int(tm[k - 1]) + (int(tm[k]) - int(tm[k - 1])) * j // parts)
                f.write(f"{sow_text(t, week_start_ns)} {incs}")
    n_fix = 0
    with open(gnss_path, "w") as f:
        for m in fixes:
            if m["gnss_time_ns"] < ts[start_i] - 2 * NS:
                continue
            h_acc = m.get("h_acc_m") or params.gnss_nominal_h_acc_m
            v_acc = m.get("v_acc_m") or params.gnss_nominal_v_acc_m
            f.write(f"{sow_text(m['gnss_time_ns'], week_start_ns)} {m['latitude']:.10f} {m['longitude']:.10f} "
                    f"{m['altitude']:.4f} {h_acc / math.sqrt(2.0):.4f} {h_acc / math.sqrt(2.0):.4f} {v_acc:.4f}\n")
            n_fix += 1

    # Initial state from the truth at the start sample's true time.
    t0 = t_true[start_i]
    llh0 = [float(np.interp(t0, tt, states["llh"][:, i])) for i in range(3)]
    vel0 = [float(np.interp(t0, tt, states["vel"][:, i])) for i in range(3)]
    root = math.sqrt(CORR_TIME_H * 3600.0 / 2.0)  # steady sigma = walk * sqrt(T / 2): same driving noise
    gb_std_dph = math.degrees(params.gyro_bias_walk) * 3600.0 * root
    ab_std_mgal = params.accel_bias_walk * 1e5 * root
    rate = round(1.0 / float(np.median(dt)))
    out, bench_out = work / "out", work / "bench_out"
    out.mkdir(exist_ok=True)
    bench_out.mkdir(exist_ok=True)

    def vec(v: Any) -> str:
        return "[" + ", ".join(f"{float(x):.10g}" for x in v) + "]"

    def config_text(outdir: Path) -> str:
        return "\n".join([
            "# written by tools/bench_kfgins.py from a recorded drive",
            f'imupath: "{imu_path}"', f'gnsspath: "{gnss_path}"', f'outputpath: "{outdir}"',
            "imudatalen: 7", f"imudatarate: {rate}",
            f"starttime: {sow_text(int(ts[start_i]), week_start_ns)}", "endtime: -1",
            f"initpos: {vec(llh0)}", f"initvel: {vec(vel0)}", f"initatt: {vec(rpy0)}",
            f"initgyrbias: {vec(bg_dph)}", "initaccbias: [0, 0, 0]", "initgyrscale: [0, 0, 0]",
            "initaccscale: [0, 0, 0]",
            f"initposstd: {vec(INIT_POS_STD_M)}", f"initvelstd: {vec(INIT_VEL_STD_MPS)}",
            f"initattstd: {vec(INIT_ATT_STD_DEG)}",
            f"initbgstd: {vec([INIT_GYRO_BIAS_STD_DPS * 3600.0] * 3)}",
            f"initbastd: {vec([params.accel_bias_sigma * 1e5] * 3)}",
            f"initsgstd: {vec([SCALE_PPM] * 3)}", f"initsastd: {vec([SCALE_PPM] * 3)}",
            "imunoise:",
            f"  arw: {vec([params.gyro_noise_dps_rthz * 60.0] * 3)}",
            f"  vrw: {vec([params.accel_vrw * 60.0] * 3)}",
            f"  gbstd: {vec([gb_std_dph] * 3)}", f"  abstd: {vec([ab_std_mgal] * 3)}",
            f"  gsstd: {vec([SCALE_PPM] * 3)}", f"  asstd: {vec([SCALE_PPM] * 3)}",
            f"  corrtime: {CORR_TIME_H:g}",
            f"antlever: {vec(params.lever_arm_m)}", ""])

    config, bench_config = work / "kf-gins.yaml", work / "kf-gins-bench.yaml"
    config.write_text(config_text(out))
    bench_config.write_text(config_text(bench_out))
    line_ts = np.array(line_t, dtype=np.int64)
    return Converted(work, config, bench_config, out, bench_out, week_start_ns, int(ts[start_i]),
                     (line_ts - week_start_ns) / NS, line_ts, np.array(line_mono, dtype=np.int64), n_fix, gaps,
                     bg_dph, notes)


def kfgins_columns(conv: Converted) -> dict[str, np.ndarray]:
    """KF-GINS's navresult and std rows as the columns nav_score reads, stamped with their IMU samples' times."""
    nav = np.loadtxt(conv.out / "KF_GINS_Navresult.nav", ndmin=2)
    std = np.loadtxt(conv.out / "KF_GINS_STD.txt", ndmin=2)
    i = np.clip(np.searchsorted(conv.imu_sow, nav[:, 1] - 5e-4), 0, len(conv.imu_sow) - 1)
    if np.any(np.abs(conv.imu_sow[i] - nav[:, 1]) > 1e-3):
        raise SystemExit("bench_kfgins: a KF-GINS row matches no IMU sample of the drive")
    return {"t_sync_ns": conv.imu_t_sync[i], "t_mono_ns": conv.imu_t_mono[i], "lat_deg": nav[:, 2],
            "lon_deg": nav[:, 3], "height_m": nav[:, 4], "sn_m": std[:, 1], "se_m": std[:, 2], "sd_m": std[:, 3]}


# ---- timing --------------------------------------------------------------------------------------------------
def child(cmd: list[str], cwd: Path) -> dict[str, float]:
    """Run a command to its end: its wall time and CPU time (user + system, os.wait4's rusage)."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    assert p.stderr is not None
    err = p.stderr.read()
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise SystemExit(f"bench_kfgins: {' '.join(cmd)} failed (exit {p.returncode}): "
                         + err.decode(errors="replace").strip()[-500:])
    return {"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime}


def kfgins_bench(harness: Path, conv: Converted) -> dict[str, float]:
    t0 = time.perf_counter()
    r = subprocess.run([str(harness), str(conv.bench_config)], cwd=conv.work, capture_output=True, text=True,
                       check=True)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    out["wall_s"] = time.perf_counter() - t0
    return out


@contextmanager
def from_memory(msgs: list[tuple[str, dict[str, Any]]]) -> Iterator[None]:
    """run_filter fed the messages already read and decoded instead of reading its files."""
    def replay(paths: list[Path], topics: Any = None, progress: Any = None,
               runs: bool = False) -> Iterator[tuple[str, dict[str, Any]]]:
        return iter(msgs)

    with mock.patch.object(trajectory_module, "read_drive", replay):
        yield


def cpu_timed(fn: Callable[[], Any]) -> tuple[Any, float, float]:
    gc.collect()
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c0, time.perf_counter() - w0


# ---- one drive -----------------------------------------------------------------------------------------------
def drive_files(arg: Path) -> list[Path]:
    files = sorted(arg.glob("*.mcap")) if arg.is_dir() else [arg]
    if not files:
        raise SystemExit(f"bench_kfgins: no MCAP file in {arg}")
    return files


def accuracy(files: list[Path], cols: dict[str, np.ndarray], truth: Truth, start_ns: int) -> dict[str, Any]:
    keep = cols["t_sync_ns"] >= start_ns
    s: Score = score({k: v[keep] for k, v in cols.items()}, truth)
    move = moving(files, s, truth)
    err = s.err[move]
    rmse = [float(x) for x in np.sqrt((err**2).mean(axis=0))] if len(err) else [float("nan")] * 3
    longest = max(s.outages, key=lambda o: o["duration_s"]) if s.outages else None
    return {"rows": s.n, "rows_moving": int(move.sum()), "rmse_moving_ned_m": rmse,
            "within_3sigma": s.within_3sigma,
            "outage": ({"start_s": longest["start_s"], "duration_s": longest["duration_s"],
                        "max_h_m": longest["max_h_m"]} if longest else None)}


def pick(values: list[float], stat: str) -> float:
    """The figure shown of several runs: their median, or the best (least) with ``--stat best``."""
    return float(min(values) if stat == "best" else statistics.median(values))


def bench_drive(arg: Path, kfgins: Path, harness: Path | None, repeat: int, keep: Path | None,
                stat: str) -> dict[str, Any]:
    files = drive_files(arg)
    truth = load_truth(files)
    params = NavParams()
    tmp = None
    if keep is not None:
        work = keep / arg.name.removesuffix(".mcap")
        work.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="bench-kfgins-")
        work = Path(tmp.name)
    try:
        conv = convert(files, work, params, truth)
        print(f"{arg.name}: KF-GINS from {(conv.start_ns - truth.t_ns[0]) / NS:.1f} s (truth time) on, "
              f"{len(conv.imu_sow)} IMU lines, {conv.fixes} fixes, gyro offset from the standstill "
              f"{', '.join(f'{v:.0f}' for v in conv.gyro_bias_dph)} deg/h" + "".join(f"; {n}" for n in conv.notes),
              flush=True)
        runs: dict[str, list[dict[str, float]]] = {k: [] for k in (
            "kfgins_process", "kfgins_bench", *(f"ours_{m}_{w}" for m in MODES for w in ("read", "filter", "files")),
            *(f"replay_{m}" for m in MODES))}
        rows: dict[str, list[Any]] = {}
        counts: dict[str, int] = {}
        replay_out = work / "replay"
        compile_tree()  # the replays' modules from bytecode, as an installed logger has them
        for r in range(repeat):
            runs["kfgins_process"].append(child([str(kfgins), str(conv.config)], work))
            if harness is not None:
                runs["kfgins_bench"].append(kfgins_bench(harness, conv))
            for mode in MODES:
                p = NavParams(mode=mode)
                msgs, c, w = cpu_timed(lambda: list(read_drive(files, runs=True)))  # as run_filter reads them
                runs[f"ours_{mode}_read"].append({"cpu_s": c, "wall_s": w, "records": len(msgs)})
                # The file pipeline holds raw bytes and decodes one message at a time: the decoded messages are
                # kept out of the garbage collector's passes (gc.freeze) so that they do not bill the filter.
                gc.collect()
                gc.freeze()
                try:
                    with from_memory(msgs):
                        (engine, _), c, w = cpu_timed(lambda p=p: run_filter(files, p))
                finally:
                    gc.unfreeze()
                runs[f"ours_{mode}_filter"].append({"cpu_s": c, "wall_s": w, "samples": engine.counters.imu})
                del msgs
                (engine, out_rows), c, w = cpu_timed(lambda p=p: run_filter(files, p))
                runs[f"ours_{mode}_files"].append({"cpu_s": c, "wall_s": w, "samples": engine.counters.imu})
                if r == 0:
                    rows[mode], counts[mode] = out_rows, engine.counters.imu
            for mode in MODES:
                runs[f"replay_{mode}"].append(child(
                    # As tools/bench_nav.py runs it: this tree's logger, whatever the venv's script points at.
                    [sys.executable, "-m", "logger.cli", "replay", *map(str, files), "--out", str(replay_out / mode),
                     "--mode", mode], ROOT))
            print(f"  run {r + 1} of {repeat} done", flush=True)

        kf_cols = kfgins_columns(conv)
        n_kf = len(kf_cols["t_sync_ns"])
        result: dict[str, Any] = {
            "drive": str(arg), "files": [str(f) for f in files], "kfgins_start_s": (conv.start_ns - truth.t_ns[0]) / NS,
            "kfgins_rows": n_kf, "kfgins_imu_lines": len(conv.imu_sow), "kfgins_fixes": conv.fixes,
            "kfgins_gaps": conv.gaps, "kfgins_init_gyro_bias_dph": conv.gyro_bias_dph, "notes": conv.notes,
            "runs": runs}

        def of(these: list[dict[str, float]], key: str) -> float:
            return pick([r[key] for r in these], stat)

        kp = runs["kfgins_process"]
        kf = {"process_cpu_s": of(kp, "cpu_s"), "process_wall_s": of(kp, "wall_s"),
              "process_us_per_sample": of(kp, "cpu_s") / n_kf * 1e6,
              "accuracy": accuracy(files, kf_cols, truth, conv.start_ns)}
        if runs["kfgins_bench"]:
            kb = runs["kfgins_bench"]
            n = kb[0]["samples"]
            kf.update(filter_us_per_sample=of(kb, "filter_cpu_s") / n * 1e6,
                      read_filter_us_per_sample=pick(
                          [(b["read_cpu_s"] + b["filter_cpu_s"]) / n * 1e6 for b in kb], stat),
                      filter_output_us_per_sample=of(kb, "filter_output_cpu_s") / n * 1e6,
                      read_us_per_sample=of(kb, "read_cpu_s") / n * 1e6)
            same = (conv.out / "KF_GINS_Navresult.nav").read_bytes() == (
                conv.bench_out / "KF_GINS_Navresult.nav").read_bytes()
            kf["harness_output_identical"] = same
        result["kfgins"] = kf
        for mode in MODES:
            n = counts[mode]
            result[f"ours_{mode}"] = {
                "samples": n,
                "filter_us_per_sample": of(runs[f"ours_{mode}_filter"], "cpu_s") / n * 1e6,
                "read_us_per_sample": of(runs[f"ours_{mode}_read"], "cpu_s") / n * 1e6,
                "read_filter_us_per_sample": of(runs[f"ours_{mode}_files"], "cpu_s") / n * 1e6,
                "process_cpu_s": of(runs[f"replay_{mode}"], "cpu_s"),
                "process_wall_s": of(runs[f"replay_{mode}"], "wall_s"),
                "accuracy": accuracy(files, engine_columns(rows[mode]), truth, conv.start_ns)}
        return result
    finally:
        if tmp is not None:
            tmp.cleanup()


# ---- the table -----------------------------------------------------------------------------------------------
def ratio(a: float | None, b: float | None) -> str:
    return f"{a / b:.2f}x" if a is not None and b else "-"


def render(results: list[dict[str, Any]], repeat: int, stat: str) -> list[str]:
    lines = ["| drive | filter | CPU per IMU sample, filter alone | x KF-GINS | read + decode + filter | x KF-GINS "
             "| whole process, CPU s (wall s) | x KF-GINS | RMSE N / E / V while moving, m | longest outage: max "
             "horizontal error |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for res in results:
        name = Path(res["drive"]).name
        kf = res["kfgins"]
        base_f, base_r = kf.get("filter_us_per_sample"), kf.get("read_filter_us_per_sample")
        entries = [("KF-GINS (C++, 21-state)", kf)] + [(f"this project, {m}-state", res[f"ours_{m}"]) for m in MODES]
        for label, e in entries:
            acc = e["accuracy"]
            r = acc["rmse_moving_ned_m"]
            out = acc["outage"]
            outage = f"{out['max_h_m']:.2f} m ({out['duration_s']:.0f} s)" if out else "no outage"
            f_us, rf_us = e.get("filter_us_per_sample"), e.get("read_filter_us_per_sample")
            f_text = f"{f_us:.1f} us" if f_us is not None else "not separated"
            rf_text = f"{rf_us:.1f} us" if rf_us is not None else "-"
            cpu, wall = e["process_cpu_s"], e["process_wall_s"]
            lines.append(
                f"| {name} | {label} | {f_text} | {ratio(f_us, base_f)} | {rf_text} | {ratio(rf_us, base_r)} "
                f"| {cpu:.2f} ({wall:.2f}) | {ratio(cpu, kf['process_cpu_s'])} "
                f"| {r[0]:.2f} / {r[1]:.2f} / {r[2]:.2f} | {outage} |")
    which = "Best" if stat == "best" else "Median"
    lines += ["", f"{which} of {repeat} alternated runs, CPU time (user + system). KF-GINS: the filter alone is its "
              "GIEngine over the samples in memory (a harness linking its own code), read + filter adds its text "
              "loaders, the whole process is the unmodified binary writing its outputs at every IMU sample. This "
              "project: run_filter fed decoded messages from memory, then run_filter on the MCAP files, then "
              "`logger replay DRIVE --out DIR --mode M` (interpreter start, modules from bytecode as installed, "
              "CSV and MCAP written). Accuracy against /truth/nav from KF-GINS's start (the truth one second before "
              "the car moves) while the car moves."]
    return lines


def own_cpu_s() -> float:
    """CPU seconds of this process and its finished children."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("drives", type=Path, nargs="+", help="a recording's folder of MCAP files, or one MCAP file")
    ap.add_argument("--kfgins", type=Path, required=True, help="the KF-GINS binary (its Release build)")
    ap.add_argument("--kfgins-bench", type=Path, default=None,
                    help="the timing harness around KF-GINS's engine (default: kfgins-bench beside --kfgins)")
    ap.add_argument("--repeat", type=int, default=3, help="alternated runs of each")
    ap.add_argument("--stat", choices=("median", "best"), default="median",
                    help="which of the runs the table shows: their median (default) or the least CPU time")
    ap.add_argument("--json", type=Path, help="write every figure here")
    ap.add_argument("--keep", type=Path, help="keep KF-GINS's inputs and outputs under this folder")
    args = ap.parse_args(argv)
    if not args.kfgins.is_file():
        raise SystemExit(f"bench_kfgins: no KF-GINS binary at {args.kfgins}")
    harness = args.kfgins_bench or args.kfgins.with_name("kfgins-bench")
    if not harness.is_file():
        print(f"bench_kfgins: no harness at {harness}: KF-GINS's filter alone is not separated", file=sys.stderr)
        harness = None
    started = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    load0, busy0, own0, t0 = loadavg(), machine_busy(), own_cpu_s(), time.monotonic()
    results = [bench_drive(d, args.kfgins.resolve(), harness.resolve() if harness else None, max(1, args.repeat),
                           args.keep, args.stat) for d in args.drives]
    wall, busy1, own = time.monotonic() - t0, machine_busy(), own_cpu_s() - own0
    busy_pct = (busy1[0] - busy0[0]) / max(busy1[1] - busy0[1], 1) * 100
    load = {"started": started, "wall_s": round(wall), "loadavg_before": load0, "loadavg_after": loadavg(),
            "machine_busy_pct": round(busy_pct, 1),
            "others_pct_of_machine": round(max(0.0, busy_pct - own * 100 / (wall * (os.cpu_count() or 1))), 1)}
    lines = render(results, max(1, args.repeat), args.stat)
    lines.append("")
    lines.append(f"Measured {started} on {cpu_model()} ({os.cpu_count()} cores), commit {tree_state()}; load average "
                 f"{load['loadavg_before']} -> {load['loadavg_after']}, machine busy {busy_pct:.0f} %, of which other "
                 f"jobs {load['others_pct_of_machine']:.0f} %.")
    print("\n".join(lines))
    for res in results:
        kf = res["kfgins"]
        if "filter_us_per_sample" not in kf:
            continue
        name = Path(res["drive"]).name
        for mode, limit in (("15", 1.0), ("17", 1.3)):
            x = res[f"ours_{mode}"]["filter_us_per_sample"] / kf["filter_us_per_sample"]
            print(f"{name}: {mode}-state filter alone {x:.2f}x KF-GINS per IMU sample (issue: <= {limit:g}x)")
        for mode in MODES:
            x = res[f"ours_{mode}"]["process_cpu_s"] / kf["process_cpu_s"]
            print(f"{name}: `logger replay --mode {mode}` {x:.2f}x KF-GINS's whole process, CPU (issue: <= 2x on "
                  f"the 1200 s urban drive)")
        if not kf.get("harness_output_identical", True):
            print(f"{name}: warning: the harness's navresult differs from the binary's", file=sys.stderr)
    if args.json:
        info = {"cpu": cpu_model(), "cores": os.cpu_count(), "load": load, "commit": tree_state(),
                "kfgins": str(args.kfgins), "harness": str(harness) if harness else None, "repeat": args.repeat,
                "stat": args.stat, "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])}
        args.json.write_text(json.dumps({"machine": info, "drives": results}, indent=1, default=float) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
