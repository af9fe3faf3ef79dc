"""An /imu/batch record (one FIFO read) is read back as the /imu records of its samples, each at its own time
among the other topics: what every reader of samples (replay, export, plot, info, the sync report) relies on."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from logger.recording.drive import iter_messages, open_drive, read_messages
from logger.recording.recorder import Recorder
from logger.recording.records import imu_batch_payload, stamped_batch, stamped_record
from logger.recording.settings import RecorderSettings
from logger.recording.topics import BARO, IMU, IMU_BATCH, TOPICS
from sync.stamp import LOCKED, Stamp, Stamps

T0 = 1_700_000_000_000_000_000
PERIOD = 1_000_000  # 1 kHz


def _stamps(mono: list[int]) -> Stamps:
    return Stamps.of([Stamp(T0 + t, LOCKED, 500, i, 0) for i, t in enumerate(mono)])


def _drive(tmp_path: Path) -> tuple[Path, list[int], list[int]]:
    """Three reads of 40 samples, and a barometer record logged in the middle of the second read's span."""
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.05), TOPICS)
    path = rec.start()
    rng = np.random.default_rng(3)
    seq, sample_times = 0, []
    baro_t = 60 * PERIOD + 400_000
    for read in range(3):
        mono = [(read * 40 + k) * PERIOD for k in range(40)]
        payload = imu_batch_payload(mono, rng.normal(0, 1, (40, 3)), rng.normal(0, 0.1, (40, 3)), 31.5, 1e-3,
                                    2 if read == 1 else 0)
        st = _stamps(mono)
        rec.submit(IMU_BATCH, stamped_batch(st, seq, payload), st.t_sync_ns[0], mono[0])
        seq += 40
        sample_times += st.t_sync_ns
        if read == 1:  # the barometer's record is written after the read that spans its time, as live
            baro = stamped_record(baro_t, Stamp(T0 + baro_t, LOCKED, 500, 0, 0), 0,
                                  {"pressure_pa": 1.0, "temp_degc": 1.0, "altitude_m": 1.0, "sea_level_pa": 1.0,
                                   "oversampling": 3, "ut": 1, "up": 1})
            rec.submit(BARO, baro, T0 + baro_t, baro_t)
    rec.stop()
    assert path is not None
    return path, sample_times, [T0 + baro_t]


def test_a_batch_is_read_as_its_samples_in_time_order_among_the_other_topics(tmp_path: Path) -> None:
    path, sample_times, (baro_time,) = _drive(tmp_path)
    got = list(iter_messages(open_drive([path]), [IMU, BARO]))
    imu = [m for m in got if m.topic == IMU]
    assert [m.msg["t_sync_ns"] for m in imu] == sample_times
    assert [m.msg["seq"] for m in imu] == list(range(120))
    assert [m.log_time for m in got] == sorted(m.log_time for m in got)  # the barometer sits among the samples
    order = [m.topic for m in got]
    assert order.index(BARO) == sum(1 for t in sample_times if t <= baro_time)
    # The lost count goes with the first sample of its read; every sample carries its read's temperature.
    assert [i for i, m in enumerate(imu) if m.msg["lost"]] == [40] and imu[40].msg["lost"] == 2
    assert True and all(m.msg["temp_degc"] == 31.5 and m.msg["fifo"] for m in imu)
    # The filter's reader gives the same samples in the same order.
    filt = [(t, m["t_sync_ns"]) for t, m in read_messages([path], [IMU, BARO])]
    assert filt == [(m.topic, m.msg["t_sync_ns"]) for m in got]


def test_a_reader_asking_for_the_batches_gets_them_as_recorded(tmp_path: Path) -> None:
    path, _, _ = _drive(tmp_path)
    got = list(iter_messages(open_drive([path]), [IMU_BATCH]))
    assert [m.topic for m in got] == [IMU_BATCH] * 3
    assert [len(m.msg["t_sync_ns"]) for m in got] == [40, 40, 40]
    assert [m.log_time for m in got] == [m.msg["t_sync_ns"][0] for m in got]
