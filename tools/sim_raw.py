"""Raw GPS observations of a simulated drive for RTKLIB, and how RTKLIB's solution compares with the truth.

    python tools/sim_raw.py --out DIR [--scenario urban] [--seed 1] [--duration 150] [--base-distance 500]
    python tools/sim_raw.py --out DIR ... --rtklib      # and process them: convbin, rnx2rtkp, the figures

writes ``DIR/rover.ubx`` and ``DIR/base.ubx`` (UBX RXM-RAWX at 1 Hz: the car on the drive, and a base station
under an open sky ``--base-distance`` m from its start) and ``DIR/nav.rnx`` (RINEX 3.04 GPS navigation: the
broadcast orbits and clocks the observations were made with, and the Klobuchar coefficients); see
``sensors/sim/raw_obs.py``. With ``--rtklib`` it runs Debian's ``rtklib`` on them as a survey engineer would:

    convbin -r ubx -v 3.04 -od -os -o rover.obs rover.ubx        (and base.obs)
    rnx2rtkp -k rtklib.conf -p 0 -o single.pos rover.obs nav.rnx
    rnx2rtkp -k rtklib.conf -p 2 -f 1 -r X Y Z -o kinematic.pos rover.obs base.obs nav.rnx

(``rtklib.conf`` tells it the models the simulation has: broadcast ionosphere, Saastamoinen troposphere, GPS;
and ECEF positions with GPS week and seconds to the microsecond)
and prints the RINEX epochs against the RAWX frames, the single-point errors, and the kinematic solution's fix
rate and errors where the sky is open, against the drive's truth at each solution's time.

A drive recorded by ``logger run --sim --config FILE`` with a raw-capable receiver (``[sim] receiver_model =
"NEO-M8T"`` or ``"ZED-F9P"``) and ``[gnss] raw_observations = true`` holds the rover's RXM-RAWX of the same model
(``sensors/sim/vehicle.py`` plugs it into the receiver); ``--scenario``, ``--seed`` and ``--start-utc`` of that
drive give the base station and the navigation file that go with it, and ``--rover`` its RXM-RAWX (the
``/gnss/raw`` bytes) to process against them.
"""

from __future__ import annotations

import argparse
import math
import shutil
import subprocess
import sys
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sensors.sim import earth  # noqa: E402
from sensors.sim.gnss_time import NS_PER_S, SECONDS_PER_WEEK, GnssTimeline  # noqa: E402
from sensors.sim.raw_obs import RawDriveFiles, record_raw_drive  # noqa: E402
from sensors.sim.scenarios import make_drive  # noqa: E402
from sensors.sim.truth import Trajectory  # noqa: E402

RTKLIB_TOOLS = ("convbin", "rnx2rtkp")
# The models the simulated signals went through, so the processor removes them (rnx2rtkp's defaults differ by
# version); GPS only, the simulation's raw observations being GPS L1.
RTKLIB_CONF = """pos1-ionoopt       =brdc
pos1-tropopt       =saas
pos1-sateph        =brdc
pos1-navsys        =1
pos1-elmask        =10
pos2-armode        =continuous
out-solformat      =xyz
out-timeform       =tow
out-timendec       =6
"""


@dataclass(frozen=True, slots=True)
class PosRow:
    """One solution of an ``rnx2rtkp`` ECEF file: GPS time, ECEF position, quality flag and satellites."""

    gps_ns: int
    ecef_m: np.ndarray
    quality: int
    satellites: int


@dataclass(frozen=True, slots=True)
class Errors:
    """A solution's error against the truth (m), north-east-up, and the sky over the car at that time."""

    row: PosRow
    enu_m: np.ndarray
    sky_open: float

    @property
    def horizontal_m(self) -> float:
        return math.hypot(float(self.enu_m[0]), float(self.enu_m[1]))


def read_pos(path: Path) -> list[PosRow]:
    """The solutions of an ``rnx2rtkp`` output in ECEF with GPS week and seconds (:data:`RTKLIB_CONF`)."""
    rows = []
    for line in path.read_text().splitlines():
        if line.startswith("%") or not line.strip():
            continue
        f = line.split()
        gps_ns = int(f[0]) * SECONDS_PER_WEEK * NS_PER_S + round(float(f[1]) * NS_PER_S)
        rows.append(PosRow(gps_ns, np.array([float(x) for x in f[2:5]]), int(f[5]), int(f[6])))
    return rows


def score(rows: list[PosRow], trajectory: Trajectory, timeline: GnssTimeline) -> list[Errors]:
    """Each solution against the truth at its own time (RTKLIB stamps it with the receiver clock removed)."""
    out = []
    for row in rows:
        s = trajectory.state(min(max(timeline.drive_ns(row.gps_ns) / NS_PER_S, 0.0), trajectory.duration_s))
        truth = earth.ecef(s.lat_rad, s.lon_rad, s.height_m)
        ned = earth.dcm_ned_to_ecef(s.lat_rad, s.lon_rad).T @ (row.ecef_m - truth)
        out.append(Errors(row, np.array((ned[1], ned[0], -ned[2])), s.sky_open))
    return out


