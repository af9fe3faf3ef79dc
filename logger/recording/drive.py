"""The one drive reader: a drive's messages for post-processing, over several files, finished or cut short.

A drive is rotated into several files, and its last file may be unfinished (power cut, ``kill -9``). A finished
file is read by walking its records with ``struct`` and keeping only the wanted channels: the ``mcap`` package's
reader handles every corner of the format but costs some 15 us per message in Python, as much as the filter's
own work per IMU sample, and the logger's own files are simple (chunked, zstd/lz4/none, JSON messages). Anything
the walk does not expect sends that file back to the package's reader, so a file written by another tool still
reads. An unfinished file is read the way recovery reads it (:func:`logger.recording.files.walk`: every CRC-valid
chunk up to the cut), so exporting, plotting or replaying a drive never needs ``logger recover`` first.

Each file also says who wrote it: the daemon's recorder (``live``) or ``logger replay`` (``replay``), so that
the live ``/nav/fix`` and a replayed one are kept apart even though they share the topic name.
"""

from __future__ import annotations

import bisect
import json
import re
import struct
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lz4.frame
import zstandard
from mcap.reader import make_reader

from logger.recording.files import MAGIC, McapFileError, is_finished, walk
from logger.recording.mcap_writer import (
    CHUNK_HEAD,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_HEADER,
    OP_MESSAGE,
    RECORD_HEAD,
)
from logger.recording.topics import IMU as IMU_TOPIC
from logger.recording.topics import IMU_BATCH

REPLAY_LIBRARY = "vehicle-logger replay"  # what logger replay writes into the MCAP header

_MSG = struct.Struct("<HIQQ")
_H = struct.Struct("<H")
_I = struct.Struct("<I")
_Q = struct.Struct("<Q")
# An IMU record as the daemon writes it: the four fields the filter needs, pulled out without decoding the
# whole JSON object (json.loads of an IMU record costs more than the strapdown step it feeds). Anything that
# does not match, written by another tool or another version, is decoded in full.
_IMU = re.compile(rb'"t_mono_ns":\s*(-?\d+),\s*"t_sync_ns":\s*(-?\d+),.*?"accel_mps2":\s*\[([^\]]*)\],\s*'
                  rb'"gyro_rps":\s*\[([^\]]*)\](?:,\s*"temp_degc":\s*(-?[0-9.eE+-]+))?')


class UnexpectedLayout(Exception):
    pass


def _walk(buf: bytes | memoryview, start: int, end: int, wanted: set[str], channels: dict[int, str],
          out: list[tuple[int, int, str, bytes]], top: bool) -> bool:
    """Collect wanted messages from records in buf[start:end]; True when the data section ended."""
    pos = start
    while pos + 9 <= end:
        op, length = RECORD_HEAD.unpack_from(buf, pos)
        body = pos + 9
        nxt = body + length
        if nxt > end:
            raise UnexpectedLayout("record runs past its container")
        if op == OP_MESSAGE:
            cid, _seq, log_time, _pub = _MSG.unpack_from(buf, body)
            topic = channels.get(cid)
            if topic is not None:
                out.append((log_time, len(out), topic, bytes(buf[body + 22:nxt])))
        elif op == OP_CHANNEL:
            cid = _H.unpack_from(buf, body)[0]
            n = _I.unpack_from(buf, body + 4)[0]
            topic = bytes(buf[body + 8:body + 8 + n]).decode()
            if topic in wanted:
                channels[cid] = topic
        elif op == OP_CHUNK and top:
            _start, _end, size, _crc = CHUNK_HEAD.unpack_from(buf, body)
            n = _I.unpack_from(buf, body + 28)[0]
            compression = bytes(buf[body + 32:body + 32 + n]).decode()
            rec_len = _Q.unpack_from(buf, body + 32 + n)[0]
            data = buf[body + 40 + n:body + 40 + n + rec_len]
            if compression == "zstd":
                data = zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=size)
            elif compression == "lz4":
                data = lz4.frame.decompress(bytes(data))
            elif compression != "":
                raise UnexpectedLayout(f"compression {compression!r}")
            _walk(data, 0, len(data), wanted, channels, out, False)
        elif op == OP_DATA_END and top:
            return True
        pos = nxt
    return False


