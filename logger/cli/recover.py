"""``logger recover FILE [-o OUT]``: make a file cut short by a crash readable and indexed again."""

from __future__ import annotations

import argparse
import sys

from logger.recording.files import McapFileError, is_finished, recover


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="logger recover",
                                     description="rewrite what survives of a cut MCAP file into a finished file")
    parser.add_argument("file", metavar="FILE")
    parser.add_argument("-o", "--out", metavar="OUT", help="write here instead of replacing FILE")
    parser.add_argument("--force", action="store_true", help="rewrite even a file that was closed cleanly")
    args = parser.parse_args(argv)
    try:
        if is_finished(args.file) and not args.force:
            print(f"{args.file}: closed cleanly, nothing to recover")
            return 0
        report = recover(args.file, args.out)
    except McapFileError as exc:
        print(f"logger recover: {exc}", file=sys.stderr)
        return 1
    except FileNotFoundError:
        print(f"logger recover: {args.file}: no such file", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"logger recover: {args.file}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(f"{report.path}: recovered {report.messages} messages from {report.chunks_ok} chunks"
          + (f", {report.chunks_bad} corrupt chunks skipped" if report.chunks_bad else "")
          + (f", {report.dropped_orphans} messages without their channel dropped" if report.dropped_orphans else ""))
    return 0
