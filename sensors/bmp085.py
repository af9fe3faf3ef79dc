"""Bosch BMP085 / BMP180 barometer over I2C (smbus2): calibration, conversions, compensation, altitude.

The compensation is Bosch's integer algorithm exactly as the reference C code computes it on a board with
32-bit ``long``: right shifts of negative numbers are arithmetic (they round down) while ``/`` truncates
toward zero, and B4/B7 are unsigned 32-bit. Float re-implementations differ from the chip's own figures
by a pascal or two, which is why the arithmetic is copied rather than derived.

Each reading is a temperature conversion followed by a pressure conversion; the driver waits the
datasheet's maximum conversion times through an injected ``sleep`` so that a test or a simulated drive
waits drive time, not wall time. The BMP180 also reports an unfinished conversion in bit 5 (Sco) of
register 0xF4, which the driver checks; the BMP085 has no such bit, so there the wait is all there is.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple, TypeVar

from sensors.errors import NoData, ProtocolError, WrongDevice
from sensors.i2c import i2c_transfer

log = logging.getLogger(__name__)

DEFAULT_ADDRESS = 0x77
CHIP_ID_VALUE = 0x55

CALIBRATION_START = 0xAA  # 11 big-endian words, 0xAA..0xBF
CALIBRATION_NAMES = ("AC1", "AC2", "AC3", "AC4", "AC5", "AC6", "B1", "B2", "MB", "MC", "MD")
CHIP_ID = 0xD0
SOFT_RESET = 0xE0
CTRL_MEAS = 0xF4
OUT_MSB = 0xF6

CMD_TEMPERATURE = 0x2E
CMD_PRESSURE = 0x34  # + (oss << 6)
CTRL_SCO = 0x20  # BMP180: set while a conversion runs

TEMPERATURE_WAIT_S = 4.5e-3
PRESSURE_WAIT_S = (4.5e-3, 7.5e-3, 13.5e-3, 25.5e-3)  # per oversampling setting, datasheet maxima
SCO_POLL_S = 1.0e-3
SCO_POLLS = 10

PRESSURE_RANGE_PA = (30000, 110000)  # the chip's operating range, 300..1100 hPa
TEMPERATURE_RANGE_DEGC = (-40.0, 85.0)
# A reading is refused as garbled only this far outside the rated range: at the range's edges the chip is still
# measuring (its accuracy there is +-2 degC and +-2.5 hPa, and the datasheet's integer compensation gives 110001 Pa
# at 1100 hPa with oversampling 0), and a car's cabin in the sun passes 85 degC. Inside the margin the reading is
# kept, and the log says once that it lies outside the rated range.
PRESSURE_MARGIN_PA = 5000
TEMPERATURE_MARGIN_DEGC = 20.0
# The result registers' power-on values (0xF6 0x80, 0xF7 0x00, 0xF8 0x00): read back unchanged when no conversion
# ran (a BMP085, which has no Sco bit to poll, whose conversions never start). They compensate to a plausible
# pressure, identical every time.
UT_RESET = 0x8000
UP_RESET = 0x800000

# Eq. 4 of the paper (the standard atmosphere's troposphere): T0, P0, temperature gradient, R, g.
ISA_T0_DEGC = 15.0
ISA_P0_PA = 101325.0
ISA_LAPSE_K_PER_M = -0.0065  # Gamma: dT/dh, temperature falls with height
# J/(kg K). The paper prints 287.058 (today's molar gas constant over the molar mass of air); the standard
# atmosphere, which Eq. 4 is and which altimeters follow, defines 287.05287. The exponent then is the
# familiar 0.190263 (1/5.25588); the paper's figure would read 4 cm higher at 3000 m.
GAS_CONSTANT_AIR = 287.05287
STANDARD_GRAVITY_MPS2 = 9.80665


class Bmp085Calibration(NamedTuple):
    """The factory calibration EEPROM: AC4..AC6 unsigned, the rest signed 16-bit."""

    ac1: int
    ac2: int
    ac3: int
    ac4: int
    ac5: int
    ac6: int
    b1: int
    b2: int
    mb: int
    mc: int
    md: int

    @classmethod
    def from_bytes(cls, raw: bytes) -> Bmp085Calibration:
        words = [int.from_bytes(raw[i: i + 2], "big") for i in range(0, 22, 2)]
        signed = [w - 0x10000 if w & 0x8000 else w for w in words]
        return cls(*signed[0:3], *words[3:6], *signed[6:11])

    def to_bytes(self) -> bytes:
        return b"".join((v & 0xFFFF).to_bytes(2, "big") for v in self)


DATASHEET_EXAMPLE_CALIBRATION = Bmp085Calibration(408, -72, -14383, 32741, 32757, 23153, 6190, 4, -32768,
                                                  -8711, 2868)


def _c_div(a: int, b: int) -> int:
    """C's integer division: truncates toward zero."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b >= 0) else -q


