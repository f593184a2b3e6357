"""Follow-me: PX4's AUTO.FOLLOW_TARGET fed by FOLLOW_TARGET messages (MAVSDK's follow_me plugin).

MAVSDK's FollowMe.start() switches to AUTO.FOLLOW_TARGET (custom main 4, sub 8), then sends the
target's FOLLOW_TARGET once a second (and at each set_target_location); its set_config writes PX4's
FLW_TGT_* parameters, which this mode reads every control step:
  FLW_TGT_DST    horizontal distance to keep from the target (m)
  FLW_TGT_HT     height: above home (FLW_TGT_ALT_M 0 and 1: the world here has no terrain) or above
                 the target's own altitude (FLW_TGT_ALT_M 2, 3D tracking)
  FLW_TGT_FA     where around the target: 0 in front of its course, clockwise in degrees (180 behind)
  FLW_TGT_RS     responsiveness of the target's velocity estimate (0 follows each fix, 1 never changes)
  FLW_TGT_MAX_VEL  cap of the vehicle's speed while following (m/s, within MPC_XY_VEL_MAX)
Between fixes the target is extrapolated with its velocity (the message's, when it carries one,
else estimated from consecutive fixes); its course is that velocity's direction, held while it
stands still. The vehicle flies a velocity target (the target's velocity plus a correction towards
the follow point, on the reference, so the lag vanishes on a steady course) facing the target. No fix
for FOLLOW_LOST_S: it holds where it is and says so; a follow point outside the geofence: it holds.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle_links import Link, Outgoing
from firmware_models.vehicle_links import finite as _finite
from firmware_models.vehicle_modes import MODE_FOLLOW

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle

R = mavlink
FOLLOW_LOST_S = 2.5  # MAVSDK sends a fix every second: more than two missed is a lost target
FOLLOW_GAIN_PER_S = 1.0  # correction speed per metre between the reference and the follow point
MOVING_MPS = 0.3  # slower than this the target's course is not updated
FOLLOW_YAW_RATE_RADPS = 0.3  # facing the target: at most this yaw rate (a 3x2 at 1 rad/s loses height)
FOLLOW_YAW_GAIN_PER_S = 1.0
EST_POS, EST_VEL = 1 << 0, 1 << 1  # FOLLOW_TARGET est_capabilities bits


class FollowService:
    """AUTO.FOLLOW_TARGET. Owns the target's track and whether the mode holds for want of it. Asks of the
    vehicle: state, home, sim time, `params`, the flight core, the mode machine, the geofence service,
    `_text`, `_count`, `_drop`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.target: dict | None = None  # {"p": ned, "v": ned, "t": sim time of the fix, "course": rad}
        self.holding = False

    # ----------------------------------------------------------------- FOLLOW_TARGET
    def on_follow_target(self, msg, lk: Link, out: list[Outgoing]) -> None:
        lat, lon, alt = msg.lat * 1e-7, msg.lon * 1e-7, msg.alt
        if not (_finite(alt) and -90 <= lat <= 90 and -180 <= lon <= 180) or (lat == 0 and lon == 0):
            self.v._drop("follow_target_invalid")
            return
        p = self.v._global_to_ned(lat, lon, alt)
        if np.linalg.norm(p[:2]) > 10_000.0:
            self.v._drop("follow_target_too_far")
            return
        vel = np.array(msg.vel, dtype=float)
        given = np.all(np.isfinite(vel)) and (msg.est_capabilities & EST_VEL or np.any(vel != 0.0))
        old = self.target
        t = self.v.sim_s
        if given:
            v = vel
        elif old is not None and t - old["t"] > 0.05:
            v = (p - old["p"]) / (t - old["t"])
        else:
            v = np.zeros(3)
        if old is not None and not given:
            rs = min(max(self.v.params["FLW_TGT_RS"], 0.0), 1.0)
            v = rs * old["v"] + (1.0 - rs) * v
        course = old["course"] if old is not None else None
        if math.hypot(v[0], v[1]) >= MOVING_MPS:
            course = math.atan2(v[1], v[0])
        self.target = {"p": p, "v": v, "t": t, "course": course}
        self.v._count("follow_target")

    # ----------------------------------------------------------------- the mode
    def enter(self) -> int:
        v = self.v
        s = v.state
        if s is None or not v.armed or v.landed:
            return v.command_service.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "not flying (take off first)")  # as PX4
        if v.source != "own":
            v.command_service.hand_back(s)
        v.autopilot.hold(s)
        v.mode = MODE_FOLLOW
        self.holding = self.target is None
        v._text("Follow target")
        return R.MAV_RESULT_ACCEPTED

    def point_ned(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(follow point, target position, target velocity) now, or None without a live target."""
        v = self.v
        tg = self.target
        if tg is None or v.sim_s - tg["t"] > FOLLOW_LOST_S or v.state is None:
            return None
        p_t = tg["p"] + tg["v"] * (v.sim_s - tg["t"])
        course = tg["course"]
        if course is None:  # never seen moving: keep the side the vehicle is on
            d = v.state.position_ned_m[:2] - p_t[:2]
            course = math.atan2(-d[1], -d[0]) if np.hypot(*d) > 1e-3 else 0.0
            tg["course"] = course
        side = course + math.radians(v.params["FLW_TGT_FA"])
        dist = v.params["FLW_TGT_DST"]
        point = np.array([p_t[0] + dist * math.cos(side), p_t[1] + dist * math.sin(side), 0.0])
        if int(v.params["FLW_TGT_ALT_M"]) == 2:
            point[2] = p_t[2] - v.params["FLW_TGT_HT"]
        else:
            point[2] = v.home_ned[2] - v.params["FLW_TGT_HT"]
        return point, p_t, tg["v"]

    def step(self) -> None:
        """Each control step in AUTO.FOLLOW_TARGET: a velocity target onto the follow point."""
        ap, s = self.v.autopilot, self.v.state
        got = self.point_ned()
        if got is None or self.v.geofence_service.setpoint_outside(got[0]):
            if not self.holding:
                self.holding = True
                ap.hold(s)
                self.v._text("Follow: target lost, holding" if got is None else "Follow: point outside the fence",
                             R.MAV_SEVERITY_WARNING)
            return
        self.holding = False
        point, p_t, v_t = got
        ref = ap.shaper.p
        v = v_t.copy()
        v[:2] = v[:2] + FOLLOW_GAIN_PER_S * (point[:2] - ref[:2])
        v[2] = FOLLOW_GAIN_PER_S * (point[2] - ref[2]) + (v_t[2] if int(self.v.params["FLW_TGT_ALT_M"]) == 2 else 0.0)
        cap = min(self.v.params["FLW_TGT_MAX_VEL"], self.v.params["MPC_XY_VEL_MAX"])
        sxy = math.hypot(v[0], v[1])
        if sxy > cap:
            v[:2] *= cap / sxy
        face = p_t[:2] - ref[:2]
        rate = 0.0
        if np.hypot(*face) > 0.5:  # turn towards the target, gently (an assembly's yaw authority is small)
            turn = (math.atan2(face[1], face[0]) - ap.shaper.yaw + math.pi) % (2 * math.pi) - math.pi
            rate = max(-FOLLOW_YAW_RATE_RADPS, min(FOLLOW_YAW_RATE_RADPS, FOLLOW_YAW_GAIN_PER_S * turn))
        ap.velocity(s, v, None, rate)
