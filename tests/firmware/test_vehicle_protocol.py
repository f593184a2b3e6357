"""The sans-IO unit vehicle, driven with real MAVLink bytes (pymavlink encoders) and a JSBSim body."""

from __future__ import annotations

import hashlib
import math
import struct

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.params import decode_value
from mars_link.mavlink.signing import enable_outgoing_signing
from firmware_models.vehicle import (
    LINK_API,
    LINK_COORDINATOR,
    LINK_GCS,
    LINK_HIL,
    Vehicle,
    VehicleConfig,
)
from mars_link.core.assembly import AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.core.messages import SensorPacket
from mars_link.core.state import ImuSample, RigidBodyState
from mars_link.mavlink.wire import sensor_packet_messages
from sitl.physics import JsbsimBody

NAN = math.nan
KEY = hashlib.sha256(b"protocol test key").digest()
T0 = 1.7e9  # a Unix wall time


class Client:
    """A peer on one link: packs with its own ids (signed if given a key), decodes the vehicle's output."""

    def __init__(self, vehicle: Vehicle, link: str, sysid: int = 245, compid: int = 190, key: bytes | None = None):
        self.v, self.link = vehicle, link
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if key is not None:
            enable_outgoing_signing(self.mav, key, 5, T0)
        self.dec = mavlink.MAVLink(None, 1, 1)

    def decode(self, out, link: str | None = None) -> list:
        msgs = []
        for o in out:
            if o.link == (link or self.link):
                msgs += self.dec.parse_buffer(o.data) or []
        return msgs

    def send(self, msg, wall: float = T0) -> list:
        return self.decode(self.v.handle(msg.pack(self.mav), wall, self.link))

    def command(self, cmd: int, *params: float, wall: float = T0, target: int = 1) -> list:
        p = list(params) + [NAN] * (7 - len(params))
        return self.send(mavlink.MAVLink_command_long_message(target, 1, cmd, 0, *p), wall)


def _ack(msgs, cmd: int) -> int:
    acks = [m.result for m in msgs if m.get_type() == "COMMAND_ACK" and m.command == cmd]
    assert len(acks) == 1, msgs
    return acks[0]


def _rest() -> RigidBodyState:
    return RigidBodyState(0.0, np.array([0.0, 0.0, -0.05]), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3),
                          on_ground=True)


def _vehicle(**kw) -> Vehicle:
    v = Vehicle(VehicleConfig(unit_id=1, **kw), T0)
    v.set_state(_rest())
    v.tick(T0, 0.0)
    return v


class Flight:
    """Vehicle + 1x1 JSBSim body stepped in lockstep (wall time advances with sim time)."""

    def __init__(self, v: Vehicle) -> None:
        self.v = v
        self.body = JsbsimBody(AssemblyModel.from_layout(["X"], v.vehicle), 500.0)
        v.set_state(self.body.state())
        self.t = 0.0
        self.out: list = []

    @property
    def wall(self) -> float:
        return T0 + self.t

    def run(self, seconds: float, each=None) -> None:
        for _ in range(int(round(seconds * 100))):
            if each is not None:
                each(self)
            self.out = self.v.tick(self.wall, self.t)
            for _ in range(5):
                self.body.set_rotor_thrusts(self.v.step_motors(0.002))
                self.body.step(1)
            self.t = self.body.t_s
            self.v.set_state(self.body.state())

    @property
    def pos(self) -> np.ndarray:
        return self.body.state().position_ned_m


# ----------------------------------------------------------------------------- identity, streams
def test_heartbeat_identity_and_wall_clock_rate_with_the_simulation_paused() -> None:
    v = _vehicle()
    gcs = Client(v, LINK_GCS)
    beats = {LINK_GCS: [], LINK_API: [], LINK_COORDINATOR: []}
    for k in range(1, 501):  # 5 s of wall time at 100 Hz, sim time frozen at 0
        out = v.tick(T0 + k * 0.01, 0.0)
        for link in beats:
            beats[link] += [m for m in gcs.decode(out, link) if m.get_type() == "HEARTBEAT"]
    assert len(beats[LINK_GCS]) == len(beats[LINK_API]) == 5
    assert beats[LINK_COORDINATOR] == []  # the coordinator link carries no telemetry
    hb = beats[LINK_GCS][-1]
    assert (hb.type, hb.autopilot) == (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4)
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.custom_mode == (4 << 16) | (3 << 24)  # AUTO.LOITER = Hold, PX4 encoding


