"""Reference trajectories for the tracked point (NED, SI). Kinds are filled in below.

A trajectory answers `sample(t_s)` with position and its derivatives, so controllers can feed
forward acceleration (and jerk where available). `t_s` runs from 0 at the start of the flight.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class TrajectoryPoint:
    position_ned_m: np.ndarray
    velocity_ned_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acceleration_ned_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    jerk_ned_mps3: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_rad: float = 0.0
    yaw_rate_radps: float = 0.0


class Trajectory:
    """Base class: subclasses set `duration_s` and implement `sample`."""

    duration_s: float = 0.0

    def sample(self, t_s: float) -> TrajectoryPoint:  # pragma: no cover - interface
        raise NotImplementedError

    def start(self) -> TrajectoryPoint:
        return self.sample(0.0)
