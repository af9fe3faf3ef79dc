"""The logger's PPS samples in a real chronyd (Debian 12's chrony 4.3), as on a board: a private chronyd
(``-x``: it never touches this machine's clock) with the ``refclock SOCK`` line of docs/sync.md, its own pidfile
and command socket, read back with ``chronyc``. chronyd makes the refclock's socket as root before it drops to its
own user, so the logger's user may not send to it until systemd/chrony.service.d/vehicle-logger.conf, run as the
unit's ExecStartPost, has given the socket to the logger's group: checked here with that very command."""

from __future__ import annotations

import grp
import os
import pwd
import re
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from sync.chrony_sock import ChronySock

ROOT = Path(__file__).resolve().parents[1]
DROP_IN = ROOT / "systemd" / "chrony.service.d" / "vehicle-logger.conf"
OFFSET_NS = 250_000  # true time ahead of the system clock in the samples sent
NOBODY = 65534

pytestmark = [
    pytest.mark.skipif(shutil.which("chronyd") is None or shutil.which("chronyc") is None,
                       reason="chrony is not installed (Debian: apt-get install chrony)"),
    pytest.mark.skipif(os.geteuid() != 0, reason="needs root: chronyd starts as root and drops to its own user"),
]


@pytest.fixture
def chronyd(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path]]:
    """A private chronyd; yields (its SOCK refclock's socket, its command socket)."""
    where = Path(subprocess.run(["mktemp", "-d", "/tmp/chronyd-XXXXXX"], capture_output=True, text=True,
                                check=True).stdout.strip())
    where.chmod(0o755)  # reachable by the logger's user, as /run is
    run = where / "run"  # the command socket's folder: chronyd wants it its own user's, closed to others
    run.mkdir(mode=0o750)
    user = next((u for u in ("_chrony", "chrony") if _exists(u)), "root")
    shutil.chown(run, user, user)
    sock, cmd = where / "refclock.sock", run / "chronyd.sock"
    (where / "chrony.conf").write_text(
        f"refclock SOCK {sock} refid GPS poll 2 precision 1e-7\n"
        f"pidfile {where / 'chronyd.pid'}\nbindcmdaddress {cmd}\ncmdport 0\nport 0\n")
    proc = subprocess.Popen(["chronyd", "-x", "-d", "-f", str(where / "chrony.conf")], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 10
        while not (sock.exists() and cmd.exists()) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert sock.exists() and cmd.exists(), "chronyd did not start"
        yield sock, cmd
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
        shutil.rmtree(where, ignore_errors=True)


def _exists(user: str) -> bool:
    try:
        pwd.getpwnam(user)
    except KeyError:
        return False
    return True


def _send_as_nobody(sock: Path, seconds: int) -> tuple[int, int]:
    """Edges once a second for ``seconds`` from a process of an unprivileged user: (sent, refused)."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.close(read)
            os.setgroups([])
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            client = ChronySock(str(sock))
            for _ in range(seconds):
                client.send_edge(time.monotonic_ns(), time.time_ns() + OFFSET_NS)
                time.sleep(1.0)
            os.write(write, f"{client.sent} {client.failed}".encode())
        finally:
            os._exit(0)
    os.close(write)
    os.waitpid(pid, 0)
    with os.fdopen(read) as f:
        sent, failed = f.read().split()
    return int(sent), int(failed)


def _gps_source(cmd: Path) -> list[str]:
    out = subprocess.run(["chronyc", "-h", str(cmd), "-c", "sources"], capture_output=True, text=True, timeout=10)
    return next(line.split(",") for line in out.stdout.splitlines() if ",GPS," in line)


def test_chronyd_takes_the_loggers_samples_once_the_drop_in_gave_it_the_socket(chronyd: tuple[Path, Path]) -> None:
    sock, cmd = chronyd
    assert sock.stat().st_uid == 0 and sock.stat().st_mode & 0o777 == 0o755  # as chronyd makes it: root's

    assert _send_as_nobody(sock, 1) == (0, 1)  # refused (EACCES), as on a board without the drop-in
    (command,) = re.findall(r"^ExecStartPost=/bin/sh -c '(.*)'$", DROP_IN.read_text(), re.M)
    here = command.replace("/run/chrony.vehicle-logger.sock", str(sock)).replace(
        "chgrp vehicle-logger", f"chgrp {grp.getgrgid(NOBODY).gr_name}")
    done = subprocess.run(["sh", "-c", here], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr

    assert _send_as_nobody(sock, 6) == (6, 0)
    deadline = time.monotonic() + 10
    source = _gps_source(cmd)
    while source[5] == "0" and time.monotonic() < deadline:  # reach: the samples of a completed poll
        time.sleep(0.5)
        source = _gps_source(cmd)
    assert source[5] != "0", source
    # chronyc's last sample: the local clock against the source, the samples' 250 us the other way
    assert abs(float(source[7]) + OFFSET_NS / 1e9) < 50e-6, source
