"""What the filter takes, as typed inputs: the engine never sees a topic or a record's keys.

IMU samples, vehicle speeds, barometric heights and PPS edges are plain arguments of the engine's methods (they
come at up to 1 kHz, and a float is their whole content); a GNSS fix has many optional parts and comes as one
:class:`GnssObservation`. The record layer (:mod:`logger.recording.records`) builds them from recorded or live
records, so the filter knows no file format, as KF-GINS' engine knows its ``IMU`` and ``GNSS`` structs only.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class GnssObservation:
    """One navigation solution of the receiver, with what it leaves out left as None."""

    t_sync_ns: int  # when the solution was read, on the logger's synchronised clock (arrival, not epoch)
    t_mono_ns: int  # the same instant on the board's monotonic clock
    gnss_time_ns: int | None  # the receiver's epoch, Unix ns UTC; None while its time is not valid
    sync_state: str  # the clock's state at t_sync_ns (sync.stamp's FREERUN, LOCKED, HOLDOVER)
    fix_ok: bool  # the receiver flags the fix as valid
    fix_mode: int | None  # 1 no fix, 2 2D, 3 3D
    lat_deg: float | None  # None: the receiver gave no position (not a fix, whatever its flags say)
    lon_deg: float | None
    height_m: float | None  # above the WGS-84 ellipsoid
    vel_ned_mps: tuple[float | None, float | None, float | None] | None  # an element is None when not given
    h_acc_m: float | None  # the receiver's accuracy estimates, 1 sigma
    v_acc_m: float | None
    s_acc_mps: float | None
    pdop: float | None
    num_sv: int | None
    hdop: float | None = None  # recordings made before the DOPs were kept have none
    vdop: float | None = None
    # The receiver said its leap count is not yet the broadcast one (records' leap_unknown): gnss_time_ns may be whole
    # seconds off, which the post-processed solution's join allows for
    leap_unknown: bool = False
    # The board time of the read the epoch's first message came in, when before t_mono_ns (a slow line: 9600 baud
    # NMEA ends an epoch's burst after the next pulse); None: the fix came in one read
    opened_mono_ns: int | None = None


@dataclass(frozen=True, slots=True)
class SolutionEpoch:
    """One epoch of a post-processed solution (RTKLIB's ``rnx2rtkp``/``rtkpost`` ``.pos``): a position and its
    covariance at a GNSS epoch, with the solution's quality. No arrival time: the epoch is placed on the logger's
    clock through the receiver's own time (:meth:`logger.nav.engine.NavEngine.use_solution`)."""

    gnss_time_ns: int  # the epoch, Unix ns UTC: the scale of GnssObservation.gnss_time_ns
    lat_deg: float
    lon_deg: float
    height_m: float  # above the WGS-84 ellipsoid
    cov_ned_m2: tuple[tuple[float, float, float], ...]  # 3x3 position covariance north, east, down, m^2
    quality: int  # RTKLIB's Q: 1 fix, 2 float, 3 SBAS, 4 DGPS, 5 single, 6 PPP
    num_sv: int
    age_s: float = 0.0  # age of the differential corrections
    ratio: float = 0.0  # the ambiguity validation ratio
