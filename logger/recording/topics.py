"""Every recorded topic and the JSON schema of its messages: the one place the file format is defined.

Field names carry their units (``_mps``, ``_ns``, ``_deg``...) so a reader needs no other document;
``docs/topics.md`` is generated from this module by ``tools/topics_doc.py`` (a test keeps it current).
``/gnss/fix`` and ``/nav/fix`` use the well-known schema name ``foxglove.LocationFix`` with its fields, so
Foxglove's map panel draws the drive; the extra fields ride along in the same JSON object. Each of the two has a
schema record of its own under that name (MCAP allows several schemas of one name), since their extra fields
differ: a channel's schema is always its own topic's, which the messages validate against.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

# A silence longer than this many sample periods is a gap: one lost sample is jitter, two and a half are not (the
# samplers count gaps by it, and a FIFO read goes on from the last only within it).
GAP_PERIODS = 2.5

@dataclass(frozen=True)
class TopicSpec:
    topic: str
    schema_name: str
    schema: dict[str, Any]
    description: str

    @property
    def schema_data(self) -> bytes:
        """The schema as a file embeds it (MCAP schema encoding ``jsonschema``): every writer puts the same bytes
        under a topic, so a reader (recovery among them) can tell two topics' schemas apart by content even where
        they share a name."""
        return json.dumps(self.schema).encode()


# The topic names, for code that writes or picks records by topic (the record layer, the recorder's readers).
IMU = "/imu"
IMU_BATCH = "/imu/batch"
BARO = "/baro"
OBD_SPEED = "/obd/speed"
GNSS_FIX = "/gnss/fix"
TIMEPULSE = "/gnss/timepulse"
GNSS_RAW = "/gnss/raw"
PPS = "/pps"
SYNC = "/sync"
HEALTH = "/health"
TRUTH_CLOCK = "/truth/clock"
TRUTH_NAV = "/truth/nav"
NAV_FIX = "/nav/fix"
NAV_STATE = "/nav/state"

# A field: (kind, description with its unit). The kind is a JSON type ("integer", "number", "string",
# "boolean", "object"), "time" (Foxglove's {sec, nsec}), or an array of one such type ("number[3]": exactly three,
# "string[]": any number). A "?" after the whole kind makes the field optional: null, or left out, where a record
# may have no value ("integer?", "number[3]?"); a "?" after an array's item type lets items be null
# ("number?[3]?": three numbers, any of which may be null, or null as a whole). Optional means null in practice,
# not just in theory: a value every record carries is required, so a reader can count on it.
Field = tuple[str, str]

STAMP: dict[str, Field] = {
    "t_mono_ns": ("integer", "acquisition time on the board's monotonic clock, ns, taken next to the bus transfer"),
    "t_sync_ns": ("integer", "synchronised time of the sample, Unix ns UTC (also the MCAP log_time)"),
    "sync_state": ("string", "state of the clock at this stamp: freerun, locked or holdover"),
    "sync_err_ns": ("integer", "bound on the error of t_sync_ns, ns"),
    "imu_cnt": ("integer", "the paper's IMU counter: IMU periods since the last PPS edge"),
    "timer_cnt": ("integer", "the paper's timer counter: IMU periods carried while PPS is missing"),
    "seq": ("integer", "per-topic message counter since the daemon started; a jump is a lost message"),
}

# Foxglove's time: whole seconds and nanoseconds, as its schemas define it.
FOXGLOVE_TIME: dict[str, Any] = {
    "type": "object", "required": ["sec", "nsec"],
    "properties": {"sec": {"type": "integer", "minimum": 0},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}


def _value(kind: str) -> dict[str, Any]:
    """One value's schema: a JSON type or ``time``, nullable with a trailing ``?``."""
    base = kind.removesuffix("?")
    prop: dict[str, Any] = dict(FOXGLOVE_TIME) if base == "time" else {"type": base}
    if base != kind:
        prop["type"] = [prop["type"], "null"]
    return prop


