"""tools/install-board.sh's own logic: every step reports done, skipped or failed with the reason, a failure skips
only the steps that need it, the summary and the exit status say so, --image never contacts udev or systemd, and
--dry-run lists the same steps whatever is installed.

The system's commands (apt-get, systemd-sysusers, udevadm, systemctl, install, ln, ...) are replaced by stand-ins
on PATH that log their arguments, so the script runs for real without touching this machine; the stand-ins are
the script's boundary, as a fake ioctl is a driver's. The real commands are exercised by tools/board-check.sh in a
Debian 12 armhf root.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
INSTALL = ROOT / "tools" / "install-board.sh"
BOARD_CHECK = ROOT / "tools" / "board-check.sh"
STANDINS = ("apt-get", "systemd-sysusers", "usermod", "udevadm", "systemctl", "install", "ln", "python3", "id",
            "runuser")


def _base(tmp_path: Path) -> Path:
    """Where a test installs (--prefix): not under /tmp, which the unit hides (PrivateTmp=) and the script refuses;
    /dev/shm, removed after each test."""
    return Path("/dev/shm") / f"install-board-test-{os.getpid()}-{tmp_path.name}"


@pytest.fixture(autouse=True)
def _remove_base(tmp_path: Path) -> Iterator[None]:
    yield
    shutil.rmtree(_base(tmp_path), ignore_errors=True)


def _standins(tmp_path: Path, failing: dict[str, int] | None = None) -> tuple[Path, Path]:
    """A bin folder of logging stand-ins (``failing`` maps a command to the exit status it returns) and its log."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    log = tmp_path / "calls.log"
    for name in STANDINS:
        rc = (failing or {}).get(name, 0)
        out = "echo 0" if name == "id" else ""
        (bin_dir / name).write_text(f'#!/bin/sh\necho "{name} $*" >> {shlex.quote(str(log))}\n{out}\nexit {rc}\n')
        (bin_dir / name).chmod(0o755)
    return bin_dir, log


def _venv(prefix: Path, pip_rc: int = 0) -> None:
    """An installed-looking venv under ``prefix`` whose pip and logger are stand-ins too."""
    bin_dir = prefix / "venv" / "bin"
    bin_dir.mkdir(parents=True)
    for name, rc in (("python", 0), ("pip", pip_rc), ("logger", 0)):
        (bin_dir / name).write_text(f"#!/bin/sh\necho \"venv-{name} $*\" >> {shlex.quote(str(prefix / 'calls.log'))}\n"
                                    f"exit {rc}\n")
        (bin_dir / name).chmod(0o755)


def _run(tmp_path: Path, *args: str, failing: dict[str, int] | None = None, pip_rc: int = 0
         ) -> tuple[subprocess.CompletedProcess[str], list[str]]:
    bin_dir, log = _standins(tmp_path, failing)
    prefix = _base(tmp_path) / "opt"
    _venv(prefix, pip_rc)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}"}
    r = subprocess.run(["sh", str(INSTALL), "--prefix", str(prefix), *args], capture_output=True, text=True,
                       env=env, timeout=60)
    calls = log.read_text().splitlines() if log.exists() else []
    return r, calls


def _summary(stdout: str) -> dict[str, str]:
    lines = stdout.split("\nsummary:\n", 1)[1].splitlines()
    out = {}
    for line in lines:
        if line.startswith("  ") and "." in line.split()[0]:
            number = line.split()[0].rstrip(".")
            out[number] = line
    return out


def test_every_step_done_on_a_system_that_takes_them(tmp_path: Path) -> None:
    r, calls = _run(tmp_path, "--operator", "survey", "--no-start")
    assert r.returncode == 0, r.stdout + r.stderr
    summary = _summary(r.stdout)
    assert sorted(summary) == ["1", "2", "3", "4", "5", "6", "7"]
    assert all(line.rstrip().endswith("done") for line in summary.values()), summary
    assert "udevadm control --reload" in calls and "systemctl daemon-reload" in calls
    assert "systemctl enable vehicle-logger.service" in calls
    assert not any(c.startswith("systemctl restart") for c in calls)  # --no-start
    # pip builds from a copy of the package's files, not in the operator's checkout (root's build/ and egg-info
    # there broke their own `pip install -e .`), and the copy is gone after.
    venv_calls = (_base(tmp_path) / "opt" / "calls.log").read_text().splitlines()
    pip = [c.split() for c in venv_calls if c.startswith("venv-pip")]
    stage = Path(pip[0][-1])
    assert stage.name.startswith("vehicle-logger-build.") and not stage.exists(), pip
    assert f"tar -C {ROOT} --exclude=__pycache__ -cf {stage}/tree.tar pyproject.toml README.md logger sensors sync" \
        in r.stdout
    # The configuration is checked as the service reads it: as its user (a kept root-only file passed as root).
    assert (f"runuser -u vehicle-logger -- {_base(tmp_path) / 'opt'}/venv/bin/logger config check "
            "/etc/vehicle-logger/logger.toml") in calls


