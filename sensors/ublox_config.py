"""Receiver setup at start: the messages, the navigation rate and the baud rate the logger relies on.

A receiver may come from the factory (NMEA only, 9600 baud) or with a configuration saved by someone
else, so the logger states what it needs instead of trusting the flash: NAV-PVT for the solution, TIM-TP
for the time of the next PPS edge, NAV-TIMEGPS for GPS week and leap seconds, one epoch per second on
GPS time. Every command must be confirmed by ACK-ACK for the same class and id, else the log would
silently lack what the time synchronisation needs.

u-blox has two configuration interfaces. Receivers up to M8 know only the legacy messages (UBX-CFG-MSG,
-RATE, -PRT); F9 knows both; M10 only the configuration keys (UBX-CFG-VALSET). The legacy message is tried
first and, once NAKed, the keys are used for the rest of the setup.

The port speed goes up to one that carries the whole output (:func:`line_budget`) whenever the current one does
not: a factory receiver's NMEA (GGA, GLL, GSA, RMC, VTG and a GSV series per constellation: 649 bytes a second on
the simulated M8 with 21 satellites in view) plus NAV-PVT, TIM-TP and NAV-TIMEGPS (148) fill more than LINE_USE of
a 9600-baud line, leaving too little for the burst after each epoch, and a full transmit buffer drops messages,
TIM-TP among them. :data:`NMEA_BYTES_PER_SOLUTION` allows 1000 for the NMEA, for skies with more satellites.

Raw observations (UBX-RXM-RAWX and -SFRBX, for RTKLIB at the office) are asked for only when the set-up says
so, and only receivers with raw firmware give them (M8T, M8P, F9P, F9T; an M8N refuses): a refusal is reported
in the result, not raised, since the logger records everything else the same. They need a fast line, so the speed
goes up first and they are turned on at the new rate: turned on at 9600 baud they would fill the receiver's
transmit buffer, which drops messages, ACKs among them.

The baud rate changes on its own, after the other settings. A legacy CFG-PRT is acknowledged at the old rate,
then the receiver switches; a VALSET takes effect at once, so its ACK (if the host is quick enough to catch it)
comes at the new rate. Either way the host follows and confirms with a MON-VER poll at the new rate, and if that stays
silent goes back to the old rate, so a lost ACK never leaves the two ends talking past each other.

Waiting goes through an injected ``sleep`` and timeouts count the time slept, so a test hands in a
simulated clock and never waits, and a slow host does not shorten a timeout.
"""

from __future__ import annotations

import termios
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import serial
from pyubx2 import POLL, SET, SET_LAYER_RAM, TXN_NONE, UBX_CONFIG_DATABASE, UBX_MSGIDS, UBXMessage

from sensors.errors import BusError, NoData, ProtocolError
from sensors.ublox_frames import KIND_NMEA, KIND_UBX, UbxNmeaFramer

__all__ = [
    "RAW_MESSAGES",
    "NoUbxAnswer",
    "ReceiverSetup",
    "SetupResult",
    "baud_for",
    "configure_receiver",
    "line_budget",
    "message_id",
]

# Message names as pyubx2 spells them ("NAV-PVT", "TIM-TP"; NMEA sentences by their id, "GGA").
_ID_BY_NAME: dict[str, bytes] = {}
for _key, _name in UBX_MSGIDS.items():
    _ID_BY_NAME.setdefault(_name, _key)

