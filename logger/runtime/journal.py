"""The journal's side of health: each problem logged when it appears and when it clears, flapping ones rate-limited.

One rate limiter serves every place that logs a recurring fault (the daemon's status problems, a sensor thread's
errors), and one rule says when two lines are the same fault: their text with the numbers (and a size's unit) and
file names masked ("no sample for 4.2 s" and "no sample for 5.1 s" are one problem while it lasts, "984 KiB free" and
"1.2 MiB free" too). A component whose one problem turns into another in the same second ("recorder: not recording:
Input/output error" then "... Read-only file system") is said to have changed, not to be resolved: it never was.
"""

from __future__ import annotations

import logging
import re

PROBLEM_LOG_REPEAT_S = 60.0  # a problem that comes and goes is logged at most this often (on average)
STILL_EVERY_S = 60.0  # a problem that lasts is said again this often, with how long it has lasted
MAX_KEYS = 256
_NUMBERS = re.compile(r"\d+(?:\.\d+)?(?: ?(?:[KMGT]iB|[kMGT]B|bytes)\b)?")
_FILES = re.compile(r"[\w.-]+\.mcap\b")  # a file renamed while the problem lasts (boot name -> dated name)


def problem_key(text: str) -> str:
    """What stays of a problem's line while it lasts: the line with every number (with its unit, for a size)
    and every file name masked."""
    return _NUMBERS.sub("#", _FILES.sub("FILE", text))


def subject(text: str) -> str:
    """Whose problem a line is: what comes before its first ": " (``recorder``, ``imu``)."""
    return text.split(": ", 1)[0]


class RateLimiter:
    """A token bucket per key: ``burst`` lines at once, refilled at one per ``refill_s``.

    A fault every few minutes is logged every time; one flapping every second is logged a few times a minute,
    and the next line that gets through says how many were held back. Bounded whatever the keys are.
    """

    def __init__(self, burst: int, refill_s: float, max_keys: int = MAX_KEYS) -> None:
        self.burst = burst
        self.refill_s = refill_s
        self.max_keys = max_keys
        self._tokens: dict[str, tuple[float, float]] = {}  # key -> (tokens, when counted)
        self._held: dict[str, int] = {}

    def allow(self, key: str, now_s: float) -> tuple[bool, int]:
        """Whether a line for ``key`` may go out now, and how many were held back before it (0 when refused)."""
        tokens, when = self._tokens.get(key, (float(self.burst), now_s))
        tokens = min(float(self.burst), tokens + (now_s - when) / self.refill_s)
        if tokens >= 1.0:
            self._tokens[key] = (tokens - 1.0, now_s)
            return True, self._held.pop(key, 0)
        self._tokens[key] = (tokens, now_s)
        self._held[key] = self._held.get(key, 0) + 1
        return False, 0

    def prune(self, now_s: float, keep: set[str] | frozenset[str] = frozenset()) -> None:
        """Past ``max_keys``: forget the buckets that have refilled by ``now_s`` (they would let the next line
        through anyway), then, if still too many, every key not in ``keep``."""
        if len(self._tokens) <= self.max_keys:
            return

        def full(v: tuple[float, float]) -> bool:
            return v[0] + (now_s - v[1]) / self.refill_s >= self.burst

        self._tokens = {k: v for k, v in self._tokens.items() if k in keep or not full(v)}
        if len(self._tokens) > self.max_keys:
            self._tokens = {k: v for k, v in self._tokens.items() if k in keep}
        self._held = {k: v for k, v in self._held.items() if k in self._tokens}


class ProblemJournal:
    """Turns the status problems of each second into journal lines: one when a problem appears, one a minute while
    it lasts (how long so far), one when it clears.

    A problem is keyed by its text with numbers masked ("no sample for 4.2 s" stays one problem while it lasts).
    Each key may announce itself ``burst`` times, refilled at one per ``refill_s``: a fault every few minutes is
    logged every time, a sensor flapping every second is logged a few times a minute with a count of the rest.
    """

    def __init__(self, burst: int = 5, refill_s: float = PROBLEM_LOG_REPEAT_S / 5,
                 still_every_s: float = STILL_EVERY_S) -> None:
        # key -> (text, announced, since, last said): "resolved" tells its last state, "still" how long
        self._active: dict[str, tuple[str, bool, float, float]] = {}
        self._limiter = RateLimiter(burst, refill_s)
        self.still_every_s = still_every_s

    def update(self, problems: list[str], now_s: float) -> list[tuple[int, str]]:
        """The lines to log for this second's problems, as (logging level, text)."""
        out: list[tuple[int, str]] = []
        current = {problem_key(p): p for p in problems}
        self._carry_changes(current, now_s, out)
        for key, text in current.items():
            if key in self._active:
                _, announced, since, said = self._active[key]
                if announced and now_s - said >= self.still_every_s:
                    out.append((logging.WARNING, f"still: {text} (for {now_s - since:.0f} s)"))
                    said = now_s
                self._active[key] = (text, announced, since, said)
                continue
            announce, unlogged = self._limiter.allow(key, now_s)
            if announce:
                out.append((logging.WARNING, f"problem: {text}"
                            + (f" (appeared {unlogged} more times, not logged)" if unlogged else "")))
            self._active[key] = (text, announce, now_s, now_s)
        for key in [k for k in self._active if k not in current]:
            text, announced, since, _ = self._active.pop(key)
            if announced:
                out.append((logging.INFO, f"resolved: {text} (lasted {now_s - since:.0f} s)"))
        self._limiter.prune(now_s, set(self._active))  # bounded whatever the problems say
        return out

    def _carry_changes(self, current: dict[str, str], now_s: float, out: list[tuple[int, str]]) -> None:
        """A component's only problem gone and its only new one there in the same update: the problem changed its
        wording (the recorder's write failure, then its retries' open failure). Said once as a change, its
        ``since`` kept, so the journal never says "resolved" for something that lasts."""
        gone: dict[str, list[str]] = {}  # by subject, taken before any is carried (carrying pops them)
        for k, (text, *_) in self._active.items():
            if k not in current:
                gone.setdefault(subject(text), []).append(k)
        new: dict[str, list[str]] = {}
        for k, text in current.items():
            if k not in self._active:
                new.setdefault(subject(text), []).append(k)
        for who, new_keys in new.items():
            old_keys = gone.get(who, [])
            if len(old_keys) != 1 or len(new_keys) != 1:
                continue
            old_text, announced, since, _ = self._active.pop(old_keys[0])
            text = current[new_keys[0]]
            if announced:
                out.append((logging.WARNING, f"changed: {text} (was: {old_text}; for {now_s - since:.0f} s)"))
            self._active[new_keys[0]] = (text, announced, since, now_s)
