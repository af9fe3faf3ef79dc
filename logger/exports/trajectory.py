"""A drive through the navigation filter, and the trajectory it gives as CSV and MCAP (``logger replay``'s work).

The same engine as the live navigator, fed by the same record layer, as fast as the files can be read,
optionally followed by the Rauch-Tung-Striebel backward pass. ``trajectory.csv`` has one row per IMU sample once
the filter runs (per fix in GNSS-only mode): the whole solution, for scoring and analysis. ``trajectory.mcap``
is for the map: ``/nav/fix`` at the rate the live navigator publishes it (``nav.publish_hz``, 5 Hz by default;
``fix_hz`` another, 0 every row) and ``/nav/state`` once a second, so Foxglove draws it next to the recording.

Both are written by the block, not by the row: the rows become columns a block at a time (the attitudes of the
block at once), the CSV lines of a block go through one format, and each ``/nav/fix`` message's JSON is one fill
of a fixed template (the same bytes as ``json.dumps`` of :func:`~logger.recording.records.nav_fix_record`).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from logger.exports.whole import written_whole
from logger.nav import boresight
from logger.nav.engine import REOPEN_DEG, NavEngine, TrajectoryRow, forward_axis_turned
from logger.nav.inputs import SolutionEpoch
from logger.nav.mounting import SETTLED, USABLE_SIGMA_DEG, MountEstimate
from logger.nav.params import NavParams
from logger.nav.rotations import dcm_from_quat
from logger.recording.drive import REPLAY_LIBRARY, REPLAY_OF_METADATA, ProgressFn, read_messages, record_of
from logger.recording.intervals import next_due_ns
from logger.recording.mcap_writer import McapWriter
from logger.recording.nav_rerun import NavRerun
from logger.recording.records import (
    NAV_INPUT_TOPICS,
    follows_on,
    nav_fix_record,
    nav_state_record,
    next_whole_second,
    record_fault,
)
from logger.recording.topics import IMU, IMU_BATCH, NAV_FIX, NAV_STATE, TOPICS
from logger.words import plural

if TYPE_CHECKING:
    from logger.nav.smoother import SmoothingReport

CSV_HEADER = ("t_sync_ns", "t_mono_ns", "lat_deg", "lon_deg", "height_m", "vn_mps", "ve_mps", "vd_mps", "roll_deg",
              "pitch_deg", "yaw_deg", "sn_m", "se_m", "sd_m")
# A CSV line: the times as integers, latitude and longitude to 1e-9 deg (0.1 mm), the rest to 3 decimals. The
# line end is the csv module's (\r\n), which the file always had.
CSV_LINE = ",".join(("%s", "%s", "%.9f", "%.9f") + ("%.3f",) * 10) + "\r\n"
BLOCK_ROWS = 2048  # rows made columns, formatted and written at a time
# What /nav/fix carries for a sigma the filter does not know yet, as the record layer writes it.
SIGMA_UNKNOWN_M: float = nav_fix_record(0, 0, 0.0, 0.0, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (math.inf,) * 3, "",
                                        "")["sigma_ned_m"][0]
# json.dumps(nav_fix_record(...)) with its values left open: floats as repr (what json writes for a finite float),
# the source and mode as JSON strings. A test holds the two to the same bytes.
NAV_FIX_JSON = ('{"t_mono_ns": %d, "t_sync_ns": %d, "timestamp": {"sec": %d, "nsec": %d}, "frame_id": "nav", '
                '"latitude": %r, "longitude": %r, "altitude": %r, '
                '"position_covariance": [%r, 0.0, 0.0, 0.0, %r, 0.0, 0.0, 0.0, %r], "position_covariance_type": 2, '
                '"vel_ned_mps": [%r, %r, %r], "rpy_deg": [%r, %r, %r], "sigma_ned_m": [%r, %r, %r], '
                '"source": %s, "mode": %s}')


def read_drive(paths: list[Path], topics: tuple[str, ...] = NAV_INPUT_TOPICS,
               progress: ProgressFn | None = None, runs: bool = False) -> Iterator[tuple[str, dict[str, Any]]]:
    """(topic, message) of the given topics over several files (a rotated drive), in log-time order; ``runs``: a
    FIFO drive's samples as blocks (``/imu/batch`` records cut at the other messages), as the live navigator
    takes them."""
    return read_messages(paths, topics, progress, runs)


# A second pass once the car's forward axis on the chip is known to this (1 sigma, pitch and yaw): half of what the
# live filter acts on, so that the second pass starts on an axis it will not have to turn again. A drive without
# turns never tells the roll (the alignment keeps the guess's): the forward axis is what the OBD speed and the
# non-holonomic rows hold the body on, and the simulated outage and tunnel drives with the board at (5, -4, 30) deg
# came out within 8 % of the configured mounting's with the roll left at the guess.
REFILTER_SIGMA_DEG = USABLE_SIGMA_DEG / 2.0


def mounting_found(engine: NavEngine, started_with: tuple[float, ...]) -> MountEstimate | None:
    """The mounting the drive showed, when it settled or its forward axis is known to REFILTER_SIGMA_DEG, and it
    differs from the one the filter started with by the live filter's rule for taking an estimate (REOPEN_DEG and
    three of its sigmas) on the forward axis or the roll; else None."""
    if engine.alignment is None:
        return None
    est = engine.alignment.estimate()
    forward_sigma = max(est.sigma_deg[1], est.sigma_deg[2])
    if not (est.state == SETTLED or forward_sigma <= REFILTER_SIGMA_DEG):
        return None
    turned = forward_axis_turned(started_with, est)
    rolled = (est.sigma_deg[0] <= REFILTER_SIGMA_DEG
              and abs(est.rpy_deg[0] - started_with[0]) >= max(REOPEN_DEG, 3.0 * est.sigma_deg[0]))
    return est if turned or rolled else None


def run_filter(paths: list[Path], params: NavParams, smooth: bool = False,
               states: list[dict[str, Any]] | None = None,
               progress: ProgressFn | None = None,
               smoothing: SmoothingReport | None = None, solution: Sequence[SolutionEpoch] = (),
               solution_replaces: bool = True, refilter: bool = False,
               notes: list[str] | None = None,
               skipped: list[str] | None = None) -> tuple[NavEngine, list[TrajectoryRow]]:
    """Run the engine over the files; returns it and its rows (smoothed when asked). With ``states``, a
    ``/nav/state`` record is appended to it for every second of drive; ``progress`` hears how far it got;
    ``smoothing`` hears where the backward pass kept the forward solution; ``solution``: a post-processed
    solution's epochs fused (``solution_replaces``: instead of the receiver's positions).

    ``refilter``: when the drive showed a mounting other than the one configured (:func:`mounting_found`), filter
    it again from the start with that mounting. The live filter can only take the mounting once the drive has
    shown it, and then relearns its attitude and offsets (tens of seconds); whatever comes first (a street canyon
    a minute in) meets a filter still converging. At the office the whole drive is there: the second pass starts
    with the mounting, as the daemon's next start does with the one it saved. ``notes`` hears a line saying so;
    ``skipped``, a line per topic whose messages were not the logger's records (skipped, counted)."""
    engine = _one_pass(paths, params, states, progress, solution, solution_replaces, notes, skipped)
    found = mounting_found(engine, params.mounting_rpy_deg) if refilter else None
    if found is not None:
        rpy = tuple(found.rpy_deg)
        line = ""
        if engine.mode == "17":  # the mounting is the constraints' business: the 15-state mode has none
            rpy, line = _boresight(paths, params, rpy, solution, solution_replaces)
        again = dataclasses.replace(params, mounting_rpy_deg=tuple(round(a, 3) for a in rpy))
        if states is not None:
            states.clear()
        if notes is not None:
            r, p_, y = found.rpy_deg
            shown = "settled" if found.state == SETTLED else "the forward axis; the roll is not shown yet"
            configured = " / ".join(f"{a:g}" for a in params.mounting_rpy_deg)
            notes.append(f"the drive showed the IMU mounted at {r:.1f} / {p_:.1f} / {y:.1f} deg ({shown}; configured "
                         f"{configured}){line}: filtered again from the start with it")
        engine = _one_pass(paths, again, states, progress, solution, solution_replaces)
    rows = engine.rows
    if smooth and engine.mode != "gnss" and engine.ekf is not None and engine.epochs:
        from logger.nav.smoother import smooth_rows  # only a smoothed replay needs the backward pass

        engine.close_epochs()
        rows = smooth_rows(rows, engine.epochs, engine.ekf.p, smoothing)
    return engine, rows


