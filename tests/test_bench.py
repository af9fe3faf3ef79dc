"""The benchmark tools' measuring parts: per-thread CPU, the simulator's share, the file analysis (no timings)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ROOT / "tools"
sys.path.insert(0, str(TOOLS))

import bench_board  # noqa: E402
import bench_daemon  # noqa: E402
import bench_recorder  # noqa: E402


def burn(cpu_s: float) -> None:
    """Spend this much of the calling thread's CPU time, however long the loaded machine makes it take."""
    end = time.thread_time() + cpu_s
    while time.thread_time() < end:
        pass


def test_bench_help_names_every_benchmark() -> None:
    out = subprocess.run([sys.executable, str(ROOT / "tools" / "bench.py"), "--help"], capture_output=True,
                         text=True, check=True).stdout
    for name in ("daemon", "recorder", "nav", "sync", "startup", "--quick", "--only"):
        assert name in out


def test_bench_refuses_an_unknown_benchmark() -> None:
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "bench.py"), "--only", "disk"], capture_output=True,
                          text=True)
    assert proc.returncode == 2
    assert "unknown benchmark disk" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_task_cpu_follows_a_busy_thread_by_name() -> None:
    ready = threading.Event()
    read = threading.Event()
    tid: list[int] = []

    def work() -> None:
        tid.append(threading.get_native_id())
        burn(0.3)
        ready.set()
        read.wait(60)  # stay alive (and listed in /proc) until the test has read it, however late that is

    t = threading.Thread(target=work, name="sampler-test")
    t.start()
    try:
        assert ready.wait(30)
        cpu = bench_daemon.task_cpu_s()
        names = bench_daemon.thread_names(cpu)
    finally:
        read.set()
        t.join()
    assert names[tid[0]] == "sampler-test"
    assert cpu[tid[0]] >= 0.25  # clock ticks of 10 ms: 0.3 s of CPU reads as at least 0.29


def test_task_wakes_count_a_threads_sleeps() -> None:
    """Each sleep a thread ends is a voluntary context switch: twenty sleeps read as at least twenty wakes."""
    started, go, done, read = (threading.Event() for _ in range(4))
    tid: list[int] = []

    def work() -> None:
        tid.append(threading.get_native_id())
        started.set()
        go.wait(60)
        for _ in range(20):
            time.sleep(0.001)
        done.set()
        read.wait(60)  # stay alive (and listed in /proc) until the test has read it

    t = threading.Thread(target=work, name="sampler-test")
    t.start()
    try:
        assert started.wait(30)
        before = bench_daemon.task_wakes()[tid[0]]
        go.set()
        assert done.wait(30)
        after = bench_daemon.task_wakes()[tid[0]]
    finally:
        go.set()
        read.set()
        t.join()
    assert after - before >= 20


def test_sim_meter_counts_nested_calls_once_and_by_thread() -> None:
    class Chip:
        def inner(self) -> None:
            burn(0.05)

        def outer(self) -> None:
            burn(0.05)
            self.inner()

    meter = bench_daemon.SimMeter()
    meter.wrap(Chip, "inner")
    meter.wrap(Chip, "outer")
    spent: list[float] = []

    def work() -> None:
        t0 = time.thread_time()
        Chip().outer()
        burn(0.05)  # outside the simulation: not metered
        spent.append(time.thread_time() - t0)

    t = threading.Thread(target=work, name="sampler-imu")
    t.start()
    t.join()
    inside = meter.snapshot()["sampler-imu"]
    assert 0.1 <= inside < spent[0] - 0.04  # outer and inner once each, the last 0.05 s left out


@pytest.mark.parametrize(("name", "kind"), [("sampler-imu", "daemon"), ("recorder", "daemon"), ("navigator", "daemon"),
                                            ("MainThread", "daemon"), ("sim-elm327", "sim"), ("ublox-model", "sim"),
                                            ("sim-irq-gpiochip1", "sim"), ("bench-monitor", "bench"),
                                            ("native:zstd", "other")])
def test_threads_are_classed_by_name(name: str, kind: str) -> None:
    assert bench_daemon.thread_class(name) == kind


