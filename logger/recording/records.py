"""The record layer: where a typed value becomes a recorded message and a recorded message a typed input.

Topic names are spelled in :mod:`logger.recording.topics` (with the schemas); the payloads of the sensor, clock
and filter records are built and read here. The sensor adapters, the daemon and the navigator build their records
with these functions, and the daemon and ``logger replay`` both hand records to the clock and to the navigation
filter through :func:`clock_observer` and :func:`nav_feeder`, so neither :mod:`sync` nor :mod:`logger.nav`
knows a topic or a payload key, and a live drive and its replay feed them the same inputs. Two records carry
what another part reports as it reports it: ``/health`` the status snapshot's sensor and recorder sections, and
a simulated drive's ``/truth/nav`` the simulator's truth.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Callable, Sequence
from itertools import chain, pairwise
from typing import TYPE_CHECKING, Any

import numpy as np

from logger.nav.engine import NavEngine
from logger.nav.inputs import GnssObservation
from logger.nav.state import N_FULL, STATE_NAMES
from logger.recording.topics import BARO, GAP_PERIODS, GNSS_FIX, IMU, IMU_BATCH, OBD_SPEED, PPS, TIMEPULSE
from sync.inputs import FixEpoch, TimeAnnouncement
from sync.stamp import NO_BOUND_NS, Stamp, StampClock, Stamps, TrackingReport

if TYPE_CHECKING:  # the receiver driver (and pyserial behind it) is not needed to replay a drive
    from sensors.bmp085 import BaroSample
    from sensors.obd import ObdSpeed
    from sensors.ublox_decode import GnssFix, TimePulse

RecordInput = Callable[[dict[str, Any]], None]
ClockInput = Callable[[dict[str, Any], int], None]

NAV_INPUT_TOPICS: tuple[str, ...] = (IMU, GNSS_FIX, OBD_SPEED, BARO, PPS)  # what the navigation filter takes


# ---- sensor records ------------------------------------------------------------------------------------------
def stamped_record(t_mono_ns: int, stamp: Stamp, seq: int, payload: dict[str, Any]) -> dict[str, Any]:
    """A sensor's record as recorded: its acquisition time, the clock's stamp, the topic's sequence number, then
    the sensor's own fields."""
    return {"t_mono_ns": t_mono_ns, "t_sync_ns": stamp.t_sync_ns, "sync_state": stamp.state,
            "sync_err_ns": stamp.err_ns, "imu_cnt": stamp.imu_cnt, "timer_cnt": stamp.timer_cnt, "seq": seq,
            **payload}


def imu_record(accel_mps2: Sequence[float], gyro_rps: Sequence[float], temp_degc: float, fifo: bool,
               lost: int) -> dict[str, Any]:
    """An ``/imu`` sample: chip axes, SI units."""
    return {"accel_mps2": accel_mps2, "gyro_rps": gyro_rps, "temp_degc": round(temp_degc, 3), "fifo": fifo,
            "lost": lost}


# A FIFO read's values are rounded far below the chip's resolution (at its finest range an LSB is 6e-4 m/s^2 and
# 1.3e-4 rad/s): the record stays short, the sample is unchanged for any use.
ACCEL_DECIMALS = 5
GYRO_DECIMALS = 6
IMU_AXES = ("x", "y", "z")


def imu_batch_payload(times_ns: Sequence[int], accel_mps2: np.ndarray, gyro_rps: np.ndarray, temp_degc: float,
                      period_s: float, lost: int) -> dict[str, Any]:
    """What a FIFO read hands the daemon: its samples as columns, their acquisition times; the daemon adds the
    stamps (:func:`stamped_batch`), so an ``/imu/batch`` record costs one message, not one per sample."""
    a = accel_mps2.round(ACCEL_DECIMALS).T.tolist()  # the method: np.round dispatches at a fifth of this cost
    g = gyro_rps.round(GYRO_DECIMALS).T.tolist()
    return {"t_mono_ns": list(times_ns),
            "accel_x_mps2": a[0], "accel_y_mps2": a[1], "accel_z_mps2": a[2],
            "gyro_x_rps": g[0], "gyro_y_rps": g[1], "gyro_z_rps": g[2],
            "temp_degc": round(temp_degc, 3), "period_s": period_s, "lost": lost}


