"""The simulated vehicle: one drive, one board crystal, and every device model wired to it.

``logger run --sim`` asks for this and gets back what a board would have: an I2C bus path with the MPU-6050
and BMP180 on it, two serial port paths (ELM327, u-blox), a GPIO chip path with the PPS line. The daemon
then opens them with the same drivers it uses on hardware. The truth (true time against board time, the
vehicle's state) stays available so a recorded drive can be scored.
"""

from __future__ import annotations

import datetime as dt
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sensors.sim import gpiod_ext
from sensors.sim.bmp085 import Bmp085Model
from sensors.sim.drive import Drive
from sensors.sim.elm327 import Elm327Model
from sensors.sim.gnss_time import GnssTimeline
from sensors.sim.governor import Governor
from sensors.sim.i2c import SimI2cAdapter
from sensors.sim.mpu6050 import Mpu6050Errors, Mpu6050Model, chip_from_body
from sensors.sim.obd_ecu import engine_ecu, transmission_ecu
from sensors.sim.oscillator import Oscillator, OscillatorClock
from sensors.sim.pps import PpsSignal, pps_chip
from sensors.sim.profile import SOLUTION_JITTER_S, SimProfile
from sensors.sim.pty import PtyPort
from sensors.sim.raw_obs import GpsBroadcast, RawObservations
from sensors.sim.scenarios import make_drive
from sensors.sim.ublox import DEFAULT_MESSAGES, NMEA_ONLY_MESSAGES, UbloxReceiverModel

NS_PER_S = 1_000_000_000
MPU6050_ADDRESS = 0x68
BMP180_ADDRESS = 0x77
PPS_CHIP_PATH = "/dev/gpiochip-sim"
PPS_LINE = 28
WALL_CLOCK_ERROR_NS = 20_000_000

# How far the vehicle's speed sensor reads high in each scenario (OBD speed = factor * true speed).
OBD_SPEED_FACTOR = {"urban": 1.02, "outage-60s": 1.02, "tunnel-130s": 1.03}
# A receiver set up for more than two fixes a second is set up for a faster line too: at 9600 baud four
# epochs of NAV-PVT, GGA and RMC already fill the UART (its transmit buffer then drops messages).
FAST_RECEIVER_BAUD = 115200


@dataclass
class VehicleDevices:
    """Where the daemon finds each simulated device, as it would find hardware."""

    i2c_path: str | None = None
    imu_address: int = MPU6050_ADDRESS
    baro_address: int = BMP180_ADDRESS
    elm327_path: str | None = None
    gnss_path: str | None = None
    gnss_baud: int = 9600
    gnss_meas_period_ms: int | None = None  # the receiver's measurement period, which a setup should keep
    gpio_chip: str | None = None
    pps_line: int = PPS_LINE
    gpsd_host: str | None = None  # a simulated gpsd reading the receiver and its PPS
    gpsd_port: int | None = None
    realtime_ns: Callable[[], int] | None = None  # the board's system clock, which gpsd stamps PPS edges with


