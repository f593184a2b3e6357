"""State and measurement records exchanged between the world, the units and the coordinator."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mars_link.core.rotations import quat_to_rotmat


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


@dataclass
class GpsSample:
    """What a unit's GNSS receiver reports (HIL_GPS's fields, at their wire precision): WGS84 position
    in degE7 and mm AMSL, NED velocity in cm/s, accuracies in cm. `t_s` is when it arrives; it measures
    the receiver of `gps_latency_s` earlier (the estimator is told the latency, as PX4's EKF2_GPS_DELAY)."""

    t_s: float
    unit_id: int
    lat_e7: int
    lon_e7: int
    alt_mm: int
    vel_ned_cmps: tuple[int, int, int]
    eph_cm: int
    epv_cm: int
    satellites: int = 12


@dataclass
class BaroSample:
    """A unit's barometer (HIL_SENSOR abs_pressure, pressure_alt; float32 on the wire)."""

    t_s: float
    unit_id: int
    pressure_hpa: float
    altitude_amsl_m: float  # the pressure altitude (ISA), m above mean sea level


@dataclass
class MagSample:
    """A unit's magnetometer (HIL_SENSOR xmag, ymag, zmag): the field in the body frame, gauss."""

    t_s: float
    unit_id: int
    field_frd_gauss: np.ndarray


def point_state(s: RigidBodyState, offset_frd_m: np.ndarray) -> RigidBodyState:
    """The state of a point fixed in the body at `offset_frd_m` from the CoM (v + R (w x r))."""
    r = quat_to_rotmat(s.quaternion_wxyz)
    w, o = s.angular_velocity_frd_radps, offset_frd_m
    w_x_o = np.array([w[1] * o[2] - w[2] * o[1], w[2] * o[0] - w[0] * o[2], w[0] * o[1] - w[1] * o[0]])
    return RigidBodyState(
        s.t_s, s.position_ned_m + r @ o, s.velocity_ned_mps + r @ w_x_o,
        s.quaternion_wxyz, w, s.acceleration_ned_mps2, s.on_ground,
    )
