"""The filter on what real receivers send: no vertical velocity, no accuracy figures, fixes at 0.5-25 Hz, no epoch
time. Each is a normal input: the filter starts on it, stays inside its own 3 sigma, and still notices when it
has lost itself."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from test_nav_filter import errors, fed_with_upset, run
from test_nav_synth import SynthErrors, records

from logger.nav import policies
from logger.nav.engine import NavEngine
from logger.nav.gnss_noise import (
    DOP,
    NOMINAL,
    RECEIVER,
    AccuracyModel,
    CorrelatedGnssNoise,
    ScatterLearner,
    UsualFigure,
)
from logger.nav.gnss_rate import FixThinner
from logger.nav.gnss_time import GnssEpochClock
from logger.nav.health import HealthJudge
from logger.nav.params import NavParams
from logger.recording.records import feed_record, nav_feeder
from sensors.sim.scenarios import make_drive

NS = 1_000_000_000
T0 = 1_700_000_000 * NS


@pytest.fixture(scope="module")
def outage_drive():
    drive = make_drive("outage-60s", seed=1, duration_s=270.0)
    (span,) = drive.spans_of("outage")
    return drive, span


def _scores(drive, span, engine) -> tuple[np.ndarray, np.ndarray, float]:
    """RMSE N, E, D outside the outage, the share of rows within 3 sigma per axis, the largest outage error."""
    t, e, s = errors(drive, engine.rows)
    out = (t >= span.start_s) & (t < span.end_s)
    return (np.sqrt((e[~out] ** 2).mean(axis=0)), (np.abs(e) <= 3.0 * s).mean(axis=0),
            float(np.hypot(e[out, 0], e[out, 1]).max()))


@pytest.mark.parametrize("mode", ["17", "15"])
def test_an_nmea_only_receiver_starts_the_filter_and_the_filter_knows_its_height(outage_drive, mode):
    drive, span = outage_drive
    # RMC and GGA: speed and course but no vertical velocity, no accuracy and no DOP; 2 m per axis in truth.
    recs = records(drive, 270.0, seed=2, gnss_off=[(span.start_s, span.end_s)], receiver="nmea",
                   errors=SynthErrors(obd_factor=1.02, gnss_h_sigma=2.0, gnss_v_sigma=3.5))
    engine = run(recs, mode=mode)
    assert engine.counters.init_method == "gnss course" and engine.counters.resets == 0
    assert engine.last_readings.fix.figures.source == NOMINAL
    rmse, within, _ = _scores(drive, span, engine)
    assert rmse[0] < 1.0 and rmse[1] < 1.0
    assert (within >= 0.95).all(), within  # the height too: no vertical velocity was made up


def test_a_dop_without_accuracy_is_used_as_such(outage_drive):
    drive, _ = outage_drive
    recs = records(drive, 60.0, seed=2, receiver="gsa")
    engine = run(recs)
    assert engine.state is not None and engine.last_readings.fix.figures.source == DOP


def _ten_hz(drive, span, **params):
    # Errors that last a few seconds, as a receiver's own navigation filter and multipath make them: ten fixes a
    # second report much the same error ten times.
    recs = records(drive, 270.0, seed=3, gnss_off=[(span.start_s, span.end_s)], receiver="nmea", gnss_hz=10.0,
                   gnss_corr_s=3.0, errors=SynthErrors(obd_factor=1.02, gnss_h_sigma=2.0, gnss_v_sigma=3.5))
    return run(recs, **params)


def test_ten_fixes_a_second_weigh_what_their_shared_error_leaves_them(outage_drive):
    drive, span = outage_drive
    engine = _ten_hz(drive, span)
    assert engine.counters.init_method == "gnss course" and engine.counters.resets == 0
    _, within, _ = _scores(drive, span, engine)
    assert (within >= 0.95).all(), within
    # Taken as ten independent fixes a second, the same fixes make the filter far too sure of itself.
    _, within_white, _ = _scores(drive, span, _ten_hz(drive, span, gnss_independent_hz=10.0))
    assert within_white.min() < 0.95, within_white  # under the 95 % a consistent filter holds


def test_the_rate_factor_follows_the_receivers_usual_interval():
    noise = CorrelatedGnssNoise(corr_s=0.0, independent_hz=1.0)
    for k in range(50):
        h, _, _ = noise.sigmas(k * NS // 10, 3.0, 5.0, 0.3)  # 10 Hz
    assert noise.rate_factor() == pytest.approx(10.0)
    assert h == pytest.approx(3.0 / math.sqrt(2.0) * math.sqrt(10.0))
    noise.sigmas(60 * NS, 3.0, 5.0, 0.3)  # after a long gap, the first fix is an independent one
    assert noise.rate_factor() == 1.0


# With its own figures a receiver's fixes are judged one by one for whether they add anything (policies.
# UNINFORMATIVE_RATIO), each weighed as its share of the floor's lasting error (gnss_floor_corr_s): at 25 Hz 249 times
# its figure's variance, and nearly all were left out. Taken at 5 Hz (every fifth: gnss_max_hz, gnss_rate.py) the 25 Hz
# receiver does better, but no better than one at 5-10 Hz does on this drive, which is still over the bound: 86 % of a
# 10 Hz receiver's rows are left out too. Seed 3: 1.35 / 1.40 m at 10 Hz, 1.68 / 1.33 m at 25 Hz thinned, 2.18 / 2.36 m
# with every fix; seeds 3-10, horizontal: 1.5 m at 10 Hz, 2.6 m thinned, 3.7 m with every fix. Judged per independent
# fix instead (as CorrelatedGnssNoise.rate_factor counts them) they gave 1.1 / 1.05 / 1.3 m over six seeds, but the
# simulated phone's 10 Hz drives were then overconfident (90.8 % within 3 sigma vertically on urban seed 1): not
# landed. The NMEA receiver's guessed figures pass.
UBX_25HZ = pytest.mark.xfail(strict=True, reason="a receiver's own figures at 5-25 Hz: most rows left out, 1.3-1.7 m")


@pytest.mark.parametrize("receiver", [pytest.param("ubx", marks=UBX_25HZ), "nmea"])
@pytest.mark.parametrize("imu_hz", [20.0, 100.0])
def test_twenty_five_fixes_a_second_even_faster_than_the_imu(outage_drive, receiver, imu_hz):
    """A receiver at its fastest (25 Hz: u-blox M9 and F9R navigate that fast), faster than a 20 Hz IMU, so that
    one or two fixes come between two samples: every fifth goes in at its epoch, on a grid through the whole
    seconds (gnss_max_hz, 10 Hz: a second of them says no more than at 10 Hz), and the filter starts, holds its
    covariance and crosses the minute's outage as at 1 Hz."""
    drive, span = outage_drive
    recs = records(drive, 270.0, seed=3, gnss_off=[(span.start_s, span.end_s)], receiver=receiver, gnss_hz=25.0,
                   gnss_corr_s=3.0, imu_hz=imu_hz, errors=SynthErrors(obd_factor=1.02, gnss_h_sigma=2.0,
                                                                      gnss_v_sigma=3.5))
    engine = run(recs)
    rmse, within, worst = _scores(drive, span, engine)
    assert engine.counters.init_method == "gnss course" and engine.counters.resets == 0
    c = engine.counters
    # Every fifth, on the grid through the whole seconds: five a second.
    assert c.gnss_fixes > 5 * 200 and c.gnss_fixes == pytest.approx(0.2 * (c.gnss_fixes + c.gnss_thinned), abs=5)
    assert (within >= 0.95).all() and rmse[:2].max() < 1.2 and worst < 10.0, (rmse, within, worst)


