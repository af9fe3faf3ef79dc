"""The receiver's byte stream out of a drive, for RTKLIB: one ``.ubx`` per drive and its gaps, and RINEX by convbin.

``/gnss/raw`` holds every byte the logger read from the receiver's port, in the pieces it read them, base64 in JSON.
Joined in log-time order over the drive's files they are the stream as it came off the port, which RTKLIB's u-blox
reader (``convbin -r ubx``, ``rtkconv``, ``str2str``) takes as a receiver log: RXM-RAWX and RXM-SFRBX become
observations and navigation data, everything else is skipped.

What the stream cannot show is where it is not whole, so that is written beside it (``NAME.ubx.json``):

- ``lost``: records that never reached the file (the recorder's queue was full, or a rotated file is missing):
  each record says how many bytes the port gave before it since it was opened (``offset``), so a jump is exactly
  the bytes lost;
- ``reopened``: the port was opened again (an adapter unplugged, a receiver that stopped answering): what the
  receiver sent meanwhile was never read, and the receiver was configured again;
- ``silence``: no bytes for longer than :data:`SILENCE_S` (a receiver sends every second at least), at a file
  boundary or anywhere else;
- the framing of the joined stream: frames that fail their checksum and bytes outside any frame (line noise,
  bytes dropped by a UART that overran, garbage around a baud rate change), and an unfinished frame at its end
  (the recording stopped mid-message).

The ``.ubx`` keeps that unfinished tail, as it came; convbin is handed the stream without it, because RTKLIB 2.4.3
loses observation epochs at the start of a file that ends inside a UBX frame (the M8T capture of the tests: 30 of
its 39 epochs instead of all).

RINEX comes from RTKLIB's own converter rather than a writer of our own: RTKLIB is what the office runs next
(``rnx2rtkp``), and its reading of the receiver's messages is the one the solution will rest on. The antenna height
and the receiver's name go into the header from ``[gnss] antenna_height_m`` and ``receiver_name``: those the drive
recorded in its ``config`` metadata, or those of a configuration file given at the office.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import datetime as dt
import json
import shutil
import subprocess
import tempfile
from collections import Counter
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from mcap.records import Metadata
from mcap.stream_reader import StreamReader
from pyubx2 import UBX_MSGIDS

from logger.exports.whole import written_whole
from logger.recording.drive import DriveFile, DriveFileError, DriveMessage, damage_spans
from logger.recording.topics import GNSS_RAW
from sensors.ublox_frames import KIND_UBX, UbxNmeaFramer

SILENCE_S = 3.0  # no bytes from the receiver for longer than this is a gap worth a note
CONVBIN = "convbin"
INSTALL_RTKLIB = "apt-get install rtklib"
RINEX_VERSION = "3.04"
# Doppler (-od) and C/N0 (-os) as well as code and phase: RXM-RAWX carries both, convbin drops them unless asked, and
# without the C/N0 (S1C) RTKLIB's SNR mask has nothing to judge a satellite by.
CONVBIN_OBS_TYPES = ("-od", "-os")
CONVBIN_TIMEOUT_S = 600.0


class ConvbinError(Exception):
    """convbin missing, or failing: one line for the user."""


@dataclass
class StreamGap:
    """One place where the exported stream is not what the receiver sent, or where it paused."""

    kind: str  # lost, damaged, reopened, silence
    at_byte: int  # where in the .ubx the gap falls (the first byte after it)
    utc: str  # log time of the first record after it, ISO 8601 UTC
    seconds: float  # board time between the records either side
    bytes_lost: int | None  # exactly, for "lost"; None where nobody counted (reopened, silence)
    file_boundary: bool  # between two of the drive's files
    detail: str


@dataclass
class StreamReport:
    """What was written: sizes, the messages found in the joined stream, and its gaps."""

    ubx: str
    bytes: int = 0
    records: int = 0
    files: list[str] = field(default_factory=list)
    first_utc: str | None = None
    last_utc: str | None = None
    messages: dict[str, int] = field(default_factory=dict)  # UBX messages by name, NMEA sentences as "NMEA"
    bad_checksum: int = 0
    garbage_bytes: int = 0
    unfinished_tail_bytes: int = 0  # the stream's last bytes: the start of a frame that never ended
    gaps: list[StreamGap] = field(default_factory=list)

    @property
    def raw_epochs(self) -> int:
        return self.messages.get("RXM-RAWX", 0)


def utc_text(t_ns: int) -> str:
    return dt.datetime.fromtimestamp(t_ns / 1e9, dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _record_bytes(m: DriveMessage, files: list[DriveFile]) -> bytes:
    try:
        return base64.b64decode(m.msg["data_b64"], validate=True)
    except (KeyError, TypeError, binascii.Error) as exc:
        raise DriveFileError(f"{files[m.file].path}: a {GNSS_RAW} message at log time {m.log_time} holds no "
                             f"base64 data ({exc})") from exc


def write_ubx(messages: Iterable[DriveMessage], files: list[DriveFile], path: Path) -> StreamReport:
    """Join ``/gnss/raw`` (``messages``, in log-time order) into ``path`` and say what the stream holds and lacks."""
    report = StreamReport(str(path), files=[str(f.path) for f in files])
    framer = UbxNmeaFramer()
    framer.decode_nmea = False  # counted, not parsed
    counts: Counter[str] = Counter()
    prev: DriveMessage | None = None
    with written_whole(path, "wb") as out:
        for m in messages:
            data = _record_bytes(m, files)
            if prev is not None:
                gap = _gap(prev, m, report.bytes)
                if gap is not None:
                    report.gaps.append(_in_damage(gap, prev, m, files))
            else:
                report.first_utc = utc_text(m.log_time)
            out.write(data)
            for frame in framer.feed(data):
                counts[_frame_name(frame.kind, frame.raw)] += 1
            report.bytes += len(data)
            report.records += 1
            prev = m
    # What is still pending is the start of a frame the stream never finished: noted as that, not as garbage (frames
    # that the end of the stream shows to lie inside it are still counted).
    report.unfinished_tail_bytes = framer.pending
    report.bad_checksum, report.garbage_bytes = framer.bad_checksum, framer.garbage_bytes
    for frame in framer.finish():
        counts[_frame_name(frame.kind, frame.raw)] += 1
    if prev is not None:
        report.last_utc = utc_text(prev.log_time)
    report.messages = dict(sorted(counts.items()))
    return report


def _in_damage(gap: StreamGap, prev: DriveMessage, m: DriveMessage, files: list[DriveFile]) -> StreamGap:
    """A "lost" gap where a damaged chunk of the drive was skipped (its CRC failed at the office: a card's bad
    sector, a copy gone wrong): those bytes were recorded once, which "the recorder dropped records" denied."""
    if gap.kind != "lost":
        return gap
    for path in {files[prev.file].path, files[m.file].path}:
        for first, last in damage_spans(path):
            if (first is None or first <= m.log_time) and (last is None or last >= prev.log_time):
                return dataclasses.replace(gap, kind="damaged", detail=f"{gap.bytes_lost} bytes the port gave were "
                                           "in a damaged chunk of the drive, skipped (see the read's note)")
    return gap


def _frame_name(kind: str, raw: bytes) -> str:
    """A UBX frame by pyubx2's name of its class and id ("RXM-RAWX"); NMEA and RTCM3 frames by their kind."""
    if kind != KIND_UBX:
        return kind
    return str(UBX_MSGIDS.get(raw[2:4], f"UBX-{raw[2]:02X}-{raw[3]:02X}"))


