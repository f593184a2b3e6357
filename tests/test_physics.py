"""JSBSim bodies generated from the assembly model: mass properties, hover, torque, free fall, ground."""

from __future__ import annotations

import numpy as np
import pytest

from mars_link.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.rotations import euler_to_quat
from mars_link.state import RigidBodyState
from sitl.physics import JsbsimBody

LAYOUTS = {"1x1": ["X"], "3x2": ["XXX", "XXX"], "L": ["X.", "XX"]}


def airborne(model: AssemblyModel, thrusts=None, **kw) -> JsbsimBody:
    start = RigidBodyState(0.0, np.array([0.0, 0.0, -10.0]), np.zeros(3), euler_to_quat(0, 0, 0), np.zeros(3))
    body = JsbsimBody(model, state=start, **kw)
    if thrusts is not None:  # forces before run_ic: no integrator transient
        body.set_rotor_thrusts(thrusts)
        body.transfer_state(start)
    return body


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_generated_mass_properties_equal_the_analytic_model(name: str) -> None:
    model = AssemblyModel.from_layout(LAYOUTS[name])
    body = JsbsimBody(model)
    mass, com, inertia = body.mass_properties()
    assert mass == pytest.approx(model.mass_kg, rel=1e-6)
    np.testing.assert_allclose(com, np.zeros(3), atol=1e-6)
    scale = np.abs(model.inertia_kgm2).max()
    np.testing.assert_allclose(inertia, model.inertia_kgm2, rtol=0, atol=1e-6 * scale)
    if name == "L":  # the product of inertia is non-zero and must keep its sign
        assert model.inertia_kgm2[0, 1] != 0
        assert np.sign(inertia[0, 1]) == np.sign(model.inertia_kgm2[0, 1])
    body.close()


@pytest.mark.parametrize("name", ["1x1", "3x2"])
def test_open_loop_hover_drifts_less_than_5mm_in_5s(name: str) -> None:
    model = AssemblyModel.from_layout(LAYOUTS[name])
    hover = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
    body = airborne(model, hover)
    p0 = body.state().position_ned_m.copy()
    body.step(2500)
    s = body.state()
    assert np.linalg.norm(s.position_ned_m - p0) < 0.005
    assert np.linalg.norm(s.angular_velocity_frd_radps) < 1e-6


def test_pure_torque_step_gives_the_analytic_angular_acceleration() -> None:
    model = AssemblyModel.from_layout(LAYOUTS["3x2"])
    hover = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
    # roll torque with zero net force: push the left rotors (y < 0) up, the right ones down
    delta = 0.05 * np.sign(-model.rotor_positions_m[:, 1])
    thrusts = hover + delta
    wrench = model.wrench_from_thrusts(thrusts)
    assert wrench[0] == pytest.approx(model.mass_kg * GRAVITY_MPS2)
    expected = np.linalg.solve(model.inertia_kgm2, wrench[1:])
    body = airborne(model, thrusts)
    dt = 0.02
    body.step(int(round(dt * 500)))
    measured = body.state().angular_velocity_frd_radps / dt
    assert measured[0] == pytest.approx(expected[0], rel=0.01)
    assert abs(measured[1]) < 0.01 * abs(expected[0])


def test_free_fall_matches_g() -> None:
    body = airborne(AssemblyModel.from_layout(["XX"]), np.zeros(8))
    body.step(500)
    s = body.state()
    # g falls off by 3e-6 relative at 10 m: well inside the tolerance; a one-step lag would be 4e-3
    assert s.t_s == pytest.approx(1.0)
    assert s.velocity_ned_mps[2] == pytest.approx(GRAVITY_MPS2 * 1.0, rel=1e-4)
    assert s.position_ned_m[2] + 10.0 == pytest.approx(0.5 * GRAVITY_MPS2 * 1.0**2, rel=1e-4)
    np.testing.assert_allclose(s.acceleration_ned_mps2, [0, 0, GRAVITY_MPS2], rtol=1e-4)
    np.testing.assert_allclose(body.specific_force_frd(), 0.0, atol=1e-6)


def test_ground_start_does_not_bounce() -> None:
    model = AssemblyModel.from_layout(LAYOUTS["3x2"])
    body = JsbsimBody(model, position_ned_m=(3.0, -2.0, 0.0), yaw_rad=0.3)
    d0 = body.state().position_ned_m[2]
    assert d0 == pytest.approx(-model.vehicle.gear_depth_m, abs=0.002)
    downs = []
    for _ in range(1000):
        body.step()
        downs.append(body.state().position_ned_m[2])
    assert max(downs) - min(downs) < 0.002
    s = body.state()
    assert s.on_ground
    np.testing.assert_allclose(s.position_ned_m[:2], [3.0, -2.0], atol=1e-4)
    np.testing.assert_allclose(body.specific_force_frd(), [0, 0, -GRAVITY_MPS2], atol=1e-3)


def test_state_transfer_into_a_new_body_is_exact() -> None:
    small = AssemblyModel.from_layout(["X"])
    q = euler_to_quat(0.1, -0.05, 1.0)
    s = RigidBodyState(1.5, np.array([1.0, 2.0, -3.0]), np.array([0.5, -0.2, 0.1]), q, np.array([0.1, -0.05, 0.2]))
    body = JsbsimBody(AssemblyModel.from_layout(["XX"]), state=s)
    got = body.state()
    np.testing.assert_allclose(got.position_ned_m, s.position_ned_m, atol=1e-9)
    np.testing.assert_allclose(got.velocity_ned_mps, s.velocity_ned_mps, atol=1e-9)
    np.testing.assert_allclose(got.quaternion_wxyz, q, atol=1e-9)
    np.testing.assert_allclose(got.angular_velocity_frd_radps, s.angular_velocity_frd_radps, atol=1e-9)
    assert got.t_s == pytest.approx(1.5)
    assert small.n_units == 1
