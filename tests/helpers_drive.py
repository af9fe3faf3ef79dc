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

from logger.recording.drive import imu_samples as samples_of
from sensors.sim.governor import FLOOR


def read_messages(path: Path, imu_samples: bool = False) -> dict[str, list[tuple[int, int, dict]]]:
    """topic -> [(log_time, publish_time, message)] after a CRC-validated walk of the whole file.

    ``imu_samples``: ``/imu`` holds the samples of the ``/imu/batch`` records too, one record each as the project's
    readers hand them on (logged and published at their own stamps, as a record per sample is), for a test of
    samples whatever way the IMU was read."""
    with open(path, "rb") as f:
        for _ in StreamReader(f, validate_crcs=True).records:
            pass
    out: dict[str, list[tuple[int, int, dict]]] = defaultdict(list)
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            out[channel.topic].append((message.log_time, message.publish_time, json.loads(message.data)))
    if imu_samples:
        out["/imu"].extend((m["t_sync_ns"], m["t_mono_ns"], m) for _, _, batch in out.get("/imu/batch", [])
                           for m in samples_of(batch))
    return out


START_AND_END_S = 120.0
"""Host seconds a run may take besides its drive: starting (imports, the devices' set-up, the first file) and ending
(the last flush, the file's summary, the run's), generous for a slow board or an emulated one."""


def drive_timeout(drive_s: float) -> float:
    """Host seconds a simulated drive of ``drive_s`` may take. Its time scale is only a ceiling: the governor lowers
    the pace to what the host keeps up with, never below real time (``FLOOR``), so a drive lasts at most its own
    length whatever scale it asked for. A wait shorter than that would measure the host's speed, not the daemon."""
    return drive_s / FLOOR + START_AND_END_S


def run_logger(*args: str, timeout: float | None = None, umask: int | None = None) -> subprocess.CompletedProcess[str]:
    """``logger run`` with ``args``, waited for as long as its ``--duration`` may take (``drive_timeout``)."""
    if timeout is None:
        timeout = drive_timeout(float(args[args.index("--duration") + 1])) if "--duration" in args else START_AND_END_S
    return subprocess.run([sys.executable, "-m", "logger.cli", "run", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=Path(__file__).resolve().parents[1],
                          preexec_fn=None if umask is None else lambda: os.umask(umask))
