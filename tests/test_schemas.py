"""Every recorded message matches the JSON schema its own file embeds for its channel.

A reader that knows nothing of this project (Foxglove, a script in another language) has only the schema in the
file to go by, so the test reads the file as such a reader would: the ``mcap`` package's reader, the schema record
of each message's channel, and ``jsonschema`` to validate the message against it. The drives are the real daemon
on the simulated vehicle, one per scenario and per profile in ``DRIVES``, and ``logger replay``'s
``trajectory.mcap`` of each; the record builders are also checked directly with what real receivers send (the
GPSD project's u-blox captures, NMEA-only ones among them) and with every optional value missing.
"""

from __future__ import annotations

import functools
import json
import math
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from extras import optional
from helpers_drive import drive_timeout
from mcap.reader import make_reader

import logger.recording.recorder as recorder_module
from logger.cli.gnss_decode import decode_pieces, strip_capture_comments
from logger.recording.files import recover
from logger.recording.recorder import Recorder
from logger.recording.records import location_fix, nav_fix_record, stamped_record, timepulse_record
from logger.recording.settings import RecorderSettings
from logger.recording.topics import GNSS_FIX, GNSS_RAW, IMU, IMU_BATCH, NAV_FIX, TIMEPULSE, TOPICS
from sensors.gpsd_decode import fix_from_tpv
from sensors.sim.scenario_names import SCENARIOS
from sensors.ublox_decode import GnssFix, TimePulse
from sync.stamp import Stamp

jsonschema, needs_jsonschema = optional("jsonschema")
ROOT = Path(__file__).resolve().parents[1]
CAPTURES = ROOT / "tests" / "data" / "gpsd-ublox"  # the GPSD project's captures (BSD-2, COPYING there)
DURATION_S = 30  # long enough for the filter to start (about 15 s in) and publish /nav/fix for a while
TIME_SCALE = 5


@dataclass(frozen=True)
class Drive:
    """One simulated drive: a scenario, a profile as the configuration text it needs (none: ``--sim`` alone), and
    the topics that profile does not record.

    The configuration is given as ``--config`` with a ``[logger]`` section naming a state folder of the test's own
    put in front, so a profile is one more line in ``DRIVES`` (for example
    ``Drive("nmea", config='[sim]\\nreceiver = "nmea"\\n', absent=(TIMEPULSE,))``).
    """

    name: str
    scenario: str = "urban"
    config: str = ""
    absent: tuple[str, ...] = (IMU,)  # the IMU is read through its FIFO: a /imu/batch record per read, no /imu


DRIVES = [
    *(Drive(scenario, scenario) for scenario in SCENARIOS),
    # The receiver read through gpsd (a simulated gpsd fed by the simulated receiver): its TPV and SKY reports.
    Drive("gpsd", config='[gnss]\nsource = "gpsd"\n[pps]\nsource = "gpsd"\n[obd]\nsource = "sim"\n',
          absent=(GNSS_RAW, TIMEPULSE, IMU)),
    # The IMU read a register burst per sample: one /imu record per sample instead of /imu/batch per read.
    Drive("imu-register", config='[imu]\nread = "register"\n', absent=(IMU_BATCH,)),
]


# ---- reading a file as any reader would ------------------------------------------------------------------------
def strict_json(data: bytes) -> Any:
    """JSON as the standard defines it: Python's own parser also takes NaN and Infinity, which no JSON is."""

    def refuse(name: str) -> Any:
        raise ValueError(f"{name} is not JSON")

    return json.loads(data, parse_constant=refuse)


