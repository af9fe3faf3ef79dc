"""A one-line progress meter on stderr for the long office commands (replay, export, plot).

Only on a terminal: a pipe, a file or the journal get nothing, so scripts and captured output stay clean. The
line is redrawn at most twice a second and wiped when the work ends, leaving the command's own output as it was.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

REDRAW_S = 0.5


class Progress:
    """``logger replay: 42 % (1234567 of 2939201 messages)``, told (done, in all, of what) by the drive reader."""

    def __init__(self, label: str, stream: TextIO | None = None, on: bool | None = None) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self.on = self.stream.isatty() if on is None else on
        self._next = 0.0
        self._width = 0

    def __call__(self, done: int, total: int, what: str = "messages") -> None:
        now = time.monotonic()
        if not self.on or total <= 0 or (now < self._next and done < total):
            return
        self._next = now + REDRAW_S
        line = f"{self.label}: {done * 100 // total} % ({done} of {total} {what})"
        self._width = max(self._width, len(line))
        self.stream.write("\r" + line.ljust(self._width))
        self.stream.flush()

    def stage(self, what: str) -> None:
        """A step after the reading (drawing a plot, writing a file)."""
        if self.on:
            line = f"{self.label}: {what}"
            self._width = max(self._width, len(line))
            self.stream.write("\r" + line.ljust(self._width))
            self.stream.flush()

    def end(self) -> None:
        """Wipe the line, so what the command prints next starts at the left margin."""
        if self.on and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0
