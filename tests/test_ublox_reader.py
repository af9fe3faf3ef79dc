"""The u-blox reader: framing, decoding into epochs, and the serial driver on a pty."""

from __future__ import annotations

import calendar
import math
import os
import threading
import time
from pathlib import Path

import pytest
from extras import given, settings, st
from pynmeagps.nmeahelpers import calc_checksum
from pyubx2 import GET, UBXMessage

from sensors.errors import BusError, DeviceNotFound
from sensors.geodesy import ecef_to_geodetic, ecef_velocity_to_ned, gps_to_unix_ns
from sensors.sim.pty import PtyPort
from sensors.ublox import (
    GnssDecoder,
    GnssFix,
    GnssRead,
    GnssReceiver,
    GnssTime,
    TimePulse,
)
from sensors.ublox_frames import (
    KIND_NMEA,
    KIND_RTCM3,
    KIND_UBX,
    UBX_MAX_PAYLOAD,
    UbxNmeaFramer,
    crc24q,
)

NS = 1_000_000_000
WGS84_A = 6_378_137.0
WGS84_E2 = (1 / 298.257223563) * (2 - 1 / 298.257223563)


def nmea(body: str) -> bytes:
    """A sentence with its checksum and CR LF, from the text between '$' and '*'."""
    return f"${body}*{calc_checksum(body)}\r\n".encode()


def rtcm3(payload: bytes) -> bytes:
    head = bytes((0xD3, len(payload) >> 8, len(payload) & 0xFF)) + payload
    return head + crc24q(head).to_bytes(3, "big")


def nav_pvt(itow: int = 345_600_250, **fields: object) -> bytes:
    values: dict[str, object] = dict(
        iTOW=itow, year=2024, month=3, day=5, hour=0, min=0, second=0, validDate=1, validTime=1,
        fullyResolved=1, tAcc=25, nano=250_000_000, fixType=3, gnssFixOk=1, numSV=14,
        lon=9.1234567, lat=48.7654321, height=312_345, hMSL=264_321, hAcc=1500, vAcc=2300,
        velN=1234, velE=-567, velD=89, gSpeed=1358, headMot=335.5, sAcc=120, headAcc=2.5, pDOP=1.37,
    )
    values.update(fields)
    return UBXMessage("NAV", "NAV-PVT", GET, **values).serialize()


def tim_tp(**fields: object) -> bytes:
    values: dict[str, object] = dict(
        towMS=345_601_000, towSubMS=0.25, qErr=-1234, week=2304, timeBase=0, utc=1, raim=2,
        qErrInvalid=0, timeRefGnss=0, utcStandard=3,
    )
    values.update(fields)
    return UBXMessage("TIM", "TIM-TP", GET, **values).serialize()


def nav_eoe(itow: int) -> bytes:
    return UBXMessage("NAV", "NAV-EOE", GET, iTOW=itow).serialize()


def mixed_stream() -> tuple[bytes, list[str]]:
    parts = [
        (nav_pvt(), KIND_UBX),
        (nmea("GPGGA,000000.25,4845.9259,N,00907.4074,E,1,14,0.9,264.3,M,48.0,M,,"), KIND_NMEA),
        (rtcm3(bytes(range(40))), KIND_RTCM3),
        (tim_tp(), KIND_UBX),
        (nmea("GPTXT,01,01,02,ANTSTATUS=OK"), KIND_NMEA),
        (nav_eoe(345_600_250), KIND_UBX),
    ]
    return b"".join(p for p, _ in parts), [k for _, k in parts]


def geodetic_to_ecef(lat: float, lon: float, h: float) -> tuple[float, float, float]:
    n = WGS84_A / math.sqrt(1 - WGS84_E2 * math.sin(lat) ** 2)
    return (
        (n + h) * math.cos(lat) * math.cos(lon),
        (n + h) * math.cos(lat) * math.sin(lon),
        (n * (1 - WGS84_E2) + h) * math.sin(lat),
    )


# ---------------------------------------------------------------------------------------------------
# Framing


def test_crc24q_check_value() -> None:
    assert crc24q(b"123456789") == 0xCDE703  # the catalogued check value of CRC-24/LTE-A (= 24Q)


def test_framing_one_byte_at_a_time_gives_the_same_frames() -> None:
    stream, kinds = mixed_stream()
    framer = UbxNmeaFramer()
    frames = [f for byte in stream for f in framer.feed(bytes([byte]))]
    assert [f.kind for f in frames] == kinds
    assert b"".join(f.raw for f in frames) == stream
    assert framer.frames_ok == 6 and framer.garbage_bytes == 0 and framer.bad_checksum == 0
    assert frames[0].message.identity == "NAV-PVT"
    assert frames[1].message.msgID == "GGA"
    assert frames[2].message is None  # RTCM3 is framed, not decoded


def test_garbage_between_frames_is_counted_and_skipped() -> None:
    stream, kinds = mixed_stream()
    junk = [b"\x00\xff\x13", b"\xb5\x00", b"$$\x01", b"\xd3\xff\xff", b"noise\r\n", b"\xb5"]
    pieces = [stream[: len(nav_pvt())]]  # start with a whole frame, then junk between the others
    framer = UbxNmeaFramer()
    frames = framer.feed(pieces[0])
    rest = stream[len(pieces[0]) :]
    for j in junk[:-1]:
        frames += framer.feed(j)
    frames += framer.feed(rest) + framer.feed(junk[-1]) + framer.finish()
    assert [f.kind for f in frames] == kinds
    assert framer.garbage_bytes == sum(map(len, junk))


def test_bad_checksum_is_counted_and_the_next_frame_survives() -> None:
    bad_ubx = bytearray(nav_pvt())
    bad_ubx[20] ^= 0x40
    bad_nmea = bytearray(nmea("GPGGA,000001.00,4845.9259,N,00907.4074,E,1,14,0.9,264.3,M,48.0,M,,"))
    bad_nmea[10] = ord("9")
    bad_rtcm = bytearray(rtcm3(b"\x3e\xd0" + bytes(20)))
    bad_rtcm[5] ^= 1
    good = tim_tp()
    framer = UbxNmeaFramer()
    frames = framer.feed(bytes(bad_ubx) + bytes(bad_nmea) + bytes(bad_rtcm) + good)
    assert [f.raw for f in frames] == [good]
    assert framer.bad_checksum == 3
    assert framer.garbage_bytes == len(bad_ubx) + len(bad_nmea) + len(bad_rtcm)


def test_truncated_frame_waits_then_counts_as_garbage_at_the_end() -> None:
    pvt = nav_pvt()
    framer = UbxNmeaFramer()
    assert framer.feed(pvt[:50]) == []
    assert framer.pending == 50 and framer.garbage_bytes == 0  # waits for the rest
    assert [f.raw for f in framer.feed(pvt[50:] + pvt[:30])] == [pvt]
    assert framer.finish() == []
    assert framer.garbage_bytes == 30 and framer.pending == 0


def test_huge_bogus_length_does_not_stall_the_stream() -> None:
    good = tim_tp()
    framer = UbxNmeaFramer()
    header = b"\xb5\x62\x01\x07" + (UBX_MAX_PAYLOAD + 1).to_bytes(2, "little")
    assert [f.raw for f in framer.feed(header + good)] == [good]  # no waiting for 8 KiB
    assert framer.garbage_bytes == len(header)


def test_plausible_bogus_length_waits_at_most_its_bound() -> None:
    good = tim_tp()
    framer = UbxNmeaFramer()
    header = b"\xb5\x62\x01\x07" + (4000).to_bytes(2, "little")  # believable, but a lie
    assert framer.feed(header + good * 3) == []
    # once the promised length is there the checksum fails and the frames inside are found
    frames = framer.feed(bytes(4000))
    assert [f.raw for f in frames] == [good] * 3
    assert framer.bad_checksum == 1 and framer.pending == 0


