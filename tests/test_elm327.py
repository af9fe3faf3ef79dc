"""The ELM327 driver against the adapter model, through pyserial on a real pty.

Every quirk of real adapters and clones the driver must survive is played by the model, and the speed that
comes out is checked against the vehicle truth: quantised to whole km/h and scaled by the ECU's error.
"""

from __future__ import annotations

import math
import re
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
import serial
from helpers_obd import SwitchableTrajectory

from sensors.elm327 import Elm327
from sensors.errors import BusError, DeviceNotFound, NoData, ProtocolError, SensorError
from sensors.obd import j1850_crc
from sensors.sim import elm327 as sim_elm
from sensors.sim.clock import DriveClock, ManualClock, ScaledClock
from sensors.sim.elm327 import AdapterQuirks, Elm327Model, ElmFault
from sensors.sim.obd_ecu import ObdEcu, engine_ecu, transmission_ecu
from sensors.sim.pty import PtyPort
from sensors.sim.truth import StraightTrajectory, TruthState

INIT = ["ATZ", "ATE0", "ATL0", "ATS0", "ATH1", "ATSP0", "ATAT1"]


@dataclass
class RampTrajectory:
    """Accelerating from rest along north: speed = accel * t, so the ECU's hold shows in its answers."""

    accel_mps2: float = 3.0
    duration_s: float = math.inf

    def state(self, t_s: float) -> TruthState:
        v = self.accel_mps2 * t_s
        z = np.zeros(3)
        return TruthState(t_s, 0.6, 2.2, 40.0, np.array([v, 0.0, 0.0]), z, z, z)


@pytest.fixture
def port() -> Iterator[PtyPort]:
    with PtyPort() as p:
        yield p


@contextmanager
def adapter(port: PtyPort, ecus: list[ObdEcu], clock: DriveClock | None = None, **kwargs: Any
            ) -> Iterator[Elm327Model]:
    """The adapter model with instant waits unless a test asks for some."""
    timing: dict[str, Any] = {"search_delay_s": 0.0, "reset_delay_s": 0.0, "ecu_delay_s": 0.0, **kwargs}
    with Elm327Model(port, ecus, clock or ManualClock(), **timing) as model:
        yield model


def driver(port: PtyPort, **kwargs: Any) -> Elm327:
    """Generous timeouts: only the tests about timeouts may ever reach one."""
    settings: dict[str, Any] = {"timeout_s": 2.0, "search_timeout_s": 5.0, "reset_timeout_s": 2.0, **kwargs}
    return Elm327(port.path, **settings)


def wait_for_input(elm: Elm327, limit_s: float = 2.0) -> None:
    """Until bytes the model wrote are readable on the driver's side (a pty hands them over a moment later)."""
    deadline = time.monotonic() + limit_s
    while elm._serial is not None and elm._serial.in_waiting == 0 and time.monotonic() < deadline:
        time.sleep(0.001)


def one_line(exc: pytest.ExceptionInfo[SensorError]) -> str:
    message = str(exc.value)
    assert message and "\n" not in message and "\r" not in message
    return message


# ------------------------------------------------------------------------------------ the model itself


def test_model_answers_like_an_elm327_v15(port: PtyPort) -> None:
    traj = StraightTrajectory(speed_mps=13.9)  # 50.04 km/h
    with adapter(port, [engine_ecu(traj)]), serial.Serial(port.path, 38400, timeout=2.0) as ser:

        def ask(command: bytes) -> bytes:
            ser.write(command + b"\r")
            return ser.read_until(b">")

        assert ask(b"ATZ") == b"ATZ\r\r\rELM327 v1.5\r\r>"
        assert ask(b"ATI") == b"ATI\rELM327 v1.5\r\r>"
        assert ask(b"AT@1") == b"AT@1\rOBDII to RS232 Interpreter\r\r>"
        assert ask(b"AT E0") == b"AT E0\rOK\r\r>"  # echoed while it is still on, spaces allowed
        assert re.fullmatch(rb"1[34]\.\dV\r\r>", ask(b"ATRV"))  # alternator charging
        assert ask(b"ATDP") == b"AUTO\r\r>"
        assert ask(b"010D") == b"SEARCHING...\r41 0D 32 \r\r>"
        assert ask(b"ATDP") == b"AUTO, ISO 15765-4 (CAN 11/500)\r\r>"
        assert ask(b"ATDPN") == b"A6\r\r>"
        assert ask(b"010D") == b"41 0D 32 \r\r>"  # connected now: no search
        assert ask(b"ath1") == b"OK\r\r>"  # commands are case-insensitive
        assert ask(b"010D") == b"7E8 03 41 0D 32 \r\r>"
        assert ask(b"ATS0") == b"OK\r\r>"
        assert ask(b"010D") == b"7E803410D32\r\r>"
        assert ask(b"") == b"7E803410D32\r\r>"  # a bare CR repeats the last command
        assert ask(b"0100") == b"7E806410000080000\r\r>"  # PIDs supported: bit 19 is PID 0x0D
        assert ask(b"0105") == b"NO DATA\r\r>"  # coolant temperature: not supported by this ECU
        assert ask(b"HELLO") == b"?\r\r>"
        assert ask(b"ATL1") == b"OK\r\n\r\n>"
        assert ask(b"ATWS") == b"\r\rELM327 v1.5\r\r>"  # warm start: back to CR-only line ends


