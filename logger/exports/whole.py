"""Office outputs written whole or not at all.

An export or a replay run into an output folder that already holds the last run's files (the usual case: the same
drive exported again with other options). Written in place, a failure part-way (a full disk, a card pulled) left a
truncated GPX or ``trajectory.mcap`` where the good one had been, and a folder mixing both runs. So each output is
written to a partial file beside it (``.NAME.partial``, hidden, in the same folder so that the rename cannot cross
file systems) and renamed over the old one only once it is complete; on a failure the partial file is removed and
the old output stays as it was. The outputs of one run go in together (:func:`written_together`): all of them
once every one is complete, or none, so that a folder never holds one run's CSV beside another's GPX or
``trajectory.mcap``. An error writing says which output it was (a write's ``OSError`` names no file, a rename's
the hidden partial file).

An export made of several files (the receiver's stream with its RINEX) is staged in a hidden folder inside the
output folder and moved into place whole. A run killed outright (SIGKILL, a power cut, the terminal's window
closed on it) cannot remove its stage, and a day's raw stream makes it hundreds of megabytes: the stage is named
with its process's id (``.export-PID-...``) and the next export into that folder removes the stages whose process
is gone (:func:`remove_stale_stages`). A partial file's name is the output's own, so the next run writing that
output replaces it.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

STAGE_PREFIX = ".export-"


def stage_prefix() -> str:
    """The name a staging folder of this process starts with: its id says whether the folder is still in use."""
    return f"{STAGE_PREFIX}{os.getpid()}-"


def remove_stale_stages(folder: Path) -> list[Path]:
    """Remove the staging folders in ``folder`` whose process has ended (a killed export's); those removed.

    Only stages named with a process id are judged; one whose process still runs is kept, whoever it is. Two
    machines exporting into one shared folder at once cannot see each other's processes: the other machine's
    stage would be taken as stale, and its export fail (it says so) rather than finish."""
    removed = []
    for stage in folder.glob(STAGE_PREFIX + "*"):
        pid, sep, rest = stage.name[len(STAGE_PREFIX):].partition("-")
        if not (pid.isdigit() and sep and rest) or _running(int(pid)):
            continue
        if stage.is_dir() and not stage.is_symlink():
            shutil.rmtree(stage, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                stage.unlink()
        if not stage.exists():
            removed.append(stage)
    return removed


def _running(pid: int) -> bool:
    """Whether a process with this id exists (another user's counts: signalling it is refused, not unknown)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def partial_path(path: Path) -> Path:
    """Where ``path`` is written until it is complete."""
    return path.with_name(f".{path.name}.partial")


@contextlib.contextmanager
def written_whole(path: Path, mode: str = "w", **open_kw: Any) -> Iterator[IO[Any]]:
    """``open(path, mode)`` for writing, with ``path`` replaced only when the block ends without an error; inside
    :func:`written_together`, only once every output of that block is complete."""
    tmp = partial_path(path)
    try:
        with open(tmp, mode, **open_kw) as f:
            yield f
        _complete(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        _name_output(exc, path)
        raise


@contextlib.contextmanager
def written_together() -> Iterator[None]:
    """The outputs written whole inside the block are put in place together, once the block ends without an error;
    on an error none is, and the folder keeps an earlier run's set as it was. A run's outputs are one set: a CSV
    and a ``trajectory.mcap``, or a GPX beside a CSV, from two runs would disagree without a word (a full disk
    after the first of them left exactly that)."""
    done: _Set = []
    token = _TOGETHER.set(done)
    try:
        yield
    except BaseException:
        _discard(done)
        raise
    finally:
        _TOGETHER.reset(token)
    _put_in_place(done)


def adopt(done: Path, path: Path) -> None:
    """A complete file made elsewhere on the output's file system (a staging folder) becomes the output ``path``:
    at once, or with the rest of the set inside :func:`written_together`."""
    tmp = partial_path(path)
    try:
        os.replace(done, tmp)
    except OSError as exc:
        _name_output(exc, path)
        raise
    _complete(tmp, path)


def retire(path: Path) -> None:
    """An earlier run's output this run does not make (``logger replay --no-mcap``: its ``trajectory.mcap``) is
    removed when the run's outputs go in (inside :func:`written_together`; at once outside one): left, it would
    stand beside this run's files as theirs. Nothing is done when there is none."""
    _complete(None, path)


# The set being written: (partial file, output) pairs, and (None, output) for an earlier output retired.
_Set = list[tuple[Path | None, Path]]
_TOGETHER: contextvars.ContextVar[_Set | None] = contextvars.ContextVar("together", default=None)


def _put_in_place(done: _Set) -> None:
    """Rename each complete partial file over its output, and remove the outputs retired. A rename in one folder
    needs no space; what can refuse it (an output's name taken by a folder) is looked for first, so that a set is
    not left half replaced."""
    try:
        for _, path in done:
            if path.is_dir() and not path.is_symlink():
                raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
        for tmp, path in done:
            try:
                if tmp is None:
                    path.unlink(missing_ok=True)
                else:
                    os.replace(tmp, path)
            except OSError as exc:
                _name_output(exc, path)
                raise
    except BaseException:
        _discard(done)
        raise


def _complete(tmp: Path | None, path: Path) -> None:
    """The partial file ``tmp`` of ``path`` is complete (None: ``path`` is retired): in place now, or with its set
    at the end of it."""
    together = _TOGETHER.get()
    if together is None:
        _put_in_place([(tmp, path)])
    else:
        together.append((tmp, path))


def _discard(done: _Set) -> None:
    for tmp, _ in done:
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()


def _name_output(exc: BaseException, path: Path) -> None:
    """An error writing says which output it was: a write's ``OSError`` names no file, and a rename's names the
    hidden partial file the user never asked for."""
    if isinstance(exc, OSError) and (not exc.filename or Path(exc.filename) == partial_path(path)):
        exc.filename, exc.filename2 = str(path), None


def save_figure(fig: Any, path: Path, dpi: int) -> None:
    """A matplotlib figure saved whole (its format from the file's suffix, as ``savefig(path)`` takes it)."""
    with written_whole(path, "wb") as f:
        fig.savefig(f, dpi=dpi, format=path.suffix.lstrip(".") or "png")
