"""gpsd as the GNSS source: its JSON reports over TCP instead of the receiver's serial port.

Many boards already run gpsd on the receiver, and then the port is gpsd's. :class:`GpsdClient` connects to
gpsd (127.0.0.1:2947 by default), asks for reports with ``?WATCH={"enable":true,"json":true,"pps":true}``
(gpsd_json(5)) and returns the JSON objects that arrive, one per line. Decoding them into fixes and PPS edges
is :mod:`sensors.gpsd_decode`'s.

The stream is untrusted: a line longer than gpsd's own limit is dropped whole, a line that is not a JSON
object with a ``class`` is counted as garbage, and neither stops the reading. I/O and decoding only, as
every driver: the sampler thread owns timing and reconnects; a connection gpsd closes raises
:class:`~sensors.errors.BusError`, a gpsd that is not listening :class:`~sensors.errors.DeviceNotFound`.
"""

from __future__ import annotations

import errno
import json
import socket
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from sensors.errors import BusError, DeviceNotFound

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 2947
# gpsd caps a report at 10240 characters including CR-LF (GPS_JSON_RESPONSE_MAX); a longer line is not gpsd's.
MAX_LINE_BYTES = 16384
MAX_COMMAND_CHARS = 80  # gpsd's limit for a request line, without the newline
RECV_BYTES = 65536
WATCH_POLICY = {"enable": True, "json": True, "pps": True}

_DENIED = {errno.EAFNOSUPPORT, errno.EPERM, errno.EACCES}


def watch_command(device: str | None = None) -> bytes:
    """The WATCH request; it names the device when that still fits gpsd's 80 characters (else the reports
    of other devices are dropped here instead)."""
    policy: dict[str, Any] = dict(WATCH_POLICY)
    plain = "?WATCH=" + json.dumps(policy, separators=(",", ":"))
    if device:
        policy["device"] = device
        named = "?WATCH=" + json.dumps(policy, separators=(",", ":"))
        if len(named) <= MAX_COMMAND_CHARS:
            plain = named
    return (plain + "\n").encode("ascii", "backslashreplace")


class LineSplitter:
    """Bytes -> complete lines (CR-LF or LF, without the terminator), each at most ``max_bytes`` long.

    A longer line is dropped whole, up to its newline, and counted; memory never grows beyond the limit.
    """

    def __init__(self, max_bytes: int = MAX_LINE_BYTES) -> None:
        self.max_bytes = max_bytes
        self._buf = bytearray()
        self._skipping = False
        self.oversized = 0

    def feed(self, data: bytes) -> list[bytes]:
        lines: list[bytes] = []
        start = 0
        while start <= len(data):
            nl = data.find(b"\n", start)
            piece = data[start:] if nl < 0 else data[start:nl]
            if self._skipping:
                if nl >= 0:
                    self._skipping = False
            elif len(self._buf) + len(piece) > self.max_bytes:
                self.oversized += 1
                self._buf.clear()
                self._skipping = nl < 0
            elif nl >= 0:
                self._buf += piece
                lines.append(bytes(self._buf).rstrip(b"\r"))
                self._buf.clear()
            else:
                self._buf += piece
            if nl < 0:
                break
            start = nl + 1
        return lines

    def reset(self) -> None:
        self._buf.clear()
        self._skipping = False


def parse_line(line: bytes) -> dict[str, Any] | None:
    """One report line -> its JSON object, or None when it is not an object with a string ``class``."""
    try:
        obj = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return None
    if not isinstance(obj, dict) or not isinstance(obj.get("class"), str):
        return None
    return obj


@dataclass
class GpsdCounters:
    """What came over the connection: for tests, the soak report and the log."""

    lines: int = 0
    objects: int = 0
    garbage: int = 0  # lines that are not a JSON object with a class
    oversized: int = 0  # lines beyond MAX_LINE_BYTES, dropped whole
    other_device: int = 0  # reports of a device other than the one configured
    errors: int = 0  # gpsd's own ERROR replies
    bytes: int = 0
    by_class: dict[str, int] = field(default_factory=dict)


