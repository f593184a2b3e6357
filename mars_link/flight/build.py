"""The composition root: a flight's parts are built here, from a scenario and a seed, and nowhere else.

Every runner (in-process, the SITL world and coordinator processes, the assembly vehicle) asks this
module for its world, trajectory, controller, estimator, fault detector and coordinator, so that the
same scenario gives the same objects in every mode. Lower layers (control, planning, sitl,
firmware_models) never import it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.core.assembly import AssemblyModel
from mars_link.control.base import Controller
from mars_link.core.errors import UserInputError
from mars_link.core.limits import check_planned_unit_count, check_wire_unit_count
from mars_link.core.rotations import quat_to_rotmat
from mars_link.config.scenario import Scenario, eta_after
from mars_link.models.trajectories import Trajectory, build_trajectory

if TYPE_CHECKING:  # (a unit process builds its firmware here without importing the coordinator's stack)
    from mars_link.coordination.coordinator import Coordinator

#: position (mocap) samples per second by default ([sensors] position_rate_hz); the IMU comes at every control step
POSITION_RATE_HZ = 50.0


#: what the EKF's magnetometer heading allows for beyond the sensor's noise: tilt errors leaking through the
#: field's inclination (mars_link.models.estimation_outdoor)
EKF_HEADING_LEAK_RAD = 0.1
#: the fault detector starts this far above the landed height on the gps profile (0.15 m on mocap): ground
#: contact is not a rotor fault. On gps the take-off is late and the wind slides and tips the landed
#: assembly (its CoM 0.2 m up on one edge, the estimate a few cm off): at 0.15 m that read as rotor faults
#: in 3 of 20 windy spirals (34 false alarms); at 0.3 m and 0.5 m none of those three
OUTDOOR_FDI_MIN_HEIGHT_M = 0.5
#: ... and dismisses a change dated within this long after lift-off as the climb's air unless a whole unit's loss is
#: overwhelming (FaultDetectorParams.early_aloft_s): fault-free 3x3 and plus-5 gps spirals in 5 m/s wind with
#: moderate turbulence read it as their centre unit's loss in 4 of 20 flights with the ESC telemetry off (3x3 seeds 3
#: and 7, plus-5 seeds 3 and 6 of 1-10)
OUTDOOR_FDI_EARLY_ALOFT_S = 0.5
#: the baro drift the EKF's barometer noise allows for: what the drift reaches in this long (s)
BARO_DRIFT_ALLOWANCE_S = 60.0


def tracked_offset(model: AssemblyModel, scenario: Scenario) -> np.ndarray:
    """The tracked point (a unit's centre, or the CoM) from the assembly's CoM, body frame (m)."""
    unit = scenario.tracked_unit()
    return np.zeros(3) if unit is None else model.unit_position(unit).copy()


def make_trajectory(scenario: Scenario, model: AssemblyModel) -> Trajectory:
    from mars_link.planning.mission_trajectory import build_mission_trajectory
    from mars_link.planning.pipeline import build_plan_trajectory

    params = {k: v for k, v in scenario.trajectory.items() if k != "kind"}
    return build_trajectory(scenario.trajectory["kind"], params, rest_height_m=model.vehicle.gear_depth_m,
                            plan_builder=build_plan_trajectory,
                            mission_builder=lambda p, rest: build_mission_trajectory(p, rest, scenario.source))


def flight_duration_s(scenario: Scenario, model: AssemblyModel | None = None) -> float:
    """How long the flight lasts: [sim] duration_s, else the trajectory's (built to find out)."""
    if scenario.sim.duration_s is not None:
        return scenario.sim.duration_s
    return make_trajectory(scenario, model or scenario.model()).duration_s


def check_flight(scenario: Scenario, model: AssemblyModel | None = None) -> int:
    """Refuse a flight that would report a result it never flew: fewer than one control step
    (`control_hz = 1e-300`, `--duration 1e-9`), or a fault timed after the last control step (the
    runner would silently never inject it). Returns the number of control steps (-1: not checked, a
    planned trajectory without [sim] duration_s)."""
    src = scenario.source
    if scenario.sim.duration_s is None and scenario.trajectory.get("kind") == "plan":
        return -1  # its length is known only after planning (seconds of work): the runner's to check
    duration = flight_duration_s(scenario, model)
    steps_f = duration * scenario.sim.control_hz
    if not math.isfinite(steps_f) or steps_f > 1e9:
        raise UserInputError(f"{src}: {duration:g} s at {scenario.sim.control_hz:g} Hz is not a flight this runner "
                             "can step (more than 1e9 control steps)")
    steps = int(round(steps_f))
    if steps < 1:
        raise UserInputError(f"{src}: a flight of {duration:g} s at control_hz {scenario.sim.control_hz:g} has no "
                             "control step (duration x control_hz must be >= 1)")
    last_t = (steps - 1) / scenario.sim.control_hz
    for f in scenario.faults:
        if f.t_s > last_t + 1e-9:
            raise UserInputError(f"{src}: fault {f.describe()} comes after the flight ends "
                                 f"(last control step at t={last_t:g}s)")
    for f in scenario.sensor_faults:
        if f.t_s > last_t + 1e-9:
            raise UserInputError(f"{src}: {f.text()} at t={f.t_s:g}s comes after the flight ends "
                                 f"(last control step at t={last_t:g}s)")
    return steps


def allocator_bounds(scenario: Scenario, model: AssemblyModel) -> tuple[float | None, float | None]:
    """The rotor thrust bounds (N) the allocator is given. `qp`, the saturation-aware mode, gets the range
    every command is clipped to before it leaves (the plant's limits; on paper 000's plant, which has none,
    the wire's full scale, +-5.1 N): its priorities, not that clip, then decide what a demand beyond the
    rotors gives up (yaw first). The other modes get the plant's limits: on the paper plant none, so the
    paper's closed-form modes fly as published."""
    v = model.vehicle
    if scenario.ftc == "qp":
        return v.command_range_n
    return v.rotor_min_thrust_n, v.rotor_max_thrust_n


def make_controller(scenario: Scenario, model: AssemblyModel, eta: np.ndarray) -> Controller:
    """The scenario's controller for the whole structure, its tracked point the scenario's."""
    return make_piece_controller(scenario, model, eta, scenario.tracked_unit())


def make_piece_controller(scenario: Scenario, piece: AssemblyModel, eta: np.ndarray,
                          tracked_unit: int | None) -> Controller:
    """The scenario's controller (cascaded or paper 000's) over `piece`'s rotors, its reference for the
    centre of the piece's unit `tracked_unit` (the piece's own numbering; None: the piece's CoM)."""
    if scenario.controller == "cascaded":
        from mars_link.allocation import make_allocator
        from mars_link.control.cascaded import CascadedController

        allocator = make_allocator(scenario.ftc, piece, eta, *allocator_bounds(scenario, piece))
        offset = np.zeros(3) if tracked_unit is None else piece.unit_position(tracked_unit).copy()
        return CascadedController(piece, allocator, tracked_offset_frd_m=offset, control_hz=scenario.sim.control_hz)
    if scenario.controller == "mars-ftcc-paper":
        from mars_link.control.paper import PaperController

        return PaperController(piece, tracked_unit_id=tracked_unit, control_hz=scenario.sim.control_hz,
                               ftc=scenario.ftc, eta=eta)
    raise UserInputError(f"unknown controller {scenario.controller!r}")


def yaw_quat(yaw_rad: float) -> np.ndarray:
    return np.array([math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2)])


