"""The composition root: a configuration in, a daemon with its sensors, clock, navigator and simulation out.

Everything that turns the sensor sections (``[imu]``, ``[baro]``, ``[obd]``, ``[gnss]``, ``[pps]``), ``[sync]``,
``[nav]`` and ``[sim]`` into objects lives here: the sensor adapters, the clock, the navigator and the simulated
vehicle reach the daemon ready-made, and ``logger run``, the evaluation tools and the tests build a daemon in
exactly one way.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from logger.config import Config, ConfigError, simulated_sections
from logger.recording.records import truth_clock_record
from logger.recording.topics import TRUTH_CLOCK, TRUTH_NAV
from logger.runtime import mount_state, tempco_state
from logger.runtime.daemon import Attachments, Daemon
from logger.runtime.gpsd_sources import GpsdPpsSource, GpsdSource
from logger.runtime.navigator import attach_navigator
from logger.runtime.sampler import Reading
from logger.runtime.sources import BaroSource, GnssSource, ImuSource, ObdSource, Plan, PpsSource
from logger.runtime.timebase import TimeBase, host_timebase
from sensors.errors import DeviceNotFound
from sensors.mpu6050_identity import WHO_AM_I_VALUE
from sensors.sim.profile import SimProfile
from sync.chrony_sock import ChronySock
from sync.clock import PpsClock
from sync.kernel_slew import raw_clock_ns
from sync.settings import SyncSettings
from sync.wallclock import boot_id, system_clock_synchronized

if TYPE_CHECKING:  # the simulated vehicle is imported only when a sensor is simulated
    from sensors.sim.vehicle import VehicleDevices


def build(cfg: Config, duration_s: float | None,
          scenario_options: dict[str, Any] | None = None) -> tuple[Daemon, Any]:
    """The daemon and, when any sensor is simulated, the vehicle behind it (already started).

    ``scenario_options`` reach the simulated drive (e.g. ``tunnel_s`` of tunnel-130s): for evaluation tools."""
    simulated = simulated_sections(cfg)
    sim_gpsd = bool(cfg["sim"]["gpsd"]) and "gpsd" in (cfg["gnss"]["source"], cfg["pps"]["source"])
    vehicle = None
    tb: TimeBase = host_timebase()
    attachments = Attachments()
    if any(simulated.values()):
        from sensors.sim.scenarios import SCENARIOS
        from sensors.sim.vehicle import build_vehicle

        sim = cfg["sim"]
        if sim["scenario"] not in SCENARIOS:
            raise ConfigError([f"unknown scenario {sim['scenario']!r}: choose one of {', '.join(SCENARIOS)}"])
        try:
            profile = SimProfile.from_config(sim)
        except ValueError as exc:  # the schema checks a file; this catches a configuration built in code
            raise ConfigError([f"sim.{exc}"]) from None
        if simulated["imu"] and profile.imu_rate_hz is not None and "imu.rate_hz" not in cfg.explicit:
            # A phone's IMU comes at its own rate (100 Hz, through the FIFO): the board reads it at that rate
            # unless the file says otherwise. Set before anything reads the rate (clock, truth, sampler).
            cfg.values["imu"]["rate_hz"] = profile.imu_rate_hz
        vehicle = build_vehicle(sim["scenario"], sim["seed"], time_scale=sim["time_scale"], duration_s=duration_s,
                                scenario_options=scenario_options,
                                imu=simulated["imu"], baro=simulated["baro"], obd=simulated["obd"],
                                gnss=cfg["gnss"]["source"] == "sim", pps=cfg["pps"]["source"] == "sim",
                                gpsd=sim_gpsd, paced=all(simulated.values()), profile=profile)
        vehicle.start()
        drive_clock, governor = vehicle.clock, vehicle.governor
        if governor is not None:  # the daemon's threads report how late they run; the drive slows to suit them
            tb = TimeBase(drive_clock.monotonic_ns, lambda: drive_clock.time_scale, late=governor.late,
                          pace=lambda: governor.report().as_dict())
        else:
            tb = TimeBase(drive_clock.monotonic_ns, drive_clock.time_scale)
        attachments.close.append(vehicle.stop)
        # What was driven, with which hardware: replay, nav_eval and nav-score read it back (SimProfile).
        attachments.metadata["simulation"] = {"scenario": vehicle.scenario, "seed": str(vehicle.seed),
                                         "time_scale": f"{vehicle.time_scale:g}",
                                         "start_utc": vehicle.timeline.start_utc.isoformat(),
                                         **vehicle.profile.metadata()}
        drive_options = {k: v for k, v in (scenario_options or {}).items() if k != "imu_error_scale"}
        if drive_options:  # a drive made with options says so: its plan cannot be made again without them
            attachments.metadata["simulation"]["drive_options"] = json.dumps(drive_options)
        if vehicle.imu is not None and ("imu_error_scale" in (scenario_options or {}) or profile.imu != "mpu6050"):
            # A drive made with a chip other than the default says so: its IMU errors are part of what it tests.
            attachments.metadata["simulation"]["imu_errors"] = json.dumps(dataclasses.asdict(vehicle.imu.errors))

        def truth_clock() -> list[Reading]:
            now = tb.monotonic_ns()
            return [Reading(TRUTH_CLOCK, truth_clock_record(now, vehicle.true_unix_ns(now)), now, stamped=False)]

        def truth_nav() -> list[Reading]:
            now = tb.monotonic_ns()
            return [Reading(TRUTH_NAV, vehicle.truth_nav(now), now, stamped=False)]

        attachments.periodic.append((0.1, truth_clock))
        attachments.periodic.append((1.0 / cfg["imu"]["rate_hz"], truth_nav))
    attachments.metadata["config"] = {f"{s}.{k}": str(v) for s, keys in cfg.values.items() for k, v in keys.items()}
    if vehicle is not None and simulated["gnss"]:
        # The simulated board's system clock is NTP-synchronised (to 20 ms): a check of the clock's first lock.
        clock = make_clock(cfg, tb, f"sim-{vehicle.oscillator.board_start_ns}-{vehicle.time_scale:g}",
                           wall_ns=vehicle.wall_clock_ns, wall_trusted=True)
    else:
        clock = make_clock(cfg, tb, clock_id(), wall_trusted=system_clock_synchronized(),
                           wall_synchronized=system_clock_synchronized)
    attachments.close.append(clock.save)
    plans = plans_from_config(cfg, tb, vehicle.devices if vehicle else None)
    mode = f"simulated drive '{cfg['sim']['scenario']}'" if vehicle and all(simulated.values()) else (
        "partly simulated" if vehicle else "")
    installation = (mount_state.simulated(vehicle.profile.mounting_rpy_deg) if vehicle is not None and simulated["imu"]
                    else mount_state.BOARD)
    imu_installation = (tempco_state.simulated(vehicle.profile.imu, cfg["sim"]["seed"])
                        if vehicle is not None and simulated["imu"]
                        else tempco_state.board(cfg["imu"]["bus"], cfg["imu"]["address"]))
    navigator = attach_navigator(cfg["nav"], attachments, Path(cfg["logger"]["state_dir"]), installation,
                                 imu_installation)
    daemon = Daemon(cfg, plans, timebase=tb, clock=clock, attachments=attachments, mode=mode)
    if navigator is not None:
        navigator.bind(daemon)
    return daemon, vehicle


def clock_id() -> str:
    """Identifies this boot for the clock's saved state: a mapping saved under the same id is still valid."""
    boot = boot_id()
    return f"boot-{boot}" if boot else ""