def stamped_batch(stamps: Stamps, seq: int, payload: dict[str, Any]) -> dict[str, Any]:
    """An ``/imu/batch`` record as recorded: each sample's stamp as columns, the first sample's number, the rest."""
    return {"t_mono_ns": payload["t_mono_ns"], "t_sync_ns": stamps.t_sync_ns, "sync_state": stamps.state,
            "sync_err_ns": stamps.err_ns, "imu_cnt": stamps.imu_cnt, "timer_cnt": stamps.timer_cnt, "seq": seq,
            **{k: v for k, v in payload.items() if k != "t_mono_ns"}}


def baro_record(s: BaroSample, sea_level_pa: float) -> dict[str, Any]:
    """A ``/baro`` reading, with the raw words kept for re-processing."""
    return {"pressure_pa": float(s.pressure_pa), "temp_degc": float(s.temp_degc),
            "altitude_m": round(float(s.altitude_m), 4), "sea_level_pa": sea_level_pa, "oversampling": s.oss,
            "ut": s.ut, "up": s.up}


def speed_record(s: ObdSpeed, interface: str) -> dict[str, Any]:
    """An ``/obd/speed`` reading: the ECU's integer km/h as it came, m/s beside it, and who answered."""
    ecu = f"{s.ecu_id:X}" if s.ecu_id is not None else ""
    return {"speed_kmh": s.speed_kmh, "speed_mps": round(s.speed_mps, 4), "ecu": ecu, "interface": interface}


def timepulse_record(tp: TimePulse, late_read: bool = False) -> dict[str, Any]:
    """A ``/gnss/timepulse`` record: UBX TIM-TP's announcement of the next pulse."""
    return {"tow_ms": tp.tow_ms, "tow_sub_ms": tp.tow_sub_ms, "week": tp.week, "qerr_ps": tp.qerr_ps,
            "time_base": tp.time_base, "late_read": late_read}


def raw_bytes_record(t_mono_ns: int, data: bytes, offset: int) -> dict[str, Any]:
    """A ``/gnss/raw`` record: the receiver's bytes exactly as read, and how many the port gave before them since it
    was opened, so that an export can tell a lost record (a jump) from a port opened anew (0 again)."""
    return {"t_mono_ns": t_mono_ns, "data_b64": base64.b64encode(data).decode(), "n_bytes": len(data),
            "offset": offset}


def pps_record(seqno: int, lost: int, gnss_time_ns: int | None = None) -> dict[str, Any]:
    """A ``/pps`` edge; ``gnss_time_ns`` only from a source that names the edge's second (gpsd)."""
    if gnss_time_ns is None:
        return {"seqno": seqno, "lost": lost}
    return {"seqno": seqno, "lost": lost, "gnss_time_ns": gnss_time_ns}


def location_fix(fix: GnssFix, t_mono_ns: int, late_read: bool = False, opened_mono_ns: int | None = None
                 ) -> dict[str, Any]:
    """A GnssFix as a foxglove.LocationFix plus the receiver's own fields; ``late_read`` when the host read it
    together with a later second's fix, so that its arrival (``t_mono_ns``) is known only as an upper bound;
    ``opened_mono_ns`` when the epoch's first message came in an earlier read than its last (a slow line)."""
    sec_ns = fix.time_utc_ns if fix.time_utc_ns is not None else 0
    lat = fix.lat_deg if fix.lat_deg is not None else 0.0
    lon = fix.lon_deg if fix.lon_deg is not None else 0.0
    # A position without a height (an NMEA epoch whose GGA did not come) records no height: 0 m would be taken for
    # one by whatever reads the record (the filter, the exports), 600 m off for a car at 600 m.
    alt = fix.height_hae_m if fix.height_hae_m is not None else (0.0 if fix.lat_deg is None else None)
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
        "num_sv": fix.num_sv, "pdop": fix.pdop, "hdop": fix.hdop,
        "vdop": fix.vdop, "source": fix.source, "late_read": late_read,
        **({"leap_second": True} if fix.leap_second else {}),
        **({"leap_unknown": not fix.leap_known} if fix.leap_known is not None and fix.time_valid else {}),
        **({"opened_mono_ns": opened_mono_ns} if opened_mono_ns is not None else {}),
    }


NO_FIX = "no fix"
FIX_NAMES = {0: "fix", 1: NO_FIX, 2: "2D", 3: "3D"}  # gpsd's modes; 0: a position without a mode (NMEA GGA)


