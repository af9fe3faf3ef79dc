"""Register-level model of the BMP085 / BMP180 barometer.

The chip holds its calibration in EEPROM at 0xAA..0xBF, answers 0x55 at 0xD0, starts a conversion when
0xF4 is written (0x2E temperature, 0x34 + (oss << 6) pressure), and only puts the result into
0xF6..0xF8 once the conversion time has passed: a driver that reads too early gets the previous result,
and on the BMP180 sees bit 5 (Sco) of 0xF4 still set. Conversion times are the datasheet's maxima, the
values a driver has to wait.

The raw values come from inverting Bosch's compensation by search (it is monotonic in UT and UP), so a
correct driver recovers the truth: the ambient temperature, and the standard-atmosphere pressure at the
truth's height above mean sea level for the day's sea-level pressure, plus the datasheet's RMS noise for
the oversampling setting.

The compensation inverted here is this module's own reading of the datasheet (section 3.5), not the
driver's (:mod:`sensors.bmp085`): the chip's side of the bus must not share a driver's mistake, or a test
of the driver against this model could not catch it. The datasheet's variables are 32-bit ``long`` (B4
and B7 ``unsigned long``), its "/ 2^n" is the reference code's arithmetic right shift and its "/" between
variables C's division, which truncates toward zero.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sensors.sim.clock import DriveClock
from sensors.sim.i2c import RegisterChip
from sensors.sim.truth import Trajectory

CALIBRATION_START = 0xAA
CHIP_ID = 0xD0
SOFT_RESET = 0xE0
CTRL_MEAS = 0xF4
OUT_MSB = 0xF6
OUT_XLSB = 0xF8
SOFT_RESET_CODE = 0xB6
SCO = 0x20
TEMPERATURE_TIME_S = 4.5e-3
PRESSURE_TIME_S = (4.5e-3, 7.5e-3, 13.5e-3, 25.5e-3)
OUT_RESET = b"\x80\x00\x00"
# Datasheet table 3 (typical RMS noise): 0.06, 0.05, 0.04, 0.03 hPa from ultra low power (oss 0) to
# ultra high resolution (oss 3).
PRESSURE_NOISE_PA = (6.0, 5.0, 4.0, 3.0)

# The International Standard Atmosphere's troposphere, which the truth's weather is expressed in: sea-level
# temperature and pressure, temperature gradient, specific gas constant of dry air, standard gravity.
ISA_T0_K = 288.15
ISA_P0_PA = 101325.0
ISA_LAPSE_K_PER_M = -0.0065
ISA_GAS_CONSTANT_AIR = 287.05287
ISA_GRAVITY_MPS2 = 9.80665


class EepromCalibration(NamedTuple):
    """The factory calibration as the EEPROM holds it, eleven big-endian words from 0xAA: AC4..AC6 are
    unsigned, the rest signed 16-bit."""

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

    def to_bytes(self) -> bytes:
        return b"".join((word & 0xFFFF).to_bytes(2, "big") for word in self)


# The calibration of the datasheet's worked example (section 3.5).
DATASHEET_EXAMPLE_CALIBRATION = EepromCalibration(
    ac1=408, ac2=-72, ac3=-14383, ac4=32741, ac5=32757, ac6=23153, b1=6190, b2=4, mb=-32768, mc=-8711, md=2868)


def isa_pressure_pa(height_msl_m: float, sea_level_pa: float = ISA_P0_PA) -> float:
    """Pressure at ``height_msl_m`` above mean sea level in the standard troposphere, for the day's
    sea-level pressure: p0 (1 + L h / T0) ^ (-g / (R L))."""
    exponent = -ISA_GRAVITY_MPS2 / (ISA_GAS_CONSTANT_AIR * ISA_LAPSE_K_PER_M)
    return sea_level_pa * (1.0 + ISA_LAPSE_K_PER_M * height_msl_m / ISA_T0_K) ** exponent


def _long(v: int) -> int:
    """``v`` as a 32-bit two's-complement ``long``: what the datasheet's integer arithmetic keeps."""
    return (v + 0x8000_0000) % 0x1_0000_0000 - 0x8000_0000


def _ulong(v: int) -> int:
    return v % 0x1_0000_0000


def _c_divide(a: int, b: int) -> int:
    """The datasheet's "/" between two variables: C division of longs, the quotient truncated toward zero."""
    quotient = abs(a) // abs(b)
    return quotient if (a < 0) == (b < 0) else -quotient


