"""Recorder throughput, and what it costs beyond the bare ``mcap`` writer, on the same messages.

    python tools/bench_recorder.py DRIVE.mcap... [--messages 200000] [--repeat 3] --json out.json

The stream is a recorded drive's own records (all but the simulation's ``/truth/*``), repeated with shifted
times until it holds ``--messages`` records: the sizes and the mix of topics a board writes. A second stream
holds only its IMU records (``/imu/batch`` from a FIFO, ``/imu`` from a polled chip: whichever the drive has),
the load of a high IMU rate. Four writers take each stream:

- ``bare``: the recorder's MCAP writer (``logger.recording.mcap_writer.McapWriter``) with the recorder's chunk size
  and compression, the recorder's JSON ``encode`` and ``add_message`` in one loop, the file finished at the end;
- ``mcap Writer``: the same loop with ``mcap.writer.Writer``, the library's writer (the recorder's until
  2026-12-05; what each keeps in memory for its index: ``tools/bench_daemon.py``'s ``writer_index``);
- ``bare + flush``: the same, closing the chunk and fsyncing once a second as the recorder does (the price of
  losing at most a second at a power cut);
- ``recorder``: ``logger.recording.recorder.Recorder``, records handed over with ``submit`` from this thread (as the
  sampler threads do) and written by its own thread; timed from the first submit until ``stop`` has finished
  the file. Its queue is made large enough that nothing is dropped.

Each run is timed as wall time and as the process's CPU time (all threads); the best of ``--repeat`` runs, the
writers taking turns, is the figure (other jobs on the machine only ever make a run slower). Messages/s and
MB/s of JSON payload are per wall second; the overhead is the recorder's CPU per message against the bare
writer's.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from logger.recording.mcap_writer import McapWriter  # noqa: E402
from logger.recording.recorder import PROFILE, Recorder, encode  # noqa: E402
from logger.recording.settings import RecorderSettings  # noqa: E402
from logger.recording.topics import IMU, IMU_BATCH, TOPICS, TopicSpec  # noqa: E402

Item = tuple[str, dict[str, Any], int, int]  # topic, payload, log time, publish time


def read_drive(files: list[Path]) -> list[Item]:
    """The drive's records (the simulator's truth left out) in log-time order, decoded once for every stream."""
    from mcap.reader import make_reader

    base: list[Item] = []
    for path in files:
        with open(path, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages():
                if not channel.topic.startswith("/truth/"):
                    base.append((channel.topic, json.loads(message.data), message.log_time, message.publish_time))
    base.sort(key=lambda item: item[2])
    return base


def imu_topic(drive: list[Item]) -> str:
    """The drive's IMU topic: ``/imu/batch`` (a FIFO's reads, the default at every rate) or ``/imu`` (polled)."""
    topics = {item[0] for item in drive}
    return IMU_BATCH if IMU_BATCH in topics or IMU not in topics else IMU


def load_stream(drive: list[Item], n: int, only: str | None = None) -> list[Item]:
    """The drive's records (of topic ``only``, if given), repeated with shifted times up to ``n`` records."""
    base = [item for item in drive if only is None or item[0] == only]
    if not base:
        raise SystemExit(f"bench_recorder: no records{' on ' + only if only else ''} in the drive")
    span = base[-1][2] - base[0][2] + 1
    out: list[Item] = []
    k = 0
    while len(out) < n:
        shift = k * span
        out.extend((t, p, log + shift, pub + shift) for t, p, log, pub in base[: n - len(out)])
        k += 1
    return out


def mcap_library_writer(f: Any, settings: RecorderSettings) -> Any:
    """mcap's own Writer with the recorder's settings."""
    from mcap.writer import CompressionType, Writer

    return Writer(f, chunk_size=settings.chunk_size_bytes, compression=CompressionType[settings.compression.upper()])


def project_writer(f: Any, settings: RecorderSettings) -> McapWriter:
    return McapWriter(f, chunk_size=settings.chunk_size_bytes, compression=settings.compression)


def run_bare(stream: list[Item], path: Path, settings: RecorderSettings, flush_s: float | None,
             make_writer: Callable[[Any, RecorderSettings], Any] = project_writer) -> dict[str, float]:
    c0, w0 = time.process_time(), time.perf_counter()
    with open(path, "wb") as f:
        writer = make_writer(f, settings)
        writer.start(profile=PROFILE, library="bench")
        ids: dict[str, int] = {}
        next_flush = time.monotonic() + (flush_s or 0.0)
        for topic, payload, log_ns, pub_ns in stream:
            cid = ids.get(topic)
            if cid is None:
                spec = TOPICS.get(topic) or TopicSpec(topic, topic, {"type": "object"}, "")
                sid = writer.register_schema(spec.schema_name, "jsonschema", spec.schema_data)
                cid = ids[topic] = writer.register_channel(topic, "json", sid)
            writer.add_message(cid, log_ns, encode(payload), pub_ns)
            if flush_s is not None and time.monotonic() >= next_flush:
                writer.flush()
                os.fsync(f.fileno())
                next_flush = time.monotonic() + flush_s
        writer.finish()
        f.flush()
        os.fsync(f.fileno())
    return {"wall_s": time.perf_counter() - w0, "cpu_s": time.process_time() - c0, "file_bytes": path.stat().st_size}


