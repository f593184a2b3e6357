"""The whole assembly as one MAVLink vehicle: the coordinator of pieces behind a PX4-persona endpoint.

Ground stations (MAVSDK, MAVProxy, QGroundControl) see one quadrotor-like system (default system id 1,
component 1): they watch its position and attitude (the CoM estimate of the piece it follows), arm it,
take it off, send offboard position/velocity setpoints and land it as they would a single drone. The
protocol side is the unit firmware's `Vehicle` (heartbeats, streams, commands with ACKs, parameters,
offboard watchdog, untrusted-input counters), not a copy of it: `AssemblyVehicle` plugs a different
flight core into that mode machine.

A docked assembly is a flight of one piece: the coordinator of pieces (mars_link.coordination.pieces) flies
every flight, docked or not (free units assembling, a reconfiguration, a commanded separation).

    AssemblyFlightCore  the Vehicle's guidance phases (UnitAutopilot: hold / takeoff ramp / go-to /
                        velocity / land / return, PX4's speed limits) shape a reference that becomes the
                        structure's mission (`SetpointSource`); the thrusts it hands the mode machine are
                        the ones the pieces' coordinators (controller + FTC allocator) commanded.
    AssemblyVehicle     Vehicle + that core; reports the piece it follows (the tracked unit's, else the one
                        with the most units); STATUSTEXT for every coordinator and executor event (faults,
                        reallocations, splits, docks, plans, a change of the followed piece); assembly
                        parameters; MAV_CMD_INJECT_FAILURE names motors 1..4N (unit u rotor r = 4 (u - 1) + r).
    VehicleFlight       sans-IO, one control period: the units' telemetry in; the coordinator of pieces;
                        the followed piece's estimate (once settled) into the vehicle, its sensor guard
                        watched (`VehicleSensorWatch`); the vehicle's tick; out go each unit's rotor command,
                        with its latch setpoint, and the vehicle's frames. Used in process
                        (mars_link.vehicles.vehicle_sim.VehicleSim, `mars-link vehicle`) and inside the SITL
                        coordinator process (`sitl up --vehicle`, mars_link.processes.vehicle_host).

What a ground station sees of a flight of pieces, in order: a landed vehicle; after arm and takeoff,
free units take off and dock in the air layer by layer (Algorithm 3), then the structure flies to the
takeoff setpoint and follows setpoints as one vehicle. A fault its detectors find (or a separation of the
scenario) makes the coordinator pause the setpoints, split, move and dock the pieces, and return to the
latest setpoint; setpoints sent meanwhile wait for that return. Nothing starts a manoeuvre while the
vehicle is on the ground or landing.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.params import INT32, REAL32, ParamSpec, ParamStore, unit_param_specs
from firmware_models.unit_controller import Phase, UnitAutopilot
from firmware_models.vehicle import LINK_API, LINK_GCS, LinkPolicy, Outgoing, Vehicle, VehicleConfig
from firmware_models.vehicle_streams import SENSOR_BITS, StreamService
from mars_link.config.scenario import Scenario
from mars_link.control.base import ControlOutput
from mars_link.coordination.pieces import Piece, PiecesCoordinator
from mars_link.core.assembly import ROTORS_PER_UNIT, AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.core.events import EventKind, event
from mars_link.core.messages import RotorCommand, SensorPacket, wire_thrust, wire_time
from mars_link.core.rotations import quat_to_rotmat
from mars_link.core.state import RigidBodyState
from mars_link.flight.events import event_text
from mars_link.models.estimation_outdoor import estimate_settled
from mars_link.models.trajectories import Trajectory, TrajectoryPoint
from mars_link.reconfig.execution import units_text
from mars_link.vehicles.vehicle_sensor_watch import VehicleSensorWatch

DEFAULT_SYSID = 1
#: coordinator event type -> STATUSTEXT severity
EVENT_SEVERITY = {
    "fault": mavlink.MAV_SEVERITY_WARNING,
    "uncontrollable": mavlink.MAV_SEVERITY_CRITICAL,
    "reallocation": mavlink.MAV_SEVERITY_NOTICE,
    "fault_detected": mavlink.MAV_SEVERITY_WARNING,
    "fault_retracted": mavlink.MAV_SEVERITY_NOTICE,
    "unit_lost": mavlink.MAV_SEVERITY_CRITICAL,
    "unit_died": mavlink.MAV_SEVERITY_CRITICAL,
    "reconfig_failed": mavlink.MAV_SEVERITY_ERROR,
    "diverged": mavlink.MAV_SEVERITY_EMERGENCY,
    "estimator_reset": mavlink.MAV_SEVERITY_WARNING,
}


class SetpointSource(Trajectory):
    """The structure's mission: whatever reference the flight core set last (held between)."""

    duration_s = math.inf

    def __init__(self, start: TrajectoryPoint) -> None:
        self.point = start

    def sample(self, t_s: float) -> TrajectoryPoint:
        return self.point