def _boresight(paths: list[Path], params: NavParams, rpy: tuple[float, ...], solution: Sequence[SolutionEpoch],
               solution_replaces: bool) -> tuple[tuple[float, ...], str]:
    """The mounting ``rpy`` refined by the side slip and climb of a pass without the car's constraints
    (:mod:`logger.nav.boresight`), and a note's words on it; ``rpy`` itself where that pass does not show them."""
    plain = dataclasses.replace(params, mode="15", mounting_rpy_deg=rpy, mount_align=False)
    r = boresight.residual(_one_pass(paths, plain, None, None, solution, solution_replaces).rows)
    if r is None:
        return rpy, ", not refined (a GNSS + IMU pass had no solution at speed)"
    if not r.usable():
        return rpy, (f", not refined (a GNSS + IMU pass's side slip {r.slip_deg:+.2f} and climb {r.climb_deg:+.2f} deg "
                     f"over {r.moving_s:.0f} s at speed with fixes: {boresight.MIN_MOVING_S:g} s and within "
                     f"{boresight.MAX_RESIDUAL_DEG:g} deg are needed)")
    refined = boresight.refined(rpy, r)
    return refined, (f", refined to {refined[0]:.2f} / {refined[1]:.2f} / {refined[2]:.2f} deg by a GNSS + IMU pass's "
                     f"side slip {r.slip_deg:+.2f} +- {r.slip_se_deg:.2f} and climb {r.climb_deg:+.2f} +- "
                     f"{r.climb_se_deg:.2f} deg over {r.moving_s:.0f} s at speed with fixes")


