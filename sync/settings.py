"""The clock's tuning, in its own small module: the configuration reads its defaults from here.

Kept apart from :mod:`sync.clock` (which needs numpy) so that checking a configuration or asking ``logger status``
does not load the clock's maths on a slow board.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

NS = 1_000_000_000
NS_PER_US = 1_000  # the configuration states the PPS latency in us, the clock works in ns


@dataclass
class SyncSettings:
    imu_rate_hz: float = 20.0
    pps_latency_ns: int = 7_000  # mean delay from the pulse to the kernel's time stamp (pps-gpio interrupt)
    pps_latency_spread_ns: int = 10_000  # allowance for that delay's variation in the error bound
    max_samples: int = 64
    lock_samples: int = 3
    holdover_after_s: float = 1.5  # no edge for this long: HOLDOVER
    restart_window_after_s: float = 30.0  # a gap this long starts the regression afresh (frequency prior)
    stability_ppm: float = 1.0  # how far the frequency may wander unseen (chrony's maxclockerror)
    tempco_bound_ppm_per_degc: float = 1.5  # assumed |df/dT| while the coefficient is not learned
    sigma_k: float = 4.0  # error bound = sigma_k * standard error + the allowances
    max_slew_ppm: float = 500.0
    min_sigma_ns: float = 500.0
    # A free-running stamp's bound when the system clock was NTP-synchronised at start (clock.NO_BOUND_NS when not)
    freerun_err_ns: int = 10 * NS
    save_interval_s: float = 300.0

    @classmethod
    def from_config(cls, section: Mapping[str, Any], *, imu_rate_hz: float) -> SyncSettings:
        """From the validated ``[sync]`` section of the logger's configuration, as a plain mapping.

        The one place that knows which key sets which field and in what unit; the configuration's schema takes
        its defaults from these fields (``pps_latency_us`` from ``pps_latency_ns / NS_PER_US``). Keys without a
        field here (``chrony_sock``) are the caller's. ``imu_rate_hz`` comes from the ``[imu]`` section and is
        required: a default here would silently misnumber the paper's counters of a board sampling faster.
        """
        return cls(imu_rate_hz=imu_rate_hz, pps_latency_ns=round(section["pps_latency_us"] * NS_PER_US),
                   stability_ppm=section["stability_ppm"], max_slew_ppm=section["max_slew_ppm"])
