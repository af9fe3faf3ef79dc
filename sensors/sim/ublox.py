"""A u-blox receiver at the far end of a serial line, driven by the truth of a simulated drive.

The model plays the device side of a :class:`~sensors.sim.pty.PtyPort`: a driver opens the port with
pyserial and cannot tell it from a NEO-M8 on a USB-serial adapter. It runs its own thread and keeps its
schedule on the true drive time of a :class:`~sensors.sim.clock.DriveClock`, so a test steps it with a
``ManualClock`` (and :meth:`UbloxReceiverModel.sync`) while the daemon runs it on a scaled clock.

What it does, as the hardware does:

- a navigation epoch every ``measRate`` ms aligned to the configured time scale (UBX-CFG-RATE; the
  receiver boots with ``meas_period_ms``), the solution computed some tens to a few hundred ms later and
  put out in epoch order; per epoch UBX NAV-PVT and NAV-TIMEGPS, NMEA GGA, RMC and GSA, and once a second a
  UBX TIM-TP announcing the next time pulse, each at the rate UBX-CFG-MSG (or the configuration keys) set on
  the port;
- with ``ubx=False``, a receiver that speaks NMEA only (an ST TESEO such as the paper's AEK-4T): no UBX
  output at all, and UBX input ignored, so configuration commands and polls go unanswered, as a receiver
  that does not know the protocol leaves them. It still drives its time pulse;
- the UART at its baud rate: messages take their transmission time, a full transmit buffer drops
  messages, and a host listening at another baud rate receives what a real UART would (see
  :mod:`sensors.sim.uart_line`);
- configuration answered with ACK-ACK / ACK-NAK. ``generation`` picks the configuration interface:
  8 (M8: legacy UBX-CFG-MSG/RATE/PRT only; CFG-VALSET is unknown and NAKed), 9 (F9: both), 10 (M10:
  configuration keys only; the legacy messages are NAKed). A legacy CFG-PRT baud change is acknowledged at
  the old rate and takes effect after the ACK; a CFG-VALSET baud change takes effect at once, so its ACK
  comes at the new rate. CFG messages outside these are NAKed, as not modelled, so a test notices. The
  interpreter and the RAM configuration it keeps are in :mod:`sensors.sim.ublox_commands`;
- GNSS errors from :mod:`sensors.sim.gnss_errors`, with the error of every epoch kept in
  :attr:`UbloxReceiverModel.history` (as :class:`~sensors.sim.ublox_encode.EpochRecord`, which the
  message encoders of :mod:`sensors.sim.ublox_encode` turn into bytes) so a decoded solution can be
  checked against truth + error;
- faults on demand: garbage bytes, corrupted checksums, unplugging (the PtyPort vanishes), power cycles;
- ``model`` names the product (:data:`~sensors.sim.ublox_commands.RECEIVER_MODELS`: NEO-M8N, NEO-M8T, ZED-F9P):
  its generation, its MON-VER, and whether it takes RXM-RAWX and RXM-SFRBX. Once the host turns them on, the
  frames ``raw_frames`` makes of each epoch (a callable of the :class:`EpochRecord`, returning serialised UBX
  frames) go out before the epoch's NAV messages; without it the receiver acknowledges them and sends none;
- ``sent_log``, a binary file, receives every byte written to the line, as the host's UART gets it, so a test
  can hold what the host recorded against what the receiver sent.

A PPS line model of the same receiver shares :attr:`UbloxReceiverModel.timeline` (edges on whole GPS
seconds, :meth:`~sensors.sim.gnss_time.GnssTimeline.pulse_drive_ns`), its ``pulse_quantisation`` (the
edge's offset that TIM-TP announces as qErr) and :func:`has_time_fix` (no pulse without a time solution).
"""

from __future__ import annotations

import heapq
import itertools
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import BinaryIO

import numpy as np
from pynmeagps import NMEAMessage
from pyubx2 import UBXMessage