@pytest.mark.parametrize(("period_ms", "step"), [(1000, 1), (200, 1), (125, 1), (100, 1), (50, 2), (40, 5)])
def test_fixes_faster_than_the_filter_needs_are_thinned_to_a_grid_through_the_whole_seconds(period_ms, step):
    """Receivers up to 10 Hz go in whole; a faster one's every step-th epoch by its epoch times, evenly spaced on a
    grid through the whole seconds, whose fixes are always taken (a 1 Hz post-processed solution is checked
    against those), even when the receiver's first fix came on an odd slot; after a gap the grid holds."""
    thinner = FixThinner(10.0)
    first = T0 + period_ms * 1_000_000  # not a whole second
    epochs = [first + k * period_ms * 1_000_000 for k in range(round(60_000 / period_ms))]
    taken = [e for e in epochs if thinner.take(e)]
    assert thinner.step == step
    settled = [e for e in taken if e >= T0 + 5 * NS]
    assert len(settled) == pytest.approx(1000 // period_ms // step * 55, abs=1)
    assert {e for e in epochs if e % NS == 0} <= set(taken)  # every whole second's
    assert {b - a for a, b in itertools.pairwise(settled)} == {step * period_ms * 1_000_000}  # evenly spaced
    # After 11 s without a fix (an outage), the receiver goes on at its rate: the grid holds.
    resumed = [epochs[-1] + 11 * NS + k * period_ms * 1_000_000 for k in range(3 * step)]
    assert [e for e in resumed if thinner.take(e)] == [e for e in resumed if e % (step * period_ms * 1_000_000) == 0]


def test_a_nav_pvt_epoch_some_nanoseconds_off_its_nominal_one_is_on_the_grid():
    """u-blox NAV-PVT gives the epoch's UTC with its ``nano``: tens of nanoseconds either side of the millisecond."""
    thinner = FixThinner(10.0)
    offsets = [14, -8, 4, -3, 22, 9, -11]
    taken = [k for k in range(500) if thinner.take(T0 + k * 40_000_000 + offsets[k % len(offsets)])]
    assert [k for k in taken if k >= 25] == list(range(25, 500, 5))


def test_the_grid_holds_through_epochs_lost_on_the_line():
    """One epoch in fifty lost (a sentence with a bad checksum): the period is the receiver's still, and every fix
    taken of a 25 Hz receiver is on the 5 Hz grid, each grid epoch that came taken. With the intervals' mean for the
    period, three in four taken were off the grid."""
    thinner = FixThinner(10.0)
    epochs = [T0 + k * 40_000_000 for k in range(2500) if k % 50 != 7]
    taken = [e for e in epochs if thinner.take(e)]
    assert taken[5:] == [e for e in epochs if e % 200_000_000 == 0 and e >= taken[5]]


def test_a_receiver_that_slows_down_has_its_fixes_taken_before_its_old_grid_is_forgotten():
    """25 Hz, then 1 Hz on epochs off the 5 Hz grid: the first slow fix, 80 ms after the last fast one, is left out
    as a grid would leave it; every one after it is taken (none for two grid spacings), while the last intervals
    still say 40 ms."""
    thinner = FixThinner(10.0)
    for k in range(100):
        thinner.take(T0 + k * 40_000_000)
    slow = [T0 + 4 * NS + 40_000_000 + k * NS for k in range(20)]
    assert [thinner.take(e) for e in slow] == [False] + [True] * 19
    assert thinner.period_ms == 1000


def test_a_receiver_whose_period_does_not_divide_the_second_has_every_step_th_fix_taken():
    """A 60 ms period (16.7 Hz; no receiver rate the logger sets, one set up by hand) has no grid through the whole
    seconds: every second fix by count. After a hole in the epochs the first fix is taken (none for two spacings),
    and the count starts again from it (and from the whole second at 3 s): before, the count went on from before the
    hole, and the fix after the first was taken too."""
    thinner = FixThinner(10.0)
    epochs = [k * 60 for k in range(40)] + [39 * 60 + 300 + k * 60 for k in range(1, 12)]
    taken = [t for t in epochs if thinner.take(T0 + t * 1_000_000)]
    assert (thinner.step, thinner.period_ms) == (2, 60)
    assert taken == [*range(0, 2340, 120), 2700, 2820, 2940, 3000, 3120, 3240]


def test_fixes_without_an_epoch_time_are_never_thinned():
    """Placed by their arrival, their spacing jitters (tens of milliseconds) and says little of the rate: taken."""
    thinner = FixThinner(10.0)
    for k in range(50):
        thinner.take(T0 + 40_000_000 * (k + 1))  # a 25 Hz receiver with its time
    assert thinner.step == 5
    assert all(thinner.take(None) for _ in range(10))


def test_a_gnss_only_solution_keeps_every_fix():
    """In GNSS-only mode the rows are the fixes: none is thinned whatever the rate."""
    engine = NavEngine(NavParams(mode="gnss"))
    assert engine._gnss._thinner.max_hz == 0.0 and engine._gnss._thinner.step == 1


def test_half_hertz_fixes_are_taken_in_full(outage_drive):
    drive, span = outage_drive
    recs = records(drive, 270.0, seed=4, gnss_off=[(span.start_s, span.end_s)], receiver="nmea", gnss_hz=0.5,
                   errors=SynthErrors(obd_factor=1.02, gnss_h_sigma=2.0, gnss_v_sigma=3.5))
    engine = run(recs)
    rmse, within, worst = _scores(drive, span, engine)
    assert engine.counters.resets == 0 and rmse[:2].max() < 1.2 and (within >= 0.95).all() and worst < 10.0


def test_without_accuracy_figures_a_filter_that_lost_itself_still_restarts():
    def teleport(engine) -> None:
        engine.state.lat += 300.0 / 6.36e6  # 300 m off, with the covariance still confident

    drive = make_drive("outage-60s", seed=3, duration_s=160.0)
    engine, done = fed_with_upset(records(drive, 160.0, seed=5, receiver="nmea"), 90.0, teleport)
    assert done and engine.counters.resets == 1
    _, e, _ = errors(drive, engine.rows)
    assert np.hypot(e[-1, 0], e[-1, 1]) < 3.0


def test_fixes_without_an_epoch_time_are_placed_by_their_arrival(outage_drive):
    drive, span = outage_drive
    recs = records(drive, 270.0, seed=2, gnss_off=[(span.start_s, span.end_s)], receiver="nmea",
                   epoch_time=False, latency_s=0.1, errors=SynthErrors(obd_factor=1.02, gnss_h_sigma=1.0))
    engine = run(recs)
    assert engine.counters.init_method == "gnss course" and engine.epoch_clock.method == "arrival"
    rmse, within, _ = _scores(drive, span, engine)
    assert rmse[:2].max() < 1.0 and (within >= 0.95).all(), (rmse, within)


def test_an_epoch_without_time_takes_the_latency_its_predecessors_showed():
    clock = GnssEpochClock()
    for k in range(20):  # locked, fixes arriving 180-220 ms after their epochs
        clock.epoch_time(T0 + k * NS + 180_000_000 + (k % 5) * 10_000_000, T0 + k * NS, "locked")
    t = clock.epoch_time(T0 + 30 * NS + 200_000_000, None, "locked")
    assert clock.method == "arrival, usual latency" and t == T0 + 30 * NS
    assert 0.02 <= clock.uncertainty_s < 0.05
    clock.epoch_time(T0 + 31 * NS + 200_000_000, None, "holdover")  # off UTC: the latency says nothing
    assert clock.method == "arrival" and clock.uncertainty_s == 0.1


def test_figures_come_from_the_receiver_then_the_dop_then_the_nominal_model():
    model = AccuracyModel(3.0, (3.0, 5.0, 0.3), learn=True)
    assert model.figures(0.8, 1.2, 0.05, 1.1) == pytest.approx(model.figures(0.8, 1.2, 0.05, None))
    fig = model.figures(0.8, None, None, None)  # GST without its vertical, no speed accuracy
    assert fig.source == RECEIVER and fig.v_acc == pytest.approx(0.8 * 5.0 / 3.0) and fig.s_acc == 0.3
    assert model.figures(None, None, None, 2.0).source == DOP
    fig = model.figures(None, None, None, None)
    assert (fig.source, fig.h_acc, fig.v_acc, fig.s_acc) == (NOMINAL, 3.0, 5.0, 0.3)
    assert NavParams().gnss_nominal_h_acc_m == 3.0  # the model's defaults are NavParams' (one place)


def test_dop_figures_follow_the_dops_definition_and_the_receivers_own_split():
    """HDOP x UERE is the horizontal 2D RMS (what hAcc is), VDOP x UERE the vertical sigma; the receiver's own
    HDOP and VDOP come first, PDOP's usual split fills in, and a GGA-only receiver's HDOP is not thrown away."""
    uere = NavParams().gnss_uere_m
    model = AccuracyModel(uere, (3.0, 5.0, 0.1), learn=False)
    fig = model.figures(None, None, None, 2.0, 1.0, 1.7)
    assert (fig.source, fig.h_acc, fig.v_acc) == (DOP, pytest.approx(uere), pytest.approx(1.7 * uere))
    fig = model.figures(None, None, None, 2.0)  # PDOP only: split 0.6 / 0.8
    assert (fig.h_acc, fig.v_acc) == (pytest.approx(1.2 * uere), pytest.approx(1.6 * uere))
    fig = model.figures(None, None, None, None, 2.5)  # GGA and RMC: HDOP only, the vertical by the nominal ratio
    assert (fig.source, fig.h_acc, fig.v_acc) == (DOP, pytest.approx(2.5 * uere), pytest.approx(2.5 * uere * 5 / 3))
    assert model.figures(None, None, None, 0.0, 0.0, 0.0).source == NOMINAL  # DOPs of 0: none given
    # The default range error puts an open sky's fix (HDOP 0.75) at the nominal figure: one receiver either way.
    assert model.figures(None, None, None, None, 0.75).h_acc == pytest.approx(NavParams().gnss_nominal_h_acc_m)


def test_guessed_heights_that_keep_one_offset_count_it_as_variance_and_stop_when_it_ends():
    """A canyon's reflections put an NMEA receiver's heights 15 m high for 40 s behind a DOP figure of about
    6 m: the innovations' running mean shows the offset, and the next fixes' vertical figure carries it; the
    horizontal is left as the DOP says. Noise alone, or an offset the filter's own variance explains (after an
    outage), adds next to nothing; once the fixes agree again, or none come, the excess fades."""
    ns = 1_000_000_000
    model = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=True)
    base = model.figures(None, None, None, None, 1.0, 1.5, 0)
    rng = np.random.default_rng(4)

    def feed(t0_s: float, seconds: int, offset_d: float, p_d: float) -> int:
        for k in range(seconds):
            t = int((t0_s + k) * ns)
            fig = model.figures(None, None, None, None, 1.0, 1.5, t)
            z = [float(rng.normal(0.0, 2.0)), float(rng.normal(0.0, 2.0)), offset_d + float(rng.normal(0.0, 4.0))]
            model.observe(t, fig, z, [0.5, 0.5, p_d])
        return t

    t = feed(0.0, 60, 0.0, 0.7)  # an open sky: noise only
    quiet = model.figures(None, None, None, None, 1.0, 1.5, t + ns)
    assert quiet.v_model < 1.1 * base.v_model and quiet.h_model == base.h_model
    t = feed(60.0, 40, 15.0, 0.7)  # the canyon
    canyon = model.figures(None, None, None, None, 1.0, 1.5, t + ns)
    assert canyon.v_model > math.hypot(base.v_model, 12.0) and canyon.h_model == base.h_model
    t = feed(100.0, 40, 0.0, 0.7)  # out of it: the fixes agree with the filter again
    assert model.figures(None, None, None, None, 1.0, 1.5, t + ns).v_model < 1.2 * base.v_model
    feed(140.0, 40, 15.0, 0.7)
    later = model.figures(None, None, None, None, 1.0, 1.5, int(240 * ns))  # a minute without fixes
    assert later.v_model < 1.1 * base.v_model
    outage = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=True)
    for k in range(20):  # the first fixes after an outage: the filter is 15 m off, and its variance says so
        outage.observe(k * ns, base, [0.0, 0.0, 15.0], [0.5, 0.5, 300.0])
    assert outage.figures(None, None, None, None, 1.0, 1.5, 20 * ns).v_model == pytest.approx(base.v_model)
    unlearnt = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=False)
    unlearnt.observe(0, base, [0.0, 0.0, 15.0], [0.5, 0.5, 0.7])
    assert unlearnt.figures(None, None, None, None, 1.0, 1.5, ns).v_model == base.v_model
    # A receiver that gives its own figures is never widened: neither learnt from nor added to.
    own = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=True)
    for k in range(40):
        own.observe(k * ns, base, [0.0, 0.0, 15.0], [0.5, 0.5, 0.7])  # even after guessed fixes showed an offset
    given = own.figures(0.5, 0.9, 0.05, 1.5, 1.0, 1.5, 41 * ns)
    assert (given.source, given.h_model, given.v_model, given.scale) == (RECEIVER, 0.5, 0.9, (1.0, 1.0))
    # After a minute without fixes, one fix 20 m off is one innovation, not an offset: nothing is added until
    # five have gone in again.
    gap = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=True)
    for k in range(30):
        gap.observe(k * ns, base, [0.0, 0.0, 0.0], [0.5, 0.5, 0.7])
    gap.observe(90 * ns, base, [0.0, 0.0, 20.0], [0.5, 0.5, 0.7])
    assert gap.figures(None, None, None, None, 1.0, 1.5, 91 * ns).v_model == base.v_model
    # A 2D fix has no height of its own: it does not move the vertical mean.
    flat = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=True)
    for k in range(40):
        flat.observe(k * ns, base, [0.0, 30.0], [0.5, 0.5])
    assert flat.figures(None, None, None, None, 1.0, 1.5, 41 * ns).v_model == base.v_model


