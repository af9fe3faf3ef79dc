"""The IMU's noise as the drive shows it: a datasheet figure is a bench's, a car shakes the chip.

The filter's process noise (velocity and angle random walk) starts at the configured densities, from the
datasheet. A car adds vibration (engine, road) and a phone-grade chip is ten times noisier than an MPU-6050;
with the datasheet's figures the filter is too sure of its dead reckoning and refuses the measurements that
would set it right. So the white part of the samples is measured as they come: second differences
x[k] - 2 x[k-1] + x[k-2] take out whatever the vehicle does smoothly (its accelerations and turns change slowly
against the sample rate) and leave the noise, whose variance they carry six times. Averaged over about half a
minute of samples, per sensor over its three axes, the variance per sample times the sample interval is the
random walk's density squared (velocity or angle error variance per second): what the filter's process noise
is. A datasheet's density is one-sided over the Nyquist band, so a chip exactly as noisy as its datasheet
measures 1/sqrt(2) of it here. The filter uses the larger of the two, so the measurement only ever widens what
the datasheet says.
"""

from __future__ import annotations

import math

TAU_S = 30.0  # the average's memory, drive time
MIN_S = 5.0  # before this much has been seen, the datasheet stands


class ImuNoiseMonitor:
    """Running white-noise densities of the accelerometer (m/s^2/sqrt(Hz)) and gyro (rad/s/sqrt(Hz))."""

    __slots__ = ("_a1", "_a2", "_g1", "_g2", "_k", "_var_a", "_var_g", "seen_s")

    def __init__(self) -> None:
        self._a1: tuple[float, float, float] | None = None
        self._a2: tuple[float, float, float] | None = None
        self._g1: tuple[float, float, float] | None = None
        self._g2: tuple[float, float, float] | None = None
        self._var_a = 0.0  # mean over axes of (second difference)^2 / 6
        self._var_g = 0.0
        self._k = 0
        self.seen_s = 0.0

    def add(self, acc: tuple[float, float, float], gyro: tuple[float, float, float], dt: float) -> None:
        """One sample and the interval since the previous one (a gap restarts the differences)."""
        if not 0.0 < dt < 0.5:
            self._a1 = self._a2 = self._g1 = self._g2 = None
        a1, a2, g1, g2 = self._a1, self._a2, self._g1, self._g2
        if a1 is not None and a2 is not None and g1 is not None and g2 is not None:
            da = ((acc[0] - 2.0 * a1[0] + a2[0]) ** 2 + (acc[1] - 2.0 * a1[1] + a2[1]) ** 2
                  + (acc[2] - 2.0 * a1[2] + a2[2]) ** 2) / 18.0
            dg = ((gyro[0] - 2.0 * g1[0] + g2[0]) ** 2 + (gyro[1] - 2.0 * g1[1] + g2[1]) ** 2
                  + (gyro[2] - 2.0 * g1[2] + g2[2]) ** 2) / 18.0
            self._k += 1
            w = max(1.0 / self._k, dt / TAU_S)
            # variance per sample times the interval: the density squared, whatever the rate
            self._var_a += w * (da * dt - self._var_a)
            self._var_g += w * (dg * dt - self._var_g)
            self.seen_s += dt
        self._a2, self._a1 = a1, acc
        self._g2, self._g1 = g1, gyro

    def densities(self) -> tuple[float, float] | None:
        """(accelerometer, gyro) white-noise densities measured, None before enough was seen."""
        if self.seen_s < MIN_S:
            return None
        return math.sqrt(self._var_a), math.sqrt(self._var_g)
