"""What the clock observes, as named inputs: PPS edges, time announcements, fix epochs, IMU samples.

The clock knows nothing of topics or record layouts: the record layer (:mod:`logger.recording.records`) turns a
recorded or live record into one of these calls, so the same clock runs in the daemon and over a recorded drive.
All times are the board's monotonic ns, at which the input was seen, unless a field says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class TimeAnnouncement:
    """The receiver's word on the GNSS time of its next pulse (UBX TIM-TP), some hundreds of ms before it."""

    week: int  # GPS week of the next edge
    tow_ms: int  # time of week of the next edge, ms
    tow_sub_ms: float  # sub-millisecond part, ms
    qerr_ps: int  # the pulse comes this much early of the instant announced (quantisation error), ps
    utc: bool  # True: the pulse is aligned to UTC; False: to GNSS (GPS) time, which needs the leap seconds
    late_read: bool = False  # read together with a later second's messages: when it arrived is not known


@dataclass(frozen=True, slots=True)
class FixEpoch:
    """The epoch of a navigation solution, as far as time goes: it arrives after the pulse of its second."""

    gnss_time_ns: int  # the epoch, Unix ns UTC (only solutions whose time is valid are epochs)
    itow_ms: int | None  # GPS time of week of the epoch, ms (UBX receivers): gives GPS-UTC with gnss_time_ns
    late_read: bool = False  # read together with a later second's messages: when it arrived is not known
    # The epoch is 23:59:60 UTC, an inserted leap second: gnss_time_ns is POSIX's value for it (the 00:00:00 after
    # it), and the clock learns from it that the next second repeats that Unix second.
    leap_second: bool = False
    # When its first message came (board monotonic ns), where that was before the read it was completed in: an
    # epoch that takes long on the line (9600 baud, u-blox's factory NMEA: over a second) ends after the next
    # pulse, so the edge it follows is the one before its beginning. None: it came in one read.
    opened_ns: int | None = None
    # The receiver said its leap-second count is not yet the broadcast one (UBX NAV-TIMEGPS leapSValid clear: a cold
    # start's first 12.5 min at most, until the almanac page with the UTC parameters came): its UTC, and the GPS-UTC
    # the clock learns from it, may be its firmware's default, whole seconds off. The clock's bound says so.
    # None: the receiver did not say (this epoch lacked NAV-TIMEGPS, or an NMEA receiver): the last word stands.
    leap_unknown: bool | None = None
