"""The filter's inputs kept from its start, to filter them again once the drive shows how the IMU is mounted.

With the board mounted at an angle it was not told, the filter drives its first minute on the wrong mounting:
the mount alignment shows the car's forward axis about half a minute in, the engine takes it and reopens its
attitude and offsets (:meth:`NavEngine.remount`), and relearns them in whatever comes next, a street canyon a
minute in on the simulated urban drive. At the office ``logger replay`` filters the whole drive again with the
mounting it showed; live, the same can be done for the first minutes: the inputs the filter took since it started
are still at hand, so at the first remount that reopens, a new engine starting with that mounting takes them all
again, as if the daemon had been started with it, and goes on from there. On the recorded urban drive with the
board at (5, -4, 30) deg this took seed 2's east RMSE while moving from 1.00 to about 0.4 m (configured: 0.37).

What is kept is bounded (:data:`TAPE_S` of drive from the tape's start, :data:`TAPE_SAMPLES` IMU samples, stored
as arrays, about 1.5 MB at the bound): the tape starts with the first input, and while the car has not moved yet
only the last :data:`STILL_KEEP_S` of it are kept, so a long wait before driving does not use up the tape (a new
engine started from there is one started then, at a standstill). When the tape is full before the first reopening
(a 1 kHz IMU fills it in 24 s), or once it has been used, nothing more is kept and the filter goes on as before.
One re-run per engine: the new engine's own remounts are refinements of a mounting it started near.
"""

from __future__ import annotations

import logging
import math
from array import array
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

from logger.nav.engine import NavEngine
from logger.nav.params import NavParams
from logger.recording.records import feed_reads, nav_feeder
from logger.recording.topics import IMU, IMU_BATCH

log = logging.getLogger(__name__)

NS = 1_000_000_000
TAPE_S = 240.0  # drive kept from the tape's start (a reopening comes about 30-40 s after the car first moves)
TAPE_SAMPLES = 24_000  # IMU samples kept at most: 240 s at 100 Hz, 24 s at 1 kHz
STILL_KEEP_S = 30.0  # of a standstill before the car first moves, the last this long is kept
MOVING_MPS = 1.0  # the filter's horizontal speed above which the car has moved

_INT_COLUMNS = ("t_sync_ns", "t_mono_ns")
_FLOAT_COLUMNS = ("accel_x_mps2", "accel_y_mps2", "accel_z_mps2", "gyro_x_rps", "gyro_y_rps", "gyro_z_rps")
_SCALARS = ("temp_degc", "period_s", "lost")

Entry = tuple[str, Any, int, int]  # topic (or "" for a run of reads), record(s), first time, samples


def _compact(m: dict[str, Any]) -> dict[str, Any]:
    """A FIFO read as the filter takes it, its columns as arrays (8 bytes a value, not a float object's 24)."""
    out: dict[str, Any] = {k: array("q", m[k]) for k in _INT_COLUMNS}
    out.update({k: array("d", m[k]) for k in _FLOAT_COLUMNS})
    out.update({k: m[k] for k in _SCALARS if k in m})
    return out


def _first_ns(topic: str, m: Any) -> int:
    if topic == "":
        return int(m[0]["t_sync_ns"][0])
    t = m["t_sync_ns"]
    return int(t[0]) if topic == IMU_BATCH else int(t)


def _samples(topic: str, m: Any) -> int:
    if topic == "":
        return sum(len(r["t_sync_ns"]) for r in m)
    return len(m["t_sync_ns"]) if topic == IMU_BATCH else 1 if topic == IMU else 0


class NavRerun:
    """An engine fed record by record, which is replaced once by one filtering its inputs again with the mounting
    of its first reopening remount (see the module's docstring). ``engine`` is the one in use."""

    def __init__(self, params: NavParams, make_engine: Callable[[NavParams], NavEngine],
                 tape_s: float = TAPE_S, tape_samples: int = TAPE_SAMPLES) -> None:
        self.params = params
        self.make_engine = make_engine
        self.engine = make_engine(params)
        self._feed = nav_feeder(self.engine)
        self.tape_s, self.tape_samples = tape_s, tape_samples
        keep = params.mount_align and params.mode != "gnss"
        self._tape: deque[Entry] | None = deque() if keep else None
        self._samples = 0
        self._moved = False
        self.rerun_mount: tuple[float, float, float] | None = None  # the mounting the inputs were filtered again with
        self.rerun_at_s: float | None = None  # how far into the tape that mounting was found, s
        self.rerun_inputs = 0  # records filtered again

    # ---- feeding ----------------------------------------------------------------------------------------
    def feed(self, topic: str, msg: dict[str, Any]) -> None:
        """One record, as :func:`nav_feeder` takes it."""
        self._feed[topic](msg)
        if self._tape is not None:
            self._keep(topic, _compact(msg) if topic == IMU_BATCH else msg)

    def feed_reads(self, msgs: Sequence[dict[str, Any]]) -> None:
        """A run of FIFO reads that follow one another, as :func:`feed_reads` takes it."""
        feed_reads(self.engine, msgs)
        if self._tape is not None:
            self._keep("", [_compact(m) for m in msgs])

    # ---- the tape ---------------------------------------------------------------------------------------
    @property
    def kept(self) -> tuple[float, int] | None:
        """The span (s, from the first input kept to the last) and the IMU samples on the tape; None once it is
        given up or used."""
        tape = self._tape
        if tape is None:
            return None
        return ((tape[-1][2] - tape[0][2]) / NS if tape else 0.0), self._samples

    def _keep(self, topic: str, what: Any) -> None:
        tape = self._tape
        assert tape is not None
        n = _samples(topic, what)
        t = _first_ns(topic, what)
        tape.append((topic, what, t, n))
        self._samples += n
        eng = self.engine
        if eng.mount_reopened_ns is not None:
            self._rerun()
            return
        if not self._moved:
            s = eng.state
            self._moved = s is not None and math.hypot(s.vn, s.ve) > MOVING_MPS
            while not self._moved and len(tape) > 1 and t - tape[0][2] > STILL_KEEP_S * NS:
                self._samples -= tape.popleft()[3]
        if self._samples > self.tape_samples or t - tape[0][2] > self.tape_s * NS:
            self._tape = None  # full before the drive showed another mounting: the filter goes on as it is

    def _rerun(self) -> None:
        """A new engine, starting with the mounting the old one just took, fed everything kept."""
        tape, old = self._tape, self.engine
        assert tape is not None
        self._tape = None
        mount = tuple(round(float(a), 3) for a in old.mount_applied)
        engine = self.make_engine(replace(self.params, mounting_rpy_deg=mount))
        feed = nav_feeder(engine)
        for topic, what, _t, _n in tape:
            if topic == "":
                feed_reads(engine, what)
            else:
                feed[topic](what)
        self.rerun_mount = (mount[0], mount[1], mount[2])
        self.rerun_at_s = ((old.mount_reopened_ns or 0) - tape[0][2]) / NS
        self.rerun_inputs = len(tape)
        self.engine, self._feed = engine, feed
        log.info("the drive showed the IMU mounted at %.1f / %.1f / %.1f deg %.0f s in: filtered its %d inputs "
                 "again from the start with it", *mount, self.rerun_at_s, len(tape))

    def note(self) -> str:
        """A line saying what the re-run did, or ""."""
        if self.rerun_mount is None:
            return ""
        r, p, y = self.rerun_mount
        return (f"the drive showed the IMU mounted at {r:.1f} / {p:.1f} / {y:.1f} deg {self.rerun_at_s:.0f} s in: "
                "the filter took its inputs again from the start with it")