def test_overlong_nmea_line_is_dropped_without_waiting_for_a_line_feed() -> None:
    good = nmea("GPTXT,01,01,02,OK")
    framer = UbxNmeaFramer()
    frames = framer.feed(b"$GP" + b"A" * 300 + good)
    assert [f.raw for f in frames] == [good]
    assert framer.garbage_bytes == 303


def test_sentence_cut_by_a_binary_frame_resyncs_on_the_frame() -> None:
    pvt = nav_pvt()
    framer = UbxNmeaFramer()
    frames = framer.feed(b"$GPGGA,0000" + pvt)
    assert [f.raw for f in frames] == [pvt]


def test_runt_message_with_a_good_checksum_is_rejected_not_zero_filled() -> None:
    body = b"\x01\x07\x03\x00\x01\x02\x03"  # NAV-PVT with a 3-byte payload
    a = b = 0
    for c in body:
        a = (a + c) & 0xFF
        b = (b + a) & 0xFF
    runt = b"\xb5\x62" + body + bytes((a, b))
    framer = UbxNmeaFramer()
    decoder = GnssDecoder()
    frames = framer.feed(runt + nav_pvt() + nav_eoe(345_600_250))
    assert framer.frames_ok == 3 and framer.bad_checksum == 0
    items = decoder.push_all(frames)
    assert decoder.rejected == 1
    assert [(i.source, i.lat_deg) for i in items] == [("NAV-PVT", pytest.approx(48.7654321))]


def test_frame_the_library_cannot_decode_is_counted_and_still_framed() -> None:
    body = b"\x02\x15\x10\x00" + bytes(11) + b"\x05" + bytes(4)  # RXM-RAWX claiming 5 measurements, none sent
    a = b = 0
    for c in body:
        a = (a + c) & 0xFF
        b = (b + a) & 0xFF
    raw = b"\xb5\x62" + body + bytes((a, b))
    framer = UbxNmeaFramer()
    frames = framer.feed(raw + tim_tp())
    assert [(f.raw, f.message is None) for f in frames] == [(raw, True), (tim_tp(), False)]
    assert framer.undecoded == 1 and framer.bad_checksum == 0


def test_sentence_with_a_garbled_time_is_rejected() -> None:
    decoder = GnssDecoder()
    framer = UbxNmeaFramer()
    good = nmea("GPGGA,120000.00,4404.1306,N,12118.8446,W,1,12,0.49,1129.9,M,-21.3,M,,")
    bad = nmea("GPGGA,12:00:01,4404.0000,N,12118.0000,W,1,12,0.49,9999.9,M,-21.3,M,,")
    decoder.push_all(framer.feed(good + bad))
    (fix,) = decoder.flush()
    assert fix.height_msl_m == 1129.9 and decoder.rejected == 1


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=300), max_size=30), st.booleans())
def test_arbitrary_bytes_never_raise_and_every_byte_is_accounted_for(chunks: list[bytes], salt: bool) -> None:
    if salt:  # make sync bytes and real frames likely, so the framer's deeper paths run
        chunks = [c + tim_tp()[: len(c) % 30] + b"\xb5\x62$\xd3" for c in chunks] + [nav_pvt()]
    framer = UbxNmeaFramer()
    decoder = GnssDecoder()
    frames = []
    for chunk in chunks:
        got = framer.feed(chunk)
        frames += got
        for frame in got:
            decoder.push(frame)
    frames += framer.finish()
    decoder.flush()
    total = sum(map(len, chunks))
    assert sum(len(f.raw) for f in frames) + framer.garbage_bytes == total
    assert framer.pending == 0 and framer.frames_ok == len(frames)


# ---------------------------------------------------------------------------------------------------
# Decoding


def decode(stream: bytes) -> list[object]:
    framer = UbxNmeaFramer()
    decoder = GnssDecoder()
    return decoder.push_all(framer.feed(stream) + framer.finish()) + decoder.flush()


def test_tim_tp_decoded_field_by_field() -> None:
    (tp,) = decode(tim_tp())
    assert tp == TimePulse(
        tow_ms=345_601_000, tow_sub_ms=0.25, week=2304, qerr_ps=-1234, qerr_valid=True,
        time_base="gnss", utc_available=True, gnss="gps",
    )
    assert tp.tow_ns == 345_601_000 * 1_000_000 + 250_000
    (utc,) = decode(tim_tp(timeBase=1, qErrInvalid=1, towSubMS=0.0))
    assert utc.time_base == "utc" and utc.gnss is None and not utc.qerr_valid


def test_nav_pvt_decoded_field_by_field() -> None:
    items = decode(nav_pvt() + nav_eoe(345_600_250))
    (fix,) = items
    assert isinstance(fix, GnssFix)
    assert fix.source == "NAV-PVT" and fix.itow_ms == 345_600_250
    assert fix.time_utc_ns == calendar.timegm((2024, 3, 5, 0, 0, 0)) * NS + 250_000_000
    assert fix.time_valid and fix.fix_mode == 3 and fix.fix_ok
    assert fix.lat_deg == pytest.approx(48.7654321, abs=1e-12)
    assert fix.lon_deg == pytest.approx(9.1234567, abs=1e-12)
    assert fix.height_hae_m == 312.345 and fix.height_msl_m == 264.321
    assert fix.vel_ned_mps == (1.234, -0.567, 0.089)
    assert (fix.h_acc_m, fix.v_acc_m, fix.s_acc_mps) == (1.5, 2.3, 0.12)
    assert fix.num_sv == 14 and fix.pdop == pytest.approx(1.37)
    assert fix.week is None  # NAV-PVT carries no week and no leap seconds were heard yet


def test_pvt_flags_drive_mode_validity_and_position() -> None:
    (no_fix,) = decode(nav_pvt(fixType=0, gnssFixOk=0) + nav_eoe(345_600_250))
    assert no_fix.fix_mode == 1 and not no_fix.fix_ok and no_fix.lat_deg is None and no_fix.vel_ned_mps is None
    (dr,) = decode(nav_pvt(fixType=1) + nav_eoe(345_600_250))
    assert dr.fix_mode == 2  # dead reckoning only counts as 2D, as in gpsd
    (unresolved,) = decode(nav_pvt(fullyResolved=0) + nav_eoe(345_600_250))
    assert unresolved.time_utc_ns is not None and not unresolved.time_valid
    (no_date,) = decode(nav_pvt(validDate=0) + nav_eoe(345_600_250))
    assert no_date.time_utc_ns is None and not no_date.time_valid
    # u-blox 9: a 3D fix type whose longitude, latitude and heights are flagged invalid is no fix to use (it was
    # recorded as a 3D fix at 0 N 0 E); its velocity stands.
    (no_llh,) = decode(nav_pvt(invalidLlh=1) + nav_eoe(345_600_250))
    assert no_llh.fix_mode == 3 and not no_llh.fix_ok and no_llh.lat_deg is None and no_llh.height_hae_m is None
    assert no_llh.vel_ned_mps is not None
    from logger.recording.records import fix_name, location_fix
    assert fix_name(location_fix(no_llh, 0)) == "no fix"


def test_epoch_is_reported_at_the_learned_end_of_its_burst() -> None:
    decoder = GnssDecoder()
    framer = UbxNmeaFramer()

    def push(raw: bytes) -> list[object]:
        return decoder.push_all(framer.feed(raw))

    dop = lambda itow: UBXMessage("NAV", "NAV-DOP", GET, iTOW=itow, pDOP=1.2).serialize()  # noqa: E731
    assert push(nav_pvt(1000)) == [] and push(dop(1000)) == []  # first burst: end not known yet
    first = push(nav_pvt(2000))  # the next epoch starts: the first one is over
    assert [f.itow_ms for f in first] == [1000]
    second = push(dop(2000))  # NAV-DOP closed the last burst, so it closes this one at once
    assert [f.itow_ms for f in second] == [2000]
    assert decoder.flush() == []


