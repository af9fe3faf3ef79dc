"""README.md's command table tells every option each ``logger`` command takes (its argparse usage says which)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from logger.cli import SUBCOMMANDS

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def usage_options(argv: list[str]) -> set[str]:
    r = subprocess.run([sys.executable, "-m", "logger.cli", *argv, "--help"], cwd=ROOT, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    usage = r.stdout.split("\n\n", 1)[0]
    options = set(re.findall(r"\[(--?[A-Za-z][\w-]*)", usage)) | set(re.findall(r" (--[a-z][\w-]*) [A-Z]", usage))
    return options - {"-h"}


def readme_row(command: str) -> str:
    rows = [line for line in README.splitlines() if line.startswith(f"| `logger {command} ") or
            line.startswith(f"| `logger {command}`")]
    assert rows, f"README.md's table has no row for `logger {command}`"
    return rows[0]


@pytest.mark.parametrize("command", [c for c in SUBCOMMANDS if c != "config"] + ["config check"])
def test_every_option_is_in_the_readme_table(command: str) -> None:
    row = readme_row(command)
    missing = sorted(o for o in usage_options(command.split()) if o not in row)
    assert not missing, f"README.md's row for `logger {command}` does not name {', '.join(missing)}"


def test_the_table_names_the_version_option() -> None:
    assert "logger --version" in README
