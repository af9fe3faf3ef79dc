"""gpsd as the GNSS source: its JSON over TCP, recorded as the same /gnss/fix and /pps records.

Everything talks to a real TCP server on 127.0.0.1 speaking gpsd's protocol (sensors/sim/gpsd.py), fed by hand,
by replaying gpsd 3.27's own decoding of real u-blox captures, or by the simulated receiver of a whole drive; and
to a real gpsd (Debian 12's 3.22) decoding real captures that gpsfake feeds it on a pty.
"""

from __future__ import annotations

import argparse
import bisect
import calendar
import collections
import contextlib
import datetime as dt
import itertools
import json
import math
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers_drive import drive_timeout
from mcap.reader import make_reader

from logger.cli.gnss_decode import decode_pieces, strip_capture_comments
from logger.cli.run import resolve_config
from logger.cli.status_view import render
from logger.config import ConfigError, parse
from logger.recording.drive import imu_samples
from logger.recording.records import location_fix
from logger.runtime import gpsd_sources
from logger.runtime.gpsd_sources import GpsdPpsSource, GpsdSource
from logger.runtime.sampler import Reading, Sampler, wait_until
from logger.runtime.status_socket import fetch
from logger.runtime.timebase import TimeBase, host_timebase
from sensors.errors import DeviceNotFound, NoData, SensorError
from sensors.gpsd import MAX_LINE_BYTES, GpsdClient, LineSplitter, watch_command
from sensors.gpsd_decode import LEAP_HOLD_NS, GpsdEpochs, fix_from_tpv, parse_time_ns, pps_report
from sensors.sim.clock import ManualClock
from sensors.sim.gpsd import SimGpsd
from sensors.ublox_decode import NO_COURSE_SPEED_MPS
from sync.clock import PpsClock
from sync.realtime import RealtimeMap
from sync.settings import SyncSettings

ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = ROOT / "tests" / "data" / "gpsd-ublox"  # the GPSD project's captures (BSD-2, COPYING there)
NS = 1_000_000_000
T0 = 1_700_000_000 * NS  # 2023-11-14T22:13:20Z



UBLOX_DEVICE = {"class": "DEVICE", "path": "/dev/ttyACM0", "driver": "u-blox", "cycle": 1.0}