def test_old_receiver_messages_are_combined_per_epoch() -> None:
    lat, lon, h = math.radians(44.0688112), math.radians(-121.31409), 1109.961
    x, y, z = geodetic_to_ecef(lat, lon, h)
    itow, week = 345_600_000, 2304
    vx, vy, vz = 1.0, -2.0, 0.5
    sol = UBXMessage(
        "NAV", "NAV-SOL", GET, iTOW=itow, fTOW=-1234, week=week, gpsFix=3, gpsfixOK=1, wknSet=1, towSet=1,
        ecefX=round(x * 100), ecefY=round(y * 100), ecefZ=round(z * 100), pAcc=250,
        ecefVX=round(vx * 100), ecefVY=round(vy * 100), ecefVZ=round(vz * 100), sAcc=40, pDOP=1.5, numSV=9,
    ).serialize()
    posllh = UBXMessage(
        "NAV", "NAV-POSLLH", GET, iTOW=itow, lon=-121.31409, lat=44.0688112, height=1_109_961,
        hMSL=1_131_311, hAcc=700, vAcc=1100,
    ).serialize()
    timegps = UBXMessage(
        "NAV", "NAV-TIMEGPS", GET, iTOW=itow, fTOW=-1234, week=week, leapS=18, towValid=1, weekValid=1,
        leapSValid=1, tAcc=20,
    ).serialize()
    items = decode(sol + posllh + timegps)
    times = [i for i in items if isinstance(i, GnssTime)]
    (fix,) = [i for i in items if isinstance(i, GnssFix)]
    assert times[0].leap_s == 18 and times[0].week == week and times[0].utc_valid
    expected_utc = gps_to_unix_ns(week, itow * 1_000_000 - 1234, 18)
    assert times[0].time_utc_ns == expected_utc
    assert fix.source == "NAV-SOL" and fix.week == week and fix.time_utc_ns == expected_utc and fix.time_valid
    # the position comes from NAV-POSLLH (it has MSL), the velocity from the ECEF one of NAV-SOL
    assert (fix.lat_deg, fix.lon_deg, fix.height_msl_m) == (44.0688112, -121.31409, 1131.311)
    assert fix.vel_ned_mps == pytest.approx(ecef_velocity_to_ned(vx, vy, vz, lat, lon), abs=1e-3)
    assert fix.num_sv == 9 and fix.pdop == 1.5 and fix.h_acc_m == 0.7


def test_ecef_to_geodetic_round_trip_below_a_millimetre() -> None:
    for lat_deg, lon_deg, h in ((44.07, -121.31, 1110.0), (-34.9, 138.6, 25.0), (89.9, 10.0, 3000.0),
                                (0.0, 0.0, -50.0), (-89.99, -170.0, 12.0)):
        lat, lon = math.radians(lat_deg), math.radians(lon_deg)
        got = ecef_to_geodetic(*geodetic_to_ecef(lat, lon, h))
        assert got[0] == pytest.approx(lat, abs=1e-11) and got[1] == pytest.approx(lon, abs=1e-11)
        assert got[2] == pytest.approx(h, abs=1e-4)


def test_nmea_sentences_are_combined_per_epoch() -> None:
    stream = b"".join(nmea(s) for s in (
        "GNRMC,235959.00,A,4404.1306024,N,12118.8446777,W,1.944,90.0,231221,,,D,V",
        "GNVTG,90.0,T,,M,1.944,N,3.600,K,D",
        "GNGGA,235959.00,4404.1306024,N,12118.8446777,W,2,12,0.49,1129.913,M,-21.350,M,,0278",
        "GNGSA,A,3,21,30,46,13,17,51,14,44,15,19,07,01,0.98,0.49,0.84,1",
        "GNGST,235959.00,32,0.19,0.12,97,0.030,0.040,0.088",
        "GNRMC,000000.00,A,4404.1306000,N,12118.8446700,W,0.000,,241221,,,D,V",
        "GNGGA,000000.00,4404.1306000,N,12118.8446700,W,2,12,0.49,1129.900,M,-21.350,M,,0278",
    ))
    first, second = decode(stream)
    assert first.source == "NMEA" and first.itow_ms is None
    assert first.time_utc_ns == calendar.timegm((2021, 12, 23, 23, 59, 59)) * NS
    assert first.fix_mode == 3 and first.fix_ok and first.time_valid
    assert first.lat_deg == pytest.approx(44 + 4.1306024 / 60, abs=1e-9)
    assert first.lon_deg == pytest.approx(-(121 + 18.8446777 / 60), abs=1e-9)
    assert first.height_msl_m == 1129.913 and first.height_hae_m == pytest.approx(1129.913 - 21.350)
    north, east, down = first.vel_ned_mps
    assert north == pytest.approx(0.0, abs=1e-9) and east == pytest.approx(1.0, abs=1e-3) and math.isnan(down)
    assert first.h_acc_m == pytest.approx(0.05) and first.v_acc_m == 0.088
    assert first.num_sv == 12 and first.pdop == 0.98
    assert (first.hdop, first.vdop) == (0.49, 0.84)  # GSA's own
    assert second.time_utc_ns == calendar.timegm((2021, 12, 24, 0, 0, 0)) * NS  # the date moved on
    assert (second.pdop, second.hdop, second.vdop) == (None, 0.49, None)  # GGA's HDOP: the only DOP without GSA


def test_gns_instead_of_gga_gives_a_3d_fix_with_its_height() -> None:
    """An NMEA 4 receiver sending RMC and GNS (no GGA, no GSA): GNS carries the height, so the fix is 3D (it was
    recorded as 2D with a height, which `logger export` then dropped point by point)."""
    first, _ = decode(b"".join(nmea(body) for body in (
        "GNRMC,120000.00,A,4807.03800,N,01131.00000,E,0.010,,301126,,,A,V",
        "GNGNS,120000.00,4807.03800,N,01131.00000,E,AAN,10,0.9,545.4,46.9,,,V",
        "GNRMC,120001.00,A,4807.03800,N,01131.00000,E,0.010,,301126,,,A,V",
        "GNGNS,120001.00,4807.03800,N,01131.00000,E,AAN,10,0.9,545.4,46.9,,,V")))
    assert first.fix_mode == 3 and first.fix_ok
    assert first.height_msl_m == 545.4 and first.height_hae_m == pytest.approx(592.3)


def test_a_high_precision_position_beside_nmea_leaves_the_fix_to_the_nmea() -> None:
    """An F9P set up by its owner for RTK: NMEA GGA/RMC/GSA plus UBX NAV-HPPOSLLH, no NAV-PVT or NAV-STATUS. The
    UBX position has no fix type and no time: it made the decoder ignore the NMEA, and every record said "no fix"
    without a time (the filter refused all, the clock got no epoch). The NMEA gives the fix."""
    stream = b""
    for k in range(4):
        hhmmss = f"1200{k:02d}.00"
        stream += (nmea(f"GNRMC,{hhmmss},A,4807.03800,N,01131.00000,E,0.010,,010326,,,R,V")
                   + nmea(f"GNGGA,{hhmmss},4807.03800,N,01131.00000,E,4,24,0.6,545.4,M,46.9,M,1.0,0000")
                   + nmea("GNGSA,A,3,01,02,03,04,05,06,07,08,,,,,1.1,0.6,0.9,1")
                   + UBXMessage("NAV", "NAV-HPPOSLLH", GET, version=0, iTOW=388_800_000 + 1000 * k, lon=11.5166666,
                                lat=48.1173, height=592_300, hMSL=545_400, hAcc=14, vAcc=20).serialize())
    fixes = [f for f in decode(stream) if isinstance(f, GnssFix)]
    assert len(fixes) == 4
    assert all(f.source == "NMEA" and f.fix_mode == 3 and f.fix_ok and f.time_valid for f in fixes)