def start_pose(scenario: Scenario, model: AssemblyModel,
               trajectory: Trajectory | None = None) -> tuple[np.ndarray, float]:
    """Where the assembly's CoM starts (under the trajectory's first point, tracked point on it) and its yaw."""
    start = (trajectory or make_trajectory(scenario, model)).sample(0.0)
    com = start.position_ned_m - quat_to_rotmat(yaw_quat(start.yaw_rad)) @ tracked_offset(model, scenario)
    return com, start.yaw_rad


def position_every(scenario: Scenario) -> int:
    """Mocap position samples every n-th exchange."""
    return max(1, round(scenario.sim.control_hz / scenario.sensors.position_rate_hz))


def sensor_params(scenario: Scenario):
    """The world's sensor model figures for the scenario's [sensors] profile."""
    from sitl.sensors import SensorParams

    p = scenario.sensors
    return SensorParams(position_noise_m=p.position_noise_m, velocity_noise_mps=p.velocity_noise_mps)


def outdoor_profile(scenario: Scenario):
    """The [sensors] profile when it puts GNSS, barometer and magnetometer on the units (gps), else None."""
    return scenario.sensors if scenario.sensors.outdoor else None


def world_config(scenario: Scenario, seed: int):
    from sitl.docking import DockTolerance
    from sitl.world import WorldConfig

    return WorldConfig(physics_hz=scenario.sim.physics_hz, exchange_hz=scenario.sim.control_hz, seed=seed,
                       noise=scenario.sim.noise, position_every=position_every(scenario),
                       dock_tolerance=DockTolerance(**scenario.docking),
                       environment=scenario.environment if scenario.environment.moves_air else None,
                       sensors=sensor_params(scenario), battery=scenario.battery, outdoor=outdoor_profile(scenario))


