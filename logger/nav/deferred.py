"""Per-sample input kept and taken in order, in one loop, when a result is asked for.

At the IMU rate a method call per sample costs more than the few sums it feeds (a stop detector's window, a
noise monitor's average): the samples are kept in a list and taken all at once, in their order and with the same
arithmetic, when the result is read (or when many are waiting). Blocks of samples likewise (:func:`joined`;
the stop detector, the noise monitor, the mount alignment's running sums, the die temperature): a block's numpy
calls cost the same whatever its length, and a run of FIFO reads reaches the bookkeeping in several segments,
cut at the measurements between them.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import numpy as np

PENDING_MAX = 1024  # samples kept before they are taken anyway
BLOCKS_KEPT = 16  # blocks kept before they are taken anyway


def joined(blocks: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """The kept blocks (each a tuple of arrays, oldest first) as one, each part concatenated; the list emptied."""
    if len(blocks) == 1:
        out = blocks[0]
    else:
        out = tuple(np.concatenate([b[i] for b in blocks]) for i in range(len(blocks[0])))
    blocks.clear()
    return out


class BlockKeeper(ABC):
    """Mixin: blocks of samples kept in ``self._blocks`` (:meth:`keep_block`) and taken as one by
    :meth:`take_block` when a result is read (:meth:`take_kept`, which every reader calls first)."""

    __slots__ = ()
    _blocks: list[tuple[np.ndarray, ...]]

    def keep_block(self, *arrays: np.ndarray) -> None:
        self._blocks.append(arrays)
        if len(self._blocks) >= BLOCKS_KEPT:
            self.take_kept()

    def take_kept(self) -> None:
        if self._blocks:
            self.take_block(*joined(self._blocks))  # the list is emptied first: a reader inside finds none

    @abstractmethod
    def take_block(self, *arrays: np.ndarray) -> None:
        """Take one block (the kept ones joined), as the block form always did."""


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
