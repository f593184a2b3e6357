"""Flies the stored mission in AUTO.MISSION through the vehicle's flight core (PX4's navigator role).

Sans-IO: `step(t_s, state, home_ned, event)` once per control step, after the flight core's own
update (`event` is what that update reported: "takeoff_done", "rtl_home", "landed" or None). The
runner drives the core with the same guidance calls the vehicle uses for takeoff, reposition, land and
return (`takeoff`, `goto`, `hold`, `land`, `rtl`), so every setpoint goes through the core's
reference shaper and speed limits, for a lone unit and for an assembly alike. Out come MAVLink
messages (MISSION_CURRENT on every change, MISSION_ITEM_REACHED for every item done), STATUSTEXTs and
a new home for DO_SET_HOME.

Items: NAV_WAYPOINT (hold time p1, acceptance radius p2, yaw p4), NAV_TAKEOFF, NAV_LAND,
NAV_RETURN_TO_LAUNCH, NAV_LOITER_TIME, NAV_LOITER_UNLIM, NAV_DELAY, DO_CHANGE_SPEED, DO_JUMP,
DO_SET_HOME; global frames (absolute or home-relative altitude) and local frames (LOCAL_NED around
the origin, LOCAL_OFFSET_NED around home). Started on the ground, the mission first climbs to the
first item's altitude (at least MIS_TAKEOFF_ALT), as PX4 does. After the last item the vehicle holds
where it is, unless that item landed it (NAV_LAND, NAV_RETURN_TO_LAUNCH: MAVSDK's
`set_return_to_launch_after_mission` appends such an RTL item).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.geo import GeoOrigin
from firmware_models.mission_protocol import GLOBAL_REL, HERE_OK, LOCAL_SCALE, MissionItem
from mars_link.core.state import RigidBodyState

R = mavlink
DEFAULT_ACCEPTANCE_M = 0.5  # NAV_WAYPOINT p2 = 0/NaN (PX4's NAV_ACC_RAD is 10 m, sized for larger craft)
MAX_ITEMS_PER_STEP = 32  # DO_* items run back to back; a DO_JUMP loop without NAV items stops here


@dataclass
class RunnerOutput:
    messages: list
    texts: list[str]
    new_home_ned: np.ndarray | None = None


class MissionRunner:
    """Current item, jump counters, speed override; the phase within the current item."""

    def __init__(self, flight_core, origin: GeoOrigin) -> None:
        self.core = flight_core
        self.origin = origin
        self.items: tuple[MissionItem, ...] = ()
        self.current = 0
        self.complete = False
        self.speed_mps: float | None = None  # DO_CHANGE_SPEED override of the horizontal speed limit
        self.takeoff_alt_m = 2.0  # MIS_TAKEOFF_ALT (the vehicle keeps it up to date)
        self.rtl_alt_m = 5.0  # RTL_RETURN_ALT
        self._jumps: dict[int, int] = {}
        self._phase: str | None = None  # None: the current item is not entered yet
        self._target: np.ndarray | None = None
        self._wait_until = 0.0
        self._reached_seq: int | None = None
        self._out: RunnerOutput = RunnerOutput([], [])
        self._announced: tuple | None = None

    # ----------------------------------------------------------------- plan and position in it
    def load(self, items: tuple[MissionItem, ...]) -> None:
        """A new plan: start at its item flagged `current` (else 0), counters reset."""
        self.items = items
        flagged = [i for i, it in enumerate(items) if it.current]
        self.current = flagged[0] if flagged else 0
        self._restart()

    def set_current(self, seq: int, reset_jumps: bool = False) -> bool:
        if not 0 <= seq < len(self.items):
            return False
        self.current = seq
        if reset_jumps:
            self._jumps.clear()
        self.complete = False
        self._phase = None
        return True

    def _restart(self) -> None:
        self._jumps.clear()
        self.complete = False
        self.speed_mps = None
        self._phase = None
        self._reached_seq = None

    def pause(self) -> None:
        """Leaving AUTO.MISSION: the current item is entered again on resume."""
        self._phase = None
        cancel = getattr(self.core, "cancel", None)  # (mission legs in front of the core: none flown now)
        if cancel is not None:
            cancel()

    def mission_state(self, in_mission_mode: bool) -> int:
        if not self.items:
            return R.MISSION_STATE_NO_MISSION
        if self.complete:
            return R.MISSION_STATE_COMPLETE
        if in_mission_mode:
            return R.MISSION_STATE_ACTIVE
        return R.MISSION_STATE_PAUSED if self._reached_seq is not None or self.current else R.MISSION_STATE_NOT_STARTED

    def current_message(self, in_mission_mode: bool):
        seq = min(self.current, max(len(self.items) - 1, 0))
        return R.MAVLink_mission_current_message(seq, len(self.items), self.mission_state(in_mission_mode),
                                                 int(in_mission_mode))

    # ----------------------------------------------------------------- geometry
    def target_ned(self, item: MissionItem, state: RigidBodyState, home_ned: np.ndarray) -> np.ndarray:
        here = item.command in HERE_OK and item.x == 0 and item.y == 0
        if item.frame in (R.MAV_FRAME_LOCAL_NED, R.MAV_FRAME_LOCAL_OFFSET_NED):
            p = np.array([item.x / LOCAL_SCALE, item.y / LOCAL_SCALE, item.z])
            if item.frame == R.MAV_FRAME_LOCAL_OFFSET_NED:
                p = p + home_ned
        else:
            amsl = item.z + (self.origin.amsl_m - float(home_ned[2]) if item.frame in GLOBAL_REL else 0.0)
            p = self.origin.to_ned(item.x * 1e-7, item.y * 1e-7, amsl)
        if here:
            p[0], p[1] = state.position_ned_m[0], state.position_ned_m[1]
        return p

    # ----------------------------------------------------------------- execution
    def step(self, t_s: float, state: RigidBodyState, home_ned: np.ndarray, event: str | None,
             in_mission_mode: bool = True) -> RunnerOutput:
        self._out = RunnerOutput([], [])
        if self.items and not self.complete:
            for _ in range(MAX_ITEMS_PER_STEP):
                home = home_ned if self._out.new_home_ned is None else self._out.new_home_ned  # DO_SET_HOME
                if self.complete or not self._advance_item(t_s, state, home, event):
                    break
                event = None  # an event belongs to the item that was current when it happened
        key = (self.current, self.mission_state(in_mission_mode))
        if key != self._announced:
            self._announced = key
            self._out.messages.append(self.current_message(in_mission_mode))
        return self._out

    def _advance_item(self, t_s: float, state: RigidBodyState, home: np.ndarray, event: str | None) -> bool:
        """Run the current item for this step; True if it finished and the next one should start now."""
        item = self.items[self.current]
        cmd = item.command
        core = self.core
        if self._phase is None:
            self._enter(item, t_s, state, home)
        ph = self._phase
        if ph == "jumped":
            self._phase = None
            return True
        if ph == "done":
            return False if self.complete else self._next(state)
        if ph == "climb":  # on the ground at the start: take off first, then the item itself
            if event == "takeoff_done" or (not core.landed and abs(state.position_ned_m[2] - self._climb_z) < 0.3):
                self._phase = None  # now airborne: enter the item for real next step
            return False
        if ph == "approach":
            if np.linalg.norm(state.position_ned_m - self._target) <= self._radius:
                self._reached(item)
                if cmd == R.MAV_CMD_NAV_LOITER_UNLIM:
                    self._phase = "forever"
                    return False
                self._wait_until = t_s + self._hold_s
                self._phase = "hold"
            return False
        if ph == "hold":
            if t_s >= self._wait_until:
                return self._next(state)
            return False
        if ph == "takeoff":
            if event == "takeoff_done" or abs(state.position_ned_m[2] - self._target[2]) <= self._radius:
                self._reached(item)
                return self._next(state)
            return False
        if ph == "to_land":
            if np.linalg.norm(state.position_ned_m[:2] - self._target[:2]) <= self._radius:
                core.land(state)
                self._phase = "landing"
            return False
        if ph in ("landing", "rtl"):
            if event == "landed":
                self._reached(item)
                self.complete = True
                self._out.texts.append("Mission finished: landed")
            return False
        if ph == "delay":
            if t_s >= self._wait_until:
                self._reached(item)
                return self._next(state)
            return False
        return False  # "forever": NAV_LOITER_UNLIM until the mode or the current item changes

    def _enter(self, item: MissionItem, t_s: float, state: RigidBodyState, home: np.ndarray) -> None:
        cmd = item.command
        core = self.core
        self._radius = DEFAULT_ACCEPTANCE_M
        positional = cmd in (R.MAV_CMD_NAV_WAYPOINT, R.MAV_CMD_NAV_LOITER_TIME, R.MAV_CMD_NAV_LOITER_UNLIM,
                             R.MAV_CMD_NAV_TAKEOFF, R.MAV_CMD_NAV_LAND)
        if positional:
            self._target = self.target_ned(item, state, home)
        if positional and cmd != R.MAV_CMD_NAV_LAND and core.landed:
            # PX4: a mission started on the ground climbs first (at least MIS_TAKEOFF_ALT)
            self._climb_z = float(self._target[2])
            if cmd != R.MAV_CMD_NAV_TAKEOFF:
                self._climb_z = min(self._climb_z, float(home[2]) - self.takeoff_alt_m)
            core.takeoff(state, self._climb_z)
            self._phase = "climb"
            return
        yaw = math.radians(item.param4) if math.isfinite(item.param4) else None
        if cmd in (R.MAV_CMD_NAV_WAYPOINT, R.MAV_CMD_NAV_LOITER_TIME, R.MAV_CMD_NAV_LOITER_UNLIM):
            if cmd == R.MAV_CMD_NAV_WAYPOINT and math.isfinite(item.param2) and item.param2 > 0:
                self._radius = item.param2
            self._hold_s = item.param1 if math.isfinite(item.param1) and cmd != R.MAV_CMD_NAV_LOITER_UNLIM else 0.0
            core.goto(state, self._target, yaw)
            self._phase = "approach"
        elif cmd == R.MAV_CMD_NAV_TAKEOFF:
            self._radius = 0.3
            core.goto(state, np.array([state.position_ned_m[0], state.position_ned_m[1], self._target[2]]), yaw)
            self._phase = "takeoff"
        elif cmd in (R.MAV_CMD_NAV_LAND, R.MAV_CMD_NAV_RETURN_TO_LAUNCH) and core.landed:
            self._reached(item)  # already down: nothing to fly, the mission ends here
            self.complete = True
            self._phase = "done"
            self._out.texts.append("Mission finished: on the ground")
        elif cmd == R.MAV_CMD_NAV_LAND:
            self._target[2] = state.position_ned_m[2]  # go over the spot at the current height, then descend
            core.goto(state, self._target, yaw)
            self._phase = "to_land"
        elif cmd == R.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            core.rtl(state, home, self.rtl_alt_m)
            self._phase = "rtl"
        elif cmd == R.MAV_CMD_NAV_DELAY:  # keep the last position setpoint (e.g. the waypoint just reached)
            self._wait_until = t_s + item.param1
            self._phase = "delay"
        else:  # DO_* items: done as soon as entered
            self._phase = "done"
            self._do(item, state, home)

    def _do(self, item: MissionItem, state: RigidBodyState, home: np.ndarray) -> None:
        cmd = item.command
        if cmd == R.MAV_CMD_DO_CHANGE_SPEED:
            if item.param1 in (0, 1) or math.isnan(item.param1):
                self.speed_mps = item.param2 if item.param2 > 0 else None  # (MAVSDK sends one per item: no text)
        elif cmd == R.MAV_CMD_DO_SET_HOME:
            if item.param1 == 1:
                new = np.array(state.position_ned_m, dtype=float)
                new[2] = home[2] if not self.core.landed else new[2]
            else:
                new = self.target_ned(item, state, home)
            self._out.new_home_ned = new
            self._out.texts.append("Mission: home set")
        self._reached(item)
        if cmd == R.MAV_CMD_DO_JUMP:
            done = self._jumps.get(item.seq, 0)
            if item.param2 < 0 or done < item.param2:
                self._jumps[item.seq] = done + 1
                self.current = int(item.param1)
                self._phase = "jumped"

    def _reached(self, item: MissionItem) -> None:
        self._reached_seq = item.seq
        self._out.messages.append(R.MAVLink_mission_item_reached_message(item.seq))

    def _next(self, state: RigidBodyState) -> bool:
        self.current += 1
        self._phase = None
        if self.current >= len(self.items):
            self.current = len(self.items) - 1
            self.complete = True
            if not self.core.landed:
                self.core.hold(state)
            self._out.texts.append("Mission finished: holding")
            return False
        return True