def make_world(scenario: Scenario, model: AssemblyModel, seed: int, com_start_ned_m: np.ndarray | None = None,
               yaw_rad: float = 0.0, bodies: list | None = None, config=None):
    """The world: one docked body of `model` at its start pose, or the given `bodies` (body model, the
    world's unit ids it carries, JsbsimBody); `config` overrides the scenario's world config."""
    from sitl.world import World

    return World(model, config or world_config(scenario, seed), com_start_ned_m, yaw_rad, bodies=bodies)


def make_estimator(scenario: Scenario, model: AssemblyModel):
    """The rigid body's EKF when sensor noise is on; None: the coordinator flies on the world's truth."""
    from mars_link.runtime.blas_threads import single_blas_thread

    single_blas_thread()  # small dense algebra at every step: threads only oversubscribe the cores
    if not scenario.sim.noise:
        return None
    from mars_link.models.estimation import AssemblyEstimator, EstimatorParams
    from mars_link.models.sensor_profiles import MIN_EKF_VELOCITY_NOISE_MPS

    from mars_link.models.sensor_health import GPS_HEALTH, SensorGuard

    p = scenario.sensors  # the EKF is told the profile's figures
    if p.outdoor:
        from mars_link.models.estimation_outdoor import OutdoorEstimator, OutdoorParams

        return SensorGuard(OutdoorEstimator(model, EstimatorParams(  # the same gate as mocap/rtk, GPS_HEALTH's figures
            position_noise_m=p.position_noise_m, velocity_noise_mps=max(p.velocity_noise_mps, MIN_EKF_VELOCITY_NOISE_MPS)),
            OutdoorParams(horizontal_noise_m=max(p.position_noise_m, 1e-3), vertical_noise_m=max(p.vertical_noise_m, 1e-3),
                          velocity_noise_mps=max(p.velocity_noise_mps, MIN_EKF_VELOCITY_NOISE_MPS),
                          delay_s=round(p.gps_latency_s * scenario.sim.control_hz) / scenario.sim.control_hz,
                          baro_noise_m=math.hypot(p.baro_noise_m, BARO_DRIFT_ALLOWANCE_S ** 0.5 * p.baro_drift_m_per_sqrt_s, 0.01),
                          heading_noise_rad=math.hypot(math.radians(p.mag_heading_noise_deg), EKF_HEADING_LEAK_RAD),
                          declination_rad=math.radians(p.mag_declination_deg))), GPS_HEALTH)
    return SensorGuard(AssemblyEstimator(model, EstimatorParams(  # failed sensors are rejected or bridged
        position_noise_m=max(p.position_noise_m, 1e-4),
        velocity_noise_mps=max(p.velocity_noise_mps, MIN_EKF_VELOCITY_NOISE_MPS))))


