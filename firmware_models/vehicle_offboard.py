"""Offboard setpoints (SET_POSITION_TARGET_*) and the coordinator's rotor commands."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.rotations import quat_to_euler
from mars_link.mavlink.wire import latch_setpoint_of
from firmware_models.vehicle_links import Link, Outgoing, finite as _finite
from firmware_models.unit_controller import Phase
from firmware_models.vehicle_modes import MODE_OFFBOARD

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle

MAX_POSITION_M = 10_000.0
MAX_SPEED_MPS = 20.0


class OffboardService:
    """Offboard setpoints, and the coordinator's rotor commands and step skips on their link. Owns the last
    setpoint and when it came (the offboard watchdog's stamp). The rotor commands go into the vehicle's
    intake and lockstep state. Asks of the vehicle: state, home, mode, the flight core, the intake, the
    geofence service, `_for_me`, `_count`, `_drop`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.setpoint: tuple | None = None  # (kind, vector, yaw, yaw_rate)
        self.setpoint_wall: float | None = None  # wall time of the last setpoint

    # ----------------------------------------------------------------- offboard setpoints
    def on_position_target(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            v._drop("wrong_target")
            return
        if v.state is None:
            v._drop("setpoint_no_state")
            return
        mask = msg.type_mask
        use_pos = not mask & 0x7
        use_vel = not mask & 0x38
        if (mask & 0x7 not in (0, 0x7)) or (mask & 0x38 not in (0, 0x38)) or not (use_pos or use_vel):
            v._drop("setpoint_unsupported")
            return
        yaw = None if mask & 0x400 else msg.yaw
        yaw_rate = 0.0 if mask & 0x800 else msg.yaw_rate
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        cur_yaw = quat_to_euler(v.state.quaternion_wxyz)[2]
        if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
            frame = msg.coordinate_frame
            pos = np.array([msg.x, msg.y, msg.z], dtype=float)
            if frame not in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
                             mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED):
                v._drop("setpoint_unsupported")
                return
            body = frame in (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED)
            if body:  # body-frame vectors turn with the heading (PX4 semantics)
                cy, sy = math.cos(cur_yaw), math.sin(cur_yaw)
                vel = np.array([cy * vel[0] - sy * vel[1], sy * vel[0] + cy * vel[1], vel[2]])
                pos = np.array([cy * pos[0] - sy * pos[1], sy * pos[0] + cy * pos[1], pos[2]])
        else:  # SET_POSITION_TARGET_GLOBAL_INT
            frame = msg.coordinate_frame
            if frame not in (mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
                v._drop("setpoint_unsupported")
                return
            alt = msg.alt
            if frame == mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT and v.home_ned is not None:
                alt = alt + v.origin.amsl_m - float(v.home_ned[2])
            pos = v._global_to_ned(msg.lat_int * 1e-7, msg.lon_int * 1e-7, alt) if use_pos else np.zeros(3)
            body = False
        values = [*(pos if use_pos else ()), *(vel if use_vel else ()), *(() if yaw is None else (yaw,)), yaw_rate]
        if not _finite(*values):
            v._drop("setpoint_non_finite")
            return
        if frame in (mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED):
            pos = pos + v.state.position_ned_m
        if (use_pos and np.abs(pos).max() > MAX_POSITION_M) or (use_vel and np.abs(vel).max() > MAX_SPEED_MPS) or abs(
            yaw_rate
        ) > 10.0 or (yaw is not None and abs(yaw) > 10.0):
            v._drop("setpoint_out_of_range")
            return
        if use_pos and v.geofence_service.setpoint_outside(pos):
            return
        if use_pos:
            self.setpoint = ("position", pos, yaw, 0.0)
        else:
            self.setpoint = ("velocity", vel, yaw, yaw_rate)
        self.setpoint_wall = v.wall_s
        v._count("setpoints")
        if v.mode == MODE_OFFBOARD and v.source == "own":
            self.apply_setpoint()

    def apply_setpoint(self) -> None:
        v = self.v
        if self.setpoint is None or v.state is None or not v.armed:
            return
        kind, vec, yaw, yaw_rate = self.setpoint
        if kind == "attitude" or (v.autopilot.phase == Phase.IDLE and not v.manual_service.setpoint_lifts(kind, vec)):
            return  # (the control step flies an attitude target; a landed vehicle stays down)
        if kind == "position":
            v.autopilot.goto(v.state, vec, yaw)
        else:
            v.autopilot.velocity(v.state, vec, yaw, yaw_rate)

    # ----------------------------------------------------------------- rotor commands
    def on_step_skip(self, msg, lk: Link, out: list[Outgoing]) -> None:
        """SYSTEM_TIME from the coordinator on its link: it sends no rotor command for the step of that time
        (`time_unix_usec`), so a unit waiting for one runs that step with what it holds, before or after its
        sensors arrive, and keeps waiting for the coordinator's next steps (the conformance harness's silent
        steps; a coordinator that leaves a unit alone). Elsewhere SYSTEM_TIME means nothing to the unit."""
        v = self.v
        if not lk.policy.rotor_commands or msg.get_srcSystem() != v.intake.params.coordinator_sysid:
            v._count(f"ignored.{msg.get_type()}")
            return
        v._count("step_skips")
        v.hil_service.step_skipped_usec = int(msg.time_unix_usec)  # (handle() answers a pending step of that time)

    def on_rotor_command(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not lk.policy.rotor_commands:
            v._drop("rotor_command_wrong_link")
            return
        if v.intake.offer(msg, v.sim_s):
            v._count("rotor_commands")
            v.hil_service.last_rotor_usec = int(msg.time_usec)
            latch = latch_setpoint_of(msg.controls[4])
            if latch is None:
                v._drop("latch_setpoint_invalid")  # (the rotors are taken; the latches keep their setpoint)
            else:
                v.latch_setpoint = latch
            if v.config.hil_await_coordinator:
                v.hil_service.await_coordinator = True  # the coordinator is back: lockstep with it again

