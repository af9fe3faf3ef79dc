"""Register-level model of the MPU-6050, sampling a vehicle truth through the chip's own error budget.

The register map is RM-MPU-6000A-00 rev. 4.2: reset values (all zero but PWR_MGMT_1 = 0x40, asleep, and
WHO_AM_I = 0x68), data registers that freeze while asleep, the sample clock SMPLRT_DIV divides, the DLPF
table's bandwidths and group delays, full-scale ranges with saturation, the 1024-byte FIFO written in
register order that drops its oldest bytes on overflow, and INT_STATUS cleared by reading it.

Errors follow the datasheet and the paper's Table 3: white noise of 400 ug/sqrt(Hz) (accelerometer) and
0.005 deg/s/sqrt(Hz) (gyro: 0.05 deg/s RMS in 100 Hz), shaped by the selected low-pass filter; a turn-on
bias drawn at each power-up; a bias random walk; the temperature sensor reading the truth's ambient.

The gyro's rate random walk K (1e-4 deg/s/sqrt(s), 21.6 deg/h/sqrt(h)) is set from published Allan-variance
characterisations of this gyro family, since the datasheet gives none: D. R. Greenheck, *Design and
Characterization of a Low Cost MEMS IMU Cluster for Precision Navigation* (Marquette University MSc thesis,
2015; its MPU-6000 figures are the defaults of AirSim's ``ImuSimpleParams.hpp``) measures an angle random walk
of 0.30 deg/sqrt(h) and a bias stability of 4.6 deg/h at tau = 500 s; an MPU-6050 log at 500 Hz (Robotics
Stack Exchange question 8860) shows 0.003 deg/sqrt(s) and a bias instability of 0.0012 deg/s (4.3 deg/h). An
Allan deviation is sqrt(N^2 / tau + K^2 tau / 3) with white noise and a rate random walk: with this model's
N = 0.005 deg/s/sqrt(Hz) and K = 1e-4 it is 2.7 deg/h at its minimum (87 s) and 4.7 deg/h at 500 s, as
measured; K = 1e-3 would put 46 deg/h at 500 s, ten times what the chip shows. The accelerometer's walk
(0.05 mg/sqrt(s)) is kept on the pessimistic side of the same thesis (36 ug at tau = 800 s). The bias does
not follow the temperature in this model: the simulated cabin warms along a half cosine over hours, so a
7-minute drive sees under 0.05 degC and a 30-minute one under 1 degC, slow enough for the filter's bias
states to follow with GNSS.
The filter is modelled as a first-order low-pass whose discrete form keeps the noise density at low
frequency exactly, since that density is what a navigation filter's tuning rests on.

A phone-grade part (:meth:`Mpu6050Errors.phone_grade`, the simulator's ``imu = "phone"``) is the same register
map with a worse error budget: ten times the noise densities, a larger turn-on gyro offset that also wanders
(a first-order Gauss-Markov process on top of the random walk) and follows the die's temperature as the
phone warms itself, and vibration while the car moves, which a phone
in a holder picks up and a board bolted to the chassis mostly does not: broadband acceleration and rate growing
with speed, the body's bounce on its springs (about 1.3 Hz, vertical) and the engine's firing frequency (25 Hz
at idle, rising with speed), each through the chip's low-pass filter like any motion.

Samples are produced lazily: each bus access first brings the chip up to the drive clock's present time,
all pending samples at once. A reader that stays away for long only costs the last FIFO's worth.

Mounting: ``chip_from_body`` rotates body FRD vectors into chip axes; the default (identity) is a chip
mounted face-down with x forward, so a parked level vehicle reads -1 g on chip z. :func:`chip_from_body` makes
it from the board's roll, pitch and yaw against the vehicle, the angles ``[nav] mounting_rpy_deg`` states.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace

import numpy as np

from sensors.sim import earth
from sensors.sim.clock import DriveClock
from sensors.sim.i2c import RegisterChip
from sensors.sim.truth import Trajectory

G0_MPS2 = 9.80665  # the g of the sensitivity figures (LSB/g)

SELF_TEST_X = 0x0D
SELF_TEST_A = 0x10
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
FIFO_EN = 0x23
I2C_MST_STATUS = 0x36
INT_PIN_CFG = 0x37
INT_ENABLE = 0x38
INT_STATUS = 0x3A
ACCEL_XOUT_H = 0x3B
GYRO_ZOUT_L = 0x48
EXT_SENS_DATA_23 = 0x60
SIGNAL_PATH_RESET = 0x68
USER_CTRL = 0x6A
PWR_MGMT_1 = 0x6B
PWR_MGMT_2 = 0x6C
FIFO_COUNTH = 0x72
FIFO_COUNTL = 0x73
FIFO_R_W = 0x74
WHO_AM_I = 0x75

READ_ONLY = frozenset(range(INT_STATUS, EXT_SENS_DATA_23 + 1)) | {I2C_MST_STATUS, FIFO_COUNTH, FIFO_COUNTL,
                                                                   WHO_AM_I}
FIFO_CAPACITY = 1024
INT_RD_CLEAR = 0x10  # INT_PIN_CFG: any read clears INT_STATUS
INT_FIFO_OFLOW = 0x10
INT_DATA_RDY = 0x01
USER_FIFO_EN = 0x40
USER_FIFO_RESET = 0x04
USER_SIG_COND_RESET = 0x01
PWR1_DEVICE_RESET = 0x80
PWR1_SLEEP = 0x40
PWR1_TEMP_DIS = 0x08
CLKSEL_STOP = 7

# DLPF_CFG: accel bandwidth Hz, accel delay s, gyro bandwidth Hz, gyro delay s, gyro output rate Hz.
# 7 is "reserved" in the register map; the chip runs it at 8 kHz like 0.
DLPF = {
    0: (260.0, 0.0, 256.0, 0.98e-3, 8000),
    1: (184.0, 2.0e-3, 188.0, 1.9e-3, 1000),
    2: (94.0, 3.0e-3, 98.0, 2.8e-3, 1000),
    3: (44.0, 4.9e-3, 42.0, 4.8e-3, 1000),
    4: (21.0, 8.5e-3, 20.0, 8.3e-3, 1000),
    5: (10.0, 13.8e-3, 10.0, 13.4e-3, 1000),
    6: (5.0, 19.0e-3, 5.0, 18.6e-3, 1000),
    7: (260.0, 0.0, 256.0, 0.98e-3, 8000),
}
ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)
# FIFO_EN bit -> columns of the 7 data words (accel x y z, temp, gyro x y z) it puts into each frame
FIFO_SOURCES = ((0x08, (0, 1, 2)), (0x80, (3,)), (0x40, (4,)), (0x20, (5,)), (0x10, (6,)))
MAX_SAMPLES_PER_CATCH_UP = 600  # more than one full FIFO even of 2-byte frames: older ones are never seen
BOUNCE_HZ = 1.3  # a passenger car's body on its springs
ENGINE_IDLE_HZ = 25.0  # firing frequency of a four-cylinder engine at 750 rpm (two firings a revolution)
ENGINE_HZ_PER_MPS = 1.0  # ... rising with speed through the gears (about 40 Hz at 50 km/h)
VIBRATION_AXES = np.array([0.6, 0.6, 1.0])  # broadband vibration: mostly vertical, less along and across
ENGINE_AXES = np.array([0.0, 0.5, 1.0])  # the engine's tone: vertical and across


@dataclass(frozen=True)
class Mpu6050Errors:
    """Sensor errors, 1-sigma per axis unless a maximum is named."""

    accel_noise_ug_per_rthz: float = 400.0
    gyro_noise_dps_per_rthz: float = 0.005
    accel_turn_on_bias_mg: float = 30.0  # datasheet: +-50 mg (x, y), +-80 mg (z) initial tolerance
    gyro_turn_on_bias_dps: float = 3.0  # datasheet: +-20 deg/s zero-rate output
    accel_bias_walk_mg_per_rts: float = 0.05
    gyro_bias_walk_dps_per_rts: float = 1.0e-4  # Allan-variance figures above, not the datasheet
    temp_noise_degc: float = 0.02
    self_heating_degc: float = 0.0
    # Beyond the datasheet's part (all off for it): a wandering gyro offset, the offsets following a warming die,
    # and the vehicle's vibration.
    gyro_bias_gm_dps: float = 0.0  # 1-sigma of a first-order Gauss-Markov gyro offset, per axis
    gyro_bias_gm_tau_s: float = 300.0  # its correlation time
    # The offsets' temperature coefficients, 1-sigma per axis (drawn at each power-up), and the die's own warming
    # after power-up (a phone's processor, screen and charger): the offsets follow the die's temperature.
    accel_tempco_mg_per_degc: float = 0.0
    gyro_tempco_dps_per_degc: float = 0.0
    warmup_degc: float = 0.0  # the die's rise above the cabin after power-up, reached exponentially
    warmup_tau_s: float = 600.0  # ... with this time constant
    vibration_accel_mps2_per_mps: float = 0.0  # broadband acceleration RMS per m/s of speed (vertical; 0.6 across)
    vibration_gyro_dps_per_mps: float = 0.0  # broadband rate RMS per m/s of speed, per axis
    bounce_mps2_per_mps: float = 0.0  # body bounce (BOUNCE_HZ, vertical) amplitude per m/s of speed
    engine_vibration_mps2: float = 0.0  # amplitude of the engine's firing-frequency tone while it runs

    @classmethod
    def ideal(cls) -> Mpu6050Errors:
        """No noise and no bias: what is left is quantisation, saturation and the filter delay."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    @classmethod
    def phone_grade(cls) -> Mpu6050Errors:
        """A phone-grade MEMS IMU in a holder: ten times the MPU-6050's noise densities (what such a part gives
        in a car, mount and all, against the datasheet's bench figure), a turn-on gyro offset of 5 deg/s with a
        ten times faster random walk, accelerometer offsets of 50 mg walking four times faster; vibration while
        moving of 0.015 m/s^2 and 0.01 deg/s RMS per m/s of speed (0.2 m/s^2 at 50 km/h), a body bounce of
        0.01 m/s^2 per m/s, and the engine's tone at 0.05 m/s^2.

        The gyro offset wanders as a consumer part's does, from data-sheet figures of phone IMUs (Bosch BMI160:
        bias instability 6 deg/h typical, offset temperature coefficient +-0.08 deg/s/K, accelerometer
        +-0.4 mg/K; TDK ICM-20602: +-0.01 deg/s/K and +-0.5 to 1 mg/K):
        - an in-run Gauss-Markov wander of 0.03 deg/s over 200 s: ten times the BMI160's bias instability, as the
          noise is ten times the datasheet's (an Allan minimum is about 0.6 of a Gauss-Markov process' sigma);
        - temperature coefficients of 0.05 deg/s/K and 0.5 mg/K (1-sigma per axis), with a die that warms by
          8 degC over its first half hour (10 min time constant) as a phone running a navigation app does. Ten
          minutes into a drive, a minute moves the gyro offset by about 0.015 deg/s through the warming (at a
          1-sigma coefficient) and 0.02 deg/s through the wander.
        The wander was 0.3 deg/s before (1080 deg/h), beyond the 10 to 1000 deg/h that bounds even rate-grade
        MEMS gyros' bias drift: a phone's outage was then set by a gyro no phone carries."""
        return cls(accel_noise_ug_per_rthz=4000.0, gyro_noise_dps_per_rthz=0.05, accel_turn_on_bias_mg=50.0,
                   gyro_turn_on_bias_dps=5.0, accel_bias_walk_mg_per_rts=0.2, gyro_bias_walk_dps_per_rts=1.0e-3,
                   gyro_bias_gm_dps=0.03, gyro_bias_gm_tau_s=200.0, accel_tempco_mg_per_degc=0.5,
                   gyro_tempco_dps_per_degc=0.05, warmup_degc=8.0, warmup_tau_s=600.0,
                   vibration_accel_mps2_per_mps=0.015, vibration_gyro_dps_per_mps=0.01, bounce_mps2_per_mps=0.01,
                   engine_vibration_mps2=0.05)

    @property
    def vibrates(self) -> bool:
        return bool(self.vibration_accel_mps2_per_mps or self.vibration_gyro_dps_per_mps
                    or self.bounce_mps2_per_mps or self.engine_vibration_mps2)

    def scaled(self, scale: float | Mapping[str, float]) -> Mpu6050Errors:
        """A worse (or better) chip: every noise density, turn-on bias and bias walk times ``scale``, or each
        named term by its own factor (a mapping of field names), for testing a filter against errors other
        than those it was tuned for. The temperature sensor is left as it is."""
        terms = [f.name for f in fields(self) if f.name in SCALABLE_TERMS]
        factors = {name: float(scale) for name in terms} if isinstance(scale, (int, float)) else dict(scale)
        unknown = sorted(set(factors) - set(terms))
        if unknown:
            raise ValueError(f"imu_error_scale: unknown term(s) {', '.join(unknown)}; known: {', '.join(terms)}")
        bad = [k for k, v in factors.items() if not (math.isfinite(v) and v >= 0.0)]
        if bad:
            raise ValueError(f"imu_error_scale: factors must be finite and >= 0 ({', '.join(sorted(bad))})")
        return replace(self, **{k: getattr(self, k) * v for k, v in factors.items()})