def make_detector(scenario: Scenario, model: AssemblyModel, ground_down_m: float):
    """The fault detector when faults are not told; `ground_down_m`: the landed CoM height (every flight
    starts landed, and ground contact at take-off is not a rotor fault)."""
    if scenario.faults_known:
        return None
    from mars_link.models.fault_detection import FaultDetector, FaultDetectorParams

    params = None
    if scenario.sensors.outdoor:  # (why: OUTDOOR_FDI_MIN_HEIGHT_M)
        params = FaultDetectorParams(min_height_m=OUTDOOR_FDI_MIN_HEIGHT_M, early_aloft_s=OUTDOOR_FDI_EARLY_ALOFT_S)
    return FaultDetector(model, params, ground_down_m=ground_down_m)


def make_esc_monitor(scenario: Scenario, model: AssemblyModel):
    """The ESC telemetry's fault monitor beside the motion detector when faults are not told and the units'
    ESCs report (`[sensors] esc_telemetry`, on by default); None otherwise."""
    if scenario.faults_known or not scenario.esc_telemetry:
        return None
    from mars_link.models.esc_monitor import EscMonitor, EscMonitorParams

    return EscMonitor(model, params=EscMonitorParams(stuck_samples=3 if scenario.sim.noise else 0))


def make_piece_coordinator(scenario: Scenario, piece: AssemblyModel, reference: Trajectory, eta: np.ndarray,
                           t_s: float, estimator=None, detector=None, *, tracked_unit: int | None = None,
                           unit_names: tuple[int, ...] | None = None, ground_down_m: float | None = None,
                           telemetry_timeout_s: float | None = None) -> Coordinator:
    """The coordinator of one rigid piece (the whole docked structure is a piece too): the scenario's
    controller and FTC mode over the piece's own rotors, told the piece's believed faults (`eta`), its
    detector, if any, starting from them.

    `reference` is for the centre of the piece's unit `tracked_unit` (its own numbering; None: the CoM);
    `unit_names`: the structure's id of each of the piece's units (events and texts); `ground_down_m`: the
    tracked point's down coordinate landed (the position failsafe lands there; default: the reference's
    start). With the scenario's packs the allocator's bounds follow the units' voltages; on an estimator
    with a sensor guard, the position-loss failsafe flies the reference."""
    from mars_link.coordination.coordinator import Coordinator

    if detector is not None:
        detector.set_model(piece, eta)
    coordinator = Coordinator(piece, reference, make_piece_controller(scenario, piece, eta, tracked_unit),
                              estimator, detector, telemetry_timeout_s=telemetry_timeout_s)
    coordinator.unit_names = unit_names
    coordinator.eta_believed = np.asarray(eta, dtype=float).copy()
    coordinator.attach_esc_monitor(make_esc_monitor(scenario, piece) if detector is not None else None)
    if t_s > 0.0 and np.any(np.asarray(eta) < 1.0):  # a piece made in flight with faults (told or found): say so
        coordinator.set_faults(eta, t_s, "piece created")
    _follow_packs(scenario, piece, coordinator, unit_names)
    if coordinator.guard is not None:  # a trajectory flight: position lost -> hold, then land
        from mars_link.models.position_failsafe import PositionFailsafe

        offset = np.zeros(3) if tracked_unit is None else piece.unit_position(tracked_unit).copy()
        ground = float(reference.sample(0.0).position_ned_m[2]) if ground_down_m is None else ground_down_m
        coordinator.failsafe = PositionFailsafe(tracked_offset_frd_m=offset, ground_down_m=ground)
    return coordinator


def _follow_packs(scenario: Scenario, model: AssemblyModel, coordinator: Coordinator,
                  unit_names: tuple[int, ...] | None = None) -> None:
    """With simulated packs and rotor limits, the coordinator's allocator bounds follow each unit's reported
    voltage (`unit_names`: the structure's id of each of the model's units, whose pack it is)."""
    spec = scenario.battery
    if spec is None or model.vehicle.rotor_max_thrust_n is None:
        return
    coordinator.battery_cells = {u: spec.pack_of(u if unit_names is None else unit_names[u - 1]).cells
                                 for u in model.unit_ids}


