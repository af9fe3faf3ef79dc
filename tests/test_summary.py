"""The end-of-run summary's judgement of the rates (a periodic sensor that fell behind in drive time is named), and
the exit of a run that recorded nothing."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

from helpers_drive import run_logger

from logger.runtime.sampler import SensorHealth
from logger.runtime.summary import shortfalls

NS = 1_000_000_000


def _sampler(name: str, rate_hz: float | None, samples: int, span_s: float, missed: int = 0,
             missed_host: int = 0) -> SimpleNamespace:
    h = SensorHealth(name, rate_hz, samples=samples, missed=missed, missed_host=missed_host)
    h.first_sample_mono_ns, h.last_sample_mono_ns = 5 * NS, 5 * NS + int(span_s * NS)
    return SimpleNamespace(rate_hz=rate_hz, health=h)


def test_a_sensor_that_fell_behind_in_drive_time_is_named_and_one_that_kept_up_is_not() -> None:
    daemon = SimpleNamespace(samplers=[
        _sampler("imu", 20.0, 35_501, 1800.0, missed=499, missed_host=450),  # a host that could not keep up
        _sampler("baro", 1.0, 8, 7.14),  # every second: stamps a little irregular over a short run are no shortfall
        _sampler("gnss", None, 1700, 1799.0),  # an event sensor: its rate is the receiver's, and outages are real
        _sampler("obd", 2.0, 0, 0.0),  # never delivered: said elsewhere
        _sampler("obd2", 2.0, 3500, 1799.0, missed=100),  # a slow adapter, not the host
    ])
    assert shortfalls(daemon) == [
        "imu let 499 of its 36000 periods pass unsampled (1.4%, 450 while the host ran late), 19.72 Hz of drive time "
        "against 20 Hz",
        "obd2 let 100 of its 3600 periods pass unsampled (2.8%), 1.94 Hz of drive time against 2 Hz"]
    # What a paced simulated drive's exit code goes by: only what the host caused.
    assert shortfalls(daemon, host_only=True) == [
        "imu let 450 of its 36000 periods pass unsampled (1.2%), 19.72 Hz of drive time against 20 Hz"]


def test_a_short_run_with_one_hiccup_held_its_rates() -> None:
    # Ten seconds at 20 Hz with three samples lost to one stall of the host: 1.5 %, but less than a second's worth.
    daemon = SimpleNamespace(samplers=[_sampler("imu", 20.0, 197, 9.95, missed=3, missed_host=3)])
    assert shortfalls(daemon) == [] and shortfalls(daemon, host_only=True) == []


def test_the_summary_names_records_deleted_with_their_file_apart_from_those_lost_in_writes() -> None:
    """On disk, then deleted under the recorder (a file or the folder removed while recording) is not "lost in a
    failed write": the run's summary names each, and only what happened."""
    from logger.runtime.summary import recorder_losses

    assert recorder_losses(0.0, {}, {}, {}) == []
    assert recorder_losses(0.0, {}, {}, {}, {"/imu/batch": 0}) == []
    lines = recorder_losses(0.0, {}, {"/imu/batch": 2}, {}, {"/imu/batch": 40, "/gnss/fix": 1})
    assert lines == ["2 records lost in failed writes (handed to the writer, never on disk)",
                     "41 records deleted with their file or folder while recording (on disk, then deleted: see the "
                     "log)"]


def test_a_fifo_imu_is_judged_by_the_samples_it_delivered_not_by_its_reads() -> None:
    """A 20 Hz IMU read through its FIFO twice a second, the host stopped 8 s (its FIFO holds about 4): the line said
    "47 of its 1349 periods" (3.5 %, reads set against samples) while 470 samples went, a quarter of them. A read
    missed while the FIFO holds its samples loses nothing, so what counts is the samples delivered over their span."""
    imu = _sampler("imu", 2.0, 1310, 90.0, missed=47, missed_host=47)
    imu.health.rate_hz, imu.health.samples_lost = 20.0, 491  # the samples' rate (the sampler's is its reads')
    kept_up = _sampler("imu", 2.0, 1783, 90.0, missed=16, missed_host=16)  # late reads, nothing lost; the chip's
    kept_up.health.rate_hz = 20.0  # clock 1 % slow: 1783 samples in 90 s is no shortfall
    daemon = SimpleNamespace(samplers=[imu, kept_up])
    assert shortfalls(daemon) == [
        "imu let 491 of its 1801 samples pass unsampled (27.3%, 470 while the host ran late), 14.54 Hz of drive time "
        "against 20 Hz"]
    assert shortfalls(daemon, host_only=True) == [
        "imu let 470 of its 1801 samples pass unsampled (26.1%), 14.54 Hz of drive time against 20 Hz"]


