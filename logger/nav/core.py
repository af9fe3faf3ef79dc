"""What the engine's rooms share: the filter core they act on, and a GNSS fix made ready for the filter.

The evidence rules (:mod:`logger.nav.evidence`) and the measurement policies (:mod:`logger.nav.policies`) each
hold their own state and act on the filter only through :class:`FilterCore`, which
:class:`logger.nav.engine.NavEngine` implements: the nominal state, the error-state EKF, and the few operations
that keep both consistent (bring the covariance to now and update, feed a correction back, look up the solution
at a past instant, reopen attitude and offsets). The start-up (:mod:`logger.nav.startup`) never touches the
filter: it is given values and hands back the initial state and covariance, which the engine installs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from logger.nav.dynamics import ProcessNoise
from logger.nav.ekf import ErrorStateEkf
from logger.nav.gnss_noise import FixFigures
from logger.nav.measurements import Observation
from logger.nav.params import NavParams
from logger.nav.state import NavState


@dataclass
class EngineCounters:
    """What the filter did since the start, for ``/nav/state``, ``logger replay`` and the health verdicts."""

    imu: int = 0
    imu_gaps: int = 0
    imu_out_of_order: int = 0
    gnss_fixes: int = 0
    gnss_thinned: int = 0  # fixes of a receiver faster than gnss_max_hz left out (gnss_rate.py)
    gnss_no_fix: int = 0
    gnss_few_sv: int = 0  # fixes left out for too few satellites
    gnss_skipped: int = 0  # GNSS rows (axes) that would add almost nothing but their bias
    gnss_canyon_heights: int = 0  # fix heights that would have gone in, left to the barometer as a street canyon's
    obd: int = 0
    baro: int = 0
    zupt: int = 0
    resets: int = 0
    reanchors: int = 0  # times good fixes or baro heights, refused in a row, made it widen its position uncertainty
    reopens: int = 0  # times trusted velocities, refused in a row, made it reopen velocity, attitude and offsets
    remounts: int = 0  # times the mount alignment, settled, replaced the mounting in use
    initialised_ns: int | None = None
    init_method: str = ""
    init_height_fixes: int = 0  # fixes the start's height was pooled from (start_height.py); 0: the start fix's


@dataclass
class PreparedFix:
    """A GNSS fix in the filter's terms: at its epoch on the logger's clock, in radians, with the noise to use."""

    t_ns: int  # the epoch (not the arrival), synchronised ns
    t_mono_ns: int
    lat: float  # rad
    lon: float  # rad
    h: float  # m above the ellipsoid
    vel: np.ndarray | None  # NED m/s (north and east given; down 0.0 unless vel_3d), None without a velocity
    vel_3d: bool  # the receiver gave the vertical velocity too (NMEA-only receivers do not)
    sigma: tuple[float, float, float]  # position noise N, E, D, m
    s_vel: float  # velocity noise, m/s
    fix_3d: bool
    figures: FixFigures  # its accuracy figures and where they came from (receiver, dop or nominal)
    # Its vertical figure over the receiver's usual one (gnss_noise.UsualFigure): a street canyon's is several
    # times the open sky's.
    v_over_usual: float = 1.0

    @property
    def h_acc(self) -> float:
        """The horizontal accuracy (hAcc convention) the fix is judged by, m: the receiver's or the model's."""
        return self.figures.h_acc


class FilterCore(Protocol):
    """The filter as its rooms see it."""

    params: NavParams
    n: int  # error states: 17 or 15
    lever: np.ndarray  # IMU to antenna, body axes, m
    state: NavState | None
    ekf: ErrorStateEkf | None
    counters: EngineCounters
    sigma: tuple[float, float, float]  # 1-sigma position N, E, D as last propagated or updated, m
    noise: ProcessNoise  # the IMU's densities in use: the configured, or wider as the drive shows them

    def apply(self, obs: Observation, gated: bool = True) -> bool:
        """Bring the covariance to now, update with ``obs`` and feed the correction back; whether it went in."""
        ...

    def feedback(self, dx: np.ndarray) -> None:
        """Feed an error estimate back into the nominal state (and into the late-fix history)."""
        ...

    def state_at(self, t_ns: int) -> NavState:
        """The solution at a past instant, corrected for every feedback since."""
        ...

    def reopen_attitude_and_offsets(self) -> None:
        """Forget what the filter believed of its attitude and IMU offsets (after it proved to be off)."""
        ...
