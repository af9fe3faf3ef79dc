"""BMP085/BMP180: Bosch's integer compensation, Eq. 4, and the driver against the register model.

The model has its own reading of the datasheet (it does not import the driver), so where both are checked
against the datasheet and Bosch's C code they are checked separately.
"""

from __future__ import annotations

import errno
import math
import shutil
import subprocess

import numpy as np
import pytest

from sensors.bmp085 import (
    DATASHEET_EXAMPLE_CALIBRATION,
    Bmp085,
    Bmp085Calibration,
    compensate_pressure,
    compensate_temperature,
    isa_pressure_pa,
    pressure_altitude_m,
)
from sensors.errors import BusError, DeviceNotFound, NoData, ProtocolError, WrongDevice
from sensors.sim import bmp085 as chip
from sensors.sim.bmp085 import (
    Bmp085Model,
    EepromCalibration,
    datasheet_b5,
    datasheet_pressure_pa,
    raw_pressure_for,
    raw_temperature_for,
)
from sensors.sim.clock import ManualClock
from sensors.sim.i2c import SimI2cAdapter, SimI2cBus
from sensors.sim.truth import ParkedTrajectory

# A calibration read from a BMP180 in the field, to check more than the datasheet's own set.
FIELD_CALIBRATION = Bmp085Calibration(7911, -934, -14306, 31567, 25671, 18974, 5498, 46, -32768, -11075, 2432)

# Computed by Bosch's bmp085.c compensation compiled with gcc, long = int32_t as on armv7:
# (calibration set, UT, UP, oss, T [0.1 degC], B5, p [Pa]). Several lie outside the physical range on
# purpose: there the C arithmetic wraps and truncates, and so must ours.
C_REFERENCE = [
    (0, 27898, 23843, 0, 150, 2400, 69964),
    (0, 27898, 23843, 3, 150, 2400, 7831),
    (0, 21000, 40000, 1, -1694, -27104, 36998),
    (0, 30000, 300000, 3, 313, 5008, 114861),
    (0, 24000, 90000, 2, -247, -3957, 60132),
    (0, 26000, 35000, 0, -17, -276, 99487),
    (0, 31000, 150000, 2, 386, 6179, 116674),
    (0, 20000, 60000, 1, 3729, 59665, 2105791),
    (0, 25000, 300000, 3, -121, -1938, 104168),
    (0, 33000, 20000, 0, 528, 8440, 63478),
    (1, 27898, 23843, 0, 287, 4584, 51067),
    (1, 27898, 23843, 3, 287, 4584, 255989),
    (1, 21000, 40000, 1, -253, -4056, 31475),
    (1, 30000, 300000, 3, 412, 6588, 97888),
    (1, 24000, 90000, 2, 24, 376, 42719),
    (1, 26000, 35000, 0, 165, 2646, 83740),
    (1, 31000, 150000, 2, 469, 7508, 99382),
    (1, 20000, 60000, 1, -388, -6208, 57115),
    (1, 25000, 300000, 3, 97, 1549, 89769),
    (1, 33000, 20000, 0, 581, 9298, 42949),
]

