"""``logger recover FILE [-o OUT] [--force]``: make a file cut short by a crash, or damaged, readable and indexed.

A cleanly closed file is walked first: when every chunk's CRC holds there is nothing to recover and nothing is
written; when some do not (a flipped byte, a zeroed page), it is rewritten without them, as a cut file is. Either
way the line says what was kept and what was lost (chunks, messages, when), so nothing goes missing unsaid.
"""

from __future__ import annotations

import argparse
import sys

from logger.recording.files import McapFileError, is_finished, recover, walk


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="logger recover",
                                     description="rewrite what survives of a cut or damaged MCAP file into a "
                                                 "finished file")
    parser.add_argument("file", metavar="FILE")
    parser.add_argument("-o", "--out", metavar="OUT", help="write here instead of replacing FILE")
    parser.add_argument("--force", action="store_true",
                        help="rewrite even a file that was closed cleanly and whose chunks all hold")
    args = parser.parse_args(argv)
    try:
        found = None
        if is_finished(args.file):
            found = walk(args.file, keep_messages=False)  # where the chunks lie, not their messages
            if not found.losses and not args.force:
                print(f"{args.file}: closed cleanly and every chunk's CRC holds: nothing to recover")
                return 0
        report = recover(args.file, args.out, found=found)
    except McapFileError as exc:
        print(f"logger recover: {exc}", file=sys.stderr)
        return 1
    except FileNotFoundError:
        print(f"logger recover: {args.file}: no such file", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"logger recover: {args.file}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    lost = report.lost()
    print(f"{report.path}: recovered {report.messages} messages from {report.chunks_ok} chunks"
          + (f"; {lost}" if lost else "; nothing lost")
          + (f"; {report.dropped_orphans} messages without their channel dropped" if report.dropped_orphans else ""))
    return 0
