"""The px4_msgs types the PX4 unit interface speaks, restated as data (field names, types, constants).

Source (facts only, restated in our own layout and words): PX4 v1.17.0, PX4-Autopilot commit
a64536802b5a5b6ba8fe6ef1b7dcb6a54a0a99ea, as published in px4_msgs tag v1.17.0
(px4_msgs commit 86d8239e962f6939e05c3737784f60c02fa884db, `msg/<Name>.msg`). Only the fields decide the
wire layout and the RIHS01 type hash; constants are restated where the unit interface or a user needs
them (VehicleCommand's long command list is cut to the commands the unit answers).

`message_version` is PX4's MESSAGE_VERSION constant (None: the message is not versioned in that release).
A field is `(name, type)` or `(name, type, fixed_array_length)`; types are ROS 2 primitive names.
"""

from __future__ import annotations

from dataclasses import dataclass

PACKAGE = "px4_msgs"
PX4_RELEASE = "v1.17.0"
PX4_COMMIT = "a64536802b5a5b6ba8fe6ef1b7dcb6a54a0a99ea"
PX4_MSGS_COMMIT = "86d8239e962f6939e05c3737784f60c02fa884db"

PRIMITIVE_TYPES = ("bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
                   "float32", "float64")


@dataclass(frozen=True)
class FieldSpec:
    name: str
    type: str                    # a ROS 2 primitive type name (PRIMITIVE_TYPES)
    array_length: int | None = None  # fixed-size array `type[N]`; None: a single value


@dataclass(frozen=True)
class ConstantSpec:
    name: str
    type: str
    value: int | float | bool


@dataclass(frozen=True)
class MessageSpec:
    name: str                    # e.g. "ActuatorMotors"
    fields: tuple[FieldSpec, ...]
    constants: tuple[ConstantSpec, ...] = ()
    message_version: int | None = None

    @property
    def ros_type_name(self) -> str:
        """As in a ROS 2 type description: `px4_msgs/msg/ActuatorMotors`."""
        return f"{PACKAGE}/msg/{self.name}"

    @property
    def dds_type_name(self) -> str:
        """As DDS (and rmw_zenoh's key expressions) name it: `px4_msgs::msg::dds_::ActuatorMotors_`."""
        return f"{PACKAGE}::msg::dds_::{self.name}_"

    def constant(self, name: str) -> int | float | bool:
        for c in self.constants:
            if c.name == name:
                return c.value
        raise KeyError(f"{self.name} has no constant {name}")


def _spec(name: str, fields: list[tuple], constants: list[tuple] = (), version: int | None = None) -> MessageSpec:
    built_fields = tuple(FieldSpec(*f) for f in fields)
    for f in built_fields:
        if f.type not in PRIMITIVE_TYPES:
            raise ValueError(f"{name}.{f.name}: type {f.type!r} is not a primitive type")
    return MessageSpec(name, built_fields, tuple(ConstantSpec(*c) for c in constants), version)


# Offboard keep-alive: which setpoint kind the off-board computer drives. Unversioned in v1.17.
OFFBOARD_CONTROL_MODE = _spec("OffboardControlMode", [
    ("timestamp", "uint64"),             # [us] since the sender's boot
    ("position", "bool"),
    ("velocity", "bool"),
    ("acceleration", "bool"),
    ("attitude", "bool"),
    ("body_rate", "bool"),
    ("thrust_and_torque", "bool"),
    ("direct_actuator", "bool"),         # the per-rotor path: ActuatorMotors drives the motors directly
])

# Normalised per-motor thrust for up to 12 motors. NaN: disarmed / motor stopped.
ACTUATOR_MOTORS = _spec("ActuatorMotors", [
    ("timestamp", "uint64"),             # [us]
    ("timestamp_sample", "uint64"),      # [us] the sample this command was computed from
    ("reversible_flags", "uint16"),      # bit i: motor i may run backwards (-1..0)
    ("control", "float32", 12),          # [-1, 1] reversible, [0, 1] otherwise; NaN = stop
], [
    ("MESSAGE_VERSION", "uint32", 0),
    ("ACTUATOR_FUNCTION_MOTOR1", "uint8", 101),
    ("NUM_CONTROLS", "uint8", 12),
], version=0)

