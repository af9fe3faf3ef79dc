"""IMU samples in batches (``NavEngine.imu_batch``: a FIFO read, replay's runs of /imu records) give the trajectory
the samples give one by one, and the block forms of the per-sample bookkeeping match their per-sample forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_nav_synth import records

from logger.nav import engine as engine_module
from logger.nav.engine import BATCH_MIN, NavEngine
from logger.nav.imu_noise import ImuNoiseMonitor
from logger.nav.mounting import MountAlignment
from logger.nav.params import NavParams
from logger.nav.rotations import dcm_from_quat, euler_from_dcm, quat_from_rotvec, quat_mul, rotvec_from_dcm
from logger.nav.startup import Startup
from logger.nav.stops import StopDetector
from logger.nav.strapdown import preintegrate
from logger.nav.thermal import TemperatureSpan
from logger.recording.records import feed_record, nav_feeder
from sensors.sim.scenarios import make_drive

NS = 1_000_000_000


def _with_temperature(recs, degc_per_s: float = 0.01):
    """The records with a die temperature that warms slowly and reads with noise, as the MPU-6050's does."""
    rng = np.random.default_rng(5)
    t0 = recs[0][0]
    for t, topic, msg in recs:
        if topic == "/imu":
            msg["temp_degc"] = 30.0 + degc_per_s * (t - t0) / NS + rng.normal(0.0, 0.03)
    return recs


def _runs(recs, longest: int):
    """Consecutive /imu records (at most ``longest``) as one item, every other record alone."""
    out, run = [], []
    for rec in recs:
        if rec[1] == "/imu":
            run.append(rec[2])
            if len(run) < longest:
                continue
        if run:
            out.append(("batch", run))
            run = []
        if rec[1] != "/imu":
            out.append((rec[1], rec[2]))
    if run:
        out.append(("batch", run))
    return out


def _twins(items, **params) -> tuple[NavEngine, NavEngine]:
    """Two engines over the same items: one sample by sample (each with its batch's temperature, as a FIFO read
    has one), one batch by batch."""
    one, many = NavEngine(NavParams(**params), record=True), NavEngine(NavParams(**params), record=True)
    feed_one, feed_many = nav_feeder(one), nav_feeder(many)
    for topic, item in items:
        if topic != "batch":
            feed_record(feed_one, topic, item)
            feed_record(feed_many, topic, item)
            continue
        temp = item[-1].get("temp_degc")
        t = [m["t_sync_ns"] for m in item]
        mono = [m["t_mono_ns"] for m in item]
        acc = np.array([m["accel_mps2"] for m in item])
        gyro = np.array([m["gyro_rps"] for m in item])
        for m in item:
            one.imu(m["t_sync_ns"], m["t_mono_ns"], tuple(m["accel_mps2"]), tuple(m["gyro_rps"]), temp)
        many.imu_batch(np.array(t), np.array(mono), acc, gyro, temp)
    return one, many


def _same_trajectory(one: NavEngine, many: NavEngine) -> None:
    assert one.state is not None and many.state is not None
    assert len(one.rows) == len(many.rows) and len(one.epochs) == len(many.epochs)
    assert [r.t_ns for r in one.rows] == [r.t_ns for r in many.rows]
    assert [r.epoch for r in one.rows] == [r.epoch for r in many.rows]
    a = np.array([(r.lat_rad, r.lon_rad) for r in one.rows]) * 6.4e6
    b = np.array([(r.lat_rad, r.lon_rad) for r in many.rows]) * 6.4e6
    assert np.abs(a - b).max() < 1e-6  # metres: round-off
    for field in ("h_m", "vn_mps", "ve_mps", "vd_mps"):
        assert np.abs(np.array([getattr(r, field) for r in one.rows])
                      - np.array([getattr(r, field) for r in many.rows])).max() < 1e-6
    assert np.abs(np.array([r.q for r in one.rows]) - np.array([r.q for r in many.rows])).max() < 1e-9
    assert np.abs(np.array([r.sigma_ned_m for r in one.rows])
                  - np.array([r.sigma_ned_m for r in many.rows])).max() < 1e-6
    assert np.abs(one.ekf.p - many.ekf.p).max() < 1e-9
    c1, c2 = vars(one.counters), vars(many.counters)
    assert c1 == c2
    assert {k: (v.accepted, v.rejected) for k, v in one.ekf.stats.items()} == \
        {k: (v.accepted, v.rejected) for k, v in many.ekf.stats.items()}