def walk_records(path: Path, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    """(log_time, order, topic, data) of the wanted topics in one finished file of the expected layout, by the
    struct walk; raises :class:`UnexpectedLayout` for anything else."""
    buf = path.read_bytes()
    if not buf.startswith(MAGIC):
        raise UnexpectedLayout("not an MCAP file")
    out: list[tuple[int, int, str, bytes]] = []
    if not _walk(memoryview(buf), len(MAGIC), len(buf), wanted, {}, out, True):
        raise UnexpectedLayout("no data end record: an unfinished file")
    return out


def read_with_mcap(path: Path, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    """The same as :func:`walk_records` through the ``mcap`` package's reader: any layout, at its cost."""

    out: list[tuple[int, int, str, bytes]] = []
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=list(wanted), log_time_order=False):
            out.append((message.log_time, len(out), channel.topic, message.data))
    return out


def raw_messages(path: Path, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    """(log_time, order, topic, data) of the wanted topics in one finished file: the record walk above, or the
    mcap package's reader for a layout the walk does not expect (its errors are then the caller's)."""
    try:
        return walk_records(path, wanted)
    except Exception:  # a layout or a damage the walk does not expect: the mcap package decides
        return read_with_mcap(path, wanted)



class DriveFileError(Exception):
    """A file that cannot be read as part of a drive; the message is one line naming the file."""


@dataclass(frozen=True)
class DriveFile:
    path: Path
    origin: str  # "live": written by the daemon; "replay": written by logger replay
    finished: bool


@dataclass(frozen=True)
class DriveMessage:
    log_time: int  # MCAP log time, Unix ns
    topic: str
    file: int  # index into the list of DriveFile
    msg: dict[str, Any]


def _header_library(path: Path) -> str:
    """The ``library`` string of the MCAP header record (the first record after the magic)."""
    with open(path, "rb") as f:
        head = f.read(4096)
    try:
        op, _length = RECORD_HEAD.unpack_from(head, len(MAGIC))
        if op != OP_HEADER:
            return ""
        pos = len(MAGIC) + 9
        n = struct.unpack_from("<I", head, pos)[0]
        pos += 4 + n
        n = struct.unpack_from("<I", head, pos)[0]
        return head[pos + 4:pos + 4 + n].decode("utf-8", "replace")
    except struct.error:
        return ""


# The daemon's file names end in the drive's part number (recorder.default_file_name, boot_safe_file_name: 0001
# at each start, one more at each rotation).
_PART = re.compile(r"_(\d{4,})$")
FOLDER_DRIVES_SHOWN = 3


def part_number(path: Path) -> int | None:
    """The part number a daemon's file name ends in (``drive_20261204T142314Z_0002.mcap``: 2), or None."""
    m = _PART.search(path.stem)
    return int(m.group(1)) if m else None


def drive_stem(path: Path) -> str:
    """A file's name without its suffix and part number: the name of what is made of the drive."""
    return _PART.sub("", path.stem)


def drive_starts(files: list[Path]) -> list[Path]:
    """The files that begin a drive, in name order: the first daemon file, and every one whose part number does
    not rise over the one before it (another start's 0001, or a later drive after an earlier one's last parts).
    Files without a part number (a replay's output) begin none."""
    parts = [(f, n) for f in sorted(files, key=lambda f: f.name) if (n := part_number(f)) is not None]
    return [f for i, (f, n) in enumerate(parts) if i == 0 or n <= parts[i - 1][1]]


def _several(starts: list[Path]) -> str:
    shown = ", ".join(f.name for f in starts[:FOLDER_DRIVES_SHOWN]) + (", ..." if len(starts) > FOLDER_DRIVES_SHOWN
                                                                      else "")
    return f"{len(starts)} drives (files {shown} each begin one): name the files of one drive"


def drive_paths(paths: Iterable[str | Path], one_drive: bool = True) -> list[Path]:
    """The files a user named, a folder standing for the drive the daemon wrote into it (``logger run --out``).

    A folder gives its MCAP files in name order (a ``logger replay`` output among them is read as such). In that
    order a drive's part numbers rise; a file whose part number does not rise over the one before it (another
    start's 0001, or a later drive after an earlier one's last parts) begins another drive (:func:`drive_starts`).
    Mixing drives would join unrelated trajectories (two cars' tracks as one, filtered as one drive), so a folder
    of several is an error naming the files that begin them, and so are files named one by one (a shell's
    ``drives/drive_*.mcap`` over two drives) that are not one drive's by the same rule, or a file named twice
    (its messages would be read twice) -- unless ``one_drive`` is false: ``logger info`` takes any files. A folder
    without MCAP files is an error too.
    """
    out: list[Path] = []
    for p in map(Path, paths):
        if not p.is_dir():
            out.append(p)
            continue
        found = [f for f in sorted(p.glob("*.mcap")) if f.is_file()]
        if not found:
            raise DriveFileError(f"{p}: a folder without recorded MCAP files")
        starts = drive_starts(found)
        if one_drive and len(starts) > 1:
            raise DriveFileError(f"{p}: a folder of {_several(starts)}")
        out += found
    if one_drive:
        seen: set[Path] = set()
        for f in out:
            key = f.resolve() if f.exists() else f
            if key in seen:
                raise DriveFileError(f"{f}: named twice (its messages would be read twice)")
            seen.add(key)
        starts = drive_starts(out)
        if len(starts) > 1:
            raise DriveFileError(f"files of {_several(starts)}")
    return out


def open_drive(paths: Iterable[str | Path]) -> list[DriveFile]:
    """Check every file and say who wrote it (a folder: the drive in it, :func:`drive_paths`); raises
    DriveFileError for a missing or non-MCAP file."""
    files = []
    for p in drive_paths(paths):
        if not p.is_file():
            raise DriveFileError(f"{p}: no such file")
        try:
            with open(p, "rb") as f:
                magic = f.read(len(MAGIC))
        except OSError as exc:
            raise DriveFileError(f"{p}: cannot open ({exc.strerror or exc})") from exc
        if magic != MAGIC:
            raise DriveFileError(f"{p}: not an MCAP file (no MCAP magic at the start)")
        origin = "replay" if _header_library(p) == REPLAY_LIBRARY else "live"
        files.append(DriveFile(p, origin, is_finished(p)))
    return files


def cut_notes(files: list[DriveFile]) -> list[str]:
    """One line per file that was not closed cleanly, for the user: such a file is read up to its cut."""
    return [f"{f.path} was not closed cleanly: read up to where it was cut" for f in files if not f.finished]


def _raw(f: DriveFile, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    """(log_time, order, topic, data) of the wanted topics in one file."""
    if f.finished:
        try:
            return raw_messages(f.path, wanted)
        except Exception as exc:  # the mcap package's reader raises its own kinds for a damaged file
            raise DriveFileError(f"{f.path}: cannot be read ({type(exc).__name__}: {exc}); "
                                 "`logger recover` may save what is left") from exc
    try:
        found = walk(f.path)
    except McapFileError as exc:
        raise DriveFileError(str(exc)) from exc
    topics = {cid: ch.topic for cid, ch in found.channels.items() if ch.topic in wanted}
    return [(m.log_time, i, topics[m.channel_id], m.data) for i, m in enumerate(found.messages)
            if m.channel_id in topics]


def _collect(files: list[DriveFile], wanted: set[str],
             progress: ProgressFn | None = None) -> list[tuple[int, int, int, str, bytes]]:
    """(log_time, file index, order, topic, data) of the wanted topics over the files, in log-time order (ties:
    file order, then order within the file)."""
    raw: list[tuple[int, int, int, str, bytes]] = []
    for index, f in enumerate(files):
        if progress is not None:
            progress(index, len(files), "files read")
        raw.extend((t, index, order, topic, data) for t, order, topic, data in _raw(f, wanted))
    raw.sort()  # (log_time, index, order) is unique: the data are never compared
    return raw


# Told (done, in all, of what): once per file read, then every PROGRESS_EVERY messages handed on.
ProgressFn = Callable[[int, int, str], None]
PROGRESS_EVERY = 4096


def _counted(raw: list[Any], progress: ProgressFn | None) -> Iterator[Any]:
    """The collected messages, telling ``progress`` how far the caller has got through them."""
    if progress is None:
        yield from raw
        return
    total = len(raw)
    for i, item in enumerate(raw):
        if i % PROGRESS_EVERY == 0:
            progress(i, total, "messages")
        yield item
    progress(total, total, "messages")


def imu_samples(batch: dict[str, Any]) -> list[dict[str, Any]]:
    """An ``/imu/batch`` record as the ``/imu`` records of its samples (their layout, their values), so that every
    reader of samples reads both kinds of drive alike."""
    ax, ay, az = batch["accel_x_mps2"], batch["accel_y_mps2"], batch["accel_z_mps2"]
    gx, gy, gz = batch["gyro_x_rps"], batch["gyro_y_rps"], batch["gyro_z_rps"]
    mono, sync, state, err = batch["t_mono_ns"], batch["t_sync_ns"], batch["sync_state"], batch["sync_err_ns"]
    imu_cnt, timer_cnt, seq, temp, lost = (batch["imu_cnt"], batch["timer_cnt"], batch["seq"], batch["temp_degc"],
                                           batch["lost"])
    return [{"t_mono_ns": mono[i], "t_sync_ns": sync[i], "sync_state": state[i], "sync_err_ns": err[i],
             "imu_cnt": imu_cnt[i], "timer_cnt": timer_cnt[i], "seq": seq + i,
             "accel_mps2": [ax[i], ay[i], az[i]], "gyro_rps": [gx[i], gy[i], gz[i]], "temp_degc": temp,
             "fifo": True, "lost": lost if i == 0 else 0} for i in range(len(mono))]


def _wanted(topics: Iterable[str]) -> tuple[set[str], bool]:
    """The topics to read, and whether ``/imu/batch`` records are to be handed on as their ``/imu`` samples: a
    reader of samples asks for ``/imu`` and gets a FIFO drive's samples too, one record each."""
    wanted = set(topics)
    expand = IMU_TOPIC in wanted and IMU_BATCH not in wanted
    if expand:
        wanted.add(IMU_BATCH)
    return wanted, expand


def imu_slice(batch: dict[str, Any], lo: int, hi: int) -> dict[str, Any]:
    """Samples ``lo`` to ``hi - 1`` of an ``/imu/batch`` record as a record of its own (its lost count goes with
    its first sample, its number is its first sample's)."""
    out = {k: v[lo:hi] if isinstance(v, list) else v for k, v in batch.items()}
    if lo:
        out["lost"] = 0
        out["seq"] = batch["seq"] + lo
    return out


def _in_time_order(items: Iterator[tuple[int, str, int, dict[str, Any]]],
                   expand: bool, runs: bool = False) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
    """(log time, topic, file index, message) with each ``/imu/batch`` replaced by its samples at their own times.

    A batch is logged at its first sample's time, so its later samples wait here until the messages logged before
    them have gone by: the samples and the other topics come out in time order, as per-sample records would.
    ``runs``: a batch's samples come as ``/imu/batch`` records of their own instead, each the batch's samples up
    to the next other message (one slice when nothing comes between), for a reader that takes blocks."""
    if runs:
        yield from in_runs(items)
        return
    if not expand:
        yield from items
        return
    pending: deque[tuple[int, int, dict[str, Any]]] = deque()
    for t, topic, index, msg in items:
        while pending and pending[0][0] <= t:
            pt, pi, pm = pending.popleft()
            yield pt, IMU_TOPIC, pi, pm
        if topic == IMU_BATCH:
            pending.extend((m["t_sync_ns"], index, m) for m in imu_samples(msg))
            continue
        yield t, topic, index, msg
    for pt, pi, pm in pending:
        yield pt, IMU_TOPIC, pi, pm


def in_runs(items: Iterator[tuple[int, str, int, dict[str, Any]]]) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
    """(log time, topic, file index, message) in log-time order, a batch logged at its first sample's time, with
    each batch cut where another message comes between its samples: replay's order, and the live navigator's
    (logger.runtime.navigator)."""
    pending: deque[tuple[int, dict[str, Any], int]] = deque()  # (file index, batch, first sample not yet out)

    def upto(t: int | None) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
        while pending:
            index, batch, lo = pending[0]
            times = batch["t_sync_ns"]
            hi = len(times) if t is None else bisect.bisect_right(times, t, lo)
            if hi > lo:
                yield times[lo], IMU_BATCH, index, batch if lo == 0 and hi == len(times) else imu_slice(batch, lo, hi)
            if hi < len(times):
                pending[0] = (index, batch, hi)
                return
            pending.popleft()

    for t, topic, index, msg in items:
        yield from upto(t)
        if topic == IMU_BATCH and msg["t_sync_ns"]:
            pending.append((index, msg, 0))
            continue
        yield t, topic, index, msg
    yield from upto(None)


def iter_messages(files: list[DriveFile], topics: Iterable[str],
                  progress: ProgressFn | None = None) -> Iterator[DriveMessage]:
    """Every message of the given topics over the files, decoded, in log-time order (ties: file order); a FIFO
    drive's ``/imu/batch`` records come as their ``/imu`` samples where ``/imu`` is asked for."""
    wanted, expand = _wanted(topics)
    for t, topic, index, msg in _in_time_order(_decoded(files, wanted, progress), expand):
        yield DriveMessage(t, topic, index, msg)


def _decoded(files: list[DriveFile], wanted: set[str],
             progress: ProgressFn | None) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
    loads = json.loads
    for t, index, _, topic, data in _counted(_collect(files, wanted, progress), progress):
        try:
            msg = loads(data)
        except ValueError as exc:  # UnicodeDecodeError and JSONDecodeError alike
            raise DriveFileError(f"{files[index].path}: a {topic} message at log time {t} is not JSON "
                                 f"({exc})") from exc
        yield t, topic, index, msg


def read_messages(paths: Iterable[Path], topics: Iterable[str],
                  progress: ProgressFn | None = None, runs: bool = False) -> Iterator[tuple[str, dict[str, Any]]]:
    """(topic, message) of the given topics over one drive's files, in log-time order, for the filter: as
    :func:`iter_messages`, with an IMU record's fields pulled out without decoding the whole JSON object.
    ``runs``: a FIFO drive's samples as ``/imu/batch`` records cut at the other messages (:func:`_in_time_order`)."""
    files = open_drive(paths)
    wanted, expand = _wanted(topics)
    for _, topic, _, msg in _in_time_order(_filter_inputs(files, wanted, progress), expand, runs):
        yield topic, msg


def _filter_inputs(files: list[DriveFile], wanted: set[str],
                   progress: ProgressFn | None) -> Iterator[tuple[int, str, int, dict[str, Any]]]:
    loads = json.loads
    imu = _IMU.match
    for t, index, _, topic, data in _counted(_collect(files, wanted, progress), progress):
        if topic == IMU_TOPIC:
            m = imu(data, 1)
            if m is not None:
                a, g = m.group(3).split(b","), m.group(4).split(b",")
                if len(a) == 3 and len(g) == 3:
                    msg = {"t_mono_ns": int(m.group(1)), "t_sync_ns": int(m.group(2)),
                           "accel_mps2": [float(a[0]), float(a[1]), float(a[2])],
                           "gyro_rps": [float(g[0]), float(g[1]), float(g[2])]}
                    if m.group(5) is not None:  # die temperature: the offsets' thermal drift (thermal.py)
                        msg["temp_degc"] = float(m.group(5))
                    yield t, topic, index, msg
                    continue
        yield t, topic, index, loads(data)
