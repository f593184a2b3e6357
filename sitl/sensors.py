"""Sensor models with seeded noise: one IMU and one position sensor per unit.

The IMU sits at the unit centre, so the accelerometer sees the lever-arm terms of the assembly's
rotation (alpha x r + omega x (omega x r)). The position sensor is mocap/RTK grade (1 cm): the
product flies indoor-scale assemblies, and the coordinator fuses every unit's position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from mars_link.core.errors import UserInputError
from mars_link.core.rotations import cross3, quat_to_rotmat
from mars_link.core.state import ImuSample, PositionSample, RigidBodyState


@dataclass
class SensorParams:
    """Noise levels (1 sigma per sample, white) and the gyro bias bound; SI units."""

    gyro_noise_radps: float = 0.003  # MEMS gyro at a few hundred Hz
    gyro_bias_max_radps: float = 0.002  # constant per-unit bias, uniform in +-max per axis
    accel_noise_mps2: float = 0.05
    position_noise_m: float = 0.01  # motion capture / RTK: indoor-scale assemblies
    velocity_noise_mps: float = 0.02
    report_velocity: bool = True  # position samples carry a velocity (RTK/mocap do)

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name != "report_velocity" and not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise UserInputError(f"sensor parameter {f.name} must be a finite number >= 0, got {v!r}")


class SensorModel:
    """Deterministic for a seed; `noise=False` returns the truth exactly.

    The angular acceleration for the lever-arm term is taken from the caller when given (JSBSim
    knows it), otherwise differenced from the body rates of successive calls, remembered per unit
    (imu) or per unit group (sample_units) so that several bodies can share one model.
    """

    def __init__(self, params: SensorParams, seed: int, noise: bool = True) -> None:
        self.params = params
        self.seed = int(seed)
        self.noise = noise
        self.rng = np.random.default_rng(self.seed)
        self._bias: dict[int, np.ndarray] = {}
        self._bias_rows: dict[tuple[int, ...], np.ndarray] = {}  # (the hot path: one body's units' biases)
        self._rates: dict[object, tuple[float, np.ndarray, np.ndarray]] = {}  # key -> (t, omega, alpha)

    def gyro_bias(self, unit_id: int) -> np.ndarray:
        """The unit's constant gyro bias: its own stream, independent of the sampling order."""
        if unit_id not in self._bias:
            b = self.params.gyro_bias_max_radps
            rng = np.random.default_rng([self.seed, int(unit_id)])
            self._bias[unit_id] = rng.uniform(-b, b, 3) if self.noise else np.zeros(3)
        return self._bias[unit_id]

    def _angular_acceleration(self, key: object, t_s: float, omega: np.ndarray) -> np.ndarray:
        """Finite difference of the body rate between sensing instants."""
        last = self._rates.get(key)
        if last is None:
            alpha = np.zeros(3)
        elif t_s > last[0]:
            alpha = (omega - last[1]) / (t_s - last[0])
        else:  # same instant again (or time went back): keep the last estimate
            alpha = last[2]
        if last is None or t_s != last[0]:
            self._rates[key] = (t_s, omega.copy(), alpha)
        return alpha

    def imu(
        self,
        t_s: float,
        body: RigidBodyState,
        specific_force_frd: np.ndarray,
        unit_offset_frd_m: np.ndarray,
        unit_id: int,
        angular_accel_frd_radps2: np.ndarray | None = None,
    ) -> ImuSample:
        """Gyro and accelerometer of the unit whose centre is `unit_offset_frd_m` from the CoM."""
        w = body.angular_velocity_frd_radps
        alpha = (
            self._angular_acceleration(unit_id, t_s, w) if angular_accel_frd_radps2 is None
            else angular_accel_frd_radps2
        )
        r = unit_offset_frd_m
        accel = specific_force_frd + cross3(alpha, r) + cross3(w, cross3(w, r))
        gyro = w.copy()
        if self.noise:
            p = self.params
            gyro = gyro + self.gyro_bias(unit_id) + self.rng.normal(0.0, p.gyro_noise_radps, 3)
            accel = accel + self.rng.normal(0.0, p.accel_noise_mps2, 3)
        return ImuSample(t_s, unit_id, gyro, accel)

    def sample_units(
        self, t_s: float, body: RigidBodyState, specific_force_frd: np.ndarray, offsets_frd_m: np.ndarray,
        unit_ids: list[int], angular_accel_frd_radps2: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """All units of one body at once: gyro, accel (N, 3) FRD; position, velocity (N, 3) NED (views of
        `sample_block`). Same physics as imu() + position()."""
        block = self.sample_block(t_s, body, specific_force_frd, offsets_frd_m, unit_ids, angular_accel_frd_radps2)
        return block[:, 0:3], block[:, 3:6], block[:, 6:9], block[:, 9:12]

    def sample_block(
        self, t_s: float, body: RigidBodyState, specific_force_frd: np.ndarray, offsets_frd_m: np.ndarray,
        unit_ids: list[int], angular_accel_frd_radps2: np.ndarray | None = None,
    ) -> np.ndarray:
        """`sample_units` as one (N, 12) array, columns gyro, accel, position, velocity (the hot path: the
        world rounds it to the wire in one call)."""
        w = body.angular_velocity_frd_radps
        alpha = (
            self._angular_acceleration(tuple(unit_ids), t_s, w) if angular_accel_frd_radps2 is None
            else angular_accel_frd_radps2
        )
        r = offsets_frd_m
        n = len(unit_ids)
        w0, w1, w2 = w.tolist()  # (floats: building from numpy scalars costs more, same values)
        a0, a1, a2 = alpha.tolist()
        wx = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
        ax = np.array([[0.0, -a2, a1], [a2, 0.0, -a0], [-a1, a0, 0.0]])
        rot = quat_to_rotmat(body.quaternion_wxyz)
        # one product for the three per-unit terms (few numpy calls: this runs every step for every body):
        # lever arm (alpha x r + omega x (omega x r)), R r, R (omega x r); then the body's own terms
        m9 = np.concatenate((ax + wx @ wx, rot, rot @ wx))
        out = r @ m9.T  # (N, 9): accel, pos, vel columns
        out += np.concatenate((specific_force_frd, body.position_ned_m, body.velocity_ned_mps))
        block = np.empty((n, 12))
        if self.noise:
            key = tuple(unit_ids)
            bias = self._bias_rows.get(key)
            if bias is None:
                bias = self._bias_rows[key] = np.array([self.gyro_bias(u) for u in unit_ids])
            noise = self.rng.normal(0.0, 1.0, (n, 12))
            noise *= self._noise_scale()
            np.add(w + bias, noise[:, 0:3], out=block[:, 0:3])
            np.add(out, noise[:, 3:12], out=block[:, 3:12])
        else:
            block[:, 0:3] = w
            block[:, 3:12] = out
        return block

    def _noise_scale(self) -> np.ndarray:
        """1-sigma of the 12 columns of one unit's sample: gyro, accel, position, velocity (3 each)."""
        p = self.params
        key = (p.gyro_noise_radps, p.accel_noise_mps2, p.position_noise_m, p.velocity_noise_mps)
        if getattr(self, "_scale_key", None) != key:
            self._scale_key, self._scale = key, np.repeat(key, 3)
        return self._scale

    def position(
        self, t_s: float, body: RigidBodyState, unit_offset_frd_m: np.ndarray, unit_id: int
    ) -> PositionSample:
        """Position (and velocity) of the unit centre: CoM + R r, v + R (omega x r)."""
        rot = quat_to_rotmat(body.quaternion_wxyz)
        pos = body.position_ned_m + rot @ unit_offset_frd_m
        vel = body.velocity_ned_mps + rot @ cross3(body.angular_velocity_frd_radps, unit_offset_frd_m)
        if self.noise:
            p = self.params
            pos = pos + self.rng.normal(0.0, p.position_noise_m, 3)
            vel = vel + self.rng.normal(0.0, p.velocity_noise_mps, 3)
        return PositionSample(t_s, unit_id, pos, vel if self.params.report_velocity else None)