def fix_name(record: dict[str, Any]) -> str:
    """A ``/gnss/fix`` record's fix in a word: ``3D``, ``2D``, ``fix`` (a position without a mode) or ``no fix``."""
    if not record.get("fix_ok"):
        return NO_FIX
    return FIX_NAMES.get(record.get("fix_mode") or 0, "fix")


def sync_record(report: TrackingReport) -> dict[str, Any]:
    """A ``/sync`` record (and the ``sync`` section of ``logger status``): the clock's tracking report."""
    return {"t_mono_ns": report.t_mono_ns, "state": report.state, "offset_ns": report.offset_ns,
            "freq_ppm": report.freq_ppm, "skew_ppm": report.skew_ppm, "rms_ns": report.rms_ns,
            "err_ns": report.err_ns, "since_edge_s": report.since_edge_s, "samples": report.samples,
            "tempco_ppm_per_degc": report.tempco_ppm_per_degc, "edges": report.edges, "rejected": report.rejected,
            "relocks": report.relocks}


def health_record(snapshot: dict[str, Any], t_mono_ns: int) -> dict[str, Any]:
    """A ``/health`` record: the verdict, problems and sensors of the status snapshot, the recorder's counters, and
    a simulated drive's pace (null otherwise)."""
    rec = snapshot["recorder"]
    return {"t_mono_ns": t_mono_ns, "verdict": snapshot["verdict"], "problems": snapshot["problems"],
            "sensors": snapshot["sensors"],
            "recorder": {k: rec[k] for k in ("state", "queue_depth", "written", "dropped", "free_bytes")},
            "pace": snapshot.get("pace")}


def truth_clock_record(t_mono_ns: int, t_true_ns: int) -> dict[str, Any]:
    """A ``/truth/clock`` record of a simulated drive: a board time and the true time at that instant."""
    return {"t_mono_ns": t_mono_ns, "t_true_ns": t_true_ns}


# ---- records to the clock ------------------------------------------------------------------------------------
def time_announcement(payload: dict[str, Any]) -> TimeAnnouncement | None:
    """A ``/gnss/timepulse`` record as the clock's input; None when it does not name its second."""
    try:
        week, tow_ms = int(payload["week"]), int(payload["tow_ms"])
    except (KeyError, TypeError, ValueError):
        return None
    return TimeAnnouncement(week, tow_ms, float(payload.get("tow_sub_ms") or 0.0), payload.get("qerr_ps") or 0,
                            payload.get("time_base") == "utc", bool(payload.get("late_read")))


def fix_epoch(payload: dict[str, Any]) -> FixEpoch | None:
    """A ``/gnss/fix`` record as the clock's input; None while the receiver's time is not valid."""
    t = payload.get("gnss_time_ns")
    return None if t is None else FixEpoch(t, payload.get("itow_ms"), bool(payload.get("late_read")),
                                           bool(payload.get("leap_second")), payload.get("opened_mono_ns"),
                                           payload.get("leap_unknown"))


def clock_observer(clock: StampClock) -> dict[str, ClockInput]:
    """Per topic, what a record (payload, board time it was taken) tells the clock; other topics tell nothing."""

    def imu(p: dict[str, Any], t: int) -> None:
        clock.on_imu_sample(t, p.get("temp_degc"))

    def imu_batch(p: dict[str, Any], t: int) -> None:
        clock.on_imu_samples(p["t_mono_ns"], p.get("temp_degc"))

    def pps(p: dict[str, Any], t: int) -> None:
        clock.on_edge(t, p.get("gnss_time_ns"))  # named when the PPS source knows the edge's second (gpsd)

    def timepulse(p: dict[str, Any], t: int) -> None:
        tp = time_announcement(p)
        if tp is not None:
            clock.on_announcement(tp, t)

    def fix(p: dict[str, Any], t: int) -> None:
        epoch = fix_epoch(p)
        if epoch is not None:
            clock.on_fix_epoch(epoch, t)

    return {IMU: imu, IMU_BATCH: imu_batch, PPS: pps, TIMEPULSE: timepulse, GNSS_FIX: fix}


def observe_clock(clock: StampClock, topic: str, payload: dict[str, Any], t_mono_ns: int) -> None:
    """One record to the clock (for tools and tests that replay records one at a time)."""
    handler = clock_observer(clock).get(topic)
    if handler is not None:
        handler(payload, t_mono_ns)


