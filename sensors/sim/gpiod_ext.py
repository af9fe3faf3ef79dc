"""A stand-in for gpiod's C extension: simulated chip paths go to line models, every other path to the kernel.

Only ``gpiod._ext`` is replaced, so the whole Python layer of gpiod (``Chip``, ``LineRequest``, the name
lookup, ``LineSettings`` conversion, the ``select`` on the request's file descriptor, ``EdgeEvent``) runs in
tests and in the simulated daemon exactly as on the board, and a driver cannot tell a simulated chip from a
real one. What the kernel does between an IRQ and ``read()`` is modelled here: per-line and per-request
sequence numbers, the event FIFO that drops its oldest entry when full (the kernel's kfifo, rounded up to a
power of two), active-low inversion, edge selection, software debounce, the realtime event clock, busy lines,
line-info watch events, and ENODEV once the chip is gone.

Edges happen in true drive time. A request catches up lazily (whenever the Python layer touches its file
descriptor, or reads), so a test that steps a :class:`~sensors.sim.clock.ManualClock` sees every edge up to
"now" without any thread; a paced chip also runs one small thread per request that wakes at each edge in
drive time, so a daemon blocked in ``wait_edge_events`` wakes like it would on an interrupt.

Install (:func:`sim_gpiochips`) before lines are requested: gpiod builds its line configuration through
whichever extension is in place, and a kernel request made before cannot take a recorded one later.
"""

from __future__ import annotations

import collections
import errno
import os
import select
import sys
import threading
import types
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Protocol

from gpiod import _ext as _real_ext
from gpiod.chip_info import ChipInfo
from gpiod.edge_event import EdgeEvent
from gpiod.info_event import InfoEvent
from gpiod.line import Value
from gpiod.line_info import LineInfo

from sensors.sim.clock import DriveClock

KERNEL_FIFO_MAX = 16 * 64  # GPIO_V2_LINES_MAX lines * 16 events
DEFAULT_READ_EVENTS = 64  # what libgpiod's Python binding reads when max_events is None


@dataclass(frozen=True, slots=True)
class LineEdge:
    """One level change of a physical line, at the moment the kernel's interrupt handler stamps it."""

    true_ns: int  # true drive time of the interrupt
    monotonic_ns: int  # the board's CLOCK_MONOTONIC at that moment
    rising: bool  # the physical level after the change is high


class EdgeSource(Protocol):
    """What drives a simulated line: a signal model in true drive time."""

    def edges_between(self, after_true_ns: int, until_true_ns: int) -> list[LineEdge]:
        """Edges whose interrupt falls in ``(after_true_ns, until_true_ns]``, in time order."""
        ...

    def next_edge_after(self, true_ns: int, horizon_ns: int) -> int | None:
        """True time of the first interrupt after ``true_ns`` within ``horizon_ns``, if any."""
        ...

    def level_at(self, true_ns: int) -> bool:
        """Physical level of the line (True: high)."""
        ...


def _identity(ns: int) -> int:
    return ns