def test_model_keeps_its_latest_command_lines_not_a_days_worth(port: PtyPort,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """An eight-hour drive asks for the speed 57 600 times: the model keeps the last lines for the tests, not all."""
    monkeypatch.setattr(sim_elm, "COMMANDS_KEPT", 4)
    traj = StraightTrajectory(speed_mps=13.9)
    with adapter(port, [engine_ecu(traj)]) as model, serial.Serial(port.path, 38400, timeout=2.0) as ser:
        sent = [b"ATI", b"ATRV", b"AT@1"] * 5 + [b"ATDP"]
        for command in sent:
            ser.write(command + b"\r")
            assert ser.read_until(b">").endswith(b">")
        assert 4 <= len(model.commands) <= 8
        assert model.commands == [c.decode() for c in sent[-len(model.commands):]]


def test_model_headers_on_the_other_buses(port: PtyPort) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    expected = {
        "7": b"18 DA F1 10 03 41 0D 32 ",
        "3": b"BUS INIT: ...OK\r48 6B 10 41 0D 32 " + b"%02X " % ((0x48 + 0x6B + 0x10 + 0x41 + 0x0D + 0x32) & 0xFF),
        "4": b"BUS INIT: ...OK\r83 F1 10 41 0D 32 " + b"%02X " % ((0x83 + 0xF1 + 0x10 + 0x41 + 0x0D + 0x32) & 0xFF),
        "2": b"48 6B 10 41 0D 32 " + b"%02X " % j1850_crc(bytes.fromhex("486B10410D32")),
    }
    for protocol, line in expected.items():
        with adapter(port, [engine_ecu(traj)], vehicle_protocol=protocol), \
                serial.Serial(port.path, 38400, timeout=2.0) as ser:
            ser.write(f"ATE0\rATH1\rATSP{protocol}\r010D\r".encode())
            answers = [ser.read_until(b">") for _ in range(4)]
            assert answers[:3] == [b"ATE0\rOK\r\r>", b"OK\r\r>", b"OK\r\r>"]
            assert answers[3] == line + b"\r\r>"


def test_j1850_crc_matches_a_recorded_frame() -> None:
    # A J1850 PWM answer to 0100 as an adapter printed it with headers on: 41 6B 10 | 41 00 BF DF B9 91 | 78.
    frame = bytes.fromhex("416B104100BFDFB991")
    assert j1850_crc(frame) == 0x78
    assert sim_elm.j1850_crc(frame) == 0x78


# ------------------------------------------------------------------------------------ set-up


def test_init_sequence_and_first_answer(port: PtyPort) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    with adapter(port, [engine_ecu(traj)]) as model, driver(port) as elm:
        # Set-up ends with one speed request, so the protocol search happens during open().
        assert model.commands == [*INIT, "010D", "ATDPN"] and elm.connect_problem is None
        assert elm.version == "ELM327 v1.5"
        assert not elm.echo_stuck
        speed = elm.read()
        assert (speed.speed_kmh, speed.ecu_id) == (50, 0x7E8)
        assert speed.speed_mps == pytest.approx(50 / 3.6)
        assert elm.protocol_number == "6"  # asked once (AT DPN) to read the headers
        assert elm.read().speed_kmh == 50
        assert model.commands == [*INIT, "010D", "ATDPN", "010D", "010D"]


def test_configured_protocol_timing_and_spaces(port: PtyPort) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    with adapter(port, [engine_ecu(traj)]) as model, \
            driver(port, protocol="6", adaptive_timing=2, obd_timeout_ms=100, spaces=True) as elm:
        assert elm.read().speed_kmh == 50
        # 100 ms / 4.096 ms = 24.4 -> 0x18; a known protocol needs no AT DPN.
        assert model.commands == ["ATZ", "ATE0", "ATL0", "ATS1", "ATH1", "ATSP6", "ATAT2", "ATST18", "010D", "010D"]


def test_clone_without_optional_commands_still_works(port: PtyPort) -> None:
    quirks = AdapterQuirks(missing_commands=frozenset({"AT", "ST"}))
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))], quirks=quirks), \
            driver(port, obd_timeout_ms=200) as elm:
        assert elm.read().speed_kmh == 50


