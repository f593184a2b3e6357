"""The world as a sans-IO component: rigid bodies, rotor spin-up, sensors and the simulation clock.

It takes actuator outputs and time steps, and returns sensor packets and ground truth. Runners move
those messages: the in-process runner by direct call, the SITL world process over each unit's HIL
link in lockstep (a step happens only when every live unit has answered for the previous one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mars_link.assembly import AssemblyModel
from mars_link.messages import ActuatorOutput, SensorPacket, f32, wire_state, wire_time
from mars_link.rotations import quat_to_rotmat
from mars_link.state import ImuSample, PositionSample, RigidBodyState
from sitl.physics import JsbsimBody
from sitl.sensors import SensorModel, SensorParams


@dataclass
class WorldConfig:
    physics_hz: float = 500.0
    exchange_hz: float = 100.0  # sensor/actuator exchange with the units (the control rate)
    seed: int = 1
    noise: bool = True
    position_every: int = 1  # position samples every n-th exchange


class World:
    """One docked assembly (one JSBSim body). Docking/undocking changes come with reconfiguration."""

    def __init__(
        self,
        model: AssemblyModel,
        config: WorldConfig,
        start_com_ned_m: np.ndarray,
        start_yaw_rad: float = 0.0,
        sensor_params: SensorParams | None = None,
    ) -> None:
        self.model = model
        self.config = config
        ratio = config.physics_hz / config.exchange_hz
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError("physics_hz must be a whole multiple of exchange_hz")
        self.substeps = int(round(ratio))
        self.dt_s = 1.0 / config.physics_hz
        self.body = JsbsimBody(
            model,
            physics_hz=config.physics_hz,
            position_ned_m=(float(start_com_ned_m[0]), float(start_com_ned_m[1]), 0.0),
            yaw_rad=start_yaw_rad,
        )
        self.sensors = SensorModel(sensor_params or SensorParams(), seed=config.seed, noise=config.noise)
        self._unit_ids = list(model.unit_ids)
        self._offsets = np.array([model.unit_position(u) for u in self._unit_ids])
        tau = model.vehicle.motor_time_constant_s
        self._lag_alpha = 1.0 if tau <= 0 else 1.0 - math.exp(-self.dt_s / tau)
        self.rotor_setpoint_n = np.zeros(model.n_rotors)  # what the units drive their motors to
        self.rotor_thrust_n = np.zeros(model.n_rotors)  # what the rotors produce (after spin-up lag)
        self.dead_units: set[int] = set()
        self.exchange_index = 0
        self.force_integral_n2s = 0.0

    # ----------------------------------------------------------------- inputs
    def actuate(self, output: ActuatorOutput) -> None:
        if output.unit_id in self.dead_units:
            return
        self.rotor_setpoint_n[self.model.unit_slots(output.unit_id)] = output.thrusts_n

    def declare_dead(self, unit_id: int) -> None:
        """A unit that stopped answering: its motors stop, it stays attached as dead weight."""
        self.dead_units.add(unit_id)
        self.rotor_setpoint_n[self.model.unit_slots(unit_id)] = 0.0

    def advance(self) -> None:
        """Integrate physics over one exchange period (`substeps` physics steps)."""
        a = self._lag_alpha
        if a >= 1.0:  # no motor lag: thrust is constant over the exchange period
            self.rotor_thrust_n = self.rotor_setpoint_n.copy()
            self.body.set_rotor_thrusts(self.rotor_thrust_n)
            self.body.step(self.substeps)
            self.force_integral_n2s += float(self.rotor_thrust_n @ self.rotor_thrust_n) * self.dt_s * self.substeps
        else:
            for _ in range(self.substeps):
                self.rotor_thrust_n = self.rotor_thrust_n + a * (self.rotor_setpoint_n - self.rotor_thrust_n)
                self.body.set_rotor_thrusts(self.rotor_thrust_n)
                self.body.step()
                self.force_integral_n2s += float(self.rotor_thrust_n @ self.rotor_thrust_n) * self.dt_s
        self.exchange_index += 1

    # ----------------------------------------------------------------- outputs
    @property
    def t_s(self) -> float:
        return self.exchange_index * self.substeps * self.dt_s

    def truth(self) -> RigidBodyState:
        return self.body.state()

    def sense(self) -> list[SensorPacket]:
        """Sensor packets of every live unit for the current time (already rounded as on the wire)."""
        t = self.t_s
        truth = self.body.state()
        sf = self.body.specific_force_frd()
        with_position = self.exchange_index % self.config.position_every == 0
        gyro, accel, pos, vel = (
            f32(a)
            for a in self.sensors.sample_units(
                t, truth, sf, self._offsets, self._unit_ids, self.body.angular_acceleration_frd()
            )
        )
        tw = wire_time(t)
        state = None if self.config.noise else wire_state(truth)
        packets = []
        for i, unit_id in enumerate(self._unit_ids):
            if unit_id in self.dead_units:
                continue
            imu = ImuSample(tw, unit_id, gyro[i], accel[i])
            p = PositionSample(tw, unit_id, pos[i], vel[i]) if with_position else None
            packets.append(SensorPacket(tw, unit_id, imu, p, state))
        return packets

    def tracked_point(self, offset_frd_m: np.ndarray, truth: RigidBodyState | None = None) -> np.ndarray:
        truth = truth or self.body.state()
        return truth.position_ned_m + quat_to_rotmat(truth.quaternion_wxyz) @ offset_frd_m

    def close(self) -> None:
        self.body.close()

    def unit_truth(self, unit_id: int, truth: RigidBodyState | None = None) -> RigidBodyState:
        """Ground truth of one unit's centre (the rigid body's state moved to that point)."""
        return point_state(truth or self.body.state(), self.model.unit_position(unit_id))

    def truth_row(self) -> list[float]:
        s = self.body.state()
        return [*s.position_ned_m, *s.quaternion_wxyz]

    def unit_rotor_thrust_n(self, unit_id: int) -> np.ndarray:
        """What the unit's four rotors produce now (N)."""
        return self.rotor_thrust_n[self.model.unit_slots(unit_id)]