def test_default_streams_rates_and_message_interval_control() -> None:
    v = _vehicle()
    gcs = Client(v, LINK_GCS)

    def counts(seconds: float, start: float) -> dict:
        c: dict = {}
        for k in range(int(seconds * 100)):
            for m in gcs.decode(v.tick(start + k * 0.01, 0.0)):
                c[m.get_type()] = c.get(m.get_type(), 0) + 1
        return c

    c = counts(4.0, T0 + 1.0)
    expected = {"SYS_STATUS": 4, "EXTENDED_SYS_STATE": 8, "ATTITUDE": 80, "ATTITUDE_QUATERNION": 80,
                "LOCAL_POSITION_NED": 80, "GLOBAL_POSITION_INT": 80, "GPS_RAW_INT": 20, "BATTERY_STATUS": 4,
                "HOME_POSITION": 2, "HIGHRES_IMU": 40, "ACTUATOR_OUTPUT_STATUS": 40, "HEARTBEAT": 4}
    for name, n in expected.items():
        assert abs(c.get(name, 0) - n) <= max(1, 0.05 * n), (name, c.get(name))
    wall = T0 + 5.0
    assert _ack(gcs.command(511, 32, 100_000, wall=wall), 511) == mavlink.MAV_RESULT_ACCEPTED  # LPN at 10 Hz
    assert _ack(gcs.command(511, 30, -1, wall=wall), 511) == mavlink.MAV_RESULT_ACCEPTED  # ATTITUDE off
    assert _ack(gcs.command(511, 999, 1000, wall=wall), 511) == mavlink.MAV_RESULT_DENIED
    c = counts(2.0, wall)
    assert abs(c["LOCAL_POSITION_NED"] - 20) <= 1 and "ATTITUDE" not in c
    interval = [m for m in gcs.command(510, 32, wall=wall) if m.get_type() == "MESSAGE_INTERVAL"]
    assert interval[0].interval_us == 100_000


def test_request_message_answers_and_refusals() -> None:
    v = _vehicle()
    gcs = Client(v, LINK_GCS)
    msgs = gcs.command(512, 148)
    assert [m.get_type() for m in msgs] == ["COMMAND_ACK", "AUTOPILOT_VERSION"]
    caps = msgs[1].capabilities
    for bit in ("MAVLINK2", "MISSION_INT", "COMMAND_INT", "PARAM_ENCODE_BYTEWISE", "MISSION_FENCE", "MISSION_RALLY"):
        assert caps & getattr(mavlink, f"MAV_PROTOCOL_CAPABILITY_{bit}"), bit
    assert msgs[0].target_system == 245 and msgs[0].target_component == 190
    legacy = gcs.command(520, 1)
    assert _ack(legacy, 520) == 0 and legacy[1].get_type() == "AUTOPILOT_VERSION"
    home = gcs.command(512, 242)
    assert _ack(home, 512) == 0 and home[1].get_type() == "HOME_POSITION"
    for refused in (300, 435, 397, 395):  # PROTOCOL_VERSION, AVAILABLE_MODES, COMPONENT_METADATA/INFORMATION
        assert _ack(gcs.command(512, refused), 512) == mavlink.MAV_RESULT_UNSUPPORTED
    assert _ack(gcs.command(519), 519) == mavlink.MAV_RESULT_UNSUPPORTED  # REQUEST_PROTOCOL_VERSION
    assert _ack(gcs.command(31000), 31000) == mavlink.MAV_RESULT_UNSUPPORTED  # unknown command


