"""The GNSS receiver's timepulse as the board's GPIO sees it: one stamped rising edge per second while in fix.

A u-blox receiver in its default timepulse configuration drives a 100 ms pulse whose rising edge is the top
of each GNSS second while it has a time fix (give ``has_fix`` the receiver model's view of that), and keeps
the line low without one; ``pulse_offset_ns`` adds the receiver's few-ns quantisation error if wanted.
The board stamps the edge in the gpiolib interrupt handler, after an interrupt latency that on a BeagleBone
averages about 7 us with a spread of about 2 us and a tail to the late side (log-normal here, never
negative); the stamp is the board's CLOCK_MONOTONIC, i.e. the oscillator's reading at that moment.

Every draw belongs to one pulse (blocks of pulses share a generator seeded from ``(seed, block)``), so the
edges do not depend on how often or in which windows they are asked for. Faults can be injected: a missed
edge (the interrupt never fires: the kernel's sequence numbers show no gap, only the time stamps do), a
double edge (a glitch on the high pulse: an extra falling and rising edge a few ms after the true one) and a
spurious edge at any time. Edges lost because the reader was too slow show up as sequence-number gaps; that
happens in the kernel's FIFO, modelled in :mod:`sensors.sim.gpiod_ext`.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable

import numpy as np

from sensors.sim.clock import DriveClock
from sensors.sim.gpiod_ext import LineEdge, SimGpioChip
from sensors.sim.oscillator import Oscillator

NS_PER_S = 1_000_000_000
_BLOCK = 1024  # pulses per generator block


class PpsSignal:
    """A receiver's PPS output, wired to a GPIO line; an :class:`~sensors.sim.gpiod_ext.EdgeSource`."""

    def __init__(self, oscillator: Oscillator, has_fix: Callable[[float], bool], *, seed: int = 0,
                 gnss_ns_at_start: int = 0, irq_latency_mean_us: float = 7.0, irq_latency_sd_us: float = 2.0,
                 pulse_width_s: float = 0.1, missed_probability: float = 0.0, double_probability: float = 0.0,
                 glitch_delay_s: float = 0.002, glitch_width_s: float = 0.0005,
                 pulse_offset_ns: Callable[[int], float] | None = None) -> None:
        if not 0.0 < pulse_width_s < 1.0:
            raise ValueError("the pulse must be shorter than its one-second period")
        if not (glitch_delay_s > 0.0 and glitch_delay_s + glitch_width_s < pulse_width_s):
            raise ValueError("a double-edge glitch must sit inside the pulse")
        if irq_latency_mean_us <= 0.0 or irq_latency_sd_us < 0.0:
            raise ValueError("interrupt latency needs a positive mean and a non-negative spread")
        self.oscillator = oscillator
        self.has_fix = has_fix
        self.seed = int(seed)
        # Where the receiver actually puts the pulse of a GNSS second, relative to the ideal instant (its
        # quantisation saw-tooth, a few ns): given the second number on the epoch of gnss_ns_at_start.
        self.pulse_offset_ns = pulse_offset_ns
        # Pulses sit on whole GNSS seconds: true times k * 1e9 - phase, counted from the drive's start.
        self.gnss_ns_at_start = int(gnss_ns_at_start)
        self._phase_ns = self.gnss_ns_at_start % NS_PER_S
        self.pulse_width_ns = round(pulse_width_s * NS_PER_S)
        self.glitch_delay_ns = round(glitch_delay_s * NS_PER_S)
        self.glitch_width_ns = round(glitch_width_s * NS_PER_S)
        self.missed_probability = float(missed_probability)
        self.double_probability = float(double_probability)
        sigma2 = math.log1p((irq_latency_sd_us / irq_latency_mean_us) ** 2)
        self._ln_mu = math.log(irq_latency_mean_us * 1000.0) - 0.5 * sigma2
        self._ln_sigma = math.sqrt(sigma2)
        self._lock = threading.Lock()
        self._blocks: dict[int, np.ndarray] = {}
        self._missed: set[int] = set()
        self._doubled: set[int] = set()
        self._spurious: list[tuple[int, int, int]] = []  # (rise true ns, rise irq latency, fall irq latency)
        self._fault_rng = np.random.default_rng([self.seed, 2])

    # pulse numbering ----------------------------------------------------------------------------------
    @property
    def first_pulse(self) -> int:
        """Index of the first pulse at or after the start of the drive."""
        return 0 if self._phase_ns == 0 else 1

    def pulse_true_ns(self, k: int) -> int:
        """True drive time of the whole GNSS second that pulse k marks."""
        return k * NS_PER_S - self._phase_ns

    def pulse_edge_true_ns(self, k: int) -> int:
        """True drive time of pulse k's rising edge on the wire: the second plus the receiver's offset."""
        t = self.pulse_true_ns(k)
        if self.pulse_offset_ns is None:
            return t
        return t + round(self.pulse_offset_ns(self.pulse_gnss_ns(k) // NS_PER_S))

    def pulse_gnss_ns(self, k: int) -> int:
        """GNSS time the pulse marks, on the epoch of ``gnss_ns_at_start``."""
        return self.gnss_ns_at_start + self.pulse_true_ns(k)

    def pulse_index(self, true_ns: int) -> int:
        """Index of the last pulse at or before ``true_ns``."""
        return (int(true_ns) + self._phase_ns) // NS_PER_S

    # faults -------------------------------------------------------------------------------------------
    def inject_missed(self, k: int) -> None:
        """Pulse k's rising edge raises no interrupt."""
        with self._lock:
            self._missed.add(int(k))

    def inject_double(self, k: int) -> None:
        """Pulse k carries a glitch: falling then rising again ``glitch_delay_s`` after the true edge."""
        with self._lock:
            self._doubled.add(int(k))

    def inject_spurious(self, true_ns: int) -> None:
        """A short positive glitch (rising, then falling after ``glitch_width_s``) at any time."""
        lat = self._fault_rng.lognormal(self._ln_mu, self._ln_sigma, 2)
        with self._lock:
            bisect.insort(self._spurious, (int(true_ns), round(float(lat[0])), round(float(lat[1]))))

    # draws --------------------------------------------------------------------------------------------
    def _draws(self, k: int) -> np.ndarray:
        """Per-pulse draws: latencies (ns) of rise, fall, glitch fall, glitch rise; two uniforms for faults."""
        block = k // _BLOCK
        with self._lock:
            arr = self._blocks.get(block)
        if arr is None:
            rng = np.random.default_rng([self.seed, 1, block])
            lat = rng.lognormal(self._ln_mu, self._ln_sigma, (_BLOCK, 4))
            uni = rng.random((_BLOCK, 2))
            arr = np.column_stack((np.round(lat), uni))
            with self._lock:
                if len(self._blocks) > 64:
                    self._blocks.clear()
                self._blocks[block] = arr
        return arr[k - block * _BLOCK]

    def latency_ns(self, k: int) -> int:
        """Interrupt latency of pulse k's rising edge (true ns from the edge on the wire)."""
        return int(self._draws(k)[0])

    def _pulse_edges(self, k: int) -> list[tuple[int, int, bool, bool]]:
        """(physical edge true ns, irq true ns, rising, raises an interrupt) of pulse k, if it is output."""
        if k < self.first_pulse or not self.has_fix(self.pulse_true_ns(k) / NS_PER_S):
            return []
        t = self.pulse_edge_true_ns(k)
        d = self._draws(k)
        with self._lock:
            missed = k in self._missed
            doubled = k in self._doubled
        missed = missed or d[4] < self.missed_probability
        doubled = doubled or d[5] < self.double_probability
        edges = [(t, t + int(d[0]), True, not missed),
                 (t + self.pulse_width_ns, t + self.pulse_width_ns + int(d[1]), False, True)]
        if doubled:
            g = t + self.glitch_delay_ns
            edges.append((g, g + int(d[2]), False, True))
            edges.append((g + self.glitch_width_ns, g + self.glitch_width_ns + int(d[3]), True, True))
        return edges

    def _spurious_edges(self, lo_ns: int, hi_ns: int) -> list[tuple[int, int, bool, bool]]:
        with self._lock:
            spurious = list(self._spurious)
        out = []
        for t, lat_r, lat_f in spurious:
            if lo_ns <= t <= hi_ns:
                out.append((t, t + lat_r, True, True))
                out.append((t + self.glitch_width_ns, t + self.glitch_width_ns + lat_f, False, True))
        return out

    def _edges_near(self, lo_ns: int, hi_ns: int) -> list[tuple[int, int, bool, bool]]:
        """All physical edges of pulses that may raise an interrupt in [lo, hi], sorted by interrupt time."""
        reach = self.pulse_width_ns + NS_PER_S // 10  # a pulse's last interrupt comes before this
        k0 = max(self.first_pulse, self.pulse_index(lo_ns - reach))
        k1 = self.pulse_index(hi_ns)
        edges = [e for k in range(k0, k1 + 1) for e in self._pulse_edges(k)]
        edges += self._spurious_edges(lo_ns - reach, hi_ns)
        edges.sort(key=lambda e: e[1])
        return edges

    # EdgeSource ---------------------------------------------------------------------------------------
    def edges_between(self, after_true_ns: int, until_true_ns: int) -> list[LineEdge]:
        board = self.oscillator.board_ns
        return [LineEdge(irq, board(irq), rising)
                for _t, irq, rising, fires in self._edges_near(after_true_ns, until_true_ns)
                if fires and after_true_ns < irq <= until_true_ns]

    def next_edge_after(self, true_ns: int, horizon_ns: int) -> int | None:
        for _t, irq, _rising, fires in self._edges_near(true_ns, true_ns + horizon_ns):
            if fires and true_ns < irq <= true_ns + horizon_ns:
                return irq
        return None

    def level_at(self, true_ns: int) -> bool:
        level = False
        for t, _irq, rising, _fires in sorted(self._edges_near(true_ns - NS_PER_S, true_ns)):
            if t <= true_ns:
                level = rising
        return level


def pps_chip(signal: PpsSignal, clock: DriveClock, *, path: str = "/dev/gpiochip-sim", offset: int = 28,
             line_name: str = "P9_12", paced: bool = False) -> SimGpioChip:
    """A BeagleBone GPIO bank (32 lines) with the PPS wired to ``offset`` (P9_12 is GPIO1_28)."""
    return SimGpioChip(path, clock, num_lines=32, line_names={offset: line_name}, sources={offset: signal},
                       name="gpiochip1", label="4804c000.gpio", paced=paced,
                       board_ns=signal.oscillator.board_ns)
