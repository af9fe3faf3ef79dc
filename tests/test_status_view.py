"""`logger status` on a person's terminal: 80x24 over SSH, the verdict and problems first, rows that agree."""

from __future__ import annotations

import copy

from logger.cli.status_view import COLUMNS, render

LONG_ERROR = ("serial port /dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A50285BI-if00-port0 does not exist: is the "
              "OBD adapter plugged in? (checked /dev/serial/by-id and /dev/ttyUSB*, no ELM327 answered at 38400 baud)")


def _flat(text: str) -> str:
    """The text with its wrapping undone, for sentences whose line breaks depend on the width."""
    return " ".join(line.strip() for line in text.split("\n"))


def _sensor(name: str, state: str = "ok", rate: float | None = 1.0, measured: float | None = 1.0,
            age: float | None = 0.4, **counts: int) -> dict[str, object]:
    return {"name": name, "state": state, "rate_hz": rate, "measured_rate_hz": measured, "last_sample_age_s": age,
            "errors": counts.get("errors", 0), "gaps": counts.get("gaps", 0), "late": counts.get("late", 0),
            "reconnects": counts.get("reconnects", 0), "last_error": "", "origin": "", "incidents": {}}


BUSY = {
    "verdict": "degraded", "uptime_s": 7384, "pid": 4242, "mode": "partly simulated", "t_mono_ns": 90_000_000_000,
    "problems": [f"obd: missing: {LONG_ERROR}", "gnss: no fix for 35 s (0 satellites in use)",
                 "pps: no pulse for 35 s (the receiver pulses only with a fix)",
                 "imu: fifo overflow: 12 samples lost in the last 30 s"],
    "sensors": [_sensor("imu", rate=20, measured=19.9, age=0.02, late=3),
                _sensor("baro"), _sensor("obd", "missing", 2, None, None, errors=1234),
                _sensor("gnss", "no fix"), _sensor("pps", "silent", 1.0, 0.0, 35.2)],
    "gnss": {"fix": "no fix", "num_sv": 0, "h_acc_m": 25.1, "pdop": 99.9, "age_s": 0.3, "last_fix_age_s": 35.2,
             "no_fix_s": 35.2},
    "sync": {"state": "holdover", "err_ns": 48_200, "offset_ns": 1500, "freq_ppm": -26.121, "since_edge_s": 35.2},
    "nav": {"lat_deg": 37.5596131, "lon_deg": 126.9996644, "height_m": 62.7, "sigma_h_m": 9.7,
            "source": "ins 17-state", "mode": "17", "age_s": 1.4,
            "verdicts": ["no GNSS fix for 35 s: dead reckoning on IMU and baro (no OBD)",
                         "no OBD speed: the filter runs without the vehicle's speed",
                         "barometer offset stable: +96.9 m (+-0.2 m), -0.17 m/min",
                         "IMU offsets within the datasheet: accel <= 47 mg, gyro <= 3.21 deg/s",
                         "IMU mounting plausible (levelled at roll +3.8 deg, pitch +0.3 deg)",
                         "filter restarted from GNSS 2 times (lost itself)"]},
    "recorder": {"state": "recording", "file": "/var/lib/vehicle-logger/drives/drive_20261201T220721Z_0001.mcap",
                 "file_bytes": 123_400_000, "free_bytes": 3_100_000_000, "written": {"/imu": 147_000},
                 "dropped": {}, "queue_depth": 12, "queue_size": 20000, "on_disk_mono_ns": {"/imu": 89_600_000_000}},
}
BUSY["sensors"][0]["incidents"] = {"fifo overflow": 3}
BUSY["sensors"][0]["samples_lost"] = 1234
BUSY["sensors"][3]["origin"] = "serial /dev/serial/by-id/usb-u-blox_AG_-_www.u-blox.com_u-blox_GNSS_receiver-if00"


def test_an_ok_beside_sensors_still_starting_says_so_on_its_line() -> None:
    """At start the verdict is ok while a sensor still opens (no fault: an ELM327's search takes seconds): the first
    line said "logger OK" alone, beside a row saying starting."""
    snap = {"verdict": "ok", "uptime_s": 2, "pid": 7, "problems": [],
            "sensors": [_sensor("imu", "ok", 20, 20.0, 0.1), _sensor("gnss", "starting", 1, None, None),
                        _sensor("obd", "starting", 2, None, None)]}
    first = render(snap, width=80).split("\n")[0]
    assert first.startswith("logger OK   up 0h00m02s   pid 7") and first.endswith("starting: gnss, obd")
    assert "starting" not in render({**snap, "sensors": snap["sensors"][:1]}, width=80).split("\n")[0]


