"""``logger status``: what an operator at a red light needs, in one screen.

The daemon's snapshot comes over its status socket (:mod:`logger.runtime.status_socket`); this renders it, and
the exit code is the verdict for scripts: 0 healthy, 1 degraded, 2 critical, 3 not running, 4 nobody can say
(running but not answering in time, or this user may not read its socket). On a terminal the
screen is drawn to its size (:mod:`logger.cli.status_view`); ``--watch`` redraws it in place.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any, NoReturn

from logger.cli.status_view import COLUMNS, render
from logger.config import DEFAULT_PATH, DEFAULT_SIM_SOCKET, SCHEMA, ConfigError, load
from logger.runtime.status_socket import (
    EXIT,
    NOT_RUNNING,
    UNKNOWN,
    StatusBusy,
    StatusDenied,
    denied,
    fetch,
    sim_sockets,
)

HOME, CLEAR_SCREEN, CLEAR_LINE, CLEAR_BELOW = "\x1b[H", "\x1b[2J", "\x1b[K", "\x1b[J"


def find_socket() -> tuple[Path, dict[str, Any]]:
    """No socket named or configured: the service's, then those of ``logger run --sim`` without a configuration
    (a second simulated run gets one of its own), the first that answers, with its snapshot; ConnectionError
    naming them all."""
    tried = [Path(SCHEMA["logger"]["status_socket"].default), *sim_sockets(Path(DEFAULT_SIM_SOCKET))]
    for p in tried:
        try:
            there = p.exists()
        except PermissionError:  # its folder may not be read (/run/vehicle-logger is the logger group's)
            raise denied(p.parent) from None
        if there:
            try:
                return p, fetch(p, timeout_s=1.0)
            except (StatusBusy, StatusDenied):
                raise  # a logger is there, only slow to answer or not ours to ask: say so, not the next socket
            except ConnectionError:
                continue  # a socket a crashed run left
    # A line per socket: over SSH on an 80-column terminal, two long paths on one line wrapped mid-path.
    raise ConnectionError("logger is not running; nobody answers on\n" + "\n".join(f"  {p}" for p in tried))


class _Parser(argparse.ArgumentParser):
    """The command line's own mistakes are one line and exit 4 (nobody can say): argparse's exit 2 is this
    command's "critical", and a script or a widget read a typo (``--jsn``) as a critical logger."""

    def error(self, message: str) -> NoReturn:
        print(f"logger status: {message} (logger status --help)", file=sys.stderr)
        raise SystemExit(UNKNOWN)


WATCH_MIN_S = 0.2  # the quickest redraw: the daemon's snapshot is a second's


def _interval(text: str) -> float:
    """--watch's seconds: a number from WATCH_MIN_S (0 drew one frame and stopped, -1 redrew five times a second)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and value >= WATCH_MIN_S):
        raise argparse.ArgumentTypeError(f"{text} seconds: from {WATCH_MIN_S:g} s up")
    return value


def redraws_in_place(tty: bool) -> bool:
    """Whether --watch may move the cursor: a terminal that says what it is, and not a dumb one (TERM=dumb, or
    none: an Emacs shell, a serial console), where the escape codes came out as text in every frame."""
    return tty and os.environ.get("TERM", "") not in ("", "dumb")


def main(argv: list[str]) -> int:
    parser = _Parser(prog="logger status", description="show the running logger's health",
                     epilog=COLUMNS, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print the raw snapshot")
    parser.add_argument("--watch", nargs="?", const=1.0, type=_interval, metavar="SECONDS",
                        help="redraw in place until Ctrl-C (default every second)")
    parser.add_argument("--socket", help="status socket path (default: from the configuration)")
    parser.add_argument("--config", default=None, help=f"configuration file (default {DEFAULT_PATH})")
    args = parser.parse_args(argv)
    path = args.socket
    if path is None:
        path = os.environ.get("LOGGER_STATUS_SOCKET")
    if path is None:
        cfg_path = Path(args.config) if args.config else DEFAULT_PATH
        try:
            # Only its [logger] section is wanted: a simulated run's file (no device ports) names its socket too.
            path = (load(cfg_path, devices=False)["logger"]["status_socket"]
                    if args.config or cfg_path.exists() else None)
        except ConfigError as exc:
            if args.config:  # named on the command line: what is wrong with it, not "not running" (exit 4: 2 is
                for line in exc.problems:  # a verdict, critical)
                    print(f"logger status: {line}", file=sys.stderr)
                return UNKNOWN
            path = None
        except OSError as exc:
            if args.config:
                print(f"logger status: {cfg_path}: {exc.strerror or exc}", file=sys.stderr)
                return UNKNOWN
            path = None  # the default one, which this user may not read: the default sockets are tried
    tty = sys.stdout.isatty()
    code = NOT_RUNNING
    first = True
    try:
        while True:
            # The screen's size, taken again for every frame (a resized window redraws to its new size); a pipe
            # gets the 80 columns of the terminal the text will most likely be read on, and every line. --watch
            # leaves one line for its cursor; a single screen two, for the command typed above it and the prompt
            # after it, so that the verdict on the first line is still on screen when the prompt comes back.
            size = shutil.get_terminal_size((80, 24))
            try:
                snap = fetch(path) if path is not None else find_socket()[1]
                code = EXIT.get(snap.get("verdict", ""), 2)
                text = json.dumps(snap, indent=1) if args.json else render(
                    snap, size.columns if tty else 80, size.lines - (1 if args.watch else 2) if tty else None)
            except (StatusBusy, StatusDenied) as exc:
                code, text = UNKNOWN, f"logger status: {exc}"
            except ConnectionError as exc:
                code, text = NOT_RUNNING, f"logger status: {exc}"
            if args.watch:
                if redraws_in_place(tty):  # over the last frame, line by line, then clear what it had below
                    frame = "".join(line + CLEAR_LINE + "\n" for line in text.split("\n"))
                    sys.stdout.write((CLEAR_SCREEN if first else "") + HOME + frame + CLEAR_BELOW)
                else:
                    sys.stdout.write(text + "\n\n")
                sys.stdout.flush()
                first = False
                time.sleep(args.watch)
                continue
            print(text, file=sys.stderr if code in (NOT_RUNNING, UNKNOWN) else sys.stdout)
            return code
    except KeyboardInterrupt:
        return code
