"""Reading a recorded drive for the filter, fast: the MCAP records parsed directly, then sorted by log time.

The ``mcap`` package's reader handles every corner of the format but costs some 15 us per message in Python,
as much as the filter's own work per IMU sample. The logger's own files are simple (chunked, zstd/lz4/none,
JSON messages), so this walks the records with ``struct`` and keeps only the wanted channels; anything it does
not expect sends it back to the package's reader, so a file written by another tool still replays.
"""

from __future__ import annotations

import json
import re
import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

MAGIC = b"\x89MCAP0\r\n"
_U8 = struct.Struct("<B")
_REC = struct.Struct("<BQ")
_MSG = struct.Struct("<HIQQ")
_CHUNK = struct.Struct("<QQQI")
_H = struct.Struct("<H")
_I = struct.Struct("<I")
_Q = struct.Struct("<Q")
OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_DATA_END = 0x04, 0x05, 0x06, 0x0F
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
        op, length = _REC.unpack_from(buf, pos)
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
            _start, _end, size, _crc = _CHUNK.unpack_from(buf, body)
            n = _I.unpack_from(buf, body + 28)[0]
            compression = bytes(buf[body + 32:body + 32 + n]).decode()
            rec_len = _Q.unpack_from(buf, body + 32 + n)[0]
            data = buf[body + 40 + n:body + 40 + n + rec_len]
            if compression == "zstd":
                import zstandard

                data = zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=size)
            elif compression == "lz4":
                import lz4.frame

                data = lz4.frame.decompress(bytes(data))
            elif compression != "":
                raise UnexpectedLayout(f"compression {compression!r}")
            _walk(data, 0, len(data), wanted, channels, out, False)
        elif op == OP_DATA_END and top:
            return True
        pos = nxt
    return False


def _fast(path: Path, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    buf = path.read_bytes()
    if not buf.startswith(MAGIC):
        raise UnexpectedLayout("not an MCAP file")
    out: list[tuple[int, int, str, bytes]] = []
    if not _walk(memoryview(buf), len(MAGIC), len(buf), wanted, {}, out, True):
        raise UnexpectedLayout("no data end record: an unfinished file")
    return out


def _slow(path: Path, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    from mcap.reader import make_reader

    out: list[tuple[int, int, str, bytes]] = []
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=list(wanted), log_time_order=False):
            out.append((message.log_time, len(out), channel.topic, message.data))
    return out


def raw_messages(path: Path, wanted: set[str]) -> list[tuple[int, int, str, bytes]]:
    """(log_time, order, topic, data) of the wanted topics in one finished file: the record walk above, or the
    mcap package's reader for a layout the walk does not expect (its errors are then the caller's)."""
    try:
        return _fast(path, wanted)
    except Exception:  # a layout or a damage the walk does not expect: the mcap package decides
        return _slow(path, wanted)


def read_messages(paths: Iterable[Path], topics: Iterable[str]) -> Iterator[tuple[str, dict[str, Any]]]:
    """(topic, message) of the given topics over one drive's files, in log-time order (ties: file order)."""
    wanted = set(topics)
    raw: list[tuple[int, int, str, bytes]] = []
    for path in paths:
        part = raw_messages(Path(path), wanted)
        base = len(raw)
        raw.extend((t, base + i, topic, data) for t, i, topic, data in part)
    raw.sort()
    loads = json.loads
    imu = _IMU.match
    for _, _, topic, data in raw:
        if topic == "/imu":
            m = imu(data, 1)
            if m is not None:
                a, g = m.group(3).split(b","), m.group(4).split(b",")
                if len(a) == 3 and len(g) == 3:
                    msg = {"t_mono_ns": int(m.group(1)), "t_sync_ns": int(m.group(2)),
                           "accel_mps2": [float(a[0]), float(a[1]), float(a[2])],
                           "gyro_rps": [float(g[0]), float(g[1]), float(g[2])]}
                    if m.group(5) is not None:  # die temperature: the offsets' thermal drift (thermal.py)
                        msg["temp_degc"] = float(m.group(5))
                    yield topic, msg
                    continue
        yield topic, loads(data)
