"""Adapters from each driver to what a sampler thread runs: open, read into records, close.

Here, and only here, a driver's result becomes a record: the acquisition time is read on the board's monotonic
clock right around the bus transfer, units go into the field names, and the topic is chosen. Drivers stay free
of clocks and threads; samplers stay free of sensor knowledge.
"""

from __future__ import annotations

import base64
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from logger.fifo_time import FifoClock
from logger.sampler import Reading
from logger.timebase import TimeBase
from sensors.errors import BusError, DeviceNotFound, SensorError

FIFO_THRESHOLD_HZ = 50.0  # above this the IMU is read through its FIFO in batches
DIRECT_CHIP_RATE_HZ = 1000.0
# How long an event sensor's read waits for data before returning empty. Data ends the wait at once, so this
# only sets how often an idle thread wakes (to beat its heartbeat and see a stop): once a second is plenty for a
# 10 s staleness limit and a 5 s stop, and five times fewer wake-ups than 0.2 s on a one-core board.
EVENT_WAIT_S = 1.0


def _i2c_bus(path_or_number: str | int) -> Any:
    import smbus2

    try:
        return smbus2.SMBus(path_or_number)
    except FileNotFoundError:
        where = path_or_number if isinstance(path_or_number, str) else f"/dev/i2c-{path_or_number}"
        raise DeviceNotFound(f"I2C bus {where} not found (is the I2C overlay enabled?)") from None
    except PermissionError:
        where = path_or_number if isinstance(path_or_number, str) else f"/dev/i2c-{path_or_number}"
        raise BusError(f"I2C bus {where}: permission denied (is the service user in the i2c group?)") from None


def _close_quietly(obj: Any) -> None:
    close = getattr(obj, "close", None)
    if close is not None:
        try:
            close()
        except Exception:
            pass