def schema_problems(path: Path) -> tuple[Counter[str], list[str]]:
    """Messages per topic in the file, and one line per (topic, problem) of a message against its channel's schema,
    with how many messages had it."""
    counts: Counter[str] = Counter()
    problems: Counter[str] = Counter()
    validators: dict[int, Any] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            counts[channel.topic] += 1
            if schema is None or schema.encoding != "jsonschema" or channel.message_encoding != "json":
                problems[f"{channel.topic}: no JSON schema for its JSON messages"] += 1
                continue
            validator = validators.get(schema.id)
            if validator is None:
                body = strict_json(schema.data)
                cls = jsonschema.validators.validator_for(body)
                cls.check_schema(body)
                validator = validators[schema.id] = cls(body)
            try:
                msg = strict_json(message.data)
            except ValueError as exc:
                problems[f"{channel.topic}: {exc}"] += 1
                continue
            for err in validator.iter_errors(msg):
                where = "".join(f"[{p!r}]" for p in err.absolute_path)
                problems[f"{channel.topic}{where}: {err.message}"] += 1
    return counts, [f"{text} ({n} messages)" for text, n in sorted(problems.items())]


def assert_own_schemas(path: Path) -> set[str]:
    """Each channel points at its own topic's schema (two topics sharing a schema name, foxglove.LocationFix, still
    have a schema record each); returns the topics."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    for ch in summary.channels.values():
        schema = summary.schemas[ch.schema_id]
        assert (schema.name, json.loads(schema.data)) == (TOPICS[ch.topic].schema_name, TOPICS[ch.topic].schema), \
            ch.topic
    return {ch.topic for ch in summary.channels.values()}


# ---- the drives --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module", params=DRIVES, ids=[d.name for d in DRIVES])
def recorded(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[Drive, list[Path]]:
    drive: Drive = request.param
    out = tmp_path_factory.mktemp(drive.name)
    args = ["--sim", "--scenario", drive.scenario, "--duration", str(DURATION_S), "--time-scale", str(TIME_SCALE),
            "--out", str(out / "drive"), "--status-socket", str(out / "status.sock")]
    if drive.config:
        cfg = out / "logger.toml"
        cfg.write_text(f'[logger]\nstate_dir = "{out / "state"}"\n{drive.config}')
        args += ["--config", str(cfg)]
    r = subprocess.run([sys.executable, "-m", "logger.cli", "run", *args], cwd=ROOT, capture_output=True, text=True,
                       timeout=drive_timeout(DURATION_S))
    assert r.returncode == 0, r.stderr
    files = sorted((out / "drive").glob("*.mcap"))
    assert files
    return drive, files


def test_every_scenario_is_driven() -> None:
    """A scenario added to the simulator is a drive of this test, whatever profiles are listed beside it."""
    assert set(SCENARIOS) <= {d.scenario for d in DRIVES}


@pytest.mark.slow_on_board
@needs_jsonschema
def test_every_message_of_a_drive_matches_its_channels_schema(recorded: tuple[Drive, list[Path]]) -> None:
    drive, files = recorded
    counts: Counter[str] = Counter()
    for path in files:
        got, problems = schema_problems(path)
        assert not problems, f"{drive.name}, {path.name}:\n" + "\n".join(problems)
        counts += got
        assert_own_schemas(path)
    # What the drive must have shown for the check to mean anything: every topic its profile records (sensors, the
    # clock, the health reports, the truth), and the filter's live output (it starts about 15 s into every scenario).
    assert set(counts) == set(TOPICS) - set(drive.absent), sorted(set(TOPICS) ^ set(counts))
    assert counts[NAV_FIX] >= 5, counts


@needs_jsonschema
def test_replayed_trajectory_matches_its_schemas(recorded: tuple[Drive, list[Path]], tmp_path: Path) -> None:
    _, files = recorded
    r = subprocess.run([sys.executable, "-m", "logger.cli", "replay", *map(str, files), "--out", str(tmp_path)],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    counts, problems = schema_problems(tmp_path / "trajectory.mcap")
    assert not problems, "\n".join(problems)
    # /nav/fix at the live rate (5 Hz) over the ~15 s the filter runs; every row is the CSV's (and --fix-hz 0's).
    assert counts[NAV_FIX] > 40 and counts["/nav/state"] >= 5, counts


# ---- the record builders -------------------------------------------------------------------------------------
STAMP = Stamp(t_sync_ns=1_700_000_000_000_000_000, state="locked", err_ns=1_000, imu_cnt=3, timer_cnt=0)


@functools.cache
def validator(topic: str) -> Any:
    schema = TOPICS[topic].schema
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema)


def validate(topic: str, payload: dict[str, Any]) -> None:
    """A sensor payload as the daemon records it (stamped), through JSON and back, against the topic's schema."""
    record = strict_json(json.dumps(stamped_record(1_000, STAMP, 0, payload), allow_nan=False))
    validator(topic).validate(record)