def test_guessed_speeds_widen_while_the_innovations_show_a_reflection_and_never_narrow():
    """An NMEA receiver gives no speed figure: the nominal 0.1 m/s is an open sky's. A reflection puts its speeds
    0.6 m/s off for 30 s (the DOP unchanged); the velocity innovations show it within seconds and the speed figure
    covers it; once the speeds agree again, or none come, it is back at the
    nominal figure, which good speeds never narrow. Before any scatter is known (the first fixes, the first after
    an outage) the nominal figure follows the DOP. A receiver's own speed figure is never touched."""
    ns = 1_000_000_000
    model = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=True)
    rng = np.random.default_rng(7)
    p_v = 0.003  # the filter's own velocity variance, held by the OBD speed and the car's constraints

    def feed(t0_s: float, seconds: int, sigma: float, offset: float = 0.0) -> int:
        for k in range(seconds):
            t = int((t0_s + k) * ns)
            fig = model.figures(None, None, None, None, 0.75, 1.2, t)
            z = [offset + float(rng.normal(0.0, sigma)), float(rng.normal(0.0, sigma))]
            model.observe_speed(t, fig, z, [p_v, p_v], fig.s_acc**2)
        return t

    t = feed(0.0, 60, math.sqrt(0.0025 + p_v))  # an open sky, speeds better than the nominal figure says
    quiet = model.figures(None, None, None, None, 0.75, 1.2, t + ns)
    assert quiet.speed_guessed and quiet.s_acc == pytest.approx(0.1)
    t = feed(60.0, 30, 0.05, 0.6)
    canyon = model.figures(None, None, None, None, 0.75, 1.2, t + ns)
    assert canyon.s_acc > 0.4 and canyon.h_model == quiet.h_model  # the position's figure is the DOP's still
    t = feed(90.0, 40, 0.05)  # out of it: the speeds agree with the filter again
    assert model.figures(None, None, None, None, 0.75, 1.2, t + ns).s_acc == pytest.approx(0.1)
    t = feed(130.0, 30, 0.05, 0.6)
    assert model.figures(None, None, None, None, 0.75, 1.2, t + 30 * ns).s_acc < 0.15  # 30 s without a fix
    # The first fix after a minute without any, from a receiver reacquiring (HDOP 4 against an open sky's 0.75).
    assert model.figures(None, None, None, None, 4.0, 6.0, t + 60 * ns).s_acc == pytest.approx(0.1 * 4.0 / 0.75)
    t = feed(200.0, 4, 0.05, 0.6)  # four innovations since are not yet a scatter: still the DOP's figure
    assert model.figures(None, None, None, None, 0.75, 1.2, t + ns).s_acc == pytest.approx(0.1)
    t = feed(204.0, 3, 0.05, 0.6)
    assert model.figures(None, None, None, None, 0.75, 1.2, t + ns).s_acc > 0.4
    unlearnt = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=False)
    for k in range(30):
        unlearnt.observe_speed(k * ns, quiet, [0.6, 0.0], [p_v, p_v], 0.01)
    assert unlearnt.figures(None, None, None, None, 0.75, 1.2, 30 * ns).s_acc == 0.1
    # A receiver that gives its own speed figure keeps it, whatever guessed fixes taught the model before.
    given = model.figures(0.5, 0.9, 0.05, 1.5, 1.0, 1.5, t + ns)
    assert (given.s_acc, given.speed_guessed) == (0.05, False)
    own = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=True)
    for k in range(30):
        own.observe_speed(k * ns, given, [0.6, 0.0], [p_v, p_v], 0.0025)
    assert own.figures(None, None, None, None, 0.75, 1.2, 30 * ns).s_acc == pytest.approx(0.1)
    # A receiver's position figures without a speed figure (NMEA GST, gpsd without eps): the speed is guessed as
    # for any other, from its DOP before the scatter is known (GGA carries the HDOP).
    gst = AccuracyModel(4.0, (3.0, 5.0, 0.1), learn=True)
    fig = gst.figures(1.5, 2.5, None, None, 3.0, 4.0, ns)
    assert fig.source == RECEIVER and fig.speed_guessed and fig.s_acc == pytest.approx(0.1 * 3.0 / 0.75)
    for k in range(30):
        t = (2 + k) * ns
        gst.observe_speed(t, gst.figures(1.5, 2.5, None, None, 0.75, 1.2, t), [0.6, 0.0], [p_v, p_v], 0.01)
    assert gst.figures(1.5, 2.5, None, None, 0.75, 1.2, t + ns).s_acc > 0.4


