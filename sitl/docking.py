"""Undocking (split one rigid body into two) and docking (merge two into one), momentum kept.

Paper 001's simulator resets a split or merged body to zero velocity and a level attitude
(specs/reconfig.md §1.4, §14 item 8); here both events are physically consistent:

* split: each child keeps the parent's attitude and body rate, and its CoM moves with the parent's
  rigid-body velocity at that point, v + ω × r. Linear and angular momentum of the children equal the
  parent's (parallel-axis theorem), exactly.
* merge: the new CoM is the mass-weighted mean of the actual CoMs, its velocity the mass-weighted
  mean of the velocities, its body rate I⁻¹·L from the total angular momentum about the new CoM
  (spins plus orbital terms). The merged body takes the attitude of the stationary (first) body:
  docking is only allowed when the attitudes agree within `DockTolerance`.

A dock happens only when the mover sits at its dock pose relative to the stationary body within
`DockTolerance` (documented figures below), like a latch that closes on contact. The grid is exact
after a dock (the merged model puts the units one pitch apart); the residual misalignment (< the
position tolerance) is absorbed in the merged CoM.

Each new body is a fresh JSBSim model generated for its layout (`JsbsimBody`, whose `state` start and
`rotor_thrusts_n` follow specs/dependencies.md §1.6: forces set before run_ic, clock aligned).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mars_link.core.assembly import AssemblyModel
from mars_link.core.rotations import quat_to_euler, quat_to_rotmat, wrap_pi
from mars_link.core.state import RigidBodyState
from sitl.physics import JsbsimBody


@dataclass(frozen=True)
class DockTolerance:
    """When a latch closes: the mover's CoM within `position_m` of its dock pose, relative speed below
    `speed_mps`, relative yaw below `yaw_deg` and relative roll/pitch below `tilt_deg`.

    Defaults: 2 cm, 5 cm/s, 2 deg, 3 deg (paper 000's scene docks within 2 cm; paper 001's detector
    uses 3 cm in distance and height).
    """

    position_m: float = 0.02
    speed_mps: float = 0.05
    yaw_deg: float = 2.0
    tilt_deg: float = 3.0


@dataclass
class DockCheck:
    """Relative pose of a mover to its dock pose (for logs) and whether the latch closes."""

    position_error_m: float
    speed_mps: float
    yaw_deg: float
    tilt_deg: float
    ready: bool


def child_state(parent: RigidBodyState, offset_frd_m: np.ndarray) -> RigidBodyState:
    """State of a rigid part whose CoM sits at `offset_frd_m` from the parent's CoM (body frame)."""
    r_world = quat_to_rotmat(parent.quaternion_wxyz) @ np.asarray(offset_frd_m, dtype=float)
    omega_world = quat_to_rotmat(parent.quaternion_wxyz) @ parent.angular_velocity_frd_radps
    return RigidBodyState(
        parent.t_s,
        parent.position_ned_m + r_world,
        parent.velocity_ned_mps + np.cross(omega_world, r_world),
        parent.quaternion_wxyz.copy(),
        parent.angular_velocity_frd_radps.copy(),
        parent.acceleration_ned_mps2.copy(),
    )


def momentum(states: list[RigidBodyState], models: list[AssemblyModel], about_ned_m: np.ndarray | None = None):
    """(linear momentum, angular momentum about `about_ned_m`, world NED) of a set of bodies.

    `about_ned_m` defaults to their common CoM.
    """
    masses = np.array([m.mass_kg for m in models])
    pos = np.array([s.position_ned_m for s in states])
    vel = np.array([s.velocity_ned_mps for s in states])
    c = (masses @ pos) / masses.sum() if about_ned_m is None else np.asarray(about_ned_m, float)
    p = masses @ vel
    ang = np.zeros(3)
    for s, m, mass in zip(states, models, masses):
        r = quat_to_rotmat(s.quaternion_wxyz)
        ang += r @ (m.inertia_kgm2 @ s.angular_velocity_frd_radps)  # spin
        ang += mass * np.cross(s.position_ned_m - c, s.velocity_ned_mps)  # orbit
    return p, ang