def test_file_analysis_finds_lost_records_and_irregular_stamps(tmp_path: Path) -> None:
    from mcap.writer import Writer

    period = 1_000_000  # 1 kHz
    stamps = [0, 1, 2, 3, 2, 3, 7, 10, 11]  # in periods: one stamp back (3 -> 2), one gap of 4 (3 -> 7)
    seqs = [0, 1, 2, 3, 4, 5, 6, 9, 10]  # records 7 and 8 lost
    lost = [0, 0, 0, 0, 0, 0, 3, 0, 0]  # a FIFO overflow of 3 before record 6
    path = tmp_path / "drive.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("imu", "jsonschema", b"{}")
        cid = w.register_channel("/imu", "json", sid)
        for k, (t, s, n) in enumerate(zip(stamps, seqs, lost, strict=True)):
            msg = {"t_mono_ns": 10**9 + t * period, "seq": s, "lost": n}
            w.add_message(cid, k, json.dumps(msg).encode(), k)
        w.finish()
    got = bench_daemon.analyse_file([path], 1000.0, 10**9, 10**9 + 11 * period)
    assert got["imu_records"] == 9
    assert got["seq_missing"] == 2
    assert got["fifo_lost"] == 3
    assert got["stamp_backwards"] == 1
    assert got["stamp_gaps"] == 1  # the jump over the lost records (7 -> 10) is no stamp step
    assert got["stamp_step_error_max_ms"] == pytest.approx(3.0)  # 4 periods where 1 was due


def test_board_verdict_against_the_budget() -> None:
    low, high = bench_board.board_range(1.0)
    assert (low, high) == (bench_board.FACTOR_LOW, bench_board.FACTOR_HIGH)
    assert "within" in bench_board.verdict(5.0, 20.0) and "over" not in bench_board.verdict(5.0, 20.0)
    assert "over it at the slow end" in bench_board.verdict(20.0, 40.0)
    assert "across the whole range" in bench_board.verdict(30.0, 60.0)


def test_compiled_tree_starts_from_bytecode_without_writing_it(tmp_path: Path) -> None:
    """tools/bytecode.py: after compile_tree, a child run with PYTHONDONTWRITEBYTECODE (as a timed replay may be)
    imports the packages' modules from their bytecode, compiling none of them from source; before it, it does."""
    import bytecode

    names = bytecode.packages()
    for name in names:
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text("VALUE = 1\n")
        (tmp_path / name / "part.py").write_text("def f() -> int:\n    return 2\n")
    probe = ("import builtins, sys\n"
             "seen = []\n"
             "real = builtins.compile\n"
             "builtins.compile = lambda src, fn, *a, **k: (seen.append(fn), real(src, fn, *a, **k))[1]\n"
             f"import {', '.join(f'{n}.part' for n in names)}\n"
             "print(len([f for f in seen if f.endswith('.py')]))\n")
    # The writer and the reader in the same environment (a bytecode prefix or -O there would move the files).
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "PYTHONPATH": os.pathsep.join((str(tmp_path), str(TOOLS)))}

    def python(code: str) -> str:
        return subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True,
                              check=True).stdout

    def compiled_from_source() -> int:
        return int(python(probe))

    assert compiled_from_source() == 2 * len(names)
    python(f"import bytecode, pathlib; bytecode.compile_tree(pathlib.Path({str(tmp_path)!r}), {names!r})")
    assert compiled_from_source() == 0
    # Changed since (its size too: within the second the bytecode was written, size is what tells it stale).
    (tmp_path / "logger" / "part.py").write_text("def f() -> int:\n    return 3\n\n\n")
    assert compiled_from_source() == 1


def test_the_packages_compiled_are_the_ones_pyproject_installs() -> None:
    import bytecode

    assert bytecode.packages() == ("logger", "sensors", "sync")


def test_compile_tree_stops_on_a_module_that_does_not_compile(tmp_path: Path) -> None:
    import bytecode

    names = bytecode.packages()
    for name in names:
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text("VALUE = 1\n")
    (tmp_path / "logger" / "broken.py").write_text("def f(:\n")
    with pytest.raises(SystemExit, match="bytecode not written for logger"):
        bytecode.compile_tree(tmp_path, names)
    assert (tmp_path / "sync" / "__pycache__").is_dir()  # the other packages were compiled all the same


