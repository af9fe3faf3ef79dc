"""The filter's inputs kept from its start, to filter them again once the drive shows how the IMU is mounted.

With the board mounted at an angle it was not told, the filter drives its first minute on the wrong mounting:
the mount alignment shows the car's forward axis about half a minute in, the engine takes it and reopens its
attitude and offsets (:meth:`NavEngine.remount`), and relearns them in whatever comes next, a street canyon a
minute in on the simulated urban drive. At the office ``logger replay`` filters the whole drive again with the
mounting it showed; live, the same can be done for the first minutes: the inputs the filter took since it started
are still at hand, so at the first remount that reopens, a new engine starting with that mounting takes them all
again, as if the daemon had been started with it, and goes on from there. On the recorded urban drive with the
board at (5, -4, 30) deg this took seed 2's east RMSE while moving from 1.00 to about 0.4 m (configured: 0.37).

What is kept is bounded: :data:`TAPE_S` of drive from the tape's start and :data:`TAPE_BYTES` as estimated per
input (:func:`_cost`; the FIFO reads' samples end to end in eight arrays, every other record cut to what the filter
reads of it). The tape starts with the first input;
while the car is known to stand (an OBD speed or a GNSS speed of nothing, or the stop detector) and has not moved
yet (an OBD, GNSS or filter speed over :data:`MOVING_MPS`), only the last :data:`STILL_KEEP_S` of it are kept, so a
long wait before driving does not use up the tape, and a new engine started from there is one started then, at a
standstill; while nothing says so (no speed yet, an IMU that does not look still) nothing is cut. The tape is let
go when it is full before the first reopening (at 20 Hz 180 s take about 0.9 MB), at once when its first
:data:`RATE_SPAN_S` show that :data:`USEFUL_S` of drive would not fit (an IMU faster than about 700 Hz: no re-run,
no memory spent on it), when the alignment has shown the car's forward axis within REOPEN_DEG of the
mounting in use (a board mounted as configured, or as the last drive saved it: no reopening is coming), or once it
has been used; the filter then goes on as before. The forward axis the first re-run takes is the alignment's first
showing of it, from half a minute of driving: on the simulated outage and tunnel drives 1.0 deg from the truth,
where a minute later the estimate holds within 0.3 deg of 0.1-0.4 deg from it (its sigma, 2.8 deg, says far less, so
the engine's own rule, three sigmas, never takes it). The tape is therefore kept after the first re-run while the
alignment shows the forward axis only, and a second re-run takes the forward axis once it has held still for 50 s
(:data:`REFINE_LOOKS` looks :data:`REFINE_LOOK_S` apart, or CONFIRM_EVERY inputs where they come more slowly, within
:data:`REFINE_HOLD_DEG`) at least :data:`REFINE_MIN_DEG` from the first's: the outage-60s seed 2 drive's east RMSE
while moving went from 1.26 to 1.05 times the configured mounting's, tunnel-130s seed 2's from 1.33 to 0.84 times
(docs/nav.md). Taking the same forward axis as a remount without re-running made those drives worse (the offsets
learnt on the old axis stay), and with turns the roll too is shown, and a street canyon's velocities can hold the
estimate still but 3 deg off (the urban seed 2 drive): there the tape is let go as before. The tape's bounds stay: a
forward axis that holds still only after 180 s (tunnel-130s seed 1) gets no second re-run, nor does an IMU whose
samples fill the 3 MB sooner (at 500 Hz about 85 s: the first re-run only). At most two re-runs; the new engine's
other remounts are refinements of a mounting it started near. In the daemon the new engine is built outside the
navigator's lock (``deferred``), so ``logger status`` reads the engine in use while it runs (seconds on the board),
and only the swap takes the lock; meanwhile the navigator's queue holds what arrives. What the first engine
published before the swap (``/nav/fix``, ``/nav/state``, replay's states) stays as it was: it is what the daemon
said then.
"""

from __future__ import annotations

import logging
import math
from array import array
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

from logger.nav.engine import REOPEN_DEG, NavEngine
from logger.nav.mounting import FORWARD, LEARNING, SETTLED, USABLE_SIGMA_DEG, forward_axis_deg
from logger.nav.params import NavParams
from logger.recording.records import NAV_INPUT_KEYS, feed_reads, nav_feeder, unplaced
from logger.recording.topics import GNSS_FIX, IMU, IMU_BATCH, OBD_SPEED