BOSCH_C = r"""
#include <stdio.h>
#include <stdint.h>
typedef int32_t s32; typedef uint32_t u32;
static short ac1,ac2,ac3,b1,b2,mb,mc,md; static unsigned short ac4,ac5,ac6; static s32 param_b5;
static short temp(u32 ut){ s32 x1,x2; x1=(((s32)ut-(s32)ac6)*(s32)ac5)>>15; x2=((s32)mc<<11)/(x1+md);
 param_b5=x1+x2; return (short)((param_b5+8)>>4);}
static s32 pres(u32 up,int oss){ s32 pressure,x1,x2,x3,b3,b6; u32 b4,b7;
 b6=param_b5-4000; x1=(b6*b6)>>12; x1*=b2; x1>>=11; x2=(ac2*b6); x2>>=11; x3=x1+x2;
 b3=(((((s32)ac1)*4+x3)<<oss)+2)>>2;
 x1=(ac3*b6)>>13; x2=(b1*((b6*b6)>>12))>>16; x3=((x1+x2)+2)>>2;
 b4=(ac4*(u32)(x3+32768))>>15; if(b4==0) return INT32_MIN; b7=((u32)(up-b3)*(50000>>oss));
 if(b7<0x80000000) pressure=(b7<<1)/b4; else pressure=(b7/b4)<<1;
 x1=pressure>>8; x1*=x1; x1=(x1*3038)>>16; x2=(pressure*-7357)>>16; pressure+=(x1+x2+3791)>>4;
 return pressure;}
int main(void){ int c[11]; unsigned ut,up; int oss;
 while(scanf("%d %d %d %d %d %d %d %d %d %d %d %u %u %d",&c[0],&c[1],&c[2],&c[3],&c[4],&c[5],&c[6],&c[7],
             &c[8],&c[9],&c[10],&ut,&up,&oss)==14){
  ac1=c[0];ac2=c[1];ac3=c[2];ac4=c[3];ac5=c[4];ac6=c[5];b1=c[6];b2=c[7];mb=c[8];mc=c[9];md=c[10];
  if((((s32)ut-(s32)ac6)*(s32)ac5>>15)+md==0){printf("skip\n");continue;}
  short t=temp(ut); s32 p=pres(up,oss); if(p==INT32_MIN){printf("skip\n");continue;}
  printf("%d %d %d\n",t,param_b5,p);}
 return 0;}
"""


# ---- the compensation ------------------------------------------------------------------------------
def test_datasheet_worked_example() -> None:
    t01, b5 = compensate_temperature(27898, DATASHEET_EXAMPLE_CALIBRATION)
    assert t01 == 150  # 15.0 degC
    assert compensate_pressure(23843, 0, b5, DATASHEET_EXAMPLE_CALIBRATION) == 69964


@pytest.mark.parametrize(("cal_set", "ut", "up", "oss", "t01", "b5", "p"), C_REFERENCE)
def test_matches_bosch_c_code(cal_set, ut, up, oss, t01, b5, p) -> None:
    cal = (DATASHEET_EXAMPLE_CALIBRATION, FIELD_CALIBRATION)[cal_set]
    assert compensate_temperature(ut, cal) == (t01, b5)
    assert compensate_pressure(up, oss, b5, cal) == p


def test_model_has_the_datasheet_example_and_its_result() -> None:
    cal = chip.DATASHEET_EXAMPLE_CALIBRATION
    assert tuple(cal) == tuple(DATASHEET_EXAMPLE_CALIBRATION)
    b5 = datasheet_b5(27898, cal)
    assert (b5 + 8) >> 4 == 150  # 15.0 degC
    assert datasheet_pressure_pa(23843, 0, b5, cal) == 69964


@pytest.mark.parametrize(("cal_set", "ut", "up", "oss", "t01", "b5", "p"), C_REFERENCE)
def test_model_compensation_matches_bosch_c_code(cal_set, ut, up, oss, t01, b5, p) -> None:
    """The model's own reading of the datasheet agrees with Bosch's code, wraps and truncations included."""
    cal = EepromCalibration(*(DATASHEET_EXAMPLE_CALIBRATION, FIELD_CALIBRATION)[cal_set])
    assert datasheet_b5(ut, cal) == b5
    assert (b5 + 8) >> 4 == t01
    assert datasheet_pressure_pa(up, oss, b5, cal) == p


def test_division_truncates_toward_zero() -> None:
    # X2 = MC * 2^11 / (X1 + MD) = -17840128 / 7611 = -2343.99...: C gives -2343, floor division -2344.
    assert compensate_temperature(27898, DATASHEET_EXAMPLE_CALIBRATION)[1] == 4743 - 2343


@pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc for the C reference")
def test_random_inputs_match_compiled_bosch_code(tmp_path) -> None:
    source = tmp_path / "bosch.c"
    source.write_text(BOSCH_C)
    binary = tmp_path / "bosch"
    subprocess.run(["gcc", "-O0", "-fwrapv", "-o", str(binary), str(source)], check=True, timeout=60)
    rng = np.random.default_rng(2018)
    cases = []
    for _ in range(400):
        cal = Bmp085Calibration(
            int(rng.integers(6000, 10000)), int(rng.integers(-1500, 0)), int(rng.integers(-15000, -13000)),
            int(rng.integers(30000, 35000)), int(rng.integers(24000, 33000)), int(rng.integers(17000, 24000)),
            int(rng.integers(5000, 7000)), int(rng.integers(1, 60)), -32768, int(rng.integers(-12000, -8000)),
            int(rng.integers(2300, 3000)))
        oss = int(rng.integers(0, 4))
        cases.append((cal, int(rng.integers(15000, 40000)), int(rng.integers(0, 1 << (16 + oss))), oss))
    stdin = "".join(" ".join(map(str, (*cal, ut, up, oss))) + "\n" for cal, ut, up, oss in cases)
    out = subprocess.run([str(binary)], input=stdin, capture_output=True, text=True, check=True, timeout=60)
    checked = 0
    for (cal, ut, up, oss), line in zip(cases, out.stdout.splitlines(), strict=True):
        if line == "skip":
            continue
        t01, b5, p = map(int, line.split())
        got_t01, got_b5 = compensate_temperature(ut, cal)
        assert ((got_t01 + 32768) % 65536 - 32768, got_b5) == (t01, b5)  # the C function returns a short
        assert compensate_pressure(up, oss, got_b5, cal) == p
        checked += 1
    assert checked > 350


def test_calibration_words_round_trip() -> None:
    raw = DATASHEET_EXAMPLE_CALIBRATION.to_bytes()
    assert raw[:2] == (408).to_bytes(2, "big")
    assert raw[16:18] == b"\x80\x00"  # MB = -32768
    assert Bmp085Calibration.from_bytes(raw) == DATASHEET_EXAMPLE_CALIBRATION


# ---- Eq. 4 -----------------------------------------------------------------------------------------
def test_eq4_equals_the_isa_barometric_formula() -> None:
    for p in np.linspace(30000.0, 110000.0, 161):
        isa = 44330.8 * (1.0 - (p / 101325.0) ** 0.190263)
        assert abs(pressure_altitude_m(p) - isa) < 0.01


def test_eq4_sign_and_reference() -> None:
    assert pressure_altitude_m(100000.0) == pytest.approx(110.9, abs=0.05)
    assert pressure_altitude_m(101325.0) == 0.0
    assert pressure_altitude_m(102000.0) < 0.0
    # With the day's sea-level pressure (QNH) as the reference, a station at QNH is at sea level.
    assert pressure_altitude_m(100600.0, reference_pa=100600.0) == 0.0
    assert pressure_altitude_m(100000.0, reference_pa=100600.0) == pytest.approx(
        44330.8 * (1 - (100000 / 100600) ** 0.190263), abs=0.01)


def test_isa_pressure_inverts_eq4() -> None:
    for h in (-300.0, 0.0, 40.0, 1500.0, 8000.0):
        assert pressure_altitude_m(isa_pressure_pa(h, 100800.0), 100800.0) == pytest.approx(h, abs=1e-6)


# ---- the model's inversion -------------------------------------------------------------------------
@pytest.mark.parametrize("cal", [DATASHEET_EXAMPLE_CALIBRATION, FIELD_CALIBRATION])
def test_model_inverts_the_compensation(cal) -> None:
    """The raw words the model makes for a truth give that truth back through the driver's compensation."""
    words = EepromCalibration(*cal)
    for temp in (-20.0, 0.0, 15.0, 31.7, 60.0):
        ut = raw_temperature_for(temp, words)
        t01, b5 = compensate_temperature(ut, cal)
        assert abs((b5 + 8) / 160 - temp) <= 0.01
        assert abs(t01 / 10 - temp) <= 0.1
        for oss in range(4):
            for p in (70000.0, 95000.5, 101325.0, 108000.0):
                up = raw_pressure_for(p, b5, oss, words)
                assert up < 1 << (16 + oss)
                assert abs(compensate_pressure(up, oss, b5, cal) - p) <= 2.0


