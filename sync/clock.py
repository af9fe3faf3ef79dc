"""The PPS-disciplined clock: board monotonic time -> GNSS (UTC) time, with a state and an honest error bound.

Samples are PPS edges (kernel time stamps on the monotonic clock) paired with the GNSS second each one marks
(:mod:`sync.pairing`). A robust line through the recent samples (:mod:`sync.regress`) gives offset and
frequency, so a stamp between edges is interpolated with the estimated frequency. When edges stop (tunnel,
blocked sky) the clock carries on in HOLDOVER with the last frequency, corrected for the board's temperature
when the temperature coefficient could be learned while locked, and its error bound grows with the frequency's
uncertainty plus an oscillator stability, as chrony's does. When edges return, the difference between the
holdover prediction and the new fit is slewed out at a bounded rate: time never runs backwards and never steps.

States: FREERUN (no GNSS time yet: the wall clock read once at start), LOCKED, HOLDOVER.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from sync.chrony_sock import ChronySock
from sync.inputs import FixEpoch, TimeAnnouncement
from sync.kernel_slew import KernelSlew
from sync.pairing import LEAP_UNKNOWN_NS, REPAIR_LABELS, EdgeLabeller
from sync.paper import PaperCounters
from sync.regress import MIN_SAMPLES_FOR_SLOPE, OUTLIER_SIGMAS, LineFit, fit_line
from sync.settings import SyncSettings
from sync.stamp import (
    FLOOR_YEAR,
    FREERUN,
    GNSS_TIME_FLOOR_NS,
    HOLDOVER,
    LOCKED,
    NO_BOUND_NS,
    Stamp,
    StampClock,
    Stamps,
    TrackingReport,
)
from sync.tempco import TempcoEstimator

log = logging.getLogger(__name__)

NS = 1_000_000_000
WALL_TOLERANCE_NS = 500_000_000
WALL_PATIENCE_NS = 60 * NS
# Before its first lock a clock started on an unsynchronised system clock looks again this often whether NTP has set
# it since (a board without RTC boots at its image's date; the network may come seconds later): its free-running
# stamps then follow it, with its bound, rather than the boot date for as long as no GNSS time comes (a garage).
WALL_RECHECK_S = 30
# A solution for second T is computed after T's pulse, so it is never read before T; a TIM-TP for T is sent after
# the pulse before it. Read earlier than that by this clock (beyond this margin), the clock is whole seconds off.
READ_BEFORE_EPOCH_MARGIN_NS = 50_000_000
ANNOUNCEMENT_LEAD_NS = 1_500_000_000  # a TIM-TP comes at most this long before the edge it announces
CONFIRM_EDGES = MIN_SAMPLES_FOR_SLOPE + 1  # edges a fit needs to refuse one of them as an outlier (fit_line)
# A missed edge's growth is put in the bound at this multiple: a frequency still changing (a temperature ramp, a
# slew of the monotonic clock beginning) makes the next miss larger than a straight line through two predicts.
MISS_GROWTH_MARGIN = 2.0
# The newest edges, this many in a row missed all one way by more than the interrupt latency's spread and on a line
# of their own (residuals within half that spread), are a change of the board clock's rate or offset, not late
# interrupts: the fit starts again from them. CONFIRM_EDGES: as many as a fit needs to refuse one of its own.
CHANGE_EDGES = CONFIRM_EDGES
# The longest a sample's labelling (its time message's arrival) may lag its edge and still count as the clock
# following the PPS (PpsClock._fresh_ns): a solution completing after the next pulse (9600-baud NMEA) is ~1.4 s late.
PAIR_LAG_MAX_NS = 1_500_000_000
# No receiver's time pairs before GNSS_TIME_FLOOR_NS (sync.stamp, 2020-01-01 UTC): an earlier date is a GPS
# week-number rollover (an old firmware counting 1024 weeks: 19.6 years early, and with every validity flag set) or a
# receiver that has no date yet. Paired, it locked the clock to 2007 behind a 12 us bound, and after a minute even
# over a synchronised system clock. Such times are not used, and the journal says so (WRONG_DATE_LOG_S apart).
WRONG_DATE_LOG_S = 60
# The state file's format (``"format"``), which a restart reads only if it is its own: 2 has the fit's own frequency
# (before, the temperature-corrected one, corrected again on restore) and, on the host's clock, what NTP had done to
# the monotonic clock (``"kernel"``; without it a restart on the same boot kept NTP's slews of the downtime in its
# stamps: 1 ms off behind a 53 us bound after an upgrade). A file of another format is not used at all.
STATE_FORMAT = 2


class PpsClock(StampClock):
    """A :class:`sync.stamp.StampClock` that observes PPS edges, time pulses, fixes and IMU temperatures."""

    def __init__(self, settings: SyncSettings | None = None, monotonic_ns: Callable[[], int] = time.monotonic_ns,
                 wall_ns: Callable[[], int] = time.time_ns, state_path: Path | None = None,
                 clock_id: str = "", wall_trusted: bool = False, raw_ns: Callable[[], int] | None = None,
                 wall_synchronized: Callable[[], bool] | None = None) -> None:
        self.s = settings or SyncSettings()
        # With the board's raw clock (CLOCK_MONOTONIC_RAW beside the monotonic clock), what NTP does to the
        # monotonic clock beyond the rate the fit's edges showed is taken out past the newest edge (sync.kernel_slew)
        self.kslew = KernelSlew(monotonic_ns, raw_ns) if raw_ns is not None else None
        # A synchronised system clock (NTP) is checked against at the first lock: a chain of edges labelled with
        # the wrong second (messages that reached us seconds late) is consistent in itself and only this sees it.
        self.wall_trusted = wall_trusted
        self._freerun_err_ns = self.s.freerun_err_ns if wall_trusted else NO_BOUND_NS
        self._wall = wall_ns
        self._wall_disagree_since: int | None = None
        self._wall_check = wall_synchronized  # whether the system clock is synchronised now (recheck_wall)
        self._wall_checked_ns: int | None = None
        self._mono = monotonic_ns
        self._lock = threading.RLock()
        mono = monotonic_ns()
        self._freerun_offset_ns = wall_ns() - mono
        # A free run from a mapping the fit gave (_pair_again), carried on as a holdover is: its time, the fit's
        # frequency then, the temperature then with the learnt coefficient's correction since and the bound the
        # temperature adds (the crystal drifts on without edges), and the kernel's K and rate then (NTP's slew of
        # the monotonic clock since is taken out, with the raw clock).
        self._freerun_from_ns: int | None = None
        self._freerun_slope = 0.0
        self._freerun_temp: float | None = None
        self._freerun_temp_ns = 0.0
        self._freerun_comp_ns = 0.0
        self._freerun_kernel: tuple[float, float] | None = None
        self.labeller = EdgeLabeller(self.s.pps_latency_ns)
        # Leap seconds: the fit runs in the labeller's continuous scale; a stamp becomes Unix time on the way out.
        self.labeller.now_ns = monotonic_ns
        self.labeller.slew_ppm = self.s.max_slew_ppm
        self.paper = PaperCounters(self.s.imu_rate_hz)
        self.tempco = TempcoEstimator()
        self.state_path = state_path
        self.clock_id = clock_id
        # Samples: board time of the edge (ns) and offset = GNSS time - board time (ns), oldest first.
        self._edges: deque[int] = deque(maxlen=self.s.max_samples)
        self._offsets: deque[int] = deque(maxlen=self.s.max_samples)
        self._base_ns = 0  # offsets are fitted relative to this, in float64 with ns resolution
        self._fit: LineFit | None = None
        self._locked_once = False
        self._consecutive = 0
        self._last_sample_ns: int | None = None
        self._slope_prior: float | None = None
        self._skew_prior = 1e-6
        self._slew_from_ns: int | None = None  # board time the current slew started
        self._slew_ns = 0.0  # correction to be slewed out, ns
        self._slew_len_ns = 1
        self._temp_at_fit: float | None = None
        self._comp_ns = 0.0  # integral of the temperature correction since the last sample
        self._comp_abs_ns = 0.0  # integral of the worst-case temperature term, for the bound
        # After a gap the regression starts again from one edge, which nothing can check but the holdover it ends:
        # their disagreement and the holdover's own bound stay in the bound until the fit has edges enough to refuse
        # a late one (CONFIRM_EDGES). An edge served 0.3-0.5 ms late gave locked stamps that far off behind 13-39 us.
        self._unconfirmed_ns = 0.0
        # An edge the fit predicted worse than the bound it claimed (a rate step the regression has not followed:
        # the newest edges look like outliers to it): how far beyond, and how fast the misses grow, stay in the
        # bound until an edge falls within it again. Without them a 5 ppm step gave stamps 31 us off behind 13 us
        # for 7 s, and CLOCK_MONOTONIC slewed by NTP at 500 ppm 1 ms behind 12 us.
        self._miss_ns = 0.0
        self._miss_growth = 0.0  # ns of miss per ns since the edge
        self._good_miss: tuple[int, float] | None = None  # (board ns, miss) of the last edge within its bound
        self._suspect_left = 0  # edges within their bounds still needed before the growth leaves the bound
        self._suspect_slope: float | None = None  # the fit's slope when the misses began
        self._prev_miss: tuple[int, float] | None = None  # (board ns, miss) of the edge before
        # After a followed change: edges within the fit's own bound still needed before its doubt (how far the
        # fit moved, in _unconfirmed_ns) leaves the bound. Four edges served equally late are a line of their own.
        self._confirm_left = 0
        # The newest edges' misses, ns: published time minus the edge's GNSS time.
        self._recent_misses: deque[float] = deque(maxlen=CHANGE_EDGES)
        # How long after their edges the newest samples were labelled (their time message's arrival), at most
        # PAIR_LAG_MAX_NS: the clock follows the PPS while its newest sample is no older than holdover_after_s plus
        # the longest of them (_fresh_ns, set as a sample comes, read at every stamp). A receiver at 9600 baud with
        # u-blox's factory NMEA labels each edge over a second after it, with its epoch's end: between two labels
        # the newest sample is up to 2.4 s old though every edge comes, and the clock said holdover all the time
        # (its bound is the same either way: it grows from the newest sample).
        self._pair_lags: deque[int] = deque(maxlen=CHANGE_EDGES)
        self._fresh_ns = round(self.s.holdover_after_s * NS)  # what _pair_lags make of it, kept as they change
        self._last_temp: tuple[int, float] | None = None
        self._saved_at: int | None = None
        self._restored = False
        self._last_offset_ns: int | None = None
        self.last_mislabel: tuple[int, str] | None = None  # (board ns, what) of the last pairing found wrong
        self.on_sample: Callable[[int, int], None] | None = None  # (edge board ns, edge GNSS unix ns), e.g. chrony
        self.chrony: ChronySock | None = None  # the chrony socket on_sample feeds, when it is one (its counts)
        self.counts = {"edges": 0, "samples": 0, "rejected": 0, "relocks": 0, "unlabelled": 0, "late_reads": 0,
                       "mislabels": 0, "wrong_dates": 0, "repairs": 0}
        self._wrong_date_logged_ns: int | None = None  # board time of the last "before GNSS_TIME_FLOOR_NS" line
        self._load()

    # ---- observation (from the record layer, for the records that tell time; any thread) ---------------------
    def on_imu_sample(self, t_mono_ns: int, temp_degc: float | None) -> None:
        """An IMU sample: the paper's counters tick, and its die temperature drives the holdover correction."""
        with self._lock:
            self.paper.on_imu(t_mono_ns)
            if temp_degc is not None:
                self._on_temperature(t_mono_ns, float(temp_degc))

    def on_imu_samples(self, times_ns: Sequence[int], temp_degc: float | None) -> None:
        """A FIFO read's samples under one lock; the temperature (one per read) goes with the last."""
        with self._lock:
            self.paper.on_imu_many(times_ns)
            if temp_degc is not None and times_ns:
                self._on_temperature(times_ns[-1], float(temp_degc))

    def on_edge(self, t_mono_ns: int, gnss_time_ns: int | None = None) -> None:
        """A PPS edge's kernel time stamp; ``gnss_time_ns`` when its source names the second it marks (gpsd)."""
        with self._lock:
            self.counts["edges"] += 1
            self.paper.on_edge(t_mono_ns)
            if gnss_time_ns is None or self._wrong_date(int(gnss_time_ns), t_mono_ns, "PPS report"):
                self._take(self.labeller.on_edge(t_mono_ns, self._predict_unix_ns))  # a wrong date: its label unused
            else:
                self._take(self.labeller.on_labelled_edge(t_mono_ns, int(gnss_time_ns), self._predict_unix_ns))

    def on_announcement(self, announcement: TimeAnnouncement, t_mono_ns: int) -> None:
        """The receiver announced the GNSS time of its next pulse (seen at ``t_mono_ns``)."""
        with self._lock:
            label = self.labeller.timepulse_unix_ns(announcement)
            if label is not None and self._wrong_date(label, t_mono_ns, "time pulse announcement"):
                return
            if label is not None:
                self._check_read_after(self.labeller.to_cont(label) - ANNOUNCEMENT_LEAD_NS, t_mono_ns,
                                       "time pulse announcement", label)
            self._take(self.labeller.on_timepulse(announcement, t_mono_ns, self._predict_unix_ns))

    def on_fix_epoch(self, epoch: FixEpoch, t_mono_ns: int) -> None:
        """A navigation solution for a valid GNSS second arrived (at ``t_mono_ns``, after that second's pulse)."""
        with self._lock:
            if self._wrong_date(epoch.gnss_time_ns, t_mono_ns, "fix"):
                return
            self._check_read_after(self.labeller.to_cont(epoch.gnss_time_ns, epoch.leap_second), t_mono_ns, "fix",
                                   epoch.gnss_time_ns)
            self._take(self.labeller.on_fix(epoch, t_mono_ns, self._predict_unix_ns))

    def time_doubt(self) -> str | None:
        if not self.labeller.leap_unknown:
            return None
        said = "receiver has no broadcast leap-second count yet (cold start, up to 12.5 min): "
        if self._locked_once or self._restored:
            return said + f"stamps within {LEAP_UNKNOWN_NS // NS} s"
        return said + "its UTC may be whole seconds off"  # free-running stamps: their own bound, none of this

    def recheck_wall(self, now_ns: int) -> None:
        """Before the first lock, on a system clock that was not synchronised at start: every WALL_RECHECK_S, whether
        it is now (NTP came after the logger); then the free-running stamps follow it with its bound, and the first
        lock is checked against it. Stamps given before stay as they were (their bound said none)."""
        check = self._wall_check
        if (check is None or self.wall_trusted or self._locked_once or self._restored
                or self._freerun_from_ns is not None):  # a free run after pairing again: the clock's own mapping
            return
        if self._wall_checked_ns is not None and now_ns - self._wall_checked_ns < WALL_RECHECK_S * NS:
            return
        self._wall_checked_ns = now_ns
        if not check():  # outside the lock: it may ask timedated (up to 2 s)
            return
        with self._lock:
            if self._locked_once or self._restored or self._freerun_from_ns is not None:
                return
            old = self._freerun_offset_ns
            self.wall_trusted = True
            self._freerun_err_ns = self.s.freerun_err_ns
            self._freerun_offset_ns = self._wall() - self._mono()
            self._freerun_from_ns = None
        log.info("the system clock is synchronised now (it moved %+.3f s since the start): free-running stamps "
                 "follow it, error bound %.0f s, until GNSS time is known", (self._freerun_offset_ns - old) / NS,
                 self._freerun_err_ns / NS)

    def _pair_again(self, diff_ns: int) -> None:
        """GNSS time disagreed with the clock's by the same whole seconds for REPAIR_LABELS edges in a row, not at a
        month's end (sync.pairing): the fit goes, and the clock locks again on the receiver's labels. Meanwhile it
        runs free from its last mapping, the disagreement in its bound, and the bound grows from then as a
        holdover's does (a free run that outlasts the relock, after a later mislabel, may last hours)."""
        now = self._mono()
        if self._fit is not None and (self._locked_once or self._restored):
            self._freerun_offset_ns = round(self._offset_at(now))
            self._freerun_err_ns = abs(diff_ns) + round(self._err_at(now, HOLDOVER))
            self._freerun_from_ns = now
            self._freerun_slope = self._current_slope(now)
            self._freerun_temp = self._last_temp[1] if self._last_temp is not None else None
            self._freerun_temp_ns = self._freerun_comp_ns = 0.0
            self._freerun_kernel = None
            if self.kslew is not None and self._edges:
                edge = self.kslew.edge_rate(*self._kernel_window())
                if edge is not None:
                    self._freerun_kernel = (self.kslew.at(now), edge[2])
        log.warning("GNSS time has disagreed with the clock's by %+.0f s for %d PPS edges (not at a month's end: no "
                    "leap second); pairing again on the receiver's time (a receiver that corrected its leap seconds, "
                    "or the clock's own chain was a second off)", diff_ns / NS, REPAIR_LABELS)
        self.counts["repairs"] += 1
        self.last_mislabel = (now, f"GNSS time moved {diff_ns / NS:+.0f} s against the clock's (no leap second): "
                                   "paired again on the receiver's time; stamps before it may be off by that")
        self._edges.clear()
        self._offsets.clear()
        self._fit = None
        self._locked_once = self._restored = False
        self._forget_misses()

    def _wrong_date(self, unix_ns: int, t_mono_ns: int, what: str) -> bool:
        """Whether a receiver's time is before GNSS_TIME_FLOOR_NS (a week rollover, or no date): not to be paired.
        Counted (``wrong_dates``) and logged at most every WRONG_DATE_LOG_S."""
        if unix_ns >= GNSS_TIME_FLOOR_NS:
            return False
        self.counts["wrong_dates"] += 1
        said = dt.datetime.fromtimestamp(unix_ns / NS, dt.UTC)
        self.last_mislabel = (t_mono_ns, f"the receiver's time says {said:%Y-%m-%d}, before {FLOOR_YEAR}: a GPS "
                                         "week-number rollover (old firmware) or no date yet; not used, the clock "
                                         "runs free")
        last = self._wrong_date_logged_ns
        if last is None or t_mono_ns - last >= WRONG_DATE_LOG_S * NS:
            self._wrong_date_logged_ns = t_mono_ns
            log.warning("the receiver's %s says %s UTC, before %d-01-01: a GPS week-number rollover (an old "
                        "firmware's date, 1024 weeks early) or no date yet; its times are not used", what,
                        f"{said:%Y-%m-%d %H:%M:%S}", FLOOR_YEAR)
        return True

    def _check_read_after(self, earliest_ns: int, t_mono_ns: int, what: str, epoch_unix_ns: int) -> None:
        """A message cannot be read before the GNSS time it could first be sent: when this clock says it was,
        the edges were paired with the wrong seconds (a host that read every message late as the chain began,
        then caught up). Every sample is as wrong as the stamps since: drop them and pair again, freerunning."""
        if self._fit is None or self._state_at(t_mono_ns) == FREERUN:
            return
        now = t_mono_ns + self._offset_at(t_mono_ns)  # both in the labeller's continuous scale
        early_ns = earliest_ns - now
        if early_ns <= READ_BEFORE_EPOCH_MARGIN_NS:
            return
        self.counts["mislabels"] += 1
        when = dt.datetime.fromtimestamp(epoch_unix_ns / NS, dt.UTC).strftime("%H:%M:%S")
        self.last_mislabel = (t_mono_ns, f"PPS edges were paired with the wrong second until {when} UTC (messages "
                                         "read late); stamps before it are off by whole seconds, pairing again")
        log.error("clock: a %s for %s UTC was read %.1f s before this clock allows: the PPS edges were paired with "
                  "the wrong seconds; pairing again (stamps freerun until then)", what, when, early_ns / NS)
        self._edges.clear()
        self._offsets.clear()
        self._fit = None
        self._locked_once = False
        self._restored = False
        self._last_sample_ns = None
        self._pair_lags.clear()
        self._fresh_ns = round(self.s.holdover_after_s * NS)
        self._slew_from_ns = None
        self._slew_ns = 0.0
        self._unconfirmed_ns = 0.0
        self._forget_misses()
        self._confirm_left = 0
        self._wall_disagree_since = None
        self.labeller.restart_chain()

    def _take(self, pairs: list[tuple[int, int]]) -> None:
        for edge_ns, label_ns in pairs:
            self._add_sample(edge_ns, label_ns)
        repair = self.labeller.take_repair()
        if repair is not None:
            self._pair_again(repair)
        self.counts["rejected"] = self.labeller.rejected
        self.counts["unlabelled"] = self.labeller.unlabelled
        self.counts["late_reads"] = self.labeller.late_reads

    # ---- samples and the fit ---------------------------------------------------------------------------------
    def _add_sample(self, edge_ns: int, label_ns: int) -> None:
        true_board_ns = edge_ns - self.s.pps_latency_ns  # the interrupt stamped the edge this much late
        offset = label_ns - true_board_ns
        if self._last_sample_ns is not None and edge_ns <= self._last_sample_ns:
            return
        state_before = self._state_at(edge_ns)
        predicted = self._offset_at(edge_ns) if state_before != FREERUN else None
        # The edge is labelled when its time message comes, up to a second after it: the slew to the new fit starts
        # then, from the time published then (from the edge, the part of it due meanwhile was a step: 47-79 us in
        # 10 ms at a relock; and two records read together were stamped out of order by the slopes' difference).
        slew_from = max(edge_ns, self._mono())
        published_then = self._offset_at(slew_from) if predicted is not None else None
        # chrony's "last offset": how far the published time was from this edge's GNSS time.
        self._last_offset_ns = round(predicted - offset) if predicted is not None else None
        gap_s = (edge_ns - self._last_sample_ns) / NS if self._last_sample_ns is not None else math.inf
        restart = predicted is not None and gap_s > self.s.restart_window_after_s
        bound_before = self._err_at(edge_ns, state_before) if restart else 0.0  # the holdover's, this edge ends
        if predicted is not None and not restart:
            self._judge_miss(edge_ns, state_before, predicted - offset)
        else:
            self._forget_misses()
            self._confirm_left = 0
        if restart:
            # After a long gap the old samples describe another temperature: start afresh, keep the frequency.
            self._slope_prior = self._current_slope(edge_ns)
            self._edges.clear()
            self._offsets.clear()
        if not (self._locked_once or self._restored) and self._offsets:
            dt_s = (true_board_ns - self._edges[-1]) / NS
            if abs(offset - self._offsets[-1]) > 2_000_000 + 200e-6 * dt_s * NS:
                # Before the first lock the samples must agree among themselves: a jump means the pairing started
                # a new chain, and the old samples go with the old chain.
                self._edges.clear()
                self._offsets.clear()
        if not self._edges:
            self._base_ns = offset
        self._edges.append(true_board_ns)
        self._offsets.append(offset)
        self._last_sample_ns = edge_ns
        if self.kslew is not None:
            self.kslew.mark_edge(true_board_ns)
        self._pair_lags.append(min(PAIR_LAG_MAX_NS, max(0, self._mono() - edge_ns)))
        self._fresh_ns = round(self.s.holdover_after_s * NS) + max(self._pair_lags)
        self.counts["samples"] += 1
        self._refit()
        if self._follow_change():
            self._forget_misses()  # the fit is now the edges that missed; the slew to it is in the bound
        self._temp_at_fit = self._last_temp[1] if self._last_temp else None
        self._comp_ns = 0.0
        self._comp_abs_ns = 0.0
        if self._fit is not None:
            self.tempco.add(edge_ns, self._fit.slope / NS, self._temp_at_fit, self._fit.n_used)
        if predicted is not None:
            new = self._offset_at(edge_ns, slewed=False)
            step = predicted - new
            if state_before == HOLDOVER:
                self.counts["relocks"] += 1
                # Short dropouts (a shaded antenna, a bridge) are routine in a car: the journal keeps the long ones.
                log.log(logging.INFO if gap_s >= 60.0 else logging.DEBUG,
                        "PPS back after %.1f s: holdover was %+.1f us off", gap_s, step / 1e3)
            if restart:
                # The truth is within the holdover's bound of its prediction, which is |step| from the new fit.
                self._unconfirmed_ns = abs(step) + bound_before
            # Whatever the new fit says, published time moves on continuously: slew the difference out.
            assert published_then is not None
            self._slew_from_ns = slew_from
            self._slew_ns = published_then - self._offset_at(slew_from, slewed=False)
            self._slew_len_ns = max(1, int(abs(self._slew_ns) / (self.s.max_slew_ppm * 1e-6)))
        if len(self._edges) >= CONFIRM_EDGES and not self._confirm_left:
            self._unconfirmed_ns = 0.0
        self._consecutive += 1
        if self.on_sample is not None and self._locked_once and not self.labeller.doubt_ns:
            # Not while the labels may be whole seconds off (a leap count the receiver has not confirmed, labels
            # that disagree): chrony would steer the system clock by them, a second off.
            self.on_sample(true_board_ns, self.labeller.to_unix_plain(label_ns))
        if not self._locked_once and len(self._edges) >= self.s.lock_samples and self._agrees_with_wall(edge_ns):
            self._locked_once = True
            if not self._restored:
                # From free-running time the jump to GNSS time is the point of locking. From a mapping restored
                # after a restart it is not: its holdover's disagreement with the fit goes on being slewed out
                # (cancelled here, published time stepped back 2.8-11 ms at the lock).
                self._slew_from_ns = None
                self._slew_ns = 0.0
            log.info("clock locked to GNSS time (%d PPS edges)", len(self._edges))
        self._maybe_save(edge_ns)

    def _judge_miss(self, edge_ns: int, state_before: str, signed_ns: float) -> None:
        """How far this edge was from the time published for it, against what the fit itself claimed there (its
        bound without the misses' terms and without a followed change's doubt) or, if more, OUTLIER_SIGMAS of its
        residuals (an edge whose interrupt latency varies more than the configured spread is no clock error).
        Beyond it, the miss (with the latency's spread) and its growth go into the bound in place of the claim.

        The growth is the largest of: since the last edge within its bound (consecutive misses differ by their
        edges' jitter too: a 5 ppm ramp's went 23.0, 32.3, 31.0 us); since the edge before, when that one missed
        too; and, after a gap, the whole miss in one second (a change late in a short outage showed its rate only
        in its last seconds). It stays in the bound until CONFIRM_EDGES edges in a row fall within theirs if the
        fit moved meanwhile (a fit that followed a rate step overshoots when the rate steps back: a 50 ppm pulse
        had stamps 94 us off behind 68 us the second after an edge within its bound); if the fit did not move, the
        miss was its edge's alone (an interrupt served late), and the next edge within its bound ends it (one edge
        2 ms late held a bound of 5.6 ms for 5 s)."""
        fit = self._fit
        claimed = self._err_at(edge_ns, state_before, with_doubts=False)
        if fit is not None:
            claimed = max(claimed, OUTLIER_SIGMAS * max(fit.rms, self.s.min_sigma_ns))
        self._recent_misses.append(signed_ns)
        miss_ns = abs(signed_ns)
        good, prev = self._good_miss, self._prev_miss
        self._prev_miss = (edge_ns, miss_ns)
        if miss_ns <= claimed:
            self._good_miss = (edge_ns, miss_ns)
            self._miss_ns = 0.0
            if self._confirm_left:
                self._confirm_left -= 1
            if self._suspect_left:
                self._suspect_left -= 1
                moved = (fit is not None and self._suspect_slope is not None
                         and abs(fit.slope - self._suspect_slope) > self.s.sigma_k * max(fit.skew, 1e-3))
                if not moved:
                    self._suspect_left = 0
            if not self._suspect_left:
                self._miss_growth = 0.0
            return
        self._miss_ns = miss_ns - claimed + self.s.pps_latency_spread_ns
        if self._confirm_left:
            self._confirm_left = CONFIRM_EDGES  # the followed change is not confirmed by an edge that misses it
        if not self._suspect_left:
            self._suspect_slope = fit.slope if fit is not None else None
        self._suspect_left = CONFIRM_EDGES
        growths = [0.0]
        if good is not None:
            growths.append((miss_ns - good[1]) / (edge_ns - good[0]))
        if prev is not None and edge_ns > prev[0]:
            growths.append((miss_ns - prev[1]) / min(edge_ns - prev[0], NS))
        self._miss_growth = max(growths)

    def _follow_change(self) -> bool:
        """Start the fit again from its newest edges when they are a change, not outliers: the last CHANGE_EDGES
        missed by the published time all one way by more than the latency's spread, and on a line of their own
        (within half of it). Not their bounds: a fit that mixes two rates has a bound to match. The regression
        took them for outliers until so many had come that they tilted its line and no longer looked like any:
        after a 500 ppm slew of CLOCK_MONOTONIC for 2 s (NTP) the fit mixed old and new edges (residuals of 200 us)
        and the stamps swung between +1 ms and -0.4 ms for 10 s. Late interrupts of a busy board scatter."""
        fit = self._fit
        k = CHANGE_EDGES
        recent, spread = self._recent_misses, self.s.pps_latency_spread_ns
        if (fit is None or not self._locked_once or len(recent) < k or len(self._edges) <= k
                or not (all(m > spread for m in recent) or all(m < -spread for m in recent))):
            return False
        x = (np.fromiter(self._edges, dtype=np.float64)[-k:] - float(self._edges[-1])) / NS
        y = (np.fromiter(self._offsets, dtype=np.int64)[-k:] - self._base_ns).astype(np.float64)
        own = fit_line(x, y, min_sigma=self.s.min_sigma_ns)
        if own.n_outliers or own.rms > 0.5 * spread:
            return False
        off_by = own.offset_at_ref - fit.offset(0.0)
        edges, offsets = list(self._edges)[-k:], list(self._offsets)[-k:]
        self._edges.clear()
        self._offsets.clear()
        self._edges.extend(edges)
        self._offsets.extend(offsets)
        self._refit()
        # Until edges after them agree, what the fit moved by stays in the bound: four edges served equally late
        # (an interrupt held off at a fixed phase) are a line of their own too, and following them without it
        # claimed 13-61 us for stamps 0.1-1 ms off.
        self._unconfirmed_ns = max(self._unconfirmed_ns, abs(off_by))
        self._confirm_left = CONFIRM_EDGES
        log.log(logging.INFO if abs(off_by) >= 100_000 else logging.DEBUG,
                "clock: the last %d PPS edges are %+.1f us off the fit, on a line of their own (%+.3f ppm): the "
                "board clock's rate changed (NTP slewing it, a temperature step); fitting again from them",
                k, off_by / 1e3, (own.slope - fit.slope) / NS * 1e6)
        return True

    def _forget_misses(self) -> None:
        self._miss_ns = self._miss_growth = 0.0
        self._good_miss = self._prev_miss = None
        self._suspect_left = 0
        self._suspect_slope = None
        self._recent_misses.clear()

    def _agrees_with_wall(self, edge_ns: int) -> bool:
        """Before the first lock: GNSS time within half a second of a synchronised wall clock, or no such clock.

        While they disagree the chain is dropped and paired again; if they still disagree after a minute, GNSS
        wins (the wall clock may claim to be synchronised and be wrong) and that is logged.
        """
        if not self.wall_trusted:
            return True
        wall_offset = self._wall() - self._mono()
        gnss_offset = self._offsets[-1]
        diff = gnss_offset - wall_offset
        if abs(diff) <= WALL_TOLERANCE_NS:
            return True
        if self._wall_disagree_since is None:
            self._wall_disagree_since = edge_ns
            log.warning("GNSS time and the synchronised system clock differ by %.3f s: pairing again", diff / NS)
        elif edge_ns - self._wall_disagree_since > WALL_PATIENCE_NS:
            log.warning("GNSS time still differs from the system clock by %.3f s after a minute: "
                        "trusting GNSS", diff / NS)
            return True
        self.counts["rejected"] += len(self._edges)
        self._edges.clear()
        self._offsets.clear()
        self._fit = None
        self.labeller.restart_chain()
        return False

    def _refit(self) -> None:
        x = (np.fromiter(self._edges, dtype=np.float64) - float(self._edges[-1])) / NS
        y = (np.fromiter(self._offsets, dtype=np.int64) - self._base_ns).astype(np.float64)
        prior = self._slope_prior * NS if self._slope_prior is not None else None  # ns of offset per s
        fit = fit_line(x, y, slope_prior=prior if len(x) < 3 else None, min_sigma=self.s.min_sigma_ns)
        if math.isnan(fit.skew):
            fit = LineFit(fit.x_ref, fit.offset_at_ref, fit.slope, fit.sigma_offset, self._skew_prior * NS, fit.rms,
                          fit.n_used, fit.n_dropped_old, fit.n_outliers)
        self._fit = fit
        self._fit_origin_ns = self._edges[-1]
        if fit.n_used >= 3:
            self._slope_prior = fit.slope / NS
            self._skew_prior = max(fit.skew / NS, 1e-9)

    def _kernel_window(self) -> tuple[int, bool]:
        """The fit's oldest edge in use (the runs test drops stale ones) and whether its slope is its prior (too few
        edges): what the kernel's rate must be measured over to be the one in the fit's slope (sync.kernel_slew)."""
        fit = self._fit
        if fit is None:
            return self._edges[0], True
        return self._edges[min(fit.n_dropped_old, len(self._edges) - 1)], fit.n_used < MIN_SAMPLES_FOR_SLOPE

    def _current_slope(self, t_ns: int) -> float:
        slope = self._fit.slope / NS if self._fit is not None else (self._slope_prior or 0.0)
        k = self.tempco.coefficient()
        if k is not None and self._last_temp is not None and self._temp_at_fit is not None:
            slope += k * (self._last_temp[1] - self._temp_at_fit)
        return slope

    def _on_temperature(self, t_ns: int, temp: float) -> None:
        last = self._last_temp
        bridge = last is None and self._restored and self._temp_at_fit is not None and self._last_sample_ns is not None
        if bridge:
            # Restarted from a saved mapping: bridge the time the daemon was down with what is known of it.
            last = (self._last_sample_ns, self._temp_at_fit)
        self._last_temp = (t_ns, temp)
        if last is None or t_ns <= last[0]:
            return
        dt = (t_ns - last[0]) / NS
        if self._freerun_from_ns is not None and self._freerun_temp is not None and t_ns > self._freerun_from_ns:
            d_free = 0.5 * (temp + last[1]) - self._freerun_temp
            k_free = self.tempco.coefficient()
            if k_free is not None:
                self._freerun_comp_ns += k_free * d_free * dt * NS
            self._freerun_temp_ns += self._tempco_uncertainty() * abs(d_free) * dt * NS
        if self._temp_at_fit is None:
            return
        d_temp = 0.5 * (temp + last[1]) - self._temp_at_fit
        k = self.tempco.coefficient()
        if k is not None:
            self._comp_ns += k * d_temp * dt * NS
        # Between two readings a second apart the mean is the temperature's path; over the minutes the daemon was
        # down it is only a guess (the cabin may have warmed just after the stop): the bound takes the worst path
        # between the two readings, at the further of them all the time.
        spread = max(abs(temp - self._temp_at_fit), abs(last[1] - self._temp_at_fit)) if bridge else abs(d_temp)
        self._comp_abs_ns += self._tempco_uncertainty() * spread * dt * NS

    def _tempco_uncertainty(self) -> float:
        k_sigma = self.tempco.sigma()
        return self.s.tempco_bound_ppm_per_degc * 1e-6 if k_sigma is None else 3.0 * k_sigma

    # ---- what a stamp is ------------------------------------------------------------------------------------
    def _state_at(self, t_ns: int) -> str:
        if not self._locked_once and not self._restored:
            return FREERUN
        if self._last_sample_ns is not None and (t_ns - self._last_sample_ns) <= self._fresh_ns:
            return LOCKED if self._locked_once else HOLDOVER
        return HOLDOVER

    def _offset_at(self, t_ns: int, slewed: bool = True) -> int:
        """GNSS time minus board time at ``t_ns``, in ns: the base (an integer of Unix time's size) plus the fitted
        part, which alone is worked in float64. Summed in float64, 1.8e18 ns has a resolution of 256 ns: every
        stamp and offset came out a multiple of it."""
        fit = self._fit
        assert fit is not None
        x = (t_ns - self._fit_origin_ns) / NS
        rel = fit.offset(x)
        if t_ns > self._last_sample_ns:
            rel += self._comp_ns
            if self.kslew is not None and self._edges:
                rel -= self.kslew.excess(t_ns, *self._kernel_window())
        if slewed and self._slew_from_ns is not None:
            left = 1.0 - (t_ns - self._slew_from_ns) / self._slew_len_ns
            if left > 0:
                rel += self._slew_ns * min(1.0, left)
        return self._base_ns + round(rel)

    def _predict_unix_ns(self, t_ns: int) -> int | None:
        """The clock's current idea of GNSS time at a board time, or None before it knows any."""
        with self._lock:
            if self._fit is None or not (self._locked_once or self._restored):
                return None  # before the first lock the pairing checks pairs against each other only
            return t_ns + round(self._offset_at(t_ns))

    def _err_at(self, t_ns: int, state: str, with_doubts: bool = True) -> float:
        fit = self._fit
        assert fit is not None
        x = (t_ns - self._fit_origin_ns) / NS
        err = self.s.sigma_k * fit.sigma_at(x) + self.s.pps_latency_spread_ns
        since = max(0.0, (t_ns - (self._last_sample_ns or t_ns)) / NS)
        if state == HOLDOVER or since > 0:
            err += self.s.stability_ppm * 1e-6 * since * NS + self._comp_abs_ns
            if self.kslew is not None:
                err += self.kslew.margin_ns
        if with_doubts:
            err += self._unconfirmed_ns + self.labeller.doubt_ns  # a change not confirmed; GNSS time moved
            if self._miss_ns or self._miss_growth:
                err += self._miss_ns + MISS_GROWTH_MARGIN * self._miss_growth * since * NS
        if self._slew_from_ns is not None:
            left = 1.0 - (t_ns - self._slew_from_ns) / self._slew_len_ns
            if left > 0:
                err += abs(self._slew_ns) * min(1.0, left)
        return err

    def stamp(self, t_mono_ns: int) -> Stamp:
        with self._lock:
            if self.kslew is not None:
                self.kslew.sample()
            return self._stamp(t_mono_ns)

    def stamp_many(self, times_ns: Sequence[int]) -> Stamps:
        """A FIFO read's samples under one lock, as arrays: the stamps :meth:`stamp` gives each (the same times; an
        error bound may differ by 1 ns where numpy's hypot rounds otherwise), at a fraction of the cost at 1 kHz."""
        with self._lock:
            t = np.asarray(times_ns, dtype=np.int64)
            imu_cnt, timer_cnt = self.paper.counters_many(times_ns)
            kslew = self.kslew
            if kslew is not None:
                kslew.sample()
            fit = self._fit
            if fit is None or (not self._locked_once and not self._restored):
                n = len(t)
                if self._freerun_from_ns is None:
                    return Stamps((t + self._freerun_offset_ns).tolist(), [FREERUN] * n, [self._freerun_err_ns] * n,
                                  imu_cnt.tolist(), timer_cnt.tolist())
                unix, err = self._repair_run(t)
                return Stamps(unix.tolist(), [FREERUN] * n, err.tolist(), imu_cnt.tolist(), timer_cnt.tolist())
            last = self._last_sample_ns
            s = self.s
            if (len(t) and last is not None and self._locked_once and times_ns[0] > last
                    and times_ns[-1] - last <= self._fresh_ns
                    and (self._slew_from_ns is None or times_ns[0] - self._slew_from_ns >= self._slew_len_ns)):
                # A read wholly after the last edge, fresh and out of any slew (89 % of a simulated 1 kHz run's
                # reads, 47 % at 20 Hz, whose half-second reads straddle an edge as often as not): the forms
                # below without their per-sample choices, in the same order of operations.
                u = (t - self._fit_origin_ns) / NS - fit.x_ref
                rel = (fit.offset_at_ref + fit.slope * u) + self._comp_ns
                err = s.sigma_k * np.hypot(fit.sigma_offset, fit.skew * u) + s.pps_latency_spread_ns
                err = err + (s.stability_ppm * 1e-6 * ((t - last) / NS) * NS + self._comp_abs_ns)
                if kslew is not None:
                    rel = rel - kslew.excess_many(t, *self._kernel_window())
                    err = err + kslew.margin_ns
                err = err + (self._unconfirmed_ns + self.labeller.doubt_ns)
                if self._miss_ns or self._miss_growth:
                    err = err + (self._miss_ns + MISS_GROWTH_MARGIN * self._miss_growth * (t - last))
                unix, leap_err = self.labeller.publish_many(t + self._base_ns + np.rint(rel).astype(np.int64))
                return Stamps(unix.tolist(), [LOCKED] * len(t),
                              np.maximum(1, np.rint(err + leap_err)).astype(np.int64).tolist(), imu_cnt.tolist(),
                              timer_cnt.tolist())
            # _state_at, per sample
            fresh = (t - last) <= self._fresh_ns if last is not None else np.zeros(len(t), bool)
            locked = fresh if self._locked_once else np.zeros(len(t), bool)
            # _offset_at, per sample, in its order of operations
            x = (t - self._fit_origin_ns) / NS
            rel = fit.offset_at_ref + fit.slope * (x - fit.x_ref)
            if last is not None:
                rel = np.where(t > last, rel + self._comp_ns, rel)
                if kslew is not None and self._edges:
                    rel = np.where(t > last, rel - kslew.excess_many(t, *self._kernel_window()), rel)
            # _err_at, per sample
            err = self.s.sigma_k * np.hypot(fit.sigma_offset, fit.skew * (x - fit.x_ref)) + self.s.pps_latency_spread_ns
            since = np.maximum(0.0, (t - (last if last is not None else t)) / NS)
            grow = ~locked | (since > 0)
            err = np.where(grow, err + (self.s.stability_ppm * 1e-6 * since * NS + self._comp_abs_ns
                                        + (kslew.margin_ns if kslew is not None else 0.0)), err)
            err = err + (self._unconfirmed_ns + self.labeller.doubt_ns)
            if self._miss_ns or self._miss_growth:
                err = err + (self._miss_ns + MISS_GROWTH_MARGIN * self._miss_growth * since * NS)
            if self._slew_from_ns is not None:
                left = 1.0 - (t - self._slew_from_ns) / self._slew_len_ns
                part = np.minimum(1.0, left)
                rel = np.where(left > 0, rel + self._slew_ns * part, rel)
                err = np.where(left > 0, err + abs(self._slew_ns) * part, err)
            states = ([LOCKED] * len(t) if locked.all() else
                      [HOLDOVER] * len(t) if not locked.any() else [LOCKED if k else HOLDOVER for k in locked.tolist()])
            unix, leap_err = self.labeller.publish_many(t + self._base_ns + np.rint(rel).astype(np.int64))
            return Stamps(unix.tolist(), states, np.maximum(1, np.rint(err + leap_err)).astype(np.int64).tolist(),
                          imu_cnt.tolist(), timer_cnt.tolist())

    def _stamp(self, t_mono_ns: int) -> Stamp:
        imu_cnt, timer_cnt = self.paper.counters(t_mono_ns)
        state = self._state_at(t_mono_ns)
        if state == FREERUN or self._fit is None:
            if self._freerun_from_ns is None:
                return Stamp(t_mono_ns + self._freerun_offset_ns, FREERUN, self._freerun_err_ns, imu_cnt, timer_cnt)
            unix, err = self._repair_run(np.array([t_mono_ns], dtype=np.int64))
            return Stamp(int(unix[0]), FREERUN, int(err[0]), imu_cnt, timer_cnt)
        off = self._offset_at(t_mono_ns)
        unix, leap_err = self.labeller.publish(t_mono_ns + round(off))
        return Stamp(unix, state, max(1, round(self._err_at(t_mono_ns, state) + leap_err)), imu_cnt, timer_cnt)

    def _repair_run(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (Unix ns) and bounds of board times in the free run after pairing again: the mapping of that
        moment carried on as a holdover's (the fit's frequency then, the learnt temperature correction since, NTP's
        slew since taken out), its bound growing as a holdover's (stability, the temperature's allowance, the
        kernel's margin), published through the leap seconds as locked stamps are. One form for stamp and
        stamp_many: the same times."""
        assert self._freerun_from_ns is not None
        d = t - self._freerun_from_ns
        rel = self._freerun_slope * d + self._freerun_comp_ns
        err = self._freerun_err_ns + self.s.stability_ppm * 1e-6 * np.abs(d) + self._freerun_temp_ns
        kernel = self._freerun_kernel
        if kernel is not None and self.kslew is not None:
            rel = rel - ((self.kslew.at_many(t) - kernel[0]) - kernel[1] * d)
            err = err + self.kslew.margin_ns
        unix, leap_err = self.labeller.publish_many(t + self._freerun_offset_ns + np.rint(rel).astype(np.int64))
        return unix, np.rint(err + leap_err).astype(np.int64)

    # ---- reporting and persistence ----------------------------------------------------------------------------
    def report(self, now_ns: int | None = None) -> TrackingReport:
        """What ``chronyc tracking`` would show, for /sync and ``logger status``."""
        now = self._mono() if now_ns is None else now_ns
        with self._lock:
            st = self.stamp(now)
            fit = self._fit
            since = (now - self._last_sample_ns) / NS if self._last_sample_ns is not None else None
            k = self.tempco.coefficient()
            return TrackingReport(
                t_mono_ns=now, state=st.state, offset_ns=self._last_offset_ns,
                # The board clock's rate error (positive: it runs fast); GNSS minus board drifts the other way.
                freq_ppm=round(-self._current_slope(now) * 1e6, 4) if fit is not None else None,
                skew_ppm=round(fit.skew / NS * 1e6, 5) if fit is not None else None,
                rms_ns=round(fit.rms, 1) if fit is not None else None,
                err_ns=st.err_ns, since_edge_s=round(since, 3) if since is not None else None,
                samples=fit.n_used if fit is not None else 0,
                tempco_ppm_per_degc=round(-k * 1e6, 4) if k is not None else None,
                edges=self.counts["edges"], rejected=self.counts["rejected"], relocks=self.counts["relocks"])

    def _in_doubt(self) -> bool:
        """Whether the newest edges disagree with the fit (misses in the bound) or it is a change not yet confirmed:
        a mapping saved then carried the change's transient rate, or lost what the bound knew of it, into the next
        start (a 50 ppm pulse saved just after the fit followed it: 2.1 ms off 45 s after the restart)."""
        return bool(self._miss_ns or self._miss_growth or self._unconfirmed_ns or self._confirm_left
                    or self.labeller.doubt_ns)

    def _maybe_save(self, now_ns: int) -> None:
        if self.state_path is None or self._fit is None or not self._locked_once or self._in_doubt():
            return
        if self._saved_at is not None and now_ns - self._saved_at < self.s.save_interval_s * NS:
            return
        self._saved_at = now_ns
        self.save()

    def save(self) -> None:
        """Write the frequency (and, for a restart on the same boot, the mapping) like chrony's driftfile."""
        if self.state_path is None or self._fit is None:
            return
        with self._lock:
            if self._last_sample_ns is None:
                return
            if self._in_doubt():
                log.debug("clock state not saved: the newest PPS edges disagree with the fit (the last save stands)")
                return
            ref = self._last_sample_ns
            state = {
                # Unix time, as a later run (which knows of no leap yet) takes it
                "format": STATE_FORMAT, "clock_id": self.clock_id, "ref_mono_ns": ref,
                "ref_offset_ns": self.labeller.to_unix_plain(ref + round(self._offset_at(ref))) - ref,
                # The fit's own frequency, at the temperature it was fitted at (temp_degc): a restart on this boot
                # corrects it for the temperature since, as this run does. The current slope, corrected already,
                # was corrected twice (10-21 ms off after a warming 10 degC in holdover, just over the bound).
                "freq": self._fit.slope / NS, "skew": self._fit.skew / NS,
                "err_ns": round(self._err_at(ref, LOCKED)), "tempco": self.tempco.coefficient(),
                "temp_degc": self._temp_at_fit,
            }
            edge = self.kslew.edge_rate(*self._kernel_window()) if self.kslew is not None and self._edges else None
            if edge is not None:
                # What NTP had done to the monotonic clock by the newest edge, and at what rate over the fit's: a
                # restart on this boot takes out what it did meanwhile (sync.kernel_slew).
                state["kernel"] = {"edge_ns": edge[0], "k_ns": edge[1], "rate": edge[2]}
        tmp = self.state_path.with_suffix(".tmp")
        try:
            self.state_path.parent.mkdir(parents=True, exist_ok=True)
            # Flushed to the card before the rename, as the daemon's other state files (logger.runtime.state_file,
            # which sync may not import): a power cut, how a car's logger stops, leaves the old state or the new
            # one, never an empty file that renamed over the old.
            with open(tmp, "w") as f:
                f.write(json.dumps(state))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.state_path)
        except OSError as exc:
            log.warning("cannot save clock state to %s: %s", self.state_path, exc.strerror or exc)

    def _load(self) -> None:
        if self.state_path is None or not self.state_path.exists():
            return
        try:
            st = json.loads(self.state_path.read_text())
            freq = float(st["freq"])
            skew = float(st["skew"])
        except (OSError, ValueError, KeyError, TypeError):
            log.warning("ignoring unreadable clock state %s", self.state_path)
            return
        if st.get("format") != STATE_FORMAT:
            log.warning("ignoring the clock state %s: saved by another version of the logger (format %s; this one "
                        "reads %d); the clock learns again from the PPS", self.state_path, st.get("format", 1),
                        STATE_FORMAT)
            return
        if not (abs(freq) < 1e-3 and 0 <= skew < 1e-4):
            return
        self._slope_prior = freq
        self._skew_prior = max(skew, 1e-9)
        if st.get("tempco") is not None:
            self.tempco.prior(float(st["tempco"]))
        if self.clock_id and st.get("clock_id") == self.clock_id:
            kernel = st.get("kernel")
            slew: tuple[int, float, float] | None = None
            if self.kslew is not None:
                try:
                    slew = (int(kernel["edge_ns"]), float(kernel["k_ns"]), float(kernel["rate"]))
                except (KeyError, TypeError, ValueError):
                    # Saved off the host's clock, before its first edge, or damaged: what NTP did to the monotonic
                    # clock while the logger was down cannot be taken out, so the mapping is no holdover to stand
                    # behind.
                    log.info("clock state %s: its frequency only (what NTP did to the clock since it was saved is "
                             "unknown); the clock locks again from the PPS", self.state_path)
                    return
            # Same boot: the monotonic clock went on, so the saved mapping still holds; start in holdover.
            ref = int(st["ref_mono_ns"])
            self._edges.append(ref)
            self._offsets.append(int(st["ref_offset_ns"]))
            self._base_ns = int(st["ref_offset_ns"])
            self._last_sample_ns = ref
            self._fit = LineFit(0.0, 0.0, freq * NS, float(st["err_ns"]) / self.s.sigma_k, skew * NS, 0.0, 1, 0, 0)
            self._fit_origin_ns = ref
            self._temp_at_fit = st.get("temp_degc")
            self._restored = True
            if slew is not None and self.kslew is not None:
                self.kslew.restore(*slew)
            log.info("clock restored from %s: holdover from the previous run's mapping", self.state_path)