def test_identical_resends_are_acked_but_executed_once() -> None:
    v = _vehicle()
    api = Client(v, LINK_API)
    results = [_ack(api.command(400, 1, wall=T0 + 0.5 * k), 400) for k in range(4)]
    assert results == [0, 0, 0, 0] and v.armed and v.stats["command_duplicate"] == 3
    assert _ack(api.command(400, 0, wall=T0 + 2.1), 400) == 0 and not v.armed
    assert _ack(api.command(400, 1, wall=T0 + 2.2), 400) == 0 and v.armed  # a new arm, not a resend


def test_commands_for_other_systems_or_components_are_dropped_without_reply() -> None:
    v = _vehicle()
    gcs = Client(v, LINK_GCS)
    assert gcs.command(400, 1, target=2) == []
    assert gcs.send(mavlink.MAVLink_command_long_message(1, 50, 400, 0, 1, 0, 0, 0, 0, 0, 0)) == []
    assert gcs.command(400, 1, target=0) == []  # no broadcast arming
    assert not v.armed and v.drop_counts()["wrong_target"] == 3


# ----------------------------------------------------------------------------- flight through the protocol
def test_arm_takeoff_offboard_watchdog_land_and_auto_disarm() -> None:
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    assert _ack(api.command(22, wall=f.wall), 22) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # not armed
    assert _ack(api.command(400, 1, wall=f.wall), 400) == 0
    assert _ack(api.command(22, wall=f.wall), 22) == 0  # NaN altitude: MIS_TAKEOFF_ALT (2 m)
    assert v.custom_mode == (4 << 16) | (2 << 24)
    f.run(7.0)
    assert v.mode == (4, 3)  # Hold after takeoff
    assert abs(-f.pos[2] - (0.05 + 2.0)) < 0.05
    # OFFBOARD needs a live setpoint stream
    assert _ack(api.command(176, 129, 6, 0, wall=f.wall), 176) == mavlink.MAV_RESULT_DENIED
    target = f.pos + np.array([1.0, 0.0, 0.0])

    streaming = [True]

    def setpoint(fl):
        if streaming[0]:  # a 20 Hz stream, like MAVSDK's
            if round(fl.t * 100) % 5 == 0:
                api.send(mavlink.MAVLink_set_position_target_local_ned_message(
                    0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0x09F8, *target, 0, 0, 0, 0, 0, 0, 0.0, 0.0), fl.wall)

    f.run(0.1, setpoint)
    assert _ack(api.command(176, 129, 6, 0, wall=f.wall), 176) == 0
    assert v.custom_mode == 6 << 16
    f.run(5.8, setpoint)
    assert np.linalg.norm(f.pos - target) < 0.05
    assert v.mode == (6, 0)
    streaming[0] = False
    f.run(0.9)
    assert v.mode == (6, 0)  # COM_OF_LOSS_T = 1 s of wall time
    f.run(0.2)
    assert v.mode == (4, 3) and v.stats["offboard_loss"] == 1
    assert _ack(api.command(21, wall=f.wall), 21) == 0
    f.run(5.0)
    assert v.landed and v.armed and f.pos[2] > -0.06
    f.run(2.2)  # COM_DISARM_LAND = 2 s
    assert not v.armed


def _airborne(seconds: float) -> tuple[Vehicle, Flight, Client]:
    """Armed and taken off (MIS_TAKEOFF_ALT) through the api link, flown for `seconds`."""
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    api.command(400, 1, wall=f.wall)
    api.command(22, wall=f.wall)
    f.run(seconds)
    return v, f, api


def test_disarm_in_flight_is_refused_unless_forced() -> None:
    v, f, api = _airborne(3.0)
    assert _ack(api.command(400, 0, wall=f.wall), 400) == mavlink.MAV_RESULT_DENIED and v.armed
    assert _ack(api.command(400, 0, 21196, wall=f.wall + 2), 400) == 0 and not v.armed
    f.run(0.4)
    assert f.body.state().velocity_ned_mps[2] > 3.5  # free fall: the motors really stopped