# ---- driver against the model ----------------------------------------------------------------------
class Rig:
    def __init__(self, *, variant: str = "BMP180", trajectory=None, noise: bool = True, seed: int = 5,
                 calibration: Bmp085Calibration = DATASHEET_EXAMPLE_CALIBRATION, chip_id: int = 0x55) -> None:
        self.clock = ManualClock()
        self.trajectory = trajectory if trajectory is not None else ParkedTrajectory(
            height_m=40.0, extras={"ambient_degc": 23.4, "sea_level_pa": 100800.0, "geoid_m": 20.0})
        self.model = Bmp085Model(self.clock, self.trajectory, seed=seed, variant=variant, noise=noise,
                                 calibration=EepromCalibration(*calibration), chip_id=chip_id)
        self.adapter = SimI2cAdapter({0x77: self.model})
        self.bus = SimI2cBus(self.adapter)
        self.variant = variant

    def driver(self, **kw) -> Bmp085:
        kw.setdefault("sleep", self.clock.sleep)
        return Bmp085(self.bus, variant=self.variant, bus_name=self.adapter.path, **kw)

    def truth_pa(self) -> float:
        """The pressure the model measures: the standard atmosphere as the model (the world) has it."""
        s = self.trajectory.state(0.0)
        return chip.isa_pressure_pa(s.height_msl_m, s.sea_level_pa)


@pytest.fixture
def rig():
    made: list[Rig] = []

    def make(**kw) -> Rig:
        r = Rig(**kw)
        made.append(r)
        return r

    yield make
    for r in made:
        r.bus.close()


@pytest.mark.parametrize("variant", ["BMP085", "BMP180"])
@pytest.mark.parametrize("oss", [0, 1, 2, 3])
def test_round_trip_recovers_truth_within_datasheet_noise(rig, variant, oss) -> None:
    r = rig(variant=variant, calibration=FIELD_CALIBRATION, seed=oss)
    d = r.driver(oversampling=oss, reference_pa=100800.0)
    d.configure()
    start = r.clock.now_ns()
    samples = [d.read() for _ in range(400)]
    pressures = np.array([s.pressure_pa for s in samples])
    truth = r.truth_pa()
    sigma = chip.PRESSURE_NOISE_PA[oss]
    # The mean of 400 reads: noise sigma/20 plus the integer compensation's half-pascal steps.
    assert abs(pressures.mean() - truth) < 4 * sigma / 20 + 1.0
    assert pressures.std() == pytest.approx(sigma, rel=0.2)
    assert all(abs(s.temp_degc - 23.4) <= 0.1 for s in samples)
    assert np.mean([s.altitude_m for s in samples]) == pytest.approx(20.0, abs=0.3)  # 40 m ellipsoid - geoid
    # Each read waited the datasheet's times and no more: temperature 4.5 ms, pressure per oss.
    per_read_s = 4.5e-3 + (4.5e-3, 7.5e-3, 13.5e-3, 25.5e-3)[oss]
    assert (r.clock.now_ns() - start) / 1e9 == pytest.approx(400 * per_read_s, rel=1e-9)
    assert samples[0].oss == oss and samples[0].ut > 0 and samples[0].up > 0


def test_model_enforces_conversion_time(rig) -> None:
    r = rig(noise=False)
    bus, clock = r.bus, r.clock
    assert bus.read_i2c_block_data(0x77, 0xF6, 3) == [0x80, 0x00, 0x00]  # reset value
    bus.write_byte_data(0x77, 0xF4, 0x2E)
    clock.advance(4.4e-3)
    assert bus.read_i2c_block_data(0x77, 0xF6, 2) == [0x80, 0x00]  # too early: the previous result
    assert bus.read_byte_data(0x77, 0xF4) & 0x20  # Sco: still converting
    clock.advance(0.1e-3)
    ut = bus.read_i2c_block_data(0x77, 0xF6, 2)
    assert ut != [0x80, 0x00]
    assert not bus.read_byte_data(0x77, 0xF4) & 0x20
    bus.write_byte_data(0x77, 0xF4, 0x34 + (3 << 6))
    clock.advance(25.4e-3)
    assert bus.read_i2c_block_data(0x77, 0xF6, 2) == ut  # still the temperature
    clock.advance(0.1e-3)
    assert bus.read_i2c_block_data(0x77, 0xF6, 2) != ut


def test_bmp085_results_at_the_registers_power_on_values_are_no_data(rig) -> None:
    """A BMP085 has no Sco bit: a driver that waits too little (or a chip whose conversions never run) reads the
    result registers' power-on values 0x8000 / 0x800000, which compensate to a plausible pressure, identical at
    every read. They are refused as no data, never recorded."""
    r = rig(variant="BMP085", noise=False)
    d = r.driver(oversampling=0, sleep=lambda s: r.clock.sleep(0.9 * s))
    d.configure()
    for _ in range(3):
        with pytest.raises(NoData, match="power-on values"):
            d.read()
    good = r.driver(oversampling=0).read()
    assert good.temp_degc == pytest.approx(23.4, abs=0.1)


