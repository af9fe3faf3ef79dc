"""``logger plot`` and the timing statistics behind its rates plot, on a drive recorded by the real daemon.

Messages are taken out of a copy of the recording (as a full queue or a cut cable would lose them), and the
statistics must find exactly that many lost by ``seq`` and a gap in the stamps where they were.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from extras import need
from helpers_drive import drive_timeout
from mcap.reader import make_reader
from mcap.writer import Writer

from logger.cli import plot as plot_cmd
from logger.exports.topic_timing import STAMPED_TOPICS, timings
from logger.recording.drive import iter_messages, open_drive

ROOT = Path(__file__).resolve().parents[1]
REMOVED = 4  # consecutive IMU records taken out: FIFO reads of about ten samples each


def run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "logger.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def without_imu_block(src: Path, dst: Path, count: int) -> list[int]:
    """Copy ``src`` leaving out ``count`` consecutive IMU records (``/imu/batch`` reads, or ``/imu`` samples where
    the IMU was read a sample at a time) from its middle; the seq numbers of the samples they held."""
    with open(src, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        records = sorted(((m.log_time, m.sequence, ch.topic, m) for _, ch, m in reader.iter_messages()),
                         key=lambda r: r[0])
    imu = [r for r in records if r[2] in ("/imu", "/imu/batch")]
    start = (len(imu) - count) // 2
    drop = {id(r[3]) for r in imu[start:start + count]}
    with open(dst, "wb") as f:
        w = Writer(f)
        w.start(library="vehicle-logger")
        sids = {sid: w.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
        cids = {cid: w.register_channel(ch.topic, ch.message_encoding, sids.get(ch.schema_id, 0), dict(ch.metadata))
                for cid, ch in summary.channels.items()}
        for _, _, _, m in records:
            if id(m) not in drop:
                w.add_message(cids[m.channel_id], log_time=m.log_time, publish_time=m.publish_time, data=m.data,
                              sequence=m.sequence)
        w.finish()
    seqs = []
    for r in imu[start:start + count]:
        m = json.loads(r[3].data)
        seqs.extend(range(m["seq"], m["seq"] + len(m["t_mono_ns"])) if r[2] == "/imu/batch" else [m["seq"]])
    return seqs


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list[int]]:
    out = tmp_path_factory.mktemp("plot")
    # Long enough for the scenario's 60 s outage (from about 100 s in), which the plots must show.
    r = run("run", "--sim", "--scenario", "outage-60s", "--duration", "180", "--time-scale", "10", "--out", str(out),
            "--status-socket", str(out / "status.sock"), timeout=drive_timeout(180))
    assert r.returncode == 0, r.stderr
    (original,) = sorted(out.glob("*.mcap"))
    thinned = out / "thinned" / original.name
    thinned.parent.mkdir()
    seqs = without_imu_block(original, thinned, REMOVED)
    return original, thinned, seqs


@pytest.mark.slow_on_board
def test_lost_messages_and_the_gap_are_found_where_they_were_taken_out(recorded: tuple[Path, Path, list[int]]):
    original, thinned, seqs = recorded
    before = timings(list(iter_messages(open_drive([original]), STAMPED_TOPICS)))
    after = timings(list(iter_messages(open_drive([thinned]), STAMPED_TOPICS)))
    assert set(before) == set(STAMPED_TOPICS)
    imu0, imu1 = before["/imu"], after["/imu"]
    removed = len(seqs)
    assert removed >= REMOVED and seqs == list(range(seqs[0], seqs[0] + removed))
    assert len(imu0.log_ns) - len(imu1.log_ns) == removed
    assert imu1.n_lost - imu0.n_lost == removed
    new_lost = [x for x in imu1.lost if x not in imu0.lost]
    (at_ns, n), = new_lost
    assert n == removed and at_ns == int(imu1.log_ns[imu1.seq == seqs[-1] + 1][0])
    (gap,) = [g for g in imu1.gaps if g.after_ns == at_ns]
    first = int(imu0.log_ns.searchsorted(at_ns))  # the message after the block, in the original
    assert gap.interval_s == (imu0.log_ns[first] - imu0.log_ns[first - removed - 1]) / 1e9
    for topic in set(STAMPED_TOPICS) - {"/imu"}:  # the other topics are untouched
        assert after[topic].summary() == before[topic].summary()


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def test_plot_writes_the_three_pngs(recorded: tuple[Path, Path, list[int]], tmp_path: Path):
    need("matplotlib")  # logger plot draws with it
    _, thinned, _ = recorded
    r = run("plot", str(thinned), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    name = thinned.stem.removesuffix("_0001")
    for kind in ("map", "rates", "sync"):
        w, h = png_size(tmp_path / f"{name}_{kind}.png")
        assert w > 500 and h > 500
        assert f"wrote {tmp_path / f'{name}_{kind}.png'}" in r.stdout
    after = timings(list(iter_messages(open_drive([thinned]), STAMPED_TOPICS)))
    assert [line for line in r.stdout.splitlines() if not line.startswith("wrote ")] == \
        [t.summary() for t in after.values()]
    img = need("matplotlib.image").imread(tmp_path / f"{name}_map.png")
    assert img[..., :3].std() > 0.01  # something was drawn


def test_without_matplotlib_it_says_how_to_install(recorded: tuple[Path, Path, list[int]], tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    assert plot_cmd.main([str(recorded[0]), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "pip install" in err and "matplotlib" in err
    assert not (tmp_path / "out").exists()


def test_what_cannot_be_plotted_is_one_line_and_exit_2(tmp_path: Path):
    need("matplotlib")  # looked for before the files are opened: without it, that is the one line
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    for path, words in ((tmp_path / "missing.mcap", "no such file"), (text, "not an MCAP file")):
        r = run("plot", str(path), "--out", str(tmp_path / "out"))
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_restart_is_not_counted_as_loss():
    from logger.exports.topic_timing import topic_timing

    period = 50_000_000
    seqs = [0, 1, 2, 6, 7, 0, 1, 2, 3]  # three lost, then the daemon started again
    monos = [k * period for k in (0, 1, 2, 6, 7)] + [100 * period + k * period for k in range(4)]
    rows = [(1_000 + m, m, s, "locked", 1000) for s, m in zip(seqs, monos, strict=True)]
    tt = topic_timing("/imu", rows)
    assert tt.lost == [(1_000 + 6 * period, 3)] and tt.restarts == [1_000 + 100 * period]
    assert tt.median_interval_s == period / 1e9
    assert [(g.before_ns, g.after_ns) for g in tt.gaps] == [(1_000 + 2 * period, 1_000 + 6 * period),
                                                            (1_000 + 7 * period, 1_000 + 100 * period)]


def test_plot_and_info_give_a_file_the_same_rates_and_gaps(recorded: tuple[Path, Path, list[int]]) -> None:
    """One rule (logger.recording.intervals) behind both tools: the same rate and the same gaps, topic by topic."""
    _, thinned, _ = recorded
    info = run("info", str(thinned), "--json")
    assert info.returncode == 0, info.stderr
    by_info = {t["topic"]: t for t in json.loads(info.stdout)["topics"]}
    plotted = timings(list(iter_messages(open_drive([thinned]), STAMPED_TOPICS)))
    for topic, tt in plotted.items():
        if topic == "/imu" and topic not in by_info:  # info counts the file's records: the IMU's FIFO reads
            continue
        assert f"at {by_info[topic]['rate_hz']:.2f} Hz;" in tt.summary(), (topic, tt.summary(), by_info[topic])
        assert by_info[topic]["gaps"] == len(tt.gaps) and by_info[topic]["count"] == len(tt.log_ns), topic
    assert set(plotted) - set(by_info) <= {"/imu"} and "/imu/batch" in by_info
    # The block taken out is a gap for both: in the reads info counts and in the samples plot counts.
    assert by_info["/imu/batch"]["gaps"] >= 1 and plotted["/imu"].gaps


def test_the_plots_find_the_outage_the_receiver_reported(recorded: tuple[Path, Path, list[int]]) -> None:
    """The receiver kept reporting once a second through the outage: its spans without a fix are what the plots
    shade, one of about the scenario's 60 s, and the rest of the drive had a fix."""
    original, _, _ = recorded
    fixes = [m for m in iter_messages(open_drive([original]), ("/gnss/fix",))]
    spans = plot_cmd.no_fix_spans(fixes, fixes[0].log_time)
    assert [round(b - a) for a, b in spans if b - a > 5] == [pytest.approx(60, abs=3)], spans
    assert all(b - a <= 2 for a, b in spans if b - a <= 5)  # anything else: the receiver's first epoch at most


def test_an_output_path_that_cannot_be_a_folder_is_one_line(tmp_path: Path) -> None:
    need("matplotlib")  # looked for first: without it, that is the one line
    drive = tmp_path / "drive.mcap"
    with open(drive, "wb") as f:
        w = Writer(f)
        w.start()
        cid = w.register_channel("/baro", "json", w.register_schema("Baro", "jsonschema", b"{}"))
        w.add_message(cid, log_time=1, publish_time=1, data=b"{}")
        w.finish()
    afile = tmp_path / "afile"
    afile.write_text("")
    r = run("plot", str(drive), "--out", str(afile / "sub"))
    assert r.returncode == 2 and r.stdout == "", r.stderr
    assert r.stderr == f"logger plot: --out {afile / 'sub'}: cannot be made, {afile} is a file and not a folder\n"
