"""The tree's modules compiled to bytecode, as an installed package has them, before a process start is timed.

pip compiles every module of a package it installs (``tools/install-board.sh`` installs this tree with pip), so
a board's ``logger`` imports bytecode from ``__pycache__``. A source checkout whose Python runs with
PYTHONDONTWRITEBYTECODE set (as on the machine these benchmarks were first taken on) compiles every one of
the logger's modules from source at each start instead: a cost no installed logger pays, measured at 0.1 to
0.3 s of a 600 s drive's ``logger replay`` here. :func:`compile_tree` writes the bytecode once before a timed
child starts; the child reads it whatever its own PYTHONDONTWRITEBYTECODE says (the variable stops writing
bytecode, not reading it), and a module changed since is compiled again.
"""

from __future__ import annotations

import compileall
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("logger", "sync", "sensors")  # pyproject.toml's packages


def compile_tree(root: Path = ROOT) -> bool:
    """Compile the packages' modules under ``root`` to bytecode where it is missing or stale; True when every
    module compiled (a module that does not compile fails its import anyway, timed or not)."""
    return all(compileall.compile_dir(str(root / name), quiet=1) for name in PACKAGES)