def test_an_old_receivers_position_and_status_take_over_from_its_nmea_at_once() -> None:
    """A u-blox 6's NAV-POSLLH and NAV-STATUS beside its NMEA: the UBX solution from the moment both are in, as
    before (taking over only once its first epoch ended gave an NMEA epoch twice, out of order)."""
    stream = b""
    for k in range(4):
        itow = 345_600_000 + 1000 * k
        stream += nmea(f"GPRMC,00000{k}.00,A,4845.9259,N,00907.4074,E,0.0,,010124,,,A")
        stream += nmea(f"GPGGA,00000{k}.00,4845.9259,N,00907.4074,E,1,14,0.9,264.3,M,48.0,M,,")
        stream += UBXMessage("NAV", "NAV-POSLLH", GET, iTOW=itow, lon=9.12, lat=48.76, height=300_000,
                             hMSL=252_000, hAcc=700, vAcc=1100).serialize()
        stream += UBXMessage("NAV", "NAV-STATUS", GET, iTOW=itow, gpsFix=3, gpsFixOk=1).serialize()
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    fixes = [i for frame in framer.feed(stream) for i in decoder.push(frame) if isinstance(i, GnssFix)]
    assert [f.source for f in fixes] == ["NMEA", "NAV-POSLLH", "NAV-POSLLH", "NAV-POSLLH", "NAV-POSLLH"]
    assert [f.itow_ms for f in fixes[1:]] == [345_600_000 + 1000 * k for k in range(4)]


def test_nav_dop_gives_its_horizontal_and_vertical_dops() -> None:
    dop = UBXMessage("NAV", "NAV-DOP", GET, iTOW=345_600_250, pDOP=1.9, hDOP=1.1, vDOP=1.55).serialize()
    (fix,) = [i for i in decode(nav_pvt() + dop + nav_eoe(345_600_250)) if isinstance(i, GnssFix)]
    assert (fix.pdop, fix.hdop, fix.vdop) == (1.37, 1.1, 1.55)  # NAV-PVT's PDOP, NAV-DOP's split


def test_ubx_solutions_take_over_from_nmea() -> None:
    gga = nmea("GPGGA,000000.25,4845.9259,N,00907.4074,E,1,14,0.9,264.3,M,48.0,M,,")
    items = decode(gga + nav_pvt() + gga + nav_eoe(345_600_250))
    assert [i.source for i in items if isinstance(i, GnssFix)] == ["NMEA", "NAV-PVT"]


def test_receiver_stops_parsing_nmea_once_ubx_solutions_arrive() -> None:
    """NMEA sentences are still framed and kept as raw bytes, but not parsed once the decoder takes UBX
    solutions, and what comes out is what a decoder given every parsed frame gives."""
    gga = nmea("GPGGA,000000.25,4845.9259,N,00907.4074,E,1,14,0.9,264.3,M,48.0,M,,")
    chunks = [gga, nav_pvt(), gga + nav_eoe(345_600_250), gga + nav_pvt(345_601_250) + nav_eoe(345_601_250)]
    with PtyPort() as device:
        receiver = GnssReceiver.open(device.path, 115200)
        try:
            frames_nmea: list[object] = []
            feed = receiver.framer.feed

            def spy(data: bytes) -> list[object]:
                frames = feed(data)
                frames_nmea.extend(f.message for f in frames if f.kind == KIND_NMEA)
                return frames

            receiver.framer.feed = spy  # type: ignore[method-assign]
            items: list[object] = []
            for chunk in chunks:  # one read per chunk: the switch happens between reads
                device.write(chunk)
                got = b""
                for _ in range(200):
                    r = receiver.read(0.05)
                    got += r.raw
                    items += r.items
                    if len(got) >= len(chunk):
                        break
        finally:
            receiver.close()
    assert frames_nmea[0] is not None and frames_nmea[0].msgID == "GGA"  # before any UBX solution: parsed
    assert frames_nmea[1:] == [None, None]  # after: framed, checked, not parsed
    assert receiver.framer.undecoded == 0 and receiver.framer.frames_ok == 7
    assert [(type(i).__name__, i.source) for i in items] == [(type(i).__name__, i.source) for i in
                                                             decode(b"".join(chunks))]


def test_a_read_that_settles_takes_the_epochs_burst_at_once() -> None:
    """The port hands over an epoch's messages as the line delivers them. Without a settle a read returns the
    first message alone (one wake-up per message); with one, the caller's wait runs after the first byte and the
    read takes what came meanwhile: the whole epoch, decoded together, every byte in the raw log."""
    gga = nmea("GPGGA,000000.25,4845.9259,N,00907.4074,E,1,14,0.9,264.3,M,48.0,M,,")
    first, rest = nav_pvt(), gga + nav_eoe(345_600_250)
    with PtyPort() as device:
        receiver = GnssReceiver.open(device.path, 115200)
        try:
            device.write(first)
            alone = receiver.read(5.0)
            while len(alone.raw) < len(first):  # the pty may hand the first message over in pieces
                more = receiver.read(5.0)
                alone = GnssRead(alone.raw + more.raw, alone.items + more.items)
            assert alone.raw == first  # nothing else was on the line

            calls = []

            def settle() -> None:  # the line delivers the rest of the burst while the reader waits
                calls.append(1)
                device.write(rest)
                deadline = time.monotonic() + 10.0
                while receiver.port.in_waiting < len(first) - 1 + len(rest) and time.monotonic() < deadline:
                    time.sleep(0.001)

            device.write(first)
            burst = receiver.read(5.0, settle)
        finally:
            receiver.close()
    assert calls == [1] and burst.raw == first + rest
    assert [type(i).__name__ for i in burst.items] == [type(i).__name__ for i in decode(first + rest)]


def test_the_gnss_thread_waits_out_an_epochs_line_time_but_never_half_a_fix_period() -> None:
    from logger.runtime.sources import BURST_SETTLE_MAX_S, EPOCH_BURST_BYTES, GnssSource
    from logger.runtime.timebase import TimeBase

    def settle(baud: int, meas_period_ms: int | None = None) -> float:
        source = GnssSource("/dev/null", baud, configure=False, tb=TimeBase(), meas_period_ms=meas_period_ms)
        return source.settle_s()

    assert settle(9600) == pytest.approx(EPOCH_BURST_BYTES * 10 / 9600)  # 0.33 s: the factory rate's epoch
    assert settle(115200) == pytest.approx(EPOCH_BURST_BYTES * 10 / 115200)  # 28 ms
    assert settle(4800) == BURST_SETTLE_MAX_S  # a slower line: never past the late-read span
    assert settle(115200, meas_period_ms=50) == pytest.approx(0.02)  # 20 Hz fixes: within the epoch


def test_time_messages_come_out_at_once() -> None:
    timeutc = UBXMessage(
        "NAV", "NAV-TIMEUTC", GET, iTOW=1000, tAcc=30, nano=-5, year=2024, month=3, day=5, hour=1,
        min=2, sec=3, validTOW=1, validWKN=1, validUTC=1,
    ).serialize()
    (item,) = decode(timeutc)
    assert isinstance(item, GnssTime) and item.source == "NAV-TIMEUTC" and item.utc_valid
    assert item.time_utc_ns == calendar.timegm((2024, 3, 5, 1, 2, 3)) * NS - 5


# ---------------------------------------------------------------------------------------------------
# The serial driver on a pty


def test_open_missing_port_is_device_not_found(tmp_path: os.PathLike[str]) -> None:
    with pytest.raises(DeviceNotFound, match="no serial port"):
        GnssReceiver.open(os.path.join(tmp_path, "ttyNONE"))