def _prop(kind: str, text: str) -> dict[str, Any]:
    whole = kind.removesuffix("?")
    if whole.endswith("]"):
        item, n = whole[:-1].split("[")
        prop: dict[str, Any] = {"type": "array", "items": _value(item)}
        if n:
            prop["minItems"] = prop["maxItems"] = int(n)
        if whole != kind:
            prop["type"] = ["array", "null"]
    else:
        prop = _value(kind)
    prop["description"] = text
    return prop


def _schema(title: str, fields: dict[str, Field], stamped: bool = True) -> dict[str, Any]:
    allf = {**(STAMP if stamped else {}), **fields}
    return {"title": title, "type": "object",
            "properties": {k: _prop(*v) for k, v in allf.items()},
            "required": [k for k, (kind, _) in allf.items() if not kind.endswith("?")]}


LATE_READ: Field = ("boolean", "read together with a later second's messages (a host that fell behind): when it "
                               "arrived is not known, and the clock does not pair PPS edges with it")

LOCATION_FIX_FIELDS: dict[str, Field] = {
    "timestamp": ("time", "foxglove.LocationFix time: {sec, nsec} of the fix, Unix UTC"),
    "frame_id": ("string", "foxglove.LocationFix frame: 'gnss' antenna or 'nav' filter output"),
    "latitude": ("number", "latitude, deg, WGS-84"),
    "longitude": ("number", "longitude, deg, WGS-84"),
    "altitude": ("number", "height above the WGS-84 ellipsoid, m"),
    "position_covariance": ("number[9]", "ENU position covariance, m^2, row-major"),
    "position_covariance_type": ("integer", "0 unknown, 1 approximated, 2 diagonal known, 3 known"),
}

GNSS_FIX_FIELDS: dict[str, Field] = {
    **LOCATION_FIX_FIELDS,
    "altitude": ("number?", "height above the WGS-84 ellipsoid, m; null for a position without a height (a 2D fix "
                            "whose receiver sent none: NMEA RMC without GGA); 0 when there is no position either"),
    "gnss_time_ns": ("integer?", "the receiver's epoch time, Unix ns UTC, null while not valid"),
    "itow_ms": ("integer?", "GPS time of week of the epoch, ms (UBX receivers)"),
    "fix_mode": ("integer", "1 no fix, 2 2D, 3 3D, 0 a position without a mode (gpsd's convention)"),
    "fix_ok": ("boolean", "the receiver flags the fix as valid (gnssFixOK / NMEA status A); a record without a "
                          "position has latitude, longitude and altitude 0 (foxglove.LocationFix has no null)"),
    "height_msl_m": ("number?", "height above mean sea level, m"),
    "vel_ned_mps": ("number?[3]?", "velocity north, east, down, m/s; null when the receiver gives none, down null "
                                   "when it gives only speed and course (NMEA, HNR-PVT, gpsd without climb)"),
    "h_acc_m": ("number?", "the receiver's horizontal accuracy estimate (1 sigma), m; null where only a guess exists "
                           "(gpsd's DOP model for an NMEA receiver without GST)"),
    "v_acc_m": ("number?", "the receiver's vertical accuracy estimate (1 sigma), m; null likewise"),
    "s_acc_mps": ("number?", "speed accuracy estimate, m/s"),
    "num_sv": ("integer?", "satellites used in the solution"),
    "pdop": ("number?", "position dilution of precision"),
    "hdop": ("number?", "horizontal dilution of precision (UBX NAV-DOP, NMEA GSA or GGA, gpsd SKY)"),
    "vdop": ("number?", "vertical dilution of precision (UBX NAV-DOP, NMEA GSA, gpsd SKY)"),
    "source": ("string", "messages the fix was built from, e.g. NAV-PVT, NMEA, or gpsd (its TPV and SKY reports)"),
    "late_read": LATE_READ,
    "opened_mono_ns": ("integer?", "board monotonic time of the read the epoch's first message came in, ns, when "
                                   "that was before the read that completed it (t_mono_ns; a slow line: 9600 baud "
                                   "NMEA ends an epoch after the next pulse; through gpsd, the read its TOFF came "
                                   "in); absent when one read held it all"),
    "leap_second": ("boolean?", "true for the epoch 23:59:60 UTC, an inserted leap second: gnss_time_ns and timestamp "
                                "are then POSIX's Unix time for it, that of the 00:00:00 after it (absent otherwise)"),
    "leap_unknown": ("boolean?", "true when the receiver said its leap-second count is not yet the broadcast one (UBX "
                                 "NAV-TIMEGPS leapSValid clear, up to 12.5 min after a cold start): gnss_time_ns may "
                                 "be whole seconds off, and the clock's bound says so; false when it said the count "
                                 "is; absent when the epoch did not say (no NAV-TIMEGPS in it, NMEA, gpsd)"),
}

