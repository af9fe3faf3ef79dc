"""The start's height: the fixes before the start carried by the barometer (logger/nav/start_height.py)."""

from __future__ import annotations

import math

import numpy as np
from test_nav_synth import NS, T0_NS, records, truth_at

from logger.nav.core import PreparedFix
from logger.nav.engine import NavEngine
from logger.nav.gnss_noise import RECEIVER, FixFigures
from logger.nav.params import NavParams
from logger.nav.start_height import MIN_WINDOW_S, StartHeight, window_s
from logger.recording.records import feed_record, nav_feeder
from sensors.sim.scenarios import make_drive


def fix(t_s: float, h: float, sigma_v: float = 1.0, vd: float | None = None, fix_3d: bool = True) -> PreparedFix:
    return PreparedFix(t_ns=T0_NS + round(t_s * NS), t_mono_ns=round(t_s * NS), lat=0.8, lon=0.2, h=h,
                       vel=None if vd is None else np.array([10.0, 0.0, vd]), vel_3d=vd is not None,
                       sigma=(0.5, 0.5, sigma_v), s_vel=0.1, fix_3d=fix_3d,
                       figures=FixFigures(0.7, sigma_v, 0.1, RECEIVER, (1.0, 1.0)))


def climbing(t_s: float) -> float:
    """The true height of a car climbing at 0.5 m/s."""
    return 100.0 + 0.5 * t_s


def test_the_fixes_before_the_start_are_brought_to_it_by_the_barometer() -> None:
    """A car climbing 0.5 m/s, a barometer 30 m off reading the climb exactly, fixes whose errors alternate +-1.5 m:
    the start is the true height (what one fix alone could not say), carried from the last barometer reading to
    the fix's epoch by its vertical velocity."""
    sh = StartHeight(60.0)
    for k in range(20):
        sh.baro(T0_NS + round((k + 0.3) * NS), climbing(k + 0.3) - 30.0)
        if k < 19:
            sh.fix(fix(float(k), climbing(k) + (1.5 if k % 2 else -1.5)))
    last = fix(19.0, climbing(19.0) + 1.5, vd=-0.5)
    start = sh.start_fix(last)
    # 18 fixes have readings on both sides (the first is before the first reading): 9 at +1.5, 9 at -1.5.
    assert sh.used == 18
    assert abs(start.h - climbing(19.0)) < 1e-6
    assert abs(last.h - climbing(19.0)) == 1.5  # what the start took before


def test_more_certain_fixes_weigh_more() -> None:
    sh = StartHeight(60.0)
    for k in range(6):
        sh.baro(T0_NS + k * NS, 50.0)
    sh.fix(fix(1.0, 102.0, sigma_v=1.0))
    sh.fix(fix(2.0, 100.0, sigma_v=0.5))  # weight 4
    start = sh.start_fix(fix(4.5, 110.0))
    assert abs(start.h - (102.0 + 4 * 100.0) / 5) < 1e-9


def test_without_what_it_needs_the_start_is_the_fix_itself() -> None:
    """No barometer, a barometer that stopped, only 2D fixes, only fixes older than the window: the fix as it is."""
    last = fix(100.0, 123.0)
    assert StartHeight(60.0).start_fix(last) is last
    stopped = StartHeight(60.0)
    for k in range(10):
        stopped.baro(T0_NS + k * NS, 10.0)
        stopped.fix(fix(float(k), 200.0))
    assert stopped.start_fix(last) is last
    flat = StartHeight(60.0)
    old = StartHeight(60.0)
    for k in range(101):
        flat.baro(T0_NS + k * NS, 10.0)
        old.baro(T0_NS + k * NS, 10.0)
        if k < 99:
            flat.fix(fix(float(k), 200.0, fix_3d=False))
        if k < 30:
            old.fix(fix(float(k), 200.0))
    assert flat.start_fix(last) is last and flat.used == 0
    assert old.start_fix(last) is last and old.used == 0


def test_a_fix_surer_than_the_pool_and_a_single_fix_keep_their_own_height() -> None:
    """The pool's variance holds the barometer's (0.5 m here, once whole for the reading at the start): a receiver
    sure of its height to 3 cm (RTK) keeps its own, and so does a start with only one fix to pool; a receiver at
    1 m takes the pool."""
    def pooled(sigma_last: float, fixes: int) -> tuple[float, int]:
        sh = StartHeight(60.0, baro_sigma_m=0.5)
        for k in range(12):
            sh.baro(T0_NS + k * NS, 50.0)
        for k in range(11 - fixes, 11):
            sh.fix(fix(float(k), 100.0 + (1.0 if k % 2 else -1.0)))
        start = sh.start_fix(fix(11.0, 103.0, sigma_v=sigma_last))
        return start.h, sh.used

    assert pooled(0.03, 10) == (103.0, 0)
    assert pooled(1.0, 1) == (103.0, 0)
    h, used = pooled(1.0, 10)
    assert used == 10 and abs(h - 100.0) < 1e-9


def start_height_errors(window_s: float | None) -> np.ndarray:
    """The filter's height error at its start on eight synthetic drives (white fix errors, 1 m vertical), with
    the fixes before the start pooled over ``window_s`` (None: the default) or not (0)."""
    out = []
    for seed in range(8):
        drive = make_drive("outage-60s", seed=6, duration_s=30.0)
        engine = NavEngine(NavParams(), record=True)
        if window_s is not None:
            engine.start_height = StartHeight(window_s)
        feed = nav_feeder(engine)
        for _, topic, msg in records(drive, 30.0, seed=100 + seed):
            feed_record(feed, topic, msg)
        row = engine.rows[0]
        assert (engine.counters.init_height_fixes > 3) == (window_s != 0.0)
        out.append(row[4] - truth_at(drive, row[0]).height_m)
    return np.array(out)


def test_the_filter_starts_nearer_the_true_height_than_its_last_fix() -> None:
    """Standing 8 s then moving off: the fixes of the ten seconds before the start (the default window, two
    multipath correlation times) are pooled. The start's height error is then the mean of theirs and the
    barometer's noise (RMS 0.5 m on these drives); from the last fix alone it is that fix's (1 m)."""
    assert window_s(NavParams()) == 10.0 and window_s(NavParams(gnss_multipath_corr_s=0.0)) == MIN_WINDOW_S
    pooled, single = start_height_errors(None), start_height_errors(0.0)
    rms_pooled, rms_single = math.sqrt(np.mean(pooled**2)), math.sqrt(np.mean(single**2))
    assert rms_pooled < 0.5 * rms_single, (pooled, single)
    assert rms_single > 0.5  # the drives' fixes do carry their 1 m error: the comparison means something