def test_a_scatter_learnt_too_wide_is_learnt_again_from_fixes_too_weak_to_go_in():
    """After a tunnel, a 10 Hz NMEA receiver's first fixes (few satellites, a high DOP) taught the scatter learner a
    horizontal scale of 14 on the simulated drive: every open-sky fix after them was then too weak to go in, and
    a learner fed by accepted fixes only never learnt again. Fed by those too weak for the gate as well, the scale
    comes back down within a few minutes and the fixes go in again."""
    drive = make_drive("outage-60s", seed=1, duration_s=270.0)
    recs = records(drive, 270.0, seed=3, receiver="nmea", gnss_hz=10.0, gnss_corr_s=3.0,
                   errors=SynthErrors(obd_factor=1.02, gnss_h_sigma=1.0, gnss_v_sigma=2.0))

    def taught_too_wide(engine) -> None:
        learner = engine._gnss.accuracy.learner
        learner._z2[0] = learner._p[0] + 14.0 * learner._r[0]
        assert learner.scale()[0] == pytest.approx(14.0)

    engine, done = fed_with_upset(recs, 100.0, taught_too_wide)
    assert done and engine.counters.resets == 0
    assert engine._gnss.accuracy.learner.scale()[0] < 3.0  # 14 when it learnt from accepted fixes only
    t, e, s = errors(drive, engine.rows)
    late = t > 250.0
    assert s[late, :2].max() < 3.0 and np.hypot(e[late, 0], e[late, 1]).max() < 1.5  # sigma 5.2 m and growing


