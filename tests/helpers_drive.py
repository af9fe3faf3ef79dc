"""Running the real daemon in a subprocess and reading back what it recorded: shared by the tests of whole runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

from mcap.reader import make_reader
from mcap.stream_reader import StreamReader


def read_messages(path: Path) -> dict[str, list[tuple[int, int, dict]]]:
    """topic -> [(log_time, publish_time, message)] after a CRC-validated walk of the whole file."""
    with open(path, "rb") as f:
        for _ in StreamReader(f, validate_crcs=True).records:
            pass
    out: dict[str, list[tuple[int, int, dict]]] = defaultdict(list)
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            out[channel.topic].append((message.log_time, message.publish_time, json.loads(message.data)))
    return out


def run_logger(*args: str, timeout: float = 120, umask: int | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "logger.cli", "run", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=Path(__file__).resolve().parents[1],
                          preexec_fn=None if umask is None else lambda: os.umask(umask))
