"""The status snapshot as one screen for a person at a red light: the verdict and the problems first, then rows.

Everything fits the terminal it is drawn on (80x24 over SSH is the case it is made for): no line reaches the
last column (a terminal wraps there), long problems wrap under their own indent, and when the screen is short
the least urgent lines go first (where the data come from, per-incident totals, then the filter's verdicts from
the last), so the verdict, the problems and the sensor rows are always on screen. ``logger status --help``
explains every column (:data:`COLUMNS`).
"""

from __future__ import annotations

import textwrap
from typing import Any

from logger.words import plural, size_text
from sync.stamp import FREERUN

# Priorities: lines of a higher number are dropped first when the screen is short.
MUST, TABLE, LINE, DETAIL, VERDICT, FOOTNOTE = range(6)
MAX_PROBLEMS = 6  # beyond this, "+N more" (logger status --json has them all)
COLUMNS = """columns:
  state    ok; silent (running, nothing arrives); no fix (a receiver talking
           without a position); starting, retrying, missing (device not
           found), no-data, stalled (thread not responding), stopped
  rate Hz  measured over the last 10 s / configured; - while not running
  last     time since the last sample (never: none yet)
  errors   read errors since start (each one retried)
  gaps     silences longer than 2.5 periods
  late     samples read after their next deadline (a host that fell behind)
  reconn   times the device was opened again after losing it
rows below the table:
  gnss     fix type, satellites used, horizontal accuracy, PDOP, raw
           observations (RXM-RAWX a second) when asked for, age
  clock    state (locked to PPS; holdover or freerun, for how long since
           the last PPS edge it used), error bound of the stamps, offset and
           frequency of the board clock, the PPS edge it locked on
  nav      filter position and its 1-sigma (or, when the filter had no IMU
           sample for a while, how old the position is), then its plain
           verdicts
  rec      state, the file being written (or where it stopped), size,
           free disk; records on disk and dropped (queue full), queue, and
           how far back everything is on disk (what a power cut loses);
           time not recording since start (disk full, write errors, storage
           not mounted), the records that came meanwhile, those lost in a
           failed write and those deleted with their file or folder
  sim      a simulated drive's pace now against the --time-scale asked for
           (it slows when the daemon falls behind), and on average
exit code: 0 ok, 1 degraded, 2 critical, 3 not running, 4 not answering in
time or not allowed to ask"""


def age(s: float | None) -> str:
    """A time since, with its unit: ``0.4 s``, ``35 s``, ``12 min``, ``3.1 h`` (``never`` for None)."""
    if s is None:
        return "never"
    s = max(0.0, s)  # a record taken just after the snapshot's clock was read
    if s < 10:
        return f"{s:.1f} s"
    if s < 600:
        return f"{s:.0f} s"
    return f"{s / 60:.0f} min" if s < 6000 else f"{s / 3600:.1f} h"


