"""The receiver's solution as ``logger status`` shows it: fix type, satellites, accuracy, PDOP, and how long ago.

What ``cgps`` shows first, and what tells an operator in a tunnel that the logger is fine and the sky is not: the
receiver keeps talking at its rate (its row stays at 1 Hz) while it has no fix. A tap on ``/gnss/fix`` keeps the
last record and when the last valid fix came; ``offer`` only assigns, so it never holds the sink up.

With ``[gnss] raw_observations`` asked for, the same tap counts the RXM-RAWX frames in ``/gnss/raw`` (the bytes as
read, so a receiver that acknowledged them and sends none shows as such): the status shows their rate, and their
absence as a problem, since a drive meant for RTKLIB is worth little without them. Finding a four-byte header in a
second's bytes costs microseconds, so the sink is still not held up.
"""

from __future__ import annotations

import base64
from typing import Any

from logger.recording.records import NO_FIX, fix_name
from logger.recording.topics import GNSS_FIX, GNSS_RAW
from logger.words import plural

NO_FIX_PROBLEM_S = 3.0  # a receiver that reports no fix for longer than this is a problem in the status
NO_RAW_PROBLEM_S = 10.0  # raw observations asked for and none for this long while the receiver reports: a problem
RAW_RATE_FRAMES = 11  # the rate of RXM-RAWX is measured over the last this many
RAWX_HEADER = b"\xb5\x62\x02\x15"  # UBX sync, class RXM, id RAWX


class GnssWatch:
    """The last ``/gnss/fix`` record and the receiver's last valid fix, for the status snapshot."""

    def __init__(self, raw_asked: bool = False) -> None:
        # (last record, board time of the last valid fix, start of the present run without one): one tuple, so a
        # reader in another thread never sees one record's fix with another's times.
        self._seen: tuple[dict[str, Any], int | None, int | None] | None = None
        self.raw_asked = raw_asked
        self._rawx_times: tuple[int, ...] = ()  # board times of the last RXM-RAWX frames (replaced, never mutated)
        self._raw_tail = b""  # the last bytes of the previous read: a header split between two reads still counts
        self._first_report: int | None = None

    def offer(self, topic: str, payload: dict[str, Any]) -> None:
        if topic == GNSS_RAW and self.raw_asked:
            self._count_rawx(payload)
            return
        if topic != GNSS_FIX:
            return
        if self._first_report is None:
            self._first_report = payload["t_mono_ns"]
        t = payload["t_mono_ns"]
        _, last_fix, no_fix_since = self._seen or (None, None, None)
        if fix_name(payload) != NO_FIX:
            last_fix, no_fix_since = t, None
        elif no_fix_since is None:
            no_fix_since = t if last_fix is None else last_fix
        self._seen = (payload, last_fix, no_fix_since)

    def _count_rawx(self, payload: dict[str, Any]) -> None:
        data = self._raw_tail + base64.b64decode(payload["data_b64"])
        n = data.count(RAWX_HEADER)
        self._raw_tail = data[-(len(RAWX_HEADER) - 1):]
        if n:
            self._rawx_times = (*self._rawx_times, *(payload["t_mono_ns"],) * n)[-RAW_RATE_FRAMES:]

    def raw_section(self, now_ns: int) -> dict[str, Any]:
        """``raw_hz`` (None until two came) and ``raw_age_s`` (None: none yet) of RXM-RAWX, when asked for."""
        times = self._rawx_times
        span = (times[-1] - times[0]) / 1e9 if len(times) >= 2 else 0.0
        return {"raw_hz": (len(times) - 1) / span if span > 0 else None,
                "raw_age_s": (now_ns - times[-1]) / 1e9 if times else None}

    def raw_problem(self, now_ns: int) -> str | None:
        """``no raw observations for 12 s`` once the receiver has reported a while without RXM-RAWX."""
        if not self.raw_asked or self._first_report is None:
            return None
        times = self._rawx_times
        since = max(self._first_report, times[-1]) if times else self._first_report
        s = (now_ns - since) / 1e9
        if s < NO_RAW_PROBLEM_S:
            return None
        return (f"no raw observations (RXM-RAWX) for {s:.0f} s" if times else
                f"no raw observations (RXM-RAWX) in {s:.0f} s: [gnss] raw_observations asks for them, the receiver "
                "refused or does not send them (see the log)")

    def no_fix_s(self, now_ns: int) -> float | None:
        """How long the receiver has reported no fix (since its last one, or its first report), None with a fix."""
        seen = self._seen
        return None if seen is None or seen[2] is None else (now_ns - seen[2]) / 1e9

    def section(self, now_ns: int) -> dict[str, Any] | None:
        """The ``gnss`` section of the snapshot; None before the receiver's first solution."""
        seen = self._seen
        if seen is None:
            return None
        last, last_fix, no_fix_since = seen
        return {"fix": fix_name(last), "num_sv": last.get("num_sv"), "h_acc_m": last.get("h_acc_m"),
                "pdop": last.get("pdop"), "age_s": (now_ns - last["t_mono_ns"]) / 1e9,
                "last_fix_age_s": (now_ns - last_fix) / 1e9 if last_fix is not None else None,
                "no_fix_s": (now_ns - no_fix_since) / 1e9 if no_fix_since is not None else None,
                **(self.raw_section(now_ns) if self.raw_asked else {})}

    def problem(self, now_ns: int) -> str | None:
        """``no fix for 42 s (0 satellites)`` once the receiver has gone without one for a few seconds."""
        s = self.no_fix_s(now_ns)
        if s is None or s < NO_FIX_PROBLEM_S:
            return None
        sv = self._seen[0].get("num_sv") if self._seen else None
        used = "" if sv is None else f" ({plural(sv, 'satellite')} in use)"
        return f"no fix for {s:.0f} s{used}"
