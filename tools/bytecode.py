"""The tree's modules compiled to bytecode, as an installed package has them, before a process start is timed.

pip compiles every module of a package it installs (``tools/install-board.sh`` installs this tree with pip), so
a board's ``logger`` imports bytecode from ``__pycache__``. A source checkout whose Python runs with
PYTHONDONTWRITEBYTECODE set (as on the machine these benchmarks were first taken on) compiles every one of the
logger's modules from source at each start instead: a cost no installed logger pays (measured here:
bench_startup's "logger's imports" 0.61 s from source, about 0.04 s of it the tool's own helper since moved out,
against 0.22 s from bytecode; ``logger replay``'s imports 0.23 s against 0.19 s, the best of eight alternated runs
each). :func:`compile_tree` writes the bytecode once before a timed child starts; the child reads it whatever its
own PYTHONDONTWRITEBYTECODE says (the variable stops writing bytecode, not reading it); a module changed since is
compiled from source again, as the test shows.
"""

from __future__ import annotations

import compileall
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def packages(root: Path = ROOT) -> tuple[str, ...]:
    """The top-level packages pyproject.toml installs (its ``packages.find`` include patterns, "logger*" ->
    "logger")."""
    with open(root / "pyproject.toml", "rb") as f:
        include = tomllib.load(f)["tool"]["setuptools"]["packages"]["find"]["include"]
    return tuple(sorted({pattern.split(".")[0].rstrip("*") for pattern in include}))


def compile_tree(root: Path = ROOT, names: tuple[str, ...] | None = None) -> None:
    """Write the bytecode of every module of the packages ``names`` (by default :func:`packages`) under ``root``,
    all of it: compileall's own staleness check reads whole seconds, so a module edited in the second its bytecode
    was written would be skipped, and fifty modules take a fraction of a second. Raises SystemExit when a package
    is missing or a module's bytecode could not be written (it does not compile, or the tree is read-only): the
    timings would then include compiling, the cost this exists to leave out."""
    failed = [name for name in (names if names is not None else packages(root))
              if not (root / name).is_dir() or not compileall.compile_dir(str(root / name), quiet=1, force=True)]
    if failed:
        raise SystemExit(f"bytecode not written for {', '.join(failed)} under {root}: a timed start would compile "
                         "them from source")
