"""The PX4 topics a mars-link vehicle logs: PX4's topic names, field names and types, for what we have.

Facts restated from PX4-Autopilot's uORB message definitions (msg/*.msg, v1.15 era: VehicleLocalPosition,
VehicleLocalPositionSetpoint, VehicleAttitude, VehicleAngularVelocity, VehicleGlobalPosition, SensorCombined,
ActuatorMotors, ActuatorOutputs, VehicleStatus, BatteryStatus, FailureDetectorStatus). Each topic here is a
consistent subset of PX4's fields with PX4's types (ULog is self-describing: a reader finds fields by name,
so the fields we cannot fill are simply absent). `timestamp` (uint64, microseconds of simulated time)
comes first. Flight Review's default plots read: vehicle_local_position x/y/z/vx/vy/vz and its setpoint,
vehicle_attitude q, vehicle_angular_velocity xyz, actuator_outputs noutputs/output (instances 0..2),
sensor_combined accelerometer_m_s2/gyro_rad, battery_status voltage_v/current_a, vehicle_status nav_state.
"""

from __future__ import annotations

from mars_link.logs.ulog import Field, Topic

F32, F64, U8, U16, U32, U64, I32, BOOL = "float", "double", "uint8_t", "uint16_t", "uint32_t", "uint64_t", "int32_t", "bool"


def _topic(name: str, *fields: tuple) -> Topic:
    return Topic(name, [Field(*f) for f in fields])


VEHICLE_LOCAL_POSITION = _topic(
    "vehicle_local_position",
    (U64, "timestamp"), (U64, "timestamp_sample"),
    (BOOL, "xy_valid"), (BOOL, "z_valid"), (BOOL, "v_xy_valid"), (BOOL, "v_z_valid"),
    (F32, "x"), (F32, "y"), (F32, "z"),
    (F32, "vx"), (F32, "vy"), (F32, "vz"), (F32, "z_deriv"),
    (F32, "ax"), (F32, "ay"), (F32, "az"),
    (F32, "heading"), (BOOL, "heading_good_for_control"),
    (BOOL, "xy_global"), (BOOL, "z_global"), (U64, "ref_timestamp"),
    (F64, "ref_lat"), (F64, "ref_lon"), (F32, "ref_alt"),
    (BOOL, "dead_reckoning"),
)

VEHICLE_LOCAL_POSITION_SETPOINT = _topic(
    "vehicle_local_position_setpoint",
    (U64, "timestamp"),
    (F32, "x"), (F32, "y"), (F32, "z"),
    (F32, "vx"), (F32, "vy"), (F32, "vz"),
    (F32, "acceleration", 3), (F32, "yaw"), (F32, "yawspeed"),
)

VEHICLE_ATTITUDE = _topic(
    "vehicle_attitude",
    (U64, "timestamp"), (U64, "timestamp_sample"), (F32, "q", 4),  # q: FRD body -> NED, Hamilton (w, x, y, z)
)

VEHICLE_ANGULAR_VELOCITY = _topic(
    "vehicle_angular_velocity",
    (U64, "timestamp"), (U64, "timestamp_sample"), (F32, "xyz", 3),  # rad/s, body FRD
)

VEHICLE_GLOBAL_POSITION = _topic(
    "vehicle_global_position",
    (U64, "timestamp"), (U64, "timestamp_sample"),
    (F64, "lat"), (F64, "lon"), (F32, "alt"),  # degrees, degrees, metres AMSL
)

SENSOR_COMBINED = _topic(
    "sensor_combined",
    (U64, "timestamp"),
    (F32, "gyro_rad", 3), (U32, "gyro_integral_dt"),
    (I32, "accelerometer_timestamp_relative"), (F32, "accelerometer_m_s2", 3), (U32, "accelerometer_integral_dt"),
    (U8, "accelerometer_clipping"), (U8, "gyro_clipping"),
)

#: actuator_motors holds 12 motors and actuator_outputs 16 outputs per instance: an assembly's 4N rotors
#: go into consecutive instances (instance k: rotors 12k+1.. / outputs 16k+1..)
MOTORS_PER_INSTANCE = 12
OUTPUTS_PER_INSTANCE = 16
FAILURE_MASK_BITS = 16

ACTUATOR_MOTORS = _topic(
    "actuator_motors",
    (U64, "timestamp"), (U64, "timestamp_sample"), (U16, "reversible_flags"),
    (F32, "control", MOTORS_PER_INSTANCE),  # thrust command / full scale, [-1, 1]; NaN: disarmed or no motor
)

ACTUATOR_OUTPUTS = _topic(
    "actuator_outputs",
    (U64, "timestamp"), (U32, "noutputs"),
    (F32, "output", OUTPUTS_PER_INSTANCE),  # what the motors are driven to, fraction of full-scale thrust 0..1
)

