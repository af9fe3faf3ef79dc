"""Office outputs written whole or not at all.

An export or a replay run into an output folder that already holds the last run's files (the usual case: the same
drive exported again with other options). Written in place, a failure part-way (a full disk, a card pulled) left a
truncated GPX or ``trajectory.mcap`` where the good one had been, and a folder mixing both runs. So each output is
written to a partial file beside it (``.NAME.partial``, hidden, in the same folder so that the rename cannot cross
file systems) and renamed over the old one only once it is complete; on a failure the partial file is removed and
the old output stays as it was. An error writing says which output it was: a write's ``OSError`` names no file.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


def partial_path(path: Path) -> Path:
    """Where ``path`` is written until it is complete."""
    return path.with_name(f".{path.name}.partial")


@contextlib.contextmanager
def written_whole(path: Path, mode: str = "w", **open_kw: Any) -> Iterator[IO[Any]]:
    """``open(path, mode)`` for writing, with ``path`` replaced only when the block ends without an error."""
    tmp = partial_path(path)
    try:
        with open(tmp, mode, **open_kw) as f:
            yield f
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError) and not exc.filename:
            exc.filename = str(path)  # a write's error names no file: the output it was writing
        raise



def save_figure(fig: Any, path: Path, dpi: int) -> None:
    """A matplotlib figure saved whole (its format from the file's suffix, as ``savefig(path)`` takes it)."""
    with written_whole(path, "wb") as f:
        fig.savefig(f, dpi=dpi, format=path.suffix.lstrip(".") or "png")