def test_inject_failure_reaches_the_motor_model_only() -> None:
    v = _vehicle(params={"SYS_FAILURE_EN": 0})
    api = Client(v, LINK_API)
    assert _ack(api.command(420, 101, 1, 2), 420) == mavlink.MAV_RESULT_DENIED
    pv = Client(v, LINK_API)
    pv.send(mavlink.MAVLink_param_set_message(1, 1, b"SYS_FAILURE_EN", struct.unpack("<f", struct.pack("<i", 1))[0],
                                              mavlink.MAV_PARAM_TYPE_INT32))
    assert _ack(api.command(420, 101, 1, 2, wall=T0 + 2), 420) == 0
    np.testing.assert_array_equal(v.motors.eta, [1, 0, 1, 1])
    assert _ack(api.command(420, 101, 5, 0, wall=T0 + 4), 420) == 0  # SLOW on all motors
    np.testing.assert_array_equal(v.motors.eta, [0.5] * 4)
    assert _ack(api.command(420, 101, 0, 0, wall=T0 + 6), 420) == 0
    np.testing.assert_array_equal(v.motors.eta, [1.0] * 4)
    assert _ack(api.command(420, 101, 2, 1, wall=T0 + 8), 420) == mavlink.MAV_RESULT_UNSUPPORTED  # STUCK
    assert _ack(api.command(420, 2, 1, 0, wall=T0 + 10), 420) == mavlink.MAV_RESULT_UNSUPPORTED  # no magnetometer
    assert _ack(api.command(420, 101, 1, 7, wall=T0 + 12), 420) == mavlink.MAV_RESULT_DENIED  # motor 7
    # motor outputs as reported are commands, not the injected truth
    api.command(420, 101, 1, 1, wall=T0 + 14)
    v.armed, v.motor_commands_n = True, np.full(4, 1.0)
    aos = [m for m in api.decode(v.tick(T0 + 20, 0.0)) if m.get_type() == "ACTUATOR_OUTPUT_STATUS"]
    assert aos and aos[0].actuator[0] == aos[0].actuator[1] > 0


# ----------------------------------------------------------------------------- parameters, missions, services
def test_parameter_protocol() -> None:
    v = _vehicle()
    gcs = Client(v, LINK_GCS)
    values = gcs.send(mavlink.MAVLink_param_request_list_message(1, 1))
    names = [m.param_id for m in values]
    assert [m.param_index for m in values] == list(range(len(values))) and len(set(names)) == len(names)
    assert all(m.param_count == len(values) for m in values)
    by_name = {m.param_id: m for m in values}
    assert by_name["MIS_TAKEOFF_ALT"].param_value == pytest.approx(2.0)
    fe = by_name["SYS_FAILURE_EN"]
    assert fe.param_type == mavlink.MAV_PARAM_TYPE_INT32 and decode_value(fe.param_value, fe.param_type) == 1
    again = gcs.send(mavlink.MAVLink_param_request_list_message(1, 1))
    assert [m.param_id for m in again] == names  # stable order
    one = gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"", names.index("MIS_TAKEOFF_ALT")))
    assert one[0].param_id == "MIS_TAKEOFF_ALT"
    assert gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"_HASH_CHECK", -1)) == []
    set_ok = gcs.send(mavlink.MAVLink_param_set_message(1, 1, b"MIS_TAKEOFF_ALT", 3.5, mavlink.MAV_PARAM_TYPE_REAL32))
    assert set_ok[0].param_value == pytest.approx(3.5) and v.params["MIS_TAKEOFF_ALT"] == 3.5
    refused = gcs.send(mavlink.MAVLink_param_set_message(1, 1, b"MIS_TAKEOFF_ALT", 1e6, mavlink.MAV_PARAM_TYPE_REAL32))
    assert refused[0].param_value == pytest.approx(3.5)
    ro = gcs.send(mavlink.MAVLink_param_set_message(1, 1, b"MAV_SYS_ID", struct.unpack("<f", struct.pack("<i", 9))[0],
                                                    mavlink.MAV_PARAM_TYPE_INT32))
    assert ro[0].get_type() == "PARAM_ERROR" and ro[0].error == mavlink.MAV_PARAM_ERROR_READ_ONLY
    assert decode_value(ro[1].param_value, ro[1].param_type) == 1 and v.params["MAV_SYS_ID"] == 1
    assert gcs.send(mavlink.MAVLink_param_set_message(1, 1, b"MIS_TAKEOFF_ALT", NAN, 9))[0].param_value == 3.5
    assert v.drop_counts()["param_rejected"] == 3