def test_every_line_fits_80_columns_and_24_rows_with_the_verdict_and_problems_on_screen() -> None:
    full = render(BUSY, width=80).split("\n")
    assert max(map(len, full)) <= 79  # the last column wraps on a real terminal
    # Out of lock, how long since the last PPS edge the clock used goes with the state ("PPS 35 s ago" read as the
    # last pulse while the pps row showed pulses coming that the clock could not label).
    assert "clock   holdover for 35 s, error bound 48.2 us, offset +1.5 us, -26.12 ppm" in full
    assert len(full) > 23  # this snapshot does not fit as a whole, so the screen has to choose
    screen = render(BUSY, width=80, height=23).split("\n")
    assert len(screen) == 23 and max(map(len, screen)) <= 79
    assert screen[0].startswith("logger DEGRADED   up 2h03m04s   pid 4242")
    problem_lines = [line for line in screen if line.startswith("! ")]
    assert [line.split(":")[0] for line in problem_lines] == ["! obd", "! gnss", "! pps", "! imu"]
    # The long error wraps under its own indent, whole.
    assert "is the OBD adapter plugged in?" in _flat("\n".join(screen))
    for name in ("imu", "baro", "obd", "gnss", "pps"):
        assert any(line.startswith(f"{name:<7} ") for line in screen), name
    assert any(line.startswith("gnss    no fix") for line in screen)
    assert any(line.startswith("clock   holdover") for line in screen)
    assert any(line.startswith("nav     37.5596131") for line in screen)
    # How old the position is, on its row (the published solution is up to a wake and a publish period old).
    assert any(line.startswith("nav     37.5596131") and ", 1.4 s ago" in line for line in screen)
    assert any(line.startswith("rec     recording drive_20261201T220721Z_0001.mcap") for line in screen)
    # What went to make room: where the data come from and the per-incident totals first, then the last verdicts.
    assert not any(line.startswith(("source ", "imu     fifo overflow: 3 since start")) for line in screen)
    # The samples those overflows destroyed, in all (the incident's line says only the last 30 s'), on the full view.
    assert "imu     samples lost (FIFO overflows, reopenings): 1234 since start" in full
    assert "filter restarted from GNSS 2 times" not in "\n".join(screen)


def test_rows_agree_with_the_problems_and_say_what_is_not_known() -> None:
    text = render(BUSY, width=80)
    lines = text.split("\n")
    header = next(i for i, line in enumerate(lines) if line.startswith("sensor  state"))
    rows = {line.split()[0]: line for line in lines[header + 1:header + 6]}
    assert rows["obd"].split()[1:3] == ["missing", "-/2"]  # no current rate for a sensor that is not running
    assert rows["pps"].split()[1:4] == ["silent", "0.0/1", "35"]
    assert rows["gnss"].split()[1:3] == ["no", "fix"]
    assert "gnss    no fix, 0 satellites, last fix 35 s ago, reported 0.3 s ago" in text
    free = copy.deepcopy(BUSY)
    free["sync"] = {"state": "freerun", "err_ns": 10_000_000_000}
    assert "clock   freerun, error bound unknown" in render(free)
    fixed = copy.deepcopy(BUSY)
    fixed["gnss"] = {"fix": "3D", "num_sv": 18, "h_acc_m": 1.24, "pdop": 1.31, "age_s": 0.4, "last_fix_age_s": 0.4,
                     "no_fix_s": None}
    assert "gnss    3D, 18 satellites, hAcc 1.2 m, PDOP 1.3, reported 0.4 s ago" in render(fixed)


def test_before_the_first_solution_the_nav_row_says_what_the_start_waits_for() -> None:
    snap = copy.deepcopy(BUSY)
    snap["nav"] = {"lat_deg": None, "mode": "17", "verdicts": [
        "initialising: levelling the IMU (6 s standing); waiting for the car to move to find the heading"]}
    text = render(snap, width=80)
    assert "nav     initialising: levelling the IMU (6 s standing);" in text
    assert "initialising: levelling the IMU (6 s standing); waiting for the car to move to find the heading" \
        in _flat(text)
    assert max(map(len, text.split("\n"))) <= 79


def test_help_explains_every_column() -> None:
    for column in ("state", "rate Hz", "last", "errors", "gaps", "late", "reconn", "gnss", "clock", "nav", "rec"):
        assert f"\n  {column} " in COLUMNS, column


def test_long_ages_keep_their_unit_and_a_silent_receiver_is_not_shown_as_fixed() -> None:
    from logger.cli.status_view import age

    assert [age(s) for s in (None, -0.01, 0.42, 35.2, 725.0, 7300.0)] == [
        "never", "0.0 s", "0.4 s", "35 s", "12 min", "2.0 h"]
    snap = copy.deepcopy(BUSY)
    snap["gnss"] = {"fix": "3D", "num_sv": 18, "h_acc_m": 1.2, "pdop": 1.3, "age_s": 40.0, "last_fix_age_s": 40.0,
                    "no_fix_s": None}
    text = render(snap)
    assert "gnss    nothing from the receiver for 40 s (its last report: 3D)" in text
    assert "18 satellites" not in text


def test_the_rec_row_says_where_recording_stopped_and_sizes_a_reader_can_use() -> None:
    """The review's disk-full screen: `rec disk-full drive_..._0001.mcap, 0.0 MB` for a 396 KiB file no longer
    written, "0.0 GB free" with 984 KiB left, "0 dropped" while 80 s went unrecorded."""
    import copy

    snap = copy.deepcopy(BUSY)
    snap["t_mono_ns"] = 100_000_000_000
    snap["recorder"].update(state="disk-full", file_bytes=405_504, free_bytes=984 * 1024,
                            state_since_mono_ns=55_000_000_000, down_s=80.0, unrecorded={"/imu": 1600},
                            lost={"/imu": 40})
    screen = render(snap, width=80).split("\n")
    assert max(map(len, screen)) <= 79
    i = next(i for i, line in enumerate(screen) if line.startswith("rec "))
    assert screen[i] == "rec     disk-full 45 s, stopped at drive_20261201T220721Z_0001.mcap 396 KiB"
    assert screen[i + 1] == "        984 KiB free, nothing is being written"
    assert "        not recorded for 80 s: 1600 records; 40 lost in failed writes" in screen
    snap["recorder"]["deleted"] = {"/imu/batch": 1234567}  # a folder deleted under the recorder
    screen = render(snap, width=80).split("\n")
    assert max(map(len, screen)) <= 79
    assert "        1234567 on disk, then deleted with their file or folder" in screen
    snap["recorder"].update(state="recording", free_bytes=3_100_000_000, file_bytes=123_400_000)
    assert "rec     recording drive_20261201T220721Z_0001.mcap 118 MiB, 2.9 GiB free" in render(snap).split("\n")