log = logging.getLogger(__name__)

NS = 1_000_000_000
TAPE_S = 180.0  # drive kept from the tape's start (the simulated drives' reopening came 36 s after their start)
TAPE_BYTES = 3_000_000  # memory the kept inputs may take, as estimated by _cost
STILL_KEEP_S = 30.0  # of a standstill before the car first moves, the last this long is kept
MOVING_MPS = 1.0  # a speed (OBD, GNSS or the filter's) above which the car has moved
STANDING_MPS = 0.3  # an OBD or GNSS speed below which the car stands, for the tape (stops.GNSS_STANDING_MPS
# is the stricter bound a fix must keep to teach the stop detector)
CONFIRM_EVERY = 50  # inputs between two looks at whether the alignment confirmed the mounting in use
# The tape must hold this much drive to be of use (a standstill's last STILL_KEEP_S and the half minute of driving
# the forward axis takes to show): once RATE_SPAN_S of it shows that it would not fit TAPE_BYTES, it is let go
# at once rather than at the budget (about 70 KB a second at 1 kHz, 38 at 500 Hz, 28 at 100 Hz with fixes at
# 10 Hz, 5 at 20 Hz).
USEFUL_S = 60.0
RATE_SPAN_S = 2.0  # at 1 kHz two seconds of tape are 0.12 MB
# After the first re-run, while the alignment still shows the forward axis only (no turns yet, as on the simulated
# outage and tunnel drives): the forward axis it has held for REFINE_LOOKS looks REFINE_LOOK_S apart, each within
# REFINE_HOLD_DEG of the newest, and REFINE_MIN_DEG or more from the one the re-run took, is taken by a second.
REFINE_LOOKS = 6
REFINE_LOOK_S = 10.0
REFINE_HOLD_DEG = 0.3
REFINE_MIN_DEG = 0.5

_COLUMNS = ("t_sync_ns", "t_mono_ns", "accel_x_mps2", "accel_y_mps2", "accel_z_mps2", "gyro_x_rps", "gyro_y_rps",
            "gyro_z_rps")
# Bytes an input holds on the tape, measured on CPython 3.11 (64-bit; a 32-bit board's are smaller): a FIFO
# sample's eight columns; the slim copies of an /imu sample, a GNSS fix and any other record (what the filter
# reads of them). A FIFO read's place in the columns (about 100 bytes) is not counted, so that the budget says
# the same of a drive however its reads were cut: live (the daemon's reads, merged into runs) and in replay
# (blocks cut at the other records). Deep size on the recorded urban drive's first 36 s at 20 Hz: 0.18 MB (the
# estimate 0.17), about 5 KB a second.
SAMPLE_BYTES, IMU_BYTES, FIX_BYTES, RECORD_BYTES = 64, 600, 2000, 400

Read = tuple[int, int, Any]  # a FIFO read's first and end index in the columns, its die temperature
Entry = tuple[str, Any, int, int]  # topic (or "" for a run of reads), record(s) or Read(s), first time, bytes


class _Columns:
    """The kept FIFO reads' samples end to end, 8 bytes a value, and the reads as ranges of them: a read's
    dict of eight short arrays took 1.8 KB besides its samples, most of the tape at a fast IMU."""

    def __init__(self) -> None:
        self.cols = [array("q"), array("q")] + [array("d") for _ in range(6)]
        self.base = 0  # the index of the first sample still held

    def add(self, m: dict[str, Any]) -> Read:
        start = self.base + len(self.cols[0])
        for col, key in zip(self.cols, _COLUMNS, strict=True):
            col.extend(m[key])
        return start, start + len(m["t_sync_ns"]), m.get("temp_degc")

    def record(self, read: Read) -> dict[str, Any]:
        """The read as the filter takes it (``feed_reads``)."""
        lo, hi = read[0] - self.base, read[1] - self.base
        out: dict[str, Any] = {key: col[lo:hi] for key, col in zip(_COLUMNS, self.cols, strict=True)}
        out["temp_degc"] = read[2]
        return out

    def forget_before(self, index: int) -> None:
        """Samples before ``index`` are no longer needed (the tape's front was cut)."""
        dead = index - self.base
        if dead > 0 and dead >= len(self.cols[0]) // 2:  # now and then: each cut moves what stays
            for col in self.cols:
                del col[:dead]
            self.base = index


