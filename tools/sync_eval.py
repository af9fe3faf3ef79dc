"""Record a simulated drive through the whole daemon and print its time-sync report.

    python tools/sync_eval.py --scenario urban --duration 4000 --pps-outage 200 3600 --time-scale 20 --out DIR

The long cases of the clock's acceptance (an hour without PPS) need more than the named scenarios give; this
runs the same daemon, drivers and device models as ``logger run --sim``, with the PPS wire cut for a stretch (or
a scenario option such as a longer tunnel), then ``logger sync-report`` on the file.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from logger.cli import sync_report as sync_report_cli
from logger.compose import build
from logger.config import defaults
from logger.runtime import logs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="tunnel-130s")
    ap.add_argument("--tunnel-s", type=float, help="dark time of the tunnel (tunnel-130s) in s")
    ap.add_argument("--pps-outage", nargs=2, type=float, metavar=("START_S", "LENGTH_S"),
                    help="cut the PPS wire for this stretch of drive (the receiver keeps its fixes)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--time-scale", type=float, default=20.0)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--png-dir", type=Path)
    args = ap.parse_args(argv)
    logs.setup()
    cfg = defaults(sim=True)
    cfg.values["logger"].update(out_dir=str(args.out), status_socket=str(args.out / "status.sock"),
                                state_dir=str(args.out / ".state"))
    cfg.values["sim"].update(scenario=args.scenario, seed=args.seed, time_scale=args.time_scale)
    if "nav" in cfg.values:
        cfg.values["nav"]["enabled"] = False  # the clock is under test: keep the CPU for the drive at this scale
    options = {"tunnel_s": args.tunnel_s} if args.tunnel_s is not None else None
    daemon, vehicle = build(cfg, args.duration, scenario_options=options)
    if args.pps_outage:
        start, length = args.pps_outage
        for k in range(int(start), int(start + length)):
            vehicle.pps.inject_missed(k)
    daemon.run(args.duration)
    files = sorted(args.out.glob("*.mcap"))
    return sync_report_cli.main([*map(str, files), *(["--png-dir", str(args.png_dir)] if args.png_dir else [])])


if __name__ == "__main__":
    sys.exit(main())
