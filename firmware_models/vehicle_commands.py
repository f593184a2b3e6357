"""COMMAND_LONG / COMMAND_INT of the unit firmware: arming, modes, takeoff, land, RTL, goto, failure injection.

Every refused command (COMMAND_ACK DENIED, TEMPORARILY_REJECTED, UNSUPPORTED, FAILED) is followed by one
STATUSTEXT saying why, so a ground station's user is not left with a bare "denied". A handler states its
reason with `refuse(result, why)`; `on_command` turns it into the text, in one place for every command.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.control_policy import FORCE_DISARM_MAGIC
from firmware_models.unit_controller import Phase
from mars_link.core.state import RigidBodyState
from firmware_models.vehicle_links import Link, Outgoing, finite as _finite
from firmware_models.vehicle_modes import (
    MODE_FOLLOW,
    MODE_HOLD,
    MODE_LAND,
    MODE_MISSION,
    MODE_OFFBOARD,
    MODE_POSCTL,
    MODE_RTL,
    MODE_TAKEOFF,
)
from firmware_models.sensor_failures import TYPE_NAMES, UNIT_SENSORS
from firmware_models.vehicle_streams import DEFAULT_STREAM_HZ
from firmware_models.vehicle_offboard import MAX_POSITION_M, MAX_SPEED_MPS

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle

FAILURE_TYPE_ETA = {0: 1.0, 1: 0.0, 5: 0.5}  # FAILURE_TYPE OK / OFF / SLOW (degraded) -> rotor efficiency
FAILURE_UNIT_SYSTEM_MOTOR = 101
SETPOINT_PROOF_OF_LIFE_S = 0.5  # OFFBOARD needs a setpoint stream faster than 2 Hz
COMMAND_DEDUP_S = 1.5  # MAVSDK resends an unacknowledged command 3 times, 0.5 s apart
#: commands whose identical resend within COMMAND_DEDUP_S is answered from the cache, not re-run
ACTION_COMMANDS = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_DO_REPOSITION,
    mavlink.MAV_CMD_INJECT_FAILURE, mavlink.MAV_CMD_MISSION_START, mavlink.MAV_CMD_DO_SET_MISSION_CURRENT,
    mavlink.MAV_CMD_DO_ORBIT,
}


#: how a refused command's STATUSTEXT names it (others: their MAV_CMD name)
COMMAND_WORDS = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: "Arming", mavlink.MAV_CMD_NAV_TAKEOFF: "Takeoff",
    mavlink.MAV_CMD_NAV_LAND: "Land", mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: "Return",
    mavlink.MAV_CMD_DO_SET_MODE: "Mode change", mavlink.MAV_CMD_DO_REPOSITION: "Goto",
    mavlink.MAV_CMD_DO_ORBIT: "Orbit", mavlink.MAV_CMD_DO_CHANGE_SPEED: "Speed change",
    mavlink.MAV_CMD_MISSION_START: "Mission start", mavlink.MAV_CMD_DO_SET_MISSION_CURRENT: "Mission item",
    mavlink.MAV_CMD_INJECT_FAILURE: "Failure injection", mavlink.MAV_CMD_REQUEST_MESSAGE: "Message request",
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: "Message interval", mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: "Message interval",
    mavlink.MAV_CMD_GET_HOME_POSITION: "Home position",
}
#: the reason when a handler gave none
RESULT_WORDS = {mavlink.MAV_RESULT_DENIED: "denied", mavlink.MAV_RESULT_TEMPORARILY_REJECTED: "not now, try again",
                mavlink.MAV_RESULT_UNSUPPORTED: "not supported", mavlink.MAV_RESULT_FAILED: "failed"}
#: requests for information: their refusal is told at INFO, not as a warning (clients probe them at connect)
QUERY_COMMANDS = {
    mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
    mavlink.MAV_CMD_GET_HOME_POSITION, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL,
    mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION,
}
REFUSAL_REPEAT_S = 1.0  # the same refusal text again within a second (a client's retries) is not repeated


def command_name(cmd: int) -> str:
    """A command's name for people: our word for it, else its MAV_CMD name, else its number."""
    if cmd in COMMAND_WORDS:
        return COMMAND_WORDS[cmd]
    entry = mavlink.enums["MAV_CMD"].get(cmd)
    return entry.name.removeprefix("MAV_CMD_") if entry is not None else f"Command {cmd}"