def iso(unix_ns: int) -> str:
    ms = unix_ns // 1_000_000
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(ms // 1000)) + f".{ms % 1000:03d}Z"


def tpv(t_ns: int | None, device: str = "/dev/ttyACM0", **fields: Any) -> dict[str, Any]:
    obj: dict[str, Any] = {"class": "TPV", "device": device, "mode": 3, "lat": 37.5, "lon": 127.0,
                           "altHAE": 60.0, "altMSL": 35.0, "speed": 10.0, "track": 90.0}
    if t_ns is not None:
        obj["time"] = iso(t_ns)
    obj.update(fields)
    return obj


def sky(t_ns: int | None, used: int = 9, **fields: Any) -> dict[str, Any]:
    obj: dict[str, Any] = {"class": "SKY", "device": "/dev/ttyACM0", "pdop": 1.5, "hdop": 0.9, "vdop": 1.2,
                           "uSat": used, "nSat": used + 3}
    if t_ns is not None:
        obj["time"] = iso(t_ns)
    obj.update(fields)
    return obj


# ---------------------------------------------------------------------------------------------------------------
# Parsing


def test_gpsd_time_in_both_of_its_formats() -> None:
    assert parse_time_ns("2023-06-28T14:52:12.000Z") == calendar.timegm((2023, 6, 28, 14, 52, 12)) * NS
    assert parse_time_ns("2023-06-28T14:52:12.25Z") == calendar.timegm((2023, 6, 28, 14, 52, 12)) * NS + NS // 4
    assert parse_time_ns("2023-06-28T14:52:12Z") == calendar.timegm((2023, 6, 28, 14, 52, 12)) * NS
    assert parse_time_ns(1270517264.24) == 1270517264_240_000_000  # gpsd before protocol 3.10: Unix seconds
    for bad in ("2023-13-28T14:52:12.000Z", "2023-06-28 14:52:12", "", None, True, float("nan"), -5, [1]):
        assert parse_time_ns(bad) is None, bad


def test_a_tpv_fills_the_fields_of_a_serial_fix() -> None:
    t = T0 + 7 * NS
    # gpsd's u-blox driver passes the receiver's hAcc, vAcc and sAcc on as eph, epv and eps
    fix = fix_from_tpv(tpv(t, eph=1.5, epv=2.5, eps=0.3, climb=0.5), sky(t, used=11), receiver_figures=True)
    assert (fix.source, fix.fix_mode, fix.fix_ok, fix.time_utc_ns, fix.time_valid) == ("gpsd", 3, True, t, True)
    assert (fix.lat_deg, fix.lon_deg, fix.height_hae_m, fix.height_msl_m) == (37.5, 127.0, 60.0, 35.0)
    assert fix.vel_ned_mps is not None
    assert fix.vel_ned_mps[0] == pytest.approx(0.0, abs=1e-12) and fix.vel_ned_mps[1] == pytest.approx(10.0)
    # gpsd's climb without velD is its own difference of altitudes (repeated between epochs), no measurement: the
    # vertical velocity is missing, as NMEA's is; the receiver's velD is taken as it is.
    assert math.isnan(fix.vel_ned_mps[2])
    assert fix_from_tpv(tpv(t, climb=0.5, velN=0.1, velE=10.0, velD=-0.4), None).vel_ned_mps == (0.1, 10.0, -0.4)
    assert (fix.h_acc_m, fix.v_acc_m, fix.s_acc_mps, fix.num_sv, fix.pdop) == (1.5, 2.5, 0.3, 11, 1.5)
    assert (fix.hdop, fix.vdop) == (0.9, 1.2)
    assert (fix.itow_ms, fix.week) == (None, None)  # gpsd does not tell
    # velN/E/D win over speed and track; heights and accuracies from the alternatives gpsd may send instead
    fix = fix_from_tpv(tpv(t, velN=1.0, velE=2.0, velD=-0.25, altHAE=None, altMSL=None, alt=30.0, geoidSep=20.0,
                           epx=3.0, epy=4.0))
    assert fix.vel_ned_mps == (1.0, 2.0, -0.25) and fix.num_sv is None and fix.pdop is None and fix.hdop is None
    # epx and epy are gpsd's DOP model at 95 %, with any driver: no accuracy of the receiver's
    assert (fix.height_msl_m, fix.height_hae_m, fix.h_acc_m) == (30.0, 50.0, None)
    # no fix: gpsd's position (if any) is not one, and its time is not valid
    fix = fix_from_tpv(tpv(t, mode=1))
    assert (fix.fix_mode, fix.fix_ok, fix.time_valid, fix.lat_deg, fix.vel_ned_mps) == (1, False, False, None, None)
    assert fix_from_tpv({"class": "TPV", "mode": "3", "lat": "x"}).fix_mode == 0  # nonsense types: unknown


def test_a_pps_report_names_its_edge() -> None:
    msg = {"class": "PPS", "device": "/dev/ttyACM0", "real_sec": 1700000000, "real_nsec": 0,
           "clock_sec": 1700000000, "clock_nsec": 12345, "precision": -20, "qErr": -2400}
    rep = pps_report(msg)
    assert rep is not None and rep.clock_ns == T0 + 12345 and rep.real_ns == T0
    assert rep.edge_gnss_ns == T0 + 2  # the pulse left qErr early of its second: -(-2.4 ns), rounded
    assert pps_report({**msg, "class": "TOFF"}) is None
    assert pps_report({**msg, "clock_nsec": 2 * NS}) is None
    assert pps_report({**msg, "real_sec": "1700000000"}) is None


# ---------------------------------------------------------------------------------------------------------------
# Lines and epochs


def test_lines_are_split_across_reads_and_an_overlong_line_is_dropped_whole() -> None:
    s = LineSplitter(max_bytes=32)
    assert s.feed(b'{"a":1}\r\n{"b"') == [b'{"a":1}']
    assert s.feed(b':2}\n') == [b'{"b":2}']
    assert s.feed(b"x" * 20) == [] and s.feed(b"y" * 20) == []  # beyond 32 bytes without a newline
    assert s.feed(b"z" * 100) == []
    assert s.feed(b'zz\n{"c":3}\n') == [b'{"c":3}'] and s.oversized == 1
    assert len(s._buf) == 0
    assert s.feed(b"q" * 40 + b"\nok\n") == [b"ok"] and s.oversized == 2


def test_watch_request_fits_gpsd_and_names_the_device_when_it_can() -> None:
    plain = watch_command()
    assert plain == b'?WATCH={"enable":true,"json":true,"pps":true}\n'
    assert b'"device":"/dev/ttyACM0"' in watch_command("/dev/ttyACM0")
    long_path = "/dev/serial/by-id/usb-u-blox_AG_-_www.u-blox.com_u-blox_GNSS_receiver-if00"
    assert watch_command(long_path) == plain  # would exceed gpsd's 80 characters: filtered here instead
    assert all(len(c.strip()) <= 80 for c in (plain, watch_command("/dev/ttyACM0")))


def test_one_fix_per_epoch_whatever_the_order_of_its_reports() -> None:
    e = GpsdEpochs(settle_ns=300_000_000)
    t1, t2, t3 = T0 + NS, T0 + 2 * NS, T0 + 3 * NS
    e.push({"class": "DEVICES", "devices": [UBLOX_DEVICE]}, 0)
    out = e.push(sky(t1, used=7), 0)  # SKY first (u-blox binary)
    out += e.push(tpv(t1, lat=1.0), 10)
    out += e.push({"class": "TPV", "time": iso(t1), "mode": 3, "lat": 1.5, "eph": 2.0}, 20)  # completes the first
    out += e.push(tpv(t2, lat=2.0), 1000)  # the next epoch closes the last one
    assert [(f.time_utc_ns, f.lat_deg, f.lon_deg, f.height_hae_m, f.h_acc_m, f.num_sv) for f, _ in out] == [
        (t1, 1.5, 127.0, 60.0, 2.0, 7)]
    assert out[0][1] == 20  # acquisition time: the arrival of the epoch's last TPV
    out = e.push(sky(t2, used=8), 1010)  # SKY after its TPV (NMEA receivers)
    out += e.push(tpv(t2, lat=2.5), 1020)
    assert out == [] and e.poll(1020 + 299_999_999) == []
    (fix, t), = e.poll(1020 + 300_000_000)
    assert (fix.time_utc_ns, fix.lat_deg, fix.num_sv, t) == (t2, 2.5, 8, 1020)
    assert e.push(tpv(t2, lat=9.0), 2000) == [] and e.counters.late == 1  # too late: never a second record
    out = e.push(sky(t3 - NS, used=5), 2100)  # gpsd kept an old sky time: the next epoch still takes it
    out += e.push(tpv(t3), 2200) + e.flush()
    assert [(f.time_utc_ns, f.num_sv) for f, _ in out] == [(t3, 5)] and e.counters.stale_sky == 1
    assert e.counters.epochs == 3


# ---------------------------------------------------------------------------------------------------------------
# The client against a gpsd on a socket


@pytest.fixture
def gpsd() -> Iterator[SimGpsd]:
    devices = [{"class": "DEVICE", "path": p, "driver": "u-blox", "activated": "2024-01-01T00:00:00.000Z"}
               for p in ("/dev/ttyACM0", "/dev/ttyUSB0")]
    server = SimGpsd(devices=devices).start()
    try:
        yield server
    finally:
        server.stop()


def read_until(read: Callable[[], list[Any]], done: Callable[[list[Any]], bool], timeout_s: float = 10.0) -> list[Any]:
    out: list[Any] = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not done(out):
        out += read()
    return out


@pytest.mark.parametrize("device", ["/dev/ttyUSB0", "/dev/serial/by-id/" + "x" * 70])
def test_the_configured_receiver_is_the_only_one_read(device: str) -> None:
    devices = [{"class": "DEVICE", "path": p, "driver": "u-blox"} for p in ("/dev/ttyACM0", device)]
    with SimGpsd(devices=devices) as gpsd, GpsdClient.connect(*gpsd.address, device=device) as client:
        assert gpsd.wait_for_watchers()
        for i in range(5):
            gpsd.publish(tpv(T0 + i * NS, device="/dev/ttyACM0"))
            gpsd.publish(tpv(T0 + i * NS, device=device))
        got = read_until(lambda: client.read(0.2), lambda o: sum(m["class"] == "TPV" for m in o) >= 5)
        assert [m["device"] for m in got if m["class"] == "TPV"] == [device] * 5
        assert client.version is not None and client.version["proto_major"] == 3
        assert client.devices == {"/dev/ttyACM0", device} and client.missing_device() is None
        # a short path is selected by gpsd itself; a long one does not fit the request and is dropped here
        assert client.counters.other_device == (0 if len(device) < 40 else 5)


def test_garbage_and_overlong_lines_are_counted_and_reading_goes_on(gpsd: SimGpsd) -> None:
    src = GpsdSource(*gpsd.address, None, host_timebase(), settle_s=0.05)
    src.open()
    try:
        assert gpsd.wait_for_watchers()
        gpsd.publish(tpv(T0))
        for junk in (b"garbage\r\n", b"{not json\r\n", b'["a list"]\r\n', b'{"noclass":1}\r\n', b"\xff\xfe{}\r\n",
                     b"[" * 5000 + b"\r\n", b"{" + b"x" * (MAX_LINE_BYTES + 10) + b"}\r\n", b"\r\n"):
            gpsd.inject(junk)
        gpsd.publish(tpv(T0 + NS))
        gpsd.publish(tpv(T0 + 2 * NS))
        got = read_until(src.read, lambda o: len(o) >= 3)
        assert [r.payload["gnss_time_ns"] for r in got] == [T0, T0 + NS, T0 + 2 * NS]
        c = src.client.counters
        assert (c.garbage, c.oversized) == (6, 1)
        assert src.incidents() == {"lines of garbage from gpsd": 6, "overlong lines from gpsd": 1}
    finally:
        src.close()


def test_a_receiver_gpsd_does_not_have_is_reported_as_no_data(gpsd: SimGpsd, monkeypatch) -> None:
    monkeypatch.setattr(gpsd_sources, "QUIET_S", 0.2)
    src = GpsdSource(*gpsd.address, "/dev/ttyS4", host_timebase())
    src.open()
    try:
        with pytest.raises(NoData, match=r"has no /dev/ttyS4 \(it has /dev/ttyACM0, /dev/ttyUSB0\)"):
            read_until(src.read, lambda o: False, timeout_s=5.0)
    finally:
        src.close()


def test_no_gpsd_listening_is_one_clear_line() -> None:
    server = SimGpsd()
    host, port = server.address
    server.stop()  # the port is free again: nothing listens
    src = GpsdSource(host, port, None, host_timebase())
    with pytest.raises(DeviceNotFound, match=rf"gpsd: nothing listens on 127.0.0.1:{port} \(is gpsd running\?\)"):
        src.open()


class EpochPublisher(threading.Thread):
    """gpsd's reports of a receiver at 20 epochs a second, whether or not gpsd is up."""

    def __init__(self, server: SimGpsd) -> None:
        super().__init__(daemon=True)
        self.server = server
        self.halt = threading.Event()

    def run(self) -> None:
        for i in itertools.count():
            if self.halt.wait(0.05):
                return
            self.server.publish(sky(T0 + i * NS))
            self.server.publish(tpv(T0 + i * NS))


def test_gpsd_restart_is_reconnected_and_fixes_resume() -> None:
    server = SimGpsd().start()
    tb = host_timebase()
    src = GpsdSource(*server.address, None, tb, settle_s=0.05)
    got: list[Reading] = []
    stop = threading.Event()
    sampler = Sampler(src, got.append, tb, None, stop, expected_hz=20.0)
    feeder = EpochPublisher(server)
    feeder.start()
    sampler.start()
    try:
        assert wait_until(lambda: len(got) >= 5, 10)
        server.stop()
        assert wait_until(lambda: sampler.health.state in ("retrying", "missing"), 10)
        assert "gpsd at 127.0.0.1" in sampler.health.last_error or "nothing listens" in sampler.health.last_error
        before = len(got)
        server.start()
        assert wait_until(lambda: sampler.health.reconnects >= 1 and len(got) >= before + 5, 20)
        assert sampler.health.state == "ok"
    finally:
        feeder.halt.set()
        stop.set()
        sampler.join(5)
        server.stop()
    times = [r.payload["gnss_time_ns"] for r in got]
    assert all(b > a for a, b in itertools.pairwise(times))  # no epoch twice, none out of order


# ---------------------------------------------------------------------------------------------------------------
# PPS through gpsd


def test_the_realtime_map_refuses_edges_a_clock_step_crossed() -> None:
    mono = ManualClock(start_ns=5 * NS)
    offset = [T0]
    rmap = RealtimeMap(lambda: mono.now_ns() + offset[0], mono.now_ns)
    rmap.sample()
    mono.advance(0.3)
    edge = mono.now_ns()
    stamp = edge + offset[0]
    mono.advance(0.2)
    rmap.sample()
    assert rmap.to_monotonic(stamp) == edge  # no step: exact
    for step_s in (0.001, -0.001, 3.0, -3.0):
        mono.advance(0.5)
        edge = mono.now_ns()
        stamp = edge + offset[0]  # stamped before the step...
        offset[0] += round(step_s * NS)
        mono.advance(0.1)
        rmap.sample()  # ...reported after it
        assert rmap.to_monotonic(stamp) is None, step_s
    assert rmap.refused_step == 4
    mono.advance(0.5)
    edge = mono.now_ns()
    mono.advance(0.1)
    rmap.sample()
    assert rmap.to_monotonic(edge + offset[0]) == edge  # after the step, edges are mapped again
    assert RealtimeMap(lambda: 0, lambda: 0).to_monotonic(5) is None  # nothing sampled: nothing vouched for


def pps(real_s: int, clock_ns: int, qerr_ps: int = 0) -> dict[str, Any]:
    return {"class": "PPS", "device": "/dev/ttyACM0", "real_sec": real_s, "real_nsec": 0,
            "clock_sec": clock_ns // NS, "clock_nsec": clock_ns % NS, "precision": -20, "qErr": qerr_ps}


def test_pps_reports_become_labelled_edges_on_the_monotonic_clock(gpsd: SimGpsd) -> None:
    mono = ManualClock(start_ns=100 * NS)
    offset = [T0 - 100 * NS + 123_456]  # the board's system clock, as NTP left it
    tb = TimeBase(mono.now_ns, 1.0)
    src = GpsdPpsSource(*gpsd.address, None, tb, realtime_ns=lambda: mono.now_ns() + offset[0])
    src.open()
    try:
        assert gpsd.wait_for_watchers()

        def edge_and_report(real_s: int, qerr_ps: int = 0, step_ns: int = 0, wait_s: float = 3.0) -> list[Reading]:
            mono.advance(1.0)
            edge = mono.now_ns()
            gpsd.publish(tpv(real_s * NS))  # reports of other classes pass by
            gpsd.publish(pps(real_s, edge + offset[0], qerr_ps))
            offset[0] += step_ns
            mono.advance(0.02)  # gpsd reports the edge a little later
            return read_until(src.read, lambda o: bool(o), timeout_s=wait_s)

        s0 = T0 // NS
        (r,) = edge_and_report(s0, qerr_ps=-2400)
        assert r.topic == "/pps" and r.t_mono_ns == mono.now_ns() - 20_000_000
        assert r.payload == {"seqno": 0, "lost": 0, "gnss_time_ns": s0 * NS + 2}
        (r,) = edge_and_report(s0 + 3)  # two seconds without a report
        assert r.payload == {"seqno": 1, "lost": 2, "gnss_time_ns": (s0 + 3) * NS}
        assert edge_and_report(s0 + 4, step_ns=2 * NS, wait_s=1.0) == []  # the system clock was stepped meanwhile
        assert src.incidents()["edges left out: system clock stepped"] == 1
        (r,) = edge_and_report(s0 + 5)
        assert r.t_mono_ns == mono.now_ns() - 20_000_000 and r.payload["seqno"] == 2
    finally:
        src.close()


def test_labelled_edges_lock_the_clock_and_a_wrong_second_is_refused() -> None:
    now = [10 * NS]
    clock = PpsClock(SyncSettings(pps_latency_ns=0), monotonic_ns=lambda: now[0], wall_ns=lambda: T0)
    board_rate = 1.0 + 30e-6  # the board's crystal runs 30 ppm fast
    for k in range(10):
        now[0] = 10 * NS + round(k * NS * board_rate)
        clock.on_edge(now[0], T0 + k * NS)
    assert clock.report().state == "locked" and clock.counts["rejected"] == 0
    assert abs(clock.stamp(now[0]).t_sync_ns - (T0 + 9 * NS)) < 1_000
    now[0] += round(NS * board_rate)
    clock.on_edge(now[0], T0 + 11 * NS)  # a second off
    assert clock.counts["rejected"] == 1
    assert abs(clock.stamp(now[0]).t_sync_ns - (T0 + 10 * NS)) < 1_000


# ---------------------------------------------------------------------------------------------------------------
# gpsd's own decoding of real captures, replayed through the socket


def merged_tpvs(lines: list[str]) -> dict[int, dict[str, Any]]:
    """gpsd's reports per epoch, as gpsd completes them: later TPVs of the same time add and replace fields."""
    out: dict[int, dict[str, Any]] = {}
    for line in lines:
        if line.startswith('{"class":"TPV"') and '"time"' in line:
            obj = json.loads(line)
            stamp = dt.datetime.strptime(obj["time"], "%Y-%m-%dT%H:%M:%S.%fZ")
            key = calendar.timegm(stamp.timetuple()) * NS + stamp.microsecond * 1000
            out.setdefault(key, {}).update(obj)
    return out


REPLAYED = ["ublox-glo.log", "ublox-neo-m8p.log", "ublox-zed-f9p-rtk.log", "ublox-8.log"]


@pytest.fixture(scope="module")
def replayed() -> dict[str, tuple[dict[int, dict[str, Any]], dict[int, dict[str, Any]]]]:
    """Per capture: gpsd's merged TPVs and our records of them, by epoch time (a capture replayed per server)."""
    results = {}
    for log in REPLAYED:
        lines = (DATA_DIR / (log + ".chk")).read_text(encoding="utf-8", errors="replace").splitlines()
        expected = merged_tpvs(lines)
        with SimGpsd(devices=[UBLOX_DEVICE]) as server:  # gpsd names its driver in reply to ?WATCH
            src = GpsdSource(*server.address, None, host_timebase())
            src.open()
            try:
                assert server.wait_for_watchers()
                server.replay(lines)
                n = len(expected)
                got = read_until(src.read, lambda o, n=n: len(o) >= n, timeout_s=20.0)
            finally:
                src.close()
        records: dict[int, dict[str, Any]] = {}
        for r in got:
            ts = r.payload["timestamp"]
            key = ts["sec"] * NS + ts["nsec"]
            assert key not in records, (log, key)  # one record per epoch
            records[key] = r.payload
        results[log] = (expected, records)
    return results


@pytest.mark.parametrize("log", REPLAYED)
def test_replayed_reports_are_recorded_as_gpsd_gave_them(replayed, log: str) -> None:
    expected, records = replayed[log]
    assert len(expected) > 5 and set(records) == set(expected)
    for key, g in expected.items():
        rec = records[key]
        assert rec["source"] == "gpsd" and rec["fix_mode"] == g["mode"]
        if g["mode"] < 2:
            continue
        assert rec["gnss_time_ns"] == key
        assert (rec["latitude"], rec["longitude"]) == (g["lat"], g["lon"])
        assert rec["altitude"] == g.get("altHAE", rec["altitude"]) and rec["height_msl_m"] == g.get("altMSL")
        assert (rec["h_acc_m"], rec["v_acc_m"], rec["s_acc_mps"]) == (g.get("eph"), g.get("epv"), g.get("eps"))
        if "velN" not in g and "track" not in g:
            # A speed without a course is no velocity; a standing receiver's few cm/s are a velocity of nought.
            assert rec["vel_ned_mps"] == ([0.0, 0.0, None] if g.get("speed", 1.0) <= NO_COURSE_SPEED_MPS else None)
            continue
        vn, ve, vd = rec["vel_ned_mps"]
        if "velN" in g:
            assert (vn, ve, vd) == (g["velN"], g["velE"], g["velD"])
        assert math.hypot(vn, ve) == pytest.approx(g["speed"], rel=1e-12, abs=1e-12) or "velN" in g
        if "track" in g and g["speed"] > 0 and "velN" not in g:
            assert math.degrees(math.atan2(ve, vn)) % 360.0 == pytest.approx(g["track"] % 360.0, abs=1e-9)
        assert vd == g.get("velD")  # the receiver's, or none: gpsd's climb is its own difference of altitudes


def our_decoding(log: str) -> dict[int, dict[str, Any]]:
    """Our own decoder's /gnss/fix records of a capture, by epoch time to the millisecond (gpsd's resolution)."""
    serial = decode_pieces([strip_capture_comments((DATA_DIR / log).read_bytes())])
    mine: dict[int, dict[str, Any]] = {}
    for fix in serial.fixes:
        if fix.time_utc_ns is not None and fix.source != "HNR-PVT":
            mine.setdefault((fix.time_utc_ns + 500_000) // 1_000_000 * 1_000_000, location_fix(fix, 0))
    return mine


@pytest.mark.parametrize("log", REPLAYED)
def test_replayed_reports_equal_our_own_decoding_of_the_capture(replayed, log: str) -> None:
    _, records = replayed[log]
    mine = our_decoding(log)
    common = set(records) & set(mine)
    assert len(common) >= len(records) - 1  # every epoch gpsd reported (test_gnss_decode_gpsd: all agree)
    for key in common:
        a, b = records[key], mine[key]
        assert a["fix_mode"] == b["fix_mode"]
        if a["fix_mode"] < 2:
            continue
        # gpsd prints 9 decimals of a degree and 4 of a metre; UBX values it passes on exactly
        assert abs(a["latitude"] - b["latitude"]) <= 5e-10 and abs(a["longitude"] - b["longitude"]) <= 5e-10
        assert abs(a["altitude"] - b["altitude"]) <= 5e-5
        assert abs(a["height_msl_m"] - b["height_msl_m"]) <= 5e-5
        # gpsd's speed is the receiver's ground speed, ours the norm of its N and E velocity: each to 1 mm/s
        assert abs(math.hypot(*a["vel_ned_mps"][:2]) - math.hypot(*b["vel_ned_mps"][:2])) <= 0.0015


# ---------------------------------------------------------------------------------------------------------------
# A real gpsd: Debian's gpsd 3.22 fed the captures by gpsfake (a pty), read by the source as on a board


GPSFAKE_CAPTURES = ["ublox-8.log", "ublox-neo-m8p.log", "ublox-neo-m9n-nmea.log"]  # UBX and NMEA, 1 and 4 Hz


def _gpsfake_missing() -> bool:
    if shutil.which("gpsfake") is None or shutil.which("gpsd") is None:
        return True
    # gpsfake is a script of the system's Python: without python3-gps it fails at its first import.
    return subprocess.run(["gpsfake", "-h"], capture_output=True).returncode != 0


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RawWatcher(threading.Thread):
    """A second client of the same gpsd: the JSON lines it sends, as they come (what our source was given)."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        import socket

        self.sock = socket.create_connection(("127.0.0.1", port), timeout=60.0)
        self.sock.sendall(b'?WATCH={"enable":true,"json":true};\n')
        self.lines: list[str] = []

    def run(self) -> None:
        buf = b""
        try:
            while chunk := self.sock.recv(65536):
                buf += chunk
                *done, buf = buf.split(b"\n")
                self.lines += [line.decode(errors="replace") for line in done]
        except OSError:
            pass
        finally:
            self.sock.close()


def _connect(src: GpsdSource, port: int) -> RawWatcher:
    """Our source and a raw watcher on gpsfake's gpsd, once it listens (gpsfake starts it after making its pty,
    and feeds the capture once a client is there: the first epochs may reach one client before the other)."""
    end = time.monotonic() + 10.0
    while True:
        try:
            watcher = RawWatcher(port)
            break
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.1)
    watcher.start()
    src.open()
    return watcher


@pytest.fixture(scope="module")
def through_gpsd() -> dict[str, tuple[dict[int, dict[str, Any]], dict[int, dict[str, Any]]]]:
    """Per capture: what a real gpsd reported of it (merged per epoch, as a raw client saw it) and our records of
    it, by epoch time. gpsfake feeds the capture to gpsd on a pty, a packet every 10 ms, once (``-1``); ``-b``
    keeps gpsd from probing or reconfiguring the "receiver" (a log cannot answer). Fed faster than real time gpsd
    reports fewer epochs than the capture holds (its cycle detection runs on arrival times): what it reported is
    what is compared. The source reads until gpsd goes away with the end of the capture. The captures go through
    gpsds of their own at once (each is paced by gpsfake, not by the CPU: one after the other took 72 s)."""
    if _gpsfake_missing():
        pytest.skip("gpsd (gpsfake, with python3-gps) is not installed")
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(len(GPSFAKE_CAPTURES)) as pool:
        return dict(zip(GPSFAKE_CAPTURES, pool.map(_through_gpsd, GPSFAKE_CAPTURES), strict=True))


def _through_gpsd(log: str) -> tuple[dict[int, dict[str, Any]], dict[int, dict[str, Any]]]:
    """One capture through its own gpsfake: gpsd's reports merged per epoch, and our records, by epoch time."""
    port = _free_port()
    # In a session of its own: gpsfake starts a gpsd, which its kill below would leave running (one daemon per
    # capture per run, found idling after many runs); the session's group goes whole.
    fake = subprocess.Popen(["gpsfake", "-1", "-q", "-c", "0.01", "-P", str(port), "--options=-b",
                             str(DATA_DIR / log)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    src = GpsdSource("127.0.0.1", port, None, host_timebase())
    got: list[Reading] = []
    try:
        watcher = _connect(src, port)
        end, quiet_since = time.monotonic() + 60.0, None
        while time.monotonic() < end:
            try:
                new = src.read()
            except SensorError:  # gpsd gone with the end of the capture, or its device closed
                break
            got += new
            if new or fake.poll() is None:
                quiet_since = None
            elif quiet_since is None:
                quiet_since = time.monotonic()
            elif time.monotonic() - quiet_since > 2.0:  # the capture fed and nothing more for 2 s
                break
        watcher.join(10.0)
    finally:
        src.close()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(fake.pid, signal.SIGKILL)
        fake.wait()
        # Killed, gpsfake never removes its gpsd's control socket (gps/fake.py names it by gpsfake's pid): one
        # file a capture a run, 204 of them found in /tmp.
        Path(os.environ.get("TMPDIR", "/tmp"), f"gpsfake-{fake.pid}.sock").unlink(missing_ok=True)
    records: dict[int, dict[str, Any]] = {}
    for r in got:
        ts = r.payload["timestamp"]
        key = ts["sec"] * NS + ts["nsec"]
        if key == 0:  # a report without a time (gpsd's first 2D fix of ublox-8.log): compared by time below
            continue
        assert key not in records, (log, key)  # one record per epoch
        records[key] = r.payload
    return merged_tpvs(watcher.lines), records


@pytest.mark.parametrize("log", GPSFAKE_CAPTURES)
def test_a_real_gpsds_reports_of_a_capture_are_recorded_as_our_own_decoding_of_it(through_gpsd, log: str) -> None:
    """gpsd 3.22 (Debian 12's) decodes the capture itself, as on a board where gpsd owns the receiver: every
    epoch it reported (from the first both clients saw) is recorded once, with its values, and with the fix our
    own decoder makes of the same bytes."""
    reported, records = through_gpsd[log]
    assert len(records) > 5
    first = min(records)
    assert set(records) == {k for k in reported if k >= first}
    for key, g in reported.items():
        if key < first or g["mode"] < 2:
            continue
        assert (records[key]["latitude"], records[key]["longitude"]) == (g["lat"], g["lon"])
    mine = our_decoding(log)
    common = set(records) & set(mine)
    assert len(common) >= len(records) - 1
    for key in common:
        a, b = records[key], mine[key]
        assert a["source"] == "gpsd" and a["fix_mode"] == b["fix_mode"], key
        if a["fix_mode"] < 2:
            continue
        assert a["gnss_time_ns"] == key
        # gpsd prints 9 decimals of a degree
        assert abs(a["latitude"] - b["latitude"]) <= 5e-10 and abs(a["longitude"] - b["longitude"]) <= 5e-10


# ---------------------------------------------------------------------------------------------------------------
# Configuration


GPSD_CONFIG = '[gnss]\nsource = "gpsd"\ngpsd_host = "::1"\ngpsd_port = 2948\ngpsd_device = "/dev/ttyACM0"\n' \
              '[pps]\nsource = "gpsd"\n[obd]\nsource = "can"\n'


def test_gpsd_configuration_and_its_one_line_errors() -> None:
    cfg = parse(GPSD_CONFIG, "logger.toml")
    assert (cfg["gnss"]["source"], cfg["gnss"]["gpsd_host"], cfg["gnss"]["gpsd_port"]) == ("gpsd", "::1", 2948)
    assert cfg["pps"]["source"] == "gpsd" and cfg["gnss"]["port"] is None  # no serial port needed
    bad = GPSD_CONFIG.replace('"::1"', '"my gpsd!"').replace("2948", "70000").replace('"/dev/ttyACM0"', '"ttyACM0"')
    with pytest.raises(ConfigError) as err:
        parse(bad, "logger.toml")
    assert err.value.problems == [
        "logger.toml:3: gnss.gpsd_host = 'my gpsd!' is not a host name or IP address",
        "logger.toml:4: gnss.gpsd_port = 70000 must be between 1 and 65535",
        "logger.toml:5: gnss.gpsd_device = 'ttyACM0' must be empty (every receiver), a device path such as "
        "/dev/ttyACM0, or a gpsd source URL"]
    url = GPSD_CONFIG.replace('"/dev/ttyACM0"', '"tcp://10.0.0.2:2947"')
    assert parse(url)["gnss"]["gpsd_device"] == "tcp://10.0.0.2:2947"


def test_sim_keeps_gpsd_as_a_simulated_gpsd_and_real_gpsd_cannot_be_time_scaled(tmp_path: Path) -> None:
    path = tmp_path / "logger.toml"
    path.write_text(GPSD_CONFIG)
    args = argparse.Namespace(config=str(path), sim=True, scenario=None, seed=None, duration=None, time_scale=5.0,
                              out=None, status_socket=None)
    cfg = resolve_config(args)
    assert cfg["gnss"]["source"] == "gpsd" and cfg["pps"]["source"] == "gpsd" and cfg["sim"]["gpsd"] is True
    assert cfg["imu"]["source"] == "sim"
    args.sim = False
    with pytest.raises(ConfigError, match="needs every sensor simulated; real: imu, baro, obd, gnss, pps"):
        resolve_config(args)


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_the_systemd_drop_in_opens_tcp_to_localhost_only(tmp_path: Path) -> None:
    """The unit forbids Internet sockets; the shipped drop-in must open exactly the way to a local gpsd."""
    units = tmp_path / "etc" / "systemd" / "system"
    (units / "vehicle-logger.service.d").mkdir(parents=True)
    unit = (ROOT / "systemd" / "vehicle-logger.service").read_text()
    (units / "vehicle-logger.service").write_text(unit.replace("/opt/vehicle-logger/venv/bin/logger", "/bin/true"))
    drop_in = ROOT / "systemd" / "vehicle-logger.service.d" / "gpsd.conf"
    (units / "vehicle-logger.service.d" / "gpsd.conf").write_text(drop_in.read_text())
    r = subprocess.run(["systemd-analyze", "security", "--offline=true", f"--root={tmp_path}", "--json=short",
                        "vehicle-logger.service"], capture_output=True, text=True, timeout=60)
    items = {i["name"]: i for i in json.loads(r.stdout)}
    assert items["RestrictAddressFamilies=~AF_(INET|INET6)"]["set"] is False  # TCP to gpsd: allowed
    assert items["RestrictAddressFamilies=~AF_NETLINK"]["set"] is True  # the rest of the list still holds
    assert "only localhost" in items["IPAddressDeny="]["description"]
    r = subprocess.run(["systemd-analyze", "security", "--offline=true", f"--root={tmp_path}",
                        "vehicle-logger.service"], capture_output=True, text=True, timeout=60)
    exposure = float(re.search(r"Overall exposure level for vehicle-logger\.service: (\d+\.\d)", r.stdout).group(1))
    assert exposure <= 2.0, r.stdout


# ---------------------------------------------------------------------------------------------------------------
# The daemon on the simulated vehicle, its receiver read through a simulated gpsd


def read_file(path: Path) -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = collections.defaultdict(list)
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            out[channel.topic].append(json.loads(message.data))
    out["/imu"].extend(m for batch in out["/imu/batch"] for m in imu_samples(batch))  # a FIFO read's samples
    return out


@pytest.mark.slow_on_board
def test_a_drive_through_gpsd_records_fixes_at_1hz_and_locks_the_clock_to_its_pps(tmp_path: Path) -> None:
    cfg = tmp_path / "logger.toml"
    cfg.write_text(f'[logger]\nstate_dir = "{tmp_path / "state"}"\n[gnss]\nsource = "gpsd"\n[pps]\nsource = "gpsd"\n'
                   '[obd]\nsource = "sim"\n')
    sock = tmp_path / "status.sock"
    duration_s = 40
    proc = subprocess.Popen([sys.executable, "-m", "logger.cli", "run", "--sim", "--config", str(cfg), "--duration",
                             str(duration_s), "--time-scale", "5", "--out", str(tmp_path), "--status-socket",
                             str(sock)], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    snap = None
    try:
        deadline = time.monotonic() + drive_timeout(10)
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                snap = fetch(sock)
                if snap["uptime_s"] > 10 and all(s["state"] == "ok" for s in snap["sensors"]):
                    break
            except ConnectionError:
                pass
            time.sleep(0.1)
        assert snap is not None, proc.stderr.read() if proc.stderr else ""
        _, stderr = proc.communicate(timeout=drive_timeout(duration_s))
    finally:
        proc.kill()
    assert proc.returncode == 0, stderr
    origins = {s["name"]: s["origin"] for s in snap["sensors"]}
    assert origins["gnss"].startswith("gpsd 127.0.0.1:") and origins["pps"].startswith("gpsd 127.0.0.1:")
    assert f"gnss from {origins['gnss']}" in render(snap)
    (path,) = sorted(tmp_path.glob("*.mcap"))
    msgs = read_file(path)
    fixes = msgs["/gnss/fix"]
    assert {f["source"] for f in fixes} == {"gpsd"}
    epochs = [f["gnss_time_ns"] for f in fixes if f["gnss_time_ns"] is not None]
    assert len(epochs) >= len(fixes) - 2 and all(b - a == NS for a, b in itertools.pairwise(epochs))
    # One fix per epoch, none missing (above), and the epochs arrive at one a second of the daemon's clock: the
    # slope of arrival time against epoch over the whole drive, which a few fixes a busy host delivered late
    # barely move (unlike the first and last arrival alone).
    timed = [(f["gnss_time_ns"], f["t_mono_ns"]) for f in fixes if f["gnss_time_ns"] is not None]
    slope = statistics.linear_regression([(g - timed[0][0]) / NS for g, _ in timed],
                                         [(m - timed[0][1]) / NS for _, m in timed]).slope
    assert abs(slope - 1.0) < 0.05 and len(fixes) >= duration_s - 4, (slope, len(fixes))
    assert all(f["num_sv"] and f["pdop"] and f["hdop"] and f["vdop"] for f in fixes if f["fix_mode"] == 3)
    # each fix sits within metres of the truth of its epoch
    truth: dict[int, dict[str, Any]] = {}
    for m in msgs["/truth/nav"]:
        truth.setdefault(m["t_true_ns"] // NS, m)  # the first sample of each second: at most 50 ms after it
    near = [abs(f["latitude"] - truth[f["gnss_time_ns"] // NS]["lat_deg"]) * 111_000 for f in fixes
            if f["fix_mode"] == 3 and f["gnss_time_ns"] is not None and f["gnss_time_ns"] // NS in truth]
    assert len(near) > 30 and max(near) < 30
    edges = msgs["/pps"]
    assert [e["seqno"] for e in edges] == list(range(len(edges))) and len(edges) >= duration_s - 4
    assert all(abs(e["gnss_time_ns"] - round(e["gnss_time_ns"] / NS) * NS) < 100 for e in edges)
    assert msgs["/sync"][-1]["state"] == "locked" and msgs["/sync"][-1]["rejected"] == 0
    # stamps of the IMU, once locked, against the true time at their board time
    errors = [error for error, _ in locked_imu_errors(msgs)]
    assert len(errors) > 500 and max(errors) < 20_000, (len(errors), max(errors))


def locked_imu_errors(msgs: dict[str, list[dict[str, Any]]]) -> list[tuple[float, int]]:
    """Each locked /imu stamp's error against the true time at its board time (/truth/clock), with its bound."""
    clock = sorted((m["t_mono_ns"], m["t_true_ns"]) for m in msgs["/truth/clock"])
    board = [c[0] for c in clock]
    out = []
    for m in msgs["/imu"]:
        i = bisect.bisect_left(board, m["t_mono_ns"])
        if m["sync_state"] != "locked" or not 0 < i < len(clock):
            continue
        (m0, t0), (m1, t1) = clock[i - 1], clock[i]
        out.append((abs(m["t_sync_ns"] - (t0 + (t1 - t0) * (m["t_mono_ns"] - m0) / (m1 - m0))), m["sync_err_ns"]))
    return out


@pytest.mark.slow_on_board
def test_fixes_through_gpsd_at_5hz_with_the_boards_own_pps_line_lock_the_clock_to_the_right_second(
        tmp_path: Path) -> None:
    """GNSS from the simulated gpsd at 5 Hz, the PPS on the board's GPIO line. The simulated gpsd once sent a TOFF
    for every epoch, named by the nearest whole second: the x.0 epoch's TOFF was the one of x-0.4 s, before the
    edge of x, and the clock, paired a second off, disagreed with the system clock and never locked. (Its TOFF now
    comes 1 ms before the TPV, mostly in the same read: these fixes are paired by their TPV's arrival; the
    real-gpsd test above is the one of a TOFF read apart.)"""
    cfg = tmp_path / "logger.toml"
    cfg.write_text(f'[logger]\nstate_dir = "{tmp_path / "state"}"\n[gnss]\nsource = "gpsd"\n[pps]\nsource = "sim"\n'
                   '[obd]\nsource = "sim"\n[sim]\ngpsd = true\ngnss_rate_hz = 5\n')
    duration_s = 30
    proc = subprocess.run([sys.executable, "-m", "logger.cli", "run", "--sim", "--config", str(cfg), "--duration",
                           str(duration_s), "--time-scale", "4", "--out", str(tmp_path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=drive_timeout(duration_s))
    assert proc.returncode == 0, proc.stderr
    msgs: dict[str, list[dict[str, Any]]] = collections.defaultdict(list)
    for path in sorted(tmp_path.glob("*.mcap")):
        for topic, items in read_file(path).items():
            msgs[topic] += items
    fixes = [f for f in msgs["/gnss/fix"] if f["gnss_time_ns"] is not None]
    assert len(fixes) >= 5 * (duration_s - 8), len(fixes)
    assert all(f["opened_mono_ns"] < f["t_mono_ns"] for f in fixes if "opened_mono_ns" in f)
    assert msgs["/sync"][-1]["state"] == "locked" and msgs["/sync"][-1]["relocks"] == 0, msgs["/sync"][-1]
    beyond = [error - bound for error, bound in locked_imu_errors(msgs)]
    assert len(beyond) > 300 and max(beyond) <= 0, (len(beyond), max(beyond))


# ---------------------------------------------------------------------------------------------------------------
# What a review found (an NMEA receiver through gpsd 3.22; captures and outputs in tests/data/gnss-review)

NMEA_DEVICE = {"class": "DEVICE", "path": "/dev/ttyACM0", "driver": "NMEA0183", "cycle": 1.0}


def gst(t_ns: int, **fields: Any) -> dict[str, Any]:
    obj: dict[str, Any] = {"class": "GST", "device": "/dev/ttyACM0", "time": iso(t_ns), "rms": 1.2, "major": 2.1,
                           "minor": 1.4, "orient": 30.0, "lat": 1.5, "lon": 2.0, "alt": 3.0}
    obj.update(fields)
    return obj


def test_accuracies_are_the_receivers_1_sigma_or_none_never_gpsds_95_percent_guess() -> None:
    # gpsd 3.22's TPVs of an NMEA receiver with GST sigmas 1.5 / 2.0 / 3.0 m: eph 17.1 and epv 27.6 (its DOP model)
    t = T0 + 5 * NS
    e = GpsdEpochs()
    e.push({"class": "DEVICES", "devices": [NMEA_DEVICE]}, 0)
    out = e.push(tpv(t, eph=17.1, epv=27.6, epx=8.0, epy=9.0, eps=0.8), 10) + e.push(gst(t), 20)
    out += e.push(tpv(t, eph=17.1, epv=27.6), 30) + e.flush()
    (fix, _), = out
    assert (fix.h_acc_m, fix.v_acc_m, fix.s_acc_mps) == (2.5, 3.0, None)  # GST, as the serial path takes it
    assert e.counters.gst == 1
    # no GST: gpsd's figures are guesses, left to the filter's DOP model (the SKY's DOPs stay)
    (fix, _), = e.push(tpv(t + NS, eph=17.1, epv=27.6, eps=0.8), 40) + e.push(sky(t + NS), 50) + e.flush()
    assert (fix.h_acc_m, fix.v_acc_m, fix.s_acc_mps, fix.hdop) == (None, None, None, 0.9)
    # a GST before its TPV goes with it too
    (fix, _), = e.push(gst(t + 2 * NS, lat=0.3, lon=0.4, alt=0.9), 60) + e.push(tpv(t + 2 * NS), 70) + e.flush()
    assert (fix.h_acc_m, fix.v_acc_m) == (0.5, 0.9)
    # gpsd's u-blox driver: eph, epv, eps are the receiver's hAcc, vAcc, sAcc
    u = GpsdEpochs()
    u.push(UBLOX_DEVICE, 0)
    (fix, _), = u.push(tpv(t, eph=1.1, epv=1.9, eps=0.2), 10) + u.flush()
    assert (fix.h_acc_m, fix.v_acc_m, fix.s_acc_mps) == (1.1, 1.9, 0.2)
    # At 5 Hz gpsd reports an epoch twice: first with the receiver's figures (NAV-PVT), then, after its cycle's
    # NMEA, with its own model's (eps 19.08 against the receiver's 0.24: the speed counted for nothing). The first
    # stand; the rest of the later report completes the epoch as before.
    u = GpsdEpochs()
    u.push(UBLOX_DEVICE, 0)
    out = u.push(tpv(t, eph=1.1, epv=1.9, eps=0.24), 10) + u.push(tpv(t, eph=9.6, epv=22.1, eps=19.08, climb=0.1),
                                                                   20_000_000)
    (fix, _), = out + u.flush()
    assert (fix.h_acc_m, fix.v_acc_m, fix.s_acc_mps) == (1.1, 1.9, 0.24)


def test_gpsds_leap_second_tpv_stamped_midnight_is_an_epoch_of_its_own() -> None:
    # gpsd 3.22 (tests/data/gnss-review/leap.nmea through gpsfake): 23:59:59, then 23:59:60 and 00:00:00 both
    # stamped 2026-01-01T00:00:00.000Z a second apart
    midnight = calendar.timegm((2026, 1, 1, 0, 0, 0)) * NS
    for poll in (False, True):  # the second midnight TPV while the first epoch is open, or after it was reported
        e = GpsdEpochs()
        out = e.push(tpv(midnight - NS, lat=48.11749), 0)
        out += e.push(tpv(midnight, lat=48.1175), NS)
        if poll:
            out += e.poll(NS + 400_000_000)  # held: the repeat may come
        out += e.push(tpv(midnight, lat=48.11751), 2 * NS) + e.push(tpv(midnight + NS, lat=48.11752), 3 * NS)
        out += e.flush()
        assert [(f.time_utc_ns - midnight, f.lat_deg) for f, _ in out] == [
            (-NS, 48.11749), (0, 48.1175), (0, 48.11751), (NS, 48.11752)], poll
        assert [f.leap_second for f, _ in out] == [False, True, False, False]
    # Live, gpsd's socket is polled between TPVs: the settle time passed before the repeat came, and 23:59:60 was
    # reported unflagged under 00:00:00's time (a second off on the clock). On a day a leap second may end, the
    # midnight second's epoch waits for its repeat; any other day's goes out after the settle time as usual.
    e = GpsdEpochs()
    e.push(tpv(midnight, lat=48.1175), NS)
    assert e.poll(NS + 400_000_000) == [] and e.due_ns() == NS + LEAP_HOLD_NS
    (fix, _), = e.poll(NS + LEAP_HOLD_NS)  # no repeat: this year had no leap second
    assert not fix.leap_second
    other_day = calendar.timegm((2026, 1, 2, 0, 0, 0)) * NS
    e = GpsdEpochs()
    e.push(tpv(other_day), NS)
    assert len(e.poll(NS + 400_000_000)) == 1
    # a TPV of a midnight completing its epoch (within the burst) is no second epoch
    e = GpsdEpochs()
    out = e.push(tpv(midnight), 0) + e.push(tpv(midnight, epv=3.0), 200_000_000) + e.flush()
    assert len(out) == 1


def test_no_fix_tpvs_without_time_are_one_record_per_cycle() -> None:
    # gpsd reports no fix as mode-1 TPVs without a time; at 5 Hz they came closer than the settle time and a whole
    # outage was one record
    e = GpsdEpochs()
    e.push({**NMEA_DEVICE, "cycle": 0.2}, 0)
    out = []
    for k in range(50):
        out += e.push({"class": "TPV", "device": "/dev/ttyACM0", "mode": 1}, k * NS // 5)
        out += e.poll(k * NS // 5 + NS // 10)
    out += e.push(tpv(T0 + 10 * NS), 10 * NS) + e.flush()
    assert [f.fix_mode for f, _ in out] == [1] * 50 + [3]


def test_the_epoch_open_when_gpsd_closes_the_socket_is_recorded() -> None:
    server = SimGpsd(devices=[UBLOX_DEVICE]).start()
    src = GpsdSource(*server.address, None, host_timebase(), settle_s=5.0)  # nothing completes by settling
    try:
        src.open()
        assert server.wait_for_watchers()
        server.publish(tpv(T0 + NS))
        server.publish(tpv(T0 + 2 * NS))  # completes the first; the second stays open
        got = read_until(src.read, lambda o: len(o) >= 1)
        server.stop()  # gpsd restarted: the socket closes with the epoch of T0 + 2 s still open
        with pytest.raises(SensorError):
            read_until(src.read, lambda o: False, timeout_s=5.0)
        src.close()
        server.start()
        src.open()
        got += read_until(src.read, lambda o: len(o) >= 1)
    finally:
        src.close()
        server.stop()
    assert [r.payload["gnss_time_ns"] for r in got] == [T0 + NS, T0 + 2 * NS]


def _open_once_listening(source: GpsdSource) -> None:
    """Open the source on a gpsd just started (it listens a moment after its start), within 10 s."""
    end = time.monotonic() + 10.0
    while True:
        try:
            source.open()
            return
        except SensorError:
            if time.monotonic() > end:
                raise
            time.sleep(0.05)


def test_a_slow_nmea_line_through_a_real_gpsd_pairs_each_fix_with_its_own_pulse() -> None:
    """A real gpsd 3.22 reading a real u-blox M9N's NMEA (the GPSD project's capture, about 1.5 kB an epoch) on a
    pty, each epoch written in three parts at 0.35, 0.7 and 1.05 s after its pulse, as a 9600-baud line brings it:
    gpsd's TPV comes after the next pulse, its TOFF (the epoch's time latched at its first sentence) before it.
    Our source's records and PPS edges at each pulse, through the clock: every fix gpsd sent a TOFF for records
    that read as its opened time, and the clock locks to the right second (without the TOFF the pairing took
    each fix's completion, after the next edge: a clock a second off behind a bound of microseconds). The filter,
    before the clock locks, places each epoch on its own pulse by the same TOFF (by the completion, a second late).
    The drive runs at twice the host's pace (gpsd goes by the sentences' times, not by when they come)."""
    import os
    import pty
    import tty

    from logger.recording.records import clock_observer
    from logger.recording.topics import GNSS_FIX, PPS

    if shutil.which("gpsd") is None:
        pytest.skip("gpsd is not installed")
    capture = strip_capture_comments(
        (Path(__file__).parent / "data" / "gpsd-ublox" / "ublox-neo-m9n-nmea.log").read_bytes())
    epochs = [b"$GNRMC" + part for part in capture.split(b"$GNRMC")[1:]][:16]
    first_utc_s = calendar.timegm((2020, 7, 11, 22, 37, 45))  # the capture's first epoch, 223745.00 on 110720
    scale = 2.0
    host0 = time.monotonic_ns()

    def drive_ns() -> int:
        return round((time.monotonic_ns() - host0) * scale)

    t0 = 2 * NS  # drive time of the first epoch's pulse: gpsd is listening by then
    master, slave = pty.openpty()
    tty.setraw(slave)
    os.chmod(os.ttyname(slave), 0o666)  # gpsd drops root for its own user before it opens the device
    port = _free_port()
    gpsd = subprocess.Popen(["gpsd", "-N", "-n", "-b", "-S", str(port), "-s", "9600", os.ttyname(slave)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    source = GpsdSource("127.0.0.1", port, None, TimeBase(drive_ns, scale))
    done = threading.Event()

    def feed() -> None:
        try:
            for k, epoch in enumerate(epochs):
                third = len(epoch) // 3
                for j, piece in enumerate((epoch[:third], epoch[third:2 * third], epoch[2 * third:])):
                    at = t0 + k * NS + (350 + 350 * j) * 1_000_000
                    time.sleep(max(0.0, (at - drive_ns()) / NS / scale))
                    os.write(master, piece)
        finally:
            done.set()

    records: list[tuple[int, dict[str, Any]]] = []
    try:
        _open_once_listening(source)
        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        stop_at = None
        while stop_at is None or drive_ns() < stop_at:
            records += [(r.t_mono_ns, r.payload) for r in source.read() if r.topic == GNSS_FIX]
            if done.is_set() and stop_at is None:
                stop_at = drive_ns() + 2 * NS
        feeder.join()
    finally:
        source.close()
        gpsd.terminate()
        gpsd.wait(timeout=10)
        os.close(master)
        os.close(slave)
    fixes = [(t, fix) for t, fix in records if fix.get("gnss_time_ns") is not None]
    assert len(fixes) >= 14, records
    opened = late = 0
    for t, fix in fixes:
        k = round(fix["gnss_time_ns"] / NS - first_utc_s)
        pulse = t0 + k * NS
        late += t - pulse > NS  # gpsd reported the first epoch at its RMC, every later one at its end (1.05 s)
        if "opened_mono_ns" in fix:
            opened += 1
            assert 350_000_000 <= fix["opened_mono_ns"] - pulse < 700_000_000, (k, fix["opened_mono_ns"] - pulse)
    assert late >= len(fixes) - 2 and opened >= len(fixes) - 4, (late, opened)  # no TOFF for gpsd's first fix
    now = [0]
    clock = PpsClock(monotonic_ns=lambda: now[0], wall_ns=lambda: 0)
    observe = clock_observer(clock)
    events = [(t0 + k * NS + 7_000, PPS, {"gnss_time_ns": None}) for k in range(len(epochs))]
    events += [(t, GNSS_FIX, fix) for t, fix in records]
    for t, topic, payload in sorted(events, key=lambda e: e[0]):
        now[0] = t
        observe[topic](payload, t)
    probe = t0 + (len(epochs) - 1) * NS + 500_000_000
    now[0] = probe
    stamp = clock.stamp(probe)
    assert stamp.state == "locked", stamp
    assert abs(stamp.t_sync_ns - ((first_utc_s + len(epochs) - 1) * NS + 500_000_000)) < 1_000_000, stamp
    # The same records to the filter before the clock locks (its synchronised scale the board's here, the PPS edges
    # known): each epoch placed by the read its first sentence came in (gpsd's TOFF), on its own pulse; placed by
    # its completion, 1.05 s after its pulse, every one was a second late.
    from logger.nav.engine import NavEngine
    from logger.nav.params import NavParams
    from logger.recording.records import feed_record, nav_feeder

    engine = NavEngine(NavParams(mode="17"))
    feed = nav_feeder(engine)
    placed = []
    events = [(t0 + k * NS + 7_000, "/pps", {}) for k in range(len(epochs))]
    events += [(t, "/gnss/fix", fix) for t, fix in fixes if "opened_mono_ns" in fix and fix.get("fix_ok")]
    for t, topic, payload in sorted(events, key=lambda e: e[0]):
        feed_record(feed, topic, {**payload, "t_sync_ns": t, "t_mono_ns": t, "sync_state": "freerun"})
        if topic == "/gnss/fix":
            k = round(payload["gnss_time_ns"] / NS - first_utc_s)
            placed.append(engine.last_readings.fix.t_ns - (t0 + k * NS))
    assert len(placed) >= len(fixes) - 4 and engine.epoch_clock.method == "pps"
    assert all(abs(d - 7_000) < 1_000_000 for d in placed), placed


def test_the_first_tpv_of_a_burst_before_the_date_is_known_joins_its_epoch() -> None:
    """gpsd 3.22 reading an NMEA receiver (GGA, RMC, GSA; GP talker) from its first burst: a 3D TPV without a time
    at the GGA (no date yet), then the timed TPVs of the same epoch 67 and 134 ms later (measured). One fix, with
    its time; before, the first was a record of its own, fix_ok and no time, the same position again after it."""
    e = GpsdEpochs()
    e.push({**NMEA_DEVICE, "cycle": 1.0}, 0)
    first = {k: v for k, v in tpv(T0).items() if k != "time"}
    out = e.push(first, 0)
    out += e.push({**tpv(T0), "speed": 10.0}, 67_000_000) + e.push(tpv(T0), 134_000_000)
    out += e.push(tpv(T0 + NS), NS) + e.flush()
    assert [f.time_utc_ns for f, _ in out] == [T0, T0 + NS]
    assert out[0][1] == 134_000_000 and out[0][0].fix_ok
    # A TPV without a time a cycle before a timed one is another cycle's (gpsd without a fix): its own record.
    e = GpsdEpochs()
    e.push({**NMEA_DEVICE, "cycle": 1.0}, 0)
    out = e.push({"class": "TPV", "device": "/dev/ttyACM0", "mode": 1}, 0) + e.push(tpv(T0), 950_000_000)
    out += e.flush()
    assert [(f.fix_mode, f.time_utc_ns) for f, _ in out] == [(1, None), (3, T0)]


def test_a_no_fix_tpv_under_the_last_fixed_epochs_time_leaves_that_fix_as_it_was() -> None:
    """gpsd 3.22 at 10 Hz, the receiver's time fields going empty: the 3D TPV of 27.700, then 89 ms later a mode-1
    TPV with no position under the same time (gpsd keeps the last one), then mode-1 TPVs without a time. The 27.7
    fix is recorded as the fix it was; merged, it became a no-fix without a time and the last fix was lost."""
    e = GpsdEpochs()
    e.push({**NMEA_DEVICE, "cycle": 0.1}, 0)
    out = e.push(tpv(T0), 762_000_000)
    out += e.push({"class": "TPV", "device": "/dev/ttyACM0", "mode": 1, "time": iso(T0)}, 851_000_000)
    out += e.push({"class": "TPV", "device": "/dev/ttyACM0", "mode": 1}, 951_000_000) + e.flush()
    assert [(f.fix_mode, f.fix_ok, f.time_utc_ns) for f, _ in out] == [(3, True, T0), (1, False, None)]
    assert e.counters.lost_fix == 1


def test_the_receivers_cycle_is_learnt_from_its_timed_epochs() -> None:
    """gpsd's DEVICE cycle is 1.00 s for any NMEA receiver: at 10 Hz the reports without a time (three an epoch,
    one per sentence) are one record an epoch once the timed epochs showed 0.1 s; a loss between two timed epochs
    is no cycle, and a receiver never seen with a time keeps gpsd's figure."""
    def loss(e: GpsdEpochs, t0_ns: int) -> list[tuple[Any, int]]:
        out = []
        for k in range(10):
            for j in range(3):
                t = t0_ns + k * NS // 10 + j * 100_000
                out += e.push({"class": "TPV", "device": "/dev/ttyACM0", "mode": 1}, t) + e.poll(t)
        return out

    e = GpsdEpochs()
    e.push(NMEA_DEVICE, 0)
    out = []
    for k in range(5):
        out += e.push(tpv(T0 + k * NS // 10), k * NS // 10)
    out += loss(e, NS // 2) + e.push(tpv(T0 + 3 * NS), 3 * NS) + e.flush()
    assert [f.fix_mode for f, _ in out] == [3] * 5 + [1] * 10 + [3]
    # the loss's interval (0.4 -> 3.0 s) taught nothing: the next loss is again one record an epoch
    out = loss(e, 4 * NS) + e.flush()
    assert len(out) == 10
    e = GpsdEpochs()
    e.push(NMEA_DEVICE, 0)
    assert len(loss(e, 0) + e.flush()) == 2  # never a time: gpsd's cycle, 0.9 s of it an epoch (10 epochs over 0.9 s)


def test_a_receiver_behind_gpsd_is_expected_at_its_configured_rate(tmp_path: Path) -> None:
    """The status judges the gnss sensor by the rate the receiver is set to: one behind gpsd was expected at 1 Hz
    whatever ``[gnss] rate_hz`` said (a 10 Hz receiver showed "10.0/1", and a 5 Hz one silent for 3.4 s was ok)."""
    from logger.compose import plans_from_config

    cfg = parse(f'[logger]\nstate_dir = "{tmp_path}"\n[gnss]\nsource = "gpsd"\nrate_hz = 5\n[pps]\nsource = "none"\n'
                '[obd]\nsource = "can"\n', "logger.toml")  # nothing is opened: the plans only
    (plan,) = [p for p in plans_from_config(cfg, host_timebase()) if isinstance(p.source, GpsdSource)]
    assert plan.expected_hz == 5


def test_a_burst_of_tpvs_without_time_filling_the_cycle_is_one_record() -> None:
    """gpsd 3.22 reading u-blox's factory NMEA at 9600 baud from a receiver without time: a TPV per sentence from
    0.05 s to 0.89 s of each second. One record a second; a window of half the cycle (at most 0.3 s) cut each
    second's burst in two records ("no fix 2.0/1" in the status)."""
    e = GpsdEpochs()
    e.push({**NMEA_DEVICE, "cycle": 1.0}, 0)
    out = []
    for k in range(12):
        for j in range(13):
            t = k * NS + (50 + 70 * j) * 1_000_000
            out += e.push({"class": "TPV", "device": "/dev/ttyACM0", "mode": 1 if j % 2 else 0}, t) + e.poll(t)
    out += e.flush()
    assert len(out) == 12 and not any(f.fix_ok for f, _ in out), len(out)
    # gpsd started in the middle of a burst, reporting per sentence (before it has learnt which sentence ends the
    # cycle): its last report of that burst is a position without a date, the next burst's first one 0.17 s later
    # has the time. One fix, with it, not a fix without. (Where gpsd reports at the cycle's end, a second after
    # the untimed one, that burst stays a fix of its own without a time: its epoch cannot be told.)
    e = GpsdEpochs()
    e.push({**NMEA_DEVICE, "cycle": 1.0}, 0)
    out = e.push({k: v for k, v in tpv(T0).items() if k != "time"}, 930_000_000)
    out += e.push(tpv(T0 + NS), 1_100_000_000) + e.push(tpv(T0 + 2 * NS), 2_100_000_000) + e.flush()
    assert [f.time_utc_ns for f, _ in out] == [T0 + NS, T0 + 2 * NS]


def test_only_a_fix_without_a_time_joins_the_timed_epoch_and_a_lost_fix_is_no_leap_second() -> None:
    """The second reading's three cases (gpsd's DEVICE cycle 1.0 s, as for an NMEA receiver it cannot query):
    A, an untimed fix merged into the timed 00:00:00 of 1 January counted its arrival as the epoch's first, and
    gpsd's later report of that epoch 0.65 s after it was taken for a leap second's repeat; B, untimed no-fix reports
    of a 0.4 s loss merged into the recovered fix (no record of the loss; its accuracy gpsd's 4294967 m); C, a
    no-fix report under 00:00:00 a second later (the receiver's time fields gone empty) was a leap second."""
    midnight = calendar.timegm((2027, 1, 1, 0, 0, 0)) * NS
    untimed = {k: v for k, v in tpv(midnight).items() if k != "time"}
    e = GpsdEpochs()
    e.push(NMEA_DEVICE, 0)
    out = e.push(untimed, 1_000_000_000) + e.push(tpv(midnight), 1_500_000_000) + e.push(tpv(midnight), 1_650_000_000)
    out += e.flush()
    assert [(f.time_utc_ns, f.leap_second) for f, _ in out] == [(midnight, False)]
    e = GpsdEpochs()
    e.push(UBLOX_DEVICE, 0)
    out = e.push(tpv(T0, eph=2.5), 100_000_000)
    out += e.push({"class": "TPV", "device": "/dev/ttyACM0", "mode": 1, "time": iso(T0)}, 189_000_000)
    for k in range(2, 5):
        out += e.push({"class": "TPV", "device": "/dev/ttyACM0", "mode": 1, "eph": 4294967.0}, k * 100_000_000)
    out += e.push(tpv(T0 + NS // 2, eph=3.0), 600_000_000) + e.flush()
    assert [(f.fix_ok, f.time_utc_ns) for f, _ in out] == [(True, T0), (False, None), (True, T0 + NS // 2)]
    assert out[2][0].h_acc_m is not None and out[2][0].h_acc_m < 10
    e = GpsdEpochs()
    e.push(NMEA_DEVICE, 0)
    out = e.push(tpv(midnight), 100_000_000) + e.poll(500_000_000)
    out += e.push({"class": "TPV", "device": "/dev/ttyACM0", "mode": 1, "time": iso(midnight)}, 1_100_000_000)
    out += e.flush()
    assert [(f.fix_ok, f.leap_second) for f, _ in out] == [(True, False)] and e.counters.lost_fix == 1


def _nmea(body: str) -> bytes:
    """One NMEA sentence with its checksum and line end."""
    cs = 0
    for ch in body.encode():
        cs ^= ch
    return f"${body}*{cs:02X}\r\n".encode()


def _nmea_epoch(utc_s: float | None, k: int) -> bytes:
    """RMC, GGA and GSA of one epoch of an NMEA-only receiver (GN talker, as a u-blox M8 or later): a 3D fix at
    ``utc_s`` moving north by a metre an epoch, or, with no time, no fix and every time field empty (a receiver
    that lost its fix and its time, as after a cold start or a long tunnel)."""
    if utc_s is None:
        return (_nmea("GNRMC,,V,,,,,,,,,,N,V") + _nmea("GNGGA,,,,,,0,00,99.99,,,,,,")
                + _nmea("GNGSA,A,1,,,,,,,,,,,,,99.99,99.99,99.99,1"))
    t = dt.datetime.fromtimestamp(utc_s, dt.UTC)
    hms, date = f"{t:%H%M%S}.{t.microsecond // 10_000:02d}", f"{t:%d%m%y}"
    lat = f"4717.{11399 + 54 * k:05d}"  # 1e-5 minute is 1.85 cm
    return (_nmea(f"GNRMC,{hms},A,{lat},N,00833.91590,E,1.944,0.00,{date},,,A,V")
            + _nmea(f"GNGGA,{hms},{lat},N,00833.91590,E,1,12,0.80,499.6,M,48.0,M,,")
            + _nmea("GNGSA,A,3,01,02,03,04,05,06,07,08,,,,,1.50,0.80,1.27,1"))


def _gpsd_through_a_time_loss(rate_hz: int, before: int, lost: int, after: int
                              ) -> tuple[list[float], list[dict[str, Any]], Any]:
    """A real gpsd reading an NMEA receiver on a pty at ``rate_hz``: ``before`` epochs with a fix, ``lost``
    without fix or time, ``after`` with a fix again, each epoch's sentences written 20 ms after its time, at the
    host's pace (gpsd tells its cycle by when sentences come). Returns the fixed epochs' times (s), our source's
    /gnss/fix records in order, and its epoch assembler's counters."""
    import pty
    import tty

    from logger.recording.topics import GNSS_FIX

    period = 1.0 / rate_hz
    first_utc_s = calendar.timegm((2026, 12, 7, 10, 0, 0))
    plan = [first_utc_s + k * period if not before <= k < before + lost else None
            for k in range(before + lost + after)]
    master, slave = pty.openpty()
    tty.setraw(slave)
    os.chmod(os.ttyname(slave), 0o666)  # gpsd drops root for its own user before it opens the device
    port = _free_port()
    gpsd = subprocess.Popen(["gpsd", "-N", "-n", "-b", "-S", str(port), "-s", "115200", os.ttyname(slave)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    source = GpsdSource("127.0.0.1", port, None, host_timebase())
    records: list[dict[str, Any]] = []
    try:
        _open_once_listening(source)
        start = time.monotonic() + 0.5
        done = threading.Event()

        def feed() -> None:  # its own thread: a read waits for gpsd's next report
            try:
                for k, utc_s in enumerate(plan):
                    time.sleep(max(0.0, start + k * period + 0.02 - time.monotonic()))
                    os.write(master, _nmea_epoch(utc_s, k))
            finally:
                done.set()

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        quiet_until = None
        while quiet_until is None or time.monotonic() < quiet_until:
            records += [r.payload for r in source.read() if r.topic == GNSS_FIX]
            if done.is_set() and quiet_until is None:
                quiet_until = time.monotonic() + 2.0 + 2 * period
        feeder.join()
        counters = source.epochs.counters
    finally:
        source.close()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(gpsd.pid, signal.SIGTERM)
        gpsd.wait(timeout=10)
        os.close(master)
        os.close(slave)
    return [u for u in plan if u is not None], records, counters


TIME_LOSS_CASES = [(10, 25, 10, 25), (1, 3, 3, 3)]  # rate (Hz), epochs with a fix, without, with again


@pytest.fixture(scope="module")
def time_losses() -> dict[tuple[int, int, int, int], tuple[list[float], list[dict[str, Any]], Any]]:
    """Each case through its own gpsd, at once (each is paced by the clock, not by the CPU)."""
    if _gpsfake_missing():  # gpsd itself; gpsfake is not used, but the same package brings both
        pytest.skip("gpsd is not installed")
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(len(TIME_LOSS_CASES)) as pool:
        return dict(zip(TIME_LOSS_CASES, pool.map(lambda c: _gpsd_through_a_time_loss(*c), TIME_LOSS_CASES),
                        strict=True))


@pytest.mark.parametrize(("rate_hz", "before", "lost", "after"), TIME_LOSS_CASES)
def test_a_receiver_losing_fix_and_time_through_a_real_gpsd_is_one_record_an_epoch(
        time_losses, rate_hz: int, before: int, lost: int, after: int) -> None:
    """A real gpsd 3.22 and an NMEA receiver whose fix and time go away for a while (every time field empty)
    and come back: every fixed epoch recorded once, with its time; the loss as one no-fix record an epoch
    (give or take the one at each edge), none of them a fix. gpsd 3.22 says "cycle": 1.00 for an NMEA receiver
    at 10 Hz too, and reports a TPV per sentence: before the cycle was learnt from the timed epochs, a second of
    the loss at 10 Hz was one record (10 epochs, 2 records)."""
    fixed_s, records, counters = time_losses[(rate_hz, before, lost, after)]
    timed = [r for r in records if r.get("gnss_time_ns") is not None]
    untimed = [r for r in records if r.get("gnss_time_ns") is None]
    times = [r["gnss_time_ns"] for r in timed]
    assert len(times) == len(set(times)), "an epoch recorded twice"
    assert all(r["fix_ok"] for r in timed) and not any(r["fix_ok"] for r in untimed), records
    expected = {round(u * NS) for u in fixed_s}
    assert set(times) <= expected
    first_after = round(fixed_s[before] * NS)
    # gpsd may start reporting an epoch or two into the stream; from then on, nothing is missing
    assert {t for t in expected if round(fixed_s[2] * NS) <= t} <= set(times), sorted(expected - set(times))
    assert lost - 1 <= len(untimed) <= lost + 1, [(r.get("fix_mode"), r.get("gnss_time_ns")) for r in records]
    # the loss's records sit between the last fix before it and the first after it
    order = [r.get("gnss_time_ns") for r in records]
    i_last_before = order.index(round(fixed_s[before - 1] * NS))
    i_first_after = order.index(first_after)
    assert all(t is None for t in order[i_last_before + 1:i_first_after])
    assert counters.epochs >= len(records) - 1
