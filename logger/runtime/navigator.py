"""The navigator thread of the daemon: the filter at the IMU rate, never in the way of the recording.

The daemon offers it every stamped record through ``offer`` (a tap), which only appends the record to a
bounded queue and counts a drop when the queue is full: the sampler threads and the recorder never wait for
the filter, and an offer never wakes the thread (a wake-up per sample would cost more than the filter step on
the board). The thread wakes every :data:`WAKE_S`, runs the engine over what has arrived, and publishes
``/nav/fix`` at ``publish_hz`` and ``/nav/state`` once a second of drive through the daemon's sink. It measures its own
CPU time, so ``logger status`` can show what the filter costs on the board.

The engine takes the records in the order of their samples' times, as ``logger replay`` does, not in the order
they were offered. A FIFO read reaches the navigator after its last sample, up to half a second after its first
(20 Hz, two reads a second), and an OBD speed or a fix read meanwhile is offered before it: taken first, the
speed was compared with the velocity of the last sample integrated, up to half a second older, and an
acceleration of 2 m/s^2 made that 1 m/s of error put into the velocity (on a recorded urban drive the published
/nav/fix was 2.32 m RMSE north, within 3 sigma 86.8 % of the time; taken in time order 0.64 m and 100 %). So a
measurement waits (:meth:`Navigator.take`) until a read brings the samples up to its time, and the read is cut
there (:func:`logger.recording.drive.in_runs`); one the IMU does not catch up with within HOLD_MAX_NS (a silent
IMU) goes in as it is.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import replace
from numbers import Integral
from pathlib import Path
from typing import Any

from logger.nav.engine import NavEngine, Solution, configured_tempco
from logger.nav.health import HealthJudge, outage_verdict
from logger.nav.params import NavParams
from logger.nav.thermal import TempcoLearner
from logger.recording.drive import in_runs
from logger.recording.intervals import next_due_ns
from logger.recording.nav_rerun import NavRerun
from logger.recording.records import (
    NAV_INPUT_TOPICS,
    follows_on,
    nav_fix_record,
    nav_state_record,
    next_whole_second,
    unplaced,
)
from logger.recording.topics import GNSS_FIX, IMU, IMU_BATCH, NAV_FIX, NAV_STATE
from logger.runtime import mount_state, tempco_state
from logger.runtime.daemon import Attachments
from logger.runtime.sampler import Reading
from logger.words import plural

log = logging.getLogger(__name__)

INPUT_TOPICS = frozenset((*NAV_INPUT_TOPICS, IMU_BATCH))  # live, a FIFO read comes as one batch
# The filter runs in batches: each wake-up costs more than the records it takes (caches gone cold while the other
# threads ran). Every 2 s rather than every second: the navigator thread 0.127-0.140 against 0.173-0.180 % of a
# core at 20 Hz, the daemon 0.51-0.57 against 0.58-0.62 % (tools/bench_daemon.py, three pairs of 150 s windows
# alternated); the live solution in `logger status` is then up to two seconds old instead of one.
WAKE_S = 2.0
FAILING_S = 3 * WAKE_S  # a failure this recent (real seconds): the filter is failing now, a problem in the status
FAILURE_LOG_REPEAT_S = 60.0  # a filter failing batch after batch is logged with its traceback at most this often
STALE_S = WAKE_S + 3.0  # a solution older than this (real seconds) is shown as the past it is
HOLD_MAX_NS = 2_000_000_000  # a measurement waits for the IMU samples before it at most this long (record time)


def in_offer_order(messages: Iterable[tuple[str, dict[str, Any]]]) -> list[tuple[int, str, dict[str, Any]]]:
    """Recorded (topic, payload) pairs in the order the daemon offers them to its taps, each with that time: a FIFO
    read once its last sample has been read, any other record at its own time (what :meth:`Navigator.in_time_order`
    puts back in order; the benchmarks and ``tools/live_check.py`` feed recorded drives so)."""
    def offered(topic: str, payload: dict[str, Any]) -> int:
        t = payload["t_sync_ns"]
        return int(t[-1]) if topic == IMU_BATCH else int(t)

    return sorted(((offered(t, m), t, m) for t, m in messages), key=lambda r: r[0])


class Navigator:
    """A daemon tap running :class:`NavEngine` on its own thread."""

    def __init__(self, params: NavParams, publish: Callable[[Reading], None] | None = None,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns, mount_path: Path | None = None,
                 installation: str = mount_state.BOARD, tempco_path: Path | None = None,
                 imu_installation: str = "") -> None:
        # The mounting the last drive settled on is this one's first guess (mount_state.py).
        self.configured_mount = tuple(float(a) for a in params.mounting_rpy_deg)
        self.mount_path = mount_path if params.mount_align else None
        self.installation = installation
        saved = mount_state.load(self.mount_path, self.configured_mount, installation) if self.mount_path else None
        self.params = replace(params, mounting_rpy_deg=saved) if saved is not None else params
        params = self.params
        self._next_mount_save_ns = 0
        # The IMU offsets' temperature coefficients earlier drives learnt of this part (tempco_state.py).
        self.tempco_path, self.imu_installation = tempco_path, imu_installation
        self._tempco_saved: tuple[list[float], list[float]] | None = None
        if tempco_path:
            bound = TempcoLearner(configured_tempco(params)).bound
            self._tempco_saved = tempco_state.load(tempco_path, imu_installation, bound)
        # The engine, replaced (once or twice) by one that filters the first minutes again if the drive shows another
        # mounting (and once more when its forward axis has held still).
        self.rerun = NavRerun(params, self._make_engine, deferred=True)
        self.publish = publish
        self.monotonic_ns = monotonic_ns
        self._timebase: Any = None  # the daemon's board clock (a TimeBase), once bound to it
        self.judge = HealthJudge()
        self._q: deque[tuple[str, dict[str, Any]]] = deque()
        self._q_lock = threading.Lock()  # the bound and the append together, for offers from many threads
        self.dropped = 0
        self.processed = 0
        self.unplaced = 0  # records not given to the filter: stamped before GNSS time, on a clock with no bound
        self.unplaced_since_placed = 0  # ... of them since the last record that was given (0: GNSS time is known)
        self.cpu_s = 0.0
        self._halt = threading.Event()
        # Set by an offer that fills a quarter of the queue: a fast simulated drive (or a 1 kHz burst) is taken
        # before the queue overflows, not only at the next WAKE_S.
        self._wake = threading.Event()
        self._wake_at = max(1, self.params.queue_size // 4)
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._next_fix_ns = 0
        self._fix_anchor_ns: int | None = None  # the publishing grid's origin: the first /nav/fix's time
        self._last_fix_mono: int | None = None  # board time of the last /nav/fix published
        self._live_ns = 0  # how long /nav/fix was published, silences left out
        self._next_state_ns = 0
        self._verdicts: list[str] = []
        self._outage_line: int | None = None  # where in _verdicts the outage's line is (HealthJudge.outage_line)
        self.error: str = ""
        self.failures = 0
        self._failed_at: float | None = None  # time.monotonic() of the last failure
        self._failure_logged_at = -math.inf
        self._failures_unlogged = 0
        self._held: list[tuple[str, dict[str, Any]]] = []  # measurements ahead of the IMU samples taken so far
        self._newest_ns: int | None = None  # the latest record time offered

    def rerun_if_due(self) -> None:
        """Filter the first minutes again once the drive showed the mounting (:mod:`logger.recording.nav_rerun`):
        the new engine is built without the lock, so ``logger status`` reads the engine in use meanwhile (on the
        board the re-run of a few minutes of inputs takes seconds), and taken under it."""
        if self.rerun.due:
            engine = self.rerun.build()
            with self._lock:
                self.rerun.adopt(engine)

    def _make_engine(self, params: NavParams) -> NavEngine:
        engine = NavEngine(params)
        if self._tempco_saved is not None:
            engine.start_tempco_from(*self._tempco_saved)
        return engine

    @property
    def engine(self) -> NavEngine:
        """The engine in use."""
        return self.rerun.engine

    # ---- the tap: never blocks ------------------------------------------------------------------------
    def offer(self, topic: str, payload: dict[str, Any]) -> None:
        if topic not in INPUT_TOPICS:
            return
        with self._q_lock:
            if len(self._q) < self.params.queue_size:
                self._q.append((topic, payload))
                if len(self._q) >= self._wake_at:
                    self._wake.set()
                return
            self.dropped += 1

    @property
    def queued(self) -> int:
        """Records offered and not yet taken by the filter thread."""
        return len(self._q)

    # ---- life cycle ---------------------------------------------------------------------------------------
    def bind(self, daemon: Any) -> None:
        """Publish through the daemon's sink (until it stops: its recorder then closes the file) and start."""
        stopping = daemon.stop_event

        def publish(r: Reading) -> None:
            if not stopping.is_set():
                daemon.sink(r)

        self.publish = publish
        self._timebase = daemon.tb
        self.start()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="navigator", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._halt.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(2.0)
        with self._lock:  # the filter thread may still be inside a batch if the join timed out
            self._save_mount()

    def _save_mount(self) -> None:
        """Keep a settled mount alignment and learnt temperature coefficients for the next start (called with the
        filter's lock held)."""
        al = self.engine.alignment
        if self.mount_path is not None and al is not None:
            mount_state.save(self.mount_path, self.configured_mount, self.installation, al.estimate())
        if self.tempco_path is not None and self.engine.ekf is not None:
            tempco_state.save(self.tempco_path, self.imu_installation, *self.engine.learnt_tempco(),
                              self.engine.tempco.bound, self.engine.tempco.data_sigma())

    def _run(self) -> None:
        cpu0 = time.thread_time()
        q = self._q
        while True:
            self._wake.wait(WAKE_S)
            self._wake.clear()  # before taking: a quarter filled meanwhile is taken at the next turn
            if self._halt.is_set():
                return
            if not q:
                continue
            batch = [q.popleft() for _ in range(len(q))]  # only this thread takes: len(q) are there
            try:
                with self._lock:
                    self.take(batch)
                self.rerun_if_due()
            except Exception as exc:  # a bug in the filter must not take the logger down: report, restart it
                self._failed(exc)
                with self._lock:
                    self.rerun = NavRerun(self.params, self._make_engine, deferred=True)
            self.cpu_s = time.thread_time() - cpu0

    def _failed(self, exc: Exception) -> None:
        """A batch the filter failed on: counted, and logged with its traceback, once a minute at most (a filter
        that fails on every batch wrote a traceback every 2 s into the journal)."""
        now = time.monotonic()
        self.failures += 1
        self._failed_at = now
        self.error = f"{type(exc).__name__}: {exc}"
        if now - self._failure_logged_at >= FAILURE_LOG_REPEAT_S:
            unlogged = self._failures_unlogged
            log.exception("navigation filter failed; restarting it%s",
                          f" ({unlogged} more failures since the last logged)" if unlogged else "")
            self._failure_logged_at, self._failures_unlogged = now, 0
        else:
            self._failures_unlogged += 1

    def failing(self) -> bool:
        """Whether the filter failed within FAILING_S: restarted, and failing again."""
        return self._failed_at is not None and time.monotonic() - self._failed_at < FAILING_S

    def in_time_order(self, records: list[tuple[str, dict[str, Any]]],
                      release: bool = False) -> list[tuple[str, dict[str, Any]]]:
        """What of the records held and these can go to the engine now, in the order of their samples' times:
        IMU records always, a measurement once an IMU sample at or after its time has come (or after HOLD_MAX_NS
        without, or at once with ``release``); FIFO reads cut where a measurement falls between their samples
        (ties keep the offer order)."""
        records = self._held + records
        imu_end = self.engine.t_last_ns
        newest = self._newest_ns
        for topic, payload in records:
            t = payload["t_sync_ns"]
            if topic == IMU_BATCH and not t:
                continue
            last = t[-1] if topic == IMU_BATCH else t
            if isinstance(last, Integral):
                newest = last if newest is None else max(newest, last)
                if topic in (IMU, IMU_BATCH):
                    imu_end = last if imu_end is None else max(imu_end, last)
        self._newest_ns = newest
        imu: list[tuple[int, str, int, dict[str, Any]]] = []
        ready: list[tuple[int, str, int, dict[str, Any]]] = []
        held: list[tuple[str, dict[str, Any]]] = []
        gnss_only = self.engine.mode == "gnss"  # no IMU to wait for
        for topic, payload in records:
            t = payload["t_sync_ns"]
            if topic in (IMU, IMU_BATCH):
                if topic == IMU or t:
                    imu.append((t[0] if topic == IMU_BATCH else t, topic, 0, payload))
            elif (release or gnss_only or not isinstance(t, Integral) or (imu_end is not None and t <= imu_end)
                  or (newest is not None and t < newest - HOLD_MAX_NS)):
                ready.append((int(t) if isinstance(t, Integral) else 0, topic, 0, payload))
            else:
                held.append((topic, payload))
        self._held = held
        # The IMU records as offered (the engine counts a read out of order), each measurement before the first
        # that starts after its time; in_runs then cuts a read at the measurements inside it.
        ready.sort(key=lambda r: r[0])
        items: list[tuple[int, str, int, dict[str, Any]]] = []
        i = 0
        for rec in imu:
            while i < len(ready) and ready[i][0] < rec[0]:
                items.append(ready[i])
                i += 1
            items.append(rec)
        items.extend(ready[i:])
        return [(topic, payload) for _, topic, _, payload in in_runs(iter(items))]

    def flush(self) -> None:
        """The measurements still waiting for IMU samples, taken as they are: no sample will come (the end of a
        recorded drive fed through :meth:`take`)."""
        self.take([], release=True)

    def take(self, records: list[tuple[str, dict[str, Any]]], merge: bool = True, release: bool = False) -> None:
        """One wake-up's records through the filter in the order of their samples' times (:meth:`in_time_order`:
        a measurement ahead of the IMU samples waits for them), publishing as they go (called with the lock held).

        At 1 kHz a FIFO read is 40 samples, too few for the engine's block forms (``BATCH_MIN``), and nothing
        else comes between most reads: so a run of reads that follow one another (:func:`follows_on`) goes in
        as one block (:func:`feed_reads`). A run ends before any other record, at the end of the wake-up, and
        with the read that reaches the next /nav/state, so /nav/state goes out after the same reads as fed read
        by read; /nav/fix goes out from inside a run, the solution at the first integration step that reaches
        its time (the engine's tap, :meth:`_tap`), as it does from reads fed one by one. A read after a gap,
        lost samples or out of order goes alone, as before. ``merge=False``: every read alone (what the
        benchmark and the tests compare with); ``release``: the measurements held go in too (:meth:`flush`)."""
        self.processed += len(records)
        # Before in_time_order (here, on this thread, not in offer on the sensors'): the filter waits for GNSS time
        # (records.unplaced), and a boot date's stamps would stand as the newest times and release measurements early.
        placed = [r for r in records if not unplaced(r[1])]
        self.unplaced += len(records) - len(placed)
        self.unplaced_since_placed = 0 if placed else self.unplaced_since_placed + len(records)
        records = self.in_time_order(placed, release)
        rerun, run = self.rerun, []
        self._arm_tap()
        last: int | None = None  # the run's last sample
        for topic, payload in records:
            if topic == IMU_BATCH and merge:
                t = payload["t_sync_ns"]
                if follows_on(payload, last if run else rerun.engine.t_last_ns):
                    run.append(payload)
                    last = t[-1]
                    if self._state_due(last):
                        rerun.feed_reads(run)
                        run = []
                        self._maybe_publish()
                    continue
            if run:
                rerun.feed_reads(run)
                run = []
                self._maybe_publish()
            rerun.feed(topic, payload)
            if topic in (IMU, IMU_BATCH) or (topic == GNSS_FIX and rerun.engine.mode == "gnss"):
                self._maybe_publish()
        if run:
            rerun.feed_reads(run)
            self._maybe_publish()

    def _state_due(self, t_ns: int) -> bool:
        """Whether a run of reads ends with the read whose last sample is at ``t_ns``: it reaches the next
        /nav/state. Never before the filter has started (nothing is published then; a configured heading that
        starts it inside a run has its first /nav/state after the run): a run then goes in whole, at 1 kHz a
        wake-up's thousand samples (:meth:`NavEngine._pre_init_block`)."""
        return self.publish is not None and t_ns >= self._next_state_ns and self.engine.state is not None

    def _publish_due(self, t_ns: int) -> bool:
        """Whether a solution at ``t_ns`` reaches the next /nav/fix or /nav/state (:meth:`_maybe_publish`)."""
        return self.publish is not None and (t_ns >= self._next_fix_ns or t_ns >= self._next_state_ns)

    def _arm_tap(self) -> None:
        """Have the engine in use hand over its solution at the next /nav/fix time as it integrates (the engine
        that a re-run put in place is armed at the next wake-up)."""
        if self.publish is not None:
            engine = self.engine
            engine.tap, engine.tap_ns = self._tap, self._next_fix_ns

    def _tap(self, sol: Solution) -> int:
        """A solution from inside a run at the /nav/fix time: published; the next time one is wanted."""
        if sol.t_ns >= self._next_fix_ns:
            self._publish_fix(sol)
        return self._next_fix_ns

    def _maybe_publish(self) -> None:
        engine = self.engine
        if engine.mode == "gnss":
            # GNSS-only, the solution is the last fix's and no IMU sample is integrated: its time is the fix's.
            sol = engine.current()
            if sol is None or not self._publish_due(sol.t_ns):
                return
        else:
            t_last = engine.t_last_ns
            if t_last is None or not self._publish_due(t_last):
                return
            sol = engine.current()
            if sol is None:
                return
        t = sol.t_ns
        if t >= self._next_fix_ns:
            self._publish_fix(sol)
        if t >= self._next_state_ns:
            self._next_state_ns = next_whole_second(t)
            self._verdicts = self.judge.verdicts(self.engine, t / 1e9)
            self._outage_line = self.judge.outage_line
            msg = nav_state_record(self.engine, t, sol.t_mono_ns, self._verdicts,
                                {"dropped": self.dropped, "cpu_s": round(self.cpu_s, 4)})
            self.publish(Reading(NAV_STATE, msg, sol.t_mono_ns, stamped=False))
            if t >= self._next_mount_save_ns:
                self._next_mount_save_ns = t + int(mount_state.SAVE_INTERVAL_S * 1e9)
                self._save_mount()

    def _publish_fix(self, sol: Solution) -> None:
        """/nav/fix of ``sol``, the next one due on a grid of the publishing period from the first (a period after
        each one, on solutions 50 ms +- us apart, published 5 Hz as 4.83 Hz: one interval in six 0.25 s)."""
        assert self.publish is not None
        t = sol.t_ns
        period_ns = int(1e9 / max(self.params.publish_hz, 0.1))
        if self._fix_anchor_ns is None:
            self._fix_anchor_ns = t
        self._next_fix_ns = self.engine.tap_ns = next_due_ns(t, self._fix_anchor_ns, period_ns)
        # Live time: the board-clock intervals between publishes, a silence (an outage in GNSS-only mode, a
        # restart) left out; the board clock, since the synchronised one may step when it first locks.
        last = self._last_fix_mono
        if last is not None and 0 < sol.t_mono_ns - last <= 3 * period_ns:
            self._live_ns += sol.t_mono_ns - last
        self._last_fix_mono = sol.t_mono_ns
        msg = nav_fix_record(t, sol.t_mono_ns, sol.lat_rad, sol.lon_rad, sol.h_m, sol.vel_ned, sol.rpy_rad,
                             sol.sigma_ned, sol.source, self.engine.mode)
        self.publish(Reading(NAV_FIX, msg, sol.t_mono_ns, stamped=False))

    # ---- status -------------------------------------------------------------------------------------------
    def section(self) -> dict[str, Any]:
        """The ``nav`` section of ``logger status``."""
        with self._lock:
            sol = self.engine.current()
            # Before the first solution nothing is published, so no verdict was drawn: say what the start waits for.
            verdicts = list(self._verdicts) if sol is not None else self.judge.verdicts(self.engine, 0.0)
            if sol is None and self.engine.counters.imu == 0 and self.queued and self.processed == 0:
                # The IMU delivers, the thread has not had its turn yet (it wakes every WAKE_S): "no sample yet"
                # beside an IMU row that says ok was not true. After its first turn the records waiting are not
                # why (an IMU that never delivers left this line up for a whole run beside the GNSS's records).
                verdicts = [f"initialising: {plural(self.queued, 'record')} waiting for the filter's first turn"]
            elif sol is None and self.engine.counters.imu == 0 and self.unplaced_since_placed:
                # Records stamped before GNSS time never reach the filter (take): its "no IMU sample yet" beside an
                # IMU that delivers sent the operator to the wrong sensor, for as long as the receiver had no fix.
                verdicts = [f"initialising: waiting for GNSS time (the clock's first lock): "
                            f"{plural(self.unplaced_since_placed, 'record')} stamped without it left out"]
            out: dict[str, Any] = {"lat_deg": None, "lon_deg": None, "height_m": None, "sigma_h_m": None,
                                   "source": "", "mode": self.engine.mode, "verdicts": verdicts,
                                   "dropped": self.dropped, "processed": self.processed,
                                   "cpu_s": round(self.cpu_s, 3), "resets": self.engine.counters.resets,
                                   "live_s": round(self._live_ns / 1e9, 1)}
            if sol is not None:
                out.update(lat_deg=math.degrees(sol.lat_rad), lon_deg=math.degrees(sol.lon_rad), height_m=sol.h_m,
                           sigma_h_m=math.hypot(sol.sigma_ned[0], sol.sigma_ned[1])
                           if math.isfinite(sol.sigma_ned[0]) else None, source=sol.source)
                tb = self._timebase
                age_s = (tb.monotonic_ns() - sol.t_mono_ns) / 1e9 if tb is not None else None
                out["age_s"] = None if age_s is None else round(age_s, 1)
                # Judged in real seconds, as the thread wakes: a simulated drive at 4x is 4 s of drive per second.
                if age_s is not None and age_s / tb.scale > STALE_S:
                    # The filter moves with the IMU's samples: without them the last solution and the verdicts drawn
                    # with it stay as they were, and would read as the present (fixes that come meanwhile only nudge
                    # the position held at the last sample's time).
                    # What is known is the filter's last sample, not why (an IMU gone silent, or this thread stuck).
                    out["verdicts"] = [f"no new solution for {age_s:.0f} s (the filter integrated no IMU sample "
                                       "since): the position above is not current"]
                    out["stale"] = True  # said on the position's own row too (the verdicts may not fit a screen)
                elif age_s is not None and self._outage_line is not None:
                    # Drawn at the last publish, up to a wake (2 s) and a publish period ago: the outage's age as of
                    # now, as the receiver's row beside it counts its own.
                    line = outage_verdict(self.engine, age_s)
                    if line is not None:
                        out["verdicts"][self._outage_line] = line
            if self.failing():
                # Its verdicts are a restarted filter's ("initialising: waiting for the IMU" while the IMU delivers):
                # what is true is that it fails. A problem for the status's verdict too.
                line = f"filter failing: {self.error} (restarted after each of {plural(self.failures, 'failure')})"
                out["verdicts"] = [line]
                out["problems"] = [f"nav: {line}"]
            elif self.error:
                out["verdicts"].append(f"filter restarted after an error: {self.error}")
            if self.dropped:
                out["verdicts"].append(f"navigator behind: {self.dropped} records skipped")
            return out


def attach_navigator(section: dict[str, Any], attachments: Attachments, state_dir: Path | None = None,
                     installation: str = mount_state.BOARD, imu_installation: str = "") -> Navigator | None:
    """A navigator for the daemon from the ``[nav]`` section, registered as a tap, a status section and a thing
    to stop; ``None`` when the section disables it. Call :meth:`Navigator.bind` once the daemon exists. The mount
    alignment is kept in ``state_dir`` from one drive to the next, for the same ``installation``, and the IMU's
    temperature coefficients for the same ``imu_installation`` (the part)."""
    if not section.get("enabled", True):
        return None
    nav = Navigator(NavParams.from_config(section),
                    mount_path=state_dir / "mount.json" if state_dir is not None else None, installation=installation,
                    tempco_path=state_dir / "imu_tempco.json" if state_dir is not None else None,
                    imu_installation=imu_installation)
    attachments.taps.append(nav)
    attachments.sections["nav"] = nav.section
    attachments.close.append(nav.stop)
    attachments.backlogs.append(lambda: (nav.queued, nav.params.queue_size))
    return nav
