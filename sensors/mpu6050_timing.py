"""The MPU-6050's sample timing: the digital low-pass filter's settings and the divider that gives a rate.

Apart from the driver (sensors.mpu6050, which needs numpy) so that checking a configuration's ``[imu] rate_hz``
(``logger config check``, ``logger status --config``: an operator's SSH session on the board's one core) loads
no numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

MAX_RATE_HZ = 1000.0  # the accelerometer's output rate: faster only repeats accelerometer samples


@dataclass(frozen=True, slots=True)
class DlpfSetting:
    """One row of the CONFIG register's DLPF_CFG table: bandwidths and group delays of the filter."""

    cfg: int
    accel_bandwidth_hz: float
    accel_delay_s: float
    gyro_bandwidth_hz: float
    gyro_delay_s: float
    gyro_output_hz: float  # the rate SMPLRT_DIV divides


DLPF_SETTINGS = (
    DlpfSetting(0, 260.0, 0.0, 256.0, 0.98e-3, 8000.0),
    DlpfSetting(1, 184.0, 2.0e-3, 188.0, 1.9e-3, 1000.0),
    DlpfSetting(2, 94.0, 3.0e-3, 98.0, 2.8e-3, 1000.0),
    DlpfSetting(3, 44.0, 4.9e-3, 42.0, 4.8e-3, 1000.0),
    DlpfSetting(4, 21.0, 8.5e-3, 20.0, 8.3e-3, 1000.0),
    DlpfSetting(5, 10.0, 13.8e-3, 10.0, 13.4e-3, 1000.0),
    DlpfSetting(6, 5.0, 19.0e-3, 5.0, 18.6e-3, 1000.0),
)


@dataclass(frozen=True, slots=True)
class SampleTiming:
    """What CONFIG and SMPLRT_DIV are set to for a requested rate, and what that gives."""

    dlpf: DlpfSetting
    smplrt_div: int

    @property
    def rate_hz(self) -> float:
        return self.dlpf.gyro_output_hz / (1 + self.smplrt_div)

    @property
    def period_s(self) -> float:
        return (1 + self.smplrt_div) / self.dlpf.gyro_output_hz


def _divider(setting: DlpfSetting, rate_hz: float) -> int | None:
    ratio = setting.gyro_output_hz / rate_hz
    div = round(ratio) - 1
    if abs(ratio - (div + 1)) > 1e-9 * ratio or not 0 <= div <= 255:
        return None
    return div


def choose_sample_timing(rate_hz: float, dlpf_cfg: int | None = None) -> SampleTiming:
    """The DLPF setting and divider for ``rate_hz``: the widest filter whose bandwidths stay below rate/2.

    Below half the rate so that the digital filter is the anti-alias filter; the widest such filter so
    that the group delay (which the time stamps must account for) stays as small as the rate allows.
    """
    if not 0 < rate_hz <= MAX_RATE_HZ:
        raise ValueError(f"MPU-6050 rate {rate_hz:g} Hz: must be above 0 and at most {MAX_RATE_HZ:g} Hz")
    if dlpf_cfg is not None:
        if dlpf_cfg not in range(len(DLPF_SETTINGS)):
            raise ValueError(f"MPU-6050 dlpf_cfg {dlpf_cfg}: must be 0..6 (7 is reserved)")
        setting = DLPF_SETTINGS[dlpf_cfg]
        div = _divider(setting, rate_hz)
        if div is None:
            raise ValueError(f"MPU-6050 rate {rate_hz:g} Hz with dlpf_cfg {dlpf_cfg}: the rate must divide "
                             f"{setting.gyro_output_hz:g} Hz by 1..256")
        return SampleTiming(setting, div)
    best: SampleTiming | None = None
    for setting in DLPF_SETTINGS:
        div = _divider(setting, rate_hz)
        if div is None or max(setting.accel_bandwidth_hz, setting.gyro_bandwidth_hz) >= rate_hz / 2:
            continue
        if best is None or setting.gyro_bandwidth_hz > best.dlpf.gyro_bandwidth_hz:
            best = SampleTiming(setting, div)
    if best is None:
        if 1000.0 % rate_hz:
            raise ValueError(f"MPU-6050 rate {rate_hz:g} Hz: must divide 1000 Hz (e.g. 20, 50, 100, 200, "
                             "500, 1000), or above 512 Hz divide 8000 Hz (800)")
        raise ValueError(f"MPU-6050 rate {rate_hz:g} Hz: even the narrowest filter (5 Hz) is not below "
                         "half the rate; use 20 Hz or more, or set dlpf_cfg")
    return best