def test_a_run_stopped_as_it_starts_is_no_failure(tmp_path: Path) -> None:
    """systemd's stop (SIGTERM) right after "recording to": nothing had arrived to record, and the run exited 4,
    "nothing of this run is on disk (the log says why)", on a disk with 68 GB free. Nothing was lost: exit 0, and
    a line saying that the stop came before the first record (or, stopped a moment later, the records on disk)."""
    import signal

    p = subprocess.Popen([sys.executable, "-m", "logger.cli", "run", "--sim", "--out", str(tmp_path / "drive"),
                          "--status-socket", str(tmp_path / "s.sock")], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True, cwd=Path(__file__).resolve().parents[1])
    assert p.stdout is not None
    seen = []
    for line in p.stdout:
        seen.append(line)
        if "recording to" in line:
            p.send_signal(signal.SIGTERM)
            break
    rest, _ = p.communicate(timeout=120)
    text = "".join(seen) + rest
    assert p.returncode == 0, text
    assert "nothing of this run is on disk" not in text


def test_a_run_of_which_nothing_is_on_disk_exits_4_and_says_so(tmp_path: Path) -> None:
    """A run that recorded nothing (here a disk with less free than `[recorder] min_free_mb` asks, 1 TiB, from the
    start to the end) exited 0 after a summary saying "recorded 0.0 s ... into 0 files": a script, or systemd after
    the stop, took it for a drive."""
    assert shutil.disk_usage(tmp_path).free < (1 << 40), "this test needs a disk with under 1 TiB free"
    cfg = tmp_path / "logger.toml"
    cfg.write_text(f'[logger]\nstate_dir = "{tmp_path / "state"}"\n[recorder]\nmin_free_mb = {1 << 20}\n')
    r = run_logger("--sim", "--duration", "2", "--out", str(tmp_path / "drive"), "--status-socket",
                   str(tmp_path / "s.sock"), "--config", str(cfg))
    assert r.returncode == 4, r.stdout + r.stderr
    assert r.stdout.startswith("logger: recorded 0.0 s of a ") and " into 0 files" in r.stdout, r.stdout
    assert r.stderr.endswith("logger: nothing of this run is on disk (see above: the recorder's state and the log "
                             "say why)\n"), r.stderr
    # The same run with the default minimum free space records (exit 0, or 3 on a host too busy to hold the rates).
    cfg.write_text(f'[logger]\nstate_dir = "{tmp_path / "state"}"\n')
    r = run_logger("--sim", "--duration", "2", "--out", str(tmp_path / "drive"), "--status-socket",
                   str(tmp_path / "s.sock"), "--config", str(cfg))
    assert r.returncode in (0, 3) and " into 1 file" in r.stdout, r.stdout + r.stderr


def test_the_summary_fits_a_terminal_and_keeps_commands_and_paths_whole() -> None:
    """On a phone's 80 columns the clock and nav lines (108-118 columns) and a recorder's loss (about 160) ran past
    the edge; on a terminal they wrap under their own indent. Commands and paths are copied whole: never cut."""
    from logger.runtime.summary import fitted

    clock = ("  clock locked at the end, error bound 14.2 us, 20 PPS edges, 0 relocks (locked 84%, freerun 16% of the "
             "run)")
    loss = ("  ! not recording for 36 s of the run (disk full, write errors or the storage not mounted: see the log); "
            "1695 records came meanwhile and were not recorded")
    plot = "  logger plot /var/lib/vehicle-logger/drives/drive_20261207T093650Z_0001.mcap --out plots/"
    path = "  /var/lib/vehicle-logger/drives/drive_20261207T093650Z_0001.mcap  12.3 MB  (not finished: recover it)"
    text = "\n".join(["logger: recorded 80.0 s of drive into 1 file, 0.4 MB", clock, loss, "next:", plot, path])
    out = fitted(text, 80).split("\n")
    assert all(len(line) <= 80 for line in out if line not in (plot, path)) and plot in out and path in out
    assert " ".join(line.strip() for line in out[1:3]) == clock.strip()  # the words all there, in order
    assert out[1].startswith("  clock ") and out[2].startswith("    ") and out[3].startswith("  ! not recording")
    assert all(line.startswith("      ") for line in out[4:out.index("next:")])  # the loss's own indent
    assert fitted(text, 200) == text
