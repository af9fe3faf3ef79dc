"""The tree's modules compiled to bytecode, as an installed package has them, before a process start is timed.

pip compiles every module of a package it installs (``tools/install-board.sh`` installs this tree with pip), so
a board's ``logger`` imports bytecode from ``__pycache__``. A source checkout whose Python runs with
PYTHONDONTWRITEBYTECODE set (as on the machine these benchmarks were first taken on) compiles every one of
the logger's modules from source at each start instead: a cost no installed logger pays, measured at 0.1 to
0.3 s of a 600 s drive's ``logger replay`` here. :func:`compile_tree` writes the bytecode once before a timed
child starts; the child reads it whatever its own PYTHONDONTWRITEBYTECODE says (the variable stops writing
bytecode, not reading it); a module changed since is compiled from source again, as the test shows.
"""

from __future__ import annotations

import compileall
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("logger", "sync", "sensors")  # pyproject.toml's packages


def compile_tree(root: Path = ROOT) -> None:
    """Write the bytecode of every module of the packages under ``root`` (all of it: compileall's own staleness
    check reads whole seconds, so a module edited in the second its bytecode was written would be skipped, and
    fifty modules take a fraction of a second). Raises SystemExit when a package is missing or a module's bytecode
    could not be written (it does not compile, or the tree is read-only): the timings would then include
    compiling, the cost this exists to leave out."""
    failed = [name for name in PACKAGES
              if not (root / name).is_dir() or not compileall.compile_dir(str(root / name), quiet=1, force=True)]
    if failed:
        raise SystemExit(f"bytecode not written for {', '.join(failed)} under {root}: a timed start would compile "
                         "them from source")
