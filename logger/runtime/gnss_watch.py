"""The receiver's solution as ``logger status`` shows it: fix type, satellites, accuracy, PDOP, and how long ago.

What ``cgps`` shows first, and what tells an operator in a tunnel that the logger is fine and the sky is not: the
receiver keeps talking at its rate (its row stays at 1 Hz) while it has no fix. A tap on ``/gnss/fix`` keeps the
last record and when the last valid fix came; ``offer`` only assigns, so it never holds the sink up.
"""

from __future__ import annotations

from typing import Any

from logger.recording.records import NO_FIX, fix_name
from logger.recording.topics import GNSS_FIX
from logger.words import plural

NO_FIX_PROBLEM_S = 3.0  # a receiver that reports no fix for longer than this is a problem in the status


class GnssWatch:
    """The last ``/gnss/fix`` record and the receiver's last valid fix, for the status snapshot."""

    def __init__(self) -> None:
        # (last record, board time of the last valid fix, start of the present run without one): one tuple, so a
        # reader in another thread never sees one record's fix with another's times.
        self._seen: tuple[dict[str, Any], int | None, int | None] | None = None

    def offer(self, topic: str, payload: dict[str, Any]) -> None:
        if topic != GNSS_FIX:
            return
        t = payload["t_mono_ns"]
        _, last_fix, no_fix_since = self._seen or (None, None, None)
        if fix_name(payload) != NO_FIX:
            last_fix, no_fix_since = t, None
        elif no_fix_since is None:
            no_fix_since = t if last_fix is None else last_fix
        self._seen = (payload, last_fix, no_fix_since)

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
                "no_fix_s": (now_ns - no_fix_since) / 1e9 if no_fix_since is not None else None}

    def problem(self, now_ns: int) -> str | None:
        """``no fix for 42 s (0 satellites)`` once the receiver has gone without one for a few seconds."""
        s = self.no_fix_s(now_ns)
        if s is None or s < NO_FIX_PROBLEM_S:
            return None
        sv = self._seen[0].get("num_sv") if self._seen else None
        used = "" if sv is None else f" ({plural(sv, 'satellite')} in use)"
        return f"no fix for {s:.0f} s{used}"
