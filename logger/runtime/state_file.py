"""What the daemon keeps in its state folder from one drive to the next: written whole or not at all."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def save_json(path: Path, state: dict[str, Any], what: str) -> bool:
    """Write ``state`` as JSON to a temporary file and rename it over ``path``, so a power cut leaves the old one;
    a failure is a warning naming ``what``, never an error (the drive goes on). Returns whether it was written."""
    tmp = path.with_suffix(".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(state))
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("cannot save %s to %s: %s", what, path, exc.strerror or exc)
        return False
    return True
