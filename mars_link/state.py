"""State and measurement records exchanged between the world, the units and the coordinator."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class RigidBodyState:
    """Kinematic state of one rigid body's CoM. World NED, body FRD, SI."""

    t_s: float
    position_ned_m: np.ndarray
    velocity_ned_mps: np.ndarray
    quaternion_wxyz: np.ndarray  # body FRD -> world NED
    angular_velocity_frd_radps: np.ndarray
    acceleration_ned_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    on_ground: bool = False


@dataclass
class ImuSample:
    """What one unit's IMU reports (body FRD of the unit = of its assembly, since units do not rotate)."""

    t_s: float
    unit_id: int
    gyro_frd_radps: np.ndarray
    accel_frd_mps2: np.ndarray  # specific force (reads -g on z at rest: (0, 0, -9.81))
    # False: that part did not update this sample (a failed sensor; HIGHRES_IMU fields_updated bits clear)
    accel_ok: bool = True
    gyro_ok: bool = True


@dataclass
class PositionSample:
    """GPS-like position of one unit's centre, local NED."""

    t_s: float
    unit_id: int
    position_ned_m: np.ndarray
    velocity_ned_mps: np.ndarray | None = None
