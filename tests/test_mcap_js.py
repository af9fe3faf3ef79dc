"""Foxglove's own JavaScript library, ``@mcap/core``, reads our files as the project's Python reader does.

Every other test reads the files with Python (the ``mcap`` package, the record walk of
:mod:`logger.recording.drive`); a reader in another language, written by the format's authors, is the
independent check that the files are MCAP and not merely what our code expects. ``tools/mcap_js/read.mjs``
reads a file with ``McapIndexedReader`` (through its summary and index) and with a plain ``McapStreamReader``
walk (what a file cut short has), and the two readings are compared with the project's: the channels' topics,
schema names and encodings, messages per topic, the time range, the chunks, every message JSON, and the
samples of ``/imu/batch`` (the IMU read through its FIFO, as by default). A copy cut at 60 % of its size is read
as a power cut leaves a file: the stream walk keeps what the project's reader recovers, and neither crashes.

The test needs ``node`` and ``npm ci --prefix tools/mcap_js``; without them it skips, except in CI, which
installs both (.ci/run) and where it fails instead.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import extras
import pytest
from helpers_drive import run_logger
from mcap.reader import make_reader
from test_schemas import CAPTURES, DRIVES, STAMP

from logger.cli.gnss_decode import decode_pieces, strip_capture_comments
from logger.recording.drive import iter_messages, open_drive
from logger.recording.files import recover, walk
from logger.recording.records import location_fix, stamped_record
from logger.recording.topics import GNSS_FIX, IMU, IMU_BATCH, NAV_FIX, TOPICS
from sensors.ublox_decode import GnssFix

ROOT = Path(__file__).resolve().parents[1]
READER = ROOT / "tools" / "mcap_js" / "read.mjs"
FOXGLOVE_SCHEMA = ROOT / "tools" / "mcap_js" / "foxglove_schema.mjs"
NODE_MODULES = ROOT / "tools" / "mcap_js" / "node_modules"
FIFO = next(d for d in DRIVES if d.name == "urban")  # test_schemas' default drive: the IMU's FIFO, /imu/batch
# (compression, simulated seconds): the default, and the other compression the recorder offers, shorter.
DRIVES_HERE = {"zstd": 20, "lz4": 10}
CUT_AT = 0.6  # share of the file a power cut leaves


def need_node() -> str:
    """``node`` with the reader's packages installed; a skip where either is missing (a failed run in CI, which
    installs both: tests/conftest.py's CI_INSTALLS)."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (apt-get install nodejs npm)")
    if not (NODE_MODULES / "@mcap" / "core").is_dir() or not (NODE_MODULES / "@foxglove" / "schemas").is_dir():
        pytest.skip("tools/mcap_js/node_modules is not installed (npm ci --prefix tools/mcap_js)")
    return node


