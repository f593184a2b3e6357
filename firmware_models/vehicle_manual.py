"""Guidance that clients steer step by step: DO_ORBIT, MANUAL_CONTROL in position mode, offboard
SET_ATTITUDE_TARGET, and the land detector that ends any descent to the ground.

Why here and not in the flight core: each is a way of *feeding* the core (UnitAutopilot or the
assembly's core) each control step, through its existing velocity phase and controller, so a lone
unit and an assembly get them alike:
  orbit     a tangential velocity plus a radial and a height correction around the reference point
            (PX4's FlightTaskOrbit idea), yaw to the centre / held / along the tangent; PX4 reports it
            as POSCTL with the ORBIT sub-mode
  manual    sticks (x forward, y right, z throttle 0..1000 with 500 = hold height, r yaw) -> body
            velocity within MPC_VEL_MANUAL / MPC_Z_VEL_MAX_*; centred sticks brake and hold; sticks older
            than MANUAL_STALE_S count as centred
  attitude  quaternion + normalised thrust -> the acceleration that attitude and thrust would give,
            fed to the controller as a reference at the current state (no position error), so the
            controller's attitude loop produces that attitude; body rates alone are integrated into an
            attitude
  landing   after being airborne, touching the ground for LAND_DETECT_S with the reference not climbing
            = landed (then COM_DISARM_LAND disarms), in every mode; setpoints that do not climb do not
            wake a landed vehicle
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.unit_controller import Phase
from firmware_models.vehicle_links import Link, Outgoing, finite
from firmware_models.vehicle_modes import MODE_FOLLOW, MODE_HOLD, MODE_MISSION, MODE_OFFBOARD, MODE_ORBIT, MODE_POSCTL

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle
from mars_link.core.assembly import GRAVITY_MPS2
from mars_link.core.rotations import quat_multiply, quat_to_euler, quat_to_rotmat
from mars_link.models.trajectories import TrajectoryPoint

R = mavlink
INT32_MAX = 2**31 - 1
ORBIT_MIN_RADIUS_M, ORBIT_MAX_RADIUS_M = 1.0, 1000.0
ORBIT_DEFAULT_SPEED_MPS = 1.0
ORBIT_RADIAL_GAIN_PER_S = 1.0
CENTRIPETAL_MAX_MPS2 = 1.6  # within the reference shaper's 2 m/s^2
MANUAL_STALE_S = 0.5
MANUAL_DEADZONE = 0.1
MANUAL_YAW_RATE_RADPS = 1.0
LAND_DETECT_S = 1.0
ATT_IGNORE_RATES, ATT_IGNORE_THRUST, ATT_IGNORE_ATTITUDE = 0x07, 0x40, 0x80


class ManualService:
    """Orbit, sticks, attitude targets and the land detector. Owns the orbit in progress, the sticks (and
    when they came), the attitude target and the land detector's state. Asks of the vehicle: state, mode,
    `params`, the flight core, the mode machine, the offboard setpoint, the geofence and follow services,
    `_text`, `_count`, `_drop`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.orbit: dict | None = None
        self.sticks: tuple[float, float, float, float] | None = None  # x, y, z, r normalised
        self.sticks_wall = -1e9
        self.sticks_moving = False
        self.attitude_sp: tuple | None = None  # (quaternion, thrust 0..1, body rates, rates only)
        self.airborne_seen = False
        self.touch_since_s: float | None = None

    # ----------------------------------------------------------------- orbit (MAV_CMD_DO_ORBIT)
    def do_orbit(self, p: list, is_int: bool) -> int:
        v = self.v
        s = v.state
        if s is None or not v.armed or v.landed:
            return v.command_service.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "not flying (take off first)")
        radius = p[0]
        if not math.isfinite(radius) or not ORBIT_MIN_RADIUS_M <= abs(radius) <= ORBIT_MAX_RADIUS_M:
            why = f"radius not in {ORBIT_MIN_RADIUS_M:g}..{ORBIT_MAX_RADIUS_M:g} m"
            return v.command_service.refuse(R.MAV_RESULT_DENIED, why)
        speed = ORBIT_DEFAULT_SPEED_MPS if not math.isfinite(p[1]) else abs(p[1])
        direction = 1.0 if radius > 0 else -1.0  # positive: clockwise seen from above
        if math.isfinite(p[1]) and p[1] < 0:
            direction = -direction
        speed = min(speed, v.params["MPC_XY_VEL_MAX"], math.sqrt(CENTRIPETAL_MAX_MPS2 * abs(radius)))
        unset = (p[4] == INT32_MAX or p[5] == INT32_MAX) if is_int else not finite(p[4], p[5])
        if unset or (p[4] == 0 and p[5] == 0):
            center = np.array(s.position_ned_m[:2], dtype=float)
        else:
            lat, lon = (p[4] * 1e-7, p[5] * 1e-7) if is_int else (p[4], p[5])
            if not (-90 <= lat <= 90 and -180 <= lon <= 180):
                return v.command_service.refuse(R.MAV_RESULT_DENIED, "centre: no valid latitude/longitude")
            center = v._global_to_ned(lat, lon, v.origin.amsl_m)[:2]
        z = -(p[6] - v.origin.amsl_m) if math.isfinite(p[6]) else float(s.position_ned_m[2])
        for a in np.linspace(0.0, 2 * math.pi, 24, endpoint=False):  # the whole circle inside the fence
            ring = np.array([center[0] + abs(radius) * math.cos(a), center[1] + abs(radius) * math.sin(a), z])
            why = v.geofence_service.violation(ring)
            if why is not None:
                return v.command_service.refuse(R.MAV_RESULT_DENIED, f"circle {why}")
        orbits = p[3] if math.isfinite(p[3]) and p[3] > 0 else math.inf
        yaw_mode = int(p[2]) if math.isfinite(p[2]) else 0
        if v.source != "own":
            v.command_service.hand_back(s)
        v.runner.pause()
        ref = v.autopilot.shaper.p
        self.orbit = {"center": center, "radius": abs(radius), "speed": speed, "dir": direction, "z": z,
                       "yaw_mode": yaw_mode, "yaw0": quat_to_euler(s.quaternion_wxyz)[2],
                       "angle": math.atan2(ref[1] - center[1], ref[0] - center[0]), "turned": 0.0,
                       "limit": 2 * math.pi * orbits}
        v.mode = MODE_ORBIT
        v._text(f"Orbit: radius {abs(radius):.1f} m at {speed:.1f} m/s")
        return R.MAV_RESULT_ACCEPTED

    def _orbit_step(self) -> None:
        v = self.v
        o = self.orbit
        ap = v.autopilot
        ref = ap.shaper.p
        d = ref[:2] - o["center"]
        r = float(np.hypot(*d))
        r_hat = d / r if r > 1e-6 else np.array([1.0, 0.0])
        t_hat = o["dir"] * np.array([-r_hat[1], r_hat[0]])
        radial = max(-o["speed"] * 2, min(o["speed"] * 2, ORBIT_RADIAL_GAIN_PER_S * (o["radius"] - r)))
        v_xy = o["speed"] * t_hat + radial * r_hat
        v_z = max(-1.0, min(1.0, ORBIT_RADIAL_GAIN_PER_S * (o["z"] - ref[2])))
        angle = math.atan2(d[1], d[0])
        step = (angle - o["angle"] + math.pi) % (2 * math.pi) - math.pi
        o["angle"] = angle
        if abs(o["radius"] - r) < 0.5:
            o["turned"] += abs(step)
        yaw = {0: math.atan2(-d[1], -d[0]), 3: math.atan2(t_hat[1], t_hat[0])}.get(o["yaw_mode"], o["yaw0"])
        if o["turned"] >= o["limit"]:
            self.orbit = None
            ap.hold(v.state)
            v.mode = MODE_HOLD
            v._text("Orbit complete: holding")
            return
        ap.velocity(v.state, np.array([v_xy[0], v_xy[1], v_z]), yaw, 0.0)

    # ----------------------------------------------------------------- MANUAL_CONTROL (position mode)
    def on_manual_control(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if msg.target != v.sysid:
            v._drop("wrong_target")
            return
        x, y, z, r = msg.x / 1000.0, msg.y / 1000.0, msg.z / 1000.0, msg.r / 1000.0
        if not (abs(x) <= 1 and abs(y) <= 1 and -1 <= z <= 1 and abs(r) <= 1):
            v._drop("manual_control_out_of_range")
            return
        self.sticks = (x, y, z, r)
        self.sticks_wall = v.wall_s
        v._count("manual_control")

    def _sticks_step(self) -> None:
        s = self.v.state
        sticks = self.sticks if self.v.wall_s - self.sticks_wall <= MANUAL_STALE_S else None
        x, y, z, r = sticks if sticks is not None else (0.0, 0.0, 0.5, 0.0)
        dz = lambda v: 0.0 if abs(v) < MANUAL_DEADZONE else v  # noqa: E731
        x, y, r = dz(x), dz(y), dz(r)
        climb = dz(2.0 * (z - 0.5))  # +1 full up
        if x == y == r == climb == 0.0:
            if self.sticks_moving:
                self.sticks_moving = False
                self.v.autopilot.hold(s)
            return
        p = self.v.params
        if self.v.autopilot.phase == Phase.IDLE and climb <= 0.0:
            return  # on the ground: only throttle up takes off
        yaw = quat_to_euler(s.quaternion_wxyz)[2]
        full = min(p["MPC_VEL_MANUAL"], p["MPC_XY_VEL_MAX"])
        fwd, right = x * full, y * full
        v = np.array([math.cos(yaw) * fwd - math.sin(yaw) * right, math.sin(yaw) * fwd + math.cos(yaw) * right,
                      -climb * (p["MPC_Z_VEL_MAX_UP"] if climb > 0 else p["MPC_Z_VEL_MAX_DN"])])
        self.sticks_moving = True
        self.v._took_off = True
        self.v.autopilot.velocity(s, v, None, r * MANUAL_YAW_RATE_RADPS)

    # ----------------------------------------------------------------- SET_ATTITUDE_TARGET (offboard)
    def on_attitude_target(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            v._drop("wrong_target")
            return
        mask = msg.type_mask
        q = np.array(msg.q, dtype=float)
        rates = np.array([msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate], dtype=float)
        thrust = msg.thrust
        if mask & ATT_IGNORE_THRUST or not finite(thrust) or not 0.0 <= thrust <= 1.0:
            v._drop("attitude_target_invalid")
            return
        rates_only = bool(mask & ATT_IGNORE_ATTITUDE)
        if rates_only:
            rates = np.where([mask & 1, mask & 2, mask & 4], 0.0, rates)
            if not finite(*rates) or np.abs(rates).max() > 10.0:
                v._drop("attitude_target_invalid")
                return
        elif not finite(*q) or not 0.5 < np.linalg.norm(q) < 1.5:
            v._drop("attitude_target_invalid")
            return
        prev = self.attitude_sp
        if rates_only:  # integrate from the previous target (or the current attitude)
            q = prev[0] if prev is not None else (v.state.quaternion_wxyz if v.state is not None else None)
            if q is None:
                v._drop("setpoint_no_state")
                return
        self.attitude_sp = (q / np.linalg.norm(q), float(thrust), rates, rates_only)
        v.offboard_service.setpoint = ("attitude", None, None, 0.0)
        v.offboard_service.setpoint_wall = v.wall_s
        v._count("setpoints")

    def _attitude_thrusts(self, t: float) -> np.ndarray:
        """One control step towards the offboard attitude and thrust target."""
        v = self.v
        q, thrust, rates, rates_only = self.attitude_sp
        if rates_only:  # q <- q * exp(rates dt / 2)
            dq = np.array([1.0, *(0.5 * rates * v.control_dt_s)])
            q = quat_multiply(q, dq / np.linalg.norm(dq))
            self.attitude_sp = (q, thrust, rates, True)
        s = v.state
        ap = v.autopilot
        model = ap.model
        max_total_n = model.n_rotors * v.full_scale_n
        specific = -quat_to_rotmat(q)[:, 2] * thrust * max_total_n / model.mass_kg
        acc = specific + np.array([0.0, 0.0, GRAVITY_MPS2])
        # the heading turns at most MANUAL_YAW_RATE_RADPS (a 180 deg step is no attitude error for the
        # geometric controller); the tilt comes from the acceleration, whatever the heading
        step = (quat_to_euler(q)[2] - ap.shaper.yaw + math.pi) % (2 * math.pi) - math.pi
        limit = MANUAL_YAW_RATE_RADPS * v.control_dt_s
        yaw = ap.shaper.yaw + max(-limit, min(limit, step))
        ap.shaper.reset(s.position_ned_m, yaw, s.velocity_ned_mps)  # leaving: continue from here
        ap.phase, ap.landed = Phase.VELOCITY, False
        ap.target_v, ap.target_yaw, ap.yaw_rate = np.array(s.velocity_ned_mps, dtype=float), None, 0.0
        ref = TrajectoryPoint(np.array(s.position_ned_m, dtype=float), np.array(s.velocity_ned_mps, dtype=float),
                              acc, np.zeros(3), yaw, float(rates[2]) if rates_only else 0.0)
        ap.reference = ref
        v._took_off = True
        return np.asarray(ap.controller.update(t, s, ref).rotor_thrusts_n, dtype=float)

    # ----------------------------------------------------------------- the control step's hooks
    def guidance_step(self, t: float) -> np.ndarray | None:
        """Before the flight core's update: steer it (orbit, sticks), or fly the attitude target
        (returns the rotor thrusts then)."""
        v = self.v
        if v.mode == MODE_MISSION and v.legs is not None:
            return v.legs.step(t, v.state)
        if v.mode == MODE_ORBIT and self.orbit is not None:
            self._orbit_step()
        elif v.mode == MODE_POSCTL:
            self._sticks_step()
        elif v.mode == MODE_FOLLOW:
            v.follow_service.step()
        elif v.mode == MODE_OFFBOARD and (sp := v.offboard_service.setpoint) is not None and sp[0] == "attitude":
            ap = v.autopilot
            hover = ap.model.mass_kg * GRAVITY_MPS2 / (ap.model.n_rotors * v.full_scale_n)
            if ap.phase == Phase.IDLE and self.attitude_sp[1] <= hover:
                return ap.zero  # landed (or not yet off): thrust below hover does not lift it
            return self._attitude_thrusts(t)
        return None

    def land_detect(self, t: float) -> str | None:
        """Landed after a descent to the ground in any mode; the core's own LAND phase reports itself."""
        v = self.v
        ap, s = v.autopilot, v.state
        if ap.phase in (Phase.IDLE, Phase.LAND, Phase.TAKEOFF) or v.source != "own":
            self.touch_since_s = None
            return None
        if not ap.touching(s):
            self.airborne_seen = True
            self.touch_since_s = None
            return None
        climbing = ap.reference is not None and ap.reference.velocity_ned_mps[2] < -0.05
        if not self.airborne_seen or climbing:
            self.touch_since_s = None
            return None
        if self.touch_since_s is None:
            self.touch_since_s = t
            return None
        if t - self.touch_since_s < LAND_DETECT_S:
            return None
        self.touch_since_s = None
        self.airborne_seen = False
        self.orbit = None
        ap.idle()
        return "landed"

    def setpoint_lifts(self, kind: str, vec) -> bool:
        """Whether an offboard setpoint would take a landed vehicle off (climb or a target above ground)."""
        if kind == "velocity":
            return vec[2] < -0.1
        if kind == "position":
            return vec[2] < self.v.autopilot.ground_z_m - 0.3
        return True
