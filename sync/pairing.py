"""Which GNSS second does a PPS edge mark? Pairing edges with the receiver's time messages.

The receiver announces the next pulse with UBX TIM-TP some hundreds of ms before it; its navigation solution for
second T (NAV-PVT, or NMEA without UBX) arrives tens to hundreds of ms after the pulse of T. Both reach this code
from other threads, a little late and in any order, so edges and messages wait here until they can be matched.

Checks: a label must fall on a whole second; once the clock has a prediction, the label must agree with it
(a message of the previous second, a false edge or a doubled edge otherwise); before that, consecutive pairs
must agree with each other (labels one second apart for edges one second apart). A message the host read late
(in one read with a later second's: ``late_read``) labels nothing, since the edge before its read may be a later
second's; the clock itself catches a mislabel that got through once a message is read before its own second.
"""

from __future__ import annotations

import datetime as dt
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sync.inputs import FixEpoch, TimeAnnouncement

log = logging.getLogger(__name__)

NS = 1_000_000_000
UNIX_NS_AT_GPS_EPOCH = 315_964_800 * NS
WEEK_NS = 604_800 * NS
ANNOUNCE_WINDOW_NS = 1_100_000_000  # a TIM-TP is followed by its edge within this
REPORT_WINDOW_NS = 1_000_000_000  # a solution arrives within this after the edge of its second
WHOLE_SECOND_TOLERANCE_NS = 1_000_000
PREDICTION_TOLERANCE_NS = 200_000_000
CHAIN_TOLERANCE_NS = 2_000_000
KEEP_NS = 3 * NS
DAY_NS = 86_400 * NS
# A leap second found by its labels alone (gpsd's PPS reports, a receiver that does not send 23:59:60): this many
# labels in a row a whole second off the prediction, the same way, after a month's end, are one. A single label a
# second off is a solution of the previous second or a doubled edge, refused as ever.
LEAP_CONFIRM_LABELS = 3
# Anywhere else, labels that keep disagreeing with the prediction by the same whole seconds are GNSS time moved
# against the clock's (a receiver that corrected its firmware's leap count once its almanac came, mid-month; or the
# clock's own chain a second off): from DOUBT_LABELS in a row the clock's bound takes the disagreement in (from the
# first: a stray label, a doubled edge, widens it until the next label agrees, and the bound never claims what a
# label doubts), and from REPAIR_LABELS in a row it pairs again from the receiver's labels. Refused for good, such
# a receiver held the clock in holdover 1 s off behind a bound of microseconds, every edge rejected.
DOUBT_LABELS = 1
REPAIR_LABELS = 10
# How far a receiver's UTC may be off while it says its leap count is not yet the broadcast one (UBX NAV-TIMEGPS
# leapSValid clear): the count it uses then is its firmware's default, as old as the firmware. GPS-UTC was 15 s
# from 2009 to mid-2012 and is 18 s since 2017-01-01, so firmware of u-blox 6 (2010) onwards is at most 3 s stale.
LEAP_UNKNOWN_NS = 3 * NS
# ... and how long the receiver's last word that its count is not confirmed stands when no word comes after it (a
# receiver read through NMEA or gpsd, or one whose NAV-TIMEGPS was switched off): the almanac's UTC page comes
# within 12.5 min, so after that, and a minute's margin, the count is the broadcast one whatever was last said.
LEAP_UNKNOWN_HOLD_NS = 810 * NS

Predict = Callable[[int], "int | None"]


@dataclass(frozen=True, slots=True)
class Leap:
    """A leap second the clock knows of: at the UTC midnight ``midnight_ns`` (Unix) a second was inserted
    (``sign`` +1: 23:59:60) or deleted (-1: 23:59:59 skipped).

    The clock works in a continuous scale, Unix time as it was before the first leap it saw: after this one, Unix
    time is ``sign`` seconds behind it. Published (Unix) time goes on at the old offset through the inserted second
    (23:59:60.x is published as POSIX's value for it, the 00:00:00.x after it) and from the end of that second (or
    from ``slew_from_ns``, continuous-scale ns, when the leap became known only later) slews the whole second out at
    the clock's slew rate, never stepping and never running backwards: the part not yet slewed out is in the bound.
    """

    midnight_ns: int
    sign: int
    slew_from_ns: int  # continuous-scale time the slew starts: the end of the leap second, or when it became known