def datasheet_b5(ut: int, cal: EepromCalibration) -> int:
    """B5 of the datasheet's temperature calculation; the true temperature is (B5 + 8) / 2^4 in 0.1 degC."""
    x1 = _long((ut - cal.ac6) * cal.ac5) >> 15
    if x1 + cal.md == 0:
        raise ValueError(f"UT {ut} divides by X1 + MD = 0: no temperature of this calibration")
    x2 = _c_divide(_long(cal.mc << 11), _long(x1 + cal.md))
    return _long(x1 + x2)


def datasheet_pressure_pa(up: int, oss: int, b5: int, cal: EepromCalibration) -> int:
    """The datasheet's true pressure p (Pa) from UP, the oversampling setting and the temperature's B5."""
    b6 = _long(b5 - 4000)
    b6_squared = _long(b6 * b6) >> 12
    x1 = _long(cal.b2 * b6_squared) >> 11
    x2 = _long(cal.ac2 * b6) >> 11
    x3 = _long(x1 + x2)
    b3 = _long((_long(cal.ac1 * 4 + x3) << oss) + 2) >> 2
    x1 = _long(cal.ac3 * b6) >> 13
    x2 = _long(cal.b1 * b6_squared) >> 16
    x3 = _long(x1 + x2 + 2) >> 2
    b4 = _ulong(cal.ac4 * _ulong(x3 + 32768)) >> 15
    if b4 == 0:
        raise ValueError("the calibration gives B4 = 0: no pressure of this calibration")
    b7 = _ulong((up - b3) * (50000 >> oss))
    p = _long(_ulong(b7 * 2) // b4) if b7 < 0x8000_0000 else _long((b7 // b4) * 2)
    x1 = _long((p >> 8) * (p >> 8))
    x1 = _long(x1 * 3038) >> 16
    x2 = _long(-7357 * p) >> 16
    return _long(p + (_long(x1 + x2 + 3791) >> 4))


def raw_temperature_for(temp_degc: float, cal: EepromCalibration) -> int:
    """The UT whose compensated B5 lies nearest the true temperature (T = (B5 + 8) / 160 degC)."""
    target_b5 = temp_degc * 160.0 - 8.0
    # Below this UT the compensation divides by X1 + MD <= 0: no temperature lives there.
    lo, hi = 0, 0xFFFF
    while lo < hi:
        mid = (lo + hi) // 2
        if ((mid - cal.ac6) * cal.ac5 >> 15) + cal.md > 0:
            hi = mid
        else:
            lo = mid + 1
    first_valid = lo
    lo, hi = first_valid, 0xFFFF
    while lo < hi:
        mid = (lo + hi) // 2
        if datasheet_b5(mid, cal) >= target_b5:
            hi = mid
        else:
            lo = mid + 1
    if lo > first_valid and (target_b5 - datasheet_b5(lo - 1, cal)
                             < datasheet_b5(lo, cal) - target_b5):
        lo -= 1
    return lo


def raw_pressure_for(pressure_pa: float, b5: int, oss: int, cal: EepromCalibration) -> int:
    """The UP (16 + oss bits) whose compensated pressure lies nearest ``pressure_pa``."""
    b6 = b5 - 4000
    b3 = (((cal.ac1 * 4 + ((((b6 * b6) >> 12) * cal.b2) >> 11) + ((cal.ac2 * b6) >> 11)) << oss) + 2) >> 2
    lo, hi = max(b3, 0), (1 << (16 + oss)) - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if datasheet_pressure_pa(mid, oss, b5, cal) >= pressure_pa:
            hi = mid
        else:
            lo = mid + 1
    if lo > max(b3, 0) and (pressure_pa - datasheet_pressure_pa(lo - 1, oss, b5, cal)
                            < datasheet_pressure_pa(lo, oss, b5, cal) - pressure_pa):
        lo -= 1
    return lo


class Bmp085Model(RegisterChip):
    """A BMP085 or BMP180 as the bus sees it, measuring ``trajectory`` at the time ``clock`` tells."""

    def __init__(self, clock: DriveClock, trajectory: Trajectory, *, seed: int | np.random.Generator = 0,
                 variant: str = "BMP180", calibration: EepromCalibration = DATASHEET_EXAMPLE_CALIBRATION,
                 noise: bool = True, chip_id: int = 0x55) -> None:
        super().__init__()
        if variant not in ("BMP085", "BMP180"):
            raise ValueError(f"variant {variant!r}: 'BMP085' or 'BMP180'")
        self.clock = clock
        self.trajectory = trajectory
        self.rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        self.variant = variant
        self.calibration = calibration
        self.eeprom = bytearray(calibration.to_bytes())  # tests may corrupt a word, as a failing chip does
        self.noise = noise
        self.chip_id = chip_id
        self.conversions = 0
        self.power_on_reset()

    def power_on_reset(self) -> None:
        self._ctrl = 0
        self._out = bytearray(OUT_RESET)
        self._pending: tuple[int, int] | None = None  # (ctrl value, end time ns)
        self.pointer = 0

    def _catch_up(self) -> None:
        if self._pending is None:
            return
        ctrl, end_ns = self._pending
        if self.clock.now_ns() < end_ns:
            return
        self._pending = None
        state = self.trajectory.state(end_ns / 1e9)
        ut = raw_temperature_for(state.ambient_degc, self.calibration)
        if ctrl & 0x3F == 0x2E:
            self._out[0:2] = ut.to_bytes(2, "big")
            return
        oss = ctrl >> 6
        pressure = isa_pressure_pa(state.height_msl_m, state.sea_level_pa)
        if self.noise:
            pressure += self.rng.standard_normal() * PRESSURE_NOISE_PA[oss]
        b5 = datasheet_b5(ut, self.calibration)
        up = raw_pressure_for(pressure, b5, oss, self.calibration)
        self._out[0:3] = (up << (8 - oss)).to_bytes(3, "big")

    def read(self, reg: int, n: int) -> bytes:
        self._catch_up()
        out = bytearray()
        for r in range(reg, reg + n):
            r &= 0xFF
            if CALIBRATION_START <= r < CALIBRATION_START + 22:
                out.append(self.eeprom[r - CALIBRATION_START])
            elif r == CHIP_ID:
                out.append(self.chip_id)
            elif r == CTRL_MEAS:
                busy = self._pending is not None
                if self.variant == "BMP180":
                    out.append((self._ctrl & ~SCO) | (SCO if busy else 0))
                else:
                    out.append(self._ctrl)
            elif OUT_MSB <= r <= OUT_XLSB:
                out.append(self._out[r - OUT_MSB])
            else:
                out.append(0)
        return bytes(out)

    def write(self, reg: int, data: bytes) -> None:
        self._catch_up()
        for i, value in enumerate(data):
            r = (reg + i) & 0xFF
            if r == SOFT_RESET and value == SOFT_RESET_CODE:
                self.power_on_reset()
            elif r == CTRL_MEAS:
                self._ctrl = value
                if value & 0x3F == 0x2E:
                    duration = TEMPERATURE_TIME_S
                elif value & 0x3F == 0x34:
                    duration = PRESSURE_TIME_S[value >> 6]
                else:
                    self._pending = None
                    continue
                self._pending = (value, self.clock.now_ns() + round(duration * 1e9))
                self.conversions += 1
