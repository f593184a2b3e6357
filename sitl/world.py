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
