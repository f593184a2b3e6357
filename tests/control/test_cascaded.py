"""Cascaded controller on a small rigid-body RK4 plant (test-only), then through the JSBSim runner.

The plant applies the allocated rotor thrusts through the assembly's own effectiveness matrix (with
the true rotor efficiencies and rotor limits), integrates the Newton-Euler equations with RK4 at
500 Hz and has a flat ground the assembly rests on, so every flight starts landed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mars_link.allocation import make_allocator
from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.control.cascaded import CascadedController, CascadedGains
from mars_link.core.errors import UserInputError
from mars_link.core.rotations import euler_to_quat, quat_multiply, quat_to_euler, quat_to_rotmat, tilt_deg
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import Trajectory, TrajectoryPoint, build_trajectory

LAYOUTS = {
    "1x1": ["X"],
    "3x2": ["XXX", "XXX"],
    "plus-5": [".X.", "XXX", ".X."],
    "L-4": ["X..", "XXX"],
}
PHYSICS_HZ = 500.0


class RigidBodyPlant:
    """Newton-Euler rigid body, RK4, thrusts held between control steps; ground at down = 0 (feet)."""

    def __init__(self, model: AssemblyModel, position_ned_m, quaternion_wxyz=(1.0, 0.0, 0.0, 0.0), eta=None):
        self.model = model
        self.eta = model.nominal_eta() if eta is None else np.asarray(eta, float)
        self.b = model.effectiveness(self.eta)
        self.j = model.inertia_kgm2
        self.j_inv = np.linalg.inv(self.j)
        self.ground_d_m = -model.vehicle.gear_depth_m  # CoM height when landed and level
        self.x = np.concatenate([position_ned_m, np.zeros(3), quaternion_wxyz, np.zeros(3)]).astype(float)
        self.t_s = 0.0
        self.thrusts = np.zeros(model.n_rotors)

    def set_thrusts(self, thrusts_n: np.ndarray) -> None:
        v = self.model.vehicle
        lo = -np.inf if v.rotor_min_thrust_n is None else v.rotor_min_thrust_n
        hi = np.inf if v.rotor_max_thrust_n is None else v.rotor_max_thrust_n
        self.thrusts = np.clip(thrusts_n, lo, hi)

    def _deriv(self, x: np.ndarray, wrench: np.ndarray) -> np.ndarray:
        q = x[6:10] / np.linalg.norm(x[6:10])
        w = x[10:13]
        acc = quat_to_rotmat(q) @ np.array([0.0, 0.0, -wrench[0]]) / self.model.mass_kg
        acc[2] += GRAVITY_MPS2
        q_dot = 0.5 * quat_multiply(q, np.array([0.0, *w]))
        w_dot = self.j_inv @ (wrench[1:] - np.cross(w, self.j @ w))
        return np.concatenate([x[3:6], acc, q_dot, w_dot])

    def step(self, dt_s: float) -> None:
        wrench = self.b @ self.thrusts
        x = self.x
        k1 = self._deriv(x, wrench)
        k2 = self._deriv(x + 0.5 * dt_s * k1, wrench)
        k3 = self._deriv(x + 0.5 * dt_s * k2, wrench)
        k4 = self._deriv(x + dt_s * k3, wrench)
        x = x + dt_s / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        x[6:10] /= np.linalg.norm(x[6:10])
        if x[2] >= self.ground_d_m:  # landed: the ground holds it level and still
            x[2] = self.ground_d_m
            x[3:6] = 0.0
            x[10:13] = 0.0
        self.x = x
        self.t_s += dt_s

    def state(self, rng: np.random.Generator | None = None) -> RigidBodyState:
        """True state, or with ~1 cm position, 2 cm/s velocity and 0.003 rad/s gyro noise."""
        p, v, q, w = self.x[0:3].copy(), self.x[3:6].copy(), self.x[6:10].copy(), self.x[10:13].copy()
        if rng is not None:
            p += rng.normal(0.0, 0.01, 3)
            v += rng.normal(0.0, 0.02, 3)
            w += rng.normal(0.0, 0.003, 3)
        return RigidBodyState(self.t_s, p, v, q, w, on_ground=bool(self.x[2] >= self.ground_d_m))


def fly(model, controller, trajectory, duration_s, offset, control_hz=100.0, noise_seed=None, plant=None):
    """Closed loop; returns times, tracked-point errors (m), tilts (deg) and the commanded thrusts."""
    rest = model.vehicle.gear_depth_m
    if plant is None:
        start = trajectory.sample(0.0).position_ned_m - offset
        plant = RigidBodyPlant(model, [start[0], start[1], -rest])
    rng = None if noise_seed is None else np.random.default_rng(noise_seed)
    ratio = int(round(PHYSICS_HZ / control_hz))
    times, errors, tilts, commands = [], [], [], []
    for k in range(int(duration_s * control_hz)):
        t = k / control_hz
        ref = trajectory.sample(t)
        out = controller.update(t, plant.state(rng), ref)
        plant.set_thrusts(out.rotor_thrusts_n)
        commands.append(out.rotor_thrusts_n)
        for _ in range(ratio):
            plant.step(1.0 / PHYSICS_HZ)
        q = plant.x[6:10]
        tracked = plant.x[0:3] + quat_to_rotmat(q) @ offset
        times.append(plant.t_s)
        errors.append(np.linalg.norm(tracked - trajectory.sample(plant.t_s).position_ned_m))
        tilts.append(tilt_deg(q))
    return np.array(times), np.array(errors), np.array(tilts), np.array(commands)


def make(layout, preset="mars-ftcc", ftc="none", control_hz=100.0, tracked_unit=1):
    model = AssemblyModel.from_layout(layout, preset)
    v = model.vehicle
    alloc = make_allocator(ftc, model, min_thrust_n=v.rotor_min_thrust_n, max_thrust_n=v.rotor_max_thrust_n)
    offset = np.zeros(3) if tracked_unit is None else model.unit_position(tracked_unit).copy()
    return model, CascadedController(model, alloc, offset, control_hz=control_hz), offset


# ----------------------------------------------------------------------------- gains
def test_gains_scale_with_control_rate_and_physical_gains_with_mass_and_inertia() -> None:
    small = AssemblyModel.from_layout(["X"])
    big = AssemblyModel.from_layout(["XXX", "XXX"])
    g100, g20 = CascadedGains.for_model(small, 100.0), CascadedGains.for_model(small, 20.0)
    assert g20.attitude_wn_radps < g100.attitude_wn_radps and g20.position_wn_radps < g100.position_wn_radps
    assert g20.attitude_wn_radps <= 20.0 / 5.0 + 1e-12
    lagged = CascadedGains.for_model(AssemblyModel.from_layout(["X"], small.vehicle.with_options(motor_time_constant_s=0.1)), 100.0)
    assert lagged.attitude_wn_radps <= 2.5 + 1e-12
    # the same small attitude error asks the 3x2 for a moment in proportion to its inertia
    level = RigidBodyState(0.0, np.array([0, 0, -1.0]), np.zeros(3), euler_to_quat(0.05, 0.0, 0.0), np.zeros(3))
    ref = build_trajectory("hover", {}, 0.05).sample(10.0)
    ref.position_ned_m = np.array([0, 0, -1.0])
    moments = []
    for model in (small, big):
        ctrl = CascadedController(model, make_allocator("none", model), control_hz=100.0)
        moments.append(ctrl.update(0.0, level, ref).wrench_demand[1])
    assert moments[0] < 0 and moments[1] < 0  # rolls back
    ratio = moments[1] / moments[0]
    assert ratio == pytest.approx(big.inertia_kgm2[0, 0] / small.inertia_kgm2[0, 0], rel=0.02)


def test_bad_construction_is_one_line_user_error() -> None:
    model = AssemblyModel.from_layout(["XX"])
    with pytest.raises(UserInputError, match="tracked_offset_frd_m"):
        CascadedController(model, make_allocator("none", model), np.zeros(2))
    with pytest.raises(UserInputError, match="control_hz"):
        CascadedController(model, make_allocator("none", model), control_hz=0.0)


# ----------------------------------------------------------------------------- flights on the RK4 plant
@pytest.mark.parametrize("name", list(LAYOUTS))
def test_takes_off_from_the_ground_and_hovers(name: str) -> None:
    model, ctrl, offset = make(LAYOUTS[name])
    traj = build_trajectory("hover", {"height_m": 1.0, "climb_s": 2.0, "duration_s": 6.0}, model.vehicle.gear_depth_m)
    t, err, tilt, _ = fly(model, ctrl, traj, 6.0, offset)
    assert err[-1] < 0.005, err[-1]  # unit 1 holds its point, not just the CoM
    assert err[t < 3.0].max() < 0.05  # tracks during the climb
    assert tilt.max() < 3.0


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_follows_a_short_helix_from_the_ground_with_noisy_state(name: str) -> None:
    model, ctrl, offset = make(LAYOUTS[name])
    traj = build_trajectory("helix", {"turns": 0.75, "climb_s": 2.0, "ramp_s": 2.0, "hold_s": 0.5},
                            model.vehicle.gear_depth_m)
    t, err, tilt, _ = fly(model, ctrl, traj, traj.duration_s, offset, noise_seed=1)
    assert np.mean(err) < 0.03, np.mean(err)
    assert err.max() < 0.08
    assert tilt.max() < 10.0


def test_spiral_feed_forward_of_the_off_centre_tracked_point_at_the_paper_rate() -> None:
    """Unit 1 of a 3x2 on the paper's spiral at 20 Hz (its first 12 s)."""
    model, ctrl, offset = make(LAYOUTS["3x2"], control_hz=20.0)
    traj = build_trajectory("mars-ftcc-spiral", {}, model.vehicle.gear_depth_m)
    t, err, _, _ = fly(model, ctrl, traj, 12.0, offset, control_hz=20.0, noise_seed=2)
    assert np.mean(err[t > 4.0]) < 0.05, np.mean(err[t > 4.0])