@pytest.fixture
def short_blocks(monkeypatch):
    """Blocks of 8 samples and more go through the block forms (the records' runs are shorter than BATCH_MIN)."""
    monkeypatch.setattr(engine_module, "BATCH_MIN", 8)


@pytest.fixture(scope="module")
def fast_drive():
    """Two and a half minutes of the outage scenario with a 100 Hz IMU: a stop, driving, turns."""
    drive = make_drive("outage-60s", seed=3, duration_s=150.0)
    return _with_temperature(records(drive, 150.0, seed=4, imu_hz=100.0))


@pytest.mark.parametrize("mode", ["17", "15"])
def test_batches_of_a_fast_imu_give_the_trajectory_of_its_samples(fast_drive, mode, short_blocks):
    one, many = _twins(_runs(fast_drive, 40), mode=mode)
    _same_trajectory(one, many)
    assert one.mech.coning and many.mech.coning


def test_batches_across_the_covariance_interval_a_stop_and_without_obd(short_blocks):
    """FIFO reads of a second each (the covariance interval, the idle check and a stop fall inside them) on a
    board mounted at an angle; no OBD speed, so the idle check decides the stops."""
    drive = make_drive("urban", seed=1, duration_s=150.0)  # stops from 131 s
    recs = [r for r in _with_temperature(records(drive, 150.0, seed=4, imu_hz=100.0)) if r[1] != "/obd/speed"]
    one, many = _twins(_runs(recs, 100), mounting_rpy_deg=(2.0, -3.0, 10.0), cov_interval_s=0.3)
    _same_trajectory(one, many)
    assert one.counters.zupt > 0


def test_short_batches_and_a_sample_out_of_order_go_sample_by_sample(fast_drive):
    one, many = _twins(_runs(fast_drive, BATCH_MIN - 1))
    _same_trajectory(one, many)
    t = many.t_last_ns
    k = BATCH_MIN + 10
    order = [1, 2, 0, *range(3, k)]
    many.imu_batch(np.array([t + 10_000_000 * i for i in order]), np.zeros(k, np.int64),
                   np.tile((0.0, 0.0, -9.8), (k, 1)), np.zeros((k, 3)))
    assert many.counters.imu_out_of_order == 1 and many.t_last_ns == t + 10_000_000 * (k - 1)


