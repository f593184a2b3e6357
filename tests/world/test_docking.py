"""Undocking and docking of JSBSim bodies (sitl/docking.py): momentum kept, latch tolerance."""

from __future__ import annotations

import numpy as np

from mars_link.core.assembly import AssemblyModel
from mars_link.core.rotations import euler_to_quat, quat_to_rotmat
from mars_link.core.state import RigidBodyState
from sitl.docking import DockTolerance, dock_check, merge_bodies, momentum, split_body
from sitl.physics import JsbsimBody


def _moving_3x1() -> tuple[AssemblyModel, JsbsimBody]:
    model = AssemblyModel.from_layout("XXX", "mars-ftcc")
    state = RigidBodyState(0.0, np.array([1.0, 2.0, -5.0]), np.array([0.4, -0.3, 0.1]),
                           euler_to_quat(0.05, -0.03, 0.7), np.array([0.2, -0.1, 0.3]))
    hover = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
    body = JsbsimBody(model, physics_hz=500, state=state, rotor_thrusts_n=hover)
    body.step(25)  # fly a little so the state is JSBSim's own, not the initial condition
    return model, body


def _parts(model):
    one = AssemblyModel.from_layout("X", model.vehicle)
    two = AssemblyModel.from_layout("XX", model.vehicle)
    off1 = model.unit_position(1)
    off23 = (model.unit_position(2) + model.unit_position(3)) / 2
    f = model.hover_thrust_per_rotor_n()
    return [(one, off1, np.full(4, f)), (two, off23, np.full(8, f))]


def test_split_keeps_linear_and_angular_momentum():
    model, body = _moving_3x1()
    before = body.state()
    p0, l0 = momentum([before], [model])
    children = split_body(body, _parts(model))
    states = [c.state() for c in children]
    p1, l1 = momentum(states, [c.model for c in children], about_ned_m=before.position_ned_m)
    assert np.allclose(p1, p0, rtol=1e-9, atol=1e-9)
    assert np.allclose(l1, l0, rtol=1e-7, atol=1e-9)
    # each child sits where its units were and moves with the parent's rigid-body velocity there
    r = quat_to_rotmat(before.quaternion_wxyz)
    assert np.allclose(states[0].position_ned_m, before.position_ned_m + r @ model.unit_position(1), atol=1e-9)
    w = r @ before.angular_velocity_frd_radps
    v1 = before.velocity_ned_mps + np.cross(w, r @ model.unit_position(1))
    assert np.allclose(states[0].velocity_ned_mps, v1, atol=1e-9)
    assert np.allclose(states[1].angular_velocity_frd_radps, before.angular_velocity_frd_radps, atol=1e-12)
    # a unit that flies off really moves away from the rest (the bodies are independent now)
    for c in children:
        c.step(50)
    gap = np.linalg.norm(children[0].state().position_ned_m - children[1].state().position_ned_m)
    assert abs(gap - 1.5 * model.vehicle.pitch_m) < 0.05
    for c in children:
        c.close()


def test_split_then_merge_gives_the_parent_back():
    model, body = _moving_3x1()
    before = body.state()
    children = split_body(body, _parts(model))
    merged = merge_bodies(children, model, np.full(model.n_rotors, model.hover_thrust_per_rotor_n()))
    after = merged.state()
    assert np.allclose(after.position_ned_m, before.position_ned_m, atol=1e-9)
    assert np.allclose(after.velocity_ned_mps, before.velocity_ned_mps, atol=1e-9)
    assert np.allclose(after.angular_velocity_frd_radps, before.angular_velocity_frd_radps, atol=1e-7)
    mass, _, inertia = merged.mass_properties()
    assert abs(mass - model.mass_kg) < 1e-6 and np.allclose(inertia, model.inertia_kgm2, rtol=1e-4, atol=1e-7)
    merged.close()


def test_merge_of_two_moving_bodies_keeps_momentum():
    vehicle = AssemblyModel.from_layout("X", "mars-ftcc").vehicle
    one, two = AssemblyModel.from_layout("X", vehicle), AssemblyModel.from_layout("XX", vehicle)
    q = euler_to_quat(0.0, 0.0, 0.3)
    r = quat_to_rotmat(q)
    s2 = RigidBodyState(0.0, np.array([0.0, 0.0, -3.0]), np.array([0.1, 0.0, 0.0]), q, np.array([0.0, 0.0, 0.05]))
    # the single unit at its dock pose on the left of the pair, closing at 4 cm/s
    off = np.array([0.0, -1.5 * vehicle.pitch_m, 0.0])
    s1 = RigidBodyState(0.0, s2.position_ned_m + r @ off, np.array([0.1, 0.04, 0.0]), q, np.zeros(3))
    bodies = [JsbsimBody(two, state=s2, rotor_thrusts_n=np.zeros(8)), JsbsimBody(one, state=s1, rotor_thrusts_n=np.zeros(4))]
    states = [b.state() for b in bodies]
    p0, l0 = momentum(states, [two, one])
    assert dock_check(states[0], states[1], off).ready
    whole = AssemblyModel.from_layout("XXX", vehicle)
    merged = merge_bodies(bodies, whole, np.zeros(12))
    s = merged.state()
    p1, l1 = momentum([s], [whole], about_ned_m=(two.mass_kg * s2.position_ned_m + one.mass_kg * s1.position_ned_m) / 1.56)
    assert np.allclose(p1, p0, atol=1e-9) and np.allclose(l1, l0, atol=1e-9)
    merged.close()


def test_dock_latch_tolerance():
    q = euler_to_quat(0.0, 0.0, 0.0)
    st = RigidBodyState(0.0, np.zeros(3), np.zeros(3), q, np.zeros(3))
    off = np.array([0.0, 0.35, 0.0])

    def mover(dp=(0, 0, 0), v=(0, 0, 0), yaw_deg=0.0):
        return RigidBodyState(0.0, off + np.array(dp, float), np.array(v, float),
                              euler_to_quat(0.0, 0.0, np.radians(yaw_deg)), np.zeros(3))

    tol = DockTolerance()
    assert dock_check(st, mover((0.01, 0, 0)), off, tol).ready
    assert not dock_check(st, mover((0.0, 0.025, 0)), off, tol).ready  # 2.5 cm off
    assert not dock_check(st, mover(v=(0, 0.06, 0)), off, tol).ready  # closing too fast
    assert not dock_check(st, mover(yaw_deg=2.5), off, tol).ready  # yawed
    assert dock_check(st, mover(yaw_deg=1.5), off, tol).ready