class SimGpioChip:
    """A GPIO chip of the simulated board, reachable through gpiod at ``path`` once registered.

    ``board_ns`` maps true drive time to the board's CLOCK_MONOTONIC (an oscillator's ``board_ns``) for
    info-event stamps; edge sources stamp their own edges. ``paced`` starts a waker thread per request:
    use it with a clock that runs by itself (a daemon), never with a ManualClock, whose ``sleep`` would
    move the test's time.
    """

    def __init__(self, path: str, clock: DriveClock, *, num_lines: int = 32,
                 line_names: dict[int, str] | None = None, sources: dict[int, EdgeSource] | None = None,
                 name: str = "gpiochip0", label: str = "sim-gpio", paced: bool = False,
                 board_ns: Callable[[int], int] = _identity, realtime_offset_ns: int = 1_700_000_000 * 10**9,
                 accessible: bool = True) -> None:
        self.path = os.path.normpath(path)
        self.clock = clock
        self.num_lines = int(num_lines)
        self.line_names = dict(line_names or {})
        self.sources: dict[int, EdgeSource] = dict(sources or {})
        for offset in [*self.line_names, *self.sources]:
            if not 0 <= offset < self.num_lines:
                raise ValueError(f"line offset {offset} outside chip {name} with {num_lines} lines")
        self.name = name
        self.label = label
        self.paced = paced
        self.board_ns = board_ns
        self.realtime_offset_ns = int(realtime_offset_ns)
        self.accessible = accessible
        self.present = True
        self._lock = threading.RLock()
        self._owners: dict[int, SimLineRequest] = {}
        self._handles: list[_SimChipHandle] = []

    def vanish(self) -> None:
        """Unplug the chip: it can no longer be opened, open requests fail with ENODEV."""
        with self._lock:
            self.present = False
            requests = list(set(self._owners.values()))
        for req in requests:
            req._wake()

    def reappear(self) -> None:
        with self._lock:
            self.present = True

    def now_board_ns(self) -> int:
        return self.board_ns(self.clock.now_ns())

    def line_info(self, offset: int) -> LineInfo:
        with self._lock:
            req = self._owners.get(offset)
            if req is None:
                return LineInfo(offset, self.line_names.get(offset, ""), False, "",
                                      _real_ext.DIRECTION_INPUT, False, _real_ext.BIAS_UNKNOWN,
                                      _real_ext.DRIVE_PUSH_PULL, _real_ext.EDGE_NONE,
                                      _real_ext.CLOCK_MONOTONIC, False, 0)
            s = req._settings[offset]
            bias = _real_ext.BIAS_UNKNOWN if s.bias == _real_ext.BIAS_AS_IS else s.bias
            direction = _real_ext.DIRECTION_INPUT if s.direction == _real_ext.DIRECTION_AS_IS else s.direction
            return LineInfo(offset, self.line_names.get(offset, ""), True, req.consumer, direction,
                                  s.active_low, bias, s.drive, s.edge_detection, s.event_clock,
                                  s.debounce_period > 0, s.debounce_period)

    def _notify(self, offsets: list[int], event_type: int) -> None:
        stamp = self.now_board_ns()
        with self._lock:
            handles = list(self._handles)
        for offset in offsets:
            info = self.line_info(offset)
            for h in handles:
                h._post(offset, InfoEvent(event_type, stamp, info))


# -- objects the Python layer receives from "_ext" ------------------------------------------------------
class LineSettings:
    """Records what gpiod hands the C extension, so a simulated chip can read it back."""

    def __init__(self, direction: int, edge_detection: int, bias: int, drive: int, active_low: bool,
                 debounce_period: int, event_clock: int, output_value: int) -> None:
        self.direction = direction
        self.edge_detection = edge_detection
        self.bias = bias
        self.drive = drive
        self.active_low = bool(active_low)
        self.debounce_period = int(debounce_period)  # microseconds
        self.event_clock = event_clock
        self.output_value = output_value

    def to_real(self) -> Any:
        return _real_ext.LineSettings(
            direction=self.direction, edge_detection=self.edge_detection, bias=self.bias, drive=self.drive,
            active_low=self.active_low, debounce_period=self.debounce_period, event_clock=self.event_clock,
            output_value=self.output_value)


class LineConfig:
    def __init__(self) -> None:
        self.entries: list[tuple[list[int], LineSettings]] = []
        self.output_values: list[Value] | None = None

    def add_line_settings(self, offsets: list[int], settings: LineSettings) -> None:
        self.entries.append((list(offsets), settings))

    def set_output_values(self, global_output_values: list[Value]) -> None:
        self.output_values = list(global_output_values)

    def to_real(self) -> Any:
        cfg = _real_ext.LineConfig()
        for offsets, settings in self.entries:
            cfg.add_line_settings(offsets, settings.to_real())
        if self.output_values is not None:
            cfg.set_output_values(self.output_values)
        return cfg

    def per_offset(self) -> dict[int, LineSettings]:
        out: dict[int, LineSettings] = {}
        for offsets, settings in self.entries:
            for offset in offsets:
                out[offset] = settings
        return out


class _RealRequest:
    """A kernel line request whose reconfiguration goes through the recorded config."""

    def __init__(self, req: Any) -> None:
        self._req = req

    def reconfigure_lines(self, line_cfg: LineConfig) -> None:
        self._req.reconfigure_lines(line_cfg.to_real())

    def __getattr__(self, name: str) -> Any:
        return getattr(self._req, name)