class PiecesDrive:
    """Stands where UnitAutopilot keeps its 1x1 controller: the shaped reference becomes the structure's
    mission (read by the coordinator of pieces at its next step), and the thrusts are the ones the pieces'
    coordinators commanded this period, in the whole layout's rotor order."""

    def __init__(self, pieces: PiecesCoordinator, source: SetpointSource, n_rotors: int) -> None:
        self.pieces = pieces
        self.source = source
        self.thrusts_n = np.zeros(n_rotors)

    def reset(self) -> None:
        """Take-off: every piece's controller starts afresh (it ran, unheard, on the ground)."""
        for piece in self.pieces.pieces.values():
            reset = getattr(piece.coordinator.controller, "reset", None)
            if reset is not None:
                reset()

    def update(self, t_s: float, state: RigidBodyState, reference: TrajectoryPoint) -> ControlOutput:
        self.source.point = reference
        return ControlOutput(self.thrusts_n.copy())


class AssemblyFlightCore(UnitAutopilot):
    """UnitAutopilot's guidance phases, flying the structure through the coordinator of pieces."""

    def __init__(self, pieces: PiecesCoordinator, source: SetpointSource, model: AssemblyModel,
                 control_hz: float) -> None:
        super().__init__(model.vehicle, control_hz)
        self.model = model
        self.drive = PiecesDrive(pieces, source, model.n_rotors)
        self.controller = self.drive
        self.zero = np.zeros(model.n_rotors)


def assembly_param_specs(sysid: int, model: AssemblyModel, ftc: str) -> list[ParamSpec]:
    """The unit's PX4-named parameters (takeoff altitude, speeds, landing, disarm, failure injection)
    without the unit-only MARS_* ones, then the assembly's own (read-only)."""
    from mars_link.config.scenario import FTC_MODES

    px4 = [s for s in unit_param_specs(sysid, model.vehicle) if not s.name.startswith("MARS_")]
    return px4 + [
        ParamSpec("MARS_UNITS", model.n_units, INT32, 1, 1000, True, "units in the assembly"),
        ParamSpec("MARS_ROTORS", model.n_rotors, INT32, 4, 4000, True, "rotors in the assembly (motor instances)"),
        ParamSpec("MARS_MASS", float(model.mass_kg), REAL32, 0.0, 1e6, True, "assembly mass, kg"),
        ParamSpec("MARS_FTC", FTC_MODES.index(ftc), INT32, 0, len(FTC_MODES) - 1, True,
                  "allocation mode: " + ", ".join(f"{i} {m}" for i, m in enumerate(FTC_MODES))),
    ]


@dataclass
class SimConfig:
    """The vehicle's options (`mars-link vehicle`, `sitl up --vehicle`, multi-vehicle runs)."""

    sysid: int = DEFAULT_SYSID
    start_north_m: float = 0.0  # the start moved by this (and turned by start_yaw_deg about the origin)
    start_east_m: float = 0.0
    start_yaw_deg: float = 0.0
    params: dict | None = None  # start-up parameter values (MIS_TAKEOFF_ALT, ...)
    signing_key: bytes | None = None  # MAVLink signing on the client links (control_policy)
    require_signing: bool = False  # unsigned clients may only read
    map_path: str | None = None  # obstacle map: mission legs planned around it (mars_link.planning.mission_legs)
    ulog_path: str | None = None  # set: the vehicle writes a ULog (.ulg) there (mars_link.logs)


