"""``logger config check FILE``: validate a configuration without starting anything."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from logger.config import SIM_SECTIONS, ConfigError, load


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="logger config", description="work with the logger's configuration")
    sub = parser.add_subparsers(dest="action", required=True)
    check = sub.add_parser("check", help="validate a configuration file; exit 1 listing every problem")
    check.add_argument("file", metavar="FILE")
    check.add_argument("--sim", action="store_true",
                       help="check it as `logger run --sim --config FILE` takes it: sensors not configured are "
                            "simulated, so no device ports are required (a file of [sim] or [recorder] alone)")
    args = parser.parse_args(argv)
    try:
        cfg = load(args.file, sim=args.sim, devices=not args.sim)  # as `logger run` loads it (logger.cli.run)
    except ConfigError as exc:
        for line in exc.problems:
            print(line, file=sys.stderr)
        return 1
    # What the file alone cannot tell: a folder it names that is a file on this machine (run would fail on it).
    places = [f"{args.file}: logger.{key} = {cfg['logger'][key]!r} exists and is not a folder"
              for key in ("out_dir", "state_dir") if (p := Path(cfg["logger"][key])).exists() and not p.is_dir()]
    if places:
        print("\n".join(places), file=sys.stderr)
        return 1
    # With --sim every sensor is simulated whatever the file says (gpsd by a simulated gpsd), as the run does.
    sources = ", ".join(f"{s}={'sim' if args.sim and cfg[s]['source'] != 'gpsd' else cfg[s]['source']}"
                        + (" (simulated)" if args.sim and cfg[s]["source"] == "gpsd" else "") for s in SIM_SECTIONS)
    print(f"{args.file}: OK ({sources})")
    return 0
