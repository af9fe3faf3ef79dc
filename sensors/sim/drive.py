"""The true motion of a simulated drive on WGS-84, built from smooth speed, heading and grade profiles.

A drive is planned as three kinematic channels of time (speed along the path, heading, road grade) that hold
still except during C2-smooth transitions whose derivatives are known in closed form; roll follows the
lateral acceleration. Whatever an ideal IMU senses is derived from those closed forms at the instant asked
for, so a perfect strapdown INS fed with it reproduces the path. Only the position depends on the ellipsoid:
it is integrated once, at construction, on a grid fine enough that quintic Hermite interpolation (values,
exact slopes and curvatures at the nodes) reproduces it to micrometres, which keeps :meth:`Drive.state`
cheap at 1 kHz.

:class:`RouteBuilder` turns driving actions (pull away, stop at a light, turn at a junction, climb a hill,
pass a tunnel) into those channels, keeping every heading and grade change to times when the vehicle moves.
The named, seeded drives live in :mod:`sensors.sim.scenarios`.
"""

from __future__ import annotations

import bisect
import copy
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sensors.sim import earth
from sensors.sim.truth import TruthState

TWO_PI = 2.0 * math.pi
# Body roll of a passenger car on its suspension, per m/s^2 of lateral acceleration (about 0.45 deg per
# m/s^2, i.e. 4.5 deg per g): the body leans out of the turn.
ROLL_PER_LATERAL_ACCEL = 0.008


