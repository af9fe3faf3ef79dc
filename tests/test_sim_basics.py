"""The shared pieces of the simulation: clocks, truth interface, earth model, pty port; and the rule that a
device model never imports a driver."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest
import serial

from sensors.sim import earth
from sensors.sim.clock import ManualClock, ScaledClock
from sensors.sim.pty import PtyPort
from sensors.sim.truth import ParkedTrajectory, StraightTrajectory

SIM_DIR = Path(__file__).resolve().parents[1] / "sensors" / "sim"


def test_manual_clock_moves_only_when_told() -> None:
    clock = ManualClock()
    assert clock.now_ns() == 0
    clock.sleep(0.0045)
    assert clock.now_ns() == 4_500_000
    with pytest.raises(ValueError):
        clock.advance(-1)


def test_scaled_clock_runs_faster() -> None:
    clock = ScaledClock(time_scale=1000.0)
    a = clock.now_ns()
    clock.sleep(1.0)  # one drive second is one host millisecond
    assert clock.now_ns() - a >= 1_000_000_000


def test_gravity_matches_published_values() -> None:
    # WGS-84 normal gravity: 9.7803253359 at the equator, 9.8321849378 at the poles.
    assert earth.gravity_ned(0.0, 0.0)[2] == pytest.approx(9.7803253359, abs=1e-9)
    assert earth.gravity_ned(math.pi / 2, 0.0)[2] == pytest.approx(9.8321849378, abs=1e-8)
    # Free-air gradient about -3.086e-6 /s^2 per metre.
    assert earth.gravity_ned(0.7, 1000.0)[2] - earth.gravity_ned(0.7, 0.0)[2] == pytest.approx(-3.086e-3, rel=0.01)


def test_dcm_is_a_rotation_and_yaw_turns_north_to_east() -> None:
    c = earth.dcm_body_to_ned(np.array([0.1, -0.2, 1.0]))
    assert np.allclose(c @ c.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(c) == pytest.approx(1.0)
    c90 = earth.dcm_body_to_ned(np.array([0.0, 0.0, math.pi / 2]))
    assert np.allclose(c90 @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_parked_vehicle_senses_gravity_and_earth_rate() -> None:
    s = ParkedTrajectory(lat_deg=45.0).state(3.0)
    assert s.forward_speed_mps == 0.0
    assert s.f_body_mps2[2] == pytest.approx(-earth.gravity_ned(s.lat_rad, s.height_m)[2])
    assert np.linalg.norm(s.w_body_rps) == pytest.approx(earth.OMEGA_IE)


def test_straight_drive_moves_at_its_speed() -> None:
    traj = StraightTrajectory(speed_mps=20.0, heading_deg=0.0)
    a, b = traj.state(0.0), traj.state(10.0)
    rn, _ = earth.radii(a.lat_rad)
    assert (b.lat_rad - a.lat_rad) * (rn + a.height_m) == pytest.approx(200.0, rel=1e-9)
    assert b.forward_speed_mps == pytest.approx(20.0)


def test_pty_port_vanishes_and_comes_back_under_the_same_path() -> None:
    with PtyPort() as port:
        ser = serial.Serial(port.path, 38400, timeout=0.5)
        ser.write(b"ATI\r")
        assert port.read(1.0) == b"ATI\r"
        port.write(b"ELM327 v1.5\r\r>")
        assert ser.read_until(b">") == b"ELM327 v1.5\r\r>"
        port.vanish()
        with pytest.raises(serial.SerialException):
            ser.read(1)
        ser.close()
        port.reappear()
        ser = serial.Serial(port.path, 38400, timeout=0.5)
        port.write(b"OK\r>")
        assert ser.read_until(b">") == b"OK\r>"
        ser.close()


def test_a_pty_port_removes_the_folders_runs_killed_before_it_left_behind(tmp_path, monkeypatch) -> None:
    """Each simulated serial port is a folder in the temporary folder; a run killed with SIGKILL left its folders
    (hundreds on a CI host). A new port removes those of processes that are gone, keeps those of live ones."""
    import os
    import subprocess
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # a folder this process has not swept yet
    dead = subprocess.Popen(["true"])  # a process that has ended: its pid is free
    dead.wait()
    for name in (f"sim-tty-{dead.pid}-abc", f"sim-tty-{os.getpid()}-def", "sim-tty-x1y2z3", "other-1-x"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "tty").symlink_to("/dev/pts/999999")
    with PtyPort() as port:
        assert Path(port.path).parent.name.startswith(f"sim-tty-{os.getpid()}-")
        left = sorted(p.name for p in tmp_path.iterdir())
    assert f"sim-tty-{dead.pid}-abc" not in left
    assert {f"sim-tty-{os.getpid()}-def", "sim-tty-x1y2z3", "other-1-x"} <= set(left)
    assert not any(p.name.startswith(f"sim-tty-{os.getpid()}-") and p.name != f"sim-tty-{os.getpid()}-def"
                   for p in tmp_path.iterdir())  # its own folder went with it


# ---- models do not import drivers -------------------------------------------------------------------
def driver_imports(source: str, module: str) -> list[tuple[int, str]]:
    """(line, imported module) of every import in ``source`` that reaches into ``sensors`` outside ``sensors.sim``.

    ``module`` is the dotted name of the file parsed, so relative imports resolve as Python resolves them.
    Imports inside functions count too: a late import is still the driver's knowledge.
    """
    package = module.split(".")[:-1]
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            # "from sensors import bmp085" imports the module sensors.bmp085; "from x.y import name" needs x.y.
            targets = [f"{base}.{alias.name}" for alias in node.names] if base == "sensors" else [base]
        else:
            continue
        for target in targets:
            parts = target.split(".")
            if parts[0] == "sensors" and parts[1:2] != ["sim"]:
                found.append((node.lineno, target))
    return found


@pytest.mark.parametrize(("source", "expected"), [
    ("from sensors.bmp085 import compensate_pressure", ["sensors.bmp085"]),
    ("import sensors.obd", ["sensors.obd"]),
    ("import sensors", ["sensors"]),
    ("from sensors import obd, sim", ["sensors.obd"]),
    ("from sensors import *", ["sensors.*"]),
    ("from .. import ublox_decode", ["sensors.ublox_decode"]),
    ("from ..geodesy import NS_PER_S", ["sensors.geodesy"]),
    ("def f():\n    from sensors.errors import NoData", ["sensors.errors"]),
    ("from sensors.sim import earth\nfrom sensors.sim.clock import DriveClock", []),
    ("from . import clock\nfrom .truth import Trajectory\nimport sensors.sim.pty", []),
    ("import numpy\nfrom pyubx2 import UBXMessage", []),
])
def test_driver_import_check_sees_every_form(source: str, expected: list[str]) -> None:
    assert [target for _, target in driver_imports(source, "sensors.sim.model")] == expected


def test_no_device_model_imports_a_driver() -> None:
    """See sensors/sim/__init__.py: a model is the datasheet's other side and must not share the driver's reading."""
    files = sorted(SIM_DIR.rglob("*.py"))
    assert len(files) > 10
    offences = []
    for path in files:
        rel = path.relative_to(SIM_DIR.parents[1]).with_suffix("")
        module = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        if rel.name == "__init__":
            module += ".__init__"  # a package's relative imports resolve against the package itself
        for line, target in driver_imports(path.read_text(encoding="utf-8"), module):
            offences.append(f"{module.removesuffix('.__init__')} (line {line}) imports {target}")
    assert not offences, "device models import drivers:\n" + "\n".join(offences)
