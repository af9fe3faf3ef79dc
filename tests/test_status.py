"""The status socket: group-only permissions, one snapshot per connection, exit codes for scripts."""

from __future__ import annotations

import os
import socket
import stat
from pathlib import Path

import pytest

from logger.cli import main
from logger.cli import status as status_cli
from logger.runtime.status_socket import SocketInUse, StatusServer, fetch, free_sim_socket

SNAP = {
    "verdict": "degraded", "uptime_s": 3723, "pid": 42, "t_mono_ns": 50_000_000_000,
    "problems": ["obd: NO DATA (engine off?)"],
    "sensors": [{"name": "imu", "state": "ok", "rate_hz": 20, "measured_rate_hz": 20.0, "last_sample_age_s": 0.02,
                 "errors": 0, "gaps": 0, "late": 0, "reconnects": 0, "last_error": ""},
                {"name": "obd", "state": "retrying", "rate_hz": 2, "measured_rate_hz": 0.0, "last_sample_age_s": 12.5,
                 "errors": 7, "gaps": 1, "late": 0, "reconnects": 0, "last_error": "NO DATA (engine off?)"}],
    "sync": {"state": "locked", "err_ns": 15000, "offset_ns": 1200, "freq_ppm": 31.2, "since_edge_s": 0.4},
    "recorder": {"state": "recording", "file": "/data/drive_1.mcap", "file_bytes": 1_200_000,
                 "free_bytes": 3_000_000_000, "written": {"/imu": 100}, "dropped": {}, "queue_depth": 0,
                 "queue_size": 20000, "on_disk_mono_ns": {"/imu": 49_400_000_000, "/baro": 49_000_000_000}},
}


def test_status_round_trip_and_exit_codes(tmp_path: Path, capsys) -> None:
    sock = tmp_path / "run" / "status.sock"
    server = StatusServer(sock, lambda: SNAP)
    server.start()
    try:
        mode = stat.S_IMODE(sock.stat().st_mode)
        assert mode == 0o660
        assert fetch(sock)["sensors"][1]["last_error"] == "NO DATA (engine off?)"
        assert main(["status", "--socket", str(sock)]) == 1
        out = capsys.readouterr().out
        assert "DEGRADED" in out and "up 1h02m03s" in out and "obd: NO DATA" in out
        assert "obd     retrying" in out and "locked" in out and "+31.20 ppm" in out
        assert "on disk up to 0.6 s ago" in out  # what a power cut now would lose, from the newest record on disk
        assert main(["status", "--json", "--socket", str(sock)]) == 1
    finally:
        server.close()
    assert main(["status", "--socket", str(sock)]) == 3
    assert "not running" in capsys.readouterr().err


def test_a_socket_another_logger_answers_on_is_not_taken_over(tmp_path: Path) -> None:
    sock = tmp_path / "status.sock"
    first = StatusServer(sock, lambda: SNAP)
    first.start()
    try:
        with pytest.raises(SocketInUse) as err:
            StatusServer(sock, lambda: {**SNAP, "pid": 43})
        assert err.value.pid == 42 and "in use by another logger (pid 42)" in str(err.value)
        assert fetch(sock)["pid"] == 42  # the first one still answers
    finally:
        first.close()
    stale = tmp_path / "stale.sock"  # a socket a crashed daemon left: nobody answers, so it is replaced
    left = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    left.bind(str(stale))
    left.close()
    again = StatusServer(stale, lambda: SNAP)
    again.start()
    try:
        assert fetch(stale)["pid"] == 42
    finally:
        again.close()