def _s32(v: int) -> int:
    """A 32-bit ``long`` after an operation: wraps around as two's complement, as on the board."""
    v &= 0xFFFFFFFF
    return v - 0x100000000 if v & 0x80000000 else v


def _u32(v: int) -> int:
    return v & 0xFFFFFFFF


def compensate_temperature(ut: int, cal: Bmp085Calibration) -> tuple[int, int]:
    """Temperature in 0.1 degC and the B5 the pressure compensation needs."""
    x1 = _s32((ut - cal.ac6) * cal.ac5) >> 15
    if x1 + cal.md == 0:
        raise ProtocolError(f"BMP085/BMP180 raw temperature {ut} is outside what the calibration covers")
    x2 = _c_div(cal.mc << 11, _s32(x1 + cal.md))
    b5 = _s32(x1 + x2)
    return (b5 + 8) >> 4, b5


def compensate_pressure(up: int, oss: int, b5: int, cal: Bmp085Calibration) -> int:
    """Pressure in Pa from the raw value, the oversampling setting and the temperature's B5."""
    b6 = _s32(b5 - 4000)
    x1 = _s32(_s32(b6 * b6) >> 12) * cal.b2
    x1 = _s32(x1) >> 11
    x2 = _s32(cal.ac2 * b6) >> 11
    x3 = _s32(x1 + x2)
    b3 = _s32(_s32(_s32(cal.ac1 * 4 + x3) << oss) + 2) >> 2
    x1 = _s32(cal.ac3 * b6) >> 13
    x2 = _s32(cal.b1 * (_s32(b6 * b6) >> 12)) >> 16
    x3 = _s32(x1 + x2 + 2) >> 2
    b4 = _u32(cal.ac4 * _u32(x3 + 32768)) >> 15
    if b4 == 0:
        raise ProtocolError("BMP085/BMP180 calibration gives B4 = 0: calibration words are corrupt")
    b7 = _u32(_u32(up - b3) * (50000 >> oss))
    p = _s32(_u32(b7 << 1) // b4) if b7 < 0x80000000 else _s32(_u32((b7 // b4) << 1))
    x1 = _s32((p >> 8) * (p >> 8))
    x1 = _s32(x1 * 3038) >> 16
    x2 = _s32(-7357 * p) >> 16
    return _s32(p + ((x1 + x2 + 3791) >> 4))


def pressure_altitude_m(pressure_pa: float, reference_pa: float = ISA_P0_PA) -> float:
    """Height by the paper's Eq. 4: H = (273.15 + T0)/Gamma * ((P/P0)^(-Gamma R/g) - 1).

    With Gamma the temperature gradient (-6.5 K/km) this is the standard atmosphere's barometric
    formula; with the day's sea-level pressure (QNH) as P0 it is height above mean sea level.
    """
    exponent = -ISA_LAPSE_K_PER_M * GAS_CONSTANT_AIR / STANDARD_GRAVITY_MPS2
    return (273.15 + ISA_T0_DEGC) / ISA_LAPSE_K_PER_M * ((pressure_pa / reference_pa) ** exponent - 1.0)


@dataclass(frozen=True, slots=True)
class BaroSample:
    """One compensated reading, with the raw values so the compensation can be replayed."""

    temp_degc: float
    pressure_pa: float
    altitude_m: float  # pressure altitude by Eq. 4 against the driver's reference pressure
    ut: int
    up: int
    oss: int


_T = TypeVar("_T")


class Bmp085:
    """A BMP085 or BMP180 behind an ``smbus2.SMBus``-like bus; ``configure()`` again after any error."""

    def __init__(self, bus: Any, address: int = DEFAULT_ADDRESS, *, variant: str = "BMP180",
                 oversampling: int = 3, reference_pa: float = ISA_P0_PA, bus_name: str = "I2C",
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if variant not in ("BMP085", "BMP180"):
            raise ValueError(f"barometer variant {variant!r}: must be 'BMP085' or 'BMP180'")
        if oversampling not in range(4):
            raise ValueError(f"{variant} oversampling {oversampling}: must be 0, 1, 2 or 3 (1 to 8 samples)")
        if not 30000.0 <= reference_pa <= 110000.0:
            raise ValueError(f"{variant} reference pressure {reference_pa:g} Pa: expected sea-level "
                             "pressure in Pa (about 101325)")
        self.bus = bus
        self.address = address
        self.variant = variant
        self.oversampling = oversampling
        self.reference_pa = reference_pa
        self.bus_name = bus_name
        self._sleep = sleep
        self.calibration: Bmp085Calibration | None = None
        self._answered = False  # the chip has answered since configure() began: a NACK is then a bus fault
        self._outside_said = False  # a reading outside the rated range was logged (once a driver)

    def _bus(self, doing: str, fn: Callable[..., _T], *args: Any) -> _T:
        return i2c_transfer(self.variant, self.address, self.bus_name, doing, fn, *args, answered=self._answered)

    def configure(self) -> None:
        """Check the chip id and read and check the calibration EEPROM."""
        self._answered = False
        chip_id = self._bus("reading the chip id", self.bus.read_byte_data, CHIP_ID)
        self._answered = True
        if chip_id != CHIP_ID_VALUE:
            raise WrongDevice(f"{self.variant} at 0x{self.address:02x} on {self.bus_name}: chip id reads "
                              f"0x{chip_id:02x}, expected 0x55 (a BME280 reads 0x60, a BMP280 0x58)")
        raw = bytes(self._bus("reading the calibration", self.bus.read_i2c_block_data, CALIBRATION_START, 22))
        for i, name in enumerate(CALIBRATION_NAMES):
            word = int.from_bytes(raw[2 * i: 2 * i + 2], "big")
            if word in (0x0000, 0xFFFF):
                raise ProtocolError(f"{self.variant} calibration word {name} (0x{CALIBRATION_START + 2 * i:02X}) "
                                    f"reads 0x{word:04X}: EEPROM not readable, chip or bus fault")
        self.calibration = Bmp085Calibration.from_bytes(raw)

    def _convert(self, command: int, wait_s: float, n: int, what: str) -> int:
        self._bus(f"starting a {what} conversion", self.bus.write_byte_data, CTRL_MEAS, command)
        self._sleep(wait_s)
        if self.variant == "BMP180":
            for _ in range(SCO_POLLS):
                ctrl = self._bus(f"polling the {what} conversion", self.bus.read_byte_data, CTRL_MEAS)
                if not ctrl & CTRL_SCO:
                    break
                self._sleep(SCO_POLL_S)
            else:
                raise NoData(f"BMP180 {what} conversion still running {(wait_s + SCO_POLLS * SCO_POLL_S) * 1e3:.1f}"
                             " ms after its start (Sco bit stays set; a BMP085, which has no Sco bit? then set "
                             "[baro] variant = \"BMP085\")")
        raw = bytes(self._bus(f"reading the {what} result", self.bus.read_i2c_block_data, OUT_MSB, n))
        return int.from_bytes(raw, "big")

    def read(self) -> BaroSample:
        """A temperature then a pressure conversion, compensated; takes up to 30 ms of ``sleep``."""
        if self.calibration is None:
            self.configure()
        cal = self.calibration
        assert cal is not None
        oss = self.oversampling
        ut = self._convert(CMD_TEMPERATURE, TEMPERATURE_WAIT_S, 2, "temperature")
        up_word = self._convert(CMD_PRESSURE + (oss << 6), PRESSURE_WAIT_S[oss], 3, "pressure")
        if ut == UT_RESET and up_word == UP_RESET:
            raise NoData(f"{self.variant} result registers read their power-on values (0x8000 / 0x800000): no "
                         "conversion ran")
        up = up_word >> (8 - oss)
        t01, b5 = compensate_temperature(ut, cal)
        p = compensate_pressure(up, oss, b5, cal)
        temp_degc = t01 / 10.0
        t_lo, t_hi = TEMPERATURE_RANGE_DEGC
        if not t_lo - TEMPERATURE_MARGIN_DEGC <= temp_degc <= t_hi + TEMPERATURE_MARGIN_DEGC:
            raise ProtocolError(f"{self.variant} temperature {temp_degc:.1f} degC (raw {ut}) is far outside the "
                                "chip's -40..85 degC: garbled read")
        p_lo, p_hi = PRESSURE_RANGE_PA
        if not p_lo - PRESSURE_MARGIN_PA <= p <= p_hi + PRESSURE_MARGIN_PA:
            raise ProtocolError(f"{self.variant} pressure {p} Pa (raw {up}) is far outside the chip's 300..1100 "
                                "hPa: garbled read")
        if not (t_lo <= temp_degc <= t_hi and p_lo <= p <= p_hi) and not self._outside_said:
            self._outside_said = True
            log.warning("%s reads %.1f degC, %.0f Pa: outside its rated -40..85 degC, 300..1100 hPa (kept; less "
                        "accurate there)", self.variant, temp_degc, p)
        return BaroSample(temp_degc, float(p), pressure_altitude_m(p, self.reference_pa), ut, up, oss)


def isa_pressure_pa(height_msl_m: float, sea_level_pa: float = ISA_P0_PA) -> float:
    """Inverse of :func:`pressure_altitude_m`: pressure at a height in the standard atmosphere."""
    exponent = -ISA_LAPSE_K_PER_M * GAS_CONSTANT_AIR / STANDARD_GRAVITY_MPS2
    t0_k = 273.15 + ISA_T0_DEGC
    return sea_level_pa * (1.0 + ISA_LAPSE_K_PER_M * height_msl_m / t0_k) ** (1.0 / exponent)

