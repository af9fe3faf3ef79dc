"""The ``logger`` command: one entry point, one module per subcommand.

Each subcommand lives in its own module with a ``main(argv) -> int``; importing it only when it is
asked for keeps ``logger status`` quick on a slow board.
"""

from __future__ import annotations

import importlib
import sys

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "run": ("logger.run_cmd", "run the logging daemon (--sim: on the simulated vehicle, no hardware needed)"),
    "gnss-decode": ("logger.gnss_decode", "decode a u-blox receiver capture to one JSON line per fix"),
    "status": ("logger.status", "show the running logger's health (exit 0 ok, 1 degraded, 2 critical, 3 not running)"),
    "config": ("logger.config_cmd", "check a configuration file without starting: logger config check FILE"),
    "info": ("logger.info", "summarise a recorded MCAP file: topics, counts, rates, gaps"),
    "recover": ("logger.recover_cmd", "make a file cut short by a crash readable and indexed again"),
}


def usage() -> str:
    lines = ["usage: logger COMMAND [ARGS...]", "", "commands:"]
    lines += [f"  {name:<14}{text}" for name, (_, text) in SUBCOMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return 0
    entry = SUBCOMMANDS.get(args[0])
    if entry is None:
        print(f"logger: unknown command {args[0]!r}\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(entry[0])
    return int(module.main(args[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