def nmea_fix(**changes: Any) -> GnssFix:
    """What an NMEA-only receiver gives (the paper's AEK-4T: GGA, RMC, GSA): no vertical velocity, no accuracy, no
    GPS time of week."""
    fields: dict[str, Any] = {
        "source": "NMEA", "itow_ms": None, "week": None, "time_utc_ns": 1_700_000_000_000_000_000,
        "time_valid": True, "fix_mode": 3, "fix_ok": True, "lat_deg": 48.1, "lon_deg": 11.5, "height_hae_m": 560.0,
        "height_msl_m": 512.0, "vel_ned_mps": (1.0, 2.0, float("nan")), "h_acc_m": None, "v_acc_m": None,
        "s_acc_mps": None, "num_sv": 8, "pdop": 1.9}
    return GnssFix(**{**fields, **changes})


def nav_solution(t_ns: int, t_mono_ns: int) -> dict[str, Any]:
    """A /nav/fix record of the filter near the fix above."""
    return nav_fix_record(t_ns, t_mono_ns, math.radians(48.1), math.radians(11.5), 560.0, (1.0, 2.0, 0.0),
                          (0.0, 0.0, 1.0), (0.5, 0.5, 1.0), "ins 17-state", "17")


@needs_jsonschema
def test_a_fix_without_vertical_velocity_or_any_optional_value_validates() -> None:
    record = location_fix(nmea_fix(), 1_000)
    assert record["vel_ned_mps"] == [1.0, 2.0, None]
    validate(GNSS_FIX, record)
    # Everything a receiver may leave out, left out: no time, no position, no heights, no DOP, no satellites.
    bare = nmea_fix(time_utc_ns=None, time_valid=False, fix_mode=1, fix_ok=False, lat_deg=None, lon_deg=None,
                    height_hae_m=None, height_msl_m=None, vel_ned_mps=None, num_sv=None, pdop=None)
    record = location_fix(bare, 1_000)
    nullable = {k for k, v in TOPICS[GNSS_FIX].schema["properties"].items() if "null" in v["type"]}
    # every optional value of the topic is null here, but the altitude of no position (0, as latitude and longitude),
    # the leap second flags (absent but on 23:59:60, and while a receiver says its leap count is not the broadcast
    # one) and when the epoch began (absent when one read held it)
    assert {k for k, v in record.items() if v is None} == nullable - {"altitude", "leap_second", "leap_unknown",
                                                                      "opened_mono_ns"}
    assert "leap_second" not in record and "opened_mono_ns" not in record and record["altitude"] == 0.0
    assert "leap_unknown" not in record
    validate(GNSS_FIX, location_fix(nmea_fix(), 2_000, opened_mono_ns=1_000))
    validate(GNSS_FIX, record)


@needs_jsonschema
def test_a_position_without_a_height_records_none_and_validates() -> None:
    """An NMEA epoch without GGA (RMC + GSA): 0 m recorded as its height was taken for one, 600 m off."""
    record = location_fix(nmea_fix(fix_mode=2, height_hae_m=None, height_msl_m=None), 1_000)
    assert (record["altitude"], record["height_msl_m"], record["fix_mode"]) == (None, None, 2)
    validate(GNSS_FIX, record)
    leap = location_fix(nmea_fix(leap_second=True), 1_000)
    assert leap["leap_second"] is True
    validate(GNSS_FIX, leap)