class Hold(Trajectory):
    def __init__(self, position_ned_m) -> None:
        self.point = TrajectoryPoint(np.asarray(position_ned_m, float))
        self.duration_s = math.inf

    def sample(self, t_s: float) -> TrajectoryPoint:
        return self.point


@pytest.mark.parametrize("name", ["1x1", "L-4"])
def test_attitude_converges_from_an_off_nominal_tilt(name: str) -> None:
    model, ctrl, offset = make(LAYOUTS[name], tracked_unit=None)
    hold = np.array([0.0, 0.0, -2.0])
    plant = RigidBodyPlant(model, hold, euler_to_quat(math.radians(25.0), math.radians(-20.0), 0.4))
    t, err, tilt, _ = fly(model, ctrl, Hold(hold), 5.0, offset, plant=plant)
    assert tilt[0] > 25.0
    assert tilt[t > 0.5].max() < 15.0  # within half a second only what the position loop asks for...
    assert tilt[t > 3.0].max() < 0.5  # ...and the position loop has levelled it again
    roll, pitch, yaw = quat_to_euler(plant.x[6:10])
    assert abs(yaw) < 0.02  # the yaw goes back to the reference
    assert err[-1] < 0.05  # and it is back over its point after drifting away


def test_yaw_reference_turns_the_assembly_about_the_tracked_unit() -> None:
    model, ctrl, offset = make(LAYOUTS["L-4"])
    traj = build_trajectory("hover", {"height_m": 1.0, "climb_s": 2.0, "duration_s": 8.0, "yaw_deg": 90.0},
                            model.vehicle.gear_depth_m)
    # start landed already turned, so the take-off is straight up under unit 1's reference
    start = traj.sample(0.0).position_ned_m - quat_to_rotmat(euler_to_quat(0, 0, math.pi / 2)) @ offset
    plant = RigidBodyPlant(model, [start[0], start[1], -0.05], euler_to_quat(0.0, 0.0, math.pi / 2))
    t, err, _, _ = fly(model, ctrl, traj, 6.0, offset, plant=plant)
    assert quat_to_euler(plant.x[6:10])[2] == pytest.approx(math.pi / 2, abs=0.01)
    assert err[-1] < 0.01