def test_an_operator_who_is_no_user_is_refused_before_any_step(tmp_path: Path) -> None:
    """A mistyped --operator failed step 3 after apt and pip had run, and with it steps 5 and 6: the board was left
    without its configuration and service."""
    r, calls = _run(tmp_path, "--operator", "surveyor", failing={"id": 1})
    assert r.returncode == 2 and r.stderr == ("install-board.sh: --operator surveyor: no such user (give the "
                                              "operator's own login, e.g. debian)\n"), r.stderr
    assert "==" not in r.stdout and calls == ["id -u", "id -u surveyor"]  # am I root; is the operator a user


def test_a_failed_step_is_named_and_the_independent_steps_still_run(tmp_path: Path) -> None:
    # udevd not running (a chroot): step 4 fails with the reason, 5-7 do not need it and complete.
    r, calls = _run(tmp_path, "--no-start", failing={"udevadm": 1})
    assert r.returncode == 1
    summary = _summary(r.stdout)
    assert "FAILED" in summary["4"] and "udevd is not running" in summary["4"] and "--image" in summary["4"]
    for n in ("1", "2", "3", "5", "6", "7"):
        assert summary[n].rstrip().endswith("done"), summary[n]
    assert "systemctl enable vehicle-logger.service" in calls
    assert "1 step(s) did not complete" in r.stderr


def test_a_failed_prerequisite_skips_only_what_needs_it(tmp_path: Path) -> None:
    # pip cannot install the tree: the configuration check, the service and the command link need the venv.
    r, calls = _run(tmp_path, "--no-start", pip_rc=1)
    assert r.returncode == 1
    summary = _summary(r.stdout)
    assert "FAILED" in summary["2"] and "pip install" in summary["2"] and "exited 1" in summary["2"]
    # Offline, pip's own reason is far above: the line says where to look and what to do instead.
    assert "exited 1 (no network? pip needs the package index; offline, install from a wheelhouse: --wheels DIR" \
        in r.stdout
    for n in ("5", "6", "7"):
        assert "skipped: step" in summary[n], summary[n]
    for n in ("1", "3", "4"):
        assert summary[n].rstrip().endswith("done"), summary[n]
    assert not any(c.startswith("systemctl") for c in calls) and not any(c.startswith("ln ") for c in calls)
    assert "4 step(s) did not complete" in r.stderr


def test_a_command_that_is_not_there_is_named(tmp_path: Path) -> None:
    # A PATH without /usr/sbin (a plain user's, or sudo with a narrow secure_path): usermod is not found.
    r, _ = _run(tmp_path, "--image", "--operator", "survey", failing={"usermod": 127})
    summary = _summary(r.stdout)
    assert r.returncode == 1 and "`usermod` was not found" in summary["3"] and "PATH" in summary["3"], summary


def test_image_contacts_neither_udev_nor_systemd(tmp_path: Path) -> None:
    r, calls = _run(tmp_path, "--image", "--operator", "survey")
    assert r.returncode == 0, r.stdout + r.stderr
    assert not any(c.startswith("udevadm") for c in calls), calls
    systemctl = [c for c in calls if c.startswith("systemctl")]
    assert systemctl == ["systemctl --root=/ enable vehicle-logger.service"], systemctl
    assert "install -D -m 0644 " + str(ROOT / "systemd" / "70-vehicle-logger.rules") + \
        " /etc/udev/rules.d/70-vehicle-logger.rules" in calls  # rules in place for the first boot
    assert any(c.startswith("systemd-sysusers") for c in calls)