@needs_jsonschema
def test_a_fix_breaking_its_schema_fails() -> None:
    """The check can fail: a required field missing, a wrong type, an array of the wrong length."""
    good = location_fix(nmea_fix(), 1_000)
    for broken in ({k: v for k, v in good.items() if k != "fix_mode"}, {**good, "fix_ok": "yes"},
                   {**good, "vel_ned_mps": [1.0, 2.0]}, {**good, "vel_ned_mps": [1.0, "2", None]},
                   {**good, "position_covariance": [0.0] * 8}, {**good, "timestamp": {"sec": 1}}):
        with pytest.raises(jsonschema.ValidationError):
            validate(GNSS_FIX, broken)


@needs_jsonschema
def test_live_and_gnss_fixes_have_schemas_of_their_own_under_foxglove_s_name() -> None:
    live, gnss = TOPICS[NAV_FIX], TOPICS[GNSS_FIX]
    assert live.schema_name == gnss.schema_name == "foxglove.LocationFix"
    assert live.schema_data != gnss.schema_data
    # A /gnss/fix record is no /nav/fix, and the other way round.
    fix = strict_json(json.dumps(stamped_record(1_000, STAMP, 0, location_fix(nmea_fix(), 1_000))))
    solution = nav_solution(STAMP.t_sync_ns, 1_000)
    jsonschema.validate(fix, gnss.schema)
    jsonschema.validate(solution, live.schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(fix, live.schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(solution, gnss.schema)


@needs_jsonschema
@pytest.mark.parametrize("capture", sorted(p.name for p in CAPTURES.glob("*.log")))
def test_what_real_receivers_send_is_recorded_within_the_schemas(capture: str) -> None:
    """Every fix and time pulse the receiver reader makes of a real capture, and every fix gpsd made of the same
    capture (its regression output, .chk), recorded as the daemon records them, validates."""
    data = strip_capture_comments((CAPTURES / capture).read_bytes())
    items = decode_pieces([data]).items
    for item in items:
        if isinstance(item, GnssFix):
            validate(GNSS_FIX, location_fix(item, 1_000))
        elif isinstance(item, TimePulse):
            validate(TIMEPULSE, timepulse_record(item))
    reports = [json.loads(line) for line in (CAPTURES / f"{capture}.chk").read_text().splitlines()
               if line.startswith("{")]
    sky = None
    for report in reports:
        if report.get("class") == "SKY":
            sky = report
        elif report.get("class") == "TPV":
            validate(GNSS_FIX, location_fix(fix_from_tpv(report, sky), 1_000))


def test_recovery_gives_a_lost_channel_its_own_topics_schema(tmp_path: Path, monkeypatch) -> None:
    """A channel whose record was in a damaged chunk is made again from the recorder's channel table, under its own
    topic's schema: /nav/fix gets /nav/fix's, not the first schema named foxglove.LocationFix that survived."""
    monkeypatch.setattr(recorder_module, "CHANNEL_TABLE_S", 0.0)  # the table at every flush
    rec = Recorder(RecorderSettings(out_dir=tmp_path, flush_interval_s=0.01), TOPICS)
    path = rec.start()
    assert path is not None
    gnss = stamped_record(1_000, STAMP, 0, location_fix(nmea_fix(), 1_000))
    t0 = STAMP.t_sync_ns
    for k in range(2):  # a first chunk with both channels' records, then one with messages only
        rec.submit(GNSS_FIX, {**gnss, "seq": k}, t0 + k, 1_000 + k)
        rec.submit(NAV_FIX, nav_solution(t0 + k, 1_000 + k), t0 + k, 1_000 + k)
        deadline = time.monotonic() + 5
        while rec.status().on_disk_mono_ns.get(NAV_FIX, -1) < 1_000 + k and time.monotonic() < deadline:
            time.sleep(0.005)
    rec.stop()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) >= 2
    first, last = summary.chunk_indexes[0], summary.chunk_indexes[-1]
    data = bytearray(path.read_bytes()[:last.chunk_start_offset + last.chunk_length])  # cut before the summary
    data[first.chunk_start_offset:first.chunk_start_offset + first.chunk_length] = bytes(first.chunk_length)
    path.write_bytes(bytes(data))
    report = recover(path)
    assert report.messages >= 2
    assert assert_own_schemas(path) == {GNSS_FIX, NAV_FIX}