def _gap(prev: DriveMessage, m: DriveMessage, at_byte: int) -> StreamGap | None:
    """The gap between two consecutive records, if there is one."""
    seconds = (m.msg.get("t_mono_ns", 0) - prev.msg.get("t_mono_ns", 0)) / 1e9
    boundary = m.file != prev.file
    where = utc_text(m.log_time)
    offset, before = m.msg.get("offset"), prev.msg.get("offset")
    if offset is not None and before is not None:
        expected = before + prev.msg.get("n_bytes", 0)
        if offset > expected:
            n = offset - expected
            return StreamGap("lost", at_byte, where, seconds, n, boundary,
                             f"{n} bytes the port gave were not recorded"
                             + (" (a file of the drive missing?)" if boundary else " (the recorder dropped records)"))
        if offset < expected:
            return StreamGap("reopened", at_byte, where, seconds, None, boundary,
                             f"the port was opened again after {seconds:.1f} s: what the receiver sent meanwhile "
                             "was not read")
    if seconds > SILENCE_S:
        return StreamGap("silence", at_byte, where, seconds, None, boundary,
                         f"no bytes from the receiver for {seconds:.1f} s")
    return None


def write_notes(path: Path, report: StreamReport) -> None:
    """The report as JSON beside the .ubx: sizes, messages, framing problems and every gap."""
    with written_whole(path) as f:
        f.write(json.dumps(asdict(report), indent=2) + "\n")