# ---- records to the navigation filter -------------------------------------------------------------------------
def gnss_observation(msg: dict[str, Any]) -> GnssObservation:
    """A ``/gnss/fix`` record as the filter's input: optional fields stay None, nothing is made up. A number that is
    not one (NaN, infinite) or a position off the globe is refused (ValueError): no receiver reports it, and the
    filter would take it in."""
    fault = _fix_numbers_fault(msg)
    if fault is not None:
        raise ValueError(fault)
    vel = msg.get("vel_ned_mps")
    return GnssObservation(
        t_sync_ns=int(msg["t_sync_ns"]), t_mono_ns=int(msg["t_mono_ns"]), gnss_time_ns=msg.get("gnss_time_ns"),
        sync_state=msg.get("sync_state", ""), fix_ok=bool(msg.get("fix_ok")), fix_mode=msg.get("fix_mode"),
        lat_deg=msg.get("latitude"), lon_deg=msg.get("longitude"),
        height_m=None if msg.get("altitude") is None else float(msg["altitude"]),
        vel_ned_mps=None if vel is None else tuple(vel), h_acc_m=msg.get("h_acc_m"), v_acc_m=msg.get("v_acc_m"),
        s_acc_mps=msg.get("s_acc_mps"), pdop=msg.get("pdop"), num_sv=msg.get("num_sv"),
        hdop=msg.get("hdop"), vdop=msg.get("vdop"), leap_unknown=msg.get("leap_unknown") is True,
        opened_mono_ns=msg.get("opened_mono_ns"))


# What the filter reads of each input record (nav_feeder and gnss_observation): a record kept for the filter alone
# (nav_rerun.py's tape) keeps these. A FIFO read's columns are feed_reads's; tests/test_nav_mounting.py checks
# that a record cut to these gives the filter the same input.
NAV_INPUT_KEYS: dict[str, tuple[str, ...]] = {
    IMU: ("t_sync_ns", "t_mono_ns", "accel_mps2", "gyro_rps", "temp_degc"),
    GNSS_FIX: ("t_sync_ns", "t_mono_ns", "gnss_time_ns", "sync_state", "fix_ok", "fix_mode", "latitude", "longitude",
               "altitude", "vel_ned_mps", "h_acc_m", "v_acc_m", "s_acc_mps", "pdop", "num_sv", "hdop", "vdop",
               "leap_unknown", "opened_mono_ns"),
    OBD_SPEED: ("t_sync_ns", "speed_mps"),
    BARO: ("t_sync_ns", "altitude_m"),
    PPS: ("t_sync_ns",),
}


def nav_feeder(engine: NavEngine) -> dict[str, RecordInput]:
    """Per topic of :data:`NAV_INPUT_TOPICS`, the engine input a record becomes."""

    def imu(m: dict[str, Any]) -> None:
        a, g = m["accel_mps2"], m["gyro_rps"]
        acc, rate = (a[0], a[1], a[2]), (g[0], g[1], g[2])
        if not all(_sample(v) for v in acc + rate):
            raise ValueError(SAMPLE_FAULT)
        engine.imu(m["t_sync_ns"], m["t_mono_ns"], acc, rate, m.get("temp_degc"))

    def imu_batch(m: dict[str, Any]) -> None:
        feed_reads(engine, (m,))

    def fix(m: dict[str, Any]) -> None:
        engine.gnss(gnss_observation(m))

    def obd(m: dict[str, Any]) -> None:
        engine.obd(m["t_sync_ns"], _finite(m["speed_mps"], "speed_mps"))

    def baro(m: dict[str, Any]) -> None:
        engine.baro(m["t_sync_ns"], _finite(m["altitude_m"], "altitude_m"))

    def pps(m: dict[str, Any]) -> None:
        engine.pps(m["t_sync_ns"])

    return {IMU: imu, IMU_BATCH: imu_batch, GNSS_FIX: fix, OBD_SPEED: obd, BARO: baro, PPS: pps}


_ACC = ("accel_x_mps2", "accel_y_mps2", "accel_z_mps2")
_GYRO = ("gyro_x_rps", "gyro_y_rps", "gyro_z_rps")
# A fix's fields that are numbers where present (gnss_observation passes them on as they are).
_FIX_NUMBERS = ("fix_mode", "latitude", "longitude", "altitude", "h_acc_m", "v_acc_m", "s_acc_mps", "pdop", "num_sv",
                "hdop", "vdop")
