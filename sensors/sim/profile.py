"""Which hardware the simulated vehicle carries: the kind of receiver, its rate and latency, the IMU, its mounting.

Real installations differ in exactly these ways (a u-blox sending UBX with accuracy figures, or an NMEA-only
receiver such as the paper's AEK-4T; one fix a second or ten; a datasheet-grade MPU-6050 or a phone-grade MEMS
IMU; a board mounted square or at an angle nobody measured), and a filter tested on one of them only has been
tested on the simulator's favourite. :class:`SimProfile` names one combination. It is the one place the
``[sim]`` keys' defaults are written: the configuration's schema reads them from its fields, and
:meth:`SimProfile.from_config` maps the keys back, as the settings classes of the logger do.

Kept free of numpy: the configuration imports it, and ``logger status`` and ``logger config check`` must not
load numpy.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

RECEIVERS = ("ubx", "nmea")  # a u-blox (UBX and NMEA, configurable), or a receiver that speaks NMEA only
# Which u-blox a "ubx" receiver is: its firmware answers MON-VER as this product, and only those with raw firmware
# (the timing M8T, the high-precision F9P) take RXM-RAWX and RXM-SFRBX; a standard-precision M8N refuses them.
# sensors.sim.ublox_commands.RECEIVER_MODELS holds each one's firmware.
RECEIVER_MODELS = ("NEO-M8N", "NEO-M8T", "ZED-F9P")
IMUS = ("mpu6050", "phone")  # the datasheet's MPU-6050, or phone-grade MEMS errors in the same register model
# Navigation rates a receiver can run at with an epoch on every whole second (measurement periods of whole
# milliseconds that divide 1000 ms): the clock pairs each PPS edge with the fix of its second.
GNSS_RATES_HZ = (1, 2, 4, 5, 8, 10, 20, 25)
# The u-blox solution comes this long after its epoch at the least, plus an exponential excess of this mean
# capped at SOLUTION_JITTER_MAX_S (or the solution period, when shorter), as NAV-PVT arrival times of M8
# receivers on a UART show.
SOLUTION_LATENCY_S = 0.04
SOLUTION_JITTER_S = 0.06
SOLUTION_JITTER_MAX_S = 0.35
# A fix must still reach the host within the second after its epoch's PPS edge (sync.pairing's report window),
# after the latency, the jitter and the line: 0.6 s leaves that.
MAX_GNSS_LATENCY_S = 0.6
MAX_LEAP_UNCONFIRMED_S = 750.0  # the almanac page with the UTC parameters comes every 12.5 min
PHONE_IMU_RATE_HZ = 100.0  # a phone's sensor framework delivers its IMU at about 100 Hz


@dataclass(frozen=True)
class SimProfile:
    """One combination of simulated hardware; the defaults are the logger's own board (u-blox M8 at 1 Hz,
    MPU-6050 mounted square to the vehicle)."""

    receiver: str = "ubx"
    gnss_rate_hz: float = 1.0
    gnss_latency_s: float = SOLUTION_LATENCY_S  # the least delay of a solution after its epoch
    imu: str = "mpu6050"
    # The IMU board's axes against the vehicle's (FRD), as roll, pitch, yaw: the same convention as
    # [nav] mounting_rpy_deg, so that the filter told the same angles undoes them exactly.
    mounting_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    receiver_model: str = "NEO-M8N"  # a "ubx" receiver's product (RECEIVER_MODELS)
    # A cold start: seconds after the first fix during which the receiver says its leap count is not yet the
    # broadcast one (NAV-TIMEGPS leapSValid clear; the almanac's UTC page comes within 12.5 min)
    leap_unconfirmed_s: float = 0.0

    def __post_init__(self) -> None:
        if self.receiver not in RECEIVERS:
            raise ValueError(f"receiver must be one of {', '.join(RECEIVERS)}, not {self.receiver!r}")
        if self.receiver_model not in RECEIVER_MODELS:
            raise ValueError(f"receiver_model must be one of {', '.join(RECEIVER_MODELS)}, not {self.receiver_model!r}")
        if self.imu not in IMUS:
            raise ValueError(f"imu must be one of {', '.join(IMUS)}, not {self.imu!r}")
        if self.gnss_rate_hz not in GNSS_RATES_HZ:
            raise ValueError(f"gnss_rate_hz must be one of {', '.join(map(str, GNSS_RATES_HZ))} "
                             f"(an epoch on every whole second), not {self.gnss_rate_hz!r}")
        if not 0.0 <= self.gnss_latency_s <= MAX_GNSS_LATENCY_S:
            raise ValueError(f"gnss_latency_s must be between 0 and {MAX_GNSS_LATENCY_S:g} s")
        if not 0.0 <= self.leap_unconfirmed_s <= MAX_LEAP_UNCONFIRMED_S:
            raise ValueError(f"leap_unconfirmed_s must be between 0 and {MAX_LEAP_UNCONFIRMED_S:g} s")
        if len(self.mounting_rpy_deg) != 3 or not all(math.isfinite(a) for a in self.mounting_rpy_deg):
            raise ValueError("mounting_rpy_deg must be three finite angles [roll, pitch, yaw]")

    @classmethod
    def from_config(cls, sim: Mapping[str, Any]) -> SimProfile:
        """The profile of a ``[sim]`` section (keys of the same names as the fields; others are the drive's)."""
        values = {f.name: sim[f.name] for f in fields(cls) if f.name in sim}
        if "mounting_rpy_deg" in values:
            values["mounting_rpy_deg"] = tuple(float(a) for a in values["mounting_rpy_deg"])
        for name in ("gnss_rate_hz", "leap_unconfirmed_s"):
            if name in values:
                values[name] = float(values[name])
        return cls(**values)

    @property
    def meas_period_ms(self) -> int:
        """The receiver's measurement period (UBX-CFG-RATE measRate)."""
        return round(1000 / self.gnss_rate_hz)

    @property
    def imu_rate_hz(self) -> float | None:
        """The rate this IMU delivers at when the configuration names none (``[imu] rate_hz`` not set): a phone's
        100 Hz; None for the MPU-6050, whose rate is the configuration's."""
        return PHONE_IMU_RATE_HZ if self.imu == "phone" else None

    def metadata(self) -> dict[str, str]:
        """The profile as a recording's ``simulation`` metadata holds it (strings; the mounting as JSON)."""
        return {"receiver": self.receiver, "receiver_model": self.receiver_model,
                "gnss_rate_hz": f"{self.gnss_rate_hz:g}", "gnss_latency_s": f"{self.gnss_latency_s:g}", "imu": self.imu,
                "mounting_rpy_deg": json.dumps([float(a) for a in self.mounting_rpy_deg]),
                "leap_unconfirmed_s": f"{self.leap_unconfirmed_s:g}"}

    @classmethod
    def from_metadata(cls, meta: Mapping[str, str]) -> SimProfile:
        """The profile a recording was driven with; a file from before profiles existed was the default one."""
        values: dict[str, Any] = {}
        for f in fields(cls):
            if f.name not in meta:
                continue
            raw = meta[f.name]
            values[f.name] = (tuple(json.loads(raw)) if f.name == "mounting_rpy_deg"
                              else float(raw) if f.name in ("gnss_rate_hz", "gnss_latency_s", "leap_unconfirmed_s")
                              else raw)
        return cls(**values)
