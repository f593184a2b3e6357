"""The whole assembly as one MAVLink vehicle: the coordinator behind a PX4-persona endpoint.

Ground stations (MAVSDK, MAVProxy, QGroundControl) see one quadrotor-like system (default system id 1,
component 1): they watch its position and attitude (the CoM estimate), arm it, take it off, send
offboard position/velocity setpoints and land it as they would a single drone. The protocol side is
the unit firmware's `Vehicle` (heartbeats, streams, commands with ACKs, parameters, offboard watchdog,
untrusted-input counters), not a copy of it: `AssemblyVehicle` plugs a different flight core into
that mode machine.

    AssemblyFlightCore   the Vehicle's guidance phases (UnitAutopilot: hold / takeoff ramp / go-to /
                         velocity / land / return, PX4's speed limits) shape a reference that a
                         `SetpointSource` hands to the assembly's Coordinator as its trajectory;
                         the coordinator's controller and FTC allocator give the 4N rotor thrusts.
    AssemblyVehicle      Vehicle + that core; STATUSTEXT for every coordinator event (faults,
                         reallocations, reconfigurations); assembly parameters; MAV_CMD_INJECT_FAILURE
                         names motors 1..4N (unit u rotor r = 4 (u - 1) + r).
    AssemblySim          sans-IO lockstep wiring of JSBSim world, unit motor paths, estimator,
                         coordinator and vehicle: `step(wall_time_s)` advances one control period
                         and returns the MAVLink bytes to send. `mars_link.processes.realtime` paces it in
                         real time behind UDP sockets.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.params import INT32, REAL32, ParamSpec, ParamStore, unit_param_specs
from firmware_models.unit_controller import UnitAutopilot
from firmware_models.vehicle import LINK_API, LINK_GCS, LinkPolicy, Outgoing, Vehicle, VehicleConfig
from firmware_models.vehicle_streams import SENSOR_BITS, StreamService
from mars_link.core.events import EventKind, event
from mars_link.core.assembly import ROTORS_PER_UNIT, AssemblyModel
from mars_link.control.base import ControlOutput
from mars_link.coordination.coordinator import Coordinator
from mars_link.core.errors import UserInputError
from mars_link.models.estimation_outdoor import estimate_settled
from mars_link.core.messages import RotorCommand, wire_thrust, wire_time
from mars_link.config.scenario import Scenario
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import Trajectory, TrajectoryPoint
from mars_link.flight.events import event_text
from mars_link.vehicles.vehicle_sensor_watch import VehicleSensorWatch, route_sensor_failure

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
#: consecutive position updates with every unit gated out before the EKF is restarted on them


class SetpointSource(Trajectory):
    """The coordinator's trajectory: whatever reference the flight core set last (held between)."""

    duration_s = math.inf

    def __init__(self, start: TrajectoryPoint) -> None:
        self.point = start

    def sample(self, t_s: float) -> TrajectoryPoint:
        return self.point


class _CoordinatorDrive:
    """Stands where UnitAutopilot keeps its 1x1 controller: the shaped reference goes to the
    coordinator (controller + FTC allocation over all rotors) instead."""

    def __init__(self, coordinator: Coordinator, source: SetpointSource) -> None:
        self.coordinator = coordinator
        self.source = source
        self.packets: list = []  # this control step's sensor packets (set by AssemblySim)

    def reset(self) -> None:
        reset = getattr(self.coordinator.controller, "reset", None)
        if reset is not None:
            reset()

    def update(self, t_s: float, state: RigidBodyState, reference: TrajectoryPoint) -> ControlOutput:
        self.source.point = reference
        self.coordinator.step(t_s, self.packets)
        return ControlOutput(self.coordinator.last.thrusts_n)


class AssemblyFlightCore(UnitAutopilot):
    """UnitAutopilot's guidance phases, flying the assembly through its coordinator."""

    def __init__(self, coordinator: Coordinator, control_hz: float) -> None:
        super().__init__(coordinator.model.vehicle, control_hz)
        self.model = coordinator.model
        start = TrajectoryPoint(np.zeros(3))
        source = coordinator.trajectory if isinstance(coordinator.trajectory, SetpointSource) else SetpointSource(start)
        coordinator.trajectory = source
        self.drive = _CoordinatorDrive(coordinator, source)
        self.controller = self.drive
        self.zero = np.zeros(self.model.n_rotors)