def test_respects_rotor_thrust_bounds_of_the_limited_preset() -> None:
    model, ctrl, offset = make(LAYOUTS["plus-5"], preset="modquad-cf2")
    v = model.vehicle
    traj = build_trajectory("helix", {"radius_m": 0.5, "turns": 0.5, "climb_s": 1.5, "ramp_s": 1.5, "hold_s": 0.5},
                            v.gear_depth_m)
    t, err, tilt, cmd = fly(model, ctrl, traj, traj.duration_s, offset, noise_seed=4)
    assert cmd.min() >= v.rotor_min_thrust_n - 1e-12 and cmd.max() <= v.rotor_max_thrust_n + 1e-12
    assert np.mean(err) < 0.03 and tilt.max() < 10.0


def test_set_faults_reaches_the_allocator_and_a_dead_unit_is_flown_around() -> None:
    model, ctrl, offset = make(LAYOUTS["3x2"], ftc="full")
    eta = model.nominal_eta()
    eta[model.unit_slots(2)] = 0.0
    ctrl.set_faults(eta)
    np.testing.assert_array_equal(ctrl.allocator.eta, eta)
    traj = build_trajectory("hover", {"height_m": 1.0, "climb_s": 2.0, "duration_s": 5.0}, model.vehicle.gear_depth_m)
    start = traj.sample(0.0).position_ned_m - offset
    plant = RigidBodyPlant(model, [start[0], start[1], -0.05], eta=eta)
    t, err, tilt, cmd = fly(model, ctrl, traj, 5.0, offset, plant=plant)
    assert np.abs(cmd[:, model.unit_slots(2)]).max() < 1e-9  # nothing asked of the dead unit
    assert err[-1] < 0.01 and tilt.max() < 3.0


