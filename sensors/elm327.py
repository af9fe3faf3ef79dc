"""Vehicle speed through an ELM327 OBD-II adapter on a serial port (USB, Bluetooth SPP, UART).

The ELM327 is a text protocol with a long tail of adapter quirks, and the clones in the field each have a
few of them: echo that ATE0 does not turn off, NUL bytes, CR LF line ends, ``SEARCHING...`` before the
first answer, and a silent reset to defaults when the supply dips while cranking. This driver reads every
answer up to the ``>`` prompt, cleans it, strips whatever echo comes back, and decodes the ``41 0D xx``
line of the engine ECU, so none of that leaks into the logger. It notices a reset (the banner again, or
echo from an adapter that had turned it off) and initialises the adapter again before answering.

Waiting is done by pyserial timeouts measured as silence on the line, not by a clock: the adapter speaks
while it works (``SEARCHING...``, ``BUS INIT: ...``) and goes quiet only when it is stuck.
"""

from __future__ import annotations

import errno
import os
import re
import time

import serial

from sensors.errors import BusError, DeviceNotFound, NoData, ProtocolError, SensorError
from sensors.obd import (
    ELM_SPEED_COMMAND,
    ENGINE_ADDRESS,
    ENGINE_RESPONSE_ID_11,
    RESPONSE_BASE_29,
    ObdSpeed,
    SpeedDriver,
    decode_speed_payload,
    isotp_single_frame_payload,
    j1850_crc,
    kline_checksum,
)

PROMPT = b">"
BANNER = re.compile(r"ELM32\d\s*v?[\w.]*", re.IGNORECASE)
MAX_ANSWER_BYTES = 4096  # far more than any answer to 010D; beyond it the line is spewing junk
# AT SP digits: 0 searches, 1..9 are the OBD-II buses, B and C user-defined CAN; "A6" searches starting
# with 6. Protocol A is SAE J1939 (trucks), which has no PID 0x0D.
PROTOCOLS = frozenset("0123456789BC") | {f"A{n}" for n in "123456789BC"}
ST_UNIT_MS = 4.096  # AT ST counts in units of 4.096 ms

# Link-layer families: how a header-on answer line is laid out.
CAN_11 = "can11"
CAN_29 = "can29"
J1850 = "j1850"  # 3 header bytes, data, CRC-8
K_LINE = "k-line"  # ISO 9141-2 / ISO 14230-4: 3 header bytes, data, sum checksum
FAMILY_OF_PROTOCOL = {"1": J1850, "2": J1850, "3": K_LINE, "4": K_LINE, "5": K_LINE,
                      "6": CAN_11, "7": CAN_29, "8": CAN_11, "9": CAN_29}

# A disturbed answer (a bus error, a check byte that fails, '?' for a request garbled on the serial line) is one
# failed sample while the adapter answers: a reset and a new protocol search cost seconds of speed (4 s measured).
# Only this many in a row make it the adapter's or the bus's fault, which the sampler answers by setting it up again.
FAILED_ANSWERS_IN_A_ROW = 3

# Messages the ELM327 prints instead of data; each maps to what the logger should make of it.
FLAGGED_LINE_ENDS = ("<DATA ERROR", "<RX ERROR")  # at the end of the data line they flag
VEHICLE_BUS_FAULTS = ("BUS ERROR", "BUS BUSY", "FB ERROR", "DATA ERROR", "RX ERROR", "BUFFER FULL", "ACT ALERT")
# What the adapter prints while it searches for the vehicle's protocol or initialises a K-line bus (seconds)
SEARCH_MARKS = ("SEARCHING", "BUS INIT")
_SEARCH_MARKS_BYTES = tuple(mark.encode() for mark in SEARCH_MARKS)


class _OneOff(Exception):
    """A disturbed answer: ``error`` is what it means once it is no longer a one-off."""

    def __init__(self, error: SensorError) -> None:
        super().__init__(str(error))
        self.error = error


class _NoPrompt(Exception):
    """The line went quiet before the adapter's prompt came."""


