"""The recorder's tuning, in its own small module: the configuration reads its defaults from here.

Kept apart from :mod:`logger.recording.recorder` (which loads the MCAP writer and its compressors) so that checking
a configuration or asking ``logger status`` stays quick on a slow board.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

MIB = 1 << 20  # the configuration states sizes in MiB (rotate_size_mb, min_free_mb), the recorder in bytes


@dataclass
class RecorderSettings:
    out_dir: Path
    prefix: str = "drive"
    flush_interval_s: float = 1.0
    rotate_duration_s: float = 3600.0
    rotate_size_bytes: int = 1024 * MIB
    min_free_bytes: int = 256 * MIB
    compression: str = "zstd"
    queue_size: int = 20000
    # Chunks are closed by time (flush_interval_s); this only caps one chunk's memory at high IMU rates.
    chunk_size_bytes: int = 4 << 20

    @classmethod
    def from_config(cls, section: Mapping[str, Any], out_dir: Path) -> RecorderSettings:
        """From the validated ``[recorder]`` section; ``out_dir`` is the caller's (``[logger]``, or a command line).

        The one place that knows which key sets which field and in what unit; the configuration's schema takes
        its defaults from these fields (``rotate_size_mb`` from ``rotate_size_bytes`` in :data:`MIB`).
        """
        return cls(out_dir=out_dir,
                   flush_interval_s=section["flush_interval_s"], rotate_duration_s=section["rotate_duration_s"],
                   rotate_size_bytes=int(section["rotate_size_mb"] * MIB),
                   min_free_bytes=int(section["min_free_mb"] * MIB),
                   compression=section["compression"], queue_size=section["queue_size"])