_FIX_TIMES = ("gnss_time_ns", "opened_mono_ns")
GNSS_EPOCH_SPAN_NS = (315_964_800_000_000_000, 7_258_118_400_000_000_000)  # 1980-01-06 (GPS time's start) to 2200
TIME_LIMIT_NS = 2**62  # a board or Unix time in ns is well within this
# No MEMS IMU reports more (the MPU-6050 at most 16 g and 2000 deg/s: 157 m/s^2, 35 rad/s): a value beyond it is not
# a sample, and the filter's squares of it overflow.
SAMPLE_LIMIT = 1.0e4
SAMPLE_FAULT = "a sample's acceleration or rate is not a number a sensor gives"


def _number(v: Any) -> bool:
    """A finite number (JSON's Infinity and NaN are not measurements; a bool is not a number here)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(v)


def _sample(v: Any) -> bool:
    """An acceleration (m/s^2) or rate (rad/s) a sensor gives."""
    return _number(v) and abs(v) <= SAMPLE_LIMIT


def _time(v: Any) -> bool:
    """A time in integer nanoseconds, as the logger writes them."""
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool) and abs(v) < TIME_LIMIT_NS


def _finite(v: Any, name: str) -> float:
    """``v`` as a float, or ValueError naming ``name`` where it is not a finite number."""
    x = float(v)
    if not math.isfinite(x):
        raise ValueError(f"{name} is not a finite number")
    return x


def _fix_numbers_fault(msg: dict[str, Any]) -> str | None:
    """What is wrong with the numbers of a ``/gnss/fix`` record (finite, on the globe, times in ns), or None."""
    for key in _FIX_NUMBERS:
        if msg.get(key) is not None and not _number(msg[key]):
            return f"{key} is not a number"
    for key in _FIX_TIMES:
        if msg.get(key) is not None and not _time(msg[key]):
            return f"{key} is not a time in integer nanoseconds"
    t = msg.get("gnss_time_ns")
    if t is not None and not GNSS_EPOCH_SPAN_NS[0] <= t <= GNSS_EPOCH_SPAN_NS[1]:
        return "gnss_time_ns is not a time between 1980 and 2200"
    if msg.get("latitude") is not None and abs(msg["latitude"]) > 90.0:
        return "latitude is off the globe"
    if msg.get("longitude") is not None and abs(msg["longitude"]) > 180.0:
        return "longitude is off the globe"
    vel = msg.get("vel_ned_mps")
    if vel is not None and (not isinstance(vel, list) or len(vel) != 3
                            or not all(v is None or _number(v) for v in vel)):
        return "vel_ned_mps is not three numbers (or nulls)"
    return None


def record_fault(topic: str, msg: Any) -> str | None:
    """What keeps ``msg`` from being a ``topic`` record the filter can take (the field and what is wrong with it), or
    None when it is one.

    Asked only after feeding a message raised: a foreign file's messages (another tool's /imu of other fields) are
    skipped and counted, but a message that is a well-formed record and still raised met a failure of the filter
    (a math domain error is a ValueError, as numpy 2's LinAlgError is), which must not be reported as the file's."""
    if not isinstance(msg, dict):
        return "not an object"
    if topic == IMU_BATCH:
        try:
            read_columns((msg,))
        except KeyError as exc:
            return f"no field {exc}"
        except (TypeError, ValueError) as exc:
            return str(exc)
        for key in ("temp_degc", "period_s", "lost"):  # the last two: what follows_on reads
            if msg.get(key) is not None and not _number(msg[key]):
                return f"{key} is not a number"
        return None
    if topic not in NAV_INPUT_KEYS:
        return None
    for key in ("t_sync_ns", "t_mono_ns") if topic in (IMU, GNSS_FIX) else ("t_sync_ns",):
        if not _time(msg.get(key)):
            return f"{key} is not a time in integer nanoseconds"
    if topic == IMU:
        for key in ("accel_mps2", "gyro_rps"):
            v = msg.get(key)
            if not isinstance(v, list) or len(v) != 3 or not all(_sample(x) for x in v):
                return f"{key} is not three numbers a sensor gives"
        return None if msg.get("temp_degc") is None or _number(msg["temp_degc"]) else "temp_degc is not a number"
    if topic == OBD_SPEED:
        return None if _number(msg.get("speed_mps")) else "speed_mps is not a number"
    if topic == BARO:
        return None if _number(msg.get("altitude_m")) else "altitude_m is not a number"
    if topic == GNSS_FIX:
        fault = _fix_numbers_fault(msg)
        if fault is not None:
            return fault
        if not isinstance(msg.get("sync_state", ""), str):
            return "sync_state is not a string"
    return None


def unplaced(m: dict[str, Any]) -> bool:
    """Whether a record's stamp has no bound: free-running on a system clock that was not synchronised at start
    (a board without RTC or network boots at its image's date, or 1970), its time the board's guess until GNSS
    time is known. The filter integrates over time and cannot take it: levelled on such stamps, it crossed the
    jump of decades at the lock and published positions thousands of degrees off. A FIFO read's samples are
    stamped under one state, so its first says."""
    err = m.get("sync_err_ns")
    if isinstance(err, list):
        err = err[0] if err else None
    return isinstance(err, int) and err >= NO_BOUND_NS


def follows_on(m: dict[str, Any], last: int | None) -> bool:
    """Whether the FIFO read ``m`` goes on from a sample at ``last``: nothing lost before it, its first sample
    within GAP_PERIODS sample periods after ``last``, its own samples in order (such reads go to
    :func:`feed_reads` together)."""
    t = m["t_sync_ns"]
    period = m.get("period_s")
    if last is None or len(t) == 0 or m.get("lost") or not period or not 0 < t[0] - last <= GAP_PERIODS * period * 1e9:
        return False
    return all(a < b for a, b in pairwise(t))


def feed_reads(engine: NavEngine, ms: Sequence[dict[str, Any]]) -> None:
    """One or more ``/imu/batch`` records that follow one another (nothing between them, each one's samples after
    the last one's) through one :meth:`NavEngine.imu_batch` call: their columns end to end, a block long enough for
    the engine's block forms where each FIFO read alone is shorter. The die temperature goes one per read (one per
    sample where the reads' differ), so the engine gives what it gives fed the reads one by one (to round-off);
    which reads may go together is the caller's to judge. Columns that are not a FIFO read's raise ValueError before
    the filter takes any of them (:func:`read_columns`)."""
    t_sync, t_mono, acc, rate = read_columns(ms)
    temp: float | np.ndarray | None = ms[0].get("temp_degc")
    if len(ms) > 1:
        temps = [r.get("temp_degc") for r in ms]
        if any(c != temp for c in temps):
            temp = np.repeat(np.array([math.nan if c is None else c for c in temps], dtype=float),
                             [len(r["t_sync_ns"]) for r in ms])
    engine.imu_batch(t_sync, t_mono, acc, rate, temp)


def read_columns(ms: Sequence[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The times (board and synchronised, int64) and the acceleration and rate (n x 3) of one or more ``/imu/batch``
    records, end to end; ValueError naming what is not a FIFO read's: no samples, columns of other lengths, times
    that are not integer nanoseconds, a value no sensor gives (NaN and Infinity among them; the filter's squares of
    1e300 overflow). The one rule of what the filter takes of a FIFO read, for :func:`feed_reads` and
    :func:`record_fault`."""
    if len(ms) == 1:
        m = ms[0]

        def column(key: str) -> list[Any]:
            return m[key]
    else:
        def column(key: str) -> list[Any]:
            return list(chain.from_iterable(r[key] for r in ms))
    t_sync, t_mono = np.asarray(column("t_sync_ns")), np.asarray(column("t_mono_ns"))
    values = [column(k) for k in (*_ACC, *_GYRO)]
    if not t_sync.size:
        raise ValueError("a FIFO read without samples")
    if t_sync.ndim != 1 or any(len(c) != len(t_sync) for c in (t_mono, *values)):
        raise ValueError("a FIFO read's columns hold different numbers of samples")
    if t_sync.dtype.kind != "i" or t_mono.dtype.kind != "i":
        raise ValueError("a FIFO read's times are not integer nanoseconds")
    cols = np.array(values, dtype=float)
    if not np.abs(cols).max() <= SAMPLE_LIMIT:  # a NaN is the max, and fails
        raise ValueError(SAMPLE_FAULT)
    return t_sync, t_mono, cols[:3].T, cols[3:].T


def feed_record(feed: dict[str, RecordInput], topic: str, msg: dict[str, Any]) -> None:
    """One record through a :func:`nav_feeder`; topics the filter does not take are ignored."""
    handler = feed.get(topic)
    if handler is not None:
        handler(msg)


# ---- the filter's output as records ---------------------------------------------------------------------------
def nav_fix_record(t_ns: int, t_mono_ns: int, lat: float, lon: float, h: float, vel: tuple[float, float, float],
                rpy: tuple[float, float, float], sigma: tuple[float, float, float], source: str,
                mode: str) -> dict[str, Any]:
    """A ``/nav/fix`` record: foxglove.LocationFix (ENU covariance) plus velocity, attitude and sigmas."""
    sn, se, sd = (s if math.isfinite(s) else 1e6 for s in sigma)
    return {
        "t_mono_ns": int(t_mono_ns), "t_sync_ns": int(t_ns),
        "timestamp": {"sec": int(t_ns) // 1_000_000_000, "nsec": int(t_ns) % 1_000_000_000},
        "frame_id": "nav", "latitude": math.degrees(lat), "longitude": math.degrees(lon), "altitude": h,
        "position_covariance": [se * se, 0.0, 0.0, 0.0, sn * sn, 0.0, 0.0, 0.0, sd * sd],
        "position_covariance_type": 2,
        "vel_ned_mps": [float(v) for v in vel], "rpy_deg": [math.degrees(a) for a in rpy],
        "sigma_ned_m": [sn, se, sd], "source": source, "mode": mode,
    }


def next_whole_second(t_ns: int) -> int:
    """When the next ``/nav/state`` is due after one at ``t_ns``: the next whole second of synchronised time. One
    a second after the last drifted later by however late each came (a solution is looked at a wake-up or a FIFO
    read at a time, half a second apart): 0.87-0.91 a second where the topic says one."""
    return (t_ns // 1_000_000_000 + 1) * 1_000_000_000


def nav_state_record(engine: NavEngine, t_ns: int, t_mono_ns: int, verdicts: list[str] | None = None,
                  extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """A ``/nav/state`` record: what the filter believes about the sensors, and how its updates fare."""
    s, ekf = engine.state, engine.ekf
    c = engine.counters
    msg: dict[str, Any] = {
        "t_mono_ns": int(t_mono_ns), "t_sync_ns": int(t_ns), "mode": engine.mode,
        "status": "navigating" if s is not None else ("gnss only" if engine.mode == "gnss" else "initialising"),
        "accel_bias_mps2": [float(b) for b in s.ba] if s else None,
        "gyro_bias_rps": [float(b) for b in s.bg] if s else None,
        "obd_scale": 1.0 + s.sf if s and engine.n >= N_FULL else None,
        "height_offset_m": s.dh if s and engine.n >= N_FULL else None,
        "p_diag": [float(v) for v in ekf.p.diagonal()] if ekf else None,
        "state_names": list(STATE_NAMES[: engine.n]),
        "innovations": {k: v.last_innovation for k, v in ekf.stats.items()} if ekf else {},
        "nis": {k: v.last_nis for k, v in ekf.stats.items()} if ekf else {},
        "updates": {k: v.accepted for k, v in ekf.stats.items()} if ekf else {},
        "rejections": {k: v.rejected for k, v in ekf.stats.items()} if ekf else {},
        "resets": c.resets, "reanchors": c.reanchors, "reopens": c.reopens, "repairs": ekf.repairs if ekf else 0,
        "stopped": engine.stopped,
        "imu_noise_x": engine.imu_noise_ratio(),
        "held_stops": engine.stops.held_learned,
        **_mount_fields(engine),
        "gnss_time": engine.epoch_clock.method,
        "verdicts": verdicts or [],
    }
    if extra:
        msg.update(extra)
    return msg


def _mount_fields(engine: NavEngine) -> dict[str, Any]:
    """The mount alignment's estimate for ``/nav/state`` (nulls when the alignment is off or has not started)."""
    al = engine.alignment
    est = al.estimate() if al is not None else None
    known = est is not None and math.isfinite(est.sigma_deg[0])
    return {"mount_rpy_deg": list(est.rpy_deg) if known else None,
            "mount_sigma_deg": list(est.sigma_deg) if known else None,
            "mount_state": est.state if est is not None else None,
            "mount_applied_rpy_deg": list(engine.mount_applied), "remounts": engine.counters.remounts,
            "mount_moves": al.moves if al is not None else 0, "rerun_at_s": engine.rerun_at_s}
