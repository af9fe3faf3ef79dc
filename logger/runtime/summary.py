"""What a run leaves behind, said when it ends: files, topics, sensors that never delivered, clock, filter, next steps.

Printed by ``logger run`` after the daemon stopped (after ``--duration`` or Ctrl-C, and in the journal under
systemd), like ``mcap``'s and ``ros2 bag``'s summaries: every file by its final name with its size and whether it
was finished, per-topic counts and rates over the run, each sensor that never delivered, ended unwell (with its
last error) or spent time unwell (how long in which state), the clock's state and its share of the run in each,
how long the filter had a position, and the commands to look at the drive.
"""

from __future__ import annotations

import math
import textwrap
from importlib.util import find_spec
from typing import Any

from logger.recording.files import file_state
from logger.runtime.daemon import CLOCK, Daemon
from logger.words import plural
from sync.stamp import FREERUN


def run_summary(daemon: Daemon) -> str:
    span_s = daemon.run_span_s
    files = daemon.recorder.files()
    states = [file_state(p) for p in files]  # one look at each file: (size, finished), None when it is gone
    rec = daemon.recorder.status()
    # The time the recorder was down (disk full, write errors) is not recorded drive: "recorded 200 s" over 50 s of
    # a full disk was not true.
    down_s = min(rec.down_s, span_s)
    run = (f"recorded {span_s - down_s:.1f} s of a {span_s:.1f} s run" if down_s >= DOWN_SHOWN_S
           else f"recorded {span_s:.1f} s of drive")
    gone = sum(state is None for state in states)
    # A file deleted or moved away meanwhile: what was recorded is not all where the run put it ("recorded 120 s"
    # with the first minute's file gone was said of 48 s left on disk).
    where = f" ({plural(gone, 'file')} of them no longer there: deleted or moved)" if gone else ""
    total = sum(state[0] for state in states if state is not None)
    lines = [f"logger: {run} into {plural(len(files), 'file')}, {total / 1e6:.1f} MB{where}"]
    for p, state in zip(files, states, strict=True):
        if state is None:
            lines.append(f"  {p}  (gone)")
        else:
            note = "" if state[1] else "  (not finished: `logger recover` it)"
            lines.append(f"  {p}  {state[0] / 1e6:.1f} MB{note}")
    written = rec.written
    if written or rec.deleted:
        topics = sorted({*written, *rec.deleted})
        width = max(len(t) for t in topics)
        # Rates over the time the recorder recorded: over the whole run, a disk full for half of it halved them.
        # And of every record that reached the disk: those deleted since were recorded at the sensors' rates (the
        # messages column is what is still there).
        rec_s = span_s - down_s if down_s >= DOWN_SHOWN_S else span_s
        lines.append(f"  {'topic':<{width}}  {'messages':>9}  {'rate Hz':>8}"
                     + ("  (rates while recording)" if rec_s < span_s else "")
                     + ("  (rates of all recorded, deleted too)" if rec.deleted else ""))
        for topic in topics:
            recorded = written.get(topic, 0) + rec.deleted.get(topic, 0)
            rate = recorded / rec_s if rec_s > 0 else math.nan
            samples = rec.samples.get(topic)
            # A batch topic's messages are reads: the samples they hold are what its rate is judged by.
            if samples is not None or topic in rec.deleted_samples:
                samples = (samples or 0) + rec.deleted_samples.get(topic, 0)
            held = (f"  ({samples} samples, {samples / rec_s:.2f} Hz)" if samples is not None and rec_s > 0
                    else "")
            lines.append(f"  {topic:<{width}}  {written.get(topic, 0):>9}  {rate:>8.2f}{held}")
    losses = recorder_losses(down_s, rec.unrecorded, rec.lost, rec.dropped, rec.deleted)
    lines += [f"  ! {line}" for line in losses]
    # The rows as they were when the run was told to stop (a sampler says "stopped" once it has), with the daemon's
    # own judgement in them (silent, stalled); the samplers' health at that time when the daemon never started.
    end = daemon.ended_mono_ns
    rows = daemon.final_sensors or [s.health.snapshot(end) for s in daemon.samplers]
    for snap in rows:
        if snap["samples"] == 0:
            lines.append(f"  ! {snap['name']} never delivered" + (f": {snap['last_error']}" if snap["last_error"]
                                                                  else ""))
        elif snap["state"] not in ("ok", "stopped"):
            lines.append(f"  ! {snap['name']} ended {snap['state']}" + (f": {snap['last_error']}" if snap["last_error"]
                                                                        else ""))
        if snap["samples"]:
            spent = daemon.time_in_state.get(snap["name"], {})
            unwell = {k: v for k, v in spent.items() if k not in ("ok", "stopped", "starting")}
            if sum(unwell.values()) >= 1.0:
                parts = ", ".join(f"{state} {s:.0f} s" for state, s in sorted(unwell.items(), key=lambda kv: -kv[1]))
                lines.append(f"  ! {snap['name']} was not ok for {sum(unwell.values()):.0f} s of the run ({parts})")
    for line in shortfalls(daemon):
        lines.append(f"  ! {line}")
    pace = daemon.tb.pace()
    if pace is not None:
        lines.append("  " + pace_line(pace))
    lines.append("  " + clock_line(daemon))
    nav = daemon.attachments.sections.get("nav")
    if nav is not None:
        lines.append("  " + nav_line(nav()))
    there = [p for p, state in zip(files, states, strict=True) if state is not None]
    if there:  # the files still there: a command naming a deleted one fails on it
        drive = " ".join(map(str, there))
        # plot needs matplotlib, an optional extra (not on the board): said here, not after the command is typed
        plot_needs = "" if find_spec("matplotlib") else "   (needs matplotlib: pip install matplotlib)"
        lines += ["next:", f"  logger info {drive}", f"  logger plot {drive} --out plots/{plot_needs}",
                  f"  logger replay {drive} --out replay/", "  or open the files in Foxglove (docs/foxglove.md)"]
    return "\n".join(lines)


