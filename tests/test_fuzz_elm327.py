"""Fuzzing the ELM327 driver's side of the serial line: whatever an adapter (or a clone, or line noise) answers,
``read()`` returns a speed or raises a SensorError, after a bounded number of bytes and commands."""

from __future__ import annotations

import os
from typing import Any

from extras import HealthCheck, given, settings, st

from sensors.elm327 import MAX_ANSWER_BYTES, Elm327
from sensors.errors import SensorError
from sensors.obd import ObdSpeed, isotp_single_frame, j1850_crc, kline_checksum

# FUZZ_EXAMPLES=5000 (environment) searches deeper than the suite's default.
FUZZ = settings(max_examples=int(os.environ.get("FUZZ_EXAMPLES", "400")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow])


class ScriptedPort:
    """A pyserial stand-in on which each command written makes the next scripted answer readable.

    Reads never wait: an empty read is the adapter falling silent. ``stream`` bytes, if any, flow without a
    command (an adapter that spews), at most ``stream_limit`` of them.
    """

    def __init__(self, answers: list[bytes], stream: bytes = b"", stream_limit: int = 0) -> None:
        self.answers = list(answers)
        self.rx = bytearray()
        self.stream = stream
        self.stream_left = stream_limit
        self.timeout: float | None = 1.0
        self.written: list[bytes] = []
        self.bytes_read = 0

    def _spew(self) -> None:
        # Like the kernel's tty buffer, at most 4095 bytes wait to be read.
        if self.stream and self.stream_left > 0 and len(self.rx) < 4095:
            take = self.stream[: min(self.stream_left, 4095 - len(self.rx))]
            self.rx += take
            self.stream_left -= len(take)

    @property
    def in_waiting(self) -> int:
        self._spew()
        return len(self.rx)

    def read(self, n: int = 1) -> bytes:
        self._spew()
        out = bytes(self.rx[:n])
        del self.rx[:n]
        self.bytes_read += len(out)
        return out

    def write(self, data: bytes) -> int:
        self.written.append(data)
        if self.answers:
            self.rx += self.answers.pop(0)
        return len(data)

    def close(self) -> None:
        pass


def adapter(headers: bool, protocol: str, port: ScriptedPort) -> Elm327:
    """A driver that finished its set-up on ``protocol`` and is about to ask for the speed."""
    elm = Elm327("/dev/fuzz", protocol=protocol, headers=headers)
    elm._serial = port  # type: ignore[assignment]
    elm.version = "ELM327 v1.5"
    from sensors.elm327 import FAMILY_OF_PROTOCOL

    elm._family = FAMILY_OF_PROTOCOL.get(protocol)
    elm._first_request = False
    return elm


def hex_line(data: bytes, spaces: bool) -> str:
    return (" " if spaces else "").join(f"{b:02X}" for b in data)


@st.composite
def answer_lines(draw: st.DrawFn) -> str:
    """A line an adapter might send: data for PID 0x0D in each bus's layout (right or broken), or a message."""
    speed = draw(st.integers(0, 255))
    payload = bytes([0x41, 0x0D, speed]) if draw(st.booleans()) else draw(st.binary(min_size=0, max_size=9))
    spaces = draw(st.booleans())
    kind = draw(st.sampled_from(["can11", "can29", "j1850", "kline", "bare", "message", "text", "noise"]))
    if kind == "can11":
        frame = isotp_single_frame(payload[:7] or b"\x41") if draw(st.booleans()) else draw(st.binary(max_size=9))
        return draw(st.sampled_from(["7E8", "7E9", "7EF", "123", "FFF"])) + (" " if spaces else "") + \
            hex_line(frame, spaces)
    if kind == "can29":
        frame = isotp_single_frame(payload[:7] or b"\x41") if draw(st.booleans()) else draw(st.binary(max_size=9))
        return hex_line(bytes.fromhex("18DAF110") + frame, spaces)
    if kind in ("j1850", "kline"):
        head = bytes([0x48, 0x6B, draw(st.integers(0, 255))]) + payload
        check = j1850_crc(head) if kind == "j1850" else kline_checksum(head)
        if draw(st.booleans()):
            check ^= draw(st.integers(1, 255))
        return hex_line(head + bytes([check]), spaces)
    if kind == "bare":
        return hex_line(payload, spaces)
    if kind == "message":
        return draw(st.sampled_from(["NO DATA", "SEARCHING...", "BUS INIT: ...OK", "BUS INIT: ...ERROR", "?",
                                     "UNABLE TO CONNECT", "CAN ERROR", "STOPPED", "BUS BUSY", "ERR71", "OK",
                                     "ELM327 v1.5", "ELM327 v2.1", "LV RESET", "010D", "ATZ", "6", "A6", ""]))
    if kind == "text":
        return draw(st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=30))
    return draw(st.binary(max_size=30)).decode("latin-1")


