"""What the OBD-II tests share: the ELM327 adapter tests and the native CAN tests drive the same ECU model."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from sensors.sim.truth import StraightTrajectory, TruthState


@dataclass
class SwitchableTrajectory:
    """A straight drive whose ignition a test turns on and off."""

    speed_mps: float = 13.9
    engine_on: bool = True
    duration_s: float = math.inf

    def state(self, t_s: float) -> TruthState:
        return replace(StraightTrajectory(speed_mps=self.speed_mps).state(t_s), engine_on=self.engine_on)
