"""``logger recover FILE [-o OUT] [--force]``: make a file cut short by a crash, or damaged, readable and indexed.

A cleanly closed file is walked first: when every chunk's CRC holds there is nothing to recover and nothing is
written; when some do not (a flipped byte, a zeroed page), it is rewritten without them, as a cut file is. Either
way the line says what was kept and what was lost (chunks, messages, when), so nothing goes missing unsaid.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from logger.recording.files import MAGIC, McapFileError, being_written, is_finished, recover, walk

# An unfinished file written to this recently may be one a logger is still recording: a logger older than the lock
# (files.hold_for_writing) gives no other sign, and recovering its open file under it lost what it wrote next (an
# upgrade installed while the old service still ran: `logger info` said "cut short", recover rewrote it, and the
# old logger's next second went with the file it had open). The recorder writes a chunk a second.
RECENT_WRITE_S = 10.0


def _mcap(path: Path) -> bool:
    """Whether the file begins as an MCAP file does (anything else is refused by the recovery itself, as such)."""
    with open(path, "rb") as f:
        return f.read(len(MAGIC)) == MAGIC


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="logger recover",
                                     description="rewrite what survives of a cut or damaged MCAP file into a "
                                                 "finished file")
    parser.add_argument("file", metavar="FILE")
    parser.add_argument("-o", "--out", metavar="OUT", help="write here instead of replacing FILE")
    parser.add_argument("--force", action="store_true",
                        help="rewrite even a file that was closed cleanly and whose chunks all hold, or an unfinished "
                             f"one written to in the last {RECENT_WRITE_S:.0f} s")
    args = parser.parse_args(argv)
    src = Path(args.file)
    out = Path(args.out) if args.out is not None else None
    if out is not None and (out.is_dir() or args.out.endswith(os.sep)):
        # A folder (one to be made, when written with its slash): the recovered file goes into it under the
        # source's name.
        out = out / src.name
    if out is not None and not out.parent.is_dir():
        print(f"logger recover: -o {args.out}: the folder {out.parent} does not exist", file=sys.stderr)
        return 1
    if out is not None and out.exists() and not (src.exists() and out.samefile(src)):
        # One wrong completion would replace another recording with this one: never without asking for FILE itself.
        print(f"logger recover: -o {out} already exists and is not {src}: name a new file or a folder",
              file=sys.stderr)
        return 2
    if src.is_file() and being_written(src):
        print(f"logger recover: {src}: a running logger is writing it (it looks cut while it is being written); "
              "recover it once that logger has finished it", file=sys.stderr)
        return 1
    try:
        found = None
        if is_finished(args.file):
            found = walk(args.file, keep_messages=False)  # where the chunks lie, not their messages
            if not found.losses and not args.force:
                print(f"{args.file}: closed cleanly and every chunk's CRC holds: nothing to recover")
                return 0
        elif not args.force and _mcap(src) and (age := time.time() - src.stat().st_mtime) < RECENT_WRITE_S:
            print(f"logger recover: {src}: not closed, and written to {max(0.0, age):.0f} s ago: a logger may still "
                  "be recording it (one older than this version marks no file it writes); stop that logger first, "
                  "or recover with --force", file=sys.stderr)
            return 1
        report = recover(src, out, found=found)
    except McapFileError as exc:
        print(f"logger recover: {exc}", file=sys.stderr)
        return 1
    except FileNotFoundError:
        print(f"logger recover: {args.file}: no such file", file=sys.stderr)
        return 1
    except OSError as exc:  # named as the file it was said of (the output's folder or disk, or the source)
        print(f"logger recover: {exc.filename or args.file}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    lost = report.lost()
    print(f"{report.path}: recovered {report.messages} messages from {report.chunks_ok} chunks"
          + (f"; {lost}" if lost else "; nothing lost")
          + (f"; {report.dropped_orphans} messages without their channel dropped" if report.dropped_orphans else ""))
    return 0
