"""The in-process assembly vehicle: the world of bodies (one per piece: a docked assembly is one), every
unit's firmware and the vehicle's flight (mars_link.vehicles.assembly_vehicle.VehicleFlight), stepped by the
engine in lockstep. Sans-IO: `handle(bytes, wall, link)` and `step(wall)` return the frames to send; `t_s`
is simulation time (scenario faults fire at their `t` from the start). `mars_link.processes.realtime` paces
it in real time behind UDP sockets (`mars-link vehicle`).
"""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle import Outgoing
from mars_link.config.scenario import Scenario
from mars_link.core.events import EventKind, event
from mars_link.core.messages import RotorCommand
from mars_link.core.state import RigidBodyState
from mars_link.vehicles.assembly_vehicle import SimConfig, VehicleFlight, attach_legs, vehicle_scenario
from mars_link.vehicles.vehicle_sensor_watch import route_sensor_failure

__all__ = ["SimConfig", "VehicleSim"]


class VehicleSim:
    """World, units and the vehicle's flight, wired by direct calls in lockstep; a fault goes into a unit's
    motor path and is told to the coordinator only with `faults_known`."""

    def __init__(self, scenario: Scenario, config: SimConfig | None = None, wall_time_s: float = 0.0) -> None:
        from mars_link.flight.build import make_pieces_world, make_unit
        from mars_link.flight.engine import Engine, Flight, InProcessUnits

        cfg = config or SimConfig()
        self.scenario = s = vehicle_scenario(scenario)
        self.model = model = s.model()
        self.control_dt_s = 1.0 / s.sim.control_hz
        self.flight = VehicleFlight(s, model, cfg, wall_time_s)
        self.vehicle = self.flight.vehicle
        self.coordinator = self.flight.pieces
        self.vehicle.on_failure = self.inject
        self.vehicle.on_sensor_failure = self.inject_sensor
        self.legs = attach_legs(self.vehicle, s, cfg.map_path, self.flight.eta_believed)
        # the bodies start landed under the executor's first references (the vehicle's start point)
        self.world = make_pieces_world(s, model, s.sim.seed, self.coordinator.executor)
        self.units = InProcessUnits({u: make_unit(s, model, u) for u in model.unit_ids}, self.world)
        if cfg.ulog_path:
            self.vehicle.start_ulog(cfg.ulog_path)
        # faults (scenario and MAVLink), sensor faults, the sensor guard's findings, the failsafe, EKF resets
        self.events: list[dict] = self.flight.events
        flight = Flight(s, model, s.sim.seed, self.flight.source, self.world, self.units, self.coordinator,
                        sorted(s.faults, key=lambda f: f.t_s), duration_s=math.inf)
        self.engine = Engine(flight, command_source=self._commands,
                             on_fault=lambda f, t: self.inject(f.unit, f.rotor, f.eta))
        self._wall_s = wall_time_s
        self._out: list[Outgoing] = []

    @property
    def t_s(self) -> float:
        return self.world.t_s

    @property
    def estimate(self) -> RigidBodyState | None:
        """The followed piece's settled estimate, as the vehicle reports it (None before)."""
        return self.flight.estimate

    @property
    def estimator_resets(self) -> int:
        return self.flight.estimator_resets

    def handle(self, data: bytes, wall_time_s: float, link: str) -> list[Outgoing]:
        return self.vehicle.handle(data, wall_time_s, link)

    def step(self, wall_time_s: float) -> list[Outgoing]:
        """One control period through the engine (faults due, sensing, units, vehicle and coordinator,
        motors, physics); returns the vehicle's frames to send."""
        self._wall_s = wall_time_s
        self._out = []
        self.engine.step()
        return self._out

    def _commands(self, t: float, packets) -> list[RotorCommand]:
        commands, self._out = self.flight.step(t, packets, self._wall_s)
        return commands

    def inject(self, unit: int, rotor: int | None, eta: float) -> None:
        """A fault in a unit's motor path; told to the coordinator only with `faults_known`."""
        t = self.t_s
        self.units.inject_failure(unit, rotor, eta)
        ev = event(t, EventKind.FAULT, unit=unit, rotor=rotor, eta=eta)
        self.events.append(ev)
        self.vehicle.report_event(ev)
        if self.scenario.faults_known:
            self.flight.tell_fault(unit, rotor, eta, t)

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

    def unit_eta(self) -> list[float]:
        return [float(x) for x in self.units.eta(self.model.unit_ids)]

    def eta_believed(self) -> np.ndarray:
        return self.flight.eta_believed()

    def event_lists(self) -> list[list[dict]]:
        """The run's event records: the vehicle's (faults, sensor findings, failsafe), the coordinator's,
        the executor's."""
        return [self.events, self.coordinator.events, self.coordinator.executor.events]

    def truth(self) -> RigidBodyState:
        """The followed piece's body."""
        return self.world.body_state(self.coordinator.tracked_piece().units[0])

    def close(self) -> None:
        self.vehicle.stop_ulog()
        self.legs.close()
        self.world.close()