def test_empty_mission_fence_and_rally_lists() -> None:
    v = _vehicle()
    gcs = Client(v, LINK_GCS)
    for kind in (0, 1, 2):
        count = gcs.send(mavlink.MAVLink_mission_request_list_message(1, 1, kind))
        assert [(m.get_type(), m.count, m.mission_type) for m in count] == [("MISSION_COUNT", 0, kind)]
        ack = gcs.send(mavlink.MAVLink_mission_count_message(1, 1, 0, kind))
        assert (ack[0].type, ack[0].mission_type) == (mavlink.MAV_MISSION_ACCEPTED, kind)
        ack = gcs.send(mavlink.MAVLink_mission_clear_all_message(1, 1, kind))
        assert ack[0].type == mavlink.MAV_MISSION_ACCEPTED
    # a non-empty upload is asked for item by item (tests/firmware/test_mission_protocol.py); an oversized one is refused
    assert gcs.send(mavlink.MAVLink_mission_count_message(1, 1, 3, 0))[0].get_type() == "MISSION_REQUEST_INT"
    assert gcs.send(mavlink.MAVLink_mission_count_message(1, 1, 5000, 0))[0].type == mavlink.MAV_MISSION_NO_SPACE
    assert gcs.send(mavlink.MAVLink_mission_request_int_message(1, 1, 0, 0))[0].type == mavlink.MAV_MISSION_INVALID_SEQUENCE


def test_ping_timesync_and_ftp_nak() -> None:
    v = _vehicle()
    gcs = Client(v, LINK_GCS)
    pong = gcs.send(mavlink.MAVLink_ping_message(123456, 7, 0, 0))
    assert (pong[0].time_usec, pong[0].seq, pong[0].target_system, pong[0].target_component) == (123456, 7, 245, 190)
    assert gcs.send(mavlink.MAVLink_ping_message(1, 1, 245, 190)) == []  # a reply to someone's ping
    ts = gcs.send(mavlink.MAVLink_timesync_message(0, 999))
    assert ts[0].ts1 == 999 and ts[0].tc1 == int(T0 * 1e9)
    payload = struct.pack("<HBBBBBBI", 41, 0, 4, 12, 0, 0, 0, 0) + b"@PARAM/param.pck" + bytes(251 - 12 - 16)
    nak = gcs.send(mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, list(payload)))
    seq, session, opcode, size, req = struct.unpack("<HBBBB", bytes(nak[0].payload[:6]))
    assert (seq, opcode, size, req, nak[0].payload[12]) == (42, 129, 1, 4, 10)


def test_bad_configuration_is_a_user_error() -> None:
    with pytest.raises(UserInputError, match="unit id"):
        Vehicle(VehicleConfig(unit_id=0))
    with pytest.raises(UserInputError, match="collides"):
        Vehicle(VehicleConfig(unit_id=201))
    with pytest.raises(UserInputError, match="MIS_TAKEOFF_ALT"):
        Vehicle(VehicleConfig(params={"MIS_TAKEOFF_ALT": -1}))
    with pytest.raises(UserInputError, match="unknown parameter"):
        Vehicle(VehicleConfig(params={"NOPE": 1}))


# ----------------------------------------------------------------------------- coordinator rotor commands
def _rotor_cmd(t_usec: int, controls, target: int = 1) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_set_actuator_control_target_message(t_usec, 0, target, 1, list(controls) + [0.0] * 4)


