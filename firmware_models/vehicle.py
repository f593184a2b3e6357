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

The microservices are members of the `Vehicle`, as PX4's mavlink module holds its mission, parameter
and FTP managers: each a class in its own module that owns its state and holds a reference back to the
vehicle for what it shares (plumbing: `_reply`, `_send`, `_text`, `_count`, `_drop`, `_for_me`; the flight
state; `params`). command_service (vehicle_commands: commands and the mode machine), offboard_service,
manual_service (orbit, sticks, attitude, land detector), follow_service, param_service, mission_service,
geofence_service (fence and rally), log_service (log download), small_service (vehicle_services: ping,
timesync, FTP, STATUSTEXT relay), shell_service (SERIAL_CONTROL shell), hil_service (the HIL link and its
in-process twin), stream_service (telemetry), px4_service (PX4's own interface); vehicle_links (links,
frame splitting) and vehicle_modes are shared definitions. This module keeps the flight state, the
plumbing, the dispatch (message type -> a service's handler), the control step and the watchdogs.

Untrusted input: every datagram is split into frames here (no bytes carried over to the next
datagram, so a truncated frame cannot swallow the next good one); anything malformed, unsigned where
signing is required, mis-addressed, non-finite or out of range is dropped and counted by reason in
`drop_counts()`; replies are rate-limited per link so a flood cannot be amplified.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models import control_policy as policy
from mars_link.core.geo import EARTH_RADIUS_M  # noqa: F401 (re-exported)
from firmware_models.battery_monitor import BatteryMonitor
from firmware_models.geofence import Geofence
from mars_link.core.geo import GeoOrigin, origin_from_env
from firmware_models.mission_protocol import MissionProtocol
from firmware_models.mission_runner import MissionRunner
from firmware_models.motor import MotorModel, MotorParams
from firmware_models.params import ParamStore, unit_param_specs
from firmware_models.rotor_intake import IntakeParams, RotorIntake
from firmware_models.sensor_failures import SensorFailures
from mars_link.core.messages import BatterySample, EscSample, wire_battery
from mars_link.models.esc import EscSensor
from mars_link.mavlink.signing import ACCEPTED, UNSIGNED, advance_outgoing_clock, is_signed
from firmware_models.unit_controller import GuidanceLimits, Phase, UnitAutopilot
from firmware_models.vehicle_commands import (  # noqa: F401 (re-exported)
    ACTION_COMMANDS, COMMAND_DEDUP_S, FAILURE_TYPE_ETA, FAILURE_UNIT_SYSTEM_MOTOR, SETPOINT_PROOF_OF_LIFE_S,
    CommandService,
)
from firmware_models.vehicle_follow import FollowService
from firmware_models.vehicle_geofence import GeofenceService
from firmware_models.vehicle_hil import HilService
from firmware_models.vehicle_logs import LogService
from firmware_models.vehicle_manual import ManualService
from firmware_models.vehicle_links import (  # noqa: F401 (re-exported)
    LINK_API, LINK_COORDINATOR, LINK_GCS, LINK_HIL, Link, LinkPolicy, Outgoing, default_links,
)
from firmware_models.vehicle_links import finite as _finite  # noqa: F401 (re-exported)
from firmware_models.vehicle_missions import MissionService
from firmware_models.vehicle_modes import (  # noqa: F401 (re-exported)
    MODE_ORBIT, SUB_POSCTL_ORBIT,
    MAIN_ACRO, MAIN_ALTCTL, MAIN_AUTO, MAIN_MANUAL, MAIN_OFFBOARD, MAIN_POSCTL, MAIN_STABILIZED, MODE_HOLD, MODE_LAND,
    MODE_MISSION, MODE_OFFBOARD, MODE_POSCTL, MODE_RTL, MODE_TAKEOFF, SUB_LAND, SUB_LOITER, SUB_MISSION, SUB_READY,
    SUB_RTL, SUB_TAKEOFF,
)
from firmware_models.vehicle_offboard import MAX_POSITION_M, MAX_SPEED_MPS, OffboardService  # noqa: F401
from firmware_models.vehicle_params import ParamService
from firmware_models.vehicle_px4 import Px4Service
from firmware_models.vehicle_services import SmallService
from firmware_models.vehicle_shell import ShellService
from firmware_models.vehicle_streams import (  # noqa: F401 (re-exported)
    CAPABILITIES, DEFAULT_STREAM_HZ, MIN_STREAM_INTERVAL_S, REFUSED_MESSAGES, SENSOR_BITS, SENSORS, StreamService,
)
from mars_link.mavlink import codec as mavlink_codec
from mars_link.core.assembly import VehicleParams, vehicle_preset
from mars_link.core.errors import UserInputError
from mars_link.core.messages import LATCH_ALL
from mars_link.core.state import ImuSample, RigidBodyState

WORLD_SYSID = 200  # the SITL world process (mars_link/processes/lockstep.py)


#: messages that command a unit or change its mission: from anyone but the coordinator, each is recorded
FOREIGN_CONTROL_MESSAGES = frozenset({
    "COMMAND_LONG", "COMMAND_INT", "SET_MODE", "MISSION_COUNT", "MISSION_ITEM", "MISSION_ITEM_INT",
    "MISSION_CLEAR_ALL", "MISSION_WRITE_PARTIAL_LIST", "MISSION_SET_CURRENT", "SET_POSITION_TARGET_LOCAL_NED",
    "SET_POSITION_TARGET_GLOBAL_INT", "SET_ATTITUDE_TARGET", "MANUAL_CONTROL", "PARAM_SET",
    "SET_ACTUATOR_CONTROL_TARGET"})
#: the motors' commands while disarmed, as the ESCs see them (never written)
_DISARMED_COMMANDS = np.zeros(4)
FOREIGN_TRAFFIC_KEYS = 64  # distinct (link, sender, message) kept; beyond, only counted


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
    sign_hil: bool = False  # with a key: the HIL (world) link is signed both ways too (a SITL run's processes)
    # False: the key is a SITL run's own (per-run) key for its internal links (coordinator, HIL) only; the
    # client links (gcs, api) keep the rules of a vehicle without a key (unsigned clients have full control)
    client_links_keyed: bool = True
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
    # set: this vehicle writes a ULog (.ulg) there from the start (mars_link.logs; or later: start_ulog)
    ulog_path: str | None = None

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



class Vehicle:
    """The unit firmware state machine. Not thread-safe: one runner drives it.

    `flight_core`: what the mode machine flies with (default: the lone unit's `UnitAutopilot`); any
    object with UnitAutopilot's guidance methods, e.g. the assembly's (mars_link.vehicles.assembly_vehicle).
    """

    motor_count = 4  # highest motor instance MAV_CMD_INJECT_FAILURE may name

    def __init__(self, config: VehicleConfig | None = None, wall_time_s: float = 0.0, flight_core=None) -> None:
        c = (config or VehicleConfig()).checked()
        self.config = c
        self.ulog = None  # mars_link.logs.VehicleUlog while this vehicle writes a .ulg
        self.origin = c.origin()
        self.vehicle = vehicle_preset(c.vehicle) if isinstance(c.vehicle, str) else c.vehicle
        self.sysid, self.compid = c.unit_id, c.component_id
        signed = c.signing_key is not None
        overrides = {"MARS_COORD_SYS": c.coordinator_sysid, "MARS_COORD_COMP": c.coordinator_compid,
                     "MARS_SIGN_REQ": int(signed), **c.params}
        self.params = ParamStore(unit_param_specs(c.unit_id, self.vehicle), overrides)
        policies = c.links if c.links is not None else default_links(signed, c.sign_client_links, c.sign_hil and signed)
        for name, p in policies.items():
            if (p.require_signing or p.sign_outgoing) and not signed:
                raise UserInputError(f"link {name!r} requires signing but no signing key is configured")
        self._keyed = {n for n in policies if c.signing_key is not None
                       and (c.client_links_keyed or n in (LINK_COORDINATOR, LINK_HIL))}  # links the key rules
        self.links = {n: Link(n, p, self.sysid, self.compid, c.signing_key if n in self._keyed else None, wall_time_s)
                      for n, p in policies.items()}
        shared = next((lk.budgets.total for lk in self.links.values()), None)  # one total reply budget, all links
        for lk in self.links.values():
            lk.budgets.total = shared or lk.budgets.total
        self._authority = policy.SAFETY  # of the frame being dispatched (control_policy.frame_authority)
        self.on_frame_in = None  # callable(link, frame bytes) for every frame that passed parsing and signing
        self._sender: tuple = ()  # (link, sysid, compid) of that frame: whose reply budget answers pay from
        self.full_scale_n = self.vehicle.full_scale_thrust_n
        self.motors = MotorModel(MotorParams.for_vehicle(self.vehicle))
        self.intake = RotorIntake(self._intake_params())
        self.autopilot = UnitAutopilot(self.vehicle, c.control_hz) if flight_core is None else flight_core
        self.control_dt_s = 1.0 / c.control_hz
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
        #: command or mission traffic from anyone but the coordinator (a ground station, a stray script):
        #: (link, system, component, message) -> [first sim time s, count]; the run's summary lists it as events
        self.foreign_traffic: dict[tuple, list] = {}
        self.events: list[tuple[float, str]] = []  # (sim time, text): STATUSTEXT history
        self._next_heartbeat = wall_time_s
        self._next_control = 0.0
        self._landed_since: float | None = None
        self._armed_at: float | None = None
        self._took_off = False
        self._pending_text: list[tuple[int, str]] = []
        self.battery = BatteryMonitor()  # the pack as measured (world's samples over HIL); thresholds, action
        self._battery_checked: tuple[float, int] | None = None  # (remaining, params.version) last checked
        self.defer_own_state = False  # set by the lockstep unit runner: see run_deferred
        self.hil_stepped_by_host = False  # set by the unit process: its engine takes each HIL step (hil_service)
        self._deferred: list = []
        self.latch_setpoint = LATCH_ALL  # the docking latches: engaged until the coordinator opens some
        self.latches = 0  # the latch sensor: the sides that hold a docked neighbour (from the world)
        self._scheduled_failures: list[tuple[float, int, float, str]] = []  # (sim time, rotor, eta, kind), sorted
        self.sensor_failures = SensorFailures(c.unit_id)  # the sensor path's injected failures
        self.esc: EscSensor | None = None  # the ESCs' telemetry (mars_link.models.esc), set by the composition root
        self._scheduled_sensor_failures: list[tuple[float, str, str]] = []  # (sim time, sensor, type), sorted
        self.mission = MissionProtocol(self.origin)
        self.runner = MissionRunner(self.autopilot, self.origin)
        self._mission_msgs: list = []  # MISSION_CURRENT / MISSION_ITEM_REACHED to broadcast
        self.hil_service = HilService(self)
        self.stream_service = StreamService(self, wall_time_s)
        self.command_service = CommandService(self)
        self.mission_service = MissionService(self)
        self.offboard_service = OffboardService(self)
        self.geofence_service = GeofenceService(self)
        self.manual_service = ManualService(self)
        self.follow_service = FollowService(self)
        self.param_service = ParamService(self)
        self.log_service = LogService(self)
        self.shell_service = ShellService(self)
        self.small_service = SmallService(self)
        self.px4_service = Px4Service(self)
        self.legs = None  # mission legs between the runner and the core (mars_link.planning.mission_legs)
        # message type -> the handler, bound once (a service's method)
        self._handlers = {t: getattr(getattr(self, member), name) for t, (member, name) in _HANDLERS.items()}
        if c.ulog_path:
            self.start_ulog(c.ulog_path)

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

    def geofence(self) -> Geofence:
        """The stored fence as geometry (the planners read it: mars_link.planning.mission_legs)."""
        return self.geofence_service.geofence()

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

    def inject_failure(self, rotor: int, eta: float, kind: str = "eta") -> None:
        """Local fault injection (rotor 1..4, 0 = all): the motor model, and what its ESC sees (`kind`)."""
        self.motors.set_rotor_eta(0, rotor, eta)
        if self.esc is not None:
            self.esc.set_kind(rotor, kind)

    def inject_sensor_failure(self, sensor: str, kind: str, instance: int) -> int:
        """A failure of this unit's own sensor (one of each: instance 0 or 1) in its sensor path."""
        R = mavlink
        if instance > 1:
            return self.command_service.refuse(R.MAV_RESULT_DENIED, f"one {sensor} (instance 0 or 1)")
        if not self.sensor_failures.supports(sensor, kind):  # e.g. a barometer this flight's sensors lack
            return self.command_service.refuse(R.MAV_RESULT_UNSUPPORTED, f"no {sensor} {kind} in this flight")
        self.sensor_failures.inject(sensor, kind)
        self._text(f"Failure injected: {sensor} {kind}", mavlink.MAV_SEVERITY_WARNING)
        return R.MAV_RESULT_ACCEPTED

    def schedule_failure(self, t_s: float, rotor: int, eta: float, kind: str = "eta") -> None:
        """A scenario fault (rotor 1..4, 0 = all) that enters the motor model at the first HIL step at
        or after sim time t_s, before that step's motor outputs are computed."""
        self._scheduled_failures.append((t_s, rotor, eta, kind))
        self._scheduled_failures.sort()

    def schedule_sensor_failure(self, t_s: float, sensor: str, kind: str) -> None:
        """A scenario sensor failure ("ok" ends one) that enters the sensor path with the first packet at
        or after sim time t_s."""
        self._scheduled_sensor_failures.append((t_s, sensor, kind))
        self._scheduled_sensor_failures.sort(key=lambda x: x[0])

    def _sensor_failures_due(self, t_s: float) -> None:
        while self._scheduled_sensor_failures and self._scheduled_sensor_failures[0][0] <= t_s + 1e-9:
            _, sensor, kind = self._scheduled_sensor_failures.pop(0)
            if sensor == "esc":
                if self.esc is not None:
                    self.esc.fail(kind)
            else:
                self.sensor_failures.inject(sensor, kind)

    def _esc_sample(self, t_s: float) -> EscSample | None:
        """The ESCs' telemetry at a HIL step, before its command: what the motors did over the last period."""
        if self.esc is None:
            return None
        return self.esc.sample(t_s, *self.esc_inputs())

    def esc_inputs(self) -> tuple[np.ndarray, np.ndarray]:
        """What the ESCs follow: the motors' commands (zeros while disarmed) and their efficiencies (eta).
        Read-only: the in-process engine samples every unit's ESCs at once from these (mars_link.models.esc)."""
        return (self.motor_commands_n if self.armed else _DISARMED_COMMANDS), self.motors.eta

    def sensor_failure_due(self, t_s: float) -> bool:
        """Whether a scheduled sensor failure comes due at `t_s` (this HIL step applies it)."""
        due = self._scheduled_sensor_failures
        return bool(due) and due[0][0] <= t_s + 1e-9

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
            frames = mavlink_codec.split_frames(data, lk.decoder, self._drop, check)
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
        has_key = link in self._keyed
        for msg, frame in frames:
            self._count("rx")
            if self.on_frame_in is not None:
                self.on_frame_in(link, frame)
            self._authority = policy.frame_authority(
                lk.verifier is not None and is_signed(frame), lk.policy.require_signing, has_key)
            # whose reply budget pays: each signed sender its own; every other sender of a link shares the
            # link's, so spoofed (rotating) system ids cannot mint fresh budgets (and all of them a total)
            self._sender = ((link, msg.get_srcSystem(), msg.get_srcComponent())
                            if self._authority == policy.SAFETY and has_key else (link, "unsigned"))
            try:
                self._dispatch(msg, lk, out)
            except (ValueError, TypeError, OverflowError, struct.error):
                self._drop("malformed_fields")  # a decoded frame whose fields we cannot use
        hil = self.hil_service
        pending = hil.pending
        if pending is not None and pending[0] in (hil.last_rotor_usec, hil.step_skipped_usec) \
                and not self.hil_stepped_by_host:
            hil.answer(out)  # the coordinator's command for the pending step (and any arm/mode
            # command in the same datagram) is in, or it said it sends none: run the step
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
        return self.hil_service.pending is not None

    def release_hil(self, wall_time_s: float) -> list[Outgoing]:
        """The runner gave up waiting for the coordinator: answer the pending step with what the unit
        holds (the last command within MARS_CMD_MISS periods, then the fail-safe), and stop waiting
        until the coordinator's commands come back."""
        self.wall_s = max(self.wall_s, wall_time_s)
        self.run_deferred()
        out: list[Outgoing] = []
        hil = self.hil_service
        if hil.pending is not None:
            self._count("hil_released")
            hil.await_coordinator = False
            if not self.hil_stepped_by_host:  # (else the host's engine answers it: hil_service.answer_step)
                hil.answer(out)
        return out

    def arm(self) -> int:
        """MAV_CMD_COMPONENT_ARM_DISARM (arm) as the coordinator sends it; returns the MAV_RESULT."""
        return self.command_service.arm_disarm(1.0, 0.0)

    def set_mode(self, mode: tuple[int, int]) -> int:
        """MAV_CMD_DO_SET_MODE to a PX4 (main, sub) mode; returns the MAV_RESULT."""
        return self.command_service.set_mode(mode)

    def start_ulog(self, config):
        """Write a ULog (.ulg) from now on: `config` a path or a `mars_link.logs.UlogConfig`. Returns the
        recorder (`mars_link.logs.VehicleUlog`); a file that cannot be opened is reported, never raised."""
        from firmware_models.vehicle_ulog import UlogConfig, VehicleUlog

        self.stop_ulog()
        self.ulog = VehicleUlog(self, config if isinstance(config, UlogConfig) else UlogConfig(config))
        return self.ulog

    def stop_ulog(self) -> dict | None:
        """Close the .ulg (if any); its status (file, stopped_reason, errors, dropped_writes, samples)."""
        log, self.ulog = self.ulog, None
        if log is None:
            return None
        log.close()
        return log.status()

    def _ulog_sample(self) -> None:
        """The ULog's topics for this step, when due at their rate. A runner that defers the unit's own
        state (`defer_own_state`) gets them off the step's critical path, with that state."""
        log = self.ulog
        if log is None or not log.due(self.sim_s):
            return
        t_s = self.sim_s
        if self.defer_own_state:
            self._deferred.append(lambda: log.sample(t_s))
        else:
            log.sample(t_s)

    def notify(self, text: str, severity: int = mavlink.MAV_SEVERITY_WARNING) -> None:
        """A STATUSTEXT from the runner (e.g. "logging stopped"), sent with the next tick."""
        self._text(text, severity)

    def hello(self, link: str) -> Outgoing:
        """A HEARTBEAT on a non-telemetry link (HIL, coordinator): peers learn the unit's address."""
        lk = self.links[link]
        return Outgoing(link, self._pack(lk, self.stream_service.heartbeat()))

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
        if self.ulog is not None:
            self._ulog_sample()
        self._watchdogs()
        if wall_time_s >= self._next_heartbeat:
            self._next_heartbeat = max(self._next_heartbeat + 1.0, wall_time_s + 0.5)
            self._broadcast(self.stream_service.heartbeat(), out)
        self.stream_service.tick(wall_time_s, out)
        for name, msg in self.mission.tick(self.wall_s):
            self._reply(self.links[name], msg, out)
        self.mission_service.flush_texts()
        self.shell_service.tick(out)
        self.log_service.tick(out)
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

    def _pack(self, lk: Link, msg) -> bytes:
        """Encode for this link; a field outside its wire range is clamped and counted
        (telemetry.clamped), never raised (mars_link.mavlink.codec.encode_clamped)."""
        if lk.policy.sign_outgoing:
            advance_outgoing_clock(lk.encoder, self.wall_s)
        frame, clamped = mavlink_codec.encode_clamped(msg, lk.encoder)
        if clamped:
            self._count("telemetry.clamped")
        return frame

    def _send(self, lk: Link, msg, out: list[Outgoing]) -> None:
        """Append `msg` for `lk`; a message that cannot be encoded is counted and dropped: telemetry
        never stops a flight."""
        try:
            out.append(Outgoing(lk.name, self._pack(lk, msg)))
        except (*mavlink_codec.ENCODE_ERRORS, mavlink.MAVError):
            self._count("telemetry.encode_error")

    def _reply(self, lk: Link, msg, out: list[Outgoing]) -> bool:
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
        if self.ulog is not None:
            self.ulog.text(severity, text, self.sim_s)
        self.events.append((self.sim_s, text))
        if len(self.events) > 200:
            del self.events[:100]
        self._pending_text.append((severity, text))

    def _for_me(self, target_system: int, target_component: int, allow_broadcast: bool) -> bool:
        ok_sys = target_system == self.sysid or (allow_broadcast and target_system == 0)
        return ok_sys and target_component in (0, self.compid)

    # ================================================================= dispatch
    def _dispatch(self, msg, lk: Link, out: list[Outgoing]) -> None:
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
            self.hil_service.on_hil(msg, t, lk, out)
            return
        if t in ("HIL_SENSOR", "HIL_STATE_QUATERNION", "HIL_GPS", "ODOMETRY"):
            self._drop("hil_wrong_link")  # state input is trusted only from the physics link
            return
        handler = self._handlers.get(t)
        if handler is None:
            self._drop("unhandled_message")
            return
        if t in FOREIGN_CONTROL_MESSAGES and not (src == self.config.coordinator_sysid and lk.name == "coordinator"):
            self._note_foreign(lk.name, src, msg.get_srcComponent(), t)
        if self._authority < policy.required_authority(msg):  # e.g. unsigned control under --require-signing
            self._drop(f"policy.denied_{policy.AUTHORITY_NAMES[self._authority]}")
            for m in policy.refusal(msg):
                self._reply(lk, m, out)
            if t in ("COMMAND_LONG", "COMMAND_INT"):
                self.command_service.tell_refusal(msg.command, mavlink.MAV_RESULT_DENIED, "needs a signed link")
            return
        handler(msg, lk, out)

    def _note_foreign(self, link: str, sysid: int, compid: int, message: str) -> None:
        key = (link, sysid, compid, message)
        seen = self.foreign_traffic.get(key)
        if seen is not None:
            seen[1] += 1
        elif len(self.foreign_traffic) < FOREIGN_TRAFFIC_KEYS:
            self.foreign_traffic[key] = [self.sim_s, 1]
        else:
            self._count("foreign_traffic_unlisted")

    def foreign_traffic_events(self) -> list[dict]:
        """The command and mission traffic not from the coordinator, one entry per sender and message."""
        return [{"t_s": round(t, 6), "link": link, "sysid": sysid, "compid": compid, "message": message,
                 "count": n} for (link, sysid, compid, message), (t, n) in self.foreign_traffic.items()]

    # ================================================================= control
    def _limits(self) -> GuidanceLimits:
        """PX4's speeds: position targets (missions, goto, return) at MPC_XY_CRUISE (a DO_CHANGE_SPEED
        command or mission item instead), velocity targets up to MPC_XY_VEL_MAX, which bounds both."""
        p = self.params
        vmax = p["MPC_XY_VEL_MAX"]
        override = self.command_service.speed_override_mps
        xy = p["MPC_XY_CRUISE"] if override is None else override
        if self.mode == MODE_MISSION and self.runner.speed_mps is not None:
            xy = self.runner.speed_mps  # DO_CHANGE_SPEED
        return GuidanceLimits(min(xy, vmax), p["MPC_Z_VEL_MAX_UP"], p["MPC_Z_VEL_MAX_DN"], p["MPC_TKO_SPEED"],
                              velocity_max_mps=vmax)

    def _control_step(self) -> None:
        t = self.sim_s
        if not self.armed:
            self.motor_commands_n = np.zeros(4)
            return
        px4 = self.px4_service
        if px4.interface is not None:  # PX4's own interface (vehicle_px4) drives the rotors while it lets them run
            px4_n = px4.command_n(t)
            if not self.armed:  # (its failsafe disarmed the unit)
                self.motor_commands_n = np.zeros(4)
                return
            if px4_n is not None:
                if self.source != "coordinator":
                    self.source = "coordinator"
                    self._text("PX4 offboard (direct actuator) drives the rotors")
                self._drive_from_coordinator(px4_n)
                return
        cmd = self.intake.command_n(t)
        driven = cmd is not None and self.mode == MODE_OFFBOARD
        if not driven:
            self.run_deferred()  # the unit's own control and fail-safes read its state
            driven = cmd is not None and self.mode == MODE_OFFBOARD
        if driven:
            if self.source != "coordinator":
                self.source = "coordinator"
                self._text("Coordinator drives the rotors")
            self._drive_from_coordinator(cmd)
            return
        if self.source == "coordinator":  # the stream was lost: fail-safe (MARS_FS_ACT)
            self._count("coordinator_failsafe")
            if int(self.params["MARS_FS_ACT"]) == 1 or self.state is None:
                self.command_service.disarm("Coordinator lost: motors off")
                return
            self.command_service.hand_back(self.state)
            self.autopilot.land(self.state)
            self.mode = MODE_LAND
            self._text("Coordinator lost: landing", mavlink.MAV_SEVERITY_CRITICAL)
        if self.state is None:
            self.motor_commands_n = np.zeros(4)
            return
        self._battery_step()
        override = self.manual_service.guidance_step(t)  # orbit, sticks, attitude target (vehicle_manual)
        if override is not None:
            thrusts, event = override, None
        else:
            thrusts, event = self.autopilot.update(t, self.state, self._limits(), self.params["MPC_LAND_SPEED"])
        if event is None:
            event = self._land_detect(t)
        self.motor_commands_n = np.array(thrusts, dtype=float)
        if self.mode == MODE_MISSION:
            self.mission_service.step(t, event)
        if event == "takeoff_done" and self.mode == MODE_TAKEOFF:
            self.mode = MODE_HOLD
            self._text("Takeoff complete: holding")
        elif event == "landed":
            self._landed_since = t
            self._text("Landed")

    def _land_detect(self, t: float) -> str | None:
        """The land detector (manual_service); a subclass may hold it off (mars_link.vehicles.assembly_vehicle.AssemblyVehicle)."""
        return self.manual_service.land_detect(t)

    def _unhealthy_sensors(self) -> int:
        """SYS_STATUS bits to clear from onboard_control_sensors_health: the unit's failed sensors."""
        failures = self.sensor_failures
        return sum(bit for name, bit in SENSOR_BITS.items() if not failures.healthy(name))

    def _global_to_ned(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> np.ndarray:
        return self.origin.to_ned(lat_deg, lon_deg, alt_amsl_m)

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
            target = MODE_LAND if change.action == "land" else MODE_RTL
            set_mode = self.command_service.set_mode
            if self.mode != target and set_mode(target) != mavlink.MAV_RESULT_ACCEPTED and target == MODE_RTL:
                set_mode(MODE_LAND)  # no home to return to: land where it is

    def _measure_battery(self, sample: BatterySample, t_s: float) -> BatterySample:
        """The power module's sample: counted, and the unit's report for the coordinator (with remaining)."""
        p = self.params
        b = self.battery
        b.measure(t_s, sample.voltage_v, sample.current_a, p["BAT1_CAPACITY"], int(p["BAT1_N_CELLS"]),
                  p["BAT1_R_INTERNAL"])
        return wire_battery(b.voltage_v, b.current_a, b.remaining)

    def _drive_from_coordinator(self, held_n: np.ndarray) -> None:
        """A control step under the coordinator: its held command drives the motors."""
        self.motor_commands_n = held_n  # (the intake's own array: a new one per accepted command)
        self.autopilot.landed = False
        self._battery_step()

    def discount_stall(self, stalled_s: float, wall_time_s: float) -> None:
        """This process did not run for `stalled_s` (a host-wide stall, as its runner measures it:
        mars_link.runtime.pacing.StallMeter). Its clients most likely did not run either, so the watchdogs
        on their silence (offboard setpoints, manual sticks) do not count that time. Never past
        `wall_time_s` (now): a client heard from since is not credited twice."""
        offboard = self.offboard_service
        if offboard.setpoint_wall is not None:
            offboard.setpoint_wall = min(wall_time_s, offboard.setpoint_wall + stalled_s)
        self.manual_service.sticks_wall = min(wall_time_s, self.manual_service.sticks_wall + stalled_s)

    def _watchdogs(self) -> None:
        p = self.params
        if self.mode == MODE_OFFBOARD and self.source == "own":
            sp_wall = self.offboard_service.setpoint_wall
            stale = sp_wall is None or self.wall_s - sp_wall > p["COM_OF_LOSS_T"]
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
                    self.command_service.disarm("Disarmed after landing")
            elif not self._took_off and self._armed_at is not None and p["COM_DISARM_PRFLT"] >= 0:
                if self.sim_s - self._armed_at >= p["COM_DISARM_PRFLT"]:
                    self.command_service.disarm("Disarmed: no takeoff")
        self.geofence_service.step()



#: message type -> (the service that serves it, its method)
_HANDLERS: dict[str, tuple[str, str]] = {
    "COMMAND_LONG": ("command_service", "on_command"),
    "COMMAND_INT": ("command_service", "on_command"),
    "SET_MODE": ("command_service", "on_set_mode"),
    "SET_POSITION_TARGET_LOCAL_NED": ("offboard_service", "on_position_target"),
    "SET_POSITION_TARGET_GLOBAL_INT": ("offboard_service", "on_position_target"),
    "SET_ATTITUDE_TARGET": ("manual_service", "on_attitude_target"),
    "MANUAL_CONTROL": ("manual_service", "on_manual_control"),
    "FOLLOW_TARGET": ("follow_service", "on_follow_target"),
    "SERIAL_CONTROL": ("shell_service", "on_serial_control"),
    "LOG_REQUEST_LIST": ("log_service", "on_request_list"),
    "LOG_REQUEST_DATA": ("log_service", "on_request_data"),
    "LOG_REQUEST_END": ("log_service", "on_request_end"),
    "LOG_ERASE": ("log_service", "on_erase"),
    "SET_ACTUATOR_CONTROL_TARGET": ("offboard_service", "on_rotor_command"),
    "PARAM_REQUEST_LIST": ("param_service", "on_param_list"),
    "PARAM_REQUEST_READ": ("param_service", "on_param_read"),
    "PARAM_SET": ("param_service", "on_param_set"),
    **dict.fromkeys(("MISSION_REQUEST_LIST", "MISSION_COUNT", "MISSION_CLEAR_ALL", "MISSION_REQUEST_INT",
                     "MISSION_REQUEST", "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_ACK",
                     "MISSION_WRITE_PARTIAL_LIST"), ("mission_service", "on_mission")),
    "MISSION_SET_CURRENT": ("mission_service", "on_set_current"),
    "PING": ("small_service", "on_ping"),
    "STATUSTEXT": ("small_service", "on_statustext"),
    "TIMESYNC": ("small_service", "on_timesync"),
    "FILE_TRANSFER_PROTOCOL": ("small_service", "on_ftp"),
    **dict.fromkeys(("HEARTBEAT", "REQUEST_DATA_STREAM", "RADIO_STATUS"), ("small_service", "on_ignored")),
    "SYSTEM_TIME": ("offboard_service", "on_step_skip"),
}
