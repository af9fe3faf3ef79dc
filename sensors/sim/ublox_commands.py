"""The configuration side of the simulated u-blox receiver: the commands a host sends it and their answers.

The counterpart of :mod:`sensors.ublox_config` on the device side. :class:`UbxInputScanner` finds the UBX
frames in what the host sent; :class:`CommandInterpreter` holds the receiver's RAM configuration and
answers each frame as the firmware of its generation would:

- 8 (M8): the legacy UBX-CFG-MSG, -RATE and -PRT only; CFG-VALSET is unknown and NAKed;
- 9 (F9): both interfaces;
- 10 (M10): the configuration keys only; the legacy messages are NAKed.

Raw observations (RXM-RAWX, RXM-SFRBX) are taken only by firmware that has them (``raw``: the M8T's timing
firmware, the F9P's high-precision one, :data:`RECEIVER_MODELS`); a standard-precision M8N NAKs them, by either
interface.

A MON-VER poll is answered and never acknowledged; other CFG messages are NAKed as not modelled, so a
test notices; other input classes are ignored, as they have no ACK. Answers leave a few milliseconds after
the command and in command order. A legacy CFG-PRT switches the port only once its ACK has left at the old
rate; a CFG-VALSET takes effect at once, so its ACK already goes out at the new rate.

The interpreter does not send anything itself: it returns a :class:`Reply` and the receiver model queues
it on its UART (or drops it, when UBX output is off), so the timing of the line stays in one place.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from pyubx2 import GET, SET, UBX_MSGIDS, UBXMessage, UBXReader

from sensors.sim.gnss_time import NS_PER_S
from sensors.sim.profile import RECEIVER_MODELS as PROFILE_MODELS
from sensors.sim.uart_line import STANDARD_BAUDS
from sensors.sim.ublox_encode import MESSAGE_IDS

__all__ = [
    "DEFAULT_BAUD",
    "FIRMWARE",
    "RECEIVER_MODELS",
    "TIME_REF_OFFSET_S",
    "CommandInterpreter",
    "PortConfig",
    "RamConfig",
    "ReceiverModel",
    "Reply",
    "UbxInputScanner",
    "mon_ver",
]

FIRMWARE: dict[int, tuple[str, str, tuple[str, ...]]] = {  # MON-VER as these firmware releases report it
    8: ("ROM CORE 3.01 (107888)", "00080000",
        ("FWVER=SPG 3.01", "PROTVER=18.00", "GPS;GLO;GAL;BDS", "SBAS;IMES;QZSS")),
    9: ("EXT CORE 1.00 (61b2dd)", "00190000",
        ("ROM BASE 0x118B2060", "FWVER=HPG 1.13", "PROTVER=27.12", "MOD=ZED-F9P", "GPS;GLO;GAL;BDS", "QZSS")),
    10: ("ROM SPG 5.10 (7b202e)", "000A0000",
         ("ROM BASE 0x118B2060", "FWVER=SPG 5.10", "PROTVER=34.10", "MOD=NEO-M10", "GPS;GAL;GLO;BDS",
          "SBAS;QZSS")),
}


@dataclass(frozen=True, slots=True)
class ReceiverModel:
    """One u-blox product as the simulator plays it: its configuration interface, MON-VER and raw output."""

    generation: int
    firmware: tuple[str, str, tuple[str, ...]]
    raw: bool  # takes RXM-RAWX and RXM-SFRBX (timing and high-precision firmware)


RECEIVER_MODELS: dict[str, ReceiverModel] = {  # the names are sensors.sim.profile.RECEIVER_MODELS
    "NEO-M8N": ReceiverModel(8, FIRMWARE[8], raw=False),  # SPG: standard precision, no raw measurements
    "NEO-M8T": ReceiverModel(8, ("ROM CORE 3.01 (107888)", "00080000",
                                 ("FWVER=TIM 1.10", "PROTVER=22.00", "MOD=NEO-M8T-0", "GPS;GLO;GAL;BDS",
                                  "SBAS;IMES;QZSS")), raw=True),
    "ZED-F9P": ReceiverModel(9, FIRMWARE[9], raw=True),
}
assert tuple(RECEIVER_MODELS) == PROFILE_MODELS, "sensors.sim.profile names the same receiver models"
RAW_MESSAGE_IDS = (MESSAGE_IDS["RXM-RAWX"], MESSAGE_IDS["RXM-SFRBX"])
_RAW_KEY_PREFIXES = ("CFG_MSGOUT_UBX_RXM_RAWX_", "CFG_MSGOUT_UBX_RXM_SFRBX_")
DEFAULT_BAUD = {8: 9600, 9: 38400, 10: 38400}  # UART1 from the factory
# Offsets of the time scales CFG-RATE timeRef can align epochs to, from GPS time in whole seconds:
# UTC, GPS, GLONASS (UTC(SU) + 3 h), BeiDou (GPS - 14 s), Galileo (GPS). None: UTC-based, offset by the
# leap seconds the receiver's timeline holds.
TIME_REF_OFFSET_S: dict[int, int | None] = {0: None, 1: 0, 2: None, 3: -14, 4: 0}

_MSGOUT_KEYS = {  # configuration keys of the modelled messages on UART1 (u-blox 9/10 interface description)
    "CFG_MSGOUT_UBX_NAV_PVT_UART1": "NAV-PVT",
    "CFG_MSGOUT_UBX_NAV_TIMEGPS_UART1": "NAV-TIMEGPS",
    "CFG_MSGOUT_UBX_TIM_TP_UART1": "TIM-TP",
    "CFG_MSGOUT_NMEA_ID_GGA_UART1": "GGA",
    "CFG_MSGOUT_NMEA_ID_RMC_UART1": "RMC",
    "CFG_MSGOUT_NMEA_ID_GSA_UART1": "GSA",
    "CFG_MSGOUT_NMEA_ID_GLL_UART1": "GLL",
    "CFG_MSGOUT_NMEA_ID_GSV_UART1": "GSV",
    "CFG_MSGOUT_NMEA_ID_VTG_UART1": "VTG",
    "CFG_MSGOUT_UBX_RXM_RAWX_UART1": "RXM-RAWX",
    "CFG_MSGOUT_UBX_RXM_SFRBX_UART1": "RXM-SFRBX",
}
_PROTOCOL_KEYS = {  # UART1 protocol switches: key -> PortConfig field
    "CFG_UART1INPROT_UBX": "in_ubx",
    "CFG_UART1INPROT_NMEA": "in_nmea",
    "CFG_UART1OUTPROT_UBX": "out_ubx",
    "CFG_UART1OUTPROT_NMEA": "out_nmea",
}
_UBX_HDR = b"\xb5\x62"
_MAX_INPUT_PAYLOAD = 4096  # a longer length field is a stray 0xB5 0x62, not a frame
_CFG = 0x06
_CFG_PRT, _CFG_MSG, _CFG_RATE, _CFG_VALSET = 0x00, 0x01, 0x08, 0x8A
_MON_VER = (0x0A, 0x04)
_UART1 = 1
_OTHER_PORTS = (0, 2, 3, 4)  # I2C, UART2, USB, SPI: they exist, but nothing of them is modelled


@dataclass(slots=True)
class PortConfig:
    """UART1: its baud rate and which protocols it takes in and puts out."""

    baud: int
    in_ubx: bool = True
    in_nmea: bool = True
    out_ubx: bool = True
    out_nmea: bool = True
    # RTCM correction input, on from the factory (RTCM 2 on an M8, RTCM 3 on an F9): an RTK receiver's corrections
    # arrive on the UART, so a host that changes the port's speed must leave them on.
    in_rtcm: bool = True
    in_rtcm3: bool = False


@dataclass(slots=True)
class RamConfig:
    """The receiver's current (RAM) configuration; a power cycle restores the one it started with."""

    port: PortConfig
    meas_ms: int = 1000
    nav_rate: int = 1
    time_ref: int = 1  # GPS
    rates: dict[tuple[int, int], int] = field(default_factory=dict)  # (class, id) -> every n-th solution

    def copy(self) -> RamConfig:
        return RamConfig(replace(self.port), self.meas_ms, self.nav_rate, self.time_ref, dict(self.rates))