def test_serial_round_trip_vanish_and_come_back() -> None:
    stream, _ = mixed_stream()
    with PtyPort() as device:
        receiver = GnssReceiver.open(device.path, 115200)
        try:
            assert receiver.read(0.01).raw == b""  # silent receiver: an empty read, not an error
            device.write(b"\x00garbage" + stream)
            raw = b""
            items: list[object] = []
            for _ in range(200):  # the pty hands the bytes over in however many reads it likes
                got = receiver.read(0.05)
                raw += got.raw
                items += got.items
                if len(raw) >= len(stream) + 8:
                    break
            assert raw == b"\x00garbage" + stream  # every byte for the raw log, garbage included
            assert [type(i).__name__ for i in items] == ["TimePulse", "GnssFix"]
            assert receiver.framer.garbage_bytes == 8

            config = UBXMessage("CFG", "CFG-RATE", 1, measRate=200, navRate=1, timeRef=1).serialize()
            receiver.write(config)
            echoed = b""
            for _ in range(50):
                echoed += device.read(0.05)
                if len(echoed) >= len(config):
                    break
            assert echoed == config

            device.vanish()
            with pytest.raises(BusError, match="serial port lost") as lost:
                receiver.read(0.05)
            assert "\n" not in str(lost.value)
        finally:
            receiver.close()

        device.reappear()
        again = GnssReceiver.open(device.path, 115200)
        try:
            sender = threading.Timer(0.05, device.write, args=(tim_tp(),))
            sender.start()
            got = again.read(1.0)
            for _ in range(20):
                if got.items:
                    break
                more = again.read(0.05)
                got = type(got)(got.raw + more.raw, got.items + more.items)
            sender.join()
            assert [type(i).__name__ for i in got.items] == ["TimePulse"]
        finally:
            again.close()


def test_a_receiver_plugged_back_in_starts_its_raw_stream_over() -> None:
    """/gnss/raw's offset counts the bytes read since the port was opened: after the receiver was unplugged and
    plugged back in it went on counting, so `logger export --format ubx` saw no gap and joined the frame cut at
    the unplugging to the new bytes. It starts at 0 again, which the export notes as the port opened again."""
    from logger.exports.raw_stream import _gap
    from logger.recording.topics import GNSS_RAW
    from logger.runtime.sources import GnssSource
    from logger.runtime.timebase import host_timebase

    pvt = nav_pvt()
    records = []
    with PtyPort() as device:
        source = GnssSource(device.path, 115200, False, host_timebase())

        def pump(data: bytes) -> None:
            device.write(data)
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:
                got = [r for r in source.read() if r.topic == GNSS_RAW]
                records.extend(got)
                if got:
                    return

        source.open()
        pump(pvt)
        pump(pvt[:40])  # the unplugging cuts a frame in half
        device.vanish()
        with pytest.raises(BusError):
            source.read()
        source.close()
        device.reappear()
        source.open()
        pump(pvt)
        source.close()

    class Message:  # what the raw export reads of a drive's message
        def __init__(self, payload: dict[str, object]) -> None:
            self.msg, self.file, self.log_time = payload, "drive.mcap", 0

    assert [r.payload["offset"] for r in records] == [0, len(pvt), 0]
    gap = _gap(Message(records[1].payload), Message(records[2].payload), 0)
    assert gap is not None and gap.kind == "reopened"


def test_write_to_a_vanished_port_is_bus_error() -> None:
    with PtyPort() as device:
        receiver = GnssReceiver.open(device.path)
        device.vanish()
        with pytest.raises(BusError):
            for _ in range(50):  # the tty layer may buffer the first writes
                receiver.write(b"\xb5\x62\x06\x08\x00\x00\x0e\x30" * 64)
        receiver.close()


def test_an_epoch_read_in_pieces_says_when_its_first_message_came() -> None:
    """At 9600 baud u-blox's factory NMEA takes over a second of line an epoch, so the read that completes it
    comes after the next pulse: the record says when the epoch's first message came (``opened_mono_ns``: the time
    of the read it came in), which the clock pairs it by (tests/test_sync.py)."""
    from logger.recording.records import fix_epoch
    from logger.recording.topics import GNSS_FIX
    from logger.runtime.sources import GnssSource
    from logger.runtime.timebase import TimeBase

    def head(hhmmss: str) -> bytes:
        return (nmea(f"GPRMC,{hhmmss},A,4845.9259,N,00907.4074,E,0.5,45.0,061226,,,A")
                + nmea("GPVTG,45.0,T,,M,0.5,N,0.9,K,A")
                + nmea(f"GPGGA,{hhmmss},4845.9259,N,00907.4074,E,1,14,0.9,264.3,M,48.0,M,,"))

    def tail(hhmmss: str) -> bytes:
        return (nmea("GPGSA,A,3,01,02,03,04,05,06,,,,,,,1.5,0.9,1.2")
                + nmea(f"GPGLL,4845.9259,N,00907.4074,E,{hhmmss},A,A"))

    now = [10 * NS]
    with PtyPort() as device:
        source = GnssSource(device.path, 9600, configure=False, tb=TimeBase(lambda: now[0], 1e6))
        source.open()
        readings = []
        try:
            for at_s, data in ((10.0, head("120000.00") + tail("120000.00")),  # one read: GLL is learnt to end one
                               (11.0, head("120001.00")), (12.2, tail("120001.00"))):
                now[0] = round(at_s * NS)
                device.write(data)
                target = source.offset + len(data)
                while source.offset < target:
                    readings += source.read()
        finally:
            source.close()
    fixes = [(r.t_mono_ns, r.payload) for r in readings if r.topic == GNSS_FIX]
    assert [(t, f.get("opened_mono_ns")) for t, f in fixes] == [(11 * NS, 10 * NS), (12_200_000_000, 11 * NS)]
    epoch = fix_epoch(fixes[1][1])
    assert epoch is not None and epoch.opened_ns == 11 * NS and epoch.gnss_time_ns % (86_400 * NS) == 43_201 * NS