# What feeding a message raises when it is not a record of its topic (a missing field, a value of another type, a
# number JSON holds and a float does not), and what the filter raises when it fails (math's domain errors, numpy's
# LinAlgError: a ValueError in numpy 2, not in Debian 12's 1.24, named for it): record_fault tells which.
_FEEDING_FAILED = (KeyError, TypeError, ValueError, IndexError, OverflowError, np.linalg.LinAlgError)


class FilterFailed(RuntimeError):
    """The filter raised on records :func:`record_fault` finds nothing wrong with: not skipped as a foreign file's
    messages are. Most likely a defect of the filter; a file of well-formed but implausible values (accelerations
    of 1000 g) could end here too, which is why the message asks for the file."""

    def __init__(self, topic: str, msg: dict[str, Any], exc: Exception) -> None:
        t = msg.get("t_sync_ns")
        t = t[0] if isinstance(t, list) and t else t
        super().__init__(f"the filter failed on a well-formed {topic} record (t_sync_ns {t}): {type(exc).__name__}: "
                         f"{exc}; nothing found wrong with the record: please report it with the file")


def _one_pass(paths: list[Path], params: NavParams, states: list[dict[str, Any]] | None,
              progress: ProgressFn | None, solution: Sequence[SolutionEpoch],
              solution_replaces: bool, notes: list[str] | None = None,
              skipped: list[str] | None = None) -> NavEngine:
    """One forward pass of the engine over the files (``states`` filled as :func:`run_filter` says), with the live
    filter's re-run of its first minutes (:mod:`logger.recording.nav_rerun`); ``notes`` hears of it, ``skipped``
    of the messages of the filter's topics that were not the logger's records (a line per topic)."""
    def make_engine(p: NavParams) -> NavEngine:
        engine = NavEngine(p, record=True)
        if solution:
            engine.use_solution(solution, solution_replaces)
        return engine

    rerun = NavRerun(params, make_engine)  # as live: the first minutes again once the drive shows the mounting
    next_state = 0
    # FIFO reads that go on from one another with nothing between them go in as one run, as the live navigator
    # takes a wake-up's (a 200 Hz IMU's reads of ten samples then go in as the ~40 between two measurements, and
    # are integrated in steps of integration_hz as a 1 kHz IMU's are); a read that does not goes alone.
    run: list[dict[str, Any]] = []

    def note_state(topic: str, msg: dict[str, Any]) -> None:
        """A /nav/state record a second, after the sample fed last (a sample's own record, or a block's last)."""
        nonlocal next_state
        engine = rerun.engine
        if states is None or engine.state is None:
            return
        t, mono = ((msg["t_sync_ns"], msg["t_mono_ns"]) if topic == IMU
                   else (msg["t_sync_ns"][-1], msg["t_mono_ns"][-1]))
        if t >= next_state:
            next_state = next_whole_second(t)
            states.append(nav_state_record(engine, t, mono))

    # Messages of the filter's topics that are not the logger's records (another tool's file with an /imu of other
    # fields): skipped and counted per topic, with what was wrong with the first, instead of a traceback.
    foreign: dict[str, tuple[int, str]] = {}
    # The record each topic's last skipped message is of: a FIFO read cut in pieces at other topics' messages is one
    # message of the file, counted once however many of its pieces are skipped (its pieces come one after another).
    last_skipped: dict[str, dict[str, Any]] = {}

    def skip(topic: str, exc: Exception, msgs: Sequence[Any]) -> None:
        if all(record_fault(topic, m) is None for m in msgs):  # the logger's own records: the filter failed
            raise FilterFailed(topic, msgs[-1], exc) from exc
        n, why = foreign.get(topic, (0, f"no field {exc}" if isinstance(exc, KeyError) else str(exc)))
        for m in msgs:
            record = record_of(m)
            if record is not last_skipped.get(topic):
                last_skipped[topic] = record
                n += 1
        foreign[topic] = (n, why)

    def feed_reads(reads: list[dict[str, Any]]) -> None:
        try:
            rerun.feed_reads(reads)
        except _FEEDING_FAILED as exc:
            if len(reads) > 1 and any(record_fault(IMU_BATCH, m) for m in reads):
                # records.read_columns refused the run before the filter took any of it: its reads one by one
                for m in reads:
                    feed_reads([m])
            else:
                skip(IMU_BATCH, exc, reads)
        else:
            note_state(IMU_BATCH, reads[-1])

    def feed_run() -> None:
        if run:
            feed_reads(run)
            run.clear()

    for topic, msg in read_drive(paths, progress=progress, runs=True):
        try:
            if topic == IMU_BATCH and follows_on(msg, run[-1]["t_sync_ns"][-1] if run else rerun.engine.t_last_ns):
                run.append(msg)
                continue
            feed_run()
            rerun.feed(topic, msg)
            if topic in (IMU, IMU_BATCH):
                note_state(topic, msg)
        except _FEEDING_FAILED as exc:
            skip(topic, exc, (msg,))
    feed_run()
    if notes is not None and rerun.note():
        notes.append(rerun.note())
    if skipped is not None:
        skipped += [f"{plural(n, f'{topic} message')} skipped: not the logger's records ({why})"
                    for topic, (n, why) in foreign.items()]
    return rerun.engine


