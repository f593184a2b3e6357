"""A lone unit's own flight: guidance phases (takeoff, hold, go-to, velocity, land, return) on top of
mars_link's CascadedController for a 1x1 assembly.

Why a reference shaper: clients send steps (MAVSDK's offboard "1 m north" is a jump of the setpoint;
takeoff is a jump of 2 m). The shaper turns them into references that respect speed and acceleration
limits (PX4's MPC_* limits) and carry a velocity/acceleration feed-forward, so the position loop never
saturates the tilt limit on a step.

The controller is never told about injected rotor faults: a unit learns them only from how it flies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from mars_link.allocation import make_allocator
from mars_link.core.assembly import AssemblyModel, VehicleParams
from mars_link.control.cascaded import CascadedController
from mars_link.core.rotations import quat_to_euler, wrap_pi
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import TrajectoryPoint

TOUCH_HEIGHT_M = 0.08  # a body this close to its ground height with ~no vertical speed is touching
TOUCH_SPEED_MPS = 0.25
LANDED_AFTER_S = 0.4  # touching this long in a landing phase = landed
TAKEOFF_DONE_M = 0.15


@dataclass
class GuidanceLimits:
    xy_speed_mps: float = 2.0
    up_speed_mps: float = 1.5
    down_speed_mps: float = 1.0
    takeoff_speed_mps: float = 1.0
    accel_mps2: float = 2.0
    yaw_rate_radps: float = 1.0
    position_gain_per_s: float = 2.5  # reference speed per metre of remaining distance
    velocity_max_mps: float | None = None  # velocity targets (offboard, sticks); None: xy_speed_mps


class Phase(Enum):
    IDLE = "idle"  # on the ground, motors at zero thrust
    TAKEOFF = "takeoff"
    HOLD = "hold"
    GOTO = "goto"  # position target (offboard position, reposition)
    VELOCITY = "velocity"  # velocity target (offboard velocity)
    LAND = "land"
    RTL_CLIMB = "rtl_climb"
    RTL_RETURN = "rtl_return"


class ReferenceShaper:
    """A reference point moved towards a target position, or at a target velocity, within limits."""

    def __init__(self) -> None:
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.yaw = 0.0

    def reset(self, position: np.ndarray, yaw: float, velocity: np.ndarray | None = None) -> None:
        self.p = np.array(position, dtype=float)
        self.v = np.zeros(3) if velocity is None else np.array(velocity, dtype=float)
        self.yaw = float(yaw)

    def step(
        self,
        dt: float,
        lim: GuidanceLimits,
        target_p: np.ndarray | None = None,
        target_v: np.ndarray | None = None,
        target_yaw: float | None = None,
        yaw_rate: float = 0.0,
    ) -> TrajectoryPoint:
        if target_p is not None:
            e = target_p - self.p
            exy = math.hypot(e[0], e[1])
            vxy = min(lim.xy_speed_mps, lim.position_gain_per_s * exy, math.sqrt(1.6 * lim.accel_mps2 * exy))
            want = np.zeros(3)
            if exy > 1e-9:
                want[0], want[1] = e[0] / exy * vxy, e[1] / exy * vxy
            vz = min(lim.position_gain_per_s * abs(e[2]), math.sqrt(1.6 * lim.accel_mps2 * abs(e[2])))
            want[2] = math.copysign(min(vz, lim.down_speed_mps if e[2] > 0 else lim.up_speed_mps), e[2])
        else:
            want = np.zeros(3) if target_v is None else np.array(target_v, dtype=float)
            sxy = math.hypot(want[0], want[1])
            vmax = lim.xy_speed_mps if lim.velocity_max_mps is None else lim.velocity_max_mps
            if sxy > vmax:
                want[:2] *= vmax / sxy
            want[2] = min(max(want[2], -lim.up_speed_mps), lim.down_speed_mps)
        dv = want - self.v
        n = float(np.linalg.norm(dv))
        if n > lim.accel_mps2 * dt:
            dv *= lim.accel_mps2 * dt / n
        acc = dv / dt if dt > 0 else np.zeros(3)
        self.p = self.p + (self.v + 0.5 * dv) * dt
        self.v = self.v + dv
        if target_yaw is not None:
            dyaw = wrap_pi(target_yaw - self.yaw)
            rate = max(-lim.yaw_rate_radps, min(lim.yaw_rate_radps, dyaw / max(dt, 1e-9)))
        else:
            rate = max(-lim.yaw_rate_radps, min(lim.yaw_rate_radps, yaw_rate))
        self.yaw = wrap_pi(self.yaw + rate * dt)
        return TrajectoryPoint(self.p.copy(), self.v.copy(), acc, np.zeros(3), self.yaw, rate)


class UnitAutopilot:
    """Guidance phases -> reference -> CascadedController (1x1) -> four rotor thrusts (N)."""

    def __init__(self, vehicle: VehicleParams, control_hz: float = 100.0) -> None:
        self.model = AssemblyModel.from_layout(["X"], vehicle)
        full = vehicle.full_scale_thrust_n
        lo = 0.0 if vehicle.rotor_min_thrust_n is None else vehicle.rotor_min_thrust_n
        hi = full if vehicle.rotor_max_thrust_n is None else vehicle.rotor_max_thrust_n
        # a real rotor cannot push down: bound the own controller even for the unbounded paper plant
        self.controller = CascadedController(
            self.model, make_allocator("none", self.model, min_thrust_n=lo, max_thrust_n=hi), control_hz=control_hz
        )
        self.dt_s = 1.0 / control_hz
        self.shaper = ReferenceShaper()
        self.phase = Phase.IDLE
        self.ground_z_m = 0.0
        self.target_p: np.ndarray | None = None
        self.target_v: np.ndarray | None = None
        self.target_yaw: float | None = None
        self.yaw_rate = 0.0
        self.rtl_z_m = 0.0
        self.home_xy = np.zeros(2)
        self.landed = True
        self._touch_since: float | None = None
        self.reference: TrajectoryPoint | None = None
        self.zero = np.zeros(4)

    # ----------------------------------------------------------------- phase changes
    def _start_from(self, state: RigidBodyState) -> None:
        """Continue smoothly from where the body is (after arming, after a coordinator hand-back)."""
        if self.phase in (Phase.IDLE,) or self.reference is None:
            self.controller.reset()
            self.shaper.reset(state.position_ned_m, quat_to_euler(state.quaternion_wxyz)[2], state.velocity_ned_mps)

    def handover(self, state: RigidBodyState) -> None:
        """Take over from another source of motor commands (e.g. the coordinator) at the current state."""
        self.controller.reset()
        self.shaper.reset(state.position_ned_m, quat_to_euler(state.quaternion_wxyz)[2], state.velocity_ned_mps)
        self.reference = None

    def idle(self, ground_z_m: float | None = None) -> None:
        self.phase = Phase.IDLE
        self.landed = True
        self.reference = None
        if ground_z_m is not None:
            self.ground_z_m = ground_z_m

    def takeoff(self, state: RigidBodyState, target_z_m: float) -> None:
        self._start_from(state)
        self.phase = Phase.TAKEOFF
        self.target_p = np.array([state.position_ned_m[0], state.position_ned_m[1], target_z_m])
        self.target_yaw = None
        self.yaw_rate = 0.0
        self.landed = False

    def hold(self, state: RigidBodyState) -> None:
        """Stop where the reference is (braking within the acceleration limit)."""
        self._start_from(state)
        if self.phase == Phase.IDLE or self.landed:
            return  # holding on the ground = staying idle
        stop = self.shaper.p + self.shaper.v * np.abs(self.shaper.v) / (2 * GuidanceLimits().accel_mps2)
        self.phase = Phase.HOLD
        self.target_p = stop
        self.target_yaw = None
        self.yaw_rate = 0.0

    def goto(self, state: RigidBodyState, position: np.ndarray, yaw: float | None) -> None:
        self._start_from(state)
        self.phase = Phase.GOTO
        self.target_p = np.array(position, dtype=float)
        self.target_yaw = yaw
        self.yaw_rate = 0.0
        self.landed = False

    def velocity(self, state: RigidBodyState, velocity: np.ndarray, yaw: float | None, yaw_rate: float) -> None:
        self._start_from(state)
        self.phase = Phase.VELOCITY
        self.target_v = np.array(velocity, dtype=float)
        self.target_yaw = yaw
        self.yaw_rate = yaw_rate
        self.landed = False

    def land(self, state: RigidBodyState) -> None:
        if self.phase in (Phase.IDLE,) and self.landed:
            return
        self._start_from(state)
        self.phase = Phase.LAND
        self.target_yaw = None
        self.yaw_rate = 0.0
        self._touch_since = None

    def rtl(self, state: RigidBodyState, home_ned: np.ndarray, return_height_m: float) -> None:
        if self.landed:
            return
        self._start_from(state)
        self.home_xy = np.array(home_ned[:2], dtype=float)
        self.rtl_z_m = min(state.position_ned_m[2], self.ground_z_m - return_height_m)
        self.phase = Phase.RTL_CLIMB
        self.target_yaw = None
        self.yaw_rate = 0.0

    # ----------------------------------------------------------------- control step
    def touching(self, state: RigidBodyState) -> bool:
        return state.on_ground or (
            state.position_ned_m[2] > self.ground_z_m - TOUCH_HEIGHT_M
            and abs(state.velocity_ned_mps[2]) < TOUCH_SPEED_MPS
        )

    def may_arm(self, state: RigidBodyState) -> bool:
        """On its ground, as far as arming goes: within TOUCH_HEIGHT_M of it, whatever the vertical speed. A
        unit's state message (HIL_STATE_QUATERNION) carries no contact flag, and a body that settles on its
        gear when the world starts (at 200 Hz physics, up to 0.56 m/s at the outer units of a 3x2) is on the
        ground, not in the air."""
        return state.on_ground or state.position_ned_m[2] > self.ground_z_m - TOUCH_HEIGHT_M

    def update(self, t_s: float, state: RigidBodyState, lim: GuidanceLimits, land_speed_mps: float) -> tuple[np.ndarray, str | None]:
        """Rotor thrusts for this control step, and an event name when a phase finished
        ("takeoff_done", "landed", "rtl_home")."""
        ref, event = self.guide(t_s, state, lim, land_speed_mps)
        if ref is None:
            return self.zero, event
        return self.controller.update(t_s, state, ref).rotor_thrusts_n, event

    def guide(self, t_s: float, state: RigidBodyState, lim: GuidanceLimits, land_speed_mps: float
              ) -> tuple[TrajectoryPoint | None, str | None]:
        """The guidance half of `update`: this step's reference (None: idle on the ground) and event.
        Apart so a reference can be flown ahead of time (mars_link.planning.mission_trajectory)."""
        event = None
        ph = self.phase
        if ph == Phase.IDLE:
            return None, None
        dt = self.dt_s
        s = self.shaper
        if ph in (Phase.TAKEOFF, Phase.HOLD, Phase.GOTO):
            if ph == Phase.TAKEOFF:
                lim = GuidanceLimits(**{**lim.__dict__, "up_speed_mps": min(lim.up_speed_mps, lim.takeoff_speed_mps)})
            ref = s.step(dt, lim, target_p=self.target_p, target_yaw=self.target_yaw)
            if ph == Phase.TAKEOFF and abs(state.position_ned_m[2] - self.target_p[2]) < TAKEOFF_DONE_M and abs(
                ref.position_ned_m[2] - self.target_p[2]
            ) < 0.02:
                self.phase, event = Phase.HOLD, "takeoff_done"
        elif ph == Phase.VELOCITY:
            ref = s.step(dt, lim, target_v=self.target_v, target_yaw=self.target_yaw, yaw_rate=self.yaw_rate)
        elif ph == Phase.RTL_CLIMB:
            target = np.array([s.p[0], s.p[1], self.rtl_z_m])
            ref = s.step(dt, lim, target_p=target)
            if abs(state.position_ned_m[2] - self.rtl_z_m) < 0.3 and abs(s.p[2] - self.rtl_z_m) < 0.02:
                self.phase = Phase.RTL_RETURN
        elif ph == Phase.RTL_RETURN:
            target = np.array([self.home_xy[0], self.home_xy[1], self.rtl_z_m])
            ref = s.step(dt, lim, target_p=target)
            if np.linalg.norm(state.position_ned_m[:2] - self.home_xy) < 0.3 and np.linalg.norm(s.p[:2] - self.home_xy) < 0.02:
                self.phase, event = Phase.LAND, "rtl_home"
                self._touch_since = None
        else:  # LAND: descend at the landing speed until touching for a while
            down = GuidanceLimits(**{**lim.__dict__, "down_speed_mps": land_speed_mps})
            ref = s.step(dt, down, target_v=np.array([0.0, 0.0, land_speed_mps]))
            if self.touching(state):
                if self._touch_since is None:
                    self._touch_since = t_s
                elif t_s - self._touch_since >= LANDED_AFTER_S:
                    self.idle()
                    return None, "landed"
            else:
                self._touch_since = None
        self.reference = ref
        return ref, event
