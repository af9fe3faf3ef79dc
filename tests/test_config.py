"""Configuration: every mistake a person makes gets one line naming the key and its line."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from logger.config import ConfigError, defaults, load, parse

GOOD = """\
# a board with everything attached
[logger]
out_dir = "/data/drives"

[imu]
bus = 2
address = 0x68
rate_hz = 200

[obd]
source = "elm327"
port = "/dev/ttyUSB0"

[gnss]
port = "/dev/ttyACM0"
baud = 115200
"""


def _problems(text: str) -> list[str]:
    with pytest.raises(ConfigError) as err:
        parse(text, "logger.toml")
    return err.value.problems


def test_good_file_fills_defaults() -> None:
    cfg = parse(GOOD, "logger.toml")
    assert cfg["imu"]["rate_hz"] == 200.0 and cfg["imu"]["gyro_range_dps"] == 500
    assert cfg["baro"]["address"] == 0x77
    assert "imu.rate_hz" in cfg.explicit and "imu.gyro_range_dps" not in cfg.explicit


def test_unknown_key_names_key_line_and_suggests() -> None:
    (msg,) = _problems(GOOD.replace("rate_hz = 200", "rat_hz = 200"))
    assert msg == "logger.toml:8: unknown key imu.rat_hz (did you mean imu.rate_hz?)"


def test_a_key_before_any_section_is_said_so_with_its_section() -> None:
    """``out_dir = ...`` on the first line, above [logger]: it was "unknown section [out_dir]"."""
    for text, said in (('out_dir = "/media/drives"\n[sim]\nseed = 2\n', "out_dir is outside any section (it "
                        "belongs under [logger])"),
                       ('port = "/dev/x"\n', "port is outside any section (a key of [obd], [gnss])"),
                       ("whatever = 3\n", "whatever is outside any section")):
        with pytest.raises(ConfigError) as exc:
            parse(text, "logger.toml", sim=True)
        assert exc.value.problems == [f"logger.toml:1: {said}"], exc.value.problems


def test_unknown_section() -> None:
    (msg,) = _problems(GOOD + "\n[gps]\nport = '/dev/ttyS1'\n")
    assert msg.startswith("logger.toml:18: unknown section [gps]")


def test_wrong_type() -> None:
    (msg,) = _problems(GOOD.replace("rate_hz = 200", 'rate_hz = "fast"'))
    assert msg == "logger.toml:8: imu.rate_hz must be a number, not 'fast'"


def test_who_am_i_takes_a_clones_and_refuses_another_parts() -> None:
    assert parse(GOOD.replace("address = 0x68", "address = 0x68\nwho_am_i = 0x98"), "logger.toml")["imu"][
        "who_am_i"] == 0x98
    assert _problems(GOOD.replace("address = 0x68", "address = 0x68\nwho_am_i = 0x70")) == [
        "logger.toml:8: imu.who_am_i = 0x70 is an MPU-6500's: another register map, FIFO and temperature scale, "
        "which the logger cannot read"]


def test_a_key_of_another_section_says_where_it_belongs() -> None:
    assert _problems(GOOD.replace("baud = 115200", "baud = 115200\nsea_level_pa = 101800.0")) == [
        "logger.toml:17: unknown key gnss.sea_level_pa (it belongs under [baro])"]


def test_bad_address_and_out_of_range_reported_together() -> None:
    problems = _problems(GOOD.replace("address = 0x68", "address = 0x90").replace("rate_hz = 200", "rate_hz = 5000"))
    assert problems == [
        "logger.toml:7: imu.address = 0x90 is not a 7-bit I2C device address (0x03..0x77)",
        "logger.toml:8: imu.rate_hz = 5000 must be between 1 and 1000",
    ]


def test_a_path_holding_a_nul_is_refused_by_the_check_not_by_a_traceback_in_run() -> None:
    (msg,) = _problems(GOOD.replace('out_dir = "/data/drives"', 'out_dir = "/data/\\u0000drives"'))
    assert msg == "logger.toml:3: logger.out_dir = '/data/\\x00drives' must not hold a NUL character"


def test_missing_device_path() -> None:
    (msg,) = _problems(GOOD.replace('port = "/dev/ttyUSB0"\n', ""))
    assert msg == "logger.toml:11: obd.port is required when obd.source = 'elm327'"


def test_toml_syntax_error_has_a_line() -> None:
    (msg,) = _problems(GOOD.replace("bus = 2", "bus = = 2"))
    assert msg.startswith("logger.toml:6: not valid TOML")


def test_sim_defaults_need_no_file() -> None:
    cfg = defaults(sim=True)
    assert {cfg[s]["source"] for s in ("imu", "baro", "obd", "gnss", "pps")} == {"sim"}


def test_world_writable_file_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "logger.toml"
    p.write_text(GOOD)
    os.chmod(p, 0o666)
    with pytest.raises(ConfigError, match="world-writable"):
        load(p)
    os.chmod(p, 0o640)
    assert load(p)["gnss"]["baud"] == 115200


def test_missing_file() -> None:
    with pytest.raises(ConfigError, match="no such configuration file"):
        load("/nonexistent/logger.toml")


def test_example_config_in_systemd_is_valid_and_documents_every_key(tmp_path: Path) -> None:
    from logger.config import SCHEMA

    example = Path(__file__).resolve().parents[1] / "systemd" / "logger.toml"
    cfg = parse(example.read_text(), str(example))
    for section, keys in SCHEMA.items():
        for key in keys:
            assert f"{section}.{key}" in cfg.explicit, f"{section}.{key} missing from the example"


def test_config_check_command(tmp_path: Path, capsys) -> None:
    from logger.cli import main

    p = tmp_path / "logger.toml"
    p.write_text(GOOD.replace("rate_hz = 200", "rat_hz = 200").replace("bus = 2", "bus = 'two'"))
    assert main(["config", "check", str(p)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "imu.bus must be an integer" in err[0] and "imu.rat_hz" in err[1]
    p.write_text(GOOD)
    assert main(["config", "check", str(p)]) == 0
    # A file for a simulated run holds what it changes only: a board needs its ports, a simulated run does not.
    capsys.readouterr()
    p.write_text("[recorder]\nrotate_duration_s = 600\n")
    assert main(["config", "check", str(p)]) == 1
    assert "obd.port is required" in capsys.readouterr().err
    assert main(["config", "check", "--sim", str(p)]) == 0
    # As `logger run --sim --config` takes it: a sensor's section without its port is simulated, not refused.
    p.write_text('[gnss]\nsource = "serial"\nbaud = 115200\n')
    capsys.readouterr()
    assert main(["config", "check", "--sim", str(p)]) == 0
    assert "gnss=sim" in capsys.readouterr().out


def test_run_refuses_bad_numbers_on_its_command_line_in_one_line(tmp_path: Path, capsys) -> None:
    """--seed -1 reached numpy (a ValueError traceback) and --duration nan passed the positive check."""
    from logger.cli import main

    common = ["--out", str(tmp_path / "d"), "--status-socket", str(tmp_path / "s.sock")]
    assert main(["run", "--sim", "--seed", "-1", *common]) == 2
    assert capsys.readouterr().err.startswith("logger: --seed -1 must be between 0 and 4294967295")
    assert main(["run", "--sim", "--duration", "nan", *common]) == 2
    assert capsys.readouterr().err == "logger: --duration must be a positive number of seconds\n"
    assert not (tmp_path / "d").exists()


def test_run_refuses_a_bad_config_with_one_line_per_problem(tmp_path: Path, capsys) -> None:
    from logger.cli import main

    p = tmp_path / "logger.toml"
    p.write_text(GOOD.replace("address = 0x68", "address = 0x90").replace('port = "/dev/ttyUSB0"\n', ""))
    assert main(["run", "--config", str(p)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"logger: {p}:7: imu.address = 0x90 is not a 7-bit I2C device address (0x03..0x77)",
                   f"logger: {p}:11: obd.port is required when obd.source = 'elm327'"]
    assert not (tmp_path / "drives").exists()


def test_time_scale_needs_every_sensor_simulated(tmp_path: Path, capsys) -> None:
    from logger.cli import main

    p = tmp_path / "logger.toml"
    p.write_text(GOOD + "\n[sim]\ntime_scale = 10\n")
    assert main(["run", "--config", str(p)]) == 2
    assert "needs every sensor simulated" in capsys.readouterr().err
    # `config check` says so too: a file it passes must not stop the service (a mix of simulated and real sensors)
    mixed = tmp_path / "mixed.toml"
    mixed.write_text('[imu]\nsource = "sim"\n[baro]\nsource = "sim"\n[gnss]\nsource = "sim"\n[pps]\nsource = "sim"\n'
                     '[obd]\nport = "/dev/ttyUSB0"\n[sim]\ntime_scale = 2\n')
    assert main(["config", "check", str(mixed)]) == 1
    assert capsys.readouterr().err == (f"{mixed}:12: sim.time_scale = 2 needs every sensor simulated; real: obd\n")
    assert main(["run", "--config", str(mixed)]) == 2


def test_files_too_long_for_the_boards_memory_are_refused() -> None:
    # A day per file at the default 1 s flush: 86400 chunk indexes held in memory until the file closes.
    with pytest.raises(ConfigError) as err:
        parse("[recorder]\nrotate_duration_s = 86400\n", "logger.toml", sim=True)
    (msg,) = err.value.problems
    assert msg.startswith("logger.toml:2: recorder.rotate_duration_s / flush_interval_s makes 86400 chunks per file")
    cfg = parse("[recorder]\nrotate_duration_s = 86400\nflush_interval_s = 10\n", "logger.toml", sim=True)
    assert cfg["recorder"]["rotate_duration_s"] == 86400


def test_the_imu_is_read_through_its_fifo_unless_told_and_register_reads_stop_at_50_hz() -> None:
    """The FIFO by default at every rate; a read per sample where asked, at the rates a thread per sample keeps."""
    from logger.compose import plans_from_config
    from logger.runtime.sources import FIFO_FRAMES, fifo_poll_hz
    from logger.runtime.timebase import TimeBase
    from sensors.sim.vehicle import VehicleDevices

    cfg = parse("", "logger.toml", sim=True)
    assert cfg["imu"]["read"] == "fifo"
    (imu, *_) = plans_from_config(cfg, TimeBase(), VehicleDevices())
    assert imu.source.fifo and imu.rate_hz == 2.0  # 20 Hz in reads of ten samples
    # ... every half second, or twice per filling of the 85-frame FIFO where that is more often
    assert [fifo_poll_hz(hz) for hz in (50, 100, 200, 500, 1000)] == [2.0, 2.5, 5.0, 12.5, 25.0]
    assert all(FIFO_FRAMES / hz >= 2 / fifo_poll_hz(hz) for hz in (20, 50, 80, 100, 200, 500, 1000))
    cfg = parse('[imu]\nread = "register"\nrate_hz = 50\n', "logger.toml", sim=True)
    (imu, *_) = plans_from_config(cfg, TimeBase(), VehicleDevices())
    assert not imu.source.fifo and imu.rate_hz == 50.0
    with pytest.raises(ConfigError) as err:
        parse('[imu]\nrate_hz = 200\nread = "register"\n', "logger.toml", sim=True)
    (msg,) = err.value.problems
    assert msg == ("logger.toml:3: imu.read = 'register' reads a sample at a time, at most 50 Hz, and imu.rate_hz is "
                   "200: use read = 'fifo' or a lower rate")
    with pytest.raises(ConfigError) as err:
        parse('[imu]\nread = "burst"\n', "logger.toml", sim=True)
    assert err.value.problems == ["logger.toml:2: imu.read = 'burst' must be one of 'fifo', 'register'"]


def test_chrony_is_only_given_real_time(tmp_path: Path) -> None:
    """The PPS edges go to chrony only from a real receiver and PPS line at real time: config check and run agree."""
    from logger.cli.run import parse_args, resolve_config

    real = ('[obd]\nsource = "can"\n[gnss]\nsource = "serial"\nport = "/dev/ttyACM0"\n[pps]\nsource = "gpio"\n'
            '[sync]\nchrony_sock = "/run/chrony.pps.sock"\n')
    assert parse(real, "logger.toml").values["sync"]["chrony_sock"] == "/run/chrony.pps.sock"
    with pytest.raises(ConfigError) as e:
        parse(real.replace('[pps]\nsource = "gpio"', '[pps]\nsource = "sim"'), "logger.toml")
    assert e.value.problems == ["logger.toml:9: sync.chrony_sock is set while pps is simulated: chrony would be "
                                "given the simulation's time (leave chrony_sock empty for simulated runs)"]
    cfg = tmp_path / "logger.toml"
    cfg.write_text(real)
    cfg.chmod(0o640)
    with pytest.raises(ConfigError) as e:  # the file is fine; `--sim` simulates the sensors it leaves out
        resolve_config(parse_args(["--config", str(cfg), "--sim"]))
    (problem,) = e.value.problems
    assert problem.endswith("sync.chrony_sock is set while imu and baro are simulated: the run's clock is then the "
                            "simulated board's, not the host's, and chrony would be given its offset as the clock's "
                            "error (leave chrony_sock empty for simulated runs)"), problem
    # A real receiver and PPS beside a simulated IMU: the run's clock is the simulated board's, a few ms from the
    # host's, and real edges reached chrony off by that (2.7 ms, behind an 11 us bound).
    with pytest.raises(ConfigError) as e:
        parse(real.replace('[obd]\nsource = "can"', '[imu]\nsource = "sim"\n[obd]\nsource = "can"'), "logger.toml")
    (problem,) = e.value.problems
    assert problem.endswith("sync.chrony_sock is set while imu is simulated: the run's clock is then the simulated "
                            "board's, not the host's, and chrony would be given its offset as the clock's error "
                            "(leave chrony_sock empty for simulated runs)"), problem


def test_what_toml_itself_refuses_is_said_in_the_configuration_s_terms() -> None:
    def problems(text: str) -> list[str]:
        with pytest.raises(ConfigError) as e:
            parse(text, "logger.toml", sim=True)
        return e.value.problems

    assert problems("[imu]\nrate_hz = 20\nrate_hz = 30\n") == [
        "logger.toml:3: imu.rate_hz is set twice (a key may be given once)"]
    assert problems("[imu]\nrate_hz = 20\n[imu]\nrate_hz = 5\n") == [
        "logger.toml:3: [imu] appears twice (give each section once, with all its keys)"]
    assert problems("x = " + "[" * 600 + "]" * 600) == [
        "logger.toml: not a configuration: arrays or tables nested hundreds deep"]
    assert problems('[sim]\nscenario = "moon"\n') == [
        "logger.toml:2: sim.scenario = 'moon' must be one of 'urban', 'outage-60s', 'tunnel-130s'"]
    assert problems("[pps]\nline = -1\n") == ["logger.toml:2: pps.line = -1 must be a line offset of 0 or more "
                                              "(or a line name)"]
    # A byte-order mark (some editors on Windows write one) is no part of the file's TOML.
    assert parse("\ufeff[imu]\nrate_hz = 50\n", "logger.toml", sim=True).values["imu"]["rate_hz"] == 50
    assert parse('[pps]\nline = "P9_12"\n', "logger.toml", sim=True).values["pps"]["line"] == "P9_12"


def test_the_scenario_names_the_configuration_checks_are_the_simulator_s() -> None:
    from sensors.sim.scenarios import SCENARIOS, make_drive

    for name in SCENARIOS:
        assert parse(f'[sim]\nscenario = "{name}"\n', "x", sim=True).values["sim"]["scenario"] == name
        assert make_drive(name, seed=1, duration_s=60.0).name == name


def test_the_receivers_rate_reaches_its_set_up() -> None:
    """[gnss] rate_hz is what the set-up asks of a real receiver (and what the status expects of it)."""
    from logger.compose import plans_from_config
    from logger.runtime.timebase import TimeBase

    for text, period_ms, expected_hz in (("", 1000, 1.0), ("rate_hz = 5\n", 200, 5.0), ("rate_hz = 25\n", 40, 25.0)):
        cfg = parse(GOOD.replace('baud = 115200\n', f"baud = 115200\n{text}"), "logger.toml")
        (gnss,) = [p for p in plans_from_config(cfg, TimeBase()) if p.source.name == "gnss"]
        assert gnss.source.meas_period_ms == period_ms and gnss.expected_hz == expected_hz
    (msg,) = _problems(GOOD.replace('baud = 115200\n', "baud = 115200\nrate_hz = 3\n"))
    assert msg == "logger.toml:17: gnss.rate_hz = 3 must be one of 1, 2, 4, 5, 8, 10, 20, 25"


def test_a_socket_path_too_long_and_an_empty_can_interface_are_refused_by_the_check() -> None:
    """A status socket's path over the 107 bytes bind() takes left the logger without its socket (and without the
    one-logger check it makes) after `config check` said OK; an empty CAN interface was taken too."""
    long_path = "/run/" + "x" * 100 + "/status.sock"
    (msg,) = _problems(GOOD.replace('out_dir = "/data/drives"',
                                    f'out_dir = "/data/drives"\nstatus_socket = "{long_path}"'))
    assert msg.endswith(f": logger.status_socket = {long_path!r} is {len(long_path)} bytes long: a Unix socket's "
                        "path holds 107 at most"), msg
    (msg,) = _problems(GOOD.replace('source = "elm327"\nport = "/dev/ttyUSB0"', 'source = "can"\nchannel = ""'))
    assert msg.endswith("obd.channel = '' must be a network interface's name (1 to 15 characters, no '/' or "
                       "space), such as can0"), msg
    assert parse(GOOD.replace('source = "elm327"\nport = "/dev/ttyUSB0"', 'source = "can"\nchannel = "can1"'),
                 "logger.toml")["obd"]["channel"] == "can1"


def test_a_folder_named_by_a_file_is_said_by_the_check_and_by_run(tmp_path: Path, capsys) -> None:
    from logger.cli import main

    a_file = tmp_path / "notes.txt"
    a_file.write_text("not a folder")
    p = tmp_path / "logger.toml"
    p.write_text(f'[logger]\nout_dir = "{a_file}"\n')
    p.chmod(0o640)
    assert main(["config", "check", "--sim", str(p)]) == 1
    assert capsys.readouterr().err == f"{p}: logger.out_dir = {str(a_file)!r} exists and is not a folder\n"
    assert main(["run", "--sim", "--config", str(p), "--duration", "1"]) == 1
    assert capsys.readouterr().err.endswith(f"logger: cannot make the output folder {a_file}: exists and is not a "
                                            "folder\n")
    # A folder under a path that cannot hold one: named as the output folder.
    p.write_text(f'[logger]\nout_dir = "{a_file}/drives"\n')
    assert main(["run", "--sim", "--config", str(p), "--duration", "1"]) == 1
    assert capsys.readouterr().err.endswith(f"logger: cannot make the output folder {a_file}/drives: Not a "
                                            "directory\n")


def test_a_rinex_receiver_name_is_ascii() -> None:
    """convbin cuts a RINEX header field at 20 bytes: 20 'Ä' (40 bytes of UTF-8) went in as 10 of them, in a header
    that is ASCII by the format."""
    (msg,) = _problems(GOOD.replace('baud = 115200', 'baud = 115200\nreceiver_name = "ÄÄÄÄ/NEO-M8T/1.0"'))
    assert "gnss.receiver_name" in msg and msg.endswith("ASCII only (a RINEX header is ASCII)"), msg
    assert parse(GOOD.replace('baud = 115200', 'baud = 115200\nreceiver_name = "SN42/NEO-M8T/TIM 1.10"'),
                 "logger.toml")["gnss"]["receiver_name"] == "SN42/NEO-M8T/TIM 1.10"


def test_a_slow_elm327_clone_gets_the_answer_timeout_the_file_gives() -> None:
    """A Bluetooth clone answers some commands after more than the default second: [obd] answer_timeout_s reaches
    the adapter's driver (there was no way to give it)."""
    from logger.compose import plans_from_config
    from logger.runtime.timebase import TimeBase
    from sensors.sim.vehicle import VehicleDevices

    cfg = parse(GOOD.replace('port = "/dev/ttyUSB0"', 'port = "/dev/ttyUSB0"\nanswer_timeout_s = 2.5'),
                "logger.toml")
    (obd,) = [p for p in plans_from_config(cfg, TimeBase(), VehicleDevices()) if p.source.name == "obd"]
    assert obd.source.make_driver().timeout_s == 2.5
    (msg,) = _problems(GOOD.replace('port = "/dev/ttyUSB0"', 'port = "/dev/ttyUSB0"\nanswer_timeout_s = 0'))
    assert "obd.answer_timeout_s = 0" in msg, msg


def test_checking_the_example_configuration_loads_no_numpy() -> None:
    """``logger config check`` and ``logger status --config`` (an operator's SSH session, on the board's one core)
    check ``[imu] rate_hz`` against the chip's dividers: that check once imported the driver, and numpy with it
    (137 ms and 12 MB here, several times that on the board)."""
    import subprocess
    import sys

    example = Path(__file__).parent.parent / "systemd" / "logger.toml"
    code = ("import sys; from logger.config import load; load(sys.argv[1]); "
            "print('numpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(example)], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out
