"""The world as a sans-IO component: rigid bodies, rotor spin-up, sensors and the simulation clock.

It takes actuator outputs and time steps, and returns sensor packets and ground truth. Runners move
those messages: the in-process runner by direct call, the SITL world process over each unit's HIL
link in lockstep (a step happens only when every live unit has answered for the previous one).
"""

from __future__ import annotations

import functools
import math
from dataclasses import KW_ONLY, dataclass, field

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.core.assembly import AssemblyModel, layout_of_cells
from mars_link.core.messages import ActuatorOutput, SensorPacket, f32, wire_state, wire_time
from mars_link.core.rotations import quat_to_rotmat
from mars_link.core.state import ImuSample, PositionSample, RigidBodyState, point_state
from sitl.docking import DockTolerance, dock_check
from mars_link.core.latches import SIDE_STEPS, LatchBoard, components, neighbour_links, opposite
from mars_link.models.environment import EnvironmentParams
from mars_link.models.sensor_profiles import SensorProfile
from sitl.environment import Air
from mars_link.models.battery import BatterySpec
from sitl.battery import Packs
from sitl.physics import JsbsimBody
from sitl.outdoor_sensors import OutdoorSensors
from sitl.sensors import SensorModel, SensorParams

#: each latch side's direction in a unit's body frame (FRD): front, right, back, left
SIDE_FRD = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: how often a unit's power module reports its pack's voltage and current
BATTERY_HZ = 10.0


@dataclass
class WorldConfig:
    physics_hz: float = 500.0
    exchange_hz: float = 100.0  # sensor/actuator exchange with the units (the control rate)
    seed: int = 1
    noise: bool = True
    position_every: int = 1  # position samples every n-th exchange
    _: KW_ONLY  # (keyword-only from here: a positional config cannot slide into the wrong field)
    dock_tolerance: DockTolerance = field(default_factory=DockTolerance)  # when facing latches close
    environment: EnvironmentParams | None = None  # wind, gusts, turbulence (sitl.environment); None = still air
    sensors: SensorParams | None = None  # the sensor figures ([sensors] profile); None = SensorParams()
    battery: BatterySpec | None = None  # the units' packs (sitl.battery); None = an ideal supply (the papers')
    outdoor: SensorProfile | None = None  # [sensors] profile "gps": GNSS, baro, magnetometer instead of mocap


@dataclass(eq=False)  # (identity: two bodies are never "equal")
class Body:
    """One rigid body of the world: a JSBSim instance and the units it carries, in its model's order."""

    model: AssemblyModel  # the body's own layout (its local unit ids 1..n)
    units: tuple[int, ...]  # the world's unit id of each local unit
    jsbsim: JsbsimBody
    offsets_frd_m: np.ndarray  # (n, 3) unit centres from the body's CoM
    slots: np.ndarray  # the world's rotor slots of the body's rotors, in its local order
    _centres: tuple | None = field(default=None, init=False, repr=False)  # (state, `centres_ned_m` of it)

    def centres_ned_m(self, state: RigidBodyState) -> np.ndarray:
        """The units' centres (NED, in the body's order) at `state`, the body's state of a step (kept for it:
        the dock check after a step and the clearance the recorder reads before the next use the same)."""
        kept = self._centres
        if kept is not None and kept[0] is state:
            return kept[1]
        centres = state.position_ned_m + (quat_to_rotmat(state.quaternion_wxyz) @ self.offsets_frd_m.T).T
        self._centres = (state, centres)
        return centres

    @property
    def cells(self) -> dict[int, tuple[int, int]]:
        """World unit id -> its (row, col) cell in the body's layout."""
        return {u: self.model.unit_cells[k + 1] for k, u in enumerate(self.units)}

    @functools.cached_property
    def radius_m(self) -> float:
        """The farthest unit centre from the CoM (the offsets never change: a split or dock makes new bodies)."""
        return float(np.max(np.linalg.norm(self.offsets_frd_m, axis=1)))

    @classmethod
    def of(cls, model: AssemblyModel, units, jsbsim: JsbsimBody, world_model: AssemblyModel) -> "Body":
        units = tuple(int(u) for u in units)
        if len(units) != model.n_units:
            raise ValueError(f"a body of {model.n_units} units cannot carry units {units}")
        offsets = np.array([model.unit_position(k + 1) for k in range(len(units))])
        slots = np.concatenate([np.arange(world_model.unit_slots(u).start, world_model.unit_slots(u).stop)
                                for u in units])
        return cls(model, units, jsbsim, offsets, slots)


