"""The native CAN driver against the ECU model on python-can's virtual bus, and the ECU model itself.

Each test has a virtual channel of its own (channels are shared by name across the process). A third
node on the channel plays the rest of the car where a test needs other traffic, and watches what the
driver sends.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import can
import pytest
from helpers_obd import SwitchableTrajectory

from sensors.errors import BusError, NoData, ProtocolError, SensorError
from sensors.obd import ObdSpeed, decode_speed_payload, isotp_single_frame, isotp_single_frame_payload
from sensors.obd_can import ObdCan
from sensors.sim.can_ecu import CanEcuModel
from sensors.sim.clock import ManualClock
from sensors.sim.obd_ecu import ObdEcu, engine_ecu, transmission_ecu
from sensors.sim.truth import StraightTrajectory

GENEROUS_P2_S = 1.0  # answers come in microseconds; a loaded machine must not turn them into timeouts


class GateClock(ManualClock):
    """Drive time that stands still; ``sleep`` waits until the test opens the gate, so frames sent by
    another node before the gate opens reach the driver before the ECU's answer, every time."""

    def __init__(self) -> None:
        super().__init__()
        self.gate = threading.Event()

    def sleep(self, seconds: float) -> None:
        self.gate.wait(timeout=5.0)
        self.gate.clear()


@pytest.fixture
def channel() -> str:
    return f"obd-test-{uuid.uuid4().hex}"


@contextmanager
def bus(channel: str) -> Iterator[can.BusABC]:
    b = can.Bus(interface="virtual", channel=channel)  # 'interface=' works on python-can 4.1 and 4.6
    try:
        yield b
    finally:
        b.shutdown()


@contextmanager
def vehicle(channel: str, ecus: list[ObdEcu], clock: ManualClock | None = None, **kwargs: Any
            ) -> Iterator[CanEcuModel]:
    with bus(channel) as b, CanEcuModel(b, ecus, clock or ManualClock(), **kwargs) as model:
        yield model


# ------------------------------------------------------------------------------------ the shared pieces


def test_request_frame_layout() -> None:
    assert isotp_single_frame(bytes([0x01, 0x0D])) == bytes.fromhex("02010D5555555555")
    assert isotp_single_frame_payload(bytes.fromhex("03410D32AAAAAAAA")) == bytes.fromhex("410D32")
    with pytest.raises(ProtocolError):
        isotp_single_frame_payload(bytes.fromhex("1014490201314731"))  # a first frame (VIN)
    with pytest.raises(ProtocolError):
        isotp_single_frame_payload(bytes.fromhex("0941"))  # length past the frame
    with pytest.raises(ProtocolError):
        decode_speed_payload(bytes.fromhex("410C1AF8"))  # engine speed, not vehicle speed
    assert decode_speed_payload(bytes.fromhex("410DFF")) == 255


def test_speed_record() -> None:
    s = ObdSpeed(90, 0x7E8)
    assert s.speed_mps == pytest.approx(25.0)
    with pytest.raises(ValueError):
        ObdSpeed(256)


def test_ecu_model_answers_as_j1979_says() -> None:
    traj = SwitchableTrajectory(speed_mps=13.9)
    ecu = engine_ecu(traj, scale_error=0.03)
    assert ecu.answer(bytes([0x01, 0x0D]), 0) == bytes([0x41, 0x0D, 49])  # 50.04 / 1.03 = 48.58
    # PIDs supported 01-20: only 0x0D, which is bit 31 - (0x0D - 1) = 19.
    assert ecu.answer(bytes([0x01, 0x00]), 0) == bytes.fromhex("4100") + (1 << 19).to_bytes(4, "big")
    assert ecu.answer(bytes([0x01, 0x0C]), 0) is None  # unsupported PID: silence, no negative answer
    assert ecu.answer(bytes([0x09, 0x02]), 0) is None  # VIN: not modelled, silent
    assert ecu.answer(bytes([0x01]), 0) is None
    traj.engine_on = False
    assert ecu.answer(bytes([0x01, 0x0D]), 0) is None
    assert ecu.speed_kmh(0) is None
    traj.engine_on = True
    ecu.silent = True
    assert ecu.answer(bytes([0x01, 0x0D]), 0) is None
    assert transmission_ecu(traj).request_id_11 == 0x7E1
    with pytest.raises(ValueError):
        ObdEcu(traj, response_id_11=0x7F0)
    with pytest.raises(ValueError):
        ObdEcu(traj, scale_error=-1.0)


# ------------------------------------------------------------------------------------ the driver


