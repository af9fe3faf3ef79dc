"""Keeps one test's logging set-up from reaching the next.

Tests that run the command line in-process call ``logger.runtime.logs.setup``, which points the root logger at the
``sys.stderr`` of that moment: pytest's capture file for that test, closed once it ends. Without the restore,
later tests' log lines fail with "I/O operation on closed file" and their output is lost from the report.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def _restore_root_logging() -> Iterator[None]:
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)