class Elm327(SpeedDriver):
    """One ELM327 adapter: ``open()`` resets and sets it up, ``read()`` asks the vehicle for its speed.

    ``protocol`` is the AT SP digit ("0" searches, "6" is CAN 11-bit 500 kbit/s, "A6" searches starting
    with 6). ``headers`` shows who answered so the engine ECU can be preferred when several do.
    ``timeout_s`` is how long the adapter may stay silent before it counts as gone; ``search_timeout_s``
    replaces it while the adapter searches or initialises the vehicle bus, which takes seconds.
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 38400,
        protocol: str = "0",
        headers: bool = True,
        spaces: bool = False,
        adaptive_timing: int | None = 1,
        obd_timeout_ms: float | None = None,
        timeout_s: float = 1.0,
        search_timeout_s: float = 15.0,
        reset_timeout_s: float = 3.0,
    ) -> None:
        protocol = protocol.upper()
        if protocol not in PROTOCOLS:
            raise ValueError(f"ELM327 protocol must be 0..9, B, C or A1..AC (AT SP), not {protocol!r}")
        if adaptive_timing not in (None, 0, 1, 2):
            raise ValueError(f"ELM327 adaptive timing is 0, 1 or 2 (AT AT), not {adaptive_timing!r}")
        if obd_timeout_ms is not None and not 0 < obd_timeout_ms <= 255 * ST_UNIT_MS:
            raise ValueError(f"ELM327 timeout must be in (0, {255 * ST_UNIT_MS:.0f}] ms, not {obd_timeout_ms}")
        self.port = port
        self.baudrate = baudrate
        self.protocol = protocol
        self.headers = headers
        self.spaces = spaces
        self.adaptive_timing = adaptive_timing
        self.obd_timeout_ms = obd_timeout_ms
        self.timeout_s = timeout_s
        self.search_timeout_s = max(search_timeout_s, timeout_s)
        self.reset_timeout_s = reset_timeout_s
        self.version: str | None = None  # the banner, e.g. "ELM327 v1.5"
        self.protocol_number: str | None = None  # the vehicle protocol the adapter settled on (AT DPN)
        self.echo_stuck = False  # the adapter ignores ATE0, as many clones do
        self.resets_seen = 0  # adapter resets noticed during reads (and recovered from)
        self.connect_problem: str | None = None  # why the vehicle did not answer during set-up, if it did not
        self._failed_answers = 0  # disturbed answers in a row (FAILED_ANSWERS_IN_A_ROW)
        self._speed_answer_s: float | None = None  # how long the last answered speed request took
        self._serial: serial.Serial | None = None
        self._rx = bytearray()
        self._owed = False  # a command was given up on: its answer may still come (_command)
        self._family: str | None = None
        self._first_request = True

    # ----------------------------------------------------------------- life cycle

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def open(self) -> None:
        """Open the port and initialise the adapter; a failed start leaves the port closed."""
        if self._serial is not None:
            return
        if not os.path.exists(self.port):
            raise DeviceNotFound(f"serial port {self.port} does not exist: is the OBD adapter plugged in?")
        try:
            self._serial = serial.Serial(self.port, self.baudrate, timeout=self.timeout_s,
                                         write_timeout=self.timeout_s, exclusive=True)
        except (serial.SerialException, OSError) as e:
            code = getattr(e, "errno", None)
            if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
                raise DeviceNotFound(f"serial port {self.port} is gone: is the OBD adapter plugged in?") from e
            if code in (errno.EACCES, errno.EPERM):
                raise BusError(f"no permission to open {self.port}: add the logger's user to group dialout") from e
            raise BusError(f"cannot open {self.port}: {e}") from e
        self._rx.clear()
        try:
            self._initialise()
        except SensorError:
            self.close()
            raise
        self._find_vehicle()

    def _find_vehicle(self) -> None:
        """Ask for the speed once during set-up, so that the adapter's protocol search (seconds, with
        SEARCHING...) happens now and not in the sampler's first period. The answer itself is not kept; a
        vehicle that does not answer yet (ignition off) is left for the reads to report."""
        try:
            self.read()
        except (NoData, BusError, ProtocolError) as exc:
            if self._serial is None:
                raise
            self.connect_problem = str(exc)
        else:
            self.connect_problem = None

    def incidents(self) -> dict[str, int]:
        return {"ELM327 reset itself and was set up again": self.resets_seen}

    def close(self) -> None:
        ser, self._serial = self._serial, None
        self._rx.clear()
        self._owed = False
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass  # the port is already gone; closing it cannot fail any further

    def __enter__(self) -> Elm327:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- reading

    def read(self) -> ObdSpeed:
        """Ask for PID 0x0D once and decode the answer; opens the port first if it is closed."""
        if self._serial is None:
            self.open()
        if self._take_unsolicited():
            self._recover_from_reset()
        self.answered_window_ns = None
        lines, echoed = self._timed_command(ELM_SPEED_COMMAND, long_wait=self._first_request)
        if self._lost_settings(lines, echoed):
            self._recover_from_reset()
            lines, echoed = self._timed_command(ELM_SPEED_COMMAND, long_wait=True)
            sign = self._lost_settings(lines, echoed)
            if sign == "headers":
                raise ProtocolError(f"ELM327 on {self.port} does not show headers after ATH1: "
                                    "run it with headers off")
            if sign:
                raise BusError(f"ELM327 on {self.port} resets again right after set-up: check its power supply")
        speed = self._checked_decode(lines)
        self._first_request = False
        if self.clock is not None and any(line.upper().startswith(SEARCH_MARKS) for line in lines):
            # The request began a protocol search or a bus initialisation (seconds): when in it the ECU was asked is
            # not known, so neither is its answer's time. Asked again, at once, for a speed whose time is.
            # Given the search's wait: a slow adapter's answer (a Bluetooth bridge's 1.2 s) is then read, and its time
            # tells the timeout's message what to change.
            lines, echoed = self._timed_command(ELM_SPEED_COMMAND, long_wait=True)
            if self._lost_settings(lines, echoed):
                raise BusError(f"ELM327 on {self.port} reset again right after a protocol search: check its power "
                               "supply")
            speed = self._checked_decode(lines)
        return speed

    def _checked_decode(self, lines: list[str]) -> ObdSpeed:
        """:meth:`_decode`, a disturbed answer taken as one failed sample (NoData: the adapter stays as it is) until
        FAILED_ANSWERS_IN_A_ROW of them come in a row."""
        try:
            speed = self._decode(lines)
        except _OneOff as one_off:
            self._failed_answers += 1
            n = self._failed_answers
            if n >= FAILED_ANSWERS_IN_A_ROW:
                raise one_off.error from None
            raise NoData(f"{one_off.error} ({n} of {FAILED_ANSWERS_IN_A_ROW} in a row before the adapter is set up "
                         "again)") from None
        except SensorError:
            self._failed_answers = 0  # an answer of another kind (NO DATA): the disturbed ones are no longer in a row
            raise
        self._failed_answers = 0
        return speed

    # ----------------------------------------------------------------- set-up

    def _initialise(self) -> None:
        self.version = self._reset()
        self.echo_stuck = False
        self._at("ATE0")
        _, echoed = self._at("ATL0")
        self.echo_stuck = echoed
        self._at(f"ATS{int(self.spaces)}", optional=True)
        self._at(f"ATH{int(self.headers)}")
        self._at(f"ATSP{self.protocol}")
        if self.adaptive_timing is not None:
            self._at(f"ATAT{self.adaptive_timing}", optional=True)
        if self.obd_timeout_ms is not None:
            hh = max(1, min(255, round(self.obd_timeout_ms / ST_UNIT_MS)))
            self._at(f"ATST{hh:02X}", optional=True)
        self._family = FAMILY_OF_PROTOCOL.get(self.protocol)
        self.protocol_number = self.protocol if self._family else None
        self._first_request = True

    def _reset(self) -> str:
        """AT Z, and wait for the banner: answers to anything sent before the reset are skipped."""
        self._owed = False
        heard = ""
        for _ in range(2):
            self._write("ATZ")
            received = 0
            try:
                while received < MAX_ANSWER_BYTES:
                    answer = self._read_answer(self.reset_timeout_s)
                    received += len(answer)
                    text = answer.decode("latin-1")
                    match = BANNER.search(text)
                    if match:
                        return match.group(0).strip()
                    heard = " / ".join(_lines(text)) or heard
            except _NoPrompt:
                heard = " / ".join(_lines(self._rx.decode("latin-1"))) or heard
                self._rx.clear()
                continue
        what = f"answered {heard[:40]!r}" if heard else "is silent"
        raise DeviceNotFound(f"no ELM327 on {self.port} at {self.baudrate} baud: the device {what} after ATZ")

    def _recover_from_reset(self) -> None:
        self.resets_seen += 1
        self._initialise()

    def _at(self, command: str, optional: bool = False) -> tuple[list[str], bool]:
        lines, echoed = self._command(command)
        if "OK" in lines:
            return lines, echoed
        if optional and "?" in lines:
            return lines, echoed  # a clone without this command: the driver copes without it
        got = " / ".join(lines) or "nothing"
        raise ProtocolError(f"ELM327 on {self.port} answered {command} with {got!r} instead of OK")

    # ----------------------------------------------------------------- the serial line

    def _timed_command(self, command: str, long_wait: bool = False) -> tuple[list[str], bool]:
        """:meth:`_command`, its request and answer timed by the caller's clock (``answered_window_ns``): a speed
        read after the adapter was set up again inside the same read (ATZ, the set-up, a protocol search: seconds)
        was stamped at the middle of all of it, 1.5-2.5 s before the ECU answered."""
        if self.clock is None:
            return self._command(command, long_wait)
        t0 = self.clock()
        answer = self._command(command, long_wait)
        self.answered_window_ns = (t0, self.clock())
        return answer

    def _command(self, command: str, long_wait: bool = False) -> tuple[list[str], bool]:
        """Send one command; the answer's lines without the echo, and whether an echo came back.

        A command given up on (no prompt in time) may still be answered: a slow clone or Bluetooth bridge took
        1.1 s over AT DPN. That late answer is waited for, once, and thrown away before the next command; read as
        the next one's, it put every answer one behind for good (the speed taken for AT DPN's, 'A6' for the
        speed)."""
        if self._owed:
            self._owed = False
            try:
                self._read_answer(self.timeout_s)
            except _NoPrompt:
                self._rx.clear()  # it never came: what there is belongs to no command
        self._write(command)
        asked = time.monotonic()  # a wait's length, not a time stamp
        try:
            answer = self._read_answer(self.timeout_s, self.search_timeout_s if long_wait else None)
        except _NoPrompt as e:
            self._owed = True
            slow = ""
            if command == ELM_SPEED_COMMAND and self._speed_answer_s is not None:
                # A slow clone or Bluetooth bridge answers every request, later than the timeout: the set-up's own
                # request (given the search's wait) showed how late, which says what to change.
                slow = (f"; its speed answer in the set-up took {self._speed_answer_s:.1f} s: a slow adapter? raise "
                        f"[obd] answer_timeout_s ({self.timeout_s:g} s)" if self._speed_answer_s > self.timeout_s
                        else "")
            raise BusError(f"ELM327 on {self.port} stopped answering ({command}: {e}){slow}") from None
        if command == ELM_SPEED_COMMAND and not any(mark in answer for mark in _SEARCH_MARKS_BYTES):
            self._speed_answer_s = time.monotonic() - asked
        wanted = command.replace(" ", "").upper()
        lines, echoed = [], False
        for line in _lines(answer[:-1].decode("latin-1")):
            if line.replace(" ", "").upper() == wanted:
                echoed = True
            else:
                lines.append(line)
        return lines, echoed

    def _write(self, command: str) -> None:
        ser = self._require_open()
        try:
            ser.write(command.encode("ascii") + b"\r")
        except (serial.SerialException, OSError) as e:
            self.close()
            raise BusError(f"ELM327 port {self.port} failed on write ({e}): adapter unplugged?") from e

    def _read_answer(self, silence_s: float, search_silence_s: float | None = None) -> bytes:
        """Bytes up to and including the next prompt; what follows it stays for the next answer.

        The bound counts bytes as they come off the line, NULs included: a line held low (a break, a wrong
        baud rate) delivers NULs without end, and those are dropped before they reach the buffer.
        """
        ser = self._require_open()
        received = 0
        junk = b""
        while True:
            end = self._rx.find(PROMPT)
            if end >= 0:
                answer = bytes(self._rx[: end + 1])
                del self._rx[: end + 1]
                return answer
            if len(self._rx) > MAX_ANSWER_BYTES or received > MAX_ANSWER_BYTES:
                junk = bytes(self._rx[:24]) or junk
                self._rx.clear()
                raise ProtocolError(f"ELM327 on {self.port} sends {MAX_ANSWER_BYTES} bytes without a prompt "
                                    f"(starting {junk!r}): wrong baud rate?")
            if search_silence_s is not None:
                wait = search_silence_s
            elif any(mark in self._rx for mark in _SEARCH_MARKS_BYTES):
                wait = max(self.search_timeout_s, silence_s)  # the adapter said it is busy with the car
            else:
                wait = silence_s
            if ser.timeout != wait:
                ser.timeout = wait
            try:
                chunk = ser.read(max(1, ser.in_waiting))
            except (serial.SerialException, OSError) as e:
                self.close()
                raise BusError(f"ELM327 port {self.port} failed on read ({e}): adapter unplugged?") from e
            if not chunk:
                raise _NoPrompt(f"no prompt within {wait:g} s")
            received += len(chunk)
            junk = junk or chunk[:24]
            self._rx += chunk.replace(b"\x00", b"")

    def _take_unsolicited(self) -> bool:
        """Empty what came in since the last answer; True if it held the banner of a reset."""
        ser = self._require_open()
        try:
            waiting = ser.in_waiting
            if waiting:
                self._rx += ser.read(waiting).replace(b"\x00", b"")
        except (serial.SerialException, OSError) as e:
            self.close()
            raise BusError(f"ELM327 port {self.port} failed ({e}): adapter unplugged?") from e
        text = self._rx.decode("latin-1")
        self._rx.clear()
        return bool(BANNER.search(text)) or "LV RESET" in text

    def _require_open(self) -> serial.Serial:
        if self._serial is None:
            raise BusError(f"ELM327 port {self.port} is closed after an earlier failure")
        return self._serial

    def _lost_settings(self, lines: list[str], echoed: bool) -> str | None:
        """The sign that the adapter was reset since we set it up ('banner', 'echo', 'headers'), or None."""
        if any(BANNER.search(line) or "LV RESET" in line.upper() for line in lines):
            return "banner"
        if echoed and not self.echo_stuck:
            return "echo"  # echo is back on: the adapter lost the settings we gave it
        # Headers asked for, yet a bare '41 0D xx' came: the adapter is back at its default AT H0.
        if self.headers and any(re.fullmatch(r"410D[0-9A-F]{2}", line.replace(" ", "").upper()) for line in lines):
            return "headers"
        return None

    # ----------------------------------------------------------------- decoding

    def _decode(self, lines: list[str]) -> ObdSpeed:
        failures: list[SensorError | _OneOff] = []
        garbled: list[str] = []
        answers: list[tuple[int | None, bytes]] = []
        for line in lines:
            upper = line.upper()
            if upper.startswith("SEARCHING"):
                continue
            if upper.startswith("BUS INIT"):
                if "ERROR" in upper:
                    failures.append(BusError("ELM327 could not initialise the vehicle bus (BUS INIT ERROR): "
                                             "ignition off or wrong protocol?"))
                continue
            failure = _message_error(upper)
            if failure is not None:
                failures.append(failure)
                continue
            answer = self._parse_line(line)
            if answer is None:
                garbled.append(line)
            else:
                answers.append(answer)
        speeds = []
        for ecu_id, payload in answers:
            try:
                speeds.append(ObdSpeed(decode_speed_payload(payload), ecu_id))
            except ProtocolError:
                continue  # an answer to something else (a late reply to another PID)
        if speeds:
            for speed in speeds:
                if _is_engine(speed.ecu_id):
                    return speed
            return speeds[0]
        if failures:
            raise failures[0]
        if garbled:  # a line that fails its check byte, or cut: a disturbed answer
            raise _OneOff(ProtocolError(f"ELM327 answer to {ELM_SPEED_COMMAND} is not OBD data: {_show(garbled[0])}"))
        if answers:
            raise ProtocolError(f"ELM327 answer to {ELM_SPEED_COMMAND} holds no vehicle speed")
        raise ProtocolError(f"ELM327 gave an empty answer to {ELM_SPEED_COMMAND}")

    def _parse_line(self, line: str) -> tuple[int | None, bytes] | None:
        """(who answered, service payload) of one data line, or None if it is not one."""
        digits = line.replace(" ", "")
        if not digits or any(c not in "0123456789ABCDEFabcdef" for c in digits):
            return None
        if not self.headers:
            return (None, bytes.fromhex(digits)) if len(digits) % 2 == 0 else None
        if self._family is None:
            self._family = self._ask_family(digits)
        try:
            if self._family == CAN_11:
                if len(digits) % 2 == 0:
                    return None
                return int(digits[:3], 16), isotp_single_frame_payload(bytes.fromhex(digits[3:]))
            raw = bytes.fromhex(digits)
        except (ValueError, ProtocolError):
            return None
        if self._family == CAN_29:
            if len(raw) < 6:
                return None
            try:
                return int.from_bytes(raw[:4], "big"), isotp_single_frame_payload(raw[4:])
            except ProtocolError:
                return None
        if len(raw) < 5:
            return None
        frame, check = raw[:-1], raw[-1]
        expected = j1850_crc(frame) if self._family == J1850 else kline_checksum(frame)
        if check != expected:
            return None
        return frame[2], frame[3:]

    def _ask_family(self, sample: str) -> str:
        """Which header layout the adapter found: AT DPN, or the line itself if a clone will not say."""
        # Asked once (the answer is kept), and given the search's wait: a slow clone answers it late (ELM327-emulator
        # itself takes 0.5 s over it), and the whole family of the answers depends on it.
        lines, _ = self._command("ATDPN", long_wait=True)
        number = lines[0].upper().removeprefix("A") if len(lines) == 1 else ""
        if number in FAMILY_OF_PROTOCOL:
            self.protocol_number = number
            return FAMILY_OF_PROTOCOL[number]
        if len(sample) % 2 == 1:
            return CAN_11  # a 3-digit identifier is the only odd-length layout
        return CAN_29 if sample.upper().startswith("18DA") else K_LINE


def _lines(text: str) -> list[str]:
    return [line.strip() for line in re.split(r"[\r\n]+", text) if line.strip()]


def _show(line: str) -> str:
    """A line for an error message: as text if it is text, else its first bytes in hex (line noise)."""
    if line.isascii() and line.isprintable():
        return repr(line[:40])
    raw = line.encode("latin-1")
    return f"{len(raw)} bytes of junk ({raw[:8].hex(' ')} ...): wrong baud rate or a noisy line?"


def _message_error(upper: str) -> SensorError | _OneOff | None:
    """What an adapter's message stands for; one that a single disturbed frame or request gives comes as a
    :class:`_OneOff` (FAILED_ANSWERS_IN_A_ROW)."""
    if upper.endswith(FLAGGED_LINE_ENDS):
        # The ELM327 flags the data line it could not receive whole at its end (7E8 03 41 0D 32 <DATA ERROR).
        flag = upper[upper.rindex("<") + 1:]
        return _OneOff(BusError(f"ELM327 flags its answer with {flag}: a frame received with an error"))
    if upper == "LP ALERT":
        return BusError("ELM327 is about to go to low power (LP ALERT): its supply, or its LP input, says so")
    if upper == "OUT OF MEMORY":
        return _OneOff(BusError("ELM327 ran out of memory for the answer (OUT OF MEMORY)"))
    if upper == "NO DATA":
        return NoData("vehicle gave no speed (ELM327: NO DATA): engine off, or PID 0x0D not supported")
    if upper == "STOPPED":
        return NoData("ELM327 request was interrupted (STOPPED): no speed this time")
    if upper == "?":
        return _OneOff(ProtocolError(f"ELM327 did not understand {ELM_SPEED_COMMAND} (answered '?'): garbled serial "
                                     "line?"))
    if upper == "UNABLE TO CONNECT":
        return BusError("ELM327 unable to connect to the vehicle: ignition off or protocol not supported")
    if upper == "CAN ERROR":
        return _OneOff(BusError("ELM327 reports CAN ERROR: no working vehicle CAN bus (ignition off? wrong "
                                "protocol?)"))
    if upper in VEHICLE_BUS_FAULTS or re.fullmatch(r"ERR\d\d", upper):
        return _OneOff(BusError(f"ELM327 reports {upper} on the vehicle bus"))
    return None


def _is_engine(ecu_id: int | None) -> bool:
    if ecu_id is None:
        return False
    return ecu_id in (ENGINE_RESPONSE_ID_11, RESPONSE_BASE_29 | ENGINE_ADDRESS, ENGINE_ADDRESS)