def read_js(node: str, path: Path) -> dict[str, Any]:
    """What ``read.mjs`` prints for the file: one JSON line."""
    r = subprocess.run([node, str(READER), str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 1, r.stdout
    return json.loads(lines[0])


@dataclasses.dataclass
class PythonView:
    """What the project's drive reader (:mod:`logger.recording.drive`) reads from one file, in read.mjs's terms."""

    counts: dict[str, int]
    time_range: list[int]
    imu_batch_samples: int


def python_view(path: Path) -> PythonView:
    """A finished file is read through the record walk or the mcap package, an unfinished one as recovery reads it
    (every CRC-valid chunk up to the cut); every message is decoded as JSON on the way (a DriveFileError if not).
    ``/imu/batch`` samples are counted as the project's readers of samples get them: asked for ``/imu``."""
    files = open_drive([path])
    counts: Counter[str] = Counter()
    times = []
    for m in iter_messages(files, TOPICS):
        counts[m.topic] += 1
        times.append(m.log_time)
    samples = sum(1 for m in iter_messages(files, [IMU]) if m.msg.get("fifo"))
    return PythonView(dict(counts), [min(times), max(times)] if times else [], samples)


@pytest.fixture(scope="module", params=sorted(DRIVES_HERE))
def recorded(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, Path]:
    """(node, the drive's one file): the default urban drive (the IMU through its FIFO), with the chunks
    compressed as ``request.param``."""
    node = need_node()
    compression = request.param
    out = tmp_path_factory.mktemp(f"mcap-js-{compression}")
    cfg = out / "logger.toml"
    cfg.write_text(f'[logger]\nstate_dir = "{out / "state"}"\n{FIFO.config}'
                   f'[recorder]\ncompression = "{compression}"\n')
    r = run_logger("--sim", "--scenario", FIFO.scenario, "--duration", str(DRIVES_HERE[compression]),
                   "--time-scale", "5", "--out", str(out / "drive"), "--status-socket", str(out / "status.sock"),
                   "--config", str(cfg))
    assert r.returncode == 0, r.stderr
    files = sorted((out / "drive").glob("*.mcap"))
    assert len(files) == 1, files
    return node, files[0]


def test_mcap_core_reads_a_drive_as_the_python_reader_does(recorded: tuple[str, Path]) -> None:
    node, path = recorded
    js = read_js(node, path)
    indexed, stream = js["indexed"], js["stream"]
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    stats = summary.statistics
    channels = {ch.topic: {"schema": summary.schemas[ch.schema_id].name,
                           "schema_encoding": summary.schemas[ch.schema_id].encoding,
                           "message_encoding": ch.message_encoding} for ch in summary.channels.values()}
    py = python_view(path)

    # The profile's topics (/nav/* once the filter runs, about 15 s in), /imu/batch among them, each with our schema
    # and JSON.
    assert IMU_BATCH in channels and not set(channels) & set(FIFO.absent), sorted(channels)
    ours = {t: {"schema": TOPICS[t].schema_name, "schema_encoding": "jsonschema", "message_encoding": "json"}
            for t in channels if t in TOPICS}
    assert channels == ours, channels
    # The indexed reader and the stream walk each read what the Python side reads.
    for name, got in (("indexed", indexed), ("stream", stream)):
        assert got["topics"] == channels, name
        assert got["counts"] == py.counts, name
        assert got["messages"] == sum(py.counts.values()) == stats.message_count, name
        assert got["time_range"] == py.time_range == [stats.message_start_time, stats.message_end_time], name
        assert got["chunks"] == stats.chunk_count == len(summary.chunk_indexes), name
        assert got["all_json"] and got["not_json"] == 0, name
        assert got["imu_batch_samples"] == py.imu_batch_samples > 0, name
    assert indexed["statistics"] == {"messages": stats.message_count, "chunks": stats.chunk_count,
                                     "time_range": [stats.message_start_time, stats.message_end_time]}
    assert stream["complete"] and stream["bytes_unread"] == 0
    assert py.counts[IMU_BATCH] > 0 and py.imu_batch_samples >= py.counts[IMU_BATCH]


def inside_a_record(data: bytes, at: int) -> int:
    """``at``, or the byte after it where ``at`` falls between two MCAP records (magic, then opcode, 8-byte length,
    body): a power cut leaves a record half written, and one that fell on a boundary left the stream reader nothing
    unread (one CI run in many)."""
    pos = 8
    while pos < at:
        pos += 9 + int.from_bytes(data[pos + 1:pos + 9], "little")
    return at + 1 if pos == at else at


def test_mcap_core_stream_walk_recovers_a_cut_file(recorded: tuple[str, Path], tmp_path: Path) -> None:
    node, path = recorded
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:inside_a_record(data, int(len(data) * CUT_AT))])
    js = read_js(node, cut)
    salvage = walk(cut)
    py = python_view(cut)
    assert not open_drive([cut])[0].finished and salvage.stopped_at.startswith("cut at byte"), salvage.stopped_at

    # The index is at the end, gone: the indexed reader says so (read.mjs keeps its error, exits 0).
    assert "error" in js["indexed"], js["indexed"]
    stream = js["stream"]
    assert not stream["complete"] and stream["bytes_unread"] > 0, stream
    # The stream walk stops at the cut chunk and keeps every message of the whole ones, as recovery does.
    assert stream["chunks"] == salvage.chunks_ok > 0 and salvage.chunks_bad == 0
    # The project's walk also names the channels registered in the cut chunk, from the recorder's channel table
    # outside the chunks (logger.recording.files._name_orphans): only those go beyond what the stream walk saw.
    with_messages = {salvage.channels[m.channel_id].topic for m in salvage.messages}
    assert with_messages <= set(stream["topics"]) <= {ch.topic for ch in salvage.channels.values()}
    assert stream["counts"] == py.counts
    assert stream["messages"] == len(salvage.messages) == sum(py.counts.values()) > 0
    assert stream["time_range"] == py.time_range
    assert stream["all_json"]
    assert stream["imu_batch_samples"] == py.imu_batch_samples > 0

    # Recovery writes what the walk kept into a finished file (logger/recording/mcap_writer.py): @mcap/core's
    # indexed reader finds every message of it through the new summary and indexes.
    recover(cut)
    again = read_js(node, cut)["indexed"]
    assert "error" not in again, again
    assert again["counts"] == py.counts and again["messages"] == len(salvage.messages)
    assert again["time_range"] == py.time_range and again["imu_batch_samples"] == py.imu_batch_samples


