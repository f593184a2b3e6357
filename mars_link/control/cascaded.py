"""Cascaded geometric controller for an assembly of any shape ("cascaded").

Position loop (PID with acceleration feed-forward) -> desired thrust direction and attitude ->
geometric attitude control on SO(3) (Lee, Leok, McClamroch 2010 form) with body-rate feed-forward
from the reference jerk -> wrench (thrust_n, L, M, N) about the CoM, FRD -> the allocator.

Shape independence: every loop is designed in acceleration units (m/s², rad/s²) from a closed-loop
natural frequency and damping, then multiplied by the assembly's mass and full inertia tensor, so a
1x1 and a 5x5 (or an L) get the same closed-loop dynamics without hand tuning. Bandwidths shrink with
the control rate (and the motor lag, when the preset has one).

The reference is for the tracked point (e.g. unit 1's centre); it is moved to the CoM with the yaw
reference, feed-forward included. Plain floats inside `update`: it runs every control step of a loop
that must run many times faster than real time.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from mars_link.allocation.base import Allocator
from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.control.base import ControlOutput, Controller
from mars_link.core.errors import UserInputError
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import TrajectoryPoint


@dataclass
class CascadedGains:
    """Closed-loop design targets; physical gains are these times mass or inertia."""

    position_wn_radps: float = 2.0
    position_damping: float = 0.9
    position_ki_per_s3: float = 0.8  # integral gain, m/s² per (m·s)
    # |∫e dt| bound per axis, m·s: ki·limit = 3.2 m/s² trims a steady wind's drag (a 5 m/s wind needs
    # 2.4 m/s² with the RotorPy drag, mars_link.models.aerodynamics); still-air flights never reach 0.5
    integral_limit_ms: float = 4.0
    attitude_wn_radps: float = 12.0
    attitude_damping: float = 0.85
    yaw_wn_radps: float = 4.0
    max_tilt_deg: float = 35.0
    max_thrust_fraction: float = 0.9  # of the allocator's total rotor thrust, keeps attitude authority

    @classmethod
    def for_model(cls, model: AssemblyModel, control_hz: float) -> "CascadedGains":
        """Bandwidths from the control rate and motor lag (a sampled loop stays well damped with
        wn below about rate/8 and 1/(4·tau)); mass and inertia enter through the controller."""
        if not (control_hz > 0 and math.isfinite(control_hz)):
            raise UserInputError(f"control_hz must be a positive number, got {control_hz!r}")
        att = min(12.0, control_hz / 5.0)
        tau = model.vehicle.motor_time_constant_s
        if tau > 0:
            att = min(att, 0.25 / tau)
        pos = min(2.0, att / 3.5)
        return cls(
            position_wn_radps=pos,
            position_ki_per_s3=0.4 * pos,
            attitude_wn_radps=att,
            yaw_wn_radps=min(4.0, att / 2.5),
        )


class CascadedController(Controller):
    """Position -> attitude -> wrench for any connected layout; allocation by `allocator`."""

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
        offset = np.zeros(3) if tracked_offset_frd_m is None else np.asarray(tracked_offset_frd_m, float)
        if offset.shape != (3,) or not np.all(np.isfinite(offset)):
            raise UserInputError(f"tracked_offset_frd_m must be 3 finite numbers, got {tracked_offset_frd_m!r}")
        self.offset = offset
        self.gains = gains or CascadedGains.for_model(model, control_hz)
        self.dt_s = 1.0 / control_hz
        self.mass_kg = model.mass_kg
        self.inertia = model.inertia_kgm2.copy()
        self._j = [[float(x) for x in row] for row in self.inertia]
        g = self.gains
        self.kp = g.position_wn_radps**2
        self.kd = 2.0 * g.position_damping * g.position_wn_radps
        self.kr = g.attitude_wn_radps**2
        self.kw = 2.0 * g.attitude_damping * g.attitude_wn_radps
        self.kr_yaw = g.yaw_wn_radps**2
        self.kw_yaw = 2.0 * g.attitude_damping * g.yaw_wn_radps
        self.max_horizontal_acc = GRAVITY_MPS2 * math.tan(math.radians(g.max_tilt_deg))
        self._update_thrust_cap()
        self.reset()

    def reset(self) -> None:
        self.integral = np.zeros(3)
        self._int = [0.0, 0.0, 0.0]

    def set_faults(self, eta: np.ndarray) -> None:
        self.allocator.set_eta(eta)
        self._update_thrust_cap()

    def set_available(self, available: np.ndarray | None) -> None:
        """Each rotor's share of its maximum thrust that its unit's battery still gives (the allocator's bounds)."""
        self.allocator.set_available(available)
        self._update_thrust_cap()

    def _update_thrust_cap(self) -> None:
        """Total thrust the live rotors can give (inf without rotor limits), derated for attitude."""
        a = self.allocator
        if a.max_thrust_n is None:
            self.max_total_thrust_n = math.inf
        elif a.available is None:
            self.max_total_thrust_n = self.gains.max_thrust_fraction * a.max_thrust_n * float(np.sum(a.eta))
        else:
            self.max_total_thrust_n = self.gains.max_thrust_fraction * float(a.upper_bounds() @ a.eta)

    # ----------------------------------------------------------------- control law
    def update(self, t_s: float, state: RigidBodyState, reference: TrajectoryPoint) -> ControlOutput:
        c0 = time.perf_counter()
        g = self.gains
        px, py, pz = state.position_ned_m.tolist()
        vx, vy, vz = state.velocity_ned_mps.tolist()
        qw, qx, qy, qz = state.quaternion_wxyz.tolist()
        wx, wy, wz = state.angular_velocity_frd_radps.tolist()
        rpx, rpy, rpz = reference.position_ned_m.tolist()
        rvx, rvy, rvz = reference.velocity_ned_mps.tolist()
        rax, ray, raz = reference.acceleration_ned_mps2.tolist()
        rjx, rjy, rjz = reference.jerk_ned_mps3.tolist()
        yaw, yaw_rate = float(reference.yaw_rad), float(reference.yaw_rate_radps)
        cy, sy = math.cos(yaw), math.sin(yaw)

        # tracked point -> CoM: p_com = p_ref - Rz(yaw) @ offset (offset z kept in the world)
        ox, oy, oz = self.offset.tolist()
        dx, dy = cy * ox - sy * oy, sy * ox + cy * oy
        w2 = yaw_rate * yaw_rate
        rpx, rpy, rpz = rpx - dx, rpy - dy, rpz - oz
        rvx, rvy = rvx + yaw_rate * dy, rvy - yaw_rate * dx
        rax, ray = rax + w2 * dx, ray + w2 * dy

        # position PID in acceleration units (bounded integral)
        ex, ey, ez = px - rpx, py - rpy, pz - rpz
        i = self._int
        if not state.on_ground:
            lim = g.integral_limit_ms
            i[0] = min(lim, max(-lim, i[0] + ex * self.dt_s))
            i[1] = min(lim, max(-lim, i[1] + ey * self.dt_s))
            i[2] = min(lim, max(-lim, i[2] + ez * self.dt_s))
        kp, kd, ki = self.kp, self.kd, g.position_ki_per_s3
        ax = rax - kp * ex - kd * (vx - rvx) - ki * i[0]
        ay = ray - kp * ey - kd * (vy - rvy) - ki * i[1]
        az = raz - kp * ez - kd * (vz - rvz) - ki * i[2]
        horiz = math.hypot(ax, ay)
        if horiz > self.max_horizontal_acc:
            ax *= self.max_horizontal_acc / horiz
            ay *= self.max_horizontal_acc / horiz
        # thrust direction: body z (down) must point along -(wanted force); never ask to fly inverted
        fx, fy, fz = ax, ay, az - GRAVITY_MPS2  # force per unit mass, NED
        fz = min(fz, -0.2 * GRAVITY_MPS2)
        if reference.max_tilt_rad is not None:  # (PX4's limitTilt: the horizontal share of the thrust, bounded)
            horiz, most = math.hypot(fx, fy), -fz * math.tan(reference.max_tilt_rad)
            if horiz > most:
                fx, fy = fx * most / horiz, fy * most / horiz
        fn = math.sqrt(fx * fx + fy * fy + fz * fz)
        b3x, b3y, b3z = -fx / fn, -fy / fn, -fz / fn

        # desired frame: b1 towards the yaw heading, projected orthogonal to b3
        b2x, b2y, b2z = -b3z * sy, b3z * cy, b3x * sy - b3y * cy  # b3 x (cos yaw, sin yaw, 0)
        n2 = math.sqrt(b2x * b2x + b2y * b2y + b2z * b2z)
        b2x, b2y, b2z = b2x / n2, b2y / n2, b2z / n2
        b1x, b1y, b1z = b2y * b3z - b2z * b3y, b2z * b3x - b2x * b3z, b2x * b3y - b2y * b3x

        # feed-forward body rates of the desired frame from the reference jerk: b3' = -(I - b3 b3^T) j / |f|
        jb = rjx * b3x + rjy * b3y + rjz * b3z
        d3x, d3y, d3z = -(rjx - jb * b3x) / fn, -(rjy - jb * b3y) / fn, -(rjz - jb * b3z) / fn
        wdx = -(b2x * d3x + b2y * d3y + b2z * d3z)
        wdy = b1x * d3x + b1y * d3y + b1z * d3z
        wdz = yaw_rate * b3z

        # current attitude R (body FRD -> NED) from the quaternion
        r00 = 1 - 2 * (qy * qy + qz * qz); r01 = 2 * (qx * qy - qw * qz); r02 = 2 * (qx * qz + qw * qy)
        r10 = 2 * (qx * qy + qw * qz); r11 = 1 - 2 * (qx * qx + qz * qz); r12 = 2 * (qy * qz - qw * qx)
        r20 = 2 * (qx * qz - qw * qy); r21 = 2 * (qy * qz + qw * qx); r22 = 1 - 2 * (qx * qx + qy * qy)
        # thrust: wanted force projected on the current thrust axis (-body z), capped
        thrust = max(0.0, -self.mass_kg * (fx * r02 + fy * r12 + fz * r22))
        thrust = min(thrust, self.max_total_thrust_n)

        # E = R_des^T R (columns b1 b2 b3 of R_des); e_R = vee(E - E^T) / 2
        e00 = b1x * r00 + b1y * r10 + b1z * r20; e01 = b1x * r01 + b1y * r11 + b1z * r21
        e02 = b1x * r02 + b1y * r12 + b1z * r22
        e10 = b2x * r00 + b2y * r10 + b2z * r20; e11 = b2x * r01 + b2y * r11 + b2z * r21
        e12 = b2x * r02 + b2y * r12 + b2z * r22
        e20 = b3x * r00 + b3y * r10 + b3z * r20; e21 = b3x * r01 + b3y * r11 + b3z * r21
        e22 = b3x * r02 + b3y * r12 + b3z * r22
        erx, ery, erz = 0.5 * (e21 - e12), 0.5 * (e02 - e20), 0.5 * (e10 - e01)
        # desired rate seen in the current body frame: R^T R_des w_des = E^T w_des
        ewx = wx - (e00 * wdx + e10 * wdy + e20 * wdz)
        ewy = wy - (e01 * wdx + e11 * wdy + e21 * wdz)
        ewz = wz - (e02 * wdx + e12 * wdy + e22 * wdz)
        alx = -self.kr * erx - self.kw * ewx
        aly = -self.kr * ery - self.kw * ewy
        alz = -self.kr_yaw * erz - self.kw_yaw * ewz

        # M = J alpha + w x J w (gyroscopic term of the rigid body)
        (j00, j01, j02), (j10, j11, j12), (j20, j21, j22) = self._j
        hx, hy, hz = j00 * wx + j01 * wy + j02 * wz, j10 * wx + j11 * wy + j12 * wz, j20 * wx + j21 * wy + j22 * wz
        mx = j00 * alx + j01 * aly + j02 * alz + (wy * hz - wz * hy)
        my = j10 * alx + j11 * aly + j12 * alz + (wz * hx - wx * hz)
        mz = j20 * alx + j21 * aly + j22 * alz + (wx * hy - wy * hx)
        self.integral[:] = i
        wrench = np.array([thrust, mx, my, mz])
        c1 = time.perf_counter()
        thrusts = self.allocator.allocate(wrench)
        c2 = time.perf_counter()
        return ControlOutput(thrusts, wrench, {"control": c1 - c0, "allocation": c2 - c1})
