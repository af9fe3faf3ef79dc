"""Synthetic edge streams for the clock: a seeded crystal, PPS interrupts, TIM-TP, fixes and IMU temperatures.

The stream is built from the same oscillator model as the simulated vehicle, but without threads or buses, so a
test can run hours of edges in a second and know the true time of every board instant.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from logger.recording.records import clock_observer
from sensors.sim.oscillator import Oscillator

NS = 1_000_000_000
UNIX_AT_GPS = 315_964_800 * NS
LEAP_S = 18
START_UTC_NS = 1_700_000_000 * NS  # a whole second


@dataclass
class Stream:
    """Events in board-time order: (board_ns, topic, payload)."""

    osc: Oscillator
    events: list[tuple[int, str, dict]] = field(default_factory=list)

    def true_unix_ns(self, board_ns: int) -> int:
        return START_UTC_NS + self.osc.true_ns(board_ns)


def make_stream(duration_s: float, seed: int = 0, offset_ppm: float = 30.0, swing_degc: float = 20.0,
                outages: tuple[tuple[float, float], ...] = (), imu_rate_hz: float = 20.0,
                latency_mean_us: float = 7.0, latency_sd_us: float = 2.0, timepulse: bool = True,
                fixes: bool = True, double_edges: tuple[int, ...] = (), spurious: tuple[float, ...] = (),
                late_fix_at: tuple[int, ...] = (), swing_period_s: float | None = None,
                stall_until_s: float = 0.0, stall_s: float = 0.0, flag_late_reads: bool = False,
                rate_pulse: tuple[float, float, float] | None = None, fix_line_s: float = 0.0) -> Stream:
    """A drive of ``duration_s`` true seconds; PPS (and time messages) missing inside ``outages`` (start, end).

    ``rate_pulse`` (start s, length s, ppm): the board clock runs that much faster for a while, its temperature
    unchanged, as CLOCK_MONOTONIC does while NTP (chrony) slews the system clock.

    ``fix_line_s``: each fix's epoch takes that long on the line (a 9600-baud NMEA burst): it is completed that long
    after its first message came, which the record says (``opened_mono_ns``), as the receiver's source does.

    ``stall_s``: messages before ``stall_until_s`` are seen that late; with ``flag_late_reads`` those late by half a
    second or more say so (``late_read``), as the receiver's source does when one read holds two seconds of them."""
    rng = np.random.default_rng(seed)
    period = swing_period_s or 2 * duration_s

    def ambient(t: float) -> float:
        return 15.0 + 0.5 * swing_degc * (1 - math.cos(math.pi * t / (period / 2)))

    def crystal(t: float) -> float:  # the oscillator's temperature: a rate pulse as degrees at 1 ppm/degC
        if rate_pulse is not None and rate_pulse[0] <= t < rate_pulse[0] + rate_pulse[1]:
            return ambient(t) + rate_pulse[2]
        return ambient(t)

    osc = Oscillator(offset_ppm=offset_ppm, tempco_ppm_per_degc=1.0, reference_degc=25.0,
                     ambient_degc=crystal, duration_s=duration_s + 10, board_start_ns=50 * NS, seed=rng)
    s = Stream(osc)
    ev = s.events
    sigma2 = math.log1p((latency_sd_us / latency_mean_us) ** 2)
    mu = math.log(latency_mean_us * 1000) - 0.5 * sigma2

    def blocked(t: float) -> bool:
        return any(a <= t < b for a, b in outages)

    for k in range(1, int(duration_s)):
        if blocked(k):
            continue
        edge = osc.board_ns(k * NS) + int(rng.lognormal(mu, math.sqrt(sigma2)))
        ev.append((edge, "/pps", {"seqno": k}))
        if k in double_edges:
            ev.append((edge + 3_000_000, "/pps", {"seqno": k}))
        utc = START_UTC_NS + k * NS
        late = int(stall_s * NS) if k < stall_until_s else 0  # the reading thread stalled: messages seen late
        flag = {"late_read": True} if flag_late_reads and late >= NS // 2 else {}
        if timepulse and not blocked(k - 1):
            gps = utc - UNIX_AT_GPS + LEAP_S * NS
            week, tow = divmod(gps, 604_800 * NS)
            ev.append((osc.board_ns(k * NS - 400_000_000 + late), "/gnss/timepulse",
                       {"tow_ms": int(tow // 1_000_000), "tow_sub_ms": 0.0, "week": int(week), "qerr_ps": 0,
                        "time_base": "gnss", **flag}))
        if fixes:
            delay = 1_300_000_000 if k in late_fix_at else int(rng.uniform(40e6, 390e6))
            gps_tow_ms = ((utc - UNIX_AT_GPS + LEAP_S * NS) % (604_800 * NS)) // 1_000_000
            line = int(fix_line_s * NS)
            opened = {"opened_mono_ns": osc.board_ns(k * NS + delay + late)} if line else {}
            ev.append((osc.board_ns(k * NS + delay + line + late), "/gnss/fix",
                       {"gnss_time_ns": utc, "itow_ms": int(gps_tow_ms), **flag, **opened}))
    for t in spurious:
        ev.append((osc.board_ns(int(t * NS)), "/pps", {"seqno": -1}))
    n_imu = int(duration_s * imu_rate_hz)
    t_imu = np.arange(n_imu) / imu_rate_hz + 0.013
    for t in t_imu[:: max(1, int(imu_rate_hz))]:  # one temperature a second is enough for the clock
        ev.append((osc.board_ns(int(t * NS)), "/imu", {"temp_degc": ambient(float(t)) + 3.0}))
    ev.sort(key=lambda e: e[0])
    return s


def feed(clock, events: list[tuple[int, str, dict]]) -> Iterator[tuple[int, str, dict]]:
    """The events through the record layer into the clock, as the daemon hands it records."""
    observe = clock_observer(clock)
    for board, topic, payload in events:
        handler = observe.get(topic)
        if handler is not None:
            handler(payload, board)
        yield board, topic, payload
