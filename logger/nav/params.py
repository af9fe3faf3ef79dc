"""The filter's tuning: sensor noise from datasheets, mounting from the installation, all overridable in ``[nav]``.

Nothing here is read from the simulator: the defaults are the MPU-6050 datasheet (PS-MPU-6000A rev. 3.4:
400 ug/sqrt(Hz) accelerometer and 0.005 deg/s/sqrt(Hz) gyro noise density, +-50 mg and +-20 deg/s initial
offsets), the BMP180 datasheet (0.03 hPa RMS noise in ultra-high-resolution mode, about 0.25 m), the OBD-II
speed resolution (1 km/h) and what u-blox receivers report as their own accuracy. A real drive adds
vibration the datasheets do not know; the noise densities can be raised in the configuration for that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

from logger.nav.earth import G0

MODES = ("17", "15", "gnss")


@dataclass
class NavParams:
    """The filter's tuning; these field defaults are the ``[nav]`` defaults, the only place they are written.

    Every ``[nav]`` key of the configuration is the field of the same name, and :data:`logger.config.SCHEMA`
    reads its defaults from here (this module must not import the configuration, which imports it).
    """

    mode: str = "17"
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU to GNSS antenna, vehicle FRD, m
    mounting_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU chip axes relative to vehicle FRD
    mount_align: bool = True  # estimate the mounting from the drive (mounting.py), mounting_rpy_deg the first guess
    accel_noise_ug_rthz: float = 400.0
    imu_noise_from_drive: bool = True  # widen the densities below to what the samples show (imu_noise.py)
    gyro_noise_dps_rthz: float = 0.005
    accel_bias_mg: float = 50.0  # initial uncertainty of the accelerometer offset
    gyro_bias_dps: float = 20.0  # initial uncertainty of the gyro offset, before the standstill calibration
    accel_bias_walk_mg_rts: float = 0.1
    # The offsets' wander at a steady temperature: 5x the MPU-6050 family's published Allan-variance bias stability
    # (1e-4 deg/s/sqrt(s), sensors/sim/mpu6050.py); the drift with temperature is the tempco terms' below.
    gyro_bias_walk_dps_rts: float = 0.0005
    # Offsets against die temperature (thermal.py), datasheet bounds (PS-MPU-6000A rev. 3.4): zero-g change +-35 mg
    # (x, y) over 0-70 degC = 0.5 mg/degC; zero-rate output variation +-20 deg/s over -40..85 degC = 0.16 deg/s/degC.
    accel_bias_tempco_mg_degc: float = 0.5
    gyro_bias_tempco_dps_degc: float = 0.16
    obd_speed_sigma_mps: float = 0.2
    obd_scale_sigma: float = 0.05
    obd_scale_walk_rts: float = 1.0e-5
    # The OBD reading's whole km/h as a state of each run of equal readings (RQ_ID, an 18th state) instead of the
    # paper's reading noise with repeats weighing less: fixes during a cruise teach its rounding, which the cruise
    # carries into an outage. On 18 simulated drives the squared horizontal RMSE 6 % lower forward and 8 % smoothed,
    # but per drive either way (docs/nav.md): off, the paper's seventeen states.
    obd_rounding_state: bool = False
    # The true speed's drift inside one 1 km/h step while the reading stays (with the rounding state): 0.016 m/s
    # over 10 s. 0 to 0.02 moved the simulated drives' figures by a few centimetres at most (docs/nav.md).
    obd_rounding_walk_mps_rts: float = 0.005
    nhc_sigma_mps: float = 0.1
    baro_sigma_m: float = 0.5
    baro_offset_walk_m_rts: float = 0.02
    # For receivers that report DOPs but no accuracy: the user range error, so that the horizontal 2D RMS is UERE x
    # HDOP and the vertical sigma UERE x VDOP. 4 m puts an open sky's fix (HDOP about 0.75 with the 15-20 satellites
    # of a multi-GNSS receiver) at the nominal 3.0 m 2D RMS below: the same data-sheet receiver either way.
    gnss_uere_m: float = 4.0
    # Receivers that report neither accuracy nor DOP (NMEA RMC and GGA only): what such receivers achieve in a
    # car. Single-frequency receivers are specified at 1.5-2.5 m CEP in open sky (u-blox M8: 2.5 m CEP; ST
    # TESEO-LIV3: 1.5 m CEP); 2.5 m CEP is sigma 2.1 m per axis (CEP = 1.18 sigma), hAcc (the 2D RMS) 3.0 m;
    # the vertical is 1.5-2x worse (VDOP over HDOP); speed 0.05-0.1 m/s specified, the 0.1 taken (0.3 m/s left
    # the NMEA velocity out as uninformative beside the OBD speed, and the heading drifted: urban east RMSE 1.77 m
    # against 0.63 m at 0.1, docs/nav.md). Positions are scaled by what the fixes' scatter shows.
    gnss_nominal_h_acc_m: float = 3.0
    gnss_nominal_v_acc_m: float = 5.0
    gnss_nominal_s_acc_mps: float = 0.1
    gnss_learn_scatter: bool = True
    # Fixes faster than this report the same error more often; they weigh together what fixes at this rate do.
    gnss_independent_hz: float = 1.0
    # A faster receiver's fixes are thinned to this rate or under, every n-th epoch on a grid through the whole
    # seconds (logger/nav/gnss_rate.py): a second of fixes says no more at 25 Hz than at 10, and weighed as one,
    # each was too weak to go in. 0: every fix.
    gnss_max_hz: float = 10.0
    # How long the error at a receiver's own accuracy floor lasts (atmosphere, orbits, clocks: minutes in truth).
    # Taken as white, the simulated drives' positions sat inside their 3 sigma 71-98 % of the time (urban: 78 / 78
    # / 71 % N/E/D); at 5 s, 99-100 % with the RMSE while moving about the same (docs/nav.md); 20 s and 60 s are
    # as consistent but weigh fixes so little that the RMSE grows. 0: the floor taken as white.
    gnss_floor_corr_s: float = 5.0
    # The same for the vertical, which the barometer holds between fixes: the receiver's slow height error (0.6-1 m
    # low for minutes on a simulated 1200 s urban drive) was followed with a 0.3 m sigma at 5 s, 90.8 % of the time
    # within 3 sigma; at 8 s 98.9 %, the vertical RMSE of five 1200 s drives 0.40 -> 0.41 m on average and of the
    # matrix's 600 s default drives unchanged (docs/nav.md).
    gnss_floor_corr_v_s: float = 8.0
    # The same for the speed (Doppler): its floor is the carrier loop's noise, which changes faster than the
    # position's. 3.5 s is not a measured correlation time but the value chosen on the simulated matrix drives,
    # whose open-sky speed errors are white (lag-1 correlation under 0.11 at 10 Hz, one drive): at the position's
    # 5 s a phone-grade IMU's gyro offset was read too slowly from the course and the phone's 60 s outage (seed 2)
    # ended 22.5 m off; at 3.5 s 17.5 m, the six default drives' squared horizontal RMSE while moving 10 % lower in
    # sum (tunnel-130s seed 1 north 0.77 -> 0.86 m the one worse). Shorter weighs them too much for the rest of the
    # model: white, that tunnel's north 1.73 m and 85 % within 3 sigma east on a 60 s outage. A real receiver's
    # 10 Hz speeds come out of its own tracking loops and filter, correlated over a fraction of a second to seconds:
    # not measured here (no recording of one against a truth), so the value is the simulator's (docs/nav.md).
    gnss_floor_corr_speed_s: float = 3.5
    gnss_acc_scale: float = 1.0
    gnss_min_sv: int = 5  # fewer satellites: the fix's own accuracy figure cannot be trusted (no redundancy)
    gnss_multipath_corr_s: float = 5.0  # how long a fix's error above the receiver's floor lasts (facades)
    zupt_sigma_mps: float = 0.02
    zaru_sigma_dps: float = 0.01
    gate_probability: float = 0.999
    heading_source: str = "gnss"  # or "config": use initial_heading_deg
    initial_heading_deg: float = 0.0
    heading_min_speed_mps: float = 3.0
    align_min_s: float = 2.0
    still_accel_mps2: float = 0.05  # starting threshold of the stop detector (adapted at OBD-confirmed stops)
    cov_interval_s: float = 0.5
    # A faster IMU's blocks (FIFO reads) are integrated a step per 1 / integration_hz s, coning and sculling within
    # each step (strapdown.preintegrate): a 1 kHz IMU costs a tenth of the steps. 0: a step per sample.
    integration_hz: float = 100.0
    publish_hz: float = 5.0
    queue_size: int = 2000
    enabled: bool = True
    extra: dict[str, Any] = field(default_factory=dict)

    # ---- SI views -------------------------------------------------------------------------------
    @property
    def accel_vrw(self) -> float:
        return self.accel_noise_ug_rthz * 1e-6 * G0

    @property
    def gyro_arw(self) -> float:
        return math.radians(self.gyro_noise_dps_rthz)

    @property
    def accel_bias_sigma(self) -> float:
        return self.accel_bias_mg * 1e-3 * G0

    @property
    def gyro_bias_sigma(self) -> float:
        return math.radians(self.gyro_bias_dps)

    @property
    def accel_bias_walk(self) -> float:
        return self.accel_bias_walk_mg_rts * 1e-3 * G0

    @property
    def gyro_bias_walk(self) -> float:
        return math.radians(self.gyro_bias_walk_dps_rts)

    @property
    def accel_bias_tempco(self) -> float:
        return self.accel_bias_tempco_mg_degc * 1e-3 * G0

    @property
    def gyro_bias_tempco(self) -> float:
        return math.radians(self.gyro_bias_tempco_dps_degc)

    @classmethod
    def from_config(cls, section: dict[str, Any]) -> NavParams:
        """From the validated ``[nav]`` section (keys as in :data:`logger.config.SCHEMA`)."""
        names = {f.name for f in fields(cls)}
        kw: dict[str, Any] = {}
        for k, v in section.items():
            if k in names:
                kw[k] = tuple(float(x) for x in v) if isinstance(v, list) else v
        return cls(**kw)