def test_a_second_simulated_run_gets_its_own_socket_and_status_finds_it(tmp_path: Path, monkeypatch,
                                                                        capsys) -> None:
    default = tmp_path / "sim" / "status.sock"
    assert free_sim_socket(default) == default  # nobody there
    monkeypatch.setattr(status_cli, "DEFAULT_SIM_SOCKET", str(default))
    monkeypatch.setattr(status_cli, "DEFAULT_PATH", tmp_path / "no-config.toml")
    monkeypatch.delenv("LOGGER_STATUS_SOCKET", raising=False)
    with pytest.raises(ConnectionError, match=r"nobody answers on\n  .*status\.sock"):
        status_cli.find_socket()
    assert main(["status"]) == 3
    err = capsys.readouterr().err
    assert err.startswith("logger status: logger is not running; nobody answers on\n  ") and f"\n  {default}\n" in err
    assert all(len(line) <= 80 for line in err.splitlines() if not line.startswith("  /")), err
    first = StatusServer(default, lambda: SNAP)
    first.start()
    try:
        own = free_sim_socket(default)
        assert own != default and own.parent == default.parent and str(os.getpid()) in own.name
        first.close()
        second = StatusServer(own, lambda: {**SNAP, "pid": 77})
        second.start()  # the first run has ended: the second one's own socket is found
        try:
            assert status_cli.find_socket()[0] == own
            assert main(["status", "--json"]) == 1 and '"pid": 77' in capsys.readouterr().out
        finally:
            second.close()
    finally:
        first.close()


def test_a_full_queue_is_waited_out_then_said_busy_not_not_running(tmp_path: Path, capsys) -> None:
    """A socket whose queue is full (a daemon that stopped accepting, or clients hammering it): logger status
    tries again until its deadline, then says the logger is busy with exit 4, never a traceback, never 3."""
    import time

    from logger.runtime.status_socket import StatusBusy

    sock = tmp_path / "status.sock"
    stuck = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stuck.bind(str(sock))
    stuck.listen(0)  # accepts nothing: the kernel queue fills at once
    held = []
    try:
        for _ in range(8):  # fill the queue (the kernel admits backlog + 1)
            c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            c.setblocking(False)
            try:
                c.connect(str(sock))
            except BlockingIOError:
                c.close()
                break
            held.append(c)
        t0 = time.monotonic()
        with pytest.raises(StatusBusy, match="busy"):
            fetch(sock, timeout_s=0.6)
        assert time.monotonic() - t0 >= 0.5  # it waited for the queue, not gave up at once
        assert main(["status", "--socket", str(sock)]) == 4
        err = capsys.readouterr().err
        assert "logger is running but busy" in err and "Traceback" not in err
    finally:
        for c in held:
            c.close()
        stuck.close()


def test_clients_polling_hard_cost_at_most_a_few_snapshots_a_second(tmp_path: Path) -> None:
    """Four clients fetching as fast as they can for a second: every one gets answers, and the daemon computed at
    most a handful of snapshots (one per CACHE_S), whatever the number of requests."""
    import threading
    import time

    from logger.runtime.status_socket import CACHE_S

    sock = tmp_path / "status.sock"
    server = StatusServer(sock, lambda: SNAP)
    server.start()
    got = [0, 0, 0, 0]
    stop = time.monotonic() + 1.0

    def poll(i: int) -> None:
        while time.monotonic() < stop:
            assert fetch(sock)["pid"] == 42
            got[i] += 1

    threads = [threading.Thread(target=poll, args=(i,)) for i in range(4)]
    t0 = time.monotonic()
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
    finally:
        server.close()
    elapsed = time.monotonic() - t0
    assert all(got) and server.answered == sum(got)
    assert server.snapshots <= elapsed / CACHE_S + 2, (server.snapshots, sum(got), elapsed)
    assert server.answered <= (elapsed + 0.5) * 50 + 4  # the answers are paced: the rest wait in the queue


def _as_nobody(argv: list[str], default_socket: Path | None = None, default_config: Path | None = None
               ) -> tuple[int, str]:
    """``logger status`` in a forked child that dropped root for the unprivileged user: its exit code and stderr."""
    import sys

    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: no exec (the interpreter may live where that user may not run it)
        code = 99
        try:
            os.dup2(write, 2)
            sys.stderr = os.fdopen(2, "w", closefd=False)
            os.setgroups([])
            os.setgid(65534)
            os.setuid(65534)
            if default_socket is not None:
                from types import SimpleNamespace

                status_cli.SCHEMA = {"logger": {"status_socket": SimpleNamespace(default=str(default_socket))}}
            if default_config is not None:
                status_cli.DEFAULT_PATH = default_config
            code = main(argv)
        except BaseException:  # what escaped main: the test shows it
            import traceback

            traceback.print_exc()
        finally:
            sys.stderr.flush()
            os._exit(code)
    os.close(write)
    with os.fdopen(read) as f:
        err = f.read()
    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]), err