def vehicle_coordinator(scenario: Scenario, model: AssemblyModel, detector, eta: np.ndarray | None = None):
    """The coordinator behind an assembly vehicle: it owns the estimator (`Coordinator.estimate`, read by
    the vehicle every period, also while it does not fly); its reference is the vehicle's setpoint
    (SetpointSource); the vehicle flies the position-loss failsafe itself (VehicleSensorWatch)."""
    from mars_link.flight.build import make_coordinator, make_estimator

    coordinator = make_coordinator(scenario, model, SetpointSource(TrajectoryPoint(np.zeros(3))),
                                   make_estimator(scenario, model), detector, eta=eta)
    coordinator.failsafe = None
    coordinator.guard_events = False  # (the vehicle reports the guard's findings)
    return coordinator


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


class AssemblyVehicle(Vehicle):
    """The PX4-persona Vehicle flying an assembly: client links only (gcs, api), no rotor intake."""

    def __init__(self, coordinator: Coordinator, sysid: int = DEFAULT_SYSID, control_hz: float = 100.0,
                 ftc: str = "none", params: dict[str, float] | None = None, wall_time_s: float = 0.0,
                 signing_key: bytes | None = None, require_signing: bool = False, *,
                 model: AssemblyModel | None = None, flight_core: UnitAutopilot | None = None) -> None:
        """`signing_key`: signed clients get full control (control_policy); `require_signing`: unsigned
        clients may only read. `model` and `flight_core` default to the coordinator's (one rigid body);
        a flight of pieces gives the whole layout's and its own (mars_link.vehicles.pieces_vehicle)."""
        model = model or coordinator.model
        client = LinkPolicy(require_signing=require_signing, sign_outgoing=require_signing, unsigned_reads=True)
        config = VehicleConfig(unit_id=sysid, vehicle=model.vehicle, control_hz=control_hz, signing_key=signing_key,
                               links={LINK_GCS: client, LINK_API: client})
        self.coordinator = coordinator
        super().__init__(config, wall_time_s, flight_core=flight_core or AssemblyFlightCore(coordinator, control_hz))
        specs = assembly_param_specs(sysid, model, ftc)
        fixed = {sp.name for sp in specs if sp.read_only}
        for name in params or {}:
            if name in fixed:
                raise UserInputError(f"parameter {name} is read-only (it follows from the assembly and options)")
        self.params = ParamStore(specs, params or {})
        self.model = model
        self.motor_count = model.n_rotors
        self.motor_commands_n = np.zeros(model.n_rotors)
        self.on_failure = None  # callable(unit, rotor | None, eta): the motor path (set by AssemblySim)
        # callable(sensor, type, instance) -> MAV_RESULT: the units' sensor paths (vehicle_sensor_watch)
        self.on_sensor_failure = None
        self.sensor_health = None  # the estimator's SensorGuard: SYS_STATUS health bits (vehicle_sensor_watch)
        self._events_seen = 0
        self._unit_batteries: dict = {}  # unit -> its last BatterySample report
        self._battery_t: float | None = None
        self.stream_service = AssemblyStreamService(self, wall_time_s)

    @property
    def core(self) -> AssemblyFlightCore:
        return self.autopilot

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
        raise NotImplementedError("the assembly's rotors are driven by its units (AssemblySim)")

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
        """The coordinator's events since the last call."""
        events = self.coordinator.events
        new = events[self._events_seen:]
        self._events_seen = len(events)
        return new


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


# ----------------------------------------------------------------------------- in-process wiring
@dataclass
class SimConfig:
    sysid: int = DEFAULT_SYSID
    start_north_m: float = 0.0
    start_east_m: float = 0.0
    start_yaw_deg: float = 0.0
    params: dict | None = None  # start-up parameter values (MIS_TAKEOFF_ALT, ...)
    signing_key: bytes | None = None  # MAVLink signing on the client links (control_policy)
    require_signing: bool = False  # unsigned clients may only read
    map_path: str | None = None  # obstacle map: mission legs planned around it (mars_link.planning.mission_legs)
    ulog_path: str | None = None  # set: the vehicle writes a ULog (.ulg) there (mars_link.logs)


def vehicle_scenario(scenario: Scenario) -> Scenario:
    """The scenario as the vehicle flies it: setpoints are for the CoM; the trajectory is unused."""
    s = copy.deepcopy(scenario)
    s.tracked = "com"
    return s


