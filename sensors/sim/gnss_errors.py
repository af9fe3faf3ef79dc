"""How wrong a single-frequency GNSS receiver is in a car, and when it has a fix at all.

The errors a navigation filter must live with are not white: the slow ones (orbit, ionosphere,
troposphere, multipath averaged over the code tracking loop) wander with a correlation time of minutes,
so they are a first-order Gauss-Markov process; in a street canyon a reflected signal adds a jump of
metres that lasts as long as the geometry does. Satellites are lost as the sky closes, the geometry
(DOP) worsens, and below three satellites there is no solution.

Everything here is a function of the truth and a seeded generator, so the receiver model and the PPS
model (through :func:`has_time_fix`) agree on when there is a fix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sensors.sim import earth
from sensors.sim.truth import TruthState

MAX_SATELLITES = 18  # GPS + GLONASS used in a solution under an open sky, typical for an M8
NO_DOP = 99.99  # what u-blox reports for a DOP without a solution


def satellites_tracked(sky_open: float, max_sv: int = MAX_SATELLITES) -> int:
    """Satellites used in the solution with a fraction ``sky_open`` of the sky visible."""
    return round(max_sv * min(1.0, max(0.0, sky_open)))


def fix_type_for(num_sv: int) -> int:
    """UBX fixType from the satellites used: 3D with four or more, 2D (height held) with three, else none."""
    if num_sv >= 4:
        return 3
    return 2 if num_sv == 3 else 0


def has_time_fix(state: TruthState, max_sv: int = MAX_SATELLITES) -> bool:
    """Whether the receiver solves its clock at this instant, so its time pulse is locked and emitted.

    A 2D fix solves the clock too (the height is held), so three satellites suffice. The sky is all this
    looks at: a receiver also needs its time to first fix after power-on
    (``UbloxReceiverModel.time_to_first_fix_s``), which a PPS model started with it should wait out too.
    """
    return fix_type_for(satellites_tracked(state.sky_open, max_sv)) >= 2


@dataclass(frozen=True, slots=True)
class Dops:
    pdop: float
    hdop: float
    vdop: float
    tdop: float


def dops_for(num_sv: int) -> Dops:
    """Dilutions of precision for ``num_sv`` satellites in use.

    An empirical fit to what u-blox receivers report on the road: PDOP ~1.2 under an open sky with 18
    satellites, ~2 with six, ~3 with four. A 2D fix (three satellites plus the held height, which acts as a
    fourth range) is given the four-satellite geometry. The split PDOP^2 = HDOP^2 + VDOP^2 with
    HDOP = 0.6 PDOP is the usual ratio for satellites spread over the sky.
    """
    if num_sv < 3:
        return Dops(NO_DOP, NO_DOP, NO_DOP, NO_DOP)
    n = max(num_sv, 4)
    pdop = 1.0 + 4.0 / (n - 2.0)
    return Dops(pdop, 0.6 * pdop, 0.8 * pdop, 0.5 * pdop)


class GaussMarkov:
    """First-order Gauss-Markov process of unit variance, stepped exactly for any time step.

    Keeping the process at unit variance and scaling it by the current sigma lets the sigma follow the
    geometry epoch by epoch while the reported accuracy stays exactly the standard deviation applied.
    """

    def __init__(self, tau_s: float, rng: np.random.Generator, size: int = 1) -> None:
        if tau_s <= 0:
            raise ValueError("a correlation time must be positive")
        self.tau_s = float(tau_s)
        self._rng = rng
        self.value = rng.standard_normal(size)  # start in the stationary distribution

    def step(self, dt_s: float) -> np.ndarray:
        a = math.exp(-max(0.0, dt_s) / self.tau_s)
        self.value = a * self.value + math.sqrt(1.0 - a * a) * self._rng.standard_normal(self.value.shape)
        return self.value


@dataclass(frozen=True, slots=True)
class EpochError:
    """The error applied to one solution and the accuracies the receiver reports for it.

    Accuracy conventions, so a filter can turn them into variances:
    ``h_acc_m`` is the DRMS of the horizontal error (sqrt(sigma_N^2 + sigma_E^2), a ~65 % radius), so each
    horizontal axis has sigma = h_acc_m / sqrt(2); ``v_acc_m`` is sigma of the height; ``s_acc_mps`` is
    sigma of each velocity component (and of the speed); ``t_acc_ns`` is sigma of the epoch time.
    """

    pos_ned_m: np.ndarray  # (3,) reported minus true position, north-east-down
    vel_ned_mps: np.ndarray  # (3,) reported minus true velocity
    time_ns: float  # reported minus true time of the epoch
    multipath_ned_m: np.ndarray  # (3,) the part of pos_ned_m due to a multipath jump (zero without one)
    h_acc_m: float
    v_acc_m: float
    s_acc_mps: float
    t_acc_ns: float
    dops: Dops


class GnssErrorModel:
    """Errors of a code-based single-frequency solution, epoch by epoch, from the sky the antenna sees.

    ``uere_m`` is the user-equivalent range error of the slow part (sigma of position = UERE x DOP);
    ``tau_s`` its correlation time. ``vel_sigma_mps`` is the Doppler velocity noise per axis under an open
    sky (white: each epoch's Doppler is a fresh measurement), growing with PDOP. Multipath jumps start
    at ``multipath_rate_hz`` x (1 - sky_open), are ``multipath_m`` metres long horizontally (uniform between
    the bounds, random direction, half that sigma vertically) and last an exponential time of mean
    ``multipath_duration_s``; the receiver sees the larger residuals and widens its accuracies by the jump.
    """

    def __init__(
        self,
        rng: np.random.Generator,
        uere_m: float = 1.0,
        tau_s: float = 60.0,
        vel_sigma_mps: float = 0.05,
        clock_sigma_ns: float = 25.0,
        multipath_rate_hz: float = 0.05,
        multipath_m: tuple[float, float] = (2.0, 10.0),
        multipath_duration_s: float = 5.0,
    ) -> None:
        self._rng = rng
        self.uere_m = uere_m
        self.vel_sigma_mps = vel_sigma_mps
        self.clock_sigma_ns = clock_sigma_ns
        self.multipath_rate_hz = multipath_rate_hz
        self.multipath_m = multipath_m
        self.multipath_duration_s = multipath_duration_s
        self._pos = GaussMarkov(tau_s, rng, 3)
        self._jump = np.zeros(3)
        self._jump_left_s = 0.0
        self._open_sky_pdop = dops_for(MAX_SATELLITES).pdop

    @property
    def multipath_active(self) -> bool:
        return self._jump_left_s > 0.0

    def step(self, dt_s: float, sky_open: float, num_sv: int) -> EpochError:
        """Advance the error processes by ``dt_s`` and return the error of a solution with ``num_sv``."""
        rng = self._rng
        unit = self._pos.step(dt_s)
        self._step_multipath(dt_s, sky_open)
        n_vel = rng.standard_normal(3)
        n_time = float(rng.standard_normal())
        d = dops_for(num_sv)
        if d.pdop >= NO_DOP:  # no solution: the processes still move on, nothing is reported
            return EpochError(np.zeros(3), np.zeros(3), 0.0, np.zeros(3), math.inf, math.inf, math.inf,
                              math.inf, d)
        sigma_axis_h = self.uere_m * d.hdop / math.sqrt(2.0)
        sigma_v = self.uere_m * d.vdop
        pos = unit * np.array([sigma_axis_h, sigma_axis_h, sigma_v]) + self._jump
        vel_sigma = self.vel_sigma_mps * d.pdop / self._open_sky_pdop
        vel = n_vel * vel_sigma
        t_sigma = self.clock_sigma_ns * d.tdop
        time_err = n_time * t_sigma
        h_acc = math.sqrt(2.0 * sigma_axis_h**2 + float(self._jump[0] ** 2 + self._jump[1] ** 2))
        v_acc = math.hypot(sigma_v, float(self._jump[2]))
        return EpochError(pos, vel, time_err, self._jump.copy(), h_acc, v_acc, vel_sigma, t_sigma, d)

    def _step_multipath(self, dt_s: float, sky_open: float) -> None:
        rng = self._rng
        # Draw every epoch whatever happens, so the stream of numbers does not depend on the sky.
        u_start, u_len, u_dir, u_dur = rng.uniform(size=4)
        n_up = float(rng.standard_normal())
        if self._jump_left_s > 0.0:
            self._jump_left_s -= dt_s
            if self._jump_left_s <= 0.0:
                self._jump = np.zeros(3)
                self._jump_left_s = 0.0
            return
        closed = 1.0 - min(1.0, max(0.0, sky_open))
        if closed <= 0.0 or u_start >= 1.0 - math.exp(-self.multipath_rate_hz * closed * dt_s):
            return
        lo, hi = self.multipath_m
        length = lo + (hi - lo) * u_len
        azimuth = 2.0 * math.pi * u_dir
        self._jump = np.array([length * math.cos(azimuth), length * math.sin(azimuth), 0.5 * length * n_up])
        self._jump_left_s = -self.multipath_duration_s * math.log(max(1.0 - u_dur, 1e-300))


# ---- satellite geometry ---------------------------------------------------------------------------------
# Constellations as circular Walker orbits: (name, planes, per plane, inclination deg, radius m, period s,
# Walker phasing F). Good to a few degrees of elevation against real almanacs, which is all the visibility
# and DOP of a drive need.
WALKER = (
    ("G", 6, 4, 55.0, 26_559_700.0, 43_082.0, 1),  # GPS
    ("R", 3, 8, 64.8, 25_508_200.0, 40_544.0, 1),  # GLONASS
    ("E", 3, 8, 56.0, 29_600_000.0, 50_680.0, 1),  # Galileo
)
ELEVATION_MASK_DEG = 10.0
CANYON_BAND_LOW_DEG = 15.0  # a street canyon blocks from here up (the paper's urban simulation: 15 to 50 deg)
SIN_BAND_LOW = math.sin(math.radians(CANYON_BAND_LOW_DEG))
DEEP_CANYON_SKY = 0.3  # below this visible fraction every tracked satellite arrives by reflection
PDOP_MASK = 25.0  # u-blox default position DOP mask (CFG-NAV5 pDop)
ACROSS_STREET_SIN = math.sin(math.radians(40.0))  # beyond 40 deg off the street's axis a low satellite is hidden


@dataclass(frozen=True, slots=True)
class CircularOrbit:
    """One satellite of :class:`Constellation`: a circular orbit, its argument of latitude ``arg_lat0_rad`` and
    node ``raan_rad`` (in the frame that turns with the earth) at constellation time 0."""

    radius_m: float
    inclination_rad: float
    raan_rad: float
    arg_lat0_rad: float
    mean_motion_rps: float


class Constellation:
    """Satellite positions (ECEF) of GPS, GLONASS and Galileo at drive time ``t_s``, phased by ``epoch_s``."""

    def __init__(self, epoch_s: float = 0.0, systems: tuple[tuple, ...] = WALKER) -> None:
        a, inc, raan, u0, period, name = [], [], [], [], [], []
        for sys_name, planes, per, inc_deg, radius, t_orbit, phasing in systems:
            total = planes * per
            for p in range(planes):
                for k in range(per):
                    name.append(f"{sys_name}{p * per + k + 1:02d}")
                    a.append(radius)
                    inc.append(math.radians(inc_deg))
                    raan.append(2.0 * math.pi * p / planes)
                    u0.append(2.0 * math.pi * (k / per + phasing * p / total))
                    period.append(t_orbit)
        self.names = name
        self._a = np.array(a)
        self._ci, self._si = np.cos(inc), np.sin(inc)
        self._raan = np.array(raan)
        self._u0 = np.array(u0)
        self._n = 2.0 * math.pi / np.array(period)
        self.epoch_s = float(epoch_s)

    def orbit(self, index: int) -> CircularOrbit:
        """The elements of satellite ``index``, for a broadcast ephemeris that puts it where :meth:`ecef` does."""
        return CircularOrbit(float(self._a[index]), math.atan2(float(self._si[index]), float(self._ci[index])),
                             float(self._raan[index]), float(self._u0[index]), float(self._n[index]))

    def __len__(self) -> int:
        return len(self.names)

    def ecef(self, t_s: float) -> np.ndarray:
        t = t_s + self.epoch_s
        u = self._u0 + self._n * t
        om = self._raan - earth.OMEGA_IE * t  # the earth turns under the orbital planes
        cu, su, co, so = np.cos(u), np.sin(u), np.cos(om), np.sin(om)
        return np.column_stack((self._a * (cu * co - su * self._ci * so), self._a * (cu * so + su * self._ci * co),
                                self._a * su * self._si))

    def look(self, t_s: float, lat: float, lon: float, h: float) -> tuple[np.ndarray, np.ndarray]:
        """Azimuth and elevation (rad) of every satellite from a point on the ellipsoid."""
        sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
        rn = earth.A / math.sqrt(1.0 - earth.E2 * sl * sl)
        rx = np.array(((rn + h) * cl * co, (rn + h) * cl * so, (rn * (1.0 - earth.E2) + h) * sl))
        d = self.ecef(t_s) - rx
        e = d @ np.array((-so, co, 0.0))
        n = d @ np.array((-sl * co, -sl * so, cl))
        u = d @ np.array((cl * co, cl * so, sl))
        return np.arctan2(e, n), np.arctan2(u, np.hypot(e, n))


def blocked_band(sky_open: float) -> tuple[float, float]:
    """Elevations (rad) a street canyon blocks when a fraction ``sky_open`` of the sky's solid angle is seen.

    The canyon blocks a band from 15 deg up, as in the paper's urban simulation (low satellites stay in view
    along the street), as wide as the visible fraction asks: sin(15 deg) + 1 - sin(top) = sky_open. A band
    of 15 to 50 deg leaves 0.49 of the sky. A sky more closed than the band below 15 deg can give blocks
    everything above asin(sky_open).
    """
    s = min(1.0, max(0.0, sky_open))
    if s >= 1.0:
        return math.pi, math.pi  # nothing blocked
    if s <= 0.0:
        return -math.pi, math.pi  # everything blocked
    if s >= SIN_BAND_LOW:
        return math.radians(CANYON_BAND_LOW_DEG), math.asin(min(1.0, 1.0 + SIN_BAND_LOW - s))
    return math.asin(s), math.pi


@dataclass(frozen=True)
class SkyView:
    """The satellites a receiver uses at one epoch: their look angles, and which ones it sees only by a
    reflection (a street canyon's low satellites: the direct path is behind a building)."""

    az: np.ndarray  # rad, of the satellites in use
    el: np.ndarray
    reflected: np.ndarray  # bool
    ids: np.ndarray  # indices into the constellation, so per-satellite errors follow each satellite
    canyon: bool
    deep: bool = False  # a tunnel's approach: longer reflected paths

    @property
    def num_sv(self) -> int:
        return len(self.el)


class SkyGeometry:
    """Which satellites a receiver on a drive tracks: constellation, elevation mask, canyon band, tunnels."""

    def __init__(self, epoch_s: float = 0.0, mask_deg: float = ELEVATION_MASK_DEG,
                 reflect_below_deg: float = CANYON_BAND_LOW_DEG) -> None:
        self.constellation = Constellation(epoch_s)
        self.mask = math.radians(mask_deg)
        self.reflect_below = math.radians(reflect_below_deg)

    def view(self, state: TruthState) -> SkyView:
        az, el = self.constellation.look(state.t_s, state.lat_rad, state.lon_rad, state.height_m)
        lo, hi = blocked_band(state.sky_open)
        keep = (el >= self.mask) & ~((el >= lo) & (el <= hi))
        ids = np.nonzero(keep)[0]
        canyon = 0.0 < state.sky_open < 1.0
        if canyon and state.sky_open < DEEP_CANYON_SKY:
            # A tunnel's approach: the walls close in and every satellite on the taller side is seen by reflection.
            reflected = np.sin(az[ids] - float(state.rpy_rad[2])) > 0.0
        elif canyon:
            # Low satellites across the street, behind the taller row of buildings (the right-hand one here), reach
            # the antenna only by a reflection off the facade opposite. Those along the street are seen directly.
            across = np.sin(az[ids] - float(state.rpy_rad[2])) > ACROSS_STREET_SIN
            reflected = (el[ids] < self.reflect_below) & across
        else:
            reflected = np.zeros(len(ids), bool)
        return SkyView(az[ids], el[ids], reflected, ids, canyon, canyon and state.sky_open < DEEP_CANYON_SKY)

    def num_sv(self, state: TruthState) -> int:
        return self.view(state).num_sv


def geometry_dops(az: np.ndarray, el: np.ndarray) -> Dops:
    """DOPs of the satellites in view (north-east-down position and clock)."""
    if len(el) < 4:
        return Dops(NO_DOP, NO_DOP, NO_DOP, NO_DOP) if len(el) < 3 else _dops_2d(az, el)
    try:
        q = np.linalg.inv(_design(az, el).T @ _design(az, el))
    except np.linalg.LinAlgError:
        return Dops(NO_DOP, NO_DOP, NO_DOP, NO_DOP)
    h = math.sqrt(max(q[0, 0] + q[1, 1], 0.0))
    v = math.sqrt(max(q[2, 2], 0.0))
    return _capped(Dops(math.hypot(h, v), h, v, math.sqrt(max(q[3, 3], 0.0))))


def _capped(d: Dops) -> Dops:
    """DOPs as a receiver reports them: 99.99 at most (NAV-PVT's field and NMEA's convention)."""
    return Dops(*(min(x, NO_DOP) if math.isfinite(x) else NO_DOP for x in (d.pdop, d.hdop, d.vdop, d.tdop)))


def _dops_2d(az: np.ndarray, el: np.ndarray) -> Dops:
    """Three satellites and the held height as a fourth measurement."""
    g = np.vstack((_design(az, el), (0.0, 0.0, 1.0, 0.0)))
    try:
        q = np.linalg.inv(g.T @ g)
    except np.linalg.LinAlgError:
        return Dops(NO_DOP, NO_DOP, NO_DOP, NO_DOP)
    h = math.sqrt(max(q[0, 0] + q[1, 1], 0.0))
    v = math.sqrt(max(q[2, 2], 0.0))
    return _capped(Dops(math.hypot(h, v), h, v, math.sqrt(max(q[3, 3], 0.0))))


def _design(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """Pseudorange partials: minus the line of sight (NED) for position, one for the clock."""
    ce = np.cos(el)
    return np.column_stack((-ce * np.cos(az), -ce * np.sin(az), np.sin(el), np.ones(len(el))))


class GeometryErrorModel:
    """Errors of a code solution computed from per-satellite range errors through the actual geometry.

    Every satellite carries a slow range error (atmosphere, orbit, clock: Gauss-Markov, ``tau_s``) whose
    sigma grows at low elevation, and a faster multipath term, metres strong between the facades of a street
    canyon (``canyon_multipath_m``) against decimetres under an open sky. In a canyon the low satellites that stay
    in view arrive by reflection (NLOS): their ranges are long by metres to tens of metres, which a least-squares
    fix on a few satellites turns into position errors of that size, not into white noise. The receiver weights
    satellites by elevation, and reports as accuracy the sigma its own model gives, widened by the post-fit
    residuals when it has redundancy to see them (a reflection on a four-satellite fix goes unnoticed, as it does
    in real receivers). On a tunnel's approach (``deep``) the reflected paths are ``deep_factor`` times longer.
    ``uere_m`` of 0.35 m under an open sky is a code-differential grade solution (SBAS or a nearby base).
    """

    def __init__(self, rng: np.random.Generator, n_satellites: int, uere_m: float = 0.35, tau_s: float = 60.0,
                 multipath_m: float = 0.3, multipath_tau_s: float = 5.0, canyon_multipath_m: float = 3.0,
                 nlos_m: float = 15.0, nlos_tau_s: float = 15.0, deep_factor: float = 3.0,
                 vel_sigma_mps: float = 0.05, nlos_vel_sigma_mps: float = 0.4, clock_sigma_ns: float = 25.0,
                 model_uere_m: float = 0.5) -> None:
        self._rng = rng
        self.uere_m = uere_m
        self.multipath_m = multipath_m
        self.canyon_multipath_m = canyon_multipath_m
        self.nlos_m = nlos_m
        self.deep_factor = deep_factor
        self.vel_sigma_mps = vel_sigma_mps
        self.nlos_vel_sigma_mps = nlos_vel_sigma_mps
        self.clock_sigma_ns = clock_sigma_ns
        self.model_uere_m = model_uere_m
        self._slow = GaussMarkov(tau_s, rng, n_satellites)
        self._mp = GaussMarkov(multipath_tau_s, rng, n_satellites)
        self._nlos = GaussMarkov(nlos_tau_s, rng, n_satellites)
        self._vel_mp = GaussMarkov(multipath_tau_s, rng, 3)  # Doppler multipath follows the same geometry

    def step(self, dt_s: float, view: SkyView) -> EpochError:
        rng = self._rng
        slow, mp, nlos = self._slow.step(dt_s), self._mp.step(dt_s), self._nlos.step(dt_s)
        vel_mp = self._vel_mp.step(dt_s)
        n_vel = rng.standard_normal(3)
        n_time = float(rng.standard_normal())
        n = view.num_sv
        if n < 3:
            d = Dops(NO_DOP, NO_DOP, NO_DOP, NO_DOP)
            return EpochError(np.zeros(3), np.zeros(3), 0.0, np.zeros(3), math.inf, math.inf, math.inf, math.inf, d)
        ids, el, az = view.ids, view.el, view.az
        shape = 0.5 + 0.5 / np.sin(el)  # range error against elevation
        if view.canyon:  # reflections off facades: strongest for low satellites, little for those overhead
            mp_err = self.canyon_multipath_m * np.cos(el) ** 2 / np.sin(el) * mp[ids]
        else:
            mp_err = self.multipath_m * shape * mp[ids]
        err = self.uere_m * shape * slow[ids] + mp_err
        scale = self.nlos_m * (self.deep_factor if view.deep else 1.0)
        nlos_part = np.where(view.reflected, scale * (0.3 + np.abs(nlos[ids])), 0.0)
        err = err + nlos_part
        g = _design(az, el)
        if n == 3:  # 2D: the held height is a fourth, error-free equation for the fix
            g = np.vstack((g, (0.0, 0.0, 1.0, 0.0)))
            err = np.append(err, 0.0)
            w = np.append(1.0 / (self.model_uere_m * shape) ** 2, 1e4)
        else:
            w = 1.0 / (self.model_uere_m * shape) ** 2
        gw = g.T * w
        try:
            cov = np.linalg.inv(gw @ g)
        except np.linalg.LinAlgError:  # a degenerate geometry: no solution, as a receiver would give none
            d = Dops(NO_DOP, NO_DOP, NO_DOP, NO_DOP)
            return EpochError(np.zeros(3), np.zeros(3), 0.0, np.zeros(3), math.inf, math.inf, math.inf, math.inf, d)
        sol = cov @ (gw @ err)
        resid = err - g @ sol
        dof = len(err) - 4
        factor = max(1.0, float(resid @ (w * resid)) / dof) if dof > 0 else 1.0
        pos = sol[:3]
        dops = geometry_dops(az, el)
        if dops.pdop > PDOP_MASK:  # the receiver's navigation masks: no fix from such a geometry
            return EpochError(np.zeros(3), np.zeros(3), 0.0, np.zeros(3), math.inf, math.inf, math.inf, math.inf,
                              Dops(NO_DOP, NO_DOP, NO_DOP, NO_DOP))
        nlos_pos = cov @ (gw @ np.append(nlos_part, 0.0) if n == 3 else gw @ nlos_part)
        h_acc = math.sqrt(factor * (cov[0, 0] + cov[1, 1]))
        v_acc = math.sqrt(factor * cov[2, 2])
        vel_sigma = self.vel_sigma_mps * dops.pdop / 1.2
        vel = n_vel * vel_sigma
        if view.reflected.any():  # reflected carriers: a Doppler error that lasts as long as the reflection
            vel = vel + vel_mp * self.nlos_vel_sigma_mps
            vel_sigma = math.hypot(vel_sigma, self.nlos_vel_sigma_mps)
        t_sigma = self.clock_sigma_ns * dops.tdop
        return EpochError(pos, vel, n_time * t_sigma, nlos_pos[:3], h_acc, v_acc, vel_sigma, t_sigma, dops)