_TIME_REF = {"utc": 0, "gps": 1, "glonass": 2, "beidou": 3, "galileo": 4}
_UART_PORT_ID = {"UART1": 1, "UART2": 2}
_UART_NAME = {v: k for k, v in _UART_PORT_ID.items()}  # CFG-PRT's port ids: 0 I2C (DDC), 1-2 UART, 3 USB, 4 SPI
_PRT_OUT_PROTO, _PRT_OUT_NMEA = 14, 0x02  # CFG-PRT payload: outProtoMask's low byte, and its NMEA bit
_BAUDS = (4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
# Shortest payload of each reply the set-up reads. pyubx2 decodes a runt with a good checksum into a message
# without the fields, and reading those would raise out of the set-up instead of waiting for a real reply.
_MIN_REPLY_PAYLOAD = {"ACK-ACK": 2, "ACK-NAK": 2, "MON-VER": 40}

RAW_MESSAGES = ("RXM-RAWX", "RXM-SFRBX")  # raw observations and navigation data bits: what RTKLIB's ubx reader needs
# The line budget: bytes on the wire (UBX frame of 8 bytes included) of each message. NAV-PVT, NAV-TIMEGPS and TIM-TP
# come once per solution; RXM-RAWX is 16 bytes plus 32 per measurement, and a dual-band receiver (F9) reports up to
# about 64 signals; NMEA is the factory set (GGA, GLL, GSA, several GSV, RMC, VTG) at its longest.
UBX_BYTES = {"NAV-PVT": 100, "NAV-TIMEGPS": 24, "TIM-TP": 24, "RXM-RAWX": 16 + 32 * 64 + 8}
NMEA_BYTES_PER_SOLUTION = 1000
# RXM-SFRBX comes as the satellites broadcast (a subframe, page or string every 0.6 to 6 s per satellite), not per
# solution: up to about 40 a second, 40 to 60 bytes each, with every constellation tracked.
SFRBX_BYTES_PER_S = 40 * 60
LINE_USE = 0.75  # the share of a UART's 8N1 capacity the output may fill: bursts after each epoch need the rest


def message_id(name: str) -> tuple[int, int]:
    """UBX class and id of an output message, by its pyubx2 name (NMEA sentences are class 0xF0)."""
    try:
        key = _ID_BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown u-blox message {name!r}") from None
    return key[0], key[1]


def _msgout_key(name: str, uart: str) -> str:
    nmea = message_id(name)[0] == 0xF0
    key = f"CFG_MSGOUT_NMEA_ID_{name}_{uart}" if nmea else f"CFG_MSGOUT_UBX_{name.replace('-', '_')}_{uart}"
    if key not in UBX_CONFIG_DATABASE:
        raise ValueError(f"u-blox has no configuration key for {name} on {uart} ({key})")
    return key


@dataclass(frozen=True, slots=True)
class ReceiverSetup:
    """What the logger asks of the receiver.

    ``uart`` is the receiver port wired to the host (configuration keys name it; the legacy CFG-MSG
    short form acts on whichever port the command arrives at). ``baud`` None keeps the current rate.
    """

    meas_period_ms: int = 1000
    nav_rate: int = 1
    time_ref: str = "gps"
    enable: tuple[str, ...] = ("NAV-PVT", "TIM-TP", "NAV-TIMEGPS")
    disable: tuple[str, ...] = ()
    baud: int | None = None
    uart: str = "UART1"
    nmea_output: bool = True
    raw_observations: bool = False

    def __post_init__(self) -> None:
        if self.time_ref not in _TIME_REF:
            raise ValueError(f"time_ref must be one of {sorted(_TIME_REF)}, not {self.time_ref!r}")
        if self.uart not in _UART_PORT_ID:
            raise ValueError(f"uart must be one of {sorted(_UART_PORT_ID)}, not {self.uart!r}")
        if self.baud is not None and self.baud not in _BAUDS:
            raise ValueError(f"baud must be one of {_BAUDS}, not {self.baud}")
        if not 25 <= self.meas_period_ms <= 65535 or not 1 <= self.nav_rate <= 127:
            raise ValueError("meas_period_ms must be 25..65535 and nav_rate 1..127")
        for name in (*self.enable, *self.disable):
            _msgout_key(name, self.uart)  # fails early on a name the receiver cannot have


@dataclass(frozen=True, slots=True)
class SetupResult:
    """What the receiver confirmed, for the log's header."""

    software: str
    hardware: str
    extensions: tuple[str, ...]
    interface: str  # "legacy" (UBX-CFG-MSG/RATE/PRT) or "keys" (UBX-CFG-VALSET)
    baud: int
    acknowledged: tuple[str, ...] = field(default=())
    raw_observations: str = "off"  # "on" (RXM-RAWX and -SFRBX acknowledged), "refused" (NAKed), "off" (not asked)
    raw_refusal: str = ""  # what the receiver refused, when it did


class NoUbxAnswer(NoData):
    """The receiver did not answer a UBX poll at all. ``nmea_sentences`` counts the checksum-valid NMEA sentences
    it sent meanwhile: some means the line and the baud rate are right and the receiver speaks NMEA only (one
    that is not a u-blox, such as an ST TESEO, or a u-blox with UBX input turned off), none that nothing is
    heard at this rate."""

    def __init__(self, message: str, nmea_sentences: int, nmea_without_checksum: int = 0) -> None:
        super().__init__(message)
        self.nmea_sentences = nmea_sentences
        self.nmea_without_checksum = nmea_without_checksum  # refused sentences: the speed was right


class _Session:
    """One setup conversation: commands out, ACKs and poll answers in, through the reader's framer."""

    def __init__(self, port: serial.SerialBase, path: str, sleep: Callable[[float], None], timeout_s: float,
                 tries: int, poll_s: float) -> None:
        self.port = port
        self.path = path
        self.sleep = sleep
        self.timeout_s = timeout_s
        self.tries = tries
        self.poll_s = poll_s
        self.framer = UbxNmeaFramer()
        self._backlog: list = []  # UBX frames read after the one an earlier wait matched (a poll's reply and ACK)
        self.interface = "legacy"
        self.acknowledged: list[str] = []
        self.nmea_sentences = 0  # checksum-valid NMEA heard while waiting for answers

    # -- bytes

    def _io(self, action: Callable[[], object], what: str) -> object:
        try:
            return action()
        except (serial.SerialException, OSError, ValueError, termios.error) as err:
            detail = " ".join(str(err).split()) or type(err).__name__
            raise BusError(f"GNSS receiver on {self.path}: serial port failed while {what}: {detail}") from err

    def write(self, msg: UBXMessage) -> None:
        raw = msg.serialize()
        self._io(lambda: (self.port.write(raw), self.port.flush()), f"sending {_name(msg)}")

    def _frames(self) -> list:
        def take() -> bytes:
            waiting = self.port.in_waiting
            return self.port.read(waiting) if waiting else b""

        data = self._io(take, "reading")
        frames = self.framer.feed(data)  # type: ignore[arg-type]
        self.nmea_sentences += sum(1 for f in frames if f.kind == KIND_NMEA)
        return [f for f in frames
                if f.kind == KIND_UBX and f.message is not None
                and len(f.raw) - 8 >= _MIN_REPLY_PAYLOAD.get(str(getattr(f.message, "identity", "")), 0)]

    def set_host_baud(self, baud: int) -> None:
        self._io(lambda: setattr(self.port, "baudrate", baud), f"switching to {baud} baud")
        self.discard_input()

    def discard_input(self) -> None:
        self._io(self.port.reset_input_buffer, "clearing input")
        self.framer = UbxNmeaFramer()  # half a frame is garbage now
        self._backlog = []

    # -- waiting

    def wait_for(self, match: Callable[[UBXMessage], object], timeout_s: float | None = None) -> object:
        """The first non-None ``match`` of an arriving UBX message, or None when the time is up."""
        limit = self.timeout_s if timeout_s is None else timeout_s
        waited = 0.0
        while True:
            frames, self._backlog = self._backlog + self._frames(), []
            for i, frame in enumerate(frames):
                hit = match(frame.message)
                if hit is not None:
                    self._backlog = frames[i + 1:]
                    return hit
            if waited >= limit:
                return None
            self.sleep(self.poll_s)
            waited += self.poll_s

    def command(self, msg: UBXMessage, what: str) -> bool:
        """Send a configuration message until ACKed (True) or NAKed (False); silence raises NoData."""
        cls, mid = msg.msg_cls[0], msg.msg_id[0]
        for _ in range(self.tries):
            self.write(msg)
            answer = self.wait_for(lambda reply: _ack_of(reply, cls, mid))
            if answer is not None:
                if answer:
                    self.acknowledged.append(what)
                return bool(answer)
        raise NoData(
            f"GNSS receiver on {self.path} did not acknowledge {what} within {self.timeout_s:g} s "
            f"({self.tries} tries): wrong baud rate, or UBX input disabled on the receiver"
        )

    def poll(self, msg: UBXMessage, identity: str, tries: int | None = None) -> UBXMessage | None:
        for _ in range(self.tries if tries is None else tries):
            self.write(msg)
            reply = self.wait_for(lambda m: m if m.identity == identity else None)
            if reply is not None:
                return reply  # type: ignore[return-value]
        return None

    # -- configuration steps

    def configure(self, legacy: UBXMessage | None, keys: list[tuple[str, int]], what: str) -> None:
        """One setting, by the legacy message while the receiver takes it, else by configuration keys."""
        refusal = self.attempt(legacy, keys, what)
        if refusal:
            raise ProtocolError(f"GNSS receiver on {self.path} rejected {refusal}")

    def attempt(self, legacy: UBXMessage | None, keys: list[tuple[str, int]], what: str,
                optional: bool = False) -> str:
        """One setting as :meth:`configure` makes it; "" when acknowledged, else what was refused by which messages.

        An ``optional`` setting (one only some firmware has, such as raw observations) that both interfaces refuse
        leaves the interface as it was: a legacy receiver's NAK to a message it lacks says nothing of its keys."""
        before = self.interface
        if self.interface == "legacy" and legacy is not None:
            if self.command(legacy, f"UBX-{legacy.identity} ({what})"):
                return ""
            self.interface = "keys"
            refused = f"UBX-{legacy.identity} and "
        else:
            refused = ""
        valset = UBXMessage.config_set(SET_LAYER_RAM, TXN_NONE, keys)
        names = ", ".join(k.replace("_", "-") for k, _ in keys)
        if self.command(valset, f"UBX-CFG-VALSET {names}"):
            return ""
        if optional:
            self.interface = before
        return f"{what} (ACK-NAK to {refused}UBX-CFG-VALSET {names})"


def _name(msg: UBXMessage) -> str:
    return f"UBX-{msg.identity}"


def _port_of(link: object) -> tuple[serial.SerialBase, str]:
    """The pyserial port behind ``link``: a port itself, or a GnssReceiver's ``port``."""
    if isinstance(link, serial.SerialBase):
        return link, str(link.port)
    port = getattr(link, "port", None)
    if isinstance(port, serial.SerialBase):
        return port, str(getattr(link, "path", None) or port.port)
    raise TypeError(f"expected a pyserial port or a GnssReceiver, not {type(link).__name__}")


def _text(value: object) -> str:
    raw = value if isinstance(value, bytes | bytearray) else str(value).encode()
    return bytes(raw).split(b"\0", 1)[0].decode("ascii", "replace").strip()


def configure_receiver(
    link: object,
    setup: ReceiverSetup | None = None,
    *,
    sleep: Callable[[float], None] = time.sleep,
    reply_timeout_s: float = 1.0,
    tries: int = 2,
    poll_s: float = 0.02,
) -> SetupResult:
    """Configure the receiver on ``link`` (a pyserial port or a GnssReceiver) and confirm every step.

    Raises NoUbxAnswer (a NoData) when the receiver does not answer the first poll (wrong baud rate, not a
    u-blox: its ``nmea_sentences`` tells the two apart), NoData when it stops answering later, ProtocolError when
    it refuses a setting by both interfaces, BusError when the port fails.
    """
    setup = setup or ReceiverSetup()
    port, path = _port_of(link)
    s = _Session(port, path, sleep, reply_timeout_s, tries, poll_s)
    s.discard_input()  # an ACK left from before must not count

    version = s.poll(UBXMessage("MON", "MON-VER", POLL), "MON-VER")
    if version is None:
        heard = (f"though it sent {s.nmea_sentences} NMEA sentences: not a u-blox receiver, or UBX input disabled"
                 if s.nmea_sentences else "and sent no NMEA either: wrong baud rate, or nothing on the line")
        if not s.nmea_sentences and s.framer.nmea_without_checksum:
            heard = (f"and sent {s.framer.nmea_without_checksum} NMEA sentences without a checksum, which the logger "
                     "refuses (a receiver older than NMEA 2.3? turn its checksums on)")
        raise NoUbxAnswer(
            f"GNSS receiver on {path} did not answer UBX-MON-VER within {reply_timeout_s:g} s ({tries} tries) "
            f"at {port.baudrate} baud, {heard}", s.nmea_sentences, s.framer.nmea_without_checksum)
    extensions = tuple(_text(v) for k, v in sorted(vars(version).items()) if k.startswith("extension"))

    time_ref = _TIME_REF[setup.time_ref]
    s.configure(
        UBXMessage("CFG", "CFG-RATE", SET, measRate=setup.meas_period_ms, navRate=setup.nav_rate,
                   timeRef=time_ref),
        [("CFG_RATE_MEAS", setup.meas_period_ms), ("CFG_RATE_NAV", setup.nav_rate),
         ("CFG_RATE_TIMEREF", time_ref)],
        f"navigation rate {setup.meas_period_ms} ms x {setup.nav_rate} on {setup.time_ref.upper()} time",
    )
    for rate, names in ((1, setup.enable), (0, setup.disable)):
        for name in names:
            s.configure(*_message_rate(name, rate, setup.uart))

    baud = setup.baud if setup.baud is not None else int(port.baudrate)
    # The port this link reaches, as a legacy receiver reports it to a CFG-PRT poll without a port number: a USB,
    # SPI or I2C link has no speed to set (and UART1 may carry an RTK radio's corrections); a UART is changed in
    # place, its NMEA output left as its owner set it.
    link = _link_port(s) if s.interface == "legacy" else None
    if link is None or link[0] in _UART_NAME:
        nmea = setup.nmea_output and (link is None or bool(link[1][_PRT_OUT_PROTO] & _PRT_OUT_NMEA))
        uart = _UART_NAME[link[0]] if link is not None else setup.uart
        # Raised whenever the output needs it: the factory NMEA beside the logger's UBX messages fills most of a
        # 9600-baud line, and raw output at a slow rate would cost messages, ACKs too (raised before it is on).
        baud = max(baud, baud_for(replace(setup, nmea_output=nmea)))
        if baud != port.baudrate:
            _change_baud(s, replace(setup, baud=baud, uart=uart, nmea_output=nmea), link[1] if link else None,
                         extensions)
    raw, refusal = "off", ""
    if setup.raw_observations:
        for name in RAW_MESSAGES:
            refusal = s.attempt(*_message_rate(name, 1, setup.uart), optional=True)
            if refusal:
                break
        raw = "refused" if refusal else "on"
    return SetupResult(_text(version.swVersion), _text(version.hwVersion), extensions, s.interface,
                       int(port.baudrate), tuple(s.acknowledged), raw, refusal)


def _message_rate(name: str, rate: int, uart: str) -> tuple[UBXMessage, list[tuple[str, int]], str]:
    """The legacy CFG-MSG and the configuration key that set message ``name`` to every ``rate``-th solution."""
    cls, mid = message_id(name)
    # The three-byte form sets the rate on the port the command arrives at, whichever that is.
    # pyubx2 defines only the eight-byte (all ports) layout, hence the explicit payload.
    legacy = UBXMessage("CFG", "CFG-MSG", SET, payload=bytes((cls, mid, rate)))
    return legacy, [(_msgout_key(name, uart), rate)], f"{name} {'on' if rate else 'off'}"


def line_budget(setup: ReceiverSetup) -> float:
    """Bytes a second the receiver's output needs with ``setup``: its UBX messages at the solution rate, the factory
    NMEA set while NMEA output is on, and raw observations when asked for (the sizes are :data:`UBX_BYTES`'s)."""
    per_s = 1000.0 / (setup.meas_period_ms * setup.nav_rate)
    names = [*setup.enable, *(("RXM-RAWX",) if setup.raw_observations else ())]
    per_solution = sum(UBX_BYTES.get(n, 0) for n in names) + (NMEA_BYTES_PER_SOLUTION if setup.nmea_output else 0)
    return per_solution * per_s + (SFRBX_BYTES_PER_S if setup.raw_observations else 0)


def baud_for(setup: ReceiverSetup) -> int:
    """The slowest UART rate whose capacity (8N1: ten bits a byte), used to :data:`LINE_USE`, carries
    :func:`line_budget`; the fastest the receiver offers when none does."""
    need = line_budget(setup)
    return next((b for b in _BAUDS if b / 10 * LINE_USE >= need), _BAUDS[-1])


def _link_port(s: _Session) -> tuple[int, bytes] | None:
    """(port id, CFG-PRT payload) of the port the receiver hears the host on, from a CFG-PRT poll without a port
    number (as gpsd asks it); None when it does not answer."""
    reply = s.poll(UBXMessage("CFG", "CFG-PRT", POLL), "CFG-PRT")
    payload = getattr(reply, "payload", b"") or b""
    if len(payload) != 20:
        return None
    s.wait_for(lambda m: _ack_of(m, 0x06, 0x00))  # the poll's own ACK, so that a change's is not taken for it
    return payload[0], bytes(payload)


def _port_settings(setup: ReceiverSetup, baud: int, polled: bytes | None, extensions: tuple[str, ...]) -> UBXMessage:
    """The legacy CFG-PRT that changes the port's speed and nothing else it holds: the port's settings as the
    receiver reported them (its input protocols, RTCM corrections for an RTK receiver among them; TX-ready; the
    mode's bits) with the new speed, and NMEA output off where the set-up says so. A receiver that did not answer
    the poll gets the factory's: 8N1, UBX, NMEA and RTCM in (RTCM 3 from protocol 20), UBX and NMEA out."""
    port_id = _UART_PORT_ID[setup.uart]
    if polled is not None and polled[0] == port_id:
        out_mask = polled[_PRT_OUT_PROTO] if setup.nmea_output else polled[_PRT_OUT_PROTO] & ~_PRT_OUT_NMEA
        changed = (polled[:8] + int(baud).to_bytes(4, "little") + polled[12:_PRT_OUT_PROTO] + bytes((out_mask,))
                   + polled[_PRT_OUT_PROTO + 1:])
        return UBXMessage("CFG", "CFG-PRT", SET, payload=changed)
    return UBXMessage("CFG", "CFG-PRT", SET, portID=port_id, reserved2=0x10, charLen=3, parity=4, nStopBits=0,
                      baudRate=baud, inUBX=1, inNMEA=1, inRTCM=1, inRTCM3=int(_protocol(extensions) >= 20),
                      outUBX=1, outNMEA=int(setup.nmea_output))


def _protocol(extensions: tuple[str, ...]) -> float:
    """The protocol version MON-VER's extensions name (PROTVER=18.00), 0 when they do not."""
    for text in extensions:
        key, _, value = text.partition("=")
        if key.strip().upper() == "PROTVER":
            try:
                return float(value)
            except ValueError:
                return 0.0
    return 0.0


def _change_baud(s: _Session, setup: ReceiverSetup, polled: bytes | None = None,
                 extensions: tuple[str, ...] = ()) -> None:
    old, new = int(s.port.baudrate), int(setup.baud or 0)
    mon_ver = UBXMessage("MON", "MON-VER", POLL)
    attempts = 0
    while attempts < s.tries:
        attempts += 1
        if s.interface == "legacy":
            what = f"UBX-CFG-PRT ({setup.uart} at {new} baud)"
            s.write(_port_settings(setup, new, polled, extensions))
            # The ACK comes at the old rate; without it the receiver may still have switched.
            if s.wait_for(lambda m: _ack_of(m, 0x06, 0x00)) is False:
                s.interface = "keys"  # refused: the configuration keys may still do it
                attempts -= 1
                continue
        else:
            what = f"UBX-CFG-VALSET CFG-{setup.uart}-BAUDRATE={new}"
            valset = UBXMessage.config_set(SET_LAYER_RAM, TXN_NONE, [(f"CFG_{setup.uart}_BAUDRATE", new)])
            s.write(valset)
            # The change takes effect at once, so the ACK leaves at the new rate and is usually lost in
            # the switch; a refusal leaves at the old rate, so listen at the old rate for a NAK first.
            s.sleep(len(valset.serialize()) * 10 / old)
            if s.wait_for(lambda m: _ack_of(m, 0x06, 0x8A), timeout_s=s.poll_s * 3) is False:
                raise ProtocolError(f"GNSS receiver on {s.path} rejected {what} (ACK-NAK)")
        s.set_host_baud(new)
        s.sleep(s.poll_s)  # what was sent around the switch is garbage: let it pass, then drop it
        s.discard_input()
        if s.poll(mon_ver, "MON-VER", tries=1) is not None:
            s.acknowledged.append(what)
            return
        s.set_host_baud(old)  # it did not follow: talk at the old rate again and retry
    raise NoData(
        f"GNSS receiver on {s.path} did not answer at {new} baud after {s.tries} tries to switch it; "
        f"it still runs at {old} baud or has stopped answering"
    )


def _ack_of(msg: UBXMessage, cls: int, mid: int) -> bool | None:
    if msg.identity in ("ACK-ACK", "ACK-NAK") and (msg.clsID, msg.msgID) == (cls, mid):
        return msg.identity == "ACK-ACK"
    return None