TOPICS: dict[str, TopicSpec] = {}


def _add(topic: str, schema_name: str, fields: dict[str, Field], description: str, stamped: bool = True) -> None:
    TOPICS[topic] = TopicSpec(topic, schema_name, _schema(schema_name, fields, stamped), description)


_add(IMU, "vehicle_logger.Imu", {
    "accel_mps2": ("number[3]", "specific force along the chip's x, y, z axes, m/s^2"),
    "gyro_rps": ("number[3]", "angular rate about the chip's x, y, z axes, rad/s"),
    "temp_degc": ("number", "die temperature, degC"),
    "fifo": ("boolean", "read through the FIFO (t_mono_ns reconstructed from the sample period)"),
    "lost": ("integer", "samples lost to a FIFO overflow just before this one (0 for reads of the data registers, "
                        "whose holes the health's gaps count)"),
}, "MPU-6050 accelerometer and gyro, one message per sample: an IMU read a register burst per sample "
   "([imu] read = \"register\", up to 50 Hz). Read through its FIFO, the default at every rate, it records "
   "/imu/batch instead; older recordings hold their 20 Hz samples here, and those made before /imu/batch existed "
   "their FIFO samples too")
_add(IMU_BATCH, "vehicle_logger.ImuBatch", {
    "t_mono_ns": ("integer[]", "board monotonic time of each sample, oldest first, ns (reconstructed from the chip's "
                               "sample period, as /imu's fifo samples)"),
    "t_sync_ns": ("integer[]", "synchronised time of each sample, Unix ns UTC; the MCAP log_time is the first's"),
    "sync_state": ("string[]", "clock state of each sample's stamp: locked, holdover or freerun"),
    "sync_err_ns": ("integer[]", "error bound of each stamp, ns"),
    "imu_cnt": ("integer[]", "the paper's IMU counter at each sample"),
    "timer_cnt": ("integer[]", "the paper's timer counter at each sample"),
    "seq": ("integer", "number of the first sample in the IMU's sample sequence since the daemon started; the next "
                       "batch starts at seq + its count, so a jump is samples lost in the logger"),
    "accel_x_mps2": ("number[]", "specific force along the chip's x axis at each sample, m/s^2"),
    "accel_y_mps2": ("number[]", "specific force along the chip's y axis, m/s^2"),
    "accel_z_mps2": ("number[]", "specific force along the chip's z axis, m/s^2"),
    "gyro_x_rps": ("number[]", "angular rate about the chip's x axis at each sample, rad/s"),
    "gyro_y_rps": ("number[]", "angular rate about the chip's y axis, rad/s"),
    "gyro_z_rps": ("number[]", "angular rate about the chip's z axis, rad/s"),
    "temp_degc": ("number", "die temperature read with the batch, degC"),
    "period_s": ("number", "the chip's sample period, s"),
    "lost": ("integer", "samples lost just before the first one: to a FIFO overflow, or while the chip was opened "
                        "again after an error"),
}, "MPU-6050 FIFO read ([imu] read = \"fifo\", the default at every rate): every sample of one read as columns, one "
   "message per read, so that writing and filtering cost per read, not per sample. The logger's own readers "
   "(replay, export, plot, info, the sync report) hand its samples on as /imu records. In Foxglove's Plot panel, "
   "set the X axis to 'Message path' with /imu/batch.t_sync_ns[:] and plot /imu/batch.accel_x_mps2[:] (or any "
   "column) over the whole range",
   stamped=False)
