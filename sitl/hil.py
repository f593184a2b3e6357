"""World -> unit ground truth as PX4's simulators send it: HIL_STATE_QUATERNION.

Position goes as latitude/longitude on the spherical Earth the unit firmware assumes (origin 0, 0,
local NED north = R * lat, `mars_link.core.geo.WIRE_ORIGIN`): 1e-7 deg is about 1.1 cm;
altitude in mm, velocity in cm/s, as the message defines them. The firmware uses it for its own
telemetry and arming checks; a coordinator never receives it.
"""

from __future__ import annotations

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.geo import WIRE_ORIGIN
from mars_link.core.state import RigidBodyState


def _int16(x: float) -> int:
    return int(max(-32767, min(32767, round(x))))


def hil_state_message(s: RigidBodyState, time_usec: int) -> mavlink.MAVLink_hil_state_quaternion_message:
    p = s.position_ned_m
    lat, lon, alt_mm = WIRE_ORIGIN.to_global_int(p)
    v = s.velocity_ned_mps
    w = s.angular_velocity_frd_radps
    speed_cms = min(65535, int(round(float(np.linalg.norm(v)) * 100)))
    return mavlink.MAVLink_hil_state_quaternion_message(
        time_usec, [float(x) for x in s.quaternion_wxyz], float(w[0]), float(w[1]), float(w[2]), lat, lon, alt_mm,
        _int16(v[0] * 100), _int16(v[1] * 100), _int16(v[2] * 100), speed_cms, speed_cms, 0, 0, 0)
