"""An ELM327 v1.5 OBD-II adapter, and the clones of it, on the device end of a pty.

The adapter turns text commands into vehicle-bus requests and answers as text, and most of the trouble a
driver has with it is in that text: the echo, the blank line and ``>`` prompt after every answer, the
``SEARCHING...`` of its protocol search, the bus error messages, and the defaults it falls back to after
a reset. The model speaks that text as the ELM327 datasheet describes it, over the same pty a USB adapter
would appear as, and answers service 01 requests from the :class:`ObdEcu` models of the vehicle.

Clone behaviour is chosen by :class:`AdapterQuirks`; bus and adapter failures are injected with
:meth:`Elm327Model.inject` and :meth:`Elm327Model.reset` (a brown-out while cranking), unplugging with the
:class:`PtyPort` itself. Waits (reset, protocol search, ECU answer, ELM timeout) pass on the drive clock.

The check bytes of J1850 and K-line frames, shown with headers on, are computed here from the bus
standards rather than taken from the driver (:mod:`sensors.obd`), so a driver that checks them wrongly
fails against the model instead of agreeing with it.
"""

from __future__ import annotations

import enum
import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sensors.sim.clock import DriveClock
from sensors.sim.device_thread import DeviceThread
from sensors.sim.obd_ecu import ObdEcu
from sensors.sim.pty import PtyPort

PROTOCOL_NAMES = {
    "1": "SAE J1850 PWM",
    "2": "SAE J1850 VPW",
    "3": "ISO 9141-2",
    "4": "ISO 14230-4 (KWP 5BAUD)",
    "5": "ISO 14230-4 (KWP FAST)",
    "6": "ISO 15765-4 (CAN 11/500)",
    "7": "ISO 15765-4 (CAN 29/500)",
    "8": "ISO 15765-4 (CAN 11/250)",
    "9": "ISO 15765-4 (CAN 29/250)",
}
CAN_PROTOCOLS = {"6": 500, "7": 500, "8": 250, "9": 250}  # kbit/s
CAN_29BIT = {"7", "9"}
K_LINE_PROTOCOLS = {"3", "4", "5"}  # need a 'BUS INIT' (5-baud or fast init) before the first request
DEVICE_DESCRIPTION = "OBDII to RS232 Interpreter"
MAX_COMMAND_CHARS = 64
COMMANDS_KEPT = 2048  # command lines the model keeps for the tests to read (see ``commands``)
DEFAULT_TIMEOUT_HH = 0x32  # AT ST default: 0x32 x 4.096 ms = 205 ms


def _j1850_crc_table() -> tuple[int, ...]:
    """CRC-8 remainders of every byte for SAE J1850's generator x^8 + x^4 + x^3 + x^2 + 1 (0x1D), MSB first."""
    table = []
    for byte in range(256):
        remainder = byte
        for _ in range(8):
            remainder = (remainder << 1) ^ (0x11D if remainder & 0x80 else 0)
        table.append(remainder)
    return tuple(table)


_J1850_CRC_TABLE = _j1850_crc_table()


def j1850_crc(frame: bytes) -> int:
    """The check byte a J1850 (PWM or VPW) node appends: the CRC-8 above over header and data, the register
    preset to all ones and the result sent complemented (SAE J1850 section 5.4)."""
    crc = 0xFF
    for byte in frame:
        crc = _J1850_CRC_TABLE[crc ^ byte]
    return crc ^ 0xFF


def kline_checksum(frame: bytes) -> int:
    """The check byte of an ISO 9141-2 or ISO 14230-4 message: header and data bytes summed modulo 256."""
    total = 0
    for byte in frame:
        total = (total + byte) % 256
    return total