@pytest.mark.parametrize("block", [50, 25], ids=["a reading a block", "a reading two blocks"])
def test_block_bookkeeping_matches_sample_by_sample(block):
    rng = np.random.default_rng(1)
    n = 3000
    t = (np.cumsum(rng.uniform(0.004, 0.006, n)) * NS).astype(np.int64)
    t[1500:] += 2 * NS  # a gap: the noise monitor restarts its differences
    acc = rng.normal((0.1, -0.2, -9.8), 0.05, (n, 3))
    gyro = rng.normal(0.0, 0.01, (n, 3))
    dt = np.diff(t, prepend=t[0]) / NS
    stops_a, stops_b = StopDetector(), StopDetector()
    noise_a, noise_b = ImuNoiseMonitor(), ImuNoiseMonitor()
    temp_a, temp_b = TemperatureSpan(), TemperatureSpan()
    mount_a, mount_b = MountAlignment((0.0, 0.0, 0.0)), MountAlignment((0.0, 0.0, 0.0))
    for i in range(n):
        stops_a.add(int(t[i]), tuple(acc[i]), tuple(gyro[i]))
        noise_a.add(tuple(acc[i]), tuple(gyro[i]), float(dt[i]))
        temp_a.add(int(t[i]), 30.0 + i // 50 * 0.04)  # one reading per block of 50, warming by steps
        mount_a.sample(int(t[i]), tuple(acc[i]), tuple(gyro[i]))
    for lo in range(0, n, block):
        sl = slice(lo, lo + block)
        stops_b.add_block(t[sl], acc[sl], gyro[sl])
        noise_b.add_block(acc[sl], gyro[sl], dt[sl])
        temp_b.add_block(t[sl], 30.0 + lo // 50 * 0.04)
        mount_b.sample_block(t[sl], acc[sl], gyro[sl])
    assert stops_b.var_a == pytest.approx(stops_a.var_a, rel=1e-9)
    assert stops_b.var_w == pytest.approx(stops_a.var_w, rel=1e-9)
    assert noise_b.densities() == pytest.approx(noise_a.densities(), rel=1e-9)
    assert noise_b.seen_s == pytest.approx(noise_a.seen_s, rel=1e-12)
    assert temp_b.take() == pytest.approx(temp_a.take(), rel=1e-9) and temp_a.range_degc > 0.5
    assert temp_b.range_degc == pytest.approx(temp_a.range_degc, rel=1e-12)
    for probe in (t[100], t[1499], t[-1]):
        a, b = mount_a._sum_at(int(probe)), mount_b._sum_at(int(probe))
        assert a[0] == b[0] and a[7] == b[7] and np.allclose(a[1:7], b[1:7], rtol=1e-12)
    assert math.isfinite(noise_a.densities()[0])


@pytest.mark.parametrize(("per_run", "mounting"), [(40, (0.0, 0.0, 0.0)), (1500, (2.0, -3.0, 10.0))],
                         ids=["reads", "runs longer than the stop window, mounted"])
def test_a_1khz_imu_is_integrated_ten_samples_a_step_on_the_trajectory_of_its_samples(per_run, mounting):
    """FIFO reads of a 1 kHz IMU go in steps of ten samples (``integration_hz`` 100: coning and sculling inside each
    step): a row per step, each where the samples one by one put the vehicle at that sample, through a start,
    turns and the covariance's intervals. Runs of 1.5 s (cut at the OBD speeds and fixes) take the start-up's
    block form too, on a board mounted at an angle."""
    drive = make_drive("outage-60s", seed=3, duration_s=40.0)
    recs = _with_temperature(records(drive, 40.0, seed=4, imu_hz=1000.0))
    one, many = _twins(_runs(recs, per_run), mounting_rpy_deg=mounting)
    assert one.startup.levelled is not None
    _same_steps(one, many)


def test_1khz_steps_close_the_covariance_interval_inside_a_read():
    """Without OBD speeds (whose updates bring the covariance up to date themselves) the covariance's interval
    (0.3 s here) ends inside a FIFO read: the step ends on that sample, the interval counts up to it, the rest of
    the read opens the next one."""
    drive = make_drive("outage-60s", seed=3, duration_s=40.0)
    recs = [r for r in _with_temperature(records(drive, 40.0, seed=4, imu_hz=1000.0)) if r[1] != "/obd/speed"]
    one, many = _twins(_runs(recs, 40), cov_interval_s=0.3)
    _same_steps(one, many)
    assert len(many.epochs) == len(one.epochs) > 60  # 88: one per 0.3 s of the 25 s the filter ran, or an update


def _same_steps(one: NavEngine, many: NavEngine) -> None:
    """``many`` (1 kHz reads in steps of ten samples) where ``one`` (sample by sample) is at the steps' ends."""
    assert one.state is not None and many.state is not None and one.mech.coning
    assert one.counters.imu == many.counters.imu == 40001
    assert one.counters.initialised_ns == many.counters.initialised_ns
    started = [r for r in one.rows if r.t_ns >= one.counters.initialised_ns]
    assert len(started) > 20_000
    # A row per step of ten samples (a step is cut short where the covariance's interval ends).
    assert 0.1 * len(started) <= len(many.rows) <= 0.12 * len(started)
    by_t = {r.t_ns: r for r in one.rows}
    assert all(r.t_ns in by_t for r in many.rows)
    a = np.array([(r.lat_rad, r.lon_rad, r.h_m, r.vn_mps, r.ve_mps, r.vd_mps) for r in many.rows])
    b = np.array([(by_t[r.t_ns].lat_rad, by_t[r.t_ns].lon_rad, by_t[r.t_ns].h_m, by_t[r.t_ns].vn_mps,
                   by_t[r.t_ns].ve_mps, by_t[r.t_ns].vd_mps) for r in many.rows])
    a[:, :2] *= 6.4e6
    b[:, :2] *= 6.4e6
    d = np.abs(a - b).max(axis=0)
    assert d[:3].max() < 1e-4 and d[3:].max() < 1e-5  # m, m/s (measured: 8 um, 1 um/s over 25 s of driving)
    q = np.abs(np.array([r.q for r in many.rows]) - np.array([by_t[r.t_ns].q for r in many.rows])).max()
    assert q < 1e-6  # 1e-4 deg (measured 6e-8)
    moved = np.hypot(*(b[-1, :2] - b[0, :2]))
    assert moved > 100.0
    assert np.abs(one.ekf.p - many.ekf.p).max() < 1e-6 * np.abs(one.ekf.p).max()


def test_preintegrated_steps_hold_the_coning_and_sculling_of_their_samples():
    """Steps of ten 1 ms samples of a coning and sculling motion (a 20 Hz wobble of 1 rad/s, a force turning with it):
    each preintegrated step against the samples' rotations chained one by one and their velocity increments summed in
    the step's first body frame. Without the cross terms the errors are tens of times larger."""
    dt, m, om = 0.001, 40, 2.0 * math.pi * 20.0
    t = np.arange(m + 1) * dt
    w = np.stack((np.cos(om * t), np.sin(om * t), 0.3 * np.ones_like(t)), axis=1)
    f = np.stack((2.0 * np.sin(om * t), -2.0 * np.cos(om * t), -9.8 + 0.5 * np.cos(om * t)), axis=1)
    starts = np.arange(0, m, 10)
    rot, dv, lengths = preintegrate(w, f, np.full(m, dt), starts)
    assert lengths == pytest.approx(np.full(4, 10 * dt))
    for g, lo in enumerate(starts.tolist()):
        q, v = (1.0, 0.0, 0.0, 0.0), np.zeros(3)
        plain_v = np.zeros(3)
        for k in range(lo, lo + 10):
            th = 0.5 * (w[k] + w[k + 1]) * dt
            u = 0.5 * (f[k] + f[k + 1]) * dt
            v += dcm_from_quat(q) @ (u + 0.5 * np.cross(th, u))  # the interval in the step's first body frame
            plain_v += u + 0.5 * np.cross(th, u)
            q = quat_mul(q, quat_from_rotvec(*th))
        exact = rotvec_from_dcm(dcm_from_quat(q))
        plain = 0.5 * ((w[lo:lo + 10] + w[lo + 1:lo + 11]) * dt).sum(axis=0)
        assert np.abs(rot[g] - exact).max() < 0.05 * np.abs(plain - exact).max()
        assert np.abs(rot[g] - exact).max() < 1e-7
        assert np.abs(dv[g] - v).max() < 0.05 * np.abs(plain_v - v).max()
        assert np.abs(dv[g] - v).max() < 5e-6  # the second order left out: alpha^2 ~ 1e-4 of a 0.1 m/s increment


@pytest.mark.parametrize("interval_s", [0.05, None], ids=["each sample", "20 Hz means, sized by the detector"])
@pytest.mark.parametrize("ask_every", [1, 7], ids=["asked after each", "blocks kept between asks"])
def test_stop_window_mixing_blocks_and_single_samples_matches_sample_by_sample(ask_every, interval_s):
    """Blocks and single samples in turn (a FIFO drive's reads cut at measurements), the window's old end inside a
    block, a block's samples leaving it from a single sample's add: the same variances as sample by sample, asked
    after each block or single, or only now and then (the blocks kept meanwhile are taken as one)."""
    rng = np.random.default_rng(3)
    n = 6000
    t = (np.cumsum(rng.uniform(0.0009, 0.0011, n)) * NS).astype(np.int64)
    acc = rng.normal((0.1, -0.2, -9.8), 0.05, (n, 3))
    gyro = rng.normal(0.0, 0.01, (n, 3))
    one, mixed = StopDetector(), StopDetector()
    if interval_s is not None:  # each sample a mean of its own; else the 1 kHz samples' first interval sizes means
        one.set_interval(interval_s)  # of 50 (stops.MEAN_S) in each detector, a mean across reads
        mixed.set_interval(interval_s)
    i, checks, steps = 0, 0, 0
    while i < n:
        k = int(rng.integers(1, 90))
        sl = slice(i, min(n, i + k))
        for j in range(sl.start, sl.stop):
            one.add(int(t[j]), tuple(acc[j]), tuple(gyro[j]))
        if k < 20:
            for j in range(sl.start, sl.stop):
                mixed.add(int(t[j]), tuple(acc[j]), tuple(gyro[j]))
        else:
            mixed.add_block(t[sl], acc[sl], gyro[sl])
        steps += 1
        i = sl.stop
        if steps % ask_every and i < n:
            continue
        # The variance is a difference of running sums 1e4 times larger than it (the mean squared): summed in
        # another grouping (blocks joined) they differ by round-off, about 1e-13 of themselves, 1e-9 of it.
        rel = 1e-9 if ask_every == 1 else 1e-8
        assert mixed.var_a == pytest.approx(one.var_a, rel=rel)
        assert mixed.var_w == pytest.approx(one.var_w, rel=rel)
        checks += 1
    assert one.group == mixed.group and (one.group == 1 if interval_s else 45 <= one.group <= 56)
    assert checks > 100 / ask_every and len(one._win) == mixed._n > 900 // one.group


@pytest.mark.parametrize("interval_s", [0.05, None], ids=["each sample", "20 Hz means, sized by the detector"])
def test_stop_flags_of_a_block_are_what_each_sample_added_alone_would_leave(interval_s):
    """``still_flags`` before the samples go in (singles, FIFO reads, a block longer than the window): after each
    sample the word :attr:`still` gives when the samples are added one by one, through stops and starts."""
    rng = np.random.default_rng(2)
    n = 6000
    t = (np.cumsum(rng.uniform(0.0009, 0.0011, n)) * NS).astype(np.int64)
    acc = rng.normal((0.1, -0.2, -9.8), 0.02, (n, 3))
    gyro = rng.normal(0.0, 0.002, (n, 3))
    for a, b in ((1500, 1700), (3000, 3050), (4000, 4600)):  # the vehicle moves (and sways at 4 Hz)
        acc[a:b] += rng.normal(0.0, 0.3, (b - a, 3)) + 0.3 * np.sin(2.0 * np.pi * 4.0 * t[a:b, None] / NS)
    one, blocks = StopDetector(), StopDetector()
    if interval_s is not None:
        one.set_interval(interval_s)
        blocks.set_interval(interval_s)
    expected = []
    for i in range(n):
        one.add(int(t[i]), tuple(acc[i]), tuple(gyro[i]))
        expected.append(one.still)
    got: list[bool] = []
    i, k = 0, 0
    while i < n:
        size = (1, 1, 3, 40, 40, 1, 2000, 40, 7)[k % 9]
        k += 1
        sl = slice(i, min(n, i + size))
        got.extend(blocks.still_flags(t[sl], acc[sl], gyro[sl]).tolist())
        if size < 3:
            for j in range(sl.start, sl.stop):
                blocks.add(int(t[j]), tuple(acc[j]), tuple(gyro[j]))
        else:
            blocks.add_block(t[sl], acc[sl], gyro[sl])
        i = sl.stop
    assert got == expected and one.group == blocks.group and (one.group == 1 if interval_s else 45 <= one.group <= 56)
    assert 0.2 < np.mean(expected) < 0.8 and np.count_nonzero(np.diff(expected)) >= 4


def test_start_up_steps_in_blocks_match_its_steps_one_by_one():
    """``Startup.step_block`` against ``step`` per sample: standstills too short to level (reset), the levelling
    ending at the first sample that moves, the provisional attitude carried on the gyro and kept per sample."""
    rng = np.random.default_rng(4)
    n = 4000
    t = (np.arange(n) * 0.005 * NS).astype(np.int64) + 10 * NS
    dts = np.full(n, 0.005)
    acc = rng.normal((0.3, -0.2, -9.8), 0.02, (n, 3))
    gyro = rng.normal((0.01, -0.02, 0.005), 0.003, (n, 3))
    still = np.zeros(n, dtype=bool)
    still[100:200] = True  # 0.5 s: too short (align_min_s 2 s), reset at the next moving sample
    still[300:1200] = True  # 4.5 s: levels at 1200
    still[1500:2500] = True  # after the levelling: ignored
    gyro[1200:, 2] += 0.1  # turning once it moves
    one, many = Startup(NavParams()), Startup(NavParams())
    for i in range(n):
        assert one.step(int(t[i]), tuple(acc[i]), tuple(gyro[i]), float(dts[i]), bool(still[i]), None) == ""
    for lo in range(0, n, 70):
        assert many.step_block(t[lo:lo + 70], acc[lo:lo + 70], gyro[lo:lo + 70], dts[lo:lo + 70],
                               still[lo:lo + 70], None) is None
    assert one.levelled is not None and many.levelled is not None
    assert one.level_span == many.level_span == (int(t[1199]), pytest.approx(899 * 0.005))
    assert np.allclose(np.array(many.levelled[:2] + many.levelled[2] + many.levelled[3]),
                       np.array(one.levelled[:2] + one.levelled[2] + one.levelled[3]), rtol=1e-12, atol=1e-15)
    assert np.abs(np.array(many.prov_q) - np.array(one.prov_q)).max() < 1e-12
    assert [h[0] for h in many._prov_hist] == [h[0] for h in one._prov_hist] == t[1200:].tolist()
    assert np.abs(np.array([h[1] for h in many._prov_hist]) - np.array([h[1] for h in one._prov_hist])).max() < 1e-12
    assert abs(euler_from_dcm(dcm_from_quat(one.prov_q))[2]) > 0.01  # the gyro turned it


@pytest.mark.parametrize("heading_source", ["gnss", "config"])
def test_blocks_before_the_start_give_the_start_and_trajectory_of_its_samples(heading_source):
    """FIFO reads of a second at 100 Hz (past ``PRE_INIT_BATCH_MIN``) from the drive's first sample: the standstill
    levelled, the attitude carried until the course tells the heading (or the configured heading starting the filter
    inside a read, the rest of the read integrated), and the same trajectory as sample by sample."""
    drive = make_drive("outage-60s", seed=3, duration_s=60.0)
    recs = _with_temperature(records(drive, 60.0, seed=4, imu_hz=100.0))
    assert engine_module.PRE_INIT_BATCH_MIN <= 100
    one, many = _twins(_runs(recs, 100), heading_source=heading_source)
    assert one.startup.levelled is not None
    assert one.counters.init_method == many.counters.init_method == (
        "config heading" if heading_source == "config" else "gnss course")
    assert one.counters.initialised_ns == many.counters.initialised_ns
    _same_trajectory(one, many)


def test_replay_takes_a_fast_imus_reads_in_a_row_as_one_block(tmp_path):
    """A 200 Hz IMU's FIFO reads are ten samples: alone each is under the block forms' least (and integrated sample by
    sample, a row each). Replay feeds the reads that follow one another with nothing between them as one run, as the
    live navigator feeds a wake-up's: the ~40 samples between two measurements go in steps of ``integration_hz``
    (100 Hz, two samples), a row per step, where the samples one by one put the vehicle at the steps' ends."""
    from test_navigator_merge import _read

    from logger.exports.trajectory import run_filter
    from logger.recording.recorder import Recorder
    from logger.recording.settings import RecorderSettings
    from logger.recording.topics import TOPICS

    drive = make_drive("outage-60s", seed=3, duration_s=40.0)
    recs = records(drive, 40.0, seed=4, imu_hz=200.0)
    rec = Recorder(RecorderSettings(out_dir=tmp_path), TOPICS)
    rec.start()
    for topic, item in _runs(recs, 10):  # FIFO reads of ten samples, each stamped with its 5 ms period
        if topic == "batch":
            read = _read(item, 30.0, period_s=0.005)
            assert rec.submit("/imu/batch", read, read["t_sync_ns"][0], read["t_mono_ns"][0])
        else:
            assert rec.submit(topic, item, item["t_sync_ns"], item["t_mono_ns"])
    rec.stop()
    files = sorted(tmp_path.glob("*.mcap"))
    engine, rows = run_filter(files, NavParams())
    one = NavEngine(NavParams(), record=True)
    feed = nav_feeder(one)
    for _, topic, msg in recs:
        feed_record(feed, topic, msg)
    assert engine.counters.imu == one.counters.imu == 8001
    started = [r for r in one.rows if r.t_ns >= one.counters.initialised_ns]
    assert 0.5 * len(started) <= len(rows) <= 0.6 * len(started)
    by_t = {r.t_ns: r for r in one.rows}
    a = np.array([(r.lat_rad, r.lon_rad) for r in rows if r.t_ns in by_t]) * 6.4e6
    b = np.array([(by_t[r.t_ns].lat_rad, by_t[r.t_ns].lon_rad) for r in rows if r.t_ns in by_t]) * 6.4e6
    assert len(a) > 0.95 * len(rows) and np.abs(a - b).max() < 0.01  # metres: the steps' second order