class _RealChip:
    """A kernel GPIO chip, seen through the recorded config."""

    def __init__(self, path: str) -> None:
        self._chip = _real_ext.Chip(path)

    def request_lines(self, line_cfg: LineConfig, consumer: str | None, event_buffer_size: int | None) -> Any:
        return _RealRequest(self._chip.request_lines(line_cfg.to_real(), consumer, event_buffer_size))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._chip, name)


def _oserror(code: int, what: str) -> OSError:
    return OSError(code, os.strerror(code), what)


class _SimChipHandle:
    """An open simulated chip (what ``_ext.Chip(path)`` returns)."""

    def __init__(self, chip: SimGpioChip) -> None:
        if not chip.present:
            raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), chip.path)
        if not chip.accessible:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), chip.path)
        self._chip = chip
        self._rfd, self._wfd = os.pipe()
        os.set_blocking(self._wfd, False)
        self._events: collections.deque[InfoEvent] = collections.deque()
        self._watched: set[int] = set()
        self._lock = threading.Lock()
        self._closed = False
        with chip._lock:
            chip._handles.append(self)

    def _check_offset(self, offset: int) -> None:
        if not 0 <= offset < self._chip.num_lines:
            raise _oserror(errno.EINVAL, f"line {offset} of {self._chip.path}")

    def _post(self, offset: int, event: InfoEvent) -> None:
        with self._lock:
            if self._closed or offset not in self._watched:
                return
            if not self._events:
                os.write(self._wfd, b"\x01")
            self._events.append(event)

    @property
    def path(self) -> str:
        return self._chip.path

    @property
    def fd(self) -> int:
        return self._rfd

    def get_info(self) -> ChipInfo:
        return ChipInfo(self._chip.name, self._chip.label, self._chip.num_lines)

    def line_offset_from_id(self, id: str) -> int:
        for offset, name in sorted(self._chip.line_names.items()):
            if name == id:
                return offset
        raise _oserror(errno.ENOENT, f"line {id!r} on {self._chip.path}")

    def get_line_info(self, offset: int, watch: bool) -> LineInfo:
        self._check_offset(offset)
        if watch:
            with self._lock:
                if offset in self._watched:
                    raise _oserror(errno.EBUSY, f"line {offset} is already watched")
                self._watched.add(offset)
        return self._chip.line_info(offset)

    def unwatch_line_info(self, offset: int) -> None:
        self._check_offset(offset)
        with self._lock:
            if offset not in self._watched:
                raise _oserror(errno.EBUSY, f"line {offset} is not watched")
            self._watched.discard(offset)

    def get_line_name(self, offset: int) -> str | None:
        self._check_offset(offset)
        return self._chip.line_names.get(offset) or None

    def read_info_event(self) -> InfoEvent:
        while True:
            with self._lock:
                if self._events:
                    event = self._events.popleft()
                    if not self._events:
                        os.read(self._rfd, 1)
                    return event
            select.select([self._rfd], [], [])

    def request_lines(self, line_cfg: LineConfig, consumer: str | None,
                      event_buffer_size: int | None) -> SimLineRequest:
        chip = self._chip
        settings = line_cfg.per_offset()
        if not settings:
            raise _oserror(errno.EINVAL, "no lines in the request")
        for offset, s in settings.items():
            self._check_offset(offset)
            _validate(s, chip.path, offset)
        offsets = [o for entry, _ in line_cfg.entries for o in entry]
        with chip._lock:
            if not chip.present:
                raise _oserror(errno.ENODEV, chip.path)
            busy = [o for o in offsets if o in chip._owners]
            if busy:
                raise _oserror(errno.EBUSY, f"line {busy[0]} of {chip.path}")
            req = SimLineRequest(chip, offsets, settings, line_cfg.output_values, consumer or "?",
                              event_buffer_size or 0)
            for o in offsets:
                chip._owners[o] = req
        chip._notify(offsets, _real_ext.INFO_EVENT_TYPE_LINE_REQUESTED)
        req._start()
        return req

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        with self._chip._lock:
            if self in self._chip._handles:
                self._chip._handles.remove(self)
        os.close(self._rfd)
        os.close(self._wfd)


def _validate(s: LineSettings, path: str, offset: int) -> None:
    """The checks the kernel makes on a line's flags (gpio_v2_line_flags_validate)."""
    if s.edge_detection != _real_ext.EDGE_NONE and s.direction != _real_ext.DIRECTION_INPUT:
        raise _oserror(errno.EINVAL, f"edge detection on line {offset} of {path} needs an input")
    if s.event_clock == _real_ext.CLOCK_HTE:
        raise _oserror(errno.EOPNOTSUPP, f"no hardware timestamp engine for line {offset} of {path}")
    if s.debounce_period < 0:
        raise _oserror(errno.EINVAL, f"negative debounce on line {offset} of {path}")