class ElmFault(enum.Enum):
    """What an injected fault does to the next request: the adapter prints the message instead of the
    ECUs' answer (the value is the text it prints), or damages the answer (bit error, garbage)."""

    NO_DATA = "NO DATA"
    STOPPED = "STOPPED"
    CAN_ERROR = "CAN ERROR"
    BUS_ERROR = "BUS ERROR"
    UNABLE_TO_CONNECT = "UNABLE TO CONNECT"
    BUS_INIT_ERROR = "BUS INIT: ...ERROR"
    MISUNDERSTOOD = "?"  # the request arrived garbled and the adapter did not recognise it
    BIT_ERROR = "bit error"  # the answer's last data byte arrives with a bit flipped
    DATA_ERROR_FLAGGED = "<DATA ERROR"  # the answer's data line, flagged at its end as received with an error
    LP_ALERT = "LP ALERT"  # the adapter is about to go to low power
    GARBAGE = "garbage"


@dataclass(frozen=True, slots=True)
class AdapterQuirks:
    """How a particular adapter departs from the datasheet.

    ``echo_stuck``: says OK to AT E0 but keeps echoing (common in v1.5 clones). ``nul_bytes``: sends NUL
    characters around its answers. ``crlf``: ends lines with CR LF whatever AT L says.
    ``linefeeds_default``: the state of the LF-mode pin at power-up (AT L after a reset).
    ``missing_commands``: AT commands the firmware lacks and answers with '?', named by the start of what
    follows "AT" (``{"AT", "ST"}`` for a clone without adaptive timing and timeout setting).
    """

    banner: str = "ELM327 v1.5"
    echo_stuck: bool = False
    nul_bytes: bool = False
    crlf: bool = False
    linefeeds_default: bool = False
    missing_commands: frozenset[str] = frozenset()


@dataclass(slots=True)
class _Settings:
    """The volatile settings AT Z, AT WS, AT D and a power-up put back to their defaults."""

    echo: bool = True
    linefeeds: bool = False
    spaces: bool = True
    headers: bool = False
    adaptive_timing: int = 1
    timeout_hh: int = DEFAULT_TIMEOUT_HH


