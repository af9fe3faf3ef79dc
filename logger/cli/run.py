"""``logger run``: the daemon in the foreground, on hardware, on the simulated vehicle, or on a mix.

``--sim`` needs no file: every sensor is simulated and files go to ./drives. With a configuration, each sensor
whose ``source`` is ``"sim"`` is simulated and the others are opened as hardware; a time scale other than 1
is refused then, because real devices cannot run faster than real time.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import shutil
import sys
from pathlib import Path

from logger.compose import build
from logger.config import (
    DEFAULT_PATH,
    DEFAULT_SIM_OUT,
    DEFAULT_SIM_SOCKET,
    SCHEMA,
    SIM_SECTIONS,
    Config,
    ConfigError,
    chrony_problem,
    defaults,
    load,
    time_scale_problem,
)
from logger.runtime import logs
from logger.runtime.daemon import Daemon
from logger.runtime.state_file import StateInUse, lock_state, unlock_state
from logger.runtime.status_socket import free_sim_socket
from logger.runtime.summary import fitted, run_summary, shortfalls

log = logging.getLogger("logger")


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


def resolve_config(args: argparse.Namespace) -> Config:
    if args.config:
        # With --sim no device of the file is opened: its serial ports are not demanded, so a file with only a
        # [sim] section (or [sim] and [nav]) is enough.
        cfg = load(args.config, sim=args.sim, devices=not args.sim)
        if args.sim:
            for s in SIM_SECTIONS:
                if cfg.values[s]["source"] == "gpsd":
                    cfg.values["sim"]["gpsd"] = True  # keep reading gpsd: a simulated one, fed by the simulation
                else:
                    cfg.values[s]["source"] = "sim"
            sim_places(cfg)
    elif args.sim:
        cfg = defaults(sim=True)
        sim_places(cfg)
    else:
        cfg = load(DEFAULT_PATH)
    sim = cfg.values["sim"]
    if args.scenario is not None:
        sim["scenario"] = args.scenario
    if args.seed is not None:
        problem = SCHEMA["sim"]["seed"].check(args.seed)  # type: ignore[misc]
        if problem:
            raise ConfigError([f"--seed {args.seed} {problem}"])
        sim["seed"] = args.seed
    if args.time_scale is not None:
        problem = SCHEMA["sim"]["time_scale"].check(args.time_scale)  # type: ignore[misc]
        if problem:
            raise ConfigError([f"--time-scale {args.time_scale:g} {problem}"])
        sim["time_scale"] = float(args.time_scale)
    if args.out:
        cfg.values["logger"]["out_dir"] = str(Path(args.out).resolve())
        if args.sim and "logger.state_dir" not in cfg.explicit:
            cfg.values["logger"]["state_dir"] = str(Path(args.out).resolve() / ".state")
    if args.status_socket:
        cfg.values["logger"]["status_socket"] = args.status_socket
    problem = time_scale_problem(cfg) or chrony_problem(cfg)  # again: --sim and --time-scale may have changed them
    if problem:
        raise ConfigError([problem])
    return cfg


def sim_places(cfg: Config) -> None:
    """Where a simulated run writes, unless its file says: files under ./drives, the clock's state beside them, a
    status socket where ``logger status`` looks (the board's /var/lib and /run are not a user's to write)."""
    places = cfg.values["logger"]
    if "logger.out_dir" not in cfg.explicit:
        places["out_dir"] = str(Path(DEFAULT_SIM_OUT).resolve())
    if "logger.status_socket" not in cfg.explicit:
        # A second simulated run beside one already running gets a socket of its own instead of taking the other's.
        places["status_socket"] = str(free_sim_socket(Path(DEFAULT_SIM_SOCKET)))
    if "logger.state_dir" not in cfg.explicit:
        places["state_dir"] = str(Path(places["out_dir"]) / ".state")


RATES_NOT_HELD = 3  # exit code of a simulated drive whose sensors fell short of their rates
NOTHING_RECORDED = 4  # exit code of a run of which no record is on disk (a full or missing disk throughout)
FILE_UMASK = 0o027  # recorded drives, the clock's state: group-readable (the operators' group), never the world's


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    logs.setup(args.verbose)
    # Whatever the caller's umask (a shell's 022 makes a drive world-readable): the service's unit sets the same.
    os.umask(FILE_UMASK | os.umask(FILE_UMASK))
    try:
        cfg = resolve_config(args)
    except ConfigError as exc:
        for line in exc.problems:
            print(f"logger: {line}", file=sys.stderr)
        return 2
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        print("logger: --duration must be a positive number of seconds", file=sys.stderr)
        return 2
    try:
        lock = lock_state(Path(cfg["logger"]["state_dir"]))  # one logger per state folder, for the whole run
    except StateInUse as exc:
        print(f"logger: {exc.filename}: {exc.strerror}", file=sys.stderr)
        return 1
    try:
        return _run(args, cfg)
    finally:
        unlock_state(lock)


def _run(args: argparse.Namespace, cfg: Config) -> int:
    try:
        daemon, _vehicle = build(cfg, args.duration)
    except ConfigError as exc:
        for line in exc.problems:
            print(f"logger: {line}", file=sys.stderr)
        return 2
    try:
        code = daemon.run(args.duration)
    except OSError as exc:  # the output folder or the socket cannot be created: say which, no traceback
        why = "exists and is not a folder" if isinstance(exc, FileExistsError) else exc.strerror or exc
        out, name = Path(cfg["logger"]["out_dir"]), Path(exc.filename or "")
        if name == out or name in out.parents:  # the folder, or the part of its path that stopped it
            print(f"logger: cannot make the output folder {out}: {why}" + (f" ({name})" if name != out else ""),
                  file=sys.stderr)
        else:
            print(f"logger: {exc.filename or ''}: {why}", file=sys.stderr)
        daemon.stop()
        return 1
    return finish(daemon, code)


def finish(daemon: Daemon, code: int) -> int:
    """After the daemon stopped: the run's summary on stdout, and the exit code (``NOTHING_RECORDED`` for a run of
    which nothing is on disk, a logger's one job; ``RATES_NOT_HELD`` for a paced simulated drive that still fell
    short of a sensor's rate: it measured the host, not the code).

    A run that recorded nothing exits non-zero so that a script, and systemd (the unit shows failed after the stop,
    with this line in the journal), do not take it for a drive. Restart= does not act on a stop, so the service
    is not restarted for it; the daemon itself never ends on a full disk, it waits for space."""
    try:
        text = run_summary(daemon)
        # On a terminal, fitted to it; the journal and a pipe get whole lines (one line, one grep)
        print(fitted(text, shutil.get_terminal_size((80, 24)).columns) if sys.stdout.isatty() else text, flush=True)
    except Exception:  # the run is over and its files are closed: a summary that fails must not change that
        log.exception("could not summarise the run")
    rec = daemon.recorder.status()
    if code == 0 and not any(rec.written.values()):
        if not any(rec.lost.values()) and not any(rec.unrecorded.values()) and not any(rec.deleted.values()) \
                and rec.down_s == 0.0:
            # Stopped before its first record arrived (a stop right after the start): no fault of the disk, and
            # nothing lost; "nothing of this run is on disk" with exit 4 sent a person to a disk with 68 GB free.
            print("logger: stopped before the first record arrived: nothing to record", file=sys.stderr)
            return code
        print("logger: nothing of this run is on disk (see above: the recorder's state and the log say why)",
              file=sys.stderr)
        return NOTHING_RECORDED
    if code == 0 and daemon.tb.pace() is not None and shortfalls(daemon, host_only=True):
        print("logger: the simulated drive did not hold its sensors' rates even at real time (see above): this "
              "host is too slow or too busy for it; the recording is not one a real drive would give",
              file=sys.stderr)
        return RATES_NOT_HELD
    return code
