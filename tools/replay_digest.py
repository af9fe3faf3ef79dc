"""Digests of what ``logger replay`` and ``logger sync-report`` make of recorded drives, for a behaviour check.

    python tools/replay_digest.py DRIVE_DIR... [--modes 17 15 gnss] [--checkout DIR] > digests.txt

For every drive (a folder of one drive's MCAP files) and every mode, with and without ``--smooth``, it runs
``logger replay`` of this checkout as a user does and prints the SHA-256 of ``trajectory.csv`` and
``trajectory.mcap``; then the SHA-256 of the drive's sync report. Run it in two checkouts (``git worktree add``)
over the same recorded drives and ``diff`` the outputs: a change that claims to keep behaviour must leave every
line the same. ``--checkout DIR`` runs another checkout's code instead of this one's (an older commit need not
have this tool). Recordings themselves are not reproducible (real threads on a real host), so record the drives
once and replay them in both.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("drives", type=Path, nargs="+", help="folders, each holding one recorded drive's .mcap files")
    ap.add_argument("--modes", nargs="+", default=["17", "15", "gnss"], choices=["17", "15", "gnss"])
    ap.add_argument("--checkout", type=Path, default=ROOT, help="the checkout whose code runs (default: this one)")
    args = ap.parse_args(argv)
    tree = args.checkout.resolve()
    env = {**os.environ, "PYTHONPATH": str(tree)}
    failed = 0
    for drive in args.drives:
        files = sorted(str(p.resolve()) for p in drive.glob("*.mcap"))
        if not files:
            print(f"replay_digest: {drive}: no .mcap files", file=sys.stderr)
            return 2
        for mode in args.modes:
            for smooth in ([], ["--smooth"]):
                with tempfile.TemporaryDirectory(prefix="replay-digest-") as out:
                    r = subprocess.run([sys.executable, "-m", "logger.cli", "replay", *files, "--out", out,
                                        "--mode", mode, *smooth], cwd=tree, env=env, capture_output=True, text=True)
                    label = f"{drive.name} mode {mode}{' smoothed' if smooth else ''}"
                    if r.returncode != 0:
                        failed += 1
                        print(f"{label}: replay failed (exit {r.returncode}): {r.stderr.strip()[-200:]}")
                        continue
                    for name in ("trajectory.csv", "trajectory.mcap"):
                        print(f"{label} {name} {sha256(Path(out) / name)}")
        old_tool = tree / "tools" / "sync_report.py"  # where the report lived before `logger sync-report`
        report_cmd = [str(old_tool)] if old_tool.exists() else ["-m", "logger.cli", "sync-report"]
        r = subprocess.run([sys.executable, *report_cmd, *files], cwd=tree, env=env, capture_output=True)
        print(f"{drive.name} sync report {hashlib.sha256(r.stdout).hexdigest()} (exit {r.returncode})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
