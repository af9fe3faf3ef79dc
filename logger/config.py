"""The daemon's configuration: one TOML file, every value checked before anything starts.

A field engineer edits this file on the board with nano; when it is wrong, each problem gets one line naming
the file, the line, the key and what is expected, and the daemon does not start. Python's ``tomllib`` gives no
line numbers for keys, so a small index of ``[table]`` headers and ``key =`` lines supplies them.
"""

from __future__ import annotations

import difflib
import os
import re
import stat
import tomllib
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from logger.nav.params import NavParams
from logger.recording.settings import MIB, RecorderSettings
from sensors.mpu6050_identity import OTHER_PARTS, WHO_AM_I_VALUE
from sensors.sim.profile import (
    GNSS_RATES_HZ,
    IMUS,
    MAX_GNSS_LATENCY_S,
    MAX_LEAP_UNCONFIRMED_S,
    RECEIVER_MODELS,
    RECEIVERS,
    SimProfile,
)
from sensors.sim.scenario_names import SCENARIOS
from sync.settings import NS_PER_US, SyncSettings

DEFAULT_PATH = Path("/etc/vehicle-logger/logger.toml")
# Navigation rates a receiver may be set to ([gnss] rate_hz): whole milliseconds apart, up to an M9's 25 Hz; the
# simulated receiver plays each of them ([sim] gnss_rate_hz).
RECEIVER_RATES_HZ = GNSS_RATES_HZ
SIM_SECTIONS = ("imu", "baro", "obd", "gnss", "pps")  # the sensors a simulated vehicle can play
DEFAULT_SIM_OUT = "drives"  # `logger run --sim` without a configuration: files under ./drives
DEFAULT_SIM_SOCKET = "/tmp/vehicle-logger-sim/status.sock"  # ... and its status socket, where `logger status` looks


