"""How regularly each sensor topic was recorded: rate over time, messages lost, and gaps.

Two independent witnesses: the per-topic ``seq`` counter (set by the sampler for every sample it produced, so
a jump is a message that never reached the file, and a step back is a restart of the daemon) and the message
times (a gap is an interval much longer than the topic's usual one, which also shows a sensor that fell silent
without any message being lost). Rate and gaps follow :mod:`logger.recording.intervals`, as ``logger info``
does, so the two never disagree on a file.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from logger.recording.drive import DriveMessage
from logger.recording.intervals import GAP_FACTOR, regularity
from logger.recording.topics import BARO, GNSS_FIX, IMU, OBD_SPEED, PPS, TIMEPULSE

STAMPED_TOPICS = (IMU, OBD_SPEED, BARO, GNSS_FIX, TIMEPULSE, PPS)


@dataclass
class Gap:
    before_ns: int  # log time of the last message before
    after_ns: int  # log time of the first message after
    interval_s: float


@dataclass
class TopicTiming:
    topic: str
    log_ns: np.ndarray  # MCAP log time of each message, Unix ns
    mono_ns: np.ndarray
    seq: np.ndarray
    sync_state: list[str]
    sync_err_ns: np.ndarray
    median_interval_s: float = 0.0
    rate_hz: float = 0.0  # over the topic's span
    lost: list[tuple[int, int]] = field(default_factory=list)  # (log time of the message after, messages lost)
    restarts: list[int] = field(default_factory=list)  # log times where seq started again
    gaps: list[Gap] = field(default_factory=list)

    @property
    def n_lost(self) -> int:
        return sum(n for _, n in self.lost)

    def rate(self, t0_ns: int, bin_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Messages per second in whole bins of ``bin_s`` of log time from the topic's first message (a part
        bin at the end would read low): (bin centres in s from t0, rate in Hz)."""
        t = (self.log_ns - t0_ns) / 1e9
        if len(t) < 2:
            return np.zeros(0), np.zeros(0)
        n = max(1, int((t.max() - t.min()) // bin_s))
        edges = t.min() + bin_s * np.arange(n + 1)
        counts, _ = np.histogram(t, bins=edges)
        return (edges[:-1] + edges[1:]) / 2.0, counts / bin_s

    def summary(self) -> str:
        largest = max((g.interval_s for g in self.gaps), default=0.0)
        text = (f"{self.topic}: {len(self.log_ns)} messages at {self.rate_hz:.2f} Hz; lost by seq: {self.n_lost}; "
                f"gaps over {GAP_FACTOR:g}x the usual interval: {len(self.gaps)}"
                + (f" (largest {largest:.2f} s)" if self.gaps else ""))
        return text + (f"; restarts: {len(self.restarts)}" if self.restarts else "")


def topic_timing(topic: str, rows: list[tuple[int, int, int, str, int]]) -> TopicTiming:
    """From (log_ns, t_mono_ns, seq, sync_state, sync_err_ns) in log-time order."""
    arr = np.array([r[:3] for r in rows], dtype=np.int64).reshape(-1, 3)
    tt = TopicTiming(topic, arr[:, 0], arr[:, 1], arr[:, 2], [r[3] for r in rows],
                     np.array([r[4] for r in rows], dtype=np.int64))
    if len(rows) < 2:
        return tt
    dseq = np.diff(tt.seq)
    reg = regularity(tt.log_ns.tolist())
    tt.median_interval_s, tt.rate_hz = reg.median_interval_s, reg.rate_hz
    for i in np.nonzero(dseq > 1)[0]:
        tt.lost.append((int(tt.log_ns[i + 1]), int(dseq[i] - 1)))
    tt.restarts = [int(tt.log_ns[i + 1]) for i in np.nonzero(dseq < 0)[0]]
    tt.gaps = [Gap(a, b, (b - a) / 1e9) for a, b in reg.gaps]
    return tt


def timings(messages: list[DriveMessage]) -> dict[str, TopicTiming]:
    """Per stamped topic present in the messages (live files only: a replay has no sensor topics)."""
    rows: dict[str, list[tuple[int, int, int, str, int]]] = {}
    for m in messages:
        if m.topic in STAMPED_TOPICS and "seq" in m.msg:
            d = m.msg
            rows.setdefault(m.topic, []).append((m.log_time, d["t_mono_ns"], d["seq"], d.get("sync_state", ""),
                                                 d.get("sync_err_ns", 0)))
    return {t: topic_timing(t, rows[t]) for t in STAMPED_TOPICS if t in rows}
