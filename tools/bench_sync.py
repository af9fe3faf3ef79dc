"""Time sync: the error of every sample's stamp against the simulation's true time, locked and in holdover.

    python tools/bench_sync.py --duration 1500 --pps-outage 600 600 --json out.json

``tools/sync_eval.py`` records the drive through the whole daemon (the tunnel scenario, plus the PPS wire cut
for a stretch so that the clock holds over for longer than the tunnel), then ``logger sync-report``'s report
of that file gives the error per topic and clock state: RMSE, largest error, and how often the error bound the
record carries covered the true error. (The paper's Eq. 1 re-timing, which ``sync_report`` also scores, counts
IMU samples and is only meaningful with none missed: ``logger sync-report`` shows it.)
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

import sync_eval  # noqa: E402

from logger.exports import sync_report  # noqa: E402


def run(duration: float, outage: tuple[float, float], time_scale: float, scenario: str) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="bench-sync-") as tmp:
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            code = sync_eval.main(["--scenario", scenario, "--duration", f"{duration:g}", "--time-scale",
                                   f"{time_scale:g}", "--pps-outage", f"{outage[0]:g}", f"{outage[1]:g}",
                                   "--out", tmp])
        if code:
            raise SystemExit(f"bench_sync: sync_eval failed ({code}):\n{printed.getvalue()}")
        report = sync_report.report(sync_report.Drive.load(sorted(Path(tmp).glob("*.mcap"))))
    return {"scenario": scenario, "duration_s": duration, "pps_outage": list(outage), "time_scale": time_scale,
            "report": report}


def render(result: dict[str, Any]) -> list[str]:
    rep = result["report"]
    out = result["pps_outage"]
    lines = [f"Drive `{result['scenario']}`, {result['duration_s']:g} s at {result['time_scale']:g}x, PPS wire cut "
             f"from {out[0]:g} s for {out[1]:g} s; longest time without PPS "
             f"{rep['table6']['longest_without_pps_s']:.0f} s.", "",
             "| topic | clock state | stamps | RMSE | largest error | error bound covered the error |",
             "| --- | --- | --- | --- | --- | --- |"]
    for key, s in rep.get("stamp_error", {}).items():
        topic, state = key.rsplit(" ", 1)
        lines.append(f"| {topic} | {state} | {s['n']} | {s['rmse_us']:.2f} us | {s['max_us']:.2f} us "
                     f"| {s['bound_covers'] * 100:.2f} % |")
    if "stamp_error" not in rep:
        lines.append("| (the file holds no /truth/clock: no error against the truth) | | | | | |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="tunnel-130s")
    ap.add_argument("--duration", type=float, default=1500.0, help="seconds of drive (default 1500)")
    ap.add_argument("--pps-outage", type=float, nargs=2, default=(600.0, 600.0), metavar=("START_S", "LENGTH_S"))
    ap.add_argument("--time-scale", type=float, default=20.0)
    ap.add_argument("--json", type=Path, help="write the result here as JSON")
    args = ap.parse_args(argv)
    if args.duration <= 0 or args.time_scale <= 0 or min(args.pps_outage) < 0:
        ap.error("--duration and --time-scale must be positive, the outage not negative")
    result = run(args.duration, tuple(args.pps_outage), args.time_scale, args.scenario)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    else:
        print("\n".join(render(result)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