def rtklib_missing() -> list[str]:
    return [t for t in RTKLIB_TOOLS if shutil.which(t) is None]


def convbin(ubx: Path) -> Path:
    """RINEX 3.04 observations of a UBX file, next to it (``.obs``), with Doppler and C/N0."""
    obs = ubx.with_suffix(".obs")
    subprocess.run(["convbin", "-r", "ubx", "-v", "3.04", "-od", "-os", "-o", str(obs), str(ubx)], check=True,
                   capture_output=True)
    return obs


def rinex_epochs(obs: Path) -> int:
    """Epoch records in a RINEX 3 observation file."""
    return sum(1 for line in obs.read_text().splitlines() if line.startswith(">"))


def rnx2rtkp(files: RawDriveFiles, rover_obs: Path, base_obs: Path | None, out: Path) -> list[PosRow]:
    """Single point (no base) or L1 kinematic against the base at its known position: the solutions."""
    conf = files.nav.parent / "rtklib.conf"
    conf.write_text(RTKLIB_CONF)
    cmd = ["rnx2rtkp", "-k", str(conf), "-o", str(out)]
    if base_obs is None:
        cmd += ["-p", "0", str(rover_obs), str(files.nav)]
    else:
        cmd += ["-p", "2", "-f", "1", "-r", *(f"{x:.4f}" for x in files.base_ecef_m), str(rover_obs),
                str(base_obs), str(files.nav)]
    subprocess.run(cmd, check=True, capture_output=True)
    return read_pos(out)


def summary(errors: list[Errors]) -> str:
    """Horizontal and vertical RMS and maximum, the median horizontal error and the share within 5 cm."""
    if not errors:
        return "no solutions"
    h = np.array([e.horizontal_m for e in errors])
    v = np.array([abs(e.enu_m[2]) for e in errors])
    return (f"{len(errors)} solutions: horizontal RMS {math.sqrt(float(np.mean(h**2))):.3f} m, median "
            f"{float(np.median(h)):.3f} m, max {h.max():.3f} m, {100.0 * float(np.mean(h < 0.05)):.0f} % within "
            f"5 cm; vertical RMS {math.sqrt(float(np.mean(v**2))):.3f} m, max {v.max():.3f} m")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scenario", default="urban")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--duration", type=float, default=150.0, help="seconds of the drive (default 150)")
    ap.add_argument("--base-distance", type=float, default=500.0, help="base station from the start, m")
    ap.add_argument("--start-utc", type=datetime.fromisoformat, default=None,
                    help="UTC of the drive's start (ISO 8601; default the simulator's 2018-03-14T01:30:00+00:00): "
                         "that of a drive `logger run --sim` recorded, for its base station and navigation file")
    ap.add_argument("--rover", type=Path, default=None,
                    help="with --rtklib: process this rover UBX (a recorded drive's receiver output) instead")
    ap.add_argument("--rtklib", action="store_true", help="process with convbin and rnx2rtkp, print the figures")
    args = ap.parse_args(argv)
    drive = make_drive(args.scenario, seed=args.seed, duration_s=args.duration)  # laps repeated as the daemon's
    timeline = GnssTimeline(args.start_utc) if args.start_utc is not None else GnssTimeline()
    files = record_raw_drive(drive, drive.gnss_sky, args.out, duration_s=args.duration,
                             timeline=timeline, seed=args.seed, base_distance_m=args.base_distance)
    print(f"{files.rover_ubx}, {files.base_ubx}: {files.epochs} RXM-RAWX epochs "
          f"({files.rover_epochs_with_measurements} of the rover's with measurements); {files.nav}")
    if not args.rtklib:
        return 0
    missing = rtklib_missing()
    if missing:
        print(f"{', '.join(missing)} is not installed: apt-get install rtklib", file=sys.stderr)
        return 1
    rover_obs, base_obs = convbin(args.rover or files.rover_ubx), convbin(files.base_ubx)
    print(f"convbin: {rinex_epochs(rover_obs)} rover and {rinex_epochs(base_obs)} base RINEX epochs")
    single = score(rnx2rtkp(files, rover_obs, None, args.out / "single.pos"), drive, timeline)
    print(f"single point, open sky: {summary([e for e in single if e.sky_open >= 1.0])}")
    print(f"single point, street canyon: {summary([e for e in single if e.sky_open < 1.0])}")
    kin = score(rnx2rtkp(files, rover_obs, base_obs, args.out / "kinematic.pos"), drive, timeline)
    open_sky = [e for e in kin if e.sky_open >= 1.0]
    fixed = [e for e in open_sky if e.row.quality == 1]
    print(f"kinematic: {len(kin)} solutions, {len(open_sky)} under an open sky, {len(fixed)} of those fixed "
          f"({100.0 * len(fixed) / max(1, len(open_sky)):.1f} %)")
    print(f"kinematic fixed, open sky: {summary(fixed)}")
    print(f"kinematic fixed, street canyon: {summary([e for e in kin if e.sky_open < 1.0 and e.row.quality == 1])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
