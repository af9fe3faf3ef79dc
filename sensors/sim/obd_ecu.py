"""The vehicle's control units as an OBD-II scan tool sees them: service 01 answers from the true drive.

An ECU's speed is not the truth. It counts wheel-sensor pulses over a fixed window, so its value is held
between updates; it assumes a nominal tyre circumference, so it is off by a scale factor of a few percent
(the paper's ``s`` in V = (1 + s) u); and J1979 sends it as whole km/h in one byte, so it is quantised
and clipped at 255. With the ignition off the ECU is unpowered and says nothing at all.

The model answers payloads only (``41 0D 32``); the bus models (CAN frames, ELM327 text) wrap them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from sensors.sim.clock import NS_PER_S
from sensors.sim.truth import Trajectory

SERVICE_CURRENT_DATA = 0x01
PID_SUPPORTED_01_20 = 0x00
PID_VEHICLE_SPEED = 0x0D


@dataclass
class ObdEcu:
    """One ECU on the diagnostic bus.

    ``response_id_11`` is its ISO 15765-4 11-bit answer id (0x7E8 engine, 0x7E9 transmission, ...);
    ``address`` is its source address on 29-bit CAN and on J1850 / ISO 9141 / KWP (0x10 engine, 0x18
    transmission). ``scale_error`` is the paper's ``s``: the true speed is (1 + s) times what the ECU
    reports. ``silent`` is a fault to inject: the ECU stops answering though the ignition is on.
    """

    trajectory: Trajectory
    response_id_11: int = 0x7E8
    address: int = 0x10
    scale_error: float = 0.0
    update_period_s: float = 0.1
    supported_pids: frozenset[int] = field(default_factory=lambda: frozenset({PID_VEHICLE_SPEED}))
    silent: bool = False

    def __post_init__(self) -> None:
        if not 0x7E8 <= self.response_id_11 <= 0x7EF:
            raise ValueError(f"ISO 15765-4 answers come from 0x7E8..0x7EF, not 0x{self.response_id_11:X}")
        if not 0 <= self.address <= 0xFF:
            raise ValueError(f"an ECU address is one byte, not 0x{self.address:X}")
        if self.scale_error <= -1.0:
            raise ValueError("scale error must be above -1 (the ECU would report infinite speed)")
        if self.update_period_s < 0:
            raise ValueError("update period cannot be negative")

    @property
    def request_id_11(self) -> int:
        """The physical request id this ECU listens on: its answer id minus 8."""
        return self.response_id_11 - 8

    def powered(self, t_ns: int) -> bool:
        return self.trajectory.state(t_ns / NS_PER_S).engine_on

    def on_the_bus(self, t_ns: int) -> bool:
        """Whether it takes part in traffic at all: what a scan tool's protocol search finds."""
        return not self.silent and self.powered(t_ns)

    def speed_kmh(self, t_ns: int) -> int | None:
        """The speed byte the ECU holds at true time ``t_ns``; ``None`` while it is unpowered."""
        hold_ns = self._last_update_ns(t_ns)
        state = self.trajectory.state(hold_ns / NS_PER_S)
        if not state.engine_on:
            return None
        kmh = abs(state.forward_speed_mps) * 3.6 / (1.0 + self.scale_error)
        return min(255, math.floor(kmh + 0.5))

    def answer(self, request: bytes, t_ns: int) -> bytes | None:
        """The positive response payload to ``request`` at true time ``t_ns``, or ``None`` for silence.

        J1979 says an ECU does not answer a service 01 PID it does not support, so unsupported requests
        and malformed ones get silence, as on a real bus. One PID per request: that is what scan tools
        and both our drivers send.
        """
        if self.silent or not self.powered(t_ns):
            return None
        if len(request) != 2 or request[0] != SERVICE_CURRENT_DATA:
            return None
        pid = request[1]
        if pid == PID_SUPPORTED_01_20:
            return bytes([0x41, pid]) + self._supported_bitmap(0x01).to_bytes(4, "big")
        if pid not in self.supported_pids:
            return None
        if pid == PID_VEHICLE_SPEED:
            kmh = self.speed_kmh(t_ns)
            return None if kmh is None else bytes([0x41, pid, kmh])
        return None

    def _supported_bitmap(self, first_pid: int) -> int:
        """J1979 'PIDs supported' word: bit 31 is ``first_pid``, bit 0 is ``first_pid + 31``."""
        bits = 0
        for pid in self.supported_pids:
            if first_pid <= pid < first_pid + 32:
                bits |= 1 << (31 - (pid - first_pid))
        return bits

    def _last_update_ns(self, t_ns: int) -> int:
        period_ns = round(self.update_period_s * NS_PER_S)
        if period_ns <= 0:
            return t_ns
        return (t_ns // period_ns) * period_ns


def engine_ecu(trajectory: Trajectory, scale_error: float = 0.0, update_period_s: float = 0.1) -> ObdEcu:
    """ECU #0, the engine controller: 0x7E8 on CAN, address 0x10 elsewhere."""
    return ObdEcu(trajectory, 0x7E8, 0x10, scale_error, update_period_s)


def transmission_ecu(trajectory: Trajectory, scale_error: float = 0.0, update_period_s: float = 0.1) -> ObdEcu:
    """ECU #1, the transmission controller: 0x7E9 on CAN, address 0x18 elsewhere."""
    return ObdEcu(trajectory, 0x7E9, 0x18, scale_error, update_period_s)