# A MAVLink-style command (params as in MAV_CMD) routed to the commander.
VEHICLE_COMMAND = _spec("VehicleCommand", [
    ("timestamp", "uint64"),             # [us]
    ("param1", "float32"),
    ("param2", "float32"),
    ("param3", "float32"),
    ("param4", "float32"),
    ("param5", "float64"),
    ("param6", "float64"),
    ("param7", "float32"),
    ("command", "uint32"),
    ("target_system", "uint8"),
    ("target_component", "uint8"),
    ("source_system", "uint8"),
    ("source_component", "uint16"),
    ("confirmation", "uint8"),
    ("from_external", "bool"),
], [
    ("MESSAGE_VERSION", "uint32", 0),
    ("VEHICLE_CMD_DO_SET_MODE", "uint16", 176),          # param1 base mode flags, param2 custom main mode
    ("VEHICLE_CMD_DO_FLIGHTTERMINATION", "uint16", 185),
    ("VEHICLE_CMD_COMPONENT_ARM_DISARM", "uint16", 400),  # param1: 1 arm, 0 disarm
    ("ARMING_ACTION_DISARM", "int8", 0),
    ("ARMING_ACTION_ARM", "int8", 1),
    ("ORB_QUEUE_LENGTH", "uint8", 8),
], version=0)

VEHICLE_COMMAND_ACK = _spec("VehicleCommandAck", [
    ("timestamp", "uint64"),             # [us]
    ("command", "uint32"),               # the command answered
    ("result", "uint8"),                 # VEHICLE_CMD_RESULT_*
    ("result_param1", "uint8"),          # progress [%] or the reason of a refusal
    ("result_param2", "int32"),
    ("target_system", "uint8"),          # the command's source system
    ("target_component", "uint16"),      # the command's source component
    ("from_external", "bool"),
], [
    ("MESSAGE_VERSION", "uint32", 0),
    ("VEHICLE_CMD_RESULT_ACCEPTED", "uint8", 0),
    ("VEHICLE_CMD_RESULT_TEMPORARILY_REJECTED", "uint8", 1),
    ("VEHICLE_CMD_RESULT_DENIED", "uint8", 2),
    ("VEHICLE_CMD_RESULT_UNSUPPORTED", "uint8", 3),
    ("VEHICLE_CMD_RESULT_FAILED", "uint8", 4),
    ("VEHICLE_CMD_RESULT_IN_PROGRESS", "uint8", 5),
    ("VEHICLE_CMD_RESULT_CANCELLED", "uint8", 6),
    ("ARM_AUTH_DENIED_REASON_GENERIC", "uint16", 0),
    ("ARM_AUTH_DENIED_REASON_NONE", "uint16", 1),
    ("ARM_AUTH_DENIED_REASON_INVALID_WAYPOINT", "uint16", 2),
    ("ARM_AUTH_DENIED_REASON_TIMEOUT", "uint16", 3),
    ("ARM_AUTH_DENIED_REASON_AIRSPACE_IN_USE", "uint16", 4),
    ("ARM_AUTH_DENIED_REASON_BAD_WEATHER", "uint16", 5),
    ("ORB_QUEUE_LENGTH", "uint8", 4),
], version=0)