@pytest.mark.parametrize(("true_scale", "learnt"), [(9.0, 9.0), (4.0, 4.0), (0.25, 1.0), (100.0, 25.0)])
def test_the_scatter_widens_nominal_figures_and_never_narrows_them(true_scale, learnt):
    rng = np.random.default_rng(1)
    learner = ScatterLearner()
    r = [4.5, 4.5, 25.0]  # the nominal figures' variances (hAcc 3 m, vAcc 5 m)
    p = [0.3, 0.3, 0.6]
    for k in range(600):  # ten minutes at 1 Hz
        z = [float(rng.standard_normal()) * math.sqrt(p[i] + true_scale * r[i]) for i in range(3)]
        learner.add(T0 + k * NS, z, p, r)
    kh, kv = learner.scale()
    assert kh == pytest.approx(learnt, rel=0.35) and kv == pytest.approx(learnt, rel=0.35)


def test_nothing_is_learnt_from_a_short_drive():
    learner = ScatterLearner()
    for k in range(20):
        learner.add(T0 + k * NS, [30.0, 30.0, 30.0], [0.3, 0.3, 0.6], [4.5, 4.5, 25.0])
    assert learner.scale() == (1.0, 1.0)


def test_fixes_too_weak_for_the_gate_may_lower_the_learnt_scale_never_raise_it():
    """Nothing vetted a fix too weak to reach the gate: a filter that lost itself but holds a tight covariance would
    read its innovations as a receiver scattering widely. So such fixes may teach the learner that the scale is
    smaller than learnt, never that it is larger."""
    r = [4.5, 4.5, 25.0]
    lost = ScatterLearner()
    for k in range(300):  # five minutes of fixes 20 m from a filter sure of itself to 1 m
        lost.add(T0 + k * NS, [20.0, 20.0, 20.0], [1.0, 1.0, 1.0], r, gated=False)
    assert lost.scale() == (1.0, 1.0)
    wide = ScatterLearner()
    for k in range(300):  # a scale learnt from vetted fixes far off
        wide.add(T0 + k * NS, [8.0, 8.0, 15.0], [1.0, 1.0, 1.0], r)
    before = wide.scale()
    assert before[0] > 5.0
    for k in range(300, 600):  # then weak fixes that agree with the filter
        wide.add(T0 + k * NS, [0.5, 0.5, 1.0], [1.0, 1.0, 1.0], r, gated=False)
    after = wide.scale()
    assert after[0] < 0.5 * before[0] and after[1] <= before[1]