def test_one_gsa_per_constellation_after_the_learnt_end_does_not_date_the_next_epoch() -> None:
    """An NMEA 4.10/4.11 receiver ending each burst with a GSA per constellation (GSV, GLL off): the end is learnt as
    "GSA", so the burst ends at the first one, and the other two opened the next epoch's burst, which then said it
    began in the previous second's read (the clock paired it with the edge a second early: locked 1 s off behind a
    13 us bound). An epoch's start is its first timed sentence's read."""
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    fixes = []
    for k in range(5):
        hhmmss = f"1200{k:02d}.00"
        decoder.read_mark = k + 1  # each epoch in a read of its own
        data = b"".join(nmea(body) for body in (
            f"GNRMC,{hhmmss},A,4807.03800,N,01131.00000,E,0.010,,301126,,,A,V",
            f"GNGGA,{hhmmss},4807.03800,N,01131.00000,E,1,10,0.9,545.4,M,46.9,M,,",
            "GNGSA,A,3,01,02,03,04,,,,,,,,,1.5,0.9,1.2,1", "GNGSA,A,3,65,66,67,,,,,,,,,,1.5,0.9,1.2,2",
            "GNGSA,A,3,301,302,,,,,,,,,,,1.5,0.9,1.2,3"))
        fixes += [(k + 1, item) for item in decoder.push_all(framer.feed(data)) if isinstance(item, GnssFix)]
    # The first epoch ends when the next begins (its end is learnt then), the others at their first GSA.
    assert [(read, fix.time_utc_ns % (60 * NS) // NS) for read, fix in fixes] == [(2, 0), (2, 1), (3, 2), (4, 3),
                                                                                   (5, 4)]
    assert [fix.opened_mark for _, fix in fixes] == [1, 2, 3, 4, 5]  # the read its RMC came in
    assert all(fix.pdop == 1.5 and fix.fix_mode == 3 for _, fix in fixes)

    # The last two GSAs read apart from the rest, every epoch, even after a quiet line (a receiver that pauses there):
    # they begin the next burst's collection as a receiver's head would, but they are the sentence the bursts end
    # with, no head to date an epoch by (dated by them, every epoch from the fourth took the previous second's read).
    for paused in (False, True):
        framer, decoder = UbxNmeaFramer(), GnssDecoder()
        fixes = []
        for k in range(8):
            hhmmss = f"1200{k:02d}.00"
            reads = (nmea(f"GNRMC,{hhmmss},A,4807.03800,N,01131.00000,E,0.010,,301126,,,A,V")
                     + nmea(f"GNGGA,{hhmmss},4807.03800,N,01131.00000,E,1,10,0.9,545.4,M,46.9,M,,")
                     + nmea("GNGSA,A,3,01,02,03,04,,,,,,,,,1.5,0.9,1.2,1"),
                     nmea("GNGSA,A,3,65,66,67,,,,,,,,,,1.5,0.9,1.2,2")
                     + nmea("GNGSA,A,3,301,302,,,,,,,,,,,1.5,0.9,1.2,3"))
            for j, data in enumerate(reads):
                decoder.read_mark, decoder.read_quiet = 2 * k + j + 1, j == 0 or paused
                fixes += [f for f in decoder.push_all(framer.feed(data)) if isinstance(f, GnssFix)]
        assert [f.time_utc_ns // NS % 60 for f in fixes] == list(range(8))
        assert [f.opened_mark for f in fixes] == [2 * k + 1 for k in range(8)]  # the read its RMC came in


def test_a_gst_sent_once_a_second_at_5_hz_gives_every_fix_its_accuracies_and_ends_no_epoch_late() -> None:
    """GST (the receiver's accuracies) once a second, fixes at 5 Hz: after the first second every GST came after
    its epoch's learnt end and was dropped (the filter fell back on its DOP model for every fix), and the end
    flapped to and fro, each burst without GST ending only when the next began. Its accuracies stand for the next
    second's fixes, and the end stays."""
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    got = []
    for k in range(20):
        sec, frac = divmod(k * 20, 100)
        hhmmss = f"1200{sec:02d}.{frac:02d}"
        bodies = [f"GNRMC,{hhmmss},A,4807.03800,N,01131.00000,E,12.0,90.0,230324,,,A,V",
                  f"GNGGA,{hhmmss},4807.03800,N,01131.00000,E,1,14,0.8,545.4,M,46.9,M,,"]
        if frac == 0:
            bodies.append(f"GNGST,{hhmmss},1.0,1.5,1.0,45.0,1.2,1.3,2.5")
        decoder.read_mark = k + 1
        got += [(k + 1, f) for f in decoder.push_all(framer.feed(b"".join(nmea(b) for b in bodies)))
                if isinstance(f, GnssFix)]
    assert len(got) == 20
    assert all(fix.h_acc_m == pytest.approx(math.hypot(1.2, 1.3)) and fix.v_acc_m == 2.5 for _, fix in got)
    assert all(read == fix.opened_mark for read, fix in got[2:])  # each in its own read once the end is learnt

    # Across midnight too: 23:59:59.8 and 00:00:00.0 are 0.2 s apart.
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    stream = b""
    for hhmmss, date, gst in (("235959.00", "230324", True), ("235959.20", "230324", False),
                              ("235959.40", "230324", False), ("235959.60", "230324", False),
                              ("235959.80", "230324", False), ("000000.00", "240324", False),
                              ("000000.20", "240324", False)):
        stream += nmea(f"GNRMC,{hhmmss},A,4807.03800,N,01131.00000,E,12.0,90.0,{date},,,A,V")
        stream += nmea(f"GNGGA,{hhmmss},4807.03800,N,01131.00000,E,1,14,0.8,545.4,M,46.9,M,,")
        if gst:
            stream += nmea(f"GNGST,{hhmmss},1.0,1.5,1.0,45.0,1.2,1.3,2.5")
    fixes = [f for f in decoder.push_all(framer.feed(stream)) if isinstance(f, GnssFix)]
    # 00:00:00.00 is 1.0 s after the GST's epoch (held), 00:00:00.20 1.2 s (not)
    assert [f.h_acc_m is not None for f in fixes] == [True, True, True, True, True, True, False]


def test_one_lost_gsa_does_not_leave_every_later_epoch_with_the_previous_ones() -> None:
    """RMC, GGA, GSA at 1 Hz (u-blox with GSV, GLL, VTG off): one GSA lost to a bad checksum had the burst's end
    learnt at GGA for good, and every later epoch took the previous one's GSA: its DOPs a second behind, and the
    first fix after the receiver regained its fix recorded as none. The GSA after the end it is regularly part of
    puts the end back."""
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    fixes = []
    for k in range(12):
        hhmmss = f"1200{k:02d}.00"
        fixed = not 6 <= k < 9  # the receiver loses its fix at epoch 6, has it again at 9
        pos = "4807.03800,N,01131.00000,E" if fixed else ",,,"
        data = nmea(f"GPRMC,{hhmmss},{'A' if fixed else 'V'},{pos},0.1,,071226,,,{'A' if fixed else 'N'}")
        data += nmea(f"GPGGA,{hhmmss},{pos},{1 if fixed else 0},{10 if fixed else 0},0.9,"
                     f"{'545.4' if fixed else ''},M,{'46.9' if fixed else ''},M,,")
        gsa = nmea(f"GPGSA,A,{3 if fixed else 1},01,02,03,04,,,,,,,,,{1.0 + k / 10:.1f},0.9,1.2")
        if k == 3:
            gsa = gsa[:-5] + b"00\r\n"  # a bad checksum: refused
        decoder.read_mark = k + 1
        fixes += [f for f in decoder.push_all(framer.feed(data + gsa)) if isinstance(f, GnssFix)]
    epoch = {f.time_utc_ns // NS % 60: f for f in fixes}
    assert sorted(epoch) == list(range(12))
    for k in (5, 9, 10):  # from the second epoch after the loss on: its own GSA
        assert epoch[k].pdop == pytest.approx(1.0 + k / 10), k
    assert epoch[9].fix_mode == 3 and epoch[9].fix_ok and epoch[9].lat_deg is not None  # regained, recorded so
    assert all(epoch[k].fix_mode == 1 and not epoch[k].fix_ok for k in (6, 7, 8))


def test_a_lost_last_sentence_does_not_report_its_successor_twice() -> None:
    """RMC, VTG, GGA, GSA x4, GLL (u-blox M9N's order without GSV), the GLL of one epoch lost to a bad checksum: that
    burst ended when the next began, its end learnt at GSA; the next burst ended at its first GSA, and its other GSAs
    and its GLL made the same epoch again (a second record of it, the GLL's position alone, which the filter took as
    a second fix). They are that epoch's tail: each epoch once, the end back at GLL."""
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    fixes = []
    for k in range(10):
        hhmmss = f"1200{k:02d}.00"
        bodies = [f"GNRMC,{hhmmss},A,4807.03800,N,01131.00000,E,12.0,90.0,071226,,,A,V",
                  "GNVTG,90.0,T,,M,12.0,N,22.2,K,A",
                  f"GNGGA,{hhmmss},4807.03800,N,01131.00000,E,1,10,0.9,545.4,M,46.9,M,,",
                  *(f"GNGSA,A,3,0{i},02,03,04,,,,,,,,,1.5,0.9,1.2,{i}" for i in range(1, 5)),
                  f"GNGLL,4807.03800,N,01131.00000,E,{hhmmss},A,A"]
        data = b"".join(nmea(b) for b in bodies)
        if k == 4:
            data = data[:-5] + b"00\r\n"  # the GLL's checksum spoilt: refused
        decoder.read_mark, decoder.read_quiet = k + 1, True
        fixes += [f for f in decoder.push_all(framer.feed(data)) if isinstance(f, GnssFix)]
    epochs = [f.time_utc_ns // NS % 60 for f in fixes]
    assert epochs == list(range(10)) and decoder._nmea_ender == "GNGLL"
    assert all(f.opened_mark == k + 1 for k, f in enumerate(fixes))


@pytest.mark.parametrize("head", ["GPGSA", "GPVTG"])
def test_a_receiver_beginning_its_bursts_with_a_time_less_sentence_ends_each_epoch_at_its_own_last(head) -> None:
    """GSA (or VTG), RMC, GGA at 1 Hz, each burst read after a quiet line: the next epoch's GSA was taken into the
    first burst, learnt as every burst's end, and every fix came a read (a second) late with the next epoch's GSA (fix
    mode and DOPs) or VTG. A time-less sentence that began the burst after a quiet line, come again after one, begins
    the next; each epoch ends at its GGA with its own GSA, dated by its RMC's read. Whether the line was quiet not
    known (a replay of reads), as before."""
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    got = []
    for k in range(6):
        hhmmss = f"1200{k:02d}.00"
        lead = (f"GPGSA,A,3,01,02,03,04,,,,,,,,,{1.0 + k / 10:.1f},0.9,1.2" if head == "GPGSA"
                else f"GPVTG,90.0,T,,M,{10 + k:.1f},N,{(10 + k) * 1.852:.2f},K,A")
        decoder.read_mark, decoder.read_quiet = k + 1, True
        data = nmea(lead) + nmea(f"GPRMC,{hhmmss},A,4807.03800,N,01131.00000,E,{10 + k:.1f},90.0,071226,,,A")
        data += nmea(f"GPGGA,{hhmmss},4807.03800,N,01131.00000,E,1,10,0.9,545.4,M,46.9,M,,")
        got += [(k + 1, f) for f in decoder.push_all(framer.feed(data)) if isinstance(f, GnssFix)]
    # The first epoch ends when its successor's head comes (its end learnt then), every other at its own GGA.
    assert [(read, f.time_utc_ns // NS % 60) for read, f in got] == [(2, 0), (2, 1), (3, 2), (4, 3), (5, 4), (6, 5)]
    assert [f.opened_mark for _, f in got] == [1, 2, 3, 4, 5, 6]
    if head == "GPGSA":
        assert [f.pdop for _, f in got] == pytest.approx([1.0, 1.1, 1.2, 1.3, 1.4, 1.5])
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    for k in range(6):
        decoder.read_mark = k + 1
        decoder.push_all(framer.feed(nmea(f"GPGSA,A,3,01,02,03,04,,,,,,,,,{1.0 + k / 10:.1f},0.9,1.2")
                                     + nmea(f"GPRMC,1200{k:02d}.00,A,4807.03800,N,01131.00000,E,10.0,90.0,071226,,,A")))
    assert decoder._nmea_ender == "GPGSA"


@pytest.mark.parametrize("paused", [False, True])
def test_a_trailing_gsa_read_apart_from_its_burst_at_the_start_does_not_stay_a_head(paused) -> None:
    """RMC, GGA, GSA, the logger's first read holding only the tail of an epoch (its GSA) after a quiet line, and the
    next epoch's GSA read apart from its RMC and GGA (a read cut by a slow line: no quiet before it, every epoch its own
    GSA). Had the receiver paused before that GSA, it would look like a head come again after a quiet line, and the
    next epochs took the previous ones' GSA (six of them here); its later GSAs come with their epochs' timed ones,
    not after a quiet line: it is no head, and the end goes back to the GSA. Every epoch is dated by its RMC's read."""
    framer, decoder = UbxNmeaFramer(), GnssDecoder()

    def gsa(k: int) -> bytes:
        return nmea(f"GPGSA,A,3,01,02,03,04,,,,,,,,,{1.0 + k / 10:.1f},0.9,1.2")

    def timed(k: int) -> bytes:
        hhmmss = f"1200{k:02d}.00"
        return (nmea(f"GPRMC,{hhmmss},A,4807.03800,N,01131.00000,E,0.1,,071226,,,A")
                + nmea(f"GPGGA,{hhmmss},4807.03800,N,01131.00000,E,1,10,0.9,545.4,M,46.9,M,,"))

    reads = [gsa(-1), timed(0), gsa(0)] + [timed(k) + gsa(k) for k in range(1, 12)]
    got = []
    for mark, data in enumerate(reads, 1):
        decoder.read_mark, decoder.read_quiet = mark, mark != 3 or paused
        got += [f for f in decoder.push_all(framer.feed(data)) if isinstance(f, GnssFix)]
    got += [f for f in decoder.flush() if isinstance(f, GnssFix)]
    epoch = {f.time_utc_ns // NS % 60: f for f in got}
    assert sorted(epoch) == list(range(12))
    assert [epoch[k].opened_mark for k in range(12)] == [2] + [k + 3 for k in range(1, 12)]  # its RMC's read
    own = range(6, 12) if paused else range(12)
    assert all(epoch[k].pdop == pytest.approx(1.0 + k / 10) for k in own)


class _IdlePort:
    """A serial port at the bus: each chunk comes after the line was idle so long (on a clock the test owns)."""

    timeout = 0.0
    baudrate = 115_200

    def __init__(self, now: list[int], chunks: list[tuple[int, bytes]]) -> None:
        self.now, self.chunks, self.buf = now, chunks, b""

    @property
    def in_waiting(self) -> int:
        return len(self.buf)

    def read(self, n: int) -> bytes:
        if not self.buf and self.chunks:
            idle_ns, self.buf = self.chunks.pop(0)
            self.now[0] += idle_ns
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def close(self) -> None:
        pass


def test_the_receiver_says_whether_the_line_was_quiet_before_a_read() -> None:
    """A read begun after a quiet line is a burst's start: nothing waiting when the reader came, and its first byte
    that long after. Bytes already waiting (a reader back late, or a burst read in pieces), a byte soon after (a
    pause inside a burst), or one seen late by a reader slow to wake, with as much line time of bytes behind it, are
    not; without the caller's clock it is not known."""
    now = [0]
    gsa = nmea("GPGSA,A,3,01,02,03,04,,,,,,,,,1.5,0.9,1.2")
    port = _IdlePort(now, [(200_000_000, gsa), (0, gsa), (10_000_000, gsa), (60_000_000, gsa),
                           (60_000_000, gsa * 20)])  # 840 bytes: 73 ms of the line at 115200 baud
    receiver = GnssReceiver(port, "/dev/fake")
    quiet = []
    for waiting in (False, True, False, False, False):
        if waiting:
            port.buf = port.chunks.pop(0)[1]  # come in while the reader was away
        receiver.read(1.0, now_ns=lambda: now[0], quiet_ns=50_000_000)
        quiet.append(receiver.decoder.read_quiet)
    assert quiet == [True, False, False, True, False]
    # A wait that timed out (a second without bytes) and the first byte just after the next began: quiet all along.
    port.chunks = [(1_000_000_000, b""), (10_000_000, gsa)]
    receiver.read(1.0, now_ns=lambda: now[0], quiet_ns=50_000_000)
    receiver.read(1.0, now_ns=lambda: now[0], quiet_ns=50_000_000)
    assert receiver.decoder.read_quiet is True
    receiver = GnssReceiver(_IdlePort(now, [(200_000_000, gsa)]), "/dev/fake")
    receiver.read(1.0)
    assert receiver.decoder.read_quiet is None


@pytest.mark.parametrize("opened_in_tail", [False, True])
def test_a_real_receivers_time_less_tail_read_after_quiet_lines_dates_each_epoch_by_its_rmc(opened_in_tail) -> None:
    """A real u-blox ZED-F9P's NMEA (the GPSD project's capture: RMC, VTG, GGA, GSA x4, GSV..., its bursts ending
    with sentences without a time), each burst read after a quiet line; and the same with the port opened inside a
    burst, its first read the rest of an epoch from its first GSA on, taken as after a quiet line too (the worst
    case: a receiver pausing there): every epoch once, dated by its RMC's read, whatever the quiet reads say of
    heads."""
    from logger.cli.gnss_decode import strip_capture_comments

    capture = strip_capture_comments(
        (Path(__file__).parent / "data" / "gpsd-ublox" / "ublox-f9p-hpnmea.log").read_bytes())
    nmea_only = b"".join(f.raw for f in UbxNmeaFramer().feed(capture) if f.kind == KIND_NMEA)
    bursts = [b"$GNRMC" + part for part in nmea_only.split(b"$GNRMC")[1:]]
    assert len(bursts) >= 7 and all(b.count(b"GNGSA") == 4 for b in bursts)
    reads = bursts[1:]
    if opened_in_tail:
        reads = [bursts[0][bursts[0].index(b"$GNGSA"):], *reads]
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    got = []
    for mark, data in enumerate(reads, 1):
        decoder.read_mark, decoder.read_quiet = mark, True
        got += [f for f in decoder.push_all(framer.feed(data)) if isinstance(f, GnssFix)]
    got += [f for f in decoder.flush() if isinstance(f, GnssFix)]
    seconds = [f.time_utc_ns // NS for f in got]
    assert seconds == list(range(seconds[0], seconds[0] + len(bursts) - 1))  # each epoch of bursts[1:] once
    rmc_read = {s: k + 1 + opened_in_tail for k, s in enumerate(seconds)}
    assert all(f.opened_mark == rmc_read[f.time_utc_ns // NS] for f in got)


def test_a_head_after_a_quiet_line_is_not_trusted_with_the_date() -> None:
    """A receiver that pauses before its trailing GSA longer than the quiet share of its period, the port opened in
    the pause: the GSA comes first after a quiet line, as a head would, every epoch. Dated by it (a head that began the
    last bursts too), every epoch took the previous second's read: the clock locked a second off, 0 mislabels. An
    epoch is dated by its first timed sentence's read; the pause costs its epochs their own GSA, not a second. The
    same order without the opening in the pause keeps each epoch its own GSA."""
    for opened_in_pause in (True, False):
        framer, decoder = UbxNmeaFramer(), GnssDecoder()
        got = []
        mark = 0
        for k in range(-1 if opened_in_pause else 0, 8):
            hhmmss = f"1200{k:02d}.00"
            timed = (nmea(f"GNRMC,{hhmmss},A,4807.03800,N,01131.00000,E,12.0,90.0,071226,,,A,V")
                     + nmea(f"GNGGA,{hhmmss},4807.03800,N,01131.00000,E,1,10,0.9,545.4,M,46.9,M,,"))
            tail = nmea(f"GNGSA,A,3,01,02,03,04,,,,,,,,,{1.0 + k / 10:.1f},0.9,1.2,1")
            for data in ((tail,) if k < 0 else (timed, tail)):  # each after a quiet line
                mark += 1
                decoder.read_mark, decoder.read_quiet = mark, True
                got += [(mark, f) for f in decoder.push_all(framer.feed(data)) if isinstance(f, GnssFix)]
        epochs = {f.time_utc_ns // NS % 60: (read, f) for read, f in got}
        first = 2 if opened_in_pause else 1  # the read epoch 0's RMC came in
        assert all(f.opened_mark == first + 2 * k for k, (_, f) in epochs.items()), epochs
        if not opened_in_pause:
            assert all(f.pdop == pytest.approx(1.0 + k / 10) for k, (_, f) in epochs.items())


def test_a_real_receivers_nmea_ending_after_the_next_pulse_labels_the_pulse_before_it() -> None:
    """A real u-blox M9N's NMEA output as it came (the GPSD project's capture: RMC, VTG, GGA, GSA x4, GSV x12, GLL,
    GST, ZDA, GBS, about 1.5 kB an epoch), each epoch on the line from 0.3 s after its pulse to 1.2 s, read by the
    GNSS source in three reads (at 0.6, 0.9 and 1.2 s): every epoch completes after the next pulse. Its records,
    PPS edges at each pulse, through the clock: locked to the right second (paired by the read that completed
    it, every epoch took the next second's edge: a clock a second off)."""
    from logger.cli.gnss_decode import strip_capture_comments
    from logger.recording.records import clock_observer
    from logger.recording.topics import GNSS_FIX, PPS
    from logger.runtime.sources import GnssSource
    from logger.runtime.timebase import TimeBase
    from sync.clock import PpsClock

    capture = strip_capture_comments(
        (Path(__file__).parent / "data" / "gpsd-ublox" / "ublox-neo-m9n-nmea.log").read_bytes())
    epochs = [b"$GNRMC" + part for part in capture.split(b"$GNRMC")[1:]][:20]
    assert all(1000 < len(e) < 2000 for e in epochs)
    first_utc_s = calendar.timegm((2020, 7, 11, 22, 37, 45))  # the capture's first epoch, 223745.00 on 110720
    base = 100 * NS  # board time of the first epoch's pulse
    now = [base]
    clock = PpsClock(monotonic_ns=lambda: now[0], wall_ns=lambda: 0)
    observe = clock_observer(clock)
    records = []
    with PtyPort() as device:
        source = GnssSource(device.path, 9600, configure=False, tb=TimeBase(lambda: now[0], 1e6))
        source.open()
        try:
            for k, epoch in enumerate(epochs):
                now[0] = base + k * NS + 7_000  # the pulse of epoch k, its interrupt 7 us late
                observe[PPS]({"gnss_time_ns": None}, now[0])
                third = len(epoch) // 3
                for j, piece in enumerate((epoch[:third], epoch[third:2 * third], epoch[2 * third:])):
                    now[0] = base + k * NS + (600 + 300 * j) * 1_000_000
                    device.write(piece)
                    target = source.offset + len(piece)
                    while source.offset < target:
                        for r in source.read():
                            if r.topic == GNSS_FIX:
                                records.append((r.t_mono_ns, r.payload))
                                observe[GNSS_FIX](r.payload, r.t_mono_ns)
        finally:
            source.close()
    # Each epoch's fix completes at 1.2 s (the next epoch's RMC, or its own learnt end), opened at 0.6 s.
    assert len(records) >= 18
    for t, fix in records:
        k = round(fix["gnss_time_ns"] / NS - first_utc_s)
        assert t - (base + k * NS) >= NS and fix["opened_mono_ns"] == base + k * NS + 600_000_000, (k, t, fix)
    probe = base + 19 * NS + 500_000_000
    now[0] = probe
    stamp = clock.stamp(probe)
    assert stamp.state == "locked" and clock.counts["mislabels"] == 0
    assert abs(stamp.t_sync_ns - ((first_utc_s + 19) * NS + 500_000_000)) < 100_000, stamp


@pytest.mark.parametrize("flag", [0, 1])
def test_a_fix_says_when_the_receiver_has_no_broadcast_leap_count(flag: int) -> None:
    """NAV-PVT's validTime and fullyResolved are set on a cold start's firmware-default leap count too; the same
    epoch's NAV-TIMEGPS says whether the count is the broadcast one (leapSValid). The fix record carries
    `leap_unknown` while it is not (the clock widens its bound on it) and validates against its schema."""
    import jsonschema

    from logger.recording.records import fix_epoch, location_fix, stamped_record
    from logger.recording.topics import GNSS_FIX, TOPICS
    from sync.stamp import Stamp

    itow, week = 345_600_250, 2304
    timegps = UBXMessage("NAV", "NAV-TIMEGPS", GET, iTOW=itow, fTOW=0, week=week, leapS=17 + flag, towValid=1,
                         weekValid=1, leapSValid=flag, tAcc=20).serialize()
    (fix,) = [i for i in decode(nav_pvt(itow) + timegps) if isinstance(i, GnssFix)]
    assert fix.time_valid and fix.leap_known is bool(flag)
    record = location_fix(fix, 1_000)
    assert record.get("leap_unknown", False) is not bool(flag)
    jsonschema.validate(stamped_record(1_000, Stamp(2_000, "locked", 3, 0, 0), 0, record), TOPICS[GNSS_FIX].schema)
    epoch = fix_epoch(record)
    assert epoch is not None and epoch.leap_unknown is not bool(flag)
    (alone,) = [i for i in decode(nav_pvt(itow)) if isinstance(i, GnssFix)]
    assert alone.leap_known is None and "leap_unknown" not in location_fix(alone, 1_000)  # not said: nothing claimed
