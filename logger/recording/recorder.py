"""The MCAP recorder: one writer thread behind a bounded queue.

Sensor threads hand over a record and return at once; a full queue is a counted drop, never a blocked sensor
(the PX4 logger's rule). The writer closes the open chunk and fsyncs at least every ``flush_interval_s``, so a
power cut loses about that much; it rotates files by duration and size, and stops recording with a clear state
before the disk is full rather than leave a file it cannot finish.

Handing over does not wake the writer: it wakes at each flush, at least every ``BATCH_WAIT_S``, or when a
quarter of the queue has filled, and writes everything waiting in one go. On a one-core board a thread woken per
record costs more than writing the record; batching costs nothing in safety, since a record is only durable at
the next flush either way and every flush first writes all that is queued.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import ujson

from logger import __version__
from logger.recording.files import CHANNEL_TABLE, LIVE_NAME, RUN_METADATA, hold_for_writing
from logger.recording.mcap_writer import McapWriter
from logger.recording.settings import RecorderSettings
from logger.recording.storage import storage_problem
from logger.recording.topics import TopicSpec
from logger.words import size_text
from sync.wallclock import boot_id

log = logging.getLogger(__name__)

BATCH_WAIT_S = 1.0  # longest real time a record waits in the queue between flushes
PROFILE = ""  # JSON messages with JSON schemas: no ROS profile
# The writer's heartbeat beats in a drain too, every this many records: a catch-up of 20000 records on a slow card
# takes longer than the daemon's staleness bounds, and between drains only it read as a writer stuck in the kernel
# ("not responding", systemd's watchdog no longer pinged) while it wrote.
HEARTBEAT_RECORDS = 64
CHANNEL_TABLE_S = 60.0  # the channel table (files.CHANNEL_TABLE) is written again this often, s of drive


@dataclass
class RecorderStatus:
    """What ``logger status`` shows of the recorder; a snapshot, safe to read from another thread."""

    state: str  # "starting", "recording", "disk-full", "failed", "stopped"
    detail: str
    file: str | None
    file_bytes: int
    files_done: int
    free_bytes: int | None
    # Records per topic on disk (fsynced): a record handed to the writer is counted here only once an fsync kept it.
    written: dict[str, int] = field(default_factory=dict)
    # Topics whose records each hold several samples (a FIFO read's /imu/batch, its stamps a list): the samples
    # written, what an operator counts by, beside the records.
    samples: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    unrecorded: dict[str, int] = field(default_factory=dict)  # arrived while recording was stopped
    # Handed to the writer but not yet fsynced (on disk at the next flush, or lost if it fails) ...
    buffered: dict[str, int] = field(default_factory=dict)
    # ... and handed to the writer but never on disk: the chunk they were in was lost to an I/O error (disk full,
    # a read-only remount, a deleted file).
    lost: dict[str, int] = field(default_factory=dict)
    # On disk once, then deleted while recording: the file that held them, or the whole output folder (taken out
    # of ``written`` and ``samples`` then, which count only what is on disk).
    deleted: dict[str, int] = field(default_factory=dict)
    deleted_samples: dict[str, int] = field(default_factory=dict)  # the samples those of a batch topic held
    # Failed because the storage the folder is on is not mounted (storage.py): a wait for the card, which a restart
    # of the service cannot end, unlike a writer that fails by itself.
    storage_missing: bool = False
    queue_depth: int = 0
    queue_size: int = 0
    # Per topic, the board time (t_mono_ns) of the newest record the last flush put on disk: what a power cut
    # now would keep. Everything of that topic up to it survives a kill; what came later waits for the next flush.
    on_disk_mono_ns: dict[str, int] = field(default_factory=dict)
    state_since_mono_ns: int = 0  # when the recorder entered its present state (the watchdog's "failing for")
    # Drive time spent not recording since start (disk-full or failed, the present spell included): what the
    # run's summary and the status row say, since "recorded 200 s" over 50 s of a full disk is not true.
    down_s: float = 0.0
    out_dir: str = ""  # the folder the files go to: named once, files by their names


def _json_default(value: Any) -> Any:
    tolist = getattr(value, "tolist", None)
    if tolist is not None:  # numpy arrays and scalars
        return tolist()
    raise TypeError(f"cannot encode {type(value).__name__}")


def encode(payload: Mapping[str, Any]) -> bytes:
    """A record as compact JSON. ujson writes the same values as the standard library for what records hold
    (floats as their shortest round-trip form, an exponent without its leading zero: ``1e-7`` for ``1e-07``) at
    2.4x its speed on a 1 kHz FIFO read's 240 floats, the recorder's largest cost at that rate. NaN and infinity
    raise ValueError, as with ``json.dumps(..., allow_nan=False)``. Beyond what records hold it differs: a bool
    key is written ``"True"``, DEL unescaped, numpy integer keys and Decimal accepted, a dict holding itself
    refused with ValueError (the standard library raised RecursionError)."""
    try:
        return ujson.dumps(payload, ensure_ascii=True, escape_forward_slashes=False, allow_nan=False,
                           default=_json_default).encode()
    except OverflowError as exc:  # ujson's word for a value JSON cannot hold
        raise ValueError(str(exc)) from None


def default_file_name(prefix: str, now_unix_ns: int | None, sequence: int) -> str:
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime((now_unix_ns or time.time_ns()) / 1e9))
    return f"{prefix}_{stamp}_{sequence:04d}.mcap"


def read_boot_id() -> str:
    """Eight hex digits of the kernel's random boot id: tells this boot's files from every other boot's.

    Falls back to random digits per process where /proc is not there; unique is what matters, not stable.
    """
    text = boot_id()
    if text is None:
        return os.urandom(4).hex()
    digits = "".join(c for c in text.lower() if c in "0123456789abcdef")
    return digits[:8] if len(digits) >= 8 else os.urandom(4).hex()


DOWN_STATES = ("disk-full", "failed")  # the recorder runs but writes nothing (it retries every RETRY_S)
RETRY_S = 5.0


def new_run_id() -> str:
    """Eight random hex digits: one daemon start's files, told apart from every other start's."""
    return os.urandom(4).hex()


def run_tagged_name(name: str, run_id: str) -> str:
    """``name`` with the run id before its part number (``drive_boot-3a79384f_0001.mcap`` ->
    ``drive_boot-3a79384f_run-5c0ffee1_0001.mcap``): the name for a file whose plain name another start's file
    holds (a crash in the same boot left its boot-named 0001), so that the folder shows two starts' 0001s, not a
    0002 that reads as the crashed start's second part."""
    stem, dot, suffix = name.rpartition(".")
    head, _, part = stem.rpartition("_")
    return f"{head}_run-{run_id}_{part}{dot}{suffix}"


