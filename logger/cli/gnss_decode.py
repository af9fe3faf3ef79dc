"""``logger gnss-decode FILE [--json]``: decode a u-blox receiver capture, one line per navigation fix.

The offline twin of the GNSS sampler: the same framer and decoder run over a file instead of a serial
port, so a capture from the field (or the raw ``/gnss/raw`` bytes of a recording) can be checked without
the receiver. ``--json`` prints gpsd-style TPV objects so the output can be compared with ``gpsdecode``
or a gpsd regression log line by line; see docs/gnss-decode.md for the keys.

Captures in the GPSD project's format start with ``#`` comment lines; comment lines between NMEA
sentences are skipped too. A ``#`` inside binary data is data, not a comment.
"""

from __future__ import annotations

import argparse
import base64
import datetime as dt
import json
import math
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from logger.recording.drive import DriveFileError, cut_notes, damage_notes, iter_messages, open_drive
from logger.recording.files import MAGIC as MCAP_MAGIC
from logger.recording.topics import GNSS_RAW
from sensors.ublox_decode import GnssDecoder, GnssFix, GnssItem
from sensors.ublox_frames import UbxNmeaFramer

NS_PER_MS = 1_000_000


def strip_capture_comments(data: bytes) -> bytes:
    """Drop gpsd capture comments: ``#`` lines at the head of the file, after an NMEA sentence or
    after another comment. Binary UBX payloads may hold ``\\n#`` and are left alone.
    """
    out = bytearray()
    pos = 0
    text_before = True  # the head of the file counts as a line boundary
    while pos < len(data):
        nl = data.find(b"\n", pos)
        end = len(data) if nl < 0 else nl + 1
        line = data[pos:end]
        pos = end
        if text_before and line.startswith(b"#"):
            continue  # a comment; the line after it starts at a line boundary too
        out += line
        body = line.rstrip(b"\r\n")
        text_before = nl >= 0 and body[:1] == b"$" and all(0x20 <= c <= 0x7E for c in body)
    return bytes(out)


@dataclass
class DecodeResult:
    """Everything a capture decoded to, with the framer's counters."""

    items: list[GnssItem]
    frames_ok: int
    bad_checksum: int
    garbage_bytes: int
    undecoded: int
    rejected: int

    @property
    def fixes(self) -> list[GnssFix]:
        return [item for item in self.items if isinstance(item, GnssFix)]


def decode_pieces(pieces: Iterable[bytes]) -> DecodeResult:
    """Feed bytes in the pieces given (as a serial port would deliver them) and decode to the end."""
    framer = UbxNmeaFramer()
    decoder = GnssDecoder()
    items: list[GnssItem] = []
    for piece in pieces:
        for frame in framer.feed(piece):
            items += decoder.push(frame)
    for frame in framer.finish():
        items += decoder.push(frame)
    items += decoder.flush()
    return DecodeResult(
        items=items,
        frames_ok=framer.frames_ok,
        bad_checksum=framer.bad_checksum,
        garbage_bytes=framer.garbage_bytes,
        undecoded=framer.undecoded,
        rejected=decoder.rejected,
    )


