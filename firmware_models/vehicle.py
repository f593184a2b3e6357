"""One unit's firmware as a sans-IO MAVLink vehicle: bytes and time in, bytes out.

    vehicle = Vehicle(VehicleConfig(unit_id=1))
    out = vehicle.handle(datagram, wall_time_s, link="api")     # -> [Outgoing(link, frame_bytes)]
    out += vehicle.tick(wall_time_s, sim_time_s)                 # heartbeats, streams, control step
    thrusts_n = vehicle.step_motors(physics_dt_s)                # motor model: limits, eta, lag

Links are named; each has a policy (`LinkPolicy`): client links "gcs" and "api" (telemetry, what
MAVSDK/MAVProxy/QGC use; who may do what over them: control_policy), "coordinator" (per-rotor
commands; signed when a key is configured) and
"hil" (sensor/state in, HIL_ACTUATOR_CONTROLS out, PX4's lockstep contract). A runner maps link names
to sockets. The surface follows specs/mavlink.md §6: PX4 persona (MAV_AUTOPILOT_PX4, custom_mode =
main << 16 | sub << 24), heartbeats at 1 Hz of wall time even with the simulation paused, default
telemetry streams, command protocol with ACKs (idempotent under MAVSDK's identical resends),
parameters, mission/fence/rally lists (mission_protocol) flown in AUTO.MISSION (mission_runner),
offboard setpoints with a watchdog, fault injection (MAV_CMD_INJECT_FAILURE into the motor model
only), MAVFTP NAK. Geographic positions are around PX4 SITL's home (geo.py).

Untrusted input: every datagram is split into frames here (no bytes carried over to the next
datagram, so a truncated frame cannot swallow the next good one); anything malformed, unsigned where
signing is required, mis-addressed, non-finite or out of range is dropped and counted by reason in
`drop_counts()`; replies are rate-limited per link so a flood cannot be amplified.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models import control_policy as policy
from firmware_models.control_policy import FORCE_DISARM_MAGIC
from firmware_models.geo import EARTH_RADIUS_M  # noqa: F401 (re-exported)
from firmware_models.geo import WIRE_ORIGIN, GeoOrigin, origin_from_env
from firmware_models.mission_protocol import MissionProtocol
from firmware_models.mission_runner import MissionRunner
from firmware_models.motor import MotorModel, MotorParams
from firmware_models.params import ParamStore, unit_param_specs
from firmware_models.rotor_intake import IntakeParams, RotorIntake
from firmware_models.control_policy import SenderBudgets
from firmware_models.signing import (
    ACCEPTED,
    UNSIGNED,
    is_signed,
    SignatureVerifier,
    advance_outgoing_clock,
    enable_outgoing_signing,
)
from firmware_models.unit_controller import GuidanceLimits, Phase, UnitAutopilot
from mars_link import mavlink_codec
from mars_link.assembly import GRAVITY_MPS2, VehicleParams, vehicle_preset
from mars_link.errors import UserInputError
from mars_link.messages import LATCH_ALL, ActuatorOutput, RotorCommand, SensorPacket, wire_thrust
from mars_link.rotations import quat_to_euler, quat_to_rotmat
from mars_link.state import ImuSample, RigidBodyState
from mars_link.wire import SensorFrameAssembler, SensorFrames, latch_from_message, latch_message, latch_setpoint_of, latches_open

LINK_GCS, LINK_API, LINK_COORDINATOR, LINK_HIL = "gcs", "api", "coordinator", "hil"
WORLD_SYSID = 200  # the SITL world process (sitl/lockstep.py)

# PX4 custom modes (main, sub): specs/mavlink.md §2.1
MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_AUTO, MAIN_ACRO, MAIN_OFFBOARD, MAIN_STABILIZED = 1, 2, 3, 4, 5, 6, 7
SUB_READY, SUB_TAKEOFF, SUB_LOITER, SUB_MISSION, SUB_RTL, SUB_LAND = 1, 2, 3, 4, 5, 6
MODE_HOLD = (MAIN_AUTO, SUB_LOITER)
MODE_TAKEOFF = (MAIN_AUTO, SUB_TAKEOFF)
MODE_LAND = (MAIN_AUTO, SUB_LAND)
MODE_RTL = (MAIN_AUTO, SUB_RTL)
MODE_MISSION = (MAIN_AUTO, SUB_MISSION)
MODE_OFFBOARD = (MAIN_OFFBOARD, 0)
MODE_POSCTL = (MAIN_POSCTL, 0)

FAILURE_TYPE_ETA = {0: 1.0, 1: 0.0, 5: 0.5}  # FAILURE_TYPE OK / OFF / SLOW (degraded) -> rotor efficiency
FAILURE_UNIT_SYSTEM_MOTOR = 101
SETPOINT_PROOF_OF_LIFE_S = 0.5  # OFFBOARD needs a setpoint stream faster than 2 Hz
COMMAND_DEDUP_S = 1.5  # MAVSDK resends an unacknowledged command 3 times, 0.5 s apart
MAX_POSITION_M = 10_000.0
MAX_SPEED_MPS = 20.0
MIN_STREAM_INTERVAL_S = 0.01

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
#: commands whose identical resend within COMMAND_DEDUP_S is answered from the cache, not re-run
ACTION_COMMANDS = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_DO_REPOSITION,
    mavlink.MAV_CMD_INJECT_FAILURE, mavlink.MAV_CMD_MISSION_START, mavlink.MAV_CMD_DO_SET_MISSION_CURRENT,
}
FTP_NAK, FTP_ACK = 129, 128
FTP_ERR_UNKNOWN_COMMAND, FTP_ERR_FILE_NOT_FOUND, FTP_ERR_INVALID_SESSION = 7, 10, 4
FTP_PATH_OPCODES = {3, 4, 6, 8, 9, 10, 11, 12, 13, 14}  # list, open, create, remove, ..., crc32
FTP_SESSION_OPCODES = {5, 7, 15}  # read, write, burst read


class Outgoing(NamedTuple):
    link: str
    data: bytes


@dataclass(frozen=True)
class LinkPolicy:
    telemetry: bool = True  # heartbeats, default streams, STATUSTEXT
    require_signing: bool = False  # an unsigned frame is dropped (or, with unsigned_reads, may only read)
    unsigned_reads: bool = False  # with require_signing: unsigned clients read (control_policy.READ)
    sign_outgoing: bool = False
    signing_link_id: int = 0
    rotor_commands: bool = False  # SET_ACTUATOR_CONTROL_TARGET is accepted only on such links
    hil: bool = False  # HIL sensor/state input and HIL_ACTUATOR_CONTROLS output
    forward_sensors: bool = False  # sensor packets from the HIL link are forwarded here
    reply_rate_hz: float = 300.0  # token bucket for replies (ACKs, params, ...), per sender on the link
    reply_burst: int = 600


def default_links(signed_coordinator: bool, sign_clients: bool = False) -> dict[str, LinkPolicy]:
    client = LinkPolicy(require_signing=sign_clients, sign_outgoing=sign_clients, unsigned_reads=True)
    return {
        LINK_GCS: client,
        LINK_API: client,
        LINK_COORDINATOR: LinkPolicy(
            telemetry=False, require_signing=signed_coordinator, sign_outgoing=signed_coordinator,
            signing_link_id=1, rotor_commands=True, forward_sensors=True,
        ),
        LINK_HIL: LinkPolicy(telemetry=False, hil=True),
    }


@dataclass
class VehicleConfig:
    unit_id: int = 1
    vehicle: VehicleParams | str = "mars-ftcc"
    component_id: int = 1
    coordinator_sysid: int = 201
    coordinator_compid: int = 1
    world_sysid: int = WORLD_SYSID
    signing_key: bytes | None = None  # set: the coordinator link requires signed frames
    sign_client_links: bool = False  # --require-signing: gcs/api unsigned clients may only read
    control_hz: float = 100.0
    links: dict[str, LinkPolicy] | None = None  # None: default_links(...)
    params: dict[str, float] = field(default_factory=dict)  # start-up parameter values
    stream_hz: dict[int, float] | None = None  # None: DEFAULT_STREAM_HZ
    # the ground point under local NED (0, 0, 0); None: PX4 SITL's home or PX4_HOME_LAT/LON/ALT (geo)
    origin_lat_deg: float | None = None
    origin_lon_deg: float | None = None
    origin_amsl_m: float | None = None
    # lockstep with a coordinator: answer each HIL step only once the coordinator's rotor command for
    # that step has arrived (the runner calls `release_hil` when it gives up waiting)
    hil_await_coordinator: bool = False
    # False: an in-process unit (direct calls; no MAVLink frame carries its id), so its id may go beyond
    # MAVLink's system ids 1..250 (an in-process flight of 20x20 units)
    on_wire: bool = True

    def checked(self) -> "VehicleConfig":
        if not self.on_wire and isinstance(self.unit_id, int) and self.unit_id >= 1:
            pass
        elif not (isinstance(self.unit_id, int) and 1 <= self.unit_id <= 250):
            raise UserInputError(f"unit id must be 1..250, got {self.unit_id!r}")
        elif self.unit_id in (self.coordinator_sysid, self.world_sysid):
            raise UserInputError(f"unit id {self.unit_id} collides with the coordinator or world system id")
        if not (math.isfinite(self.control_hz) and 1.0 <= self.control_hz <= 2000.0):
            raise UserInputError(f"control rate must be 1..2000 Hz, got {self.control_hz!r}")
        if self.signing_key is not None and len(self.signing_key) != 32:
            raise UserInputError("the signing key must be 32 bytes")
        return self

    def origin(self) -> GeoOrigin:
        env = origin_from_env()
        pick = lambda v, d: d if v is None else v  # noqa: E731
        return GeoOrigin(pick(self.origin_lat_deg, env.lat_deg), pick(self.origin_lon_deg, env.lon_deg),
                         pick(self.origin_amsl_m, env.amsl_m)).checked()


class _Link:
    def __init__(self, name: str, policy: LinkPolicy, sysid: int, compid: int, key: bytes | None, now: float) -> None:
        self.name = name
        self.policy = policy
        self.decoder = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)  # never given a key
        self.decoder.robust_parsing = True
        self.encoder = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if policy.sign_outgoing:
            enable_outgoing_signing(self.encoder, key, policy.signing_link_id, now)
        # with a key every non-HIL link checks signatures: a signed frame earns SAFETY authority
        self.verifier = SignatureVerifier(key) if policy.require_signing or (key and not policy.hil) else None
        self.budgets = SenderBudgets(policy.reply_rate_hz, policy.reply_burst)


def split_frames(data: bytes | bytearray, decoder: mavlink.MAVLink, drop, pre_check=None) -> list[tuple[mavlink.MAVLink_message, bytearray]]:
    """Decode every complete, CRC-valid frame of one datagram; count the rest via `drop(reason)`.

    Resynchronises one byte after a bad frame (a random 0xFD in junk must not hide a good frame).
    `pre_check(frame) -> bool` runs on the raw bytes before decoding (signature verification: an
    unsigned or forged frame costs a flag test or one SHA-256, never a decode).
    """
    out = []
    n = len(data)
    i = 0
    junk = False
    while i < n:
        b = data[i]
        if b == 0xFD:
            if n - i < 12:
                drop("parse.truncated")
                break
            flags = data[i + 2]
            if flags & ~0x01:
                drop("parse.unknown_flags")
                i += 1
                continue
            flen = 12 + data[i + 1] + (13 if flags & 0x01 else 0)
        elif b == 0xFE:
            if n - i < 8:
                drop("parse.truncated")
                break
            flen = 8 + data[i + 1]
        else:
            nxt = min((j for j in (data.find(b"\xfd", i), data.find(b"\xfe", i)) if j >= 0), default=n)
            junk = True
            i = nxt
            continue
        if i + flen > n:
            drop("parse.truncated")
            i += 1
            continue
        frame = bytearray(data[i:i + flen])
        if pre_check is not None and not pre_check(frame):
            i += flen
            continue
        try:
            msg = mavlink_codec.decode(frame, decoder)
        except Exception as e:  # pymavlink raises MAVError and, on odd payloads, others
            drop("parse.bad_crc" if "CRC" in str(e) else "parse.malformed")
            i += 1
            continue
        if isinstance(msg, mavlink.MAVLink_unknown) or msg.get_type() == "BAD_DATA":
            drop("parse.unknown_message")
        else:
            out.append((msg, frame))
        i += flen
    if junk:
        drop("parse.junk")
    return out


def _finite(*values) -> bool:
    return all(math.isfinite(v) for v in values)


class Vehicle:
    """The unit firmware state machine. Not thread-safe: one runner drives it.

    `flight_core`: what the mode machine flies with (default: the lone unit's `UnitAutopilot`); any
    object with UnitAutopilot's guidance methods, e.g. the assembly's (mars_link.assembly_vehicle).
    """

    motor_count = 4  # highest motor instance MAV_CMD_INJECT_FAILURE may name

    def __init__(self, config: VehicleConfig | None = None, wall_time_s: float = 0.0, flight_core=None) -> None:
        c = (config or VehicleConfig()).checked()
        self.config = c
        self.origin = c.origin()
        self.vehicle = vehicle_preset(c.vehicle) if isinstance(c.vehicle, str) else c.vehicle
        self.sysid, self.compid = c.unit_id, c.component_id
        signed = c.signing_key is not None
        overrides = {"MARS_COORD_SYS": c.coordinator_sysid, "MARS_COORD_COMP": c.coordinator_compid,
                     "MARS_SIGN_REQ": int(signed), **c.params}
        self.params = ParamStore(unit_param_specs(c.unit_id, self.vehicle), overrides)
        policies = c.links if c.links is not None else default_links(signed, c.sign_client_links)
        for name, p in policies.items():
            if (p.require_signing or p.sign_outgoing) and not signed:
                raise UserInputError(f"link {name!r} requires signing but no signing key is configured")
        self.links = {n: _Link(n, p, self.sysid, self.compid, c.signing_key, wall_time_s) for n, p in policies.items()}
        self._authority = policy.SAFETY  # of the frame being dispatched (control_policy.frame_authority)
        self.on_frame_in = None  # callable(link, frame bytes) for every frame that passed parsing and signing
        self._sender: tuple = ()  # (link, sysid, compid) of that frame: whose reply budget answers pay from
        self.full_scale_n = self.vehicle.full_scale_thrust_n
        self.motors = MotorModel(MotorParams.for_vehicle(self.vehicle))
        self.intake = RotorIntake(self._intake_params())
        self.autopilot = UnitAutopilot(self.vehicle, c.control_hz) if flight_core is None else flight_core
        self.control_dt_s = 1.0 / c.control_hz
        self.assembler = SensorFrameAssembler()
        # state
        self.armed = False
        self.mode = MODE_HOLD
        self.source = "own"  # who drives the motors: "own" controller or "coordinator"
        self.state: RigidBodyState | None = None
        self.imu: ImuSample | None = None
        self.home_ned: np.ndarray | None = None
        self.wall_s = wall_time_s
        self.sim_s = 0.0
        self.motor_commands_n = np.zeros(4)
        self.drops: dict[str, int] = {}
        self.stats: dict[str, int] = {}
        self.events: list[tuple[float, str]] = []  # (sim time, text): STATUSTEXT history
        self._next_heartbeat = wall_time_s
        self._next_control = 0.0
        rates = DEFAULT_STREAM_HZ if c.stream_hz is None else c.stream_hz
        self.stream_interval_s = {mid: 1.0 / hz for mid, hz in rates.items() if hz > 0}
        self._next_stream = {mid: wall_time_s for mid in self.stream_interval_s}
        self._setpoint: tuple | None = None  # (kind, vector, yaw, yaw_rate)
        self._setpoint_wall: float | None = None
        self._landed_since: float | None = None
        self._armed_at: float | None = None
        self._took_off = False
        self._last_cmd: dict[tuple, tuple] = {}
        self._pending_text: list[tuple[int, str]] = []
        self.battery_used_c = 0.0  # coulombs
        self._hil_pending: tuple[int, str] | None = None  # (time_usec, link) of an unanswered HIL step
        self.defer_own_state = False  # set by the lockstep unit runner: see run_deferred
        self._deferred: list = []
        self._last_rotor_usec: int | None = None  # time of the last accepted coordinator command
        self.latch_setpoint = LATCH_ALL  # the docking latches: engaged until the coordinator opens some
        self.latches = 0  # the latch sensor: the sides that hold a docked neighbour (from the world)
        self._await_coordinator = c.hil_await_coordinator
        self._scheduled_failures: list[tuple[float, int, float]] = []  # (sim time, rotor, eta), sorted
        self.mission = MissionProtocol(self.origin)
        self.runner = MissionRunner(self.autopilot, self.origin)
        self._mission_version = 0
        self._mission_msgs: list = []  # MISSION_CURRENT / MISSION_ITEM_REACHED to broadcast
        self.mission_reached: list[dict] = []  # (seq, sim time, position) of every MISSION_ITEM_REACHED

    def _intake_params(self) -> IntakeParams:
        p = self.params
        return IntakeParams(
            unit_sysid=self.sysid, full_scale_thrust_n=self.full_scale_n, unit_compid=self.compid,
            coordinator_sysid=int(p["MARS_COORD_SYS"]), coordinator_compid=int(p["MARS_COORD_COMP"]),
            period_s=1.0 / p["MARS_CMD_HZ"], hold_periods=int(p["MARS_CMD_MISS"]),
            # a plant without a rotor minimum (paper 000's) takes reversed thrust, down to -full scale
            control_min=0.0 if self.vehicle.rotor_min_thrust_n is not None else -1.0,
        )

    # ================================================================= public API
    @property
    def custom_mode(self) -> int:
        return (self.mode[0] << 16) | (self.mode[1] << 24)

    @property
    def landed(self) -> bool:
        return self.autopilot.landed if self.source == "own" else bool(
            self.state is not None and self.autopilot.touching(self.state))

    def drop_counts(self) -> dict[str, int]:
        """Every dropped input, by reason (parse.*, signing.<link>.*, intake.*, and the rest)."""
        out = dict(self.drops)
        for k, v in self.intake.counters.items():
            out[f"intake.{k}"] = v
        for k, v in self.mission.counts.items():
            if k.startswith(("refused.", "cancelled", "duplicate_item", "client_ack_error")):
                out[f"mission.{k}"] = v
        for name, link in self.links.items():
            if link.verifier is not None:
                for k, v in link.verifier.counters.items():
                    if k != ACCEPTED:
                        out[f"signing.{name}.{k}"] = v
        return out

    def set_state(self, state: RigidBodyState, imu: ImuSample | None = None) -> None:
        """In-process sensor input: the unit's state (from the world or an estimator)."""
        self.state = state
        if imu is not None:
            self.imu = imu
        if self.home_ned is None:
            self.home_ned = np.array(state.position_ned_m, dtype=float)
            self.autopilot.idle(float(state.position_ned_m[2]))

    def inject_failure(self, rotor: int, eta: float) -> None:
        """Local fault injection (rotor 1..4, 0 = all): the motor model only."""
        self.motors.set_rotor_eta(0, rotor, eta)

    def schedule_failure(self, t_s: float, rotor: int, eta: float) -> None:
        """A scenario fault (rotor 1..4, 0 = all) that enters the motor model at the first HIL step at
        or after sim time t_s, before that step's motor outputs are computed."""
        self._scheduled_failures.append((t_s, rotor, eta))
        self._scheduled_failures.sort()

    def step_motors(self, dt_s: float) -> np.ndarray:
        """Produced rotor thrusts (N) after one physics step of dt_s (limits, eta, lag)."""
        return self.motors.step(self.motor_commands_n if self.armed else np.zeros(4), dt_s)

    def handle(self, data, wall_time_s: float, link: str = LINK_GCS) -> list[Outgoing]:
        """One received datagram (bytes) or an already parsed message from `link`."""
        self.wall_s = max(self.wall_s, wall_time_s)
        lk = self.links.get(link)
        if lk is None:
            raise ValueError(f"unknown link {link!r}")
        out: list[Outgoing] = []
        if isinstance(data, (bytes, bytearray, memoryview)):
            data = bytes(data)
            check = None
            if lk.verifier is not None:  # HMAC-first verification before any decoding
                verifier = lk.verifier
                unsigned_ok = not lk.policy.require_signing or lk.policy.unsigned_reads
                check = lambda raw: verifier.verify(raw, wall_time_s) in (  # noqa: E731
                    (ACCEPTED, UNSIGNED) if unsigned_ok else (ACCEPTED,))
            frames = split_frames(data, lk.decoder, self._drop, check)
        else:
            msg = data
            raw = msg.get_msgbuf() if hasattr(msg, "get_msgbuf") else b""
            if lk.verifier is not None:
                if not raw or lk.verifier.verify(bytearray(raw), wall_time_s) != ACCEPTED:
                    return out
            frames = [(msg, raw)]
        if self._deferred and not (link == LINK_COORDINATOR and all(
                m.get_type() == "SET_ACTUATOR_CONTROL_TARGET" for m, _ in frames)):
            self.run_deferred()  # (a rotor command alone does not read the unit's own state)
        has_key = self.config.signing_key is not None
        for msg, frame in frames:
            self._count("rx")
            if self.on_frame_in is not None:
                self.on_frame_in(link, frame)
            self._authority = policy.frame_authority(
                lk.verifier is not None and is_signed(frame), lk.policy.require_signing, has_key)
            # whose reply budget pays: each signed (or, without a key, each) sender its own; unsigned
            # senders next to a key share one, so spoofed system ids cannot mint fresh budgets
            self._sender = ((link, msg.get_srcSystem(), msg.get_srcComponent()) if self._authority == policy.SAFETY
                            else (link, "unsigned"))
            try:
                self._dispatch(msg, lk, out)
            except (ValueError, TypeError, OverflowError, struct.error):
                self._drop("malformed_fields")  # a decoded frame whose fields we cannot use
        pending = self._hil_pending
        if pending is not None and self._last_rotor_usec == pending[0]:
            self._answer_hil(out)  # the coordinator's command for the pending step (and any arm/mode
            # command in the same datagram) is in: run the step
        return out

    @property
    def has_deferred(self) -> bool:
        return bool(self._deferred)

    def run_deferred(self) -> None:
        """Bring the unit's own state (attitude, position, last IMU sample) up to the last sensor
        packet. With `defer_own_state` a HIL step only forwards the sensors to the coordinator and
        queues this: the runner calls it in the step's slack, after the coordinator's command is in
        and answered, so the sensor -> coordinator -> motor path carries no bookkeeping; everything
        that reads the state (ticks, client commands, the unit's own control) runs it first."""
        while self._deferred:
            self._deferred.pop(0)()

    @property
    def hil_pending(self) -> bool:
        """A HIL step waits for the coordinator's command (`hil_await_coordinator`)."""
        return self._hil_pending is not None

    def release_hil(self, wall_time_s: float) -> list[Outgoing]:
        """The runner gave up waiting for the coordinator: answer the pending step with what the unit
        holds (the last command within MARS_CMD_MISS periods, then the fail-safe), and stop waiting
        until the coordinator's commands come back."""
        self.wall_s = max(self.wall_s, wall_time_s)
        self.run_deferred()
        out: list[Outgoing] = []
        if self._hil_pending is not None:
            self._count("hil_released")
            self._await_coordinator = False
            self._answer_hil(out)
        return out

    def notify(self, text: str, severity: int = mavlink.MAV_SEVERITY_WARNING) -> None:
        """A STATUSTEXT from the runner (e.g. "logging stopped"), sent with the next tick."""
        self._text(text, severity)

    def hello(self, link: str) -> Outgoing:
        """A HEARTBEAT on a non-telemetry link (HIL, coordinator): peers learn the unit's address."""
        lk = self.links[link]
        return Outgoing(link, self._pack(lk, self._heartbeat()))

    def tick(self, wall_time_s: float, sim_time_s: float) -> list[Outgoing]:
        """Advance both clocks: heartbeats and streams on wall time, control on sim time."""
        self.wall_s = max(self.wall_s, wall_time_s)
        self.run_deferred()
        out: list[Outgoing] = []
        if sim_time_s + 1e-9 >= self._next_control:
            self.sim_s = sim_time_s
            self._control_step()
            self._next_control = max(self._next_control + self.control_dt_s, sim_time_s + 0.5 * self.control_dt_s)
        else:
            self.sim_s = max(self.sim_s, sim_time_s)
        self._watchdogs()
        if wall_time_s >= self._next_heartbeat:
            self._next_heartbeat = max(self._next_heartbeat + 1.0, wall_time_s + 0.5)
            self._broadcast(self._heartbeat(), out)
        for mid, interval in self.stream_interval_s.items():
            due = self._next_stream.get(mid, wall_time_s)
            if wall_time_s >= due:
                self._next_stream[mid] = max(due + interval, wall_time_s + 0.5 * interval)
                try:
                    msg = self._stream_message(mid)
                except (*mavlink_codec.ENCODE_ERRORS, FloatingPointError):  # e.g. int() of a NaN state
                    self._count("telemetry.encode_error")
                    msg = None
                if msg is not None:
                    self._broadcast(msg, out)
        for name, msg in self.mission.tick(self.wall_s):
            self._reply(self.links[name], msg, out)
        self._flush_mission_texts()
        while self._mission_msgs:
            self._broadcast(self._mission_msgs.pop(0), out)
        while self._pending_text:
            severity, text = self._pending_text.pop(0)
            self._broadcast(mavlink.MAVLink_statustext_message(severity, text.encode()[:50], 0, 0), out)
        return out

    # ================================================================= plumbing
    def _count(self, key: str) -> None:
        self.stats[key] = self.stats.get(key, 0) + 1

    def _drop(self, reason: str) -> None:
        self.drops[reason] = self.drops.get(reason, 0) + 1

    def _pack(self, lk: _Link, msg) -> bytes:
        """Encode for this link; a field outside its wire range is clamped and counted
        (telemetry.clamped), never raised (mars_link.mavlink_codec.encode_clamped)."""
        if lk.policy.sign_outgoing:
            advance_outgoing_clock(lk.encoder, self.wall_s)
        frame, clamped = mavlink_codec.encode_clamped(msg, lk.encoder)
        if clamped:
            self._count("telemetry.clamped")
        return frame

    def _send(self, lk: _Link, msg, out: list[Outgoing]) -> None:
        """Append `msg` for `lk`; a message that cannot be encoded is counted and dropped: telemetry
        never stops a flight."""
        try:
            out.append(Outgoing(lk.name, self._pack(lk, msg)))
        except (*mavlink_codec.ENCODE_ERRORS, mavlink.MAVError):
            self._count("telemetry.encode_error")

    def _reply(self, lk: _Link, msg, out: list[Outgoing]) -> bool:
        """An answer to the current sender, paid from its own reply budget (control_policy.SenderBudgets)."""
        if lk.budgets.take(self._sender, self.wall_s):
            self._send(lk, msg, out)
            return True
        self._drop("reply_rate_limited")
        return False

    def _broadcast(self, msg, out: list[Outgoing]) -> None:
        for lk in self.links.values():
            if lk.policy.telemetry:
                self._send(lk, msg, out)

    def _text(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        self.events.append((self.sim_s, text))
        if len(self.events) > 200:
            del self.events[:100]
        self._pending_text.append((severity, text))

    def _for_me(self, target_system: int, target_component: int, allow_broadcast: bool) -> bool:
        ok_sys = target_system == self.sysid or (allow_broadcast and target_system == 0)
        return ok_sys and target_component in (0, self.compid)

    # ================================================================= dispatch
    def _dispatch(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        src = msg.get_srcSystem()
        if src == self.sysid:
            self._drop("own_sysid")  # an echo or a spoof of ourselves
            return
        t = msg.get_type()
        self._count("rx." + t)
        if src == self.config.coordinator_sysid and msg.get_srcComponent() == self.config.coordinator_compid:
            self._count("from_coordinator")  # (after signing, where required): runners learn the reply address
        if lk.policy.hil:
            if src != self.config.world_sysid:
                self._drop("hil_wrong_source")
                return
            self._on_hil(msg, t, lk, out)
            return
        if t in ("HIL_SENSOR", "HIL_STATE_QUATERNION", "HIL_GPS", "ODOMETRY"):
            self._drop("hil_wrong_link")  # state input is trusted only from the physics link
            return
        handler = _HANDLERS.get(t)
        if handler is None:
            self._drop("unhandled_message")
            return
        if self._authority < policy.required_authority(msg):  # e.g. unsigned control under --require-signing
            self._drop(f"policy.denied_{policy.AUTHORITY_NAMES[self._authority]}")
            for m in policy.refusal(msg):
                self._reply(lk, m, out)
            return
        handler(self, msg, lk, out)

    # ----------------------------------------------------------------- commands
    def _on_command(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            self._drop("wrong_target")
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
            last = self._last_cmd.get(src)
            if last is not None and last[0] == key and self.wall_s - last[1] <= COMMAND_DEDUP_S:
                self._count("command_duplicate")
                self._ack(lk, msg, cmd, last[2], out)
                return
        result, followups = self._execute(cmd, p, is_int, msg)
        if cmd in ACTION_COMMANDS:  # only a success is replayed: a refused command may succeed now
            self._last_cmd[src] = (key, self.wall_s, result) if result == mavlink.MAV_RESULT_ACCEPTED else (None, 0.0, 0)
            if len(self._last_cmd) > 64:
                self._last_cmd.pop(next(iter(self._last_cmd)))
        self._ack(lk, msg, cmd, result, out)
        for m in followups:
            self._reply(lk, m, out)

    def _ack(self, lk: _Link, msg, cmd: int, result: int, out: list[Outgoing]) -> None:
        self._count(f"ack.{result}")
        self._reply(lk, mavlink.MAVLink_command_ack_message(
            cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()), out)

    def _execute(self, cmd: int, p: list, is_int: bool, msg) -> tuple[int, list]:
        R = mavlink
        if cmd == R.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm_disarm(p[0], p[1]), []
        if cmd == R.MAV_CMD_NAV_TAKEOFF:
            return self._takeoff(p[6]), []
        if cmd == R.MAV_CMD_NAV_LAND:
            return self._set_mode(MODE_LAND), []
        if cmd == R.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._set_mode(MODE_RTL), []
        if cmd == R.MAV_CMD_DO_SET_MODE:
            if not _finite(p[0], p[1]) or not (int(p[0]) & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED):
                return R.MAV_RESULT_DENIED, []
            sub = int(p[2]) if math.isfinite(p[2]) else 0
            if not (0 <= p[1] <= 255 and 0 <= sub <= 255):
                return R.MAV_RESULT_DENIED, []
            return self._set_mode((int(p[1]), sub)), []
        if cmd == R.MAV_CMD_DO_REPOSITION:
            return self._reposition(p, is_int), []
        if cmd == R.MAV_CMD_MISSION_START:
            first = int(p[0]) if math.isfinite(p[0]) and p[0] >= 0 else None  # PX4: start at p1 if given
            if first is not None and not self.runner.set_current(first, reset_jumps=True):
                return R.MAV_RESULT_DENIED, []
            return self._set_mode(MODE_MISSION), []
        if cmd == R.MAV_CMD_DO_SET_MISSION_CURRENT:
            return self._set_mission_current(p[0], p[1] == 1), []
        if cmd == R.MAV_CMD_INJECT_FAILURE:
            return self._inject(p), []
        if cmd == R.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(p[0], p[1])
        if cmd == R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return (R.MAV_RESULT_ACCEPTED, [self._autopilot_version()]) if p[0] == 1 else (R.MAV_RESULT_DENIED, [])
        if cmd == R.MAV_CMD_GET_HOME_POSITION:
            home = self._home_position()
            return (R.MAV_RESULT_ACCEPTED, [home]) if home else (R.MAV_RESULT_TEMPORARILY_REJECTED, [])
        if cmd == R.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(p[0], p[1]), []
        if cmd == R.MAV_CMD_GET_MESSAGE_INTERVAL:
            if not math.isfinite(p[0]) or int(p[0]) not in DEFAULT_STREAM_HZ:
                return R.MAV_RESULT_DENIED, []
            iv = self.stream_interval_s.get(int(p[0]))
            return R.MAV_RESULT_ACCEPTED, [R.MAVLink_message_interval_message(
                int(p[0]), -1 if iv is None else int(round(iv * 1e6)))]
        return R.MAV_RESULT_UNSUPPORTED, []  # includes REQUEST_PROTOCOL_VERSION (519): MAVLink 2 only

    def _arm_disarm(self, arm: float, force: float) -> int:
        R = mavlink
        if arm == 1.0:
            if self.armed:
                return R.MAV_RESULT_ACCEPTED
            if self.state is None:
                return R.MAV_RESULT_TEMPORARILY_REJECTED  # no position yet
            if not self.autopilot.touching(self.state):
                return R.MAV_RESULT_DENIED  # never arm in the air
            self.armed = True
            self.home_ned = np.array(self.state.position_ned_m, dtype=float)
            self.autopilot.idle(float(self.state.position_ned_m[2]))
            self._armed_at = self.sim_s
            self._took_off = False
            self._text("Armed")
            return R.MAV_RESULT_ACCEPTED
        if arm == 0.0:
            if not self.armed:
                return R.MAV_RESULT_ACCEPTED
            if not self.landed and force != FORCE_DISARM_MAGIC:
                return R.MAV_RESULT_DENIED
            self._disarm("Disarmed" if force != FORCE_DISARM_MAGIC else "Killed: motors off")
            return R.MAV_RESULT_ACCEPTED
        return R.MAV_RESULT_DENIED

    def _disarm(self, why: str) -> None:
        self.armed = False
        self.source = "own"
        self.autopilot.idle()
        self.motor_commands_n = np.zeros(4)
        if self.mode not in (MODE_HOLD, MODE_POSCTL):
            self.mode = MODE_HOLD
        self._text(why)

    def _takeoff(self, altitude_amsl_m: float) -> int:
        R = mavlink
        if not self.armed or self.state is None:
            return R.MAV_RESULT_TEMPORARILY_REJECTED
        if self.mode == MODE_TAKEOFF or not self.landed:
            return R.MAV_RESULT_ACCEPTED  # already on its way / flying: nothing to restart
        ground = float(self.home_ned[2])
        if math.isfinite(altitude_amsl_m):
            target = -(altitude_amsl_m - self.origin.amsl_m)
            if not (ground - 100.0 <= target <= ground - 0.3):
                return R.MAV_RESULT_DENIED
        else:
            target = ground - self.params["MIS_TAKEOFF_ALT"]
        self.source = "own"
        self.autopilot.takeoff(self.state, target)
        self.mode = MODE_TAKEOFF
        self._took_off = True
        self._text(f"Takeoff to {ground - target:.1f} m")
        return R.MAV_RESULT_ACCEPTED

    def _set_mode(self, mode: tuple[int, int]) -> int:
        R = mavlink
        if mode == self.mode:
            return R.MAV_RESULT_ACCEPTED
        if mode == MODE_MISSION:
            return self._enter_mission()
        s = self.state
        self.runner.pause()  # (a no-op unless leaving AUTO.MISSION: it resumes at its current item)
        if mode in (MODE_HOLD, MODE_POSCTL):
            if s is not None and self.source == "own":
                self.autopilot.hold(s)
            elif s is not None:
                self._hand_back(s)
                self.autopilot.hold(s)
        elif mode == MODE_LAND:
            if s is None:
                return R.MAV_RESULT_TEMPORARILY_REJECTED
            if self.source != "own":
                self._hand_back(s)
            self.autopilot.land(s)
        elif mode == MODE_RTL:
            if s is None or self.home_ned is None:
                return R.MAV_RESULT_TEMPORARILY_REJECTED
            if self.source != "own":
                self._hand_back(s)
            self.autopilot.rtl(s, self.home_ned, self.params["RTL_RETURN_ALT"])
        elif mode == MODE_TAKEOFF:
            return self._takeoff(math.nan)
        elif mode == MODE_OFFBOARD:
            live_sp = self._setpoint_wall is not None and self.wall_s - self._setpoint_wall <= SETPOINT_PROOF_OF_LIFE_S
            if not (live_sp or self.intake.is_live(self.sim_s)):
                return R.MAV_RESULT_DENIED  # PX4: no OFFBOARD without a live setpoint stream
            self.mode = mode
            if live_sp:
                self._apply_setpoint()
            self._text("Offboard")
            return R.MAV_RESULT_ACCEPTED
        else:
            return R.MAV_RESULT_UNSUPPORTED  # manual/stabilised/acro modes need RC
        self.mode = mode
        self._text({MODE_HOLD: "Hold", MODE_POSCTL: "Position", MODE_LAND: "Land", MODE_RTL: "Return"}[mode])
        return R.MAV_RESULT_ACCEPTED

    def _enter_mission(self) -> int:
        R = mavlink
        if not self.runner.items:
            self._text("Mission: no mission stored", mavlink.MAV_SEVERITY_WARNING)
            return R.MAV_RESULT_DENIED
        if self.state is None or self.home_ned is None:
            return R.MAV_RESULT_TEMPORARILY_REJECTED
        if self.source != "own":
            self._hand_back(self.state)
        if self.runner.complete:
            self.runner.set_current(0, reset_jumps=True)  # PX4 restarts a finished mission
        self.runner.pause()
        self.mode = MODE_MISSION
        self._took_off = True
        self._text("Mission")
        return R.MAV_RESULT_ACCEPTED

    def _set_mission_current(self, seq: float, reset_jumps: bool) -> int:
        if not math.isfinite(seq) or seq != int(seq) or not self.runner.set_current(int(seq), reset_jumps):
            return mavlink.MAV_RESULT_DENIED
        self.mission.current_seq = self.runner.current
        self._mission_msgs.append(self.runner.current_message(self.mode == MODE_MISSION))
        return mavlink.MAV_RESULT_ACCEPTED

    def _mission_step(self, t: float, event: str | None) -> None:
        """AUTO.MISSION: the runner drives the flight core (after its update for this step)."""
        r = self.runner
        r.takeoff_alt_m, r.rtl_alt_m = self.params["MIS_TAKEOFF_ALT"], self.params["RTL_RETURN_ALT"]
        res = r.step(t, self.state, self.home_ned, event)
        for m in res.messages:
            if m.get_type() == "MISSION_ITEM_REACHED":
                self.mission_reached.append({"seq": m.seq, "sim_time_s": t,
                                             "position_ned_m": [float(x) for x in self.state.position_ned_m]})
                del self.mission_reached[:-2000]
            self._mission_msgs.append(m)
        for text in res.texts:
            self._text(text)
        if res.new_home_ned is not None:
            self.home_ned = res.new_home_ned
        self.mission.current_seq = r.current

    def _flush_mission_texts(self) -> None:
        while self.mission.texts:
            severity, text = self.mission.texts.pop(0)
            self._text(text, severity)

    def _hand_back(self, s: RigidBodyState) -> None:
        """The coordinator drove the motors; the own controller takes over from the current state."""
        self.source = "own"
        self.autopilot.handover(s)
        self.autopilot.landed = self.autopilot.touching(s)
        self.autopilot.phase = Phase.HOLD if not self.autopilot.landed else Phase.IDLE

    def _reposition(self, p: list, is_int: bool) -> int:
        R = mavlink
        if self.state is None or not self.armed or self.landed:
            return R.MAV_RESULT_TEMPORARILY_REJECTED
        lat = p[4] * 1e-7 if is_int else p[4]
        lon = p[5] * 1e-7 if is_int else p[5]
        if not _finite(lat, lon, p[6]) or not (-90 <= lat <= 90 and -180 <= lon <= 180):
            return R.MAV_RESULT_DENIED
        target = self._global_to_ned(lat, lon, p[6])
        if np.linalg.norm(target[:2] - self.state.position_ned_m[:2]) > MAX_POSITION_M:
            return R.MAV_RESULT_DENIED
        yaw = math.radians(p[3]) if math.isfinite(p[3]) else None
        if self.source != "own":
            self._hand_back(self.state)
        self.autopilot.goto(self.state, target, yaw)
        self.mode = MODE_HOLD
        return R.MAV_RESULT_ACCEPTED

    def _inject(self, p: list) -> int:
        R = mavlink
        if int(self.params["SYS_FAILURE_EN"]) != 1:
            return R.MAV_RESULT_DENIED
        if not _finite(p[0], p[1], p[2]) or int(p[0]) != FAILURE_UNIT_SYSTEM_MOTOR:
            return R.MAV_RESULT_UNSUPPORTED
        eta = FAILURE_TYPE_ETA.get(int(p[1]))
        if eta is None:
            return R.MAV_RESULT_UNSUPPORTED
        instance = int(p[2])
        if instance != p[2] or not 0 <= instance <= self.motor_count:
            return R.MAV_RESULT_DENIED
        self.inject_failure(instance, eta)
        self._count("failures_injected")
        self._text(f"Failure injected: motor {instance or 'all'} eta {eta:g}", mavlink.MAV_SEVERITY_WARNING)
        return R.MAV_RESULT_ACCEPTED

    def _request_message(self, msgid: float, p2: float) -> tuple[int, list]:
        R = mavlink
        if not math.isfinite(msgid) or msgid != int(msgid):
            return R.MAV_RESULT_DENIED, []
        mid = int(msgid)
        if mid == R.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return R.MAV_RESULT_ACCEPTED, [self._autopilot_version()]
        if mid == R.MAVLINK_MSG_ID_HEARTBEAT:
            return R.MAV_RESULT_ACCEPTED, [self._heartbeat()]
        if mid in DEFAULT_STREAM_HZ:
            msg = self._stream_message(mid)
            return (R.MAV_RESULT_ACCEPTED, [msg]) if msg is not None else (R.MAV_RESULT_TEMPORARILY_REJECTED, [])
        return R.MAV_RESULT_UNSUPPORTED, []  # incl. REFUSED_MESSAGES (PROTOCOL_VERSION, AVAILABLE_MODES, ...)

    def _set_interval(self, msgid: float, interval_us: float) -> int:
        R = mavlink
        if not _finite(msgid, interval_us) or int(msgid) not in DEFAULT_STREAM_HZ:
            return R.MAV_RESULT_DENIED
        mid = int(msgid)
        if interval_us < 0:
            self.stream_interval_s.pop(mid, None)
        else:
            iv = 1.0 / DEFAULT_STREAM_HZ[mid] if interval_us == 0 else max(MIN_STREAM_INTERVAL_S, interval_us * 1e-6)
            self.stream_interval_s[mid] = iv
            self._next_stream[mid] = self.wall_s
        return R.MAV_RESULT_ACCEPTED

    def _on_set_mode(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, 0, allow_broadcast=False):
            self._drop("wrong_target")
            return
        if not msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            self._drop("set_mode_not_custom")
            return
        self._set_mode(((msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF))

    # ----------------------------------------------------------------- offboard setpoints
    def _on_position_target(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            self._drop("wrong_target")
            return
        if self.state is None:
            self._drop("setpoint_no_state")
            return
        mask = msg.type_mask
        use_pos = not mask & 0x7
        use_vel = not mask & 0x38
        if (mask & 0x7 not in (0, 0x7)) or (mask & 0x38 not in (0, 0x38)) or not (use_pos or use_vel):
            self._drop("setpoint_unsupported")
            return
        yaw = None if mask & 0x400 else msg.yaw
        yaw_rate = 0.0 if mask & 0x800 else msg.yaw_rate
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        cur_yaw = quat_to_euler(self.state.quaternion_wxyz)[2]
        if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
            frame = msg.coordinate_frame
            pos = np.array([msg.x, msg.y, msg.z], dtype=float)
            if frame not in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
                             mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED):
                self._drop("setpoint_unsupported")
                return
            body = frame in (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED)
            if body:  # body-frame vectors turn with the heading (PX4 semantics)
                cy, sy = math.cos(cur_yaw), math.sin(cur_yaw)
                vel = np.array([cy * vel[0] - sy * vel[1], sy * vel[0] + cy * vel[1], vel[2]])
                pos = np.array([cy * pos[0] - sy * pos[1], sy * pos[0] + cy * pos[1], pos[2]])
        else:  # SET_POSITION_TARGET_GLOBAL_INT
            frame = msg.coordinate_frame
            if frame not in (mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
                self._drop("setpoint_unsupported")
                return
            alt = msg.alt
            if frame == mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT and self.home_ned is not None:
                alt = alt + self.origin.amsl_m - float(self.home_ned[2])
            pos = self._global_to_ned(msg.lat_int * 1e-7, msg.lon_int * 1e-7, alt) if use_pos else np.zeros(3)
            body = False
        values = [*(pos if use_pos else ()), *(vel if use_vel else ()), *(() if yaw is None else (yaw,)), yaw_rate]
        if not _finite(*values):
            self._drop("setpoint_non_finite")
            return
        if frame in (mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED):
            pos = pos + self.state.position_ned_m
        if (use_pos and np.abs(pos).max() > MAX_POSITION_M) or (use_vel and np.abs(vel).max() > MAX_SPEED_MPS) or abs(
            yaw_rate
        ) > 10.0 or (yaw is not None and abs(yaw) > 10.0):
            self._drop("setpoint_out_of_range")
            return
        if use_pos:
            self._setpoint = ("position", pos, yaw, 0.0)
        else:
            self._setpoint = ("velocity", vel, yaw, yaw_rate)
        self._setpoint_wall = self.wall_s
        self._count("setpoints")
        if self.mode == MODE_OFFBOARD and self.source == "own":
            self._apply_setpoint()

    def _apply_setpoint(self) -> None:
        if self._setpoint is None or self.state is None or not self.armed:
            return
        kind, vec, yaw, yaw_rate = self._setpoint
        if kind == "position":
            self.autopilot.goto(self.state, vec, yaw)
        else:
            self.autopilot.velocity(self.state, vec, yaw, yaw_rate)

    # ----------------------------------------------------------------- rotor commands
    def _on_rotor_command(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if not lk.policy.rotor_commands:
            self._drop("rotor_command_wrong_link")
            return
        if self.intake.offer(msg, self.sim_s):
            self._count("rotor_commands")
            self._last_rotor_usec = int(msg.time_usec)
            latch = latch_setpoint_of(msg.controls[4])
            if latch is None:
                self._drop("latch_setpoint_invalid")  # (the rotors are taken; the latches keep their setpoint)
            else:
                self.latch_setpoint = latch
            if self.config.hil_await_coordinator:
                self._await_coordinator = True  # the coordinator is back: lockstep with it again

    # ----------------------------------------------------------------- parameters
    def _on_param_list(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=True):
            self._drop("wrong_target")
            return
        for i in range(self.params.count):
            if not self._reply(lk, self.params.value_message(i), out):
                break  # this sender's budget is spent: the client re-requests what it misses

    def _on_param_read(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=True):
            self._drop("wrong_target")
            return
        i = msg.param_index if msg.param_index >= 0 else self.params.index(_param_name(msg.param_id))
        if i is None or not 0 <= i < self.params.count:
            self._drop("param_unknown")  # PX4 stays silent; clients time out (e.g. QGC's _HASH_CHECK)
            return
        self._reply(lk, self.params.value_message(i), out)

    def _on_param_set(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            self._drop("wrong_target")
            return
        name = _param_name(msg.param_id)
        i = self.params.index(name)
        if i is None:
            self._drop("param_unknown")
            return
        error = policy.param_set_error(self.params.specs[i], msg.param_type, self.armed, self._authority)
        if error is not None:  # PARAM_ERROR, then (for clients that do not know it) the value in force
            self._drop("param_rejected")
            self._reply(lk, policy.param_error(msg, i, error), out)
        elif not self.params.set_from_wire(name, msg.param_value, msg.param_type):
            self._drop("param_rejected")
        elif name in ("MARS_CMD_HZ", "MARS_CMD_MISS"):
            self.intake.params = self._intake_params()
        self._reply(lk, self.params.value_message(i), out)  # the value in force, changed or not

    # ----------------------------------------------------------------- missions (mission_protocol)
    def _on_mission(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        broadcast_ok = msg.get_type() == "MISSION_REQUEST_LIST"
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=broadcast_ok):
            self._drop("wrong_target")
            return
        for name, reply in self.mission.handle(msg, lk.name, self.wall_s):
            self._reply(self.links[name], reply, out)
        self._flush_mission_texts()
        version = self.mission.versions[0]
        if version != self._mission_version:  # a new mission (or none): fly it from its start
            self._mission_version = version
            self.runner.load(self.mission.plans[0])
            self.mission.current_seq = self.runner.current
            if self.mode == MODE_MISSION and not self.runner.items and self.state is not None:
                self._set_mode(MODE_HOLD)
            self._mission_msgs.append(self.runner.current_message(self.mode == MODE_MISSION))

    def _on_mission_set_current(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            self._drop("wrong_target")
            return
        if self._set_mission_current(msg.seq, False) != mavlink.MAV_RESULT_ACCEPTED:
            self._drop("mission_set_current_invalid")

    # ----------------------------------------------------------------- small services
    def _on_ping(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if msg.target_system == 0 and msg.target_component == 0:  # a request: answer to the sender
            self._reply(lk, mavlink.MAVLink_ping_message(
                msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()), out)

    def _on_timesync(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        if msg.tc1 == 0:
            self._reply(lk, mavlink.MAVLink_timesync_message(int(self.wall_s * 1e9), msg.ts1), out)

    def _on_ftp(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        """MAVFTP: no file system. A quick NAK saves MAVProxy a 10 s timeout before the param list."""
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            self._drop("wrong_target")
            return
        payload = bytes(msg.payload)
        seq = payload[0] | payload[1] << 8
        session, opcode = payload[2], payload[3]
        if opcode in (1, 2):  # TerminateSession, ResetSessions: nothing open, trivially done
            reply_op, size, err = FTP_ACK, 0, 0
        else:
            reply_op, size = FTP_NAK, 1
            err = (FTP_ERR_FILE_NOT_FOUND if opcode in FTP_PATH_OPCODES
                   else FTP_ERR_INVALID_SESSION if opcode in FTP_SESSION_OPCODES else FTP_ERR_UNKNOWN_COMMAND)
        body = struct.pack("<HBBBBBBI", (seq + 1) & 0xFFFF, session, reply_op, size, opcode, 0, 0, 0)
        data = body + bytes([err]) + bytes(251 - len(body) - 1)
        self._reply(lk, mavlink.MAVLink_file_transfer_protocol_message(
            0, msg.get_srcSystem(), msg.get_srcComponent(), list(data)), out)

    def _on_ignored(self, msg, lk: _Link, out: list[Outgoing]) -> None:
        self._count(f"ignored.{msg.get_type()}")  # GCS heartbeats, legacy stream requests...

    # ----------------------------------------------------------------- HIL link (lockstep)
    def _on_hil(self, msg, t: str, lk: _Link, out: list[Outgoing]) -> None:
        if t == "HIL_STATE_QUATERNION":
            if self.defer_own_state:
                self._deferred.append(lambda: self._apply_hil_state(msg))
            else:
                self._apply_hil_state(msg)
            return
        if t == "NAMED_VALUE_INT":
            mask = latch_from_message(msg)
            if mask is None:
                self._count(f"ignored.{t}")
                return
            self.latches = mask  # the latch sensor, forwarded to the coordinator before this step's IMU frame
            for name, other in self.links.items():
                if other.policy.forward_sensors:
                    out.append(Outgoing(name, self._pack(other, latch_message(msg.time_boot_ms / 1000.0, mask))))
            return
        if t not in ("HIL_SENSOR", "ODOMETRY"):
            self._count(f"ignored.{t}")
            return
        values = ([msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro, msg.zgyro] if t == "HIL_SENSOR"
                  else [msg.x, msg.y, msg.z, *msg.q, msg.vx, msg.vy, msg.vz])
        if not _finite(*values):
            self._drop("hil_non_finite")
            return
        frames = self.assembler.feed_frames(msg)
        if frames is None:
            return
        forward = [name for name, other in self.links.items() if other.policy.forward_sensors]
        if forward:  # (on the real-time path: straight from the received fields)
            upstream = frames.upstream_messages()
            for name in forward:
                other = self.links[name]
                out.extend(Outgoing(name, self._pack(other, m)) for m in upstream)
        if self.defer_own_state:
            self._deferred.append(lambda: self._apply_sensors(frames))
        else:
            self._apply_sensors(frames)
        # lockstep: the sensor time stamps the step; answer with the motor outputs for it
        t_s = frames.imu.time_usec / 1e6
        self.sim_s = t_s
        self._next_control = t_s + self.control_dt_s
        self._hil_pending = (int(msg.time_usec), lk.name)
        if self._await_coordinator:
            return  # answered when the coordinator's command for this step arrives (or on release)
        self._answer_hil(out)

    def _apply_hil_state(self, msg) -> None:
        """HIL_STATE_QUATERNION: the unit centre's ground truth, for its own telemetry and checks."""
        q = np.array(msg.attitude_quaternion, dtype=float)
        values = [*q, msg.rollspeed, msg.pitchspeed, msg.yawspeed]
        if not _finite(*values) or not 0.5 < np.linalg.norm(q) < 1.5:
            self._drop("hil_non_finite")
            return
        pos = WIRE_ORIGIN.to_ned(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)  # sitl.hil's encoding
        self.set_state(RigidBodyState(msg.time_usec * 1e-6, pos, np.array([msg.vx, msg.vy, msg.vz]) * 0.01,
                                      q / np.linalg.norm(q), np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed])))

    def _apply_sensors(self, frames: SensorFrames) -> None:
        packet = frames.packet()
        self.imu = ImuSample(packet.t_s, self.sysid, packet.imu.gyro_frd_radps, packet.imu.accel_frd_mps2)
        if packet.truth is not None:
            self.set_state(packet.truth)

    def _answer_hil(self, out: list[Outgoing]) -> None:
        time_usec, name = self._hil_pending
        self._hil_pending = None
        lk = self.links[name]
        sp = self._motor_setpoint_n() / self.full_scale_n
        mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        controls = [float(x) for x in sp] + [latches_open(self.latch_setpoint)] + [0.0] * 11
        out.append(Outgoing(lk.name, self._pack(lk, mavlink.MAVLink_hil_actuator_controls_message(
            time_usec, controls, mode, 1))))

    def _motor_setpoint_n(self) -> np.ndarray:
        """One HIL step's motor outputs (N): due scenario faults enter the motor model, the control step
        runs, and the motors are driven to the clamped, eta-scaled command."""
        while self._scheduled_failures and self._scheduled_failures[0][0] <= self.sim_s + 1e-9:
            _, rotor, eta = self._scheduled_failures.pop(0)
            self.inject_failure(rotor, eta)
        self._count("hil_steps")
        self._control_step()
        return self.motors.setpoint(self.motor_commands_n if self.armed else np.zeros(4))

    # ================================================================= in-process messages
    # The same steps as the HIL and coordinator links, with the messages as objects instead of MAVLink
    # bytes: what the in-process engine calls. The values are already at wire precision (float32,
    # microseconds), so a unit driven this way moves its motors exactly as over MAVLink.
    def take_sensors(self, packet: SensorPacket, unit_truth: RigidBodyState | None = None) -> SensorPacket:
        """A HIL step: the unit's sensors (HIL_SENSOR/ODOMETRY) and, when given, its centre's truth
        (HIL_STATE_QUATERNION). Returns the telemetry it forwards to the coordinator (HIGHRES_IMU and
        ODOMETRY carry exactly these fields)."""
        if unit_truth is not None:
            self.set_state(unit_truth)
        self.latches = packet.latches
        self.imu = packet.imu
        if packet.truth is not None:
            self.set_state(packet.truth)
        self.sim_s = packet.t_s
        self._next_control = packet.t_s + self.control_dt_s
        return packet

    def take_rotor_command(self, cmd: RotorCommand) -> bool:
        """A coordinator command (SET_ACTUATOR_CONTROL_TARGET's values); True if it is now held."""
        if cmd.unit_id != self.sysid:
            return self.intake.drop("wrong_target")
        # cmd.thrusts_n are wire values (float32 controls x full scale): x / full scale is the control back
        s = self.full_scale_n
        a, b, c, d = cmd.thrusts_n.tolist()
        t_usec = round(cmd.t_s * 1e6)
        if not self.intake.accept(a / s, b / s, c / s, d / s, t_usec, self.sim_s, cmd.thrusts_n):
            return False
        self._count("rotor_commands")
        self._last_rotor_usec = t_usec
        self.latch_setpoint = cmd.latch_setpoint
        return True

    def drive_motors(self) -> ActuatorOutput:
        """The HIL answer (HIL_ACTUATOR_CONTROLS' values): what the motors are driven to for this step."""
        sp = self._motor_setpoint_n()
        if sp is not self.intake.thrusts_n:  # (the held command itself is at wire precision already)
            sp = wire_thrust(sp, self.full_scale_n)
        return ActuatorOutput(self.sim_s, self.sysid, sp, self.latch_setpoint)

    def arm(self) -> int:
        """MAV_CMD_COMPONENT_ARM_DISARM (arm) as the coordinator sends it; returns the MAV_RESULT."""
        return self._arm_disarm(1.0, 0.0)

    def set_mode(self, mode: tuple[int, int]) -> int:
        """MAV_CMD_DO_SET_MODE to a PX4 (main, sub) mode; returns the MAV_RESULT."""
        return self._set_mode(mode)

    # ================================================================= control
    def _limits(self) -> GuidanceLimits:
        p = self.params
        xy = p["MPC_XY_VEL_MAX"]
        if self.mode == MODE_MISSION and self.runner.speed_mps is not None:
            xy = min(xy, self.runner.speed_mps)  # DO_CHANGE_SPEED, within PX4's limit
        return GuidanceLimits(xy, p["MPC_Z_VEL_MAX_UP"], p["MPC_Z_VEL_MAX_DN"], p["MPC_TKO_SPEED"])

    def _control_step(self) -> None:
        t = self.sim_s
        if not self.armed:
            self.motor_commands_n = np.zeros(4)
            return
        cmd = self.intake.command_n(t)
        if not (self.mode == MODE_OFFBOARD and cmd is not None):
            self.run_deferred()  # the unit's own control and fail-safes read its state
        if self.mode == MODE_OFFBOARD and cmd is not None:
            if self.source != "coordinator":
                self.source = "coordinator"
                self._text("Coordinator drives the rotors")
            self.motor_commands_n = cmd  # (the intake's own array: a new one per accepted command)
            self.autopilot.landed = False
            self._account_battery()
            return
        if self.source == "coordinator":  # the stream was lost: fail-safe (MARS_FS_ACT)
            self._count("coordinator_failsafe")
            if int(self.params["MARS_FS_ACT"]) == 1 or self.state is None:
                self._disarm("Coordinator lost: motors off")
                return
            self._hand_back(self.state)
            self.autopilot.land(self.state)
            self.mode = MODE_LAND
            self._text("Coordinator lost: landing", mavlink.MAV_SEVERITY_CRITICAL)
        if self.state is None:
            self.motor_commands_n = np.zeros(4)
            return
        self._account_battery()
        thrusts, event = self.autopilot.update(t, self.state, self._limits(), self.params["MPC_LAND_SPEED"])
        self.motor_commands_n = np.array(thrusts, dtype=float)
        if self.mode == MODE_MISSION:
            self._mission_step(t, event)
        if event == "takeoff_done" and self.mode == MODE_TAKEOFF:
            self.mode = MODE_HOLD
            self._text("Takeoff complete: holding")
        elif event == "landed":
            self._landed_since = t
            self._text("Landed")

    def _watchdogs(self) -> None:
        p = self.params
        if self.mode == MODE_OFFBOARD and self.source == "own":
            stale = self._setpoint_wall is None or self.wall_s - self._setpoint_wall > p["COM_OF_LOSS_T"]
            if stale and not self.intake.is_live(self.sim_s):
                self._count("offboard_loss")
                if self.state is not None:
                    self.autopilot.hold(self.state)
                self.mode = MODE_HOLD
                self._text("Offboard setpoints lost: holding", mavlink.MAV_SEVERITY_WARNING)
        if self.armed and self.source == "own" and self.autopilot.phase == Phase.IDLE:
            if self._landed_since is not None and p["COM_DISARM_LAND"] >= 0:
                if self.sim_s - self._landed_since >= p["COM_DISARM_LAND"]:
                    self._landed_since = None
                    self._disarm("Disarmed after landing")
            elif not self._took_off and self._armed_at is not None and p["COM_DISARM_PRFLT"] >= 0:
                if self.sim_s - self._armed_at >= p["COM_DISARM_PRFLT"]:
                    self._disarm("Disarmed: no takeoff")

    # ================================================================= telemetry
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
        """(voltage mV, current cA, remaining %): a 4S 2.2 Ah pack drawn by thrust (~2 A per N).
        Clamped to the wire fields (uint16 mV, int16 cA, int8 %); not a number -> MAVLink's "not
        sent" value (UINT16_MAX, -1, -1). Above 327.67 A the current field saturates at 32767."""
        current_a = self._current_a()
        remaining = max(0.0, 1.0 - self.battery_used_c / (2.2 * 3600))
        volts = 4 * (3.6 + 0.6 * remaining) - 0.02 * current_a

        def wire(x: float, lo: int, hi: int, unknown: int) -> int:
            return unknown if math.isnan(x) else int(min(max(x, lo), hi))

        return (wire(volts * 1000, 0, 65534, 65535), wire(current_a * 100, 0, 32767, -1),
                wire(round(remaining * 100) if math.isfinite(remaining) else remaining, 0, 100, -1))

    def _stream_message(self, mid: int):
        R = mavlink
        s = self.state
        tb = self._time_boot_ms()
        if mid == R.MAVLINK_MSG_ID_SYS_STATUS:
            mv, ca, pct = self._battery()
            return R.MAVLink_sys_status_message(SENSORS, SENSORS, SENSORS, 200, mv, ca, pct, 0, 0, 0, 0, 0, 0)
        if mid == R.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return R.MAVLink_extended_sys_state_message(R.MAV_VTOL_STATE_UNDEFINED, self._landed_state())
        if mid == R.MAVLINK_MSG_ID_BATTERY_STATUS:
            mv, ca, pct = self._battery()
            cells = [mv // 4 if mv != 65535 else 65535] * 4 + [65535] * 6
            used_mah = int(self.battery_used_c / 3.6)
            return R.MAVLink_battery_status_message(0, R.MAV_BATTERY_FUNCTION_ALL, R.MAV_BATTERY_TYPE_LIPO, 32767,
                                                    cells, ca, used_mah, -1, pct, 0, R.MAV_BATTERY_CHARGE_STATE_OK,
                                                    [0] * 4, 0, 0)
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
            return R.MAVLink_gps_raw_int_message(int(self.sim_s * 1e6), R.GPS_FIX_TYPE_3D_FIX, lat, lon, alt, 80, 120,
                                                 int(min(speed * 100, 65534)), cog, 12, alt, 300, 500, 200, 0, 0)
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

    def _current_a(self) -> float:
        """The pack's current: ~2 A per newton of rotor thrust (0.5 A armed and idle, 0.3 A disarmed);
        any number of rotors (the assembly vehicle has 4N); unbounded, NaN with a NaN command."""
        if not self.armed:
            return 0.3
        return 0.5 + 2.0 * sum(map(abs, self.motor_commands_n.tolist()))

    def _account_battery(self) -> None:
        current_a = self._current_a()
        if math.isfinite(current_a):  # a NaN command must not poison the charge count
            self.battery_used_c += int(current_a * 100) * 0.01 * self.control_dt_s


def _param_name(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


_HANDLERS = {
    "COMMAND_LONG": Vehicle._on_command,
    "COMMAND_INT": Vehicle._on_command,
    "SET_MODE": Vehicle._on_set_mode,
    "SET_POSITION_TARGET_LOCAL_NED": Vehicle._on_position_target,
    "SET_POSITION_TARGET_GLOBAL_INT": Vehicle._on_position_target,
    "SET_ACTUATOR_CONTROL_TARGET": Vehicle._on_rotor_command,
    "PARAM_REQUEST_LIST": Vehicle._on_param_list,
    "PARAM_REQUEST_READ": Vehicle._on_param_read,
    "PARAM_SET": Vehicle._on_param_set,
    "MISSION_REQUEST_LIST": Vehicle._on_mission,
    "MISSION_COUNT": Vehicle._on_mission,
    "MISSION_CLEAR_ALL": Vehicle._on_mission,
    "MISSION_REQUEST_INT": Vehicle._on_mission,
    "MISSION_REQUEST": Vehicle._on_mission,
    "MISSION_ITEM_INT": Vehicle._on_mission,
    "MISSION_ITEM": Vehicle._on_mission,
    "MISSION_ACK": Vehicle._on_mission,
    "MISSION_WRITE_PARTIAL_LIST": Vehicle._on_mission,
    "MISSION_SET_CURRENT": Vehicle._on_mission_set_current,
    "PING": Vehicle._on_ping,
    "TIMESYNC": Vehicle._on_timesync,
    "FILE_TRANSFER_PROTOCOL": Vehicle._on_ftp,
    "HEARTBEAT": Vehicle._on_ignored,
    "REQUEST_DATA_STREAM": Vehicle._on_ignored,
    "SYSTEM_TIME": Vehicle._on_ignored,
    "RADIO_STATUS": Vehicle._on_ignored,
}