def next_month_start_ns(unix_ns: int) -> int:
    """The first 00:00:00 UTC of a month after ``unix_ns``: where a leap second can end (ITU-R TF.460)."""
    day = dt.datetime.fromtimestamp(unix_ns // NS, dt.UTC)
    year, month = (day.year + 1, 1) if day.month == 12 else (day.year, day.month + 1)
    return int(dt.datetime(year, month, 1, tzinfo=dt.UTC).timestamp()) * NS


class EdgeLabeller:
    def __init__(self, latency_ns: int = 0) -> None:
        self.latency_ns = latency_ns
        self.leap_s: int | None = None
        self.rejected = 0
        self.unlabelled = 0
        self.late_reads = 0  # messages not used because the host read them late (with a later second's)
        self._edges: deque[int] = deque()
        # (received at, label of the next edge, True when the label is UTC: it moves when a leap is learnt after it)
        self._announced: deque[tuple[int, int, bool]] = deque()
        self._reported: deque[tuple[int, int]] = deque()  # (received at, epoch just past)
        self._last: tuple[int, int] | None = None  # last accepted (edge, label)
        # Labels are kept in the continuous scale (see Leap); the leaps known so far, oldest first.
        self.leaps: list[Leap] = []
        self.slew_ppm = 500.0  # the clock's slew rate, for the leap's slew
        self.now_ns: Callable[[], int] | None = None  # the clock's board time now, for when a leap became known
        self._candidate: tuple[int, int, int] | None = None  # (midnight, sign, labels so far) of a leap not yet sure
        self._disagree: tuple[int, int] = (0, 0)  # (whole seconds, labels in a row) the labels say off the prediction
        # When the receiver last said its leap count is not the broadcast one (FixEpoch.leap_unknown; None: it said
        # it is, or never said): the word stands until it says otherwise, or for LEAP_UNKNOWN_HOLD_NS without a word
        self._leap_unknown_at: int | None = None
        self.repair_due = False  # REPAIR_LABELS in a row disagreed: the clock is to pair again (take_repair)
        self._last_ambiguous = False  # the last label was a Unix second a leap second shares (gpsd's PPS)
        self._unsure_cache: tuple[object, int | None] | None = None

    # ---- inputs ----------------------------------------------------------------------------------------------
    def on_edge(self, edge_ns: int, predict: Predict) -> list[tuple[int, int]]:
        self._edges.append(edge_ns)
        return self._match(predict)

    def on_labelled_edge(self, edge_ns: int, label_ns: int, predict: Predict) -> list[tuple[int, int]]:
        """An edge whose source names the GNSS second it marks (gpsd's PPS report): no matching needed, but
        the label must fall on a whole second and pass the same checks as a matched pair."""
        whole = (label_ns + NS // 2) // NS * NS
        if abs(label_ns - whole) > WHOLE_SECOND_TOLERANCE_NS:
            self.rejected += 1
            return []
        label = self._accept(edge_ns, self.to_cont(label_ns), predict)
        if label is None:
            self.rejected += 1
            return []
        # gpsd names 23:59:60 and the 00:00:00 after it by one Unix second: a midnight label says nothing sure yet
        self._last_ambiguous = whole % DAY_NS == 0
        return [(edge_ns, label)]

    def on_timepulse(self, tp: TimeAnnouncement, received_ns: int, predict: Predict) -> list[tuple[int, int]]:
        label = self.timepulse_unix_ns(tp)
        if tp.late_read:
            self.late_reads += 1  # when it came is not known: which edge follows it is not either
        elif label is not None:
            # GPS time knows no leap seconds: GPS time less the GPS-UTC of before the first leap seen is the
            # continuous scale itself (the leaps since are in leap_s, which moves with them).
            cont = self.to_cont(label) if tp.utc else label + self._leaps_shift_ns()
            self._announced.append((received_ns, cont, tp.utc))
        return self._match(predict)

    def on_fix(self, fix: FixEpoch, received_ns: int, predict: Predict) -> list[tuple[int, int]]:
        utc = fix.gnss_time_ns
        if fix.leap_unknown is not None:  # an epoch without the word (a NAV-TIMEGPS dropped) changes nothing
            self._leap_unknown_at = received_ns if fix.leap_unknown else None
        itow = fix.itow_ms
        if fix.leap_second and utc % DAY_NS < NS:
            # The receiver says this epoch is 23:59:60: the Unix second after it repeats this one's.
            self._learn_leap(utc - utc % DAY_NS, 1, received_ns, predict)
        if itow is not None and not fix.leap_second:  # (23:59:60's own iTOW gives the GPS-UTC of before it)
            utc_tow_ns = (utc - UNIX_NS_AT_GPS_EPOCH) % WEEK_NS
            leap = round(((itow * 1_000_000 - utc_tow_ns) % WEEK_NS) / NS)
            if 0 <= leap < 100:
                if self.leap_s is not None and abs(leap - self.leap_s) == 1 and not self._known(utc):
                    # GPS-UTC moved by a second (a receiver whose 23:59:60 did not reach us): a leap at the month's
                    # end just past, if there was one since the last label.
                    midnight = self._month_end_before(utc)
                    if midnight is not None:
                        self._learn_leap(midnight, leap - self.leap_s, received_ns, predict)
                self.leap_s = leap
        whole = round(utc / NS) * NS
        if fix.late_read:
            self.late_reads += 1  # read a second or more after it came: the edge before its read is not its own
        elif abs(utc - whole) <= WHOLE_SECOND_TOLERANCE_NS:
            # Its edge is the one before its first message (an epoch can end after the next pulse on a slow line).
            began = fix.opened_ns if fix.opened_ns is not None and fix.opened_ns < received_ns else received_ns
            self._reported.append((began, self.to_cont(whole, fix.leap_second)))
        return self._match(predict)

    # ---- leap seconds ----------------------------------------------------------------------------------------
    def _leaps_shift_ns(self) -> int:
        return sum(leap.sign for leap in self.leaps) * NS

    def to_cont(self, unix_ns: int, leap_second: bool = False) -> int:
        """A Unix (UTC) label in the clock's continuous scale: plus each known leap it comes after (23:59:60 itself,
        ``leap_second``, comes before the one it is)."""
        cont = unix_ns
        for leap in self.leaps:
            inside = leap_second and leap.sign > 0 and leap.midnight_ns <= unix_ns < leap.midnight_ns + NS
            if unix_ns >= leap.midnight_ns and not inside:
                cont += leap.sign * NS
        return cont

    def _leap_end_cont(self, leap: Leap) -> int:
        """Where in the continuous scale Unix time moves by the leap: the end of 23:59:60 (the start of the
        00:00:00 after 23:59:58, for a deleted second)."""
        before = sum(other.sign for other in self.leaps if other.midnight_ns < leap.midnight_ns) * NS
        return leap.midnight_ns + before + leap.sign * NS

    def publish(self, cont_ns: int) -> tuple[int, float]:
        """A stamp in the continuous scale -> (Unix ns to publish, what to add to its bound): see :class:`Leap`;
        plus a second in the bound where a leap may have happened that nothing has told of yet."""
        unix, extra = cont_ns, 0.0
        for leap in self.leaps:
            if cont_ns >= self._leap_end_cont(leap):
                left = self._left(leap, cont_ns)
                unix -= leap.sign * round(NS * (1.0 - left))
                extra += NS * left
        unsure = self._unsure_from()
        if unsure is not None and cont_ns >= unsure:
            extra += NS
        return unix, extra

    def publish_many(self, cont_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`publish` for an array of stamps (int64 ns): (Unix ns, bound to add)."""
        unsure = self._unsure_from()
        if not self.leaps and (unsure is None or not len(cont_ns) or int(cont_ns.max()) < unsure):
            return cont_ns, np.zeros(len(cont_ns))  # no leap and none in doubt: a FIFO read's usual case
        unix = cont_ns.copy()
        extra = np.zeros(len(cont_ns))
        for leap in self.leaps:
            after = cont_ns >= self._leap_end_cont(leap)
            if after.any():
                left = np.clip(1.0 - (cont_ns - leap.slew_from_ns) / (NS / (self.slew_ppm * 1e-6)), 0.0, 1.0)
                left = np.where(after, left, 0.0)
                unix = unix - np.where(after, leap.sign * np.rint(NS * (1.0 - left)).astype(np.int64), 0)
                extra = extra + NS * left
        if unsure is not None:
            extra = extra + np.where(cont_ns >= unsure, float(NS), 0.0)
        return unix, extra

    def _left(self, leap: Leap, cont_ns: int) -> float:
        """The part of the leap's second not yet slewed out at ``cont_ns``."""
        return min(1.0, max(0.0, 1.0 - (cont_ns - leap.slew_from_ns) / (NS / (self.slew_ppm * 1e-6))))

    def _unsure_from(self) -> int | None:
        """The cached :meth:`_unsure_from_now` (stamps ask for it; it changes only with a label or a leap)."""
        key = (self._last, self._candidate, len(self.leaps), self._last_ambiguous)
        if self._unsure_cache is None or self._unsure_cache[0] != key:
            self._unsure_cache = (key, self._unsure_from_now())
        return self._unsure_cache[1]

    def _unsure_from_now(self) -> int | None:
        """Continuous-scale time from which a stamp may be a whole second off by a leap nothing told of: the end of
        a possible leap second at the first month's end after the last label (until a label after it shows whether
        it came), and from a leap's first labels until they are enough to be sure of it."""
        if self._candidate is not None:
            return self.to_cont(self._candidate[0]) + NS
        if self._last is None:
            return None
        last_unix = self.to_unix_plain(self._last[1])
        midnight = next_month_start_ns(last_unix - (NS if self._last_ambiguous else 0))
        if self._known(midnight):
            return None
        return self.to_cont(midnight) + NS

    def to_unix_plain(self, cont_ns: int) -> int:
        """A continuous-scale time as Unix time, with every known leap whole (no slew): for labels."""
        unix = cont_ns
        for leap in self.leaps:
            if cont_ns >= self._leap_end_cont(leap):
                unix -= leap.sign * NS
        return unix

    def _known(self, unix_ns: int) -> bool:
        """Whether a leap is known at the month's end at or just before ``unix_ns``."""
        return any(0 <= unix_ns - leap.midnight_ns < 2 * DAY_NS for leap in self.leaps)

    def _month_end_before(self, unix_ns: int) -> int | None:
        """The month's end between the last label and ``unix_ns``, if one is."""
        if self._last is None:
            return None
        midnight = next_month_start_ns(self.to_unix_plain(self._last[1]) - NS)
        return midnight if midnight <= unix_ns else None

    def _learn_leap(self, midnight_ns: int, sign: int, received_ns: int | None, predict: Predict) -> None:
        """Take a leap second: labels after it move into the continuous scale, and GPS-UTC with it."""
        if self._known(midnight_ns):
            return
        leap = Leap(midnight_ns, sign, 0)
        end = self._leap_end_cont(leap)
        t_now = self.now_ns() if self.now_ns is not None else received_ns
        now = predict(t_now) if t_now is not None else None
        self.leaps.append(Leap(midnight_ns, sign, max(end, now) if now is not None else end))
        self.leaps.sort(key=lambda x: x.midnight_ns)
        self._candidate = None
        if self.leap_s is not None:
            self.leap_s += sign
        # Labels queued before it was known, from Unix time after it, move with it (GPS-time ones do not).
        self._reported = deque((r, lab + sign * NS if lab >= midnight_ns else lab) for r, lab in self._reported)
        self._announced = deque((r, lab + sign * NS if utc and lab >= midnight_ns else lab, utc)
                                for r, lab, utc in self._announced)
        when = dt.datetime.fromtimestamp(midnight_ns // NS, dt.UTC).strftime("%Y-%m-%d")
        log.warning("clock: a leap second %s at the end of the day before %s UTC; published time slews the second "
                    "out at %.0f ppm, the rest of it in the error bound", "inserted" if sign > 0 else "deleted",
                    when, self.slew_ppm)

    def _leap_from_labels(self, label: int, p: int, predict: Predict) -> int | None:
        """A label a whole second off the prediction after a month's end: a leap second nobody announced (gpsd's
        repeated second, a receiver that skips 23:59:60). Taken once LEAP_CONFIRM_LABELS in a row say so; returns
        the label in the continuous scale then, else None (refused, as any label that disagrees)."""
        diff = p - label
        sign = round(diff / NS)
        if abs(sign) != 1 or abs(diff - sign * NS) > PREDICTION_TOLERANCE_NS or self._last is None:
            return None
        unix = self.to_unix_plain(label)
        midnight = next_month_start_ns(self.to_unix_plain(self._last[1]) - NS)
        if not midnight <= unix or self._known(midnight):
            return None
        cand = self._candidate
        count = cand[2] + 1 if cand is not None and cand[:2] == (midnight, sign) else 1
        self._candidate = (midnight, sign, count)
        if count < LEAP_CONFIRM_LABELS:
            return None
        self._learn_leap(midnight, sign, None, predict)
        return label + sign * NS

    def timepulse_unix_ns(self, tp: TimeAnnouncement) -> int | None:
        """The Unix time (ns, UTC) of the edge a TIM-TP announces; None while GPS-UTC is unknown for a GPS pulse."""
        sub_ns = round(tp.tow_sub_ms * 1e6)
        t = UNIX_NS_AT_GPS_EPOCH + tp.week * WEEK_NS + tp.tow_ms * 1_000_000 + sub_ns
        if not tp.utc:
            if self.leap_s is None:
                return None  # GPS-based pulse time, and GPS-UTC not known yet
            t -= self.leap_s * NS
        # The receiver puts the pulse qErr early of the ideal instant it announces.
        return t - round(tp.qerr_ps / 1000)

    def restart_chain(self) -> None:
        """Forget the last accepted pair: the next pairs must agree among themselves again."""
        self._last = None

    # ---- matching --------------------------------------------------------------------------------------------
    def _match(self, predict: Predict) -> list[tuple[int, int]]:
        out: list[tuple[int, int]] = []
        for edge in list(self._edges):
            label = self._label_for(edge, predict)
            if label is None:
                continue
            self._edges.remove(edge)
            accepted = self._accept(edge, label, predict)
            if accepted is not None:
                self._last_ambiguous = False
                out.append((edge, accepted))
            else:
                self.rejected += 1
        self._expire()
        return out

    def _label_for(self, edge: int, predict: Predict) -> int | None:
        # Another, earlier edge in the same window is the better candidate unless the prediction says otherwise.
        for received, label, _utc in self._announced:
            if received < edge <= received + ANNOUNCE_WINDOW_NS and self._first_candidate(edge, received, label,
                                                                                          predict):
                return label
        for received, label in self._reported:
            if received - REPORT_WINDOW_NS < edge < received and self._first_candidate(
                    edge, received - REPORT_WINDOW_NS, label, predict):
                return label
        return None

    def _first_candidate(self, edge: int, window_start: int, label: int, predict: Predict) -> bool:
        others = [e for e in self._edges if window_start < e < edge]
        if not others:
            return True
        p = predict(edge)
        if p is None:
            return False  # keep the earliest edge: a glitch comes after the real one
        best = min([edge, *others], key=lambda e: abs((predict(e) or 0) - label))
        return best == edge

    def _accept(self, edge: int, label: int, predict: Predict) -> int | None:
        """The label (continuous scale) an edge is paired with, or None when the pair is refused."""
        p = predict(edge)
        if p is not None and abs(p - label) > PREDICTION_TOLERANCE_NS:
            moved = self._leap_from_labels(label, p, predict)
            if moved is None:
                self._count_disagreement(label - p)
                return None
            label = moved
        if p is None and self._last is not None:
            last_edge, last_label = self._last
            if abs((label - last_label) - (edge - last_edge)) > CHAIN_TOLERANCE_NS and edge - last_edge < 100 * NS:
                self._last = (edge, label)  # a chain starts again from here
                return None
        if self._last is not None and label <= self._last[1]:
            return None  # this second has a pulse already
        self._last = (edge, label)
        self._candidate = None
        self._disagree = (0, 0)
        return label

    def _count_disagreement(self, diff_ns: int) -> None:
        """A label refused for disagreeing with the prediction: counted when by whole seconds, as the last ones."""
        k = round(diff_ns / NS)
        if k == 0 or abs(diff_ns - k * NS) > PREDICTION_TOLERANCE_NS:
            self._disagree = (0, 0)
            return
        n = self._disagree[1] + 1 if self._disagree[0] == k else 1
        self._disagree = (k, n)
        if n >= REPAIR_LABELS:
            self.repair_due = True

    @property
    def doubt_ns(self) -> int:
        """The whole seconds the latest labels (DOUBT_LABELS or more in a row) say the clock is off, or a receiver
        without its broadcast leap count may be (LEAP_UNKNOWN_NS): its bound's."""
        k, n = self._disagree
        said = abs(k) * NS if n >= DOUBT_LABELS else 0
        return max(said, LEAP_UNKNOWN_NS) if self.leap_unknown else said

    @property
    def leap_unknown(self) -> bool:
        """Whether the receiver's last word on its leap count, within LEAP_UNKNOWN_HOLD_NS, was "not confirmed"."""
        at = self._leap_unknown_at
        if at is None:
            return False
        return self.now_ns is None or self.now_ns() - at <= LEAP_UNKNOWN_HOLD_NS

    def take_repair(self) -> int | None:
        """The disagreement (ns, labels minus prediction) when REPAIR_LABELS in a row said it, once; else None."""
        if not self.repair_due:
            return None
        self.repair_due = False
        k = self._disagree[0]
        self._disagree = (0, 0)
        self._last = None  # the receiver's labels make the chain from here
        return k * NS

    def _expire(self) -> None:
        newest = max([*self._edges, *(r for r, _, _ in self._announced), *(r for r, _ in self._reported)], default=0)
        while self._edges and newest - self._edges[0] > KEEP_NS:
            self._edges.popleft()
            self.unlabelled += 1
        while self._announced and newest - self._announced[0][0] > KEEP_NS:
            self._announced.popleft()
        while self._reported and newest - self._reported[0][0] > KEEP_NS:
            self._reported.popleft()
