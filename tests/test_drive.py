"""The vehicle truth: a perfect INS reproduces it, its derivatives agree, and the scenarios hold what they say."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensors.sim import earth
from sensors.sim.drive import Drive, RouteBuilder, SmoothSteps
from sensors.sim.scenarios import INTRO_S, SCENARIOS, make_drive


@pytest.fixture(scope="module")
def urban() -> Drive:
    return make_drive("urban", seed=1)


def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _nav_rates(x: np.ndarray, f_body: np.ndarray, w_body: np.ndarray) -> np.ndarray:
    """Strapdown mechanisation in NED on WGS-84: d/dt of (lat, lon, h, v_ned, C_b^n)."""
    lat, h, v = x[0], x[2], x[3:6]
    c = x[6:].reshape(3, 3)
    rn, re = earth.radii(lat)
    w_ie = earth.earth_rate_ned(lat)
    w_en = earth.transport_rate_ned(lat, h, v)
    dc = c @ _skew(w_body) - _skew(w_ie + w_en) @ c
    dv = c @ f_body - np.cross(2.0 * w_ie + w_en, v) + earth.gravity_ned(lat, h)
    return np.concatenate(([v[0] / (rn + h), v[1] / ((re + h) * math.cos(lat)), -v[2]], dv, dc.ravel()))


def strapdown(drive: Drive, t0: float, duration: float, dt: float = 0.02) -> tuple[np.ndarray, ...]:
    """Integrate ideal IMU output (RK4, sensors sampled at the step ends and middle) from the truth at t0."""
    s = drive.state(t0)
    x = np.concatenate(([s.lat_rad, s.lon_rad, s.height_m], s.vel_ned_mps, earth.dcm_body_to_ned(s.rpy_rad).ravel()))
    t = t0
    for _ in range(round(duration / dt)):
        a, m, b = drive.state(t), drive.state(t + dt / 2), drive.state(t + dt)
        k1 = _nav_rates(x, a.f_body_mps2, a.w_body_rps)
        k2 = _nav_rates(x + dt / 2 * k1, m.f_body_mps2, m.w_body_rps)
        k3 = _nav_rates(x + dt / 2 * k2, m.f_body_mps2, m.w_body_rps)
        k4 = _nav_rates(x + dt * k3, b.f_body_mps2, b.w_body_rps)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += dt
    s = drive.state(t)
    rn, re = earth.radii(s.lat_rad)
    pos_err = np.array([(x[0] - s.lat_rad) * (rn + s.height_m),
                        (x[1] - s.lon_rad) * (re + s.height_m) * math.cos(s.lat_rad), x[2] - s.height_m])
    vel_err = x[3:6] - s.vel_ned_mps
    e = x[6:].reshape(3, 3) @ earth.dcm_body_to_ned(s.rpy_rad).T - np.eye(3)
    return pos_err, vel_err, np.array([e[2, 1], e[0, 2], e[1, 0]])


def _window(drive: Drive, what: str) -> float:
    if what == "turn":
        return drive.spans_of("turn")[0].start_s - 40.0  # pull-away, a junction turn, acceleration
    if what == "tunnel":
        return drive.spans_of("tunnel")[1].start_s  # dip down and up with a curve and counter-curve
    return drive.spans_of("grade")[0].start_s - 5.0  # a hill at speed


@pytest.mark.parametrize("what", ["turn", "tunnel", "hill"])
def test_perfect_strapdown_reproduces_the_trajectory_over_a_minute(urban, what):
    pos_err, vel_err, att_err = strapdown(urban, _window(urban, what), 60.0)
    # Leaving out Coriolis, transport rate or earth rate would cost metres here, not millimetres.
    assert np.abs(pos_err).max() < 1e-3
    assert np.abs(vel_err).max() < 1e-4
    assert np.abs(att_err).max() < 1e-6


def test_velocity_is_the_derivative_of_position(urban):
    h = 1e-3
    for t in np.random.default_rng(0).uniform(0.0, urban.duration_s, 300):
        a, s, b = urban.state(t - h), urban.state(t), urban.state(t + h)
        rn, re = earth.radii(s.lat_rad)
        v_fd = np.array([(b.lat_rad - a.lat_rad) * (rn + s.height_m),
                         (b.lon_rad - a.lon_rad) * (re + s.height_m) * math.cos(s.lat_rad),
                         -(b.height_m - a.height_m)]) / (2 * h)
        # Central differences of float64 longitudes resolve about 1 um/s at this step.
        assert np.abs(v_fd - s.vel_ned_mps).max() < 5e-6


def test_position_is_the_integral_of_velocity(urban):
    for t0 in np.random.default_rng(2).uniform(0.0, urban.duration_s - 2.0, 40):
        ts = np.linspace(t0, t0 + 2.0, 201)
        states = [urban.state(t) for t in ts]
        rates = np.array([[s.vel_ned_mps[0] / (earth.radii(s.lat_rad)[0] + s.height_m),
                           s.vel_ned_mps[1] / ((earth.radii(s.lat_rad)[1] + s.height_m) * math.cos(s.lat_rad)),
                           -s.vel_ned_mps[2]] for s in states])
        w = np.ones(201)
        w[1:-1:2], w[2:-1:2] = 4.0, 2.0
        travelled = (ts[1] - ts[0]) / 3.0 * (w @ rates)  # Simpson
        a, b = states[0], states[-1]
        rn, re = earth.radii(a.lat_rad)
        err_m = (np.array([b.lat_rad - a.lat_rad, b.lon_rad - a.lon_rad, b.height_m - a.height_m]) - travelled) \
            * np.array([rn, re * math.cos(a.lat_rad), 1.0])
        assert np.abs(err_m).max() < 1e-6


def test_specific_force_and_rate_are_the_derivatives_of_velocity_and_attitude(urban):
    h = 1e-4
    for t in np.random.default_rng(1).uniform(0.0, urban.duration_s, 300):
        a, s, b = urban.state(t - h), urban.state(t), urban.state(t + h)
        c = earth.dcm_body_to_ned(s.rpy_rad)
        w_ie = earth.earth_rate_ned(s.lat_rad)
        w_en = earth.transport_rate_ned(s.lat_rad, s.height_m, s.vel_ned_mps)
        dv = (b.vel_ned_mps - a.vel_ned_mps) / (2 * h)
        f_nav = dv + np.cross(2 * w_ie + w_en, s.vel_ned_mps) - earth.gravity_ned(s.lat_rad, s.height_m)
        assert np.abs(c @ s.f_body_mps2 - f_nav).max() < 1e-5
        dc = (earth.dcm_body_to_ned(b.rpy_rad) - earth.dcm_body_to_ned(a.rpy_rad)) / (2 * h)
        w_nb = c.T @ dc  # skew(omega_nb^b)
        w_fd = np.array([w_nb[2, 1], w_nb[0, 2], w_nb[1, 0]]) + c.T @ (w_ie + w_en)
        assert np.abs(w_fd - s.w_body_rps).max() < 1e-6


def test_standing_still_senses_only_gravity_and_earth_rate(urban):
    stop = urban.spans_of("stop")[0]
    s = urban.state(0.5 * (stop.start_s + stop.end_s))
    c = earth.dcm_body_to_ned(s.rpy_rad)
    assert np.all(s.vel_ned_mps == 0.0) and s.forward_speed_mps == 0.0
    np.testing.assert_allclose(c @ s.f_body_mps2, -earth.gravity_ned(s.lat_rad, s.height_m), atol=1e-12)
    np.testing.assert_allclose(c @ s.w_body_rps, earth.earth_rate_ned(s.lat_rad), atol=1e-15)


def _sample(drive: Drive, dt: float = 0.1) -> dict[str, np.ndarray]:
    ts = np.arange(0.0, drive.duration_s, dt)
    states = [drive.state(t) for t in ts]
    return {
        "t": ts,
        "v": np.array([s.forward_speed_mps for s in states]),
        "yaw": np.unwrap([s.rpy_rad[2] for s in states]),
        "pitch": np.array([s.rpy_rad[1] for s in states]),
        "roll": np.array([s.rpy_rad[0] for s in states]),
        "sky": np.array([s.sky_open for s in states]),
        "engine": np.array([s.engine_on for s in states]),
        "f_y": np.array([s.f_body_mps2[1] for s in states]),
        "w_z": np.array([s.w_body_rps[2] for s in states]),
    }


def test_urban_drive_has_what_the_scenario_promises(urban):
    d = _sample(urban)
    assert 10 * 60 <= urban.duration_s <= 30 * 60
    assert d["v"].min() >= 0.0 and d["v"].max() <= 60 / 3.6
    acc = np.gradient(d["v"], d["t"])
    assert np.abs(acc).max() < 3.0
    lateral = d["v"] * np.gradient(d["yaw"], d["t"])
    assert np.abs(lateral).max() < 4.0 and np.abs(d["f_y"]).max() < 4.0
    assert np.abs(d["roll"]).max() < math.radians(2.0)
    # Four right-angle junction turns, at realistic yaw rates.
    turns = urban.spans_of("turn")
    assert len(turns) == 4
    for turn in turns:
        before, after = urban.state(turn.start_s), urban.state(turn.end_s)
        turned = math.remainder(after.rpy_rad[2] - before.rpy_rad[2], 2 * math.pi)
        assert turned == pytest.approx(math.pi / 2, abs=1e-9)
    assert math.radians(15) < np.abs(d["w_z"]).max() < math.radians(40)
    # Traffic-light stops of tens of seconds, exactly still, engine running (three in the first lap, whose
    # opening light is the intro).
    stops = urban.spans_of("stop")
    assert len(stops) >= 3 and all(20.0 <= s.duration_s <= 60.0 for s in stops)
    for s in stops:
        inside = (d["t"] >= s.start_s) & (d["t"] <= s.end_s)
        assert np.all(d["v"][inside] == 0.0) and np.all(d["engine"][inside])
    # Grades of a few percent.
    assert 0.03 <= np.abs(d["pitch"]).max() <= 0.07
    # Two tunnels, dark for exactly their configured times (24 s in all: the paper's Table 8 urban conditions),
    # and street canyons with partial sky.
    tunnels = urban.spans_of("tunnel")
    assert [round(s.duration_s, 6) for s in tunnels] == [10.0, 14.0]
    for s in tunnels:
        inside = (d["t"] >= s.start_s) & (d["t"] <= s.end_s)
        assert np.all(d["sky"][inside] == 0.0)
        assert urban.state(s.start_s - 0.5).sky_open > 0.0 and urban.state(s.end_s + 0.5).sky_open > 0.0
    dark = d["sky"] == 0.0
    assert dark.sum() * 0.1 == pytest.approx(24.0, abs=0.25)
    canyons = urban.spans_of("canyon")
    assert len(canyons) == 2
    for s in canyons:
        inside = (d["t"] >= s.start_s) & (d["t"] <= s.end_s)
        assert np.all((d["sky"][inside] >= 0.3) & (d["sky"][inside] <= 0.8))
        assert np.ptp(d["sky"][inside]) > 0.1
    # Idling at the start (the logger comes up with the ignition) long enough to level, moving off right after,
    # so a one-minute run has the filter running; parked with the engine off at the end.
    intro = urban.spans_of("idle")[0]
    assert intro.start_s == 0.0 and intro.duration_s == pytest.approx(INTRO_S) and urban.state(0.0).engine_on
    assert urban.state(INTRO_S + 7.0).forward_speed_mps > 3.0
    parked = urban.spans_of("parked")
    assert parked[-1].end_s == pytest.approx(urban.duration_s)
    for s in parked:
        inside = (d["t"] >= s.start_s) & (d["t"] < s.end_s)
        assert not np.any(d["engine"][inside]) and np.all(d["v"][inside] == 0.0)
    assert d["engine"].mean() > 0.9


def test_urban_weather_and_geoid(urban):
    first, last = urban.state(0.0), urban.state(urban.duration_s)
    # A 16-minute drive sees the start of the cabin's 20 degC warming over 4 h; a day's drive sees all of it.
    expected = 20.0 * 0.5 * (1 - math.cos(math.pi * urban.duration_s / (4 * 3600.0)))
    assert last.ambient_degc - first.ambient_degc == pytest.approx(expected)
    long = make_drive("urban", seed=0, duration_s=5 * 3600.0)
    assert long.state(long.duration_s).ambient_degc - long.state(0.0).ambient_degc == pytest.approx(20.0)
    drift_hpa_per_h = (last.sea_level_pa - first.sea_level_pa) / 100.0 / (urban.duration_s / 3600.0)
    assert 0.5 <= abs(drift_hpa_per_h) <= 1.5
    assert 95000.0 < first.sea_level_pa < 105000.0
    assert first.height_m - first.height_msl_m == pytest.approx(25.0)
    assert math.degrees(first.lat_rad) == pytest.approx(37.5665)


def test_urban_lap_closes(urban):
    first, last = urban.state(0.0), urban.state(urban.duration_s)
    rn, re = earth.radii(first.lat_rad)
    north = (last.lat_rad - first.lat_rad) * rn
    east = (last.lon_rad - first.lon_rad) * re * math.cos(first.lat_rad)
    assert math.hypot(north, east) < 1.0  # what is left is the ellipsoid's meridian convergence
    assert abs(last.height_m - first.height_m) < 1e-6
    assert math.remainder(last.rpy_rad[2] - first.rpy_rad[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_outage_scenario_is_a_steady_straightish_run():
    drive = make_drive("outage-60s", seed=3)
    (outage,) = drive.spans_of("outage")
    assert outage.duration_s == pytest.approx(60.0)
    for t in np.arange(outage.start_s, outage.end_s, 0.5):
        s = drive.state(t)
        assert s.sky_open == 0.0 and s.forward_speed_mps == pytest.approx(15.0, abs=1e-12)
    d = _sample(drive, 0.5)
    moving = d["v"] > 0.0
    yaw = d["yaw"][moving]
    assert np.ptp(yaw) < math.radians(15.0)
    assert np.all(d["sky"][d["t"] < outage.start_s - 1.0] == 1.0)


def test_tunnel_scenario_has_one_130s_tunnel():
    drive = make_drive("tunnel-130s", seed=4)
    (tunnel,) = drive.spans_of("tunnel")
    assert tunnel.duration_s == pytest.approx(130.0)
    s_in, s_out = drive.state(tunnel.start_s - 1.0), drive.state(tunnel.end_s + 1.0)
    assert s_out.height_m == pytest.approx(s_in.height_m, abs=1e-6)  # the dip comes back up
    assert min(drive.state(t).height_m for t in np.arange(tunnel.start_s, tunnel.end_s, 1.0)) < s_in.height_m - 10


def test_any_duration_by_repeating_the_route():
    drive = make_drive("urban", seed=5, duration_s=2 * 3600.0)
    assert drive.duration_s == 2 * 3600.0
    laps = len(drive.spans_of("turn")) // 4
    assert laps >= 6 and len(drive.spans_of("tunnel")) == 2 * laps
    end = drive.state(drive.duration_s)
    assert not end.engine_on and end.forward_speed_mps == 0.0
    first = drive.state(0.0)
    rn, re = earth.radii(first.lat_rad)
    offset = math.hypot((end.lat_rad - first.lat_rad) * rn,
                        (end.lon_rad - first.lon_rad) * re * math.cos(first.lat_rad))
    assert offset < 10.0
    # Laps are re-drawn, so stops differ from lap to lap.
    assert len({round(s.duration_s, 3) for s in drive.spans_of("stop")}) > 10
    short = make_drive("outage-60s", seed=1, duration_s=100.0)
    assert short.duration_s == 100.0 and short.state(100.0).forward_speed_mps > 0.0


def test_same_seed_same_drive_other_seed_other_drive():
    a, b, c = make_drive("urban", seed=9), make_drive("urban", seed=9), make_drive("urban", seed=10)
    for t in (0.0, 123.4, 456.7, a.duration_s):
        sa, sb = a.state(t), b.state(t)
        assert (sa.lat_rad, sa.lon_rad, sa.height_m, sa.sky_open) == (sb.lat_rad, sb.lon_rad, sb.height_m, sb.sky_open)
        assert np.array_equal(sa.f_body_mps2, sb.f_body_mps2)
    assert a.duration_s != c.duration_s


def test_before_start_and_after_end_the_vehicle_stands_still(urban):
    for t in (-5.0, urban.duration_s + 100.0):
        s = urban.state(t)
        assert s.t_s == t and np.all(s.vel_ned_mps == 0.0)
    assert urban.state(-5.0).engine_on and not urban.state(urban.duration_s + 100.0).engine_on
    assert urban.state(-5.0).lat_rad == urban.state(0.0).lat_rad


def test_unknown_scenario_and_option_are_refused():
    with pytest.raises(ValueError, match="urban, outage-60s, tunnel-130s"):
        make_drive("motorway")
    with pytest.raises(ValueError, match="no option 'tunnels_s'"):
        make_drive("urban", tunnels_s=(10, 20))
    with pytest.raises(ValueError, match="two positive"):
        make_drive("urban", tunnel_s=(10.0,))
    assert set(SCENARIOS) == {"urban", "outage-60s", "tunnel-130s"}


def test_configurable_tunnel_times():
    drive = make_drive("urban", seed=2, tunnel_s=(25.0, 150.0))
    assert [round(s.duration_s, 6) for s in drive.spans_of("tunnel")] == [25.0, 150.0]


def test_smooth_steps_derivatives_and_vector_form_agree():
    ch = SmoothSteps(2.0)
    ch.add(1.0, 4.0, 3.0)
    ch.add(6.0, 2.0, -1.0)
    ts = np.linspace(0.0, 9.0, 901)
    x, xd, xdd = ch.sample(ts)
    scalar = np.array([ch.at(t) for t in ts])
    np.testing.assert_allclose(scalar, np.column_stack((x, xd, xdd)), atol=1e-12)
    np.testing.assert_allclose(np.gradient(x, ts)[1:-1], xd[1:-1], atol=2e-3)
    np.testing.assert_allclose(np.gradient(xd, ts)[1:-1], xdd[1:-1], atol=2e-2)
    assert ch.at(0.5) == (2.0, 0.0, 0.0) and ch.at(5.5) == (5.0, 0.0, 0.0) and ch.at(9.0) == (4.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="overlap"):
        ch.add(7.0, 1.0, 1.0)


def test_builder_refuses_what_a_car_cannot_do():
    b = RouteBuilder()
    with pytest.raises(ValueError, match="moving"):
        b.turn(math.pi / 2, 3.0)
    b.speed_to(10.0, 2.0)
    with pytest.raises(ValueError, match="standstill"):
        b.engine(False)
    with pytest.raises(ValueError, match="standstill"):
        b.finish()