def test_reset_clears_the_integral() -> None:
    model, ctrl, offset = make(LAYOUTS["1x1"])
    ref = build_trajectory("hover", {}, 0.05).sample(10.0)
    off = RigidBodyState(0.0, ref.position_ned_m + 0.3, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3))
    first = ctrl.update(0.0, off, ref).wrench_demand
    for k in range(50):
        ctrl.update(0.01 * k, off, ref)
    assert np.abs(ctrl.integral).max() > 0.1
    ctrl.reset()
    np.testing.assert_allclose(ctrl.update(0.0, off, ref).wrench_demand, first)


# ----------------------------------------------------------------------------- JSBSim runner (slow)
def _runner_scenario(layout, kind, preset="mars-ftcc", **sim):
    from mars_link.config.scenario import scenario_from_dict

    return scenario_from_dict({
        "name": "cascaded",
        "vehicle": {"preset": preset},
        "assembly": {"layout": layout, "tracked": "unit:1"},
        "trajectory": {"kind": kind},
        "control": {"controller": "cascaded", "ftc": "none"},
        "sim": {"noise": True, "seed": 7, **sim},
    })


@pytest.mark.slow
@pytest.mark.parametrize(
    "layout,kind,preset,sim",
    [
        (["X.", "X.", "XX"], "mars-ftcc-spiral", "mars-ftcc", {}),  # the other L-4 of the brief
        (["XXX", "XXX"], "mars-ftcc-spiral", "modquad-cf2", {}),  # rotor limits, T/W 2.5
        ([".X.", "XXX", ".X."], "helix", "modquad-cf2", {}),
        (["XXX", "XXX"], "mars-ftcc-spiral", "mars-ftcc", {"physics_hz": 200, "control_hz": 20}),  # paper rates
    ],
)
def test_runner_flights_with_noise(layout, kind, preset, sim) -> None:
    pytest.importorskip("jsbsim")
    from mars_link.flight.runner import run_scenario

    summary = run_scenario(_runner_scenario(layout, kind, preset, **sim))
    assert summary["completed"] and not summary["diverged"]
    limit = 0.15 if sim.get("control_hz") == 20 else 0.10
    assert summary["mean_error_m"] < limit, summary["mean_error_m"]