def point_state(s: RigidBodyState, offset_frd_m: np.ndarray) -> RigidBodyState:
    """The state of a point fixed in the body at `offset_frd_m` from the CoM (v + R (w x r))."""
    r = quat_to_rotmat(s.quaternion_wxyz)
    w, o = s.angular_velocity_frd_radps, offset_frd_m
    w_x_o = np.array([w[1] * o[2] - w[2] * o[1], w[2] * o[0] - w[0] * o[2], w[0] * o[1] - w[1] * o[0]])
    return RigidBodyState(
        s.t_s, s.position_ned_m + r @ o, s.velocity_ned_mps + r @ w_x_o,
        s.quaternion_wxyz, w, s.acceleration_ned_mps2, s.on_ground,
    )


class FreeUnitsWorld:
    """N free units side by side on the ground, each its own 1x1 JSBSim body, on one clock.

    Same surface as `World` (actuate, declare_dead, advance, sense, t_s), unit ids 1..N; unit i
    stands `spacing_m` east of unit i-1. Sensor packets carry the unit's truth (wire precision): a
    lone unit flies itself on it, as the lone-unit UDP runner does.
    """

    def __init__(self, n_units: int, vehicle, config: WorldConfig, spacing_m: float = 2.0) -> None:
        self.model = AssemblyModel.from_layout(["X"], vehicle)
        self.unit_ids = list(range(1, n_units + 1))
        self.worlds = {
            u: World(self.model, WorldConfig(config.physics_hz, config.exchange_hz, config.seed + u - 1, False,
                                             config.position_every),
                     np.array([0.0, (u - 1) * spacing_m, 0.0]))
            for u in self.unit_ids
        }
        self.dead_units: set[int] = set()

    @property
    def t_s(self) -> float:
        return next(iter(self.worlds.values())).t_s

    def actuate(self, output: ActuatorOutput) -> None:
        w = self.worlds.get(output.unit_id)
        if w is not None:
            w.actuate(ActuatorOutput(output.t_s, 1, output.thrusts_n))

    def declare_dead(self, unit_id: int) -> None:
        self.dead_units.add(unit_id)
        self.worlds[unit_id].declare_dead(1)

    def advance(self) -> None:
        for w in self.worlds.values():
            w.advance()

    def sense(self) -> list[SensorPacket]:
        out = []
        for u, w in self.worlds.items():
            if u in self.dead_units:
                continue
            for p in w.sense():
                out.append(SensorPacket(p.t_s, u, ImuSample(p.t_s, u, p.imu.gyro_frd_radps, p.imu.accel_frd_mps2),
                                        None if p.position is None else PositionSample(
                                            p.t_s, u, p.position.position_ned_m, p.position.velocity_ned_mps),
                                        p.truth))
        return out

    def unit_truth(self, unit_id: int) -> RigidBodyState:
        return self.worlds[unit_id].body.state()

    def unit_rotor_thrust_n(self, unit_id: int) -> np.ndarray:
        return self.worlds[unit_id].rotor_thrust_n

    def truth_row(self) -> list[float]:
        row: list[float] = []
        for w in self.worlds.values():
            s = w.body.state()
            row += [*s.position_ned_m, *s.quaternion_wxyz]
        return row

    def close(self) -> None:
        for w in self.worlds.values():
            w.close()