def test_startup_worker_sees_every_sensor_topic_whichever_way_the_imu_is_read(tmp_path: Path) -> None:
    """The start-up benchmark's worker ends when every sensor's first record is written; the IMU's first record is
    a FIFO read (/imu/batch) by default, counted as its first samples (a worker waiting for /imu would sit out its
    90 s limit and report no IMU time)."""
    out = tmp_path / "result.json"
    r = subprocess.run([sys.executable, str(TOOLS / "bench_startup.py"), "--worker", str(time.monotonic_ns()),
                        "--out", str(tmp_path / "drive"), "--json", str(out)],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    result = json.loads(out.read_text())
    assert set(result["first_s"]) == {"/imu", "/baro", "/obd/speed", "/gnss/fix", "/pps"}, result["first_s"]
    assert result["cpu_at_first_imu_s"] is not None and result["ready_s"] is not None


def test_the_daemon_benchmark_runs_with_the_units_environment(tmp_path: Path) -> None:
    """The unit's Environment= lines are what the benchmark applies (glibc reads MALLOC_ARENA_MAX at start): a
    child started by its main block has them, whatever the parent's environment said."""
    env = bench_daemon.unit_environment()
    assert env.get("MALLOC_ARENA_MAX") == "2"
    unit = tmp_path / "x.service"
    unit.write_text('[Service]\nEnvironment=A=1 "B=two"\n# Environment=C=3\nEnvironment=D=4\n', encoding="utf-8")
    assert bench_daemon.unit_environment(unit) == {"A": "1", "B": "two", "D": "4"}
    probe = ("import os, runpy, sys; sys.argv = ['bench_daemon.py', '--help']; "
             "print(os.environ.get('MALLOC_ARENA_MAX'), flush=True); "
             f"runpy.run_path({str(TOOLS / 'bench_daemon.py')!r}, run_name='__main__')")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         env={k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}).stdout
    # The first line is the parent's (unset); the re-executed benchmark prints its help with the unit's value set.
    assert out.splitlines()[0] == "None" and "usage: bench_daemon.py" in out


def test_the_simulators_modules_are_measured_apart_from_the_daemons() -> None:
    """What the simulator's modules add on top of every other module is positive, and nothing without them."""
    import logger.compose  # noqa: F401
    import sensors.sim.vehicle  # noqa: F401

    loaded = list(sys.modules)
    assert bench_daemon.sim_modules_rss_mb(loaded)[1] > 0.5
    assert bench_daemon.sim_modules_rss_mb([n for n in loaded if not n.startswith("sensors.sim")]) == (0.0, 0.0)
    r = {"rss_end_mb": 50.0, "sim_build_rss_mb": 7.5, "sim_modules_rss_mb": 2.5}
    assert bench_daemon.daemon_alone_mb(r) == 40.0
    del r["sim_modules_rss_mb"]  # figures saved before the modules were measured: no estimate, not a wrong one
    assert bench_daemon.daemon_alone_mb(r) is None


def test_libraries_only_the_simulator_loads_while_building_are_the_simulators() -> None:
    """numpy.random is loaded by the simulator's drive and never by the daemon's code: with numpy 2 it is the
    simulator's memory; with Debian 12's numpy 1.24.2 ``import numpy`` loads it anyway (the daemon's, the board's).
    A library the daemon's code imports (smbus2) stays the daemon's whoever loaded it first."""
    import numpy as np
    import numpy.random
    import smbus2  # noqa: F401

    import logger.compose  # noqa: F401
    import sensors.sim.vehicle  # noqa: F401

    named = bench_daemon.daemon_named_modules()
    assert {"numpy", "smbus2", "mcap.stream_reader"} <= named and "pty" not in named and "numpy.random" not in named
    loaded = list(sys.modules)
    drive_libraries = [n for n in loaded if n == "numpy.random" or n.startswith("numpy.random.")]
    built_mb, sim_mb = bench_daemon.sim_modules_rss_mb(loaded, [*drive_libraries, "smbus2"])
    if int(np.__version__.split(".")[0]) >= 2:
        assert 1.0 < built_mb < sim_mb
    else:
        assert built_mb < 0.5
    assert bench_daemon.sim_modules_rss_mb(loaded, ["smbus2"])[0] == 0.0


