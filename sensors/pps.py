"""The PPS line: edges of the GNSS receiver's timepulse, stamped by the kernel, read through libgpiod v2.

The kernel stamps each edge in its interrupt handler on CLOCK_MONOTONIC, the clock the sampler threads stamp
samples with, so an edge and a sample are directly comparable. Edges the kernel had to drop because nobody
read them in time (its event FIFO is small) leave a gap in the line's sequence numbers: the driver reports
that gap as ``lost`` so the sync clock knows whole seconds went by unseen, rather than taking the next edge
for the next second. An edge the hardware never saw leaves no gap; only its time stamp can tell.
"""

from __future__ import annotations

import errno
from dataclasses import dataclass
from datetime import timedelta
from types import TracebackType
from typing import Any

import gpiod
from gpiod.line import Bias, Clock, Direction, Edge

from sensors.errors import BusError, DeviceNotFound

_EDGES = {"rising": (Edge.RISING, gpiod.EdgeEvent.Type.RISING_EDGE),
          "falling": (Edge.FALLING, gpiod.EdgeEvent.Type.FALLING_EDGE)}
_BIASES = {"as-is": Bias.AS_IS, "disabled": Bias.DISABLED, "pull-up": Bias.PULL_UP, "pull-down": Bias.PULL_DOWN}


@dataclass(frozen=True, slots=True)
class PpsEdge:
    """One timepulse edge as the kernel saw it."""

    timestamp_ns: int  # kernel CLOCK_MONOTONIC at the interrupt
    line_seqno: int  # counts every edge the kernel saw on the line since the request, from 1
    global_seqno: int  # the same over all lines of the request
    lost: int  # edges the kernel saw but dropped before this one (gap in line_seqno)


class PpsLine:
    """A PPS input on one GPIO line of a chip, by offset or by line name.

    ``edge`` is the edge that marks the second (``rising`` for a u-blox timepulse in its default polarity).
    Not thread-safe: one sampler thread owns it.
    """

    def __init__(self, chip_path: str, line: int | str, *, edge: str = "rising", bias: str = "as-is",
                 consumer: str = "vehicle-logger-pps", event_buffer_size: int = 16) -> None:
        if edge not in _EDGES:
            raise ValueError(f"PPS edge must be one of {', '.join(_EDGES)}, got {edge!r}")
        if bias not in _BIASES:
            raise ValueError(f"PPS bias must be one of {', '.join(_BIASES)}, got {bias!r}")
        if isinstance(line, int) and line < 0:
            raise ValueError(f"PPS line offset must be >= 0, got {line}")
        if event_buffer_size < 1:
            raise ValueError("PPS event buffer needs room for at least one edge")
        self.chip_path = chip_path
        self.line = line
        self.edge = edge
        self._edge, self._event_type = _EDGES[edge]
        self._bias = _BIASES[bias]
        self.consumer = consumer
        self.event_buffer_size = event_buffer_size
        self._request: gpiod.LineRequest | None = None
        self._last_seqno: int | None = None
        self.edges_total = 0
        self.lost_total = 0

    def _where(self) -> str:
        return f"line {self.line} of {self.chip_path}"

    @property
    def is_open(self) -> bool:
        return self._request is not None

    def open(self) -> None:
        """Request the line for rising-edge (or falling-edge) events stamped on CLOCK_MONOTONIC."""
        if self._request is not None:
            return
        try:
            chip = gpiod.Chip(self.chip_path)
        except FileNotFoundError:
            raise DeviceNotFound(f"PPS: no GPIO chip at {self.chip_path} (wanted line {self.line}); "
                                 "check the chip path and the device tree overlay") from None
        except PermissionError:
            raise BusError(f"PPS: permission denied opening {self.chip_path} (line {self.line}); "
                           "add the logger's user to the gpio group") from None
        except OSError as exc:
            if exc.errno in (errno.ENOTTY, errno.ENODEV, errno.ENXIO, errno.EINVAL):
                raise DeviceNotFound(f"PPS: {self.chip_path} is not a GPIO chip ({exc.strerror}); "
                                     f"wanted line {self.line}") from None
            raise BusError(f"PPS: cannot open {self.chip_path}: {exc.strerror}") from None
        try:
            settings = gpiod.LineSettings(direction=Direction.INPUT, edge_detection=self._edge,
                                          bias=self._bias, event_clock=Clock.MONOTONIC)
            self._request = chip.request_lines(config={self.line: settings}, consumer=self.consumer,
                                               event_buffer_size=self.event_buffer_size)
        except ValueError:
            raise DeviceNotFound(f"PPS: {self.chip_path} has no line {self.line} "
                                 f"(it has {self._num_lines(chip)} lines)") from None
        except OSError as exc:
            raise self._request_error(exc) from None
        finally:
            chip.close()
        self._last_seqno = None

    @staticmethod
    def _num_lines(chip: gpiod.Chip) -> Any:
        try:
            return chip.get_info().num_lines
        except OSError:
            return "?"

    def _request_error(self, exc: OSError) -> Exception:
        code = exc.errno
        if code == errno.ENOENT:
            return DeviceNotFound(f"PPS: no line named {self.line!r} on {self.chip_path}; "
                                  "check the line name or give its offset")
        if code == errno.EBUSY:
            return BusError(f"PPS: {self._where()} is busy: another program (gpiomon?) or the kernel's "
                            "pps-gpio driver holds it")
        if code in (errno.EACCES, errno.EPERM):
            return BusError(f"PPS: permission denied requesting {self._where()}")
        if code == errno.ENODEV:
            return BusError(f"PPS: GPIO chip {self.chip_path} went away while requesting line {self.line}")
        return BusError(f"PPS: cannot request {self._where()} for edge events: {exc.strerror}")

    def close(self) -> None:
        request, self._request = self._request, None
        if request is not None:
            try:
                request.release()
            except OSError:
                pass  # the chip is gone: nothing left to release

    def __enter__(self) -> PpsLine:
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def wait(self, timeout_s: float) -> list[PpsEdge]:
        """Edges that arrived, waiting up to ``timeout_s`` for the first; empty on timeout."""
        request = self._request
        if request is None:
            raise BusError(f"PPS: {self._where()} is not open")
        try:
            if not request.wait_edge_events(timedelta(seconds=max(0.0, timeout_s))):
                return []
            events = request.read_edge_events()
        except (OSError, gpiod.RequestReleasedError) as exc:
            self.close()
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise BusError(f"PPS: reading {self._where()} failed: {reason}") from None
        return self._decode(events)

    def _decode(self, events: list[gpiod.EdgeEvent]) -> list[PpsEdge]:
        out: list[PpsEdge] = []
        for ev in events:
            if ev.event_type is not self._event_type:
                continue
            last = self._last_seqno
            # line_seqno starts at 1 with each request; a smaller number means a new request.
            lost = ev.line_seqno - 1 if last is None else max(0, ev.line_seqno - last - 1)
            self._last_seqno = ev.line_seqno
            self.edges_total += 1
            self.lost_total += lost
            out.append(PpsEdge(ev.timestamp_ns, ev.line_seqno, ev.global_seqno, lost))
        return out
