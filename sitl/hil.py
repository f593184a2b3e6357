"""World -> unit ground truth as PX4's simulators send it: HIL_STATE_QUATERNION.

Position goes as latitude/longitude on the spherical Earth the unit firmware assumes (origin 0, 0,
local NED north = R * lat, `mars_link.core.geo.WIRE_ORIGIN`): 1e-7 deg is about 1.1 cm;
altitude in mm, velocity in cm/s, as the message defines them (`mars_link.mavlink.wire.hil_state_fields`;
`hil_state_received` is what the unit takes from it). The firmware uses it for its own
telemetry and arming checks; a coordinator never receives it.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.state import RigidBodyState
from mars_link.mavlink.wire import hil_state_fields


def hil_state_message(s: RigidBodyState, time_usec: int) -> mavlink.MAVLink_hil_state_quaternion_message:
    q, rates, lat, lon, alt_mm, vx, vy, vz, speed_cms = hil_state_fields(s)
    return mavlink.MAVLink_hil_state_quaternion_message(
        time_usec, q, *rates, lat, lon, alt_mm, vx, vy, vz, speed_cms, speed_cms, 0, 0, 0)
