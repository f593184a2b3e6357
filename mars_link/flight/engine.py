"""The flight engine: one lockstep loop over the flight's components, and their in-process wiring
(messages as objects, moved by direct calls).

`InProcessUnits` is every unit's firmware (`firmware_models.vehicle.Vehicle`, the object a unit process
runs) on its HIL and coordinator links, without the MAVLink bytes: sensors in, telemetry out; rotor
commands in, motor outputs out. The coordinator takes the units over as it does in SITL: at its first
command to a unit it arms it and switches it to OFFBOARD around that command.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np
from pymavlink.dialects.v20.common import MAV_RESULT_ACCEPTED

from firmware_models.vehicle import MODE_OFFBOARD
from mars_link.core.events import EventKind, event, unit_died
from mars_link.core.assembly import AssemblyModel
from mars_link.core.messages import ActuatorOutput, RotorCommand, SensorPacket, wire_time
from mars_link.mavlink.wire import hil_state_received, usec
from mars_link.flight.metrics import STAGES
from mars_link.models.esc import sample_steady
from mars_link.runtime.pacing import Pacer
from mars_link.config.scenario import FaultSpec, Scenario, eta_after
from mars_link.config.scenario_sensor_faults import sensor_fault_events
from mars_link.core.state import RigidBodyState, point_state
from mars_link.models.trajectories import Trajectory

if TYPE_CHECKING:  # (a world process steps the engine without the coordinator's stack)
    from mars_link.coordination.coordinator import Coordinator


class InProcessUnits:
    """The units of one flight, driven by direct calls in lockstep with the world."""

    batched = True  # the steady state of every unit in one pass (_drive_steady); False: unit by unit, the
    # reference the batched pass must equal (tests/engine/test_engine_batched.py, benchmarks/bench_scale.py)

    def __init__(self, vehicles: dict, world) -> None:
        self.vehicles = vehicles  # unit id -> firmware_models.vehicle.Vehicle
        self.world = world
        self.dead: set[int] = set()  # units whose process died: they neither sense nor drive
        self._taken_over: set[int] = set()  # units armed and in OFFBOARD under the coordinator
        self._accepted: dict[int, set[str]] = {}  # unit -> what of the take-over it accepted so far
        self.px4: dict | None = None  # unit id -> mars_link.px4.commander.Px4Commander: PX4's interface instead
        self._own_state: dict[int, tuple] = {}  # unit -> its last HIL_STATE_QUATERNION not given yet: (body state, offset), usec

    def use_px4_interface(self, full_scale_thrust_n: float, reversible: bool) -> None:
        """Drive every unit through PX4's per-rotor interface ([units] interface = "px4-zenoh"): the same
        messages as over rmw_zenoh (OffboardControlMode, VehicleCommand, ActuatorMotors; acks back), as objects."""
        from mars_link.px4.commander import Px4Commander

        self.px4 = {u: Px4Commander(u, full_scale_thrust_n, reversible) for u in self.vehicles}
        self.batched = False

    def kill(self, unit_id: int) -> None:
        """The unit's process dies: no more telemetry, its motors stop (the world's dead weight)."""
        self.dead.add(unit_id)
        self.world.declare_dead(unit_id)

    def inject_failure(self, unit_id: int, rotor: int | None, eta: float, kind: str = "eta") -> None:
        """A fault in the unit's motor model (rotor 1..4, None = all four): only the unit knows it."""
        self.vehicles[unit_id].inject_failure(rotor or 0, eta, kind)

    def take_sensors(self, packets: list[SensorPacket]) -> list[SensorPacket]:
        """The world's sensor packets into each unit; the units' telemetry to the coordinator."""
        vehicles, world, sampled = self.vehicles, self.world, self._own_state
        escs = self._esc_steady(packets) if self.batched and len(packets) > 1 else None
        out = []
        for i, p in enumerate(packets):
            u = p.unit_id
            v = vehicles[u]
            # the unit's own state as SITL's world sends it (processes.engine_links.unit_sensor_messages): its
            # centre's truth in HIL_STATE_QUATERNION, at that message's precision, with each position or GPS
            # sample of a packet that carries no truth (noise off: the packet's truth, as on the wire). A unit
            # flying its own fail-safe flies on these numbers (given the exact truth at every step instead, a
            # lost unit's fall differed from SITL's by 2 mm in the air and 5 cm where it came to rest)
            if p.truth is None and (p.position is not None or p.gps is not None):
                sampled[u] = (world.unit_truth_parts(u), usec(p.t_s))  # (the body's state object: kept, cheap)
            # it matters only while the unit flies itself or may have to (arming, a command stream about to
            # lapse), or logs it now (.ulg): decoded only then, the last sample's (as a SITL unit holds it)
            own = (v.source != "coordinator" or not v.intake.is_live(p.t_s + v.control_dt_s)
                   or v.ulog is not None and v.ulog.due(p.t_s))
            hil = v.hil_service
            sample = sampled.pop(u, None) if own else None
            truth = None
            if sample is not None:
                (body, offset), t_usec = sample
                truth = hil_state_received(point_state(body, offset), t_usec)
            if escs is None:
                out.append(hil.take_sensors(p, truth))
            else:
                out.append(hil.take_sensors(p, truth, esc_sampled=True, esc=escs[i]))
        return out

    def _esc_steady(self, packets: list[SensorPacket]) -> list | None:
        """Every unit's ESC sample of the step in one pass (mars_link.models.esc.sample_steady: the same
        samples as unit by unit), when every packet's unit has ESCs and no sensor failure of theirs comes
        due now; None: the units sample their own."""
        t = packets[0].t_s
        sensors, commands, etas = [], [], []
        for p in packets:
            v = self.vehicles[p.unit_id]
            if v.esc is None or p.t_s != t or v.sensor_failure_due(t):
                return None
            sensors.append(v.esc)
            command, eta = v.esc_inputs()
            commands.append(command)
            etas.append(eta)
        return sample_steady(sensors, t, np.array(commands), np.array(etas))

    def drive(self, commands: list[RotorCommand]) -> None:
        """The coordinator's commands into the units; their motor outputs into the world. A live unit
        without a command this step still answers (it flies itself, or its fail-safe does), as every unit
        answers every HIL step in SITL."""
        done, actuate, taken_over, vehicles = self.dead, self.world.actuate, self._taken_over, self.vehicles
        rest = self._drive_steady(commands) if self.batched and len(commands) > 1 else commands
        for cmd in rest:
            u = cmd.unit_id
            if u in done:
                continue
            if u in taken_over:  # (`command` without the take-over)
                v = vehicles[u]
                v.hil_service.take_rotor_command(cmd)
                actuate(v.hil_service.drive_motors())
            else:
                actuate(self.command(cmd))
        if len(commands) < len(self.vehicles):
            commanded = {c.unit_id for c in commands}
            for u, v in self.vehicles.items():
                if u not in commanded and u not in done:
                    out = v.hil_service.drive_motors()
                    if out.unit_id != u:  # (a lone unit keeps its own system id; the world calls it u)
                        out = dataclasses.replace(out, unit_id=u)
                    self.world.actuate(out)

    def _drive_steady(self, commands: list[RotorCommand]) -> list[RotorCommand]:
        """Every unit in the steady state under the coordinator in one pass: the commands' values are
        bounded as one array, each unit takes the same checks and state changes as `take_rotor_command`
        then `drive_motors` (HilService.drive_steady), and the world takes their thrusts in one copy. Returns
        the commands left to the general path (the others, or all of them when any value is not finite:
        the general path counts it)."""
        t_s = commands[0].t_s
        rows = [c.thrusts_n for c in commands]
        block = np.concatenate(rows)
        least_n, greatest_n = float(block.min()), float(block.max())  # (NaN anywhere makes the least NaN)
        if not (math.isfinite(least_n) and math.isfinite(greatest_n)):
            return commands
        t_usec = round(t_s * 1e6)
        vehicles, taken_over, done = self.vehicles, self._taken_over, self.dead
        world_latches = self.world.latches.setpoint
        rest, ids, held = [], [], []
        for i, c in enumerate(commands):
            u = c.unit_id
            v = vehicles.get(u)
            if (v is None or u not in taken_over or u in done or c.t_s != t_s or v.sysid != u
                    or c.latch_setpoint != world_latches.get(u)):
                rest.append(c)
                continue
            s = v.full_scale_n
            driven = v.hil_service.drive_steady(rows[i], least_n / s, greatest_n / s, t_usec, c.latch_setpoint)
            if driven:
                ids.append(u)
                held.append(rows[i])
            elif driven is None:  # not in the steady state
                rest.append(c)
            else:  # dropped by the intake (counted): the unit answers as after any dropped command
                self.world.actuate(v.hil_service.drive_motors())
        if ids:
            self.world.actuate_rows(ids, held)
        return rest

    def command(self, cmd: RotorCommand) -> ActuatorOutput:
        v = self.vehicles[cmd.unit_id]
        if self.px4 is not None:
            return self._command_px4(v, cmd)
        u = cmd.unit_id
        if u not in self._taken_over:  # the take-over: as SITL's coordinator sends it with every command
            self._take_over(v, cmd, self._accepted.setdefault(u, set()))
        else:
            v.hil_service.take_rotor_command(cmd)
        return v.hil_service.drive_motors()

    def _take_over(self, v, cmd: RotorCommand, accepted: set[str]) -> None:
        """ARM before the command, OFFBOARD after it, each again with every command until the unit accepted
        it (as processes.engine_links._with_takeover): a unit without a state yet refuses to arm for now
        (TEMPORARILY_REJECTED, PX4's pre-arm check) and is asked again at the next step."""
        if "arm" not in accepted and v.arm() == MAV_RESULT_ACCEPTED:
            accepted.add("arm")
        v.hil_service.take_rotor_command(cmd)
        if "offboard" not in accepted and v.set_mode(MODE_OFFBOARD) == MAV_RESULT_ACCEPTED:
            accepted.add("offboard")
        if len(accepted) == 2:
            self._taken_over.add(cmd.unit_id)

    def _command_px4(self, v, cmd: RotorCommand) -> ActuatorOutput:
        from mars_link.px4.rmw_zenoh import VEHICLE_COMMAND_ACK

        assert self.px4 is not None
        commander = self.px4[cmd.unit_id]
        for topic, message in commander.step(cmd.t_s, cmd.thrusts_n):
            for reply_topic, reply in v.px4_service.take(topic, message):
                if reply_topic is VEHICLE_COMMAND_ACK:
                    commander.take_ack(reply)
        return v.hil_service.drive_motors()

    def eta(self, unit_ids) -> np.ndarray:
        """Every rotor's true efficiency (the units' motor models), in `unit_ids` order."""
        return np.concatenate([self.vehicles[u].motors.eta for u in unit_ids])


