"""The vehicle's ECUs on a CAN bus: ISO 15765-4 diagnostic answers from the :class:`ObdEcu` models.

Plays the far side of the OBD-II socket for the native CAN driver. It takes its own python-can bus
object (a ``virtual`` one in tests and in the simulated drive, a socketcan one on a bench), listens for
functional requests (0x7DF, or 0x18DB33F1 with 29-bit ids) and for each ECU's physical id, and answers
each single-frame request with one padded single frame per ECU that has the value, as the standard has
it. Answers leave after ``response_delay_s`` of drive time, the ECU's own processing time.
"""

from __future__ import annotations

from collections.abc import Sequence

import can

from sensors.sim.clock import DriveClock
from sensors.sim.device_thread import DeviceThread
from sensors.sim.obd_ecu import ObdEcu

FUNCTIONAL_11 = 0x7DF
FUNCTIONAL_29 = 0x18DB33F1
TESTER = 0xF1


class CanEcuModel(DeviceThread):
    """A thread answering OBD-II requests on ``bus`` for ``ecus``; ``silent`` mutes them all at once."""

    thread_name = "sim-can-ecu"

    def __init__(
        self,
        bus: can.BusABC,
        ecus: Sequence[ObdEcu],
        clock: DriveClock,
        *,
        extended_id: bool = False,
        response_delay_s: float = 0.005,
        padding: int = 0x55,
    ) -> None:
        self.bus = bus
        self.ecus = list(ecus)
        self.clock = clock
        self.extended_id = extended_id
        self.response_delay_s = response_delay_s
        self.padding = padding
        self.silent = False
        self.requests: list[can.Message] = []  # every diagnostic request heard, for the tests to inspect
        super().__init__()

    def _run(self) -> None:
        while not self.stopping.is_set():
            try:
                msg = self.bus.recv(timeout=0.02)
            except can.CanError:
                return  # the bus was shut down under us: the vehicle is gone
            if msg is None or msg.is_error_frame or msg.is_extended_id != self.extended_id:
                continue
            addressed = self._addressees(msg.arbitration_id)
            if not addressed:
                continue
            self.requests.append(msg)
            request = _single_frame_payload(bytes(msg.data))
            if request is None or self.silent:
                continue
            self.clock.sleep(self.response_delay_s)
            t_ns = self.clock.now_ns()
            for ecu in addressed:
                payload = ecu.answer(request, t_ns)
                if payload is None or len(payload) > 7:
                    continue
                data = bytes([len(payload)]) + payload + bytes([self.padding]) * (7 - len(payload))
                answer = can.Message(arbitration_id=self._answer_id(ecu), data=data,
                                     is_extended_id=self.extended_id)
                try:
                    self.bus.send(answer)
                except can.CanError:
                    return

    def _addressees(self, can_id: int) -> list[ObdEcu]:
        if self.extended_id:
            if can_id == FUNCTIONAL_29:
                return self.ecus
            # Physical: priority 0x18, PF 0xDA, target = the ECU, source = the tester.
            return [e for e in self.ecus if can_id == (0x18DA0000 | (e.address << 8) | TESTER)]
        if can_id == FUNCTIONAL_11:
            return self.ecus
        return [e for e in self.ecus if can_id == e.request_id_11]

    def _answer_id(self, ecu: ObdEcu) -> int:
        if self.extended_id:
            return 0x18DA0000 | (TESTER << 8) | ecu.address
        return ecu.response_id_11


def _single_frame_payload(data: bytes) -> bytes | None:
    """The request inside an ISO-TP single frame; ECUs ignore anything else sent to the OBD ids."""
    if not data or data[0] >> 4 != 0:
        return None
    length = data[0] & 0x0F
    if not 1 <= length <= len(data) - 1:
        return None
    return data[1 : 1 + length]
