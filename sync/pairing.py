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

from collections import deque
from collections.abc import Callable

from sync.inputs import FixEpoch, TimeAnnouncement

NS = 1_000_000_000
UNIX_NS_AT_GPS_EPOCH = 315_964_800 * NS
WEEK_NS = 604_800 * NS
ANNOUNCE_WINDOW_NS = 1_100_000_000  # a TIM-TP is followed by its edge within this
REPORT_WINDOW_NS = 1_000_000_000  # a solution arrives within this after the edge of its second
WHOLE_SECOND_TOLERANCE_NS = 1_000_000
PREDICTION_TOLERANCE_NS = 200_000_000
CHAIN_TOLERANCE_NS = 2_000_000
KEEP_NS = 3 * NS

Predict = Callable[[int], "int | None"]


class EdgeLabeller:
    def __init__(self, latency_ns: int = 0) -> None:
        self.latency_ns = latency_ns
        self.leap_s: int | None = None
        self.rejected = 0
        self.unlabelled = 0
        self.late_reads = 0  # messages not used because the host read them late (with a later second's)
        self._edges: deque[int] = deque()
        self._announced: deque[tuple[int, int]] = deque()  # (received at, label of the next edge)
        self._reported: deque[tuple[int, int]] = deque()  # (received at, epoch just past)
        self._last: tuple[int, int] | None = None  # last accepted (edge, label)

    # ---- inputs ----------------------------------------------------------------------------------------------
    def on_edge(self, edge_ns: int, predict: Predict) -> list[tuple[int, int]]:
        self._edges.append(edge_ns)
        return self._match(predict)

    def on_labelled_edge(self, edge_ns: int, label_ns: int, predict: Predict) -> list[tuple[int, int]]:
        """An edge whose source names the GNSS second it marks (gpsd's PPS report): no matching needed, but
        the label must fall on a whole second and pass the same checks as a matched pair."""
        whole = (label_ns + NS // 2) // NS * NS
        if abs(label_ns - whole) > WHOLE_SECOND_TOLERANCE_NS or not self._accept(edge_ns, label_ns, predict):
            self.rejected += 1
            return []
        return [(edge_ns, label_ns)]

    def on_timepulse(self, tp: TimeAnnouncement, received_ns: int, predict: Predict) -> list[tuple[int, int]]:
        label = self.timepulse_unix_ns(tp)
        if tp.late_read:
            self.late_reads += 1  # when it came is not known: which edge follows it is not either
        elif label is not None:
            self._announced.append((received_ns, label))
        return self._match(predict)

    def on_fix(self, fix: FixEpoch, received_ns: int, predict: Predict) -> list[tuple[int, int]]:
        utc = fix.gnss_time_ns
        itow = fix.itow_ms
        if itow is not None:
            utc_tow_ns = (utc - UNIX_NS_AT_GPS_EPOCH) % WEEK_NS
            leap = round(((itow * 1_000_000 - utc_tow_ns) % WEEK_NS) / NS)
            if 0 <= leap < 100:
                self.leap_s = leap
        whole = round(utc / NS) * NS
        if fix.late_read:
            self.late_reads += 1  # read a second or more after it came: the edge before its read is not its own
        elif abs(utc - whole) <= WHOLE_SECOND_TOLERANCE_NS:
            self._reported.append((received_ns, whole))
        return self._match(predict)

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
            if self._accept(edge, label, predict):
                out.append((edge, label))
            else:
                self.rejected += 1
        self._expire()
        return out

    def _label_for(self, edge: int, predict: Predict) -> int | None:
        # Another, earlier edge in the same window is the better candidate unless the prediction says otherwise.
        for received, label in self._announced:
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

    def _accept(self, edge: int, label: int, predict: Predict) -> bool:
        p = predict(edge)
        if p is not None and abs(p - label) > PREDICTION_TOLERANCE_NS:
            return False
        if p is None and self._last is not None:
            last_edge, last_label = self._last
            if abs((label - last_label) - (edge - last_edge)) > CHAIN_TOLERANCE_NS and edge - last_edge < 100 * NS:
                self._last = (edge, label)  # a chain starts again from here
                return False
        if self._last is not None and label <= self._last[1]:
            return False  # this second has a pulse already
        self._last = (edge, label)
        return True

    def _expire(self) -> None:
        newest = max([*self._edges, *(r for r, _ in self._announced), *(r for r, _ in self._reported)], default=0)
        while self._edges and newest - self._edges[0] > KEEP_NS:
            self._edges.popleft()
            self.unlabelled += 1
        while self._announced and newest - self._announced[0][0] > KEEP_NS:
            self._announced.popleft()
        while self._reported and newest - self._reported[0][0] > KEEP_NS:
            self._reported.popleft()
