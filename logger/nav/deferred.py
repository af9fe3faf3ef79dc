"""Per-sample input kept and taken in order, in one loop, when a result is asked for.

At the IMU rate a method call per sample costs more than the few sums it feeds (a stop detector's window, a
noise monitor's average): the samples are kept in a list and taken all at once, in their order and with the same
arithmetic, when the result is read (or when many are waiting).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

PENDING_MAX = 1024  # samples kept before they are taken anyway


class Deferred(ABC):
    """Mixin: ``self._pending`` holds the samples not yet taken; :meth:`take_pending` takes them, in order."""

    __slots__ = ()
    _pending: list[Any]

    def flush_pending(self) -> None:
        pending = self._pending
        if pending:
            self.take_pending(pending)
            pending.clear()

    @abstractmethod
    def take_pending(self, pending: list[Any]) -> None:
        """Take the kept samples, oldest first, as the per-sample method would have one by one."""