class AssemblyVehicle(Vehicle):
    """The PX4-persona Vehicle flying an assembly (one piece or several): client links only (gcs, api),
    no rotor intake; it follows the tracked piece."""

    def __init__(self, pieces: PiecesCoordinator, model: AssemblyModel, source: SetpointSource,
                 config: SimConfig, control_hz: float, ftc: str, wall_time_s: float,
                 battery_failsafe: dict[str, float] | None = None) -> None:
        """`config.signing_key`: signed clients get full control (control_policy); `config.require_signing`:
        unsigned clients may only read; `battery_failsafe`: the scenario's packs' failsafe parameters."""
        client = LinkPolicy(require_signing=config.require_signing, sign_outgoing=config.require_signing,
                            unsigned_reads=True)
        vc = VehicleConfig(unit_id=config.sysid, vehicle=model.vehicle, control_hz=control_hz,
                           signing_key=config.signing_key, links={LINK_GCS: client, LINK_API: client})
        self.pieces = pieces
        super().__init__(vc, wall_time_s, flight_core=AssemblyFlightCore(pieces, source, model, control_hz))
        specs = assembly_param_specs(config.sysid, model, ftc)
        fixed = {sp.name for sp in specs if sp.read_only}
        # the scenario's packs set the low-battery failsafe (COM_LOW_BAT_ACT, ...); the options may override it
        params = {**(battery_failsafe or {}), **(config.params or {})}
        for name in params:
            if name in fixed:
                raise UserInputError(f"parameter {name} is read-only (it follows from the assembly and options)")
        self.params = ParamStore(specs, params)
        self.model = model
        self.motor_count = model.n_rotors
        self.motor_commands_n = np.zeros(model.n_rotors)
        self.on_failure = None  # callable(unit, rotor | None, eta): the motor path (set by the host)
        # callable(sensor, type, instance) -> MAV_RESULT: the units' sensor paths (vehicle_sensor_watch)
        self.on_sensor_failure = None
        self.sensor_health = None  # the followed piece's SensorGuard: SYS_STATUS health bits (vehicle_sensor_watch)
        self._unit_batteries: dict = {}  # unit -> its last BatterySample report
        self._battery_t: float | None = None
        self._seen = {"coordinator": 0, "executor": 0}
        self.followed: tuple[int, ...] | None = None
        self._follow_event: dict | None = None
        self.stream_service = AssemblyStreamService(self, wall_time_s)

    @property
    def core(self) -> AssemblyFlightCore:
        return self.autopilot

    def believed_eta(self) -> np.ndarray:
        """Every rotor's believed efficiency, the whole layout's rotor order (failure_detector_status)."""
        return np.concatenate([self.pieces.eta_believed[u] for u in self.model.unit_ids])

    def rotor_thrusts_n(self) -> np.ndarray:
        """The 4N thrusts to command this step (zeros when disarmed or idle)."""
        cmd = self.motor_commands_n
        if not self.armed or cmd.shape != (self.model.n_rotors,):
            return np.zeros(self.model.n_rotors)
        return cmd

    def inject_failure(self, rotor: int, eta: float) -> None:
        """MAV_CMD_INJECT_FAILURE: motor instance 1..4N (0 = all) into the units' motor path only."""
        if self.on_failure is None:
            return
        if rotor == 0:
            for u in self.model.unit_ids:
                self.on_failure(u, None, eta)
        else:
            self.on_failure(self.model.unit_ids[(rotor - 1) // ROTORS_PER_UNIT], (rotor - 1) % ROTORS_PER_UNIT + 1, eta)

    def inject_sensor_failure(self, sensor: str, kind: str, instance: int) -> int:
        """MAV_CMD_INJECT_FAILURE of a sensor: every unit's (instance 0) or the i-th unit's sensor path."""
        if self.on_sensor_failure is None:
            return self.command_service.refuse(mavlink.MAV_RESULT_UNSUPPORTED, "no sensor failures in this run")
        result = self.on_sensor_failure(sensor, kind, instance)
        if result == mavlink.MAV_RESULT_ACCEPTED:
            where = "all units" if instance == 0 else f"unit {self.model.unit_ids[instance - 1]}"
            self._text(f"Failure injected: {sensor} {kind}, {where}", mavlink.MAV_SEVERITY_WARNING)
        elif result == mavlink.MAV_RESULT_DENIED:
            return self.command_service.refuse(result, f"no unit {instance} (1..{len(self.model.unit_ids)}, 0 all)")
        elif result == mavlink.MAV_RESULT_UNSUPPORTED:
            return self.command_service.refuse(result, f"a unit has no {sensor} {kind}")
        return result

    def _unhealthy_sensors(self) -> int:
        bad = set() if self.sensor_health is None else self.sensor_health.unhealthy_sensors()
        return sum(SENSOR_BITS[s] for s in bad if s in SENSOR_BITS)

    def step_motors(self, dt_s: float) -> np.ndarray:
        raise NotImplementedError("the assembly's rotors are driven by its units (VehicleFlight)")

    def take_unit_batteries(self, t_s: float, packets) -> None:
        """The units' battery reports -> the assembly's pack as BATTERY_STATUS/SYS_STATUS show it and its
        low-battery failsafe reads it: the currents summed, the lowest voltage, and the lowest remaining
        charge (the assembly's endurance is its emptiest pack's: that unit's rotors go first)."""
        fresh = False
        for p in packets:
            if p.battery is not None:
                self._unit_batteries[p.unit_id] = p.battery
                fresh = True
        if not fresh:
            return
        reports = self._unit_batteries.values()
        current = sum(b.current_a for b in reports)
        known = [b.remaining for b in reports if b.remaining >= 0]
        used = self.battery.used_c
        if self._battery_t is not None and t_s > self._battery_t:
            used += self.battery.current_a * (t_s - self._battery_t)
        self._battery_t = t_s
        self.battery.report(min(b.voltage_v for b in reports), current, min(known) if known else math.nan,
                            used if math.isfinite(used) else 0.0)

    def report_event(self, event: dict) -> None:
        """STATUSTEXT for an event (severity by its type)."""
        self._text(event_text(event), EVENT_SEVERITY.get(str(event.get("type")), mavlink.MAV_SEVERITY_INFO))

    def tick(self, wall_time_s: float, sim_time_s: float) -> list[Outgoing]:
        """Vehicle.tick, after queueing a STATUSTEXT for each event the coordinator recorded since
        the last tick (reported one control period after the step that recorded it)."""
        for ev in self.new_events():
            self.report_event(ev)
        return super().tick(wall_time_s, sim_time_s)

    def new_events(self) -> list[dict]:
        """The coordinator's and the executor's events since the last call, in time order."""
        new = []
        for name, events in (("coordinator", self.pieces.events), ("executor", self.pieces.executor.events)):
            new += events[self._seen[name]:]
            self._seen[name] = len(events)
        new.sort(key=lambda e: e["t_s"])
        if self._follow_event is not None:  # (after the dock or split that made it)
            new.append(self._follow_event)
            self._follow_event = None
        return new

    def follow(self, t_s: float) -> Piece:
        """The piece the vehicle reports (the tracked one); a STATUSTEXT when it changes."""
        piece = self.pieces.tracked_piece()
        units = tuple(sorted(piece.units))
        if units != self.followed:
            if self.followed is not None:
                self._follow_event = event(t_s, EventKind.FOLLOWING, units=list(units),
                                           text=f"Following u{units_text(units)} ({len(units)} units)")
            self.followed = units
        return piece

    def _land_detect(self, t: float) -> str | None:
        """No landing while the coordinator manoeuvres: a rebuild on the ground sets the structure down on
        purpose, and it takes off again by itself (PX4 would disarm the vehicle on the ground)."""
        if self.pieces.executor.phase != "mission":
            self.manual_service.touch_since_s = None
            return None
        return super()._land_detect(t)

    def flying(self) -> bool:
        """Armed and off the ground under a guidance phase (not landing): manoeuvres may start."""
        phase = self.autopilot.phase
        return self.armed and phase not in (Phase.IDLE, Phase.LAND) and not self.autopilot.landed

    def drives_rotors(self) -> bool:
        """Armed under a guidance phase: the pieces' thrusts go to the units (also taking off and landing)."""
        return self.armed and self.autopilot.phase != Phase.IDLE


class AssemblyStreamService(StreamService):
    """The assembly's telemetry: ACTUATOR_OUTPUT_STATUS carries its 4N rotors (up to MAVLink's 32)."""

    v: AssemblyVehicle

    def message(self, mid: int):
        if mid == mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS:
            v = self.v
            n = min(32, v.model.n_rotors)
            cmd = np.clip(v.rotor_thrusts_n() / v.full_scale_n, 0.0, 1.0)[:n]
            return mavlink.MAVLink_actuator_output_status_message(
                int(v.sim_s * 1e6), (1 << n) - 1, [float(x) for x in cmd] + [0.0] * (32 - n))
        return super().message(mid)


def vehicle_scenario(scenario: Scenario) -> Scenario:
    """The scenario as the vehicle flies it: setpoints are for the CoM; the trajectory is unused."""
    s = copy.deepcopy(scenario)
    s.tracked = "com"
    return s


def start_point(scenario: Scenario, model: AssemblyModel, trajectory: Trajectory, config: SimConfig) -> TrajectoryPoint:
    """Where the structure's CoM starts: the scenario's start (under its trajectory's first point), turned
    by `start_yaw_deg` about the origin and moved by `start_north_m`/`start_east_m` (several vehicles in
    one air space)."""
    from mars_link.flight.build import start_pose, yaw_quat

    com, yaw = start_pose(scenario, model, trajectory)
    turn = math.radians(config.start_yaw_deg)
    moved = quat_to_rotmat(yaw_quat(turn)) @ np.asarray(com, dtype=float) + np.array(
        [config.start_north_m, config.start_east_m, 0.0])
    return TrajectoryPoint(moved, yaw_rad=yaw + turn)


def attach_legs(vehicle: Vehicle, scenario: Scenario, map_path: str | None, believed_eta):
    """Mission legs between the vehicle's mission runner and its flight core (mars_link.planning.mission_legs):
    planned around the map (`map_path`, else the scenario's [mission] map) for the believed faults."""
    from mars_link.planning.mission_legs import LegConfig, attach_mission_legs

    return attach_mission_legs(vehicle, LegConfig(map_path or scenario.mission.get("map"), tuple(scenario.layout),
                                                  scenario.preset), believed_eta)


class VehicleFlight:
    """One control period of the vehicle's flight (one piece or several); sans-IO. The followed piece's
    coordinator leaves its sensor guard's findings and the position-loss failsafe to the vehicle
    (`VehicleSensorWatch`: PX4's hold, then land, as flight modes)."""

    def __init__(self, scenario: Scenario, model: AssemblyModel, config: SimConfig, wall_time_s: float,
                 telemetry_timeout_s: float | None = None) -> None:
        from mars_link.flight.build import make_pieces_coordinator, make_trajectory

        self.scenario = scenario
        self.model = model
        trajectory = make_trajectory(scenario, model)  # (where the structure starts; its snap weighs plans)
        self.source = SetpointSource(start_point(scenario, model, trajectory, config))
        self.pieces, _ = make_pieces_coordinator(scenario, model, self.source, telemetry_timeout_s,
                                                 plan_for=trajectory, vehicle=True)
        self.pieces.manoeuvres_allowed = False
        self.vehicle = AssemblyVehicle(self.pieces, model, self.source, config, scenario.sim.control_hz,
                                       scenario.ftc, wall_time_s,
                                       scenario.battery.failsafe if scenario.battery is not None else None)
        self.estimate: RigidBodyState | None = None
        self.estimate_ready = False  # the estimate has settled once (estimation_outdoor.estimate_settled)
        self.estimator_resets = 0  # the followed piece's EKF restarts on the measured positions (after gated batches)
        self.events: list[dict] = []  # the sensor guard's findings, the failsafe's and the estimator's resets
        self.sensor_watch: VehicleSensorWatch | None = None
        self._followed: Piece | None = None
        self._resets_seen = 0
        self.full_scale_n = model.vehicle.full_scale_thrust_n
        self._take_over(self.vehicle.follow(0.0))

    @property
    def executor(self):
        return self.pieces.executor

    def eta_believed(self) -> np.ndarray:
        return self.vehicle.believed_eta()

    def tell_fault(self, unit: int, rotor: int | None, eta: float, t_s: float) -> None:
        """A fault told to the coordinator (`faults_known`)."""
        told = self.eta_believed()
        told[self.model.unit_slots(unit) if rotor is None else self.model.rotor_slot(unit, rotor)] = eta
        self.pieces.set_faults(told, t_s, "fault told to the coordinator")

    def _take_over(self, piece: Piece) -> None:
        """The followed piece's sensor guard reports to the vehicle, whose flight modes fly the failsafe."""
        if piece is self._followed:
            return
        self._followed = piece
        c = piece.coordinator
        c.failsafe = None
        c.guard_events = False
        ekf = c.estimator
        self._resets_seen = 0 if ekf is None else ekf.stats.position_resets  # (a moved EKF keeps its count)
        if c.guard is None:
            return
        if self.sensor_watch is None:
            self.sensor_watch = VehicleSensorWatch(self.vehicle, c.guard, self.events)
        else:
            self.sensor_watch.watch(c.guard)

    def _followed_estimate(self, t_s: float, piece: Piece) -> RigidBodyState | None:
        """The followed piece's estimate once its EKF has settled (None before); its guard watched and its
        EKF's position resets reported."""
        self._take_over(piece)
        last = piece.coordinator.last
        est = None if last is None else last.estimate
        ekf = piece.coordinator.estimator
        if ekf is None or est is None:
            return est
        if not ekf.initialised or not (self.estimate_ready or estimate_settled(ekf)):
            return None
        self.estimate_ready = True  # (once: a failsafe's dead reckoning later grows the sigma again)
        if self.sensor_watch is not None:
            self.vehicle.set_state(est)  # (the failsafe holds where the estimate says the assembly is)
            self.sensor_watch.update(t_s)
        resets = ekf.stats.position_resets
        if resets > self._resets_seen:  # e.g. after a touchdown shock
            self.estimator_resets += resets - self._resets_seen
            self._resets_seen = resets
            ev = event(t_s, EventKind.ESTIMATOR_RESET, text="EKF reset on positions",
                       reason=f"{ekf.params.position_reset_after_batches} position updates gated")
            self.events.append(ev)
            self.vehicle.report_event(ev)
        return est

    def step(self, t_s: float, packets: list[SensorPacket], wall_time_s: float,
             live: set[int] | None = None) -> tuple[list[RotorCommand], list[Outgoing]]:
        """The coordinator of pieces (always: every piece's EKF and detector run, also on the ground), the
        followed piece's estimate into the vehicle, the vehicle's tick (its guidance sets the mission for
        the next period); the units' commands: the pieces' thrusts while the vehicle's guidance drives the
        rotors, else zero, and every unit's latch setpoint (`live`: only for these units)."""
        v = self.vehicle
        v.take_unit_batteries(t_s, packets)
        self.pieces.manoeuvres_allowed = v.flying()
        self.pieces.rotors_driven = v.drives_rotors()  # (the units get zeros otherwise: rotor_thrusts_n)
        if v.armed and v.autopilot.phase == Phase.TAKEOFF and self.executor.phase == "grounded":
            self.executor.begin_take_off(t_s)  # free units: they take off when the vehicle does
        commands = self.pieces.step(t_s, packets)
        piece = v.follow(t_s)
        est = self._followed_estimate(t_s, piece)
        if est is not None:
            self.estimate = est
            # (the IMU logged is the followed piece's first unit's: its units are rigidly docked)
            first = piece.units[0]
            v.set_state(est, next((p.imu for p in packets if p.unit_id == first), None))
        drive = v.autopilot.drive
        drive.thrusts_n = np.zeros(self.model.n_rotors)
        for c in commands:
            drive.thrusts_n[self.model.unit_slots(c.unit_id)] = c.thrusts_n
        out = v.tick(wall_time_s, t_s)
        thrusts = wire_thrust(v.rotor_thrusts_n(), self.full_scale_n)  # zeros unless armed and flying
        tw = wire_time(t_s)
        return [RotorCommand(tw, u, thrusts[self.model.unit_slots(u)], self.pieces.latch_setpoint[u])
                for u in self.model.unit_ids if live is None or u in live], out