def test_a_user_outside_the_loggers_group_is_told_so_not_that_it_is_not_running(tmp_path: Path) -> None:
    """On a board /run/vehicle-logger is the logger group's (0750): another user's `logger status` printed a traceback
    (the default socket's folder may not be looked into) or said "not running" (exit 3) of a running daemon. Now one
    line, and exit 4: nobody can say how it is. Run as an unprivileged user (root reads any folder)."""
    if os.geteuid() != 0:
        pytest.skip("needs root to ask as another user")
    run_dir = tmp_path / "run"
    sock = run_dir / "status.sock"
    server = StatusServer(sock, lambda: SNAP)
    server.start()
    tmp_path.chmod(0o755)
    run_dir.chmod(0o750)  # root's group: not the unprivileged user's
    try:
        for argv, default, config in ((["status", "--socket", str(sock)], None, None),
                                      (["status"], sock, Path("/nonexistent.toml")),
                                      (["status"], sock, tmp_path / "none.toml")):  # a config not to be looked at
            code, err = _as_nobody(argv, default, config)
            assert code == 4 and "Traceback" not in err, (argv, err)
            assert err.startswith("logger status: not allowed to read ") and "logger's group" in err, err
    finally:
        server.close()


def test_a_member_added_since_this_login_is_told_to_log_in_again(tmp_path: Path, monkeypatch) -> None:
    """install-board.sh --operator adds the operator to the group, but their open SSH session keeps the groups it
    started with: "add yourself to the logger's group" was wrong advice there."""
    import grp
    import pwd
    from types import SimpleNamespace

    import logger.runtime.status_socket as status_socket

    sock = tmp_path / "status.sock"
    sock.write_text("")
    gid = sock.stat().st_gid
    me = pwd.getpwuid(os.getuid()).pw_name
    real = grp.getgrgid(gid)
    monkeypatch.setattr(status_socket.grp, "getgrgid", lambda g: SimpleNamespace(gr_name="vehicle-logger",
                                                                                  gr_mem=[me], gr_gid=real.gr_gid))
    monkeypatch.setattr(status_socket.os, "getgroups", lambda: [g for g in (gid + 1, gid + 2)])
    assert str(status_socket.denied(sock)) == (f"not allowed to read {sock}:\n  you were added to the group "
                                               "vehicle-logger after this login: log in again (or run `newgrp "
                                               "vehicle-logger`)")
    monkeypatch.setattr(status_socket.os, "getgroups", lambda: [gid])  # a member in this session: not that
    told = str(status_socket.denied(sock))
    assert "\n  sudo usermod -a -G vehicle-logger $USER" in told and max(map(len, told.split("\n")[1:])) < 80, told


def test_status_reads_the_socket_from_a_simulated_runs_configuration_and_says_what_is_wrong_with_one(
        tmp_path: Path, capsys) -> None:
    """`logger status --config FILE` loaded FILE as a hardware configuration: a simulated run's file (no device
    ports) failed, was passed over silently, and the default sockets said "not running" of a running logger; a
    mistyped path was passed over the same way."""
    sock = tmp_path / "sim.sock"
    cfg = tmp_path / "sim.toml"
    cfg.write_text(f'[logger]\nstatus_socket = "{sock}"\n[sim]\nseed = 2\n')
    server = StatusServer(sock, lambda: SNAP)
    server.start()
    try:
        assert main(["status", "--config", str(cfg)]) == 1  # SNAP's verdict: degraded
        assert "DEGRADED" in capsys.readouterr().out
    finally:
        server.close()
    assert main(["status", "--config", str(tmp_path / "typo.toml")]) == 4
    assert capsys.readouterr().err == f"logger status: {tmp_path / 'typo.toml'}: no such configuration file\n"


