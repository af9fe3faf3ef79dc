"""Keeps one test's logging set-up from reaching the next, and fails a run in which a test skipped for anything
but a missing tool (or, with LOGGER_TESTS_NO_SKIP=1, for a missing package of the [test] extra), or, on a board
(LOGGER_BOARD=1, as tools/board-check.sh runs the suite), for being marked ``slow_on_board``.

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
# (CI: .ci/run sets LOGGER_TESTS_NO_SKIP=1, and installs RTKLIB and node) such a skip would hide a regression,
# and fails the run too, as a skip for a missing RTKLIB or node does there.
TOOL_SKIP_REASONS = ("is not installed", "needs gcc", "needs root")  # root: to mount a small disk of its own
EXTRAS_INSTALLED = os.environ.get("LOGGER_TESTS_NO_SKIP") == "1"
# What .ci/run installs besides the extra, as the skip reasons name it: RTKLIB, node with @mcap/core, gpsd, chrony.
CI_INSTALLS = ("rtklib", "nodejs", "tools/mcap_js", "gpsd", "chrony")
_unexpected_skips: list[str] = []

# On a board's single slow core (or an emulated one: tools/board-check.sh sets LOGGER_BOARD=1) the tests that spend
# minutes of CPU on long simulated drives, whole-drive replays or the soak are left to the x86 CI, which runs every
# one; the rest of the suite, the drivers, the record layer, the clock, the filter's units and short drives, runs.
ON_BOARD = os.environ.get("LOGGER_BOARD") == "1"
BOARD_SKIP_REASON = "slow on a board: minutes of CPU on one core (LOGGER_BOARD=1); the x86 CI runs it"


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "slow_on_board: minutes of CPU on a board's one core; skipped where "
                            "LOGGER_BOARD=1 (tools/board-check.sh), run everywhere else")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if ON_BOARD:
        for item in items:
            if item.get_closest_marker("slow_on_board"):
                item.add_marker(pytest.mark.skip(reason=BOARD_SKIP_REASON))


def pytest_collectreport(report: pytest.CollectReport) -> None:
    """A module skipped whole (a module-level skip, importorskip) counts as well."""
    _note_skip(report)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    _note_skip(report)


def _note_skip(report: pytest.CollectReport | pytest.TestReport) -> None:
    if report.skipped and not hasattr(report, "wasxfail"):
        reason = str(report.longrepr[-1]) if isinstance(report.longrepr, tuple) else str(report.longrepr)
        allowed = (*TOOL_SKIP_REASONS, BOARD_SKIP_REASON) if ON_BOARD else TOOL_SKIP_REASONS
        expected_here = extras.MISSING in reason or any(tool in reason for tool in CI_INSTALLS)
        if not any(words in reason for words in allowed) or (EXTRAS_INSTALLED and expected_here):
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