_add(BARO, "vehicle_logger.Baro", {
    "pressure_pa": ("number", "compensated static pressure, Pa"),
    "temp_degc": ("number", "compensated temperature, degC"),
    "altitude_m": ("number", "pressure altitude by the paper's Eq. 4 against sea_level_pa, m"),
    "sea_level_pa": ("number", "reference pressure P0 used for altitude_m, Pa"),
    "oversampling": ("integer", "BMP085 oversampling setting 0..3"),
    "ut": ("integer", "raw temperature word, for re-processing"),
    "up": ("integer", "raw pressure word, for re-processing"),
}, "BMP085/BMP180 pressure, temperature and pressure altitude")
_add(OBD_SPEED, "vehicle_logger.ObdSpeed", {
    "speed_kmh": ("integer", "vehicle speed as the ECU reports it (OBD-II PID 0x0D), km/h, 1 km/h steps"),
    "speed_mps": ("number", "the same speed, m/s"),
    "ecu": ("string", "which ECU answered (CAN id such as 7E8, or '' when headers are off)"),
    "interface": ("string", "elm327 or can"),
}, "OBD-II vehicle speed")
_add(GNSS_FIX, "foxglove.LocationFix", GNSS_FIX_FIELDS,
     "u-blox navigation solution, one per epoch, read on the serial port or through gpsd")
