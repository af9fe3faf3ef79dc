"""Logging to stderr, which systemd puts in the journal with the right priority.

Under systemd (``JOURNAL_STREAM`` is set) each line starts with a syslog ``<N>`` prefix that journald turns into
the entry's priority, so ``journalctl -p warning`` shows exactly the warnings; at a terminal lines carry a time.

Whatever fails and however often, a person gets a few lines a second at most (:class:`LineCap`): each fault is
rate-limited where it is logged, and this is the cap over all of them together. What the cap holds back is counted
and said in the next line that passes.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Callable

from logger.runtime.journal import RateLimiter

LINES_PER_S = 5.0  # lines a second, on average, that reach a person whatever fails
LINES_BURST = 20

_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}


class _JournalFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return f"<{_PRIORITY.get(record.levelno, 6)}>{record.name}: {record.getMessage()}"


class LineCap(logging.Filter):
    """A token bucket over every line: ``LINES_BURST`` at once, ``LINES_PER_S`` a second after that. Errors and
    worse always pass (a crash must be told); the lines held back are counted into the next line that passes."""

    def __init__(self, per_s: float = LINES_PER_S, burst: int = LINES_BURST,
                 clock: Callable[[], float] | None = None) -> None:
        super().__init__()
        self._bucket = RateLimiter(burst, 1.0 / per_s, max_keys=1)
        self._clock = clock or time.monotonic
        self.held = 0

    def filter(self, record: logging.LogRecord) -> bool:
        allowed, _ = self._bucket.allow("all", self._clock())
        if not allowed and record.levelno < logging.ERROR:
            self.held += 1
            return False
        if self.held:
            record.msg = f"{record.getMessage()} ({self.held} log lines held back before this one)"
            record.args = None
            self.held = 0
        return True


def setup(verbose: bool = False) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.addFilter(LineCap())
    if os.environ.get("JOURNAL_STREAM"):
        handler.setFormatter(_JournalFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