# ---- Foxglove's own schema ---------------------------------------------------------------------------------------
def foxglove_schema(node: str, name: str) -> dict[str, Any]:
    """Foxglove's JSON schema ``name`` as @foxglove/schemas publishes it."""
    r = subprocess.run([node, str(FOXGLOVE_SCHEMA), name], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)[name]


def location_fix_problems(validator: Any, record: dict[str, Any]) -> list[str]:
    """Where a /gnss/fix or /nav/fix record breaks Foxglove's foxglove.LocationFix, but for the one documented
    departure (docs/foxglove.md): ``altitude`` null on a position without a height (an NMEA epoch without GGA),
    where Foxglove's schema has a number and any number would be a height nobody measured."""
    return [f"{''.join(f'[{p!r}]' for p in err.absolute_path)}: {err.message}"
            for err in validator.iter_errors(record)
            if not (list(err.absolute_path) == ["altitude"] and record["altitude"] is None
                    and record.get("fix_mode") != 3)]


@functools.cache
def location_fix_validator(node: str) -> Any:
    jsonschema = extras.need("jsonschema")
    schema = foxglove_schema(node, "LocationFix")
    assert schema["title"] == "foxglove.LocationFix" and "altitude" in schema["required"]
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema)


@pytest.mark.parametrize("recorded", ["zstd"], indirect=True)  # the longer drive: the filter starts in it
def test_location_fixes_are_foxglove_s_location_fixes(recorded: tuple[str, Path], tmp_path: Path) -> None:
    """Our topics named foxglove.LocationFix hold to Foxglove's own schema of that name (the Map panel reads them
    by it), not only to the schema our files embed: fields, types, the covariance's length, the time's range. The
    drive's /gnss/fix and live /nav/fix, and the /nav/fix of its replay (the live filter may not have started
    within a short drive on a busy host; the replay's rows are the same record)."""
    node, path = recorded
    validator = location_fix_validator(node)
    r = subprocess.run([sys.executable, "-m", "logger.cli", "replay", str(path), "--out", str(tmp_path)], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    counts: Counter[str] = Counter()
    for name, source in (("drive", path), ("replay", tmp_path / "trajectory.mcap")):
        with open(source, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages(topics=[GNSS_FIX, NAV_FIX]):
                record = json.loads(message.data)
                counts[f"{name} {channel.topic}"] += 1
                assert not location_fix_problems(validator, record), (name, channel.topic, record)
    assert counts[f"drive {GNSS_FIX}"] >= 10 and counts[f"replay {NAV_FIX}"] >= 5, counts
    # The check can fail: a covariance of eight, a time before 1970, a latitude as text, a covariance type of 4.
    with open(path, "rb") as f:
        fix = next(json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=[GNSS_FIX]))
    for broken in ({**fix, "position_covariance": [0.0] * 8}, {**fix, "timestamp": {"sec": -1, "nsec": 0}},
                   {**fix, "latitude": "48.1"}, {**fix, "position_covariance_type": 4}):
        assert location_fix_problems(validator, broken), broken


def test_what_real_receivers_send_is_a_foxglove_location_fix() -> None:
    """Every fix the receiver reader makes of the real captures (the GPSD project's, tests/data/gpsd-ublox: UBX and
    NMEA-only receivers), recorded as the daemon records it, against Foxglove's schema."""
    validator = location_fix_validator(need_node())
    per_capture: Counter[str] = Counter()
    for capture in sorted(CAPTURES.glob("*.log")):
        data = strip_capture_comments(capture.read_bytes())
        for item in decode_pieces([data]).items:
            if isinstance(item, GnssFix):
                record = json.loads(json.dumps(stamped_record(1_000, STAMP, 0, location_fix(item, 1_000))))
                assert not location_fix_problems(validator, record), (capture.name, record)
                per_capture[capture.name] += 1
    assert len(per_capture) >= 20 and sum(per_capture.values()) >= 500, per_capture
