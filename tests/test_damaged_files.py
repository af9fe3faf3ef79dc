"""Damaged files are read without their damaged chunks, and said so: a chunk whose CRC fails is skipped whole by every
reader (replay, export, plot, nav-score through the drive reader; ``logger info``; ``logger recover``), counted in
chunks and messages with the time it spanned, and the rest of the drive is read.

The files are written by the project's own writer (``McapWriter``), a chunk per second of drive, then damaged in
a copy: a digit flipped inside a message (a chunk stored without compression: the JSON stays valid and only the CRC
tells), bytes flipped in a compressed chunk, chunk heads zeroed (a zeroed page).
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
from pathlib import Path

from mcap.reader import make_reader

from logger.recording.drive import DriveFileError, damage_notes, iter_messages, open_drive, read_messages
from logger.recording.files import CHANNEL_TABLE, is_finished, recover, walk
from logger.recording.mcap_writer import McapWriter
from logger.recording.topics import BARO, GNSS_FIX, TOPICS

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_796_000_000_000_000_000
PER_CHUNK = 20
CHUNKS = 8
STEP_NS = 50_000_000  # 20 messages a second: a chunk a second


def write_file(path: Path, compression: str = "none", bad_json_at: int | None = None,
               finish: bool = True) -> list[tuple[int, int, str, bytes]]:
    """A file of CHUNKS chunks of PER_CHUNK messages on two topics, with the recorder's channel table outside the
    chunks; returns (chunk, log time, topic, data) of every message."""
    written = []
    with open(path, "wb") as f:
        w = McapWriter(f, compression=compression, chunk_size=1 << 20)
        w.start(profile="", library="vehicle-logger test")
        channels = {}
        for topic in (GNSS_FIX, BARO):
            spec = TOPICS[topic]
            sid = w.register_schema(spec.schema_name, "jsonschema", spec.schema_data)
            channels[topic] = w.register_channel(topic, "json", sid)
        for c in range(CHUNKS):
            for i in range(PER_CHUNK):
                k = c * PER_CHUNK + i
                topic = GNSS_FIX if k % 2 else BARO
                t = T0 + k * STEP_NS
                data = json.dumps({"t_sync_ns": t, "value": 1000 + k, "latitude": 48.1 + k * 1e-6}).encode()
                if k == bad_json_at:
                    data = b'{"t_sync_ns": ' + str(t).encode() + b', "value": '  # cut short by its writer
                w.add_message(channels[topic], t, data, t)
                written.append((c, t, topic, data))
            w.flush()
            w.add_metadata(CHANNEL_TABLE, {str(cid): topic for topic, cid in channels.items()})
        if finish:
            w.finish()
    return written


def chunk_spans(path: Path) -> list[tuple[int, int]]:
    """(offset, length) of each chunk record, from the file's chunk index."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return [(ci.chunk_start_offset, ci.chunk_length) for ci in summary.chunk_indexes]


def got(path: Path) -> list[tuple[int, str, int]]:
    return [(m.log_time, m.topic, m.msg["value"]) for m in iter_messages(open_drive([path]), [GNSS_FIX, BARO])]


def expected(written: list[tuple[int, int, str, bytes]], lost: set[int]) -> list[tuple[int, str, int]]:
    return [(t, topic, json.loads(data)["value"]) for c, t, topic, data in written if c not in lost]


def test_a_flipped_digit_in_a_cleanly_closed_file_skips_its_chunk_and_says_so(tmp_path: Path) -> None:
    """One bit flipped in a number: the JSON is still valid, so only the chunk's CRC tells. The chunk is skipped
    whole by both readers, the line names the file, the chunk's messages and time, and the rest is read."""
    p = tmp_path / "drive_20261205T094239Z_0001.mcap"
    written = write_file(p)
    data = bytearray(p.read_bytes())
    start, length = chunk_spans(p)[3]
    at = data.index(b'"value": 10', start, start + length) + len(b'"value": 10')
    data[at] ^= 0x02  # a digit becomes another digit: 1066 -> 1266
    p.write_bytes(bytes(data))
    assert is_finished(p)
    assert got(p) == expected(written, {3})
    (line,) = damage_notes([p])
    assert line.startswith(f"{p}: 1 damaged chunk skipped (CRC mismatch), {PER_CHUNK} messages lost, at ")
    assert line.endswith(" UTC; read the rest")
    filt = [(topic, m["value"]) for topic, m in read_messages([p], [GNSS_FIX, BARO])]
    assert filt == [(topic, v) for _, topic, v in expected(written, {3})]