def _slim(topic: str, m: dict[str, Any]) -> dict[str, Any]:
    """A record with only what the filter reads of it (:data:`NAV_INPUT_KEYS`)."""
    return {k: m[k] for k in NAV_INPUT_KEYS[topic] if k in m}


def _cost(topic: str, what: Any) -> int:
    """Bytes of a kept input as the budget counts them."""
    if topic == "":
        return sum(SAMPLE_BYTES * (r[1] - r[0]) for r in what)
    if topic == IMU_BATCH:
        return SAMPLE_BYTES * (what[1] - what[0])
    return IMU_BYTES if topic == IMU else FIX_BYTES if topic == GNSS_FIX else RECORD_BYTES


def _speed(topic: str, m: Any) -> float | None:
    """The car's speed an OBD or GNSS record says (m/s), or None."""
    if topic == OBD_SPEED:
        v = m.get("speed_mps")
        return float(v) if v is not None else None
    if topic == GNSS_FIX and m.get("fix_ok"):
        v = m.get("vel_ned_mps")
        if v and v[0] is not None and v[1] is not None:
            return math.hypot(v[0], v[1])
    return None


class NavRerun:
    """An engine fed record by record, which is replaced by one filtering its inputs again with the mounting of its
    first reopening remount, and perhaps once more with the forward axis held still after it (see the module's
    docstring). ``engine`` is the one in use. The re-run happens
    inside the feeding call that found the mounting, or, ``deferred``, when the caller asks (:attr:`due`)."""

    def __init__(self, params: NavParams, make_engine: Callable[[NavParams], NavEngine],
                 tape_s: float = TAPE_S, tape_bytes: int = TAPE_BYTES, deferred: bool = False) -> None:
        self.params = params
        # deferred: the re-run waits for the caller (:meth:`build` then :meth:`adopt`), which can run it without
        # holding what guards the engine in use: the daemon's navigator, whose status reads that engine meanwhile.
        self.deferred = deferred
        self._due: tuple[tuple[float, float, float], int] | None = None  # mounting and time of a re-run to come
        self.make_engine = make_engine
        self.engine = make_engine(params)
        self._feed = nav_feeder(self.engine)
        self.tape_s, self.tape_bytes = tape_s, tape_bytes
        keep = params.mount_align and params.mode != "gnss"
        self._tape: deque[Entry] | None = deque() if keep else None
        self._columns = _Columns()
        self._bytes = 0
        self._moved = False
        self._standing = False  # the latest evidence says the car stands
        self._heard_speed = False  # an OBD or GNSS speed came: it, not the IMU's stillness, says whether
        self._since_look = 0
        self._refining = False  # after the first re-run: the tape kept for a second (the forward axis held still)
        self._looks: deque[tuple[int, tuple[float, float, float]]] = deque(maxlen=REFINE_LOOKS)
        self.reruns: list[tuple[tuple[float, float, float], float]] = []  # (mounting, s into the tape) of each
        self.unplaced = 0  # records left out: stamped before GNSS time was known, on a clock with no bound

    # ---- feeding ----------------------------------------------------------------------------------------
    def feed(self, topic: str, msg: dict[str, Any]) -> None:
        """One record, as :func:`nav_feeder` takes it; one whose stamp has no bound is left out (:func:`unplaced`)."""
        if unplaced(msg):
            self.unplaced += 1
            return
        thinned = self.engine.counters.gnss_thinned
        self._feed[topic](msg)
        if self._tape is not None:
            if self.engine.counters.gnss_thinned != thinned:
                return  # a fast receiver's fix the filter left out (gnss_rate.py): a re-run leaves it out too
            if topic == IMU_BATCH:
                t = msg["t_sync_ns"]
                self._keep(topic, self._columns.add(msg), int(t[0]), int(t[-1]))
            else:
                self._keep(topic, _slim(topic, msg), int(msg["t_sync_ns"]))

    def feed_reads(self, msgs: Sequence[dict[str, Any]]) -> None:
        """A run of FIFO reads that follow one another, as :func:`feed_reads` takes it (without unplaced ones)."""
        kept = [m for m in msgs if not unplaced(m)]
        self.unplaced += len(msgs) - len(kept)
        if not kept:
            return
        msgs = kept
        feed_reads(self.engine, msgs)
        if self._tape is not None and msgs:
            self._keep("", [self._columns.add(m) for m in msgs], int(msgs[0]["t_sync_ns"][0]),
                       int(msgs[-1]["t_sync_ns"][-1]))

    # ---- the tape ---------------------------------------------------------------------------------------
    @property
    def kept(self) -> tuple[float, int] | None:
        """The span (s, from the first input kept to the last) and the estimated bytes on the tape; None once it
        is given up or no re-run can come any more."""
        tape = self._tape
        if tape is None:
            return None
        return ((tape[-1][2] - tape[0][2]) / NS if tape else 0.0), self._bytes

    def _keep(self, topic: str, what: Any, t: int, t_end: int | None = None) -> None:
        """An input onto the tape at ``t`` (a read's or a run's first sample); ``t_end``: its last sample, which
        the span its bytes are counted over reaches (a run of a whole wake-up's reads is a second of them)."""
        tape = self._tape
        assert tape is not None
        cost = _cost(topic, what)
        tape.append((topic, what, t, cost))
        self._bytes += cost
        if self._due is not None:
            return  # found, waiting for build and adopt: what comes meanwhile is kept for them too
        eng = self.engine
        # The first re-run comes with the engine's first reopening. After it, the engine in use is the re-run's,
        # which may reopen while it filters the kept inputs again: a remount it makes itself, as live, and no
        # second re-run (that one comes only with the forward axis held still, _refine_look). Taken for one, it
        # re-ran at once, dated before the first, and its line said "forward axis held" of a hold never looked at.
        if eng.mount_reopened_ns is not None and not self.reruns:
            m = eng.mount_applied
            self._due = ((round(float(m[0]), 3), round(float(m[1]), 3), round(float(m[2]), 3)),
                         eng.mount_reopened_ns)
            if not self.deferred:
                self.adopt(self.build())
            return
        if not self._moved:
            self._trim_standstill(topic, what, t)
        self._since_look += 1
        if self._since_look >= CONFIRM_EVERY:
            self._since_look = 0
            if self._refining:
                if self._refine_look(t):
                    return
            elif self._confirmed():
                self._let_go()  # the drive showed the mounting in use: no reopening is coming
                return
        span_s = ((t if t_end is None else t_end) - tape[0][2]) / NS
        if (self._bytes > self.tape_bytes or span_s > self.tape_s
                or (span_s >= RATE_SPAN_S and self._bytes / span_s * USEFUL_S > self.tape_bytes)):
            self._let_go()  # full (or would be) before the drive showed another mounting: the filter goes on

    def _trim_standstill(self, topic: str, what: Any, t: int) -> None:
        """Before the car first moves, of a known standstill only the last STILL_KEEP_S are kept."""
        speed = _speed(topic, what) if topic in (OBD_SPEED, GNSS_FIX) else None
        s = self.engine.state
        if (speed is not None and speed > MOVING_MPS) or (s is not None and math.hypot(s.vn, s.ve) > MOVING_MPS):
            self._moved = True
            return
        if speed is not None:
            self._standing = speed < STANDING_MPS
            self._heard_speed = True
        elif not self._heard_speed and topic in (IMU, IMU_BATCH, ""):
            self._standing = self.engine.stops.still  # no speed has come: the IMU's stillness is all there is
        tape = self._tape
        assert tape is not None
        cut = False
        while self._standing and len(tape) > 1 and t - tape[0][2] > STILL_KEEP_S * NS:
            self._bytes -= tape.popleft()[3]
            cut = True
        if cut:
            self._columns.forget_before(self._first_sample())

    def _let_go(self) -> None:
        self._tape = None
        self._columns = _Columns()
        self._bytes = 0

    def _first_sample(self) -> int:
        """The index of the first FIFO sample the tape still refers to (the columns' end if none)."""
        for topic, what, _t, _c in self._tape or ():
            if topic == IMU_BATCH:
                return int(what[0])
            if topic == "":
                return int(what[0][0])
        return self._columns.base + len(self._columns.cols[0])

    def _confirmed(self) -> bool:
        """Whether the alignment has shown the car's forward axis (to USABLE_SIGMA_DEG, as the engine acts on it)
        within REOPEN_DEG of the mounting in use: the engine's own rule then has no reopening to make."""
        al = self.engine.alignment
        if al is None:
            return False
        est = al.estimate()
        return (max(est.sigma_deg[1], est.sigma_deg[2]) < USABLE_SIGMA_DEG
                and forward_axis_deg(self.engine.mount_applied, est.rpy_deg) < REOPEN_DEG)

    def _refine_look(self, t: int) -> bool:
        """After the first re-run: whether the forward axis has held still long enough, far enough from the one in
        use, for a second (then due), or the alignment has gone past the forward axis alone (the tape let go)."""
        al = self.engine.alignment
        if al is None:
            self._let_go()
            return True
        est = al.estimate()
        if est.state != FORWARD:
            if est.state == LEARNING and not max(est.sigma_deg[1], est.sigma_deg[2]) < USABLE_SIGMA_DEG:
                self._looks.clear()  # not shown at the moment (a fit started again): a hold starts again after it
                return False
            self._let_go()  # the roll is showing (turns), or settled: the engine's own rules take it from here
            return True
        looks = self._looks
        if looks and t - looks[-1][0] < REFINE_LOOK_S * NS:
            return False
        looks.append((t, est.rpy_deg))
        held = all(forward_axis_deg(rpy, est.rpy_deg) <= REFINE_HOLD_DEG for _, rpy in looks)
        if len(looks) == REFINE_LOOKS and held and forward_axis_deg(self.engine.mount_applied,
                                                                    est.rpy_deg) >= REFINE_MIN_DEG:
            r, p, y = est.rpy_deg
            self._due = ((round(float(r), 3), round(float(p), 3), round(float(y), 3)), t)
            if not self.deferred:
                self.adopt(self.build())
            return True
        return False

    @property
    def due(self) -> bool:
        """Whether a re-run is due (the first reopening came, or the forward axis held still after it) and the inputs
        wait to be filtered again (``deferred``)."""
        return self._due is not None and self._tape is not None

    def build(self) -> NavEngine:
        """A new engine, starting with the mounting the re-run is for, fed everything kept. Changes nothing here:
        the engine in use goes on being read (the daemon's status) while this runs."""
        assert self._due is not None and self._tape is not None
        engine = self.make_engine(replace(self.params, mounting_rpy_deg=self._due[0]))
        feed = nav_feeder(engine)
        record = self._columns.record
        for topic, what, _t, _n in self._tape:
            if topic == "":
                feed_reads(engine, [record(r) for r in what])
            elif topic == IMU_BATCH:
                feed[topic](record(what))
            else:
                feed[topic](what)
        return engine

    def adopt(self, engine: NavEngine) -> None:
        """Use the engine :meth:`build` gave from now on. After the first re-run the tape is kept while the
        alignment shows the forward axis only (a second may come); after the second, or otherwise, it is let go."""
        tape, due = self._tape, self._due
        assert tape is not None and due is not None
        self._due = None
        engine.rerun_at_s = round((due[1] - tape[0][2]) / NS, 1)
        self.reruns.append((due[0], engine.rerun_at_s))
        self.engine, self._feed = engine, nav_feeder(engine)
        est = engine.alignment.estimate() if engine.alignment is not None else None
        self._refining = len(self.reruns) == 1 and est is not None and est.state != SETTLED
        self._looks.clear()
        self._since_look = 0
        if not self._refining:
            self._let_go()
        log.info("the drive showed the IMU mounted at %.1f / %.1f / %.1f deg %.0f s in: filtered its %d inputs "
                 "again from the start with it", *due[0], engine.rerun_at_s, len(tape))

    @property
    def rerun_at_s(self) -> float | None:
        """How far into the kept inputs the re-run's remount came, s; None before a re-run."""
        return self.engine.rerun_at_s

    @property
    def rerun_mount(self) -> tuple[float, ...] | None:
        """The mounting the inputs were filtered again with; None before a re-run."""
        return tuple(self.engine.params.mounting_rpy_deg) if self.engine.rerun_at_s is not None else None

    def note(self) -> str:
        """A line saying what the re-run did, or ""."""
        if not self.reruns:
            return ""
        (r, p, y), at = self.reruns[0]
        line = f"the drive showed the IMU mounted at {r:.1f} / {p:.1f} / {y:.1f} deg {at:.0f} s in"
        if len(self.reruns) == 1:
            return line + ": the filter took its inputs again from the start with it"
        (r, p, y), at = self.reruns[1]
        return (line + f", and its forward axis held at {r:.2f} / {p:.2f} / {y:.2f} deg at {at:.0f} s: the filter "
                "took its inputs again from the start with each")