def test_clone_without_headers_command_is_refused_clearly(port: PtyPort) -> None:
    quirks = AdapterQuirks(missing_commands=frozenset({"H"}))
    with adapter(port, [engine_ecu(StraightTrajectory())], quirks=quirks):
        elm = driver(port)
        with pytest.raises(ProtocolError) as exc:
            elm.open()
        assert "ATH1" in one_line(exc)
        assert not elm.is_open


def test_bad_configuration_is_a_value_error(port: PtyPort) -> None:
    with pytest.raises(ValueError, match="protocol"):
        Elm327(port.path, protocol="A")  # SAE J1939: no PID 0x0D
    with pytest.raises(ValueError, match="adaptive"):
        Elm327(port.path, adaptive_timing=3)
    with pytest.raises(ValueError, match="timeout"):
        Elm327(port.path, obd_timeout_ms=2000)


def test_missing_port_is_device_not_found() -> None:
    elm = Elm327("/dev/serial/by-id/usb-no-such-adapter")
    with pytest.raises(DeviceNotFound) as exc:
        elm.read()
    assert "does not exist" in one_line(exc)


def test_silent_device_is_device_not_found(port: PtyPort) -> None:
    elm = driver(port, reset_timeout_s=0.1)
    with pytest.raises(DeviceNotFound) as exc:
        elm.open()
    assert "is silent" in one_line(exc)
    assert not elm.is_open


def test_something_else_on_the_port_is_device_not_found(port: PtyPort) -> None:
    """A modem-like device answers, but with no banner and no prompt."""
    stop = threading.Event()

    def modem() -> None:
        while not stop.is_set():
            if b"\r" in port.read(0.02):
                port.write(b"\r\nOK\r\n")

    thread = threading.Thread(target=modem)
    thread.start()
    try:
        # The modem thread must answer each ATZ within this, and each of the two tries then waits it out for a
        # prompt that never comes: a second, not a fraction that a busy host could take to run the thread.
        elm = driver(port, reset_timeout_s=1.0)
        with pytest.raises(DeviceNotFound) as exc:
            elm.open()
        assert "answered 'OK'" in one_line(exc)
    finally:
        stop.set()
        thread.join()


# ------------------------------------------------------------------------------------ speed against the truth


@pytest.mark.parametrize(
    ("speed_mps", "scale_error", "kmh"),
    [
        (13.9, 0.0, 50),  # 50.04
        (13.9, 0.03, 49),  # 48.58: the ECU under-reads by the paper's s = 3 %
        (13.9, -0.03, 52),  # 51.59
        (1.26, 0.0, 5),  # 4.536 rounds up
        (1.24, 0.0, 4),  # 4.464 rounds down
        (0.0, 0.0, 0),
        (-5.0, 0.0, 18),  # reversing: PID 0x0D has no sign
        (80.0, 0.0, 255),  # 288 km/h does not fit the byte
    ],
)
def test_speed_is_quantised_and_scaled_like_the_ecu(port: PtyPort, speed_mps: float, scale_error: float,
                                                    kmh: int) -> None:
    traj = StraightTrajectory(speed_mps=speed_mps)
    with adapter(port, [engine_ecu(traj, scale_error)]), driver(port) as elm:
        speed = elm.read()
    assert speed.speed_kmh == kmh
    assert speed.speed_mps == pytest.approx(kmh / 3.6)
    # What the paper's model recovers with the true s: within half a step of the true speed (unclipped).
    if kmh < 255:
        assert (1 + scale_error) * speed.speed_mps == pytest.approx(abs(speed_mps), abs=0.5 / 3.6 * (1 + scale_error))


