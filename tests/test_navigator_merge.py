"""The navigator hands a run of consecutive FIFO reads to the filter as one block (``Navigator.take``): at 1 kHz a
read is 40 samples, too few for the engine's block forms alone. The trajectory, its rows and epochs, the counters
and what is published are those of the reads fed one by one, as the navigator fed them before."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from test_nav_batch import _runs, _same_trajectory, _with_temperature
from test_nav_synth import records

from logger.nav.engine import BATCH_MIN, PRE_INIT_BATCH_MIN, NavEngine
from logger.nav.params import NavParams
from logger.recording.intervals import GRID_TOLERANCE
from logger.recording.nav_rerun import NavRerun
from logger.recording.topics import IMU_BATCH, NAV_FIX, NAV_STATE
from logger.runtime.navigator import WAKE_S, Navigator
from logger.runtime.sampler import Reading
from sensors.sim.scenarios import make_drive

NS = 1_000_000_000
IMU_HZ = 1000.0
PER_READ = 40  # 25 FIFO reads a second at 1 kHz

Item = tuple[int, str, dict[str, Any]]  # (time queued, topic, record)


def _read(msgs: list[dict[str, Any]], temp_degc: float | None, lost: int = 0,
          period_s: float = 1.0 / IMU_HZ) -> dict[str, Any]:
    """An /imu/batch record (the fields the navigator uses) from /imu samples: one die temperature per read."""
    a, g = np.array([m["accel_mps2"] for m in msgs]).T, np.array([m["gyro_rps"] for m in msgs]).T
    return {"t_sync_ns": [m["t_sync_ns"] for m in msgs], "t_mono_ns": [m["t_mono_ns"] for m in msgs],
            "accel_x_mps2": a[0].tolist(), "accel_y_mps2": a[1].tolist(), "accel_z_mps2": a[2].tolist(),
            "gyro_x_rps": g[0].tolist(), "gyro_y_rps": g[1].tolist(), "gyro_z_rps": g[2].tolist(),
            "temp_degc": None if temp_degc is None else round(temp_degc, 3), "period_s": period_s, "lost": lost,
            "seq": msgs[0].get("seq", 0)}


@pytest.fixture(scope="module")
def reads() -> list[Item]:
    """A minute of the outage scenario as a 1 kHz FIFO IMU gives it: reads of 40 samples (shorter where a GNSS
    fix, an OBD speed or a barometer reading came in between), each with its die temperature, which warms, reads
    with noise, and steps by half a degree at 30 s; the filter starts at about 15 s."""
    recs = _with_temperature(records(make_drive("outage-60s", seed=3, duration_s=60.0), 60.0, seed=4,
                                     imu_hz=IMU_HZ))
    t0 = recs[0][0]
    out: list[Item] = []
    for topic, item in _runs(recs, PER_READ):
        if topic == "batch":
            t = item[-1]["t_sync_ns"]
            out.append((t, IMU_BATCH, _read(item, item[-1]["temp_degc"] + (0.5 if t - t0 > 30 * NS else 0.0))))
        else:
            out.append((item["t_sync_ns"], topic, item))
    return out


def _navigator(**params: Any) -> tuple[Navigator, list[Reading], list[tuple[int, int]]]:
    """A navigator (no thread) whose engine keeps its rows and epochs, what it publishes, and each engine call
    for IMU samples as (first sample's time, samples). A strapdown step per sample unless ``integration_hz`` is
    given: steps of several samples end where a block ends, so merging would move them (see the last test)."""
    params.setdefault("integration_hz", 0.0)
    published: list[Reading] = []
    nav = Navigator(NavParams(**params), publish=published.append)
    calls: list[tuple[int, int]] = []

    def make_engine(p: NavParams) -> NavEngine:
        engine = NavEngine(p, record=True)
        block = engine.imu_batch

        def imu_batch(t: Any, *rest: Any) -> None:
            calls.append((int(t[0]), len(t)))
            block(t, *rest)

        engine.imu_batch = imu_batch  # type: ignore[method-assign]
        return engine

    nav.rerun = NavRerun(nav.params, make_engine)
    return nav, published, calls


def _read_by_read(nav: Navigator, items: list[Item]) -> None:
    """What the navigator did before runs were merged: each record fed alone, a publish check after each read
    (and /nav/fix from the engine's tap, at the first sample that reaches its time)."""
    nav._arm_tap()
    for _, topic, m in items:
        nav.rerun.feed(topic, m)
        if topic == IMU_BATCH:
            nav._maybe_publish()


def _merged(nav: Navigator, items: list[Item], merge: bool = True, phase_ns: int = 0) -> None:
    """The navigator's wake-ups: what was queued in each WAKE_S, taken at once (``phase_ns``: the first wake-up
    that much later)."""
    wake = int(WAKE_S * NS)
    chunk: list[tuple[str, dict[str, Any]]] = []
    end = items[0][0] + wake + phase_ns
    for t, topic, m in items:
        if t >= end:
            nav.take(chunk, merge)
            chunk, end = [], end + (t - end) // wake * wake + wake
        chunk.append((topic, m))
    nav.take(chunk, merge)
    nav.flush()  # the drive's last measurements, after its last IMU sample


def _same_publishing(one: list[Reading], many: list[Reading]) -> None:
    for topic in (NAV_FIX, NAV_STATE):
        a = [r.payload for r in one if r.topic == topic]
        b = [r.payload for r in many if r.topic == topic]
        assert len(a) > (10 if topic == NAV_STATE else 100)
        assert [m["t_sync_ns"] for m in a] == [m["t_sync_ns"] for m in b]
        assert [m["t_mono_ns"] for m in a] == [m["t_mono_ns"] for m in b]
    fa = np.array([(m["latitude"], m["longitude"]) for m in (r.payload for r in one if r.topic == NAV_FIX)])
    fb = np.array([(m["latitude"], m["longitude"]) for m in (r.payload for r in many if r.topic == NAV_FIX)])
    assert np.abs(fa - fb).max() * 111_000 < 1e-6  # metres


@pytest.mark.parametrize("mode", ["17", "15"])
def test_merged_reads_give_the_trajectory_and_fixes_of_reads_one_by_one(reads, mode):
    one, pub_one, calls_one = _navigator(mode=mode)
    many, pub_many, calls_many = _navigator(mode=mode)
    _read_by_read(one, reads)
    _merged(many, reads)
    _same_trajectory(one.engine, many.engine)
    assert many.processed == len(reads)
    assert many.engine.thermal.range_degc == pytest.approx(one.engine.thermal.range_degc, rel=1e-9)
    assert one.engine.thermal.range_degc > 0.5  # the step counted, in both
    assert one.engine.counters.imu == sum(len(m["t_sync_ns"]) for _, topic, m in reads if topic == IMU_BATCH)
    _same_publishing(pub_one, pub_many)
    # Read by read, no call reaches the block forms; merged, most samples after the start go through them.
    assert max(n for _, n in calls_one) <= PER_READ
    start = many.engine.counters.initialised_ns
    after = [n for t, n in calls_many if t > start + NS]
    # Runs end at every other record (OBD speeds at 2 Hz, barometer and fixes at 1 Hz), at each /nav/state and at
    # each wake-up, not at the /nav/fix times (five a second) that the engine's tap serves from inside them.
    assert sum(n for n in after if n >= BATCH_MIN) > 0.75 * sum(after)
    assert max(after) >= 10 * PER_READ
    assert len(after) < 6 * (many.engine.t_last_ns - start) / NS
    # Before the start nothing is published: runs end only at other records (here the OBD speed's and the
    # barometer's, a few a second), none at a publishing time, and go through the engine's block form.
    before = [n for t, n in calls_many if t < start]
    assert sum(n for n in before if n >= PRE_INIT_BATCH_MIN) > 0.9 * sum(before) > 10 * IMU_HZ
    assert max(before) >= 10 * PER_READ


def test_before_a_configured_heading_starts_the_filter_runs_go_in_whole(reads):
    """With ``heading_source = "config"`` the filter starts at the end of the levelling, inside a run: until then
    nothing is published and runs are not cut for it either; the trajectory is the one of reads one by one."""
    one, _, _ = _navigator(heading_source="config")
    many, _, calls = _navigator(heading_source="config")
    _read_by_read(one, reads)
    _merged(many, reads)
    _same_trajectory(one.engine, many.engine)
    assert many.engine.counters.init_method == "config heading"
    before = [n for t, n in calls if t < many.engine.counters.initialised_ns]
    assert sum(n for n in before if n >= PRE_INIT_BATCH_MIN) > 0.9 * sum(before) > 5 * IMU_HZ


def test_fixes_go_out_at_publish_hz_after_merged_reads(reads):
    nav, published, _ = _navigator(publish_hz=5.0)
    _merged(nav, reads)
    fixes = [r.payload for r in published if r.topic == NAV_FIX]
    states = [r.payload for r in published if r.topic == NAV_STATE]
    t = np.array([m["t_sync_ns"] for m in fixes])
    span_s = (reads[-1][0] - nav.engine.counters.initialised_ns) / NS
    gaps = np.diff(t) / NS
    # Each fix after the first read to reach the next tick of a 0.2 s grid (or GRID_TOLERANCE of it before): never
    # sooner, later by at most that read.
    assert gaps.min() >= 0.2 * (1 - GRID_TOLERANCE) and gaps.max() <= 0.2 + PER_READ / IMU_HZ + 1e-9
    assert span_s / (0.2 + PER_READ / IMU_HZ) <= len(fixes) <= span_s / 0.2 + 1
    assert span_s / (1.0 + PER_READ / IMU_HZ) <= len(states) <= span_s + 1
    assert t[0] >= nav.engine.counters.initialised_ns


def test_a_gap_lost_samples_and_a_read_out_of_order_go_alone(reads):
    """Half a second without reads (a gap the filter counts), a read after a FIFO overflow, and two reads queued
    the wrong way round: each goes to the filter alone, as before, and nothing else changes."""
    items = list(reads)
    at = [i for i, (t, topic, _) in enumerate(items) if topic == IMU_BATCH and t > reads[0][0] + 35 * NS]
    gap = at[:15]  # 0.6 s of reads: gone
    overflow = at[40]
    swapped = at[60], at[61]
    t_over, _, m = items[overflow]
    items[overflow] = (t_over, IMU_BATCH, {**{k: v[3:] if isinstance(v, list) else v for k, v in m.items()},
                                           "lost": 3})
    items[swapped[0]], items[swapped[1]] = items[swapped[1]], items[swapped[0]]
    alone = [items[i][2] for i in (at[15], overflow, *swapped)]  # the later of the two jumps ahead: alone too
    items = [r for i, r in enumerate(items) if i not in set(gap)]
    one, pub_one, _ = _navigator()
    many, pub_many, calls = _navigator()
    _read_by_read(one, items)
    _merged(many, items)
    _same_trajectory(one.engine, many.engine)
    _same_publishing(pub_one, pub_many)
    c = many.engine.counters
    assert c.imu_gaps == 1 and c.imu_out_of_order == len(alone[3]["t_sync_ns"])
    for m in alone:
        assert (m["t_sync_ns"][0], len(m["t_sync_ns"])) in calls


def test_take_without_merging_is_read_by_read(reads):
    """``take(records, merge=False)``, the benchmark's comparison, feeds every read alone as before."""
    part = reads[: len(reads) // 2]
    one, pub_one, calls_one = _navigator()
    alone, pub_alone, calls_alone = _navigator()
    _read_by_read(one, part)
    _merged(alone, part, merge=False)
    assert calls_alone == calls_one and max(n for _, n in calls_alone) <= PER_READ
    _same_trajectory(one.engine, alone.engine)
    assert [r.payload for r in pub_alone] == [r.payload for r in pub_one]


def test_merged_reads_in_steps_of_ten_samples_publish_the_solution_of_their_time(reads):
    """With the default ``integration_hz`` (a strapdown step per ten samples at 1 kHz) /nav/fix is the solution at
    the end of the first step that reaches its time, whether the reads go one by one or merged (a step ends where
    a block does, so they step at other samples): each fix a publishing period after the last and at most a step
    later, and where the filter stepping sample by sample is at that time, to micrometres."""
    one, pub_one, _ = _navigator(integration_hz=100.0)
    many, pub_many, _ = _navigator(integration_hz=100.0)
    each, _, _ = _navigator()
    _read_by_read(one, reads)
    _merged(many, reads)
    _read_by_read(each, reads)
    assert len(many.engine.rows) < 0.2 * len(each.engine.rows)
    at = {r.t_ns: r for r in each.engine.rows}
    for pub in (pub_one, pub_many):
        a = [r.payload for r in pub if r.topic == NAV_FIX]
        t = np.array([m["t_sync_ns"] for m in a])
        gaps = np.diff(t) / NS
        assert len(a) > 100 and gaps.min() >= 0.2 and gaps.max() <= 0.2 + 10 / IMU_HZ + 1e-9
        pa = np.array([(m["latitude"], m["longitude"], m["altitude"]) for m in a])
        pb = np.array([(math.degrees(at[k].lat_rad), math.degrees(at[k].lon_rad), at[k].h_m) for k in t.tolist()])
        assert np.abs(pa[:, :2] - pb[:, :2]).max() * 111_000 < 1e-4 and np.abs(pa[:, 2] - pb[:, 2]).max() < 1e-4


def _offered(recs: list[tuple[int, str, dict[str, Any]]], per_read: int, period_s: float) -> list[Item]:
    """Records as the daemon offers them: FIFO reads of ``per_read`` samples queued after their last sample (not
    cut at anything), every other record at its own time, so a speed or a fix read while the FIFO filled comes
    before the read that holds the samples before it."""
    out: list[Item] = []
    run: list[dict[str, Any]] = []
    for t, topic, m in recs:
        if topic != "/imu":
            out.append((t, topic, m))
            continue
        run.append(m)
        if len(run) == per_read:
            out.append((run[-1]["t_sync_ns"], IMU_BATCH, _read(run, run[-1]["temp_degc"], period_s=period_s)))
            run = []
    if run:
        out.append((run[-1]["t_sync_ns"], IMU_BATCH, _read(run, run[-1]["temp_degc"], period_s=period_s)))
    return sorted(out, key=lambda x: x[0])  # stable: a read queued at a measurement's time stays before it


def test_measurements_offered_ahead_of_their_samples_wait_for_them():
    """20 Hz through the FIFO, two reads a second: an OBD speed, a fix or a barometer reading is offered before
    the read holding the samples before it. The navigator gives them to the filter where their time falls among
    the samples, as replay does: the same trajectory as the records fed in time order. Taken as offered, the
    speed was compared with the velocity of the last sample integrated, up to half a second older (on a recorded
    urban drive the live /nav/fix was 2.3 m RMSE north instead of 0.6 m)."""
    recs = _with_temperature(records(make_drive("urban", seed=2, duration_s=150.0), 150.0, seed=3, imu_hz=20.0))
    samples = [m for _, topic, m in recs if topic == "/imu"]
    for k in range(0, len(samples), 10):  # a read's die temperature, read once with its samples
        for m in samples[k:k + 10]:
            m["temp_degc"] = samples[min(k + 9, len(samples) - 1)]["temp_degc"]
    offered = _offered(recs, 10, 0.05)
    assert any(topic == "/obd/speed" and t < next(u for u, tp, _ in offered[i:] if tp == IMU_BATCH)
               for i, (t, topic, _) in enumerate(offered))
    in_order = [(t, IMU_BATCH if topic == "/imu" else topic,
                 _read([m], m["temp_degc"], period_s=0.05) if topic == "/imu" else m) for t, topic, m in recs]
    replayed, _, _ = _navigator(mode="17")
    _merged(replayed, in_order)
    # Wake-ups at two phases: at 0.77 s past the drive's first record a wake-up falls between a measurement and
    # the read that brings the samples before it, which then waits for the next wake-up (held at least once).
    for phase_ns in (0, 770_000_000):
        live, _, _ = _navigator(mode="17")
        held: list[int] = []
        order = live.in_time_order

        def watched(records, release=False, order=order, live=live, held=held):
            out = order(records, release)
            held.append(len(live._held))
            return out

        live.in_time_order = watched  # type: ignore[method-assign]
        _merged(live, offered, phase_ns=phase_ns)
        _same_trajectory(replayed.engine, live.engine)
        assert live.processed == len(offered)
        if phase_ns:
            assert max(held) > 0

    as_offered, _, _ = _navigator(mode="17")
    as_offered.in_time_order = lambda records, release=False: records  # type: ignore[method-assign]
    _merged(as_offered, offered)
    a = np.array([(r.lat_rad, r.lon_rad) for r in replayed.engine.rows]) * 6.4e6
    b = np.array([(r.lat_rad, r.lon_rad) for r in as_offered.engine.rows[:len(a)]]) * 6.4e6
    assert np.abs(a - b).max() > 0.5  # metres: what the wait prevents