def make_clock(cfg: Config, tb: TimeBase, clock_id: str, wall_ns: Callable[[], int] = time.time_ns,
               wall_trusted: bool = False, wall_synchronized: Callable[[], bool] | None = None) -> PpsClock:
    """The PPS clock of ``[sync]``: its settings come from :meth:`SyncSettings.from_config`, which alone maps the
    keys to fields; what the settings do not hold (state file, chrony socket) is wired here."""
    sc = cfg["sync"]
    settings = SyncSettings.from_config(sc, imu_rate_hz=cfg["imu"]["rate_hz"])
    # On the host's own clock its raw twin tells what NTP does to it (sync.kernel_slew); a simulated drive's clock
    # has no NTP, and the host's raw clock has nothing to do with it.
    host = tb.monotonic_ns is time.monotonic_ns
    clock = PpsClock(settings, monotonic_ns=tb.monotonic_ns, wall_ns=wall_ns,
                     state_path=Path(cfg["logger"]["state_dir"]) / "clock.json", clock_id=clock_id,
                     wall_trusted=wall_trusted, raw_ns=raw_clock_ns if host else None,
                     wall_synchronized=wall_synchronized)
    if sc["chrony_sock"]:
        clock.chrony = ChronySock(sc["chrony_sock"])
        clock.on_sample = clock.chrony.send_edge
    return clock


