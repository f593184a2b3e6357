"""PX4's per-rotor interface over rmw_zenoh (issue 42, foundation): our px4_msgs definitions, CDR codec,
RIHS01 hashes and keys checked against an implementation that is not ours (rosbags), the unit-side
semantics in simulated time, and one exchange over real zenoh sessions on loopback."""

from __future__ import annotations

import json
import socket
import struct
import time

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

from mars_link.px4 import cdr, definitions as d, rmw_zenoh as rz, telemetry
from mars_link.px4.endpoint import Px4UnitEndpoint
from mars_link.px4.type_hash import rihs01
from mars_link.px4.unit_interface import (
    OffboardLossAction, Px4MainMode, Px4UnitInterface, Px4UnitParams, motor_commands,
)

# --- an independent implementation: rosbags, fed .msg text generated from our definitions ------------


@pytest.fixture(scope="module")
def rosbags_store():
    store = get_typestore(Stores.EMPTY)
    for spec in d.ALL_MESSAGES:
        store.register(get_types_from_msg(d.msg_text(spec), spec.ros_type_name))
    return store


_INT_RANGES = {"int8": (-128, 127), "uint8": (0, 255), "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
               "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1), "int64": (-2**63, 2**63 - 1),
               "uint64": (0, 2**64 - 1)}