class GpsdClient:
    """One connection to gpsd in watcher mode: ``read`` returns the report objects that arrived.

    With ``device`` set, reports naming another device are dropped (reports without a ``device`` pass).
    ``devices`` is the set of receivers gpsd has active (None until gpsd said), ``version`` gpsd's VERSION
    object, ``error`` the message of gpsd's last ERROR reply.
    """

    def __init__(self, sock: socket.socket, host: str, port: int, device: str | None = None) -> None:
        self._sock = sock
        self.host, self.port, self.device = host, port, device or None
        self.where = f"{host}:{port}"
        self._lines = LineSplitter()
        self.counters = GpsdCounters()
        self.devices: set[str] | None = None
        self.version: dict[str, Any] | None = None
        self.error: str | None = None

    @classmethod
    def connect(cls, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, device: str | None = None,
                timeout_s: float = 2.0) -> GpsdClient:
        """Connect and start watching. gpsd's VERSION banner and WATCH reply arrive with the first reads."""
        where = f"{host}:{port}"
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except ConnectionRefusedError:
            raise DeviceNotFound(f"gpsd: nothing listens on {where} (is gpsd running?)") from None
        except socket.gaierror as err:
            raise DeviceNotFound(f"gpsd: cannot resolve {host!r}: {err.strerror or err}") from None
        except TimeoutError:
            raise BusError(f"gpsd at {where}: no answer within {timeout_s:g} s") from None
        except OSError as err:
            if err.errno in _DENIED:
                raise BusError(f"gpsd at {where}: TCP is not allowed to this process ({err.strerror}); under "
                               "systemd install the drop-in systemd/vehicle-logger.service.d/gpsd.conf") from None
            raise BusError(f"gpsd at {where}: cannot connect: {err.strerror or err}") from None
        client = cls(sock, host, port, device)
        try:
            client.send(watch_command(client.device))
        except BusError:
            client.close()
            raise
        return client

    def send(self, data: bytes) -> None:
        try:
            self._sock.settimeout(2.0)
            self._sock.sendall(data)
        except OSError as err:
            raise BusError(f"gpsd at {self.where}: connection lost: {err.strerror or err}") from None

    def read(self, timeout_s: float) -> list[dict[str, Any]]:
        """Wait up to ``timeout_s`` for reports; return those complete (none when gpsd stayed quiet)."""
        try:
            self._sock.settimeout(max(0.0, timeout_s))
            data = self._sock.recv(RECV_BYTES)
        except TimeoutError:
            return []
        except BlockingIOError:
            return []
        except OSError as err:
            raise BusError(f"gpsd at {self.where}: connection lost: {err.strerror or err}") from None
        if not data:
            raise BusError(f"gpsd at {self.where} closed the connection")
        return self.feed(data)

    def feed(self, data: bytes) -> list[dict[str, Any]]:
        """Bytes from gpsd -> the report objects they complete (the bookkeeping objects are kept here too)."""
        c = self.counters
        c.bytes += len(data)
        out: list[dict[str, Any]] = []
        for line in self._lines.feed(data):
            if not line.strip():
                continue
            c.lines += 1
            obj = parse_line(line)
            if obj is None:
                c.garbage += 1
                continue
            c.objects += 1
            kind = obj["class"]
            if len(c.by_class) < 64 or kind in c.by_class:
                c.by_class[kind] = c.by_class.get(kind, 0) + 1
            self._note(kind, obj)
            device = obj.get("device")
            if self.device is not None and isinstance(device, str) and device != self.device:
                c.other_device += 1
                continue
            out.append(obj)
        c.oversized = self._lines.oversized
        return out

    def _note(self, kind: str, obj: Mapping[str, Any]) -> None:
        if kind == "VERSION":
            self.version = dict(obj)
        elif kind == "DEVICES":
            listed = obj.get("devices")
            if isinstance(listed, list):
                self.devices = {d["path"] for d in listed if isinstance(d, dict) and isinstance(d.get("path"), str)}
        elif kind == "DEVICE":
            path = obj.get("path")
            if isinstance(path, str):
                if self.devices is None:
                    self.devices = set()
                if _active(obj):
                    self.devices.add(path)
                else:
                    self.devices.discard(path)
        elif kind == "ERROR":
            self.counters.errors += 1
            message = obj.get("message")
            self.error = " ".join(str(message).split())[:200] if message is not None else "error"

    def missing_device(self) -> str | None:
        """Why no reports can come, when gpsd said so: no receiver at all, or not the configured one."""
        if self.devices is None:
            return None
        if not self.devices:
            return f"gpsd at {self.where} has no receiver"
        if self.device is not None and self.device not in self.devices:
            return f"gpsd at {self.where} has no {self.device} (it has {', '.join(sorted(self.devices))})"
        return None

    def close(self) -> None:
        try:
            self._sock.close()
        except OSError:
            pass

    def __enter__(self) -> GpsdClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _active(device: Mapping[str, Any]) -> bool:
    """A DEVICE notification of a receiver gpsd still has: one it closed comes with ``"activated":0``."""
    return device.get("activated", True) not in (0, "", False, None)