@dataclass
class SimVehicle:
    """A drive with its devices; ``start()`` powers them, ``stop()`` unplugs everything."""

    scenario: str
    seed: int
    profile: SimProfile
    drive: Drive
    oscillator: Oscillator
    clock: OscillatorClock
    timeline: GnssTimeline
    devices: VehicleDevices
    i2c: SimI2cAdapter | None = None
    imu: Mpu6050Model | None = None
    baro: Bmp085Model | None = None
    elm327_port: PtyPort | None = None
    elm327: Elm327Model | None = None
    gnss_port: PtyPort | None = None
    gnss: UbloxReceiverModel | None = None
    pps: PpsSignal | None = None
    gpio: Any = None
    gpsd: Any = None
    governor: Governor | None = None  # paces the drive when every device is simulated (``paced``)
    realtime_offset_ns: int = 0  # the board's system clock minus its monotonic clock (no NTP step during a drive)
    _stack: list[Any] = field(default_factory=list)

    @property
    def time_scale(self) -> float:
        """The time scale asked for: the pace itself when the drive is not governed, its ceiling when it is."""
        return self.governor.ceiling if self.governor is not None else self.clock.time_scale

    def true_unix_ns(self, board_ns: int) -> int:
        """True UTC time (Unix ns) at a board monotonic time: what a perfect stamp would say."""
        return self.timeline.utc_unix_ns(self.timeline.gps_ns(self.oscillator.true_ns(board_ns)))

    def wall_clock_ns(self) -> int:
        """The simulated board's system clock: NTP-synchronised, 20 ms off true time (an LTE link's worth)."""
        return self.true_unix_ns(self.clock.monotonic_ns()) + WALL_CLOCK_ERROR_NS

    def board_realtime_ns(self) -> int:
        """The board's CLOCK_REALTIME as a simulated gpsd stamps PPS edges with: monotonic plus a fixed offset."""
        return self.clock.monotonic_ns() + self.realtime_offset_ns

    def truth_nav(self, board_ns: int) -> dict[str, Any]:
        true_ns = self.oscillator.true_ns(board_ns)
        s = self.drive.state(true_ns / NS_PER_S)
        return {"t_true_ns": self.timeline.utc_unix_ns(self.timeline.gps_ns(true_ns)),
                "lat_deg": math.degrees(s.lat_rad), "lon_deg": math.degrees(s.lon_rad), "height_m": s.height_m,
                "vel_ned_mps": [float(v) for v in s.vel_ned_mps],
                "rpy_deg": [math.degrees(float(a)) for a in s.rpy_rad]}

    def start(self) -> None:
        if self.governor is not None:
            self.governor.start()
            self._stack.append(self.governor.stop)
        if self.elm327 is not None:
            self.elm327.start()
            self._stack.append(self.elm327.stop)
        if self.gnss is not None:
            self.gnss.start()
            self._stack.append(self.gnss.stop)
        if self.gpio is not None:
            gpiod_ext.install()
            gpiod_ext.register(self.gpio)
            self._stack.append(gpiod_ext.uninstall)
            self._stack.append(lambda: gpiod_ext.unregister(self.gpio))
        if self.gpsd is not None:
            self.gpsd.start()
            self._stack.append(self.gpsd.stop)

    def stop(self) -> None:
        while self._stack:
            fn = self._stack.pop()
            try:
                fn()
            except Exception:  # unplugging a model must never stop the others from being unplugged
                pass
        for port in (self.elm327_port, self.gnss_port):
            if port is not None:
                port.close()
        if self.gpsd is not None:
            self.gpsd.stop()  # also when never started: it listens from the moment it is built


