"""Controller interface shared by every flight controller."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import TrajectoryPoint


@dataclass
class ControlOutput:
    rotor_thrusts_n: np.ndarray  # (4N,) commanded thrust per rotor, slot order of AssemblyModel
    wrench_demand: np.ndarray = field(default_factory=lambda: np.zeros(4))  # (thrust_n, L, M, N)
    timings_s: dict[str, float] = field(default_factory=dict)  # e.g. {"control": .., "allocation": ..}


class Controller:
    """A controller keeps its own internal state; `update` is called at the control rate.

    `reference` is for the tracked point; `tracked_offset_frd_m` (set at construction) is where that
    point sits relative to the CoM in the body frame (zero for "com").
    """

    def update(self, t_s: float, state: RigidBodyState, reference: TrajectoryPoint) -> ControlOutput:
        raise NotImplementedError  # pragma: no cover - interface

    def set_faults(self, eta: np.ndarray) -> None:
        """Tell the controller the rotor efficiencies it should allocate around (FTC)."""
