"""JSBSim bodies generated from the assembly model: mass properties, hover, torque, free fall, ground."""

from __future__ import annotations

import numpy as np
import pytest

from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.core.rotations import euler_to_quat, quat_to_euler, tilt_deg
from mars_link.core.state import RigidBodyState
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


@pytest.mark.parametrize("axis", ["roll", "pitch", "yaw"])
def test_pure_torque_step_gives_the_analytic_angular_acceleration(axis: str) -> None:
    model = AssemblyModel.from_layout(LAYOUTS["L"])
    hover = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
    # a torque about one axis with zero net force change (the L's CoM is off the unit grid)
    pattern = {
        "roll": -model.rotor_positions_m[:, 1],  # left rotors (y < 0) up: + roll
        "pitch": model.rotor_positions_m[:, 0],  # front rotors up: + pitch (nose up)
        "yaw": model.rotor_yaw_signs.astype(float),  # + yaw reaction torque
    }[axis]
    delta = 0.05 * (pattern - pattern.mean())
    delta /= np.abs(delta).max() / 0.05
    thrusts = hover + delta
    wrench = model.wrench_from_thrusts(thrusts)
    assert wrench[0] == pytest.approx(model.mass_kg * GRAVITY_MPS2)
    k = ["roll", "pitch", "yaw"].index(axis)
    assert wrench[1 + k] > 0
    expected = np.linalg.solve(model.inertia_kgm2, wrench[1:])  # the L couples roll and pitch
    body = airborne(model, thrusts)
    dt = 0.02
    body.step(int(round(dt * 500)))
    measured = body.state().angular_velocity_frd_radps / dt
    np.testing.assert_allclose(measured, expected, rtol=0, atol=0.01 * abs(expected[k]))
    assert measured[k] > 0
    np.testing.assert_allclose(body.angular_acceleration_frd(), expected, rtol=0, atol=0.01 * abs(expected[k]))


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
    assert quat_to_euler(s.quaternion_wxyz)[2] == pytest.approx(0.3, abs=1e-6)
    np.testing.assert_allclose(body.specific_force_frd(), [0, 0, -GRAVITY_MPS2], atol=1e-3)


@pytest.mark.parametrize("name", ["1x1", "3x2", "L"])
def test_touch_down_from_feet_on_the_ground_sinks_level_without_bounce(name: str) -> None:
    """The settling that a ground start hides before t = 0, watched from its first step."""
    model = AssemblyModel.from_layout(LAYOUTS[name])
    depth = model.vehicle.gear_depth_m
    touching = RigidBodyState(0.0, np.array([0.0, 0.0, -depth]), np.zeros(3), euler_to_quat(0, 0, 0), np.zeros(3))
    with JsbsimBody(model, state=touching) as body:
        downs, tilts = [], []
        for _ in range(1000):
            body.step()
            s = body.state()
            downs.append(s.position_ned_m[2] + depth)  # compression, m
            tilts.append(tilt_deg(s.quaternion_wxyz))
    downs = np.array(downs)
    assert downs.min() > -1e-6  # never lifts off
    assert 0.0 < downs.max() < 0.002  # sinks less than 2 mm
    assert downs[-1] == pytest.approx(downs.max(), abs=2e-5)  # overdamped: no overshoot back up
    assert max(tilts) < 0.01  # contact stiffness centred on the CoM, also for the L
    assert s.on_ground


def test_lift_off_with_more_than_hover_thrust() -> None:
    model = AssemblyModel.from_layout(LAYOUTS["3x2"])
    with JsbsimBody(model) as body:
        assert body.state().on_ground
        body.set_rotor_thrusts(np.full(model.n_rotors, 1.2 * model.hover_thrust_per_rotor_n()))
        body.step(500)
        body.step()  # acceleration_ned_mps2 is the mean over the last step() call
        s = body.state()
    assert not s.on_ground
    # 0.2 g up for (nearly) 1 s after the springs let go: about a metre
    assert -s.position_ned_m[2] - model.vehicle.gear_depth_m == pytest.approx(0.1 * GRAVITY_MPS2, rel=0.05)
    np.testing.assert_allclose(s.acceleration_ned_mps2, [0, 0, -0.2 * GRAVITY_MPS2], atol=1e-4)


def test_bodies_in_one_process_are_independent_and_clean_up() -> None:
    a = JsbsimBody(AssemblyModel.from_layout(["X"]), position_ned_m=(0.0, 0.0, 0.0))
    b = airborne(AssemblyModel.from_layout(["XX"]), np.zeros(8))
    a_before = a.state().position_ned_m.copy()
    # the generated aircraft folders are gone once the models are loaded (a SIGKILLed unit leaks none)
    assert not a._dir.exists() and not b._dir.exists()
    b.step(250)
    a.step(250)
    np.testing.assert_allclose(a.state().position_ned_m, a_before, atol=1e-5)
    assert b.state().velocity_ned_mps[2] == pytest.approx(0.5 * GRAVITY_MPS2, rel=1e-4)
    assert a.t_s == pytest.approx(0.5) and b.t_s == pytest.approx(0.5)
    b.close()
    a.close()
    assert b.fdm is None and a.fdm is None


def test_bad_rate_state_and_thrust_count_are_refused() -> None:
    model = AssemblyModel.from_layout(["X"])
    with pytest.raises(UserInputError, match="physics rate"):
        JsbsimBody(model, physics_hz=0.0)
    bad = RigidBodyState(0.0, np.array([0.0, np.nan, -1.0]), np.zeros(3), euler_to_quat(0, 0, 0), np.zeros(3))
    with pytest.raises(UserInputError, match="finite"):
        JsbsimBody(model, state=bad)
    with JsbsimBody(model) as body, pytest.raises(ValueError, match="4 rotor thrusts"):
        body.set_rotor_thrusts(np.zeros(3))


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


def test_a_transferred_body_flies_on_like_the_original() -> None:
    """Thrusts set before run_ic: the copy continues the manoeuvre (no integrator kick)."""
    model = AssemblyModel.from_layout(LAYOUTS["L"])
    thrusts = np.full(model.n_rotors, model.hover_thrust_per_rotor_n()) + 0.03 * np.sign(-model.rotor_positions_m[:, 1])
    start = RigidBodyState(0.0, np.array([0.0, 0.0, -10.0]), np.array([1.0, 0.0, 0.0]), euler_to_quat(0, 0, 0),
                           np.array([0.0, 0.0, 0.5]))
    with JsbsimBody(model, state=start, rotor_thrusts_n=thrusts) as original:
        original.step(100)
        with JsbsimBody(model, state=original.state(), rotor_thrusts_n=thrusts) as copy:
            original.step(500)
            copy.step(500)
            a, b = original.state(), copy.state()
    assert a.t_s == pytest.approx(b.t_s) and a.t_s == pytest.approx(1.2)
    assert np.linalg.norm(a.angular_velocity_frd_radps) > 0.3  # it really manoeuvred
    np.testing.assert_allclose(b.position_ned_m, a.position_ned_m, atol=1e-4)
    np.testing.assert_allclose(b.velocity_ned_mps, a.velocity_ned_mps, atol=1e-4)
    np.testing.assert_allclose(b.quaternion_wxyz, a.quaternion_wxyz, atol=1e-5)
    np.testing.assert_allclose(b.angular_velocity_frd_radps, a.angular_velocity_frd_radps, atol=1e-9)
