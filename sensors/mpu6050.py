"""InvenSense MPU-6050 over I2C (smbus2): set-up, one-shot reads and the FIFO.

Register numbers, bit fields, scale factors and the filter table are those of the MPU-6000/MPU-6050
Register Map and Descriptions (RM-MPU-6000A-00, rev. 4.2). Axes are the chip's axes as printed on the
package (x and y in its plane, z out of its top, right-handed); a chip lying face-up senses about
+9.8 m/s^2 on z. How the chip sits in the vehicle is configuration applied above this driver.

Two ways to read:

- ``read()``: one coherent 14-byte burst of the data registers, for a sampler that polls at the sample
  rate (the paper's 20 Hz).
- ``read_fifo()``: the chip's 1024-byte FIFO, so rates up to 1 kHz lose nothing while the reader wakes up
  only now and then. Frames hold accelerometer and gyro (12 bytes); the temperature is left out because it
  changes in minutes, not milliseconds: one TEMP_OUT read per batch costs 2 bytes instead of 2 bytes per
  sample, and the FIFO holds 85 frames instead of 73. At 1 kHz the FIFO traffic is 12 kB/s, more than a
  100 kHz bus carries: run the bus at 400 kHz for that rate.

The chip has no sample counter, so the number of samples an overflow destroyed is derived from the
caller's read times and the nominal rate (the chip's own clock is good to about 1 %).
"""

from __future__ import annotations

import errno
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from sensors.errors import BusError, ProtocolError, WrongDevice
from sensors.i2c import i2c_transfer
from sensors.mpu6050_identity import CLONE_WHO_AM_I, OTHER_PARTS, WHO_AM_I_VALUE
from sensors.mpu6050_timing import choose_sample_timing

_BURST = struct.Struct(">7h")  # ACCEL_XOUT_H..GYRO_ZOUT_L: accel x y z, temperature, gyro x y z

STANDARD_GRAVITY_MPS2 = 9.80665

DEFAULT_ADDRESS = 0x68  # AD0 low; 0x69 with AD0 high

# Register map
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
FIFO_EN = 0x23
INT_PIN_CFG = 0x37
INT_ENABLE = 0x38
INT_STATUS = 0x3A
ACCEL_XOUT_H = 0x3B
TEMP_OUT_H = 0x41
GYRO_XOUT_H = 0x43
SIGNAL_PATH_RESET = 0x68
USER_CTRL = 0x6A
PWR_MGMT_1 = 0x6B
PWR_MGMT_2 = 0x6C
FIFO_COUNTH = 0x72
FIFO_R_W = 0x74
WHO_AM_I = 0x75

# Bits
FIFO_EN_TEMP = 0x80
FIFO_EN_XG = 0x40
FIFO_EN_YG = 0x20
FIFO_EN_ZG = 0x10
FIFO_EN_ACCEL = 0x08
INT_FIFO_OFLOW = 0x10
INT_DATA_RDY = 0x01
USER_CTRL_FIFO_EN = 0x40
USER_CTRL_FIFO_RESET = 0x04
PWR1_DEVICE_RESET = 0x80
PWR1_SLEEP = 0x40
CLKSEL_PLL_XGYRO = 0x01

FIFO_SIZE_BYTES = 1024
FIFO_FRAME_BYTES = 12  # accel x,y,z then gyro x,y,z, big-endian int16, register order
SMBUS_BLOCK_MAX = 32  # the most one SMBus block transfer (and smbus2) moves
RESET_WAIT_S = 0.100  # after DEVICE_RESET, as InvenSense's own driver waits
TEMP_READ_INTERVAL_NS = 1_000_000_000
"""How often a FIFO read also reads the die temperature (TEMP_OUT is not in the FIFO; a batch carries the last
one read). A warming die moves by hundredths of a degree a second and its users average over tens of seconds
(the offsets' temperature terms, the crystal's); at 1 kHz a read per FIFO read was 25 of the 100 transfers a
second."""

# Full-scale settings: range -> (register code, sensitivity)
ACCEL_FULL_SCALE = {2: (0, 16384.0), 4: (1, 8192.0), 8: (2, 4096.0), 16: (3, 2048.0)}  # g -> LSB/g
GYRO_FULL_SCALE = {250: (0, 131.0), 500: (1, 65.5), 1000: (2, 32.8), 2000: (3, 16.4)}  # deg/s -> LSB/(deg/s)