def test_real_receivers_nmea_reaches_the_filter_as_a_horizontal_velocity_with_figures():
    """The NMEA of the 36 real u-blox captures (GPSD's regression logs), decoded by the driver and recorded by the
    record layer, as the filter's GNSS policy takes it: every fix with a position is prepared, its velocity
    horizontal (NMEA has no vertical speed), its figures from GST, GSA or the nominal model as the capture holds."""
    from test_gnss_decode_gpsd import DATA_DIR, frames_of, load_capture

    from logger.nav.core import EngineCounters
    from logger.nav.gnss_time import GnssEpochClock
    from logger.nav.policies import GnssPolicy, LastReadings
    from logger.recording.records import gnss_observation, location_fix
    from sensors.ublox_decode import GnssDecoder, GnssFix
    from sensors.ublox_frames import KIND_NMEA

    sources: dict[str, int] = {}
    prepared = with_velocity = 0
    for log in sorted(p.name for p in DATA_DIR.glob("*.log")):
        decoder = GnssDecoder()
        frames = [f for f in frames_of(load_capture(log)) if f.kind == KIND_NMEA]
        fixes = [i for i in decoder.push_all(frames) + decoder.flush()
                 if isinstance(i, GnssFix) and i.source == "NMEA" and i.time_utc_ns is not None]
        policy = GnssPolicy(NavParams(), GnssEpochClock(), LastReadings(), None, None, None)  # type: ignore[arg-type]
        for fix in fixes:
            rec = location_fix(fix, 0)
            rec.update(t_sync_ns=fix.time_utc_ns + 200_000_000, t_mono_ns=fix.time_utc_ns, sync_state="locked")
            p = policy.prepare(gnss_observation(rec), EngineCounters())
            if fix.lat_deg is None or not fix.fix_ok or (fix.fix_mode or 1) < 2:
                assert p is None
                continue
            assert p is not None and math.isfinite(p.sigma[0]) and 0.0 < p.h_acc < 100.0, (log, fix)
            assert p.fix_3d == (fix.fix_mode == 3)  # a 2D fix goes in horizontally (its height, if any, unused)
            prepared += 1
            sources[p.figures.source] = sources.get(p.figures.source, 0) + 1
            if p.vel is not None:
                with_velocity += 1
                assert not p.vel_3d
    assert prepared > 100 and with_velocity > 100, (prepared, with_velocity)
    assert set(sources) == {RECEIVER, DOP, NOMINAL}, sources  # GST, else GSA, else the nominal model


