"""Cascaded geometric controller for an assembly of any shape.

Position loop (PID with acceleration feed-forward) -> desired thrust vector and attitude -> geometric
attitude control on SO(3) (Lee et al. 2010 form) -> wrench (thrust, L, M, N) -> allocator.

Shape independence: the loops are designed in acceleration units (linear m/s², angular rad/s²) and
then multiplied by the assembly's mass and full inertia tensor, so a 1x1 and a 5x5 get the same
closed-loop bandwidths without hand tuning. Bandwidths shrink with the control rate.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from mars_link.allocation.base import Allocator
from mars_link.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.control.base import ControlOutput, Controller
from mars_link.rotations import cross3, quat_to_rotmat
from mars_link.state import RigidBodyState
from mars_link.trajectories import TrajectoryPoint


@dataclass
class CascadedGains:
    position_wn_radps: float = 2.0
    position_damping: float = 0.9
    position_ki_per_s3: float = 0.8  # integral gain, m/s² per (m·s)
    integral_limit_ms: float = 0.5  # |∫e dt| bound per axis
    attitude_wn_radps: float = 12.0
    attitude_damping: float = 0.85
    max_tilt_deg: float = 35.0
    yaw_wn_radps: float = 4.0

    @classmethod
    def for_model(cls, model: AssemblyModel, control_hz: float) -> "CascadedGains":
        """Bandwidths from the control rate (a digital loop tolerates roughly wn < rate / 8)."""
        att = min(12.0, control_hz / 8.0)
        pos = min(2.0, att / 5.0)
        return cls(position_wn_radps=pos, attitude_wn_radps=att, yaw_wn_radps=min(4.0, att / 2.5),
                   position_ki_per_s3=0.4 * pos)


class CascadedController(Controller):
    def __init__(
        self,
        model: AssemblyModel,
        allocator: Allocator,
        tracked_offset_frd_m: np.ndarray | None = None,
        control_hz: float = 100.0,
        gains: CascadedGains | None = None,
    ) -> None:
        self.model = model
        self.allocator = allocator
        self.offset = np.zeros(3) if tracked_offset_frd_m is None else np.asarray(tracked_offset_frd_m, float)
        self.dt_s = 1.0 / control_hz
        self.gains = gains or CascadedGains.for_model(model, control_hz)
        self.mass_kg = model.mass_kg
        self.inertia = model.inertia_kgm2.copy()
        g = self.gains
        self.kp = g.position_wn_radps**2
        self.kd = 2.0 * g.position_damping * g.position_wn_radps
        self.kr = g.attitude_wn_radps**2
        self.kw = 2.0 * g.attitude_damping * g.attitude_wn_radps
        self.kr_yaw = g.yaw_wn_radps**2
        self.kw_yaw = 2.0 * g.attitude_damping * g.yaw_wn_radps
        self.max_horizontal_acc = GRAVITY_MPS2 * math.tan(math.radians(g.max_tilt_deg))
        self.reset()

    def reset(self) -> None:
        self.integral = np.zeros(3)

    def set_faults(self, eta: np.ndarray) -> None:
        self.allocator.set_eta(eta)

    # ----------------------------------------------------------------- reference for the CoM
    def _com_reference(self, ref: TrajectoryPoint) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The trajectory drives the tracked point; shift it to the CoM through the yaw reference."""
        if not self.offset.any():
            return ref.position_ned_m, ref.velocity_ned_mps, ref.acceleration_ned_mps2
        c, s = math.cos(ref.yaw_rad), math.sin(ref.yaw_rad)
        d = np.array([c * self.offset[0] - s * self.offset[1], s * self.offset[0] + c * self.offset[1], self.offset[2]])
        w = ref.yaw_rate_radps
        wxd = np.array([-w * d[1], w * d[0], 0.0])
        return (
            ref.position_ned_m - d,
            ref.velocity_ned_mps - wxd,
            ref.acceleration_ned_mps2 + w * w * np.array([d[0], d[1], 0.0]),
        )

    # ----------------------------------------------------------------- control law
    def update(self, t_s: float, state: RigidBodyState, reference: TrajectoryPoint) -> ControlOutput:
        c0 = time.perf_counter()
        p_ref, v_ref, a_ref = self._com_reference(reference)
        e_p = state.position_ned_m - p_ref
        e_v = state.velocity_ned_mps - v_ref
        g = self.gains
        if not state.on_ground:
            self.integral = np.clip(self.integral + e_p * self.dt_s, -g.integral_limit_ms, g.integral_limit_ms)
        acc = a_ref - self.kp * e_p - self.kd * e_v - g.position_ki_per_s3 * self.integral
        horiz = math.hypot(acc[0], acc[1])
        if horiz > self.max_horizontal_acc:
            acc[:2] *= self.max_horizontal_acc / horiz
        force = self.mass_kg * (acc - np.array([0.0, 0.0, GRAVITY_MPS2]))  # NED, thrust force wanted
        rot = quat_to_rotmat(state.quaternion_wxyz)
        # desired body z (down) opposes the wanted force; keep some thrust so the direction is defined
        norm = np.linalg.norm(force)
        b3 = -force / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])
        if b3[2] < 0.2:  # never ask to fly upside down
            b3[2] = 0.2
            b3 /= np.linalg.norm(b3)
        yaw = reference.yaw_rad
        b1c = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        b2 = cross3(b3, b1c)
        b2 /= np.linalg.norm(b2)
        b1 = cross3(b2, b3)
        r_des = np.column_stack((b1, b2, b3))
        thrust = max(0.0, float(-force @ rot[:, 2]))
        # geometric attitude error and rate error (desired rate: the yaw rate of the reference)
        e_rm = 0.5 * (r_des.T @ rot - rot.T @ r_des)
        e_r = np.array([e_rm[2, 1], e_rm[0, 2], e_rm[1, 0]])
        omega = state.angular_velocity_frd_radps
        omega_des = rot.T @ (r_des @ np.array([0.0, 0.0, reference.yaw_rate_radps]))
        e_w = omega - omega_des
        alpha = np.array([
            -self.kr * e_r[0] - self.kw * e_w[0],
            -self.kr * e_r[1] - self.kw * e_w[1],
            -self.kr_yaw * e_r[2] - self.kw_yaw * e_w[2],
        ])
        j = self.inertia
        moment = j @ alpha + cross3(omega, j @ omega)
        wrench = np.array([thrust, moment[0], moment[1], moment[2]])
        c1 = time.perf_counter()
        thrusts = self.allocator.allocate(wrench)
        c2 = time.perf_counter()
        return ControlOutput(thrusts, wrench, {"control": c1 - c0, "allocation": c2 - c1})
