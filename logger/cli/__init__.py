"""The ``logger`` command: one entry point, one module per subcommand.

Each subcommand lives in its own module with a ``main(argv) -> int``; importing it only when it is
asked for keeps ``logger status`` quick on a slow board.

The name is shared with util-linux's ``/usr/bin/logger``, which shell scripts on the board call
(``logger -t tag msg``, ``echo msg | logger``). Anything that is not one of our subcommands or ``--help``
is therefore handed over unchanged to the system's logger: the process is replaced by it (``exec``), so
it gets the same arguments, stdin, stdout, stderr and environment, and its exit code is the exit code. A typo of
one of our commands typed at a terminal goes there too (a script may mean util-linux), with a one-line hint.
``--version`` names both programs.
"""

from __future__ import annotations

import difflib
import importlib
import os
import subprocess
import sys
import textwrap
from collections.abc import Callable, Sequence

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "run": ("logger.cli.run", "run the logging daemon (--sim: on the simulated vehicle, no hardware needed)"),
    "gnss-decode": ("logger.cli.gnss_decode",
                    "decode a u-blox receiver capture: a line per fix (--json: one JSON line per fix)"),
    "status": ("logger.cli.status",
               "show the running logger's health (exit 0 ok, 1 degraded, 2 critical, 3 not running, "
               "4 cannot tell: not answering, not allowed or a bad --config)"),
    "config": ("logger.cli.config_check", "check a configuration file without starting: logger config check FILE"),
    "info": ("logger.cli.info", "summarise a recorded MCAP file: topics, counts, rates, gaps"),
    "replay": ("logger.cli.replay", "run the navigation filter over recorded drives: trajectory CSV and MCAP"),
    "recover": ("logger.cli.recover", "make a file cut short by a crash readable and indexed again"),
    "export": ("logger.cli.export", "a drive's /gnss/fix and /nav/fix as GPX, KML and CSV"),
    "plot": ("logger.cli.plot", "PNG plots of a drive: map, sensor rates and gaps, clock sync state"),
    "sync-report": ("logger.cli.sync_report", "the paper's time-sync tables and the stamp error of a recorded drive"),
    "nav-score": ("logger.cli.nav_score", "score replayed trajectories against a simulated drive's truth"),
}


SYSTEM_LOGGER = "/usr/bin/logger"
HANDOVER_ENV = "VEHICLE_LOGGER_HANDED_OVER"  # set for the system logger: a second hand-over means a loop


def usage() -> str:
    """The commands, each wrapped to 80 columns under its name."""
    lines = ["usage: logger COMMAND [ARGS...]", "", "commands:"]
    for name, (_, text) in SUBCOMMANDS.items():
        lines += textwrap.wrap(text, 79, initial_indent=f"  {name:<14}", subsequent_indent=" " * 16,
                               break_on_hyphens=False)
    lines += ["", *textwrap.wrap("Anything else (logger -t TAG MESSAGE, echo MESSAGE | logger, ...) goes to the "
                                 f"system's logger (util-linux, {SYSTEM_LOGGER}) unchanged.", 79)]
    return "\n".join(lines)


def _is_ourselves(path: str, own: set[str]) -> bool:
    """True for this program under any name: the same file, or a script that starts ``logger.cli``."""
    try:
        if os.path.realpath(path) in own:
            return True
        with open(path, "rb") as f:
            head = f.read(512)
    except OSError:
        return False
    # A pip console script (venv or /usr/local/bin) is a short Python file importing our entry point.
    return head.startswith(b"#!") and b"python" in head.split(b"\n", 1)[0] and b"logger.cli" in head


def find_system_logger(path_env: str | None, own: Sequence[str]) -> str | None:
    """The first ``logger`` on ``path_env`` that is not this program, else /usr/bin/logger if it is there."""
    own_real = {os.path.realpath(p) for p in own if p}
    for folder in (path_env or "").split(os.pathsep):
        candidate = os.path.join(folder or ".", "logger")
        if os.path.isfile(candidate) and os.access(candidate, os.X_OK) and not _is_ourselves(candidate, own_real):
            return candidate
    if os.path.isfile(SYSTEM_LOGGER) and os.access(SYSTEM_LOGGER, os.X_OK) \
            and not _is_ourselves(SYSTEM_LOGGER, own_real):
        return SYSTEM_LOGGER
    return None