def test_the_velocity_of_a_fix_whose_position_the_gate_refused_is_not_used(outage_drive):
    """A receiver just out of a tunnel gives a first solution off in every part (on the simulated urban drive: 12.8 m
    in height, its velocity 0.9 m/s off behind a 0.49 m/s figure). The gate refuses the position; the velocity of
    the same solution, taken on its own, moved the position a metre through the outage's correlations."""
    drive, span = outage_drive
    recs = records(drive, 270.0, seed=2, gnss_off=[(span.start_s, span.end_s)])
    first = next(i for i, (ts, tp, m) in enumerate(recs) if tp == "/gnss/fix" and m["fix_ok"]
                 and (m["gnss_time_ns"] - T0) / NS >= span.end_s)
    ts, tp, m = recs[first]
    bad_pos = {**m, "altitude": m["altitude"] + 40.0}
    bad_both = {**bad_pos, "vel_ned_mps": [m["vel_ned_mps"][0] + 1.5, m["vel_ned_mps"][1] - 1.5,
                                            m["vel_ned_mps"][2]]}
    upset = run([*recs[:first], (ts, tp, bad_both), *recs[first + 1:]])
    assert upset.ekf.stats["gnss_pos"].rejected >= 1
    # What the velocity said makes no difference: the solution's velocity went out with its position.
    other = run([*recs[:first], (ts, tp, bad_pos), *recs[first + 1:]])
    t_u, e_u, _ = errors(drive, upset.rows)
    t_o, e_o, _ = errors(drive, other.rows)
    assert len(t_u) == len(t_o) and np.abs(e_u - e_o).max() < 1e-9


def _in_a_canyon(recs, start_s: float, end_s: float, high_m: float) -> list:
    """The fixes of [start_s, end_s) as a street canyon's: heights ``high_m`` too high behind a vertical figure five
    times the open sky's (the horizontal twice): reflections, which lengthen every path they take."""
    out = []
    for ts, topic, m in recs:
        if topic == "/gnss/fix" and start_s <= (m["gnss_time_ns"] - T0) / NS < end_s:
            m = {**m, "altitude": m["altitude"] + high_m, "v_acc_m": 5.0 * m["v_acc_m"], "h_acc_m": 2.0 * m["h_acc_m"]}
        out.append((ts, topic, m))
    return out


def test_a_canyons_heights_are_left_to_the_barometer(outage_drive, monkeypatch):
    """90 s of canyon fixes 8 m high behind five times the open sky's vertical figure: with a barometer the height
    is held by it (the canyon's heights that would have gone in are left out, counted) and stays within half a
    metre (0.38 m); taken in, they moved it 0.83 m. Without a barometer (15 states) they are all there is and go
    in."""
    drive, _ = outage_drive
    recs = _in_a_canyon(records(drive, 270.0, seed=3), 60.0, 150.0, 8.0)

    def worst_height(engine) -> float:
        t, e, s = errors(drive, engine.rows)
        assert (np.abs(e[:, 2]) <= 3.0 * s[:, 2]).all()
        return float(np.abs(e[(t >= 60.0) & (t < 210.0), 2]).max())

    held = run(recs)
    assert held.counters.gnss_canyon_heights > 30 and held.counters.resets == 0
    assert worst_height(held) < 0.5
    no_baro = run(recs, mode="15")
    assert no_baro.counters.gnss_canyon_heights == 0
    monkeypatch.setattr(policies, "CANYON_HEIGHT_RATIO", math.inf)
    taken = run(recs)
    assert taken.counters.gnss_canyon_heights == 0
    assert worst_height(taken) > 1.5 * worst_height(held)


def test_a_long_canyon_checks_the_barometer_against_the_receiver_every_two_minutes(outage_drive):
    """A canyon longer than CANYON_HEIGHT_HOLD_NS: one height goes in once that long has passed since the last one
    did (the barometer's offset, which weather moves, is checked against the receiver), the others are left out."""
    drive, _ = outage_drive
    recs = _in_a_canyon(records(drive, 270.0, seed=3), 40.0, 200.0, 8.0)
    engine = NavEngine(NavParams(), record=True)
    feed = nav_feeder(engine)
    went_in, rows_in = [], []  # fixes whose height went in; fixes any of whose rows went in
    for _, topic, msg in recs:
        before, rows_before = engine.last_readings.height_in_ns, engine.last_readings.pos_ok
        feed_record(feed, topic, msg)
        if topic == "/gnss/fix" and engine.last_readings.height_in_ns != before:
            went_in.append((engine.last_readings.height_in_ns - T0) / NS)
        if topic == "/gnss/fix" and engine.last_readings.pos_ok != rows_before:
            rows_in.append((engine.last_readings.pos_ok[0] - T0) / NS)
    hold_s = policies.CANYON_HEIGHT_HOLD_NS / NS
    in_canyon = [t for t in went_in if 40.0 <= t < 200.0]
    before = max(t for t in went_in if t < 40.0)
    # The first fix after the hold whose rows go in takes its height along (one whose horizontal rows are too weak
    # as well), and no other in the canyon does: their rows went in without it.
    first = min(t for t in rows_in if t > before + hold_s)
    assert in_canyon == [first] and first < 200.0
    assert sum(40.0 <= t < before + hold_s for t in rows_in) > 30
    assert engine.counters.gnss_canyon_heights > 60