def plans_from_config(cfg: Config, tb: TimeBase, devices: VehicleDevices | None = None) -> list[Plan]:
    """One plan per configured sensor; ``devices`` (a simulated vehicle's) replaces paths of 'sim' sources."""
    plans: list[Plan] = []
    imu, baro, obd, gnss, pps = (cfg[s] for s in ("imu", "baro", "obd", "gnss", "pps"))

    def bus_of(section: dict[str, Any]) -> str | int:
        return devices.i2c_path if section["source"] == "sim" else section["bus"]

    imu_addr = devices.imu_address if imu["source"] == "sim" else imu["address"]
    src = ImuSource(bus_of(imu), imu_addr, imu["rate_hz"], imu["accel_range_g"], imu["gyro_range_dps"], tb,
                    imu["read"], imu["who_am_i"] if imu["source"] != "sim" else WHO_AM_I_VALUE)
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
        from sensors.elm327 import Elm327  # pyserial's driver, only for a configured adapter

        port = devices.elm327_path if obd["source"] == "sim" else obd["port"]
        plans.append(Plan(ObdSource(lambda: Elm327(port, baudrate=obd["baud"], protocol=obd["protocol"],
                                                   headers=obd["headers"], timeout_s=obd["answer_timeout_s"]),
                                    "elm327", tb),
                          obd["rate_hz"], obd["rate_hz"]))
    # gpsd: the one at gnss.gpsd_host, or the simulated vehicle's when sim.gpsd asks for it.
    sim_gpsd = bool(cfg["sim"]["gpsd"]) and devices is not None and devices.gpsd_port is not None
    gpsd_at = (devices.gpsd_host, devices.gpsd_port) if sim_gpsd else (gnss["gpsd_host"], gnss["gpsd_port"])
    if gnss["source"] == "gpsd":
        # The rate the receiver behind gpsd runs at, as it is set (gpsd does not set it): the status's expected rate
        # and silence limit (a 5 Hz receiver silent for 3.4 s was "ok 5.0/1"); a simulated one's, its profile's.
        g_rate = 1000.0 / devices.gnss_meas_period_ms if sim_gpsd and devices.gnss_meas_period_ms else gnss["rate_hz"]
        plans.append(Plan(GpsdSource(*gpsd_at, gnss["gpsd_device"], tb), None, g_rate))
    else:
        g_path = devices.gnss_path if gnss["source"] == "sim" else gnss["port"]
        g_baud = devices.gnss_baud if gnss["source"] == "sim" else gnss["baud"]
        # A simulated receiver keeps the navigation rate it runs at (its profile's), as its baud rate; hardware is
        # set to [gnss] rate_hz.
        meas_ms = devices.gnss_meas_period_ms if gnss["source"] == "sim" else round(1000 / gnss["rate_hz"])
        plans.append(Plan(GnssSource(g_path, g_baud, gnss["configure"], tb, meas_ms, gnss["raw_observations"]), None,
                          1000.0 / meas_ms if meas_ms else 1.0))
    if pps["source"] == "gpsd":
        realtime = devices.realtime_ns if sim_gpsd else time.time_ns  # the clock gpsd stamps edges with
        # Any device's PPS: a /dev/ppsN given to gpsd beside the receiver reports as a device of its own.
        plans.append(Plan(GpsdPpsSource(*gpsd_at, None, tb, realtime), None, 1.0))
    elif pps["source"] != "none":
        chip = devices.gpio_chip if pps["source"] == "sim" else pps["chip"]
        line = devices.pps_line if pps["source"] == "sim" else pps["line"]
        plans.append(Plan(PpsSource(chip, line), None, 1.0))
    return plans