def test_any_flipped_byte_of_a_compressed_file_is_a_skipped_chunk_never_other_values(tmp_path: Path) -> None:
    """Anywhere in a zstd file: what is read is the original's messages less whole chunks, never altered ones and
    never an exception, and whatever is missing is told."""
    src = tmp_path / "src.mcap"
    written = write_file(src, compression="zstd")
    clean = expected(written, set())
    data = src.read_bytes()
    rng = random.Random(5)
    for trial in range(60):
        p = tmp_path / f"flip{trial}.mcap"
        damaged = bytearray(data)
        at = rng.randrange(8, len(data))
        damaged[at] ^= 1 << rng.randrange(8)
        p.write_bytes(bytes(damaged))
        try:
            read = got(p)
        except DriveFileError as exc:  # a file whose start is gone: one line, never a traceback
            assert str(exc).startswith(str(p)), exc
            continue
        assert set(read) <= set(clean), at
        chunks_read = {c for c, t, topic, d in written if (t, topic, json.loads(d)["value"]) in set(read)}
        assert read == expected(written, set(range(CHUNKS)) - chunks_read), at  # whole chunks only
        assert (len(read) < len(clean)) == bool(damage_notes([p])), (at, damage_notes([p]))


def test_a_damaged_first_chunk_loses_only_itself_not_its_channels_later_messages(tmp_path: Path) -> None:
    """The channel records are in the first chunk: without them the later chunks' messages would go unnamed. The
    reader falls back to recovery's walk, which names them from the recorder's channel table."""
    p = tmp_path / "drive_20261205T094239Z_0001.mcap"
    written = write_file(p)
    data = bytearray(p.read_bytes())
    start, length = chunk_spans(p)[0]
    at = data.index(b'"value": 10', start, start + length) + len(b'"value": 10')
    data[at] ^= 0x02
    p.write_bytes(bytes(data))
    assert got(p) == expected(written, {0})
    (line,) = damage_notes([p])
    assert f"1 damaged chunk skipped, {PER_CHUNK} messages lost" in line


def test_a_message_that_is_not_json_is_skipped_and_counted_not_a_traceback(tmp_path: Path) -> None:
    p = tmp_path / "drive_20261205T094239Z_0001.mcap"
    written = write_file(p, bad_json_at=45)
    good = [(t, topic, json.loads(d)["value"]) for c, t, topic, d in written if not d.endswith(b": ")]
    assert got(p) == good
    assert damage_notes([p]) == [f"{p}: 1 message that is not JSON skipped; read the rest"]
    assert len(list(read_messages([p], [GNSS_FIX, BARO]))) == len(good)  # the filter's reader too


def test_info_and_recover_tell_a_damaged_cleanly_closed_file_and_recover_needs_no_force(tmp_path: Path,
                                                                                         capsys) -> None:
    from logger.cli import main

    p = tmp_path / "drive_20261205T094239Z_0001.mcap"
    written = write_file(p, compression="zstd")
    data = bytearray(p.read_bytes())
    for k in (2, 5):
        start, length = chunk_spans(p)[k]
        data[start + length - 10] ^= 0x10  # in the compressed records
    p.write_bytes(bytes(data))
    assert main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "Closed:    cleanly, but 2 chunks damaged" in out
    assert "Damaged:   2 damaged chunks skipped" in out and f"{2 * PER_CHUNK} messages lost" in out
    assert f"Messages:  {(CHUNKS - 2) * PER_CHUNK}" in out
    assert main(["recover", str(p)]) == 0  # no --force needed: the file is damaged, not cleanly whole
    out = capsys.readouterr().out
    assert out.startswith(f"{p}: recovered {(CHUNKS - 2) * PER_CHUNK} messages from {CHUNKS - 2} chunks; "
                          f"2 damaged chunks skipped, {2 * PER_CHUNK} messages lost, at "), out
    with open(p, "rb") as f:
        kept = [(m.log_time, ch.topic, json.loads(m.data)["value"])
                for _, ch, m in make_reader(f, validate_crcs=True).iter_messages()]
    assert kept == expected(written, {2, 5})
    assert main(["recover", str(p)]) == 0
    assert "every chunk's CRC holds: nothing to recover" in capsys.readouterr().out
    assert main(["info", str(p)]) == 0
    assert "Damaged:" not in capsys.readouterr().out


def test_recover_counts_the_chunks_and_messages_a_zeroed_page_cost(tmp_path: Path) -> None:
    """A cut file (no summary to count from) whose two chunk heads were zeroed: the walk cannot see those chunks,
    but their message indexes, after them, tell what they held. A finished file's statistics give the exact count."""
    full = tmp_path / "full.mcap"
    written = write_file(full, compression="zstd")
    spans = chunk_spans(full)
    data = bytearray(full.read_bytes())
    for k in (3, 4):
        start, _ = spans[k]
        data[start:start + 40] = bytes(40)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(bytes(data[:spans[-1][0] + spans[-1][1] + 200]))  # the summary never written
    report = recover(cut, tmp_path / "cut.rec.mcap")
    assert report.messages == (CHUNKS - 2) * PER_CHUNK
    lost = report.lost()
    assert lost.startswith(f"at least 2 damaged chunks skipped, at least {2 * PER_CHUNK} messages lost, at "), lost
    finished = tmp_path / "finished.mcap"
    finished.write_bytes(bytes(data))
    report = recover(finished, tmp_path / "finished.rec.mcap")
    assert report.lost().startswith(f"2 damaged chunks skipped, {2 * PER_CHUNK} messages lost, at "), report.lost()
    found = walk(tmp_path / "finished.rec.mcap")
    assert len(found.messages) == len(expected(written, {3, 4})) and not found.losses