def boot_safe_file_name(prefix: str, boot_id: str, sequence: int) -> str:
    """A name that needs no wall clock, for files started before time is known (a board without an RTC).

    The boot id keeps boots apart and the sequence orders the files of one boot; the recorder renames the
    file to a dated name as soon as the clock knows the time (see ``synced_unix_ns``).
    """
    return f"{prefix}_boot-{boot_id}_{sequence:04d}.mcap"


class Recorder:
    """Writes records to rotating MCAP files from its own thread."""

    def __init__(self, settings: RecorderSettings, topics: Mapping[str, TopicSpec],
                 metadata: Mapping[str, Mapping[str, str]] | None = None,
                 file_name: Callable[[str, int | None, int], str] = default_file_name,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns, time_scale: float | Callable[[], float] = 1.0,
                 synced_unix_ns: Callable[[int], int | None] | None = None) -> None:
        self.settings = settings
        # Flush cadence and retries run on the drive's clock, so a simulated drive at 60x still closes its
        # chunk every drive second: what is lost at a cut is measured in the data's own time.
        self._mono_ns = monotonic_ns
        self._scale = time_scale if callable(time_scale) else (lambda fixed=float(time_scale): fixed)
        self.topics = dict(topics)
        self.metadata = {k: dict(v) for k, v in (metadata or {}).items()}
        self._file_name = file_name
        # With ``synced_unix_ns`` (monotonic time -> synchronised Unix time, None while the time is unknown),
        # names never come from the wall clock: a board without an RTC boots in the past. Files started before
        # the time is known get a boot-safe name and are renamed once it is; without it, the wall clock names.
        self._synced_unix_ns = synced_unix_ns
        self._boot_id = read_boot_id()
        self.run_id = new_run_id()
        self._tag_names = False  # once a name collided, this run's names all carry its run id
        self._unnamed: list[tuple[Path, int, int]] = []  # (path, start monotonic ns, sequence) awaiting a date
        # A deque behind one short lock (bound and append together, so the bound is exact with many producers):
        # unlike queue.Queue it does not notify the writer on every record.
        self._queue: deque[tuple[str, Mapping[str, Any], int, int]] = deque()
        self._queue_lock = threading.Lock()
        self._wake = threading.Event()  # set at a backlog of ``_wake_at`` records, and to stop
        self._wake_at = max(1, min(settings.queue_size // 4, 1024))
        self._stopping = False
        self._lock = threading.Lock()
        self._dropped: Counter[str] = Counter()  # queue full: the writer could not keep up
        self._unrecorded: Counter[str] = Counter()  # arrived while recording was stopped (disk full, I/O error)
        self._written: Counter[str] = Counter()  # on disk (an fsync kept them)
        self._samples: Counter[str] = Counter()
        self._pending: Counter[str] = Counter()  # handed to the writer since the last fsync
        self._pending_samples: Counter[str] = Counter()
        self._lost: Counter[str] = Counter()  # handed to the writer, never on disk (an I/O error)
        self._deleted: Counter[str] = Counter()  # on disk, then deleted with their file or folder
        self._deleted_samples: Counter[str] = Counter()
        self._storage_missing = False  # the last open was refused: the storage is not mounted (storage.py)
        # What is on disk in the open file and in the output folder as it is now (files of this run; a folder made
        # again starts at zero), records and samples, and the newest records on disk before either was started:
        # what a deleted file or folder takes with it.
        self._in_file: tuple[Counter[str], Counter[str]] = (Counter(), Counter())
        self._in_dir: tuple[Counter[str], Counter[str]] = (Counter(), Counter())
        self._on_disk_before_file: dict[str, int] = {}
        self._on_disk_before_dir: dict[str, int] = {}
        self._down_ns = 0  # drive time in DOWN_STATES before the present state
        self._newest_written: dict[str, int] = {}  # topic -> t_mono_ns of its newest record handed to the writer
        # Called from the writer thread with a topic the first time one of its records is written (start-up timing).
        self.on_first_record: Callable[[str], None] | None = None
        self._topics_written: set[str] = set()
        self._on_disk: dict[str, int] = {}  # ... and of its newest record fsynced
        self._state = "starting"
        self._detail = ""
        self._state_since = self._mono_ns()
        self._dir_id: tuple[int, int] | None = None  # (device, inode) of the output folder the open file is in
        # ... and that folder held open: a new folder at the next open (made again, or made by a user) tells only
        # through it whether the old one was deleted or moved away, between two files as well as during one
        self._dir_fd: int | None = None
        self._thread: threading.Thread | None = None
        self._writer: McapWriter | None = None
        self._stream: Any = None
        # The open (or last) file's size as of its last flush, kept by the writer thread: status() must not ask the
        # stream, whose tell() waits for a write stuck on a stalled card, while holding the lock that submit() needs
        # to count a drop (a frozen filesystem froze every sensor thread and the status socket).
        self._file_bytes = 0
        self._path: Path | None = None
        self._channels: dict[str, int] = {}
        # (name, content) -> schema id: two topics may share a schema's name (foxglove.LocationFix) but not its fields
        self._schemas: dict[tuple[str, bytes], int] = {}
        self._file_started_mono = 0.0
        self._first_log_ns: int | None = None
        self._first_pub_ns: int | None = None  # board (monotonic) time of the open file's first record
        self._sequence = 0  # the part number of the last file actually started (a failed open takes none)
        self._files_done = 0
        self._files: list[Path] = []  # every file this recorder started, by its current name
        self._free: int | None = None
        self._last_flush = 0.0
        self._table_written = 0.0
        self._next_retry = 0.0
        self.on_file_closed: Callable[[Path], None] | None = None
        # The writer thread's proof of life, on the drive's monotonic clock: the daemon stops petting systemd's
        # watchdog when it goes stale (a writer stuck in the kernel on a dying SD card).
        self.heartbeat_mono_ns = self._mono_ns()

    # ---- producer side (any thread) -------------------------------------------------------------------
    def submit(self, topic: str, payload: Mapping[str, Any], log_time_ns: int, publish_time_ns: int) -> bool:
        """Queue one record; False (and a counted drop) when the queue is full or recording has stopped."""
        if self._state in ("stopped", "disk-full", "failed"):
            with self._lock:
                self._unrecorded[topic] += 1
            return False
        q = self._queue
        with self._queue_lock:
            full = len(q) >= self.settings.queue_size
            if not full:
                q.append((topic, payload, log_time_ns, publish_time_ns))
        if full:
            with self._lock:
                self._dropped[topic] += 1
            return False
        if len(q) >= self._wake_at:
            self._wake.set()
        return True

    def files(self) -> list[Path]:
        """Every file this recorder started, oldest first, by its name now (boot-time names renamed once the time
        was known)."""
        with self._lock:
            return list(self._files)

    def status(self) -> RecorderStatus:
        with self._lock:
            down = self._down_ns
            if self._state in DOWN_STATES:
                down += self._mono_ns() - self._state_since
            return RecorderStatus(
                # Recording: the file it writes, under its name now (renamed once the time is known)
                state=self._state, detail=f"writing {self._path.name}" if self._state == "recording" and self._path
                else self._detail,
                file=str(self._path) if self._path else None,
                file_bytes=self._file_bytes,
                files_done=self._files_done, free_bytes=self._free,
                written=dict(self._written), samples=dict(self._samples), dropped=dict(self._dropped),
                unrecorded=dict(self._unrecorded), buffered=dict(self._pending), lost=dict(self._lost),
                deleted=dict(self._deleted), deleted_samples=dict(self._deleted_samples),
                storage_missing=self._storage_missing and self._state == "failed",
                queue_depth=len(self._queue), queue_size=self.settings.queue_size,
                on_disk_mono_ns=dict(self._on_disk), state_since_mono_ns=self._state_since,
                down_s=max(0, down) / 1e9, out_dir=str(self.settings.out_dir))

    # ---- life cycle --------------------------------------------------------------------------------------
    def start(self) -> Path | None:
        """Open the first file (so a bad output folder fails at start) and start the writer thread."""
        self._check_space_and_open()  # makes the folder, where its storage is there
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()
        return self._path

    def stop(self, timeout_s: float = 10.0) -> None:
        """Write what is queued, finish the file cleanly, and stop the thread."""
        if self._thread is None:
            return
        self._stopping = True
        self._wake.set()
        self._thread.join(timeout_s)
        self._thread = None

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _now(self) -> float:
        return self._mono_ns() / 1e9

    # ---- writer thread -----------------------------------------------------------------------------------
    def _run(self) -> None:
        interval = self.settings.flush_interval_s
        while True:
            self.heartbeat_mono_ns = self._mono_ns()
            wait = max(0.0, self._last_flush + interval - self._now()) / self._scale()
            if not self._stopping:
                self._wake.wait(min(wait, BATCH_WAIT_S))
                self._wake.clear()  # before draining: a backlog reached meanwhile is drained now
            try:
                self._drain()
                if self._stopping:
                    self._drain()
                    self._close_file()
                    self._hold_folder(None)
                    self._set_state("stopped", "recorder stopped")
                    return
                if self._now() - self._last_flush >= interval:
                    self._flush()
            except Exception as exc:  # the writer ends only at stop: anything else is a failure it reports
                log.exception("recorder: unexpected error")
                self._io_failed(exc)
                if self._stopping:
                    self._hold_folder(None)  # the storage is not kept busy by a recorder that has stopped
                    self._set_state("stopped", f"recorder stopped after an error: {type(exc).__name__}: {exc}")
                    return

    def _drain(self) -> None:
        """Write everything queued, oldest first (producers may go on appending meanwhile)."""
        q, write, n = self._queue, self._write, 0
        while q:
            write(q.popleft())
            n += 1
            if n == HEARTBEAT_RECORDS:
                self.heartbeat_mono_ns = self._mono_ns()
                n = 0

    def _write(self, item: tuple[str, Mapping[str, Any], int, int]) -> None:
        topic, payload, log_ns, pub_ns = item
        if self._writer is None:
            if self._now() >= self._next_retry:
                self._check_space_and_open()
            if self._writer is None:
                with self._lock:
                    self._unrecorded[topic] += 1
                return
        try:
            data = encode(payload)
        except (TypeError, ValueError) as exc:
            log.error("record on %s cannot be encoded as JSON (%s); dropped", topic, exc)
            with self._lock:
                self._dropped[topic] += 1
            return
        try:
            channel = self._channel(topic)
            self._writer.add_message(channel, log_ns, data, pub_ns)
        except OSError as exc:
            with self._lock:
                self._pending[topic] += 1  # handed over: lost with the rest of what was not yet on disk
            self._io_failed(exc)
            return
        if self._first_log_ns is None:
            self._first_log_ns, self._first_pub_ns = log_ns, pub_ns
        self._newest_written[topic] = pub_ns
        stamps = payload.get("t_sync_ns")
        with self._lock:
            self._pending[topic] += 1  # written once the next fsync keeps it (_kept_on_disk)
            if stamps.__class__ is list:  # a batch record: its samples' stamps
                self._pending_samples[topic] += len(stamps)
        if topic not in self._topics_written:
            self._topics_written.add(topic)
            if self.on_first_record is not None:
                self.on_first_record(topic)
        # By board time, not log time: before GNSS time is known a board without RTC logs at its boot date (1970, the
        # image's), and the log time then jumps at the lock: decades forward (the file cut there, its first part a
        # minute long with a "duration" of 56 years) or back (a clock a day ahead: no file rotated for a day).
        if self._first_pub_ns is not None and pub_ns - self._first_pub_ns >= self.settings.rotate_duration_s * 1e9:
            self._rotate()

    def _channel(self, topic: str) -> int:
        cid = self._channels.get(topic)
        if cid is not None:
            return cid
        assert self._writer is not None
        spec = self.topics.get(topic) or TopicSpec(topic, topic.strip("/").replace("/", "."), {"type": "object"},
                                                    "unregistered topic")
        key = (spec.schema_name, spec.schema_data)
        sid = self._schemas.get(key)
        if sid is None:
            sid = self._schemas[key] = self._writer.register_schema(spec.schema_name, "jsonschema", spec.schema_data)
        cid = self._writer.register_channel(topic, "json", sid, {"description": spec.description[:200]})
        self._channels[topic] = cid
        self._write_channel_table()
        return cid

    def _write_channel_table(self) -> None:
        """Channel ids and topics as a metadata record outside the chunks, again at every new channel and every
        CHANNEL_TABLE_S: the channel records live in the chunk where each was first used, so without this a damaged
        first chunk would leave every later message of the file without its topic."""
        assert self._writer is not None
        self._writer.add_metadata(CHANNEL_TABLE, {str(cid): topic for topic, cid in self._channels.items()})
        self._table_written = self._now()

    def _flush(self) -> None:
        self._last_flush = self._now()
        if self._unnamed:
            self._name_files_when_time_known()
        if self._writer is None:
            if self._state in ("disk-full", "failed") and self._now() >= self._next_retry:
                self._check_space_and_open()
            return
        try:
            self._writer.flush()
            os.fsync(self._stream.fileno())
        except OSError as exc:
            self._io_failed(exc)
            return
        lost = self._file_lost()
        if lost:  # the file is not where it is written: recording goes on in a new one
            problem, event, gone, kept = lost
            if gone:  # deleted: what it held (and the folder's other files, with the folder) is not on disk
                self._deleted_with(gone)
            elif kept:  # moved away or unmounted: what was just flushed is in it, wherever it is now
                self._kept_on_disk(True)
            self._io_failed(OSError(errno.ENOENT, event), problem, event)
            self._next_retry = self._now()  # a new file (in a recreated folder) at the next flush
            return
        self._kept_on_disk(True)
        if self._channels and self._now() - self._table_written >= CHANNEL_TABLE_S:
            self._write_channel_table()
        size = self._file_bytes = self._stream.tell()
        self._free = self._free_bytes()
        if self._free is not None and self._free < self.settings.min_free_bytes:
            name = self._path.name if self._path else "?"
            self._close_file()
            self._set_state("disk-full", self._disk_full_detail())
            log.error("recording stopped: %s free in %s, below the %s minimum; %s finished, retrying every %.0f s",
                      size_text(self._free), self.settings.out_dir, size_text(self.settings.min_free_bytes), name,
                      RETRY_S)
            self._next_retry = self._now() + RETRY_S
            return
        if size >= self.settings.rotate_size_bytes:
            self._rotate()

    def _file_lost(self) -> tuple[str, str, str, bool] | None:
        """Why the open file cannot be found where it is written (None when it can): deleted, or its folder deleted,
        replaced or gone (moved away, its storage unmounted); as (the problem, short and the same on every retry;
        the event for the log, with the folder; what went with it: "file" or "folder" when the file was deleted, ""
        when it was not or that is not known; whether the file still exists somewhere, its flushed records with
        it). Writes and fsyncs to an unlinked file succeed, so only this check notices. Deleted means unlinked: a
        folder that is gone while the open file still has a link was moved or unmounted (a card's lazy unmount),
        and its files, the open one up to its last flush, are on the card."""
        assert self._stream is not None
        out = self.settings.out_dir
        name = self._path.name if self._path else "the open file"
        try:
            linked = os.fstat(self._stream.fileno()).st_nlink > 0
        except OSError as exc:
            why = exc.strerror or str(exc)
            return f"its file cannot be checked: {why}", f"{name} in {out} cannot be checked: {why}", "", False
        try:  # the folder first: deleting it deletes the file too, and the folder is the news
            d = os.stat(out)
        except FileNotFoundError:
            if not linked:
                return ("the output folder was deleted", f"the output folder {out} was deleted while recording",
                        "folder", False)
            return ("the output folder is gone", f"the output folder {out} is gone while recording (moved away or "
                    f"its storage unmounted: {name} is not deleted, up to its last flush)", "", True)
        except OSError as exc:
            why = exc.strerror or str(exc)
            return (f"the output folder cannot be checked: {why}",
                    f"the output folder {out} cannot be checked: {why}", "", linked)
        if self._dir_id is not None and (d.st_dev, d.st_ino) != self._dir_id:
            if not linked:  # deleted and made again: its files went with it
                return ("the output folder was replaced",
                        f"the output folder {out} was deleted and made again while recording", "folder", False)
            return ("the output folder was replaced",
                    f"the output folder {out} was replaced while recording (moved away or its storage unmounted: "
                    f"{name} is not deleted, up to its last flush)", "", True)
        if not linked:
            return "its file was deleted", f"{name} was deleted from {out} while being written", "file", False
        return None

    def _deleted_with(self, gone: str) -> None:
        """The records on disk in the deleted file ("file") or in the whole output folder ("folder") are not on
        disk any more: counted deleted instead of written, and the newest on disk is what it was before them."""
        records, samples = (Counter(c) for c in (self._in_file if gone == "file" else self._in_dir))
        with self._lock:
            self._written.subtract(records)
            self._samples.subtract(samples)
            self._written += Counter()  # drops the topics left at zero
            self._samples += Counter()
            self._deleted.update(records)
            self._deleted_samples.update(samples)
            self._deleted_samples += Counter()
            self._on_disk = dict(self._on_disk_before_file if gone == "file" else self._on_disk_before_dir)
        self._newest_written = dict(self._on_disk)
        for c in (*self._in_file, *self._in_dir) if gone == "folder" else self._in_file:
            c.clear()
        if gone == "file":
            for held, went in zip(self._in_dir, (records, samples), strict=True):
                held.subtract(went)

    def _hold_folder(self, out: Path | None) -> None:
        """Hold the output folder ``out`` open in place of the last one (None: none)."""
        if self._dir_fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._dir_fd)
            self._dir_fd = None
        if out is not None:
            try:
                self._dir_fd = os.open(out, os.O_RDONLY | os.O_DIRECTORY)
            except OSError:
                self._dir_fd = None

    def _folder_deleted(self) -> bool:
        """Whether the output folder held open was deleted (no link left; moved away, it keeps one)."""
        if self._dir_fd is None:
            return False
        try:
            return os.fstat(self._dir_fd).st_nlink == 0
        except OSError:
            return False

    def _rotate(self) -> None:
        self._close_file()
        self._check_space_and_open()

    def _free_bytes(self) -> int | None:
        try:
            st = os.statvfs(self.settings.out_dir)
        except OSError:
            return None
        return st.f_bavail * st.f_frsize

    def _disk_full_detail(self) -> str:
        """The disk-full state's line, the same while the disk stays full (whichever way it was found: the minimum
        reached at a flush, ENOSPC in a write or an open), so the journal keeps it one problem; no file name."""
        free = "free space unknown" if self._free is None else f"{size_text(self._free)} free"
        minimum = (f", {size_text(self.settings.min_free_bytes)} minimum" if self.settings.min_free_bytes > 0
                   else "")
        return f"not recording: disk full ({free}{minimum})"

    def _check_space_and_open(self) -> None:
        """Start the next file, or say why not (and retry in RETRY_S). The part number is taken only by a file
        actually started: a drive's parts run 0001, 0002, ... from each start, which the name rule of the drive
        reader relies on for files without a run id."""
        missing = storage_problem(self.settings.out_dir)
        if missing is not None:
            if self._state not in DOWN_STATES or self._detail != f"not recording: {missing}":
                log.error("not recording into %s, which would be made on the filesystem underneath: %s; checking "
                          "again every %.0f s", self.settings.out_dir, missing.removesuffix("; waiting for it"),
                          RETRY_S)
            self._set_state("failed", f"not recording: {missing}")
            self._storage_missing = True
            self._free = None  # the free space shown was the card's, before it went
            self._next_retry = self._now() + RETRY_S
            return
        self._storage_missing = False
        self._free = self._free_bytes()
        if self._free is not None and self._free < self.settings.min_free_bytes:
            if self._state not in DOWN_STATES:
                log.error("not recording: %s free in %s, below the %s minimum; retrying every %.0f s",
                          size_text(self._free), self.settings.out_dir, size_text(self.settings.min_free_bytes),
                          RETRY_S)
            self._set_state("disk-full", self._disk_full_detail())
            self._next_retry = self._now() + RETRY_S
            return
        part = self._sequence + 1
        start_mono = self._mono_ns()
        start_unix = self._synced_unix_ns(start_mono) if self._synced_unix_ns is not None else None
        out = self.settings.out_dir
        path = out / self._name_at_open(start_unix, part)
        stream = None
        try:
            if not out.is_dir() and self._dir_id is None:  # no file yet: the configured folder, with its parents
                out.mkdir(parents=True)
                log.info("made the output folder %s", out)
            elif not out.is_dir() and out.parent.is_dir():
                # Deleted under a running recorder: made again where it was (not when its parent went too, and
                # never on a mount point whose storage is not mounted, storage_problem above: the root filesystem
                # must not stand in for the storage).
                out.mkdir()
                log.warning("the output folder %s was missing: made it again", out)
            if path.exists():  # another start's file (a crash in this boot left its boot-named 0001)
                self._tag_names = True
                path = out / self._name_at_open(start_unix, part)
            stream = open(path, "xb")  # noqa: SIM115 - lives until the file is finished
            hold_for_writing(stream)  # no recovery (a second logger's, `logger recover`) takes it meanwhile
            writer = McapWriter(stream, chunk_size=self.settings.chunk_size_bytes,
                                compression=self.settings.compression)
            writer.start(profile=PROFILE, library=f"{LIVE_NAME} {__version__}")
            # First after the header, outside any chunk: a reader finds it in the file's first bytes, cut or not.
            writer.add_metadata(RUN_METADATA, {"run": self.run_id, "part": str(part)})
            for name_, data in self.metadata.items():
                writer.add_metadata(name_, data)
            stream.flush()
            os.fsync(stream.fileno())
            d = os.stat(out)
        except OSError as exc:
            if stream is not None:  # a file that holds no record (disk full mid-header) is not left behind
                with contextlib.suppress(OSError):
                    stream.close()
                with contextlib.suppress(OSError):
                    path.unlink()
            full = exc.errno == errno.ENOSPC
            if self._state not in DOWN_STATES:  # each retry's failure is not news: the state says it lasts
                log.error("cannot open %s in %s: %s; retrying every %.0f s", path.name, out, exc.strerror or exc,
                          RETRY_S)
            else:
                log.debug("cannot open %s: %s", path.name, exc.strerror or exc)
            if full:
                self._free = self._free_bytes()
                self._set_state("disk-full", self._disk_full_detail())
            else:
                self._set_state("failed", f"not recording: {exc.strerror or exc}")  # as a failed write says it
            self._next_retry = self._now() + RETRY_S
            return
        self._sequence = part
        if self._dir_id != (d.st_dev, d.st_ino):  # a folder of its own (the first, or one made again)
            if self._dir_id is not None and sum(self._in_dir[0].values()) and self._folder_deleted():
                # Deleted between two files (a rotation's close and this open): the flushes' own check, which needs
                # an open file, never saw it, and the run's earlier files were still counted on disk.
                log.error("the output folder %s was deleted while recording", out)
                self._deleted_with("folder")
            for c in self._in_dir:
                c.clear()
            self._on_disk_before_dir = dict(self._on_disk)
            self._hold_folder(out)
        self._dir_id = (d.st_dev, d.st_ino)
        for c in self._in_file:
            c.clear()
        self._on_disk_before_file = dict(self._on_disk)
        with self._lock:
            self._writer, self._stream, self._path = writer, stream, path
            self._files.append(path)
            self._file_bytes = 0
        if self._synced_unix_ns is not None and start_unix is None:
            self._unnamed.append((path, start_mono, part))
        self._channels.clear()
        self._schemas.clear()
        self._first_log_ns = self._first_pub_ns = None
        self._file_started_mono = self._now()
        self._last_flush = self._now()
        self._set_state("recording", "")  # its detail is the open file's name (status)

    # ---- file names on a board that boots without knowing the time ------------------------------------------
    def _name_at_open(self, start_unix_ns: int | None, part: int) -> str:
        if self._synced_unix_ns is None:
            name = self._file_name(self.settings.prefix, self._first_log_ns, part)
        elif start_unix_ns is None:
            name = boot_safe_file_name(self.settings.prefix, self._boot_id, part)
        else:
            name = self._file_name(self.settings.prefix, start_unix_ns, part)
        return run_tagged_name(name, self.run_id) if self._tag_names else name

    def _name_files_when_time_known(self) -> None:
        """Rename this run's boot-named files (the open one included) to their start time, once it is known.

        The synchronised time of a file's start comes from its monotonic start, so a name given late is the
        same as one given at open would have been. Renaming an open file is safe: the writer holds its fd.
        """
        assert self._synced_unix_ns is not None
        still: list[tuple[Path, int, int]] = []
        for old, start_mono, sequence in self._unnamed:
            unix_ns = self._synced_unix_ns(start_mono)
            if unix_ns is None:
                still.append((old, start_mono, sequence))
                continue
            new = old.with_name(self._file_name(self.settings.prefix, unix_ns, sequence))
            if new.exists():  # another start's file of that second: this run's name says which run it is
                new = old.with_name(run_tagged_name(new.name, self.run_id))
            try:
                if new.exists():
                    raise FileExistsError(errno.EEXIST, "a file of that name exists", str(new))
                os.rename(old, new)
                _fsync_dir(old.parent)
            except OSError as exc:
                log.warning("could not rename %s to %s (%s); it keeps its boot-time name", old.name, new.name,
                            exc.strerror or exc)
                continue
            log.info("time known: %s renamed to %s", old.name, new.name)
            with self._lock:
                if self._path == old:
                    self._path = new
                self._files = [new if f == old else f for f in self._files]
        self._unnamed = still

    def _close_file(self) -> None:
        writer, stream, path = self._writer, self._stream, self._path
        if writer is None:
            return
        try:
            writer.finish()
            stream.flush()
            os.fsync(stream.fileno())
            self._kept_on_disk(True)
            self._file_bytes = stream.tell()
        except OSError as exc:
            log.error("could not finish %s in %s (%s); it will be recovered at the next start",
                      path.name if path else "?", self.settings.out_dir, exc.strerror or exc)
            self._kept_on_disk(False)
        finally:
            try:
                stream.close()
            except OSError:
                pass
            with self._lock:
                self._writer = None
                self._stream = None
                self._files_done += 1
        if self.on_file_closed is not None and path is not None:
            self.on_file_closed(path)

    def _kept_on_disk(self, kept: bool) -> None:
        """After an fsync: what was handed to the writer is on disk, and counted written; or (it failed) it is not
        and never will be: counted lost, since the chunk it was in is gone (recovery keeps only flushed chunks)."""
        with self._lock:
            if kept:
                self._on_disk.update(self._newest_written)
                self._written.update(self._pending)
                self._samples.update(self._pending_samples)
                for records, samples in (self._in_file, self._in_dir):
                    records.update(self._pending)
                    samples.update(self._pending_samples)
            else:
                self._lost.update(self._pending)
            self._pending.clear()
            self._pending_samples.clear()
        if not kept:
            self._newest_written = dict(self._on_disk)

    def _io_failed(self, exc: BaseException, problem: str = "", event: str = "") -> None:
        """A write failed: leave the file as it is (recovery keeps every flushed chunk) and stop writing until the
        next retry (a new file then)."""
        path = self._path
        try:
            if self._stream is not None:
                self._stream.close()
        except OSError:
            pass
        with self._lock:
            self._writer = None
            self._stream = None
        self._kept_on_disk(False)
        name = path.name if path else "?"
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            self._free = self._free_bytes()
            self._set_state("disk-full", self._disk_full_detail())
            what = "disk full"
        elif problem:
            self._set_state("failed", f"not recording: {problem}")
            what = problem
        elif isinstance(exc, OSError):
            self._set_state("failed", f"not recording: {exc.strerror or exc}")
            what = str(exc.strerror or exc)
        else:
            self._set_state("failed", f"not recording: {type(exc).__name__}: {exc}")
            what = f"{type(exc).__name__}: {exc}"
        where = event or f"{what} while writing {name} in {self.settings.out_dir}"
        log.error("recording stopped: %s; what was not yet flushed is lost; retrying every %.0f s", where, RETRY_S)
        self._next_retry = self._now() + RETRY_S

    def _set_state(self, state: str, detail: str) -> None:
        with self._lock:
            if state != self._state:
                now = self._mono_ns()
                if self._state in DOWN_STATES:
                    self._down_ns += now - self._state_since
                self._state_since = now
            self._state, self._detail = state, detail


def _fsync_dir(path: Path) -> None:
    """Make a rename survive a power cut: the directory entry is only durable once the directory is synced."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
