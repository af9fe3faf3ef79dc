"""What the commands that write files (``export``, ``plot``, ``replay``) share about their outputs: whether the
output folder can be one, an error writing them in one line, and their name.

Kept apart from :mod:`logger.cli.export` so that ``replay`` and ``plot`` do not import the export's formats and
the receiver-stream tools (pyubx2, RTKLIB's helpers) for three small functions: those imports were a quarter of a
short replay's CPU time.
"""

from __future__ import annotations

import os
from pathlib import Path

from logger.recording.drive import DriveFile, drive_stem


def out_folder_problem(out: Path, option: str = "--out") -> str | None:
    """Why ``out`` cannot be (or become) the output folder, in a line naming it; None when it can. Checked before
    the work (``export``, ``plot``, ``replay``), so that a file given as the folder, a folder under a file or one
    that may not be written is said at once instead of a traceback once the drive was read (for ``replay``, after
    the whole filter run). Nothing is created."""
    if os.path.lexists(out) and not out.exists():
        return f"{option} {out}: a link to nothing"
    if out.exists():
        if not out.is_dir():
            return f"{option} {out}: exists and is not a folder"
        if not os.access(out, os.W_OK | os.X_OK):
            return f"{option} {out}: the folder may not be written to"
        return None
    for above in out.parents:  # the nearest that exists (a relative path ends at "."): the folder is made in it
        if above.exists():
            if not above.is_dir():
                return f"{option} {out}: cannot be made, {above} is a file and not a folder"
            if not os.access(above, os.W_OK | os.X_OK):
                return f"{option} {out}: cannot be made, {above} may not be written to"
            return None
    return None


def os_error_line(exc: OSError) -> str:
    """An error writing the outputs in one line: what the system said and the path it said it of."""
    return f"{exc.filename}: {exc.strerror}" if exc.filename and exc.strerror else str(exc)


def drive_name(files: list[DriveFile]) -> str:
    """The name of the outputs: the drive's first file's stem without the rotation number (``drive_..._0001``),
    whatever order the files were given in (a drive's parts are named by the times they began): the part numbered
    first by the recorder, else the daemon's file whose name sorts first, else the first file given."""
    if not files:
        return "drive"
    numbered = [(f.run[1], f.path.name, f.path) for f in files if f.run is not None]
    live = [f.path for f in files if f.origin == "live"]
    first = min(numbered)[2] if numbered else min(live) if live else files[0].path
    return drive_stem(first) or "drive"