def iso_time_ms(time_ns: int, leap_second: bool = False) -> str:
    """Unix ns -> ISO-8601 UTC rounded to the millisecond, e.g. 2007-12-23T23:11:20.000Z; ``leap_second``: the
    epoch is 23:59:60 (whose Unix time is the following 00:00:00's), printed as the receiver named it."""
    ms = (time_ns + NS_PER_MS // 2) // NS_PER_MS - (1000 if leap_second else 0)
    stamp = dt.datetime(1970, 1, 1, tzinfo=dt.UTC) + dt.timedelta(milliseconds=ms)
    text = stamp.strftime("%Y-%m-%dT%H:%M:%S.") + f"{ms % 1000:03d}Z"
    return text[:17] + "60" + text[19:] if leap_second else text


def fix_to_tpv(fix: GnssFix) -> dict[str, object]:
    """A fix as a gpsd-style TPV object: gpsd's key names where the meaning is the same."""
    tpv: dict[str, object] = {"class": "TPV", "source": fix.source}
    if fix.time_utc_ns is not None:
        tpv["time"] = iso_time_ms(fix.time_utc_ns, fix.leap_second)
    tpv["mode"] = fix.fix_mode
    tpv["fixOk"] = fix.fix_ok
    tpv["timeValid"] = fix.time_valid
    if fix.itow_ms is not None:
        tpv["itow"] = fix.itow_ms
    if fix.week is not None:
        tpv["week"] = fix.week
    if fix.lat_deg is not None and fix.lon_deg is not None:
        tpv["lat"] = round(fix.lat_deg, 9)
        tpv["lon"] = round(fix.lon_deg, 9)
    if fix.height_hae_m is not None:
        tpv["altHAE"] = round(fix.height_hae_m, 4)
    if fix.height_msl_m is not None:
        tpv["altMSL"] = round(fix.height_msl_m, 4)
    if fix.vel_ned_mps is not None:
        north, east, down = fix.vel_ned_mps
        tpv["velN"] = round(north, 4)
        tpv["velE"] = round(east, 4)
        if not math.isnan(down):
            tpv["velD"] = round(down, 4)
        tpv["speed"] = round(math.hypot(north, east), 4)
    for key, value in (("hAcc", fix.h_acc_m), ("vAcc", fix.v_acc_m), ("sAcc", fix.s_acc_mps)):
        if value is not None:
            tpv[key] = round(value, 4)
    if fix.num_sv is not None:
        tpv["numSV"] = fix.num_sv
    if fix.pdop is not None:
        tpv["pdop"] = round(fix.pdop, 2)
    return tpv


def fix_to_text(fix: GnssFix) -> str:
    """One fixed-width line per fix for a person reading a terminal."""
    when = iso_time_ms(fix.time_utc_ns, fix.leap_second) if fix.time_utc_ns is not None else "-" * 24
    mode = {0: "?", 1: "NO", 2: "2D", 3: "3D"}.get(fix.fix_mode, "?")
    ok = "ok" if fix.fix_ok else "--"
    if fix.lat_deg is None or fix.lon_deg is None:
        where = "no position"
    else:
        where = f"{fix.lat_deg:14.9f} {fix.lon_deg:15.9f}"
        if fix.height_hae_m is not None:
            where += f" hae {fix.height_hae_m:9.3f} m"
        if fix.height_msl_m is not None:
            where += f" msl {fix.height_msl_m:9.3f} m"
    sats = f" sv {fix.num_sv:2d}" if fix.num_sv is not None else ""
    return f"{when} {fix.source:<11} {mode} {ok} {where}{sats}"


def tpv_lines(result: DecodeResult, as_json: bool) -> Iterator[str]:
    for fix in result.fixes:
        yield json.dumps(fix_to_tpv(fix), separators=(",", ":")) if as_json else fix_to_text(fix)


def recorded_bytes(path: Path) -> list[bytes]:
    """The receiver's bytes a recording kept on ``/gnss/raw``, in the order they were read (cut files too, and past
    damaged chunks: what was cut or skipped is said on stderr, as every reader of a drive says it)."""
    files = open_drive([path])
    for line in cut_notes(files):
        print(f"logger gnss-decode: {line}", file=sys.stderr)
    pieces = [base64.b64decode(m.msg["data_b64"]) for m in iter_messages(files, [GNSS_RAW])]
    for line in damage_notes(files):
        print(f"logger gnss-decode: {line}", file=sys.stderr)
    return pieces


def not_receiver_output(result: DecodeResult, size: int) -> str | None:
    """Why bytes that gave not one frame are no receiver capture (an empty file, a text, another receiver's binary
    protocol), or None. Without it such a file read as a capture that happened to hold "0 fixes", exit 0, as if the
    receiver had sent frames without a position. A capture with frames but no fix is still one: it says so."""
    if result.frames_ok:
        return None
    if not size:
        return "is empty: no receiver output to decode"
    bad = f", {result.bad_checksum} with bad checksums (the wrong baud rate?)" if result.bad_checksum else ""
    return f"is not receiver output: no UBX, NMEA or RTCM3 frame in its {size} bytes{bad}"


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="logger gnss-decode",
        description="Decode a u-blox receiver capture (UBX, NMEA, RTCM3) to one line per navigation fix.",
    )
    parser.add_argument("file", help="capture file (raw receiver bytes, gpsd '#' comment header allowed), or a "
                                     "recording (.mcap): its /gnss/raw bytes")
    parser.add_argument("--json", action="store_true", help="print gpsd-style TPV JSON objects")
    args = parser.parse_args(argv)
    try:
        with open(args.file, "rb") as handle:
            data = handle.read()
    except OSError as err:
        reason = err.strerror or type(err).__name__
        print(f"logger gnss-decode: cannot read {args.file}: {reason}", file=sys.stderr)
        return 1
    what = args.file
    if data.startswith(MCAP_MAGIC):
        try:
            pieces = recorded_bytes(Path(args.file))
        except DriveFileError as err:
            print(f"logger gnss-decode: {err}", file=sys.stderr)
            return 1
        if not pieces:
            print(f"logger gnss-decode: {args.file} is a recording without /gnss/raw (a receiver read through gpsd "
                  "leaves none): nothing to decode", file=sys.stderr)
            return 1
        result = decode_pieces(pieces)
        what, size = f"{args.file}'s {GNSS_RAW}", sum(map(len, pieces))
    else:
        result = decode_pieces([strip_capture_comments(data)])
        size = len(data)
    problem = not_receiver_output(result, size)
    if problem:
        print(f"logger gnss-decode: {what} {problem}", file=sys.stderr)
        return 1
    for line in tpv_lines(result, args.json):
        print(line)  # a reader that stops early (head, less): logger.cli.run_subcommand ends it quietly
    print(
        f"logger gnss-decode: {len(result.fixes)} fixes, {result.frames_ok} frames, "
        f"{result.bad_checksum} bad checksums, {result.garbage_bytes} garbage bytes, "
        f"{result.undecoded} undecoded frames",
        file=sys.stderr,
    )
    return 0