def test_bmp180_driver_waits_for_sco_when_its_sleep_is_short(rig) -> None:
    r = rig(variant="BMP180", noise=False)
    d = r.driver(oversampling=3, sleep=lambda s: r.clock.sleep(0.9 * s))
    d.configure()
    sample = d.read()
    assert sample.pressure_pa == pytest.approx(r.truth_pa(), abs=1.0)
    assert sample.temp_degc == pytest.approx(23.4, abs=0.1)


def test_bmp180_conversion_that_never_ends_is_no_data(rig) -> None:
    r = rig(variant="BMP180")
    d = r.driver(sleep=lambda s: None)  # time stands still: the conversion never finishes
    d.configure()
    with pytest.raises(NoData, match="Sco bit stays set"):
        d.read()


def test_soft_reset(rig) -> None:
    r = rig()
    r.bus.write_byte_data(0x77, 0xF4, 0x2E)
    r.clock.advance(0.01)
    assert r.bus.read_i2c_block_data(0x77, 0xF6, 3) != [0x80, 0, 0]
    r.bus.write_byte_data(0x77, 0xE0, 0xB6)
    assert r.bus.read_i2c_block_data(0x77, 0xF6, 3) == [0x80, 0, 0]
    assert r.bus.read_byte_data(0x77, 0xF4) == 0
    r.bus.write_byte_data(0x77, 0xE0, 0x55)  # anything but 0xB6 does nothing
    assert r.bus.read_byte_data(0x77, 0xD0) == 0x55