def test_speed_holds_between_ecu_updates(port: PtyPort) -> None:
    clock = ManualClock()
    ecu = engine_ecu(RampTrajectory(accel_mps2=3.0), update_period_s=0.1)
    with adapter(port, [ecu], clock), driver(port) as elm:
        clock.advance(1.19)  # the ECU last counted pulses at 1.1 s: 3.3 m/s = 11.88 km/h, not 12.85
        assert elm.read().speed_kmh == 12
        clock.advance(3.81)  # 5.0 s exactly: a fresh count, 15 m/s
        assert elm.read().speed_kmh == 54


# ------------------------------------------------------------------------------------ clones and several ECUs


def test_echo_stuck_clone_is_read_without_false_resets(port: PtyPort) -> None:
    quirks = AdapterQuirks(echo_stuck=True)
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))], quirks=quirks) as model, \
            driver(port) as elm:
        assert elm.echo_stuck
        assert [elm.read().speed_kmh for _ in range(3)] == [50, 50, 50]
        assert elm.resets_seen == 0
        assert model.commands.count("ATZ") == 1


def test_nul_bytes_and_crlf_clone(port: PtyPort) -> None:
    quirks = AdapterQuirks(nul_bytes=True, crlf=True, linefeeds_default=True, banner="ELM327 v2.1")
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))], quirks=quirks), driver(port) as elm:
        assert elm.version == "ELM327 v2.1"
        assert elm.read().speed_kmh == 50


@pytest.mark.parametrize("spaces", [False, True])
def test_two_ecus_with_headers_the_engine_wins(port: PtyPort, spaces: bool) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    # The gearbox answers first and reads 10 % low: 45 km/h against the engine's 50.
    ecus = [transmission_ecu(traj, 0.10), engine_ecu(traj)]
    with adapter(port, ecus), driver(port, spaces=spaces) as elm:
        speed = elm.read()
    assert (speed.speed_kmh, speed.ecu_id) == (50, 0x7E8)


def test_two_ecus_without_headers_the_first_answer_counts(port: PtyPort) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    ecus = [transmission_ecu(traj, 0.10), engine_ecu(traj)]
    with adapter(port, ecus), driver(port, headers=False) as elm:
        speed = elm.read()
    assert (speed.speed_kmh, speed.ecu_id) == (45, None)


def test_only_the_gearbox_answers(port: PtyPort) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    engine = engine_ecu(traj)
    with adapter(port, [transmission_ecu(traj, 0.10), engine]), driver(port) as elm:
        engine.silent = True
        speed = elm.read()
    assert (speed.speed_kmh, speed.ecu_id) == (45, 0x7E9)


@pytest.mark.parametrize(
    ("vehicle", "configured", "ecu_id"),
    [
        ("7", "0", 0x18DAF110),  # CAN 29-bit, found by search
        ("9", "9", 0x18DAF110),  # CAN 29-bit 250 kbit/s, configured
        ("3", "3", 0x10),  # ISO 9141-2: BUS INIT, sum checksum
        ("5", "5", 0x10),  # KWP fast init
        ("1", "1", 0x10),  # J1850 PWM: CRC-8
        ("2", "0", 0x10),  # J1850 VPW, found by search
    ],
)
def test_headers_of_every_obd_bus(port: PtyPort, vehicle: str, configured: str, ecu_id: int) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    ecus = [transmission_ecu(traj, 0.10), engine_ecu(traj)]
    with adapter(port, ecus, vehicle_protocol=vehicle), driver(port, protocol=configured) as elm:
        speed = elm.read()
        assert (speed.speed_kmh, speed.ecu_id) == (50, ecu_id)
        assert elm.protocol_number == vehicle


# ------------------------------------------------------------------------------------ slow search


def test_slow_protocol_search_is_waited_for(port: PtyPort) -> None:
    # A real-time drive clock: the adapter spends 2 s searching, twice the 1 s it may otherwise stay silent
    # (every other answer comes at once, but a busy host may take a good part of a second to deliver it).
    # The driver waits on the first request, and on a later one because the adapter said SEARCHING...
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))], ScaledClock(1.0),
                 search_delay_s=2.0) as model, driver(port, timeout_s=1.0, search_timeout_s=5.0) as elm:
        assert elm.read().speed_kmh == 50
        model.inject(ElmFault.UNABLE_TO_CONNECT)  # the link drops: the next request searches again
        with pytest.raises(BusError):
            elm.read()
        assert elm.read().speed_kmh == 50
        assert model.commands.count("ATZ") == 1


