"""Vehicle speed over the vehicle's own CAN bus (ISO 15765-4), without an ELM327 in between.

A CAN interface on the logger (socketcan on the board) removes the adapter's text layer and its seconds
of protocol search: one request frame, one answer frame per ECU within P2 (50 ms by the standard). The
bus is shared with whatever else the car says, so the driver installs a receive filter for the diagnostic
answer ids and still checks every frame it gets: other PIDs, other services and answers that arrive after
their request was given up are ignored, not decoded.
"""

from __future__ import annotations

import time

import can

from sensors.errors import BusError, NoData, ProtocolError
from sensors.obd import (
    ENGINE_ADDRESS,
    ENGINE_RESPONSE_ID_11,
    FUNCTIONAL_REQUEST_ID_11,
    FUNCTIONAL_REQUEST_ID_29,
    NEGATIVE_RESPONSE_SID,
    PHYSICAL_REQUEST_BASE_11,
    PHYSICAL_REQUEST_BASE_29,
    RESPONSE_BASE_11,
    RESPONSE_BASE_29,
    SERVICE_CURRENT_DATA,
    SPEED_REQUEST,
    ObdSpeed,
    SpeedDriver,
    decode_speed_payload,
    isotp_single_frame,
    isotp_single_frame_payload,
)

P2_CAN_S = 0.050  # ISO 15765-4: an ECU answers within 50 ms of the request
MAX_STALE_FRAMES = 1000  # a bound on emptying the receive queue, so a flooding bus cannot hold us

NEGATIVE_RESPONSE_PREFIX = bytes([NEGATIVE_RESPONSE_SID, SERVICE_CURRENT_DATA])  # 7F 01 <reason>
RESPONSE_FILTER_11 = {"can_id": RESPONSE_BASE_11, "can_mask": 0x7F8, "extended": False}
RESPONSE_FILTER_29 = {"can_id": RESPONSE_BASE_29, "can_mask": 0x1FFFFF00, "extended": True}


class ObdCan(SpeedDriver):
    """PID 0x0D requests on a python-can bus (socketcan on the board, the virtual bus in tests).

    The driver sets the bus's receive filters, replacing any: give it a bus of its own. ``extended_id``
    selects 29-bit addressing. ``engine_only`` asks the engine ECU by its physical id instead of every
    ECU by the functional id, which halves the answer traffic on cars where the gearbox answers too.
    """

    def __init__(
        self,
        bus: can.BusABC,
        *,
        extended_id: bool = False,
        engine_only: bool = False,
        p2_timeout_s: float = P2_CAN_S,
    ) -> None:
        if p2_timeout_s <= 0:
            raise ValueError("P2 timeout must be positive")
        self.bus = bus
        self.extended_id = extended_id
        self.p2_timeout_s = p2_timeout_s
        if extended_id:
            self.request_id = (PHYSICAL_REQUEST_BASE_29 | (ENGINE_ADDRESS << 8) if engine_only
                               else FUNCTIONAL_REQUEST_ID_29)
            self.engine_id = RESPONSE_BASE_29 | ENGINE_ADDRESS
        else:
            self.request_id = PHYSICAL_REQUEST_BASE_11 if engine_only else FUNCTIONAL_REQUEST_ID_11
            self.engine_id = ENGINE_RESPONSE_ID_11
        self.request_data = isotp_single_frame(SPEED_REQUEST)
        try:
            bus.set_filters([RESPONSE_FILTER_29 if extended_id else RESPONSE_FILTER_11])
        except (can.CanError, OSError) as e:
            raise BusError(f"cannot set CAN receive filter on {self._where()}: {e}") from e

    def close(self) -> None:
        """Shut the bus down: it is this driver's own (its receive filters were replaced), and a reconnect opens a
        new one."""
        try:
            self.bus.shutdown()
        except (can.CanError, OSError):
            pass  # the interface is already gone

    def read(self) -> ObdSpeed:
        """One request, then the engine ECU's answer, or the first other ECU's if the engine stays silent."""
        self._drop_stale()
        self._send()
        deadline = time.monotonic() + self.p2_timeout_s  # a wait limit, not a time stamp
        first: ObdSpeed | None = None
        refusal: str | None = None
        error_frames = 0
        while (left := deadline - time.monotonic()) > 0:
            msg = self._recv(left)
            if msg is None:
                break
            if msg.is_error_frame:
                error_frames += 1
                continue
            if not self._is_answer_id(msg):
                continue
            try:
                payload = isotp_single_frame_payload(bytes(msg.data))
            except ProtocolError:
                continue  # a multi-frame answer: not to a single-byte PID of ours
            if len(payload) >= 3 and payload[:2] == NEGATIVE_RESPONSE_PREFIX:
                refusal = f"ECU 0x{msg.arbitration_id:X} refused service 01 (code 0x{payload[2]:02X})"
                continue
            try:
                speed = ObdSpeed(decode_speed_payload(payload), msg.arbitration_id)
            except ProtocolError:
                continue  # another PID's or service's answer
            if msg.arbitration_id == self.engine_id:
                return speed
            if first is None:
                first = speed
        if first is not None:
            return first
        if error_frames:
            raise BusError(f"{error_frames} CAN error frame(s) and no answer to PID 0x0D on {self._where()}")
        if refusal is not None:
            raise NoData(refusal)
        raise NoData(f"no ECU answered PID 0x0D within {self.p2_timeout_s * 1e3:.0f} ms on {self._where()}: "
                     "ignition off?")

    def _send(self) -> None:
        msg = can.Message(arbitration_id=self.request_id, data=self.request_data, is_extended_id=self.extended_id)
        try:
            self.bus.send(msg, timeout=self.p2_timeout_s)
        except (can.CanError, OSError, ValueError) as e:
            raise BusError(f"CAN request failed on {self._where()}: {e}") from e

    def _recv(self, timeout_s: float) -> can.Message | None:
        try:
            return self.bus.recv(timeout=timeout_s)
        except (can.CanError, OSError, ValueError) as e:
            raise BusError(f"CAN receive failed on {self._where()}: {e}") from e

    def _drop_stale(self) -> None:
        """Answers still queued belong to an earlier request that was given up; they must not count now."""
        for _ in range(MAX_STALE_FRAMES):
            if self._recv(0.0) is None:
                return

    def _is_answer_id(self, msg: can.Message) -> bool:
        if msg.is_extended_id != self.extended_id:
            return False
        if self.extended_id:
            return msg.arbitration_id & 0x1FFFFF00 == RESPONSE_BASE_29
        return RESPONSE_BASE_11 <= msg.arbitration_id <= RESPONSE_BASE_11 + 7

    def _where(self) -> str:
        return str(getattr(self.bus, "channel_info", None) or "the CAN bus")
