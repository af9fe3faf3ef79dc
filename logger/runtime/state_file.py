"""What the daemon keeps in its state folder from one drive to the next: written whole or not at all."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def save_json(path: Path, state: dict[str, Any], what: str) -> bool:
    """Write ``state`` as JSON to a temporary file, flushed to the card, and rename it over ``path``, the folder
    flushed too: a power cut (how a car's logger stops) leaves the old file or the new one, never an empty one.
    A failure is a warning naming ``what``, never an error (the drive goes on). Returns whether it was
    written."""
    tmp = path.with_suffix(".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "w") as f:
            f.write(json.dumps(state))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("cannot save %s to %s: %s", what, path, exc.strerror or exc)
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass  # what stands in its way is not ours to remove
        return False
    try:  # the rename itself to the card; best effort (some file systems refuse a folder's fsync)
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass
    return True