_add(TIMEPULSE, "vehicle_logger.TimePulse", {
    "tow_ms": ("integer", "GPS time of week of the next PPS edge, ms"),
    "tow_sub_ms": ("number", "sub-millisecond part, ms"),
    "week": ("integer", "GPS week of the next edge"),
    "qerr_ps": ("integer", "quantisation error of the next edge, ps"),
    "time_base": ("string", "gnss or utc: the time scale the pulse is aligned to"),
    "late_read": LATE_READ,
}, "UBX TIM-TP: the GNSS time of the next PPS edge")
_add(GNSS_RAW, "vehicle_logger.RawBytes", {
    "t_mono_ns": ("integer", "board monotonic time when these bytes were read, ns"),
    "data_b64": ("string", "the receiver's bytes exactly as read, base64 (UBX, NMEA, RTCM, garbage included)"),
    "n_bytes": ("integer", "number of bytes"),
    "offset": ("integer", "bytes read from the port before these since it was opened: a jump is bytes lost between "
                          "records, 0 again a port opened anew (absent in drives from before it was recorded)"),
}, "the receiver's byte stream for post-processing (RTKLIB, gpsd tools)", stamped=False)
_add(PPS, "vehicle_logger.PpsEdge", {
    "seqno": ("integer", "the line's edge sequence number from the kernel; from gpsd: edges recorded since start"),
    "lost": ("integer", "edges the kernel saw but were not read (sequence gap); from gpsd: seconds skipped"),
    "gnss_time_ns": ("integer?", "GNSS time of the edge when the source names it (gpsd: real time less qErr), "
                                 "Unix ns UTC; null from a GPIO line"),
}, "PPS rising edges; t_mono_ns is the kernel's edge time stamp (from gpsd: its system-clock stamp, mapped)")
_add(SYNC, "vehicle_logger.Sync", {
    "t_mono_ns": ("integer", "board monotonic time of this report, ns"),
    "state": ("string", "freerun, locked or holdover"),
    "offset_ns": ("integer?", "at the last PPS edge, published time minus the edge's GNSS time, ns"),
    "freq_ppm": ("number?", "estimated rate error of the board clock, ppm (positive: it runs fast)"),
    "skew_ppm": ("number?", "uncertainty of freq_ppm, ppm"),
    "rms_ns": ("number?", "RMS of the regression residuals, ns"),
    "err_ns": ("integer", "current error bound of stamps, ns"),
    "since_edge_s": ("number?", "time since the last PPS edge used, s"),
    "samples": ("integer", "edges in the regression"),
    "tempco_ppm_per_degc": ("number?", "learned temperature coefficient of the board clock, ppm per degC"),
    "edges": ("integer", "PPS edges seen since start"),
    "rejected": ("integer", "edges or time messages refused by the pairing checks (false, doubled, stale)"),
    "relocks": ("integer", "returns from holdover to locked"),
}, "the clock's state once a second (what `chronyc tracking` shows)", stamped=False)
_add(HEALTH, "vehicle_logger.Health", {
    "t_mono_ns": ("integer", "board monotonic time of this report, ns"),
    "verdict": ("string", "ok, degraded or critical"),
    "problems": ("string[]", "one line per problem"),
    "sensors": ("object[]", "per sensor: state (ok, silent, no fix, starting: opening it, or open and nothing from "
                            "it yet within its rate's limit, retrying, missing, no-data, stalled, stopped), measured "
                            "rate (null while not delivering), errors, gaps, late, missed, reconnects, samples_lost "
                            "(a FIFO's samples its overflows and reopenings lost), last_error (cleared on recovery)"),
    "recorder": ("object", "queue depth, written and dropped records per topic, free disk"),
    "pace": ("object?", "a simulated drive's pace: ceiling (the --time-scale asked), now, achieved (on average), "
                        "slowest, held_back_s (host seconds below the ceiling); null for a real drive"),
}, "the daemon's health once a second", stamped=False)
_add(TRUTH_CLOCK, "vehicle_logger.TruthClock", {
    "t_mono_ns": ("integer", "board monotonic time, ns"),
    "t_true_ns": ("integer", "true GNSS time at that instant, Unix ns UTC (simulation only)"),
}, "simulation: pairs of board time and true time, 10 Hz", stamped=False)
_add(TRUTH_NAV, "vehicle_logger.TruthNav", {
    "t_true_ns": ("integer", "true time, Unix ns UTC"),
    "lat_deg": ("number", "true latitude, deg"),
    "lon_deg": ("number", "true longitude, deg"),
    "height_m": ("number", "true height above the ellipsoid, m"),
    "vel_ned_mps": ("number[3]", "true velocity north, east, down, m/s"),
    "rpy_deg": ("number[3]", "true roll, pitch, yaw, deg"),
}, "simulation: the vehicle's true state at the IMU rate", stamped=False)
_add(NAV_FIX, "foxglove.LocationFix", {
    "t_mono_ns": ("integer", "board monotonic time of the IMU sample this solution is for, ns"),
    "t_sync_ns": ("integer", "synchronised time of that sample, Unix ns UTC (also the MCAP log_time)"),
    **LOCATION_FIX_FIELDS,
    "vel_ned_mps": ("number[3]", "velocity north, east, down, m/s"),
    "rpy_deg": ("number[3]", "roll, pitch, yaw of the vehicle, deg"),
    "sigma_ned_m": ("number[3]", "1-sigma position uncertainty north, east, down, m"),
    "source": ("string", "what the solution rests on: 'ins 17-state', 'ins 15-state' or 'gnss'"),
    "mode": ("string", "filter mode: 17, 15 or gnss"),
}, "navigation filter solution (live and logger replay: at nav.publish_hz; logger replay --fix-hz 0: one "
   "per IMU sample)", stamped=False)
