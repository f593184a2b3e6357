"""The coordinator's side of the flight view in the multi-process SITL, on the lockstep link.

Why the world hosts run.mcap and the live Foxglove view (mars_link.flight.flight_view): it owns the truth of every
body (the /tf and /scene the view is about) and the rotor thrusts the units actually drove, it runs in every
set-up (also --units, also with an external or dead coordinator), and the coordinator must never be handed
the truth. What only the coordinator knows (its estimate, its reference, its events) comes to the world
after each step's commands are out, as standard MAVLink: ODOMETRY (the CoM estimate), POSITION_TARGET_LOCAL_NED
(the tracked point's reference) and one STATUSTEXT per event (its text; the event type as the id field's
index in EVENT_TYPES). The world logs them with the next step it logs (one control period late).
"""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mars_link.flight.flight_view import ViewPoint
from mars_link.core.rotations import quat_to_rotmat

EVENT_TYPES = ("event", "fault", "fault_detected", "reallocation", "uncontrollable", "unit_lost", "unit_died",
               "estimator_reset", "diverged")
_NAN21 = [math.nan] * 21
#: POSITION_TARGET_LOCAL_NED type mask: position and yaw only
_POSITION_YAW = 0b0000_1001_1111_1000


def feed_messages(record, new_events: list[dict]) -> list:
    """The coordinator's step (coordinator.StepRecord) and its new events as MAVLink messages to the world."""
    from mars_link.flight.events import event_text

    msgs = []
    t_us = int(round(record.t_s * 1e6))
    est = record.estimate
    if est is not None:
        p, q, v, w = est.position_ned_m, est.quaternion_wxyz, est.velocity_ned_mps, est.angular_velocity_frd_radps
        msgs.append(mavlink.MAVLink_odometry_message(
            t_us, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD, *map(float, p), [float(x) for x in q],
            *map(float, v), *map(float, w), _NAN21, _NAN21))
    ref = record.reference
    rp = ref.position_ned_m
    msgs.append(mavlink.MAVLink_position_target_local_ned_message(
        int(t_us // 1000), mavlink.MAV_FRAME_LOCAL_NED, _POSITION_YAW, *map(float, rp), 0, 0, 0, 0, 0, 0,
        float(ref.yaw_rad), 0))
    for ev in new_events:
        kind = str(ev.get("type", "event"))
        msgs.append(mavlink.MAVLink_statustext_message(
            mavlink.MAV_SEVERITY_INFO, event_text(ev).encode()[:50],
            EVENT_TYPES.index(kind) if kind in EVENT_TYPES else 0))
    return msgs


class ViewFeed:
    """World side: the latest estimate and reference from the coordinator, and its events, for the view."""

    def __init__(self, tracked_offset_frd_m: np.ndarray) -> None:
        self.offset = tracked_offset_frd_m
        self.estimate: tuple[np.ndarray, np.ndarray] | None = None
        self.reference: tuple[np.ndarray, float] | None = None
        self.events: list[dict] = []
        self._t_s = 0.0

    def take(self, m) -> bool:
        """A frame from the coordinator; True if it was one of the feed's."""
        kind = m.get_type()
        if kind == "ODOMETRY":
            q = np.array(m.q, dtype=float)
            p = np.array([m.x, m.y, m.z])
            if np.isfinite(p).all() and np.isfinite(q).all():
                self.estimate = (p + quat_to_rotmat(q) @ self.offset, q)
                self._t_s = m.time_usec / 1e6
        elif kind == "POSITION_TARGET_LOCAL_NED":
            p = np.array([m.x, m.y, m.z])
            if np.isfinite(p).all() and math.isfinite(m.yaw):
                self.reference = (p, float(m.yaw))
                self._t_s = m.time_boot_ms / 1e3
        elif kind == "STATUSTEXT":
            text = m.text if isinstance(m.text, str) else m.text.decode(errors="replace")
            kind_i = m.id if 0 <= m.id < len(EVENT_TYPES) else 0
            self.events.append({"t_s": round(self._t_s, 6), "type": EVENT_TYPES[kind_i], "text": text.rstrip("\x00")})
        else:
            return False
        return True

    def point(self, fallback_reference=None) -> ViewPoint | None:
        """The coordinator's latest (reference, estimate), or the scenario's reference (`fallback_reference`:
        a TrajectoryPoint) until the coordinator says."""
        if self.reference is not None:
            ref_p, ref_yaw = self.reference
        elif fallback_reference is not None:
            ref_p, ref_yaw = fallback_reference.position_ned_m, fallback_reference.yaw_rad
        else:
            return None
        est = self.estimate
        return ViewPoint(ref_p, ref_yaw, None if est is None else est[0], None if est is None else est[1])