def test_request_on_the_wire_and_decoded_answer(channel: str) -> None:
    with vehicle(channel, [engine_ecu(StraightTrajectory(speed_mps=13.9))]) as model, \
            bus(channel) as mine, bus(channel) as sniffer:
        speed = ObdCan(mine, p2_timeout_s=GENEROUS_P2_S).read()
        request = sniffer.recv(timeout=1.0)
        answer = sniffer.recv(timeout=1.0)
    assert (speed.speed_kmh, speed.ecu_id) == (50, 0x7E8)
    assert speed.speed_mps == pytest.approx(50 / 3.6)
    assert request is not None and answer is not None
    assert (request.arbitration_id, request.is_extended_id, request.dlc) == (0x7DF, False, 8)
    assert bytes(request.data) == bytes.fromhex("02010D5555555555")
    assert (answer.arbitration_id, bytes(answer.data)) == (0x7E8, bytes.fromhex("03410D3255555555"))
    assert len(model.requests) == 1


@pytest.mark.parametrize(
    ("speed_mps", "scale_error", "kmh"),
    [(13.9, 0.0, 50), (13.9, 0.05, 48), (27.0, -0.02, 99), (1.24, 0.0, 4), (-3.0, 0.0, 11), (90.0, 0.0, 255)],
)
def test_speed_against_the_truth(channel: str, speed_mps: float, scale_error: float, kmh: int) -> None:
    # 13.9 m/s = 50.04 km/h, /1.05 = 47.66; 27 m/s = 97.2 km/h, /0.98 = 99.18; 1.24 m/s = 4.46 km/h;
    # reversing at 3 m/s = 10.8 km/h; 90 m/s = 324 km/h clips at 255.
    with vehicle(channel, [engine_ecu(StraightTrajectory(speed_mps=speed_mps), scale_error)]), bus(channel) as mine:
        assert ObdCan(mine, p2_timeout_s=GENEROUS_P2_S).read().speed_kmh == kmh


def test_two_ecus_the_engine_wins_even_when_second(channel: str) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    ecus = [transmission_ecu(traj, 0.10), engine_ecu(traj)]  # the gearbox answers first, 45 km/h
    with vehicle(channel, ecus), bus(channel) as mine:
        speed = ObdCan(mine, p2_timeout_s=GENEROUS_P2_S).read()
    assert (speed.speed_kmh, speed.ecu_id) == (50, 0x7E8)


def test_silent_engine_the_gearbox_answer_is_taken_after_p2(channel: str) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    engine = engine_ecu(traj)
    engine.silent = True
    with vehicle(channel, [transmission_ecu(traj, 0.10), engine]), bus(channel) as mine:
        speed = ObdCan(mine, p2_timeout_s=GENEROUS_P2_S).read()
    assert (speed.speed_kmh, speed.ecu_id) == (45, 0x7E9)


def test_29_bit_addressing(channel: str) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    with vehicle(channel, [transmission_ecu(traj, 0.10), engine_ecu(traj)], extended_id=True), \
            bus(channel) as mine, bus(channel) as sniffer:
        speed = ObdCan(mine, extended_id=True, p2_timeout_s=GENEROUS_P2_S).read()
        request = sniffer.recv(timeout=1.0)
    assert (speed.speed_kmh, speed.ecu_id) == (50, 0x18DAF110)
    assert request is not None
    assert (request.arbitration_id, request.is_extended_id) == (0x18DB33F1, True)
    assert bytes(request.data) == bytes.fromhex("02010D5555555555")


@pytest.mark.parametrize(("extended", "request_id", "engine_id"),
                         [(False, 0x7E0, 0x7E8), (True, 0x18DA10F1, 0x18DAF110)])
def test_engine_only_asks_the_engine_by_its_physical_id(channel: str, extended: bool, request_id: int,
                                                        engine_id: int) -> None:
    traj = StraightTrajectory(speed_mps=13.9)
    with vehicle(channel, [transmission_ecu(traj, 0.10), engine_ecu(traj)], extended_id=extended) as model, \
            bus(channel) as mine, bus(channel) as sniffer:
        speed = ObdCan(mine, extended_id=extended, engine_only=True, p2_timeout_s=GENEROUS_P2_S).read()
        frames = [sniffer.recv(timeout=1.0) for _ in range(2)]
    assert speed.speed_kmh == 50
    assert [f.arbitration_id for f in frames if f is not None] == [request_id, engine_id]
    # The gearbox is first in line: had it been asked, its answer would have come before the engine's.
    assert [m.arbitration_id for m in model.requests] == [request_id]


def test_silence_is_no_data_within_p2(channel: str) -> None:
    with vehicle(channel, [engine_ecu(StraightTrajectory())]) as model, bus(channel) as mine:
        model.silent = True
        with pytest.raises(NoData) as exc:
            ObdCan(mine).read()  # the standard's 50 ms
        assert "50 ms" in str(exc.value) and "\n" not in str(exc.value)


def test_ignition_off_is_no_data_then_speed_returns(channel: str) -> None:
    traj = SwitchableTrajectory(speed_mps=13.9, engine_on=False)
    with vehicle(channel, [engine_ecu(traj)]), bus(channel) as mine:
        driver = ObdCan(mine, p2_timeout_s=0.1)
        with pytest.raises(NoData):
            driver.read()
        traj.engine_on = True
        driver.p2_timeout_s = GENEROUS_P2_S
        assert driver.read().speed_kmh == 50