@dataclass
class Columns:
    """The trajectory by column, in the units of ``trajectory.csv``: what both files are written from. The numbers
    are the filter's own (Python or numpy floats) where the file has them as they are, the angles in degrees."""

    t_ns: Sequence[int]
    t_mono_ns: Sequence[int]
    lat_deg: Sequence[float]
    lon_deg: Sequence[float]
    h_m: Sequence[float]
    vn: Sequence[float]
    ve: Sequence[float]
    vd: Sequence[float]
    roll_deg: Sequence[float]
    pitch_deg: Sequence[float]
    yaw_deg: Sequence[float]
    sn: Sequence[float]
    se: Sequence[float]
    sd: Sequence[float]

    def __len__(self) -> int:
        return len(self.t_ns)

    def table(self) -> list[Sequence[Any]]:
        """The columns in ``CSV_HEADER`` order."""
        return [self.t_ns, self.t_mono_ns, self.lat_deg, self.lon_deg, self.h_m, self.vn, self.ve, self.vd,
                self.roll_deg, self.pitch_deg, self.yaw_deg, self.sn, self.se, self.sd]


def columns(rows: Sequence[TrajectoryRow]) -> Columns:
    """The rows as columns, the attitudes of all rows at a time. The values are those a row at a time gives
    (``math.degrees``, ``euler_from_dcm(dcm_from_quat(q))``) to the bit: the same operations in the same order,
    the matrix's arithmetic elementwise in numpy, the arc tangents and degrees ``math``'s own."""
    if not rows:
        return Columns(*(() for _ in CSV_HEADER))
    t, t_mono, lat, lon, h, vn, ve, vd, q, sig, _ = zip(*rows, strict=True)
    qa = np.fromiter(itertools.chain.from_iterable(q), dtype=float, count=4 * len(q)).reshape(-1, 4)
    c = dcm_from_quat((qa[:, 0], qa[:, 1], qa[:, 2], qa[:, 3]))  # 3 x 3 x rows
    c21, c22 = c[2, 1].tolist(), c[2, 2].tolist()
    roll = map(math.atan2, c21, c22)
    pitch = map(math.atan2, (-c[2, 0]).tolist(), map(math.hypot, c21, c22))
    yaw = map(math.atan2, c[1, 0].tolist(), c[0, 0].tolist())
    sn, se, sd = zip(*sig, strict=True)
    deg = math.degrees
    return Columns(t, t_mono, list(map(deg, lat)), list(map(deg, lon)), h, vn, ve, vd, list(map(deg, roll)),
                   list(map(deg, pitch)), list(map(deg, yaw)), sn, se, sd)