from sensors.sim import earth
from sensors.sim.clock import DriveClock
from sensors.sim.gnss_errors import (
    MAX_SATELLITES,
    GeometryErrorModel,
    GnssErrorModel,
    fix_type_for,
    has_time_fix,
    satellites_tracked,
)
from sensors.sim.gnss_time import NS_PER_MS, NS_PER_S, GnssTimeline, PulseQuantisation
from sensors.sim.profile import SOLUTION_JITTER_MAX_S, SOLUTION_JITTER_S, SOLUTION_LATENCY_S
from sensors.sim.pty import PtyPort
from sensors.sim.truth import Trajectory
from sensors.sim.uart_line import STANDARD_BAUDS, HostSide, resample
from sensors.sim.ublox_commands import (
    DEFAULT_BAUD,
    FIRMWARE,
    RECEIVER_MODELS,
    TIME_REF_OFFSET_S,
    CommandInterpreter,
    PortConfig,
    RamConfig,
    Reply,
    UbxInputScanner,
)
from sensors.sim.ublox_encode import (
    MESSAGE_IDS,
    EpochRecord,
    gga,
    gll,
    gsa,
    gsv,
    nav_pvt,
    nav_timegps,
    rmc,
    tim_tp,
    vtg,
)

__all__ = [
    "DEFAULT_MESSAGES",
    "FACTORY_MESSAGES",
    "NMEA_ONLY_MESSAGES",
    "ModelCounters",
    "UbloxReceiverModel",
    "has_time_fix",
]

DEFAULT_MESSAGES = ("NAV-PVT", "TIM-TP", "GGA", "RMC")  # a receiver whose flash holds the logger's setup
# Fresh from the factory: NMEA only, u-blox's default set (TXT aside): 649 bytes a second under the urban drive's
# sky (21 satellites in three GSV series, GSV 56 % of it; /var/tmp/b49/gsvshare.py), two thirds of a 9600-baud line
# before any UBX message is added.
FACTORY_MESSAGES = ("GGA", "GLL", "GSA", "GSV", "RMC", "VTG")
# An NMEA-only receiver's output: position, speed and course, and the DOPs; no GST, so no accuracy figures, and
# no vertical velocity (NMEA has none).
NMEA_ONLY_MESSAGES = ("GGA", "RMC", "GSA")

_HOST_BUFFER_BYTES = 4095  # Linux n_tty read buffer: beyond it a host that does not read loses bytes
_MIN_MOVING_MPS = 0.5  # below this speed the receiver keeps its last heading of motion
_CLOCK_HOLDOVER_NS_PER_S = 100.0  # growth of tAcc without a fix: a TCXO known to 0.1 ppm
_UBX_HDR = b"\xb5\x62"
# An epoch served this late (by a model thread the host woke late) puts its messages out late: past a quarter
# of a second, fixes bunch and a paced drive slows down (DriveClock.late).
EPOCH_LATE_TOLERANCE_NS = 250_000_000


@dataclass(slots=True)
class ModelCounters:
    """What the model did, for tests and the soak report."""

    sent: dict[str, int] = field(default_factory=dict)
    bytes_written: int = 0  # to the pty, after the UART line (what the host can read)
    tx_overflow_drops: int = 0  # messages dropped because the receiver's transmit buffer was full
    host_overrun_drops: int = 0  # messages lost because the host left its receive buffer full
    unplugged_drops: int = 0
    acks: int = 0
    naks: int = 0
    garbage_bytes: int = 0
    corrupted: int = 0
    input_frames: int = 0


@dataclass(order=True, slots=True)
class _TxItem:
    ready_ns: int
    seq: int
    data: bytes = field(compare=False)
    label: str = field(compare=False)
    after: Callable[[], None] | None = field(compare=False, default=None)


def _child_rngs(seed: int | np.random.Generator, n: int) -> list[np.random.Generator]:
    """Independent generators, so that (say) command timing never shifts the GNSS error sequence."""
    if isinstance(seed, np.random.Generator):
        return [np.random.default_rng(int(seed.integers(2**63))) for _ in range(n)]
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]


