"""The optional packages some tests need (the ``[test]`` extra: hypothesis, matplotlib, jsonschema, ELM327-emulator,
obd): a test that needs one skips where it is not installed, with a reason naming it, instead of failing or taking
its module's other tests down with it. A board with Debian's packages may lack one; CI installs them all, and there
``LOGGER_TESTS_NO_SKIP=1`` makes such a skip fail the run (tests/conftest.py).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from types import ModuleType
from typing import Any

import pytest

MISSING = "is not installed (pip install -e '.[test]')"
"""The end of every reason given here: tests/conftest.py tells these skips by it."""


def need(name: str) -> ModuleType:
    """The module, or this test (or module, at import) skipped: ``name`` is not installed."""
    return pytest.importorskip(name, reason=f"{name} {MISSING}")


def optional(name: str) -> tuple[ModuleType | None, pytest.MarkDecorator]:
    """The module (None where it is not installed) and a mark that skips the tests needing it there, for a module
    whose other tests run without it."""
    try:
        module: ModuleType | None = importlib.import_module(name)
    except ModuleNotFoundError:
        module = None
    return module, pytest.mark.skipif(module is None, reason=f"{name} {MISSING}")


def _skipped_without(name: str) -> Callable[..., Callable[[Any], Any]]:
    """Stands in for a decorator factory (``given(...)``, ``settings(...)``): the test it decorates skips."""
    def factory(*args: Any, **kwargs: Any) -> Callable[[Any], Any]:
        return pytest.mark.skip(reason=f"{name} {MISSING}")
    return factory


class _Absent:
    """Stands in for hypothesis's ``strategies`` and ``HealthCheck`` where it is not installed: every attribute and
    every call gives itself, so a module's strategies can be built (to nothing) and its other tests still run."""

    def __getattr__(self, name: str) -> _Absent:
        return self

    def __call__(self, *args: Any, **kwargs: Any) -> _Absent:
        return self


try:
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
except ModuleNotFoundError:
    HealthCheck = st = _Absent()  # type: ignore[assignment]
    given = settings = _skipped_without("hypothesis")  # type: ignore[assignment]

__all__ = ["MISSING", "HealthCheck", "given", "need", "optional", "settings", "st"]
