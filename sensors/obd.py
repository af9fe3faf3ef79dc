"""OBD-II vehicle speed (service 01, PID 0x0D): what the ELM327 and the native CAN driver share.

The paper reads the vehicle's own speed through OBD-II because it bounds INS velocity drift in urban
canyons. SAE J1979 defines it as one byte, km/h, 0..255, so the driver keeps the ECU's integer as it came
(the navigation filter estimates the scale error of exactly that number) and gives m/s beside it.

The ISO 15765-4 constants live here too: the functional request ids, the response id ranges and the
single-frame layout, which the CAN driver uses directly and the ELM327 driver needs to read headers. So do
the check bytes of the older buses' frames (SAE J1850 CRC-8, ISO 9141-2 / ISO 14230-4 sum), which the
ELM327 shows with headers on (the adapter model computes them on its own, from the standards).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field

from sensors.errors import ProtocolError

SERVICE_CURRENT_DATA = 0x01
POSITIVE_RESPONSE_OFFSET = 0x40  # a positive answer to service s carries s + 0x40
NEGATIVE_RESPONSE_SID = 0x7F
PID_VEHICLE_SPEED = 0x0D

SPEED_REQUEST = bytes([SERVICE_CURRENT_DATA, PID_VEHICLE_SPEED])
SPEED_RESPONSE_PREFIX = bytes([SERVICE_CURRENT_DATA + POSITIVE_RESPONSE_OFFSET, PID_VEHICLE_SPEED])
ELM_SPEED_COMMAND = SPEED_REQUEST.hex().upper()  # "010D": what an ELM327 is sent

KMH_PER_MPS = 3.6

# ISO 15765-4, 11-bit identifiers: the tester asks everyone on 0x7DF, ECU #n listens on 0x7E0+n and
# answers from 0x7E8+n. ECU #0 (0x7E8) is the engine controller on every vehicle the standard covers.
FUNCTIONAL_REQUEST_ID_11 = 0x7DF
PHYSICAL_REQUEST_BASE_11 = 0x7E0
RESPONSE_BASE_11 = 0x7E8
ENGINE_RESPONSE_ID_11 = 0x7E8

# ISO 15765-4, 29-bit identifiers (normal fixed addressing): priority 0x18, PF 0xDB functional / 0xDA
# physical, target address, source address. The tester is 0xF1, the engine ECU conventionally 0x10.
TESTER_ADDRESS = 0xF1
FUNCTIONAL_REQUEST_ID_29 = 0x18DB33F1
RESPONSE_BASE_29 = 0x18DAF100  # | source address of the answering ECU
PHYSICAL_REQUEST_BASE_29 = 0x18DA00F1  # | (ECU address << 8)
ENGINE_ADDRESS = 0x10

ISOTP_PADDING = 0x55  # ISO 15765-4 wants DLC 8; unused bytes are filled
CAN_FRAME_BYTES = 8


@dataclass(frozen=True, slots=True)
class ObdSpeed:
    """One answer to PID 0x0D.

    ``ecu_id`` names who answered: the CAN identifier (0x7E8, 0x18DAF110) on CAN, the source address byte
    (0x10) on the older K-line and J1850 buses, ``None`` when the ELM327 was told to hide headers.
    """

    speed_kmh: int
    ecu_id: int | None = None
    speed_mps: float = field(init=False)

    def __post_init__(self) -> None:
        if not 0 <= self.speed_kmh <= 255:
            raise ValueError(f"PID 0x0D speed is one byte, got {self.speed_kmh} km/h")
        object.__setattr__(self, "speed_mps", self.speed_kmh / KMH_PER_MPS)


def decode_speed_payload(payload: bytes) -> int:
    """The speed byte of a service 01 answer ``41 0D A``; anything else is not our answer."""
    if len(payload) < 3 or payload[:2] != SPEED_RESPONSE_PREFIX:
        raise ProtocolError(f"not an answer to PID 0x0D: {payload.hex(' ').upper() or 'empty'}")
    return payload[2]


def isotp_single_frame(payload: bytes, padding: int = ISOTP_PADDING) -> bytes:
    """An ISO 15765-2 single frame: length nibble, payload, padding up to the 8 bytes ISO 15765-4 requires."""
    if not 1 <= len(payload) <= 7:
        raise ValueError(f"a single frame carries 1..7 bytes, not {len(payload)}")
    return bytes([len(payload)]) + payload + bytes([padding]) * (CAN_FRAME_BYTES - 1 - len(payload))


def isotp_single_frame_payload(data: bytes) -> bytes:
    """The payload of a single frame; first, consecutive and flow-control frames are refused."""
    if not data:
        raise ProtocolError("empty CAN frame")
    frame_type, length = data[0] >> 4, data[0] & 0x0F
    if frame_type != 0:
        raise ProtocolError(f"not an ISO-TP single frame (PCI 0x{data[0]:02X})")
    if not 1 <= length <= len(data) - 1:
        raise ProtocolError(f"ISO-TP length {length} does not fit a {len(data)}-byte frame")
    return bytes(data[1 : 1 + length])


def j1850_crc(data: bytes) -> int:
    """SAE J1850 CRC-8 (polynomial 0x1D, preset 0xFF, inverted), the check byte of PWM and VPW frames."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def kline_checksum(data: bytes) -> int:
    """ISO 9141-2 / ISO 14230-4 check byte: the sum of the header and data bytes, modulo 256."""
    return sum(data) & 0xFF


class SpeedDriver(ABC):
    """What every vehicle-speed driver offers, whatever the interface (ELM327 adapter, native CAN).

    The optional parts have their defaults here, as python-can's ``BusABC`` does, so the code that runs a driver
    reads the contract in one place instead of probing each driver for what it might have.
    """

    # The caller's monotonic clock (ns), set by whoever stamps the speeds. A driver that may do more than the
    # speed request inside one read (an ELM327 set up again after it reset, its protocol asked after the answer)
    # times the request that was answered by it: ``answered_window_ns`` (None: the whole read is the window).
    clock: Callable[[], int] | None = None
    answered_window_ns: tuple[int, int] | None = None

    def open(self) -> None:  # noqa: B027 - optional: a driver handed a ready bus has nothing to set up
        """Set the interface up (an adapter's reset and protocol search); nothing for a bus handed over ready."""

    @abstractmethod
    def read(self) -> ObdSpeed:
        """One request for the vehicle speed and its answer; raises a :class:`sensors.errors.SensorError`."""

    def close(self) -> None:  # noqa: B027 - optional: nothing to release by default
        """Release the interface; never raises for one that is already gone."""

    def incidents(self) -> dict[str, int]:
        """Cumulative counts of faults the driver recovered from by itself (an adapter that reset); none here."""
        return {}
