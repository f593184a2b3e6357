"""Telemetry of the unit firmware: heartbeat, default streams, message requests and intervals.

A mixin of `firmware_models.vehicle.Vehicle`: it uses the Vehicle's state and plumbing (_reply, _text, ...).
"""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.unit_controller import Phase
from mars_link.core.assembly import GRAVITY_MPS2
from mars_link.core.rotations import quat_to_euler, quat_to_rotmat
from firmware_models.vehicle_links import finite as _finite
from firmware_models.vehicle_modes import MAIN_AUTO, MAIN_OFFBOARD, MODE_MISSION
from mars_link.core.messages import BatterySample, wire_battery
from mars_link.runtime.pacing import REANCHOR_S
from mars_link.mavlink.wire import battery_status

MIN_STREAM_INTERVAL_S = 0.001  # 1 kHz: the protocol's floor; the vehicle's own is one message per tick
#: (its control rate: streams go out when the runner ticks it, once per control step; `stream_cap_hz`)
#: msg id -> default rate (Hz, wall clock), specs/mavlink.md §6
DEFAULT_STREAM_HZ: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 2.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 20.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 20.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 20.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 20.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 10.0,
    mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS: 10.0,
    mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
}
#: REQUEST_MESSAGE ids answered with a refusal: PROTOCOL_VERSION, COMPONENT_INFORMATION,
#: COMPONENT_METADATA, AVAILABLE_MODES, CURRENT_MODE (not in pymavlink 2.4.50's common dialect)
REFUSED_MESSAGES = {300, 395, 397, 435, 436}
CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
)
SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | mavlink.MAV_SYS_STATUS_GEOFENCE | mavlink.MAV_SYS_STATUS_AHRS
    | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY | mavlink.MAV_SYS_STATUS_PREARM_CHECK
    | mavlink.MAV_SYS_STATUS_SENSOR_PROPULSION
)

#: SYS_STATUS sensor bit of each failure-injectable sensor
SENSOR_BITS = {
    "gps": mavlink.MAV_SYS_STATUS_SENSOR_GPS, "accel": mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL,
    "gyro": mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO, "mag": mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG,
    "baro": mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE,
}

#: a stream sent on a tick this late (wall clock) stays on its grid: the late tick and the runner's catch-up
#: ticks after it send what fell due, one message per tick, so a starved moment loses no sample. Later than
#: this the runner re-anchors its pacing (mars_link.runtime.pacing), and the stream starts again from now.
STREAM_CATCH_UP_S = REANCHOR_S


def next_stream_due(due_s: float, interval_s: float, now_s: float) -> float:
    """When a stream that fell due at `due_s` and went out at `now_s` is due again (wall clock)."""
    if now_s - due_s < STREAM_CATCH_UP_S:
        return due_s + interval_s
    return now_s + 0.5 * interval_s


