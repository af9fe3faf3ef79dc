"""Named, seeded drives: the urban loop, a GNSS outage at a steady speed, a long tunnel.

Each drive is an intro (idling with the engine running for ``intro_s``: the logger is powered with the
ignition, and the vehicle stands still long enough for the filter to level the IMU, then moves off, so a
one-minute run shows the filter working), a body that repeats until the requested duration is filled, and an
outro (stop, idle, engine off). A seed fixes every
choice (speeds, stop lengths, grades, sky in street canyons, weather) so a run can be repeated exactly; the
body is re-drawn for each repetition from ``(seed, repetition)``, so a long drive does not repeat itself
while a short one does not depend on how long the long one was.

The urban lap closes on itself: it is driven once on a scratch copy to measure where it ends, and the
level, straight filler stretches of the southbound and westbound legs absorb the difference, so any number
of laps stays around the start instead of wandering off.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from sensors.sim.drive import Drive, RouteBuilder, Weather, horizontal_displacement
from sensors.sim.gnss_errors import SkyGeometry
from sensors.sim.scenario_names import SCENARIOS

INTRO_S = 8.0  # standing with the engine running before moving off: levelling needs 2 s, the rest is margin
_START_OPTIONS = ("intro_s",)
_DRIVE_OPTIONS = ("start_lat_deg", "start_lon_deg", "start_height_m", "geoid_m", "grid_dt_s")
_WEATHER_OPTIONS = ("ambient_start_degc", "ambient_swing_degc", "sea_level_pa", "sea_level_rate_pa_per_s")
_SCENARIO_OPTIONS: dict[str, dict[str, Any]] = {
    "urban": {"tunnel_s": (10.0, 14.0)},
    "outage-60s": {"outage_s": 60.0, "speed_mps": 15.0},
    "tunnel-130s": {"tunnel_s": 130.0, "speed_mps": 13.9},
}
MIN_FILL_M = 60.0  # shortest straight a closing stretch may have
# Street canyons of the urban lap: the visible sky fraction wanders here, which blocks satellites from 15 deg
# up to 42..59 deg (sensors.sim.gnss_errors.blocked_band): the paper's simulated urban blockage of 15 to 50 deg.
CANYON_SKY = (0.40, 0.58)
# Buildings close in over the approach to each urban tunnel: the sky narrows to nothing over this long, so the
# receiver works on ever fewer satellites before it loses them (the paper's Table 8: under 5 for about 30 s).
URBAN_PORTAL_S = 8.0
TRAFFIC_MPS = 1.0  # how far the speed wanders with the traffic on the urban lap's canyon and tunnel stretches
HALF_PI = 0.5 * math.pi


def make_drive(name: str = "urban", seed: int = 0, duration_s: float | None = None, **options: Any) -> Drive:
    """The drive called ``name``, drawn from ``seed``; repeated to ``duration_s`` when given.

    The body repeats while a whole repetition and the outro still fit, then the vehicle parks until
    ``duration_s``; a duration shorter than one repetition cuts the drive there instead.

    Options: ``intro_s`` (standing before moving off, default :data:`INTRO_S`),
    ``tunnel_s`` (urban: the two tunnels' dark times; tunnel-130s: its one), ``outage_s`` and
    ``speed_mps`` (outage-60s), start position (``start_lat_deg``, ``start_lon_deg``, ``start_height_m``
    ellipsoidal, ``geoid_m``) and weather (``ambient_start_degc``, ``ambient_swing_degc``,
    ``sea_level_pa``, ``sea_level_rate_pa_per_s``).
    """
    if name not in _SCENARIO_OPTIONS:
        raise ValueError(f"unknown drive scenario {name!r}: choose one of {', '.join(SCENARIOS)}")
    if duration_s is not None and not duration_s > 0:
        raise ValueError(f"drive duration must be positive, got {duration_s}")
    allowed = set(_SCENARIO_OPTIONS[name]) | set(_START_OPTIONS) | set(_DRIVE_OPTIONS) | set(_WEATHER_OPTIONS)
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise ValueError(f"scenario {name!r} has no option {unknown[0]!r}: it takes {', '.join(sorted(allowed))}")
    scenario_opts = {**_SCENARIO_OPTIONS[name], **{k: v for k, v in options.items() if k in _SCENARIO_OPTIONS[name]}}
    drive_opts = {k: v for k, v in options.items() if k in _DRIVE_OPTIONS}
    intro_s = float(options.get("intro_s", INTRO_S))
    if not intro_s >= 0.0:
        raise ValueError(f"intro_s must be 0 s or more, got {intro_s}")

    rng = np.random.default_rng([seed, 0])
    weather = Weather(
        ambient_start_degc=options.get("ambient_start_degc", float(rng.uniform(5.0, 15.0))),
        ambient_swing_degc=options.get("ambient_swing_degc", 20.0),
        sea_level_pa=options.get("sea_level_pa", float(rng.uniform(100300.0, 102300.0))),
        sea_level_rate_pa_per_s=options.get(
            "sea_level_rate_pa_per_s", float(rng.choice((-1.0, 1.0)) * rng.uniform(60.0, 140.0) / 3600.0)),
    )
    heading0, body, speed = _SCENARIO_BODIES[name](rng, scenario_opts)

    b = RouteBuilder(heading_rad=heading0, engine_on=True)
    if intro_s > 0.0:
        b.stand(intro_s, "idle")
    if speed > 0.0:
        b.speed_to(speed, 1.5)
    outro_s = 60.0
    body(b, [seed, 1, 0])
    rep = 1
    while duration_s is not None:
        # Add another repetition only if it still ends, with the outro, within the duration: the drive
        # then ends parked, padded with parked time, rather than being cut in the middle of a tunnel.
        probe = copy.deepcopy(b)
        body(probe, [seed, 1, rep])
        if probe.t + outro_s > duration_s:
            break
        body(b, [seed, 1, rep])
        rep += 1
    if b.v > 0.0:
        b.speed_to(0.0, 2.0)
    b.stand(15.0, "idle")
    b.engine(False)
    b.stand(20.0, "parked")
    if duration_s is not None and b.t < duration_s:
        b.stand(duration_s - b.t, "parked")
    plan = b.finish()
    drive = Drive(plan, weather=weather, duration_s=duration_s if duration_s is not None else plan.end_s,
                  name=name, **drive_opts)
    # Where the satellites stand: a seeded time of day, drawn apart so the drive itself does not change.
    drive.gnss_sky = SkyGeometry(epoch_s=float(np.random.default_rng([seed, 5]).uniform(0.0, 86400.0)))
    return drive


# urban loop ----------------------------------------------------------------------------------------------
def _urban(rng: np.random.Generator, opts: dict[str, Any]) -> tuple[float, Body, float]:
    tunnels = tuple(float(x) for x in opts["tunnel_s"])
    if len(tunnels) != 2 or min(tunnels) <= 0.0:
        raise ValueError(f"urban tunnel_s needs two positive dark times in s, got {opts['tunnel_s']!r}")

    def lap(b: RouteBuilder, words: list[int]) -> None:
        if b.v != 0.0:
            b.speed_to(0.0, 2.0)
        probe = copy.deepcopy(b)
        t0 = probe.t
        _urban_lap(probe, words, tunnels, 0.0, 0.0, 0.0, 0.0)
        dn, de = horizontal_displacement(probe, t0, probe.t)
        # The lap starts heading north, so its own axes are north and east.
        extra_n = max(0.0, MIN_FILL_M - dn)
        extra_e = max(0.0, MIN_FILL_M - de)
        _urban_lap(b, words, tunnels, extra_n, extra_e, dn + extra_n, de + extra_e)

    return 0.0, lap, 0.0


def _urban_lap(b: RouteBuilder, words: list[int], tunnels: tuple[float, float], extra_n: float,
               extra_e: float, fill_s: float, fill_w: float) -> None:
    """One lap of four blocks with right turns, from a red light heading north back to the same light.

    The first lap (repetition 0) moves off at once: the drive's intro was its wait at the light."""
    rng = np.random.default_rng(words)
    sky = np.random.default_rng([*words, 1])
    traffic = np.random.default_rng([*words, 2])  # speed wandering with the traffic on fixed-length stretches
    v_n, v_e, v_s, v_w = (float(x) for x in rng.uniform(11.0, 16.4, 4))
    v_turn = float(rng.uniform(4.5, 6.0))
    acc = float(rng.uniform(1.3, 2.1))
    brake = float(rng.uniform(1.8, 2.8))
    lateral = float(rng.uniform(2.2, 3.2))
    stops = [float(x) for x in rng.uniform(20.0, 60.0, 4)]
    grade_1, grade_2 = (float(x) for x in rng.uniform(0.03, 0.06, 2))
    hold_1, hold_2 = (float(x) for x in rng.uniform(100.0, 200.0, 2))
    bend = math.radians(float(rng.uniform(8.0, 15.0)))
    canyon_1, canyon_2 = (float(x) for x in rng.uniform(45.0, 80.0, 2))
    fill_n, fill_e = (float(x) for x in rng.uniform(150.0, 350.0, 2))
    ramp = 2.0

    if words[-1] > 0:
        b.stand(stops[0], "stop")
    # Northbound: street canyon with an S-curve pair, a red light, a hill.
    b.speed_to(v_n, acc)
    b.cruise_m(120.0)
    t_c = b.t
    b.canyon(canyon_1, sky, low=CANYON_SKY[0], high=CANYON_SKY[1], ramp_s=ramp)
    b.speed_wander(44.0, traffic, TRAFFIC_MPS)  # the S-curves below last 4 x 11 s
    for sign in (1.0, -1.0, -1.0, 1.0):
        b.bend(sign * bend, 7.0)
        b.cruise(4.0)
    b.cruise(max(0.0, t_c + canyon_1 + 2.0 * ramp + 1.0 - b.t))
    b.speed_to(0.0, brake)
    b.stand(stops[1], "stop")
    b.speed_to(v_n, acc)
    b.cruise_m(80.0)
    b.hill(grade_1, 60.0, hold_1)
    b.cruise_m(fill_n + extra_n)
    b.speed_to(v_turn, brake)
    b.turn(HALF_PI, lateral)
    # Eastbound: the first tunnel, a red light at the junction.
    b.speed_to(v_e, acc)
    b.cruise_m(100.0)
    b.speed_wander(0.5 * (tunnels[0] + URBAN_PORTAL_S), traffic, TRAFFIC_MPS, repeat=2)
    b.tunnel(tunnels[0], portal_s=URBAN_PORTAL_S)
    b.cruise_m(fill_e + extra_e)
    b.speed_to(0.0, brake)
    b.stand(stops[2], "stop")
    b.speed_to(v_turn, acc)
    b.turn(HALF_PI, lateral)
    # Southbound: a canyon with a red light in it, a dip, the closing stretch.
    b.speed_to(v_s, acc)
    b.cruise_m(100.0)
    t_c = b.t
    b.canyon(canyon_2, sky, low=CANYON_SKY[0], high=CANYON_SKY[1], ramp_s=ramp)
    b.cruise(15.0)
    b.speed_to(0.0, brake)
    b.stand(stops[3], "stop")
    b.speed_to(v_s, acc)
    rest = max(5.0, t_c + canyon_2 + 2.0 * ramp + 1.0 - b.t)
    b.speed_wander(rest, traffic, TRAFFIC_MPS)
    b.cruise(rest)
    b.hill(-grade_2, 60.0, hold_2)
    b.cruise_m(fill_s)
    b.speed_to(v_turn, brake)
    b.turn(HALF_PI, lateral)
    # Westbound: the second, curved tunnel, the closing stretch, back north to the start light.
    b.speed_to(v_w, acc)
    b.cruise_m(100.0)
    b.speed_wander(0.5 * (tunnels[1] + URBAN_PORTAL_S), traffic, TRAFFIC_MPS, repeat=2)
    b.tunnel(tunnels[1], bend_rad=math.radians(6.0), portal_s=URBAN_PORTAL_S)
    b.cruise_m(fill_w)
    b.speed_to(v_turn, brake)
    b.turn(HALF_PI, lateral)
    b.speed_to(v_turn + 3.0, acc)
    b.cruise_m(40.0)
    b.speed_to(0.0, brake)


# steady-speed outage -------------------------------------------------------------------------------------
def _outage(rng: np.random.Generator, opts: dict[str, Any]) -> tuple[float, Body, float]:
    outage_s = float(opts["outage_s"])
    speed = float(opts["speed_mps"])
    if outage_s <= 0.0 or not 0.0 < speed <= 16.7:
        raise ValueError(f"outage-60s needs outage_s > 0 and 0 < speed_mps <= 16.7, got {outage_s}, {speed}")

    def body(b: RouteBuilder, words: list[int]) -> None:
        r = np.random.default_rng(words)
        delta = math.radians(float(r.uniform(2.0, 6.0))) * float(r.choice((-1.0, 1.0)))
        b.cruise(20.0)
        b.bend(delta, 15.0)
        b.cruise(25.0)
        b.bend(-delta, 15.0)
        b.cruise(15.0)
        b.tunnel(outage_s, dip_pitch_rad=0.0, bend_rad=math.radians(float(r.uniform(1.0, 3.0))), kind="outage")
        b.cruise(30.0)
        b.bend(-delta, 15.0)
        b.cruise(15.0)
        b.bend(delta, 15.0)
        b.cruise(15.0)

    return float(rng.uniform(0.0, 2.0 * math.pi)), body, speed


# long tunnel ---------------------------------------------------------------------------------------------
def _tunnel(rng: np.random.Generator, opts: dict[str, Any]) -> tuple[float, Body, float]:
    dark_s = float(opts["tunnel_s"])
    speed = float(opts["speed_mps"])
    if dark_s <= 0.0 or not 0.0 < speed <= 16.7:
        raise ValueError(f"tunnel-130s needs tunnel_s > 0 and 0 < speed_mps <= 16.7, got {dark_s}, {speed}")

    def body(b: RouteBuilder, words: list[int]) -> None:
        r = np.random.default_rng(words)
        traffic = np.random.default_rng([*words, 1])
        # Speed wanders with the traffic by up to 1.4 m/s, inside the tunnel too (the same in its dip and its
        # climb, so the exit is at the entry's height).
        b.speed_wander(57.0, traffic, 1.4)
        b.cruise(30.0)
        b.bend(math.radians(float(r.uniform(-10.0, 10.0))), 12.0)
        b.cruise(15.0)
        portal_s = 1.0
        b.speed_wander(0.5 * (dark_s + portal_s), traffic, 1.4, repeat=2)
        b.tunnel(dark_s, dip_pitch_rad=float(r.uniform(0.02, 0.04)), bend_rad=math.radians(float(r.uniform(5.0, 10.0))),
                 portal_s=portal_s)
        b.speed_wander(45.0, traffic, 1.4)
        b.cruise(45.0)

    return float(rng.uniform(0.0, 2.0 * math.pi)), body, speed


Body = Callable[[RouteBuilder, list[int]], None]
_SCENARIO_BODIES: dict[str, Callable[[np.random.Generator, dict[str, Any]], tuple[float, Body, float]]] = {
    "urban": _urban,
    "outage-60s": _outage,
    "tunnel-130s": _tunnel,
}