class _LineState:
    """What the kernel keeps per requested line: its sequence number and its debouncer."""

    def __init__(self, level: bool) -> None:
        self.seqno = 0
        self.stable_level = level  # physical level last reported through the debouncer
        self.pending: LineEdge | None = None
        self.output: Value = Value.INACTIVE


class SimLineRequest:
    """A line request on a simulated chip (what ``_ext.Chip.request_lines`` returns)."""

    def __init__(self, chip: SimGpioChip, offsets: list[int], settings: dict[int, LineSettings],
                 output_values: list[Value] | None, consumer: str, event_buffer_size: int) -> None:
        self._chip = chip
        self._offsets = list(offsets)
        self._settings = dict(settings)
        self.consumer = consumer
        size = event_buffer_size if event_buffer_size > 0 else 16 * len(offsets)
        size = min(size, KERNEL_FIFO_MAX)
        self._capacity = 1 << (size - 1).bit_length()  # kfifo_alloc rounds up to a power of two
        self._fifo: collections.deque[EdgeEvent] = collections.deque()
        self._seqno = 0
        self._lock = threading.RLock()
        self._since = chip.clock.now_ns()
        self._lines = {o: _LineState(self._physical_level(o, self._since)) for o in offsets}
        for o in offsets:
            self._lines[o].output = Value(settings[o].output_value)
        if output_values is not None:
            for o, value in zip(offsets, output_values, strict=False):
                self._lines[o].output = value
        self._rfd, self._wfd = os.pipe()
        os.set_blocking(self._wfd, False)
        self._released = False
        self._woken = False
        self._stop = threading.Event()
        self._pacer: threading.Thread | None = None

    def _start(self) -> None:
        if self._chip.paced:
            self._pacer = threading.Thread(target=self._pace, name=f"sim-irq-{self._chip.name}", daemon=True)
            self._pacer.start()

    # the kernel side ----------------------------------------------------------------------------------
    def _physical_level(self, offset: int, true_ns: int) -> bool:
        source = self._chip.sources.get(offset)
        return source.level_at(true_ns) if source is not None else False

    def _wake(self) -> None:
        """Make the descriptor readable so that a poller wakes and its read reports the gone chip."""
        with self._lock:
            if not self._released and not self._fifo and not self._woken:
                self._woken = True
                os.write(self._wfd, b"\x01")

    def _emit(self, offset: int, true_ns: int, mono_ns: int, physical_high: bool,
              out: list[tuple[int, int, int, bool]]) -> None:
        s = self._settings[offset]
        logical_high = physical_high != s.active_low
        wanted = {
            _real_ext.EDGE_RISING: logical_high,
            _real_ext.EDGE_FALLING: not logical_high,
            _real_ext.EDGE_BOTH: True,
        }.get(s.edge_detection, False)
        if wanted:
            out.append((true_ns, mono_ns, offset, logical_high))

    def _catch_up(self) -> None:
        """Turn every edge up to the clock's now into events, as the interrupt handlers would have."""
        now = self._chip.clock.now_ns()
        with self._lock:
            if self._released or now <= self._since:
                return
            produced: list[tuple[int, int, int, bool]] = []
            for offset in self._offsets:
                s = self._settings[offset]
                source = self._chip.sources.get(offset)
                if source is None or s.direction != _real_ext.DIRECTION_INPUT:
                    continue
                line = self._lines[offset]
                debounce_ns = s.debounce_period * 1000
                for edge in source.edges_between(self._since, now):
                    if debounce_ns == 0:
                        self._emit(offset, edge.true_ns, edge.monotonic_ns, edge.rising, produced)
                        continue
                    pend = line.pending
                    if pend is not None and edge.true_ns - pend.true_ns >= debounce_ns:
                        self._settle(offset, line, pend, debounce_ns, produced)
                    line.pending = edge
                pend = line.pending
                if pend is not None and pend.true_ns + debounce_ns <= now:
                    self._settle(offset, line, pend, debounce_ns, produced)
            self._since = now
            produced.sort(key=lambda e: e[0])
            for _true_ns, mono_ns, offset, logical_high in produced:
                self._push(offset, mono_ns, logical_high)

    def _settle(self, offset: int, line: _LineState, edge: LineEdge, debounce_ns: int,
                out: list[tuple[int, int, int, bool]]) -> None:
        """Software debounce: the level held for the debounce period; report it if it changed."""
        line.pending = None
        if edge.rising != line.stable_level:
            line.stable_level = edge.rising
            self._emit(offset, edge.true_ns + debounce_ns, edge.monotonic_ns + debounce_ns, edge.rising, out)

    def _push(self, offset: int, mono_ns: int, logical_high: bool) -> None:
        line = self._lines[offset]
        line.seqno += 1
        self._seqno += 1
        s = self._settings[offset]
        stamp = mono_ns + (self._chip.realtime_offset_ns if s.event_clock == _real_ext.CLOCK_REALTIME else 0)
        kind = _real_ext.EDGE_EVENT_TYPE_RISING if logical_high else _real_ext.EDGE_EVENT_TYPE_FALLING
        event = EdgeEvent(kind, stamp, offset, self._seqno, line.seqno)
        if len(self._fifo) >= self._capacity:
            self._fifo.popleft()  # the kernel drops the oldest event when its FIFO is full
        elif not self._fifo:
            os.write(self._wfd, b"\x01")
        self._fifo.append(event)

    def _pace(self) -> None:
        clock = self._chip.clock
        while not self._stop.is_set():
            self._catch_up()
            now = clock.now_ns()
            nexts: list[int] = []
            for o in self._offsets:
                source = self._chip.sources.get(o)
                t_next = source.next_edge_after(now, 2_000_000_000) if source is not None else None
                if t_next is not None:
                    nexts.append(t_next)
                pending = self._lines[o].pending
                if pending is not None:
                    nexts.append(pending.true_ns + self._settings[o].debounce_period * 1000)
            wait_s = 0.1 if not nexts else (min(nexts) - now) / 1e9
            clock.sleep(min(0.1, max(wait_s, 1e-4)))

    def _check_present(self) -> None:
        if not self._chip.present:
            raise _oserror(errno.ENODEV, self._chip.path)

    # what gpiod's LineRequest calls -------------------------------------------------------------------
    @property
    def chip_name(self) -> str:
        return self._chip.name

    @property
    def num_lines(self) -> int:
        return len(self._offsets)

    @property
    def offsets(self) -> list[int]:
        return list(self._offsets)

    @property
    def fd(self) -> int:
        # gpiod polls this descriptor next; bring the FIFO up to date so that it is readable iff events
        # are waiting (or the chip is gone, which a read then reports).
        self._catch_up()
        if not self._chip.present:
            self._wake()
        return self._rfd

    def read_edge_events(self, max_events: int | None) -> list[EdgeEvent]:
        limit = DEFAULT_READ_EVENTS if max_events is None else int(max_events)
        if limit <= 0:
            raise _oserror(errno.EINVAL, "max_events must be positive")
        while True:
            self._check_present()
            self._catch_up()
            with self._lock:
                if self._released:
                    raise _oserror(errno.EBADF, "request released")
                if self._fifo:
                    events = [self._fifo.popleft() for _ in range(min(limit, len(self._fifo)))]
                    if not self._fifo:
                        os.read(self._rfd, 1)
                    return events
            # Like read() on the kernel's descriptor: block until an edge arrives.
            select.select([self._rfd], [], [], 0.05)

    def get_values(self, offsets: list[int], values: list[Value]) -> None:
        self._check_present()
        now = self._chip.clock.now_ns()
        for i, offset in enumerate(offsets):
            if offset not in self._lines:
                raise _oserror(errno.EINVAL, f"line {offset} is not in this request")
            s = self._settings[offset]
            if s.direction == _real_ext.DIRECTION_OUTPUT:
                values[i] = self._lines[offset].output
            else:
                high = self._physical_level(offset, now) != s.active_low
                values[i] = Value.ACTIVE if high else Value.INACTIVE

    def set_values(self, values: dict[int, Value]) -> None:
        self._check_present()
        for offset, value in values.items():
            if offset not in self._lines:
                raise _oserror(errno.EINVAL, f"line {offset} is not in this request")
            if self._settings[offset].direction != _real_ext.DIRECTION_OUTPUT:
                raise _oserror(errno.EPERM, f"line {offset} is an input")
            self._lines[offset].output = value

    def reconfigure_lines(self, line_cfg: LineConfig) -> None:
        self._check_present()
        self._catch_up()
        settings = line_cfg.per_offset()
        for offset, s in settings.items():
            if offset not in self._lines:
                raise _oserror(errno.EINVAL, f"line {offset} is not in this request")
            _validate(s, self._chip.path, offset)
        with self._lock:
            self._settings.update(settings)
        self._chip._notify(list(settings), _real_ext.INFO_EVENT_TYPE_LINE_CONFIG_CHANGED)

    def release(self) -> None:
        with self._lock:
            if self._released:
                return
            self._released = True
        self._stop.set()
        if self._pacer is not None and self._pacer is not threading.current_thread():
            self._pacer.join(timeout=2.0)
        with self._chip._lock:
            for o in self._offsets:
                if self._chip._owners.get(o) is self:
                    del self._chip._owners[o]
        self._chip._notify(self._offsets, _real_ext.INFO_EVENT_TYPE_LINE_RELEASED)
        os.close(self._rfd)
        os.close(self._wfd)


