"""Adapters from each driver to what a sampler thread runs: open, read into records, close.

Here, and only here, a driver's result becomes a record: the acquisition time is read on the board's monotonic
clock right around the bus transfer, units go into the field names, and the topic is chosen. Drivers stay free
of clocks and threads; samplers stay free of sensor knowledge.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from logger.config import IMU_READS
from logger.recording.records import (
    baro_record,
    imu_batch_payload,
    imu_record,
    location_fix,
    pps_record,
    raw_bytes_record,
    speed_record,
    timepulse_record,
)
from logger.recording.topics import BARO, GNSS_FIX, GNSS_RAW, IMU, IMU_BATCH, OBD_SPEED, PPS, TIMEPULSE
from logger.runtime.sampler import Reading, Source
from logger.runtime.timebase import TimeBase
from sensors.errors import BusError, DeviceNotFound, ProtocolError, SensorError
from sensors.mpu6050 import FIFO_FRAME_BYTES, FIFO_SIZE_BYTES
from sensors.mpu6050_identity import WHO_AM_I_VALUE
from sensors.obd import SpeedDriver
from sync.fifo import FifoClock

log = logging.getLogger(__name__)

DIRECT_CHIP_RATE_HZ = 1000.0
# How long an event sensor's read waits for data before returning empty. Data ends the wait at once, so this
# only sets how often an idle thread wakes (to beat its heartbeat and see a stop): once a second is plenty for a
# 10 s staleness limit and a 5 s stop, and five times fewer wake-ups than 0.2 s on a one-core board.
EVENT_WAIT_S = 1.0
LATE_READ_SPAN_NS = 500_000_000  # epochs this far apart in one read: the older ones were read late
# After a receiver's first byte, the GNSS thread waits for the rest of the epoch's burst before reading it: the
# line time of EPOCH_BURST_BYTES (NAV-PVT, NAV-TIMEGPS, GGA, RMC and TIM-TP: 296 bytes, 0.31 s at the factory's
# 9600 baud, 26 ms at 115200), at most BURST_SETTLE_MAX_S and 0.4 of the configured fix period. One wake-up per
# epoch instead of one per message (the simulated receiver hands the pty a message at a time) or per tty flush (a
# board's UART delivers a burst in pieces of a few bytes). The records' arrival times move by as much, which
# nothing times by: fixes carry their epoch, the clock pairs a time pulse with the PPS edge after it, and a read is
# taken as late only when its epochs lie LATE_READ_SPAN_NS apart.
EPOCH_BURST_BYTES = 320
BURST_SETTLE_MAX_S = 0.35
# A read whose first byte came this share of the fix period (one second when not configured), and at least
# READ_QUIET_MIN_S, after the reader began to wait for it, nothing waiting before, began after a quiet line: a
# burst's start (a receiver sends a burst back to back, its next one a period later). What a receiver that begins its
# bursts with a sentence without a time (GSA, VTG) needs to tell its head from the last epoch's tail; a receiver that
# pauses this long inside its burst has a tail read after a quiet line too, when the port opens in the pause (its
# epochs then carry the GSA before theirs). The head after a 9600 baud burst of GSA, GSV x3, RMC and VTG comes 0.22 s
# after the reader's settling wait.
READ_QUIET_PERIODS = 0.1
READ_QUIET_MIN_S = 0.05
READ_MARKS_KEPT = 64  # reads whose time is kept to date an epoch's first message (a slow line's epoch spans ~5)
# A receiver that restarts (a voltage dip while the engine cranks) comes back at the speed and with the messages its
# flash holds, while the logger's port stays open at the speed the set-up raised it to. Bytes with not one message
# in them for this many fix periods (at least this many seconds), or messages without the ones the set-up turned on
# for as long, mean that: the port is opened again and the receiver set up again.
RESTART_SEEN_PERIODS = 5
RESTART_SEEN_MIN_S = 5.0
# An MPU-6050 whose supply dipped while its bus did not (its own cable, a loose connector) restarts asleep at its
# reset values: its FIFO stays empty, its data registers read zero, and no I2C transfer fails. After this long
# without a FIFO sample (or at an all-zero register sample), the IMU thread reads the configuration back, at most
# once per this long.
IMU_AWAKE_CHECK_S = 1.0
FIFO_READS_MIN_HZ = 2.0  # a FIFO read every half second at low rates
FIFO_FRAMES = FIFO_SIZE_BYTES // FIFO_FRAME_BYTES  # the MPU-6050's FIFO holds 85 accelerometer and gyro frames
FIFO_FRAMES_PER_READ = 40.0  # ... and at most this many frames a read: twice per filling, 2.5 frames to spare


def _i2c_bus(path_or_number: str | int) -> Any:
    import smbus2

    try:
        return smbus2.SMBus(path_or_number)
    except FileNotFoundError:
        where = path_or_number if isinstance(path_or_number, str) else f"/dev/i2c-{path_or_number}"
        raise DeviceNotFound(f"I2C bus {where} not found (is the I2C overlay enabled?)") from None
    except PermissionError:
        where = path_or_number if isinstance(path_or_number, str) else f"/dev/i2c-{path_or_number}"
        raise BusError(f"I2C bus {where}: permission denied (is the service user in the i2c group?)") from None


def _close_quietly(obj: Any) -> None:
    """Close a bus or a driver, if there is one, whatever state its device is in."""
    if obj is None:
        return
    try:
        obj.close()
    except Exception:  # a device already gone cannot be closed any further
        pass


def fifo_poll_hz(rate_hz: float) -> float:
    """How often the FIFO is read: every half second (ten samples at 20 Hz, the default), or twice per filling
    of its 85 frames (FIFO_FRAMES) where that is more often (from 80 Hz up: 5 reads a second at 200 Hz, 25 at 1 kHz).

    Every read costs a wake-up, four I2C transfers, a stamping and a record whatever it holds: 0.3 to 0.5 ms of
    the sampler thread's CPU here at 20 Hz, 200 Hz and 1 kHz alike (tools/bench_daemon.py), so the reads, not
    the samples, are the thread's cost (twenty reads a second at 200 Hz took it to 0.74 % of a core, five take
    0.25 %; two at 20 Hz 0.10 %). Nothing needs the samples sooner: the live filter wakes every two seconds
    (navigator.WAKE_S) and ``logger status`` shows rates. A read later than the FIFO's filling less one period
    (45 ms at 1 kHz, 225 ms at 200 Hz, 3.75 s at 20 Hz) loses samples, counted as the chip's overflow."""
    return max(FIFO_READS_MIN_HZ, rate_hz / FIFO_FRAMES_PER_READ)


