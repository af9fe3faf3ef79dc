"""``logger plot FILE... --out DIR``: a drive at a glance as PNG files.

- ``NAME_map.png``: the receiver's valid fixes against the filter's ``/nav/fix`` (live, and any replay given),
  in equal-aspect metres east and north of the first position, each track broken where it has gaps.
- ``NAME_rates.png``: per sensor topic, the message rate over time, messages lost (``seq`` jumps) and gaps (the
  rule ``logger info`` counts them by); the receiver's fixes apart from its messages (a receiver in a tunnel
  still reports once a second, without a position) and a panel of its fix quality (satellites used, horizontal
  accuracy); the spans without a fix shaded grey in every panel.
- ``NAME_sync.png``: the clock's state and error bound over time, from ``/sync`` and from the sync fields
  every stamped message carries, and the offset measured at each PPS edge; the spans without a fix shaded grey
  (the clock holds over through them).

Needs matplotlib (the ``plots`` extra); without it the command says how to install it.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from logger.cli.outputs import drive_name, os_error_line, out_folder_problem
from logger.cli.progress import Progress
from logger.exports.formats import utc_iso
from logger.exports.plotting import PlotsUnavailable, local_en, pyplot
from logger.exports.topic_timing import STAMPED_TOPICS, TopicTiming, timings
from logger.exports.tracks import EXPORT_TOPICS, Track, build_tracks
from logger.exports.whole import save_figure, written_together
from logger.recording.drive import DriveFileError, DriveMessage, cut_notes, damage_notes, iter_messages, open_drive
from logger.recording.records import NO_FIX, fix_name
from logger.recording.topics import GNSS_FIX, SYNC
from logger.words import plural

STATES = ("freerun", "holdover", "locked")
DPI = 110


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="logger plot", description="PNG plots of a drive: map, rates and gaps, sync")
    p.add_argument("files", nargs="+", type=Path, metavar="FILE",
                   help="MCAP files of one drive (rotated files, a cut file) or the folder holding them, and/or "
                        "logger replay's trajectory.mcap")
    p.add_argument("--out", required=True, type=Path, help="folder for the PNG files")
    return p.parse_args(argv)


def _seconds(log_ns: np.ndarray | list[int], t0_ns: int) -> np.ndarray:
    return (np.asarray(log_ns, dtype=np.int64) - t0_ns) / 1e9


def nice_step(x: float) -> float:
    """The smallest 1, 2 or 5 times a power of ten that is at least ``x``."""
    power = 10.0 ** math.floor(math.log10(x))
    return next(m * power for m in (1.0, 2.0, 5.0, 10.0) if m * power >= x * (1 - 1e-9))


def draw_map(plt: Any, tracks: list[Track], path: Path) -> Path | None:
    pts = [p for t in tracks for p in t.points]
    if not pts:
        return None
    lat0, lon0 = math.radians(pts[0].lat_deg), math.radians(pts[0].lon_deg)
    fig, ax = plt.subplots(figsize=(8, 8))
    for i, t in enumerate(tracks):
        colour = f"C{i}"
        for k, seg in enumerate(t.segments):
            east, north = local_en(np.radians([p.lat_deg for p in seg]), np.radians([p.lon_deg for p in seg]),
                                   lat0, lon0)
            label = f"{t.label}: {plural(t.n_points, 'point')}, {plural(len(t.gaps), 'gap')}" if k == 0 else None
            if t.topic == GNSS_FIX:
                ax.plot(east, north, ".", ms=3, color=colour, label=label)
            else:
                ax.plot(east, north, "-", lw=1.0, color=colour, label=label)
        for g in t.gaps:
            east, north = local_en(np.radians([g.before.lat_deg, g.after.lat_deg]),
                                   np.radians([g.before.lon_deg, g.after.lon_deg]), lat0, lon0)
            ax.plot(east, north, ":", lw=0.8, color=colour)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.set_title(f"drive from {pts[0].lat_deg:.6f}, {pts[0].lon_deg:.6f} (dotted: gaps, not driven as drawn)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, DPI)
    plt.close(fig)
    return path


def no_fix_spans(fixes: list[DriveMessage], t0_ns: int) -> list[tuple[float, float]]:
    """(start, end) in s since ``t0_ns`` of each run of receiver reports without a fix."""
    spans: list[tuple[float, float]] = []
    start: float | None = None
    x = 0.0
    for m in fixes:
        x = (m.log_time - t0_ns) / 1e9
        if fix_name(m.msg) == NO_FIX:
            start = x if start is None else start
        elif start is not None:
            spans.append((start, x))
            start = None
    if start is not None:
        spans.append((start, x))
    return spans


def _shade(ax: Any, spans: list[tuple[float, float]]) -> None:
    for a, b in spans:
        ax.axvspan(a, b, color="0.5", alpha=0.18, lw=0)


def draw_rates(plt: Any, tim: dict[str, TopicTiming], fixes: list[DriveMessage], t0_ns: int, span_s: float,
               path: Path) -> Path:
    base_bin_s = max(1.0, span_s / 400.0)
    outages = no_fix_spans(fixes, t0_ns)
    panels = len(tim) + (1 if fixes else 0)
    fig, axes = plt.subplots(panels, 1, figsize=(11, 1.9 * panels + 0.8), sharex=True, squeeze=False)
    for ax, tt in zip(axes[:, 0], tim.values(), strict=False):
        bin_s = nice_step(max(base_bin_s, 5.0 * tt.median_interval_s))  # several messages a bin, not jitter
        x, rate = tt.rate(t0_ns, bin_s)
        ax.step(x, rate, where="mid", lw=0.9, color="C0", label="messages")
        if tt.topic == GNSS_FIX:
            valid = [m.log_time for m in fixes if fix_name(m.msg) != NO_FIX]
            if valid and len(x):
                # The messages' own bins, so the two lines share every bin and a late first fix is not cut off.
                edges = np.append(x - bin_s / 2.0, x[-1] + bin_s / 2.0)
                counts, _ = np.histogram((np.array(valid) - t0_ns) / 1e9, bins=edges)
                ax.step(x, counts / bin_s, where="mid", lw=0.9, color="C2", label="with a fix")
            ax.legend(fontsize=7, loc="lower right")
        _shade(ax, outages)
        for g in tt.gaps:
            ax.axvspan((g.before_ns - t0_ns) / 1e9, (g.after_ns - t0_ns) / 1e9, color="C1", alpha=0.35, lw=0)
        if tt.lost:
            xs = _seconds([t for t, _ in tt.lost], t0_ns)
            top = float(rate.max()) if len(rate) else 1.0
            ax.plot(xs, np.full(len(xs), top), "v", color="C3", ms=6)
            for x_lost, (_, n_lost) in zip(xs, tt.lost, strict=True):
                ax.annotate(f"-{n_lost}", (x_lost, top), textcoords="offset points", xytext=(3, -10), fontsize=7,
                            color="C3")
        for r in tt.restarts:
            ax.axvline((r - t0_ns) / 1e9, color="k", lw=0.8, ls="--")
        ax.set_ylabel(f"Hz ({bin_s:g} s bins)")
        ax.set_title(tt.summary(), fontsize=8, loc="left")
        ax.grid(alpha=0.3)
    if fixes:
        draw_fix_quality(axes[-1, 0], fixes, t0_ns, outages)
    axes[-1, 0].set_xlabel(f"s since {utc_iso(t0_ns)} (grey: no GNSS fix, orange: gaps, red: messages lost by seq, "
                           "dashed: restart)")
    fig.tight_layout()
    save_figure(fig, path, DPI)
    plt.close(fig)
    return path


def draw_fix_quality(ax: Any, fixes: list[DriveMessage], t0_ns: int, outages: list[tuple[float, float]]) -> None:
    """Satellites used (left axis) and the receiver's horizontal accuracy (right axis, m, log) per report."""
    xs = _seconds([m.log_time for m in fixes], t0_ns)
    sv = np.array([m.msg.get("num_sv") if m.msg.get("num_sv") is not None else np.nan for m in fixes], float)
    ax.step(xs, sv, where="post", lw=0.9, color="C0", label="satellites used")
    ax.set_ylabel("satellites")
    ax.set_ylim(bottom=0)
    acc = ax.twinx()
    h = np.array([m.msg["h_acc_m"] if m.msg.get("h_acc_m") is not None and fix_name(m.msg) != NO_FIX else np.nan
                  for m in fixes], float)
    if np.isfinite(h).any():
        acc.plot(xs, h, ".", ms=2, color="C3", label="horizontal accuracy")
        acc.set_yscale("log")
    acc.set_ylabel("hAcc, m", color="C3")
    _shade(ax, outages)
    no_fix_s = sum(b - a for a, b in outages)
    ax.set_title(f"{GNSS_FIX} fix quality: {plural(len(outages), 'span')} without a fix, {no_fix_s:.0f} s in all",
                 fontsize=8, loc="left")
    ax.grid(alpha=0.3)