# -- the replacement module and its installation ----------------------------------------------------------
_registry_lock = threading.RLock()
_chips: dict[str, SimGpioChip] = {}
_install_count = 0
_patched: list[tuple[types.ModuleType, str, Any]] = []


def _lookup(path: str) -> SimGpioChip | None:
    with _registry_lock:
        return _chips.get(os.path.normpath(path))


def _chip(path: str) -> Any:
    sim = _lookup(path)
    if sim is not None:
        return _SimChipHandle(sim)
    return _RealChip(path)


def _is_gpiochip_device(path: str) -> bool:
    sim = _lookup(path)
    if sim is not None:
        return sim.present
    return bool(_real_ext.is_gpiochip_device(path))


def _make_module() -> types.ModuleType:
    mod = types.ModuleType(_real_ext.__name__, __doc__)
    for name in dir(_real_ext):
        if not name.startswith("__"):
            setattr(mod, name, getattr(_real_ext, name))
    mod.Chip = _chip  # type: ignore[attr-defined]
    mod.LineConfig = LineConfig  # type: ignore[attr-defined]
    mod.LineSettings = LineSettings  # type: ignore[attr-defined]
    mod.is_gpiochip_device = _is_gpiochip_device  # type: ignore[attr-defined]
    return mod


routing_ext = _make_module()