class ImuSource(Source):
    """MPU-6050: the FIFO in batches stamped by the chip's own sample clock (``read = "fifo"``, the default), or
    one register burst per sample stamped by the board's read (``read = "register"``, up to 50 Hz: for a chip
    whose FIFO cannot be trusted, and the way the logger read at 20 Hz before)."""

    name = "imu"

    def __init__(self, bus: str | int, address: int, rate_hz: float, accel_range_g: int, gyro_range_dps: int,
                 tb: TimeBase, read: str, who_am_i: int = WHO_AM_I_VALUE) -> None:
        if read not in IMU_READS:
            raise ValueError(f"MPU-6050 read {read!r}: must be one of {', '.join(IMU_READS)}")
        self.bus_id, self.address, self.rate_hz, self.who_am_i = bus, address, rate_hz, who_am_i
        self.ranges = (accel_range_g, gyro_range_dps)
        self.tb = tb
        self.fifo = read == "fifo"  # the configuration refuses register reads above REGISTER_READ_MAX_HZ
        self.poll_hz = fifo_poll_hz(rate_hz) if self.fifo else rate_hz
        self.driver: Any = None
        self._bus: Any = None
        self._pending_lost = 0
        self._fifo_clock: FifoClock | None = None
        self._sampled_ns = self._checked_ns = 0  # drive time of the last samples read, of the last awake check
        self._last_sample_ns: int | None = None  # the last delivered sample's time, kept across reopenings

    def open(self) -> None:
        from sensors.mpu6050 import Mpu6050, choose_sample_timing

        self._fifo_clock = None  # a reopened chip starts an empty FIFO on a new count

        if self.fifo:
            chip_rate, dlpf = self.rate_hz, None
        else:
            # Read on demand: the chip samples at 1 kHz behind the low-pass filter chosen for the read rate,
            # so each read gets a sample at most 1 ms old and none is read twice or skipped when the board's
            # and the chip's clocks slide past each other.
            try:
                chip_rate, dlpf = DIRECT_CHIP_RATE_HZ, choose_sample_timing(self.rate_hz).dlpf.cfg
            except ValueError as exc:  # an unsupported rate: a configuration problem, reported as one line
                raise SensorError(f"MPU-6050: {exc}") from None
        self._bus = _i2c_bus(self.bus_id)
        try:
            self.driver = Mpu6050(self._bus, self.address, rate_hz=chip_rate, dlpf_cfg=dlpf,
                                  accel_range_g=self.ranges[0], gyro_range_dps=self.ranges[1], fifo=self.fifo,
                                  bus_name=f"I2C bus {self.bus_id}", sleep=self.tb.sleep, who_am_i=self.who_am_i)
        except ValueError as exc:
            raise SensorError(f"MPU-6050: {exc}") from None
        self.driver.configure(now_ns=self.tb.monotonic_ns)
        self._sampled_ns = self._checked_ns = self.tb.monotonic_ns()
        started, last = self.driver.fifo_started_ns, self._last_sample_ns
        if started is not None and last is not None:  # started is None for register reads: no FIFO
            # Opened again after an error (a NACK, a brown-out): the chip's samples from the last one delivered up
            # to the FIFO's reset in configure() are gone (those left in the FIFO, those of the reopening), and
            # are counted as an overflow's are, with the next samples.
            self._pending_lost += max(0, (started - last) // round(self.driver.sample_period_s * 1e9))

    def _check_awake(self, t_ns: int) -> None:
        """Raise SensorError (the sampler closes the chip and configures it again) when it is no longer as
        configured: restarted by a dip in its supply that no transfer saw."""
        self._checked_ns = t_ns
        if not self.driver.is_configured():
            raise SensorError(f"MPU-6050 on I2C bus {self.bus_id}: found asleep at its reset values (its supply "
                              "dipped?); configuring it again")

    def read(self) -> list[Reading]:
        if not self.fifo:
            t0 = self.tb.monotonic_ns()
            s = self.driver.read()
            t1 = self.tb.monotonic_ns()
            if not any(s.accel_mps2) and not any(s.gyro_rps):  # reset values: no real sample is all zero
                self._check_awake(t1)
            return [Reading(IMU, imu_record(s.accel_mps2, s.gyro_rps, s.temp_degc, False, 0), (t0 + t1) // 2)]
        t_read = self.tb.monotonic_ns()
        batch = self.driver.read_fifo(t_read, now_ns=self.tb.monotonic_ns)
        t_done = self.tb.monotonic_ns()
        if self._fifo_clock is None:
            self._fifo_clock = FifoClock(batch.period_s * 1e9)
        if batch.overflowed:
            self._pending_lost += batch.lost_samples if batch.lost_samples is not None else 1
            self._fifo_clock.reset()
            if self.driver.fifo_started_ns is not None:
                self._last_sample_ns = self.driver.fifo_started_ns  # counted up to the reset: a reopening from there
        n = len(batch)
        if not n:
            check_ns = round(IMU_AWAKE_CHECK_S * 1e9)
            if t_done - self._sampled_ns > check_ns and t_done - self._checked_ns > check_ns:
                self._check_awake(t_done)
            return []  # the lost count waits for the next samples, the first of which it precedes
        self._sampled_ns = t_done
        times = self._fifo_clock.stamps(n, t_read, t_done, self.driver.backlog_frames)
        self._last_sample_ns = times[-1]
        payload = imu_batch_payload(times, batch.accel_mps2, batch.gyro_rps, batch.temp_degc, batch.period_s,
                                    self._pending_lost)
        self._pending_lost = 0
        return [Reading(IMU_BATCH, payload, times[0], times=times)]

    def close(self) -> None:
        _close_quietly(self._bus)
        self._bus = None


class BaroSource(Source):
    name = "baro"

    def __init__(self, bus: str | int, address: int, oversampling: int, sea_level_pa: float, variant: str,
                 tb: TimeBase) -> None:
        self.bus_id, self.address, self.oss, self.p0, self.variant = bus, address, oversampling, sea_level_pa, variant
        self.tb = tb
        self.driver: Any = None
        self._bus: Any = None

    def open(self) -> None:
        from sensors.bmp085 import Bmp085

        self._bus = _i2c_bus(self.bus_id)
        self.driver = Bmp085(self._bus, self.address, variant=self.variant, oversampling=self.oss,
                             reference_pa=self.p0, bus_name=f"I2C bus {self.bus_id}", sleep=self.tb.sleep)
        self.driver.configure()

    def read(self) -> list[Reading]:
        t0 = self.tb.monotonic_ns()
        s = self.driver.read()
        t1 = self.tb.monotonic_ns()
        return [Reading(BARO, baro_record(s, self.p0), (t0 + t1) // 2)]

    def close(self) -> None:
        _close_quietly(self._bus)
        self._bus = None


class ObdSource(Source):
    """Vehicle speed from an ELM327 adapter or straight from the CAN bus; the same record either way."""

    name = "obd"

    def __init__(self, make_driver: Callable[[], SpeedDriver], interface: str, tb: TimeBase) -> None:
        self.make_driver, self.interface, self.tb = make_driver, interface, tb
        self.driver: SpeedDriver | None = None

    def open(self) -> None:
        self.driver = self.make_driver()
        self.driver.clock = self.tb.monotonic_ns
        self.driver.open()

    def read(self) -> list[Reading]:
        t0 = self.tb.monotonic_ns()
        s = self.driver.read()
        t1 = self.tb.monotonic_ns()
        # The ECU sampled its speed somewhere between request and answer: the midpoint is the best guess. Of the
        # request that was answered, where the driver did more inside the read (an adapter set up again).
        w0, w1 = self.driver.answered_window_ns or (t0, t1)
        return [Reading(OBD_SPEED, speed_record(s, self.interface), (w0 + w1) // 2)]

    def incidents(self) -> dict[str, int]:
        return {} if self.driver is None else self.driver.incidents()

    def close(self) -> None:
        _close_quietly(self.driver)
        self.driver = None


class GnssSource(Source):
    """The u-blox receiver: every byte kept for post-processing, each decoded fix and time pulse recorded.

    ``meas_period_ms`` is the navigation rate the setup asks for (None: the driver's one fix a second), and
    ``raw_observations`` asks for RXM-RAWX and RXM-SFRBX as well: the set-up raises the port speed to carry them,
    so a port opened again (a USB adapter unplugged) opens at the speed last set, and at the configured one when the
    receiver is silent there (it was power-cycled and came back at the speed in its flash). A receiver that refuses
    raw observations (an M8N) is recorded without them, with one warning. A receiver that answers no UBX but sends
    NMEA (one that is not a u-blox, such as the paper's ST TESEO, or a
    u-blox with UBX input off) is recorded as it is, unconfigured: its fixes carry their UTC time, which the
    clock pairs with the PPS edges as it does a u-blox's, only without TIM-TP's announcement.
    """

    name = "gnss"
    sample_topic = GNSS_FIX

    def __init__(self, path: str, baud: int, configure: bool, tb: TimeBase, meas_period_ms: int | None = None,
                 raw_observations: bool = False) -> None:
        self.path, self.baud, self.configure, self.tb = path, baud, configure, tb
        self.meas_period_ms = meas_period_ms
        self.raw_observations = raw_observations
        self.origin = f"serial {path}"
        self.receiver: Any = None
        self.setup: Any = None
        self.nmea_only = False  # the receiver answered no UBX when last opened, but spoke NMEA
        self.port_baud = baud  # the speed the port is opened at: the configured one, or the one the set-up set
        self.offset = 0  # bytes read since the port was opened (each /gnss/raw record says where it starts)
        # (the receiver's read mark, drive time) of the latest reads: when an epoch began to arrive (_opened_at)
        self._read_at: deque[tuple[int, int]] = deque(maxlen=READ_MARKS_KEPT)
        self._settle = lambda: tb.sleep(self.settle_s())
        self._quiet_ns = round(max(READ_QUIET_MIN_S, READ_QUIET_PERIODS * (meas_period_ms or 1000) / 1000) * 1e9)
        self._raw_warned = False
        self._heard_ns = 0  # drive time of the last message of any kind
        self._frames_ok = self._bad_frames = 0
        self._watched: dict[tuple[int, int], str] = {}  # the UBX messages the set-up turned on, every epoch's
        self._watch_counts: dict[tuple[int, int], int] = {}
        self._watch_seen_ns: dict[tuple[int, int], int] = {}
        self._restart: ProtocolError | None = None  # seen in a read whose records went out first
        # How long without them a restart is taken for seen: RESTART_SEEN_PERIODS fix periods, RESTART_SEEN_MIN_S
        self._restart_after_ns = round(max(RESTART_SEEN_MIN_S, RESTART_SEEN_PERIODS * (meas_period_ms or 1000) / 1000)
                                       * 1e9)

    def _setup_wanted(self) -> Any:
        from sensors.ublox_config import ReceiverSetup

        if self.meas_period_ms is None:
            return ReceiverSetup(raw_observations=self.raw_observations)
        return ReceiverSetup(meas_period_ms=self.meas_period_ms, raw_observations=self.raw_observations)

    def open(self) -> None:
        from sensors.ublox import GnssReceiver

        if not self.configure:
            self.receiver = GnssReceiver.open(self.path, self.port_baud)
            self._opened()
            return
        from sensors.ublox_config import NoUbxAnswer, baud_for, configure_receiver

        setup = self._setup_wanted()
        # Where the receiver may be talking: the speed last used, its flash's (the configured one: after its own
        # restart), and the one a set-up gives it (the logger restarted while the receiver kept its RAM setting).
        speeds = list(dict.fromkeys((self.port_baud, self.baud, baud_for(setup))))
        for speed in speeds:
            self.receiver = GnssReceiver.open(self.path, speed)
            try:
                self.setup = configure_receiver(self.receiver, setup, sleep=self.tb.sleep)
            except NoUbxAnswer as exc:
                if exc.nmea_without_checksum and not exc.nmea_sentences:
                    # The speed is right, the sentences are refused: that is what to say, not the next speed's
                    # silence ("wrong baud rate").
                    _close_quietly(self.receiver)
                    raise
                if not exc.nmea_sentences:  # nothing understood at this speed: try the next
                    _close_quietly(self.receiver)
                    continue
                # Refusing it would record nothing, forever: a working receiver that does not know UBX.
                if not self.nmea_only:
                    log.warning("gnss: %s; recording its NMEA unconfigured, as it comes (no UBX: no accuracy figures "
                                "unless it sends GST, no vertical velocity, no TIM-TP: the clock pairs PPS edges "
                                "with the NMEA fixes' UTC times)", exc)
                self.nmea_only, self.setup, self.port_baud = True, None, speed
            except SensorError:
                _close_quietly(self.receiver)
                raise
            else:
                self.nmea_only = False
                self.port_baud = self.setup.baud
                self._report_raw(self.setup)
            self._opened()
            return
        self.port_baud = self.baud
        raise NoUbxAnswer(f"GNSS receiver on {self.path} answered no UBX-MON-VER and sent no NMEA at "
                          f"{', '.join(str(b) for b in speeds)} baud: wrong baud rate, or nothing on the line", 0)

    def _opened(self) -> None:
        """Counted from the end of the set-up, which may take seconds of retries: a restart is what comes after."""
        from sensors.ublox_config import message_id

        # Each /gnss/raw record says where its bytes start in the port's stream since it was opened: opened again
        # (unplugged and back, or set up again after a restart), the stream starts over, and an offset back at 0
        # tells the office's raw export that what came meanwhile was not read (it went on counting: no gap shown,
        # and a UBX frame cut at the unplugging joined to the new bytes).
        self.offset = 0
        now = self.tb.monotonic_ns()
        self._heard_ns, self._restart = now, None
        self._read_at.clear()  # a new receiver object numbers its reads from 1 again
        self._frames_ok, self._bad_frames = self.receiver.framer.frames_ok, self.receiver.framer.bad_checksum
        names = () if self.setup is None else (
            "NAV-PVT", "NAV-TIMEGPS", *(("RXM-RAWX",) if self.setup.raw_observations == "on" else ()))
        self._watched = {message_id(n): n for n in names}
        self._watch_counts = {k: self.receiver.ubx_counts[k] for k in self._watched}
        self._watch_seen_ns = dict.fromkeys(self._watched, now)

    def settle_s(self) -> float:
        """How long to wait for the rest of an epoch's burst once its first byte is in (drive time)."""
        settle = min(BURST_SETTLE_MAX_S, EPOCH_BURST_BYTES * 10 / self.port_baud)  # 8N1: ten bits a byte
        return min(settle, 0.4e-3 * self.meas_period_ms) if self.meas_period_ms else settle

    def _report_raw(self, result: Any) -> None:
        """Raw observations granted (info) or refused (one warning per run, not one per reconnection)."""
        if result.raw_observations == "on":
            log.info("gnss: raw observations (RXM-RAWX, RXM-SFRBX) on at %d baud", result.baud)
        elif result.raw_observations == "refused" and not self._raw_warned:
            self._raw_warned = True
            log.warning("gnss: the receiver refused raw observations, %s: its firmware has none (an M8N; M8T, M8P, "
                        "F9P and F9T do); recording without them", result.raw_refusal)

    def read(self) -> list[Reading]:
        from sensors.ublox import GnssFix, TimePulse

        if self._restart is not None:
            raise self._restart
        got = self.receiver.read(EVENT_WAIT_S, self._settle, self.tb.monotonic_ns, self._quiet_ns)
        t = self.tb.monotonic_ns()
        out: list[Reading] = []
        if got.raw:
            self._read_at.append((got.mark, t))
            out.append(Reading(GNSS_RAW, raw_bytes_record(t, got.raw, self.offset), t, stamped=False))
            self.offset += len(got.raw)
            self._watch_for_a_restart(t)
        # Epochs half a second or more apart in one read (or two time pulses): the host read the older messages
        # that long after they came, so their stamp says nothing of when; paired with PPS edges they could name
        # the wrong second.
        epochs = [item.time_utc_ns for item in got.items
                  if isinstance(item, GnssFix) and item.time_valid and item.time_utc_ns is not None]
        pulses = sum(1 for item in got.items if isinstance(item, TimePulse))
        late = (bool(epochs) and max(epochs) - min(epochs) >= LATE_READ_SPAN_NS) or pulses > 1
        for item in got.items:
            if isinstance(item, GnssFix):
                if item.source == "HNR-PVT":
                    continue  # already fused with the receiver's own sensors: not a GNSS measurement
                out.append(Reading(GNSS_FIX, location_fix(item, t, late, self._opened_at(item.opened_mark, t)), t))
            elif isinstance(item, TimePulse):
                out.append(Reading(TIMEPULSE, timepulse_record(item, late), t))
        return out

    def _opened_at(self, mark: int | None, t_ns: int) -> int | None:
        """When the read an epoch's first message came in was taken (drive time), where that was an earlier read
        than this one; None when it was this one, or is not known any more."""
        for read_mark, at in reversed(self._read_at):
            if read_mark == mark:
                return at if at < t_ns else None
        return None

    def _watch_for_a_restart(self, t_ns: int) -> None:
        """Note a ProtocolError for the next read (the sampler then closes the port and opens it again, which sets
        the receiver up again) when what arrives says the receiver restarted since its set-up: bytes at a speed the
        port is no longer at (nothing but garbage, and no damaged frame either), or messages (its factory NMEA)
        without the UBX messages the set-up turned on. This read's records go out first: nothing is lost."""
        framer = self.receiver.framer
        heard = framer.frames_ok != self._frames_ok
        if heard or framer.bad_checksum != self._bad_frames:  # a frame, whole or damaged: the speed is right
            self._frames_ok, self._bad_frames, self._heard_ns = framer.frames_ok, framer.bad_checksum, t_ns
        counts = self.receiver.ubx_counts
        for key in self._watched:
            if counts[key] != self._watch_counts[key]:
                self._watch_counts[key], self._watch_seen_ns[key] = counts[key], t_ns
        limit_ns = self._restart_after_ns
        if self.port_baud != self.baud and t_ns - self._heard_ns > limit_ns:
            self._restart = ProtocolError(
                f"GNSS receiver on {self.path}: only garbage at {self.port_baud} baud, no message for "
                f"{(t_ns - self._heard_ns) / 1e9:.0f} s: restarted at the {self.baud} baud of its flash? "
                "Setting it up again")
            self.port_baud = self.baud  # the likeliest speed first; the others are tried after it
            return
        missing = [name for key, name in self._watched.items() if t_ns - self._watch_seen_ns[key] > limit_ns]
        if heard and missing:
            self._restart = ProtocolError(
                f"GNSS receiver on {self.path}: messages but no {', '.join(missing)} for "
                f"{(t_ns - min(self._watch_seen_ns.values())) / 1e9:.0f} s: restarted without the logger's set-up? "
                f"Setting it up again")

    def incidents(self) -> dict[str, int]:
        if self.receiver is None:
            return {}
        framer = self.receiver.framer
        return {"bytes of garbage on the serial line": framer.garbage_bytes,
                "frames with a bad checksum": framer.bad_checksum,
                "NMEA sentences without a checksum (refused)": framer.nmea_without_checksum}

    def close(self) -> None:
        _close_quietly(self.receiver)
        self.receiver = None


class PpsSource(Source):
    name = "pps"

    def __init__(self, chip: str, line: int | str) -> None:
        self.chip, self.line = chip, line
        self.origin = f"gpio {chip} line {line}"
        self.driver: Any = None

    def open(self) -> None:
        from sensors.pps import PpsLine

        self.driver = PpsLine(self.chip, self.line)
        self.driver.open()

    def read(self) -> list[Reading]:
        return [Reading(PPS, pps_record(e.line_seqno, e.lost), e.timestamp_ns) for e in self.driver.wait(EVENT_WAIT_S)]

    def close(self) -> None:
        _close_quietly(self.driver)
        self.driver = None


@dataclass
class Plan:
    source: Any
    rate_hz: float | None
    expected_hz: float | None