def write_csv(path: Path, rows: Sequence[TrajectoryRow]) -> None:
    """``trajectory.csv``: the header, then a line per row, a block of rows at a time made columns, formatted and
    written."""
    with written_whole(path, "w", newline="") as f:
        f.write(",".join(CSV_HEADER) + "\r\n")
        for i in range(0, len(rows), BLOCK_ROWS):
            block = list(zip(*columns(rows[i:i + BLOCK_ROWS]).table(), strict=True))
            f.write((CSV_LINE * len(block)) % tuple(itertools.chain.from_iterable(block)))


def fix_rows(t_ns: Sequence[int], hz: float) -> list[int]:
    """The rows ``/nav/fix`` is written for at ``hz``: the first row, then the first row at (or a hair before) each
    tick of a grid of the period from it (:func:`logger.recording.intervals.next_due_ns`), so that ``hz`` asked is
    ``hz`` written. "The first row at least a period after the last one written" on 20 Hz rows 50 ms +- us apart
    passed over a row a microsecond short of the period, one interval in six 0.25 s: 4.83 Hz for 5. Rows sparser
    than the grid (GNSS-only, an outage) are each written. ``hz`` 0 (or less): every row."""
    if hz <= 0.0:
        return list(range(len(t_ns)))
    if not t_ns:
        return []
    period_ns = round(1e9 / hz)
    anchor = t_ns[0]
    keep: list[int] = []
    due = -math.inf
    for i, t in enumerate(t_ns):
        if t >= due:
            keep.append(i)
            due = next_due_ns(t, anchor, period_ns)
    return keep


