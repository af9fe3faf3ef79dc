"""Serial NMEA epochs a review found lost or misread (captures in tests/data/gnss-review, written by hand as an
NMEA receiver sends them): the leap second 23:59:60, a GNS fix without GPS, a 3D fix whose GGA never came."""

from __future__ import annotations

import calendar
from pathlib import Path

from logger.cli.gnss_decode import decode_pieces, fix_to_tpv, strip_capture_comments
from logger.recording.records import fix_epoch, gnss_observation, location_fix
from sensors.ublox_decode import GnssFix

DATA = Path(__file__).resolve().parent / "data" / "gnss-review"
NS = 1_000_000_000
MIDNIGHT = calendar.timegm((2026, 1, 1, 0, 0, 0)) * NS  # the leap second of leap.nmea ends here


def fixes(name: str) -> list[GnssFix]:
    result = decode_pieces([strip_capture_comments((DATA / name).read_bytes())])
    return result.fixes


def test_the_leap_second_is_an_epoch_of_its_own_with_posix_time_and_a_flag() -> None:
    got = fixes("leap.nmea")
    rmc_times = [line.split(",")[1] for line in (DATA / "leap.nmea").read_text().splitlines()
                 if line.startswith("$GPRMC")]
    assert len(got) == len(rmc_times)  # every epoch a fix, 23:59:60 too
    at_midnight = [f for f in got if f.time_utc_ns == MIDNIGHT]
    assert [f.leap_second for f in at_midnight] == [True, False]  # 23:59:60, then 00:00:00: POSIX's one Unix second
    leap = at_midnight[0]
    assert (leap.fix_mode, leap.fix_ok, leap.time_valid, leap.lat_deg) == (3, True, True, 48.1175)
    assert fix_to_tpv(leap)["time"] == "2025-12-31T23:59:60.000Z"
    record = location_fix(leap, 0)
    assert record["leap_second"] is True and "leap_second" not in location_fix(at_midnight[1], 0)
    epoch = fix_epoch({**record, "t_sync_ns": 0})
    assert epoch is not None and epoch.leap_second and epoch.gnss_time_ns == MIDNIGHT


def test_a_gns_fix_without_gps_is_a_fix() -> None:
    # posMode NA / NNA: GLONASS alone; RMC status A, no GSA, no GGA. GNS's height makes it 3D, as GGA's does (gpsd
    # 3.22 says mode 2 with the position; as 2D every point was dropped from `logger export` and no height reached
    # the filter, though ten satellites gave one).
    got = fixes("gns_glonass_only.nmea")
    assert len(got) == 20
    assert all(f.fix_mode == 3 and f.fix_ok and f.lat_deg is not None and f.height_msl_m == 545.4 for f in got)


def test_a_3d_fix_without_its_gga_has_no_height_and_is_not_3d() -> None:
    got = fixes("badck.nmea")  # the GGA of 12:00:03 has a bad checksum; its RMC and GSA (3D) are intact
    lost = [f for f in got if f.height_hae_m is None]
    assert len(lost) == 1 and len(got) == 6
    fix = lost[0]
    assert (fix.fix_mode, fix.fix_ok, fix.height_msl_m, fix.lat_deg) == (2, True, None, 48.1173)
    record = location_fix(fix, 0)
    assert (record["altitude"], record["height_msl_m"], record["fix_mode"]) == (None, None, 2)
    obs = gnss_observation({**record, "t_sync_ns": 0, "t_mono_ns": 0})
    assert obs.height_m is None and obs.fix_mode == 2  # the filter takes no height of 0 m, and no 3D fix