class World:
    """Rigid bodies on one clock: one docked assembly, free units, or any mix, split and merged in flight.

    The world's `model` names every unit and its rotor slots (unit ids and the slot order of the
    world-level arrays `rotor_setpoint_n` / `rotor_thrust_n`); each `Body` carries some of the units in
    its own JSBSim instance. `World(model, config, com, yaw)` is one docked body of `model`;
    `World.of_bodies` builds any set. `split` and `merge` keep linear and angular momentum
    (sitl.docking). Sensing goes body by body, units in each body's order: one body senses exactly as
    the one-body world always did.
    """

    def __init__(
        self,
        model: AssemblyModel,
        config: WorldConfig,
        start_com_ned_m: np.ndarray | None = None,
        start_yaw_rad: float = 0.0,
        sensor_params: SensorParams | None = None,
        bodies: list[tuple[AssemblyModel, tuple[int, ...], JsbsimBody]] | None = None,
    ) -> None:
        self.model = model
        self.config = config
        ratio = config.physics_hz / config.exchange_hz
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError("physics_hz must be a whole multiple of exchange_hz")
        self.substeps = int(round(ratio))
        self.dt_s = 1.0 / config.physics_hz
        if bodies is None:
            jsb = JsbsimBody(
                model,
                physics_hz=config.physics_hz,
                position_ned_m=(float(start_com_ned_m[0]), float(start_com_ned_m[1]), 0.0),
                yaw_rad=start_yaw_rad,
            )
            bodies = [(model, tuple(model.unit_ids), jsb)]
        self.bodies: list[Body] = [Body.of(m, units, jsb, model) for m, units, jsb in bodies]
        carried = sorted(u for b in self.bodies for u in b.units)
        if carried != sorted(model.unit_ids):
            raise ValueError(f"the bodies carry units {carried}, the world has {sorted(model.unit_ids)}")
        self.sensors = SensorModel(sensor_params or config.sensors or SensorParams(), seed=config.seed, noise=config.noise)
        self.outdoor = None if config.outdoor is None else OutdoorSensors(
            config.outdoor, config.seed, config.noise, config.exchange_hz, config.position_every)
        tau = model.vehicle.motor_time_constant_s
        self._lag_alpha = 1.0 if tau <= 0 else 1.0 - math.exp(-self.dt_s / tau)
        self.rotor_setpoint_n = np.zeros(model.n_rotors)  # what the units drive their motors to
        self.rotor_thrust_n = np.zeros(model.n_rotors)  # what the rotors produce (after spin-up lag)
        self.dead_units: set[int] = set()
        self.exchange_index = 0
        self.force_integral_n2s = 0.0
        self._unit_slots = {u: model.unit_slots(u) for u in model.unit_ids}  # (the hot path's lookup)
        self._unit_order = sorted(self._unit_slots, key=lambda u: self._unit_slots[u].start)  # slot order
        self.latches = LatchBoard(model.unit_ids)
        for b in self.bodies:
            self.latches.add(neighbour_links(b.cells))
        self._released = False  # a latch opened since the last advance: the world splits that body
        self.latch_events: list[dict] = []  # the world's record of every split and dock (truth, for logs)
        self.air = Air(config.environment, config.seed)
        # the units' packs: measured at BATTERY_HZ (every `battery_every`-th exchange), as a power module reports
        self.packs = None if config.battery is None else Packs(config.battery, list(model.unit_ids),
                                                                model.vehicle.rotor_max_thrust_n)
        self.battery_every = max(1, round(config.exchange_hz / BATTERY_HZ))
        self._index_bodies()

    @classmethod
    def of_bodies(cls, model: AssemblyModel, config: WorldConfig,
                  bodies: list[tuple[AssemblyModel, tuple[int, ...], RigidBodyState | None, tuple[float, float, float]]],
                  sensor_params: SensorParams | None = None) -> "World":
        """A world of several bodies: (body model, world unit ids in its order, airborne state or None,
        (north, east, yaw) of a landed start)."""
        made = []
        for m, units, state, (n, e, yaw) in bodies:
            jsb = JsbsimBody(m, physics_hz=config.physics_hz, position_ned_m=(n, e, 0.0), yaw_rad=yaw, state=state)
            made.append((m, tuple(units), jsb))
        return cls(model, config, sensor_params=sensor_params, bodies=made)

    def _index_bodies(self) -> None:
        self._body_of = {u: b for b in self.bodies for u in b.units}
        owner = np.array([i for i, b in enumerate(self.bodies) for _ in b.units])
        self._same_body = owner[:, None] == owner[None, :]  # (unit pairs of one body: `min_clearance_m`)
        self._single = len(self.bodies) == 1 and self.bodies[0].units == tuple(self.model.unit_ids)
        self.air.attach(b.jsbsim for b in self.bodies)

    # ----------------------------------------------------------------- bodies
    @property
    def body(self) -> JsbsimBody:
        """The JSBSim instance of the first body (the whole assembly in a one-body world)."""
        return self.bodies[0].jsbsim

    def body_of(self, unit_id: int) -> Body:
        return self._body_of[unit_id]

    def body_state(self, unit_id: int) -> RigidBodyState:
        """State of the CoM of the body that carries `unit_id`."""
        return self._body_of[unit_id].jsbsim.state()

    def split(self, units: tuple[int, ...], parts: list[tuple[AssemblyModel, tuple[int, ...], np.ndarray]]) -> list[Body]:
        """Undock the body that carries `units` into `parts` (model, world unit ids in its order, CoM
        offset FRD from the parent CoM); momentum kept, each part keeps its rotors' thrust."""
        from sitl.docking import split_body

        parent = self._body_of[units[0]]
        parted = [(m, off, self.rotor_thrust_n[self._slots_of(us)]) for m, us, off in parts]
        new = [Body.of(m, us, jsb, self.model) for (m, us, _), jsb in zip(parts, split_body(parent.jsbsim, parted))]
        i = self.bodies.index(parent)
        self.bodies[i:i + 1] = new
        self._index_bodies()
        return new

    def merge(self, stationary_unit: int, mover_unit: int, merged: AssemblyModel, units: tuple[int, ...]) -> Body:
        """Dock the body of `mover_unit` onto the body of `stationary_unit` (whose attitude it takes):
        one body of `merged`, carrying `units` (world ids in its order); momentum kept."""
        from sitl.docking import merge_bodies

        st, mv = self._body_of[stationary_unit], self._body_of[mover_unit]
        if st is mv:
            raise ValueError(f"units {stationary_unit} and {mover_unit} are already one body")
        jsb = merge_bodies([st.jsbsim, mv.jsbsim], merged, self.rotor_thrust_n[self._slots_of(units)])
        body = Body.of(merged, units, jsb, self.model)
        i = min(self.bodies.index(st), self.bodies.index(mv))
        self.bodies = [b for b in self.bodies if b is not st and b is not mv]
        self.bodies.insert(i, body)
        self._index_bodies()
        return body

    def _slots_of(self, units) -> np.ndarray:
        return np.concatenate([np.arange(self.model.unit_slots(u).start, self.model.unit_slots(u).stop)
                               for u in units])

    # ----------------------------------------------------------------- inputs
    def actuate(self, output: ActuatorOutput) -> None:
        if output.unit_id in self.dead_units:
            return
        sl = self._unit_slots.get(output.unit_id)
        if sl is None:  # not a unit of this world: the model names it in one line
            sl = self.model.unit_slots(output.unit_id)
        self.rotor_setpoint_n[sl] = output.thrusts_n
        if output.latch_setpoint != self.latches.setpoint[output.unit_id] and self.latches.command(
                output.unit_id, output.latch_setpoint):
            self._released = True

    def actuate_rows(self, unit_ids: list[int], thrusts_n: list[np.ndarray]) -> None:
        """`actuate` for many units whose latch setpoints are unchanged (the in-process engine's steady
        state): unit_ids[i] drives its motors to thrusts_n[i]."""
        sp = self.rotor_setpoint_n
        if not self.dead_units and unit_ids == self._unit_order:  # every unit, in slot order: one copy
            sp[:] = np.concatenate(thrusts_n)
            return
        for u, t in zip(unit_ids, thrusts_n):
            if u not in self.dead_units:
                sp[self._unit_slots[u]] = t

    def declare_dead(self, unit_id: int) -> None:
        """A unit that stopped answering: its motors stop, it stays attached as dead weight."""
        self.dead_units.add(unit_id)
        self.rotor_setpoint_n[self.model.unit_slots(unit_id)] = 0.0

    def advance(self) -> None:
        """Integrate physics over one exchange period (`substeps` physics steps) for every body."""
        if self._released:
            self._split_released()
        if self.air.active:
            self.air.before_exchange(self.t_s, [b.jsbsim for b in self.bodies])
        packs = self.packs
        if packs is not None and packs.thrust_cap_n is not None:  # a sagging pack cannot drive its rotors as hard
            sp = self.rotor_setpoint_n.reshape(-1, 4)
            np.minimum(sp, packs.thrust_cap_n[:, None], out=sp)
        a = self._lag_alpha
        if a >= 1.0:  # no motor lag: thrust is constant over the exchange period
            self.rotor_thrust_n = self.rotor_setpoint_n.copy()
            if self._single:
                self.body.set_rotor_thrusts(self.rotor_thrust_n)
                self.body.step(self.substeps)
            else:
                for b in self.bodies:
                    b.jsbsim.set_rotor_thrusts(self.rotor_thrust_n[b.slots])
                    b.jsbsim.step(self.substeps)
            self.force_integral_n2s += float(self.rotor_thrust_n @ self.rotor_thrust_n) * self.dt_s * self.substeps
        else:
            for _ in range(self.substeps):
                self.rotor_thrust_n = self.rotor_thrust_n + a * (self.rotor_setpoint_n - self.rotor_thrust_n)
                for b in self.bodies:
                    b.jsbsim.set_rotor_thrusts(self.rotor_thrust_n if self._single else self.rotor_thrust_n[b.slots])
                    b.jsbsim.step()
                self.force_integral_n2s += float(self.rotor_thrust_n @ self.rotor_thrust_n) * self.dt_s
        if packs is not None:
            packs.add_power(self.rotor_thrust_n, self.dt_s * self.substeps)
        self.exchange_index += 1
        if packs is not None and self.exchange_index % self.battery_every == 0:
            packs.step()  # the packs at the battery rate, before this exchange's sample
        if not self._single and len(self.bodies) > 1:
            self._latch_docks()

    # ----------------------------------------------------------------- latches
    def _split_released(self) -> None:
        """Every body whose opened latches leave it in several linked groups becomes one body per group."""
        self._released = False
        links = self.latches.links
        for body in list(self.bodies):
            groups = components(body.units, links)
            if len(groups) < 2:
                continue
            cells = body.cells
            parts = []
            for g in groups:
                order = tuple(sorted(g, key=cells.get))
                model = AssemblyModel.from_layout(layout_of_cells(cells[u] for u in order), self.model.vehicle)
                offset = np.mean([body.offsets_frd_m[body.units.index(u)] for u in order], axis=0)
                parts.append((model, order, offset))
            self.split(body.units, parts)
            self.latch_events.append(event(self.t_s, EventKind.RELEASED, parts=[sorted(g) for g in groups]))

    def _latch_docks(self) -> None:
        """Two bodies dock when a pair of facing units, both latches engaged, sit at their dock pose within
        the docking tolerance (sitl.docking.dock_check on the truth): the latches close and the bodies merge."""
        tol = self.config.dock_tolerance
        pitch = self.model.vehicle.pitch_m
        bodies = self.bodies
        states = [b.jsbsim.state() for b in bodies]
        centres = [b.centres_ned_m(s) for s, b in zip(states, bodies)]
        # (the bodies' CoMs and reach as floats: most pairs are far apart, and numpy's norm of a 3-vector
        # costs ~3 us a pair; a pair within reach is judged on the unit centres, as ever)
        coms = [s.position_ned_m.tolist() for s in states]
        reach = [b.radius_m for b in bodies]
        for i in range(len(bodies)):
            for j in range(i + 1, len(bodies)):
                if math.dist(coms[i], coms[j]) > reach[i] + reach[j] + pitch + 0.1:  # (a margin of 0.1 m)
                    continue
                d = np.linalg.norm(centres[i][:, None, :] - centres[j][None, :, :], axis=2)
                for a_k, b_k in zip(*np.nonzero(np.abs(d - pitch) < 2 * tol.position_m + 0.05)):
                    if self._try_dock(bodies[i], bodies[j], states[i], states[j], int(a_k), int(b_k), tol):
                        return  # (the body list changed: the next pair waits for the next step)

    def _try_dock(self, bi: "Body", bj: "Body", si: RigidBodyState, sj: RigidBodyState, a_k: int, b_k: int,
                  tol: DockTolerance) -> bool:
        # the heavier body (else the slower one) is the stationary one: the merged body keeps its attitude
        if (len(bj.units), -np.linalg.norm(sj.velocity_ned_mps)) > (len(bi.units), -np.linalg.norm(si.velocity_ned_mps)):
            bi, bj, si, sj, a_k, b_k = bj, bi, sj, si, b_k, a_k
        a, b = bi.units[a_k], bj.units[b_k]
        rel = quat_to_rotmat(si.quaternion_wxyz).T @ (
            (sj.position_ned_m + quat_to_rotmat(sj.quaternion_wxyz) @ bj.offsets_frd_m[b_k])
            - (si.position_ned_m + quat_to_rotmat(si.quaternion_wxyz) @ bi.offsets_frd_m[a_k]))
        side = int(np.argmax(SIDE_FRD @ rel))
        if not (self.latches.engaged(a, side) and self.latches.engaged(b, opposite(side))):
            return False
        offset = bi.offsets_frd_m[a_k] + SIDE_FRD[side] * self.model.vehicle.pitch_m - bj.offsets_frd_m[b_k]
        chk = dock_check(si, sj, offset, tol)
        if not chk.ready:
            return False
        st_cells, mv_cells = bi.cells, bj.cells
        target = (st_cells[a][0] + SIDE_STEPS[side][0], st_cells[a][1] + SIDE_STEPS[side][1])
        dr, dc = target[0] - mv_cells[b][0], target[1] - mv_cells[b][1]
        cells = {**st_cells, **{u: (c[0] + dr, c[1] + dc) for u, c in mv_cells.items()}}
        if len(set(cells.values())) != len(cells):
            return False  # (cells would overlap: not a dock pose)
        order = tuple(sorted(cells, key=cells.get))
        merged = AssemblyModel.from_layout(layout_of_cells(cells[u] for u in order), self.model.vehicle)
        self.merge(a, b, merged, order)
        engaged = self.latches.engaged
        self.latches.add({link: sides for link, sides in neighbour_links(cells).items()
                          if len(link & set(st_cells)) == 1 and engaged(min(link), sides[0])
                          and engaged(max(link), sides[1])})
        self.latch_events.append(event(self.t_s, EventKind.DOCK_LATCHED, stationary=sorted(st_cells),
                                       mover=sorted(mv_cells), position_error_m=round(chk.position_error_m, 4),
                                       speed_mps=round(chk.speed_mps, 4), yaw_deg=round(chk.yaw_deg, 3),
                                       text=f"Dock latched: {chk.position_error_m * 100:.1f} cm"))
        return True

    # ----------------------------------------------------------------- outputs
    @property
    def t_s(self) -> float:
        return self.exchange_index * self.substeps * self.dt_s

    def truth(self) -> RigidBodyState:
        """State of the first body (the whole assembly in a one-body world)."""
        return self.body.state()

    def sense(self) -> list[SensorPacket]:
        """Sensor packets of every live unit for the current time (already rounded as on the wire)."""
        t = self.t_s
        with_position = self.exchange_index % self.config.position_every == 0
        with_battery = self.packs is not None and self.exchange_index % self.battery_every == 0
        tw = wire_time(t)
        packets = []
        latch, dead = self.latches.mask, self.dead_units
        for b in self.bodies:
            truth = b.jsbsim.state()
            block = f32(self.sensors.sample_block(  # (N, 12): gyro, accel, position, velocity, rounded at once
                t, truth, b.jsbsim.specific_force_frd(), b.offsets_frd_m, list(b.units),
                b.jsbsim.angular_acceleration_frd(),
            ))
            # each unit's vectors as row views (made in one call per column group, not indexed one by one)
            gyro, accel, pos, vel = list(block[:, 0:3]), list(block[:, 3:6]), list(block[:, 6:9]), list(block[:, 9:12])
            state = None if self.config.noise else wire_state(truth)
            outdoor = self._outdoor_samples(tw, b, truth) if self.outdoor is not None else None
            for i, unit_id in enumerate(b.units):
                if unit_id in dead:
                    continue
                imu = ImuSample(tw, unit_id, gyro[i], accel[i])
                battery = self.packs.sample(unit_id - 1) if with_battery else None
                if outdoor is None:
                    p = PositionSample(tw, unit_id, pos[i], vel[i]) if with_position else None
                    packets.append(SensorPacket(tw, unit_id, imu, p, state, latch(unit_id), None, None, None, battery))
                else:
                    packets.append(SensorPacket(tw, unit_id, imu, None, state, latch(unit_id), *outdoor[i],
                                                battery=battery))
        if not self._single:
            packets.sort(key=lambda p: p.unit_id)
        return packets

    def _outdoor_samples(self, t_s: float, b: Body, truth: RigidBodyState) -> list[tuple]:
        """(gps, baro, mag) of each of the body's units from its centre's truth (gps profile)."""
        rot = quat_to_rotmat(truth.quaternion_wxyz)
        w = truth.angular_velocity_frd_radps
        pos = truth.position_ned_m + b.offsets_frd_m @ rot.T
        vel = truth.velocity_ned_mps + np.cross(w, b.offsets_frd_m) @ rot.T
        return [self.outdoor.sample(self.exchange_index, t_s, u, pos[i], vel[i], rot) for i, u in enumerate(b.units)]

    def tracked_point(self, offset_frd_m: np.ndarray, truth: RigidBodyState | None = None) -> np.ndarray:
        truth = truth or self.body.state()
        return truth.position_ned_m + quat_to_rotmat(truth.quaternion_wxyz) @ offset_frd_m

    def close(self) -> None:
        for b in self.bodies:
            b.jsbsim.close()

    def unit_truth(self, unit_id: int, truth: RigidBodyState | None = None) -> RigidBodyState:
        """Ground truth of one unit's centre (its rigid body's state moved to that point)."""
        b = self._body_of[unit_id]
        return point_state(truth or b.jsbsim.state(), b.offsets_frd_m[b.units.index(unit_id)])

    def unit_truth_parts(self, unit_id: int) -> tuple[RigidBodyState, np.ndarray]:
        """(the state of the body carrying the unit, now; the unit's centre from that body's CoM, FRD):
        `point_state` of them is `unit_truth(unit_id)`, for a caller that may need it later (the body's
        state object of a step is never changed, a step makes a new one)."""
        b = self._body_of[unit_id]
        return b.jsbsim.state(), b.offsets_frd_m[b.units.index(unit_id)]

    def min_clearance_m(self) -> float:
        """Smallest gap between units of different bodies (centre distance less one unit pitch: each
        unit counted as a disc of its pitch); inf with one body. Negative means two bodies overlap."""
        if len(self.bodies) < 2:
            return math.inf
        p = np.concatenate([b.centres_ned_m(b.jsbsim.state()) for b in self.bodies])
        d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
        d[self._same_body] = np.inf
        return float(d.min()) - self.model.vehicle.pitch_m

    def truth_row(self) -> list[float]:
        s = self.body.state()
        return [*s.position_ned_m, *s.quaternion_wxyz]

    def units_row(self) -> list[float]:
        """Every unit's centre (NED), in unit id order: the truth log of a world of several bodies."""
        row: list[float] = []
        for u in self.model.unit_ids:
            b = self._body_of[u]
            s = b.jsbsim.state()
            row += [*(s.position_ned_m + quat_to_rotmat(s.quaternion_wxyz) @ b.offsets_frd_m[b.units.index(u)])]
        return row

    def unit_rotor_thrust_n(self, unit_id: int) -> np.ndarray:
        """What the unit's four rotors produce now (N)."""
        return self.rotor_thrust_n[self.model.unit_slots(unit_id)]
