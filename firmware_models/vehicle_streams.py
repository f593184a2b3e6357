"""Telemetry of the unit firmware: heartbeat, default streams, message requests and intervals."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.unit_controller import Phase
from mars_link.core.assembly import GRAVITY_MPS2
from mars_link.core.rotations import quat_to_euler, quat_to_rotmat
from firmware_models.vehicle_links import finite as _finite
from firmware_models.vehicle_modes import MAIN_AUTO, MAIN_OFFBOARD, MODE_MISSION
from mars_link.runtime.pacing import REANCHOR_S
from mars_link.mavlink.wire import battery_status
from mars_link.mavlink import codec as mavlink_codec

if TYPE_CHECKING:
    from firmware_models.vehicle import Outgoing, Vehicle

MIN_STREAM_INTERVAL_S = 0.001  # 1 kHz: the protocol's floor; the vehicle's own is one message per tick
#: (its control rate: streams go out when the runner ticks it, once per control step; `cap_hz`)
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


class StreamService:
    """The telemetry streams and what clients ask of them. Owns each stream's interval and when it is due
    next. Asks of the vehicle: its state, mode, home, battery, the mission runner, `_unhealthy_sensors`
    (a subclass's own health), `_broadcast`, `_count`, and `command_service.refuse` for a request refused."""

    def __init__(self, vehicle: Vehicle, wall_time_s: float) -> None:
        self.v = vehicle
        c = vehicle.config
        rates = DEFAULT_STREAM_HZ if c.stream_hz is None else c.stream_hz
        self.interval_s = {mid: 1.0 / hz for mid, hz in rates.items() if hz > 0}  # msg id -> interval (wall)
        self.next_due = {mid: wall_time_s for mid in self.interval_s}  # msg id -> wall time it is due

    def tick(self, wall_time_s: float, out: list[Outgoing]) -> None:
        """Every stream that is due (wall clock) to every telemetry link."""
        v = self.v
        next_due = self.next_due
        for mid, interval in self.interval_s.items():
            due = next_due.get(mid, wall_time_s)
            if wall_time_s + 1e-6 >= due:  # (a tick exactly on the interval counts despite float rounding)
                next_due[mid] = next_stream_due(due, interval, wall_time_s)
                try:
                    msg = self.message(mid)
                except (*mavlink_codec.ENCODE_ERRORS, FloatingPointError):  # e.g. int() of a NaN state
                    v._count("telemetry.encode_error")
                    msg = None
                if msg is not None:
                    v._broadcast(msg, out)

    def request_message(self, msgid: float, p2: float) -> tuple[int, list]:
        v = self.v
        R = mavlink
        if not math.isfinite(msgid) or msgid != int(msgid):
            return v.command_service.refuse(R.MAV_RESULT_DENIED, "param1 is no message id"), []
        mid = int(msgid)
        if mid == R.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return R.MAV_RESULT_ACCEPTED, [self.autopilot_version()]
        if mid == R.MAVLINK_MSG_ID_HEARTBEAT:
            return R.MAV_RESULT_ACCEPTED, [self.heartbeat()]
        if mid in DEFAULT_STREAM_HZ:
            msg = self.message(mid)
            if msg is None:
                why = f"no {R.mavlink_map[mid].msgname} yet"
                return v.command_service.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, why), []
            return R.MAV_RESULT_ACCEPTED, [msg]
        # (incl. REFUSED_MESSAGES: PROTOCOL_VERSION, AVAILABLE_MODES, ...)
        name = R.mavlink_map[mid].msgname if mid in R.mavlink_map else f"message {mid}"
        return v.command_service.refuse(R.MAV_RESULT_UNSUPPORTED, f"{name} not sent"), []

    @property
    def cap_hz(self) -> float:
        """The fastest a stream goes: one message per tick, and the runners tick once per control step
        (100 Hz by default; a unit at --control-hz 250 streams HIGHRES_IMU at 250 Hz)."""
        return 1.0 / max(MIN_STREAM_INTERVAL_S, self.v.control_dt_s)

    def set_interval(self, msgid: float, interval_us: float) -> int:
        """SET_MESSAGE_INTERVAL: faster than `cap_hz` is accepted and runs at the cap (its
        MESSAGE_INTERVAL then reports the interval in force)."""
        v = self.v
        R = mavlink
        if not _finite(msgid, interval_us) or int(msgid) not in DEFAULT_STREAM_HZ:
            return v.command_service.refuse(R.MAV_RESULT_DENIED, "not a streamed message")
        mid = int(msgid)
        if interval_us < 0:
            self.interval_s.pop(mid, None)
        else:
            iv = 1.0 / DEFAULT_STREAM_HZ[mid] if interval_us == 0 else max(1.0 / self.cap_hz, interval_us * 1e-6)
            self.interval_s[mid] = iv
            self.next_due[mid] = v.wall_s
        return R.MAV_RESULT_ACCEPTED


    def _ned_to_global(self, p: np.ndarray) -> tuple[int, int, int]:
        """(lat degE7, lon degE7, alt AMSL mm)."""
        return self.v.origin.to_global_int(p)

    def _time_boot_ms(self) -> int:
        return int(self.v.sim_s * 1000) & 0xFFFFFFFF

    def heartbeat(self):
        v = self.v
        R = mavlink
        base = R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | R.MAV_MODE_FLAG_STABILIZE_ENABLED
        if v.mode[0] in (MAIN_AUTO, MAIN_OFFBOARD):
            base |= R.MAV_MODE_FLAG_GUIDED_ENABLED | (R.MAV_MODE_FLAG_AUTO_ENABLED if v.mode[0] == MAIN_AUTO else 0)
        if v.armed:
            base |= R.MAV_MODE_FLAG_SAFETY_ARMED
        status = R.MAV_STATE_ACTIVE if v.armed else R.MAV_STATE_STANDBY
        return R.MAVLink_heartbeat_message(R.MAV_TYPE_QUADROTOR, R.MAV_AUTOPILOT_PX4, base, v.custom_mode, status, 3)

    def autopilot_version(self):
        uid = (0x4D415253 << 32) | self.v.sysid  # "MARS" + unit id
        sw = (0 << 24) | (1 << 16) | (0 << 8) | 255  # mars-link 0.1.0, release
        return mavlink.MAVLink_autopilot_version_message(
            CAPABILITIES, sw, sw, 0, 0, list(b"marslink"), [0] * 8, [0] * 8, 0, 0, uid, [0] * 18)

    def home_position(self):
        v = self.v
        if v.home_ned is None:
            return None
        lat, lon, alt = self._ned_to_global(v.home_ned)
        h = v.home_ned
        return mavlink.MAVLink_home_position_message(
            lat, lon, alt, float(h[0]), float(h[1]), float(h[2]), [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
            int(v.sim_s * 1e6))

    def _landed_state(self) -> int:
        v = self.v
        R = mavlink
        ph = v.autopilot.phase
        if v.landed:
            return R.MAV_LANDED_STATE_ON_GROUND
        if v.source == "own" and ph == Phase.TAKEOFF:
            return R.MAV_LANDED_STATE_TAKEOFF
        if v.source == "own" and ph == Phase.LAND:
            return R.MAV_LANDED_STATE_LANDING
        return R.MAV_LANDED_STATE_IN_AIR

    def _battery(self) -> tuple[int, int, int]:
        """(voltage mV, current cA, remaining %) as measured (firmware_models.battery_monitor); clamped to
        the wire fields (uint16 mV, int16 cA, int8 %). Nothing measured (no simulated pack: the papers'
        plants) or not a number -> MAVLink's "not sent" values (UINT16_MAX, -1, -1)."""
        b = self.v.battery

        def wire(x: float, lo: int, hi: int, unknown: int) -> int:
            return unknown if not math.isfinite(x) else int(min(max(x, lo), hi))

        return (wire(b.voltage_v * 1000, 0, 65534, 65535), wire(b.current_a * 100, 0, 32767, -1),
                wire(round(b.remaining * 100) if math.isfinite(b.remaining) else b.remaining, 0, 100, -1))

    def message(self, mid: int):
        R = mavlink
        s = self.v.state
        tb = self._time_boot_ms()
        if mid == R.MAVLINK_MSG_ID_SYS_STATUS:
            mv, ca, pct = self._battery()
            healthy = SENSORS & ~self.v._unhealthy_sensors()
            return R.MAVLink_sys_status_message(SENSORS, SENSORS, healthy, 200, mv, ca, pct, 0, 0, 0, 0, 0, 0)
        if mid == R.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return R.MAVLink_extended_sys_state_message(R.MAV_VTOL_STATE_UNDEFINED, self._landed_state())
        if mid == R.MAVLINK_MSG_ID_BATTERY_STATUS:
            mv, ca, pct = self._battery()
            return battery_status_message(mv, ca, self.v.battery.used_c, pct, self.v.battery.level)
        if mid == R.MAVLINK_MSG_ID_HOME_POSITION:
            return self.home_position()
        if mid == R.MAVLINK_MSG_ID_MISSION_CURRENT:
            return self.v.runner.current_message(self.v.mode == MODE_MISSION)
        if mid == R.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS:
            # what the ESCs are told (normalised, limits applied); injected faults are not visible here
            cmd = np.clip(self.v.motor_commands_n / self.v.full_scale_n, 0.0, 1.0) if self.v.armed else np.zeros(4)
            return R.MAVLink_actuator_output_status_message(int(self.v.sim_s * 1e6), 0xF,
                                                            [float(x) for x in cmd] + [0.0] * 28)
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
            rel = int(round((float(self.v.home_ned[2]) - p[2]) * 1000)) if self.v.home_ned is not None else 0
            hdg = int(round(math.degrees(quat_to_euler(q)[2]) * 100)) % 36000
            vel = [int(max(-32767, min(32767, round(x * 100)))) for x in v]
            return R.MAVLink_global_position_int_message(tb, lat, lon, alt, rel, *vel, hdg)
        if mid == R.MAVLINK_MSG_ID_GPS_RAW_INT:
            speed = math.hypot(v[0], v[1])
            cog = int(round(math.degrees(math.atan2(v[1], v[0])) * 100)) % 36000 if speed > 0.2 else 65535
            fix = R.GPS_FIX_TYPE_NO_FIX if self.v._unhealthy_sensors() & SENSOR_BITS["gps"] else R.GPS_FIX_TYPE_3D_FIX
            return R.MAVLink_gps_raw_int_message(int(self.v.sim_s * 1e6), fix, lat, lon, alt, 80, 120,
                                                 int(min(speed * 100, 65534)), cog, 12 if fix else 0, alt, 300, 500,
                                                 200, 0, 0)
        if mid == R.MAVLINK_MSG_ID_HIGHRES_IMU:
            if self.v.imu is not None:
                acc, gyro = self.v.imu.accel_frd_mps2, self.v.imu.gyro_frd_radps
            else:  # specific force from the state: R^T (a - g)
                acc = quat_to_rotmat(q).T @ (s.acceleration_ned_mps2 - np.array([0.0, 0.0, GRAVITY_MPS2]))
                gyro = w
            alt_m = self.v.origin.amsl_m - p[2]
            pressure_hpa = 1013.25 * (1 - 2.25577e-5 * alt_m) ** 5.25588
            return R.MAVLink_highres_imu_message(int(self.v.sim_s * 1e6), *map(float, acc), *map(float, gyro),
                                                 0.21, 0.0, 0.42, pressure_hpa, 0.0, alt_m, 20.0, 0x1A3F, 0)
        return None

def battery_status_message(mv: int, ca: int, used_c: float, pct: int, level: int = 0):
    """The vehicle's BATTERY_STATUS stream: its measured pack, with the charge state of its low-battery level."""
    R = mavlink
    state = (R.MAV_BATTERY_CHARGE_STATE_OK, R.MAV_BATTERY_CHARGE_STATE_LOW, R.MAV_BATTERY_CHARGE_STATE_CRITICAL,
             R.MAV_BATTERY_CHARGE_STATE_EMERGENCY)[level] if pct >= 0 else R.MAV_BATTERY_CHARGE_STATE_UNDEFINED
    return battery_status(mv, ca, pct, int(used_c / 3.6) if math.isfinite(used_c) else -1, state)