_add(NAV_STATE, "vehicle_logger.NavState", {
    "t_mono_ns": ("integer", "board monotonic time of the IMU sample this state is for, ns"),
    "t_sync_ns": ("integer", "synchronised time of that sample, Unix ns UTC"),
    "mode": ("string", "filter mode: 17, 15 or gnss"),
    "status": ("string", "initialising, navigating or gnss only"),
    "accel_bias_mps2": ("number[3]?", "estimated accelerometer offset, vehicle x y z, m/s^2"),
    "gyro_bias_rps": ("number[3]?", "estimated gyro offset, vehicle x y z, rad/s"),
    "obd_scale": ("number?", "true speed divided by OBD speed (1 + the scale factor state)"),
    "height_offset_m": ("number?", "ellipsoidal height minus barometric altitude, m"),
    "p_diag": ("number[]?", "covariance diagonal in state_names order: m^2, (m/s)^2, rad^2, (m/s^2)^2, (rad/s)^2, 1, "
                            "m^2 (and (m/s)^2 with [nav] obd_rounding_state)"),
    "state_names": ("string[]", "names of the error states, in covariance order"),
    "innovations": ("object", "last innovation (predicted minus measured) per update type, SI units of that type"),
    "nis": ("object", "last normalised innovation squared per update type (chi-square distributed when consistent)"),
    "updates": ("object", "accepted updates per type since the start"),
    "rejections": ("object", "updates refused by the chi-square gate per type since the start"),
    "resets": ("integer", "times the filter lost itself and restarted from GNSS"),
    "reanchors": ("integer", "times refused good fixes or baro heights, agreeing, widened the position sigma"),
    "reopens": ("integer", "times trusted velocities refused in a row made the filter reopen velocity, attitude and "
                           "IMU offsets"),
    "repairs": ("integer", "times the covariance lost positive definiteness and was repaired"),
    "stopped": ("boolean", "the vehicle is standing still (zero-motion updates running)"),
    "imu_noise_x": ("number[2]?", "the IMU's white noise as the drive measures it over the configured densities, "
                                  "accelerometer and gyro (3 or more: a board that shakes or a consumer part); null "
                                  "until measured or with nav.imu_noise_from_drive off"),
    "held_stops": ("integer", "stops held by the OBD speed or the fixes that taught the stop detector a standstill "
                              "it never read still (an IMU noisier than its thresholds)"),
    "mount_rpy_deg": ("number[3]?", "the IMU's mounting as the drive shows it: roll, pitch, yaw of the chip against "
                                    "the vehicle, deg (nav.mounting_rpy_deg's convention); null until estimated"),
    "mount_sigma_deg": ("number[3]?", "1-sigma of mount_rpy_deg, deg"),
    "mount_state": ("string?", "the mount alignment: learning, forward (the car's forward axis known, the roll "
                               "still the guess: no turns yet) or settled; null when nav.mount_align is off"),
    "mount_applied_rpy_deg": ("number[3]", "the mounting the filter turns the samples with now, deg"),
    "remounts": ("integer", "times the mount alignment replaced the mounting in use (its forward axis once known, "
                            "then the settled estimate)"),
    "mount_moves": ("integer", "times the mounting was seen to move during the drive (the board knocked)"),
    "rerun_at_s": ("number?", "how far into its kept inputs the remount that reopened attitude and offsets came "
                              "(or, for a second re-run, the forward axis that held still), s, once the filter took "
                              "those inputs again from the start with that mounting (the first minutes of a drive on "
                              "a mounting not configured); null if it has not"),
    "gnss_time": ("string", "how fix epochs are placed on the logger's clock: clock locked, pps, shortest delay, "
                            "by arrival for a fix without a valid time, none before the first fix"),
    "verdicts": ("string[]", "plain health verdicts, one sentence each (live only)"),
    "dropped": ("integer?", "records the live navigator skipped because it was behind (live only)"),
    "cpu_s": ("number?", "CPU time the live navigator thread has used since the start, s (live only)"),
}, "navigation filter state once a second (the first solution of each whole second of synchronised time): biases, "
   "scale factor, height offset, covariance, innovations", stamped=False)