TEMP_LSB_PER_DEGC = 340.0
TEMP_OFFSET_DEGC = 36.53

_OTHER_CHIPS = {**OTHER_PARTS, 0x68: "an MPU-6050",
                0x00: "nothing driving the bus (stuck low?)", 0xFF: "nothing driving the bus (no pull-ups?)"}


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One sample in chip axes.

    A direct read gives tuples of Python floats: the record is JSON-encoded and the filter works on scalars,
    and both are cheaper with floats than with small numpy arrays at every sample on the board.
    """

    accel_mps2: np.ndarray | tuple[float, float, float]  # (3,) specific force
    gyro_rps: np.ndarray | tuple[float, float, float]  # (3,) angular rate
    temp_degc: float


@dataclass(frozen=True, slots=True)
class ImuBatch:
    """What one FIFO read brought: samples oldest first, evenly spaced by ``period_s``.

    ``lost_samples`` counts samples an overflow destroyed before this batch (0 when none; ``None`` when
    an overflow happened but no read times were given to count them).
    """

    accel_mps2: np.ndarray  # (n, 3)
    gyro_rps: np.ndarray  # (n, 3)
    temp_degc: float
    period_s: float
    overflowed: bool = False
    lost_samples: int | None = 0

    def __len__(self) -> int:
        return len(self.accel_mps2)

    def samples(self) -> list[ImuSample]:
        return [ImuSample(a, g, self.temp_degc) for a, g in zip(self.accel_mps2, self.gyro_rps, strict=True)]


_T = TypeVar("_T")


def _raise(_address: int, exc: OSError) -> None:
    """For :func:`sensors.i2c.i2c_transfer`: an error already caught, mapped as every other transfer's."""
    raise exc