def initial_eta(scenario: Scenario, model: AssemblyModel) -> np.ndarray:
    """What the coordinator believes at t = 0: the scenario's faults due then if they are told."""
    faults = sorted(scenario.faults, key=lambda f: f.t_s)
    return eta_after(model, faults, 0.0) if scenario.faults_known else model.nominal_eta()


def make_coordinator(scenario: Scenario, model: AssemblyModel, reference: Trajectory, estimator, detector,
                     eta: np.ndarray | None = None, telemetry_timeout_s: float | None = None) -> Coordinator:
    """The coordinator: `reference` is the scenario's trajectory or a vehicle's setpoint source; `estimator`
    and `detector` come from `make_estimator` / `make_detector`."""
    from mars_link.coordination.coordinator import Coordinator

    eta = initial_eta(scenario, model) if eta is None else eta
    coordinator = Coordinator(model, reference, make_controller(scenario, model, eta), estimator, detector,
                              telemetry_timeout_s=telemetry_timeout_s)
    coordinator.attach_esc_monitor(make_esc_monitor(scenario, model))
    _follow_packs(scenario, model, coordinator)
    if coordinator.guard is not None:  # a trajectory flight: position lost -> hold, then land
        from mars_link.models.position_failsafe import PositionFailsafe

        coordinator.failsafe = PositionFailsafe(tracked_offset_frd_m=tracked_offset(model, scenario),
                                                ground_down_m=float(reference.sample(0.0).position_ned_m[2]))
    return coordinator


def make_unit(scenario: Scenario, model: AssemblyModel, unit_id: int, *, coordinator_driven: bool = True,
              signing_key: bytes | None = None, wall_time_s: float = 0.0, require_signing: bool = False,
              on_wire: bool = True, sign_hil: bool = False, client_links_keyed: bool = True):
    """One unit's firmware (`firmware_models.vehicle.Vehicle`: rotor intake, motor model, fail-safes), the
    same object in-process and in a unit process. The scenario's faults for this unit are scheduled in
    its motor model: the unit, not the coordinator, knows them. `on_wire=False`: an in-process unit, whose
    id no MAVLink frame carries (it may exceed the system ids 1..250)."""
    from firmware_models.vehicle import Vehicle, VehicleConfig

    if on_wire:
        check_wire_unit_count(model.n_units)
    params = {} if scenario.battery is None else scenario.battery.unit_params(unit_id)  # its pack, its failsafe
    vehicle = Vehicle(VehicleConfig(unit_id=unit_id, vehicle=model.vehicle, control_hz=scenario.sim.control_hz,
                                    hil_await_coordinator=coordinator_driven, signing_key=signing_key,
                                    sign_client_links=require_signing, sign_hil=sign_hil,
                                    client_links_keyed=client_links_keyed, on_wire=on_wire,
                                    params=params), wall_time_s)
    if scenario.esc_telemetry:  # the unit's ESCs report RPM and current (mars_link.models.esc)
        from mars_link.models.esc import EscSensor, MotorConstants

        vehicle.esc = EscSensor(MotorConstants.for_vehicle(model.vehicle), seed=scenario.sim.seed, unit_id=unit_id,
                                noise=scenario.sim.noise)
    for f in scenario.faults:
        if f.unit == unit_id:
            vehicle.schedule_failure(f.t_s, f.rotor or 0, f.eta, f.kind)
    from firmware_models.sensor_failures import SensorFailures

    vehicle.sensor_failures = SensorFailures(unit_id, scenario.sim.seed)  # (seeded: garbage, intermittent)
    for sf in scenario.sensor_faults:
        if sf.applies_to(unit_id):
            for t_s, sensor, kind in sf.schedule():
                vehicle.schedule_sensor_failure(t_s, sensor, kind)
    return vehicle