class _JsonNumber(float):
    """A float whose ``%r`` is what JSON writes for it (``NaN``, ``Infinity``, as ``json.dumps`` does)."""

    def __repr__(self) -> str:
        return json.dumps(float(self))


def nav_fix_json(cols: Columns, source: str, mode: str) -> list[bytes]:
    """The ``/nav/fix`` message of each row of ``cols`` as JSON bytes: the bytes of
    ``json.dumps(nav_fix_record(...))`` for that row. The numbers are derived (unknown sigmas, the covariance)
    for all rows at a time, then each message is one fill of the template."""
    if not len(cols):
        return []
    sig = np.array([cols.sn, cols.se, cols.sd], dtype=float)
    sn, se, sd = np.where(np.isfinite(sig), sig, SIGMA_UNKNOWN_M)  # nav_fix_record's rule
    numbers = np.array([np.asarray(cols.lat_deg, dtype=float), np.asarray(cols.lon_deg, dtype=float),
                        np.asarray(cols.h_m, dtype=float), se * se, sn * sn, sd * sd,
                        np.asarray(cols.vn, dtype=float), np.asarray(cols.ve, dtype=float),
                        np.asarray(cols.vd, dtype=float), np.asarray(cols.roll_deg, dtype=float),
                        np.asarray(cols.pitch_deg, dtype=float), np.asarray(cols.yaw_deg, dtype=float), sn, se, sd])
    finite = np.isfinite(numbers).all(axis=0).tolist()
    t = [int(v) for v in cols.t_ns]
    times = zip([int(v) for v in cols.t_mono_ns], t, [v // 1_000_000_000 for v in t], [v % 1_000_000_000 for v in t],
                strict=True)
    names = (json.dumps(source), json.dumps(mode))
    out = []
    for ok, stamp, values in zip(finite, times, zip(*numbers.tolist(), strict=True), strict=True):
        if not ok:  # a filter gone astray: NaN and Infinity, as json.dumps writes them
            values = tuple(map(_JsonNumber, values))
        out.append((NAV_FIX_JSON % (stamp + values + names)).encode())
    return out


def write_mcap(path: Path, rows: Sequence[TrajectoryRow], engine: NavEngine, states: list[dict[str, Any]],
               fix_hz: float | None = None, source_run: str | None = None) -> int:
    """``trajectory.mcap``: ``/nav/fix`` at ``fix_hz`` (None: the engine's ``publish_hz``, the live rate; 0: every
    row) and the ``/nav/state`` records. ``source_run``: the run id of the drive replayed, recorded first (the
    drive reader refuses the file beside another drive's). Returns how many ``/nav/fix`` messages it wrote."""
    hz = engine.params.publish_hz if fix_hz is None else fix_hz
    keep = fix_rows([row[0] for row in rows], hz)
    source = "gnss" if engine.mode == "gnss" else f"ins {engine.mode}-state"
    with written_whole(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="", library=REPLAY_LIBRARY)
        if source_run:
            w.add_metadata(REPLAY_OF_METADATA, {"run": source_run})
        ids = {}
        for topic in (NAV_FIX, NAV_STATE):
            spec = TOPICS[topic]
            sid = w.register_schema(spec.schema_name, "jsonschema", spec.schema_data)
            ids[topic] = w.register_channel(topic, "json", sid)
        fix_id, add = ids[NAV_FIX], w.add_message
        for i in range(0, len(keep), BLOCK_ROWS):
            cols = columns([rows[k] for k in keep[i:i + BLOCK_ROWS]])
            for t, t_mono, data in zip(cols.t_ns, cols.t_mono_ns, nav_fix_json(cols, source, engine.mode),
                                       strict=True):
                add(fix_id, log_time=t, publish_time=t_mono, data=data)
        for st in states:
            add(ids[NAV_STATE], log_time=st["t_sync_ns"], publish_time=st["t_mono_ns"], data=json.dumps(st).encode())
        w.finish()
    return len(keep)