def test_offline_wheelhouse_keeps_pip_off_the_network(tmp_path: Path) -> None:
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    r, _ = _run(tmp_path, "--image", "--no-apt", "--wheels", str(wheels))
    assert r.returncode == 0, r.stdout + r.stderr
    calls = (_base(tmp_path) / "opt" / "calls.log").read_text().splitlines()
    pip = [c for c in calls if c.startswith("venv-pip install")]
    assert pip and all(f"--no-index --find-links {wheels}" in c and "--no-build-isolation" in c for c in pip)
    assert "skipped: --no-apt" in _summary(r.stdout)["1"]


def test_missing_wheelhouse_is_one_clear_line(tmp_path: Path) -> None:
    r, calls = _run(tmp_path, "--wheels", str(tmp_path / "nowhere"))
    assert r.returncode == 2 and calls == ["id -u"]  # nothing done
    assert r.stderr.count("\n") == 1 and "nowhere" in r.stderr and "--fetch-wheels" in r.stderr


def test_dry_run_lists_the_same_steps_before_and_after_an_installation(tmp_path: Path) -> None:
    def steps(prefix: Path) -> list[str]:
        r = subprocess.run(["sh", str(INSTALL), "--dry-run", "--operator", "survey", "--prefix", str(prefix)],
                           capture_output=True, text=True, timeout=30)
        assert r.returncode == 0, r.stderr
        # it says it did nothing (it ended "done: systemctl status vehicle-logger; ..." as if it had installed)
        assert r.stdout.splitlines()[-1] == ("dry run: nothing was done; run it again without --dry-run, as root, "
                                             "to install")
        return [line.replace(str(prefix), "PREFIX") for line in r.stdout.splitlines()]

    fresh = _base(tmp_path) / "fresh"
    installed = _base(tmp_path) / "installed"
    _venv(installed)
    before, after = steps(fresh), steps(installed)
    assert before == after
    assert "+ python3 -m venv --system-site-packages PREFIX/venv" in before


@pytest.mark.parametrize("script", [INSTALL, BOARD_CHECK], ids=lambda p: p.name)
def test_scripts_parse_and_explain_themselves(script: Path) -> None:
    assert subprocess.run(["sh", "-n", str(script)], timeout=30).returncode == 0
    r = subprocess.run(["sh", str(script), "--help"], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0 and ("--image" if script == INSTALL else "--suite") in r.stdout
    bad = subprocess.run(["sh", str(script), "--no-such-option"], capture_output=True, text=True, timeout=30)
    assert bad.returncode == 2 and "unknown option --no-such-option" in bad.stderr


def test_another_prefix_points_the_unit_at_its_venv(tmp_path: Path) -> None:
    """The unit starts /opt/vehicle-logger's logger; installed elsewhere, a drop-in replaces its ExecStart with the
    same command from the venv that was installed (the unit itself stays as shipped)."""
    r, calls = _run(tmp_path, "--no-start")
    assert r.returncode == 0, r.stdout + r.stderr
    prefix = _base(tmp_path) / "opt"
    dropin = "/etc/systemd/system/vehicle-logger.service.d/prefix.conf"
    assert f"install -D -m 0644 {prefix}/prefix.conf {dropin}" in calls
    lines = (prefix / "prefix.conf").read_text().splitlines()
    shipped = next(x for x in (ROOT / "systemd" / "vehicle-logger.service").read_text().splitlines()
                   if x.startswith("ExecStart="))
    assert lines[1:] == ["[Service]", "ExecStart=", shipped.replace("/opt/vehicle-logger/", f"{prefix}/")]
    assert (prefix / "venv" / "bin" / "logger").exists()
    assert calls.index(f"install -D -m 0644 {prefix}/prefix.conf {dropin}") < calls.index("systemctl daemon-reload")


@pytest.mark.parametrize("prefix, says", [("opt/vl", "must be an absolute path"), ("/srv/v l", "holds a space"),
                                          ("/home/debian/vl", "the unit hides /home"),
                                          ("/var/tmp/vl", "the unit hides /var/tmp"), ("/tmp", "the unit hides /tmp"),
                                          ("/run/user/1000/vl", "the unit hides /run/user"),
                                          ("/root/vl", "the unit hides /root")])
def test_a_prefix_the_unit_could_not_run_from_is_refused(tmp_path: Path, prefix: str, says: str) -> None:
    r = subprocess.run(["sh", str(INSTALL), "--dry-run", "--prefix", prefix], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and says in r.stderr and len(r.stderr.splitlines()) == 1, r.stderr
    assert "==" not in r.stdout  # refused before any step