def test_a_sensor_open_with_nothing_from_it_yet_is_starting_not_ok_at_zero_hz() -> None:
    """In the first second after an open, a sensor that has sent nothing yet showed "ok" at 0.0 Hz beside the
    navigator waiting for it: it is "starting" (no rate) until its first sample, and "silent" once overdue."""
    from types import SimpleNamespace

    from logger.runtime.daemon import Daemon

    fake = SimpleNamespace(tb=SimpleNamespace(scale=1.0))
    health = SimpleNamespace(heartbeat_mono_ns=10**9, ok_since_mono_ns=10**9)
    sampler = SimpleNamespace(health=health)
    base = {"name": "gnss", "state": "ok", "rate_hz": 1.0, "measured_rate_hz": 0.0, "last_error": ""}
    fresh = {**base, "last_sample_age_s": None}
    assert Daemon._sensor_problem(fake, sampler, fresh, 2 * 10**9, None) == ""  # type: ignore[arg-type]
    assert fresh["state"] == "starting" and fresh["measured_rate_hz"] is None
    late = {**base, "last_sample_age_s": None}
    assert Daemon._sensor_problem(fake, sampler, late, 10 * 10**9, None) == \
        "no sample since it was opened 9 s ago"  # type: ignore[arg-type]
    assert late["state"] == "silent"
    flowing = {**base, "last_sample_age_s": 0.5, "measured_rate_hz": 1.0}
    assert Daemon._sensor_problem(fake, sampler, flowing, 2 * 10**9, None) == ""  # type: ignore[arg-type]
    assert flowing["state"] == "ok" and flowing["measured_rate_hz"] == 1.0


@pytest.mark.parametrize("term", ["dumb", "", "xterm-256color"])
def test_watch_moves_the_cursor_only_on_a_terminal_that_can(tmp_path: Path, term: str) -> None:
    """`logger status --watch` on a phone's SSH with TERM=dumb (or none) sent its escape codes as text in every
    frame; there it prints plain frames, as into a pipe."""
    import pty
    import subprocess
    import sys
    import time

    sock = tmp_path / "status.sock"
    server = StatusServer(sock, lambda: SNAP)
    server.start()
    master, slave = pty.openpty()
    env = {**os.environ, "TERM": term, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.Popen([sys.executable, "-m", "logger.cli", "status", "--watch", "0.2", "--socket", str(sock)],
                            stdout=slave, stderr=slave, stdin=subprocess.DEVNULL, env=env)
    try:
        got = b""
        deadline = time.monotonic() + 30.0
        while got.count(b"DEGRADED") < 2 and time.monotonic() < deadline:
            got += os.read(master, 65536)
    finally:
        proc.kill()
        proc.wait()
        os.close(master)
        os.close(slave)
        server.close()
    assert got.count(b"DEGRADED") >= 2, got
    assert (b"\x1b[" in got) is (term == "xterm-256color"), got[:200]


@pytest.mark.parametrize("args", [["--jsn"], ["--watch", "abc"], ["extra"], ["--watch", "0"], ["--watch=-1"]])
def test_a_mistyped_command_is_one_line_and_not_the_critical_exit(args: list[str], capsys) -> None:
    """argparse's usage error exits 2, which for this command means "critical": a typo read as a critical logger
    by a script or a phone widget. It is one line and exit 4 (nobody can say)."""
    with pytest.raises(SystemExit) as stop:
        main(["status", *args])
    err = capsys.readouterr().err
    assert stop.value.code == 4 and err.count("\n") == 1 and err.startswith("logger status: "), err


def test_a_receivers_first_two_fixes_read_together_do_not_double_its_rate() -> None:
    """At start a 1 Hz receiver's first two fixes come in one read (one arrival time): the status said gnss 2.1/1,
    then 1.6, 1.4 ..., 1.0 only once the 10 s window had passed them. Samples at the window's first time start it
    as one; a FIFO read's samples (distinct times) count as before."""
    from logger.runtime.sampler import SensorHealth

    h = SensorHealth("gnss", 1.0)
    h._recent.extend([5 * NS_S, 5 * NS_S, 6 * NS_S])
    assert h.measured_rate_hz(6 * NS_S) == 1.0
    h._recent.extend([7 * NS_S, 7 * NS_S, 8 * NS_S])  # two in one read later on: both counted (a host behind)
    assert h.measured_rate_hz(8 * NS_S) == pytest.approx(4 / 3)
    imu = SensorHealth("imu", 20.0)
    imu._recent.extend(range(NS_S, 2 * NS_S + 1, NS_S // 20))
    assert imu.measured_rate_hz(2 * NS_S) == pytest.approx(20.0)


NS_S = 1_000_000_000
