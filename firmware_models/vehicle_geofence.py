"""Geofence and rally points in the unit firmware's mode machine (PX4's navigator geofence and RTL roles).

In flight, every control step checks the vehicle's position against the stored fence and the
GF_MAX_HOR_DIST / GF_MAX_VER_DIST limits; the first step outside sends a STATUSTEXT and runs
GF_ACTION (none, warn, hold, return, terminate, land), once per breach (inside again re-arms it).
What clients ask for is checked before it is flown: mission uploads (whole plan, MAV_MISSION_ERROR
naming the item), the mission start, goto (MAV_RESULT_DENIED) and offboard position setpoints
(dropped, counted as setpoint_outside_fence). Return (RTL) goes to the rally point nearest to the
vehicle when rally points are stored, else home (PX4's RTL_TYPE 0 among rally points).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.geofence import (
    GF_ACTION_NAMES, GF_HOLD, GF_LAND, GF_NONE, GF_RTL, GF_TERMINATE, FenceLimits, Geofence, fence_shape_error,
)
from firmware_models.mission_protocol import FENCE, HERE_OK, MISSION, NAV_POSITION, RALLY, MissionItem
from firmware_models.vehicle_modes import MODE_HOLD, MODE_LAND, MODE_RTL

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle

R = mavlink


class GeofenceService:
    """The fence and rally points at work. Owns the fence's geometry (cached per fence version and home),
    the breach state and record (`breaches`). Asks of the vehicle: the stored lists (`mission`, `runner`),
    home and state, `params`, the mode machine for GF_ACTION, `_text`, `_count`, `_drop`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.cache: tuple | None = None  # (fence version, home) -> Geofence
        self.breached = False
        self.breaches: list[dict] = []  # {sim_time_s, position_ned_m, why, action} per breach
        self.text_wall = -1e9
        vehicle.mission.plan_check = self.plan_check

    # ----------------------------------------------------------------- geometry
    def geofence(self) -> Geofence:
        """The stored fence as geometry (rebuilt when the fence list or home changes)."""
        v = self.v
        home = None if v.home_ned is None else tuple(np.round(v.home_ned, 6))
        key = (v.mission.versions[FENCE], home)
        if self.cache is None or self.cache[0] != key:
            self.cache = (key, Geofence.from_items(v.mission.plans[FENCE], v.origin, v.home_ned))
        return self.cache[1]

    def limits(self) -> FenceLimits:
        v = self.v
        return FenceLimits(v.params["GF_MAX_HOR_DIST"], v.params["GF_MAX_VER_DIST"])

    def violation(self, p_ned: np.ndarray) -> str | None:
        """Why p_ned is not allowed (zones, then GF_* limits around home), or None."""
        return self.geofence().violation(np.asarray(p_ned, dtype=float), self.v.home_ned, self.limits())

    def _item_ned(self, item: MissionItem) -> np.ndarray | None:
        """Where a positional mission item sends the vehicle (None: no position or "where it is")."""
        v = self.v
        if item.command not in NAV_POSITION or (item.command in HERE_OK and item.x == 0 and item.y == 0):
            return None
        home = v.home_ned if v.home_ned is not None else (
            v.state.position_ned_m if v.state is not None else np.zeros(3))
        return v.runner.target_ned(item, v.state, np.asarray(home, dtype=float))

    def _first_outside(self, items: tuple[MissionItem, ...]) -> tuple[int, str] | None:
        for it in items:
            p = self._item_ned(it)
            why = None if p is None else self.violation(p)
            if why is not None:
                return it.seq, why
        return None

    # ----------------------------------------------------------------- uploads and commands
    def plan_check(self, mission_type: int, items: tuple[MissionItem, ...]) -> tuple[int, int, str, str] | None:
        """MissionProtocol.plan_check: a fence's polygons whole; a mission's waypoints inside the fence."""
        if mission_type == FENCE:
            bad = fence_shape_error(items)
            return None if bad is None else (R.MAV_MISSION_INVALID_PARAM1, bad[0], bad[1], "polygon vertices incomplete")
        if mission_type == MISSION:
            bad = self._first_outside(items)
            if bad is not None:
                return R.MAV_MISSION_ERROR, bad[0], "outside_fence", bad[1]
        return None

    def mission_refusal(self) -> str | None:
        """A stored mission that the (later uploaded) fence forbids is not started (PX4's feasibility check)."""
        bad = self._first_outside(self.v.runner.items)
        return None if bad is None else f"Mission item {bad[0]} {bad[1]}"

    def setpoint_outside(self, p_ned: np.ndarray) -> bool:
        v = self.v
        why = self.violation(p_ned)
        if why is None:
            return False
        v._drop("setpoint_outside_fence")
        if v.wall_s - self.text_wall >= 1.0:  # one STATUSTEXT a second for a stream of them
            self.text_wall = v.wall_s
            v._text(f"Setpoint refused: {why}", R.MAV_SEVERITY_WARNING)
        return True

    def return_point_ned(self) -> np.ndarray | None:
        """Where RTL goes: the nearest rally point (at home's ground height), else home."""
        v = self.v
        if v.home_ned is None:
            return None
        rally = v.mission.plans[RALLY]
        if not rally or v.state is None:
            return v.home_ned
        here = v.state.position_ned_m
        points = [v.runner.target_ned(it, v.state, v.home_ned) for it in rally]
        best = min(points, key=lambda p: float(np.hypot(*(p[:2] - here[:2]))))
        return np.array([best[0], best[1], v.home_ned[2]])

    # ----------------------------------------------------------------- in flight
    def step(self) -> None:
        """Once per tick: a breach by the vehicle's position triggers GF_ACTION once."""
        v = self.v
        s = v.state
        if s is None or not v.armed or v.landed:
            self.breached = False
            return
        why = self.violation(s.position_ned_m)
        if why is None:
            self.breached = False
            return
        if self.breached:
            return
        self.breached = True
        action = int(v.params["GF_ACTION"])
        v._count("geofence_breach")
        self.breaches.append({"sim_time_s": v.sim_s, "position_ned_m": [float(x) for x in s.position_ned_m],
                                    "why": why, "action": GF_ACTION_NAMES.get(action, str(action))})
        del self.breaches[:-100]
        if action == GF_NONE:
            return
        severity = R.MAV_SEVERITY_WARNING if action == 1 else R.MAV_SEVERITY_CRITICAL
        v._text(f"Geofence breached: {why}"[:50], severity)
        if action == GF_HOLD:
            if v.source != "own":
                v.command_service.hand_back(s)
            v.runner.pause()
            v.autopilot.hold(s)
            v.mode = MODE_HOLD
            v._text("Geofence: holding", severity)
        elif action == GF_RTL and v.mode != MODE_RTL:
            v.command_service.set_mode(MODE_RTL)
        elif action == GF_LAND and v.mode != MODE_LAND:
            v.command_service.set_mode(MODE_LAND)
        elif action == GF_TERMINATE:
            v.command_service.disarm("Geofence: flight terminated")