def fitted(text: str, width: int) -> str:
    """The summary for a terminal ``width`` columns wide: a line of words longer than that wrapped under its own
    indent (two more for the lines after the first); commands and file paths, which are copied whole, stay whole.
    The clock and nav lines and a recorder's loss ran to 108-160 columns on a phone's 80."""
    out: list[str] = []
    for line in text.split("\n"):
        body = line.lstrip(" ")
        if len(line) <= width or body.startswith(("logger ", "/")):
            out.append(line)
            continue
        lead = line[:len(line) - len(body)]
        more = lead + ("    " if body.startswith("! ") else "  ")
        out += textwrap.wrap(body, width, initial_indent=lead, subsequent_indent=more, break_long_words=False,
                             break_on_hyphens=False)
    return "\n".join(out)


DOWN_SHOWN_S = 1.0  # recorder downtime below this is not worth a line (a rotation's open is not downtime)


def recorder_losses(down_s: float, unrecorded: dict[str, int], lost: dict[str, int],
                    dropped: dict[str, int], deleted: dict[str, int] | None = None) -> list[str]:
    """What the run's files lack, one line each: the time the recorder was not recording and the records that came
    meanwhile, the records lost in a failed write (handed to the writer, never on disk), the records dropped for a
    full queue, the records deleted with their file or folder while recording. The topic table counts only what is
    on disk."""
    out = []
    n_unrec = sum(unrecorded.values())
    if down_s >= DOWN_SHOWN_S or n_unrec:
        out.append(f"not recording for {down_s:.0f} s of the run (disk full, write errors or the storage not "
                   f"mounted: see the log); {plural(n_unrec, 'record')} came meanwhile and were not recorded")
    if sum(lost.values()):
        out.append(f"{plural(sum(lost.values()), 'record')} lost in failed writes (handed to the writer, never on "
                   "disk)")
    if sum(dropped.values()):
        out.append(f"{plural(sum(dropped.values()), 'record')} dropped (the recorder's queue was full)")
    if deleted and sum(deleted.values()):
        out.append(f"{plural(sum(deleted.values()), 'record')} deleted with their file or folder while recording "
                   "(on disk, then deleted: see the log)")
    return out


