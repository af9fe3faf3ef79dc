"""gpsd as its clients see it: a TCP server on 127.0.0.1 (an ephemeral port) speaking gpsd's JSON protocol.

:class:`SimGpsd` answers what gpsd_json(5) describes: the VERSION banner on connect, ``?WATCH=`` (with the
DEVICES list and the WATCH policy in reply), ``?DEVICES;``, ``?VERSION;``, ``?POLL;``, an ERROR object for
anything else, and in watcher mode the reports, one JSON object per CR-LF line, PPS and TOFF only to clients
that asked for them and only the watched device's when a client named one. Reports come from a feed:

- :class:`ReceiverFeed` turns a simulated u-blox receiver's epochs into TPV and SKY as gpsd's u-blox driver
  reports them (values at NAV-PVT's resolution, at the time the receiver's messages would reach gpsd), and the
  receiver's PPS line into PPS reports stamped on the simulated board's system clock, as gpsd's KPPS thread
  stamps them;
- or a test publishes objects itself (:meth:`SimGpsd.publish`), e.g. gpsd's own JSON decoding of a real
  capture, and line noise (:meth:`SimGpsd.inject`).

``stop`` makes gpsd go away (every connection closed, nothing listening), ``start`` brings it back on the same
port, as a restarted gpsd.service would.
"""

from __future__ import annotations

import datetime as dt
import heapq
import itertools
import json
import math
import selectors
import socket
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from sensors.sim.gnss_time import NS_PER_S
from sensors.sim.pps import PpsSignal
from sensors.sim.ublox import UbloxReceiverModel
from sensors.sim.ublox_encode import EpochRecord

NS_PER_MS = 1_000_000
RELEASE = "3.22"  # Debian 12's gpsd
PROTO = (3, 14)
MAX_REQUEST_BYTES = 4096  # a client that sends more without a newline is not speaking gpsd's protocol
MAX_PENDING_BYTES = 4 << 20  # gpsd drops a client that does not read its reports
_GNSS_ID = {"G": 0, "E": 2, "R": 6}  # u-blox gnssId, which gpsd passes on
_PRN_BASE = {"G": 0, "E": 300, "R": 64}  # gpsd's PRN numbering: GPS 1-32, GLONASS 65-96, Galileo 301-336