def test_an_answer_that_comes_after_its_command_was_given_up_is_not_the_next_ones(port: PtyPort) -> None:
    """A slow clone answers AT DPN after the driver gave up on it (the search's wait, 1 s here): that late 'A6' was
    read as the next request's answer, every answer after it one behind ('A6' for the speed, the speed for AT DPN,
    and the header layout guessed wrong from it), the OBD never delivering again. It is waited out and dropped."""
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))], ScaledClock(1.0),
                 slow_commands={"ATDPN": 1.3}) as model, \
            driver(port, timeout_s=1.0, search_timeout_s=1.0) as elm:
        assert elm.connect_problem is not None and "(ATDPN: no prompt within 1 s)" in elm.connect_problem
        model.slow_commands.clear()  # the clone answers in time from now on
        assert [elm.read().speed_kmh for _ in range(3)] == [50, 50, 50]
        assert elm.protocol_number == "6"


def test_search_longer_than_allowed_is_reported_by_open(port: PtyPort) -> None:
    # The control for the test above: an adapter searching twice as long as the driver allows (0.5 s, 0.25 s).
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))], ScaledClock(1.0), search_delay_s=0.5), \
            driver(port, timeout_s=0.25, search_timeout_s=0.25) as elm:
        # The search runs during set-up; its failure is kept for the reads to tell, not raised by open().
        assert elm.connect_problem is not None and "stopped answering" in elm.connect_problem
        assert "\n" not in elm.connect_problem


# ------------------------------------------------------------------------------------ failures


def test_engine_off_is_no_data_and_speed_returns(port: PtyPort) -> None:
    traj = SwitchableTrajectory(speed_mps=13.9)
    with adapter(port, [engine_ecu(traj)]), driver(port) as elm:
        assert elm.read().speed_kmh == 50
        traj.engine_on = False
        with pytest.raises(NoData) as exc:
            elm.read()
        assert "NO DATA" in one_line(exc)
        traj.engine_on = True
        assert elm.read().speed_kmh == 50


def test_ignition_off_at_start_is_unable_to_connect(port: PtyPort) -> None:
    traj = SwitchableTrajectory(speed_mps=13.9, engine_on=False)
    with adapter(port, [engine_ecu(traj)]), driver(port) as elm:
        with pytest.raises(BusError) as exc:
            elm.read()
        assert "unable to connect" in one_line(exc)
        traj.engine_on = True
        assert elm.read().speed_kmh == 50


@pytest.mark.parametrize(
    ("fault", "error", "text"),
    [
        (ElmFault.NO_DATA, NoData, "NO DATA"),
        (ElmFault.STOPPED, NoData, "STOPPED"),
        # A disturbed answer once is one failed sample: the adapter is left as it is (NoData); see the next test.
        (ElmFault.CAN_ERROR, NoData, "CAN ERROR"),
        (ElmFault.BUS_ERROR, NoData, "BUS ERROR"),
        (ElmFault.UNABLE_TO_CONNECT, BusError, "unable to connect"),
        (ElmFault.BUS_INIT_ERROR, BusError, "BUS INIT ERROR"),
        (ElmFault.MISUNDERSTOOD, NoData, "did not understand"),
        (ElmFault.DATA_ERROR_FLAGGED, NoData, "flags its answer with DATA ERROR"),
        (ElmFault.LP_ALERT, BusError, "about to go to low power (LP ALERT)"),
        (ElmFault.GARBAGE, NoData, "junk"),
    ],
)
def test_each_adapter_message_maps_to_its_error_and_recovers(port: PtyPort, fault: ElmFault,
                                                             error: type[SensorError], text: str) -> None:
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))]) as model, driver(port) as elm:
        assert elm.read().speed_kmh == 50
        model.inject(fault)
        with pytest.raises(error) as exc:
            elm.read()
        assert text in one_line(exc)
        assert elm.read().speed_kmh == 50  # the next request is answered again
        assert model.commands.count("ATZ") == 1  # no needless reset for a one-off failure