def merged_state(states: list[RigidBodyState], models: list[AssemblyModel], merged: AssemblyModel) -> RigidBodyState:
    """State of the body made by docking `states` (first = stationary body, whose attitude it takes)."""
    masses = np.array([m.mass_kg for m in models])
    total = masses.sum()
    com = (masses @ np.array([s.position_ned_m for s in states])) / total
    p, ang = momentum(states, models, com)
    q = states[0].quaternion_wxyz.copy()
    r = quat_to_rotmat(q)
    omega = np.linalg.solve(merged.inertia_kgm2, r.T @ ang)
    acc = (masses @ np.array([s.acceleration_ned_mps2 for s in states])) / total
    return RigidBodyState(states[0].t_s, com, p / total, q, omega, acc)


def dock_check(
    stationary: RigidBodyState, mover: RigidBodyState, dock_offset_frd_m: np.ndarray,
    tolerance: DockTolerance = DockTolerance(),
) -> DockCheck:
    """Is the mover at `dock_offset_frd_m` (its CoM from the stationary CoM, stationary body frame)?"""
    rs = quat_to_rotmat(stationary.quaternion_wxyz)
    offset = np.asarray(dock_offset_frd_m, dtype=float)
    target = stationary.position_ned_m + rs @ offset
    err = float(np.linalg.norm(mover.position_ned_m - target))
    omega_world = rs @ stationary.angular_velocity_frd_radps
    v_point = stationary.velocity_ned_mps + np.cross(omega_world, rs @ offset)
    speed = float(np.linalg.norm(mover.velocity_ned_mps - v_point))
    r_rel = rs.T @ quat_to_rotmat(mover.quaternion_wxyz)
    yaw = abs(math.degrees(math.atan2(r_rel[1, 0], r_rel[0, 0])))
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(r_rel[2, 2])))))
    ready = (err < tolerance.position_m and speed < tolerance.speed_mps and yaw < tolerance.yaw_deg
             and tilt < tolerance.tilt_deg)
    return DockCheck(err, speed, yaw, tilt, ready)


def split_body(
    parent: JsbsimBody, parts: list[tuple[AssemblyModel, np.ndarray, np.ndarray]], work_dirs=None,
) -> list[JsbsimBody]:
    """Undock: one new JsbsimBody per part (model, CoM offset FRD from the parent CoM, rotor thrusts).

    The parent is closed. The parts' masses must add up to the parent's.
    """
    total = sum(m.mass_kg for m, _, _ in parts)
    if not math.isclose(total, parent.model.mass_kg, rel_tol=1e-9):
        raise ValueError(f"parts weigh {total} kg, the parent {parent.model.mass_kg} kg")
    state = parent.state()
    hz = 1.0 / parent.dt_s
    bodies = [
        JsbsimBody(model, physics_hz=hz, state=child_state(state, offset), rotor_thrusts_n=np.asarray(thrusts, float),
                   work_dir=None if work_dirs is None else work_dirs[i])
        for i, (model, offset, thrusts) in enumerate(parts)
    ]
    parent.close()
    return bodies


def merge_bodies(bodies: list[JsbsimBody], merged: AssemblyModel, rotor_thrusts_n: np.ndarray) -> JsbsimBody:
    """Dock: one JsbsimBody for `merged` from `bodies` (first = stationary); the inputs are closed."""
    state = merged_state([b.state() for b in bodies], [b.model for b in bodies], merged)
    hz = 1.0 / bodies[0].dt_s
    new = JsbsimBody(merged, physics_hz=hz, state=state, rotor_thrusts_n=np.asarray(rotor_thrusts_n, float))
    for b in bodies:
        b.close()
    return new


def yaw_deg(state: RigidBodyState) -> float:
    return math.degrees(quat_to_euler(state.quaternion_wxyz)[2])


def yaw_difference_deg(a_deg: float, b_deg: float) -> float:
    return math.degrees(wrap_pi(math.radians(a_deg - b_deg)))