_NAV_STATES = [
    ("MANUAL", 0), ("ALTCTL", 1), ("POSCTL", 2), ("AUTO_MISSION", 3), ("AUTO_LOITER", 4), ("AUTO_RTL", 5),
    ("POSITION_SLOW", 6), ("FREE5", 7), ("ALTITUDE_CRUISE", 8), ("FREE3", 9), ("ACRO", 10), ("FREE2", 11),
    ("DESCEND", 12), ("TERMINATION", 13), ("OFFBOARD", 14), ("STAB", 15), ("FREE1", 16),
    ("AUTO_TAKEOFF", 17), ("AUTO_LAND", 18), ("AUTO_FOLLOW_TARGET", 19), ("AUTO_PRECLAND", 20),
    ("ORBIT", 21), ("AUTO_VTOL_TAKEOFF", 22), ("EXTERNAL1", 23), ("EXTERNAL2", 24), ("EXTERNAL3", 25),
    ("EXTERNAL4", 26), ("EXTERNAL5", 27), ("EXTERNAL6", 28), ("EXTERNAL7", 29), ("EXTERNAL8", 30),
    ("MAX", 31),
]
_ARM_DISARM_REASONS = [
    ("TRANSITION_TO_STANDBY", 0), ("STICK_GESTURE", 1), ("RC_SWITCH", 2), ("COMMAND_INTERNAL", 3),
    ("COMMAND_EXTERNAL", 4), ("MISSION_START", 5), ("SAFETY_BUTTON", 6), ("AUTO_DISARM_LAND", 7),
    ("AUTO_DISARM_PREFLIGHT", 8), ("KILL_SWITCH", 9), ("LOCKDOWN", 10), ("FAILURE_DETECTOR", 11),
    ("SHUTDOWN", 12), ("UNIT_TEST", 13),
]
_FAILURES = [("NONE", 0), ("ROLL", 1), ("PITCH", 2), ("ALT", 4), ("EXT", 8), ("ARM_ESC", 16), ("BATTERY", 32),
             ("IMBALANCED_PROP", 64), ("MOTOR", 128)]

# The commander's state: arming, navigation state (mode) and failsafe. Version 1 in v1.17.
VEHICLE_STATUS = _spec("VehicleStatus", [
    ("timestamp", "uint64"),             # [us]
    ("armed_time", "uint64"),            # [us] when armed, 0 if disarmed
    ("takeoff_time", "uint64"),          # [us]
    ("arming_state", "uint8"),           # ARMING_STATE_*
    ("latest_arming_reason", "uint8"),   # ARM_DISARM_REASON_*
    ("latest_disarming_reason", "uint8"),
    ("nav_state_timestamp", "uint64"),   # [us] when nav_state last changed
    ("nav_state_user_intention", "uint8"),  # the mode the user asked for (a failsafe may override it)
    ("nav_state", "uint8"),              # NAVIGATION_STATE_*: the mode in force
    ("executor_in_charge", "uint8"),
    ("valid_nav_states_mask", "uint32"),
    ("can_set_nav_states_mask", "uint32"),
    ("failure_detector_status", "uint16"),  # FAILURE_* bits
    ("hil_state", "uint8"),
    ("vehicle_type", "uint8"),           # VEHICLE_TYPE_*
    ("failsafe", "bool"),
    ("failsafe_and_user_took_over", "bool"),
    ("failsafe_defer_state", "uint8"),
    ("gcs_connection_lost", "bool"),
    ("gcs_connection_lost_counter", "uint8"),
    ("high_latency_data_link_lost", "bool"),
    ("is_vtol", "bool"),
    ("is_vtol_tailsitter", "bool"),
    ("in_transition_mode", "bool"),
    ("in_transition_to_fw", "bool"),
    ("system_type", "uint8"),            # MAV_TYPE
    ("system_id", "uint8"),
    ("component_id", "uint8"),
    ("safety_button_available", "bool"),
    ("safety_off", "bool"),
    ("power_input_valid", "bool"),
    ("usb_connected", "bool"),
    ("open_drone_id_system_present", "bool"),
    ("open_drone_id_system_healthy", "bool"),
    ("parachute_system_present", "bool"),
    ("parachute_system_healthy", "bool"),
    ("rc_calibration_in_progress", "bool"),
    ("calibration_enabled", "bool"),
    ("pre_flight_checks_pass", "bool"),
], [
    ("MESSAGE_VERSION", "uint32", 1),
    ("ARMING_STATE_DISARMED", "uint8", 1),
    ("ARMING_STATE_ARMED", "uint8", 2),
    *[(f"ARM_DISARM_REASON_{n}", "uint8", v) for n, v in _ARM_DISARM_REASONS],
    *[(f"NAVIGATION_STATE_{n}", "uint8", v) for n, v in _NAV_STATES],
    *[(f"FAILURE_{n}", "uint16", v) for n, v in _FAILURES],
    ("HIL_STATE_OFF", "uint8", 0),
    ("HIL_STATE_ON", "uint8", 1),
    ("VEHICLE_TYPE_UNSPECIFIED", "uint8", 0),
    ("VEHICLE_TYPE_ROTARY_WING", "uint8", 1),
    ("VEHICLE_TYPE_FIXED_WING", "uint8", 2),
    ("VEHICLE_TYPE_ROVER", "uint8", 3),
    ("FAILSAFE_DEFER_STATE_DISABLED", "uint8", 0),
    ("FAILSAFE_DEFER_STATE_ENABLED", "uint8", 1),
    ("FAILSAFE_DEFER_STATE_WOULD_FAILSAFE", "uint8", 2),
], version=1)