def check_px4_interface(scenario: Scenario, model: AssemblyModel) -> None:
    """What PX4's per-rotor interface cannot carry, as one UserInputError: more units than PX4 system ids,
    and the latch commands of a flight of pieces (ActuatorMotors has no docking latch)."""
    if model.n_units > 255:
        raise UserInputError(f"[units] interface = \"px4-zenoh\": at most 255 units (PX4 system ids), got {model.n_units}")
    if scenario.has_pieces:
        raise UserInputError("[units] interface = \"px4-zenoh\" carries no docking-latch commands: a flight of "
                             "pieces (free start, reconfiguration, separations) needs the mavlink interface")


#: a unit silent for this many control periods is declared lost (in-process flights with unit deaths)
UNIT_TIMEOUT_PERIODS = 5


#: cap on a reconfiguration manoeuvre: a flight of pieces ends this long after its mission would have
MAX_RECONFIG_S = 600.0


@dataclass(frozen=True)
class BodyStart:
    """One body of a world at its start, landed: its model (local unit ids 1..n), the world's unit ids it
    carries in that order, where it stands (north, east) and its yaw."""

    model: AssemblyModel
    units: tuple[int, ...]
    north_m: float
    east_m: float
    yaw_rad: float


def make_bodies_world(scenario: Scenario, model: AssemblyModel, bodies: list[BodyStart], seed: int, config=None):
    """The world of a list of bodies, each landed at its start: every set-up is one (a docked assembly: one
    body; a flight of pieces: one per piece of its start; free units: one 1x1 body each). `model` names every
    unit of the world and its rotor slots."""
    from sitl.physics import JsbsimBody

    config = config or world_config(scenario, seed)
    made = [(b.model, b.units, JsbsimBody(b.model, physics_hz=config.physics_hz, position_ned_m=(b.north_m, b.east_m, 0.0),
                                          yaw_rad=b.yaw_rad)) for b in bodies]
    return make_world(scenario, model, seed, bodies=made, config=config)


def docked_bodies(model: AssemblyModel, com_start_ned_m: np.ndarray, yaw_rad: float) -> list[BodyStart]:
    """A docked assembly: one body of `model`, its CoM landed under `com_start_ned_m`."""
    return [BodyStart(model, tuple(model.unit_ids), float(com_start_ned_m[0]), float(com_start_ned_m[1]), yaw_rad)]


def pieces_bodies(model: AssemblyModel, executor) -> list[BodyStart]:
    """A flight of pieces: one body per piece of the executor's start, landed under its reference's first point."""
    bodies = []
    for shape in executor.shapes.values():
        start = executor.refs[shape.key].sample(0.0)
        bodies.append(BodyStart(shape.model(model.vehicle), tuple(shape.units_local_order()),
                                float(start.position_ned_m[0]), float(start.position_ned_m[1]), start.yaw_rad))
    return bodies


def make_pieces_world(scenario: Scenario, model: AssemblyModel, seed: int, executor, config=None):
    """The world of a flight of pieces (`pieces_bodies`)."""
    return make_bodies_world(scenario, model, pieces_bodies(model, executor), seed, config)


#: `sitl up --units N`: unit u stands this far east of unit u-1 on the ground
FREE_UNIT_SPACING_M = 2.0


def free_units_bodies(vehicle, n_units: int) -> tuple[AssemblyModel, list[BodyStart]]:
    """N lone units (`sitl up --units N`), side by side on the ground: the world's model (the row of N units:
    unit ids 1..N, slots in that order) and one 1x1 body each."""
    one = AssemblyModel.from_layout(["X"], vehicle)
    return (AssemblyModel.from_layout(["X" * n_units], vehicle),
            [BodyStart(one, (u,), 0.0, (u - 1) * FREE_UNIT_SPACING_M, 0.0) for u in range(1, n_units + 1)])


def free_units_config(config):
    """A free units' world config: each unit flies itself on its truth, so the sensor packets carry it (no
    sensor noise), as a lone unit's runner does."""
    import dataclasses

    return dataclasses.replace(config, noise=False)


