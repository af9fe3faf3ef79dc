"""Our ``logger`` shares its name with util-linux's: scripts that call the system logger must keep working.

Everything that is not one of our subcommands (or --help) is handed to the system's logger with the same
arguments, stdin and exit code. Checked with a stand-in system logger on PATH, and with the real util-linux
logger where it is installed (``--no-act --stderr`` makes it print instead of writing to the journal).
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from logger.cli import SUBCOMMANDS, find_system_logger

ROOT = Path(__file__).resolve().parents[1]
OUR_SCRIPT = Path(sys.executable).parent / "logger"  # the console script pip installed next to this Python

STAND_IN = """#!/bin/sh
# a stand-in for util-linux logger: records what it got, answers with a telling exit code
printf '%s\\n' "$@" > "$RECORD.args"
cat > "$RECORD.stdin"
echo "stand-in says hi" >&2
exit 7
"""


@pytest.fixture
def stand_in(tmp_path: Path) -> tuple[dict[str, str], Path]:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    script = bin_dir / "logger"
    script.write_text(STAND_IN)
    script.chmod(0o755)
    env = {**os.environ, "PATH": f"{OUR_SCRIPT.parent}{os.pathsep}{bin_dir}{os.pathsep}/usr/bin:/bin",
           "RECORD": str(tmp_path / "got")}
    env.pop("VEHICLE_LOGGER_HANDED_OVER", None)
    return env, tmp_path / "got"


def run(cmd: list[str], env: dict[str, str], stdin: str = "",
        executable: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, input=stdin, capture_output=True, text=True, env=env, timeout=60, cwd=ROOT,
                          executable=executable)


needs_script = pytest.mark.skipif(not OUR_SCRIPT.exists(), reason=f"no console script at {OUR_SCRIPT} (pip -e .)")


@needs_script
def test_foreign_arguments_and_stdin_reach_the_system_logger(stand_in: tuple[dict[str, str], Path]) -> None:
    env, got = stand_in
    r = run([str(OUR_SCRIPT), "-t", "backup", "-p", "user.err", "disk 93% full"], env, stdin="line one\nline two\n")
    assert r.returncode == 7, r.stderr  # the system logger's exit code
    assert Path(f"{got}.args").read_text().splitlines() == ["-t", "backup", "-p", "user.err", "disk 93% full"]
    assert Path(f"{got}.stdin").read_text() == "line one\nline two\n"
    assert r.stderr == "stand-in says hi\n"  # nothing of ours in between


@needs_script
def test_a_pipe_without_arguments_is_handed_over(stand_in: tuple[dict[str, str], Path]) -> None:
    env, got = stand_in
    r = run([str(OUR_SCRIPT)], env, stdin="echoed message\n")  # echo msg | logger
    assert r.returncode == 7
    assert Path(f"{got}.args").read_text() == "\n"  # printf with no arguments prints one empty line
    assert Path(f"{got}.stdin").read_text() == "echoed message\n"


def test_started_as_a_module_it_still_skips_itself(stand_in: tuple[dict[str, str], Path]) -> None:
    env, got = stand_in
    r = run([sys.executable, "-m", "logger.cli", "--id=42", "hello"], env)
    assert r.returncode == 7
    assert Path(f"{got}.args").read_text().splitlines() == ["--id=42", "hello"]


@needs_script
def test_our_commands_and_help_stay_ours(stand_in: tuple[dict[str, str], Path], tmp_path: Path) -> None:
    env, got = stand_in
    r = run([str(OUR_SCRIPT), "--help"], env)
    assert r.returncode == 0 and all(name in r.stdout for name in SUBCOMMANDS)
    r = run([str(OUR_SCRIPT), "status", "--socket", str(tmp_path / "none.sock")], env)
    assert r.returncode == 3 and "not running" in r.stderr
    assert not Path(f"{got}.args").exists()


@needs_script
def test_a_system_logger_that_hands_back_is_a_loop_not_a_hang(tmp_path: Path) -> None:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    bounce = bin_dir / "logger"
    bounce.write_text(f'#!/bin/sh\nexec "{OUR_SCRIPT}" "$@"\n')
    bounce.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{OUR_SCRIPT.parent}"}
    env.pop("VEHICLE_LOGGER_HANDED_OVER", None)
    r = run([str(OUR_SCRIPT), "-t", "x", "y"], env)
    assert r.returncode == 127 and "not looping" in r.stderr


def test_finding_the_system_logger(tmp_path: Path) -> None:
    ours = tmp_path / "venv" / "bin"
    ours.mkdir(parents=True)
    (ours / "logger").write_text("#!/opt/vehicle-logger/venv/bin/python3\nimport sys\nfrom logger.cli import main\n")
    (ours / "logger").chmod(0o755)
    other = tmp_path / "usr" / "bin"
    other.mkdir(parents=True)
    (other / "logger").write_bytes(b"\x7fELF not really")
    (other / "logger").chmod(0o755)
    not_exec = tmp_path / "noexec"
    not_exec.mkdir()
    (not_exec / "logger").write_text("#!/bin/sh\n")
    path = os.pathsep.join([str(not_exec), str(ours), str(other)])
    assert find_system_logger(path, [str(ours / "logger")]) == str(other / "logger")
    # A copy of our console script elsewhere is recognised by what it runs, not by where it is.
    assert find_system_logger(os.pathsep.join([str(ours), str(other)]), []) == str(other / "logger")
    fallback = find_system_logger(str(ours), [])
    assert fallback == ("/usr/bin/logger" if os.access("/usr/bin/logger", os.X_OK) else None)


UTIL_LINUX = shutil.which("logger", path="/usr/bin:/bin")


def _normalise(text: str) -> str:
    # <13>Nov 22 16:50:01 tag: message -> <13>TIME tag: message (the two runs may straddle a second)
    return re.sub(r"[A-Z][a-z]{2} [ \d]\d \d\d:\d\d:\d\d", "TIME", text)


@pytest.fixture
def syslog(tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    """A datagram socket standing in for /dev/log, so that the real logger has somewhere to write."""
    path = str(tmp_path / "log.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(5)
    yield path, sock
    sock.close()


@pytest.mark.skipif(UTIL_LINUX is None, reason="util-linux logger is not installed here")
@needs_script
@pytest.mark.parametrize(("argv", "stdin"), [
    (["--stderr", "-t", "vl-test", "hello from a script"], ""),
    (["--stderr", "-t", "vl-test"], "piped line\n"),
    (["--stderr", "--priority", "daemon.warning", "-t", "vl-test", "warned"], ""),
])
def test_same_message_as_the_real_util_linux_logger(argv: list[str], stdin: str,
                                                     syslog: tuple[str, socket.socket]) -> None:
    path, sock = syslog
    env = {**os.environ, "PATH": f"{OUR_SCRIPT.parent}{os.pathsep}/usr/bin:/bin"}
    env.pop("VEHICLE_LOGGER_HANDED_OVER", None)
    argv = ["--socket", path, *argv]
    ours = run([str(OUR_SCRIPT), *argv], env, stdin)
    got_ours = sock.recv(4096).decode()
    theirs = run([str(UTIL_LINUX), *argv], env, stdin)
    got_theirs = sock.recv(4096).decode()
    assert ours.returncode == theirs.returncode == 0, (ours.stderr, theirs.stderr)
    assert _normalise(got_ours) == _normalise(got_theirs) and "vl-test" in got_ours
    assert _normalise(ours.stderr) == _normalise(theirs.stderr)


@pytest.mark.skipif(UTIL_LINUX is None, reason="util-linux logger is not installed here")
@needs_script
def test_the_real_logger_s_errors_and_exit_code_come_through() -> None:
    env = {**os.environ, "PATH": f"{OUR_SCRIPT.parent}{os.pathsep}/usr/bin:/bin"}
    env.pop("VEHICLE_LOGGER_HANDED_OVER", None)
    no_socket = ["--socket-errors=on", "--socket", "/nonexistent/log.sock", "-t", "x", "y"]
    for argv in (["--definitely-not-an-option"], no_socket):
        ours = run([str(OUR_SCRIPT), *argv], env)
        theirs = run(["logger", *argv], env, executable=UTIL_LINUX)  # as a script calling `logger` runs it
        assert ours.returncode == theirs.returncode != 0
        assert ours.stderr == theirs.stderr and ours.stderr


def test_version_names_ours_and_the_system_logger(stand_in: tuple[dict[str, str], Path]) -> None:
    env, _ = stand_in
    r = run([sys.executable, "-m", "logger.cli", "--version"], env)
    assert r.returncode == 0
    ours, theirs = r.stdout.splitlines()
    assert ours.startswith("logger (vehicle-logger) ")
    assert "system logger (" in theirs and "stand-in says hi" in theirs  # the stand-in prints on stderr only


def test_a_reader_that_closes_the_pipe_early_gets_no_traceback() -> None:
    """``logger info FILE | head -1``: the command ends quietly with the shell's SIGPIPE code."""
    code = ("import sys, types\n"
            "import logger.cli as cli\n"
            "m = types.ModuleType('talkative')\n"
            "def main(args):\n"
            "    for i in range(200000):\n"
            "        print('line', i)\n"
            "    return 0\n"
            "m.main = main\n"
            "sys.modules['talkative'] = m\n"
            "sys.exit(cli.run_subcommand('talkative', []))\n")
    p = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdout is not None and p.stdout.readline() == b"line 0\n"
    p.stdout.close()
    _, err = p.communicate(timeout=60)
    assert p.returncode == 141, err
    assert b"Traceback" not in err and b"BrokenPipe" not in err