def test_replay_skips_a_damaged_chunk_says_so_and_writes_the_rest(tmp_path: Path) -> None:
    """A minute of simulated drive, a chunk a second, one chunk in the middle damaged: the trajectory is written
    (exit 0) and one line on stderr names the file, the chunk and what it held."""
    from test_nav_synth import records

    from sensors.sim.scenarios import make_drive

    p = tmp_path / "drive_20261205T094239Z_0001.mcap"
    with open(p, "wb") as f:
        w = McapWriter(f, compression="zstd")
        w.start(profile="", library="vehicle-logger test")
        channels: dict[str, int] = {}
        next_flush = None
        for t, topic, msg in records(make_drive("urban", seed=2, duration_s=60.0), 60.0, seed=2):
            if topic not in channels:
                spec = TOPICS[topic]
                channels[topic] = w.register_channel(topic, "json", w.register_schema(spec.schema_name, "jsonschema",
                                                                                      spec.schema_data))
            if next_flush is None or t >= next_flush:
                w.flush()
                next_flush = t + 1_000_000_000
            w.add_message(channels[topic], t, json.dumps(msg).encode(), t)
        w.finish()
    data = bytearray(p.read_bytes())
    spans = chunk_spans(p)
    start, length = spans[len(spans) // 2]
    data[start + length // 2] ^= 0x01
    p.write_bytes(bytes(data))
    r = subprocess.run([sys.executable, "-m", "logger.cli", "replay", str(p), "--out", str(tmp_path / "out"),
                        "--no-mcap"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    (line,) = [x for x in r.stderr.splitlines() if "damaged chunk" in x]
    assert line.startswith(f"logger replay: {p}: 1 damaged chunk skipped (") and "messages lost, at " in line
    assert (tmp_path / "out" / "trajectory.csv").is_file()


def test_a_lost_chunk_that_overlaps_its_neighbours_in_time_keeps_its_own_span(tmp_path: Path) -> None:
    """Messages are logged at their own time but written when they come (the navigator's /nav/fix seconds late), so
    a chunk can begin before the one written before it. Its intact head's span was taken for a damaged head's and
    the loss said as the short gap between its neighbours (0.7 s of a 4.7 s loss); now it is its own, in every
    reader (the drive reader, and logger info / recover's walk)."""
    from logger.recording.drive import damage_spans

    p = tmp_path / "drive_20261205T094239Z_0001.mcap"
    late_t = T0 + (2 * PER_CHUNK - 15) * STEP_NS  # inside chunk 1, written with chunk 3
    with open(p, "wb") as f:
        w = McapWriter(f, compression="none", chunk_size=1 << 20)
        w.start(profile="", library="vehicle-logger test")
        spec = TOPICS[GNSS_FIX]
        cid = w.register_channel(GNSS_FIX, "json", w.register_schema(spec.schema_name, "jsonschema",
                                                                     spec.schema_data))
        for c in range(CHUNKS):
            for i in range(PER_CHUNK):
                t = T0 + (c * PER_CHUNK + i) * STEP_NS
                w.add_message(cid, t, json.dumps({"t_sync_ns": t, "value": 1000 + c * PER_CHUNK + i}).encode(), t)
            if c == 3:
                w.add_message(cid, late_t, json.dumps({"t_sync_ns": late_t, "value": 1}).encode(), late_t)
            w.flush()
            w.add_metadata(CHANNEL_TABLE, {str(cid): GNSS_FIX})
        w.finish()
    data = bytearray(p.read_bytes())
    start, length = chunk_spans(p)[3]
    at = data.index(b'"value": 10', start, start + length) + len(b'"value": 10')
    data[at] ^= 0x02  # the CRC fails; the head is intact
    p.write_bytes(bytes(data))
    chunk3_last = T0 + (4 * PER_CHUNK - 1) * STEP_NS
    list(iter_messages(open_drive([p]), [GNSS_FIX]))
    assert damage_spans(p) == [(late_t, chunk3_last)]
    (loss,) = walk(p, keep_messages=False).losses
    assert (loss.first_ns, loss.last_ns) == (late_t, chunk3_last)