def test_signed_rotor_commands_drive_the_motors_and_bad_ones_are_counted() -> None:
    v = _vehicle(signing_key=KEY)
    coord = Client(v, LINK_COORDINATOR, sysid=201, compid=1, key=KEY)
    assert _ack(coord.command(400, 1), 400) == 0
    hover = 0.52 * 9.80665 / 4 / v.full_scale_n
    coord.send(_rotor_cmd(10_000, [hover] * 4))
    assert _ack(coord.command(176, 129, 6, 0), 176) == 0  # OFFBOARD with a live rotor stream
    v.tick(T0 + 0.01, 0.01)
    assert v.source == "coordinator"
    np.testing.assert_allclose(v.motor_commands_n, hover * v.full_scale_n, rtol=1e-6)
    before = v.intake.accepted
    coord.send(_rotor_cmd(20_000, [NAN, 0, 0, 0]))
    coord.send(_rotor_cmd(20_000, [1.5, 0, 0, 0]))
    coord.send(_rotor_cmd(10_000, [0.1] * 4))  # older than the last accepted frame
    coord.send(_rotor_cmd(20_000, [0.1] * 4, target=2))
    coord.send(_rotor_cmd(5_000_000, [0.1] * 4))  # 5 s ahead of the learnt coordinator clock
    intruder = Client(v, LINK_COORDINATOR, sysid=77, compid=1, key=KEY)  # holds the key, wrong ids
    intruder.send(_rotor_cmd(30_000, [0.9] * 4))
    unsigned = Client(v, LINK_COORDINATOR, sysid=201, compid=1)
    unsigned.send(_rotor_cmd(40_000, [0.9] * 4))
    forged = Client(v, LINK_COORDINATOR, sysid=201, compid=1, key=hashlib.sha256(b"guess").digest())
    forged.send(_rotor_cmd(40_000, [0.9] * 4))
    assert v.intake.accepted == before
    d = v.drop_counts()
    for reason in ("non_finite", "out_of_range", "out_of_order", "wrong_target", "future", "wrong_source"):
        assert d[f"intake.{reason}"] == 1, (reason, d)
    assert d["signing.coordinator.unsigned"] == 1 and d["signing.coordinator.bad_signature"] == 1
    np.testing.assert_allclose(v.motor_commands_n, hover * v.full_scale_n, rtol=1e-6)
    # rotor commands on a client link are never accepted
    Client(v, LINK_GCS, sysid=201, compid=1).send(_rotor_cmd(50_000, [0.9] * 4))
    assert v.drop_counts()["rotor_command_wrong_link"] == 1


@pytest.mark.parametrize("action, expect_armed", [(0, True), (1, False)])
def test_coordinator_loss_fails_safe(action: int, expect_armed: bool) -> None:
    v = _vehicle(signing_key=KEY, params={"MARS_FS_ACT": action})
    f = Flight(v)
    coord = Client(v, LINK_COORDINATOR, sysid=201, compid=1, key=KEY)
    coord.command(400, 1, wall=f.wall)
    coord.command(22, wall=f.wall)
    f.run(4.0)  # own takeoff to 2 m, then the coordinator takes over with a hover command
    hover = [0.52 * 9.80665 / 4 / v.full_scale_n] * 4

    def stream(fl):
        if fl.t < 5.0:
            coord.send(_rotor_cmd(int(round(fl.t * 1e6)), hover), fl.wall)

    f.run(0.05, stream)
    assert _ack(coord.command(176, 129, 6, 0, wall=f.wall), 176) == 0
    f.run(0.95, stream)
    assert v.source == "coordinator" and v.mode == (6, 0)
    f.run(0.1, stream)  # the stream stops at t = 5 s: 3 periods held, then the fail-safe
    assert v.stats["coordinator_failsafe"] == 1 and v.intake.lost_events == 1
    assert v.armed == expect_armed
    if action == 0:
        assert v.mode == (4, 6) and v.source == "own"
        f.run(6.0)
        assert v.landed and f.pos[2] > -0.1 and np.linalg.norm(f.body.state().velocity_ned_mps) < 0.05