def draw_sync(plt: Any, sync: list[DriveMessage], tim: dict[str, TopicTiming], fixes: list[DriveMessage], t0_ns: int,
              path: Path) -> Path:
    fig, (ax_state, ax_err, ax_off) = plt.subplots(3, 1, figsize=(11, 8), sharex=True)
    outages = no_fix_spans(fixes, t0_ns)
    level = {s: i for i, s in enumerate(STATES)}
    if sync:
        xs = _seconds([m.log_time for m in sync], t0_ns)
        ax_state.step(xs, [level.get(m.msg.get("state"), -1) for m in sync], where="post", lw=1.5, color="k",
                      label="/sync state")
        err_us = np.array([m.msg.get("err_ns", 0) for m in sync], dtype=float) / 1e3
        ax_err.plot(xs, np.maximum(err_us, 1e-3), "k-", lw=1.5, label="/sync error bound")
        # offset_ns is the last edge's: a report more than a second after its edge repeats an old value
        off = [(x, m.msg["offset_ns"] / 1e3) for x, m in zip(xs, sync, strict=True)
               if m.msg.get("offset_ns") is not None and (m.msg.get("since_edge_s") or 0.0) <= 1.0]
        if off:
            ax_off.plot([o[0] for o in off], [o[1] for o in off], ".-", ms=3, lw=0.6, color="k")
    for i, tt in enumerate(tim.values()):
        xs = _seconds(tt.log_ns, t0_ns)
        ax_state.plot(xs, [level.get(s, -1) + 0.06 * (i + 1) for s in tt.sync_state], ".", ms=1.5,
                      color=f"C{i}", label=f"{tt.topic} sync_state")
        ax_err.plot(xs, np.maximum(tt.sync_err_ns / 1e3, 1e-3), ".", ms=1.5, color=f"C{i}",
                    label=f"{tt.topic} error bound")
    ax_state.set_yticks(range(len(STATES)), STATES)
    ax_state.set_ylim(-0.5, len(STATES) - 0.1)
    ax_state.set_title("clock state (per-message states drawn a little above their level)", fontsize=9, loc="left")
    ax_state.legend(fontsize=7, ncol=4, loc="lower right", markerscale=4)
    ax_err.set_yscale("log")
    ax_err.set_ylabel("error bound, us")
    ax_err.legend(fontsize=7, ncol=4, loc="upper right", markerscale=4)
    ax_off.set_ylabel("offset at PPS edge, us")
    ax_off.set_xlabel(f"s since {utc_iso(t0_ns)} (grey: no GNSS fix)")
    for ax in (ax_state, ax_err, ax_off):
        ax.grid(alpha=0.3)
        _shade(ax, outages)
    fig.tight_layout()
    save_figure(fig, path, DPI)
    plt.close(fig)
    return path


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    progress = Progress("logger plot")
    try:
        plt = pyplot()
        files = open_drive(args.files)
        problem = out_folder_problem(args.out)
        if problem:
            raise DriveFileError(problem)
        messages = list(iter_messages(files, (*STAMPED_TOPICS, SYNC, *EXPORT_TOPICS), progress))
    except (PlotsUnavailable, DriveFileError) as exc:
        progress.end()
        print(f"logger plot: {exc}", file=sys.stderr)
        return 2
    for line in cut_notes(files) + damage_notes(files):
        print(f"logger plot: {line}", file=sys.stderr)
    if not messages:
        print(f"logger plot: nothing to plot in {', '.join(map(str, args.files))}: no sensor, /sync or position "
              "topics", file=sys.stderr)
        return 2
    tracks = build_tracks(messages, files)
    tim = timings(messages)
    sync = [m for m in messages if m.topic == SYNC]
    fixes = [m for m in messages if m.topic == GNSS_FIX]
    t0 = messages[0].log_time
    span_s = (messages[-1].log_time - t0) / 1e9
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        name = drive_name(files)
        with written_together():  # one run's figures, or none
            progress.stage("drawing the map")
            written = [draw_map(plt, tracks, args.out / f"{name}_map.png")]
            if tim:
                progress.stage("drawing the rates")
                written.append(draw_rates(plt, tim, fixes, t0, span_s, args.out / f"{name}_rates.png"))
            if tim or sync:
                progress.stage("drawing the clock")
                written.append(draw_sync(plt, sync, tim, fixes, t0, args.out / f"{name}_sync.png"))
    except OSError as exc:  # the folder was checked first; what is left: a disk full, a folder changed meanwhile
        progress.end()
        print(f"logger plot: {os_error_line(exc)}", file=sys.stderr)
        return 2
    progress.end()
    for tt in tim.values():
        print(tt.summary())
    for p in written:
        if p is not None:
            print(f"wrote {p}")
    return 0
