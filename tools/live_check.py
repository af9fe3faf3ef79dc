"""The live navigator against the truth on a recorded simulated drive: what the daemon published, and what a
navigator gives the drive's records fed as the daemon offered them.

    python tools/live_check.py DRIVE...

For each drive (a folder of one recording's MCAP files, or one file, with ``/truth/nav``): the recorded
``/nav/fix`` (the live filter's, as published), and the records the navigator takes (IMU, GNSS, OBD, barometer,
PPS) offered to a :class:`~logger.runtime.navigator.Navigator` in the daemon's order (a FIFO read when its last
sample was read, every other record at its own time), a wake-up per second, its ``/nav/fix`` scored the same way;
and ``logger replay``'s forward solution. RMSE N / E / V and the share within 3 sigma per axis, over the whole
drive (parked time included: the three are compared with each other, not with the targets).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from nav_eval import trajectory

from logger.exports.nav_score import Score, load_truth, score
from logger.exports.trajectory import run_filter
from logger.nav.params import NavParams
from logger.recording.drive import read_messages
from logger.recording.topics import NAV_FIX
from logger.runtime.navigator import INPUT_TOPICS, WAKE_S, Navigator, in_offer_order

NS = 1_000_000_000


def fix_columns(fixes: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """/nav/fix records as the columns nav_score reads."""
    sig = np.array([m["sigma_ned_m"] for m in fixes], float).reshape(-1, 3)
    return {"t_sync_ns": np.array([m["t_sync_ns"] for m in fixes], np.int64),
            "t_mono_ns": np.array([m["t_mono_ns"] for m in fixes], np.int64),
            "lat_deg": np.array([m["latitude"] for m in fixes], float),
            "lon_deg": np.array([m["longitude"] for m in fixes], float),
            "height_m": np.array([m["altitude"] for m in fixes], float),
            "sn_m": sig[:, 0], "se_m": sig[:, 1], "sd_m": sig[:, 2]}


def as_offered(files: list[Path]) -> list[dict[str, Any]]:
    """The /nav/fix a navigator publishes from the drive's records in the daemon's order."""
    recs = in_offer_order(read_messages(files, tuple(INPUT_TOPICS)))
    out: list[dict[str, Any]] = []
    nav = Navigator(NavParams(), publish=lambda r: out.append(r.payload) if r.topic == NAV_FIX else None)
    i, wake = 0, recs[0][0] + int(WAKE_S * NS) if recs else 0
    while i < len(recs):
        batch = []
        while i < len(recs) and recs[i][0] < wake:
            batch.append(recs[i][1:])
            i += 1
        nav.take(batch)
        nav.rerun_if_due()
        wake += int(WAKE_S * NS)
    nav.flush()  # the measurements after the drive's last IMU sample
    return out


def line(name: str, s: Score) -> str:
    rmse, within = s.rmse, [w * 100 for w in s.within_3sigma]
    return (f"  {name:28s} RMSE N / E / V {rmse[0]:.2f} / {rmse[1]:.2f} / {rmse[2]:.2f} m, within 3 sigma "
            f"{within[0]:.1f} / {within[1]:.1f} / {within[2]:.1f} %")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("drives", type=Path, nargs="+")
    args = ap.parse_args(argv)
    for drive in args.drives:
        files = sorted(drive.glob("*.mcap")) if drive.is_dir() else [drive]
        truth = load_truth(files)
        print(drive.name)
        recorded = [m for _, m in read_messages(files, (NAV_FIX,))]
        if recorded:
            print(line("recorded live /nav/fix", score(fix_columns(recorded), truth)))
        print(line("navigator, as offered", score(fix_columns(as_offered(files)), truth)))
        _, rows = run_filter(files, NavParams())
        print(line("replay, forward", score(trajectory(rows), truth)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
