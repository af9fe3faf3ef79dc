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
"""

from __future__ import annotations

import numpy as np

from sensors.bmp085 import (
    DATASHEET_EXAMPLE_CALIBRATION,
    PRESSURE_NOISE_PA,
    Bmp085Calibration,
    compensate_pressure,
    compensate_temperature,
    isa_pressure_pa,
)
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


def raw_temperature_for(temp_degc: float, cal: Bmp085Calibration) -> int:
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
        if compensate_temperature(mid, cal)[1] >= target_b5:
            hi = mid
        else:
            lo = mid + 1
    if lo > first_valid and (target_b5 - compensate_temperature(lo - 1, cal)[1]
                             < compensate_temperature(lo, cal)[1] - target_b5):
        lo -= 1
    return lo


def raw_pressure_for(pressure_pa: float, b5: int, oss: int, cal: Bmp085Calibration) -> int:
    """The UP (16 + oss bits) whose compensated pressure lies nearest ``pressure_pa``."""
    b6 = b5 - 4000
    b3 = (((cal.ac1 * 4 + ((((b6 * b6) >> 12) * cal.b2) >> 11) + ((cal.ac2 * b6) >> 11)) << oss) + 2) >> 2
    lo, hi = max(b3, 0), (1 << (16 + oss)) - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if compensate_pressure(mid, oss, b5, cal) >= pressure_pa:
            hi = mid
        else:
            lo = mid + 1
    if lo > max(b3, 0) and (pressure_pa - compensate_pressure(lo - 1, oss, b5, cal)
                            < compensate_pressure(lo, oss, b5, cal) - pressure_pa):
        lo -= 1
    return lo


class Bmp085Model(RegisterChip):
    """A BMP085 or BMP180 as the bus sees it, measuring ``trajectory`` at the time ``clock`` tells."""

    def __init__(self, clock: DriveClock, trajectory: Trajectory, *, seed: int | np.random.Generator = 0,
                 variant: str = "BMP180", calibration: Bmp085Calibration = DATASHEET_EXAMPLE_CALIBRATION,
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
        _, b5 = compensate_temperature(ut, self.calibration)
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