def run_recorder(stream: list[Item], out: Path, settings: RecorderSettings) -> dict[str, float]:
    settings.out_dir = out
    settings.queue_size = len(stream) + 16
    recorder = Recorder(settings, TOPICS)
    c0, w0 = time.process_time(), time.perf_counter()
    recorder.start()
    t0 = time.thread_time()
    submit = recorder.submit
    refused = sum(1 for topic, payload, log_ns, pub_ns in stream if not submit(topic, payload, log_ns, pub_ns))
    submit_cpu = time.thread_time() - t0
    recorder.stop(timeout_s=3600.0)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    status = recorder.status()
    return {"wall_s": wall, "cpu_s": cpu, "file_bytes": sum(p.stat().st_size for p in out.glob("*.mcap")),
            "submit_us": submit_cpu / len(stream) * 1e6, "refused": refused, "state": status.state,
            "written": sum(status.written.values())}


def measure(stream: list[Item], repeat: int, settings: Callable[[], RecorderSettings]) -> dict[str, Any]:
    """Each writer's best figures over ``repeat`` rounds, the writers taking turns."""
    payload_bytes = sum(len(encode(p)) for _, p, _, _ in stream)
    runs: dict[str, list[dict[str, float]]] = {"bare": [], "mcap Writer": [], "bare + flush": [], "recorder": []}
    with tempfile.TemporaryDirectory(prefix="bench-recorder-") as tmp:
        for i in range(repeat):
            runs["bare"].append(run_bare(stream, Path(tmp) / f"bare{i}.mcap", settings(), None))
            runs["mcap Writer"].append(run_bare(stream, Path(tmp) / f"lib{i}.mcap", settings(), None,
                                                mcap_library_writer))
            flush_s = settings().flush_interval_s
            runs["bare + flush"].append(run_bare(stream, Path(tmp) / f"flush{i}.mcap", settings(), flush_s))
            folder = Path(tmp) / f"rec{i}"
            folder.mkdir()
            runs["recorder"].append(run_recorder(stream, folder, settings()))
    n = len(stream)
    out: dict[str, Any] = {"messages": n, "payload_mb": payload_bytes / 1e6,
                           "mean_payload_bytes": payload_bytes / n, "writers": {}}
    for name, rs in runs.items():
        wall = min(r["wall_s"] for r in rs)
        cpu = min(r["cpu_s"] for r in rs)
        out["writers"][name] = {"wall_s": wall, "cpu_s": cpu, "msgs_per_s": n / wall,
                                "mb_per_s": payload_bytes / 1e6 / wall, "cpu_us_per_msg": cpu / n * 1e6,
                                "file_mb": statistics.median(r["file_bytes"] for r in rs) / 1e6}
        if name == "recorder":
            out["writers"][name]["submit_us"] = min(r["submit_us"] for r in rs)
            out["writers"][name]["refused"] = max(r["refused"] for r in rs)
            out["writers"][name]["written_ok"] = all(r["written"] == n and r["state"] == "stopped" for r in rs)
    bare = out["writers"]["bare"]
    for w in out["writers"].values():
        w["cpu_vs_bare"] = w["cpu_us_per_msg"] / bare["cpu_us_per_msg"]
        w["wall_vs_bare"] = w["wall_s"] / bare["wall_s"]
    return out


def render(result: dict[str, Any]) -> list[str]:
    lines = ["| stream | writer | messages/s | MB/s (JSON payload) | CPU per message | CPU vs bare | wall vs bare "
             "| file |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, s in result["streams"].items():
        for writer, w in s["writers"].items():
            lines.append(f"| {name} ({s['messages']} records, {s['mean_payload_bytes']:.0f} B each) | {writer} "
                         f"| {w['msgs_per_s']:,.0f} | {w['mb_per_s']:.2f} | {w['cpu_us_per_msg']:.1f} us "
                         f"| {w['cpu_vs_bare']:.2f}x | {w['wall_vs_bare']:.2f}x | {w['file_mb']:.1f} MB |")
    lines.append("")
    for name, s in result["streams"].items():
        r = s["writers"]["recorder"]
        lines.append(f"- {name}: a sampler thread's `submit` costs {r['submit_us']:.1f} us per record; records "
                     f"refused {r['refused']}; every record written and the file finished: "
                     f"{'yes' if r['written_ok'] else 'NO'}.")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", type=Path, nargs="+", help="a recorded drive (its records make the stream)")
    ap.add_argument("--messages", type=int, default=200_000, help="records per stream (default 200000)")
    ap.add_argument("--repeat", type=int, default=3, help="rounds per writer; the best counts (default 3)")
    ap.add_argument("--json", type=Path, help="write the result here as JSON")
    args = ap.parse_args(argv)
    missing = [str(f) for f in args.files if not f.is_file()]
    if missing:
        ap.error(f"no such file: {', '.join(missing)}")
    if args.messages < 100 or args.repeat < 1:
        ap.error("--messages must be at least 100 and --repeat at least 1")
    result: dict[str, Any] = {"streams": {}, "compression": RecorderSettings(Path()).compression,
                              "chunk_mb": RecorderSettings(Path()).chunk_size_bytes / 2**20,
                              "flush_interval_s": RecorderSettings(Path()).flush_interval_s}
    drive = read_drive(args.files)
    imu = imu_topic(drive)
    for name, only in (("drive mix", None), (f"{imu} only", imu)):
        stream = load_stream(drive, args.messages, only)
        result["streams"][name] = measure(stream, args.repeat, lambda: RecorderSettings(Path()))
        print(f"{name}: " + ", ".join(f"{w} {v['msgs_per_s']:,.0f} msg/s, {v['cpu_us_per_msg']:.1f} us CPU/msg"
                                      for w, v in result["streams"][name]["writers"].items()), flush=True)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
