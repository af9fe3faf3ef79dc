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