def _chunked_file(path: Path, channels: int, chunks: int) -> Path:
    """An MCAP file of ``chunks`` chunks a second apart, each with a message on every one of ``channels``."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start("bench", "test")
        schema = w.register_schema("s", "jsonschema", b"{}")
        ids = [w.register_channel(f"/t{i}", "json", schema) for i in range(channels)]
        for k in range(chunks):
            for c in ids:
                w.add_message(c, log_time=k * 1_000_000_000 + c, data=b"{}", publish_time=k * 1_000_000_000)
            w.flush()
        w.finish()
    return path


def test_the_writers_index_at_rotation_follows_chunks_and_channels(tmp_path: Path) -> None:
    """What the MCAP writer keeps per chunk until the file rotates: read from the file's chunks, measured per index,
    and scaled to an hour's file; more channels a chunk, more memory a chunk."""
    few = bench_daemon.writer_index([_chunked_file(tmp_path / "few.mcap", 3, 11)])
    many = bench_daemon.writer_index([_chunked_file(tmp_path / "many.mcap", 12, 11)])
    assert few["channels_per_chunk"] == 3.0 and many["channels_per_chunk"] == 12.0
    assert few["chunks_per_s"] == 1.0 and few["held_s"] == 10  # 11 chunks, a second apart
    assert 0 < few["bytes_per_chunk"] < many["bytes_per_chunk"] < 3000
    assert few["at_rotation_mb"] < many["at_rotation_mb"]
    assert few["beyond_window_mb"] == pytest.approx(few["at_rotation_mb"] * (3600 - 10) / 3600, abs=0.1)
    (tmp_path / "cut.mcap").write_bytes((tmp_path / "few.mcap").read_bytes()[:200])  # no summary: no figure
    assert bench_daemon.writer_index([tmp_path / "cut.mcap"]) == {}


def test_the_board_interpreter_is_checked_before_measuring(tmp_path: Path) -> None:
    """--board-python runs the daemon benchmark again: refused without it, or with an interpreter that is not one
    or cannot import the daemon's modules, before any measuring starts."""
    import argparse

    import bench

    ap = argparse.ArgumentParser(prog="bench.py")
    with pytest.raises(SystemExit):
        bench.board_interpreter(sys.executable, ["recorder"], ap)
    with pytest.raises(SystemExit):
        bench.board_interpreter(str(tmp_path / "no-python"), ["daemon"], ap)
    assert bench.board_interpreter(sys.executable, ["daemon"], ap) == os.path.abspath(sys.executable)


def test_the_recorder_benchmark_streams_the_imu_topic_the_drive_has() -> None:
    """A FIFO drive (the default at every rate) records /imu/batch, a polled one /imu: the IMU-only stream is made of
    whichever the drive holds, not of a topic it lacks (the benchmark stopped with "no records on /imu")."""
    fifo = [("/imu/batch", {"t_sync_ns": [1, 2]}, 1, 1), ("/baro", {}, 2, 2)]
    polled = [("/imu", {"t_sync_ns": 1}, 1, 1), ("/baro", {}, 2, 2)]
    assert bench_recorder.imu_topic(fifo) == "/imu/batch" and bench_recorder.imu_topic(polled) == "/imu"
    stream = bench_recorder.load_stream(fifo, 5, bench_recorder.imu_topic(fifo))
    assert [t for t, *_ in stream] == ["/imu/batch"] * 5 and stream[1][2] > stream[0][2]


def test_sections_from_different_hosts_are_flagged() -> None:
    """A report whose sections ran on two hosts (a moved virtual machine keeps its CPU's name) says so in its
    summary, from the kernels and the fixed work's time beside each step; one host says nothing."""
    import bench

    one = {"daemon": {"loads": [{"kernel": "k1", "reference_ms": 20.0}]},
           "nav": {"loads": [{"kernel": "k1", "reference_ms": 21.0}]}}
    assert bench.hosts_line(one) == ""
    two = {"daemon": {"loads": [{"kernel": "k1", "reference_ms": 20.0}]},
           "nav": {"loads": [{"kernel": "k2", "reference_ms": 31.0}]}}
    line = bench.hosts_line(two)
    assert "kernels k1, k2" in line and "20.0 to 31.0 ms" in line
    assert bench.host_reference(two["nav"]["loads"][0]) == "31.0 ms (k2)" and bench.host_reference({}) == "-"
    assert 0.0 < bench.reference_ms(repeat=1) < 10_000.0