def test_other_traffic_and_other_answers_are_ignored(channel: str) -> None:
    """Before the ECU's answer, the rest of the car says things that a careless driver would take."""
    clock = GateClock()
    noise = [
        can.Message(arbitration_id=0x123, data=bytes.fromhex("03410D7F00000000"), is_extended_id=False),
        can.Message(arbitration_id=0x7E8, data=bytes.fromhex("04410C1AF8555555"), is_extended_id=False),
        can.Message(arbitration_id=0x7E8, data=bytes.fromhex("1014490201314731"), is_extended_id=False),
        can.Message(arbitration_id=0x7E9, data=bytes.fromhex("03410E7F55555555"), is_extended_id=False),
        can.Message(arbitration_id=0x18DAF110, data=bytes.fromhex("03410D7F55555555"), is_extended_id=True),
        can.Message(arbitration_id=0x7E8, data=bytes.fromhex("03010D7F55555555"), is_extended_id=False),
        can.Message(arbitration_id=0x7E8, data=bytes.fromhex("21410D7F55555555"), is_extended_id=False),
        can.Message(arbitration_id=0x7E8, data=bytes.fromhex("02410D7F55555555"), is_extended_id=False),
    ]
    with vehicle(channel, [engine_ecu(StraightTrajectory(speed_mps=13.9))], clock), bus(channel) as mine, \
            bus(channel) as car:
        stop = threading.Event()

        def rest_of_the_car() -> None:
            while not stop.is_set():
                msg = car.recv(timeout=0.02)
                if msg is not None and msg.arbitration_id == 0x7DF:
                    for frame in noise:
                        car.send(frame)
                    clock.gate.set()  # now the ECU may answer

        thread = threading.Thread(target=rest_of_the_car)
        thread.start()
        try:
            speed = ObdCan(mine, p2_timeout_s=GENEROUS_P2_S).read()
        finally:
            stop.set()
            thread.join()
    assert (speed.speed_kmh, speed.ecu_id) == (50, 0x7E8)


def test_stale_answer_from_an_earlier_request_is_not_taken(channel: str) -> None:
    with vehicle(channel, [engine_ecu(StraightTrajectory(speed_mps=13.9))]), bus(channel) as mine, \
            bus(channel) as late:
        driver = ObdCan(mine, p2_timeout_s=GENEROUS_P2_S)
        late.send(can.Message(arbitration_id=0x7E8, data=bytes.fromhex("03410D7F55555555"), is_extended_id=False))
        assert driver.read().speed_kmh == 50  # not 127, the answer that came after its request was given up


def test_negative_answer_is_no_data_naming_the_ecu(channel: str) -> None:
    with vehicle(channel, [engine_ecu(StraightTrajectory())]) as model, bus(channel) as mine, bus(channel) as car:
        model.silent = True
        stop = threading.Event()

        def refusing_ecu() -> None:
            while not stop.is_set():
                msg = car.recv(timeout=0.02)
                if msg is not None and msg.arbitration_id == 0x7DF:
                    car.send(can.Message(arbitration_id=0x7E8, data=bytes.fromhex("037F011255555555"),
                                         is_extended_id=False))

        thread = threading.Thread(target=refusing_ecu)
        thread.start()
        try:
            with pytest.raises(NoData) as exc:
                ObdCan(mine, p2_timeout_s=GENEROUS_P2_S).read()
        finally:
            stop.set()
            thread.join()
    assert "ECU 0x7E8 refused" in str(exc.value) and "0x12" in str(exc.value)


def test_closed_bus_is_a_bus_error(channel: str) -> None:
    with vehicle(channel, [engine_ecu(StraightTrajectory())]), bus(channel) as mine:
        driver = ObdCan(mine, p2_timeout_s=GENEROUS_P2_S)
        mine.shutdown()
        with pytest.raises(BusError) as exc:
            driver.read()
    assert "closed bus" in str(exc.value)
    assert isinstance(exc.value, SensorError)


def test_receive_filter_is_installed(channel: str) -> None:
    with bus(channel) as mine, bus(channel) as other:
        ObdCan(mine)
        other.send(can.Message(arbitration_id=0x123, data=b"\x00", is_extended_id=False))
        other.send(can.Message(arbitration_id=0x7E8, data=bytes.fromhex("03410D3255555555"), is_extended_id=False))
        got = mine.recv(timeout=1.0)
        assert got is not None and got.arbitration_id == 0x7E8


def test_close_shuts_the_drivers_own_bus_down(channel: str) -> None:
    """The driver owns its bus (it replaced the bus's filters): a reconnect opens a new one, so close releases it."""
    with bus(channel) as mine:
        driver = ObdCan(mine)
        driver.close()
        with pytest.raises(can.CanError):
            mine.send(can.Message(arbitration_id=0x7DF, data=bytes(8), is_extended_id=False))
        driver.close()  # nothing left to release: no error
