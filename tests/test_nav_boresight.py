"""The mounting refined at the office from a constraint-free solution's side slip and climb (nav/boresight.py)."""

from __future__ import annotations

import math

import numpy as np

from logger.nav.boresight import MAX_RESIDUAL_DEG, MIN_MOVING_S, refined, residual
from logger.nav.engine import TrajectoryRow
from logger.nav.mounting import mount_matrix
from logger.nav.rotations import dcm_from_euler, euler_from_dcm, quat_from_dcm, skew

TRUE_MOUNT = (5.0, -4.0, 30.0)


def _assumed(true_rpy, e_rad) -> tuple[float, float, float]:
    """A mounting off the true one by the small rotation ``e`` (true axes = (I + [e x]) x assumed axes)."""
    m = np.linalg.solve(np.eye(3) + skew(e_rad), mount_matrix(true_rpy))
    u, _, vt = np.linalg.svd(m)
    return tuple(math.degrees(a) for a in euler_from_dcm(u @ vt))


def _rows(assumed_rpy, seconds: float, parked_s: float = 0.0, hz: float = 20.0,
          dead_reckoned: tuple[float, float] = (0.0, 0.0)) -> list[TrajectoryRow]:
    """A solution computed with ``assumed_rpy`` of a car driving along its own axis (turning, on grades), after
    ``parked_s`` standing with a slewing attitude that would bias the mean if it counted; from ``dead_reckoned[0]`` s
    of driving on for ``dead_reckoned[1]`` s no fix holds it: its velocity drifts 1.5 deg off the car's axis and its
    position sigma grows past boresight.MAX_SIGMA_M."""
    m_err = mount_matrix(TRUE_MOUNT) @ mount_matrix(assumed_rpy).T  # assumed vehicle axes -> true vehicle axes
    rows = []
    n_parked, n = int(parked_s * hz), int((parked_s + seconds) * hz)
    for i in range(n):
        t = i / hz
        heading = 0.3 * t + 0.8 * math.sin(0.05 * t)
        grade = 0.03 * math.sin(0.02 * t)
        c_n_true = dcm_from_euler(0.01 * math.sin(0.1 * t), grade, heading)
        moving = i >= n_parked
        speed = 8.0 + 4.0 * math.sin(0.01 * t) if moving else 0.0
        drifting = 0.0 <= t - parked_s - dead_reckoned[0] < dead_reckoned[1]
        v = c_n_true @ np.array((speed, speed * math.radians(1.5) if drifting else 0.0, 0.0))
        c_n_assumed = c_n_true @ m_err if moving else dcm_from_euler(0.0, 0.2, 3.0 * t)
        sigma = 2.0 + (t - parked_s - dead_reckoned[0]) if drifting else 1.0
        rows.append(TrajectoryRow(int(1e18 + t * 1e9), int(t * 1e9), 0.9, 0.2, 100.0, float(v[0]), float(v[1]),
                                  float(v[2]), quat_from_dcm(c_n_assumed), (sigma, sigma, sigma), 0))
    return rows


def test_the_side_slip_and_climb_give_back_the_mounting_in_pitch_and_yaw():
    e = (0.0, math.radians(0.3), math.radians(-0.6))  # the alignment 0.3 deg off about the car's y, 0.6 about z
    assumed = _assumed(TRUE_MOUNT, e)
    rows = _rows(assumed, 300.0, parked_s=60.0)
    r = residual(rows)
    assert r is not None and r.usable()
    assert residual(rows[::-1]) == r  # rows given in any order
    # Only the rows at speed count (the parked minute's attitude would move the mean by degrees).
    assert abs(r.moving_s - 300.0) < 1.0, r.moving_s
    assert abs(r.slip_deg - 0.6) < 0.005 and abs(r.climb_deg + 0.3) < 0.005, r
    assert r.slip_se_deg < 0.01 and r.climb_se_deg < 0.01  # noise-free rows: no scatter
    before = np.abs(np.array(assumed) - TRUE_MOUNT)
    after = np.abs(np.array(refined(assumed, r)) - TRUE_MOUNT)
    assert before.max() > 0.3 and after.max() < 0.01, (before, after)


def test_dead_reckoning_does_not_count():
    """A tunnel's minute without fixes: the constraint-free solution's velocity drifts off the car's axis, and its rows
    (position sigma past MAX_SIGMA_M) are left out; its first seconds, still near the last fix, count."""
    e = (0.0, 0.0, math.radians(-0.6))
    rows = _rows(_assumed(TRUE_MOUNT, e), 300.0, dead_reckoned=(100.0, 60.0))
    r = residual(rows)
    # Its sigma passes 5 m after 3 s: 61 of its 1200 rows count, 4861 in all (242.95 s between them).
    assert r is not None and abs(r.moving_s - 242.95) < 0.01, r
    # Those 61 move the mean by 61 / 4861 of the drift's 1.5 deg (all 1200 would by 1200 / 6000: 0.3 deg).
    assert abs(r.slip_deg - (0.6 + 1.5 * 61 / 4861)) < 0.002, r


def test_a_short_drive_or_a_large_residual_is_not_taken_for_the_mounting():
    short = residual(_rows(_assumed(TRUE_MOUNT, (0.0, 0.0, 0.005)), MIN_MOVING_S - 20.0))
    assert short is not None and not short.usable()
    large = residual(_rows(_assumed(TRUE_MOUNT, (0.0, 0.0, math.radians(MAX_RESIDUAL_DEG + 0.5))), 300.0))
    assert large is not None and not large.usable()
    assert residual(_rows(TRUE_MOUNT, 0.0, parked_s=30.0)) is None  # nothing at speed