def attach_legs(vehicle: Vehicle, scenario: Scenario, map_path: str | None, believed_eta):
    """Mission legs between the vehicle's mission runner and its flight core (mars_link.planning.mission_legs):
    planned around the map (`map_path`, else the scenario's [mission] map) for the believed faults."""
    from mars_link.planning.mission_legs import LegConfig, attach_mission_legs

    return attach_mission_legs(vehicle, LegConfig(map_path or scenario.mission.get("map"), tuple(scenario.layout),
                                                  scenario.preset), believed_eta)


class EngineSim:
    """What the in-process vehicles share (`AssemblySim`, mars_link.vehicles.pieces_vehicle.PiecesSim): the engine
    steps the world, the units and the vehicle's command source; a fault goes into a unit's motor path and
    is told to the coordinator (`_tell`) only with `faults_known`. Subclasses set scenario, world, units,
    vehicle, engine, model and events."""

    @property
    def t_s(self) -> float:
        return self.world.t_s

    def handle(self, data: bytes, wall_time_s: float, link: str) -> list[Outgoing]:
        return self.vehicle.handle(data, wall_time_s, link)

    def inject(self, unit: int, rotor: int | None, eta: float) -> None:
        """A fault in a unit's motor path; told to the coordinator only with `faults_known`."""
        t = self.t_s
        self.units.inject_failure(unit, rotor, eta)
        ev = event(t, EventKind.FAULT, unit=unit, rotor=rotor, eta=eta)
        self.events.append(ev)
        self.vehicle.report_event(ev)
        if self.scenario.faults_known:
            self._tell(unit, rotor, eta, t)

    def _tell(self, unit: int, rotor: int | None, eta: float, t_s: float) -> None:
        raise NotImplementedError

    def step(self, wall_time_s: float) -> list[Outgoing]:
        """One control period through the engine (faults due, sensing, units, vehicle and coordinator,
        motors, physics); returns the vehicle's frames to send."""
        self._wall_s = wall_time_s
        self._out = []
        self.engine.step()
        return self._out

    def unit_eta(self) -> list[float]:
        return [float(x) for x in self.units.eta(self.model.unit_ids)]

    def close(self) -> None:
        self.vehicle.stop_ulog()
        self.legs.close()
        self.world.close()