RATE_HELD = 0.99  # a periodic sensor that let more than 1 % of its periods pass unsampled fell behind ...
SHORTFALL_MIN_S = 1.0  # ... and more than a second's worth: a short run's one hiccup is not a rate not held


def shortfalls(daemon: Daemon, host_only: bool = False) -> list[str]:
    """The periodic sensors that did not hold their configured rate, one line each: the periods their sampler
    let pass unsampled (a read that ended after the next was due: a host that fell behind, a bus too slow)
    against all it was due, and the rate in drive time; more than 1 % of them and more than a second's worth.
    ``host_only``: only misses after a read the host made late (a paced simulated drive measures that), the
    ones a faster host would not have had."""
    out = []
    for s in daemon.samplers:
        h = s.health
        if not s.rate_hz or h.samples < 2 or h.first_sample_mono_ns is None or h.last_sample_mono_ns is None:
            continue
        span_s = (h.last_sample_mono_ns - h.first_sample_mono_ns) / 1e9
        rate_hz = h.rate_hz or s.rate_hz
        if rate_hz > s.rate_hz:
            # A FIFO read a few times a second: a read period missed loses no sample while the FIFO holds them, and
            # its samples are not its periods (47 missed reads of a 20 Hz IMU read "47 of 1349 periods", 3.5 %, as
            # 470 samples went). The samples its overflows destroyed are what it did not deliver (not the rate
            # times the span: the chip's own clock is good to about 1 %); of those, the host's part is at most its
            # late reads' worth.
            lost = h.samples_lost
            due = h.samples + lost
            host = min(lost, round(h.missed_host * rate_hz / s.rate_hz))
            missed, unit = (host if host_only else lost), "samples"
        else:
            due, host = h.samples + h.missed, h.missed_host
            missed, unit = (host if host_only else h.missed), "periods"
        if missed <= max((1.0 - RATE_HELD) * due, SHORTFALL_MIN_S * rate_hz):
            continue
        rate = f", {(h.samples - 1) / span_s:.2f} Hz of drive time against {rate_hz:g} Hz" if span_s > 0 else ""
        cause = f", {host} while the host ran late" if host and not host_only else ""
        out.append(f"{h.name} let {missed} of its {due} {unit} pass unsampled ({missed / due:.1%}{cause}){rate}")
    return out


def pace_line(pace: dict[str, Any]) -> str:
    """A governed simulated drive: how fast it ran against the time scale asked for."""
    held = (f"; slowed to {pace['slowest']:.1f}x at the slowest, below the ceiling for {pace['held_back_s']:.0f} s "
            "of host time" if pace["held_back_s"] >= 1.0 else "")
    return f"simulated drive at {pace['achieved']:.1f}x on average of {pace['ceiling']:g}x asked{held}"


def clock_line(daemon: Daemon) -> str:
    end = daemon.ended_mono_ns
    report = daemon.clock.report(end)
    if report is None:
        st = daemon.clock.stamp(end)
        return f"clock {st.state} (no PPS discipline)"
    bound = "unknown" if report.state == FREERUN else f"{report.err_ns / 1e3:.1f} us"
    spent = daemon.time_in_state.get(CLOCK, {})
    total = sum(spent.values())
    shares = (" (" + ", ".join(f"{state} {s / total:.0%}" for state, s in sorted(spent.items(), key=lambda kv: -kv[1]))
              + " of the run)") if total > 0 else ""
    return (f"clock {report.state} at the end, error bound {bound}, {plural(report.edges, 'PPS edge')}, "
            f"{plural(report.relocks, 'relock')}{shares}")


def nav_line(nav: dict[str, Any]) -> str:
    verdicts = nav.get("verdicts") or []
    where = (f"live position for {nav.get('live_s', 0.0):.0f} s, last {nav['lat_deg']:.6f} {nav['lon_deg']:.6f} "
             f"({nav['source']})" if nav.get("lat_deg") is not None else
             "no position" + (f" ({verdicts[0]})" if verdicts else ""))
    return (f"navigation mode {nav.get('mode', '?')}: {where}; {nav.get('processed', 0)} records, "
            f"{plural(nav.get('resets', 0), 'restart')}")


