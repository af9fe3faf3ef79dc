"""``logger run``: the daemon in the foreground, on hardware, on the simulated vehicle, or on a mix.

``--sim`` needs no file: every sensor is simulated and files go to ./drives. With a configuration, each sensor
whose ``source`` is ``"sim"`` is simulated and the others are opened as hardware; a time scale other than 1
is refused then, because real devices cannot run faster than real time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from logger import logs
from logger.config import DEFAULT_PATH, SCHEMA, Config, ConfigError, defaults, load
from logger.daemon import Daemon, Extras
from logger.sampler import Reading
from logger.sources import plans_from_config
from logger.timebase import TimeBase, host_timebase
from sync.clock import PpsClock, SyncSettings

log = logging.getLogger("logger")

SIM_SECTIONS = ("imu", "baro", "obd", "gnss", "pps")
DEFAULT_SIM_OUT = "drives"
DEFAULT_SIM_SOCKET = "/tmp/vehicle-logger-sim/status.sock"


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="logger run", description="run the logging daemon in the foreground")
    p.add_argument("--config", help=f"configuration file (default {DEFAULT_PATH}; none needed with --sim)")
    p.add_argument("--sim", action="store_true", help="simulate every sensor (the vehicle, its drive and devices)")
    p.add_argument("--scenario", help="simulated drive: urban (default), outage-60s, tunnel-130s")
    p.add_argument("--seed", type=int, help="seed of the simulated drive and its sensor errors")
    p.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this many seconds of drive")
    p.add_argument("--time-scale", type=float, metavar="X", help="run a simulated drive X times faster")
    p.add_argument("--out", metavar="DIR", help="folder for the MCAP files (overrides logger.out_dir)")
    p.add_argument("--status-socket", metavar="PATH", help="status socket (overrides logger.status_socket)")
    p.add_argument("-v", "--verbose", action="store_true")
    return p.parse_args(argv)


def simulated_sections(cfg: Config) -> dict[str, bool]:
    """Which sensors the simulated vehicle plays: those with source 'sim', and 'gpsd' ones when sim.gpsd says
    that gpsd is simulated too."""
    return {s: cfg[s]["source"] == "sim" or (cfg[s]["source"] == "gpsd" and bool(cfg["sim"]["gpsd"]))
            for s in SIM_SECTIONS}


def resolve_config(args: argparse.Namespace) -> Config:
    if args.config:
        cfg = load(args.config)
        if args.sim:
            for s in SIM_SECTIONS:
                if cfg.values[s]["source"] == "gpsd":
                    cfg.values["sim"]["gpsd"] = True  # keep reading gpsd: a simulated one, fed by the simulation
                else:
                    cfg.values[s]["source"] = "sim"
    elif args.sim:
        cfg = defaults(sim=True)
        cfg.values["logger"]["out_dir"] = str(Path(DEFAULT_SIM_OUT).resolve())
        cfg.values["logger"]["status_socket"] = DEFAULT_SIM_SOCKET
        cfg.values["logger"]["state_dir"] = str(Path(DEFAULT_SIM_OUT).resolve() / ".state")
    else:
        cfg = load(DEFAULT_PATH)
    sim = cfg.values["sim"]
    if args.scenario is not None:
        sim["scenario"] = args.scenario
    if args.seed is not None:
        sim["seed"] = args.seed
    if args.time_scale is not None:
        problem = SCHEMA["sim"]["time_scale"].check(args.time_scale)  # type: ignore[misc]
        if problem:
            raise ConfigError([f"--time-scale {args.time_scale:g} {problem}"])
        sim["time_scale"] = float(args.time_scale)
    if args.out:
        cfg.values["logger"]["out_dir"] = str(Path(args.out).resolve())
        if args.sim and not args.config:
            cfg.values["logger"]["state_dir"] = str(Path(args.out).resolve() / ".state")
    if args.status_socket:
        cfg.values["logger"]["status_socket"] = args.status_socket
    simulated = simulated_sections(cfg)
    real = [s for s in SIM_SECTIONS if not simulated[s] and cfg[s]["source"] != "none"]
    if real and sim["time_scale"] != 1.0:
        raise ConfigError([f"sim.time_scale = {sim['time_scale']:g} needs every sensor simulated; real: "
                           + ", ".join(real)])
    return cfg


def build(cfg: Config, duration_s: float | None,
          scenario_options: dict[str, Any] | None = None) -> tuple[Daemon, Any]:
    """The daemon and, when any sensor is simulated, the vehicle behind it (already started).

    ``scenario_options`` reach the simulated drive (e.g. ``tunnel_s`` of tunnel-130s): for evaluation tools."""
    simulated = simulated_sections(cfg)
    sim_gpsd = bool(cfg["sim"]["gpsd"]) and "gpsd" in (cfg["gnss"]["source"], cfg["pps"]["source"])
    vehicle = None
    tb: TimeBase = host_timebase()
    extras = Extras()
    if any(simulated.values()):
        from sensors.sim.scenarios import SCENARIOS
        from sensors.sim.vehicle import build_vehicle

        sim = cfg["sim"]
        if sim["scenario"] not in SCENARIOS:
            raise ConfigError([f"unknown scenario {sim['scenario']!r}: choose one of {', '.join(SCENARIOS)}"])
        vehicle = build_vehicle(sim["scenario"], sim["seed"], time_scale=sim["time_scale"], duration_s=duration_s,
                                scenario_options=scenario_options,
                                imu=simulated["imu"], baro=simulated["baro"], obd=simulated["obd"],
                                gnss=cfg["gnss"]["source"] == "sim", pps=cfg["pps"]["source"] == "sim",
                                gpsd=sim_gpsd)
        vehicle.start()
        tb = TimeBase(vehicle.clock.monotonic_ns, vehicle.time_scale)
        extras.close.append(vehicle.stop)
        extras.metadata["simulation"] = {"scenario": vehicle.scenario, "seed": str(vehicle.seed),
                                         "time_scale": f"{vehicle.time_scale:g}",
                                         "start_utc": vehicle.timeline.start_utc.isoformat()}
        if vehicle.imu is not None and "imu_error_scale" in (scenario_options or {}):
            # A drive made with a chip other than the default says so: its IMU errors are part of what it tests.
            extras.metadata["simulation"]["imu_errors"] = json.dumps(dataclasses.asdict(vehicle.imu.errors))

        def truth_clock() -> list[Reading]:
            now = tb.monotonic_ns()
            return [Reading("/truth/clock", {"t_mono_ns": now, "t_true_ns": vehicle.true_unix_ns(now)}, now,
                            stamped=False)]

        def truth_nav() -> list[Reading]:
            now = tb.monotonic_ns()
            return [Reading("/truth/nav", vehicle.truth_nav(now), now, stamped=False)]

        extras.periodic.append((0.1, truth_clock))
        extras.periodic.append((1.0 / cfg["imu"]["rate_hz"], truth_nav))
    extras.metadata["config"] = {f"{s}.{k}": str(v) for s, keys in cfg.values.items() for k, v in keys.items()}
    if vehicle is not None and simulated["gnss"]:
        # The simulated board's system clock is NTP-synchronised (to 20 ms): a check of the clock's first lock.
        clock = make_clock(cfg, tb, f"sim-{vehicle.oscillator.board_start_ns}-{vehicle.time_scale:g}",
                           wall_ns=vehicle.wall_clock_ns, wall_trusted=True)
    else:
        from sync.wallclock import system_clock_synchronized

        clock = make_clock(cfg, tb, boot_id(), wall_trusted=system_clock_synchronized())
    extras.close.append(clock.save)
    plans = plans_from_config(cfg, tb, vehicle.devices if vehicle else None)
    mode = f"simulated drive '{cfg['sim']['scenario']}'" if vehicle and all(simulated.values()) else (
        "partly simulated" if vehicle else "")
    from logger.nav.live import attach_navigator

    navigator = attach_navigator(cfg["nav"], extras)
    daemon = Daemon(cfg, plans, timebase=tb, clock=clock, extras=extras, mode=mode)
    if navigator is not None:
        navigator.bind(daemon)
    return daemon, vehicle


def boot_id() -> str:
    """Identifies this boot: a clock mapping saved under the same id is still valid (CLOCK_MONOTONIC went on)."""
    try:
        return "boot-" + Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def make_clock(cfg: Config, tb: TimeBase, clock_id: str, wall_ns: Callable[[], int] = time.time_ns,
               wall_trusted: bool = False) -> PpsClock:
    sc = cfg["sync"]
    settings = SyncSettings(imu_rate_hz=cfg["imu"]["rate_hz"], pps_latency_ns=round(sc["pps_latency_us"] * 1000),
                            stability_ppm=sc["stability_ppm"], max_slew_ppm=sc["max_slew_ppm"])
    clock = PpsClock(settings, monotonic_ns=tb.monotonic_ns, wall_ns=wall_ns,
                     state_path=Path(cfg["logger"]["state_dir"]) / "clock.json", clock_id=clock_id,
                     wall_trusted=wall_trusted)
    if sc["chrony_sock"]:
        from sync.chrony_sock import ChronySock

        clock.on_sample = ChronySock(sc["chrony_sock"]).send_edge
    return clock


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    logs.setup(args.verbose)
    try:
        cfg = resolve_config(args)
    except ConfigError as exc:
        for line in exc.problems:
            print(f"logger: {line}", file=sys.stderr)
        return 2
    if args.duration is not None and args.duration <= 0:
        print("logger: --duration must be positive", file=sys.stderr)
        return 2
    try:
        daemon, _vehicle = build(cfg, args.duration)
    except ConfigError as exc:
        for line in exc.problems:
            print(f"logger: {line}", file=sys.stderr)
        return 2
    try:
        return daemon.run(args.duration)
    except OSError as exc:  # the output folder or the socket cannot be created: say which, no traceback
        print(f"logger: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        daemon.stop()
        return 1