# Estimated pose and twist (REP 147 style). Version 0 in v1.17.
VEHICLE_ODOMETRY = _spec("VehicleOdometry", [
    ("timestamp", "uint64"),             # [us]
    ("timestamp_sample", "uint64"),      # [us]
    ("pose_frame", "uint8"),             # POSE_FRAME_*
    ("position", "float32", 3),          # [m] in pose_frame; NaN if unknown
    ("q", "float32", 4),                 # [-] body to pose frame, Hamilton (w, x, y, z)
    ("velocity_frame", "uint8"),         # VELOCITY_FRAME_*
    ("velocity", "float32", 3),          # [m/s] in velocity_frame
    ("angular_velocity", "float32", 3),  # [rad/s] body FRD
    ("position_variance", "float32", 3),     # [m^2]
    ("orientation_variance", "float32", 3),  # [rad^2]
    ("velocity_variance", "float32", 3),     # [m^2/s^2]
    ("reset_counter", "uint8"),
    ("quality", "int8"),
], [
    ("MESSAGE_VERSION", "uint32", 0),
    ("POSE_FRAME_UNKNOWN", "uint8", 0),
    ("POSE_FRAME_NED", "uint8", 1),
    ("POSE_FRAME_FRD", "uint8", 2),
    ("VELOCITY_FRAME_UNKNOWN", "uint8", 0),
    ("VELOCITY_FRAME_NED", "uint8", 1),
    ("VELOCITY_FRAME_FRD", "uint8", 2),
    ("VELOCITY_FRAME_BODY_FRD", "uint8", 3),
], version=0)

# IMU averages in the body FRD frame. Unversioned in v1.17.
SENSOR_COMBINED = _spec("SensorCombined", [
    ("timestamp", "uint64"),             # [us] (also the gyro sample time)
    ("gyro_rad", "float32", 3),          # [rad/s] body FRD
    ("gyro_integral_dt", "uint32"),      # [us]
    ("accelerometer_timestamp_relative", "int32"),  # [us] accel time - timestamp
    ("accelerometer_m_s2", "float32", 3),  # [m/s^2] body FRD specific force
    ("accelerometer_integral_dt", "uint32"),  # [us]
    ("accelerometer_clipping", "uint8"),  # CLIPPING_* bits
    ("gyro_clipping", "uint8"),
    ("accel_calibration_count", "uint8"),
    ("gyro_calibration_count", "uint8"),
], [
    ("RELATIVE_TIMESTAMP_INVALID", "int32", 2147483647),
    ("CLIPPING_X", "uint8", 1),
    ("CLIPPING_Y", "uint8", 2),
    ("CLIPPING_Z", "uint8", 4),
])