def refusal_text(cmd: int, result: int, why: str | None) -> str:
    """The STATUSTEXT that follows a refused command: what was refused and why."""
    return f"{command_name(cmd)} refused: {why or RESULT_WORDS.get(result, f'result {result}')}"


class CommandService:
    """COMMAND_LONG/INT and SET_MODE, and the mode machine they drive (arm, disarm, takeoff, modes, hand
    back from the coordinator), which the other services and the watchdogs use too. Owns what the command
    protocol remembers: each sender's last action (identical resends answered from it), the refusal texts
    told lately, the reason of the refusal being made, and the speed DO_CHANGE_SPEED set. The flight state
    it changes (armed, mode, source, home) is the vehicle's. Asks of the vehicle: that state, the flight
    core, `params`, the intake, the other services a command reaches, `_for_me`, `_reply`, `_text`,
    `_count`, `_drop`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.last_cmd: dict[tuple, tuple] = {}  # sender -> (command key, wall time, result) of its last action
        self.refusals_told: dict[str, float] = {}  # refusal STATUSTEXT -> wall time told
        self.refusal_why: str | None = None  # set by refuse while a command runs
        self.speed_override_mps: float | None = None  # MAV_CMD_DO_CHANGE_SPEED (else MPC_XY_CRUISE)

    def refuse(self, result: int, why: str) -> int:
        """A command handler's refusal with its reason (told once by _on_command as a STATUSTEXT)."""
        if self.refusal_why is None:
            self.refusal_why = why
        return result

    def tell_refusal(self, cmd: int, result: int, why: str | None) -> None:
        """The one place a refused command becomes a STATUSTEXT (a client's identical retry within
        REFUSAL_REPEAT_S is not told twice)."""
        v = self.v
        text = refusal_text(cmd, result, why)
        said = self.refusals_told
        if v.wall_s - said.get(text, -1e9) < REFUSAL_REPEAT_S:
            return
        said[text] = v.wall_s
        if len(said) > 64:
            said.pop(next(iter(said)))
        v._count("command_refusal_told")
        if cmd in QUERY_COMMANDS:  # a client's protocol probes: told, but not a flight event
            v._pending_text.append((mavlink.MAV_SEVERITY_INFO, text))
        else:
            v._text(text, mavlink.MAV_SEVERITY_WARNING)

    def on_command(self, msg, lk: Link, out: list[Outgoing]) -> None:
        if not self.v._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            self.v._drop("wrong_target")
            return
        cmd = msg.command
        is_int = msg.get_type() == "COMMAND_INT"
        if is_int:
            p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z]
        else:
            p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        src = (lk.name, msg.get_srcSystem(), msg.get_srcComponent())
        key = (cmd, is_int, tuple("nan" if isinstance(v, float) and v != v else v for v in p))
        if cmd in ACTION_COMMANDS:
            last = self.last_cmd.get(src)
            if last is not None and last[0] == key and self.v.wall_s - last[1] <= COMMAND_DEDUP_S:
                self.v._count("command_duplicate")
                self._ack(lk, msg, cmd, last[2], out)
                return
        self.refusal_why = None
        result, followups = self._execute(cmd, p, is_int, msg)
        if result in RESULT_WORDS:
            self.tell_refusal(cmd, result, self.refusal_why)
        self.refusal_why = None
        if cmd in ACTION_COMMANDS:  # only a success is replayed: a refused command may succeed now
            accepted = result == mavlink.MAV_RESULT_ACCEPTED
            self.last_cmd[src] = (key, self.v.wall_s, result) if accepted else (None, 0.0, 0)
            if len(self.last_cmd) > 64:
                self.last_cmd.pop(next(iter(self.last_cmd)))
        self._ack(lk, msg, cmd, result, out)
        for m in followups:
            self.v._reply(lk, m, out)

    def _ack(self, lk: Link, msg, cmd: int, result: int, out: list[Outgoing]) -> None:
        v = self.v
        v._count(f"ack.{result}")
        v._reply(lk, mavlink.MAVLink_command_ack_message(
            cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()), out)

    def _change_speed(self, speed_type: float, speed_mps: float) -> int:
        """MAV_CMD_DO_CHANGE_SPEED (MAVSDK's action.set_current_speed): the horizontal speed of position
        targets (goto, return, missions) from now on, within MPC_XY_VEL_MAX; -2 back to MPC_XY_CRUISE,
        -1 unchanged. Climb/descent speed types (2, 3) are refused: MPC_Z_VEL_MAX_* set those."""
        if not (math.isnan(speed_type) or speed_type in (0, 1)):
            return self.refuse(mavlink.MAV_RESULT_DENIED, "only ground/air speed (MPC_Z_VEL_MAX_* climb)")
        if speed_mps == -2.0:
            self.speed_override_mps = None
        elif not (math.isfinite(speed_mps) and (speed_mps == -1.0 or 0.0 < speed_mps <= MAX_SPEED_MPS)):
            return self.refuse(mavlink.MAV_RESULT_DENIED, f"speed not in 0..{MAX_SPEED_MPS:g} m/s")
        elif speed_mps > 0:
            self.speed_override_mps = float(speed_mps)
        return mavlink.MAV_RESULT_ACCEPTED

    def _execute(self, cmd: int, p: list, is_int: bool, msg) -> tuple[int, list]:
        v = self.v
        R = mavlink
        if cmd == R.MAV_CMD_COMPONENT_ARM_DISARM:
            return self.arm_disarm(p[0], p[1]), []
        if cmd == R.MAV_CMD_NAV_TAKEOFF:
            return self.takeoff(p[6]), []
        if cmd == R.MAV_CMD_NAV_LAND:
            return self.set_mode(MODE_LAND), []
        if cmd == R.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self.set_mode(MODE_RTL), []
        if cmd == R.MAV_CMD_DO_SET_MODE:
            if not _finite(p[0], p[1]) or not (int(p[0]) & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED):
                return self.refuse(R.MAV_RESULT_DENIED, "only PX4 custom modes"), []
            sub = int(p[2]) if math.isfinite(p[2]) else 0
            if not (0 <= p[1] <= 255 and 0 <= sub <= 255):
                return self.refuse(R.MAV_RESULT_DENIED, "no such mode"), []
            return self.set_mode((int(p[1]), sub)), []
        if cmd == R.MAV_CMD_DO_REPOSITION:
            return self._reposition(p, is_int), []
        if cmd == R.MAV_CMD_DO_ORBIT:
            return v.manual_service.do_orbit(p, is_int), []
        if cmd == R.MAV_CMD_DO_CHANGE_SPEED:
            return self._change_speed(p[0], p[1]), []
        if cmd == R.MAV_CMD_MISSION_START:
            first = int(p[0]) if math.isfinite(p[0]) and p[0] >= 0 else None  # PX4: start at p1 if given
            if first is not None and not v.runner.set_current(first, reset_jumps=True):
                return self.refuse(R.MAV_RESULT_DENIED, f"no mission item {first}"), []
            return self.set_mode(MODE_MISSION), []
        if cmd == R.MAV_CMD_DO_SET_MISSION_CURRENT:
            return v.mission_service.set_current(p[0], p[1] == 1), []
        if cmd == R.MAV_CMD_INJECT_FAILURE:
            return self._inject(p), []
        if cmd == R.MAV_CMD_REQUEST_MESSAGE:
            return v.stream_service.request_message(p[0], p[1])
        if cmd == R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            if p[0] != 1:
                return self.refuse(R.MAV_RESULT_DENIED, "param1 must be 1"), []
            return R.MAV_RESULT_ACCEPTED, [v.stream_service.autopilot_version()]
        if cmd == R.MAV_CMD_GET_HOME_POSITION:
            home = v.stream_service.home_position()
            if not home:
                return self.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "no home yet"), []
            return R.MAV_RESULT_ACCEPTED, [home]
        if cmd == R.MAV_CMD_SET_MESSAGE_INTERVAL:
            return v.stream_service.set_interval(p[0], p[1]), []
        if cmd == R.MAV_CMD_GET_MESSAGE_INTERVAL:
            if not math.isfinite(p[0]) or int(p[0]) not in DEFAULT_STREAM_HZ:
                return self.refuse(R.MAV_RESULT_DENIED, f"message {p[0]:g} is not streamed"), []
            iv = v.stream_service.interval_s.get(int(p[0]))
            return R.MAV_RESULT_ACCEPTED, [R.MAVLink_message_interval_message(
                int(p[0]), -1 if iv is None else int(round(iv * 1e6)))]
        return R.MAV_RESULT_UNSUPPORTED, []  # includes REQUEST_PROTOCOL_VERSION (519): MAVLink 2 only
        # (the default reason, "not supported", is the STATUSTEXT)

    def arm_disarm(self, arm: float, force: float) -> int:
        v = self.v
        R = mavlink
        if arm == 1.0:
            if v.armed:
                return R.MAV_RESULT_ACCEPTED
            if v.state is None:
                return self.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "no position estimate yet")
            if not v.autopilot.may_arm(v.state):
                return self.refuse(R.MAV_RESULT_DENIED, "not on the ground")  # never arm in the air
            v.armed = True
            v.home_ned = np.array(v.state.position_ned_m, dtype=float)
            v.autopilot.idle(float(v.state.position_ned_m[2]))
            v._armed_at = v.sim_s
            v._took_off = False
            v._text("Armed")
            return R.MAV_RESULT_ACCEPTED
        if arm == 0.0:
            if not v.armed:
                return R.MAV_RESULT_ACCEPTED
            if not v.landed and force != FORCE_DISARM_MAGIC:
                return self.refuse(R.MAV_RESULT_DENIED, "flying: land first (or force)")
            self.disarm("Disarmed" if force != FORCE_DISARM_MAGIC else "Killed: motors off")
            return R.MAV_RESULT_ACCEPTED
        return self.refuse(R.MAV_RESULT_DENIED, "param1 must be 0 or 1")

    def disarm(self, why: str) -> None:
        v = self.v
        v.armed = False
        v.px4_service.disarmed()  # (the unit's other persona: PX4's interface, vehicle_px4)
        v.source = "own"
        v.autopilot.idle()
        v.motor_commands_n = np.zeros(4)
        if v.mode not in (MODE_HOLD, MODE_POSCTL):
            v.mode = MODE_HOLD
        v._text(why)

    def takeoff(self, altitude_amsl_m: float) -> int:
        v = self.v
        R = mavlink
        if v.state is None:
            return self.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "no position estimate yet")
        if not v.armed:
            return self.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "not armed")
        if v.mode == MODE_TAKEOFF or not v.landed:
            return R.MAV_RESULT_ACCEPTED  # already on its way / flying: nothing to restart
        ground = float(v.home_ned[2])
        lowest = ground - v.params["MIS_TAKEOFF_ALT"]
        target = lowest
        if math.isfinite(altitude_amsl_m):
            # PX4 (navigator/takeoff.cpp): an altitude (AMSL) below home + MIS_TAKEOFF_ALT is raised to it
            # and said; MAVProxy's `takeoff 10` is 10 m AMSL to PX4
            target = -(altitude_amsl_m - v.origin.amsl_m)
            if target > lowest + 0.1:  # (PX4 says nothing for less than 10 cm)
                v._text(f"Using minimum takeoff altitude: {ground - lowest:.2f} m", R.MAV_SEVERITY_CRITICAL)
            target = min(target, lowest)
        why = v.geofence_service.violation(np.array([v.state.position_ned_m[0], v.state.position_ned_m[1], target]))
        if why is not None:
            return self.refuse(R.MAV_RESULT_DENIED, why)
        v.source = "own"
        v.autopilot.takeoff(v.state, target)
        v.mode = MODE_TAKEOFF
        v._took_off = True
        v._text(f"Takeoff to {ground - target:.1f} m")
        return R.MAV_RESULT_ACCEPTED

    def set_mode(self, mode: tuple[int, int]) -> int:
        v = self.v
        R = mavlink
        if mode == v.mode:
            return R.MAV_RESULT_ACCEPTED
        if mode == MODE_MISSION:
            return v.mission_service.enter()
        if mode == MODE_FOLLOW:
            v.runner.pause()
            v.manual_service.orbit = None
            return v.follow_service.enter()
        s = v.state
        v.runner.pause()  # (a no-op unless leaving AUTO.MISSION: it resumes at its current item)
        v.manual_service.orbit = None
        if mode in (MODE_HOLD, MODE_POSCTL):
            if s is not None and v.source == "own":
                v.autopilot.hold(s)
            elif s is not None:
                self.hand_back(s)
                v.autopilot.hold(s)
        elif mode == MODE_LAND:
            if s is None:
                return self.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "no position estimate yet")
            if v.source != "own":
                self.hand_back(s)
            v.autopilot.land(s)
        elif mode == MODE_RTL:
            if s is None or v.home_ned is None:
                return self.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "no home yet (arm first)")
            if v.source != "own":
                self.hand_back(s)
            v.autopilot.rtl(s, v.geofence_service.return_point_ned(), v.params["RTL_RETURN_ALT"])
        elif mode == MODE_TAKEOFF:
            return self.takeoff(math.nan)
        elif mode == MODE_OFFBOARD:
            sp_wall = v.offboard_service.setpoint_wall
            live_sp = sp_wall is not None and v.wall_s - sp_wall <= SETPOINT_PROOF_OF_LIFE_S
            if not (live_sp or v.intake.is_live(v.sim_s)):
                return self.refuse(R.MAV_RESULT_DENIED, "no setpoint stream (send setpoints first)")  # as PX4
            v.mode = mode
            if live_sp:
                v.offboard_service.apply_setpoint()
            v._text("Offboard")
            return R.MAV_RESULT_ACCEPTED
        else:
            return self.refuse(R.MAV_RESULT_UNSUPPORTED, "mode needs RC sticks (manual/stabilized/acro)")
        v.mode = mode
        v._text({MODE_HOLD: "Hold", MODE_POSCTL: "Position", MODE_LAND: "Land", MODE_RTL: "Return"}[mode])
        return R.MAV_RESULT_ACCEPTED

    def hand_back(self, s: RigidBodyState) -> None:
        """The coordinator drove the motors; the own controller takes over from the current state."""
        v = self.v
        v.source = "own"
        v.autopilot.handover(s)
        v.autopilot.landed = v.autopilot.touching(s)
        v.autopilot.phase = Phase.HOLD if not v.autopilot.landed else Phase.IDLE

    def _reposition(self, p: list, is_int: bool) -> int:
        v = self.v
        R = mavlink
        if v.state is None or not v.armed or v.landed:
            return self.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "not flying (take off first)")
        lat = p[4] * 1e-7 if is_int else p[4]
        lon = p[5] * 1e-7 if is_int else p[5]
        if not _finite(lat, lon, p[6]) or not (-90 <= lat <= 90 and -180 <= lon <= 180):
            return self.refuse(R.MAV_RESULT_DENIED, "no valid latitude, longitude and altitude")
        target = v._global_to_ned(lat, lon, p[6])
        if np.linalg.norm(target[:2] - v.state.position_ned_m[:2]) > MAX_POSITION_M:
            return self.refuse(R.MAV_RESULT_DENIED, f"farther than {MAX_POSITION_M:g} m")
        why = v.geofence_service.violation(target)
        if why is not None:
            return self.refuse(R.MAV_RESULT_DENIED, why)
        yaw = math.radians(p[3]) if math.isfinite(p[3]) else None
        if v.source != "own":
            self.hand_back(v.state)
        v.autopilot.goto(v.state, target, yaw)
        v.mode = MODE_HOLD
        return R.MAV_RESULT_ACCEPTED

    def _inject(self, p: list) -> int:
        v = self.v
        R = mavlink
        if int(v.params["SYS_FAILURE_EN"]) != 1:
            return self.refuse(R.MAV_RESULT_DENIED, "SYS_FAILURE_EN is 0")
        if _finite(p[0], p[1], p[2]) and int(p[0]) in UNIT_SENSORS:  # a sensor: its path (sensor_failures)
            kind = TYPE_NAMES.get(int(p[1]))
            instance = int(p[2])
            if kind is None:
                return self.refuse(R.MAV_RESULT_UNSUPPORTED, f"failure type {p[1]:g} not simulated")
            if instance != p[2] or instance < 0:
                return self.refuse(R.MAV_RESULT_DENIED, "no such sensor instance")
            result = v.inject_sensor_failure(UNIT_SENSORS[int(p[0])], kind, instance)
            if result == R.MAV_RESULT_ACCEPTED:
                v._count("failures_injected")
            return result
        if not _finite(p[0], p[1], p[2]) or int(p[0]) != FAILURE_UNIT_SYSTEM_MOTOR:
            return self.refuse(R.MAV_RESULT_UNSUPPORTED, "failure unit not simulated")
        eta = FAILURE_TYPE_ETA.get(int(p[1]))
        if eta is None:
            return self.refuse(R.MAV_RESULT_UNSUPPORTED, "only motor ok/off/slow")
        instance = int(p[2])
        if instance != p[2] or not 0 <= instance <= v.motor_count:
            return self.refuse(R.MAV_RESULT_DENIED, f"no motor {p[2]:g} (1..{v.motor_count}, 0 all)")
        v.inject_failure(instance, eta)
        v._count("failures_injected")
        v._text(f"Failure injected: motor {instance or 'all'} eta {eta:g}", mavlink.MAV_SEVERITY_WARNING)
        return R.MAV_RESULT_ACCEPTED

    def on_set_mode(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, 0, allow_broadcast=False):
            v._drop("wrong_target")
            return
        if not msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            v._drop("set_mode_not_custom")
            return
        self.set_mode(((msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF))

