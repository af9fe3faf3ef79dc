"""The solution at a late measurement's own instant: between two history entries, and after the newest."""

from __future__ import annotations

import math

from logger.nav import earth
from logger.nav.history import HISTORY_S, NS, SolutionHistory
from logger.nav.state import NavState

LAT, LON, H = math.radians(48.0), math.radians(11.0), 500.0
A_N = 2.0  # m/s^2 north: a car pulling away
V0 = 10.0
STEP_NS = 50_000_000  # a 20 Hz IMU's entries


def truth(t_s: float) -> tuple[float, float, float, float]:
    """Latitude, longitude, height and north velocity of the accelerating car at ``t_s``."""
    lat, lon, h = earth.offset_llh(LAT, LON, H, V0 * t_s + 0.5 * A_N * t_s * t_s, 0.0, 0.0)
    return lat, lon, h, V0 + A_N * t_s


def history_of(n: int) -> SolutionHistory:
    hist = SolutionHistory()
    for i in range(n):
        lat, lon, h, vn = truth(i * STEP_NS / NS)
        hist.add(i * STEP_NS, NavState(lat, lon, h, vn))
    return hist


def north_m(s: NavState, t_s: float) -> float:
    """How far north of the truth at ``t_s`` the solution ``s`` is, m."""
    lat, lon, h, _ = truth(t_s)
    return earth.ned_offset_m(lat, lon, h, s.lat, s.lon, s.h)[0]


def test_between_two_entries_the_solution_is_the_one_between_them_not_the_earlier_carried_on() -> None:
    hist = history_of(5)
    current = NavState(LAT, LON, H)
    t_ns = 2 * STEP_NS + STEP_NS // 2  # a fix epoch halfway between two IMU samples
    s = hist.state_at(t_ns, current)
    t_s = t_ns / NS
    # The earlier entry carried on its velocity says 10.2 m/s; the car does 10.25 at that instant.
    assert abs(s.vn - truth(t_s)[3]) < 1e-9
    assert abs(north_m(s, t_s)) < 1e-3  # the chord's sag over 50 ms at 2 m/s^2: 0.6 mm
    at_entry = hist.state_at(3 * STEP_NS, current)
    assert abs(at_entry.vn - truth(3 * STEP_NS / NS)[3]) < 1e-12
    assert abs(north_m(at_entry, 3 * STEP_NS / NS)) < 1e-6


def test_corrections_fed_back_between_the_entries_are_taken_out_of_each() -> None:
    hist = SolutionHistory()
    lat, lon, h, vn = truth(0.0)
    hist.add(0, NavState(lat, lon, h, vn))
    # A correction of 1 m north and 0.5 m/s: the nominal moved; the next entry was integrated after it.
    hist.fed_back([1.0, 0.0, 0.0, 0.5, 0.0, 0.0])
    lat1, lon1, h1, vn1 = truth(STEP_NS / NS)
    lat1, lon1, h1 = earth.offset_llh(lat1, lon1, h1, -1.0, 0.0, 0.0)  # nominal = truth - 1 m after the fix
    hist.add(STEP_NS, NavState(lat1, lon1, h1, vn1 - 0.5))
    s = hist.state_at(STEP_NS // 2, NavState(LAT, LON, H))
    # Both entries, corrected for what came after each, are the truth minus the one correction.
    assert abs(north_m(s, STEP_NS / 2 / NS) + 1.0) < 1e-3
    assert abs(s.vn - (truth(STEP_NS / 2 / NS)[3] - 0.5)) < 1e-9


def test_after_the_newest_entry_it_is_carried_on_its_velocity() -> None:
    hist = history_of(3)
    t_ns = 2 * STEP_NS + 20_000_000
    s = hist.state_at(t_ns, NavState(LAT, LON, H))
    lat, lon, h, vn = truth(2 * STEP_NS / NS)
    assert s.vn == vn
    dn = earth.ned_offset_m(lat, lon, h, s.lat, s.lon, s.h)[0]
    assert abs(dn - vn * 0.02) < 1e-6


def test_the_history_keeps_the_last_ten_seconds_not_minutes_of_a_slow_imu() -> None:
    hist = history_of(20 * 60)  # a minute at 20 Hz: the sample bound alone keeps every one
    newest = (20 * 60 - 1) * STEP_NS
    hist.trim(newest)
    assert hist.entries[0][0] >= newest - int(HISTORY_S * NS)
    assert len(hist.entries) == 20 * 10 + 1
    t_ns = newest - 2 * NS + STEP_NS // 2  # a fix two seconds late is still judged between its own entries
    s = hist.state_at(t_ns, NavState(LAT, LON, H))
    assert abs(s.vn - truth(t_ns / NS)[3]) < 1e-9