def _sample_values(spec: d.MessageSpec, seed: int) -> dict:
    """Values that exercise every byte: extremes of the integer ranges, float32-exact floats, NaN."""
    rng = np.random.default_rng(seed)
    values = {}
    for i, f in enumerate(spec.fields):
        count = f.array_length or 1
        if f.type == "bool":
            v = rng.integers(0, 2, count).astype(bool)
        elif f.type in _INT_RANGES:
            lo, hi = _INT_RANGES[f.type]
            picks = [lo, hi, (lo + hi) // 2 + 1, int(rng.integers(0, min(hi, 2**31 - 1)))]
            v = np.array([picks[(i + k) % 4] for k in range(count)],
                         dtype=np.dtype(f.type if f.type != "bool" else bool))
        else:
            dtype = np.float32 if f.type == "float32" else np.float64
            v = (rng.standard_normal(count) * 1000).astype(dtype)
            if f.array_length:
                v[0] = np.nan
        values[f.name] = v if f.array_length is not None else v[0].item()
    return values


def _ours(spec: d.MessageSpec, values: dict):
    return cdr.message_class(spec.name)(**values)


def _theirs(store, spec: d.MessageSpec, values: dict):
    return store.types[spec.ros_type_name](**values)


def _assert_same_fields(spec: d.MessageSpec, a, b) -> None:
    for f in spec.fields:
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.array_length is not None:
            assert np.array_equal(np.asarray(x), np.asarray(y), equal_nan=f.type.startswith("float")), f.name
        elif f.type.startswith("float"):
            assert (np.isnan(x) and np.isnan(y)) or x == y, f.name
        else:
            assert x == y, f.name


@pytest.mark.parametrize("spec", d.ALL_MESSAGES, ids=lambda s: s.name)
def test_type_hash_and_key_match_rosbags(spec, rosbags_store):
    theirs = rosbags_store.hash_rihs01(spec.ros_type_name)
    assert rihs01(spec) == theirs
    key = rz.data_key(rz.Px4Topic("/fmu/in/x", spec, rz.Direction.IN), "px4_2", domain_id=7)
    assert key == f"7/px4_2/fmu/in/x/px4_msgs::msg::dds_::{spec.name}_/{theirs}"


@pytest.mark.parametrize("spec", d.ALL_MESSAGES, ids=lambda s: s.name)
def test_cdr_bytes_match_rosbags_both_ways(spec, rosbags_store):
    for seed in (1, 2):
        values = _sample_values(spec, seed)
        ours = cdr.encode(_ours(spec, values))
        theirs = bytes(rosbags_store.serialize_cdr(_theirs(rosbags_store, spec, values), spec.ros_type_name))
        assert ours[:4] == b"\x00\x01\x00\x00"          # CDR little endian, as rmw_zenoh sends
        assert ours == theirs
        assert len(ours) == cdr.encoded_size(spec.name)
        # ours -> their decoder, their bytes -> our decoder
        _assert_same_fields(spec, rosbags_store.deserialize_cdr(ours, spec.ros_type_name), _ours(spec, values))
        _assert_same_fields(spec, cdr.decode(spec.name, theirs), _ours(spec, values))
    big = bytes(rosbags_store.serialize_cdr(_theirs(rosbags_store, spec, values), spec.ros_type_name,
                                            little_endian=False))
    assert cdr.encode(_ours(spec, values), big_endian=True) == big
    _assert_same_fields(spec, cdr.decode(spec.name, big), _ours(spec, values))


def test_decode_refuses_short_and_foreign_payloads():
    good = cdr.encode(cdr.ActuatorMotors())
    with pytest.raises(cdr.CdrError, match="needs"):
        cdr.decode("ActuatorMotors", good[:-1])
    with pytest.raises(cdr.CdrError, match="encapsulation"):
        cdr.decode("ActuatorMotors", b"\x00\x11\x00\x00" + good[4:])   # XCDR2 is not what rmw_zenoh sends
    with pytest.raises(cdr.CdrError, match="expected 12"):
        cdr.encode(cdr.ActuatorMotors(control=np.zeros(4)))


def test_actuator_motors_layout_by_hand():
    """The alignment rule spelled out: uint16 at 16, two pad bytes, float32[12] from 20 (after the header)."""
    control = np.arange(12, dtype=np.float32) / 10
    payload = cdr.encode(cdr.ActuatorMotors(timestamp=1, timestamp_sample=2, reversible_flags=0xABCD,
                                            control=control))
    expected = b"\x00\x01\x00\x00" + struct.pack("<QQH2x12f", 1, 2, 0xABCD, *control.tolist())
    assert payload == expected


# --- our definitions against PX4's own text (v1.17.0, restated: field lines only) ---------------------

# PX4 v1.17.0 (PX4-Autopilot a64536802b5a5b6ba8fe6ef1b7dcb6a54a0a99ea, px4_msgs tag v1.17.0): the fields of
# each message in order, in .msg syntax, restated for this check. Parsed by rosbags' .msg parser.
PX4_V1_17_FIELDS = {
    "OffboardControlMode": "uint64 timestamp\nbool position\nbool velocity\nbool acceleration\nbool attitude\n"
                           "bool body_rate\nbool thrust_and_torque\nbool direct_actuator",
    "ActuatorMotors": "uint64 timestamp\nuint64 timestamp_sample\nuint16 reversible_flags\nfloat32[12] control",
    "VehicleCommand": "uint64 timestamp\nfloat32 param1\nfloat32 param2\nfloat32 param3\nfloat32 param4\n"
                      "float64 param5\nfloat64 param6\nfloat32 param7\nuint32 command\nuint8 target_system\n"
                      "uint8 target_component\nuint8 source_system\nuint16 source_component\nuint8 confirmation\n"
                      "bool from_external",
    "VehicleCommandAck": "uint64 timestamp\nuint32 command\nuint8 result\nuint8 result_param1\n"
                         "int32 result_param2\nuint8 target_system\nuint16 target_component\nbool from_external",
    "VehicleStatus": "uint64 timestamp\nuint64 armed_time\nuint64 takeoff_time\nuint8 arming_state\n"
                     "uint8 latest_arming_reason\nuint8 latest_disarming_reason\nuint64 nav_state_timestamp\n"
                     "uint8 nav_state_user_intention\nuint8 nav_state\nuint8 executor_in_charge\n"
                     "uint32 valid_nav_states_mask\nuint32 can_set_nav_states_mask\nuint16 failure_detector_status\n"
                     "uint8 hil_state\nuint8 vehicle_type\nbool failsafe\nbool failsafe_and_user_took_over\n"
                     "uint8 failsafe_defer_state\nbool gcs_connection_lost\nuint8 gcs_connection_lost_counter\n"
                     "bool high_latency_data_link_lost\nbool is_vtol\nbool is_vtol_tailsitter\n"
                     "bool in_transition_mode\nbool in_transition_to_fw\nuint8 system_type\nuint8 system_id\n"
                     "uint8 component_id\nbool safety_button_available\nbool safety_off\nbool power_input_valid\n"
                     "bool usb_connected\nbool open_drone_id_system_present\nbool open_drone_id_system_healthy\n"
                     "bool parachute_system_present\nbool parachute_system_healthy\n"
                     "bool rc_calibration_in_progress\nbool calibration_enabled\nbool pre_flight_checks_pass",
    "VehicleOdometry": "uint64 timestamp\nuint64 timestamp_sample\nuint8 pose_frame\nfloat32[3] position\n"
                       "float32[4] q\nuint8 velocity_frame\nfloat32[3] velocity\nfloat32[3] angular_velocity\n"
                       "float32[3] position_variance\nfloat32[3] orientation_variance\n"
                       "float32[3] velocity_variance\nuint8 reset_counter\nint8 quality",
    "SensorCombined": "uint64 timestamp\nfloat32[3] gyro_rad\nuint32 gyro_integral_dt\n"
                      "int32 accelerometer_timestamp_relative\nfloat32[3] accelerometer_m_s2\n"
                      "uint32 accelerometer_integral_dt\nuint8 accelerometer_clipping\nuint8 gyro_clipping\n"
                      "uint8 accel_calibration_count\nuint8 gyro_calibration_count",
    "BatteryStatus": "uint64 timestamp\nbool connected\nfloat32 voltage_v\nfloat32 current_a\n"
                     "float32 current_average_a\nfloat32 discharged_mah\nfloat32 remaining\nfloat32 scale\n"
                     "float32 time_remaining_s\nfloat32 temperature\nuint8 cell_count\nuint8 source\n"
                     "uint8 priority\nuint16 capacity\nuint16 cycle_count\nuint16 average_time_to_empty\n"
                     "uint16 manufacture_date\nuint16 state_of_health\nuint16 max_error\nuint8 id\n"
                     "uint16 interface_error\nfloat32[14] voltage_cell_v\nfloat32 max_cell_voltage_delta\n"
                     "bool is_powering_off\nbool is_required\nuint8 warning\nuint16 faults\n"
                     "float32 full_charge_capacity_wh\nfloat32 remaining_capacity_wh\nuint16 over_discharge_count\n"
                     "float32 nominal_voltage\nfloat32 internal_resistance_estimate\nfloat32 ocv_estimate\n"
                     "float32 ocv_estimate_filtered\nfloat32 volt_based_soc_estimate\nfloat32 voltage_prediction\n"
                     "float32 prediction_error\nfloat32 estimation_covariance_norm",
    "VehicleLocalPosition": "uint64 timestamp\nuint64 timestamp_sample\nbool xy_valid\nbool z_valid\n"
                            "bool v_xy_valid\nbool v_z_valid\nfloat32 x\nfloat32 y\nfloat32 z\n"
                            "float32[2] delta_xy\nuint8 xy_reset_counter\nfloat32 delta_z\nuint8 z_reset_counter\n"
                            "float32 vx\nfloat32 vy\nfloat32 vz\nfloat32 z_deriv\nfloat32[2] delta_vxy\n"
                            "uint8 vxy_reset_counter\nfloat32 delta_vz\nuint8 vz_reset_counter\nfloat32 ax\n"
                            "float32 ay\nfloat32 az\nfloat32 heading\nfloat32 heading_var\nfloat32 unaided_heading\n"
                            "float32 delta_heading\nuint8 heading_reset_counter\nbool heading_good_for_control\n"
                            "float32 tilt_var\nbool xy_global\nbool z_global\nuint64 ref_timestamp\n"
                            "float64 ref_lat\nfloat64 ref_lon\nfloat32 ref_alt\nbool dist_bottom_valid\n"
                            "float32 dist_bottom\nfloat32 dist_bottom_var\nfloat32 delta_dist_bottom\n"
                            "uint8 dist_bottom_reset_counter\nuint8 dist_bottom_sensor_bitfield\nfloat32 eph\n"
                            "float32 epv\nfloat32 evh\nfloat32 evv\nbool dead_reckoning\nfloat32 vxy_max\n"
                            "float32 vz_max\nfloat32 hagl_min\nfloat32 hagl_max_z\nfloat32 hagl_max_xy",
}
PX4_V1_17_MESSAGE_VERSION = {"ActuatorMotors": 0, "VehicleCommand": 0, "VehicleCommandAck": 0, "VehicleOdometry": 0,
                             "VehicleStatus": 1, "BatteryStatus": 1, "VehicleLocalPosition": 1,
                             "OffboardControlMode": None, "SensorCombined": None}


def _parsed_fields(msg_text: str, name: str) -> list[tuple[str, str, int | None]]:
    _, fields = get_types_from_msg(msg_text, f"px4_msgs/msg/{name}")[f"px4_msgs/msg/{name}"]
    out = []
    for field_name, (node, detail) in fields:
        if node == Nodetype.ARRAY:
            (_, (elem, _)), length = detail
            out.append((field_name, elem, length))
        else:
            out.append((field_name, detail[0], None))
    return out


@pytest.mark.parametrize("spec", d.ALL_MESSAGES, ids=lambda s: s.name)
def test_definitions_match_px4_v1_17_text(spec):
    assert _parsed_fields(d.msg_text(spec), spec.name) == _parsed_fields(PX4_V1_17_FIELDS[spec.name], spec.name)
    assert spec.message_version == PX4_V1_17_MESSAGE_VERSION[spec.name]
    if spec.message_version is not None:
        assert spec.constant("MESSAGE_VERSION") == spec.message_version


def test_type_hash_ignores_constants_but_not_fields():
    """REP-2011: constants are not part of the hashed description; a field's name or size is."""
    no_constants = d.MessageSpec("ActuatorMotors", d.ACTUATOR_MOTORS.fields)
    assert rihs01(no_constants) == rihs01(d.ACTUATOR_MOTORS)
    fields = list(d.ACTUATOR_MOTORS.fields)
    fields[-1] = d.FieldSpec("control", "float32", 8)
    assert rihs01(d.MessageSpec("ActuatorMotors", tuple(fields))) != rihs01(d.ACTUATOR_MOTORS)


# --- rmw_zenoh keys, attachment, liveliness ------------------------------------------------------------


def test_topic_names_and_namespacing():
    ns = rz.vehicle_namespace(3)
    assert rz.topic_name(rz.ACTUATOR_MOTORS, ns) == "/px4_3/fmu/in/actuator_motors"
    assert rz.topic_name(rz.ACTUATOR_MOTORS) == "/fmu/in/actuator_motors"
    # PX4's zenoh module keeps the yaml names; uxrce_dds_client's spelling adds _v<N> for version > 0 only
    assert rz.topic_name(rz.VEHICLE_STATUS, ns) == "/px4_3/fmu/out/vehicle_status"
    assert rz.topic_name(rz.VEHICLE_STATUS, ns, version_suffix=True) == "/px4_3/fmu/out/vehicle_status_v1"
    assert rz.topic_name(rz.ACTUATOR_MOTORS, ns, version_suffix=True) == "/px4_3/fmu/in/actuator_motors"
    key = rz.data_key(rz.ACTUATOR_MOTORS, ns)
    assert key.startswith("0/px4_3/fmu/in/actuator_motors/px4_msgs::msg::dds_::ActuatorMotors_/RIHS01_")
    parsed = rz.parse_data_key(key)
    assert (parsed.domain_id, parsed.topic, parsed.dds_type_name) == (
        0, "/px4_3/fmu/in/actuator_motors", "px4_msgs::msg::dds_::ActuatorMotors_")
    assert parsed.type_hash == rihs01(d.ACTUATOR_MOTORS)
    for bad in ("px4/3", "3px4", "px4 3"):
        with pytest.raises(ValueError):
            rz.topic_name(rz.ACTUATOR_MOTORS, bad)
    with pytest.raises(ValueError):
        rz.data_key(rz.ACTUATOR_MOTORS, ns, domain_id=233)


def test_attachment_layout():
    gid = bytes(range(16))
    raw = rz.encode_attachment(rz.Attachment(sequence_number=-2, source_timestamp_ns=1_700_000_000_123_456_789,
                                             source_gid=gid))
    assert len(raw) == 33
    assert raw[:8] == (-2).to_bytes(8, "little", signed=True)
    assert raw[8:16] == (1_700_000_000_123_456_789).to_bytes(8, "little", signed=True)
    assert raw[16] == 16 and raw[17:] == gid
    assert rz.decode_attachment(raw) == rz.Attachment(-2, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError):
        rz.decode_attachment(raw[:-1])
    keyed = (b"\x0fsequence_number" + (5).to_bytes(8, "little") + b"\x10source_timestamp" + (6).to_bytes(8, "little")
             + b"\x0asource_gid\x10" + gid)            # the earlier rmw_zenoh layout, still decoded
    assert rz.decode_attachment(keyed) == rz.Attachment(5, 6, gid)
    with pytest.raises(ValueError, match="field name"):
        rz.decode_attachment(keyed.replace(b"source_gid", b"source_gie"))
    seq = rz.PublisherSequence(rz.unit_gid(4, "actuator_motors"))
    assert [rz.decode_attachment(seq.next(t)).sequence_number for t in (5, 6, 7)] == [1, 2, 3]


def test_liveliness_tokens_follow_design_md():
    node = rz.NodeIdentity(domain_id=2, session_id="8b20917502ee955ac4476e0266340d5c", node_name="px4_ab")
    assert rz.node_token(node) == "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/0/NN/%/%/px4_ab"
    token = rz.endpoint_token(node, 10, rz.VEHICLE_STATUS, "px4_3", publisher=True)
    assert token == ("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/px4_ab/%px4_3%fmu%out%vehicle_status/"
                     f"px4_msgs::msg::dds_::VehicleStatus_/{rihs01(d.VEHICLE_STATUS)}/::,7:,:,:,,")
    tokens = rz.unit_liveliness_tokens(node, "px4_3")
    assert len(tokens) == 1 + len(rz.UNIT_TOPICS)
    assert sum("/MS/" in t for t in tokens) == 3 and sum("/MP/" in t for t in tokens) == 6
    assert all(t.count("/") == tokens[1].count("/") for t in tokens[1:])


# --- the unit side: PX4's gating, keep-alive and commands, in simulated time --------------------------

SYS = 3
HOST_SYS, HOST_COMP = 255, 190


def _cmd(command: int, time_s: float, unit: Px4UnitInterface, target: int = SYS, **params):
    cmd = cdr.VehicleCommand(timestamp=int(time_s * 1e6), command=command, target_system=target,
                             target_component=1, source_system=HOST_SYS, source_component=HOST_COMP,
                             from_external=True, **params)
    return unit.on_vehicle_command(cmd, time_s)


def _arm(unit, t, arm=True):
    return _cmd(cdr.VehicleCommand.VEHICLE_CMD_COMPONENT_ARM_DISARM, t, unit, param1=1.0 if arm else 0.0)


def _set_mode(unit, t, main_mode=Px4MainMode.OFFBOARD):
    return _cmd(cdr.VehicleCommand.VEHICLE_CMD_DO_SET_MODE, t, unit, param1=1.0, param2=float(main_mode))


def _keepalive(unit, t, direct_actuator=True, **flags):
    unit.on_offboard_control_mode(cdr.OffboardControlMode(timestamp=int(t * 1e6), direct_actuator=direct_actuator,
                                                          **flags), t)


def _motors(unit, t, values):
    control = np.full(12, np.nan, dtype=np.float32)
    control[:len(values)] = values
    unit.on_actuator_motors(cdr.ActuatorMotors(timestamp=int(t * 1e6), control=control), t)


ACCEPTED = cdr.VehicleCommandAck.VEHICLE_CMD_RESULT_ACCEPTED
REJECTED = cdr.VehicleCommandAck.VEHICLE_CMD_RESULT_TEMPORARILY_REJECTED
OFFBOARD = cdr.VehicleStatus.NAVIGATION_STATE_OFFBOARD


def _flying_unit(**params) -> Px4UnitInterface:
    unit = Px4UnitInterface(Px4UnitParams(system_id=SYS, **params))
    _keepalive(unit, 0.0)
    _motors(unit, 0.0, [0.4, 0.5, 0.6, 0.7])
    assert _set_mode(unit, 0.01).result == ACCEPTED
    assert _arm(unit, 0.02).result == ACCEPTED
    return unit


def test_motors_run_only_when_armed_in_offboard_with_direct_actuator():
    unit = Px4UnitInterface(Px4UnitParams(system_id=SYS))
    _keepalive(unit, 0.0)
    _motors(unit, 0.0, [0.5] * 4)
    assert not unit.update(0.05).running.any()                  # disarmed, position mode
    assert _arm(unit, 0.1).result == ACCEPTED
    out = unit.update(0.15)
    assert out.armed and out.nav_state != OFFBOARD and not out.running.any()   # armed, not offboard
    assert _set_mode(unit, 0.2).result == ACCEPTED
    out = unit.update(0.25)
    assert out.nav_state == OFFBOARD and out.running.all() and np.allclose(out.thrust_fraction, 0.5)
    _keepalive(unit, 0.3, direct_actuator=False, position=True)   # offboard, but not the per-rotor path
    assert not unit.update(0.35).running.any()
    _keepalive(unit, 0.4)
    assert unit.update(0.45).running.all()
    assert _arm(unit, 0.5, arm=False).result == ACCEPTED
    assert not unit.update(0.55).running.any()


def test_nan_negative_and_out_of_range_controls():
    unit = _flying_unit()
    _motors(unit, 0.1, [np.nan, -0.2, 1.7, 0.25])
    out = unit.update(0.1)
    assert out.running.tolist() == [False, False, True, True]
    assert out.thrust_fraction.tolist() == [0.0, 0.0, 1.0, 0.25]
    reversible = cdr.ActuatorMotors(reversible_flags=0b0010,
                                    control=np.array([-0.2, -1.5, np.inf, 0.0] + [np.nan] * 8, dtype=np.float32))
    command, running = motor_commands(reversible, 4)
    assert running.tolist() == [False, True, False, True]
    assert command.tolist() == [0.0, -1.0, 0.0, 0.0]


def test_keepalive_loss_after_com_of_loss_t_then_fresh_arm_needed():
    unit = _flying_unit()
    last_keepalive_s = 0.5
    for t in np.arange(0.1, last_keepalive_s + 1e-9, 0.1):       # 10 Hz keep-alive, then silence
        _keepalive(unit, float(t))
    # Setpoints keep coming: PX4 times out the keep-alive, not ActuatorMotors.
    t = last_keepalive_s
    while t < last_keepalive_s + 0.999:
        t = round(t + 0.004, 6)
        _motors(unit, t, [0.6] * 4)
        out = unit.update(t)
        if t < last_keepalive_s + 1.0:
            assert out.running.all() and not out.failsafe, t
    out = unit.update(last_keepalive_s + 1.0)                    # COM_OF_LOSS_T = 1.0 s in simulated time
    assert out.failsafe and not out.armed and not out.running.any()
    assert out.nav_state == cdr.VehicleStatus.NAVIGATION_STATE_POSCTL
    kinds = [e.kind for e in unit.take_events()]
    assert kinds[-4:] == ["offboard_lost", "failsafe", "disarmed", "mode"]
    # The keep-alive and setpoints come back: offboard again, but the motors stay off until a fresh arm.
    _keepalive(unit, 2.0)
    _motors(unit, 2.0, [0.6] * 4)
    out = unit.update(2.01)
    assert out.nav_state == OFFBOARD and not out.failsafe and not out.armed and not out.running.any()
    assert _arm(unit, 2.02).result == ACCEPTED
    assert unit.update(2.03).running.all()


def test_arming_and_offboard_need_the_keepalive():
    unit = Px4UnitInterface(Px4UnitParams(system_id=SYS))
    assert _set_mode(unit, 0.0).result == REJECTED                # no offboard signal yet
    _keepalive(unit, 0.0, direct_actuator=False)                 # all flags false: no signal (PX4)
    assert _set_mode(unit, 0.1).result == REJECTED
    _keepalive(unit, 0.2)
    assert _set_mode(unit, 0.3).result == ACCEPTED
    assert _arm(unit, 1.3).result == REJECTED                     # keep-alive 1.1 s old: lost
    _keepalive(unit, 1.4)
    assert _arm(unit, 1.5).result == ACCEPTED


def test_command_acks_and_targeting():
    unit = Px4UnitInterface(Px4UnitParams(system_id=SYS))
    ack = _arm(unit, 0.0)
    assert (ack.command, ack.result, ack.target_system, ack.target_component, ack.timestamp) == (
        400, ACCEPTED, HOST_SYS, HOST_COMP, 0)
    assert _cmd(400, 0.1, unit, target=SYS + 1, param1=0.0) is None       # another unit's command
    assert unit.armed
    assert _cmd(400, 0.2, unit, target=0, param1=0.0).result == ACCEPTED  # broadcast
    assert not unit.armed
    assert _cmd(400, 0.3, unit, param1=2.0).result == cdr.VehicleCommandAck.VEHICLE_CMD_RESULT_UNSUPPORTED
    assert not unit.armed
    assert _cmd(400, 0.35, unit, param1=0.5).result == ACCEPTED and unit.armed   # lroundf(0.5) = 1: arm
    assert _arm(unit, 0.38, arm=False).result == ACCEPTED
    assert _cmd(cdr.VehicleCommand.VEHICLE_CMD_DO_FLIGHTTERMINATION, 0.4, unit, param1=1.0).result == \
        cdr.VehicleCommandAck.VEHICLE_CMD_RESULT_UNSUPPORTED
    assert _cmd(176, 0.5, unit, param1=0.0, param2=6.0).result == \
        cdr.VehicleCommandAck.VEHICLE_CMD_RESULT_UNSUPPORTED                # no custom-mode flag
    assert _set_mode(unit, 0.6, Px4MainMode.AUTO).result == REJECTED     # no onboard navigator here
    assert _set_mode(unit, 0.7, Px4MainMode.STABILIZED).result == ACCEPTED
    assert unit.nav_state == cdr.VehicleStatus.NAVIGATION_STATE_STAB


def test_terminate_action_latches_until_reset():
    unit = _flying_unit(offboard_loss_action=OffboardLossAction.TERMINATE)
    out = unit.update(1.0)
    assert out.failsafe and not out.armed and out.nav_state == cdr.VehicleStatus.NAVIGATION_STATE_TERMINATION
    _keepalive(unit, 1.1)
    assert _arm(unit, 1.2).result == cdr.VehicleCommandAck.VEHICLE_CMD_RESULT_DENIED
    assert unit.update(1.3).nav_state == cdr.VehicleStatus.NAVIGATION_STATE_TERMINATION
    unit.reset()
    _keepalive(unit, 2.0)
    assert _set_mode(unit, 2.1).result == ACCEPTED and _arm(unit, 2.2).result == ACCEPTED


def _recorded_stream() -> list[tuple[float, str, bytes, bytes]]:
    """A host's command stream as a run log would keep it: (arrival time, key, payload, attachment);
    a 250 Hz setpoint stream with a 10 Hz keep-alive that stops at 0.6 s."""
    ns, seq, stream = "px4_3", rz.PublisherSequence(bytes(range(16))), []

    def put(t, topic, msg):
        stream.append((t, rz.data_key(topic, ns), cdr.encode(msg), seq.next(int(t * 1e9))))

    put(0.0, rz.OFFBOARD_CONTROL_MODE, cdr.OffboardControlMode(direct_actuator=True))
    common = dict(target_system=SYS, target_component=1, source_system=HOST_SYS, source_component=HOST_COMP)
    put(0.001, rz.VEHICLE_COMMAND, cdr.VehicleCommand(command=176, param1=1.0, param2=6.0, **common))
    put(0.002, rz.VEHICLE_COMMAND, cdr.VehicleCommand(command=400, param1=1.0, **common))
    for k in range(1, 500):
        t = k * 0.004
        if k % 25 == 0 and k <= 150:                       # t <= 0.6 s
            put(t, rz.OFFBOARD_CONTROL_MODE, cdr.OffboardControlMode(timestamp=int(t * 1e6), direct_actuator=True))
        control = np.full(12, np.nan, dtype=np.float32)
        control[:4] = 0.5 + 0.4 * np.sin(t * np.array([1.0, 2.0, 3.0, 4.0]))
        put(t, rz.ACTUATOR_MOTORS, cdr.ActuatorMotors(timestamp=int(t * 1e6), control=control))
    return stream


def _replay(stream, **params) -> bytes:
    endpoint, unit = Px4UnitEndpoint(SYS), Px4UnitInterface(Px4UnitParams(system_id=SYS, **params))
    outputs = []
    for t, key, payload, attachment in stream:
        got = endpoint.decode(key, payload, attachment)
        if got.topic is rz.OFFBOARD_CONTROL_MODE:
            unit.on_offboard_control_mode(got.message, t)
        elif got.topic is rz.ACTUATOR_MOTORS:
            unit.on_actuator_motors(got.message, t)
        else:
            unit.on_vehicle_command(got.message, t)
        out = unit.update(t)
        outputs.append(np.concatenate([[t], out.thrust_fraction, out.running]).tobytes())
    return b"".join(outputs)


def test_replayed_command_stream_reproduces_motor_outputs_byte_for_byte():
    stream = _recorded_stream()
    first = _replay(stream)
    assert first == _replay(stream)
    rows = np.frombuffer(first, dtype=np.float64).reshape(-1, 9)
    running_until = rows[rows[:, 5:].all(axis=1), 0].max()
    assert abs(running_until - (0.6 + 1.0 - 0.004)) < 1e-9      # last step before COM_OF_LOSS_T ran out
    assert not rows[rows[:, 0] >= 1.6, 5:].any()
    # A unit with the test switch that breaks its keep-alive keeps the motors running: the harness's red case.
    broken = np.frombuffer(_replay(stream, keepalive_timeout_enabled=False), dtype=np.float64).reshape(-1, 9)
    assert broken[broken[:, 0] >= 1.6, 5:].all()


def test_vehicle_status_reflects_state_and_round_trips():
    unit = _flying_unit()
    status = cdr.decode("VehicleStatus", cdr.encode(unit.vehicle_status(0.5)))
    assert status.arming_state == cdr.VehicleStatus.ARMING_STATE_ARMED and status.armed_time == 20_000
    assert status.nav_state == OFFBOARD and status.nav_state_user_intention == OFFBOARD
    assert (status.system_id, status.timestamp, status.failsafe) == (SYS, 500_000, False)
    status = unit.vehicle_status(1.5)
    assert status.arming_state == cdr.VehicleStatus.ARMING_STATE_DISARMED and status.failsafe


def test_endpoint_keys_decode_and_reordering():
    endpoint = Px4UnitEndpoint(5)
    assert set(t.base_name for t in endpoint.subscribe_keys().values()) == {
        "/fmu/in/offboard_control_mode", "/fmu/in/actuator_motors", "/fmu/in/vehicle_command"}
    assert all(k.startswith("0/px4_5/fmu/out/") for k in endpoint.publish_keys())
    seq = rz.PublisherSequence(bytes(16))
    key = rz.data_key(rz.ACTUATOR_MOTORS, "px4_5")
    first, second = seq.next(1), seq.next(2)
    payload = cdr.encode(cdr.ActuatorMotors(timestamp=7))
    assert endpoint.decode(key, payload, second).message.timestamp == 7
    endpoint.decode(key, payload, first)                   # an older sample arrives late: kept, counted
    assert endpoint.reordered == 1
    with pytest.raises(ValueError, match="not an inbound topic"):
        endpoint.decode(rz.data_key(rz.ACTUATOR_MOTORS, "px4_6"), payload, None)   # another unit's
    wrong_hash = key.rsplit("/", 1)[0] + "/RIHS01_" + "0" * 64
    with pytest.raises(ValueError, match="not an inbound topic"):
        endpoint.decode(wrong_hash, payload, None)
    with pytest.raises(ValueError, match="not published"):
        endpoint.encode(rz.ACTUATOR_MOTORS, cdr.ActuatorMotors(), 0.0)
    key, _, attachment = endpoint.encode(rz.VEHICLE_STATUS, cdr.VehicleStatus(), 1.25)
    assert rz.decode_attachment(attachment).source_timestamp_ns == 1_250_000_000
    assert key == rz.data_key(rz.VEHICLE_STATUS, "px4_5")
    assert Px4UnitEndpoint(5, version_suffix=True).key(rz.VEHICLE_STATUS).startswith(
        "0/px4_5/fmu/out/vehicle_status_v1/")


def test_telemetry_builders_carry_si_values():
    odom = cdr.decode("VehicleOdometry", cdr.encode(telemetry.vehicle_odometry(
        2.5, [1.0, -2.0, -3.0], [0.5, 0.5, 0.5, 0.5], [0.1, 0.2, -0.3], [0.01, 0.02, 0.03])))
    assert odom.timestamp == 2_500_000 and odom.pose_frame == cdr.VehicleOdometry.POSE_FRAME_NED
    assert np.allclose(odom.position, [1.0, -2.0, -3.0]) and np.allclose(odom.q, [0.5] * 4)
    imu = telemetry.sensor_combined(1.0, [0.1, 0.0, 0.0], [0.0, 0.0, -9.81], integral_dt_s=0.004)
    assert imu.gyro_integral_dt == 4000 and np.isclose(imu.accelerometer_m_s2[2], -9.81)
    lpos = telemetry.vehicle_local_position(1.0, [1, 2, -3], [0.5, 0, 0], [0, 0, 0], 0.25,
                                            ref_lat_deg=47.4, ref_lon_deg=8.5, ref_alt_m=400.0)
    assert (lpos.x, lpos.z, lpos.vx, lpos.xy_global) == (1.0, -3.0, 0.5, True)
    battery = telemetry.battery_status(1.0, 15.2, 12.0, 0.8, cell_count=4)
    assert np.allclose(battery.voltage_cell_v[:4], 3.8) and np.isnan(battery.voltage_cell_v[4])


# --- over real zenoh sessions on loopback ---------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _loopback_config(listen: list[str], connect: list[str]) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps("peer"))
    cfg.insert_json5("listen/endpoints", json.dumps(listen))
    cfg.insert_json5("connect/endpoints", json.dumps(connect))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return cfg


def _recv(subscriber, deadline_s: float = 10.0):
    """The next sample; the deadline only stops a hung test, it asserts nothing about speed."""
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        sample = subscriber.try_recv()
        if sample is not None:
            return sample
        time.sleep(0.005)
    raise AssertionError("no sample before the deadline")


class _IndependentHost:
    """An off-board computer that knows only rmw_zenoh's conventions (design.md) and PX4's message text:
    payloads and type hashes from rosbags fed PX4_V1_17_FIELDS, keys and attachments written out here.
    No project code."""

    def __init__(self, session: zenoh.Session, namespace: str):
        self.session, self.ns = session, namespace
        self.store = get_typestore(Stores.EMPTY)
        for name, text in PX4_V1_17_FIELDS.items():
            self.store.register(get_types_from_msg(text, f"px4_msgs/msg/{name}"))
        self.gid = bytes(range(100, 116))
        self.sequence = 0
        self.publishers: dict[str, zenoh.Publisher] = {}

    def key(self, topic: str, type_name: str) -> str:
        type_hash = self.store.hash_rihs01(f"px4_msgs/msg/{type_name}")
        return f"0/{self.ns}/{topic}/px4_msgs::msg::dds_::{type_name}_/{type_hash}"

    def send(self, topic: str, type_name: str, sim_time_s: float, **fields) -> None:
        key = self.key(topic, type_name)
        if key not in self.publishers:
            self.publishers[key] = self.session.declare_publisher(key)
        message = self.store.types[f"px4_msgs/msg/{type_name}"](**fields)
        payload = bytes(self.store.serialize_cdr(message, f"px4_msgs/msg/{type_name}"))
        self.sequence += 1
        attachment = struct.pack("<qqB16s", self.sequence, int(sim_time_s * 1e9), 16, self.gid)
        self.publishers[key].put(payload, attachment=attachment)

    def decode(self, sample, type_name: str):
        return self.store.deserialize_cdr(sample.payload.to_bytes(), f"px4_msgs/msg/{type_name}")


def _defaults(type_name: str) -> dict:
    """Every field of a PX4 message at zero (rosbags wants them all)."""
    out = {}
    for name, kind, length in _parsed_fields(PX4_V1_17_FIELDS[type_name], type_name):
        dtype = np.dtype(bool if kind == "bool" else kind)
        out[name] = np.zeros(length, dtype=dtype) if length else (False if kind == "bool" else dtype.type(0).item())
    return out


def test_arm_and_drive_a_unit_over_zenoh_with_rmw_keys():
    """An independent host (rosbags + design.md, no project code) arms a unit and streams ActuatorMotors
    over loopback zenoh. The unit side subscribes by the rmw_zenoh pattern (any vehicle namespace, exact
    type and hash), decodes through Px4UnitEndpoint, feeds Px4UnitInterface and answers with
    VehicleCommandAck and VehicleStatus; the host discovers it through its liveliness tokens."""
    port = _free_port()
    unit_session = zenoh.open(_loopback_config([f"tcp/127.0.0.1:{port}"], []))
    host_session = zenoh.open(_loopback_config([], [f"tcp/127.0.0.1:{port}"]))
    try:
        ns = rz.vehicle_namespace(SYS)
        unit = Px4UnitInterface(Px4UnitParams(system_id=SYS))
        endpoint = Px4UnitEndpoint(SYS)
        tokens = [unit_session.liveliness().declare_token(t)
                  for t in endpoint.liveliness_tokens(str(unit_session.zid()))]
        inbound = {t.spec.name: unit_session.declare_subscriber(
            f"0/*/{t.base_name.lstrip('/')}/{t.spec.dds_type_name}/{rihs01(t.spec)}")
            for t in endpoint.subscribe_keys().values()}
        unit_pubs = {key: unit_session.declare_publisher(key) for key in endpoint.publish_keys()}

        host = _IndependentHost(host_session, ns)
        ack_sub = host_session.declare_subscriber(host.key("fmu/out/vehicle_command_ack", "VehicleCommandAck"))
        status_sub = host_session.declare_subscriber(host.key("fmu/out/vehicle_status", "VehicleStatus"))
        # Discovery as rmw_zenoh does it: the unit's node and a subscription on actuator_motors.
        node_name = f"px4_{rz.unit_gid(SYS).hex()}"
        motors_token_tail = (f"/MS/%/%/{node_name}/%{ns}%fmu%in%actuator_motors/px4_msgs::msg::dds_::ActuatorMotors_/"
                             f"{host.store.hash_rihs01('px4_msgs/msg/ActuatorMotors')}/::,7:,:,:,,")
        seen: set[str] = set()
        end = time.monotonic() + 10.0
        while len(seen) < len(tokens) and time.monotonic() < end:
            seen = {str(r.ok.key_expr) for r in host_session.liveliness().get("@ros2_lv/0/**") if r.ok}
            time.sleep(0.05)
        assert f"@ros2_lv/0/{unit_session.zid()}/0/0/NN/%/%/{node_name}" in seen
        assert any(t.endswith(motors_token_tail) for t in seen)
        assert len(seen) == 1 + len(rz.UNIT_TOPICS)

        def unit_take(name: str, sim_time_s: float):
            sample = _recv(inbound[name])
            got = endpoint.decode(str(sample.key_expr), sample.payload.to_bytes(), sample.attachment.to_bytes())
            assert got.attachment.source_gid == host.gid
            assert got.attachment.source_timestamp_ns == int(sim_time_s * 1e9)
            return got

        def unit_publish(topic, msg, sim_time_s: float) -> None:
            key, payload, attachment = endpoint.encode(topic, msg, sim_time_s)
            unit_pubs[key].put(payload, attachment=attachment)

        def round_trip_command(sim_time_s: float, **fields):
            values = _defaults("VehicleCommand") | dict(
                timestamp=int(sim_time_s * 1e6), target_system=SYS, target_component=1, source_system=HOST_SYS,
                source_component=HOST_COMP, from_external=True) | fields
            host.send("fmu/in/vehicle_command", "VehicleCommand", sim_time_s, **values)
            ack = unit.on_vehicle_command(unit_take("VehicleCommand", sim_time_s).message, sim_time_s)
            unit_publish(rz.VEHICLE_COMMAND_ACK, ack, sim_time_s)
            sample = _recv(ack_sub)
            assert struct.unpack("<qqB16s", sample.attachment.to_bytes())[3] == rz.unit_gid(
                SYS, rz.VEHICLE_COMMAND_ACK.base_name)
            return host.decode(sample, "VehicleCommandAck")

        host.send("fmu/in/offboard_control_mode", "OffboardControlMode", 0.0,
                  **(_defaults("OffboardControlMode") | dict(direct_actuator=True)))
        keepalive = unit_take("OffboardControlMode", 0.0)
        assert keepalive.attachment.sequence_number == 1
        unit.on_offboard_control_mode(keepalive.message, 0.0)
        ack = round_trip_command(0.01, command=176, param1=np.float32(1.0), param2=np.float32(6.0))
        assert (ack.command, ack.result, ack.target_system) == (176, ACCEPTED, HOST_SYS)
        ack = round_trip_command(0.02, command=400, param1=np.float32(1.0))
        assert (ack.command, ack.result) == (400, ACCEPTED)

        control = np.full(12, np.nan, dtype=np.float32)
        control[:4] = [0.31, 0.42, np.nan, 0.64]
        host.send("fmu/in/actuator_motors", "ActuatorMotors", 0.03,
                  **(_defaults("ActuatorMotors") | dict(timestamp=30_000, timestamp_sample=29_000, control=control)))
        unit.on_actuator_motors(unit_take("ActuatorMotors", 0.03).message, 0.03)
        out = unit.update(0.03)
        assert out.running.tolist() == [True, True, False, True]
        assert np.allclose(out.thrust_fraction, [0.31, 0.42, 0.0, 0.64], atol=1e-6)

        unit_publish(rz.VEHICLE_STATUS, unit.vehicle_status(0.04), 0.04)
        status = host.decode(_recv(status_sub), "VehicleStatus")
        assert (status.arming_state, status.nav_state, status.system_id) == (2, 14, SYS)  # armed, offboard
        assert endpoint.reordered == 0
        del tokens
    finally:
        host_session.close()
        unit_session.close()