class StreamsMixin:
    def _unhealthy_sensors(self) -> int:
        """SYS_STATUS bits to clear from onboard_control_sensors_health: the unit's failed sensors."""
        failures = self.sensor_failures
        return sum(bit for name, bit in SENSOR_BITS.items() if not failures.healthy(name))

    def _request_message(self, msgid: float, p2: float) -> tuple[int, list]:
        R = mavlink
        if not math.isfinite(msgid) or msgid != int(msgid):
            return self.command_service.refuse(R.MAV_RESULT_DENIED, "param1 is no message id"), []
        mid = int(msgid)
        if mid == R.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return R.MAV_RESULT_ACCEPTED, [self._autopilot_version()]
        if mid == R.MAVLINK_MSG_ID_HEARTBEAT:
            return R.MAV_RESULT_ACCEPTED, [self._heartbeat()]
        if mid in DEFAULT_STREAM_HZ:
            msg = self._stream_message(mid)
            if msg is None:
                return self.command_service.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, f"no {R.mavlink_map[mid].msgname} yet"), []
            return R.MAV_RESULT_ACCEPTED, [msg]
        # (incl. REFUSED_MESSAGES: PROTOCOL_VERSION, AVAILABLE_MODES, ...)
        name = R.mavlink_map[mid].msgname if mid in R.mavlink_map else f"message {mid}"
        return self.command_service.refuse(R.MAV_RESULT_UNSUPPORTED, f"{name} not sent"), []

    @property
    def stream_cap_hz(self) -> float:
        """The fastest a stream goes: one message per tick, and the runners tick once per control step
        (100 Hz by default; a unit at --control-hz 250 streams HIGHRES_IMU at 250 Hz)."""
        return 1.0 / max(MIN_STREAM_INTERVAL_S, self.control_dt_s)

    def _set_interval(self, msgid: float, interval_us: float) -> int:
        """SET_MESSAGE_INTERVAL: faster than `stream_cap_hz` is accepted and runs at the cap (its
        MESSAGE_INTERVAL then reports the interval in force)."""
        R = mavlink
        if not _finite(msgid, interval_us) or int(msgid) not in DEFAULT_STREAM_HZ:
            return self.command_service.refuse(R.MAV_RESULT_DENIED, "not a streamed message")
        mid = int(msgid)
        if interval_us < 0:
            self.stream_interval_s.pop(mid, None)
        else:
            iv = 1.0 / DEFAULT_STREAM_HZ[mid] if interval_us == 0 else max(1.0 / self.stream_cap_hz, interval_us * 1e-6)
            self.stream_interval_s[mid] = iv
            self._next_stream[mid] = self.wall_s
        return R.MAV_RESULT_ACCEPTED


    def _global_to_ned(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> np.ndarray:
        return self.origin.to_ned(lat_deg, lon_deg, alt_amsl_m)

    def _ned_to_global(self, p: np.ndarray) -> tuple[int, int, int]:
        """(lat degE7, lon degE7, alt AMSL mm)."""
        return self.origin.to_global_int(p)

    def _time_boot_ms(self) -> int:
        return int(self.sim_s * 1000) & 0xFFFFFFFF

    def _heartbeat(self):
        R = mavlink
        base = R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | R.MAV_MODE_FLAG_STABILIZE_ENABLED
        if self.mode[0] in (MAIN_AUTO, MAIN_OFFBOARD):
            base |= R.MAV_MODE_FLAG_GUIDED_ENABLED | (R.MAV_MODE_FLAG_AUTO_ENABLED if self.mode[0] == MAIN_AUTO else 0)
        if self.armed:
            base |= R.MAV_MODE_FLAG_SAFETY_ARMED
        status = R.MAV_STATE_ACTIVE if self.armed else R.MAV_STATE_STANDBY
        return R.MAVLink_heartbeat_message(R.MAV_TYPE_QUADROTOR, R.MAV_AUTOPILOT_PX4, base, self.custom_mode, status, 3)

    def _autopilot_version(self):
        uid = (0x4D415253 << 32) | self.sysid  # "MARS" + unit id
        sw = (0 << 24) | (1 << 16) | (0 << 8) | 255  # mars-link 0.1.0, release
        return mavlink.MAVLink_autopilot_version_message(
            CAPABILITIES, sw, sw, 0, 0, list(b"marslink"), [0] * 8, [0] * 8, 0, 0, uid, [0] * 18)

    def _home_position(self):
        if self.home_ned is None:
            return None
        lat, lon, alt = self._ned_to_global(self.home_ned)
        h = self.home_ned
        return mavlink.MAVLink_home_position_message(
            lat, lon, alt, float(h[0]), float(h[1]), float(h[2]), [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
            int(self.sim_s * 1e6))

    def _landed_state(self) -> int:
        R = mavlink
        ph = self.autopilot.phase
        if self.landed:
            return R.MAV_LANDED_STATE_ON_GROUND
        if self.source == "own" and ph == Phase.TAKEOFF:
            return R.MAV_LANDED_STATE_TAKEOFF
        if self.source == "own" and ph == Phase.LAND:
            return R.MAV_LANDED_STATE_LANDING
        return R.MAV_LANDED_STATE_IN_AIR

    def _battery(self) -> tuple[int, int, int]:
        """(voltage mV, current cA, remaining %) as measured (firmware_models.battery_monitor); clamped to
        the wire fields (uint16 mV, int16 cA, int8 %). Nothing measured (no simulated pack: the papers'
        plants) or not a number -> MAVLink's "not sent" values (UINT16_MAX, -1, -1)."""
        b = self.battery

        def wire(x: float, lo: int, hi: int, unknown: int) -> int:
            return unknown if not math.isfinite(x) else int(min(max(x, lo), hi))

        return (wire(b.voltage_v * 1000, 0, 65534, 65535), wire(b.current_a * 100, 0, 32767, -1),
                wire(round(b.remaining * 100) if math.isfinite(b.remaining) else b.remaining, 0, 100, -1))

    def _stream_message(self, mid: int):
        R = mavlink
        s = self.state
        tb = self._time_boot_ms()
        if mid == R.MAVLINK_MSG_ID_SYS_STATUS:
            mv, ca, pct = self._battery()
            return R.MAVLink_sys_status_message(SENSORS, SENSORS, SENSORS & ~self._unhealthy_sensors(), 200, mv, ca, pct,
                                                0, 0, 0, 0, 0, 0)
        if mid == R.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return R.MAVLink_extended_sys_state_message(R.MAV_VTOL_STATE_UNDEFINED, self._landed_state())
        if mid == R.MAVLINK_MSG_ID_BATTERY_STATUS:
            mv, ca, pct = self._battery()
            return battery_status_message(mv, ca, self.battery.used_c, pct, self.battery.level)
        if mid == R.MAVLINK_MSG_ID_HOME_POSITION:
            return self._home_position()
        if mid == R.MAVLINK_MSG_ID_MISSION_CURRENT:
            return self.runner.current_message(self.mode == MODE_MISSION)
        if mid == R.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS:
            # what the ESCs are told (normalised, limits applied); injected faults are not visible here
            cmd = np.clip(self.motor_commands_n / self.full_scale_n, 0.0, 1.0) if self.armed else np.zeros(4)
            return R.MAVLink_actuator_output_status_message(int(self.sim_s * 1e6), 0xF, [float(x) for x in cmd] + [0.0] * 28)
        if s is None:
            return None
        q = s.quaternion_wxyz
        w = s.angular_velocity_frd_radps
        if mid == R.MAVLINK_MSG_ID_ATTITUDE:
            roll, pitch, yaw = quat_to_euler(q)
            return R.MAVLink_attitude_message(tb, roll, pitch, yaw, *map(float, w))
        if mid == R.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            return R.MAVLink_attitude_quaternion_message(tb, *map(float, q), *map(float, w), [0.0] * 4)
        p, v = s.position_ned_m, s.velocity_ned_mps
        if mid == R.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            return R.MAVLink_local_position_ned_message(tb, *map(float, p), *map(float, v))
        lat, lon, alt = self._ned_to_global(p)
        if mid == R.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            rel = int(round((float(self.home_ned[2]) - p[2]) * 1000)) if self.home_ned is not None else 0
            hdg = int(round(math.degrees(quat_to_euler(q)[2]) * 100)) % 36000
            vel = [int(max(-32767, min(32767, round(x * 100)))) for x in v]
            return R.MAVLink_global_position_int_message(tb, lat, lon, alt, rel, *vel, hdg)
        if mid == R.MAVLINK_MSG_ID_GPS_RAW_INT:
            speed = math.hypot(v[0], v[1])
            cog = int(round(math.degrees(math.atan2(v[1], v[0])) * 100)) % 36000 if speed > 0.2 else 65535
            fix = R.GPS_FIX_TYPE_NO_FIX if self._unhealthy_sensors() & SENSOR_BITS["gps"] else R.GPS_FIX_TYPE_3D_FIX
            return R.MAVLink_gps_raw_int_message(int(self.sim_s * 1e6), fix, lat, lon, alt, 80, 120,
                                                 int(min(speed * 100, 65534)), cog, 12 if fix else 0, alt, 300, 500,
                                                 200, 0, 0)
        if mid == R.MAVLINK_MSG_ID_HIGHRES_IMU:
            if self.imu is not None:
                acc, gyro = self.imu.accel_frd_mps2, self.imu.gyro_frd_radps
            else:  # specific force from the state: R^T (a - g)
                acc = quat_to_rotmat(q).T @ (s.acceleration_ned_mps2 - np.array([0.0, 0.0, GRAVITY_MPS2]))
                gyro = w
            alt_m = self.origin.amsl_m - p[2]
            pressure_hpa = 1013.25 * (1 - 2.25577e-5 * alt_m) ** 5.25588
            return R.MAVLink_highres_imu_message(int(self.sim_s * 1e6), *map(float, acc), *map(float, gyro),
                                                 0.21, 0.0, 0.42, pressure_hpa, 0.0, alt_m, 20.0, 0x1A3F, 0)
        return None

    def _battery_step(self) -> None:
        """A low-battery level crossed: STATUSTEXT, and the action COM_LOW_BAT_ACT asks for when this
        vehicle flies itself (a unit under the coordinator only reports: the assembly decides)."""
        p = self.params
        checked = (self.battery.remaining, p.version)  # a level changes only when one of them moves
        if checked == self._battery_checked:
            return
        self._battery_checked = checked
        change = self.battery.level_change(p["BAT_LOW_THR"], p["BAT_CRIT_THR"], p["BAT_EMERGEN_THR"],
                                           int(p["COM_LOW_BAT_ACT"]))
        if change is None:
            return
        severity = {"low": mavlink.MAV_SEVERITY_WARNING, "critical": mavlink.MAV_SEVERITY_CRITICAL}.get(
            change.level, mavlink.MAV_SEVERITY_EMERGENCY)
        act = change.action is not None and self.source == "own" and self.armed and not self.landed
        self._text(change.text if act or change.action is None else change.text.split(":")[0], severity)
        if act:
            from firmware_models.vehicle_modes import MODE_LAND, MODE_RTL

            target = MODE_LAND if change.action == "land" else MODE_RTL
            if self.mode != target and self.command_service.set_mode(target) != mavlink.MAV_RESULT_ACCEPTED and target == MODE_RTL:
                self.command_service.set_mode(MODE_LAND)  # no home to return to: land where it is

    def _measure_battery(self, sample: BatterySample, t_s: float) -> BatterySample:
        """The power module's sample: counted, and the unit's report for the coordinator (with remaining)."""
        p = self.params
        b = self.battery
        b.measure(t_s, sample.voltage_v, sample.current_a, p["BAT1_CAPACITY"], int(p["BAT1_N_CELLS"]),
                  p["BAT1_R_INTERNAL"])
        return wire_battery(b.voltage_v, b.current_a, b.remaining)


def battery_status_message(mv: int, ca: int, used_c: float, pct: int, level: int = 0):
    """The vehicle's BATTERY_STATUS stream: its measured pack, with the charge state of its low-battery level."""
    R = mavlink
    state = (R.MAV_BATTERY_CHARGE_STATE_OK, R.MAV_BATTERY_CHARGE_STATE_LOW, R.MAV_BATTERY_CHARGE_STATE_CRITICAL,
             R.MAV_BATTERY_CHARGE_STATE_EMERGENCY)[level] if pct >= 0 else R.MAV_BATTERY_CHARGE_STATE_UNDEFINED
    return battery_status(mv, ca, pct, int(used_c / 3.6) if math.isfinite(used_c) else -1, state)