class ConfigError(Exception):
    """One or more problems in a configuration; ``problems`` holds one readable line each."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


@dataclass(frozen=True)
class Key:
    """One allowed key: its type, default, and the rule its value must follow."""

    kind: type | tuple[type, ...]
    default: Any = None
    check: Callable[[Any], str | None] | None = None  # returns the complaint, or None when fine
    help: str = ""


# The MCAP writer keeps every chunk's index until the file is closed (about 0.2 kB with this logger's topics,
# recording/mcap_writer.py; mcap's own Writer kept 1.3-2 kB): 14400 chunks, 4 h at the default 1 s flush, hold
# about 3 MB.
MAX_CHUNKS_PER_FILE = 14400
IMU_READS = ("fifo", "register")  # [imu] read: the chip's FIFO in batches, or one register burst per sample
REGISTER_READ_MAX_HZ = 50.0  # a thread woken per sample costs most of the IMU's CPU; above this it is not offered


def _number(v: float) -> str:
    """A bound as a person reads it: whole numbers in full (4294967295, not 4.29497e+09), others as %g."""
    return str(int(v)) if float(v).is_integer() else f"{v:g}"


def _range(lo: float, hi: float) -> Callable[[Any], str | None]:
    return lambda v: None if lo <= v <= hi else f"must be between {_number(lo)} and {_number(hi)}"


def _one_of(*choices: Any) -> Callable[[Any], str | None]:
    return lambda v: None if v in choices else "must be one of " + ", ".join(repr(c) for c in choices)


def _gpio_line(v: int | str) -> str | None:
    if isinstance(v, str):
        return None if v.strip() else "must be a line offset (0 or more) or a line name, not empty"
    return None if v >= 0 else "must be a line offset of 0 or more (or a line name)"


def _home_of(key: str) -> str:
    """Where a key put in the wrong place belongs, for its message: " (it belongs under [baro])", or ""."""
    homes = [sec for sec, ks in SCHEMA.items() if key in ks]
    if len(homes) == 1:
        return f" (it belongs under [{homes[0]}])"
    return f" (a key of [{'], ['.join(homes)}])" if homes else ""


def _who_am_i(v: int) -> str | None:
    if not 0 <= v <= 0xFF:
        return "is not a register value (0x00..0xff)"
    if v in OTHER_PARTS:
        return f"is {OTHER_PARTS[v]}'s: another register map, FIFO and temperature scale, which the logger cannot read"
    return None


def _i2c_address(v: int) -> str | None:
    return None if 0x03 <= v <= 0x77 else "is not a 7-bit I2C device address (0x03..0x77)"


def _imu_rate(v: float) -> str | None:
    from sensors.mpu6050_timing import MAX_RATE_HZ, choose_sample_timing

    if not 1 <= v <= MAX_RATE_HZ:
        return f"must be between 1 and {_number(MAX_RATE_HZ)}"
    try:
        choose_sample_timing(v)
    except ValueError as exc:
        return str(exc).split(": ", 1)[-1].replace(", or set dlpf_cfg", "")
    return None


def _vector3(limit: float) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        if len(v) != 3 or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v):
            return "must be three numbers [x, y, z]"
        return None if all(abs(x) <= limit for x in v) else f"must stay within +-{limit:g}"
    return check


def _abs_path(v: str) -> str | None:
    if "\0" in v:  # TOML's "\u0000" gets one in; no file system takes it (open() raises ValueError)
        return "must not hold a NUL character"
    return None if v.startswith("/") else "must be an absolute path"


SOCKET_PATH_MAX = 107  # bytes of a Unix socket's path (sun_path is 108, its NUL included)
IFNAME_MAX = 15  # a network interface's name (IFNAMSIZ 16, its NUL included)


def _socket_path(v: str) -> str | None:
    """An absolute path a Unix socket can have: a longer one is refused by bind() ("AF_UNIX path too long"), which
    left the logger without its status socket, and without the one-logger check it makes."""
    problem = _abs_path(v)
    if problem is None and len(v.encode()) > SOCKET_PATH_MAX:
        return f"is {len(v.encode())} bytes long: a Unix socket's path holds {SOCKET_PATH_MAX} at most"
    return problem


def _ifname(v: str) -> str | None:
    if 0 < len(v) <= IFNAME_MAX and v.isprintable() and not any(c in v for c in "/ \t"):
        return None
    return f"must be a network interface's name (1 to {IFNAME_MAX} characters, no '/' or space), such as can0"


_HOST = re.compile(r"[A-Za-z0-9._:-]{1,253}")


def _host(v: str) -> str | None:
    return None if _HOST.fullmatch(v) else "is not a host name or IP address"


def _gpsd_device(v: str) -> str | None:
    """gpsd names a receiver by its path, or by a URL for a network source (tcp://, udp://, ...)."""
    if v == "" or (v.startswith("/") and v.isprintable()) or re.fullmatch(r"[a-z]+://\S+", v):
        return None
    return "must be empty (every receiver), a device path such as /dev/ttyACM0, or a gpsd source URL"


def _rinex_receiver(v: str) -> str | None:
    """RINEX gives the receiver's number, type and version 20 characters each, in an ASCII header (convbin cuts a
    field at 20 bytes: an 'Ä' is two, and half of one went into the file); convbin takes them split by '/'."""
    parts = v.split("/")
    if len(parts) > 3 or not (v.isascii() and v.isprintable()) or any(len(p) > 20 for p in parts):
        return ("must be up to three parts separated by '/' (number/type/version), each at most 20 characters, "
                "ASCII only (a RINEX header is ASCII)")
    return None


def _field_default(cls: type, name: str) -> Any:
    """The default that settings dataclass ``cls`` gives its field ``name``.

    The ``[nav]``, ``[sync]`` and ``[recorder]`` defaults are written once, in the dataclasses the code runs on
    (``NavParams``, ``SyncSettings``, ``RecorderSettings``), and the schema reads them from there, so a default
    changed in one place cannot leave a configuration that says otherwise. A name that is not a field with a
    default fails here, at import, rather than leave a key without one.
    """
    for f in fields(cls):
        if f.name == name and f.default is not MISSING:
            return f.default
        if f.name == name and f.default_factory is not MISSING:
            return f.default_factory()
    raise TypeError(f"{cls.__name__} has no field {name!r} with a default")


FIELD: Any = object()  # a key's default: the field of the same name of its section's settings (_defaults_from)


def _defaults_from(cls: type, keys: dict[str, Key]) -> dict[str, Key]:
    """``keys`` with every :data:`FIELD` default replaced by that of ``cls``' field of the same name.

    Tuples (NavParams' vectors) become lists, as TOML arrays are. Keys whose field has another name or unit
    state their default as the conversion of :func:`_field_default`, the inverse of the ``from_config`` beside
    the dataclass; keys without a field keep their own default.
    """
    def own(name: str) -> Any:
        value = _field_default(cls, name)
        return list(value) if isinstance(value, tuple) else value

    return {name: replace(key, default=own(name)) if key.default is FIELD else key for name, key in keys.items()}


NUM = (int, float)
SOURCES_I2C = ("i2c", "sim")

SCHEMA: dict[str, dict[str, Key]] = {
    "logger": {
        "out_dir": Key(str, "/var/lib/vehicle-logger/drives", _abs_path, "folder for the MCAP files"),
        "state_dir": Key(str, "/var/lib/vehicle-logger", _abs_path,
                         "kept between runs: the clock state, the mount alignment, the IMU temperature coefficients"),
        "status_socket": Key(str, "/run/vehicle-logger/status.sock", _socket_path, "Unix socket of `logger status`"),
    },
    "recorder": _defaults_from(RecorderSettings, {
        "flush_interval_s": Key(NUM, FIELD, _range(0.05, 60), "close the chunk and fsync this often"),
        "rotate_duration_s": Key(NUM, FIELD, _range(10, 86400), "start a new file after this much drive time"),
        "rotate_size_mb": Key(NUM, _field_default(RecorderSettings, "rotate_size_bytes") // MIB, _range(1, 65536),
                              "start a new file at this size"),
        "min_free_mb": Key(NUM, _field_default(RecorderSettings, "min_free_bytes") // MIB, _range(0, 1 << 20),
                           "stop recording below this much free disk"),
        "compression": Key(str, FIELD, _one_of("zstd", "lz4", "none"), "MCAP chunk compression"),
        "queue_size": Key(int, FIELD, _range(100, 1_000_000), "records waiting for the writer before drops"),
    }),
    "imu": {
        "source": Key(str, "i2c", _one_of(*SOURCES_I2C)),
        "bus": Key(int, 2, _range(0, 255), "I2C bus number: /dev/i2c-N"),
        "address": Key(int, 0x68, _i2c_address, "0x68, or 0x69 with AD0 high"),
        "who_am_i": Key(int, WHO_AM_I_VALUE, _who_am_i,
                        "the chip's WHO_AM_I: 0x68, or a GY-521 clone's (0x98, 0x72) that works as an MPU-6050"),
        "rate_hz": Key(NUM, 20, lambda v: _imu_rate(v), "sample rate"),
        "read": Key(str, IMU_READS[0], _one_of(*IMU_READS),
                    "'fifo' (batches, stamped by the chip's sample clock) or 'register' (a read per sample, to 50 Hz)"),
        "accel_range_g": Key(int, 4, _one_of(2, 4, 8, 16)),
        "gyro_range_dps": Key(int, 500, _one_of(250, 500, 1000, 2000)),
    },
    "baro": {
        "source": Key(str, "i2c", _one_of(*SOURCES_I2C)),
        "bus": Key(int, 2, _range(0, 255)),
        "address": Key(int, 0x77, _i2c_address),
        "rate_hz": Key(NUM, 1, _range(0.1, 10)),
        "variant": Key(str, "BMP180", _one_of("BMP085", "BMP180")),
        "oversampling": Key(int, 3, _one_of(0, 1, 2, 3), "0 ultra low power .. 3 ultra high resolution"),
        "sea_level_pa": Key(NUM, 101325.0, _range(85000, 110000), "P0 of the altitude formula (QNH)"),
    },
    "obd": {
        "source": Key(str, "elm327", _one_of("elm327", "can", "sim")),
        "port": Key(str, None, _abs_path, "ELM327 serial port, e.g. /dev/serial/by-id/..."),
        "baud": Key(int, 38400, _one_of(9600, 38400, 57600, 115200, 230400, 500000)),
        "protocol": Key(str, "0", _one_of(*"0123456789BC"), "ATSP protocol number, 0 = automatic"),
        "headers": Key(bool, True, None, "ask the adapter for headers: tells which ECU answered, prefers the engine"),
        "answer_timeout_s": Key(NUM, 1.0, _range(0.2, 10),
                                "silence after which an ELM327 command counts as unanswered (slow clones: 2-3)"),
        "channel": Key(str, "can0", _ifname, "SocketCAN interface for source = 'can'"),
        "extended_id": Key(bool, False, None, "29-bit OBD addressing"),
        "rate_hz": Key(NUM, 2, _range(0.1, 20)),
    },
    "gnss": {
        "source": Key(str, "serial", _one_of("serial", "gpsd", "sim")),
        "port": Key(str, None, _abs_path, "receiver serial/USB port"),
        "gpsd_host": Key(str, "127.0.0.1", _host, "gpsd to read for source = 'gpsd' (and pps.source = 'gpsd')"),
        "gpsd_port": Key(int, 2947, _range(1, 65535), "gpsd's TCP port"),
        "gpsd_device": Key(str, "", _gpsd_device, "the receiver gpsd reads, when it has several; empty: any"),
        "baud": Key(int, 9600, _one_of(4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600),
                    "the speed the receiver talks at when the port opens (a factory M8: 9600)"),
        "configure": Key(bool, True, None, "turn on NAV-PVT and TIM-TP at rate_hz at start, and raise a UART's "
                         "speed to one that carries them beside the NMEA (9600 -> 19200 at 1 Hz, in RAM only)"),
        "rate_hz": Key(NUM, 1, _one_of(*RECEIVER_RATES_HZ), "navigation solutions a second: what the set-up asks "
                       "for, or (configure = false) what the receiver is set to; an M8 does up to 10 with one "
                       "constellation, an F9P 25 (20 in RTK)"),
        "raw_observations": Key(bool, False, None, "also RXM-RAWX and RXM-SFRBX for RTKLIB (M8T, M8P, F9P, F9T); "
                                "the port speed goes up to carry them"),
        "antenna_height_m": Key(NUM, 0.0, _range(-100, 100), "antenna above the marker, m: RINEX ANTENNA: DELTA H"),
        "receiver_name": Key(str, "", _rinex_receiver, "RINEX REC # / TYPE / VERS, e.g. '1234/NEO-M8T/TIM 1.10'"),
    },
    "pps": {
        "source": Key(str, "gpio", _one_of("gpio", "gpsd", "sim", "none")),
        "chip": Key(str, "/dev/gpiochip0", _abs_path),
        "line": Key((int, str), 60, _gpio_line, "line offset or line name"),
    },
    "sync": _defaults_from(SyncSettings, {
        "pps_latency_us": Key(NUM, _field_default(SyncSettings, "pps_latency_ns") / NS_PER_US, _range(0, 1000),
                              "mean delay of the PPS interrupt's time stamp"),
        "stability_ppm": Key(NUM, FIELD, _range(0.01, 100), "how far the board clock may wander unseen (holdover)"),
        "max_slew_ppm": Key(NUM, FIELD, _range(1, 10000), "how fast a correction is slewed in after holdover"),
        "chrony_sock": Key(str, "", lambda v: None if v == "" else _socket_path(v),
                           "chronyd's SOCK refclock socket to hand PPS samples to; empty: off"),
    }),
    "nav": _defaults_from(NavParams, {  # every key is the NavParams field of the same name
        "enabled": Key(bool, FIELD, None, "run the navigation filter live and publish /nav/fix, /nav/state"),
        "mode": Key(str, FIELD, _one_of("17", "15", "gnss"), "17 (GNSS, IMU, OBD, baro), 15 (GNSS + IMU), gnss"),
        "lever_arm_m": Key(list, FIELD, _vector3(5.0), "GNSS antenna from the IMU, vehicle x y z (FRD), m"),
        "mounting_rpy_deg": Key(list, FIELD, _vector3(180.0), "IMU chip axes against the vehicle"),
        "mount_align": Key(bool, FIELD, None, "estimate the mounting from the drive, mounting_rpy_deg the first guess"),
        "accel_noise_ug_rthz": Key(NUM, FIELD, _range(1, 100000), "accelerometer noise density (datasheet)"),
        "imu_noise_from_drive": Key(bool, FIELD, None, "widen the noise densities to what the samples show"),
        "gyro_noise_dps_rthz": Key(NUM, FIELD, _range(1e-5, 10), "gyro noise density (datasheet)"),
        "accel_bias_mg": Key(NUM, FIELD, _range(0.01, 1000), "initial accelerometer offset uncertainty"),
        "gyro_bias_dps": Key(NUM, FIELD, _range(0.001, 200), "initial gyro offset uncertainty"),
        "accel_bias_walk_mg_rts": Key(NUM, FIELD, _range(0, 100), "accelerometer offset random walk"),
        # 5x the chip family's Allan-variance bias stability; the temperature drift is the tempcos' (datasheet)
        "gyro_bias_walk_dps_rts": Key(NUM, FIELD, _range(0, 10), "gyro offset random walk at a steady temperature"),
        "accel_bias_tempco_mg_degc": Key(NUM, FIELD, _range(0, 100), "accel offset change per degC of die (0: off)"),
        "gyro_bias_tempco_dps_degc": Key(NUM, FIELD, _range(0, 10), "gyro offset change per degC of die (0: off)"),
        "obd_speed_sigma_mps": Key(NUM, FIELD, _range(0.01, 10), "OBD speed noise (1 km/h steps, timing)"),
        "obd_scale_sigma": Key(NUM, FIELD, _range(1e-4, 0.5), "initial uncertainty of the OBD scale factor"),
        "obd_scale_walk_rts": Key(NUM, FIELD, _range(0, 0.01), "OBD scale factor random walk, 1/sqrt(s)"),
        "obd_rounding_state": Key(bool, FIELD, None, "OBD reading's rounding as a state (an 18th)"),
        "obd_rounding_walk_mps_rts": Key(NUM, FIELD, _range(0, 1), "true speed's drift inside one OBD step"),
        "nhc_sigma_mps": Key(NUM, FIELD, _range(0.001, 10), "lateral and vertical body velocity allowed"),
        "baro_sigma_m": Key(NUM, FIELD, _range(0.01, 100), "barometric altitude noise"),
        "baro_offset_walk_m_rts": Key(NUM, FIELD, _range(0, 10), "random walk of baro-GNSS height offset"),
        "gnss_uere_m": Key(NUM, FIELD, _range(0.01, 100), "range error for receivers giving DOPs, no accuracy"),
        "gnss_acc_scale": Key(NUM, FIELD, _range(0.1, 100), "multiply the receiver's own accuracies"),
        "gnss_nominal_h_acc_m": Key(NUM, FIELD, _range(0.01, 100),
                                    "horizontal accuracy (2D RMS) of fixes without accuracy or DOP, m"),
        "gnss_nominal_v_acc_m": Key(NUM, FIELD, _range(0.01, 200), "vertical accuracy of such fixes, m"),
        "gnss_nominal_s_acc_mps": Key(NUM, FIELD, _range(0.001, 10), "speed accuracy of fixes without one, m/s"),
        "gnss_learn_scatter": Key(bool, FIELD, None, "widen guessed accuracies by what the fixes' scatter shows"),
        "gnss_floor_corr_s": Key(NUM, FIELD, _range(0, 3600),
                                 "how long the error at the receiver's own accuracy floor lasts, s (0: white)"),
        "gnss_floor_corr_v_s": Key(NUM, FIELD, _range(0, 3600),
                                   "how long the error at the receiver's floor lasts in the vertical, s (0: white)"),
        "gnss_floor_corr_speed_s": Key(NUM, FIELD, _range(0, 3600),
                                       "how long the error at the receiver's speed floor lasts, s (0: white)"),
        "gnss_independent_hz": Key(NUM, FIELD, _range(0.01, 100),
                                   "faster fixes weigh together what fixes at this rate do (errors last)"),
        "gnss_max_hz": Key(NUM, FIELD, _range(0, 100),
                           "a faster receiver's fixes are thinned to this rate or under (0: all)"),
        "gnss_min_sv": Key(int, FIELD, _range(4, 40), "fixes on fewer satellites are not used"),
        "gnss_multipath_corr_s": Key(NUM, FIELD, _range(0, 600),
                                     "correlation time of GNSS errors above the receiver's floor, s"),
        "zupt_sigma_mps": Key(NUM, FIELD, _range(1e-4, 1), "velocity noise of a zero-velocity update"),
        "zaru_sigma_dps": Key(NUM, FIELD, _range(1e-5, 10), "angular rate noise of a zero-rate update"),
        "gate_probability": Key(NUM, FIELD, _range(0.5, 0.999999), "chi-square gate of every update"),
        "heading_source": Key(str, FIELD, _one_of("gnss", "config"), "initial heading from GNSS course or config"),
        "initial_heading_deg": Key(NUM, FIELD, _range(-360, 360), "used when heading_source = 'config'"),
        "heading_min_speed_mps": Key(NUM, FIELD, _range(0.5, 50), "GNSS course trusted for heading above this"),
        "align_min_s": Key(NUM, FIELD, _range(0.1, 600), "standstill needed to level the IMU"),
        "still_accel_mps2": Key(NUM, FIELD, _range(1e-4, 5), "stop detector's first threshold (then adapted)"),
        "cov_interval_s": Key(NUM, FIELD, _range(0.01, 2), "covariance propagation interval"),
        "integration_hz": Key(NUM, FIELD, _range(0, 1000),
                              "strapdown steps per second for a faster IMU's FIFO blocks (0: one per sample)"),
        "publish_hz": Key(NUM, FIELD, _range(0.1, 1000), "rate of /nav/fix while running live"),
        "queue_size": Key(int, FIELD, _range(10, 1_000_000), "records waiting for the filter before drops"),
    }),
    "sim": _defaults_from(SimProfile, {  # the drive's keys have their own defaults; the hardware's are SimProfile's
        "scenario": Key(str, "urban", _one_of(*SCENARIOS), "drive to simulate"),
        "seed": Key(int, 1, _range(0, 2**32 - 1)),
        "time_scale": Key(NUM, 1.0, _range(0.01, 1000)),
        "gpsd": Key(bool, False, None, "gnss/pps sources 'gpsd' read a simulated gpsd (logger run --sim sets it)"),
        "receiver": Key(str, FIELD, _one_of(*RECEIVERS),
                        "'ubx' (u-blox: UBX and NMEA) or 'nmea' (GGA, RMC, GSA only; answers no UBX)"),
        "receiver_model": Key(str, FIELD, _one_of(*RECEIVER_MODELS),
                              "which u-blox: 'NEO-M8N' (no raw observations), 'NEO-M8T' or 'ZED-F9P' (raw)"),
        "gnss_rate_hz": Key(NUM, FIELD, _one_of(*GNSS_RATES_HZ), "the simulated receiver's fixes per second"),
        "gnss_latency_s": Key(NUM, FIELD, _range(0, MAX_GNSS_LATENCY_S), "least delay of a fix after its epoch"),
        "leap_unconfirmed_s": Key(NUM, FIELD, _range(0, MAX_LEAP_UNCONFIRMED_S),
                                  "a cold start: seconds after the first fix with the leap count not yet broadcast"),
        "imu": Key(str, FIELD, _one_of(*IMUS), "'mpu6050' (datasheet errors) or 'phone' (phone-grade, 100 Hz)"),
        "mounting_rpy_deg": Key(list, FIELD, _vector3(180.0),
                                "simulated IMU board against the vehicle; the filter is not told"),
    }),
}

# Keys that a source makes necessary: (section, source value) -> keys that must be set.
REQUIRED_FOR_SOURCE = {("obd", "elm327"): ["port"], ("gnss", "serial"): ["port"]}


@dataclass
class Config:
    """Validated settings: ``section -> key -> value`` with defaults filled in."""

    values: dict[str, dict[str, Any]]
    path: Path | None = None
    explicit: set[str] = field(default_factory=set)  # "section.key" set in the file

    def __getitem__(self, section: str) -> dict[str, Any]:
        return self.values[section]


def defaults(sim: bool = False) -> Config:
    """The configuration with nothing set; with ``sim``, every sensor is simulated (``logger run --sim``)."""
    values = {sec: {k: list(key.default) if isinstance(key.default, list) else key.default for k, key in keys.items()}
              for sec, keys in SCHEMA.items()}
    if sim:
        for sec in ("imu", "baro", "obd", "gnss", "pps"):
            values[sec]["source"] = "sim"
    return Config(values)


MAX_FILE_BYTES = 1 << 20  # a configuration is a few kB; anything this large is the wrong file

_TABLE_NAME = re.compile(r"[A-Za-z0-9_.\-\" ]+")
_KEY = re.compile(r"^\s*([A-Za-z0-9_\-\"]+(?:\s*\.\s*[A-Za-z0-9_\-\"]+)*)\s*=")


def _line_index(text: str) -> dict[str, int]:
    """Map ``section.key`` (and ``section``) to the 1-based line where the file sets it."""
    index: dict[str, int] = {}
    table = ""
    for no, line in enumerate(text.splitlines(), 1):
        header = _table_header(line)
        if header is not None:
            table = header.replace('"', "").replace(" ", "")
            index.setdefault(table, no)
            continue
        m = _KEY.match(line)
        if m:
            key = m.group(1).replace('"', "").replace(" ", "")
            index.setdefault(f"{table}.{key}" if table else key, no)
    return index


def _table_header(line: str) -> str | None:
    """The name in a ``[table]`` header line, else None.

    String operations, not one regular expression: a lazy pattern around blanks backtracks in cubic time, and
    a line of a few thousand blanks (valid TOML inside a multi-line string) took minutes.
    """
    text = line.strip()
    if not text.startswith("[") or text.startswith("[["):
        return None
    end = text.find("]")
    if end < 0:
        return None
    rest = text[end + 1 :].lstrip()
    if rest and not rest.startswith("#"):
        return None
    name = text[1:end].strip()
    return name if name and _TABLE_NAME.fullmatch(name) else None


def _shown(name: str) -> str:
    """A name from the file as it may be printed: control characters (a newline, a terminal escape) escaped."""
    return name if name.isprintable() else repr(name)


def _type_name(kind: type | tuple[type, ...]) -> str:
    names = {int: "an integer", float: "a number", str: "a string", bool: "true or false", list: "a list"}
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if set(kinds) == {int, float}:
        return "a number"
    return " or ".join(names.get(k, k.__name__) for k in kinds)


def _check_type(value: Any, kind: type | tuple[type, ...]) -> bool:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if isinstance(value, bool):
        return bool in kinds
    return isinstance(value, kinds)


def _toml_problem(msg: str, text: str, line_no: int) -> str:
    """tomllib's complaint in the configuration's terms: a key or a table given twice is named."""
    lines = text.splitlines()
    if msg == "Cannot overwrite a value" and 0 < line_no <= len(lines):
        key = lines[line_no - 1].split("=", 1)[0].strip()
        table = next((t for t in map(_table_header, reversed(lines[:line_no - 1])) if t), None)
        path = f"{table}.{key}" if table else key
        return f"{_shown(path)} is set twice (a key may be given once)"
    twice = re.fullmatch(r"Cannot declare \((.*)\) twice", msg)
    if twice:
        table = ".".join(part.strip().strip("'\"") for part in twice.group(1).split(",") if part.strip())
        return f"[{_shown(table)}] appears twice (give each section once, with all its keys)"
    return f"not valid TOML: {msg}"


def parse(text: str, name: str = "config", sim: bool = False, devices: bool = True) -> Config:
    """Validate TOML text; raise :class:`ConfigError` listing every problem, one line each.

    With ``sim`` the sensors the file leaves unsaid are simulated. ``devices`` False is for a caller that opens
    no device the file names (``logger replay`` takes only ``[nav]``; ``logger run --sim`` simulates every
    sensor): every key is still checked, but the keys a source makes necessary (its serial port) are not
    demanded, so a file with only the sections the command uses is a whole configuration for it."""
    text = text.removeprefix("\ufeff")  # a byte-order mark some Windows editors write: not part of the TOML
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"\(at line (\d+), column (\d+)\)", str(exc))
        where = f"{name}:{m.group(1)}" if m else name
        msg = re.sub(r"\s*\(at line \d+, column \d+\)", "", str(exc))
        raise ConfigError([f"{where}: {_toml_problem(msg, text, int(m.group(1)) if m else 0)}"]) from None
    except RecursionError:
        raise ConfigError([f"{name}: not a configuration: arrays or tables nested hundreds deep"]) from None
    lines = _line_index(text)
    problems: list[str] = []
    cfg = defaults(sim=sim)

    def at(path: str) -> str:
        no = lines.get(path) or lines.get(path.split(".")[0])
        return f"{name}:{no}" if no else name

    for section, body in raw.items():
        keys = SCHEMA.get(section)
        if keys is None and not isinstance(body, dict):
            # A key written before any [section] header: not a section of its own. Which section holds that key?
            problems.append(f"{at(section)}: {_shown(section)} is outside any section{_home_of(section)}")
            continue
        if keys is None:
            hint = difflib.get_close_matches(section, SCHEMA, n=1)
            problems.append(f"{at(section)}: unknown section [{_shown(section)}]"
                            + (f" (did you mean [{hint[0]}]?)" if hint else ""))
            continue
        if not isinstance(body, dict):
            problems.append(f"{at(section)}: {section} must be a table [{section}]")
            continue
        for key, value in body.items():
            path = f"{section}.{key}"
            spec = keys.get(key)
            if spec is None:
                hint = difflib.get_close_matches(key, keys, n=1)
                where = _home_of(key) or (f" (did you mean {section}.{hint[0]}?)" if hint else "")  # another's key?
                problems.append(f"{at(path)}: unknown key {_shown(path)}{where}")
                continue
            if not _check_type(value, spec.kind):
                problems.append(f"{at(path)}: {path} must be {_type_name(spec.kind)}, not {value!r}")
                continue
            complaint = spec.check(value) if spec.check else None
            if complaint:
                shown = f"{value:#04x}" if key in ("address", "who_am_i") and isinstance(value, int) else repr(value)
                problems.append(f"{at(path)}: {path} = {shown} {complaint}")
                continue
            cfg.values[section][key] = float(value) if spec.kind == NUM else value
            cfg.explicit.add(path)
    for (section, source), needed in REQUIRED_FOR_SOURCE.items():
        if devices and cfg.values[section]["source"] == source:
            for key in needed:
                if cfg.values[section][key] is None:
                    problems.append(f"{at(section + '.source')}: {section}.{key} is required when "
                                    f"{section}.source = {source!r}")
    chrony = chrony_problem(cfg)
    if chrony:
        problems.append(f"{at('sync.chrony_sock')}: {chrony}")
    scale = time_scale_problem(cfg)
    if scale:
        problems.append(f"{at('sim.time_scale')}: {scale}")
    imu = cfg.values["imu"]
    if imu["read"] == "register" and imu["rate_hz"] > REGISTER_READ_MAX_HZ:
        problems.append(f"{at('imu.read')}: imu.read = 'register' reads a sample at a time, at most "
                        f"{REGISTER_READ_MAX_HZ:g} Hz, and imu.rate_hz is {imu['rate_hz']:g}: use read = 'fifo' "
                        "or a lower rate")
    rec = cfg.values["recorder"]
    chunks = rec["rotate_duration_s"] / rec["flush_interval_s"]
    if chunks > MAX_CHUNKS_PER_FILE:
        problems.append(f"{at('recorder.rotate_duration_s')}: recorder.rotate_duration_s / flush_interval_s makes "
                        f"{chunks:.0f} chunks per file, more than {MAX_CHUNKS_PER_FILE} (each chunk's index stays in "
                        f"memory until the file is closed): rotate sooner or flush less often")
    if problems:
        raise ConfigError(problems)
    return cfg