class ImuSource:
    """MPU-6050: one burst per sample at low rates; the FIFO in batches above ``FIFO_THRESHOLD_HZ``."""

    name = "imu"

    def __init__(self, bus: str | int, address: int, rate_hz: float, accel_range_g: int, gyro_range_dps: int,
                 tb: TimeBase) -> None:
        self.bus_id, self.address, self.rate_hz = bus, address, rate_hz
        self.ranges = (accel_range_g, gyro_range_dps)
        self.tb = tb
        self.fifo = rate_hz > FIFO_THRESHOLD_HZ
        # The FIFO holds 85 frames: poll at least twice per filling.
        self.poll_hz = max(20.0, rate_hz / 40.0) if self.fifo else rate_hz
        self.driver: Any = None
        self._bus: Any = None
        self._pending_lost = 0
        self._fifo_clock: FifoClock | None = None

    def open(self) -> None:
        from sensors.mpu6050 import Mpu6050, choose_sample_timing

        self._fifo_clock = None  # a reopened chip starts an empty FIFO on a new count

        if self.fifo:
            chip_rate, dlpf = self.rate_hz, None
        else:
            # Read on demand: the chip samples at 1 kHz behind the low-pass filter chosen for the read rate,
            # so each read gets a sample at most 1 ms old and none is read twice or skipped when the board's
            # and the chip's clocks slide past each other.
            try:
                chip_rate, dlpf = DIRECT_CHIP_RATE_HZ, choose_sample_timing(self.rate_hz).dlpf.cfg
            except ValueError as exc:  # an unsupported rate: a configuration problem, reported as one line
                raise SensorError(f"MPU-6050: {exc}") from None
        self._bus = _i2c_bus(self.bus_id)
        try:
            self.driver = Mpu6050(self._bus, self.address, rate_hz=chip_rate, dlpf_cfg=dlpf,
                                  accel_range_g=self.ranges[0], gyro_range_dps=self.ranges[1], fifo=self.fifo,
                                  bus_name=f"I2C bus {self.bus_id}", sleep=self.tb.sleep)
        except ValueError as exc:
            raise SensorError(f"MPU-6050: {exc}") from None
        self.driver.configure()

    def read(self) -> list[Reading]:
        if not self.fifo:
            t0 = self.tb.monotonic_ns()
            s = self.driver.read()
            t1 = self.tb.monotonic_ns()
            return [Reading("/imu", {"accel_mps2": s.accel_mps2, "gyro_rps": s.gyro_rps,
                                     "temp_degc": round(s.temp_degc, 3), "fifo": False, "lost": 0}, (t0 + t1) // 2)]
        t_read = self.tb.monotonic_ns()
        batch = self.driver.read_fifo(t_read)
        t_done = self.tb.monotonic_ns()
        if self._fifo_clock is None:
            self._fifo_clock = FifoClock(batch.period_s * 1e9)
        if batch.overflowed:
            self._pending_lost += batch.lost_samples if batch.lost_samples is not None else 1
            self._fifo_clock.reset()
        n = len(batch)
        times = self._fifo_clock.stamps(n, t_read, t_done, self.driver.backlog_frames)
        out = []
        for i in range(n):
            out.append(Reading("/imu", {"accel_mps2": batch.accel_mps2[i], "gyro_rps": batch.gyro_rps[i],
                                        "temp_degc": round(batch.temp_degc, 3), "fifo": True,
                                        "lost": self._pending_lost if i == 0 else 0}, times[i]))
        if n:
            self._pending_lost = 0
        return out

    def close(self) -> None:
        _close_quietly(self._bus)
        self._bus = None


class BaroSource:
    name = "baro"

    def __init__(self, bus: str | int, address: int, oversampling: int, sea_level_pa: float, variant: str,
                 tb: TimeBase) -> None:
        self.bus_id, self.address, self.oss, self.p0, self.variant = bus, address, oversampling, sea_level_pa, variant
        self.tb = tb
        self.driver: Any = None
        self._bus: Any = None

    def open(self) -> None:
        from sensors.bmp085 import Bmp085

        self._bus = _i2c_bus(self.bus_id)
        self.driver = Bmp085(self._bus, self.address, variant=self.variant, oversampling=self.oss,
                             reference_pa=self.p0, bus_name=f"I2C bus {self.bus_id}", sleep=self.tb.sleep)
        self.driver.configure()

    def read(self) -> list[Reading]:
        t0 = self.tb.monotonic_ns()
        s = self.driver.read()
        t1 = self.tb.monotonic_ns()
        return [Reading("/baro", {"pressure_pa": float(s.pressure_pa), "temp_degc": float(s.temp_degc),
                                  "altitude_m": round(float(s.altitude_m), 4), "sea_level_pa": self.p0,
                                  "oversampling": s.oss, "ut": s.ut, "up": s.up}, (t0 + t1) // 2)]

    def close(self) -> None:
        _close_quietly(self._bus)
        self._bus = None


class ObdSource:
    """Vehicle speed from an ELM327 adapter or straight from the CAN bus; the same record either way."""

    name = "obd"

    def __init__(self, make_driver: Callable[[], Any], interface: str, tb: TimeBase) -> None:
        self.make_driver, self.interface, self.tb = make_driver, interface, tb
        self.driver: Any = None

    def open(self) -> None:
        self.driver = self.make_driver()
        opener = getattr(self.driver, "open", None)
        if opener is not None:
            opener()

    def read(self) -> list[Reading]:
        t0 = self.tb.monotonic_ns()
        s = self.driver.read()
        t1 = self.tb.monotonic_ns()
        ecu = f"{s.ecu_id:X}" if s.ecu_id is not None else ""
        # The ECU sampled its speed somewhere between request and answer: the midpoint is the best guess.
        return [Reading("/obd/speed", {"speed_kmh": s.speed_kmh, "speed_mps": round(s.speed_mps, 4), "ecu": ecu,
                                       "interface": self.interface}, (t0 + t1) // 2)]

    def incidents(self) -> dict[str, int]:
        resets = getattr(self.driver, "resets_seen", None)
        return {} if resets is None else {"ELM327 reset itself and was set up again": resets}

    def close(self) -> None:
        _close_quietly(self.driver)
        self.driver = None


def location_fix(fix: Any, t_mono_ns: int) -> dict[str, Any]:
    """A GnssFix as a foxglove.LocationFix plus the receiver's own fields."""
    sec_ns = fix.time_utc_ns if fix.time_utc_ns is not None else 0
    lat = fix.lat_deg if fix.lat_deg is not None else 0.0
    lon = fix.lon_deg if fix.lon_deg is not None else 0.0
    alt = fix.height_hae_m if fix.height_hae_m is not None else 0.0
    cov_type = 0
    cov = [0.0] * 9
    if fix.h_acc_m is not None and fix.v_acc_m is not None:
        # u-blox hAcc is a horizontal 1-sigma over both axes: each axis gets hAcc^2 / 2.
        cov[0] = cov[4] = fix.h_acc_m**2 / 2.0
        cov[8] = fix.v_acc_m**2
        cov_type = 2
    vel = None
    if fix.vel_ned_mps is not None:
        vel = [None if (v is None or (isinstance(v, float) and math.isnan(v))) else float(v) for v in fix.vel_ned_mps]
    return {
        "timestamp": {"sec": sec_ns // 1_000_000_000, "nsec": sec_ns % 1_000_000_000},
        "frame_id": "gnss", "latitude": lat, "longitude": lon, "altitude": alt,
        "position_covariance": cov, "position_covariance_type": cov_type,
        "gnss_time_ns": fix.time_utc_ns if fix.time_valid else None, "itow_ms": fix.itow_ms,
        "fix_mode": fix.fix_mode, "fix_ok": bool(fix.fix_ok), "height_msl_m": fix.height_msl_m,
        "vel_ned_mps": vel, "h_acc_m": fix.h_acc_m, "v_acc_m": fix.v_acc_m, "s_acc_mps": fix.s_acc_mps,
        "num_sv": fix.num_sv, "pdop": fix.pdop, "source": fix.source,
    }


class GnssSource:
    """The u-blox receiver: every byte kept for post-processing, each decoded fix and time pulse recorded."""

    name = "gnss"
    sample_topic = "/gnss/fix"

    def __init__(self, path: str, baud: int, configure: bool, tb: TimeBase) -> None:
        self.path, self.baud, self.configure, self.tb = path, baud, configure, tb
        self.origin = f"serial {path}"
        self.receiver: Any = None
        self.setup: Any = None

    def open(self) -> None:
        from sensors.ublox import GnssReceiver

        self.receiver = GnssReceiver.open(self.path, self.baud)
        if self.configure:
            from sensors.ublox_config import configure_receiver

            try:
                self.setup = configure_receiver(self.receiver, sleep=self.tb.sleep)
            except SensorError:
                _close_quietly(self.receiver)
                raise

    def read(self) -> list[Reading]:
        from sensors.ublox import GnssFix, TimePulse

        got = self.receiver.read(EVENT_WAIT_S)
        t = self.tb.monotonic_ns()
        out: list[Reading] = []
        if got.raw:
            out.append(Reading("/gnss/raw", {"t_mono_ns": t, "data_b64": base64.b64encode(got.raw).decode(),
                                             "n_bytes": len(got.raw)}, t, stamped=False))
        for item in got.items:
            if isinstance(item, GnssFix):
                if item.source == "HNR-PVT":
                    continue  # already fused with the receiver's own sensors: not a GNSS measurement
                out.append(Reading("/gnss/fix", location_fix(item, t), t))
            elif isinstance(item, TimePulse):
                out.append(Reading("/gnss/timepulse", {"tow_ms": item.tow_ms, "tow_sub_ms": item.tow_sub_ms,
                                                       "week": item.week, "qerr_ps": item.qerr_ps,
                                                       "time_base": item.time_base}, t))
        return out

    def incidents(self) -> dict[str, int]:
        framer = getattr(self.receiver, "framer", None)
        if framer is None:
            return {}
        return {"bytes of garbage on the serial line": framer.garbage_bytes,
                "frames with a bad checksum": framer.bad_checksum}

    def close(self) -> None:
        _close_quietly(self.receiver)
        self.receiver = None


class PpsSource:
    name = "pps"

    def __init__(self, chip: str, line: int | str) -> None:
        self.chip, self.line = chip, line
        self.origin = f"gpio {chip} line {line}"
        self.driver: Any = None

    def open(self) -> None:
        from sensors.pps import PpsLine

        self.driver = PpsLine(self.chip, self.line)
        self.driver.open()

    def read(self) -> list[Reading]:
        return [Reading("/pps", {"seqno": e.line_seqno, "lost": e.lost}, e.timestamp_ns)
                for e in self.driver.wait(EVENT_WAIT_S)]

    def close(self) -> None:
        _close_quietly(self.driver)
        self.driver = None


@dataclass
class Plan:
    source: Any
    rate_hz: float | None
    expected_hz: float | None


def plans_from_config(cfg: Any, tb: TimeBase, devices: Any | None = None) -> list[Plan]:
    """One plan per configured sensor; ``devices`` (a simulated vehicle's) replaces paths of 'sim' sources."""
    plans: list[Plan] = []
    imu, baro, obd, gnss, pps = (cfg[s] for s in ("imu", "baro", "obd", "gnss", "pps"))

    def bus_of(section: dict[str, Any]) -> str | int:
        return devices.i2c_path if section["source"] == "sim" else section["bus"]

    imu_addr = devices.imu_address if imu["source"] == "sim" else imu["address"]
    src = ImuSource(bus_of(imu), imu_addr, imu["rate_hz"], imu["accel_range_g"], imu["gyro_range_dps"], tb)
    plans.append(Plan(src, src.poll_hz, imu["rate_hz"]))
    baro_addr = devices.baro_address if baro["source"] == "sim" else baro["address"]
    plans.append(Plan(BaroSource(bus_of(baro), baro_addr, baro["oversampling"], baro["sea_level_pa"],
                                 baro["variant"], tb), baro["rate_hz"], baro["rate_hz"]))
    if obd["source"] == "can":
        def make_can() -> Any:
            import can

            from sensors.obd_can import ObdCan

            try:
                bus = can.Bus(interface="socketcan", channel=obd["channel"])
            except (OSError, can.CanError) as exc:
                raise DeviceNotFound(f"CAN interface {obd['channel']}: {exc}") from None
            return ObdCan(bus, extended_id=obd["extended_id"])

        plans.append(Plan(ObdSource(make_can, "can", tb), obd["rate_hz"], obd["rate_hz"]))
    else:
        from sensors.elm327 import Elm327

        port = devices.elm327_path if obd["source"] == "sim" else obd["port"]
        plans.append(Plan(ObdSource(lambda: Elm327(port, baudrate=obd["baud"], protocol=obd["protocol"],
                                                   headers=obd["headers"]), "elm327", tb),
                          obd["rate_hz"], obd["rate_hz"]))
    # gpsd: the one at gnss.gpsd_host, or the simulated vehicle's when sim.gpsd asks for it.
    sim_gpsd = bool(cfg["sim"]["gpsd"]) and getattr(devices, "gpsd_port", None) is not None
    gpsd_at = (devices.gpsd_host, devices.gpsd_port) if sim_gpsd else (gnss["gpsd_host"], gnss["gpsd_port"])
    if gnss["source"] == "gpsd":
        from logger.gpsd_sources import GpsdSource

        plans.append(Plan(GpsdSource(*gpsd_at, gnss["gpsd_device"], tb), None, 1.0))
    else:
        g_path = devices.gnss_path if gnss["source"] == "sim" else gnss["port"]
        g_baud = devices.gnss_baud if gnss["source"] == "sim" else gnss["baud"]
        plans.append(Plan(GnssSource(g_path, g_baud, gnss["configure"], tb), None, 1.0))
    if pps["source"] == "gpsd":
        from logger.gpsd_sources import GpsdPpsSource

        realtime = devices.realtime_ns if sim_gpsd else time.time_ns  # the clock gpsd stamps edges with
        # Any device's PPS: a /dev/ppsN given to gpsd beside the receiver reports as a device of its own.
        plans.append(Plan(GpsdPpsSource(*gpsd_at, None, tb, realtime), None, 1.0))
    elif pps["source"] != "none":
        chip = devices.gpio_chip if pps["source"] == "sim" else pps["chip"]
        line = devices.pps_line if pps["source"] == "sim" else pps["line"]
        plans.append(Plan(PpsSource(chip, line), None, 1.0))
    return plans
