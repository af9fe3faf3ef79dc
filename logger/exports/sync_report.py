"""Time-sync report of a recorded drive: the paper's Tables 6 and 7 for both methods, and the stamp error.

    logger sync-report DRIVE.mcap... [--png-dir DIR] [--json]

- Table 6: the largest IMU counter value (the paper's IMU_CNT with its timer carry, and the counter as it would be
  without the carry, i.e. reset by PPS only) and the longest interval without PPS.
- Table 7 (Eq. 14-15): intervals between consecutive PPS epochs, once as the board clock measures them (what the
  paper's interval counter saw) and once in synchronised time (this logger's clock).
- Where the file holds /truth/clock (simulated drives): the error of every sensor stamp against the true time, for
  this logger's clock (by state) and for the paper's Eq. 1 re-timing of the IMU samples.
- PNG: the paper's Figure 18 (counter values over time) and Figure 19 (interval trend and histogram).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from logger.exports.plotting import pyplot
from logger.exports.raw_stream import recorded_config
from logger.exports.whole import save_figure, written_together
from logger.recording.drive import DriveFile, DriveFileError, iter_messages, open_drive
from logger.recording.topics import BARO, GNSS_FIX, IMU, OBD_SPEED, PPS, TRUTH_CLOCK

SENSOR_TOPICS = (IMU, BARO, OBD_SPEED, GNSS_FIX, PPS)
NEEDED = (IMU, PPS)
"""What the report is made of: the IMU's counters (Table 6) and the PPS edges (Tables 6 and 7). A file without
them (a trajectory of logger replay, a capture of other topics) has no time sync to report, not a table of zeros."""
NS = 1_000_000_000


@dataclass
class Drive:
    topics: dict[str, list[dict]]
    imu_rate_hz: float
    files: list[DriveFile] = field(default_factory=list)

    @classmethod
    def load(cls, paths: list[Path]) -> Drive:
        """The drive's sensor records through the project's one drive reader, so a file cut short is read up to
        the cut as every other command reads it (a FIFO drive's /imu/batch comes as its /imu samples), and the
        IMU rate its configuration recorded. DriveFileError, one line naming the file, for a file it cannot read
        or one without the records the report needs (NEEDED)."""
        files = open_drive(paths)
        topics: dict[str, list[dict]] = {}
        for m in iter_messages(files, (*SENSOR_TOPICS, TRUTH_CLOCK)):
            topics.setdefault(m.topic, []).append(m.msg)
        missing = [t for t in NEEDED if not topics.get(t)]
        if missing:
            names = ", ".join(str(f.path) for f in files)
            raise DriveFileError(f"{names}: no {' or '.join(missing)} records: not a recorded drive's time sync "
                                 "(the report needs the IMU's counters and the PPS edges)")
        config = recorded_config(files)
        rate = float(config["imu.rate_hz"]) if "imu.rate_hz" in config else 20.0
        for msgs in topics.values():
            msgs.sort(key=lambda m: m["t_mono_ns"])
        return cls(topics, rate, files)


def truth_span(drive: Drive) -> tuple[int, int] | None:
    clock = drive.topics.get(TRUTH_CLOCK)
    return (clock[0]["t_mono_ns"], clock[-1]["t_mono_ns"]) if clock else None


def true_time(drive: Drive, t_mono: np.ndarray) -> np.ndarray | None:
    """True time at board times inside the span of /truth/clock (outside it there is nothing to compare with)."""
    clock = drive.topics.get(TRUTH_CLOCK)
    if not clock:
        return None
    mono = np.array([m["t_mono_ns"] for m in clock], dtype=np.int64)
    true = np.array([m["t_true_ns"] for m in clock], dtype=np.int64)
    # Interpolate in integer-safe pieces: offsets from the first pair keep float64 at sub-ns resolution.
    return true[0] + np.round(np.interp(t_mono - mono[0], mono - mono[0], (true - true[0]).astype(np.float64))
                              ).astype(np.int64)


def paper_times(drive: Drive) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 1 for every IMU sample after the first labelled edge: GPS time(k) + (IMU_CNT + Timer_CNT) / Fs."""
    imu = drive.topics.get(IMU, [])
    pps = [m for m in drive.topics.get(PPS, []) if m["sync_state"] != "freerun"]
    if not imu or not pps:
        return np.array([], dtype=np.int64), np.array([], dtype=np.int64)
    edge_mono = np.array([m["t_mono_ns"] for m in pps], dtype=np.int64)
    edge_gps = np.array([round(m["t_sync_ns"] / NS) * NS for m in pps], dtype=np.int64)  # the second it marks
    t = np.array([m["t_mono_ns"] for m in imu], dtype=np.int64)
    cnt = np.array([m["imu_cnt"] + m["timer_cnt"] for m in imu], dtype=np.int64)
    k = np.searchsorted(edge_mono, t, side="right") - 1
    ok = k >= 1
    t, cnt, k = t[ok], cnt[ok], k[ok]
    period_ns = round(NS / drive.imu_rate_hz)
    # A sample stamped just after an edge, before the PPS thread reported it, still counts from the edge before:
    # take the edge whose distance the count matches (board-clock data only, as the paper's board had).
    prev_fits = np.abs(cnt * period_ns - (t - edge_mono[k - 1])) < np.abs(cnt * period_ns - (t - edge_mono[k]))
    k = np.where(prev_fits, k - 1, k)
    return t, edge_gps[k] + cnt * period_ns


def interval_stats(t_ns: np.ndarray) -> dict[str, float]:
    dt = np.diff(t_ns) / NS
    dt = dt[(dt > 0.5) & (dt < 1.5)]  # consecutive edges only (a missed edge is an outage, not an interval)
    if not len(dt):
        return {"n": 0}
    return {"n": len(dt), "mean_s": float(dt.mean()), "rmse_s": float(np.sqrt(np.mean((dt - 1.0) ** 2))),
            "max_s": float(dt.max()), "accum_s": float(np.sum(dt - 1.0))}


def report(drive: Drive) -> dict:
    imu = drive.topics.get(IMU, [])
    pps = drive.topics.get(PPS, [])
    out: dict = {}
    cnt = np.array([m["imu_cnt"] for m in imu]) if imu else np.array([0])
    total = np.array([m["imu_cnt"] + m["timer_cnt"] for m in imu]) if imu else np.array([0])
    edge_mono = np.array([m["t_mono_ns"] for m in pps], dtype=np.int64)
    span = [m["t_mono_ns"] for m in imu] or [0]
    gaps = np.diff(np.concatenate(([span[0]], edge_mono, [span[-1]]))) / NS if len(edge_mono) else np.array(
        [(span[-1] - span[0]) / NS])
    out["table6"] = {"duration_s": (span[-1] - span[0]) / NS, "max_count_without_carry": int(total.max()),
                     "max_count_with_carry": int(cnt.max()), "longest_without_pps_s": float(gaps.max())}
    locked = [m for m in pps if m["sync_state"] != "freerun"]
    out["table7_board_clock"] = interval_stats(np.array([m["t_mono_ns"] for m in locked], dtype=np.int64))
    out["table7_synchronised"] = interval_stats(np.array([m["t_sync_ns"] for m in locked], dtype=np.int64))
    stamp: dict = {}
    span = truth_span(drive)
    for topic in SENSOR_TOPICS:
        if span is None:
            break
        msgs = [m for m in drive.topics.get(topic, [])
                if m["sync_state"] != "freerun" and span[0] <= m["t_mono_ns"] <= span[1]]
        if not msgs:
            continue
        mono = np.array([m["t_mono_ns"] for m in msgs], dtype=np.int64)
        truth = true_time(drive, mono)
        if truth is None:
            break
        err = np.array([m["t_sync_ns"] for m in msgs], dtype=np.int64) - truth
        bound = np.array([m["sync_err_ns"] for m in msgs], dtype=np.int64)
        states = np.array([m["sync_state"] for m in msgs])
        for state in ("locked", "holdover"):
            sel = states == state
            if sel.any():
                e = err[sel].astype(np.float64)
                stamp[f"{topic} {state}"] = {"n": int(sel.sum()), "rmse_us": float(np.sqrt(np.mean(e**2)) / 1e3),
                                             "max_us": float(np.abs(e).max() / 1e3),
                                             "bound_covers": float(np.mean(np.abs(err[sel]) <= bound[sel]))}
    if stamp:
        out["stamp_error"] = stamp
        t_mono, t_paper = paper_times(drive)
        inside = (t_mono >= span[0]) & (t_mono <= span[1])
        t_mono, t_paper = t_mono[inside], t_paper[inside]
        truth = true_time(drive, t_mono)
        if truth is not None and len(t_mono):
            e = (t_paper - truth).astype(np.float64)
            out["stamp_error_paper_eq1_imu"] = {"n": len(e), "rmse_us": float(np.sqrt(np.mean(e**2)) / 1e3),
                                               "max_us": float(np.abs(e).max() / 1e3)}
    return out


def render(out: dict) -> str:
    t6 = out["table6"]
    lines = ["Table 6  (counter values; the paper: 262,818 without, 21 with the method, over 60 h)",
             f"  duration {t6['duration_s']:.0f} s   max count without carry {t6['max_count_without_carry']}"
             f"   with carry {t6['max_count_with_carry']}   longest without PPS {t6['longest_without_pps_s']:.1f} s",
             "", "Table 7  (intervals between PPS epochs, Eq. 14; the paper: mean 1.0000509 s, RMSE 0.463 ms, "
             "max 1.004823 s)"]
    for name, key in (("board clock (paper's counter)", "table7_board_clock"),
                      ("synchronised (this clock)", "table7_synchronised")):
        s = out[key]
        if s.get("n"):
            lines.append(f"  {name:<30} n {s['n']:>6}  mean {s['mean_s']:.7f} s  RMSE {s['rmse_s'] * 1e3:.4f} ms"
                         f"  max {s['max_s']:.6f} s  accumulated {s['accum_s'] * 1e3:+.3f} ms")
    if "stamp_error" in out:
        lines += ["", "Stamp error against the truth"]
        for k, s in out["stamp_error"].items():
            lines.append(f"  {k:<22} n {s['n']:>7}  RMSE {s['rmse_us']:9.2f} us  max {s['max_us']:9.2f} us"
                         f"  bound covers {s['bound_covers'] * 100:6.2f} %")
        p = out.get("stamp_error_paper_eq1_imu")
        if p:
            lines.append(f"  {'/imu paper Eq. 1':<22} n {p['n']:>7}  RMSE {p['rmse_us']:9.2f} us"
                         f"  max {p['max_us']:9.2f} us")
    return "\n".join(lines)


def plots(drive: Drive, out_dir: Path) -> list[Path]:
    """Figures 18 and 19 of the drive into ``out_dir``: both, or neither (an earlier pair left as it was)."""
    with written_together():
        return _plots(drive, out_dir)


def _plots(drive: Drive, out_dir: Path) -> list[Path]:
    plt = pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    imu = drive.topics.get(IMU, [])
    t0 = imu[0]["t_mono_ns"] if imu else 0
    t = np.array([(m["t_mono_ns"] - t0) / NS for m in imu])
    fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    ax[0].plot(t, [m["imu_cnt"] + m["timer_cnt"] for m in imu], lw=0.8)
    ax[0].set_ylabel("count")
    ax[0].set_title("(a) IMU counter without the timer carry (reset by PPS only)")
    ax[1].plot(t, [m["imu_cnt"] for m in imu], lw=0.8, color="C1")
    ax[1].set_ylabel("count")
    ax[1].set_xlabel("time since start (s)")
    ax[1].set_title("(b) IMU counter with the timer carry (the paper's method)")
    fig.tight_layout()
    f18 = out_dir / "figure18_counters.png"
    save_figure(fig, f18, 100)
    plt.close(fig)
    pps = [m for m in drive.topics.get(PPS, []) if m["sync_state"] != "freerun"]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for key, label in (("t_mono_ns", "board clock"), ("t_sync_ns", "synchronised")):
        ts = np.array([m[key] for m in pps], dtype=np.int64)
        dt = np.diff(ts) / NS
        keep = (dt > 0.5) & (dt < 1.5)
        ax[0].plot(((ts[1:] - ts[0]) / NS)[keep], (dt[keep] - 1.0) * 1e6, ".", ms=2, label=label)
        ax[1].hist((dt[keep] - 1.0) * 1e6, bins=60, alpha=0.6, label=label)
    ax[0].set_xlabel("time (s)")
    ax[0].set_ylabel("interval - 1 s (us)")
    ax[0].set_title("(a) interval between synchronised epochs")
    ax[0].legend()
    ax[1].set_xlabel("interval - 1 s (us)")
    ax[1].set_title("(b) histogram")
    ax[1].legend()
    fig.tight_layout()
    f19 = out_dir / "figure19_intervals.png"
    save_figure(fig, f19, 100)
    plt.close(fig)
    return [f18, f19]