def to_ms(unix_ns: int) -> int:
    """Unix ns rounded to gpsd's millisecond, as whole ms."""
    return (unix_ns + NS_PER_MS // 2) // NS_PER_MS


def iso_ms(unix_ns: int) -> str:
    """Unix ns -> gpsd's time format, ISO 8601 UTC rounded to the millisecond."""
    ms = to_ms(unix_ns)
    stamp = dt.datetime(1970, 1, 1, tzinfo=dt.UTC) + dt.timedelta(milliseconds=ms)
    return stamp.strftime("%Y-%m-%dT%H:%M:%S.") + f"{ms % 1000:03d}Z"


def encode(obj: dict[str, Any]) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode() + b"\r\n"


class GpsdFeed(Protocol):
    """Where a simulated gpsd's reports come from."""

    def devices(self) -> list[dict[str, Any]]:
        """The DEVICE objects of the receivers gpsd has."""
        ...

    def poll(self) -> list[dict[str, Any]]:
        """The reports due now, in order."""
        ...


@dataclass
class _Policy:
    enable: bool = False
    json: bool = False
    pps: bool = False
    device: str | None = None

    def as_watch(self) -> dict[str, Any]:
        out: dict[str, Any] = {"class": "WATCH", "enable": self.enable, "json": self.json, "nmea": False, "raw": 0,
                               "scaled": False, "timing": False, "split24": False, "pps": self.pps}
        if self.device:
            out["device"] = self.device
        return out

    def wants(self, obj: dict[str, Any]) -> bool:
        if not (self.enable and self.json):
            return False
        if obj.get("class") in ("PPS", "TOFF") and not self.pps:
            return False
        return not (self.device and isinstance(obj.get("device"), str) and obj["device"] != self.device)


@dataclass
class _Client:
    sock: socket.socket
    policy: _Policy = field(default_factory=_Policy)
    inbox: bytearray = field(default_factory=bytearray)
    outbox: bytearray = field(default_factory=bytearray)


@dataclass
class SimGpsdCounters:
    connections: int = 0
    commands: int = 0
    reports: int = 0  # report objects sent (one per watching client)
    dropped_clients: int = 0  # closed for not reading


class SimGpsd:
    """A gpsd on ``host`` (127.0.0.1) and an ephemeral port that stays the same across ``stop``/``start``."""

    def __init__(self, feed: GpsdFeed | None = None, *, host: str = "127.0.0.1", port: int = 0,
                 devices: list[dict[str, Any]] | None = None, poll_s: float = 0.004) -> None:
        self.feed = feed
        self.host = host
        self._port = port
        self._devices = devices
        self.poll_s = poll_s
        self.counters = SimGpsdCounters()
        self._lock = threading.Lock()
        self._published: list[dict[str, Any] | bytes] = []
        self._clients: list[_Client] = []
        self._sel: selectors.BaseSelector | None = None
        self._listener: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()
        self._last: dict[str, dict[str, Any]] = {}
        self.error: BaseException | None = None
        self._listen()

    # ---- life cycle ---------------------------------------------------------------------------------------
    @property
    def address(self) -> tuple[str, int]:
        return self.host, self._port

    @property
    def running(self) -> bool:
        return self._thread is not None

    def _listen(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((self.host, self._port))
        sock.listen(8)
        sock.setblocking(False)
        self._port = sock.getsockname()[1]
        self._listener = sock

    def start(self) -> SimGpsd:
        if self._thread is not None:
            return self
        if self._listener is None:
            self._listen()
        self._halt.clear()
        self._thread = threading.Thread(target=self._run, name="sim-gpsd", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """gpsd exits: every client sees its connection closed, and nothing listens until ``start``."""
        self._halt.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        for client in list(self._clients):
            self._drop(client)
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    def restart(self) -> None:
        self.stop()
        self.start()

    def __enter__(self) -> SimGpsd:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---- what a test does -----------------------------------------------------------------------------------
    def publish(self, obj: dict[str, Any]) -> None:
        """Send a report to every client whose watch policy takes it."""
        with self._lock:
            self._published.append(dict(obj))

    def replay(self, lines: Iterable[str]) -> int:
        """Publish each line that is a JSON object (gpsd's own output, e.g. a regression .chk file), in order."""
        n = 0
        for line in lines:
            line = line.strip()
            if not line.startswith("{"):
                continue
            try:
                obj = json.loads(line)
            except ValueError:
                continue
            if isinstance(obj, dict):
                self.publish(obj)
                n += 1
        return n

    def inject(self, data: bytes) -> None:
        """Raw bytes to every watching client: line noise, a truncated report, an overlong line."""
        with self._lock:
            self._published.append(bytes(data))

    def watchers(self) -> int:
        return sum(1 for c in list(self._clients) if c.policy.enable)

    def wait_for_watchers(self, n: int = 1, timeout_s: float = 5.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.watchers() >= n:
                return True
            time.sleep(0.005)
        return self.watchers() >= n

    def devices(self) -> list[dict[str, Any]]:
        if self._devices is not None:
            return self._devices
        return self.feed.devices() if self.feed is not None else []

    # ---- the server thread ---------------------------------------------------------------------------------
    def _run(self) -> None:
        sel = self._sel = selectors.DefaultSelector()
        listener = self._listener
        if listener is None:
            return
        sel.register(listener, selectors.EVENT_READ, None)
        try:
            while not self._halt.is_set():
                for key, mask in sel.select(self.poll_s):
                    if key.data is None:
                        self._accept(sel, listener)
                        continue
                    client: _Client = key.data
                    if mask & selectors.EVENT_READ:
                        self._receive(client)
                    if mask & selectors.EVENT_WRITE and client in self._clients:
                        self._flush(client)
                reports = self.feed.poll() if self.feed is not None else []
                with self._lock:
                    published, self._published = self._published, []
                for item in [*reports, *published]:
                    self._broadcast(item)
                for client in list(self._clients):
                    self._flush(client)
                    if client in self._clients:
                        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.outbox else 0)
                        sel.modify(client.sock, events, client)
        except BaseException as exc:  # a model that dies must say so to the test that drives it
            self.error = exc
            raise
        finally:
            self._sel = None
            sel.close()

    def _accept(self, sel: selectors.BaseSelector, listener: socket.socket) -> None:
        try:
            sock, _ = listener.accept()
        except (BlockingIOError, OSError):
            return
        sock.setblocking(False)
        client = _Client(sock)
        self._clients.append(client)
        self.counters.connections += 1
        sel.register(sock, selectors.EVENT_READ, client)
        client.outbox += encode({"class": "VERSION", "release": RELEASE, "rev": RELEASE,
                                 "proto_major": PROTO[0], "proto_minor": PROTO[1]})

    def _drop(self, client: _Client) -> None:
        if client in self._clients:
            self._clients.remove(client)
        if self._sel is not None:
            try:
                self._sel.unregister(client.sock)
            except (KeyError, ValueError):
                pass
        try:
            client.sock.close()
        except OSError:
            pass

    def _receive(self, client: _Client) -> None:
        try:
            data = client.sock.recv(4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._drop(client)
            return
        client.inbox += data
        while b"\n" in client.inbox:
            line, _, rest = bytes(client.inbox).partition(b"\n")
            client.inbox = bytearray(rest)
            self._command(client, line.decode("ascii", "replace").strip())
        if len(client.inbox) > MAX_REQUEST_BYTES:
            self._drop(client)

    def _command(self, client: _Client, line: str) -> None:
        """One request line: ``?NAME;`` or ``?NAME={json}``, possibly several on the line."""
        pos = 0
        decoder = json.JSONDecoder()
        while pos < len(line):
            if line[pos] in "; \t\r":
                pos += 1
                continue
            if line[pos] != "?":
                self._reply(client, {"class": "ERROR", "message": f"Unrecognized request '{line[pos:pos + 20]}'"})
                return
            end = pos + 1
            while end < len(line) and line[end].isalpha():
                end += 1
            name, arg = line[pos + 1:end], None
            pos = end
            if pos < len(line) and line[pos] == "=":
                try:
                    arg, pos = decoder.raw_decode(line, pos + 1)
                except ValueError:
                    self._reply(client, {"class": "ERROR", "message": f"Invalid {name} argument"})
                    return
            self.counters.commands += 1
            self._handle(client, name, arg if isinstance(arg, dict) else None)

    def _handle(self, client: _Client, name: str, arg: dict[str, Any] | None) -> None:
        devices = self.devices()
        if name == "VERSION":
            self._reply(client, {"class": "VERSION", "release": RELEASE, "rev": RELEASE, "proto_major": PROTO[0],
                                 "proto_minor": PROTO[1]})
        elif name == "DEVICES":
            self._reply(client, {"class": "DEVICES", "devices": devices})
        elif name == "WATCH":
            p = client.policy
            if arg is not None:
                p.enable = bool(arg.get("enable", True))
                p.json = bool(arg.get("json", p.json))
                p.pps = bool(arg.get("pps", p.pps))
                device = arg.get("device")
                p.device = device if isinstance(device, str) and device else None
            self._reply(client, {"class": "DEVICES", "devices": devices})
            self._reply(client, p.as_watch())
        elif name == "POLL":
            self._reply(client, {"class": "POLL", "time": iso_ms(time.time_ns()), "active": len(devices),
                                 "tpv": [self._last["TPV"]] if "TPV" in self._last else [],
                                 "sky": [self._last["SKY"]] if "SKY" in self._last else []})
        elif name == "DEVICE" and devices:
            self._reply(client, devices[0])
        else:
            self._reply(client, {"class": "ERROR", "message": f"Unrecognized request '?{name}'"})

    def _reply(self, client: _Client, obj: dict[str, Any]) -> None:
        client.outbox += encode(obj)

    def _broadcast(self, item: dict[str, Any] | bytes) -> None:
        if isinstance(item, dict) and item.get("class") in ("TPV", "SKY"):
            self._last[item["class"]] = item
        data = item if isinstance(item, bytes) else encode(item)
        for client in list(self._clients):
            if isinstance(item, bytes):
                if not client.policy.enable:
                    continue
            elif not client.policy.wants(item):
                continue
            client.outbox += data
            self.counters.reports += 1
            if len(client.outbox) > MAX_PENDING_BYTES:
                self.counters.dropped_clients += 1
                self._drop(client)

    def _flush(self, client: _Client) -> None:
        if not client.outbox:
            return
        try:
            sent = client.sock.send(client.outbox)
        except BlockingIOError:
            return
        except OSError:
            self._drop(client)
            return
        del client.outbox[:sent]


class ReceiverFeed:
    """A simulated receiver (and its PPS line) reported the way gpsd's u-blox driver reports the real one.

    Each navigation epoch the receiver model computed becomes a SKY and a TPV, due when the receiver's messages
    for it would have reached gpsd: the solution latency plus the UART time of a NAV-PVT. Values carry NAV-PVT's
    resolution (1e-7 deg, mm, mm/s). Each PPS edge (rising edges on whole seconds, glitches left out as gpsd's
    sanity checks do) becomes a PPS report a few ms later: ``clock`` is the board's system clock at the edge's
    interrupt, ``real`` the UTC second it marks, ``qErr`` the quantisation error TIM-TP announced for it. The
    board's system clock is its monotonic clock plus ``realtime_offset_ns`` (set once, as NTP left it).
    """

    def __init__(self, receiver: UbloxReceiverModel, *, pps: PpsSignal | None = None, realtime_offset_ns: int = 0,
                 device: str | None = None, seed: int | np.random.Generator = 0,
                 pps_delay_s: tuple[float, float] = (0.001, 0.02)) -> None:
        self.receiver = receiver
        self.clock = receiver.clock
        self.timeline = receiver.timeline
        self.pps = pps
        self.realtime_offset_ns = int(realtime_offset_ns)
        self._board_ns = pps.oscillator.board_ns if pps is not None else None  # true drive time -> board clock
        self.device = device or receiver.port.path
        self.pps_delay_s = pps_delay_s
        self._rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng([int(seed), 47])
        self._queue: list[tuple[int, int, dict[str, Any]]] = []
        self._seq = itertools.count()
        self._last_epoch_ns: int | None = None
        self._pps_since = self.clock.now_ns()
        self._pps_last_k: int | None = None
        self._time_known = False
        self._toff_second: int | None = None  # the UTC second of the last TOFF sent
        self._activated = iso_ms(time.time_ns())

    def devices(self) -> list[dict[str, Any]]:
        return [{"class": "DEVICE", "path": self.device, "driver": "u-blox", "activated": self._activated,
                 "flags": 1, "native": 1, "bps": self.receiver.baud, "parity": "N", "stopbits": 1,
                 "cycle": self.receiver.meas_period_ms / 1000.0, "mincycle": 0.02}]

    def poll(self) -> list[dict[str, Any]]:
        now = self.clock.now_ns()
        for rec in self._new_epochs():
            self._schedule_epoch(rec)
        self._schedule_edges(now)
        due = []
        while self._queue and self._queue[0][0] <= now:
            due.append(heapq.heappop(self._queue)[2])
        return due

    # ---- epochs ---------------------------------------------------------------------------------------------
    def _new_epochs(self) -> list[EpochRecord]:
        """Epochs the receiver computed since the last poll. Its thread appends to ``history`` meanwhile: read
        from the newest end (an append only shifts older entries) and keep each epoch once."""
        history = self.receiver.history
        found: dict[int, EpochRecord] = {}
        i = 1
        while i <= len(history):
            try:
                rec = history[-i]
            except IndexError:
                break
            if self._last_epoch_ns is not None and rec.drive_ns <= self._last_epoch_ns:
                break
            found[rec.drive_ns] = rec
            i += 1
        recs = [found[k] for k in sorted(found)]
        if recs:
            self._last_epoch_ns = recs[-1].drive_ns
        return recs

    def _schedule_epoch(self, rec: EpochRecord) -> None:
        lo, mean = self.receiver.latency_s
        uart_s = 100 * 10 / self.receiver.baud  # a NAV-PVT frame on the line, 8N1
        excess = min(float(self._rng.exponential(mean)), self.receiver.latency_cap_s)
        ready = rec.drive_ns + round((lo + excess + uart_s) * NS_PER_S)
        utc = self.timeline.utc_unix_ns(rec.gps_ns + round(rec.time_error_ns))  # as the receiver states it
        tpv, sky = self._tpv(rec, utc), self._sky(rec)
        # gpsd latches an epoch's time when the receiver's first message of it comes, and sends the TOFF then,
        # before the epoch's reports; only for the first epoch of each second (gpsd 3.22 skips "not a new time":
        # at 5 Hz the x.0 epoch), naming that epoch's own time as its TPV does.
        real = to_ms(utc) * NS_PER_MS if "time" in tpv else None
        if real is not None and self._board_ns is not None and real // NS_PER_S != self._toff_second:
            self._toff_second = real // NS_PER_S
            clock = self._board_ns(ready) + self.realtime_offset_ns
            self._push(ready, {"class": "TOFF", "device": self.device, "real_sec": real // NS_PER_S,
                               "real_nsec": real % NS_PER_S, "clock_sec": clock // NS_PER_S,
                               "clock_nsec": clock % NS_PER_S, "precision": -2})
        self._push(ready, sky)
        self._push(ready + NS_PER_MS, tpv)

    def _push(self, due_ns: int, obj: dict[str, Any]) -> None:
        heapq.heappush(self._queue, (int(due_ns), next(self._seq), obj))

    def _tpv(self, rec: EpochRecord, utc_ns: int) -> dict[str, Any]:
        fix = rec.fix_type >= 2
        self._time_known = self._time_known or fix
        tpv: dict[str, Any] = {"class": "TPV", "device": self.device, "mode": 3 if rec.fix_type == 3 else 2 if fix
                               else 1}
        if fix:
            tpv["status"] = 1
        if self._time_known:
            tpv.update(time=iso_ms(utc_ns), leapseconds=self.timeline.leap_s, ept=0.005)
        if not fix:
            return tpv
        hae = round(rec.height_m * 1000) / 1000
        msl = round((rec.height_m - rec.truth.geoid_m) * 1000) / 1000
        vn, ve, vd = (round(float(v) * 1000) / 1000 for v in rec.vel_ned_mps)
        g_speed = round(math.hypot(*(float(v) for v in rec.vel_ned_mps[:2])) * 1000) / 1000
        tpv.update(lat=round(round(rec.lat_deg * 1e7) / 1e7, 9), lon=round(round(rec.lon_deg * 1e7) / 1e7, 9),
                   altHAE=round(hae, 4), altMSL=round(msl, 4), alt=round(msl, 4), geoidSep=round(hae - msl, 3),
                   velN=vn, velE=ve, velD=vd, speed=g_speed,
                   track=round(round(rec.head_mot_deg * 1e5) % 36_000_000 / 1e5, 4), climb=-vd)
        for key, value in (("eph", rec.h_acc_m), ("epv", rec.v_acc_m), ("eps", rec.s_acc_mps)):
            if math.isfinite(value):
                tpv[key] = round(value, 3)
        return tpv

    def _sky(self, rec: EpochRecord) -> dict[str, Any]:
        sky: dict[str, Any] = {"class": "SKY", "device": self.device}
        if self._time_known or rec.fix_type >= 2:
            sky["time"] = iso_ms(self.timeline.utc_unix_ns(rec.gps_ns + round(rec.time_error_ns)))
        d = rec.error.dops
        sky.update(hdop=round(d.hdop, 2), vdop=round(d.vdop, 2), pdop=round(d.pdop, 2), tdop=round(d.tdop, 2))
        sats: list[dict[str, Any]] = []
        geometry = self.receiver.sky
        if geometry is not None and rec.num_sv > 0:
            view = geometry.view(rec.truth)
            names = geometry.constellation.names
            for n, (idx, az, el, reflected) in enumerate(zip(view.ids, view.az, view.el, view.reflected,
                                                             strict=True)):
                name = names[int(idx)]
                svid = int(name[1:])
                sats.append({"PRN": _PRN_BASE[name[0]] + svid, "gnssid": _GNSS_ID[name[0]], "svid": svid,
                             "az": round(math.degrees(float(az)) % 360.0, 1), "el": round(math.degrees(float(el)), 1),
                             "ss": round(20.0 + 25.0 * math.sin(float(el)) - (8.0 if reflected else 0.0), 1),
                             "used": n < rec.num_sv, "health": 1})
            sky["satellites"] = sats
        sky.update(nSat=len(sats) if sats else rec.num_sv, uSat=rec.num_sv)
        return sky

    # ---- PPS ------------------------------------------------------------------------------------------------
    def _schedule_edges(self, now: int) -> None:
        pps = self.pps
        if pps is None or now <= self._pps_since:
            return
        edges = pps.edges_between(self._pps_since, now)
        self._pps_since = now
        for edge in edges:
            if not edge.rising:
                continue
            k = pps.pulse_index(edge.true_ns)
            if k == self._pps_last_k or edge.true_ns - pps.pulse_edge_true_ns(k) > NS_PER_MS:
                continue  # a glitch: not the first edge of a second, or not on the second at all
            self._pps_last_k = k
            gps_ns = pps.pulse_gnss_ns(k)
            real = self.timeline.utc_unix_ns(gps_ns)
            clock = edge.monotonic_ns + self.realtime_offset_ns
            lo, hi = self.pps_delay_s
            delay = round(float(self._rng.uniform(lo, hi)) * NS_PER_S)
            self._push(edge.true_ns + delay, {
                "class": "PPS", "device": self.device, "real_sec": real // NS_PER_S, "real_nsec": real % NS_PER_S,
                "clock_sec": clock // NS_PER_S, "clock_nsec": clock % NS_PER_S, "precision": -20, "shm": "NTP2",
                "qErr": self.receiver.pulse_quantisation.qerr_ps(gps_ns // NS_PER_S)})