# ----------------------------------------------------------------------------- HIL lockstep link
def test_hil_sensor_steps_the_unit_and_is_forwarded_to_the_coordinator() -> None:
    v = _vehicle()
    world = Client(v, LINK_HIL, sysid=200, compid=1)
    truth = RigidBodyState(0.02, np.array([1.0, 2.0, -0.05]), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3))
    packet = SensorPacket(0.02, 1, ImuSample(0.02, 1, np.zeros(3), np.array([0, 0, -9.81])), None, truth)
    out = []
    for m in sensor_packet_messages(packet):
        out += v.handle(m.pack(world.mav), T0, LINK_HIL)
    hil = [m for m in world.decode(out) if m.get_type() == "HIL_ACTUATOR_CONTROLS"]
    assert len(hil) == 1 and hil[0].time_usec == 20_000 and hil[0].flags & 1
    assert [m.get_type() for m in world.decode(out, LINK_COORDINATOR)] == ["ODOMETRY", "HIGHRES_IMU"]
    np.testing.assert_allclose(v.state.position_ned_m, [1.0, 2.0, -0.05])
    # state input on any other link is refused, and so is a HIL frame from another system
    spoof = Client(v, LINK_GCS)
    for m in sensor_packet_messages(packet):
        spoof.send(m)
    Client(v, LINK_HIL, sysid=9).send(sensor_packet_messages(packet)[-1])
    assert v.drop_counts()["hil_wrong_link"] == 2 and v.drop_counts()["hil_wrong_source"] == 1


def test_velocity_setpoints_reposition_by_command_int_and_return_to_launch() -> None:
    v, f, api = _airborne(5.0)
    # body-frame velocity 0.5 m/s forward (heading north) for 2 s, in OFFBOARD
    vel = mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mavlink.MAV_FRAME_BODY_NED, 0x0DC7, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0)

    def stream(fl):
        if round(fl.t * 100) % 5 == 0:
            api.send(vel, fl.wall)

    f.run(0.1, stream)
    assert _ack(api.command(176, 129, 6, 0, wall=f.wall), 176) == 0
    x0 = f.pos[0]
    f.run(3.0, stream)
    assert abs(f.body.state().velocity_ned_mps[0] - 0.5) < 0.05 and f.pos[0] - x0 > 1.0
    # DO_REPOSITION as COMMAND_INT: lat/lon in degE7, altitude AMSL (origin at PX4 SITL's home, 488 m)
    lat = int(round((47.397742 + math.degrees(-3.0 / 6371000.0)) * 1e7))
    lon = int(round((8.545594 + math.degrees(2.0 / (6371000.0 * math.cos(math.radians(47.397742))))) * 1e7))
    reposition = mavlink.MAVLink_command_int_message(1, 1, mavlink.MAV_FRAME_GLOBAL, 192, 0, 0, -1, 0, 0, NAN,
                                                     lat, lon, 491.0)
    assert _ack(api.send(reposition, f.wall + 1), 192) == 0
    assert v.mode == (4, 3)
    f.run(8.0)
    np.testing.assert_allclose(f.pos, [-3.0, 2.0, -3.0], atol=0.05)
    # RTL: back over home at RTL_RETURN_ALT or higher, then land there
    assert _ack(api.command(20, wall=f.wall + 2), 20) == 0
    f.run(25.0)
    assert v.landed and np.linalg.norm(f.pos[:2]) < 0.1 and f.pos[2] > -0.06


def test_hil_state_quaternion_is_the_state_on_the_physics_link() -> None:
    v = _vehicle()
    world = Client(v, LINK_HIL, sysid=200, compid=1)
    lat = int(round(math.degrees(5.0 / 6371000.0) * 1e7))
    world.send(mavlink.MAVLink_hil_state_quaternion_message(
        1_000_000, [1.0, 0.0, 0.0, 0.0], 0.1, 0.0, 0.0, lat, 0, -2000, 30, 0, -10, 0, 0, 0, 0, 0))
    np.testing.assert_allclose(v.state.position_ned_m, [5.0, 0.0, 2.0], atol=0.01)
    np.testing.assert_allclose(v.state.velocity_ned_mps, [0.3, 0.0, -0.1])
    world.send(mavlink.MAVLink_hil_state_quaternion_message(
        2_000_000, [NAN, 0.0, 0.0, 0.0], 0.1, 0.0, 0.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0))
    assert v.drop_counts()["hil_non_finite"] == 1 and v.state.t_s == 1.0
