"""RINEX 3.04 observation and navigation files of a known geometry, for RTKLIB's ``rnx2rtkp`` to solve.

    python tools/rinex_synth.py OUT_DIR [--epochs 40] [--seed 1]

Writes ``rover.obs`` (a receiver driving north-east at 10 m/s), ``base.obs`` (a station 1.2 km away, standing)
and ``gps.nav`` (the broadcast ephemerides of a 30-satellite GPS constellation on circular orbits), with C1C
pseudoranges and L1C carrier phases computed the way RTKLIB models them (the satellite at the transmission
time by IS-GPS-200's ephemeris algorithm, the Sagnac term, receiver clocks; no ionosphere or troposphere: the
processing turns its models off with ``rtklib.conf``), and ``truth.csv``, the rover's position per epoch.

Why synthetic: ``tests/data/rtklib/`` holds ``.pos`` files written by the real ``rnx2rtkp`` in each of its output
options, for the parser's tests. The real M8T capture among the test data (``ublox-neo-m8t.log``) has RXM-RAWX
but only 30 s of RXM-SFRBX, from which ``convbin`` decodes one ephemeris: ``rnx2rtkp`` then says ``no nav data``.
A geometry made here gives every quality a relative solution has (fix, float, DGPS, single) from one set of files,
and a truth to check the parsed positions against.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

C = 299792458.0
MU = 3.986005e14  # the GPS value RTKLIB's eph2pos uses
OMGE = 7.2921151467e-5
L1_HZ = 1575.42e6
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
GPS_EPOCH_DAYS = 3657  # 1980-01-06 in days after 1970-01-01
SQRT_A = 5153.7  # m^0.5: 26 560 km
START = (2018, 10, 25, 20, 56, 13.0)  # GPST, the M8T capture's hour (Bend, OR)
ROVER_LLH = (math.radians(44.06), math.radians(-121.31), 1100.0)
BASE_OFFSET_ENU_M = (-800.0, -900.0, 5.0)
ROVER_VEL_ENU_MPS = (7.0, 7.0, 0.0)
MASK_DEG = 15.0


def ecef_from_llh(lat: float, lon: float, h: float) -> np.ndarray:
    e2 = WGS84_F * (2.0 - WGS84_F)
    n = WGS84_A / math.sqrt(1.0 - e2 * math.sin(lat) ** 2)
    return np.array([(n + h) * math.cos(lat) * math.cos(lon), (n + h) * math.cos(lat) * math.sin(lon),
                     (n * (1.0 - e2) + h) * math.sin(lat)])


def enu_matrix(lat: float, lon: float) -> np.ndarray:
    """Rows: east, north, up in ECEF."""
    sl, cl, sp, cp = math.sin(lon), math.cos(lon), math.sin(lat), math.cos(lat)
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def gps_seconds(y: int, mo: int, d: int, h: int, mi: int, s: float) -> float:
    """Seconds since the GPS epoch of a GPST calendar time."""
    import datetime as dt

    days = (dt.date(y, mo, d) - dt.date(1970, 1, 1)).days - GPS_EPOCH_DAYS
    return days * 86400.0 + h * 3600.0 + mi * 60.0 + s


def constellation(toe_s: float) -> list[dict[str, float]]:
    """30 satellites, 6 planes at 55 deg, 5 a plane: the elements of a circular broadcast ephemeris each."""
    sats = []
    for k in range(30):
        plane, slot = divmod(k, 5)
        sats.append({"prn": k + 1, "toe": toe_s, "sqrtA": SQRT_A, "e": 0.0, "i0": math.radians(55.0),
                     "OMG0": math.radians(60.0 * plane), "omg": 0.0,
                     "M0": math.radians(72.0 * slot + 15.0 * plane), "OMGd": 0.0})
    return sats


def sat_position(eph: dict[str, float], t_s: float) -> np.ndarray:
    """ECEF at GPS time t_s (IS-GPS-200, as RTKLIB's eph2pos with no harmonic terms and e = 0)."""
    week_s = eph["toe"] - (eph["toe"] % 604800.0)
    tk = t_s - eph["toe"]
    a = eph["sqrtA"] ** 2
    m = eph["M0"] + math.sqrt(MU / a**3) * tk
    u = m + eph["omg"]
    x, y = a * math.cos(u), a * math.sin(u)
    o = eph["OMG0"] + (eph["OMGd"] - OMGE) * tk - OMGE * (eph["toe"] - week_s)
    i = eph["i0"]
    return np.array([x * math.cos(o) - y * math.cos(i) * math.sin(o), x * math.sin(o) + y * math.cos(i) * math.cos(o),
                     y * math.sin(i)])


def pseudorange(eph: dict[str, float], t_rx: float, rr: np.ndarray, clock_m: float) -> float:
    """Range as RTKLIB computes it: the satellite at the transmission time, plus the Sagnac term and the clock."""
    pr = 2.0e7
    for _ in range(4):
        rs = sat_position(eph, t_rx - pr / C)
        pr = float(np.linalg.norm(rs - rr)) + OMGE * (rs[0] * rr[1] - rs[1] * rr[0]) / C + clock_m
    return pr


def elevation(rs: np.ndarray, rr: np.ndarray, lat: float, lon: float) -> float:
    d = enu_matrix(lat, lon) @ (rs - rr)
    return math.asin(d[2] / float(np.linalg.norm(d)))


def calendar(gps_s: float) -> tuple[int, int, int, int, int, float]:
    import datetime as dt

    whole = math.floor(gps_s)
    t = dt.datetime(1980, 1, 6) + dt.timedelta(seconds=whole)
    return t.year, t.month, t.day, t.hour, t.minute, t.second + (gps_s - whole)


def header_line(text: str, label: str) -> str:
    return f"{text:<60}{label}\n"


def write_obs(path: Path, name: str, epochs: list[tuple[float, list[tuple[int, float, float]]]],
              approx: np.ndarray) -> None:
    y, mo, d, h, mi, s = calendar(epochs[0][0])
    lines = [header_line("     3.04           OBSERVATION DATA    G: GPS", "RINEX VERSION / TYPE"),
             header_line("tools/rinex_synth.py", "PGM / RUN BY / DATE"),
             header_line(name, "MARKER NAME"),
             header_line("".join(f"{v:14.4f}" for v in approx), "APPROX POSITION XYZ"),
             header_line("".join(f"{0.0:14.4f}" for _ in range(3)), "ANTENNA: DELTA H/E/N"),
             header_line("G    2 C1C L1C", "SYS / # / OBS TYPES"),
             header_line(f"  {y:4d}    {mo:2d}    {d:2d}    {h:2d}    {mi:2d}   {s:10.7f}     GPS",
                         "TIME OF FIRST OBS"),
             header_line("", "END OF HEADER")]
    for t, sats in epochs:
        y, mo, d, h, mi, s = calendar(t)
        lines.append(f"> {y:4d} {mo:02d} {d:02d} {h:02d} {mi:02d}{s:11.7f}  0{len(sats):3d}\n")
        lines += [f"G{prn:02d}{pr:14.3f}  {ph:14.3f}  \n" for prn, pr, ph in sats]
    path.write_text("".join(lines))


def write_nav(path: Path, sats: list[dict[str, float]]) -> None:
    def d(v: float) -> str:
        return f"{v:19.12E}"

    lines = [header_line("     3.04           N: GNSS NAV DATA    G: GPS", "RINEX VERSION / TYPE"),
             header_line("tools/rinex_synth.py", "PGM / RUN BY / DATE"),
             header_line("", "END OF HEADER")]
    for e in sats:
        week, toe = divmod(e["toe"], 604800.0)
        y, mo, dd, h, mi, s = calendar(e["toe"])
        lines.append(f"G{int(e['prn']):02d} {y:4d} {mo:02d} {dd:02d} {h:02d} {mi:02d} {int(s):02d}"
                     + d(0.0) + d(0.0) + d(0.0) + "\n")
        rows = [(1.0, 0.0, 0.0, e["M0"]), (0.0, e["e"], 0.0, e["sqrtA"]), (toe, 0.0, e["OMG0"], 0.0),
                (e["i0"], 0.0, e["omg"], e["OMGd"]), (0.0, 1.0, week, 0.0), (2.0, 0.0, 0.0, 1.0),
                (toe - 30.0, 4.0, 0.0, 0.0)]
        lines += ["    " + "".join(d(v) for v in row) + "\n" for row in rows]
    path.write_text("".join(lines))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    t0 = gps_seconds(*START)
    sats = constellation(t0 - (t0 % 7200.0))
    lat, lon, h = ROVER_LLH
    r0 = ecef_from_llh(lat, lon, h)
    m = enu_matrix(lat, lon)
    base = r0 + m.T @ np.array(BASE_OFFSET_ENU_M)
    amb = {int(e["prn"]): (float(rng.integers(-500, 500)), float(rng.integers(-500, 500))) for e in sats}
    rover_epochs, base_epochs, truth = [], [], []
    lam = C / L1_HZ
    for k in range(args.epochs):
        t = t0 + k
        rr = r0 + m.T @ (np.array(ROVER_VEL_ENU_MPS) * k)
        clocks = (float(rng.normal(0.0, 30.0)), float(rng.normal(0.0, 30.0)))  # receiver clocks, m
        rov, bas = [], []
        for e in sats:
            prn = int(e["prn"])
            if elevation(sat_position(e, t), r0, lat, lon) < math.radians(MASK_DEG):
                continue
            for rx, clk, out, n in ((rr, clocks[0], rov, amb[prn][0]), (base, clocks[1], bas, amb[prn][1])):
                rho = pseudorange(e, t, rx, clk)
                out.append((prn, rho + float(rng.normal(0.0, 0.3)), rho / lam + n + float(rng.normal(0.0, 0.01))))
        rover_epochs.append((t, rov))
        base_epochs.append((t, bas))
        truth.append((t, *rr))
    args.out.mkdir(parents=True, exist_ok=True)
    write_obs(args.out / "rover.obs", "ROVER", rover_epochs, r0)
    write_obs(args.out / "base.obs", "BASE", base_epochs, base)
    write_nav(args.out / "gps.nav", sats)
    with open(args.out / "truth.csv", "w") as f:
        f.write("gpst_week,gpst_tow_s,x_m,y_m,z_m\n")
        for t, x, y, z in truth:
            f.write(f"{int(t // 604800)},{t % 604800:.3f},{x:.4f},{y:.4f},{z:.4f}\n")
    print(f"base station ECEF: {base[0]:.4f} {base[1]:.4f} {base[2]:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