@pytest.mark.parametrize(("fault", "error", "text"), [(ElmFault.BUS_ERROR, BusError, "BUS ERROR"),
                                                     (ElmFault.CAN_ERROR, BusError, "CAN ERROR"),
                                                     (ElmFault.MISUNDERSTOOD, ProtocolError, "did not understand")])
def test_disturbed_answers_in_a_row_are_the_adapters_fault(port: PtyPort, fault: ElmFault, error: type[SensorError],
                                                          text: str) -> None:
    """One disturbed answer was a BusError, which the sampler answers by closing the adapter and setting it up
    again (4 s without speed for one frame); it is one failed sample now, and only FAILED_ANSWERS_IN_A_ROW of them
    in a row are the adapter's or the bus's fault. A good answer between them starts the count again."""
    from sensors.elm327 import FAILED_ANSWERS_IN_A_ROW

    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))]) as model, driver(port) as elm:
        assert elm.read().speed_kmh == 50
        for _ in range(FAILED_ANSWERS_IN_A_ROW - 1):
            model.inject(fault)
            with pytest.raises(NoData, match=re.escape(text) if text.isupper() else text):
                elm.read()
        assert elm.read().speed_kmh == 50
        for _ in range(FAILED_ANSWERS_IN_A_ROW - 1):  # an answer of another kind between them: not in a row either
            model.inject(fault)
            with pytest.raises(NoData, match=f"1 of {FAILED_ANSWERS_IN_A_ROW} in a row"):
                elm.read()
            model.inject(ElmFault.NO_DATA)
            with pytest.raises(NoData, match="NO DATA"):
                elm.read()
        for k in range(FAILED_ANSWERS_IN_A_ROW):
            model.inject(fault)
            with pytest.raises(error if k == FAILED_ANSWERS_IN_A_ROW - 1 else NoData) as exc:
                elm.read()
            assert text in one_line(exc)
            if k < FAILED_ANSWERS_IN_A_ROW - 1:
                assert f"{k + 1} of {FAILED_ANSWERS_IN_A_ROW} in a row" in one_line(exc)


def test_an_adapter_slower_than_the_timeout_is_told_by_its_set_up(port: PtyPort) -> None:
    """A slow clone or Bluetooth bridge answers every request later than the timeout: its set-up's request (given
    the search's wait) was answered and thrown away, and the reads' timeouts blamed the adapter. They name the
    answer's time and the setting to change."""
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))], ScaledClock(1.0),
                 slow_commands={"010D": 0.6}):
        elm = driver(port, timeout_s=0.3)
        elm.clock = time.monotonic_ns
        elm.open()
        try:
            with pytest.raises(BusError) as exc:
                elm.read()
        finally:
            elm.close()
    message = one_line(exc)
    took = re.search(r"speed answer in the set-up took (\d+\.\d) s: a slow adapter\? raise \[obd\] "
                     r"answer_timeout_s \(0\.3 s\)", message)
    assert took is not None and float(took.group(1)) >= 0.6, message


def test_bus_init_error_on_a_k_line_car(port: PtyPort) -> None:
    traj = SwitchableTrajectory(speed_mps=13.9, engine_on=False)
    with adapter(port, [engine_ecu(traj)], vehicle_protocol="3"), driver(port, protocol="3") as elm:
        with pytest.raises(BusError) as exc:
            elm.read()
        assert "BUS INIT ERROR" in one_line(exc)
        traj.engine_on = True
        assert elm.read().ecu_id == 0x10


@pytest.mark.parametrize("vehicle", ["1", "3", "4"])
def test_bit_error_is_caught_by_the_check_byte(port: PtyPort, vehicle: str) -> None:
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))], vehicle_protocol=vehicle) as model, \
            driver(port, protocol=vehicle) as elm:
        assert elm.read().speed_kmh == 50
        model.inject(ElmFault.BIT_ERROR)  # 0x32 would arrive as 0x72 = 114 km/h
        with pytest.raises(NoData) as exc:  # a disturbed answer: no speed this time, the adapter left as it is
            elm.read()
        assert "not OBD data" in one_line(exc)
        assert elm.read().speed_kmh == 50