class AssemblySim(EngineSim):
    """World (one JSBSim body), unit motor paths, estimator, coordinator and the assembly vehicle,
    wired by direct calls in lockstep. Sans-IO: `handle(bytes, wall, link)` and `step(wall)` return
    the frames to send; `t_s` is simulation time (scenario faults fire at their `t` from the start)."""

    def __init__(self, scenario: Scenario, config: SimConfig | None = None, wall_time_s: float = 0.0) -> None:
        from mars_link.flight.build import make_detector, make_unit, make_world
        from mars_link.flight.engine import Engine, Flight, InProcessUnits

        cfg = config or SimConfig()
        self.scenario = s = vehicle_scenario(scenario)
        self.model = model = s.model()
        hz = s.sim.control_hz
        self.control_dt_s = 1.0 / hz
        self.eta_told = model.nominal_eta()
        yaw = math.radians(cfg.start_yaw_deg)
        self.world = make_world(s, model, s.sim.seed, np.array([cfg.start_north_m, cfg.start_east_m, 0.0]), yaw)
        # the vehicle starts landed: ground contact at take-off is not a rotor fault
        detector = make_detector(s, model, float(self.world.truth().position_ned_m[2]))
        self.coordinator = vehicle_coordinator(s, model, detector, self.eta_told)
        self.estimator = self.coordinator.estimator  # (the coordinator's; None: it flies on the truth)
        self.units = InProcessUnits({u: make_unit(s, model, u) for u in model.unit_ids}, self.world)
        params = {**(s.battery.failsafe if s.battery is not None else {}), **(cfg.params or {})}
        self.vehicle = AssemblyVehicle(self.coordinator, cfg.sysid, hz, s.ftc, params, wall_time_s,
                                       cfg.signing_key, cfg.require_signing)
        self.vehicle.on_failure = self.inject
        self.vehicle.on_sensor_failure = self.inject_sensor
        self.legs = attach_legs(self.vehicle, s, cfg.map_path, self.eta_believed)
        if cfg.ulog_path:
            self.vehicle.start_ulog(cfg.ulog_path)
        self.estimate: RigidBodyState | None = None
        self.estimator_resets = 0  # the EKF's own restarts on the measured positions (after gated batches)
        self.events: list[dict] = []  # faults (scenario and MAVLink), with coordinator.events = the record
        self.sensor_watch = None
        self.estimate_ready = False  # the estimate has settled once (estimation_outdoor.estimate_settled)
        if self.estimator is not None:  # the coordinator's detector reads the guard's usable IMUs; the vehicle reports
            self.sensor_watch = VehicleSensorWatch(self.vehicle, self.estimator, self.events)
        # the engine's loop; the vehicle's flight modes stand in front of the coordinator, and it flies until stopped
        flight = Flight(s, model, s.sim.seed, self.coordinator.trajectory, self.world, self.units, self.coordinator,
                        sorted(s.faults, key=lambda f: f.t_s), duration_s=math.inf)
        self.engine = Engine(flight, command_source=self._commands,
                             on_fault=lambda f, t: self.inject(f.unit, f.rotor, f.eta))
        self._wall_s = wall_time_s
        self._out: list[Outgoing] = []

    def _tell(self, unit: int, rotor: int | None, eta: float, t_s: float) -> None:
        sl = self.model.unit_slots(unit) if rotor is None else self.model.rotor_slot(unit, rotor)
        self.eta_told[sl] = eta
        self.coordinator.set_faults(self.eta_told, t_s, "fault told to the coordinator")

    def inject_sensor(self, sensor: str, kind: str, instance: int) -> int:
        """A sensor failure injected on the vehicle: into the named units' sensor paths."""
        units = route_sensor_failure(self.vehicle, self.units.vehicles, sensor, kind, instance)
        if isinstance(units, int):
            return units
        for u in units:
            self.units.vehicles[u].sensor_failures.inject(sensor, kind)
        self.events.append(event(self.t_s, EventKind.SENSOR_FAULT, sensor=sensor, failure=kind,
                                 unit=None if instance == 0 else units[0],
                                 text=f"Sensor fault: {sensor} {kind}, " + ("all units" if instance == 0 else f"unit {units[0]}")))
        return mavlink.MAV_RESULT_ACCEPTED

    def _commands(self, t: float, packets) -> list[RotorCommand]:
        """The engine's command source: estimate, the vehicle's tick (its coordinator runs when it flies),
        and the rotor thrusts it decided, one RotorCommand per unit."""
        self.vehicle.core.drive.packets = packets
        self.vehicle.take_unit_batteries(t, packets)
        est = self._estimate(t, packets)
        if est is not None:
            self.estimate = est
            self.vehicle.set_state(est)
        self._out = self.vehicle.tick(self._wall_s, t)
        wired = wire_thrust(self.vehicle.rotor_thrusts_n(), self.model.vehicle.full_scale_thrust_n)
        tw = wire_time(t)
        return [RotorCommand(tw, u, wired[self.model.unit_slots(u)]) for u in self.model.unit_ids]

    def _estimate(self, t: float, packets) -> RigidBodyState | None:
        est = self.coordinator.estimate(t, packets)  # (the gps profile's fixes, barometers and magnetometers too)
        ekf = self.estimator
        if ekf is None:
            return est
        if not ekf.initialised or not (self.estimate_ready or estimate_settled(ekf)):
            return None
        self.estimate_ready = True  # (once: a failsafe's dead reckoning later grows the sigma again)
        if self.sensor_watch is not None:
            self.vehicle.set_state(est)  # (the failsafe holds where the estimate says the assembly is)
            self.sensor_watch.update(t)
        if ekf.stats.position_resets > self.estimator_resets:  # e.g. after a touchdown shock
            self.estimator_resets = ekf.stats.position_resets
            ev = event(t, EventKind.ESTIMATOR_RESET, text="EKF reset on positions",
                       reason=f"{ekf.params.position_reset_after_batches} position updates gated")
            self.events.append(ev)
            self.vehicle.report_event(ev)
        return est

    def eta_believed(self) -> np.ndarray:
        return self.coordinator.eta_believed

    def event_lists(self) -> list[list[dict]]:
        """The run's event records: faults (scenario and MAVLink), the coordinator's."""
        return [self.events, self.coordinator.events]

    def truth(self) -> RigidBodyState:
        return self.world.truth()