@st.composite
def answers(draw: st.DrawFn) -> bytes:
    lines = draw(st.lists(answer_lines(), max_size=6))
    end = draw(st.sampled_from(["\r", "\r\n", "\n"]))
    body = end.join(lines).encode("latin-1")
    if draw(st.booleans()):
        body = body.replace(b"\r", b"\r\x00")  # clones that send NULs
    prompt = draw(st.sampled_from([b"\r\r>", b">", b"", b"\r\r>extra"]))
    return body + prompt


@FUZZ
@given(st.lists(answers(), max_size=25), st.booleans(), st.sampled_from(["0", "1", "3", "6", "7", "A6"]))
def test_any_answers_give_a_speed_or_a_sensor_error(script: list[bytes], headers: bool, protocol: str) -> None:
    port = ScriptedPort(script)
    elm = adapter(headers, protocol, port)
    for _ in range(3):  # a few periods in a row: state carried between reads must stay sane
        try:
            speed = elm.read()
        except SensorError:
            continue
        assert isinstance(speed, ObdSpeed) and 0 <= speed.speed_kmh <= 255
    # Bounded: every command consumed at most one scripted answer, and a reset's re-initialisation is finite.
    assert len(port.written) <= 3 * 40


@FUZZ
@given(st.binary(min_size=1, max_size=64), st.booleans())
def test_an_adapter_spewing_without_a_prompt_is_cut_off(noise: bytes, headers: bool) -> None:
    """A wrong baud rate looks like endless junk: the driver gives up after a bounded number of bytes."""
    junk = noise.replace(b">", b"") or b"\xff"
    port = ScriptedPort([], stream=junk * (4095 // len(junk) + 1), stream_limit=10**9)
    elm = adapter(headers, "6", port)
    try:
        elm.read()
    except SensorError:
        pass
    assert port.bytes_read <= 2 * MAX_ANSWER_BYTES + 2 * 4095


def test_a_line_of_nuls_does_not_hang_the_reader() -> None:
    """Found by fuzzing: NULs were dropped before the length bound was checked, so a line held low (a break
    reads as endless NULs) kept the reader in its loop for ever."""
    port = ScriptedPort([], stream=b"\x00" * 4095, stream_limit=40 * MAX_ANSWER_BYTES)  # finite, so it can fail
    elm = adapter(True, "6", port)
    try:
        elm.read()
    except SensorError as exc:
        assert "without a prompt" in str(exc) and "x00" in str(exc)
    else:
        raise AssertionError("a speed out of NULs")
    assert port.bytes_read <= 2 * MAX_ANSWER_BYTES + 2 * 4095


J1850 = bytes([0x48, 0x6B, 0x10, 0x41, 0x0D, 0x21])
KLINE = bytes([0x48, 0x6B, 0x10, 0x41, 0x0D, 0x05])


def test_decoding_examples_for_each_bus() -> None:
    """The fuzzer's generators produce answers the driver reads: otherwise the fuzzing above proves little."""
    cases: list[tuple[str, str, bool, int | None]] = [
        ("6", "7E8 03 41 0D 3C", True, 60),
        ("7", "18 DA F1 10 03 41 0D 50", True, 80),
        ("1", hex_line(J1850 + bytes([j1850_crc(J1850)]), True), True, 33),
        ("3", hex_line(KLINE + bytes([kline_checksum(KLINE)]), False), True, 5),
        ("6", "41 0D 7F", False, 127),
    ]
    for protocol, line, headers, kmh in cases:
        port = ScriptedPort([line.encode() + b"\r\r>"])
        speed: Any = adapter(headers, protocol, port).read()
        assert speed.speed_kmh == kmh, (protocol, line)