def make_free_units_world(scenario: Scenario, vehicle, n_units: int, seed: int, config=None):
    """The world of N lone units (`free_units_bodies`, `free_units_config`)."""
    model, bodies = free_units_bodies(vehicle, n_units)
    return make_bodies_world(scenario, model, bodies, seed, free_units_config(config or world_config(scenario, seed)))


def make_executor(scenario: Scenario, model: AssemblyModel, mission, plan_for: Trajectory | None = None,
                  defer_take_off: bool = False) -> tuple[object, list[dict], bool]:
    """The executor a flight starts with, the events of its planning, and whether it will reconfigure on
    the scenario's own (told) faults.

    A free start assembles first (Algorithm 3; `defer_take_off`: once told to take off). A flight with
    told faults executes the plan for all of them. Otherwise the structure flies its mission as one body
    through the executor's references, and a plan is made in flight from the faults the detectors find.
    `plan_for`: the trajectory whose snap weighs where the units go (default: the mission; the assembly
    vehicle's mission is its setpoints, which have no duration)."""
    from mars_link.reconfig.execution import Executor, FreeStart
    from mars_link.reconfig.placement import nominal_cells
    from mars_link.reconfig.plans import (execution_params, free_ground_positions, make_plan, plan_event,
                                          unhoverable_pieces)
    from mars_link.reconfig.sequencing import ReconfigPlan, plan_assembly

    vehicle = model.vehicle
    params = execution_params(scenario)
    tracked = scenario.tracked_unit()
    events: list[dict] = []
    if scenario.starts_free:  # free units on the ground: assemble in the air (Algorithm 3), then the mission
        free = FreeStart(free_ground_positions(scenario, model, *start_pose(scenario, model, mission)))
        return Executor(plan_assembly(model), vehicle, mission, tracked, params, free, defer_take_off), events, False
    if scenario.reconfig.get("enabled", False) and scenario.faults_known:
        plan = make_plan(scenario, model, plan_for or mission)
        eta = eta_after(model, sorted(scenario.faults, key=lambda f: f.t_s), math.inf)
        events.append(plan_event(0.0, plan, vehicle, {u: eta[model.unit_slots(u)] for u in model.unit_ids}))
        if plan.feasible and plan.disassembly_layers:
            refused = unhoverable_pieces(plan, model, eta)
            if not refused:
                return Executor(plan, vehicle, mission, tracked, params), events, True
            events.append(event(0.0, EventKind.RECONFIG_REFUSED, reason="; ".join(refused),
                                text="Reconfig refused: a piece cannot hover"))
    stub = ReconfigPlan(model.layout, nominal_cells(model), None, True, 0, 0)  # type: ignore[arg-type]
    return Executor(stub, vehicle, mission, tracked, params), events, False