# ----------------------------------------------------------------------------- the parts
class WorldPart(Protocol):
    """What the engine asks of the world each step. In process: `sitl.world.World`; in a process that does
    not host the world, a proxy over its links (mars_link.processes.engine_links.LinkedUnits: the step's time is
    known once the step's telemetry is in, so reading `t_s` may wait for it)."""

    @property
    def t_s(self) -> float: ...
    def sense(self) -> list[SensorPacket]: ...
    def truth(self) -> RigidBodyState | None: ...
    def advance(self) -> None: ...


class UnitsPart(Protocol):
    """What the engine asks of the units each step: `InProcessUnits`, or a proxy over their links."""

    def take_sensors(self, packets: list[SensorPacket]) -> list[SensorPacket]: ...
    def drive(self, commands: list[RotorCommand]) -> None: ...
    def kill(self, unit_id: int) -> None: ...


# ----------------------------------------------------------------------------- the loop
@dataclass
class Flight:
    """A flight's parts, built by `mars_link.flight.build.build_flight` from a scenario and a seed."""

    scenario: Scenario
    model: AssemblyModel
    seed: int
    trajectory: Trajectory
    world: WorldPart  # sitl.world.World, or the world seen over the links of another process
    units: UnitsPart  # InProcessUnits, or the units seen over the links of another process
    coordinator: Coordinator | None  # None: the units fly themselves (a lone unit under a ground station)
    faults: list[FaultSpec]  # sorted by time: they act in the units' motor models (scheduled there)
    deaths: list[tuple[float, int]] = field(default_factory=list)  # (time, unit): the unit's process dies
    tracked_offset_frd_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    duration_s: float = 0.0
    end_s: Callable[[], float] | None = None  # a flight whose end moves (a reconfiguration): its end sim time

    @property
    def n_steps(self) -> float:
        """Control periods to fly (math.inf: until stopped)."""
        if math.isinf(self.duration_s):
            return math.inf
        return int(round(self.duration_s * self.scenario.sim.control_hz))