def test_one_unusually_good_figure_does_not_make_the_ordinary_ones_a_canyons():
    """The usual figure is a low quantile of each second's lowest, over 300 s of fixes: one figure of 0.3 m among
    1.0 m ones (a moment of SBAS) leaves it at 1.0; at 10 Hz the window is as long in seconds as at 1 Hz."""
    usual = UsualFigure()
    for k in range(100):
        got = usual.add(T0 + k * NS, 0.3 if k == 50 else 1.0)
    assert got == 1.0
    ten = UsualFigure()
    for k in range(5000):  # 500 s at 10 Hz: 0.5 m for the first 200 s, 3 m after (a canyon lasting 300 s)
        got = ten.add(T0 + k * NS // 10, 0.5 if k < 2000 else 3.0)
        if k == 4000:  # 200 s into the canyon: a third of the window is open sky, still the usual
            assert got == 0.5
    assert got == 3.0  # a window of canyon: the canyon is this receiver's usual now


def test_a_barometer_that_jumps_in_a_canyon_has_its_offset_widened_not_the_height(outage_drive):
    """The barometer reads 3 m off from 100 s on (a pressure port knocked) while the canyon's heights are left to
    it: its refusals widen its offset, as when the receiver's heights go in, and the height the last of them left
    stays (within 0.45 m; 1.95 m off when both were widened and the barometer pulled the height along)."""
    drive, _ = outage_drive
    recs = [(ts, topic, {**m, "altitude_m": m["altitude_m"] + 3.0} if topic == "/baro" and ts >= T0 + 100 * NS
             else m) for ts, topic, m in _in_a_canyon(records(drive, 270.0, seed=3), 60.0, 200.0, 8.0)]
    engine = run(recs)
    assert engine.counters.reanchors >= 1 and engine.counters.gnss_canyon_heights > 30
    t, e, _ = errors(drive, engine.rows)
    assert np.abs(e[(t >= 100.0) & (t < 200.0), 2]).max() < 0.6


def test_a_silent_barometer_gets_no_verdict_on_its_offset(outage_drive):
    """The barometer unplugged 100 s in: its offset stands still because nothing moves it, which "stable, +0.00
    m/min" would have called good news. The operator reads that there is no barometer, and for how long."""
    drive, _ = outage_drive
    recs = [r for r in records(drive, 270.0, seed=3) if not (r[1] == "/baro" and r[0] >= T0 + 100 * NS)]
    engine = NavEngine(NavParams(), record=False)
    feed = nav_feeder(engine)
    judge = HealthJudge()
    said = {}
    for ts, topic, msg in recs:
        feed_record(feed, topic, msg)
        t_s = (ts - T0) / NS
        if topic == "/imu" and engine.state is not None and round(t_s * 20) % 200 == 0:  # every 10 s
            said[round(t_s)] = judge.verdicts(engine, t_s)
    assert any(v.startswith("barometer offset stable") for v in said[90])
    late = said[max(said)]
    assert not any(v.startswith("barometer offset") for v in late), late
    assert any(v.startswith("no barometer for 1") and "runs without it" in v for v in late), late


def test_a_fix_held_past_a_second_is_placed_on_its_own_epoch_by_the_pps():
    """Clock not locked yet, PPS edges known: the offset's whole seconds come from the shortest delay of the last
    fixes, not from each fix's own: an NMEA epoch held until the next burst (1.5 s after it) took a second too many
    and landed on its successor's time."""
    clock = GnssEpochClock()
    frac = 123_000_000  # the board clock 0.123 s past UTC's seconds
    for k in range(5):
        clock.pps(T0 + k * NS + frac)
    for k in range(5):  # arriving 0.2 s after their epochs
        assert clock.epoch_time(T0 + k * NS + frac + 200_000_000, T0 + k * NS, "free") == T0 + k * NS + frac
    assert clock.method == "pps"
    assert clock.epoch_time(T0 + 5 * NS + frac + 1_500_000_000, T0 + 5 * NS, "free") == T0 + 5 * NS + frac


def test_an_epoch_completed_over_a_second_after_it_is_placed_by_the_read_it_began_in():
    """u-blox's factory NMEA at 9600 baud: a 0.9 s burst that begins 0.15 s after its epoch is read whole 1.07 s after
    it, every epoch. Clock not locked yet, PPS edges known: the whole seconds come from the read each epoch began in
    (the record's opened_mono_ns), as the clock pairs it; from the completing read, every epoch was placed a second
    late (20 m at 20 m/s) until the clock locked."""
    frac = 123_000_000  # the board clock 0.123 s past UTC's seconds; its t_sync runs 40 s ahead of its t_mono
    feed = nav_feeder(engine := NavEngine(NavParams(mode="17")))
    for k in range(5):
        feed_record(feed, "/pps", {"t_sync_ns": T0 + k * NS + frac, "t_mono_ns": T0 - 40 * NS + k * NS + frac,
                                   "seqno": k})
        began, done = T0 + k * NS + frac + 150_000_000, T0 + k * NS + frac + 1_070_000_000
        feed_record(feed, "/gnss/fix", {
            "t_sync_ns": done, "t_mono_ns": done - 40 * NS, "opened_mono_ns": began - 40 * NS,
            "gnss_time_ns": T0 + k * NS, "sync_state": "freerun", "fix_ok": True, "fix_mode": 3, "latitude": 48.1,
            "longitude": 11.5, "altitude": 545.0, "vel_ned_mps": [0.0, 0.0, None], "pdop": 1.5, "hdop": 0.9,
            "vdop": 1.2, "num_sv": 9})
        fix = engine.last_readings.fix
        assert engine.epoch_clock.method == "pps" and fix is not None and fix.t_ns == T0 + k * NS + frac, k
    # The same fixes without the read they began in (one read held each): a second late.
    clock = GnssEpochClock()
    clock.pps(T0 + frac)
    assert clock.epoch_time(T0 + frac + 1_070_000_000, T0, "free") == T0 + NS + frac
    # One epoch whose first message is dated a second early (a tail taken for its head): it and the next are placed
    # by the others' reads, not a second early (the shortest of the last ten moved ten epochs).
    clock = GnssEpochClock()
    clock.pps(T0 + frac)
    placed = []
    for k in range(8):
        began = T0 + k * NS + frac + 150_000_000 - (NS if k == 3 else 0)
        placed.append(clock.epoch_time(T0 + k * NS + frac + 1_070_000_000, T0 + k * NS, "free", began)
                      - (T0 + k * NS))
    assert placed == [frac] * 8