@dataclass(frozen=True, slots=True)
class Reply:
    """The firmware's answer to one command, due on the UART at ``ready_ns``.

    ``after`` runs once the last message has left (or at once, if UBX output is off): a legacy baud change
    waits for it. ``reschedule`` says the navigation rate was (re)applied, so the receiver must compute its
    next epoch again.
    """

    ready_ns: int
    messages: tuple[UBXMessage, ...]
    ack: bool | None = None  # ACK-ACK, ACK-NAK, or no acknowledgement (a MON-VER poll)
    after: Callable[[], None] | None = None
    reschedule: bool = False


def mon_ver(generation: int, firmware: tuple[str, str, tuple[str, ...]] | None = None) -> UBXMessage:
    """UBX-MON-VER as the firmware of ``generation`` (or the given ``firmware``) reports itself."""
    sw, hw, ext = firmware or FIRMWARE[generation]
    payload = sw.encode().ljust(30, b"\0") + hw.encode().ljust(10, b"\0")
    payload += b"".join(e.encode().ljust(30, b"\0") for e in ext)
    return UBXMessage("MON", "MON-VER", GET, payload=payload)


class UbxInputScanner:
    """Complete UBX frames with a valid checksum out of the host's bytes; anything else is dropped.

    Bytes arrive in arbitrary pieces, so an unfinished frame (or a lone 0xB5 that may start one) is kept
    for the next call. A frame that fails its checksum costs its two sync bytes only, so a frame starting
    inside it is still found.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def clear(self) -> None:
        self._buf.clear()

    def feed(self, data: bytes) -> list[bytes]:
        buf = self._buf
        buf += data
        frames: list[bytes] = []
        while True:
            start = buf.find(_UBX_HDR)
            if start < 0:
                del buf[:-1 if buf.endswith(b"\xb5") else len(buf)]
                return frames
            del buf[:start]
            if len(buf) < 8:
                return frames
            length = int.from_bytes(buf[4:6], "little")
            if length > _MAX_INPUT_PAYLOAD:
                del buf[:2]
                continue
            if len(buf) < 8 + length:
                return frames
            frame = bytes(buf[:8 + length])
            if frame[-2:] != _fletcher(frame[2:-2]):
                del buf[:2]
                continue
            del buf[:8 + length]
            frames.append(frame)


class CommandInterpreter:
    """The configuration interface of a u-blox receiver of ``generation``, and the RAM configuration it sets.

    ``rng`` draws the firmware's reply delay; it is the receiver's own generator for commands, so command
    timing never shifts any other random sequence of the model. ``raw`` says whether the firmware has raw
    observations (RXM-RAWX, RXM-SFRBX); ``firmware`` is what MON-VER reports (that of the generation by default).
    """

    def __init__(self, generation: int, startup: RamConfig, rng: np.random.Generator, *,
                 min_meas_period_ms: int, raw: bool = False,
                 firmware: tuple[str, str, tuple[str, ...]] | None = None, link_port: int = _UART1) -> None:
        if generation not in FIRMWARE:
            raise ValueError(f"generation must be one of {sorted(FIRMWARE)}, not {generation}")
        self.generation = generation
        self.raw = raw
        self.firmware = firmware or FIRMWARE[generation]
        self.startup = startup
        self.ram = startup.copy()
        self.min_meas_period_ms = min_meas_period_ms
        # The port the host is on (UART1, or USB: 3), whose settings RAM's ``port`` holds; the others exist and are
        # not modelled.
        self.link_port = link_port
        self._other_ports = tuple(p for p in (_UART1, *_OTHER_PORTS) if p != link_port)
        self._rng = rng
        self._last_reply_ns = 0

    def power_on(self) -> None:
        """Forget every command: RAM holds the configuration the receiver boots with."""
        self.ram = self.startup.copy()

    def handle(self, frame: bytes, now: int) -> Reply | None:
        """The answer to one checksum-valid UBX frame received at drive time ``now``; None if it has none."""
        cls, mid = frame[2], frame[3]
        payload = frame[6:-2]
        legacy = self.generation <= 9
        if (cls, mid) == _MON_VER and not payload:  # a poll: answered, never acknowledged
            return self._reply(now, mon_ver(self.generation, self.firmware))
        if cls != _CFG:
            return None  # other input classes (AID, MGA, RXM...) are not modelled and have no ACK
        if mid == _CFG_MSG and legacy:
            return self._cfg_msg(frame, payload, now)
        if mid == _CFG_RATE and legacy:
            return self._cfg_rate(frame, payload, now)
        if mid == _CFG_PRT and legacy:
            return self._cfg_prt(frame, payload, now)
        if mid == _CFG_VALSET and self.generation >= 9:
            return self._cfg_valset(frame, now)
        return self._ack(now, mid, False)

    # ------------------------------------------------------------------ answers

    def _reply(self, now: int, *messages: UBXMessage, ack: bool | None = None,
               after: Callable[[], None] | None = None, reschedule: bool = False) -> Reply:
        """Answers leave a few ms after the command, as the firmware takes that long, and in command order."""
        ready = now + round(self._rng.uniform(0.002, 0.015) * NS_PER_S)
        ready = self._last_reply_ns = max(ready, self._last_reply_ns)
        return Reply(ready, messages, ack, after, reschedule)

    def _ack(self, now: int, mid: int, ok: bool, *before: UBXMessage, after: Callable[[], None] | None = None,
             reschedule: bool = False) -> Reply:
        """ACK-ACK or ACK-NAK for CFG message ``mid``, after any poll answer in ``before``."""
        ack = UBXMessage("ACK", "ACK-ACK" if ok else "ACK-NAK", GET, clsID=_CFG, msgID=mid)
        return self._reply(now, *before, ack, ack=ok, after=after, reschedule=reschedule)

    # ------------------------------------------------------------------ legacy messages

    def _cfg_msg(self, frame: bytes, payload: bytes, now: int) -> Reply:
        if len(payload) == 2:  # poll the rates of one message
            key = (payload[0], payload[1])
            rate = self.ram.rates.get(key, 0)
            reply = UBXMessage("CFG", "CFG-MSG", GET, msgClass=key[0], msgID=key[1], rateUART1=rate)
            return self._ack(now, _CFG_MSG, True, reply)
        if len(payload) == 3:
            # The short form sets the port the command came in on. pyubx2 knows only the eight-byte
            # layout, so these three bytes are read directly.
            key, rate = (payload[0], payload[1]), payload[2]
        elif len(payload) == 8:
            msg = UBXReader.parse(frame, msgmode=SET)
            key, rate = (msg.msgClass, msg.msgID), msg.rateUART1
        else:
            return self._ack(now, _CFG_MSG, False)
        if bytes(key) not in UBX_MSGIDS and key[0] not in (0xF0, 0xF1):
            return self._ack(now, _CFG_MSG, False)  # no such message on this receiver
        if key in RAW_MESSAGE_IDS and not self.raw:
            return self._ack(now, _CFG_MSG, False)  # firmware without raw measurements
        self.ram.rates[key] = rate
        return self._ack(now, _CFG_MSG, True)

    def _cfg_rate(self, frame: bytes, payload: bytes, now: int) -> Reply:
        cfg = self.ram
        if not payload:
            reply = UBXMessage("CFG", "CFG-RATE", GET, measRate=cfg.meas_ms, navRate=cfg.nav_rate,
                               timeRef=cfg.time_ref)
            return self._ack(now, _CFG_RATE, True, reply)
        if len(payload) != 6:
            return self._ack(now, _CFG_RATE, False)
        msg = UBXReader.parse(frame, msgmode=SET)
        if not self._apply_rate(msg.measRate, msg.navRate, msg.timeRef):
            return self._ack(now, _CFG_RATE, False)
        return self._ack(now, _CFG_RATE, True, reschedule=True)

    def _apply_rate(self, meas_ms: int, nav_rate: int, time_ref: int) -> bool:
        """Set the navigation rate in RAM unless out of range: measRate below the firmware's floor, navRate
        above 127, an unknown time scale."""
        if meas_ms < self.min_meas_period_ms or not 1 <= nav_rate <= 127 or time_ref not in TIME_REF_OFFSET_S:
            return False
        cfg = self.ram
        cfg.meas_ms, cfg.nav_rate, cfg.time_ref = meas_ms, nav_rate, time_ref
        return True

    def _cfg_prt(self, frame: bytes, payload: bytes, now: int) -> Reply:
        port = self.ram.port
        usb = self.link_port != _UART1
        if len(payload) in (0, 1):
            port_id = payload[0] if payload else self.link_port  # no port number: the one the poll came in on
            if port_id != self.link_port:
                return self._ack(now, _CFG_PRT, port_id in self._other_ports)
            reply = UBXMessage(  # USB's layout has no mode or speed (reserved, zero)
                "CFG", "CFG-PRT", GET, portID=port_id, reserved2=0 if usb else 0x10, charLen=0 if usb else 3,
                parity=0 if usb else 4, nStopBits=0, baudRate=0 if usb else port.baud, inUBX=int(port.in_ubx),
                inNMEA=int(port.in_nmea), inRTCM=int(port.in_rtcm), inRTCM3=int(port.in_rtcm3),
                outUBX=int(port.out_ubx), outNMEA=int(port.out_nmea),
            )
            return self._ack(now, _CFG_PRT, True, reply)
        if len(payload) != 20:
            return self._ack(now, _CFG_PRT, False)
        msg = UBXReader.parse(frame, msgmode=SET)
        if msg.portID != self.link_port:
            return self._ack(now, _CFG_PRT, msg.portID in self._other_ports)
        if usb:  # no speed: only which protocols go in and out
            self.ram.port = PortConfig(port.baud, bool(msg.inUBX), bool(msg.inNMEA), bool(msg.outUBX),
                                       bool(msg.outNMEA), bool(msg.inRTCM), bool(msg.inRTCM3))
            return self._ack(now, _CFG_PRT, True)
        # Only 8N1 (charLen 3 = 8 bit, parity 10x = none, one stop bit) at a rate the UART offers.
        if msg.charLen != 3 or msg.parity not in (4, 5) or msg.nStopBits != 0 \
                or msg.baudRate not in STANDARD_BAUDS:
            return self._ack(now, _CFG_PRT, False)
        new = PortConfig(msg.baudRate, bool(msg.inUBX), bool(msg.inNMEA), bool(msg.outUBX), bool(msg.outNMEA),
                         bool(msg.inRTCM), bool(msg.inRTCM3))

        def switch() -> None:  # after the ACK has left at the old rate, on whatever RAM holds by then
            self.ram.port = new

        return self._ack(now, _CFG_PRT, True, after=switch)

    # ------------------------------------------------------------------ configuration keys

    def _cfg_valset(self, frame: bytes, now: int) -> Reply:
        """Apply a key list all or nothing: one key the model cannot honour NAKs the whole message."""
        try:
            msg = UBXReader.parse(frame, msgmode=SET)
        except Exception:  # a malformed key list: the receiver rejects the whole message
            return self._ack(now, _CFG_VALSET, False)
        if msg.version != 0:  # transactions are not modelled
            return self._ack(now, _CFG_VALSET, False)
        items = {k: v for k, v in vars(msg).items() if k.startswith("CFG_")}
        cfg = self.ram.copy()
        rate = [cfg.meas_ms, cfg.nav_rate, cfg.time_ref]
        for key, value in items.items():
            if key.startswith(_RAW_KEY_PREFIXES) and not self.raw:
                return self._ack(now, _CFG_VALSET, False)  # firmware without raw measurements: no such key
            if key in _MSGOUT_KEYS:
                cfg.rates[MESSAGE_IDS[_MSGOUT_KEYS[key]]] = int(value)
            elif key.startswith("CFG_MSGOUT_") and not key.startswith("CFG_0x"):
                continue  # a message the model does not produce, or another port
            elif key == "CFG_RATE_MEAS":
                rate[0] = int(value)
            elif key == "CFG_RATE_NAV":
                rate[1] = int(value)
            elif key == "CFG_RATE_TIMEREF":
                rate[2] = int(value)
            elif key == "CFG_UART1_BAUDRATE":
                if int(value) not in STANDARD_BAUDS:
                    return self._ack(now, _CFG_VALSET, False)
                cfg.port.baud = int(value)
            elif key in _PROTOCOL_KEYS:
                setattr(cfg.port, _PROTOCOL_KEYS[key], bool(value))
            else:  # an unknown or unmodelled key: the receiver rejects the whole message
                return self._ack(now, _CFG_VALSET, False)
        if not msg.ram:  # BBR or flash only: acknowledged, nothing changes now
            return self._ack(now, _CFG_VALSET, True)
        saved = self.ram
        self.ram = cfg
        if not self._apply_rate(rate[0], rate[1], rate[2]):
            self.ram = saved
            return self._ack(now, _CFG_VALSET, False)
        # Configuration keys take effect at once, the baud rate included: the ACK leaves at the new rate.
        return self._ack(now, _CFG_VALSET, True, reschedule=True)


def _fletcher(body: bytes) -> bytes:
    """The UBX checksum (8-bit Fletcher) over class, id, length and payload."""
    ck_a = ck_b = 0
    for b in body:
        ck_a = (ck_a + b) & 0xFF
        ck_b = (ck_b + ck_a) & 0xFF
    return bytes((ck_a, ck_b))