def test_ctrl_c_ends_a_command_with_one_line_and_the_shells_code() -> None:
    """Ctrl-C during an office command (a replay, an export): no traceback, one line, the shell's 130."""
    code = ("import os, signal, sys, time\n"
            "import logger.cli as cli\n"
            "import types\n"
            "m = types.ModuleType('slow_work')\n"
            "def main(args):\n"
            "    signal.signal(signal.SIGINT, signal.default_int_handler)\n"  # as at a terminal: a job started in
            "    os.kill(os.getpid(), signal.SIGINT)\n"  # the background (CI's) inherits SIGINT ignored
            "    time.sleep(30)\n"
            "    return 0\n"
            "m.main = main\n"
            "sys.modules['slow_work'] = m\n"
            "sys.exit(cli.run_subcommand('slow_work', []))\n")
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert p.returncode == 130, p.stderr
    assert p.stderr == "\nlogger slow-work: interrupted\n", p.stderr


@pytest.mark.parametrize("flag", ["--help", "--version"])
def test_help_and_version_into_a_closed_pipe_get_no_traceback(flag: str) -> None:
    """``logger --help | head -3`` on a slow board: the reader may be gone before the text is written."""
    p = subprocess.Popen([sys.executable, "-m", "logger.cli", flag], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    assert p.stdout is not None
    p.stdout.close()  # before the interpreter has even started: its first write meets a closed pipe
    _, err = p.communicate(timeout=60)
    assert p.returncode == 141, err
    assert b"Traceback" not in err and b"BrokenPipe" not in err

@needs_script
def test_a_typo_at_a_terminal_gets_a_hint_and_still_reaches_the_system_logger(
        stand_in: tuple[dict[str, str], Path]) -> None:
    import pty

    env, got = stand_in
    master, slave = pty.openpty()
    os.write(master, b"\x04")  # Ctrl-D: the stand-in's read of the terminal ends
    try:
        r = subprocess.run([str(OUR_SCRIPT), "stauts"], stdin=slave, capture_output=True, text=True, env=env,
                           timeout=60, cwd=ROOT)
    finally:
        os.close(slave)
        os.close(master)
    assert r.returncode == 7  # the stand-in's exit code: it got the call
    assert Path(f"{got}.args").read_text() == "stauts\n"
    assert "did you mean `logger status`?" in r.stderr and "passing it to the system logger" in r.stderr
    r = run([str(OUR_SCRIPT), "stauts"], env)  # from a script (stdin not a terminal): no hint, same hand-over
    assert r.returncode == 7 and "did you mean" not in r.stderr


def test_the_commands_list_fits_80_columns() -> None:
    from logger.cli import usage

    assert max(len(line) for line in usage().splitlines()) < 80  # `status`'s line was 160 columns


def test_ctrl_c_while_a_command_loads_is_one_line_and_exit_130(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """Loading a command's modules is most of a short command's time (seconds on the board): Ctrl-C there gave a
    traceback and a death by the signal."""
    from logger.cli import run_subcommand

    (tmp_path / "interrupted_while_loading.py").write_text("raise KeyboardInterrupt\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert run_subcommand("interrupted_while_loading", []) == 130
    assert capsys.readouterr().err == "\nlogger interrupted-while-loading: interrupted\n"


@pytest.mark.parametrize("args", [["--help"], ["info", "/nonexistent.mcap"], ["run", "--sim", "--duration", "2"]])
def test_a_command_started_with_stdout_closed_ends_with_its_own_code(args: list[str], tmp_path: Path) -> None:
    """Started with stdout closed (`>&-`), every command did its work and then died at the final flush: a
    traceback and exit 1 (a good `logger run` read as a failure)."""
    def with_out(n: int) -> list[str]:  # a run records into a folder of its own, with its own socket
        return [*args, "--out", str(tmp_path / f"d{n}"), "--status-socket", str(tmp_path / f"s{n}")] \
            if args[0] == "run" else args

    own = subprocess.run([sys.executable, "-m", "logger.cli", *with_out(1)], capture_output=True, text=True,
                         timeout=120)
    closed = subprocess.run([sys.executable, "-m", "logger.cli", *with_out(2)], stderr=subprocess.PIPE, text=True,
                            timeout=120, preexec_fn=lambda: os.close(1))
    # A simulated run may also exit 3 on a host too busy to hold its rates; the traceback's exit was 1.
    assert closed.returncode == own.returncode or {closed.returncode, own.returncode} <= {0, 3}, \
        own.stderr + closed.stderr
    assert "Traceback" not in closed.stderr, closed.stderr
