"""Paper 000's per-unit controller (mars-ftcc-paper): tables, frame map, signs, closed loop.

The closed-loop checks fly a small test-only plant: one rigid body with the paper's plant
(specs/ftc.md §2: linear thrust, reaction torque ±0.002 N·m per command, no lag, no limits,
g = 9.81), RK4 at 200 Hz, controller at 20 Hz, a floor at the start height. Numbers to compare
with are the spec's (§7.2 Table I, §9 re-simulation).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mars_link.core.assembly import AssemblyModel
from mars_link.control.paper import (
    MIXER_ROWS,
    PaperController,
    rotor_baselines,
)
from mars_link.control.paper_tables import TABLES, formula_table, named_table, table_for, thrust_shares
from mars_link.core.errors import UserInputError
from mars_link.core.rotations import euler_to_quat, quat_multiply, quat_to_rotmat
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import TrajectoryPoint

G_SCENE = 9.81
#: scene <-> project map of ftc.md §1.3 (its own inverse)
M_MAP = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: ftc.md §1.2: scene propeller offsets and reaction-torque signs about scene +z
SCENE_PROP_XY = np.array([(1, 1), (-1, 1), (-1, -1), (1, -1)], dtype=float) * 0.0919
SCENE_PROP_SIGN = np.array([-1.0, 1.0, -1.0, 1.0])
#: ftc.md §3: P_nr rows (columns Tx, Ty, Tz)
SCENE_P_NR = np.array([(-1, 1, 1), (-1, -1, -1), (1, -1, 1), (1, 1, -1)], dtype=float)


def model_3x2() -> AssemblyModel:
    return AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")


def unit_eta(model: AssemblyModel, failed=(), rotor_eta: dict | None = None) -> np.ndarray:
    eta = model.nominal_eta()
    for u in failed:
        eta[model.unit_slots(u)] = 0.0
    for (u, r), value in (rotor_eta or {}).items():
        eta[model.rotor_slot(u, r)] = value
    return eta


def hover_state(q=(1.0, 0.0, 0.0, 0.0), pos=(0.0, 0.0, -2.0)) -> RigidBodyState:
    return RigidBodyState(0.0, np.array(pos, float), np.zeros(3), np.array(q, float), np.zeros(3))


# ----------------------------------------------------------------------------- §4.1 closed form
SECTION_41_ROWS = [
    (["XXX", "XXX"], (2,), (1.5, 0, 1.5, 1, 1, 1)),
    (["XXX", "XXX"], (3,), (1.2, 1.8, 0, 0.4, 1, 1.6)),
    (["XXX", "XXX"], (2, 5), (1.5, 0, 1.5, 1.5, 0, 1.5)),
    (["XXX", "XXX"], (3, 4), (1.5, 1.5, 0, 0, 1.5, 1.5)),
    (["XXXX"], (3,), (8 / 7, 9 / 7, 0, 11 / 7)),
    (["XXXX"], (4,), (1 / 3, 4 / 3, 7 / 3, 0)),
]


@pytest.mark.parametrize("layout,failed,repo_k_f", SECTION_41_ROWS)
def test_closed_form_reproduces_repo_thrust_shares(layout, failed, repo_k_f):
    model = AssemblyModel.from_layout(layout, "mars-ftcc")
    k_f, balanced = thrust_shares(model, frozenset(failed))
    assert balanced
    np.testing.assert_allclose(k_f, repo_k_f, atol=1e-12)
    np.testing.assert_allclose(table_for(model, frozenset(failed)).k_f, repo_k_f, atol=1e-12)


def test_fail_2_4_repo_values_are_feasible_but_not_minimum_norm():
    model = model_3x2()
    k_f, balanced = thrust_shares(model, frozenset({2, 4}))
    np.testing.assert_allclose(k_f, (2.1, 0, 0.9, 0, 1.8, 1.2), atol=1e-12)
    repo = np.array(TABLES["3x2-fail-2-4"].k_f)
    np.testing.assert_allclose(repo, (2, 0, 1, 0, 2, 1))
    xy = model.unit_positions_m[:, :2]
    for shares in (k_f, repo):  # both satisfy eq. (1b)-(1c)
        assert shares.sum() == pytest.approx(6.0)
        np.testing.assert_allclose(shares @ xy, 0.0, atol=1e-12)
    assert repo @ repo == pytest.approx(10.0) and k_f @ k_f == pytest.approx(9.9)  # min-norm wins


def test_degenerate_rows_fall_back_and_report_unbalanceable_sets():
    row = AssemblyModel.from_layout(["XXXX"], "mars-ftcc")  # collinear: roll-moment row is zero
    k_f, balanced = thrust_shares(row, frozenset())
    assert balanced and np.allclose(k_f, 1.0)
    model = model_3x2()
    k_f, balanced = thrust_shares(model, frozenset({1, 2, 3}))  # whole front row dead
    assert not balanced
    assert k_f.sum() == pytest.approx(6.0) and np.all(k_f[:3] == 0.0)


# ----------------------------------------------------------------------------- §1.3 frame map
def scene_3x2_unit_positions() -> np.ndarray:
    """Scene world positions of units 1..6 (ftc.md §1.1) relative to their centroid, z up."""
    raw = np.array([[0.0, 0.35], [0.35, 0.35], [0.70, 0.35], [0.0, 0.0], [0.35, 0.0], [0.70, 0.0]])
    rel = raw - raw.mean(axis=0)
    return np.column_stack([rel, np.zeros(6)])


def test_frame_map_keeps_ids_rotor_order_and_the_fail_2_balance():
    model = model_3x2()
    scene = scene_3x2_unit_positions()
    np.testing.assert_allclose(scene @ M_MAP.T, model.unit_positions_m, atol=1e-12)
    assert np.linalg.det(M_MAP) == pytest.approx(1.0)
    # propeller[0..3] -> rotors 1..4 with the yaw sign flipped by z_p = -z_s
    unit1 = model.unit_position(1)
    for j in range(4):
        mapped = M_MAP @ np.array([*SCENE_PROP_XY[j], 0.0])
        np.testing.assert_allclose(model.rotors[j].position_m - unit1, mapped, atol=1e-12)
        assert model.rotors[j].yaw_sign == -SCENE_PROP_SIGN[j]

    k_f = np.array(TABLES["3x2-fail-2"].k_f)
    weight_n = model.mass_kg * G_SCENE
    per_unit_n = k_f * weight_n / 6.0
    # scene frame: forces along +z_s at the unit centres, moments about the CoM
    f_scene = np.column_stack([np.zeros(6), np.zeros(6), per_unit_n])
    moment_scene = np.cross(scene, f_scene).sum(axis=0)
    assert f_scene[:, 2].sum() == pytest.approx(weight_n)
    np.testing.assert_allclose(moment_scene, 0.0, atol=1e-12)
    # project frame: the same shares through the assembly's own effectiveness matrix
    thrusts = np.repeat(per_unit_n / 4.0, 4)
    wrench = model.wrench_from_thrusts(thrusts, unit_eta(model, failed=(2,)))
    assert wrench[0] == pytest.approx(weight_n)
    np.testing.assert_allclose(wrench[1:], 0.0, atol=1e-12)
    # and the moment vector itself maps with the frame (a proper rotation keeps r x f)
    f_proj = f_scene @ M_MAP.T
    np.testing.assert_allclose(
        np.cross(scene @ M_MAP.T, f_proj).sum(axis=0), M_MAP @ moment_scene, atol=1e-12
    )


class SceneFrameController:
    """ftc.md §3 written literally in the scene frame (z up), for one fixed gain table."""

    def __init__(self, table_name: str, unit_pos_scene: np.ndarray, yaw_p: float = 0.1):
        t = TABLES[table_name]
        # the scene's own names: k_alpha = project pitch gain, k_beta = project roll gain
        self.k_f, self.k_alpha, self.k_beta = np.array(t.k_f), np.array(t.k_pitch), np.array(t.k_roll)
        self.k_rot = np.array(t.k_yaw)
        self.yaw_p = t.yaw_p if t.yaw_p is not None else yaw_p
        self.r = unit_pos_scene
        n = len(self.k_f)
        self.cumul, self.last_e = np.zeros(n), np.zeros(n)
        self.p_alpha = self.p_beta = self.psp1 = self.psp2 = self.prev_euler = 0.0

    def step(self, pos_s, vel_s, rot_s, target_pos_s, target_rot_s, omega_world_s) -> np.ndarray:
        base = pos_s + self.r @ rot_s.T
        e = target_pos_s[2] - base[:, 2]
        self.cumul += e
        v1 = vel_s + np.cross(omega_world_s, rot_s @ self.r[0])
        thrust = 5.45 + 2 * e + 0.05 * self.cumul + 0 * (e - self.last_e) - 2 * v1[2]
        self.last_e = e
        alpha_e, beta_e = rot_s[2, 1], rot_s[2, 0]
        sp = rot_s.T @ (target_pos_s - base[0])
        alpha = 0.25 * alpha_e + 2.1 * (alpha_e - self.p_alpha) + sp[1] * 0.005 + (sp[1] - self.psp2)
        beta = -0.25 * beta_e - 2.1 * (beta_e - self.p_beta) - sp[0] * 0.005 - (sp[0] - self.psp1)
        rel = target_rot_s.T @ rot_s
        gamma = math.atan2(-rel[0, 1], rel[0, 0])
        rot_corr = gamma * self.yaw_p + 2 * (gamma - self.prev_euler)
        self.p_alpha, self.p_beta, self.psp1, self.psp2, self.prev_euler = (
            alpha_e, beta_e, sp[0], sp[1], gamma
        )
        tx = np.clip(self.k_alpha * alpha, -1, 1)
        ty = np.clip(self.k_beta * beta, -1, 1)
        tz = np.clip(self.k_rot * rot_corr, -1, 1)
        corr = np.column_stack([tx, ty, tz])
        v = thrust[:, None] * (self.k_f[:, None] + corr @ SCENE_P_NR.T)
        v[self.k_f == 0] = 0.0
        return v.reshape(-1)


@pytest.mark.parametrize("table_name,failed", [("3x2", ()), ("3x2-fail-2", (2,)), ("3x2-fail-3", (3,))])
def test_project_controller_equals_the_literal_scene_controller(table_name, failed):
    model = model_3x2()
    ours = PaperController(model, ftc="unit", eta=unit_eta(model, failed), gain_table=table_name)
    scene = SceneFrameController(table_name, scene_3x2_unit_positions())
    rng = np.random.default_rng(7)
    for k in range(30):
        rpy = rng.normal(0.0, 0.15, 3)
        q = euler_to_quat(*rpy)
        pos = rng.normal(0.0, 0.5, 3) + np.array([0.0, 0.0, -1.0])
        vel, omega = rng.normal(0.0, 0.4, 3), rng.normal(0.0, 0.5, 3)
        ref = pos + rng.normal(0.0, 0.3, 3)
        yaw_ref = float(rng.normal(0.0, 0.2))
        state = RigidBodyState(k * 0.05, pos, vel, q, omega)
        out = ours.update(k * 0.05, state, TrajectoryPoint(ref, yaw_rad=yaw_ref))
        rot = quat_to_rotmat(q)
        target_rot_s = M_MAP @ quat_to_rotmat(euler_to_quat(0.0, 0.0, yaw_ref)) @ M_MAP
        v_scene = scene.step(
            M_MAP @ pos, M_MAP @ vel, M_MAP @ rot @ M_MAP, M_MAP @ ref, target_rot_s,
            M_MAP @ (rot @ omega),
        )
        np.testing.assert_allclose(out.rotor_thrusts_n, 0.23366 * v_scene, atol=1e-9, rtol=1e-9)
    assert ours.table.name == table_name


# ----------------------------------------------------------------------------- §3 signs
def test_mixer_rows_are_the_scene_rows_in_roll_pitch_yaw_order():
    np.testing.assert_array_equal(MIXER_ROWS, SCENE_P_NR[:, [1, 0, 2]])


@pytest.mark.parametrize(
    "rpy,axis,sign",
    [((0.1, 0, 0), 1, -1), ((-0.1, 0, 0), 1, +1), ((0, 0.1, 0), 2, -1), ((0, -0.1, 0), 2, +1),
     ((0, 0, 0.2), 3, -1), ((0, 0, -0.2), 3, +1)],
)
def test_tilting_the_body_gives_a_restoring_moment(rpy, axis, sign):
    model = model_3x2()
    ctrl = PaperController(model)
    q = euler_to_quat(*rpy)
    state = hover_state(q)
    ref_unit1 = state.position_ned_m + quat_to_rotmat(q) @ model.unit_position(1)
    out = ctrl.update(0.0, state, TrajectoryPoint(ref_unit1))
    assert np.sign(out.wrench_demand[axis]) == sign


def test_target_ahead_or_right_accelerates_towards_it():
    model = model_3x2()
    for offset, axis, sign in (((0.5, 0, 0), 2, -1), ((0, 0.5, 0), 1, +1)):
        ctrl = PaperController(model)
        state = hover_state()
        ref = state.position_ned_m + model.unit_position(1) + np.array(offset)
        out = ctrl.update(0.0, state, TrajectoryPoint(ref))
        # nose-down (M < 0) tilts thrust forward, right-wing-down (L > 0) tilts it right
        assert np.sign(out.wrench_demand[axis]) == sign


def test_per_unit_altitude_loops_resist_a_tilt():
    model = model_3x2()
    ctrl = PaperController(model, gain_table="3x2")
    q = euler_to_quat(0.0, 0.1, 0.0)  # nose up: front row higher than the rear row
    state = hover_state(q)
    ref = state.position_ned_m + quat_to_rotmat(q) @ model.unit_position(1)
    ref[2] = state.position_ned_m[2]  # reference height = CoM height
    out = ctrl.update(0.0, state, TrajectoryPoint(ref))
    per_unit = out.rotor_thrusts_n.reshape(6, 4).sum(axis=1)
    assert per_unit[:3].max() < per_unit[3:].min()  # front units push less, rear more


# ----------------------------------------------------------------------------- FTC modes
def hover_wrench(model: AssemblyModel, ctrl: PaperController, eta: np.ndarray) -> np.ndarray:
    state = hover_state()
    out = ctrl.update(0.0, state, TrajectoryPoint(state.position_ned_m + model.unit_position(1)))
    return model.wrench_from_thrusts(out.rotor_thrusts_n, eta)


@pytest.mark.parametrize(
    "rotor_eta", [{(2, 2): 0.5}, {(2, 1): 0.5, (2, 2): 0.5}, {(2, 1): 0.0}, {(4, 3): 0.3, (2, 1): 0.7}]
)
def test_rotor_level_reallocation_restores_the_hover_wrench(rotor_eta):
    model = model_3x2()
    eta = unit_eta(model, rotor_eta=rotor_eta)
    nominal = hover_wrench(model, PaperController(model), model.nominal_eta())
    moments = {}
    for ftc in ("none", "partial", "full", "hybrid"):
        w = hover_wrench(model, PaperController(model, ftc=ftc, eta=eta), eta)
        moments[ftc] = w
    np.testing.assert_allclose(moments["partial"], nominal, atol=1e-9)
    np.testing.assert_allclose(moments["hybrid"], nominal, atol=1e-9)
    assert np.abs(moments["none"][:3] - nominal[:3]).max() > 0.05
    dead = any(v == 0.0 for v in rotor_eta.values())
    # full re-balances inside the unit: thrust and roll/pitch exact; yaw only with no dead rotor
    np.testing.assert_allclose(moments["full"][:3], nominal[:3], atol=1e-9)
    if dead:
        assert abs(moments["full"][3]) > 1e-3
    else:
        np.testing.assert_allclose(moments["full"][3], nominal[3], atol=1e-9)


def test_full_reallocation_with_half_thrust_doubles_that_rotor():
    model = model_3x2()
    eta = unit_eta(model, rotor_eta={(2, 2): 0.5})
    realloc = rotor_baselines(model, eta, np.ones(6), "full")
    np.testing.assert_allclose(realloc.baseline[1], (1, 2, 1, 1), atol=1e-12)
    np.testing.assert_allclose(np.delete(realloc.baseline, 1, axis=0), 1.0)


def test_unit_that_cannot_balance_itself_falls_back_to_partial_in_hybrid():
    model = model_3x2()
    eta = unit_eta(model, rotor_eta={(2, 1): 0.0, (2, 2): 0.0})  # both front rotors of unit 2
    full = rotor_baselines(model, eta, np.ones(6), "full")
    np.testing.assert_allclose(full.baseline, 1.0)  # keeps its commands
    nominal = hover_wrench(model, PaperController(model), model.nominal_eta())
    w = hover_wrench(model, PaperController(model, ftc="hybrid", eta=eta), eta)
    np.testing.assert_allclose(w, nominal, atol=1e-9)


def test_failed_units_are_switched_off_and_tables_follow_the_fault_set():
    model = model_3x2()
    eta = unit_eta(model, failed=(2,))
    none = PaperController(model, ftc="none", eta=eta)
    unit = PaperController(model, ftc="unit", eta=eta)
    assert none.table.name == "3x2" and unit.table.name == "3x2-fail-2"
    assert unit.yaw_p == 1.0 and none.yaw_p == 0.1
    for ctrl in (none, unit):
        out = ctrl.update(0.0, hover_state(), TrajectoryPoint(np.array([0.2, 0.1, -2.3])))
        assert np.all(out.rotor_thrusts_n[model.unit_slots(2)] == 0.0)
    w_unit = hover_wrench(model, PaperController(model, ftc="unit", eta=eta), eta)
    w_none = hover_wrench(model, PaperController(model, ftc="none", eta=eta), eta)
    np.testing.assert_allclose(w_unit[1:3], 0.0, atol=1e-9)  # eq. (1): moments balanced
    assert abs(w_none[2]) > 0.5  # the missing front-middle unit leaves a pitch moment
    # set_faults switches mid-flight; an unknown set on a tabled layout uses eq. (1) + formula
    unit.set_faults(unit_eta(model, failed=(1,)))
    assert unit.table.name == "formula"
    np.testing.assert_allclose(unit.table.k_f, thrust_shares(model, frozenset({1}))[0])


def test_formula_gains_normalise_to_the_single_unit_gain():
    model = model_3x2()
    table = formula_table(model, frozenset())
    j_unit = np.array(model.vehicle.unit_inertia_kgm2)
    j_asm = np.diag(model.inertia_kgm2)
    assert sum(table.k_roll) == pytest.approx(j_asm[0] / j_unit[0])
    assert sum(table.k_pitch) == pytest.approx(j_asm[1] / j_unit[1])
    assert sum(table.k_yaw) == pytest.approx(j_asm[2] / j_unit[2])
    # outer units (larger |y|) get the larger roll gain, as the published tables do
    assert table.k_roll[0] > table.k_roll[1]
    single = formula_table(AssemblyModel.from_layout(["X"], "mars-ftcc"), frozenset())
    assert single.k_roll == single.k_pitch == single.k_yaw == (1.0,)


@pytest.mark.parametrize(
    "kwargs,fragment",
    [
        ({"ftc": "qp"}, "ftc mode 'qp'"),
        ({"gain_table": "5x5"}, "unknown gain table"),
        ({"gain_table": "4x1"}, "is for a 4x1 assembly"),
        ({"tracked_unit_id": 9}, "unit 9 does not exist"),
        ({"control_hz": 0.0}, "control_hz"),
        ({"eta": np.ones(3)}, "eta must be 24"),
        ({"family": "race"}, "unknown scene family"),
    ],
)
def test_bad_input_is_one_clear_line(kwargs, fragment):
    with pytest.raises(UserInputError) as err:
        PaperController(model_3x2(), **kwargs)
    assert fragment in str(err.value) and "\n" not in str(err.value)


def test_other_plants_are_refused():
    with pytest.raises(UserInputError, match="tuned for the mars-ftcc plant"):
        PaperController(AssemblyModel.from_layout(["XX"], "modquad-cf2"))


def test_named_tables_have_one_entry_per_unit():
    for name, table in TABLES.items():
        model = AssemblyModel.from_layout(
            ["X" * int(table.layout_key.split("x")[0])] * int(table.layout_key.split("x")[1]),
            "mars-ftcc",
        )
        assert named_table(name, model).n_units == model.n_units
        for gains in (table.k_f, table.k_roll, table.k_pitch, table.k_yaw):
            assert len(gains) == model.n_units
            assert all(gains[u - 1] == 0.0 for u in table.failed_units)


# ----------------------------------------------------------------------------- closed loop
def spiral_point_ned(t_s: float, k: float = 0.5, period_t: float = 40.0) -> np.ndarray:
    """ftc.md §7.1 spiral in the scene frame, minus its start, mapped to NED (north = y_s)."""
    a = 1.0 - k * t_s / period_t
    scene = np.array([a * math.cos(k * t_s) - 1.0, a * math.sin(k * t_s), 0.1 * k * t_s])
    return M_MAP @ scene


SPIRAL_END_S = 4 * 2 * math.pi / 0.5


class PaperPlant:
    """Test-only rigid body with the paper's actuator law; RK4.

    Ground: a floor at the start height; while the thrust cannot lift the body it rests there
    without sliding or turning (the scenes' friction), so a too-weak assembly waits on the floor
    while the target leaves.
    """

    def __init__(self, model: AssemblyModel, eta: np.ndarray, com_ned_m: np.ndarray):
        self.model = model
        self.b_eta = model.effectiveness(eta)
        self.mass = model.mass_kg
        self.inertia = model.inertia_kgm2
        self.inertia_inv = np.linalg.inv(self.inertia)
        self.floor_d = com_ned_m[2]
        # state: position (3), velocity (3), quaternion wxyz (4), body rates (3)
        self.x = np.concatenate([com_ned_m, np.zeros(3), [1.0, 0, 0, 0], np.zeros(3)])
        self.wrench = np.zeros(4)

    def deriv(self, x: np.ndarray) -> np.ndarray:
        q, w = x[6:10], x[10:13]
        rot = quat_to_rotmat(q)
        acc = rot @ np.array([0.0, 0.0, -self.wrench[0]]) / self.mass + np.array([0, 0, G_SCENE])
        torque = self.wrench[1:]
        w_dot = self.inertia_inv @ (torque - np.cross(w, self.inertia @ w))
        q_dot = 0.5 * quat_multiply(q, np.array([0.0, *w]))
        return np.concatenate([x[3:6], acc, q_dot, w_dot])

    def step(self, thrusts_n: np.ndarray, dt_s: float) -> None:
        self.wrench = self.b_eta @ thrusts_n
        x = self.x
        lift_mps2 = (quat_to_rotmat(x[6:10]) @ np.array([0.0, 0.0, -self.wrench[0]]))[2] / self.mass
        if x[2] >= self.floor_d and lift_mps2 + G_SCENE >= 0.0:  # resting: friction holds it
            x[3:6] = 0.0
            x[10:13] = 0.0
            return
        k1 = self.deriv(x)
        k2 = self.deriv(x + 0.5 * dt_s * k1)
        k3 = self.deriv(x + 0.5 * dt_s * k2)
        k4 = self.deriv(x + dt_s * k3)
        x = x + dt_s / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        x[6:10] /= np.linalg.norm(x[6:10])
        if x[2] > self.floor_d:  # no sinking below the floor
            x[2] = self.floor_d
            x[5] = min(x[5], 0.0)
        self.x = x

    def state(self, t_s: float) -> RigidBodyState:
        x = self.x
        return RigidBodyState(t_s, x[0:3].copy(), x[3:6].copy(), x[6:10].copy(), x[10:13].copy())


def fly_spiral(
    ftc: str = "none",
    failed=(),
    rotor_eta: dict | None = None,
    layout=("XXX", "XXX"),
    physics_hz: float = 200.0,
    control_hz: float = 20.0,
    stop_error_m: float = 20.0,
    **ctrl_kwargs,
) -> float:
    """Mean 3-D error of unit 1 over the spiral (ftc.md §7.1 metric), sampled at control steps."""
    model = AssemblyModel.from_layout(list(layout), "mars-ftcc")
    eta = unit_eta(model, failed, rotor_eta)
    ctrl = PaperController(model, ftc=ftc, eta=eta, control_hz=control_hz, **ctrl_kwargs)
    com0 = spiral_point_ned(0.0) - model.unit_position(1)
    plant = PaperPlant(model, eta, com0)
    substeps = int(round(physics_hz / control_hz))
    dt = 1.0 / physics_hz
    errors = []
    k = 0
    while True:
        t = k / control_hz
        if t > SPIRAL_END_S:
            break
        state = plant.state(t)
        ref = spiral_point_ned(t)
        unit1 = state.position_ned_m + quat_to_rotmat(state.quaternion_wxyz) @ model.unit_position(1)
        errors.append(float(np.linalg.norm(ref - unit1)))
        if not errors[-1] < stop_error_m:  # diverged: count the rest of the run at this error
            errors += [stop_error_m] * int((SPIRAL_END_S - t) * control_hz)
            break
        out = ctrl.update(t, state, TrajectoryPoint(ref))
        for _ in range(substeps):
            plant.step(out.rotor_thrusts_n, dt)
        k += 1
    return float(np.mean(errors))


PAPER_NOMINAL_M = 0.2230


def test_nominal_spiral_lands_near_the_paper():
    err = fly_spiral()
    assert 0.7 * PAPER_NOMINAL_M <= err <= 1.3 * PAPER_NOMINAL_M, err


@pytest.mark.slow
@pytest.mark.parametrize("failed,spec_with_ftc", [((2,), 0.208), ((3,), 0.188), ((2, 4), 0.189),
                                                   ((2, 5), 0.205), ((3, 4), 0.178)])
def test_unit_failures_tracked_with_unit_ftc_and_much_worse_without(failed, spec_with_ftc):
    with_ftc = fly_spiral("unit", failed)
    without = fly_spiral("none", failed)
    assert with_ftc < 1.3 * PAPER_NOMINAL_M and abs(with_ftc - spec_with_ftc) < 0.3 * spec_with_ftc
    # symmetric sets keep the moments balanced without FTC but lack thrust: ~3x worse, not diverged
    assert without > 2.5 * with_ftc, (with_ftc, without)


@pytest.mark.slow
@pytest.mark.parametrize("rotor_eta", [{(2, 2): 0.5}, {(2, 1): 0.5, (2, 2): 0.5}])
def test_table_one_rotor_degradation(rotor_eta):
    without = fly_spiral("none", rotor_eta=rotor_eta)
    for ftc in ("partial", "full", "hybrid"):
        with_ftc = fly_spiral(ftc, rotor_eta=rotor_eta)
        assert with_ftc < 1.5 * PAPER_NOMINAL_M and without > 3.0 * with_ftc, (ftc, with_ftc, without)


@pytest.mark.slow
@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_formula_gains_and_other_rates_still_fly_the_spiral():
    # no published table: eq. (1) k_f + formula E_i, tracked unit itself failed
    assert fly_spiral("unit", (1,)) < 1.3 * PAPER_NOMINAL_M
    assert fly_spiral("none", (1,)) > 5 * PAPER_NOMINAL_M
    assert fly_spiral(gain_table="formula") < 1.3 * PAPER_NOMINAL_M
    assert fly_spiral(layout=(".X.", "XXX", ".X.")) < 1.3 * PAPER_NOMINAL_M
    # at 100 Hz the per-step terms are rescaled to the 50 ms step: same flight quality
    assert fly_spiral(physics_hz=500.0, control_hz=100.0) < 1.3 * PAPER_NOMINAL_M


@pytest.mark.slow
def test_dead_rotor_needs_the_residual_passed_on():
    # full leaves the dead rotor's yaw residual to the weak yaw loop; hybrid hands it over
    hybrid = fly_spiral("hybrid", rotor_eta={(2, 1): 0.0})
    assert hybrid < 1.3 * PAPER_NOMINAL_M
    assert fly_spiral("none", rotor_eta={(2, 1): 0.0}) > 10 * hybrid


@pytest.mark.slow
def test_runner_flies_the_paper_spiral_within_30_percent_of_the_paper():
    """Acceptance: mars-ftcc-paper on the 3x2 spiral through the in-process runner (JSBSim)."""
    try:
        from mars_link.flight.runner import run_trial
        from mars_link.config.scenario import Scenario, SimSpec
        import sitl.physics  # noqa: F401  (JSBSim body)
    except ImportError as err:  # the runner's pieces are written by other engineers
        pytest.skip(f"in-process runner not complete yet: {err}")
    scenario = Scenario(
        name="spiral_3x2_paper",
        controller="mars-ftcc-paper",
        ftc="none",
        sim=SimSpec(physics_hz=1000.0, control_hz=20.0, seed=1, noise=False),
    )
    result = run_trial(scenario, seed=1)
    assert result.completed
    assert 0.7 * PAPER_NOMINAL_M <= result.mean_error_m <= 1.3 * PAPER_NOMINAL_M, result.mean_error_m