# Battery state. Version 1 in v1.17.
BATTERY_STATUS = _spec("BatteryStatus", [
    ("timestamp", "uint64"),             # [us]
    ("connected", "bool"),
    ("voltage_v", "float32"),            # [V]
    ("current_a", "float32"),            # [A], -1 if unknown
    ("current_average_a", "float32"),    # [A]
    ("discharged_mah", "float32"),       # [mAh]
    ("remaining", "float32"),            # [0, 1]
    ("scale", "float32"),                # [-] throttle compensation factor
    ("time_remaining_s", "float32"),     # [s]
    ("temperature", "float32"),          # [degC]
    ("cell_count", "uint8"),
    ("source", "uint8"),                 # SOURCE_*
    ("priority", "uint8"),
    ("capacity", "uint16"),              # [mAh]
    ("cycle_count", "uint16"),
    ("average_time_to_empty", "uint16"),  # [min]
    ("manufacture_date", "uint16"),
    ("state_of_health", "uint16"),       # [%]
    ("max_error", "uint16"),             # [%]
    ("id", "uint8"),
    ("interface_error", "uint16"),
    ("voltage_cell_v", "float32", 14),   # [V]
    ("max_cell_voltage_delta", "float32"),  # [V]
    ("is_powering_off", "bool"),
    ("is_required", "bool"),
    ("warning", "uint8"),                # WARNING_*
    ("faults", "uint16"),                # bit FAULT_*
    ("full_charge_capacity_wh", "float32"),  # [Wh]
    ("remaining_capacity_wh", "float32"),    # [Wh]
    ("over_discharge_count", "uint16"),
    ("nominal_voltage", "float32"),      # [V]
    ("internal_resistance_estimate", "float32"),  # [Ohm]
    ("ocv_estimate", "float32"),         # [V]
    ("ocv_estimate_filtered", "float32"),  # [V]
    ("volt_based_soc_estimate", "float32"),  # [0, 1]
    ("voltage_prediction", "float32"),   # [V]
    ("prediction_error", "float32"),     # [V]
    ("estimation_covariance_norm", "float32"),
], [
    ("MESSAGE_VERSION", "uint32", 1),
    ("MAX_INSTANCES", "uint8", 3),
    ("SOURCE_POWER_MODULE", "uint8", 0),
    ("SOURCE_EXTERNAL", "uint8", 1),
    ("SOURCE_ESCS", "uint8", 2),
    ("WARNING_NONE", "uint8", 0),
    ("WARNING_LOW", "uint8", 1),
    ("WARNING_CRITICAL", "uint8", 2),
    ("WARNING_EMERGENCY", "uint8", 3),
    ("WARNING_FAILED", "uint8", 4),
    ("STATE_UNHEALTHY", "uint8", 6),
    ("STATE_CHARGING", "uint8", 7),
    ("FAULT_DEEP_DISCHARGE", "uint8", 0),
    ("FAULT_SPIKES", "uint8", 1),
    ("FAULT_CELL_FAIL", "uint8", 2),
    ("FAULT_OVER_CURRENT", "uint8", 3),
    ("FAULT_OVER_TEMPERATURE", "uint8", 4),
    ("FAULT_UNDER_TEMPERATURE", "uint8", 5),
    ("FAULT_INCOMPATIBLE_VOLTAGE", "uint8", 6),
    ("FAULT_INCOMPATIBLE_FIRMWARE", "uint8", 7),
    ("FAULT_INCOMPATIBLE_MODEL", "uint8", 8),
    ("FAULT_HARDWARE_FAILURE", "uint8", 9),
    ("FAULT_FAILED_TO_ARM", "uint8", 10),
    ("FAULT_COUNT", "uint8", 11),
], version=1)