def hand_over(args: list[str]) -> int:
    """Replace this process by the system's logger with the same arguments; returns only if that fails."""
    if os.environ.get(HANDOVER_ENV):
        print("logger: the system logger found on PATH hands back to this program; not looping", file=sys.stderr)
        return 127
    target = find_system_logger(os.environ.get("PATH"), [sys.argv[0], __file__])
    if target is None:
        print(f"logger: {args[0] if args else 'stdin'}: not a vehicle-logger command, and no system logger "
              f"(util-linux) was found on PATH or at {SYSTEM_LOGGER}", file=sys.stderr)
        return 127
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        os.execve(target, ["logger", *args], {**os.environ, HANDOVER_ENV: "1"})
    except OSError as exc:
        print(f"logger: cannot run {target}: {exc.strerror or exc}", file=sys.stderr)
    return 126


def version() -> str:
    """This program's version, and the system logger's that everything else goes to."""
    from logger import __version__  # the running code's own (an installed package's metadata can be another's)

    lines = [f"logger (vehicle-logger) {__version__}"]
    target = find_system_logger(os.environ.get("PATH"), [sys.argv[0], __file__])
    if target is None:
        lines.append(f"system logger: none found on PATH or at {SYSTEM_LOGGER}")
        return "\n".join(lines)
    try:
        r = subprocess.run([target, "--version"], capture_output=True, text=True, timeout=5,
                           env={**os.environ, HANDOVER_ENV: "1"})
        theirs = (r.stdout or r.stderr).strip().splitlines()[0] if (r.stdout or r.stderr).strip() else "?"
    except (OSError, subprocess.SubprocessError):
        theirs = "?"
    lines.append(f"system logger ({target}): {theirs}")
    return "\n".join(lines)


def near_miss(word: str) -> str | None:
    """The one of our commands ``word`` looks like a typo of, if any ("stauts" -> "status")."""
    if word.startswith("-"):
        return None
    close = difflib.get_close_matches(word, list(SUBCOMMANDS), n=1, cutoff=0.75)
    return close[0] if close else None


def run_subcommand(module_name: str, args: list[str]) -> int:
    """A subcommand; a reader that closes the pipe early (``logger info F | head -1``) ends it quietly, and Ctrl-C
    with one line (a replay or an export stopped part-way writes its outputs whole or not at all; ``logger run``
    stopped before its own handlers are in place has recorded nothing yet, or leaves a file the next start
    recovers)."""
    try:
        # The import inside: it is most of a short command's time (seconds on a board's core), and Ctrl-C there gave
        # a traceback and a death by the signal.
        module = importlib.import_module(module_name)
        return quiet_on_closed_pipe(lambda: int(module.main(args) or 0))
    except KeyboardInterrupt:
        name = module_name.rsplit(".", 1)[-1].replace("_", "-")
        print(f"\nlogger {name}: interrupted", file=sys.stderr)
        return 130  # 128 + SIGINT, what a shell reports for a command stopped by Ctrl-C


def quiet_on_closed_pipe(body: Callable[[], int]) -> int:
    """``body``'s exit code, or 141 without a traceback when the reader of stdout went away (``| head``)."""
    try:
        code = body()
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        # Python's own recipe: point stdout at /dev/null so the interpreter's final flush does not fail again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a writer whose reader went away


def _print(text: str) -> int:
    print(text)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run a subcommand; from the command line (``argv`` None), hand anything else to the system's logger.

    Called with an explicit ``argv`` (from Python), an unknown command is an error instead: replacing the
    calling process would be a surprise there.
    """
    args = sys.argv[1:] if argv is None else argv
    if sys.stdout is None:
        # Started with stdout closed (``>&-``): Python leaves sys.stdout None, print() writes nothing, and every
        # other use of it (the final flush, a run's summary asking isatty()) failed with a traceback, after the work.
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - for the life of the process
    if args and args[0] in ("-h", "--help"):
        return quiet_on_closed_pipe(lambda: _print(usage()))
    if args and args[0] in ("-V", "--version") and len(args) == 1:
        return quiet_on_closed_pipe(lambda: _print(version()))
    entry = SUBCOMMANDS.get(args[0]) if args else None
    if entry is None:
        if argv is not None:
            print(f"logger: unknown command {args[0] if args else ''!r}\n{usage()}", file=sys.stderr)
            return 2
        if not args and sys.stdin.isatty():
            print("logger: no command: passing the terminal to the system logger (Ctrl-D ends); "
                  "`logger --help` lists the vehicle logger's commands", file=sys.stderr)
        elif args and sys.stdin.isatty() and (guess := near_miss(args[0])) is not None:
            print(f"logger: {args[0]!r} is not a vehicle-logger command (did you mean `logger {guess}`?); "
                  "passing it to the system logger", file=sys.stderr)
        return hand_over(args)  # not ours, including no arguments at all (``echo msg | logger``)
    return run_subcommand(entry[0], args[1:])