def build_vehicle(scenario: str = "urban", seed: int = 1, *, time_scale: float = 1.0,
                  duration_s: float | None = None, imu: bool = True, baro: bool = True, obd: bool = True,
                  gnss: bool = True, pps: bool = True, start_utc: dt.datetime | None = None,
                  host_monotonic_ns: Any = time.monotonic_ns,
                  scenario_options: dict[str, Any] | None = None, gpsd: bool = False,
                  paced: bool = False, profile: SimProfile | None = None) -> SimVehicle:
    """Build the drive and the models asked for. Board time starts at the host's monotonic clock, so at time
    scale 1 simulated and real devices share one clock; the drive starts at the current UTC second.

    With ``gpsd`` a simulated gpsd on 127.0.0.1 reads the receiver and its PPS (``devices.gpsd_host/port``),
    whether or not the daemon also opens the receiver's port or PPS line itself.

    ``scenario_options`` go to the drive (:func:`sensors.sim.scenarios.make_drive`), except ``imu_error_scale``:
    a factor on the MPU-6050's error terms, or a mapping of term to factor (:meth:`Mpu6050Errors.scaled`), for
    testing the filter on a chip worse than its configuration assumes (applied to the profile's chip).

    ``profile`` says which hardware the vehicle carries (:class:`~sensors.sim.profile.SimProfile`: the kind of
    receiver, its rate and latency, the IMU's grade and its mounting); by default the logger's own board.

    With ``paced`` the drive is governed (:mod:`sensors.sim.governor`): ``time_scale`` is then a ceiling, and
    the drive runs as fast as the threads reporting to ``clock.late`` keep up with. Only for a daemon whose
    devices are all simulated: a real device keeps the host's time."""
    horizon = duration_s if duration_s is not None else 8 * 3600.0
    options = dict(scenario_options or {})
    profile = profile if profile is not None else SimProfile()
    imu_scale = options.pop("imu_error_scale", None)
    chip = Mpu6050Errors.phone_grade() if profile.imu == "phone" else Mpu6050Errors()
    imu_errors = chip.scaled(imu_scale) if imu_scale is not None else chip
    drive = make_drive(scenario, seed=seed, duration_s=horizon + 60.0, **options)
    rng = np.random.default_rng([seed, 7])
    oscillator = Oscillator.for_trajectory(drive, horizon_s=horizon + 60.0, board_start_ns=host_monotonic_ns(),
                                           offset_ppm=float(rng.uniform(-40.0, 40.0)), seed=rng)
    clock = OscillatorClock(oscillator, time_scale, host_monotonic_ns=host_monotonic_ns)
    if start_utc is None:
        start_utc = dt.datetime.fromtimestamp(math.floor(time.time()), dt.UTC)
    timeline = GnssTimeline(start_utc=start_utc)
    devices = VehicleDevices()
    v = SimVehicle(scenario, seed, profile, drive, oscillator, clock, timeline, devices)
    if paced:
        v.governor = Governor(clock, time_scale, host_monotonic_ns=host_monotonic_ns)
    child = np.random.SeedSequence([seed, 11]).spawn(5)
    if imu or baro:
        v.i2c = SimI2cAdapter()
        devices.i2c_path = v.i2c.path
        if imu:
            v.imu = Mpu6050Model(clock, drive, seed=np.random.default_rng(child[0]), errors=imu_errors,
                                 chip_from_body=chip_from_body(profile.mounting_rpy_deg))
            v.i2c.attach(MPU6050_ADDRESS, v.imu)
        if baro:
            v.baro = Bmp085Model(clock, drive, seed=np.random.default_rng(child[1]))
            v.i2c.attach(BMP180_ADDRESS, v.baro)
    if obd:
        scale = OBD_SPEED_FACTOR.get(scenario, 1.02)
        ecus = [engine_ecu(drive, scale_error=1.0 / scale - 1.0),
                transmission_ecu(drive, scale_error=1.0 / scale - 1.0)]
        v.elm327_port = PtyPort()
        v.elm327 = Elm327Model(v.elm327_port, ecus, clock, seed=np.random.default_rng(child[2]))
        devices.elm327_path = v.elm327_port.path
    if gnss or pps or gpsd:
        v.gnss_port = PtyPort()
        nmea_only = profile.receiver == "nmea"
        # What a raw-capable receiver (M8T, F9P) sends as RXM-RAWX once the host turns raw observations on.
        raw = RawObservations(GpsBroadcast(drive.gnss_sky.constellation, timeline, seed), sky=drive.gnss_sky,
                              seed=seed)
        v.gnss = UbloxReceiverModel(v.gnss_port, clock, drive, seed=np.random.default_rng(child[3]),
                                    timeline=timeline, ubx=not nmea_only, model=profile.receiver_model,
                                    raw_frames=raw.for_epoch,
                                    messages=NMEA_ONLY_MESSAGES if nmea_only else DEFAULT_MESSAGES,
                                    meas_period_ms=profile.meas_period_ms,
                                    baud=FAST_RECEIVER_BAUD if profile.gnss_rate_hz > 2 else None,
                                    latency_s=(profile.gnss_latency_s, SOLUTION_JITTER_S),
                                    leap_unconfirmed_s=profile.leap_unconfirmed_s)
        devices.gnss_path = v.gnss_port.path
        devices.gnss_baud = v.gnss.baud
        devices.gnss_meas_period_ms = v.gnss.meas_period_ms
    if (pps or gpsd) and v.gnss is not None:
        v.pps = PpsSignal(oscillator, v.gnss.time_pulse_locked, seed=int(child[4].generate_state(1)[0]),
                          gnss_ns_at_start=timeline.start_gps_ns,
                          pulse_offset_ns=v.gnss.pulse_quantisation.edge_offset_ns)
    if pps and v.pps is not None:
        v.gpio = pps_chip(v.pps, clock, path=PPS_CHIP_PATH, offset=PPS_LINE, paced=True)
        devices.gpio_chip = PPS_CHIP_PATH
    if gpsd and v.gnss is not None:
        from sensors.sim.gpsd import ReceiverFeed, SimGpsd

        # The board's system clock as NTP set it at boot; gpsd stamps PPS edges on it.
        v.realtime_offset_ns = v.wall_clock_ns() - clock.monotonic_ns()
        feed = ReceiverFeed(v.gnss, pps=v.pps, realtime_offset_ns=v.realtime_offset_ns,
                            seed=np.random.default_rng([seed, 13]))
        v.gpsd = SimGpsd(feed)
        devices.gpsd_host, devices.gpsd_port = v.gpsd.address
        devices.realtime_ns = v.board_realtime_ns
    return v
