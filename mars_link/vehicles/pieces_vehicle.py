"""The assembly MAVLink vehicle over a flight of pieces (free units assembling, a reconfiguration, a
commanded separation): ground stations still see one vehicle.

    PiecesFlight   sans-IO, one control period: the units' telemetry in; the coordinator of pieces
                   (mars_link.coordination.pieces) flies every piece; the vehicle's guidance (takeoff, hold,
                   offboard, missions, land) is the mission of the structure: the reference of the
                   piece that flies the mission (`SetpointSource`); out go each unit's rotor command,
                   with its latch setpoint, and the vehicle's frames.
    PiecesVehicle  `AssemblyVehicle` that reports the piece with the most units (its CoM estimate is
                   the vehicle's position and attitude) and sends STATUSTEXT for every split, dock,
                   detection, plan and change of the piece it follows.

What a ground station sees, in order: a landed vehicle; after arm and takeoff, free units take off and
dock in the air layer by layer (Algorithm 3), then the structure flies to the takeoff setpoint and
follows setpoints as one vehicle. A fault its detectors find (or a separation of the scenario) makes
the coordinator pause the setpoints, split, move and dock the pieces, and return to the latest
setpoint; setpoints sent meanwhile wait for that return. Nothing starts a manoeuvre while the vehicle
is on the ground or landing. Used in-process (`PiecesSim`, `mars-link vehicle`) and inside the SITL
coordinator process (`sitl up --vehicle`, mars_link.processes.vehicle_host).
"""

from __future__ import annotations

import math

import numpy as np
from firmware_models.unit_controller import Phase, UnitAutopilot
from firmware_models.vehicle import Outgoing
from mars_link.core.events import EventKind, event
from mars_link.core.assembly import AssemblyModel
from mars_link.vehicles.assembly_vehicle import AssemblySim, AssemblyVehicle, EngineSim, SetpointSource, attach_legs, SimConfig, vehicle_scenario
from mars_link.control.base import ControlOutput
from mars_link.core.errors import UserInputError
from mars_link.core.messages import RotorCommand, SensorPacket, wire_thrust, wire_time
from mars_link.coordination.pieces import PiecesCoordinator
from mars_link.reconfig.execution import units_text
from mars_link.config.scenario import Scenario
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import TrajectoryPoint


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


class PiecesFlightCore(UnitAutopilot):
    """UnitAutopilot's guidance phases, flying the structure through the coordinator of pieces."""

    def __init__(self, pieces: PiecesCoordinator, source: SetpointSource, model: AssemblyModel,
                 control_hz: float) -> None:
        super().__init__(model.vehicle, control_hz)
        self.model = model
        self.drive = PiecesDrive(pieces, source, model.n_rotors)
        self.controller = self.drive
        self.zero = np.zeros(model.n_rotors)


class PiecesVehicle(AssemblyVehicle):
    """The vehicle of a flight of pieces: it follows the piece with the most units."""

    def __init__(self, pieces: PiecesCoordinator, model: AssemblyModel, source: SetpointSource,
                 config: SimConfig, control_hz: float, ftc: str, wall_time_s: float) -> None:
        self.pieces = pieces
        super().__init__(pieces, config.sysid, control_hz, ftc, config.params, wall_time_s, config.signing_key,
                         config.require_signing, model=model,
                         flight_core=PiecesFlightCore(pieces, source, model, control_hz))
        self._seen = {"coordinator": 0, "executor": 0}
        self.followed: tuple[int, ...] | None = None
        self._follow_event: dict | None = None

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

    def follow(self, t_s: float) -> RigidBodyState | None:
        """The followed piece's estimate (None before its EKF has one); a STATUSTEXT when it changes."""
        piece = self.pieces.tracked_piece()
        units = tuple(sorted(piece.units))
        if units != self.followed:
            if self.followed is not None:
                self._follow_event = event(t_s, EventKind.FOLLOWING, units=list(units),
                                           text=f"Following u{units_text(units)} ({len(units)} units)")
            self.followed = units
        last = piece.coordinator.last
        return None if last is None else last.estimate

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