def test_a_report_says_the_units_environment_only_where_every_run_had_it() -> None:
    """A run records the unit's variables as it had them, empty when unset (bench_daemon.main called without the
    re-executing main block): only runs with the unit's own values are reported as having its environment."""
    unit = bench_daemon.unit_environment()
    assert unit  # the unit sets some (MALLOC_ARENA_MAX)
    unset = {k: "" for k in unit}
    assert bench_daemon.had_unit_environment([{"environment": unit}, {"environment": dict(unit)}])
    assert not bench_daemon.had_unit_environment([{"environment": unit}, {"environment": unset}])
    assert not bench_daemon.had_unit_environment([{}])


def test_the_navigator_benchmark_compares_two_checkouts_side_by_side() -> None:
    """``tools/bench_navigator.py`` runs each checkout in its own process (here this one twice, a short drive at
    100 Hz) and prints each one's share and their ratio; the filter starts and publishes in the drive."""
    out = subprocess.run([sys.executable, str(TOOLS / "bench_navigator.py"), "--imu-rate", "100", "--seconds", "40",
                          "--repeat", "1", "--against", str(ROOT)], capture_output=True, text=True, check=True).stdout
    lines = out.strip().splitlines()
    assert len(lines) == 3 and all("filter started: True" in line for line in lines[:2])
    assert all(int(line.split("(")[1].split()[0]) > 50 for line in lines[:2])  # records published
    assert lines[2].startswith("ratio this / other: ")


def test_resident_set_natively_is_vmrss() -> None:
    import resident

    if resident.emulated():  # tools/board-check.sh's suite under qemu-user: the guest's window, not VmRSS (next test)
        assert resident.source() != "VmRSS" and resident.rss_kb() > 0
        return
    status = Path("/proc/self/status").read_text()
    vm = int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmRSS:")))
    assert abs(resident.rss_kb() - vm) < 4096 and resident.peak_kb() >= resident.rss_kb() // 2
    assert resident.source() == "VmRSS"


def test_resident_set_under_qemu_is_the_guests_window(tmp_path: Path) -> None:
    """qemu-user's /proc/self/maps (the guest's view, guest addresses) and /proc/self/smaps (qemu's process), as
    Debian 12's qemu-arm 7.2 gives them for an armhf python (shapes from the emulated board root): the guest's
    first file mapping in both gives the window's base, 0x1000 here, and only the mappings inside the 4 GB window
    count; qemu's own heap and code cache above it do not."""
    import resident

    (tmp_path / "maps").write_text(
        "00010000-003d4000 r-xp 00000000 fe:00 1541649    /usr/bin/python3.11\n"
        "003d5000-0049c000 rw-p 003c4000 fe:00 1541649    /usr/bin/python3.11\n"
        "3fc70000-3fdb4000 rw-p 00000000 00:00 0\n")
    smaps = []
    for span, perms, offset, path, rss in (
            ("00001000-00011000", "---p", "00000000", "", 0),
            ("00011000-003d5000", "r--p", "00000000", "/usr/bin/python3.11", 2400),
            ("003d6000-0049d000", "rw-p", "003c4000", "/usr/bin/python3.11", 300),
            ("3fc71000-3fdb5000", "rw-p", "00000000", "", 1200),
            ("100001000-100100000", "rw-p", "00000000", "", 50),  # base + 4 GB: past the window
            ("5555a0000000-5555a0400000", "r-xp", "00000000", "/usr/libexec/qemu-binfmt/arm-binfmt-P", 3000),
            ("7f0000000000-7f0040000000", "rwxp", "00000000", "", 20000)):
        smaps.append(f"{span} {perms} {offset} fe:00 1    {path}\nSize:  4 kB\nRss:   {rss} kB\nPss:   {rss} kB\n")
    (tmp_path / "smaps").write_text("".join(smaps))
    host = resident.host_mappings(str(tmp_path / "smaps"))
    assert resident.guest_base(host, str(tmp_path / "maps")) == 0x1000
    assert resident.guest_rss_kb(str(tmp_path / "smaps"), str(tmp_path / "maps")) == 2400 + 300 + 1200