VEHICLE_STATUS = _topic(
    "vehicle_status",
    (U64, "timestamp"), (U64, "armed_time"), (U64, "takeoff_time"),
    (U8, "arming_state"), (U64, "nav_state_timestamp"), (U8, "nav_state_user_intention"), (U8, "nav_state"),
    (U16, "failure_detector_status"), (U8, "hil_state"), (U8, "vehicle_type"),
    (BOOL, "failsafe"), (BOOL, "is_vtol"), (BOOL, "in_transition_mode"),
    (U8, "system_type"), (U8, "system_id"), (U8, "component_id"),
)

BATTERY_STATUS = _topic(
    "battery_status",
    (U64, "timestamp"), (BOOL, "connected"),
    (F32, "voltage_v"), (F32, "current_a"), (F32, "discharged_mah"), (F32, "remaining"),
    (U8, "id"), (U8, "warning"),
)

FAILURE_DETECTOR_STATUS = _topic(
    "failure_detector_status",
    (U64, "timestamp"),
    (BOOL, "fd_roll"), (BOOL, "fd_pitch"), (BOOL, "fd_alt"), (BOOL, "fd_ext"), (BOOL, "fd_arm_escs"),
    (BOOL, "fd_battery"), (BOOL, "fd_imbalanced_prop"), (BOOL, "fd_motor"),
    (F32, "imbalanced_prop_metric"),
    (U16, "motor_failure_mask"),  # motors (bit i: motor 16k+i+1 of instance k) known failed (eta < 1)
    (U16, "motor_stop_mask"),  # ... stopped (eta 0)
)

ALL_TOPICS = (VEHICLE_LOCAL_POSITION, VEHICLE_LOCAL_POSITION_SETPOINT, VEHICLE_ATTITUDE, VEHICLE_ANGULAR_VELOCITY,
              VEHICLE_GLOBAL_POSITION, SENSOR_COMBINED, ACTUATOR_MOTORS, ACTUATOR_OUTPUTS, VEHICLE_STATUS,
              BATTERY_STATUS, FAILURE_DETECTOR_STATUS)

# vehicle_status values
ARMING_STATE_DISARMED, ARMING_STATE_ARMED = 1, 2  # (v1.14: 1 STANDBY, 2 ARMED)
VEHICLE_TYPE_ROTARY_WING = 1
HIL_STATE_ON = 1
MAV_TYPE_QUADROTOR = 2
NAV_MANUAL, NAV_ALTCTL, NAV_POSCTL, NAV_AUTO_MISSION, NAV_AUTO_LOITER, NAV_AUTO_RTL = 0, 1, 2, 3, 4, 5
NAV_ACRO, NAV_OFFBOARD, NAV_STAB = 10, 14, 15
NAV_AUTO_TAKEOFF, NAV_AUTO_LAND, NAV_AUTO_FOLLOW_TARGET, NAV_AUTO_PRECLAND, NAV_ORBIT = 17, 18, 19, 20, 21
FAILURE_MOTOR = 128  # vehicle_status.failure_detector_status bit


_NAV_STATES: dict[tuple[int, int], int] = {}


def nav_state(main_mode: int, sub_mode: int) -> int:
    """PX4's nav_state of a PX4 custom mode (main, sub), as HEARTBEAT carries it."""
    key = (main_mode, sub_mode)
    nav = _NAV_STATES.get(key)
    if nav is None:
        nav = _NAV_STATES[key] = _nav_state(main_mode, sub_mode)
    return nav


def _nav_state(main_mode: int, sub_mode: int) -> int:
    from firmware_models import vehicle_modes as m

    if main_mode == m.MAIN_AUTO:
        return {m.SUB_READY: NAV_AUTO_LOITER, m.SUB_TAKEOFF: NAV_AUTO_TAKEOFF, m.SUB_LOITER: NAV_AUTO_LOITER,
                m.SUB_MISSION: NAV_AUTO_MISSION, m.SUB_RTL: NAV_AUTO_RTL, m.SUB_LAND: NAV_AUTO_LAND,
                m.SUB_FOLLOW_TARGET: NAV_AUTO_FOLLOW_TARGET, 9: NAV_AUTO_PRECLAND}.get(sub_mode, NAV_AUTO_LOITER)
    if main_mode == m.MAIN_POSCTL:
        return NAV_ORBIT if sub_mode == m.SUB_POSCTL_ORBIT else NAV_POSCTL
    return {m.MAIN_MANUAL: NAV_MANUAL, m.MAIN_ALTCTL: NAV_ALTCTL, m.MAIN_ACRO: NAV_ACRO,
            m.MAIN_OFFBOARD: NAV_OFFBOARD, m.MAIN_STABILIZED: NAV_STAB}.get(main_mode, NAV_MANUAL)
