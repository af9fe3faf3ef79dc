"""Keeps one test's logging set-up from reaching the next, and fails a run in which a test skipped for anything
but a missing tool (or, with LOGGER_TESTS_NO_SKIP=1, for a missing package of the [test] extra).

Tests that run the command line in-process call ``logger.runtime.logs.setup``, which points the root logger at the
``sys.stderr`` of that moment: pytest's capture file for that test, closed once it ends. Without the restore,
later tests' log lines fail with "I/O operation on closed file" and their output is lost from the report.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator

import extras
import pytest


@pytest.fixture(autouse=True)
def _restore_root_logging() -> Iterator[None]:
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


# A machine without a tool may skip the tests that need it; nothing else may skip. Data the tests need is in the
# tree (tests/data), so a skip for anything but a missing tool is a test that silently stopped testing: the run
# fails (CI runs exactly README's test command, so the rule lives here). A missing package of the [test] extra
# (tests/extras.py) is a missing tool on a board with Debian's packages; where the extra is installed for sure
# (CI: .ci/run sets LOGGER_TESTS_NO_SKIP=1) such a skip would hide a regression, and fails the run too.
TOOL_SKIP_REASONS = ("is not installed", "needs gcc", "needs root")  # root: to mount a small disk of its own
EXTRAS_INSTALLED = os.environ.get("LOGGER_TESTS_NO_SKIP") == "1"
_unexpected_skips: list[str] = []


def pytest_collectreport(report: pytest.CollectReport) -> None:
    """A module skipped whole (a module-level skip, importorskip) counts as well."""
    _note_skip(report)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    _note_skip(report)


def _note_skip(report: pytest.CollectReport | pytest.TestReport) -> None:
    if report.skipped and not hasattr(report, "wasxfail"):
        reason = str(report.longrepr[-1]) if isinstance(report.longrepr, tuple) else str(report.longrepr)
        if not any(words in reason for words in TOOL_SKIP_REASONS) or (EXTRAS_INSTALLED and extras.MISSING in reason):
            _unexpected_skips.append(f"{report.nodeid}: {reason}")


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if _unexpected_skips and exitstatus == 0:
        session.exitstatus = 1


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    if _unexpected_skips:
        terminalreporter.section("skipped without a missing tool, or for a missing [test] extra where "
                                 "LOGGER_TESTS_NO_SKIP=1 (counts as a failure)")
        for line in _unexpected_skips:
            terminalreporter.write_line(line)