class Elm327Model(DeviceThread):
    """The adapter: a thread that reads command lines from the pty and writes the ELM327's answers.

    ``vehicle_protocol`` is the bus the car has (the AT SP digit it would be found as). The delays are
    drive time: ``search_delay_s`` for a protocol search or K-line init, ``reset_delay_s`` for AT Z,
    ``ecu_delay_s`` for the ECUs to answer a request once connected, ``slow_commands`` for the answer to given
    commands (a slow clone). ``seed`` drives the battery
    voltage noise and the bytes of injected garbage.
    """

    thread_name = "sim-elm327"

    def __init__(
        self,
        port: PtyPort,
        ecus: Sequence[ObdEcu],
        clock: DriveClock,
        *,
        vehicle_protocol: str = "6",
        quirks: AdapterQuirks | None = None,
        search_delay_s: float = 1.5,
        reset_delay_s: float = 0.5,
        ecu_delay_s: float = 0.02,
        slow_commands: dict[str, float] | None = None,
        seed: int | np.random.Generator = 0,
    ) -> None:
        if vehicle_protocol not in PROTOCOL_NAMES:
            raise ValueError(f"vehicle protocol must be one of 1..9, not {vehicle_protocol!r}")
        self.port = port
        self.ecus = list(ecus)
        self.clock = clock
        self.vehicle_protocol = vehicle_protocol
        self.quirks = quirks or AdapterQuirks()
        self.search_delay_s = search_delay_s
        self.reset_delay_s = reset_delay_s
        self.ecu_delay_s = ecu_delay_s
        # Commands (spaces removed, upper case) answered only after this much drive time: a slow clone or Bluetooth
        # bridge (ELM327-emulator itself takes 0.5 s over AT DPN), whose answer may come after the host gave up.
        self.slow_commands = dict(slow_commands or {})
        self._rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        self._lock = threading.RLock()
        self._faults: deque[ElmFault] = deque()
        super().__init__()
        # Kept in the adapter's EEPROM: AT SP survives a reset, the other settings do not.
        self._stored_protocol = "0"
        self._auto = True
        self._settings = self._defaults()
        self._connected: str | None = None
        self._last_command = ""
        # The command lines received, spaces removed, upper case: the last COMMANDS_KEPT to 2 x COMMANDS_KEPT of them
        # (speed is asked twice a second: an unbounded list grew ~3 MB over an eight-hour simulated drive).
        self.commands: list[str] = []

    # ----------------------------------------------------------------- control from the test side

    def inject(self, fault: ElmFault, count: int = 1) -> None:
        """Answer the next ``count`` OBD requests with ``fault`` instead of the ECUs' data."""
        with self._lock:
            self._faults.extend([fault] * count)

    def reset(self, announce: bool = True) -> None:
        """A power glitch: settings back to defaults, the link to the vehicle lost, the banner printed.

        ``announce=False`` loses the banner on the line (the glitch also hit the serial bridge), so the
        only trace of the reset is the adapter's default settings.
        """
        with self._lock:
            self._settings = self._defaults()
            self._connected = None
            if announce:
                self._send("\r\r" + self.quirks.banner + "\r\r>")

    def line_noise(self, nbytes: int = 16) -> None:
        """Unsolicited junk on the serial line, as a loose connector or a baud glitch produces it."""
        with self._lock:
            self.port.write(self._junk(nbytes) + b"\r")

    @property
    def connected_protocol(self) -> str | None:
        return self._connected

    # ----------------------------------------------------------------- the adapter

    def _defaults(self) -> _Settings:
        return _Settings(linefeeds=self.quirks.linefeeds_default)

    def _run(self) -> None:
        line = bytearray()
        while not self.stopping.is_set():
            if not self.port.present:
                line.clear()
                self.stopping.wait(0.01)
                continue
            for byte in self.port.read(timeout_s=0.02):
                if byte == 0x0D:
                    self._handle(line.decode("ascii", "replace"))
                    line.clear()
                elif byte >= 0x20 and byte != 0x7F:  # the ELM327 ignores LF, NUL and other controls
                    line.append(byte)

    def _handle(self, raw: str) -> None:
        with self._lock:
            command = raw.replace(" ", "").upper()
            if self._settings.echo or self.quirks.echo_stuck:
                self._send(raw + "\r")
            if not command:
                command = self._last_command  # a bare CR repeats the last command
                if not command:
                    self._send(">")
                    return
            self.commands.append(command)
            if len(self.commands) > 2 * COMMANDS_KEPT:
                del self.commands[:-COMMANDS_KEPT]
            if command in self.slow_commands:
                self.clock.sleep(self.slow_commands[command])
            self._last_command = command
            if len(command) > MAX_COMMAND_CHARS:
                self._answer(["?"])
            elif command.startswith("AT"):
                self._at(command[2:])
            elif _is_obd_request(command):
                self._obd(bytes.fromhex(command))
            else:
                self._answer(["?"])

    def _at(self, arg: str) -> None:
        s = self._settings
        flags = {"E": "echo", "L": "linefeeds", "S": "spaces", "H": "headers"}
        if any(arg.startswith(name) for name in self.quirks.missing_commands):
            self._answer(["?"])
        elif arg in ("Z", "WS"):
            if arg == "Z":
                self.clock.sleep(self.reset_delay_s)  # the LED test
            self._settings = self._defaults()
            self._connected = None
            self._send("\r\r" + self.quirks.banner + "\r\r>")
        elif arg == "D":
            self._settings = self._defaults()
            self._answer(["OK"])
        elif arg == "I":
            self._answer([self.quirks.banner])
        elif arg == "@1":
            self._answer([DEVICE_DESCRIPTION])
        elif arg == "RV":
            self._answer([f"{self._battery_volts():.1f}V"])
        elif len(arg) == 2 and arg[0] in flags and arg[1] in "01":
            setattr(s, flags[arg[0]], arg[1] == "1")
            self._answer(["OK"])
        elif arg == "M0" or arg == "M1":
            self._answer(["OK"])
        elif len(arg) == 3 and arg.startswith("AT") and arg[2] in "012":
            s.adaptive_timing = int(arg[2])
            self._answer(["OK"])
        elif len(arg) == 4 and arg.startswith("ST") and _is_hex(arg[2:]):
            s.timeout_hh = int(arg[2:], 16) or DEFAULT_TIMEOUT_HH  # AT ST 00 restores the default
            self._answer(["OK"])
        elif arg[:2] in ("SP", "TP") and self._set_protocol(arg[2:]):
            self._answer(["OK"])
        elif arg == "DP":
            name = PROTOCOL_NAMES.get(self._connected or self._stored_protocol, "")
            self._answer([("AUTO, " + name if name else "AUTO") if self._auto else name])
        elif arg == "DPN":
            if self._auto:
                self._answer(["A" + self._connected if self._connected else "0"])
            else:
                self._answer([self._stored_protocol])
        elif arg == "PC":
            self._connected = None
            self._answer(["OK"])
        else:
            self._answer(["?"])

    def _set_protocol(self, arg: str) -> bool:
        auto = arg.startswith("A") and len(arg) == 2
        number = arg[1:] if auto else arg
        if number != "0" and number not in PROTOCOL_NAMES:
            return False
        self._stored_protocol = number
        self._auto = auto or number == "0"
        self._connected = None
        return True

    def _obd(self, request: bytes) -> None:
        fault = self._faults.popleft() if self._faults else None
        if fault is not None and fault not in (ElmFault.BIT_ERROR, ElmFault.DATA_ERROR_FLAGGED):
            self._fail(fault)
            return
        flip_bit = fault is ElmFault.BIT_ERROR
        lines: list[str] = []
        if self._connected is None:
            protocol = self._connect()
            if protocol is None:
                return
            lines = self._ecu_lines(request, protocol, flip_bit)
            if not lines:  # the bus is up (the ECUs answered 01 00) but nobody has this PID
                lines = ["NO DATA"]
        else:
            self.clock.sleep(self.ecu_delay_s)
            lines = self._ecu_lines(request, self._connected, flip_bit)
            if not lines:
                self.clock.sleep(self._settings.timeout_hh * 4.096e-3)  # the ELM waits out its timeout
                lines = ["NO DATA"]
        if fault is ElmFault.DATA_ERROR_FLAGGED and lines:
            lines[-1] += f" {fault.value}"
        self._answer(lines)

    def _connect(self) -> str | None:
        """The first request after a reset or AT SP: search or initialise the vehicle bus."""
        vehicle = self.vehicle_protocol
        if self._auto:
            self._send("SEARCHING...\r")
            self.clock.sleep(self.search_delay_s)
            if any(ecu.on_the_bus(self.clock.now_ns()) for ecu in self.ecus):
                self._connected = vehicle
                return vehicle
            self._answer(["UNABLE TO CONNECT"])
            return None
        wanted = self._stored_protocol
        if wanted in K_LINE_PROTOCOLS:
            self._send("BUS INIT: ...")
            self.clock.sleep(self.search_delay_s)
            if wanted == vehicle and any(ecu.on_the_bus(self.clock.now_ns()) for ecu in self.ecus):
                self._send("OK\r")
                self._connected = vehicle
                return vehicle
            self._answer(["ERROR"])
            return None
        if wanted == vehicle:
            self._connected = vehicle
            return vehicle
        if wanted in CAN_PROTOCOLS and vehicle in CAN_PROTOCOLS and CAN_PROTOCOLS[wanted] == CAN_PROTOCOLS[vehicle]:
            self._answer(["NO DATA"])  # right bit rate, wrong identifier length: nobody answers
        elif wanted in CAN_PROTOCOLS:
            self._answer(["CAN ERROR"])  # wrong bit rate: nobody acknowledges our frames
        else:
            self._answer(["NO DATA"])
        return None

    def _fail(self, fault: ElmFault) -> None:
        if fault is ElmFault.GARBAGE:
            self.port.write(self._junk(int(self._rng.integers(8, 40))))
            self._answer([])
            return
        if fault in (ElmFault.UNABLE_TO_CONNECT, ElmFault.BUS_INIT_ERROR):
            self._connected = None
        if fault is ElmFault.UNABLE_TO_CONNECT and self._auto:
            self._send("SEARCHING...\r")
        self._answer([fault.value])

    def _ecu_lines(self, request: bytes, protocol: str, flip_bit: bool = False) -> list[str]:
        t_ns = self.clock.now_ns()
        lines = []
        for ecu in self.ecus:
            payload = ecu.answer(request, t_ns)
            if payload is not None:
                lines.append(self._format(ecu, payload, protocol, flip_bit))
        return lines

    def _format(self, ecu: ObdEcu, payload: bytes, protocol: str, flip_bit: bool = False) -> str:
        """One answer line as the ELM327 prints it with the current AT H and AT S settings.

        ``flip_bit`` damages the last data byte after the check byte was computed, as a bit error on the
        serial line to the logger would (the ELM327 flags checksum errors on the vehicle bus itself).
        """
        sep = " " if self._settings.spaces else ""
        prefix = ""
        check: bytes = b""
        if not self._settings.headers:
            frame = payload
        elif protocol in CAN_29BIT:
            frame = bytes([0x18, 0xDA, 0xF1, ecu.address, len(payload)]) + payload
        elif protocol in CAN_PROTOCOLS:
            prefix = f"{ecu.response_id_11:03X}" + sep
            frame = bytes([len(payload)]) + payload
        elif protocol in ("1", "2"):
            frame = bytes([0x41 if protocol == "1" else 0x48, 0x6B, ecu.address]) + payload
            check = bytes([j1850_crc(frame)])
        elif protocol == "3":
            frame = bytes([0x48, 0x6B, ecu.address]) + payload
            check = bytes([kline_checksum(frame)])
        else:
            frame = bytes([0x80 | len(payload), 0xF1, ecu.address]) + payload
            check = bytes([kline_checksum(frame)])
        if flip_bit:
            frame = frame[:-1] + bytes([frame[-1] ^ 0x40])
        return prefix + _hex(frame + check, sep)

    def _answer(self, lines: list[str]) -> None:
        self._send("".join(line + "\r" for line in lines) + "\r>")

    def _send(self, text: str) -> None:
        eol = "\r\n" if self._settings.linefeeds or self.quirks.crlf else "\r"
        data = text.replace("\r", eol).encode("ascii")
        if self.quirks.nul_bytes:
            data = b"\x00" + data.replace(b">", b"\x00>")
        self.port.write(data)

    def _junk(self, nbytes: int) -> bytes:
        # High-bit bytes: what a wrong baud rate or a noisy line turns ASCII into. No '>' or CR among them.
        return bytes(self._rng.integers(0x80, 0x100, size=nbytes, dtype=np.uint8).tolist())

    def _battery_volts(self) -> float:
        running = any(ecu.powered(self.clock.now_ns()) for ecu in self.ecus)
        nominal = 14.2 if running else 12.5  # alternator charging vs a resting battery
        return nominal + float(self._rng.normal(0.0, 0.05))


def _is_hex(text: str) -> bool:
    return bool(text) and all(c in "0123456789ABCDEF" for c in text)


def _is_obd_request(command: str) -> bool:
    return _is_hex(command) and len(command) % 2 == 0 and 2 <= len(command) <= 16


def _hex(data: bytes, sep: str) -> str:
    # The ELM327 follows every byte with a space when spaces are on, the last one included.
    return "".join(f"{b:02X}{sep}" for b in data)