def recorded_config(files: list[DriveFile]) -> dict[str, str]:
    """The daemon's configuration as the drive's first file keeps it (``config`` metadata, written at its start);
    empty for a file without one."""
    for f in files:
        try:
            with open(f.path, "rb") as fh:
                for record in StreamReader(fh, emit_chunks=True, record_size_limit=max(f.path.stat().st_size, 1)
                                           ).records:
                    if isinstance(record, Metadata) and record.name == "config":
                        return dict(record.metadata)
        except Exception:  # a file cut short: its head was read as far as it goes
            continue
    return {}


def convbin_path() -> str:
    """Where RTKLIB's convbin is; ConvbinError naming the package when it is not installed."""
    found = shutil.which(CONVBIN)
    if found is None:
        raise ConvbinError(f"--format rinex needs RTKLIB's {CONVBIN}, which is not installed ({INSTALL_RTKLIB})")
    return found


@dataclass
class RinexResult:
    obs: Path
    nav: Path
    epochs: int  # observation epochs in the RINEX file


def to_rinex(ubx: Path, obs: Path, nav: Path, antenna_height_m: float, receiver_name: str,
             unfinished_tail_bytes: int = 0, named: Path | None = None) -> RinexResult:
    """``convbin -r ubx`` of the stream into RINEX observations and navigation data, the header carrying the antenna
    height (ANTENNA: DELTA H/E/N) and, when set, the receiver (REC # / TYPE / VERS). A stream that ends inside a
    frame is converted without that tail (see the module's note), from a copy of the same name. On failure nothing
    of convbin's is left behind (a navigation file without its observations is no RINEX for RTKLIB). ``named``:
    the stream as the user knows it, in messages (``ubx`` may be a staged copy)."""
    cmd = [convbin_path(), "-r", "ubx", "-v", RINEX_VERSION, *CONVBIN_OBS_TYPES, "-hd", f"{antenna_height_m:.4f}/0/0",
           "-o", str(obs.absolute()), "-n", str(nav.absolute())]
    if receiver_name:
        cmd += ["-hr", receiver_name]
    with tempfile.TemporaryDirectory(prefix="logger-export-") as tmp:
        source = ubx
        if unfinished_tail_bytes:
            source = Path(tmp) / ubx.name
            with open(ubx, "rb") as whole, open(source, "wb") as trimmed:
                shutil.copyfileobj(whole, trimmed)
                trimmed.truncate(ubx.stat().st_size - unfinished_tail_bytes)
        try:
            # Named from its own folder: convbin writes the input's path into the header ("log: ..."), which is
            # then the stream's name, not a staging folder's or a temporary one's.
            done = subprocess.run([*cmd, source.name], cwd=source.parent, capture_output=True, text=True,
                                  timeout=CONVBIN_TIMEOUT_S)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise ConvbinError(f"{CONVBIN} could not be run: {exc}") from None
    if done.returncode != 0 or not obs.is_file():
        for made in (obs, nav):
            made.unlink(missing_ok=True)
        said = convbin_said(done.stderr + "\n" + done.stdout)
        raise ConvbinError(f"{CONVBIN} wrote no observations from {named or ubx} (exit status {done.returncode}"
                           + (f": {said})" if said else ")"))
    return RinexResult(obs, nav, count_epochs(obs))


def convbin_said(output: str) -> str:
    """What convbin said that is not its progress: it echoes its files and prints a "scanning: ..." or ":" per block
    it reads, which as an error message is a line of colons; the last other line, cut to 200 characters."""
    said = ""
    for line in output.replace("\r", "\n").splitlines():
        line = " ".join(line.split())
        if not line.strip(": ") or line.startswith(("scanning:", "input file", "->rinex")):
            continue
        said = line
    return said[-200:]


def count_epochs(obs: Path) -> int:
    """Observation epochs of a RINEX 3 file: the records that start with '>' after the header."""
    epochs, body = 0, False
    with open(obs, encoding="ascii", errors="replace") as f:
        for line in f:
            if body:
                epochs += line.startswith(">")
            elif line[60:].startswith("END OF HEADER"):
                body = True
    return epochs