class PiecesFlight:
    """One control period of the vehicle's flight of pieces; sans-IO."""

    def __init__(self, scenario: Scenario, model: AssemblyModel, config: SimConfig, wall_time_s: float,
                 telemetry_timeout_s: float | None = None) -> None:
        from mars_link.flight.build import make_pieces_coordinator, make_trajectory, start_pose

        self.scenario = scenario
        self.model = model
        trajectory = make_trajectory(scenario, model)  # (where the structure starts; its snap weighs plans)
        com, yaw = start_pose(scenario, model, trajectory)
        self.source = SetpointSource(TrajectoryPoint(np.array(com, dtype=float), yaw_rad=yaw))
        self.pieces, _ = make_pieces_coordinator(scenario, model, self.source, telemetry_timeout_s,
                                                 plan_for=trajectory, vehicle=True)
        self.pieces.manoeuvres_allowed = False
        self.vehicle = PiecesVehicle(self.pieces, model, self.source, config, scenario.sim.control_hz,
                                     scenario.ftc, wall_time_s)
        self.estimate: RigidBodyState | None = None
        self.full_scale_n = model.vehicle.full_scale_thrust_n

    @property
    def executor(self):
        return self.pieces.executor

    def eta_believed(self) -> np.ndarray:
        return np.concatenate([self.pieces.eta_believed[u] for u in self.model.unit_ids])

    def tell_fault(self, unit: int, rotor: int | None, eta: float, t_s: float) -> None:
        """A fault told to the coordinator (`faults_known`)."""
        told = self.eta_believed()
        told[self.model.unit_slots(unit) if rotor is None else self.model.rotor_slot(unit, rotor)] = eta
        self.pieces.set_faults(told, t_s, "fault told to the coordinator")

    def step(self, t_s: float, packets: list[SensorPacket], wall_time_s: float,
             live: set[int] | None = None) -> tuple[list[RotorCommand], list[Outgoing]]:
        """The coordinator of pieces (always: every piece's EKF and detector run, also on the ground), the
        followed piece's estimate into the vehicle, the vehicle's tick (its guidance sets the mission for
        the next period); the units' commands: the pieces' thrusts while the vehicle flies, else zero, and
        every unit's latch setpoint."""
        v = self.vehicle
        flying = v.flying()
        self.pieces.manoeuvres_allowed = flying
        self.pieces.rotors_driven = flying  # (the units get zeros otherwise, below)
        if v.armed and v.autopilot.phase == Phase.TAKEOFF and self.executor.phase == "grounded":
            self.executor.begin_take_off(t_s)  # free units: they take off when the vehicle does
        commands = self.pieces.step(t_s, packets)
        est = v.follow(t_s)
        if est is not None:
            self.estimate = est
            v.set_state(est)
        drive = v.autopilot.drive
        drive.thrusts_n = np.zeros(self.model.n_rotors)
        for c in commands:
            drive.thrusts_n[self.model.unit_slots(c.unit_id)] = c.thrusts_n
        out = v.tick(wall_time_s, t_s)
        thrusts = wire_thrust(v.rotor_thrusts_n(), self.full_scale_n)  # zeros unless armed and flying
        tw = wire_time(t_s)
        return [RotorCommand(tw, u, thrusts[self.model.unit_slots(u)], self.pieces.latch_setpoint[u])
                for u in self.model.unit_ids if live is None or u in live], out


class PiecesSim(EngineSim):
    """`AssemblySim` for a flight of pieces: the world of bodies, the units' firmware and the
    `PiecesFlight`, stepped by the engine; the same sans-IO surface (`handle`, `step`) for
    mars_link.processes.realtime."""

    def __init__(self, scenario: Scenario, config: SimConfig | None = None, wall_time_s: float = 0.0) -> None:
        from mars_link.flight.build import make_pieces_world, make_unit
        from mars_link.flight.engine import Engine, Flight, InProcessUnits

        cfg = config or SimConfig()
        if (cfg.start_north_m, cfg.start_east_m, cfg.start_yaw_deg) != (0.0, 0.0, 0.0):
            raise UserInputError("a flight of pieces starts where its scenario puts it (no start offset)")

        self.scenario = s = vehicle_scenario(scenario)
        self.model = model = s.model()
        self.control_dt_s = 1.0 / s.sim.control_hz
        self.flight = PiecesFlight(s, model, cfg, wall_time_s)
        self.vehicle = self.flight.vehicle
        self.coordinator = self.flight.pieces
        self.vehicle.on_failure = self.inject
        self.legs = attach_legs(self.vehicle, s, cfg.map_path, self.flight.eta_believed)
        self.world = make_pieces_world(s, model, s.sim.seed, self.coordinator.executor)
        self.units = InProcessUnits({u: make_unit(s, model, u) for u in model.unit_ids}, self.world)
        self.estimator_resets = 0
        self.events: list[dict] = []  # faults (scenario and MAVLink)
        flight = Flight(s, model, s.sim.seed, self.flight.source, self.world, self.units, self.coordinator,
                        sorted(s.faults, key=lambda f: f.t_s), duration_s=math.inf)
        self.engine = Engine(flight, command_source=self._commands,
                             on_fault=lambda f, t: self.inject(f.unit, f.rotor, f.eta))
        self._wall_s = wall_time_s
        self._out: list[Outgoing] = []

    @property
    def estimate(self) -> RigidBodyState | None:
        return self.flight.estimate

    def eta_believed(self) -> np.ndarray:
        return self.flight.eta_believed()

    def event_lists(self) -> list[list[dict]]:
        """The run's event records: faults (scenario and MAVLink), the coordinator's, the executor's."""
        return [self.events, self.coordinator.events, self.coordinator.executor.events]

    def _tell(self, unit: int, rotor: int | None, eta: float, t_s: float) -> None:
        self.flight.tell_fault(unit, rotor, eta, t_s)

    def _commands(self, t: float, packets) -> list[RotorCommand]:
        commands, self._out = self.flight.step(t, packets, self._wall_s)
        return commands

    def truth(self) -> RigidBodyState:
        """The followed piece's body."""
        return self.world.body_state(self.coordinator.tracked_piece().units[0])


def make_sim(scenario: Scenario, config: SimConfig | None = None, wall_time_s: float = 0.0):
    """The in-process vehicle for the scenario: one rigid body (`AssemblySim`) or pieces (`PiecesSim`)."""
    if scenario.has_pieces:
        return PiecesSim(scenario, config, wall_time_s)
    return AssemblySim(scenario, config, wall_time_s)