@dataclass
class StepView:
    """What observers see after a control step: the coordinator's record and the world's truth."""

    index: int
    t_s: float
    record: object  # coordinator.StepRecord of this step (None: no coordinator ran, or its thrusts were not sent)
    truth: RigidBodyState | None  # None: the world is in another process
    telemetry: list = field(default_factory=list)  # the units' SensorPackets to the coordinator
    commands: list = field(default_factory=list)  # the coordinator's RotorCommands to the units


class Engine:
    """The one lockstep loop: faults due -> world senses -> units take sensors -> coordinator commands ->
    units drive motors -> world actuates and advances -> observers. Pacing is a parameter (`Pacer`),
    not another loop. An observer's `on_step` returning True ends the flight (e.g. divergence).

    `command_source(t, telemetry) -> commands` stands for the coordinator's step (default
    `flight.coordinator.step`): the assembly vehicle puts its flight modes in front of the coordinator
    there. `on_fault(fault, t)` replaces the default record-and-tell of a scenario fault coming due."""

    def __init__(self, flight: Flight, observers: list | None = None, pacer: Pacer | None = None,
                 command_source: Callable[[float, list[SensorPacket]], list[RotorCommand]] | None = None,
                 on_fault: Callable[[FaultSpec, float], None] | None = None) -> None:
        self.flight = flight
        self.observers = list(observers or [])
        self.pacer = pacer or Pacer(0.0)
        self.command_source = command_source or flight.coordinator.step  # (a flight without one names its own)
        self.on_fault = on_fault or self._record_fault
        self.events: list[dict] = []
        self.stage_time_s = dict.fromkeys(STAGES, 0.0)
        self.steps = 0
        self.stopped = False
        self._next_fault = 0
        self._deaths = list(flight.deaths)
        # [[sensor_faults]] act in the units' sensor paths (scheduled there); their start and end are events here
        self._sensor_events = sensor_fault_events(flight.scenario.sensor_faults, flight.scenario.sim.control_hz, math.inf)

    def _faults_due(self, t: float) -> None:
        f = self.flight
        faults = f.faults
        while self._next_fault < len(faults) and faults[self._next_fault].t_s <= t + 1e-9:
            self._next_fault += 1
            self.on_fault(faults[self._next_fault - 1], t)
        while self._sensor_events and self._sensor_events[0]["t_s"] <= t + 1e-9:
            self.events.append(self._sensor_events.pop(0))
        while self._deaths and self._deaths[0][0] <= t + 1e-9:
            _, u = self._deaths.pop(0)
            f.units.kill(u)
            self.events.append(unit_died(t, u))

    def _record_fault(self, fault: FaultSpec, t: float) -> None:
        """A scenario fault came due (the unit's motor model applies it): an event; told to the coordinator
        when the scenario says faults are known."""
        f = self.flight
        self.events.append(event(t, EventKind.FAULT, unit=fault.unit, rotor=fault.rotor, eta=fault.eta,
                                 text=fault.event_text()))
        if f.scenario.faults_known and f.coordinator is not None:  # (None: the coordinator is another process's)
            f.coordinator.set_faults(eta_after(f.model, f.faults[:self._next_fault], t), t,
                                     "fault told to the coordinator")

    def step(self) -> bool:
        """One control period; False once the flight is over (its duration flown, or an observer stopped it)."""
        f = self.flight
        if self.stopped or (self.steps >= f.n_steps if f.end_s is None else f.world.t_s >= f.end_s() - 1e-9):
            return False
        world, stage, clock = f.world, self.stage_time_s, time.perf_counter
        t = wire_time(world.t_s)  # the step's time as its sensor packets carry it (as a SITL coordinator reads it)
        if self.pacer.paced:
            self.pacer.wait(t, 1.0 / f.scenario.sim.control_hz)
        self._faults_due(t)
        c0 = clock()
        telemetry = f.units.take_sensors(world.sense())  # the sensors stage: the world's samples into the units
        c1 = clock()
        coordinator = f.coordinator
        commands = self.command_source(t, telemetry)
        c2 = clock()
        f.units.drive(commands)
        c3 = clock()
        rec = None if coordinator is None else coordinator.last
        stage["sensors"] += c1 - c0
        if rec is not None:
            for name in ("estimation", "control", "allocation"):
                stage[name] += rec.timings_s[name]
            if not coordinator.rotors_driven:  # (a vehicle on the ground: its units got zeros, not these thrusts)
                rec = None
        stage["motors"] += c3 - c2
        view = StepView(self.steps, t, rec, world.truth(), telemetry, commands)
        for obs in self.observers:
            if obs.on_step(self, view):
                self.stopped = True
        c4 = clock()
        stage["logging"] += c4 - c3
        if self.stopped:
            return False
        world.advance()
        stage["physics"] += clock() - c4
        self.steps += 1
        return True

    def run(self, on_progress: Callable[[float], None] | None = None) -> None:
        """Step until the flight is over; `on_progress(share flown)` about 200 times (a flight whose end
        moves: the share of its end as it stands, never going back)."""
        f = self.flight
        n = f.n_steps
        every = max(1, int(n // 200)) if math.isfinite(n) else 50
        shown = 0.0
        while self.step():
            if on_progress is not None and self.steps % every == 1:
                end_s = f.end_s() if f.end_s is not None else f.duration_s
                shown = max(shown, min(1.0, f.world.t_s / end_s) if 0 < end_s < math.inf else 0.0)
                on_progress(shown)
