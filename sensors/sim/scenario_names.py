"""The names of the simulated drives, apart from the drives themselves: the configuration checks a name
(``logger config check`` agrees with ``logger run``) without loading numpy and the vehicle model."""

from __future__ import annotations

SCENARIOS = ("urban", "outage-60s", "tunnel-130s")
