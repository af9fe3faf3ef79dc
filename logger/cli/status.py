"""``logger status``: what an operator at a red light needs, in one screen.

The daemon's snapshot comes over its status socket (:mod:`logger.runtime.status_socket`); this renders it, and
the exit code is the verdict for scripts: 0 healthy, 1 degraded, 2 critical, 3 not running.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from logger.config import DEFAULT_PATH, DEFAULT_SIM_SOCKET, SCHEMA, ConfigError, load
from logger.runtime.status_socket import EXIT, NOT_RUNNING, fetch, sim_sockets


def _age(s: float | None) -> str:
    if s is None:
        return "never"
    return f"{s:.1f}s" if s < 120 else f"{s / 60:.0f}min"


def _duration(s: float) -> str:
    s = int(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m{s % 60:02d}s"


def render(snap: dict[str, Any]) -> str:
    verdict = snap.get("verdict", "?")
    lines = [f"logger: {verdict.upper()}   up {_duration(snap.get('uptime_s', 0))}   pid {snap.get('pid', '?')}"
             + (f"   [{snap['mode']}]" if snap.get("mode") else "")]
    for p in snap.get("problems", []):
        lines.append(f"  ! {p}")
    lines.append("")
    lines.append(f"  {'sensor':<8} {'state':<9} {'rate Hz':>12} {'last':>7} {'errors':>6} {'gaps':>5} "
                 f"{'late':>5} {'reconn':>6}  last error")
    for h in snap.get("sensors", []):
        rate = f"{h['measured_rate_hz']:.1f}/{h['rate_hz']:g}" if h.get("rate_hz") else f"{h['measured_rate_hz']:.1f}"
        lines.append(f"  {h['name']:<8} {h['state']:<9} {rate:>12} {_age(h['last_sample_age_s']):>7} "
                     f"{h['errors']:>6} {h['gaps']:>5} {h['late']:>5} {h['reconnects']:>6}  {h['last_error']}")
    for h in snap.get("sensors", []):
        for kind, count in (h.get("incidents") or {}).items():
            lines.append(f"  {h['name']:<8} {kind}: {count} since start")
    origins = [f"{h['name']} from {h['origin']}" for h in snap.get("sensors", []) if h.get("origin")]
    if origins:
        lines.append("  source   " + ", ".join(origins))
    sync = snap.get("sync")
    if sync:
        lines.append("")
        lines.append(f"  clock    {sync.get('state', '?'):<9} error bound {sync.get('err_ns', 0) / 1e3:.1f} us"
                     + (f", offset {sync['offset_ns'] / 1e3:+.1f} us" if sync.get("offset_ns") is not None else "")
                     + (f", freq {sync['freq_ppm']:+.3f} ppm" if sync.get("freq_ppm") is not None else "")
                     + (f", last PPS {_age(sync.get('since_edge_s'))} ago" if "since_edge_s" in sync else ""))
    nav = snap.get("nav")
    if nav and nav.get("lat_deg") is not None:
        lines.append(f"  position {nav['lat_deg']:.7f} {nav['lon_deg']:.7f} h {nav['height_m']:.1f} m"
                     + (f"  (sigma {nav['sigma_h_m']:.1f} m)" if nav.get("sigma_h_m") is not None else "")
                     + (f"  {nav['source']}" if nav.get("source") else ""))
    if nav:
        for v in nav.get("verdicts") or []:
            lines.append(f"  nav      {v}")
    rec = snap.get("recorder") or {}
    if rec:
        lines.append("")
        free = rec.get("free_bytes")
        lines.append(f"  recorder {rec.get('state', '?')}: {rec.get('file') or '-'}"
                     f" ({rec.get('file_bytes', 0) / 1e6:.1f} MB), free disk "
                     + (f"{free / 1e9:.2f} GB" if free is not None else "?"))
        dropped = sum((rec.get("dropped") or {}).values())
        on_disk = rec.get("on_disk_mono_ns") or {}
        at_risk = (f", on disk up to {(snap['t_mono_ns'] - max(on_disk.values())) / 1e9:.1f} s ago"
                   if on_disk and snap.get("t_mono_ns") else "")
        lines.append(f"  records  {sum((rec.get('written') or {}).values())} written, {dropped} dropped, "
                     f"queue {rec.get('queue_depth', 0)}/{rec.get('queue_size', 0)}{at_risk}")
    return "\n".join(lines)


def find_socket() -> tuple[Path, dict[str, Any]]:
    """No socket named or configured: the service's, then those of ``logger run --sim`` without a configuration
    (a second simulated run gets one of its own), the first that answers, with its snapshot; ConnectionError
    naming them all."""
    tried = [Path(SCHEMA["logger"]["status_socket"].default), *sim_sockets(Path(DEFAULT_SIM_SOCKET))]
    for p in tried:
        if p.exists():
            try:
                return p, fetch(p, timeout_s=1.0)
            except ConnectionError:
                continue  # a socket a crashed run left
    raise ConnectionError("logger is not running (nobody answers on " + ", ".join(map(str, tried)) + ")")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="logger status", description="show the running logger's health")
    parser.add_argument("--json", action="store_true", help="print the raw snapshot")
    parser.add_argument("--watch", nargs="?", const=1.0, type=float, metavar="SECONDS",
                        help="refresh until Ctrl-C (default every second)")
    parser.add_argument("--socket", help="status socket path (default: from the configuration)")
    parser.add_argument("--config", default=None, help=f"configuration file (default {DEFAULT_PATH})")
    args = parser.parse_args(argv)
    path = args.socket
    if path is None:
        path = os.environ.get("LOGGER_STATUS_SOCKET")
    if path is None:
        cfg_path = Path(args.config) if args.config else DEFAULT_PATH
        try:
            path = load(cfg_path)["logger"]["status_socket"] if cfg_path.exists() else None
        except ConfigError:
            path = None
    code = NOT_RUNNING
    try:
        while True:
            try:
                snap = fetch(path) if path is not None else find_socket()[1]
                code = EXIT.get(snap.get("verdict", ""), 2)
                text = json.dumps(snap, indent=1) if args.json else render(snap)
            except ConnectionError as exc:
                code, text = NOT_RUNNING, f"logger status: {exc}"
            if args.watch:
                sys.stdout.write("\x1b[H\x1b[2J" + text + "\n")
                sys.stdout.flush()
                time.sleep(max(0.2, args.watch))
                continue
            print(text, file=sys.stderr if code == NOT_RUNNING else sys.stdout)
            return code
    except KeyboardInterrupt:
        return code