def duration(s: float) -> str:
    s = int(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m{s % 60:02d}s"


class Screen:
    """Entries (a line, wrapped to the width) with their priorities; :meth:`fit` keeps the most urgent ones."""

    def __init__(self, width: int) -> None:
        self.width = max(40, width) - 1  # never the last column: a terminal wraps there
        self.entries: list[tuple[int, list[str]]] = []

    def add(self, prio: int, text: str, indent: int = 8) -> None:
        parts = textwrap.wrap(text, self.width, subsequent_indent=" " * indent, break_on_hyphens=False) or [""]
        self.entries.append((prio, parts))

    def fit(self, height: int | None) -> list[str]:
        """The lines, with whole entries of the least urgent kind dropped from the bottom up until ``height``."""
        entries = list(self.entries)

        def size() -> int:
            return sum(len(lines) for _, lines in entries)

        if height is not None:
            for prio in range(FOOTNOTE, TABLE, -1):  # the header, the problems and the table always stay
                while size() > height and any(p == prio for p, _ in entries):
                    del entries[max(i for i, (p, _) in enumerate(entries) if p == prio)]
        return [line for _, lines in entries for line in lines]


def render(snap: dict[str, Any], width: int = 80, height: int | None = None) -> str:
    """The snapshot as text at most ``width`` columns wide (and ``height`` lines high, when given)."""
    sc = Screen(width)
    verdict = str(snap.get("verdict", "?")).upper()
    head = f"logger {verdict}   up {duration(snap.get('uptime_s', 0))}   pid {snap.get('pid', '?')}"
    head += f"   {snap['mode']}" if snap.get("mode") else ""
    starting = [str(h.get("name")) for h in snap.get("sensors") or [] if h.get("state") == "starting"]
    if starting:
        # A sensor still opening (an ELM327's protocol search, a receiver's set-up: seconds at every start) is no
        # fault, and the verdict is ok; the first line says that it is not delivering yet, beside the OK.
        head += f"   starting: {', '.join(starting)}"
    sc.add(MUST, head)
    problems = snap.get("problems") or []
    shown = problems if len(problems) <= MAX_PROBLEMS else problems[:MAX_PROBLEMS - 1]
    for p in shown:
        sc.add(MUST, f"! {p}", indent=4)
    if len(shown) < len(problems):
        sc.add(MUST, f"! +{len(problems) - len(shown)} more problems (logger status --json)")
    sc.add(DETAIL, "")
    _sensors(sc, snap.get("sensors") or [])
    _gnss(sc, snap.get("gnss"))
    _clock(sc, snap.get("sync"))
    _nav(sc, snap.get("nav"))
    _recorder(sc, snap)
    _pace(sc, snap.get("pace"))
    return "\n".join(sc.fit(height))


def _sensors(sc: Screen, sensors: list[dict[str, Any]]) -> None:
    sc.add(TABLE, f"{'sensor':<7} {'state':<9} {'rate Hz':>10} {'last':>7} {'errors':>7} {'gaps':>5} "
                  f"{'late':>5} {'reconn':>6}")
    for h in sensors:
        measured = h.get("measured_rate_hz")
        now = "-" if measured is None else f"{measured:.1f}"
        rate = f"{now}/{h['rate_hz']:g}" if h.get("rate_hz") else now
        sc.add(TABLE, f"{h['name']:<7} {h['state']:<9} {rate:>10} {age(h.get('last_sample_age_s')):>7} "
                      f"{h.get('errors', 0):>7} {h.get('gaps', 0):>5} {h.get('late', 0):>5} "
                      f"{h.get('reconnects', 0):>6}")
    for h in sensors:
        for kind, count in (h.get("incidents") or {}).items():
            sc.add(FOOTNOTE, f"{h['name']:<7} {kind}: {count} since start")
        if h.get("samples_lost"):  # a FIFO's overflows and reopenings: samples gone, which its rate does not count
            sc.add(FOOTNOTE, f"{h['name']:<7} samples lost (FIFO overflows, reopenings): {h['samples_lost']} since "
                             "start")
    origins = [f"{h['name']} from {h['origin']}" for h in sensors if h.get("origin")]
    if origins:
        sc.add(FOOTNOTE, "source  " + ", ".join(origins))


STALE_GNSS_S = 3.0  # a receiver silent this long: its last solution is history, not the present
STALE_RAW_S = 3.0  # no RXM-RAWX for this long: say since when, not the rate they came at


def _gnss(sc: Screen, g: dict[str, Any] | None) -> None:
    if not g:
        return
    # "no fix" is logger.recording.records.NO_FIX: the view reads the snapshot only, it imports no record code.
    if (g.get("age_s") or 0.0) > STALE_GNSS_S:
        sc.add(LINE, f"gnss    nothing from the receiver for {age(g.get('age_s'))} (its last report: {g['fix']})")
        return
    parts = [g["fix"]]
    if g.get("num_sv") is not None:
        parts.append(plural(g["num_sv"], "satellite"))
    if g["fix"] != "no fix":
        if g.get("h_acc_m") is not None:
            parts.append(f"hAcc {g['h_acc_m']:.1f} m")
        if g.get("pdop") is not None:
            parts.append(f"PDOP {g['pdop']:.1f}")
    elif g.get("last_fix_age_s") is not None:
        parts.append(f"last fix {age(g['last_fix_age_s'])} ago")
    else:
        parts.append("no fix since start")
    if "raw_age_s" in g:  # raw observations asked for ([gnss] raw_observations)
        raw_age = g["raw_age_s"]
        parts.append("raw none yet" if raw_age is None else f"raw none for {age(raw_age)}" if raw_age > STALE_RAW_S
                     else f"raw {g['raw_hz']:.2g} Hz" if g.get("raw_hz") is not None else "raw coming")
    parts.append(f"reported {age(g.get('age_s'))} ago")
    sc.add(LINE, "gnss    " + ", ".join(parts))


def _clock(sc: Screen, sync: dict[str, Any] | None) -> None:
    if not sync:
        return
    state = sync.get("state", "?")
    bound = "unknown" if state == FREERUN or sync.get("err_ns") is None else f"{sync['err_ns'] / 1e3:.1f} us"
    # The age of the last PPS edge the clock used: locked, the pulse it locked on; otherwise how long it has gone
    # without one, said with the state ("PPS 24 s ago" read as the last pulse while the pps row showed them coming:
    # pulses the clock cannot label, with the receiver's time gone, are not used).
    used = sync.get("since_edge_s")
    held = f" for {age(used)}" if "since_edge_s" in sync and used is not None and state != "locked" else ""
    parts = [f"{state}{held}, error bound {bound}"]
    if sync.get("offset_ns") is not None:
        parts.append(f"offset {sync['offset_ns'] / 1e3:+.1f} us")
    if sync.get("freq_ppm") is not None:
        parts.append(f"{sync['freq_ppm']:+.2f} ppm")
    if "since_edge_s" in sync and not held:
        parts.append(f"PPS {age(used)} ago" if used is not None else "no PPS used yet")
    sc.add(LINE, "clock   " + ", ".join(parts))


def _nav(sc: Screen, nav: dict[str, Any] | None) -> None:
    if not nav:
        return
    verdicts = list(nav.get("verdicts") or [])
    if nav.get("lat_deg") is not None:
        where = f"nav     {nav['lat_deg']:.7f} {nav['lon_deg']:.7f} h {nav['height_m']:.1f} m"
        if nav.get("stale"):  # on the row itself: on a full screen the verdict saying so is the first dropped
            sc.add(LINE, f"{where}, {age(nav.get('age_s'))} old: not current")
        else:
            sigma = f", sigma {nav['sigma_h_m']:.1f} m" if nav.get("sigma_h_m") is not None else ""
            # Its age too: published on the whole seconds and taken up to a wake (2 s) later, a car's position is
            # tens of metres behind it at speed, which a bare position does not say.
            ago = f", {age(nav['age_s'])} ago" if nav.get("age_s") is not None else ""
            sc.add(LINE, f"{where}{sigma}{ago}" + (f" ({nav['source']})" if nav.get("source") else ""))
        for v in verdicts:
            sc.add(VERDICT, f"        {v}")
    elif verdicts:  # before the first solution: what the start waits for, on the row itself
        sc.add(LINE, f"nav     {verdicts[0]}")
        for v in verdicts[1:]:
            sc.add(VERDICT, f"        {v}")
    else:
        sc.add(LINE, f"nav     mode {nav.get('mode', '?')}: no position yet")


def _recorder(sc: Screen, snap: dict[str, Any]) -> None:
    rec = snap.get("recorder") or {}
    if not rec:
        return
    free = rec.get("free_bytes")
    free_text = f"{size_text(free)} free" if free is not None else "free disk unknown"
    state = rec.get("state", "?")
    name = str(rec.get("file") or "").rsplit("/", 1)[-1]
    held = f"{name} {size_text(rec.get('file_bytes', 0))}" if name else "no file"
    if state in ("recording", "stalled"):
        sc.add(LINE, f"rec     {state} {held}, {free_text}")
    else:
        # Not writing: the file named is where recording stopped (finished or cut), not one still growing; how long
        # the state has lasted comes from the snapshot's clock.
        since = rec.get("state_since_mono_ns")
        lasted = (f" {age((snap['t_mono_ns'] - since) / 1e9)}" if since and snap.get("t_mono_ns") else "")
        sc.add(LINE, f"rec     {state}{lasted}, " + (f"stopped at {held}" if name else "no file started"))
        sc.add(LINE, f"        {free_text}, nothing is being written")
    dropped = sum((rec.get("dropped") or {}).values())
    on_disk = rec.get("on_disk_mono_ns") or {}
    at_risk = (f", on disk up to {(snap['t_mono_ns'] - max(on_disk.values())) / 1e9:.1f} s ago"
               if on_disk and snap.get("t_mono_ns") else "")
    sc.add(DETAIL, f"        {sum((rec.get('written') or {}).values())} on disk, {dropped} dropped, "
                   f"queue {rec.get('queue_depth', 0)}/{rec.get('queue_size', 0)}{at_risk}")
    if rec.get("recovering"):
        sc.add(LINE, f"        recovering {rec['recovering']}")
    down = rec.get("down_s") or 0.0
    unrecorded = sum((rec.get("unrecorded") or {}).values())
    lost = sum((rec.get("lost") or {}).values())
    deleted = sum((rec.get("deleted") or {}).values())
    if down >= 1.0 or unrecorded or lost or deleted:
        # Since start: the time the recorder wrote nothing, the records that came meanwhile, those lost with a
        # failed write and those deleted with their file or folder (the row above counts only what is on disk).
        head = f"not recorded for {age(down)}: {unrecorded} records" if down >= 1.0 or unrecorded else ""
        tail = f"{lost} lost in failed writes" if lost else ""
        if head or tail:
            sc.add(LINE, "        " + "; ".join(p for p in (head, tail) if p))
        if deleted:  # a line of its own: the three together do not fit 80 columns
            sc.add(LINE, f"        {deleted} on disk, then deleted with their file or folder")


def _pace(sc: Screen, pace: dict[str, Any] | None) -> None:
    if not pace:
        return
    held = " (the host sets the pace)" if pace["now"] < pace["ceiling"] else ""
    sc.add(LINE, f"sim     drive at {pace['now']:.1f}x of {pace['ceiling']:g}x asked, "
                 f"{pace['achieved']:.1f}x on average{held}")