def simulated_sections(cfg: Config) -> dict[str, bool]:
    """Which sensors the simulated vehicle plays: those with source 'sim', and 'gpsd' ones when sim.gpsd says
    that gpsd is simulated too."""
    gpsd_simulated = bool(cfg.values["sim"]["gpsd"])
    return {s: cfg.values[s]["source"] == "sim" or (cfg.values[s]["source"] == "gpsd" and gpsd_simulated)
            for s in SIM_SECTIONS}


def time_scale_problem(cfg: Config) -> str:
    """Why the drive's time scale cannot be had ("" when it can): a real sensor runs at real time. Checked by
    ``config check`` and again by ``logger run`` once its command line has had its say."""
    scale = cfg.values["sim"]["time_scale"]
    simulated = simulated_sections(cfg)
    real = [s for s in SIM_SECTIONS if not simulated[s] and cfg.values[s]["source"] != "none"]
    if real and scale != 1.0:
        return f"sim.time_scale = {scale:g} needs every sensor simulated; real: {', '.join(real)}"
    return ""


def chrony_problem(cfg: Config) -> str:
    """Why the PPS edges must not go to chrony ("" when they may): only real time may steer a system clock.

    A simulated receiver or PPS line, or a drive faster than real time, would hand chrony the simulation's time,
    and a chronyd started without ``-x`` would set the board's clock to it. Checked by ``config check`` and again
    by ``logger run`` once its command line has had its say (``--sim``, ``--time-scale``)."""
    if not cfg.values["sync"]["chrony_sock"]:
        return ""
    sim = cfg.values["sim"]
    played = simulated_sections(cfg)
    timing = [s for s in ("gnss", "pps") if played[s]]
    # Any other simulated sensor makes the simulated vehicle's board clock the run's, a few milliseconds from the
    # host's: real gpsd edges mapped through it reached chrony off by that (2.7 ms, with 11 us claimed).
    simulated = timing or [s for s in SIM_SECTIONS if played[s]]
    if simulated:
        named = simulated[0] if len(simulated) == 1 else f"{', '.join(simulated[:-1])} and {simulated[-1]}"
        why = ("chrony would be given the simulation's time" if timing else "the run's clock is then the simulated "
               "board's, not the host's, and chrony would be given its offset as the clock's error")
        return (f"sync.chrony_sock is set while {named} {'is' if len(simulated) == 1 else 'are'} simulated: {why} "
                "(leave chrony_sock empty for simulated runs)")
    if sim["time_scale"] != 1.0:
        return (f"sync.chrony_sock is set with sim.time_scale = {sim['time_scale']:g}: chrony would be given time "
                "running faster than real time")
    return ""