def make_pieces_coordinator(scenario: Scenario, model: AssemblyModel, mission: Trajectory,
                            telemetry_timeout_s: float | None = None, plan_for: Trajectory | None = None,
                            vehicle: bool = False):
    """The coordinator of a flight of pieces (`PiecesCoordinator`: one EKF, detector, controller and
    allocator per piece, the executor inside) and when its flight ends (a function of no argument
    giving the end's sim time: a manoeuvre moves it). `plan_for`: see `make_executor`. `vehicle`: flown by a
    ground station (mars_link.vehicles.assembly_vehicle): free units wait for its take-off, and faults may come from it."""
    from mars_link.coordination.pieces import PiecesCoordinator
    from mars_link.reconfig.plans import check_reconfig_scenario, plan_or_reason, plan_separation

    if scenario.has_pieces:
        check_reconfig_scenario(scenario, faults_may_come=vehicle)
    executor, plan_events, told = make_executor(scenario, model, mission, plan_for, defer_take_off=vehicle)

    def new_coordinator(shape, piece: AssemblyModel, reference, tracked_unit, eta, t_s, estimator):
        """A piece at the start stands landed under its reference's first point (its detector's and
        failsafe's ground); one made in flight has the ground the structure took off from."""
        if estimator is None:
            estimator = make_estimator(scenario, piece)
        names = tuple(shape.units_local_order())
        if t_s == 0.0:
            ground = float(reference.sample(0.0).position_ned_m[2])
            com_ground = float(reference.com_reference.sample(0.0).position_ned_m[2])
        else:
            com_ground = executor.ground_down_m
            ground = com_ground + float(reference.offset[2])
        return make_piece_coordinator(scenario, piece, reference, eta, t_s, estimator,
                                      make_detector(scenario, piece, com_ground), tracked_unit=tracked_unit,
                                      unit_names=names, ground_down_m=ground)

    enabled = bool(scenario.reconfig.get("enabled", False))
    at_s = scenario.reconfig.get("at_s")
    planner = None
    if enabled and not scenario.faults_known:
        def planner(eta_by_unit, current_cells):
            eta = np.concatenate([eta_by_unit[u] for u in model.unit_ids])
            return plan_or_reason(scenario, model, plan_for or mission, eta, current_cells)
    coordinator = PiecesCoordinator(
        executor, model.vehicle, model.unit_ids, new_coordinator, tracked_unit=scenario.tracked_unit(),
        planner=planner, told_faults=len(scenario.faults) if told and at_s is None else 0,
        at_s=at_s if told or planner is not None else None,
        separations=[(s.t_s, plan_separation(model, s.units, s.redock_t_s is not None), s.redock_t_s)
                     for s in scenario.separations], telemetry_timeout_s=telemetry_timeout_s)
    coordinator.events += plan_events
    duration = scenario.sim.duration_s or mission.duration_s

    def end_s() -> float:
        # (apart for good, or landed for good after a rebuild on the ground that ended early: the mission's end)
        if executor.phase in ("mission", "landed") or executor.hold_until_s == math.inf:
            return duration + executor.shift_s
        return duration + MAX_RECONFIG_S

    return coordinator, end_s


def build_flight(scenario: Scenario, seed: int, unit_deaths: dict[int, float] | None = None):
    """Every part of one in-process flight, wired for `mars_link.flight.engine.Engine`: a world of rigid bodies
    (one per piece of the executor's start: the docked structure is one), every unit's firmware, and the
    coordinator of pieces (a docked flight is a flight of one piece, flying the mission itself).

    `unit_deaths` (unit -> time): that unit's process dies then; the coordinator, not told, declares it
    lost after `UNIT_TIMEOUT_PERIODS` silent control periods. A flight that may become several bodies
    ends when its executor says (a manoeuvre moves the mission's end); the others after their duration."""
    from mars_link.flight.engine import Flight, InProcessUnits

    model = scenario.model()
    if scenario.has_pieces:
        check_planned_unit_count(model.n_units, "a flight of pieces' layout")
    mission = make_trajectory(scenario, model)
    deaths = sorted((t_d, u) for u, t_d in (unit_deaths or {}).items())
    for _, u in deaths:
        model.check_rotor(u, None)
    timeout = UNIT_TIMEOUT_PERIODS / scenario.sim.control_hz if deaths else None
    coordinator, end_s = make_pieces_coordinator(scenario, model, mission, timeout)
    world = make_pieces_world(scenario, model, seed, coordinator.executor)
    units = InProcessUnits({u: make_unit(scenario, model, u, on_wire=False) for u in model.unit_ids}, world)
    if scenario.unit_interface == "px4-zenoh":
        check_px4_interface(scenario, model)
        units.use_px4_interface(model.vehicle.full_scale_thrust_n, reversible=model.vehicle.rotor_min_thrust_n is None)
    faults = sorted(scenario.faults, key=lambda f: f.t_s)
    return Flight(scenario, model, seed, mission, world, units, coordinator, faults, deaths,
                  tracked_offset(model, scenario), scenario.sim.duration_s or mission.duration_s,
                  end_s=end_s if scenario.has_pieces else None)

