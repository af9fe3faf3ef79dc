"""The ``[nav]``, ``[sync]`` and ``[recorder]`` defaults are written once, in the settings dataclasses.

The configuration's schema reads them from ``NavParams``, ``SyncSettings`` and ``RecorderSettings``, and each
dataclass's ``from_config`` turns a section back into settings. These tests hold the two directions together: a
configuration with nothing set must give exactly the dataclass's own defaults (a key mapped to the wrong field, or
a unit converted one way and not back, breaks that), and one key set in a file must reach its field, through the
same code the daemon runs (``make_clock``, ``Daemon.__init__``, the navigator's ``NavParams.from_config``).
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from logger.compose import make_clock
from logger.config import FIELD, SCHEMA, Config, defaults, parse
from logger.nav.params import NavParams
from logger.recording.settings import MIB, RecorderSettings
from logger.runtime.daemon import Daemon
from logger.runtime.timebase import host_timebase
from sync.settings import NS_PER_US, SyncSettings

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "systemd" / "logger.toml"


def configured(text: str) -> Config:
    """A validated file; sensors simulated, so no serial port is required (no [nav]/[sync]/[recorder] key changes)."""
    return parse(text, "logger.toml", sim=True)


def sync_settings(cfg: Config, tmp_path: Path) -> SyncSettings:
    """The SyncSettings the daemon's clock gets from ``cfg`` (state kept under ``tmp_path``, not /var/lib)."""
    cfg.values["logger"]["state_dir"] = str(tmp_path)
    return make_clock(cfg, host_timebase(), "").s


def recorder_settings(cfg: Config, tmp_path: Path) -> RecorderSettings:
    """The RecorderSettings ``Daemon.__init__`` builds from ``cfg`` (nothing is started or written)."""
    return Daemon(cfg, [], out_dir=tmp_path).recorder.settings


# ---- nothing set: the dataclasses' own defaults --------------------------------------------------------------
def test_no_key_is_left_with_the_placeholder_default() -> None:
    """FIELD is resolved only inside ``_defaults_from``: a key using it in another section would leak it."""
    assert [f"{s}.{k}" for s, keys in SCHEMA.items() for k, key in keys.items() if key.default is FIELD] == []


def test_nav_defaults_are_navparams_defaults() -> None:
    assert NavParams.from_config(defaults()["nav"]) == NavParams()
    assert NavParams.from_config(configured("")["nav"]) == NavParams()


def test_sync_defaults_are_syncsettings_defaults(tmp_path: Path) -> None:
    cfg = defaults()
    assert SyncSettings.from_config(cfg["sync"], imu_rate_hz=cfg["imu"]["rate_hz"]) == SyncSettings()
    assert sync_settings(defaults(), tmp_path) == SyncSettings()
    assert defaults()["sync"]["pps_latency_us"] == SyncSettings().pps_latency_ns / NS_PER_US


def test_recorder_defaults_are_recordersettings_defaults(tmp_path: Path) -> None:
    assert RecorderSettings.from_config(defaults()["recorder"], tmp_path) == RecorderSettings(out_dir=tmp_path)
    assert recorder_settings(defaults(), tmp_path) == RecorderSettings(out_dir=tmp_path)


def test_defaults_keep_their_configuration_types() -> None:
    """MiB stay whole numbers and vectors lists: ``str()`` of each value goes into every file's metadata."""
    rec, nav = defaults()["recorder"], defaults()["nav"]
    assert type(rec["rotate_size_mb"]) is int and type(rec["min_free_mb"]) is int
    assert type(nav["lever_arm_m"]) is list and type(nav["mounting_rpy_deg"]) is list
    assert defaults()["nav"]["lever_arm_m"] is not defaults()["nav"]["lever_arm_m"]  # no shared mutable default


# ---- one key set: its field, and only its field, changes ------------------------------------------------------
def test_a_nav_key_reaches_its_field() -> None:
    cfg = configured("[nav]\nlever_arm_m = [0.5, 0, -1.25]\n")
    assert NavParams.from_config(cfg["nav"]) == dataclasses.replace(NavParams(), lever_arm_m=(0.5, 0.0, -1.25))


def test_a_sync_key_reaches_its_field_in_ns(tmp_path: Path) -> None:
    cfg = configured("[sync]\npps_latency_us = 12.5\n")
    expected = dataclasses.replace(SyncSettings(), pps_latency_ns=12_500)
    assert SyncSettings.from_config(cfg["sync"], imu_rate_hz=cfg["imu"]["rate_hz"]) == expected
    assert sync_settings(cfg, tmp_path) == expected


def test_the_imu_rate_reaches_the_clock(tmp_path: Path) -> None:
    cfg = configured("[imu]\nrate_hz = 100\n")
    assert sync_settings(cfg, tmp_path) == dataclasses.replace(SyncSettings(), imu_rate_hz=100.0)


def test_a_recorder_key_reaches_its_field_in_bytes(tmp_path: Path) -> None:
    cfg = configured("[recorder]\nrotate_size_mb = 512\n")
    expected = RecorderSettings(out_dir=tmp_path, rotate_size_bytes=512 * MIB)
    assert RecorderSettings.from_config(cfg["recorder"], tmp_path) == expected
    assert recorder_settings(cfg, tmp_path) == expected


# ---- the example configuration shows the defaults -------------------------------------------------------------
def test_example_config_shows_the_defaults() -> None:
    """Its header says "the values shown are the defaults"; keys tests/test_config.py checks are all there.

    Only keys without a default (required for their source: the serial ports) may show something else.
    """
    example = parse(EXAMPLE.read_text(), str(EXAMPLE))
    wrong = [f"{section}.{key} = {example[section][key]!r}, default {value!r}"
             for section, keys in defaults().values.items() for key, value in keys.items()
             if value is not None and example[section][key] != value]
    assert not wrong, "systemd/logger.toml does not show the default of:\n" + "\n".join(wrong)


# ---- the direction the defaults flow in ------------------------------------------------------------------------
@pytest.mark.parametrize(("module", "must_not_load"), [
    ("sync.clock", "logger"),  # the clock is usable without the logger package
    ("logger.nav.params", "logger.config"),  # the configuration imports the tuning, never the reverse
])
def test_settings_modules_do_not_import_the_configuration(module: str, must_not_load: str) -> None:
    code = (f"import sys, {module}\n"
            f"print(sorted(m for m in sys.modules if m == {must_not_load!r} or m.startswith({must_not_load + '.'!r})))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True,
                         timeout=60).stdout.strip()
    assert out == "[]", f"importing {module} loads {out}"