SCALABLE_TERMS = ("accel_noise_ug_per_rthz", "gyro_noise_dps_per_rthz", "accel_turn_on_bias_mg",
                  "gyro_turn_on_bias_dps", "accel_bias_walk_mg_per_rts", "gyro_bias_walk_dps_per_rts")


def _first_order(pole: float | np.ndarray, x: np.ndarray, drive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A first-order process over the rows of ``drive`` (x = pole * x + drive): every step, and the last state."""
    out = np.empty_like(drive)
    for i in range(len(drive)):
        x = pole * x + drive[i]
        out[i] = x
    return out, x


def chip_from_body(mounting_rpy_deg: tuple[float, float, float] | list[float]) -> np.ndarray:
    """The rotation from vehicle (FRD) axes to the chip's, for a board mounted at roll, pitch, yaw (deg).

    The angles are the chip frame's attitude in the vehicle frame, as a vehicle's attitude is given in NED: the
    chip's axes are the vehicle's turned by yaw, then pitch, then roll. A filter that multiplies the chip's
    readings by the direction cosine matrix of the same angles (C_bn of roll, pitch, yaw) gets the vehicle's
    readings back, so this is that matrix's transpose."""
    return earth.dcm_body_to_ned(np.radians(np.asarray(mounting_rpy_deg, float))).T


class Mpu6050Model(RegisterChip):
    """An MPU-6050 as the bus sees it, driven by ``trajectory`` at the time ``clock`` tells."""

    def __init__(self, clock: DriveClock, trajectory: Trajectory, *, seed: int | np.random.Generator = 0,
                 errors: Mpu6050Errors | None = None, who_am_i: int = 0x68,
                 chip_from_body: np.ndarray | None = None, clock_error_ppm: float = 0.0,
                 startup_s: float = 0.030) -> None:
        super().__init__()
        self.clock = clock
        self.trajectory = trajectory
        self.errors = errors if errors is not None else Mpu6050Errors()
        self.rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        self.who_am_i = who_am_i
        self.chip_from_body = np.eye(3) if chip_from_body is None else np.asarray(chip_from_body, float)
        self.clock_error_ppm = clock_error_ppm
        self.startup_ns = round(startup_s * 1e9)
        self.samples_generated = 0  # every sample the chip made while awake, seen or not
        self.fifo_bytes_dropped = 0  # pushed out of a full FIFO
        # Factory self-test trims live in OTP: they survive resets.
        xg, yg, zg, xa, ya, za = (int(v) for v in self.rng.integers(8, 24, 6))
        self._self_test = bytes((((xa >> 2) << 5) | xg, ((ya >> 2) << 5) | yg, ((za >> 2) << 5) | zg,
                                 ((xa & 3) << 4) | ((ya & 3) << 2) | (za & 3)))
        self._tempco: np.ndarray | None = None  # the offsets' temperature coefficients, set at the first power-up
        self.power_on_reset()

    # ---- power and reset -------------------------------------------------------------------------
    def power_on_reset(self) -> None:
        """Supply (re)applied: a new turn-on bias, registers at reset values, asleep."""
        e = self.errors
        scale = np.array([e.accel_turn_on_bias_mg * 1e-3 * G0_MPS2] * 3
                         + [math.radians(e.gyro_turn_on_bias_dps)] * 3)
        self._bias_on = self.rng.standard_normal(6) * scale
        self._bias_walk = np.zeros(6)
        # The wandering offset starts anywhere in its stationary spread (no draw when there is none, so a chip
        # without it keeps its random sequence).
        self._gyro_gm = (self.rng.standard_normal(3) * math.radians(e.gyro_bias_gm_dps) if e.gyro_bias_gm_dps
                         else np.zeros(3))
        # Temperature coefficients: the part's, drawn at its first power-up and only for a chip that has them (a
        # chip without keeps its random sequence). A power cycle restarts the die's warming from the cabin's
        # temperature at once (a simplification: a die cools over minutes).
        tc = (e.accel_tempco_mg_per_degc * 1e-3 * G0_MPS2, math.radians(e.gyro_tempco_dps_per_degc))
        if self._tempco is None and any(tc):
            self._tempco = self.rng.standard_normal(6) * np.repeat(tc, 3)
        self._powered_s = self.clock.now_ns() / 1e9
        self._die_ref: float | None = None  # the die's temperature at the first sample: the turn-on bias's
        self._engine_phase = 0.0
        self._device_reset()

    def _device_reset(self) -> None:
        self.regs = bytearray(256)
        self.regs[SELF_TEST_X: SELF_TEST_A + 1] = self._self_test
        self.regs[PWR_MGMT_1] = PWR1_SLEEP
        self.fifo = bytearray()
        self._fifo_last = 0
        self._noise = np.zeros(6)
        self._anchor_ns: int | None = None
        self._k = 0
        self.pointer = 0

    def _should_run(self) -> bool:
        pwr = self.regs[PWR_MGMT_1]
        return not pwr & PWR1_SLEEP and (pwr & 0x07) != CLKSEL_STOP

    def _start_or_stop(self, now_ns: int) -> None:
        """Sleep stops the sample clock; waking starts it after the start-up time."""
        if not self._should_run():
            self._anchor_ns = None
        elif self._anchor_ns is None:
            self._anchor_ns = now_ns + self.startup_ns
            self._k = 0

    def _restart_sample_clock(self, now_ns: int) -> None:
        """A new divider or filter: the next sample is one new period from now (or from start-up's end)."""
        if self._anchor_ns is not None and self._anchor_ns < now_ns:
            self._anchor_ns = now_ns
            self._k = 0

    # ---- the sample clock ------------------------------------------------------------------------
    def _period_fraction(self) -> tuple[int, int]:
        """Sample period in ns as numerator/denominator: counting due samples stays exact over hours."""
        out_hz = DLPF[self.regs[CONFIG] & 0x07][4]
        scale = 10**9 + round(self.clock_error_ppm * 1000)
        return (1 + self.regs[SMPLRT_DIV]) * 10**9 * scale, out_hz * 10**9

    @property
    def sample_rate_hz(self) -> float:
        num, den = self._period_fraction()
        return 1e9 * den / num

    def _catch_up(self) -> None:
        now_ns = self.clock.now_ns()
        if self._anchor_ns is None or now_ns < self._anchor_ns:
            return
        num, den = self._period_fraction()
        due = (now_ns - self._anchor_ns) * den // num
        n = due - self._k
        if n <= 0:
            return
        period_s = num / den / 1e9
        # Without the FIFO the host sees only the newest sample (the data registers): the older ones advance the
        # error states in one step, as ones overwritten in the FIFO do. The noise is then drawn stationary, which
        # is what the filter's output is after more than a few periods; what the host reads is the same in law.
        visible = MAX_SAMPLES_PER_CATCH_UP if self.regs[USER_CTRL] & USER_FIFO_EN else 1
        if n > visible:
            self._skip(n - visible, period_s)
        ks = np.arange(self._k + 1, due + 1)
        times_s = (self._anchor_ns + ks * (num / den)) / 1e9
        self._k = due
        self._emit(times_s, period_s)

    def _skip(self, count: int, period_s: float) -> None:
        """Samples nobody can see any more: advance the error states in one step and count them."""
        walk_sigma, noise_sigma, _ = self._noise_params(period_s)
        self._bias_walk += self.rng.standard_normal(6) * walk_sigma * math.sqrt(count)
        self._noise = self.rng.standard_normal(6) * noise_sigma
        if self.errors.gyro_bias_gm_dps:
            phi = math.exp(-count * period_s / self.errors.gyro_bias_gm_tau_s)
            self._gyro_gm = (phi * self._gyro_gm + self.rng.standard_normal(3)
                             * math.radians(self.errors.gyro_bias_gm_dps) * math.sqrt(1 - phi * phi))
        frame = self._fifo_frame_columns()
        if self.regs[USER_CTRL] & USER_FIFO_EN and frame:
            self.fifo_bytes_dropped += len(self.fifo) + 2 * len(frame) * count
            self.fifo.clear()
        self.samples_generated += count
        self._k += count

    def _noise_params(self, period_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-sample bias-walk step, stationary noise sigma and filter pole, accel x y z then gyro."""
        e = self.errors
        a_bw, _, g_bw, _, _ = DLPF[self.regs[CONFIG] & 0x07]
        rate = 1.0 / period_s
        pole = np.array([math.exp(-2 * math.pi * a_bw / rate)] * 3 + [math.exp(-2 * math.pi * g_bw / rate)] * 3)
        density = np.array([e.accel_noise_ug_per_rthz * 1e-6 * G0_MPS2] * 3
                           + [math.radians(e.gyro_noise_dps_per_rthz)] * 3)
        # First-order low-pass of white noise, discretised so that its density at 0 Hz stays `density`.
        sigma = density * np.sqrt(rate * (1 - pole) / (2 * (1 + pole)))
        walk = np.array([e.accel_bias_walk_mg_per_rts * 1e-3 * G0_MPS2] * 3
                        + [math.radians(e.gyro_bias_walk_dps_per_rts)] * 3) * math.sqrt(period_s)
        return walk, sigma, pole

    def _emit(self, times_s: np.ndarray, period_s: float) -> None:
        m = len(times_s)
        _, a_delay, _, g_delay, _ = DLPF[self.regs[CONFIG] & 0x07]
        f = np.empty((m, 3))
        w = np.empty((m, 3))
        ambient = np.empty(m)
        vibrates = self.errors.vibrates
        speed = np.zeros(m)
        engine = np.zeros(m, bool)
        for i, t in enumerate(times_s):
            sa = self.trajectory.state(max(float(t) - a_delay, 0.0))
            sg = sa if g_delay == a_delay else self.trajectory.state(max(float(t) - g_delay, 0.0))
            f[i] = sa.f_body_mps2
            w[i] = sg.w_body_rps
            ambient[i] = sg.ambient_degc
            if vibrates:
                speed[i] = math.sqrt(float(sa.vel_ned_mps @ sa.vel_ned_mps))
                engine[i] = sa.engine_on
        if vibrates:
            vib_f, vib_w = self._vibration(times_s, period_s, speed, engine)
            f += vib_f
            w += vib_w
        truth = np.hstack((f @ self.chip_from_body.T, w @ self.chip_from_body.T))

        walk_step, sigma, pole = self._noise_params(period_s)
        walk = self._bias_walk + np.cumsum(self.rng.standard_normal((m, 6)) * walk_step, axis=0)
        self._bias_walk = walk[-1].copy()
        drive = self.rng.standard_normal((m, 6)) * sigma * np.sqrt(1 - pole**2)
        noise, self._noise = _first_order(pole, self._noise, drive)
        measured = truth + self._bias_on + walk + noise
        if self.errors.gyro_bias_gm_dps:
            measured[:, 3:6] += self._gyro_wander(m, period_s)
        e = self.errors
        die = ambient + e.self_heating_degc
        if e.warmup_degc:
            die += e.warmup_degc * -np.expm1(-np.maximum(times_s - self._powered_s, 0.0) / e.warmup_tau_s)
        if self._tempco is not None:
            if self._die_ref is None:
                self._die_ref = float(die[0])
            measured += np.outer(die - self._die_ref, self._tempco)

        accel_sens = ACCEL_LSB_PER_G[(self.regs[ACCEL_CONFIG] >> 3) & 3]
        gyro_sens = GYRO_LSB_PER_DPS[(self.regs[GYRO_CONFIG] >> 3) & 3]
        temp = die + self.rng.standard_normal(m) * e.temp_noise_degc
        counts = np.empty((m, 7))
        counts[:, 0:3] = measured[:, 0:3] / G0_MPS2 * accel_sens
        counts[:, 3] = (temp - 36.53) * 340.0
        counts[:, 4:7] = np.degrees(measured[:, 3:6]) * gyro_sens
        raw = np.clip(np.rint(counts), -32768, 32767).astype(np.int16)

        previous = np.frombuffer(bytes(self.regs[ACCEL_XOUT_H: GYRO_ZOUT_L + 1]), dtype=">i2")
        frozen = [c for c, bit in zip((0, 1, 2, 4, 5, 6), (0x20, 0x10, 0x08, 0x04, 0x02, 0x01), strict=True)
                  if self.regs[PWR_MGMT_2] & bit]
        if self.regs[PWR_MGMT_1] & PWR1_TEMP_DIS:
            frozen.append(3)
        raw[:, frozen] = previous[frozen]
        self.regs[ACCEL_XOUT_H: GYRO_ZOUT_L + 1] = raw[-1].astype(">i2").tobytes()

        columns = self._fifo_frame_columns()
        if self.regs[USER_CTRL] & USER_FIFO_EN and columns:
            self._fifo_push(raw[:, columns].astype(">i2").tobytes())
        if self.regs[INT_ENABLE] & INT_DATA_RDY:
            self.regs[INT_STATUS] |= INT_DATA_RDY
        self.samples_generated += m

    def _gyro_wander(self, m: int, period_s: float) -> np.ndarray:
        """The Gauss-Markov part of the gyro offset at each of ``m`` samples (rad/s, chip axes)."""
        e = self.errors
        phi = math.exp(-period_s / e.gyro_bias_gm_tau_s)
        drive = self.rng.standard_normal((m, 3)) * math.radians(e.gyro_bias_gm_dps) * math.sqrt(1 - phi * phi)
        out, self._gyro_gm = _first_order(phi, self._gyro_gm, drive)
        return out

    def _vibration(self, times_s: np.ndarray, period_s: float, speed: np.ndarray,
                   engine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the vehicle's vibration adds to the specific force and the rate (body axes) at each sample.

        Real motion, so it passes the chip's low-pass filter: the tones by its gain at their frequency, the
        broadband part as white noise at the output rate (the filter's band is at least the Nyquist band at
        the rates the phone profile runs)."""
        e = self.errors
        m = len(times_s)
        a_bw, _, _, _, _ = DLPF[self.regs[CONFIG] & 0x07]
        vib_f = self.rng.standard_normal((m, 3)) * VIBRATION_AXES * (e.vibration_accel_mps2_per_mps * speed)[:, None]
        vib_w = self.rng.standard_normal((m, 3)) * (math.radians(e.vibration_gyro_dps_per_mps) * speed)[:, None]
        gain_bounce = 1.0 / math.hypot(1.0, BOUNCE_HZ / a_bw)
        vib_f[:, 2] += (e.bounce_mps2_per_mps * gain_bounce) * speed * np.sin(2 * math.pi * BOUNCE_HZ * times_s)
        # The engine's tone keeps its phase from sample to sample while its frequency follows the speed.
        f_engine = ENGINE_IDLE_HZ + ENGINE_HZ_PER_MPS * speed
        phase = self._engine_phase + 2 * math.pi * np.cumsum(f_engine) * period_s
        self._engine_phase = float(phase[-1] % (2 * math.pi))
        tone = e.engine_vibration_mps2 / np.hypot(1.0, f_engine / a_bw) * np.sin(phase) * engine
        vib_f += tone[:, None] * ENGINE_AXES
        return vib_f, vib_w

    def _fifo_frame_columns(self) -> list[int]:
        enabled = self.regs[FIFO_EN]
        return [c for bit, cols in FIFO_SOURCES if enabled & bit for c in cols]

    def _fifo_push(self, data: bytes) -> None:
        self.fifo += data
        excess = len(self.fifo) - FIFO_CAPACITY
        if excess > 0:
            del self.fifo[:excess]
            self.fifo_bytes_dropped += excess
            if self.regs[INT_ENABLE] & INT_FIFO_OFLOW:
                self.regs[INT_STATUS] |= INT_FIFO_OFLOW

    # ---- the bus ---------------------------------------------------------------------------------
    def next_register(self, reg: int, n: int) -> int:
        for _ in range(n):
            if reg == FIFO_R_W:
                return reg
            reg = (reg + 1) & 0xFF
        return reg

    def read(self, reg: int, n: int) -> bytes:
        self._catch_up()
        count = len(self.fifo)  # FIFO_COUNT is latched for the whole burst
        out = bytearray()
        status_read = False
        while len(out) < n:
            if reg == FIFO_R_W:
                out += self._fifo_pop(n - len(out))
                break
            if reg == FIFO_COUNTH:
                out.append(count >> 8)
            elif reg == FIFO_COUNTL:
                out.append(count & 0xFF)
            elif reg == WHO_AM_I:
                out.append(self.who_am_i)
            else:
                out.append(self.regs[reg])
                status_read = status_read or reg == INT_STATUS
            reg = (reg + 1) & 0xFF
        if status_read or self.regs[INT_PIN_CFG] & INT_RD_CLEAR:
            self.regs[INT_STATUS] = 0
        return bytes(out)

    def _fifo_pop(self, n: int) -> bytes:
        """An empty FIFO repeats the last byte it gave, as the register map says."""
        take = min(n, len(self.fifo))
        data = bytes(self.fifo[:take])
        del self.fifo[:take]
        if take:
            self._fifo_last = data[-1]
        return data + bytes((self._fifo_last,)) * (n - take)

    def write(self, reg: int, data: bytes) -> None:
        self._catch_up()
        for value in data:
            self._write_register(reg, value)
            if reg != FIFO_R_W:
                reg = (reg + 1) & 0xFF

    def _write_register(self, reg: int, value: int) -> None:
        now_ns = self.clock.now_ns()
        if reg == FIFO_R_W:
            self._fifo_push(bytes((value,)))
        elif reg in READ_ONLY:
            return
        elif reg == PWR_MGMT_1:
            if value & PWR1_DEVICE_RESET:
                self._device_reset()
                return
            self.regs[reg] = value
            self._start_or_stop(now_ns)
        elif reg in (SMPLRT_DIV, CONFIG):
            self.regs[reg] = value
            self._restart_sample_clock(now_ns)
        elif reg == USER_CTRL:
            if value & USER_FIFO_RESET and not value & USER_FIFO_EN:
                self.fifo.clear()
            if value & USER_SIG_COND_RESET:
                self.regs[ACCEL_XOUT_H: GYRO_ZOUT_L + 1] = bytes(GYRO_ZOUT_L + 1 - ACCEL_XOUT_H)
                self._noise = np.zeros(6)
            self.regs[reg] = value & ~0x07  # the reset bits clear themselves
        elif reg == SIGNAL_PATH_RESET:
            if value & 0x04:
                self._noise[3:6] = 0.0
            if value & 0x02:
                self._noise[0:3] = 0.0
        else:
            self.regs[reg] = value