def test_wrong_can_bit_rate_is_can_error(port: PtyPort) -> None:
    from sensors.elm327 import FAILED_ANSWERS_IN_A_ROW

    with adapter(port, [engine_ecu(StraightTrajectory())], vehicle_protocol="6"), driver(port, protocol="8") as elm:
        assert "CAN ERROR" in (elm.connect_problem or "")  # the set-up's own request
        for _ in range(FAILED_ANSWERS_IN_A_ROW - 2):
            with pytest.raises(NoData, match="CAN ERROR"):
                elm.read()
        with pytest.raises(BusError) as exc:  # every answer the same: the bus's fault, not a disturbed frame
            elm.read()
        assert "CAN ERROR" in one_line(exc)


def test_line_noise_between_requests_is_ignored(port: PtyPort) -> None:
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))]) as model, driver(port) as elm:
        for _ in range(3):
            model.line_noise(20)
            assert elm.read().speed_kmh == 50


# ------------------------------------------------------------------------------------ resets and unplugging


def test_reset_mid_drive_is_noticed_and_the_adapter_set_up_again(port: PtyPort) -> None:
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))]) as model, driver(port) as elm:
        assert elm.read().speed_kmh == 50
        model.reset()  # brown-out while cranking: banner, echo on, headers off
        speed = elm.read()
        assert (speed.speed_kmh, speed.ecu_id) == (50, 0x7E8)
        assert elm.resets_seen == 1
        assert model.commands.count("ATZ") == 2
        assert model.commands[-len(INIT) - 2 :][: len(INIT)] == INIT


def test_reset_announced_between_requests_is_handled_before_asking(port: PtyPort) -> None:
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))]) as model, driver(port) as elm:
        assert elm.read().speed_kmh == 50
        model.reset()
        wait_for_input(elm)  # the banner has reached the driver's side of the line
        assert elm.read().speed_kmh == 50
        # Set up again first: no request went to an adapter at its defaults.
        assert model.commands == [*INIT, "010D", "ATDPN", "010D", *INIT, "010D", "ATDPN"]


def test_a_speed_after_the_adapter_was_set_up_again_is_timed_by_its_own_request(port: PtyPort) -> None:
    """Set up again inside a read (its reset, the set-up, the protocol search: seconds), the speed was stamped at
    the middle of all of it, 1.5-2.5 s before the ECU answered. The driver times the request that was answered, by
    its caller's clock; the one that began the protocol search is asked again, as its ECU time within the search
    is not known."""
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))]) as model, driver(port) as elm:
        elm.clock = lambda: len(model.commands)  # a clock that tells which command the model is at
        assert elm.read().speed_kmh == 50
        assert elm.answered_window_ns == (len(model.commands) - 1, len(model.commands))
        model.reset()
        wait_for_input(elm)
        assert elm.read().speed_kmh == 50
        assert model.commands[-4:] == [*INIT[-1:], "010D", "ATDPN", "010D"]  # the search's request, asked again
        assert elm.answered_window_ns == (len(model.commands) - 1, len(model.commands))


@pytest.mark.parametrize(("echo_stuck", "headers"), [(False, True), (False, False), (True, True)])
def test_reset_without_banner_is_noticed_by_its_defaults(port: PtyPort, echo_stuck: bool, headers: bool) -> None:
    # The banner was lost: echo coming back (or, on an always-echoing clone, the missing headers) tells.
    quirks = AdapterQuirks(echo_stuck=echo_stuck)
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))], quirks=quirks) as model, \
            driver(port, headers=headers) as elm:
        assert elm.read().speed_kmh == 50
        model.reset(announce=False)
        speed = elm.read()
        assert (speed.speed_kmh, speed.ecu_id) == (50, 0x7E8 if headers else None)
        assert elm.resets_seen == 1
        assert model.commands.count("ATZ") == 2


def test_unplugged_adapter_is_a_bus_error_and_reopens(port: PtyPort) -> None:
    with adapter(port, [engine_ecu(StraightTrajectory(speed_mps=13.9))]) as model, driver(port) as elm:
        assert elm.read().speed_kmh == 50
        port.vanish()
        with pytest.raises(BusError) as exc:
            elm.read()
        assert "unplugged" in one_line(exc)
        assert not elm.is_open
        with pytest.raises(DeviceNotFound):
            elm.read()  # still unplugged: the path is gone
        port.reappear()
        assert elm.read().speed_kmh == 50  # opened and set up again
        assert model.commands.count("ATZ") == 2
