"""Self-reconfiguration after rotor faults (paper 001, Gandhi et al. 2020; spec: specs/reconfig.md).

Pipeline: `solve_placement` (which unit goes where, given rotor health and trajectory snap weights)
-> `plan_reconfiguration` (fewest disassembly layers that keep every piece flyable, then the
docking layers; infinite-cost fallback with bound blocks) -> `build_configuration_tree` (plans
precomputed per fault sequence). In flight: `execution.Executor` turns a plan into timed per-piece
references and split/dock requests; `flight.runner.run_scenario` flies it with one JSBSim body,
controller and coordinator per piece (splits and docks by sitl/docking.py, momentum kept).

Rotor numbers are mars-link's everywhere (1..4 = FR, FL, RL, RR). Paper 001 numbers rotors
clockwise from top-right; `rotor_from_paper001` is the one place that maps them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mars_link.core.errors import UserInputError
from mars_link.reconfig.flyability import FlyabilityRule, is_flyable
from mars_link.reconfig.placement import Placement, SnapWeights, health_from_eta, solve_placement
from mars_link.reconfig.sequencing import ReconfigPlan, Sequencer, plan_reconfiguration
from mars_link.reconfig.tree import ConfigurationTree, FaultEvent, build_configuration_tree

#: paper 001 rotor (1 top-right = front-right, then clockwise seen from above) -> mars-link rotor
PAPER001_TO_MARS_ROTOR: dict[int, int] = {1: 1, 2: 4, 3: 3, 4: 2}


def rotor_from_paper001(rotor: int) -> int:
    """Paper 001 rotor number -> mars-link rotor number (FR, FL, RL, RR)."""
    if rotor not in PAPER001_TO_MARS_ROTOR:
        raise UserInputError(f"paper 001 rotor {rotor!r} does not exist (rotors are 1..4)")
    return PAPER001_TO_MARS_ROTOR[rotor]


@dataclass(frozen=True)
class HelixReference:
    """The Fig. 1 / Fig. 5 helix of paper 001's driver (spec §3, §12.1), for the flight comparisons.

    As the paper-era code drew it: start at the origin on the ground, a radial leg of one radius
    along +x, then `turns` turns around the origin with the height rising linearly by `rise_m`,
    waypoints every `angle_step_rad`, flown at `speed_mps` through a min-snap fit. (The driver's
    final ~1 m exit leg is not in the text; spec §3 gives 35.5 m in total, this polyline 34.0 m.)
    Paper frame: x forward, y left, z up; `waypoints_ned` maps it once to NED (n = x, e = -y, d = -z).
    """

    radius_m: float = 2.5
    rise_m: float = 3.0
    turns: float = 2.0
    speed_mps: float = 1.25
    angle_step_rad: float = math.pi / 36  # 5 degrees (the code comment "ten steps" is wrong)
    start_at_origin: bool = True  # include the origin, hence the radial first leg

    def waypoints_paper(self) -> np.ndarray:
        """(K, 3) waypoints in the paper's z-up frame, circle centred on the origin."""
        steps = int(round(self.turns * 2 * math.pi / self.angle_step_rad))
        th = np.arange(steps + 1) * self.angle_step_rad
        pts = np.column_stack([
            self.radius_m * np.cos(th), self.radius_m * np.sin(th), self.rise_m * th / th[-1],
        ])
        return np.vstack([np.zeros(3), pts]) if self.start_at_origin else pts

    def waypoints_ned(self, ground_down_m: float = 0.0) -> np.ndarray:
        p = self.waypoints_paper()
        return np.column_stack([p[:, 0], -p[:, 1], ground_down_m - p[:, 2]])

    def path_length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.waypoints_paper(), axis=0), axis=1).sum())

    def duration_s(self) -> float:
        """t_max = polyline length / speed, as the paper-era driver computes it."""
        return self.path_length_m() / self.speed_mps

    def trajectory_params(self, start_height_m: float = 1.0) -> dict:
        """Parameters for mars-link's smooth `helix` trajectory kind (analytic, no radial jump).

        That kind starts on the circle after a vertical take-off; use it when the paper's take-off
        jump is not wanted (spec §14 item 10).
        """
        return {"radius_m": self.radius_m, "speed_mps": self.speed_mps, "turns": self.turns,
                "start_height_m": start_height_m, "height_m": start_height_m + self.rise_m}


__all__ = [
    "ConfigurationTree", "FaultEvent", "FlyabilityRule", "HelixReference", "PAPER001_TO_MARS_ROTOR",
    "Placement", "ReconfigPlan", "Sequencer", "SnapWeights", "build_configuration_tree",
    "health_from_eta", "is_flyable", "plan_reconfiguration", "rotor_from_paper001", "solve_placement",
]