# Local NED position estimate. Version 1 in v1.17.
VEHICLE_LOCAL_POSITION = _spec("VehicleLocalPosition", [
    ("timestamp", "uint64"),             # [us]
    ("timestamp_sample", "uint64"),      # [us]
    ("xy_valid", "bool"),
    ("z_valid", "bool"),
    ("v_xy_valid", "bool"),
    ("v_z_valid", "bool"),
    ("x", "float32"),                    # [m] north
    ("y", "float32"),                    # [m] east
    ("z", "float32"),                    # [m] down
    ("delta_xy", "float32", 2),          # [m] last xy reset step
    ("xy_reset_counter", "uint8"),
    ("delta_z", "float32"),              # [m]
    ("z_reset_counter", "uint8"),
    ("vx", "float32"),                   # [m/s] north
    ("vy", "float32"),                   # [m/s] east
    ("vz", "float32"),                   # [m/s] down
    ("z_deriv", "float32"),              # [m/s] derivative of z
    ("delta_vxy", "float32", 2),         # [m/s]
    ("vxy_reset_counter", "uint8"),
    ("delta_vz", "float32"),             # [m/s]
    ("vz_reset_counter", "uint8"),
    ("ax", "float32"),                   # [m/s^2] NED
    ("ay", "float32"),
    ("az", "float32"),
    ("heading", "float32"),              # [rad] Euler yaw
    ("heading_var", "float32"),          # [rad^2]
    ("unaided_heading", "float32"),      # [rad]
    ("delta_heading", "float32"),        # [rad]
    ("heading_reset_counter", "uint8"),
    ("heading_good_for_control", "bool"),
    ("tilt_var", "float32"),             # [rad^2]
    ("xy_global", "bool"),
    ("z_global", "bool"),
    ("ref_timestamp", "uint64"),         # [us]
    ("ref_lat", "float64"),              # [deg]
    ("ref_lon", "float64"),              # [deg]
    ("ref_alt", "float32"),              # [m] AMSL
    ("dist_bottom_valid", "bool"),
    ("dist_bottom", "float32"),          # [m]
    ("dist_bottom_var", "float32"),      # [m^2]
    ("delta_dist_bottom", "float32"),    # [m]
    ("dist_bottom_reset_counter", "uint8"),
    ("dist_bottom_sensor_bitfield", "uint8"),  # DIST_BOTTOM_SENSOR_* bits
    ("eph", "float32"),                  # [m] horizontal position error (1 sigma)
    ("epv", "float32"),                  # [m]
    ("evh", "float32"),                  # [m/s]
    ("evv", "float32"),                  # [m/s]
    ("dead_reckoning", "bool"),
    ("vxy_max", "float32"),              # [m/s] limits the estimator imposes (inf: none)
    ("vz_max", "float32"),
    ("hagl_min", "float32"),             # [m]
    ("hagl_max_z", "float32"),
    ("hagl_max_xy", "float32"),
], [
    ("MESSAGE_VERSION", "uint32", 1),
    ("DIST_BOTTOM_SENSOR_NONE", "uint8", 0),
    ("DIST_BOTTOM_SENSOR_RANGE", "uint8", 1),
    ("DIST_BOTTOM_SENSOR_FLOW", "uint8", 2),
], version=1)

ALL_MESSAGES: tuple[MessageSpec, ...] = (
    OFFBOARD_CONTROL_MODE, ACTUATOR_MOTORS, VEHICLE_COMMAND, VEHICLE_COMMAND_ACK, VEHICLE_STATUS,
    VEHICLE_ODOMETRY, SENSOR_COMBINED, BATTERY_STATUS, VEHICLE_LOCAL_POSITION,
)
BY_NAME: dict[str, MessageSpec] = {m.name: m for m in ALL_MESSAGES}


def _format_value(type_name: str, value: int | float | bool) -> str:
    if type_name == "bool":
        return "true" if value else "false"
    return repr(value)


def msg_text(spec: MessageSpec) -> str:
    """The message as ROS 2 `.msg` text (fields and constants, no comments), generated from our data:
    what a ROS 2 tool (rosidl, rosbags) needs to build the same type."""
    lines = []
    for c in spec.constants:
        lines.append(f"{c.type} {c.name} = {_format_value(c.type, c.value)}")
    for f in spec.fields:
        array = f"[{f.array_length}]" if f.array_length is not None else ""
        lines.append(f"{f.type}{array} {f.name}")
    return "\n".join(lines) + "\n"