def register(chip: SimGpioChip) -> None:
    with _registry_lock:
        other = _chips.get(chip.path)
        if other is not None and other is not chip:
            raise ValueError(f"a simulated chip is already registered at {chip.path}")
        _chips[chip.path] = chip


def unregister(chip: SimGpioChip) -> None:
    with _registry_lock:
        if _chips.get(chip.path) is chip:
            del _chips[chip.path]


def install() -> None:
    """Route gpiod's extension calls through :data:`routing_ext` (counted: nested installs are fine)."""
    global _install_count
    with _registry_lock:
        _install_count += 1
        if _install_count > 1:
            return
        for name, mod in list(sys.modules.items()):
            if (name == "gpiod" or name.startswith("gpiod.")) and getattr(mod, "_ext", None) is _real_ext:
                _patched.append((mod, "_ext", _real_ext))
                mod._ext = routing_ext  # type: ignore[attr-defined]
        _patched.append((sys, _real_ext.__name__, sys.modules[_real_ext.__name__]))
        sys.modules[_real_ext.__name__] = routing_ext


def uninstall() -> None:
    """Undo :func:`install` once every installer has uninstalled."""
    global _install_count
    with _registry_lock:
        if _install_count == 0:
            return
        _install_count -= 1
        if _install_count > 0:
            return
        while _patched:
            mod, attr, original = _patched.pop()
            if mod is sys:
                sys.modules[attr] = original
            else:
                setattr(mod, attr, original)


def installed() -> bool:
    with _registry_lock:
        return _install_count > 0


@contextmanager
def sim_gpiochips(*chips: SimGpioChip) -> Iterator[None]:
    """Make ``chips`` reachable through gpiod at their paths for the duration of the block."""
    for chip in chips:
        register(chip)
    install()
    try:
        yield
    finally:
        uninstall()
        for chip in chips:
            unregister(chip)