class Mpu6050:
    """The MPU-6050 behind an ``smbus2.SMBus``-like bus (give each driver its own bus object).

    ``configure()`` does all set-up and may be called again after any error; a sampler thread owns the
    timing and the retries.
    """

    def __init__(self, bus: Any, address: int = DEFAULT_ADDRESS, *, rate_hz: float = 20.0,
                 accel_range_g: int = 2, gyro_range_dps: int = 250, fifo: bool = False,
                 dlpf_cfg: int | None = None, bus_name: str = "I2C",
                 sleep: Callable[[float], None] = time.sleep, fifo_burst: bool = True,
                 who_am_i: int = WHO_AM_I_VALUE) -> None:
        if accel_range_g not in ACCEL_FULL_SCALE:
            raise ValueError(f"MPU-6050 accel range {accel_range_g} g: must be one of 2, 4, 8, 16")
        if gyro_range_dps not in GYRO_FULL_SCALE:
            raise ValueError(f"MPU-6050 gyro range {gyro_range_dps} deg/s: must be one of 250, 500, 1000, 2000")
        self.bus = bus
        self.address = address
        self.who_am_i = who_am_i  # what the chip must answer: the MPU-6050's 0x68, or a clone's its owner named
        self.timing = choose_sample_timing(rate_hz, dlpf_cfg)
        self.accel_range_g = accel_range_g
        self.gyro_range_dps = gyro_range_dps
        self.fifo = fifo
        self.bus_name = bus_name
        self._sleep = sleep
        self._afs_sel, self.accel_lsb_per_g = ACCEL_FULL_SCALE[accel_range_g]
        self._fs_sel, self.gyro_lsb_per_dps = GYRO_FULL_SCALE[gyro_range_dps]
        self._accel_scale = STANDARD_GRAVITY_MPS2 / self.accel_lsb_per_g
        self._gyro_scale = math.radians(1.0) / self.gyro_lsb_per_dps
        self._partial = bytearray()  # bytes of a frame whose rest is still in the chip
        # A bus with combined transactions (smbus2.SMBus.i2c_rdwr) reads the FIFO in one (_read_fifo_combined)
        # unless fifo_burst is off; otherwise in SMBus blocks.
        self._combined = fifo and fifo_burst and callable(getattr(bus, "i2c_rdwr", None))
        self._msg: Any = None
        if self._combined:
            from smbus2 import i2c_msg

            self._msg = i2c_msg
        self._overflow_seen = False
        self._last_read_ns: int | None = None
        self._backlog_frames = 0  # frames generated but not delivered at the last read
        self._temp: tuple[int, float] | None = None  # (read time, degC) of the die temperature last read
        self._answered = False  # the chip has answered since configure() began: a NACK is then a bus fault
        # The caller's time of the FIFO's last start (configure()'s reset, or an overflow's), when it gave a clock.
        self.fifo_started_ns: int | None = None

    # ---- what the configuration gives ------------------------------------------------------------
    @property
    def sample_rate_hz(self) -> float:
        return self.timing.rate_hz

    @property
    def sample_period_s(self) -> float:
        return self.timing.period_s

    @property
    def dlpf_cfg(self) -> int:
        return self.timing.dlpf.cfg

    @property
    def accel_delay_s(self) -> float:
        """Group delay of the accelerometer filter: a sample shows the motion this long before."""
        return self.timing.dlpf.accel_delay_s

    @property
    def gyro_delay_s(self) -> float:
        return self.timing.dlpf.gyro_delay_s

    def _config_registers(self) -> bytes:
        """SMPLRT_DIV, CONFIG, GYRO_CONFIG, ACCEL_CONFIG: four consecutive registers."""
        return bytes((self.timing.smplrt_div, self.dlpf_cfg, self._fs_sel << 3, self._afs_sel << 3))

    # ---- bus access with errors a field engineer can act on ---------------------------------------
    def _bus(self, doing: str, fn: Callable[..., _T], *args: Any) -> _T:
        return i2c_transfer("MPU-6050", self.address, self.bus_name, doing, fn, *args,
                            no_ack_hint="check wiring, power and the AD0 address", answered=self._answered)

    def _read_byte(self, reg: int, doing: str) -> int:
        return self._bus(doing, self.bus.read_byte_data, reg)

    def _read_block(self, reg: int, n: int, doing: str) -> bytes:
        return bytes(self._bus(doing, self.bus.read_i2c_block_data, reg, n))

    def _write_byte(self, reg: int, value: int, doing: str) -> None:
        self._bus(doing, self.bus.write_byte_data, reg, value)

    # ---- set-up ----------------------------------------------------------------------------------
    def configure(self, now_ns: Callable[[], int] | None = None) -> None:
        """Identify, reset, wake on the gyro PLL, set filter, rate and ranges, and start the FIFO if wanted.

        ``now_ns``, the caller's clock, dates the FIFO's start (:attr:`fifo_started_ns`): an overflow before the
        first read then counts its loss from there (without it, one sample stands for what was lost)."""
        self._answered = False
        who = self._read_byte(WHO_AM_I, "reading WHO_AM_I")
        self._answered = True
        if who != self.who_am_i:
            seen = (f"an MPU-6050 clone's? if it works as one, set [imu] who_am_i = 0x{who:02x}"
                    if who in CLONE_WHO_AM_I else f"looks like {_OTHER_CHIPS.get(who, 'another chip')}")
            raise WrongDevice(f"MPU-6050 at 0x{self.address:02x} on {self.bus_name}: WHO_AM_I reads "
                              f"0x{who:02x}, expected 0x{self.who_am_i:02x} ({seen})")
        self._write_byte(PWR_MGMT_1, PWR1_DEVICE_RESET, "resetting")
        self._sleep(RESET_WAIT_S)
        if self._read_byte(PWR_MGMT_1, "checking the reset") & PWR1_DEVICE_RESET:
            raise BusError(f"MPU-6050 at 0x{self.address:02x}: still in reset {RESET_WAIT_S * 1e3:.0f} ms "
                           "after DEVICE_RESET")
        # Waking on the X gyro's PLL: the internal RC oscillator drifts by percent over temperature.
        self._write_byte(PWR_MGMT_1, CLKSEL_PLL_XGYRO, "waking up")
        self._bus("configuring", self.bus.write_i2c_block_data, SMPLRT_DIV, list(self._config_registers()))
        got = self._read_block(SMPLRT_DIV, 4, "checking the configuration")
        pwr = self._read_byte(PWR_MGMT_1, "checking the power state")
        if got != self._config_registers() or pwr != CLKSEL_PLL_XGYRO:
            raise ProtocolError(f"MPU-6050 at 0x{self.address:02x}: configuration did not stick (read back "
                                f"{got.hex()} / PWR_MGMT_1 0x{pwr:02x})")
        self._write_byte(INT_ENABLE, INT_FIFO_OFLOW | INT_DATA_RDY, "enabling status flags")
        if self.fifo:
            self._reset_fifo()
        else:
            self._write_byte(FIFO_EN, 0, "disabling the FIFO")
            self._write_byte(USER_CTRL, 0, "disabling the FIFO")
        self._read_byte(INT_STATUS, "clearing status flags")
        self._overflow_seen = False
        self._last_read_ns = self.fifo_started_ns = now_ns() if now_ns is not None and self.fifo else None
        self._backlog_frames = 0
        self._temp = None

    def is_configured(self) -> bool:
        """Whether the chip still runs as ``configure()`` left it (a brown-out puts it back to sleep)."""
        regs = self._read_block(SMPLRT_DIV, 4, "checking the configuration")
        pwr = self._read_byte(PWR_MGMT_1, "checking the power state")
        ok = regs == self._config_registers() and pwr == CLKSEL_PLL_XGYRO
        if self.fifo:
            ok = ok and self._read_byte(USER_CTRL, "checking the FIFO") & USER_CTRL_FIFO_EN != 0
        return ok

    def _reset_fifo(self) -> None:
        """The register map's order: FIFO_RESET acts only while USER_CTRL.FIFO_EN is 0."""
        doing = "resetting the FIFO"
        self._write_byte(FIFO_EN, 0, doing)
        self._write_byte(USER_CTRL, 0, doing)
        self._write_byte(USER_CTRL, USER_CTRL_FIFO_RESET, doing)
        self._write_byte(USER_CTRL, USER_CTRL_FIFO_EN, doing)
        self._write_byte(FIFO_EN, FIFO_EN_ACCEL | FIFO_EN_XG | FIFO_EN_YG | FIFO_EN_ZG, doing)
        self._partial.clear()

    # ---- data ------------------------------------------------------------------------------------
    def _int_status(self) -> int:
        """INT_STATUS clears on read, so a seen overflow is kept until the FIFO reader handles it."""
        status = self._read_byte(INT_STATUS, "reading INT_STATUS")
        if status & INT_FIFO_OFLOW:
            self._overflow_seen = True
        return status

    def data_ready(self) -> bool:
        """Whether a sample arrived since INT_STATUS was last read."""
        return bool(self._int_status() & INT_DATA_RDY)

    def read(self) -> ImuSample:
        """The latest sample: one burst ACCEL_XOUT_H..GYRO_ZOUT_L, coherent within itself."""
        raw = self._read_block(ACCEL_XOUT_H, 14, "reading the data registers")
        ax, ay, az, t, gx, gy, gz = _BURST.unpack(raw)
        sa, sg = self._accel_scale, self._gyro_scale
        return ImuSample((ax * sa, ay * sa, az * sa), (gx * sg, gy * sg, gz * sg),
                         t / TEMP_LSB_PER_DEGC + TEMP_OFFSET_DEGC)

    def read_temperature_degc(self) -> float:
        raw = self._read_block(TEMP_OUT_H, 2, "reading the temperature")
        return float(int.from_bytes(raw, "big", signed=True) / TEMP_LSB_PER_DEGC + TEMP_OFFSET_DEGC)

    @property
    def backlog_frames(self) -> int:
        """Frames that were in the FIFO at the last read but not delivered by it (a bounded read, a split frame)."""
        return self._backlog_frames

    def read_fifo(self, read_time_ns: int | None = None, max_bytes: int | None = None,
                  now_ns: Callable[[], int] | None = None) -> ImuBatch:
        """All complete samples waiting in the FIFO (or up to ``max_bytes`` of them), oldest first.

        ``read_time_ns`` is the caller's monotonic time of this read. It is used only to count the
        samples lost when the FIFO overflowed since the previous read; without it that count is None.
        ``now_ns``, the caller's clock, dates the reset after an overflow: what came between the read's time and
        the reset (a host stalled inside the read) is lost with the rest, and counted.
        ``max_bytes`` bounds how long one call holds the bus; bytes of a frame cut by it are kept for
        the next call. After an overflow the FIFO is reset and the batch is empty.
        """
        if not self.fifo:
            raise RuntimeError("MPU-6050 driver was configured without the FIFO")
        count_raw = self._read_block(FIFO_COUNTH, 2, "reading FIFO_COUNT")
        count = int.from_bytes(count_raw, "big")
        if self._overflow_seen or count >= FIFO_SIZE_BYTES:
            return self._recover_from_overflow(read_time_ns, now_ns)
        want = count if max_bytes is None else min(count, max_bytes)
        remaining = want
        if want and self._combined:
            self._partial += self._read_fifo_combined(want)
            remaining = 0
        while remaining > 0:
            piece = min(remaining, SMBUS_BLOCK_MAX)
            # Each piece joins the buffer at once: a failure later in the loop keeps what was read.
            self._partial += self._read_block(FIFO_R_W, piece, "reading the FIFO")
            remaining -= piece
        # INT_STATUS after the data, not before: a FIFO that overflowed since the last read is full (its count says
        # so), but one that overflowed while its bytes were being read (a host stalled between FIFO_COUNT and the
        # burst, the FIFO a frame or two short of full) lost its oldest bytes under the reader, and the bytes read
        # are frames no longer (the chip drops bytes, not frames: 1024 is no multiple of 12). Read before, the flag
        # said so one read late, once the misaligned batch had been delivered and recorded.
        self._int_status()
        if self._overflow_seen:
            return self._recover_from_overflow(read_time_ns, now_ns)
        whole = len(self._partial) // FIFO_FRAME_BYTES * FIFO_FRAME_BYTES
        frames = bytes(self._partial[:whole])
        del self._partial[:whole]
        undelivered = count - want + len(self._partial)
        self._backlog_frames = -(-undelivered // FIFO_FRAME_BYTES)
        self._last_read_ns = read_time_ns
        values = np.frombuffer(frames, dtype=">i2").astype(np.float64).reshape(-1, 6)
        return ImuBatch(values[:, 0:3] * self._accel_scale, values[:, 3:6] * self._gyro_scale,
                        self._fifo_temperature(read_time_ns), self.sample_period_s)

    def _fifo_temperature(self, read_time_ns: int | None) -> float:
        """The die temperature for a FIFO batch: read again once TEMP_READ_INTERVAL_NS has passed (every time for a
        caller that gives no read times)."""
        last = self._temp
        if read_time_ns is not None and last is not None and 0 <= read_time_ns - last[0] < TEMP_READ_INTERVAL_NS:
            return last[1]
        temp = self.read_temperature_degc()
        self._temp = None if read_time_ns is None else (read_time_ns, temp)
        return temp

    def _read_fifo_combined(self, n: int) -> bytes:
        """The FIFO's ``n`` bytes in one combined I2C transaction (register write, repeated start, burst read), as
        InvenSense's own drivers read it: one ioctl instead of one per 32 bytes, which at 1 kHz is the bulk of
        the sampler thread's transfers. An adapter without I2C_RDWR (SMBus-only) refuses it: then, and from then
        on, the FIFO is read in 32-byte SMBus blocks."""
        write, read = self._msg.write(self.address, [FIFO_R_W]), self._msg.read(self.address, n)
        try:
            self.bus.i2c_rdwr(write, read)
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.ENOTTY, errno.EINVAL):
                self._bus("reading the FIFO", _raise, exc)
            self._combined = False
            return b"".join(self._read_block(FIFO_R_W, min(SMBUS_BLOCK_MAX, n - i), "reading the FIFO")
                            for i in range(0, n, SMBUS_BLOCK_MAX))
        return bytes(read)

    def _recover_from_overflow(self, read_time_ns: int | None, now_ns: Callable[[], int] | None = None) -> ImuBatch:
        """The oldest bytes were overwritten, so frame boundaries are lost: reset, and count the loss: every sample
        since the last read up to the reset (the caller's clock dates it; without one, the read's time)."""
        self._reset_fifo()
        reset_ns = now_ns() if now_ns is not None and read_time_ns is not None else read_time_ns
        lost: int | None = None
        if reset_ns is not None and self._last_read_ns is not None:
            elapsed_s = (reset_ns - self._last_read_ns) / 1e9
            lost = round(elapsed_s * self.sample_rate_hz) + self._backlog_frames
        self._read_byte(INT_STATUS, "clearing status flags")
        self._overflow_seen = False
        self._backlog_frames = 0
        self._last_read_ns = reset_ns
        if reset_ns is not None:
            self.fifo_started_ns = reset_ns  # its loss counted up to here
        empty = np.empty((0, 3))
        return ImuBatch(empty, empty.copy(), self.read_temperature_degc(), self.sample_period_s,
                        overflowed=True, lost_samples=lost)