@pytest.mark.parametrize(("word", "offset"), [(0x0000, 0), (0xFFFF, 8), (0xFFFF, 20)])
def test_calibration_sanity_check(rig, word, offset) -> None:
    r = rig()
    r.model.eeprom[offset: offset + 2] = word.to_bytes(2, "big")
    name = ("AC1", "AC2", "AC3", "AC4", "AC5", "AC6", "B1", "B2", "MB", "MC", "MD")[offset // 2]
    with pytest.raises(ProtocolError, match=f"calibration word {name} .* reads 0x{word:04X}"):
        r.driver().configure()


def test_wrong_chip_id(rig) -> None:
    r = rig(chip_id=0x58)
    with pytest.raises(WrongDevice, match="chip id reads 0x58, expected 0x55"):
        r.driver().configure()


@pytest.mark.parametrize("code", [errno.EREMOTEIO, errno.ENXIO])
def test_no_chip_is_device_not_found(code) -> None:
    with SimI2cBus(SimI2cAdapter({}, nack_errno=code)) as bus, pytest.raises(DeviceNotFound) as exc:
        Bmp085(bus, bus_name="/dev/i2c-2").configure()
    assert "BMP180 at 0x77 on /dev/i2c-2" in str(exc.value)
    assert "\n" not in str(exc.value)


def test_eio_is_bus_error_then_recovers(rig) -> None:
    r = rig(noise=False)
    d = r.driver()
    d.configure()
    r.adapter.fail_next(1)
    with pytest.raises(BusError, match="I2C transfer failed while starting a temperature conversion"):
        d.read()
    assert d.read().pressure_pa == pytest.approx(r.truth_pa(), abs=1.0)


def test_pressure_outside_the_chips_range_is_rejected(rig) -> None:
    r = rig(trajectory=ParkedTrajectory(height_m=-4000.0), noise=False)
    d = r.driver()
    d.configure()
    with pytest.raises(ProtocolError, match=r"far outside the chip's 300\.\.1100 hPa"):
        d.read()


@pytest.mark.parametrize(("temp_degc", "sea_level_pa", "oss", "said"), [
    (86.0, 100800.0, 3, True),  # past 85 degC
    (23.4, 110000.0, 0, True),  # the compensation gives 110002 Pa
    (-40.0, 30000.0, 0, False),  # both limits, read as exactly 30000 Pa
])
def test_a_reading_at_or_just_past_the_rated_range_is_kept_and_said_once(rig, caplog, temp_degc, sea_level_pa,
                                                                          oss, said) -> None:
    """A chip at the edge of its rating still measures (+-2 degC there; the integer compensation gives 110001 Pa
    at 1100 hPa with oversampling 0): kept, and the log says once that it lies outside the rated range. Refused as
    garbled it reopened the chip at every read and a hot cabin lost its barometer."""
    r = rig(trajectory=ParkedTrajectory(height_m=0.0, extras={"ambient_degc": temp_degc,
                                                               "sea_level_pa": sea_level_pa, "geoid_m": 0.0}),
            noise=False, calibration=FIELD_CALIBRATION)
    d = r.driver(oversampling=oss)
    d.configure()
    with caplog.at_level("WARNING", logger="sensors.bmp085"):
        first, second = d.read(), d.read()
    assert first.temp_degc == pytest.approx(temp_degc, abs=0.2)
    assert second.pressure_pa == pytest.approx(sea_level_pa, abs=3.0)
    outside = [rec for rec in caplog.records if "outside its rated" in rec.getMessage()]
    assert len(outside) == (1 if said else 0)


def test_a_temperature_far_past_the_rated_range_is_refused(rig) -> None:
    r = rig(trajectory=ParkedTrajectory(height_m=0.0, extras={"ambient_degc": 115.0, "sea_level_pa": 100800.0,
                                                               "geoid_m": 0.0}), noise=False)
    d = r.driver()
    d.configure()
    with pytest.raises(ProtocolError, match=r"115\.0 degC .* far outside the chip's -40\.\.85 degC"):
        d.read()


def test_a_bmp085_read_as_a_bmp180_names_the_variant_setting(rig) -> None:
    """A BMP085 keeps CTRL_MEAS as written, so its command's bit 5 reads as a BMP180's Sco that never clears."""
    r = rig(variant="BMP085")
    d = Bmp085(r.bus, variant="BMP180", bus_name=r.adapter.path, sleep=r.clock.sleep)
    d.configure()
    with pytest.raises(NoData, match=r'Sco bit stays set; a BMP085.*variant = "BMP085"'):
        d.read()


def test_a_nack_from_a_chip_that_answered_is_a_bus_error_not_a_missing_chip(rig) -> None:
    """Some adapters (the BeagleBone's i2c-omap) say EREMOTEIO for a NACK of any byte: on a chip that answered
    since it was opened that is a glitch on the bus (the sampler retries), not a wiring or address fault."""
    r = rig(noise=False)
    d = r.driver()
    d.configure()
    r.adapter.fail_next(1, code=errno.EREMOTEIO)
    with pytest.raises(BusError, match="no ACK while starting a temperature conversion, after it had answered"):
        d.read()
    assert d.read().pressure_pa == pytest.approx(r.truth_pa(), abs=1.0)


def test_an_address_held_by_a_kernel_driver_says_so(rig) -> None:
    r = rig()
    r.adapter.bind_kernel_driver(0x77)
    with pytest.raises(BusError) as exc:
        r.driver().configure()
    message = str(exc.value)
    assert "address busy" in message and "device-tree overlay" in message and "\n" not in message
    assert "/driver/unbind" in message


def test_bad_configuration_named() -> None:
    with pytest.raises(ValueError, match="oversampling 4"):
        Bmp085(None, oversampling=4)
    with pytest.raises(ValueError, match="variant 'BMP280'"):
        Bmp085(None, variant="BMP280")
    with pytest.raises(ValueError, match=r"reference pressure 1013\.25 Pa"):
        Bmp085(None, reference_pa=1013.25)


def test_altitude_follows_the_truth_height(rig) -> None:
    """Pressure altitude with QNH as reference is height above mean sea level, to the noise."""
    for height in (0.0, 250.0, 1200.0):
        r = rig(trajectory=ParkedTrajectory(height_m=height, extras={"sea_level_pa": 101800.0}), seed=9)
        d = r.driver(oversampling=3, reference_pa=101800.0)
        d.configure()
        altitude = np.mean([d.read().altitude_m for _ in range(50)])
        assert altitude == pytest.approx(height, abs=0.25)
        assert math.isfinite(altitude)