class UbloxReceiverModel:
    """A u-blox receiver (M8 by default) playing the device end of ``port``, driven by ``trajectory``."""

    def __init__(
        self,
        port: PtyPort,
        clock: DriveClock,
        trajectory: Trajectory,
        *,
        seed: int | np.random.Generator = 0,
        timeline: GnssTimeline | None = None,
        generation: int = 8,
        baud: int | None = None,
        messages: Iterable[str] = DEFAULT_MESSAGES,
        nmea_talker: str = "GN",
        time_to_first_fix_s: float = 1.0,
        pulse_time_base: str = "utc",
        error_model: GnssErrorModel | None = None,
        max_satellites: int = MAX_SATELLITES,
        tx_buffer_bytes: int = 4096,
        min_meas_period_ms: int = 25,
        meas_period_ms: int = 1000,
        ubx: bool = True,
        latency_s: tuple[float, float] = (SOLUTION_LATENCY_S, SOLUTION_JITTER_S),
        history_len: int = 3600,
        poll_s: float = 0.002,
        model: str | None = None,
        raw_frames: Callable[[EpochRecord], Iterable[bytes]] | None = None,
        sent_log: BinaryIO | None = None,
        usb: bool = False,
        leap_unconfirmed_s: float = 0.0,
    ) -> None:
        if model is not None and model not in RECEIVER_MODELS:
            raise ValueError(f"model must be one of {', '.join(RECEIVER_MODELS)}, not {model!r}")
        spec = RECEIVER_MODELS[model] if model is not None else None
        generation = spec.generation if spec is not None else generation
        if generation not in FIRMWARE:
            raise ValueError(f"generation must be one of {sorted(FIRMWARE)}, not {generation}")
        if pulse_time_base not in ("utc", "gps"):
            raise ValueError("pulse_time_base must be 'utc' or 'gps'")
        unknown = set(messages) - set(MESSAGE_IDS)
        if unknown:
            raise ValueError(f"the model cannot output {sorted(unknown)}; it knows {sorted(MESSAGE_IDS)}")
        self.port = port
        self.clock = clock
        self.trajectory = trajectory
        self.timeline = timeline or GnssTimeline()
        self.generation = generation
        self.nmea_talker = nmea_talker
        self.time_to_first_fix_s = float(time_to_first_fix_s)
        # A cold start: the leap count is the firmware's (NAV-TIMEGPS leapSValid clear) for this long after the
        # first fix, until the almanac's UTC page (12.5 min at most); the count itself is the right one here.
        self.leap_unconfirmed_s = float(leap_unconfirmed_s)
        self._known_since_ns: int | None = None
        self.pulse_time_base = pulse_time_base
        self.max_satellites = max_satellites
        self.tx_buffer_bytes = tx_buffer_bytes
        # The fastest epoch the firmware accepts: 25 ms is the protocol's floor; a product that runs at
        # most 10 Hz with two constellations NAKs anything below 100 ms.
        self.min_meas_period_ms = max(25, min_meas_period_ms)
        self.latency_s = latency_s  # (minimum, mean of the exponential excess) of the solution delay
        self.ubx = ubx
        self.poll_s = poll_s
        self.model = model
        self.raw_frames = raw_frames  # the epoch's RXM-RAWX / RXM-SFRBX frames, once the host turned them on
        self.sent_log = sent_log  # every byte put on the line; may be set while the model runs
        rng_err, rng_lat, rng_cmd, rng_garbage, rng_pulse = _child_rngs(seed, 5)
        self.errors = error_model or GnssErrorModel(rng_err)
        # A drive that describes its sky (satellite geometry, street canyons) gets errors through that geometry;
        # a bare trajectory keeps the simpler model driven by the visible sky fraction alone.
        self.sky = getattr(trajectory, "gnss_sky", None) if error_model is None else None
        self.geometry_errors = None if self.sky is None else GeometryErrorModel(
            rng_err, len(self.sky.constellation), **getattr(trajectory, "gnss_error_options", {}))
        self.pulse_quantisation = PulseQuantisation.from_seed(rng_pulse)
        self._rng_latency = rng_lat
        self._rng_garbage = rng_garbage
        start_baud = baud if baud is not None else DEFAULT_BAUD[generation]
        if start_baud not in STANDARD_BAUDS:
            raise ValueError(f"{start_baud} is not a baud rate a u-blox UART offers")
        if not self.min_meas_period_ms <= meas_period_ms <= 65535:
            raise ValueError(f"meas_period_ms must be {self.min_meas_period_ms}..65535, not {meas_period_ms}")
        # An NMEA-only receiver neither takes nor sends UBX: its port is NMEA in and out, for good.
        uart = PortConfig(start_baud, in_rtcm3=generation >= 9) if ubx else \
            PortConfig(start_baud, in_ubx=False, out_ubx=False, in_rtcm3=generation >= 9)
        startup = RamConfig(uart, meas_ms=meas_period_ms, rates={MESSAGE_IDS[m]: 1 for m in messages})
        # Without a named product: the generation's firmware, raw observations as its generic firmware has them (F9).
        raw = spec.raw if spec is not None else generation == 9
        self._commands = CommandInterpreter(generation, startup, rng_cmd, min_meas_period_ms=self.min_meas_period_ms,
                                            raw=raw, firmware=spec.firmware if spec is not None else None,
                                            link_port=3 if usb else 1)
        self.history: deque[EpochRecord] = deque(maxlen=history_len)
        self.counters = ModelCounters()
        self.error: BaseException | None = None

        self._host = HostSide(port.path)
        self._probe = HostSide(port.path)  # used by sync() on the caller's thread
        self._tx: list[_TxItem] = []
        self._seq = itertools.count()
        self._line_free_ns = 0
        self._input = UbxInputScanner()
        self._written_this_pass = 0
        self._pending: list[Callable[[int], None]] = []  # fault injections, run by the model thread
        self._corrupt_left = 0
        self._lock = threading.Lock()
        self._cv = threading.Condition()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._started_passes = 0
        self._completed_passes = 0
        self._power_on(clock.now_ns())

    # ------------------------------------------------------------------ life cycle

    def start(self) -> UbloxReceiverModel:
        if self._thread is not None:
            raise RuntimeError("the receiver model is already running")
        self._thread = threading.Thread(target=self._run, name="ublox-model", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise RuntimeError("the receiver model thread did not stop")
            self._thread = None
        self._host.close()
        self._probe.close()

    def __enter__(self) -> UbloxReceiverModel:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def sync(self, timeout_s: float = 5.0, settle: bool = True) -> None:
        """Return once the model has handled everything up to the clock's present, input included.

        With a ManualClock a test advances the clock and syncs, so every byte due by then has been
        written to the pty, whatever the host's scheduler did meanwhile. The kernel hands bytes from the
        pty master to the slave asynchronously; with ``settle`` sync also waits (at most ``timeout_s``)
        until the bytes written meanwhile can be read on the host side. That assumes nobody reads the port
        while sync runs, which holds when the caller is the reader; pass ``settle=False`` otherwise.
        """
        unread0 = self._probe.unread() if settle else -1
        written0 = self.counters.bytes_written
        with self._cv:
            target = self._started_passes
            self._wake.set()
            done = self._cv.wait_for(
                lambda: self._completed_passes > target or self.error is not None or self._thread is None,
                timeout_s,
            )
        if self.error is not None:
            raise RuntimeError("the receiver model failed") from self.error
        if self._thread is None:
            raise RuntimeError("the receiver model is not running")
        if not done:
            raise RuntimeError(f"the receiver model did not catch up within {timeout_s} s")
        if unread0 >= 0:
            expect = min(_HOST_BUFFER_BYTES, unread0 + self.counters.bytes_written - written0)
            deadline = time.monotonic() + timeout_s
            while 0 <= self._probe.unread() < expect and time.monotonic() < deadline:
                time.sleep(0.0002)

    # ------------------------------------------------------------------ faults

    def inject_garbage(self, n_bytes: int = 64) -> None:
        """Queue ``n_bytes`` of line noise into the output stream now."""
        self._post(lambda now: self._enqueue(
            now, self._rng_garbage.integers(0, 256, n_bytes, dtype=np.uint8).tobytes(), "garbage"))

    def corrupt_checksums(self, count: int = 1) -> None:
        """Damage the checksum of the next ``count`` messages sent (UBX or NMEA)."""
        def arm(_now: int) -> None:
            self._corrupt_left += count
        self._post(arm)

    def vanish(self) -> None:
        """Unplug the USB-serial adapter: the driver gets an error, the receiver keeps running."""
        self.port.vanish()

    def reappear(self, power_cycle: bool = False) -> None:
        """Plug the adapter back in; with ``power_cycle`` the receiver also restarts (RAM config lost)."""
        self.port.reappear()
        if power_cycle:
            self._post(self._power_on)

    def _post(self, action: Callable[[int], None]) -> None:
        with self._lock:
            self._pending.append(action)
        self._wake.set()

    # ------------------------------------------------------------------ state

    @property
    def _cfg(self) -> RamConfig:
        """The RAM configuration, as the command interpreter holds it (a VALSET or power cycle replaces it)."""
        return self._commands.ram

    @property
    def usb(self) -> bool:
        """On USB (CDC-ACM) the host's baud rate means nothing and bytes go at the bus's speed."""
        return self._commands.link_port != 1

    @property
    def baud(self) -> int:
        return self._cfg.port.baud

    @property
    def meas_period_ms(self) -> int:
        return self._cfg.meas_ms

    @property
    def latency_cap_s(self) -> float:
        """The longest a solution takes beyond the least latency: what M8s are seen to need at most at 1 Hz, but
        never more than the solution period (a receiver that took longer would fall behind its own rate)."""
        return min(SOLUTION_JITTER_MAX_S, self._cfg.meas_ms * self._cfg.nav_rate / 1000)

    def rate(self, message: str) -> int:
        """Output rate of a modelled message on the port (0 = off), as configured now."""
        return self._cfg.rates.get(MESSAGE_IDS[message], 0)

    def time_pulse_locked(self, t_s: float) -> bool:
        """Whether the receiver drives its time pulse at drive time ``t_s``: its first fix since power-on is
        behind it and the sky gives it a time solution. The ``has_fix`` a PPS line model wants."""
        if (t_s * NS_PER_S - self._power_on_ns) < self.time_to_first_fix_s * NS_PER_S:
            return False
        state = self.trajectory.state(min(t_s, self.trajectory.duration_s))
        if self.sky is not None:
            return fix_type_for(self.sky.num_sv(state)) >= 2
        return has_time_fix(state, self.max_satellites)

    def solution_for_itow(self, itow_ms: int) -> EpochRecord | None:
        for rec in reversed(self.history):
            if rec.itow_ms == itow_ms:
                return rec
        return None

    def _power_on(self, now_ns: int) -> None:
        """Start (again) as from power-up: the configuration the receiver boots with, no output pending,
        and a fix only after the time to first fix."""
        self._commands.power_on()
        self._tx.clear()
        self._input.clear()
        self._power_on_ns = now_ns
        self._time_known = False
        self._known_since_ns = None
        self._last_fix: EpochRecord | None = None
        self._last_solution_ns: int | None = None
        self._head_mot_deg = 0.0
        self._last_pulse_second = -1
        self._last_ready_ns = 0
        self._next_epoch_ns = self._epoch_after(now_ns)

    # ------------------------------------------------------------------ thread

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                with self._cv:
                    self._started_passes += 1
                self._wake.clear()
                self._service()
                with self._cv:
                    self._completed_passes = self._started_passes
                    self._cv.notify_all()
                self._wake.wait(self.poll_s)
        except BaseException as exc:  # reported through sync(); a model must never die silently
            self.error = exc
            with self._cv:
                self._cv.notify_all()

    def _service(self) -> None:
        now = self.clock.now_ns()
        self._written_this_pass = 0
        with self._lock:
            pending, self._pending = self._pending, []
        for action in pending:
            action(now)
        self._advance(now)
        data = self.port.read(0.0, 65536)
        if data:
            host_out = self._host.speeds()[1]  # the host's bytes went out at its output speed
            self._receive(data if self.usb else resample(data, host_out or 0, self._cfg.port.baud), now)
        self._advance(now)

    def _advance(self, now: int) -> None:
        """Run epochs and transmissions in time order up to ``now``."""
        while True:
            t_tx = math.inf
            if self._tx:
                head = self._tx[0]
                t_tx = max(head.ready_ns, self._line_free_ns) + self._tx_ns(len(head.data))
            t_epoch = self._next_epoch_ns
            if min(t_tx, t_epoch) > now:
                return
            if t_epoch <= t_tx:
                self._next_epoch_ns = self._epoch_after(t_epoch)
                self.clock.late(now - t_epoch, EPOCH_LATE_TOLERANCE_NS)
                self._epoch(t_epoch)
            else:
                item = heapq.heappop(self._tx)
                self._line_free_ns = int(t_tx)
                self._transmit(item)
                if item.after is not None:
                    item.after()

    def _tx_ns(self, n_bytes: int) -> int:
        if self.usb:
            return n_bytes * 1000  # a full-speed USB bulk endpoint: about a megabyte a second
        return -(-n_bytes * 10 * NS_PER_S // self._cfg.port.baud)  # 8N1: ten bit times a byte

    def _enqueue(self, ready_ns: int, data: bytes, label: str, after: Callable[[], None] | None = None) -> None:
        pending = sum(len(i.data) for i in self._tx)
        if pending + len(data) > self.tx_buffer_bytes:
            self.counters.tx_overflow_drops += 1
            return
        heapq.heappush(self._tx, _TxItem(int(ready_ns), next(self._seq), data, label, after))

    def _transmit(self, item: _TxItem) -> None:
        data = item.data
        if item.label == "garbage":
            self.counters.garbage_bytes += len(data)
        elif self._corrupt_left > 0:
            self._corrupt_left -= 1
            self.counters.corrupted += 1
            data = self._corrupt(data)
        host_in, _ = self._host.speeds()
        wire = data if self.usb else resample(data, self._cfg.port.baud, host_in)
        unread = self._host.unread()
        if unread < 0 or not self.port.present:
            self.counters.unplugged_drops += 1
            return
        if unread + self._written_this_pass + len(wire) > _HOST_BUFFER_BYTES:
            self.counters.host_overrun_drops += 1
            return
        self.port.write(wire)
        if self.sent_log is not None:
            self.sent_log.write(wire)
        self._written_this_pass += len(wire)
        self.counters.bytes_written += len(wire)
        self.counters.sent[item.label] = self.counters.sent.get(item.label, 0) + 1

    @staticmethod
    def _corrupt(data: bytes) -> bytes:
        if data.startswith(_UBX_HDR):
            return data[:-1] + bytes([data[-1] ^ 0x5A])
        star = data.rfind(b"*")
        if star >= 0:  # NMEA: a checksum that is valid hex but wrong
            wrong = (int(data[star + 1:star + 3], 16) ^ 0x5A) & 0xFF
            return data[:star + 1] + f"{wrong:02X}".encode() + data[star + 3:]
        return data

    # ------------------------------------------------------------------ epochs

    def _epoch_after(self, drive_ns: int) -> int:
        """Drive time of the first measurement epoch strictly after ``drive_ns``."""
        meas_ns = self._cfg.meas_ms * NS_PER_MS
        offset_ns = self._time_scale_offset_ns()
        gps = self.timeline.gps_ns(drive_ns) + offset_ns
        return self.timeline.drive_ns((gps // meas_ns + 1) * meas_ns - offset_ns)

    def _time_scale_offset_ns(self) -> int:
        offset_s = TIME_REF_OFFSET_S[self._cfg.time_ref]
        if offset_s is None:  # UTC-based scales: UTC itself or GLONASS time (UTC + 3 h)
            offset_s = -self.timeline.leap_s
        return offset_s * NS_PER_S

    def _epoch(self, t_ns: int) -> None:
        meas_ns = self._cfg.meas_ms * NS_PER_MS
        gps_ns = self.timeline.gps_ns(t_ns)
        index = (gps_ns + self._time_scale_offset_ns()) // meas_ns
        if index % self._cfg.nav_rate:
            return  # a measurement without a navigation solution
        solution_index = index // self._cfg.nav_rate
        rec = self._solve(t_ns, gps_ns)
        excess = self._rng_latency.exponential(self.latency_s[1])
        ready = t_ns + round((self.latency_s[0] + min(excess, self.latency_cap_s)) * NS_PER_S)
        # One navigation engine: a solution is never put out before the previous epoch's, which matters once
        # epochs come faster than the latency varies (10 Hz).
        ready = self._last_ready_ns = max(ready, self._last_ready_ns)
        rates = self._cfg.rates

        def due(name: str, count: int) -> bool:
            r = rates.get(MESSAGE_IDS[name], 0)
            return r > 0 and count % r == 0

        known = self._time_known
        utc_ns = self._reported_utc_ns(rec)
        leap_s = self.timeline.leap_s
        if self.raw_frames is not None and (due("RXM-RAWX", solution_index) or self.rate("RXM-SFRBX") > 0):
            # Measurements come out before the solution computed from them; SFRBX as the subframes come.
            for frame in self.raw_frames(rec):
                label = "RXM-RAWX" if frame[2:4] == bytes(MESSAGE_IDS["RXM-RAWX"]) else "RXM-SFRBX"
                if due("RXM-RAWX", solution_index) if label == "RXM-RAWX" else self.rate(label) > 0:
                    self._enqueue_raw(ready, frame, label)
        if due("NAV-PVT", solution_index):
            pvt = nav_pvt(rec, utc_ns, time_known=known, position_known=self._last_fix is not None,
                          generation=self.generation)
            self._enqueue_ubx(ready, pvt, "NAV-PVT")
        if due("NAV-TIMEGPS", solution_index):
            leap_known = (self._known_since_ns is not None
                          and t_ns - self._known_since_ns >= self.leap_unconfirmed_s * NS_PER_S)
            self._enqueue_ubx(ready, nav_timegps(rec, leap_s=leap_s, time_known=known, leap_known=leap_known),
                              "NAV-TIMEGPS")
        if due("GGA", solution_index):
            self._enqueue_nmea(ready, gga(rec, utc_ns if known else None, talker=self.nmea_talker), "GGA")
        if due("RMC", solution_index):
            self._enqueue_nmea(ready, rmc(rec, utc_ns if known else None, talker=self.nmea_talker), "RMC")
        if due("GSA", solution_index):
            self._enqueue_nmea(ready, gsa(rec, talker=self.nmea_talker), "GSA")
        if due("GLL", solution_index):
            self._enqueue_nmea(ready, gll(rec, utc_ns if known else None, talker=self.nmea_talker), "GLL")
        if due("VTG", solution_index):
            self._enqueue_nmea(ready, vtg(rec, talker=self.nmea_talker), "VTG")
        if due("GSV", solution_index):
            for sentence in gsv(rec):
                self._enqueue_nmea(ready, sentence, "GSV")
        second = gps_ns // NS_PER_S
        if second != self._last_pulse_second:
            self._last_pulse_second = second
            # The pulse is locked, and announced, only while the clock is solved (see has_time_fix).
            if rec.fix_type >= 2 and due("TIM-TP", second):
                pulse = second + 1
                tp = tim_tp(pulse, leap_s=leap_s, utc_base=self.pulse_time_base == "utc",
                            qerr_ps=self.pulse_quantisation.qerr_ps(pulse), utc_known=known)
                self._enqueue_ubx(ready, tp, "TIM-TP")

    def _tracking(self, t_ns: int) -> bool:
        return (t_ns - self._power_on_ns) >= self.time_to_first_fix_s * NS_PER_S

    def _enqueue_ubx(self, ready: int, msg: UBXMessage, label: str) -> None:
        if self._cfg.port.out_ubx:
            self._enqueue(ready, msg.serialize(), label)

    def _enqueue_raw(self, ready: int, frame: bytes, label: str) -> None:
        if self._cfg.port.out_ubx:
            self._enqueue(ready, frame, label)

    def _enqueue_nmea(self, ready: int, msg: NMEAMessage, label: str) -> None:
        if self._cfg.port.out_nmea:
            self._enqueue(ready, msg.serialize(), label)

    def _solve(self, t_ns: int, gps_ns: int) -> EpochRecord:
        """The navigation solution of one epoch: truth plus the error model, or the last fix held."""
        dur = self.trajectory.duration_s
        truth = self.trajectory.state(min(t_ns / NS_PER_S, dur))
        dt_s = 1.0 if self._last_solution_ns is None else (t_ns - self._last_solution_ns) / NS_PER_S
        self._last_solution_ns = t_ns
        if self.sky is not None and self.geometry_errors is not None:
            view = self.sky.view(truth)
            if not self._tracking(t_ns):
                view = replace(view, az=view.az[:0], el=view.el[:0], reflected=view.reflected[:0], ids=view.ids[:0])
            err = self.geometry_errors.step(dt_s, view)
            num_sv = view.num_sv if math.isfinite(err.h_acc_m) else min(view.num_sv, 2)  # masked: no fix
            names = self.sky.constellation.names
            satellites = tuple(
                (names[i], math.degrees(e), math.degrees(a) % 360.0, round(30 + 15 * math.sin(e) - 8 * r))
                for i, e, a, r in zip(view.ids.tolist(), view.el.tolist(), view.az.tolist(), view.reflected.tolist(),
                                      strict=True))
        else:
            satellites = ()
            num_sv = satellites_tracked(truth.sky_open, self.max_satellites) if self._tracking(t_ns) else 0
            err = self.errors.step(dt_s, truth.sky_open, num_sv)
        fix_type = fix_type_for(num_sv)
        rn, re = earth.radii(truth.lat_rad)
        last = self._last_fix
        itow_ms = (GnssTimeline.week_tow(gps_ns)[1] + NS_PER_MS // 2) // NS_PER_MS
        if fix_type >= 2:
            pos_err = err.pos_ned_m.copy()
            v_acc = err.v_acc_m
            if fix_type == 2:  # 2D: the height is held at the last one known
                held = last.height_m if last is not None else truth.height_m - pos_err[2]
                pos_err[2] = truth.height_m - held  # down error
                v_acc = math.hypot(err.v_acc_m, pos_err[2])
            vel = truth.vel_ned_mps + err.vel_ned_mps
            if fix_type == 2:
                vel = np.array([vel[0], vel[1], 0.0])
            lat = math.degrees(truth.lat_rad + pos_err[0] / (rn + truth.height_m))
            lon = math.degrees(truth.lon_rad + pos_err[1] / ((re + truth.height_m) * math.cos(truth.lat_rad)))
            height = truth.height_m - pos_err[2]
            if not self._time_known:
                self._known_since_ns = t_ns
            self._time_known = True
            rec = EpochRecord(t_ns, gps_ns, itow_ms, truth, fix_type, num_sv, lat, lon, height, vel, pos_err,
                              vel - truth.vel_ned_mps, err.time_ns, err, err.h_acc_m, v_acc, err.s_acc_mps,
                              err.t_acc_ns)
            self._last_fix = rec
        elif last is not None:  # no fix now: the last position is kept, its accuracy grows to bound it
            pos_err = np.array([
                (math.radians(last.lat_deg) - truth.lat_rad) * (rn + truth.height_m),
                (math.radians(last.lon_deg) - truth.lon_rad) * (re + truth.height_m) * math.cos(truth.lat_rad),
                truth.height_m - last.height_m,
            ])
            held_s = (t_ns - last.drive_ns) / NS_PER_S
            h_acc = max(last.h_acc_m, 1.5 * math.hypot(pos_err[0], pos_err[1]))
            v_acc = max(last.v_acc_m, 1.5 * abs(pos_err[2]))
            s_acc = max(last.s_acc_mps, 1.5 * float(np.linalg.norm(truth.vel_ned_mps)))
            rec = EpochRecord(t_ns, gps_ns, itow_ms, truth, 0, num_sv, last.lat_deg, last.lon_deg, last.height_m,
                              np.zeros(3), pos_err, -truth.vel_ned_mps, last.time_error_ns, err, h_acc, v_acc,
                              s_acc, last.t_acc_ns + _CLOCK_HOLDOVER_NS_PER_S * held_s)
        else:  # nothing known yet: u-blox reports zeros and no accuracy at all
            rec = EpochRecord(t_ns, gps_ns, itow_ms, truth, 0, num_sv, 0.0, 0.0, 0.0, np.zeros(3),
                              np.full(3, math.nan), -truth.vel_ned_mps, 0.0, err, math.inf, math.inf,
                              math.inf, math.inf)
        vn, ve = float(rec.vel_ned_mps[0]), float(rec.vel_ned_mps[1])
        g_speed = math.hypot(vn, ve)
        head_acc = 180.0
        if rec.fix_type >= 2 and g_speed >= _MIN_MOVING_MPS:  # slower: the heading is noise, keep the last
            self._head_mot_deg = math.degrees(math.atan2(ve, vn)) % 360.0
            head_acc = min(180.0, math.degrees(math.atan2(rec.s_acc_mps, g_speed)))
        rec = replace(rec, head_mot_deg=self._head_mot_deg, head_acc_deg=head_acc, satellites=satellites)
        self.history.append(rec)
        return rec

    def _reported_utc_ns(self, rec: EpochRecord) -> int:
        """UTC (Unix ns) of the epoch as the receiver states it: the true epoch plus its clock error."""
        return self.timeline.utc_unix_ns(rec.gps_ns + round(rec.time_error_ns))

    # ------------------------------------------------------------------ input and configuration

    def _receive(self, data: bytes, now: int) -> None:
        """Hand the host's UBX frames to the firmware's command interpreter, while UBX input is on."""
        for frame in self._input.feed(data):
            self.counters.input_frames += 1
            if self._cfg.port.in_ubx:
                reply = self._commands.handle(frame, now)
                if reply is not None:
                    self._send_reply(reply)
                    if reply.reschedule:
                        self._next_epoch_ns = self._epoch_after(now)

    def _send_reply(self, reply: Reply) -> None:
        """Queue the answer on the UART; with UBX output off it is lost, but what waits for it still happens."""
        if reply.ack is not None:
            if reply.ack:
                self.counters.acks += 1
            else:
                self.counters.naks += 1
        if not self._cfg.port.out_ubx:
            if reply.after is not None:
                reply.after()
            return
        last = len(reply.messages) - 1
        for i, msg in enumerate(reply.messages):
            self._enqueue(reply.ready_ns, msg.serialize(), msg.identity, reply.after if i == last else None)