class SmoothSteps:
    """A quantity that holds still except during cycloidal transitions.

    The cycloidal profile ``x0 + dx * (s - sin(2 pi s) / (2 pi))`` starts and ends with zero first and
    second derivative, so speed, heading and grade built from it give a continuous acceleration and a
    continuous angular rate: what a real vehicle can do and what an ideal IMU can sense.
    """

    def __init__(self, initial: float) -> None:
        # A sentinel step at -inf makes every lookup land on some step, without a branch.
        self._t0: list[float] = [-math.inf]
        self._dur: list[float] = [1.0]
        self._x0: list[float] = [float(initial)]
        self._dx: list[float] = [0.0]
        self._end_t = -math.inf

    @property
    def end_value(self) -> float:
        return self._x0[-1] + self._dx[-1]

    @property
    def end_time(self) -> float:
        return self._end_t

    def add(self, t0_s: float, duration_s: float, delta: float) -> None:
        """Append a transition by ``delta`` over ``[t0_s, t0_s + duration_s]``."""
        if duration_s <= 0.0:
            raise ValueError("a transition needs a positive duration")
        if t0_s < self._end_t - 1e-9:
            raise ValueError("transitions of one channel must not overlap")
        self._x0.append(self.end_value)
        self._t0.append(float(t0_s))
        self._dur.append(float(duration_s))
        self._dx.append(float(delta))
        self._end_t = t0_s + duration_s

    def at(self, t_s: float) -> tuple[float, float, float]:
        """Value, first and second time derivative at ``t_s``."""
        i = bisect.bisect_right(self._t0, t_s) - 1
        dur = self._dur[i]
        s = (t_s - self._t0[i]) / dur
        dx = self._dx[i]
        if s >= 1.0:
            return self._x0[i] + dx, 0.0, 0.0
        a = TWO_PI * s
        return (self._x0[i] + dx * (s - math.sin(a) / TWO_PI),
                dx / dur * (1.0 - math.cos(a)),
                TWO_PI * dx / (dur * dur) * math.sin(a))

    def sample(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`at` for an array of times."""
        t0 = np.asarray(self._t0)
        i = np.searchsorted(t0, t_s, side="right") - 1
        dur = np.asarray(self._dur)[i]
        dx = np.asarray(self._dx)[i]
        s = np.clip((t_s - t0[i]) / dur, 0.0, 1.0)
        a = TWO_PI * s
        x = np.asarray(self._x0)[i] + dx * (s - np.sin(a) / TWO_PI)
        xd = dx / dur * (1.0 - np.cos(a))
        xdd = np.where(s < 1.0, TWO_PI * dx / (dur * dur) * np.sin(a), 0.0)
        return x, xd, xdd


@dataclass(frozen=True, slots=True)
class DriveSpan:
    """A stretch of the drive a test or a report may look for.

    kinds: ``parked`` (engine off), ``idle`` (engine on, standing, not at a light), ``stop`` (standing at a
    light), ``turn`` (junction), ``bend``, ``grade`` (road pitch changing), ``tunnel`` and ``outage`` (sky
    fully blocked), ``canyon`` (sky partly blocked). ``value`` is the heading change of a turn or bend
    (rad, positive to the right) or the final road pitch of a grade change (rad, positive uphill).
    """

    kind: str
    start_s: float
    end_s: float
    value: float = 0.0

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


@dataclass(frozen=True)
class Weather:
    """Surroundings that change slowly over a drive.

    The ambient temperature (at the board, in the cabin) follows a half cosine from ``ambient_start_degc`` to
    ``ambient_start_degc + ambient_swing_degc`` over ``ambient_swing_s`` or the whole drive, whichever is longer:
    a cabin warms over hours, so a short drive sees only the start of the swing and a day's drive all of it.
    """

    ambient_start_degc: float = 12.0
    ambient_swing_degc: float = 20.0
    ambient_swing_s: float = 4 * 3600.0
    sea_level_pa: float = 101325.0
    sea_level_rate_pa_per_s: float = 100.0 / 3600.0  # 1 hPa per hour


@dataclass
class RoutePlan:
    """The channels and markers a :class:`RouteBuilder` produced: everything a :class:`Drive` needs."""

    speed: SmoothSteps
    heading: SmoothSteps
    grade: SmoothSteps
    sky_t: list[float]
    sky_v: list[float]
    engine_t: list[float]
    engine_on: list[bool]
    spans: list[DriveSpan]
    end_s: float


class RouteBuilder:
    """Drives a plan forward in time, one action after another.

    Heading and grade change only while the vehicle moves at constant speed, and the engine stops only at
    standstill, so every plan it makes is something a car can do. Sky changes (tunnels, street canyons)
    are markers scheduled at the current time; the motion actions that follow carry the vehicle through.
    """

    def __init__(self, heading_rad: float = 0.0, engine_on: bool = False, start_s: float = 0.0) -> None:
        self.t = float(start_s)
        self.speed = SmoothSteps(0.0)
        self.heading = SmoothSteps(heading_rad)
        self.grade = SmoothSteps(0.0)
        self.sky_t: list[float] = [0.0]
        self.sky_v: list[float] = [1.0]
        self.engine_t: list[float] = [0.0]
        self.engine_on: list[bool] = [bool(engine_on)]
        self.spans: list[DriveSpan] = []

    # state --------------------------------------------------------------------------------------------
    @property
    def v(self) -> float:
        return self.speed.end_value

    @property
    def psi(self) -> float:
        return self.heading.end_value

    @property
    def theta(self) -> float:
        return self.grade.end_value

    @property
    def sky(self) -> float:
        return self.sky_v[-1]

    def _need_moving(self, what: str) -> None:
        if self.v <= 0.1:
            raise ValueError(f"{what} needs the vehicle moving (speed {self.v:.2f} m/s at t={self.t:.1f} s)")

    # motion -------------------------------------------------------------------------------------------
    def stand(self, seconds: float, kind: str | None = None) -> None:
        """Stand still; ``kind`` names the span (``stop`` at a light, ``idle``, ``parked``)."""
        if self.v != 0.0:
            raise ValueError(f"cannot stand still at {self.v:.2f} m/s")
        if kind is not None:
            self.spans.append(DriveSpan(kind, self.t, self.t + seconds))
        self.t += seconds

    def engine(self, on: bool) -> None:
        if not on and self.v != 0.0:
            raise ValueError("the engine stops only at standstill")
        if self.engine_t[-1] == self.t:
            self.engine_on[-1] = bool(on)
        else:
            self.engine_t.append(self.t)
            self.engine_on.append(bool(on))

    def speed_to(self, v_mps: float, peak_accel_mps2: float) -> float:
        """Change speed with a cycloidal profile whose peak acceleration is ``peak_accel_mps2``."""
        dv = float(v_mps) - self.v
        if dv == 0.0:
            return 0.0
        if v_mps < 0.0:
            raise ValueError("the route model drives forward only")
        duration = 2.0 * abs(dv) / peak_accel_mps2
        # end_value + (v - end_value) is exact for v = 0, so a stop is an exact standstill.
        self.speed.add(self.t, duration, dv)
        self.t += duration
        return duration

    def speed_wander(self, seconds: float, rng: np.random.Generator, spread_mps: float, repeat: int = 1,
                     hold_s: tuple[float, float] = (4.0, 10.0), ramp_s: tuple[float, float] = (4.0, 8.0)) -> None:
        """Schedule gentle speed changes around the present speed over the next ``seconds`` (traffic), without
        advancing time: the motion actions that follow carry the vehicle through, and must last as long.

        The speed is back where it started at the end of each of the ``repeat`` identical periods, so a
        symmetric manoeuvre laid over them (a tunnel's dip and climb) still ends at the height it started.
        A real speed sensor's 1 km/h steps then dither, as they do on the road, instead of reading one
        constant value that a perfectly steady speed would give.
        """
        v0, t0 = self.v, self.t
        steps: list[tuple[float, float, float]] = []  # (offset in the period, duration, delta)
        t, cur = 0.0, v0
        while True:
            hold, ramp = float(rng.uniform(*hold_s)), float(rng.uniform(*ramp_s))
            if t + hold + 2.0 * ramp > seconds:
                break
            target = max(0.5, v0 + float(rng.uniform(-spread_mps, spread_mps)))
            steps.append((t + hold, ramp, target - cur))
            t, cur = t + hold + ramp, target
        if cur != v0:
            ramp = min(float(rng.uniform(*ramp_s)), max(seconds - t, 1e-3))
            steps.append((t, ramp, v0 - cur))
        for k in range(repeat):
            for off, dur, delta in steps:
                self.speed.add(t0 + k * seconds + off, dur, delta)

    def cruise(self, seconds: float) -> None:
        if seconds < 0.0:
            raise ValueError("cannot cruise for a negative time")
        if seconds > 0.0:
            self._need_moving("cruising")
        self.t += seconds

    def cruise_m(self, distance_m: float) -> None:
        self._need_moving("cruising")
        self.cruise(distance_m / self.v)

    def turn(self, delta_rad: float, peak_lateral_mps2: float, peak_yaw_rate_rps: float = 0.6) -> None:
        """A junction turn at the current speed, as short as the lateral and yaw-rate limits allow."""
        self._need_moving("a turn")
        duration = max(2.0 * self.v * abs(delta_rad) / peak_lateral_mps2,
                       2.0 * abs(delta_rad) / peak_yaw_rate_rps)
        self._heading_change(delta_rad, duration, "turn")

    def bend(self, delta_rad: float, seconds: float) -> None:
        """A gentle curve of the road."""
        self._need_moving("a bend")
        self._heading_change(delta_rad, seconds, "bend")

    def _heading_change(self, delta_rad: float, seconds: float, kind: str) -> None:
        self.heading.add(self.t, seconds, delta_rad)
        self.spans.append(DriveSpan(kind, self.t, self.t + seconds, delta_rad))
        self.t += seconds

    def grade_to(self, pitch_rad: float, distance_m: float) -> None:
        """Change the road pitch over ``distance_m`` of road at the current speed (a vertical curve)."""
        self._need_moving("a grade change")
        duration = distance_m / self.v
        delta = float(pitch_rad) - self.theta
        if delta != 0.0:
            self.grade.add(self.t, duration, delta)
            self.spans.append(DriveSpan("grade", self.t, self.t + duration, float(pitch_rad)))
        self.t += duration

    def hill(self, pitch_rad: float, ramp_m: float, hold_m: float) -> None:
        """Climb (pitch > 0) or descend, then the reverse, ending level at the height it started from.

        Both halves run at the same constant speed with mirrored pitch profiles, so their height changes
        cancel exactly: a lap with hills still closes in height.
        """
        for sign in (1.0, -1.0):
            self.grade_to(sign * pitch_rad, ramp_m)
            self.cruise_m(hold_m)
            self.grade_to(0.0, ramp_m)

    # sky ----------------------------------------------------------------------------------------------
    def _sky_point(self, t_s: float, value: float) -> None:
        if t_s < self.sky_t[-1] - 1e-9:
            raise ValueError(f"sky change at t={t_s:.1f} s overlaps one scheduled up to t={self.sky_t[-1]:.1f} s")
        if not 0.0 <= value <= 1.0:
            raise ValueError("sky_open is a fraction in [0, 1]")
        self.sky_t.append(float(t_s))
        self.sky_v.append(float(value))

    def sky_to(self, value: float, ramp_s: float = 1.0, at_s: float | None = None) -> None:
        """Move the visible sky fraction linearly to ``value`` over ``ramp_s`` from now (or ``at_s``)."""
        t0 = self.t if at_s is None else at_s
        self._sky_point(t0, self.sky_v[-1])
        self._sky_point(t0 + ramp_s, value)

    def canyon(self, seconds: float, rng: np.random.Generator, low: float = 0.3, high: float = 0.8,
               ramp_s: float = 2.0) -> None:
        """Schedule a street canyon for the next ``seconds``: sky fraction wandering in [low, high].

        The sky changes every few seconds, as buildings and gaps pass; the motion actions that follow
        must last at least ``seconds + ramp_s``.
        """
        t = self.t
        self.sky_to(float(rng.uniform(low, high)), ramp_s, at_s=t)
        start = t + ramp_s
        end = start + seconds
        tk = start
        while True:
            tk += float(rng.uniform(3.0, 9.0))
            if tk >= end:
                break
            self._sky_point(tk, float(rng.uniform(low, high)))
        self._sky_point(end, float(rng.uniform(low, high)))
        self._sky_point(end + ramp_s, 1.0)
        self.spans.append(DriveSpan("canyon", start, end))

    def tunnel(self, dark_s: float, dip_pitch_rad: float = 0.03, bend_rad: float = 0.0,
               portal_s: float = 1.0, kind: str = "tunnel") -> None:
        """Pass a tunnel at the current speed: the sky is fully blocked for exactly ``dark_s``.

        The road dips inside (down, level, up, level) with mirrored pitch profiles so the exit is at the
        entry height; ``bend_rad`` adds a curve and its counter-curve inside, as long tunnels have.
        """
        self._need_moving("a tunnel")
        self.sky_to(0.0, portal_s)
        dark_start = self.t + portal_s
        inside = portal_s + dark_s  # motion from the first portal ramp to the start of the exit ramp
        t_g = min(8.0, inside / 6.0)
        hold = (inside - 4.0 * t_g) / 2.0
        v = self.v
        for sign in (-1.0, 1.0):
            self.grade_to(sign * dip_pitch_rad, v * t_g)
            if bend_rad != 0.0 and hold > 3.0:
                t_b = min(10.0, hold / 2.0)
                self.cruise((hold - t_b) / 2.0)
                self.bend(-sign * bend_rad, t_b)
                self.cruise((hold - t_b) / 2.0)
            else:
                self.cruise(hold)
            self.grade_to(0.0, v * t_g)
        self.sky_to(1.0, portal_s)
        self.spans.append(DriveSpan(kind, dark_start, dark_start + dark_s))

    def finish(self) -> RoutePlan:
        """The plan so far; the vehicle must be standing still (the drive stays parked after its end)."""
        if self.v != 0.0:
            raise ValueError("a drive ends at standstill")
        end = max(self.t, self.sky_t[-1])
        speed, heading, grade = copy.deepcopy((self.speed, self.heading, self.grade))
        return RoutePlan(speed, heading, grade, list(self.sky_t), list(self.sky_v),
                         list(self.engine_t), list(self.engine_on), list(self.spans), end)


def horizontal_displacement(plan: RoutePlan | RouteBuilder, t0_s: float, t1_s: float,
                            dt_s: float = 0.05) -> tuple[float, float]:
    """North and east distance travelled between two times, on a flat local tangent plane (m).

    Used to close a lap: a few centimetres of earth curvature over a few kilometres do not matter there.
    """
    n = max(2, math.ceil((t1_s - t0_s) / dt_s))
    t = np.linspace(t0_s, t1_s, 2 * n + 1)
    v = plan.speed.sample(t)[0]
    psi = plan.heading.sample(t)[0]
    theta = plan.grade.sample(t)[0]
    vh = v * np.cos(theta)
    w = np.ones(2 * n + 1)
    w[1:-1:2] = 4.0
    w[2:-1:2] = 2.0
    h = (t1_s - t0_s) / (2 * n)
    return float(h / 3.0 * np.sum(w * vh * np.cos(psi))), float(h / 3.0 * np.sum(w * vh * np.sin(psi)))


def _cumulative_simpson(f_nodes: np.ndarray, f_mid: np.ndarray, dt: float) -> np.ndarray:
    steps = dt / 6.0 * (f_nodes[:-1] + 4.0 * f_mid + f_nodes[1:])
    return np.concatenate(([0.0], np.cumsum(steps)))


@dataclass
class Drive:
    """A planned drive as a :class:`~sensors.sim.truth.Trajectory`.

    ``duration_s`` is what the drive advertises; the vehicle stands parked at its last position after the
    plan ends and at its first position before t = 0.
    """

    plan: RoutePlan
    start_lat_deg: float = 37.5665
    start_lon_deg: float = 126.9780
    start_height_m: float = 63.0  # ellipsoidal: 38 m above mean sea level in central Seoul
    geoid_m: float = 25.0  # EGM undulation around Seoul, taken as constant over a few km
    weather: Weather = field(default_factory=Weather)
    duration_s: float = math.nan
    grid_dt_s: float = 0.1
    roll_per_lateral_mps2: float = ROLL_PER_LATERAL_ACCEL
    name: str = "drive"
    # The sky as a GNSS receiver sees it (sensors.sim.gnss_errors.SkyGeometry: constellation, canyon band) and
    # options of its error model; a drive without them gets the simpler sky-fraction receiver errors.
    gnss_sky: Any = None
    gnss_error_options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if math.isnan(self.duration_s):
            self.duration_s = self.plan.end_s
        if self.duration_s <= 0.0:
            raise ValueError("a drive needs a positive duration")
        self._speed = self.plan.speed
        self._heading = self.plan.heading
        self._grade = self.plan.grade
        self._sky_t = self.plan.sky_t
        self._sky_v = self.plan.sky_v
        self._engine_t = self.plan.engine_t
        self._engine_on = self.plan.engine_on
        self._integrate_position()

    @property
    def spans(self) -> list[DriveSpan]:
        return self.plan.spans

    def spans_of(self, kind: str) -> list[DriveSpan]:
        return [s for s in self.plan.spans if s.kind == kind]

    # construction -------------------------------------------------------------------------------------
    def _kinematics(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """NED velocity and its time derivative (both (3, n)) at an array of times."""
        v, v_dot, _ = self._speed.sample(t)
        psi, psi_dot, _ = self._heading.sample(t)
        theta, theta_dot, _ = self._grade.sample(t)
        sp, cp, st, ct = np.sin(psi), np.cos(psi), np.sin(theta), np.cos(theta)
        u = np.array((ct * cp, ct * sp, -st))
        u_dot = np.array((-st * theta_dot * cp - ct * sp * psi_dot,
                          -st * theta_dot * sp + ct * cp * psi_dot,
                          -ct * theta_dot))
        return v * u, v_dot * u + v * u_dot

    def _integrate_position(self) -> None:
        """Latitude, longitude and height on the grid, with their exact first and second time derivatives.

        Height does not depend on position; latitude and longitude do, only through the radii of
        curvature, so a fixed-point iteration on vectorised Simpson sums converges in a few passes. The
        derivatives at the nodes let :meth:`_position` interpolate with quintic Hermite polynomials, whose
        slope then matches the velocity to far below a micrometre per second.
        """
        dt = self.grid_dt_s
        end = max(self.plan.end_s, dt)
        n = math.ceil(end / dt) + 1
        t = np.arange(n) * dt
        tm = t[:-1] + 0.5 * dt
        (vn, ve, vd), (an, ae, ad) = self._kinematics(t)
        (vnm, vem, vdm), _ = self._kinematics(tm)
        h = self.start_height_m - _cumulative_simpson(vd, vdm, dt)
        hm = 0.5 * (h[:-1] + h[1:])
        lat0 = math.radians(self.start_lat_deg)
        lon0 = math.radians(self.start_lon_deg)
        lat = np.full(n, lat0)
        for _ in range(4):
            rn, _re = _radii(lat)
            rnm, _rem = _radii(0.5 * (lat[:-1] + lat[1:]))
            lat = lat0 + _cumulative_simpson(vn / (rn + h), vnm / (rnm + hm), dt)
        latm = 0.5 * (lat[:-1] + lat[1:])
        rn, re = _radii(lat)
        _rnm, rem = _radii(latm)
        lon = lon0 + _cumulative_simpson(ve / ((re + h) * np.cos(lat)), vem / ((rem + hm) * np.cos(latm)), dt)
        # First derivatives, and second ones by the chain rule through the radii and the height.
        slat, clat = np.sin(lat), np.cos(lat)
        w = np.sqrt(1.0 - earth.E2 * slat**2)
        drn = 3.0 * earth.A * (1.0 - earth.E2) * earth.E2 * slat * clat / w**5  # d rn / d lat
        dre = earth.A * earth.E2 * slat * clat / w**3  # d re / d lat
        mlat, mlon = rn + h, (re + h) * clat
        dlat = vn / mlat
        dlon = ve / mlon
        ddlat = an / mlat - vn * (drn * dlat - vd) / mlat**2
        ddlon = ae / mlon - ve * ((dre * dlat - vd) * clat - (re + h) * slat * dlat) / mlon**2
        self._grid_n = n
        self._grid_end_s = (n - 1) * dt
        self._grid = np.column_stack((lat, lon, h, dlat, dlon, -vd, ddlat, ddlon, -ad))

    # evaluation ---------------------------------------------------------------------------------------
    def _position(self, t: float) -> tuple[float, float, float]:
        dt = self.grid_dt_s
        if t >= self._grid_end_s:
            row = self._grid[-1]
            return float(row[0]), float(row[1]), float(row[2])
        i = min(int(t / dt), self._grid_n - 2)
        s = t / dt - i
        p0, p1 = self._grid[i:i + 2].tolist()
        s2 = s * s
        s3 = s2 * s
        s4 = s3 * s
        s5 = s4 * s
        # Quintic Hermite basis: values, slopes (times dt) and curvatures (times dt^2) at both ends.
        h5 = 10.0 * s3 - 15.0 * s4 + 6.0 * s5
        h1 = (s - 6.0 * s3 + 8.0 * s4 - 3.0 * s5) * dt
        h4 = (-4.0 * s3 + 7.0 * s4 - 3.0 * s5) * dt
        dt2 = dt * dt
        h2 = 0.5 * (s2 - 3.0 * s3 + 3.0 * s4 - s5) * dt2
        h3 = 0.5 * (s3 - 2.0 * s4 + s5) * dt2
        # h0 + h5 = 1: interpolating the change from p0 keeps a standing vehicle exactly where it is.
        return (p0[0] + h1 * p0[3] + h2 * p0[6] + h3 * p1[6] + h4 * p1[3] + h5 * (p1[0] - p0[0]),
                p0[1] + h1 * p0[4] + h2 * p0[7] + h3 * p1[7] + h4 * p1[4] + h5 * (p1[1] - p0[1]),
                p0[2] + h1 * p0[5] + h2 * p0[8] + h3 * p1[8] + h4 * p1[5] + h5 * (p1[2] - p0[2]))

    def sky_open(self, t_s: float) -> float:
        i = bisect.bisect_right(self._sky_t, t_s) - 1
        if i < 0:
            return self._sky_v[0]
        if i >= len(self._sky_t) - 1:
            return self._sky_v[-1]
        t0, t1 = self._sky_t[i], self._sky_t[i + 1]
        if t1 <= t0:
            return self._sky_v[i + 1]
        return self._sky_v[i] + (self._sky_v[i + 1] - self._sky_v[i]) * (t_s - t0) / (t1 - t0)

    def engine_on(self, t_s: float) -> bool:
        i = bisect.bisect_right(self._engine_t, t_s) - 1
        return self._engine_on[max(i, 0)]

    def ambient_degc(self, t_s: float) -> float:
        w = self.weather
        span = max(self.duration_s, w.ambient_swing_s)
        x = min(max(t_s, 0.0), span) / span
        return w.ambient_start_degc + w.ambient_swing_degc * 0.5 * (1.0 - math.cos(math.pi * x))

    def sea_level_pa(self, t_s: float) -> float:
        return self.weather.sea_level_pa + self.weather.sea_level_rate_pa_per_s * t_s

    def state(self, t_s: float) -> TruthState:
        t = float(t_s) if t_s > 0.0 else 0.0  # numpy scalars would make every step below slower
        v, v_dot, _ = self._speed.at(t)
        psi, psi_dot, psi_ddot = self._heading.at(t)
        theta, theta_dot, _ = self._grade.at(t)
        lat, lon, h = self._position(t)

        # Roll leans out of the turn in proportion to the lateral (centripetal) acceleration v * psi_dot.
        k = self.roll_per_lateral_mps2
        phi = -k * v * psi_dot
        phi_dot = -k * (v_dot * psi_dot + v * psi_ddot)

        sp, cp = math.sin(psi), math.cos(psi)
        st, ct = math.sin(theta), math.cos(theta)
        sr, cr = math.sin(phi), math.cos(phi)
        # Velocity along the path (body x, no side slip) and its rate of change in the NED frame.
        un, ue, ud = ct * cp, ct * sp, -st
        vn, ve, vd = v * un, v * ue, v * ud
        an = v_dot * un + v * (-st * theta_dot * cp - ct * sp * psi_dot)
        ae = v_dot * ue + v * (-st * theta_dot * sp + ct * cp * psi_dot)
        ad = v_dot * ud - v * ct * theta_dot

        # Earth and transport rates; gravity (Somigliana with the free-air term).
        slat, clat = math.sin(lat), math.cos(lat)
        w_ = math.sqrt(1.0 - earth.E2 * slat * slat)
        rn = earth.A * (1.0 - earth.E2) / (w_ * w_ * w_)
        re = earth.A / w_
        wie_n, wie_d = earth.OMEGA_IE * clat, -earth.OMEGA_IE * slat
        wen_n = ve / (re + h)
        wen_e = -vn / (rn + h)
        wen_d = -ve * slat / clat / (re + h)
        g0 = earth.GAMMA_E * (1.0 + earth.K_SOMIGLIANA * slat * slat) / w_
        g = g0 * (1.0 - 2.0 / earth.A * (1.0 + earth.F + earth.M_RATIO - 2.0 * earth.F * slat * slat) * h
                  + 3.0 * h * h / (earth.A * earth.A))

        # Specific force in NED: f = a + (2 w_ie + w_en) x v - g.
        cx, cy, cz = 2.0 * wie_n + wen_n, wen_e, 2.0 * wie_d + wen_d
        fn = an + (cy * vd - cz * ve)
        fe = ae + (cz * vn - cx * vd)
        fd = ad + (cx * ve - cy * vn) - g
        # Inertial rate of the navigation frame, to be seen by the gyros on top of the body's own turning.
        inn, ine, ind = wie_n + wen_n, wen_e, wie_d + wen_d

        # C_b^n rows (z-y-x Euler angles); body vectors are C^T times NED vectors.
        c11, c12, c13 = ct * cp, sr * st * cp - cr * sp, cr * st * cp + sr * sp
        c21, c22, c23 = ct * sp, sr * st * sp + cr * cp, cr * st * sp - sr * cp
        c31, c32, c33 = -st, sr * ct, cr * ct
        f_body = np.array((c11 * fn + c21 * fe + c31 * fd,
                           c12 * fn + c22 * fe + c32 * fd,
                           c13 * fn + c23 * fe + c33 * fd))
        w_body = np.array((phi_dot - psi_dot * st + c11 * inn + c21 * ine + c31 * ind,
                           theta_dot * cr + psi_dot * sr * ct + c12 * inn + c22 * ine + c32 * ind,
                           -theta_dot * sr + psi_dot * cr * ct + c13 * inn + c23 * ine + c33 * ind))
        yaw = math.remainder(psi, TWO_PI)
        return TruthState(
            t_s, lat, lon, h, np.array((vn, ve, vd)), np.array((phi, theta, yaw)), f_body, w_body,
            geoid_m=self.geoid_m,
            ambient_degc=self.ambient_degc(t),
            sea_level_pa=self.sea_level_pa(t),
            sky_open=self.sky_open(t),
            engine_on=self.engine_on(t),
        )


def _radii(lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w = np.sqrt(1.0 - earth.E2 * np.sin(lat) ** 2)
    return earth.A * (1.0 - earth.E2) / w**3, earth.A / w
