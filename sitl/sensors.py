"""Sensor models with seeded noise: one IMU and one position sensor per unit.

The IMU sits at the unit centre, so the accelerometer sees the lever-arm terms of the assembly's
rotation (alpha x r + omega x (omega x r)). The position sensor is mocap/RTK grade (1 cm): the
product flies indoor-scale assemblies, and the coordinator fuses every unit's position.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mars_link.rotations import cross3, quat_to_rotmat
from mars_link.state import ImuSample, PositionSample, RigidBodyState


@dataclass
class SensorParams:
    gyro_noise_radps: float = 0.003  # white noise per sample (1 sigma)
    gyro_bias_max_radps: float = 0.002  # constant per-unit bias, uniform in +-max per axis
    accel_noise_mps2: float = 0.05
    position_noise_m: float = 0.01
    velocity_noise_mps: float = 0.02


class SensorModel:
    """Deterministic for a seed; `noise=False` returns the truth exactly."""

    def __init__(self, params: SensorParams, seed: int, noise: bool = True) -> None:
        self.params = params
        self.noise = noise
        self.rng = np.random.default_rng(seed)
        self._bias: dict[int, np.ndarray] = {}
        self._last_omega: np.ndarray | None = None
        self._last_t: float | None = None
        self._alpha = np.zeros(3)

    def _gyro_bias(self, unit_id: int) -> np.ndarray:
        if unit_id not in self._bias:
            b = self.params.gyro_bias_max_radps
            self._bias[unit_id] = self.rng.uniform(-b, b, 3) if self.noise else np.zeros(3)
        return self._bias[unit_id]

    def _angular_acceleration(self, t_s: float, omega: np.ndarray) -> np.ndarray:
        """Finite difference of the body rate between sensing instants (same for every unit)."""
        if self._last_t is not None and t_s > self._last_t:
            self._alpha = (omega - self._last_omega) / (t_s - self._last_t)
        if self._last_t != t_s:
            self._last_t, self._last_omega = t_s, omega.copy()
        return self._alpha

    def imu(
        self,
        t_s: float,
        body: RigidBodyState,
        specific_force_frd: np.ndarray,
        unit_offset_frd_m: np.ndarray,
        unit_id: int,
    ) -> ImuSample:
        w = body.angular_velocity_frd_radps
        alpha = self._angular_acceleration(t_s, w)
        r = unit_offset_frd_m
        accel = specific_force_frd + cross3(alpha, r) + cross3(w, cross3(w, r))
        gyro = w.copy()
        if self.noise:
            p = self.params
            gyro = gyro + self._gyro_bias(unit_id) + self.rng.normal(0.0, p.gyro_noise_radps, 3)
            accel = accel + self.rng.normal(0.0, p.accel_noise_mps2, 3)
        return ImuSample(t_s, unit_id, gyro, accel)

    def sample_units(
        self, t_s: float, body: RigidBodyState, specific_force_frd: np.ndarray, offsets_frd_m: np.ndarray,
        unit_ids: list[int],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """All units at once (the hot path): gyro, accel (N, 3) body; position, velocity (N, 3) NED."""
        w = body.angular_velocity_frd_radps
        alpha = self._angular_acceleration(t_s, w)
        r = offsets_frd_m
        n = len(unit_ids)
        wx = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        ax = np.array([[0.0, -alpha[2], alpha[1]], [alpha[2], 0.0, -alpha[0]], [-alpha[1], alpha[0], 0.0]])
        lever = (ax + wx @ wx) @ r.T  # (3, N)
        accel = specific_force_frd[None, :] + lever.T
        gyro = np.broadcast_to(w, (n, 3))
        rot = quat_to_rotmat(body.quaternion_wxyz)
        pos = body.position_ned_m[None, :] + (rot @ r.T).T
        vel = body.velocity_ned_mps[None, :] + (rot @ (wx @ r.T)).T
        if self.noise:
            p = self.params
            bias = np.array([self._gyro_bias(u) for u in unit_ids])
            noise = self.rng.normal(0.0, 1.0, (n, 12))
            gyro = gyro + bias + p.gyro_noise_radps * noise[:, 0:3]
            accel = accel + p.accel_noise_mps2 * noise[:, 3:6]
            pos = pos + p.position_noise_m * noise[:, 6:9]
            vel = vel + p.velocity_noise_mps * noise[:, 9:12]
        return gyro, accel, pos, vel

    def position(
        self, t_s: float, body: RigidBodyState, unit_offset_frd_m: np.ndarray, unit_id: int
    ) -> PositionSample:
        rot = quat_to_rotmat(body.quaternion_wxyz)
        pos = body.position_ned_m + rot @ unit_offset_frd_m
        vel = body.velocity_ned_mps + rot @ cross3(body.angular_velocity_frd_radps, unit_offset_frd_m)
        if self.noise:
            p = self.params
            pos = pos + self.rng.normal(0.0, p.position_noise_m, 3)
            vel = vel + self.rng.normal(0.0, p.velocity_noise_mps, 3)
        return PositionSample(t_s, unit_id, pos, vel)