def load(path: str | os.PathLike[str], sim: bool = False, devices: bool = True) -> Config:
    """Read and validate a file (``sim``, ``devices``: as :func:`parse`); refuse one that anybody may write, as
    it steers a root-started service."""
    p = Path(path)
    try:
        # O_NONBLOCK: a FIFO given by mistake must not block the start; its type is refused right after.
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
        with os.fdopen(fd, "rb") as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise ConfigError([f"{p}: not a regular file"])
            if st.st_size > MAX_FILE_BYTES:
                raise ConfigError([f"{p}: too large for a configuration file ({st.st_size} bytes)"])
            text = f.read(MAX_FILE_BYTES + 1).decode("utf-8")
    except FileNotFoundError:
        raise ConfigError([f"{p}: no such configuration file"]) from None
    except PermissionError:
        raise ConfigError([f"{p}: not allowed to read the configuration file"]) from None
    except UnicodeDecodeError:
        raise ConfigError([f"{p}: not a text file (TOML must be UTF-8)"]) from None
    except IsADirectoryError:
        raise ConfigError([f"{p}: not a regular file"]) from None
    except OSError as exc:
        raise ConfigError([f"{p}: cannot read ({exc.strerror})"]) from None
    if len(text) > MAX_FILE_BYTES:  # grew while being read
        raise ConfigError([f"{p}: too large for a configuration file"])
    if st.st_mode & stat.S_IWOTH:
        raise ConfigError([f"{p}: refusing a world-writable configuration file (chmod o-w {p})"])
    cfg = parse(text, str(p), sim=sim, devices=devices)
    cfg.path = p
    return cfg
