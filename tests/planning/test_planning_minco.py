"""MINCO s = 3 (interpolation, C4 continuity, closed-form energy, exact adjoint gradients) and the
MINCO back end in the planning pipeline (walls map: collision-free, exact validation, back end "minco")."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mars_link.core.assembly import AssemblyModel
from mars_link.planning import backend as B
from mars_link.planning.attitude import OptimalYaw
from mars_link.planning.footprint import Footprint, footprint_clearance
from mars_link.planning.maps import ObstacleMap, SignedDistanceField
from mars_link.planning.minco import Minco, MincoSpline, basis
from mars_link.planning.pipeline import Planner, sample_trajectory



def random_problem(seed: int = 0, n: int = 6):
    rng = np.random.default_rng(seed)
    head = np.array([[0.0, 0.0, 0.1], [0.3, -0.2, 0.0], [0.0, 0.1, 0.0]])
    tail = np.array([[6.0, 2.0, 1.5], [0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    q = np.linspace(head[0], tail[0], n + 1)[1:-1] + rng.normal(scale=0.7, size=(n - 1, 3))
    return Minco(head, tail), q, rng.uniform(0.4, 2.5, n), rng


def test_spline_passes_the_waypoints_and_the_head_and_tail_states():
    m, q, T, _ = random_problem()
    sp = m.solve(q, T)
    knots = sp.knots_s
    assert np.allclose(sp.evaluate(knots[1:-1]), q, atol=1e-10)
    for order in range(3):
        assert np.allclose(sp.evaluate(np.array([0.0]), order)[0], m.head[order], atol=1e-10)
        assert np.allclose(sp.evaluate(np.array([knots[-1]]), order)[0], m.tail[order], atol=1e-9)


def test_continuous_to_snap_at_every_knot_and_crackle_jumps():
    m, q, T, _ = random_problem(1)
    sp = m.solve(q, T)
    c = sp.coeffs
    jumps = []
    for order in range(6):
        left = np.einsum("ij,ijd->id", basis(T[:-1], order), c[:-1])
        right = np.einsum("j,ijd->id", basis(np.zeros(1), order)[0], c[1:])
        jumps.append(np.abs(left - right).max() / max(1.0, np.abs(left).max()))
    assert max(jumps[:5]) < 1e-9  # C4
    assert jumps[5] > 1e-3  # s = 3: only jerk is minimised, crackle is free to jump


def test_closed_form_jerk_energy_matches_quadrature():
    m, q, T, _ = random_problem(2)
    sp = m.solve(q, T)
    w = np.array([1.0, 1.0, 3.0])
    energy, _, _ = m.jerk_energy(w)
    x, wq = np.polynomial.legendre.leggauss(4)  # exact for the degree-4 integrand on each piece
    total = 0.0
    for k0, dur in zip(sp.knots_s[:-1], T):
        t = k0 + dur * (x + 1) / 2
        total += dur / 2 * float(wq @ ((sp.evaluate(t, 3) * w) ** 2).sum(1))
    assert math.isclose(energy, total, rel_tol=1e-9)


def test_equals_the_minimum_jerk_qp_solved_directly():
    """Independent oracle: minimise the jerk energy over all piecewise quintics that pass the
    waypoints with continuous position, velocity and acceleration (a KKT system, dense); the optimum
    is MINCO's (whose C4 continuity is the optimality condition, not a constraint)."""
    m, q, T, _ = random_problem(3)
    sp = m.solve(q, T)
    n = len(T)
    H = np.zeros((6 * n, 6 * n))
    for i, t in enumerate(T):
        blk = np.array([[36 * t, 72 * t ** 2, 120 * t ** 3], [72 * t ** 2, 192 * t ** 3, 360 * t ** 4],
                        [120 * t ** 3, 360 * t ** 4, 720 * t ** 5]])
        H[6 * i + 3:6 * i + 6, 6 * i + 3:6 * i + 6] = blk
    rows, rhs = [], []

    def row(entries, value):
        r = np.zeros(6 * n)
        for piece, vec in entries:
            r[6 * piece:6 * piece + 6] += vec
        rows.append(r)
        rhs.append(value)

    zero = np.zeros(1)
    for o in range(3):
        row([(0, basis(zero, o)[0])], m.head[o])
        row([(n - 1, basis(T[-1:], o)[0])], m.tail[o])
    for i in range(n - 1):
        row([(i, basis(T[i:i + 1], 0)[0])], q[i])
        for o in range(3):
            row([(i, basis(T[i:i + 1], o)[0]), (i + 1, -basis(zero, o)[0])], np.zeros(3))
    A, b = np.array(rows), np.array(rhs)
    kkt = np.block([[2 * H, A.T], [A, np.zeros((len(A), len(A)))]])
    sol = np.linalg.solve(kkt, np.vstack([np.zeros((6 * n, 3)), b]))[:6 * n]
    assert np.allclose(sol.reshape(n, 6, 3), sp.coeffs, rtol=1e-7, atol=1e-8)


def cost_gradient_check(cost, x, rng, picks: int = 30, h: float = 1e-6) -> float:
    f0, g = cost(x)
    worst = 0.0
    for i in rng.choice(len(x), min(picks, len(x)), replace=False):
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        num = (cost(xp)[0] - cost(xm)[0]) / (2 * h)
        worst = max(worst, abs(num - g[i]) / max(1.0, abs(num)))
    return worst


def test_adjoint_gradient_matches_central_differences_in_waypoints_and_durations():
    m, q, T, rng = random_problem(4)
    W = rng.normal(size=(6 * len(T), 3))

    def cost(x):  # energy + an arbitrary linear function of the coefficients
        qq, TT = x[:q.size].reshape(q.shape), x[q.size:]
        m.solve(qq, TT)
        e, dc, dT = m.jerk_energy(np.array([1.0, 1.0, 0.5]))
        gq, gT = m.grad(dc + W, dT)
        return e + float((W * m.c).sum()), np.concatenate([gq.ravel(), gT])

    x = np.concatenate([q.ravel(), T])
    assert cost_gradient_check(cost, x, rng, picks=len(x)) < 1e-6


def gap_map(gap_m: float = 1.2) -> ObstacleMap:
    half = 3.0
    boxes = [[5.0, -gap_m / 2 - half, half, 0.1, math.pi / 2], [5.0, gap_m / 2 + half, half, 0.1, math.pi / 2]]
    m = ObstacleMap(boxes=np.array(boxes))
    m.bounds = (-1.0, 11.0, -4.0, 4.0)
    return m


def test_back_end_cost_gradient_with_obstacle_limits_and_attitude_terms_active():
    model = AssemblyModel.from_layout("XXX,XXX")
    eta = model.nominal_eta()
    eta[model.unit_slots(2)] = 0.0
    fp = Footprint.from_model(model, 0.2)
    sdf = SignedDistanceField(gap_map(), 0.05)
    wp = np.column_stack([np.linspace(0, 10, 9), 0.4 * np.sin(np.linspace(0, 3, 9)), np.linspace(0, 1.0, 9)])
    p = B.BackendParams(margin_m=0.2, v_max_mps=0.3, a_max_mps2=0.05, j_max_mps3=0.05, yaw_rate_max_radps=0.02,
                        w_room=2.0, w_accel_effort=3.0)
    cost = B._Cost(wp[0], wp[-1], len(wp) - 1, sdf, B.thin_body_points(fp.body_points(), 0.1), OptimalYaw(model, eta), p)
    q0, T0 = B.initial_guess(wp, cost.r_body, p)
    rng = np.random.default_rng(5)
    x = np.concatenate([q0.ravel() + rng.normal(scale=0.05, size=q0.size), np.log(T0) - 0.6])
    cost(x)
    for term in ("obstacle", "velocity", "acceleration", "jerk", "yaw_rate", "attitude", "yaw_motion", "accel_effort"):
        assert cost.terms[term] > 0, term  # every term takes part in the check
    assert cost_gradient_check(cost, x, rng, picks=40) < 1e-5


def test_back_end_rejects_a_single_pose():
    with pytest.raises(ValueError, match="at least a start and a goal"):
        B.optimize_trajectory(np.zeros((1, 3)), None, np.zeros((1, 2)))


@pytest.fixture(scope="module")
def walls_3x2():
    """3x2 with unit 2 failed on the paper's walls: the planner and both methods' plans."""
    from mars_link.apps.planning_eval import WALLS_GOAL, WALLS_START, walls_map
    from mars_link.planning.pipeline import PlanParams

    model = AssemblyModel.from_layout("XXX,XXX")
    eta = model.nominal_eta()
    eta[model.unit_slots(2)] = 0.0
    planner = Planner(walls_map(), model, eta, PlanParams(margin_m=0.3))
    start, goal = np.array([*WALLS_START[:2], 0.0]), np.array(WALLS_GOAL[:2])
    return planner, start, goal, {m: planner.plan(start, goal, m, -2.3) for m in ("ours", "svsdf")}


@pytest.mark.parametrize("method", ["ours", "svsdf"])
def test_walls_plan_is_a_collision_free_minco_trajectory(walls_3x2, method):
    planner, start, goal, plans = walls_3x2
    res = plans[method]
    assert res.success and res.backend == "minco", (res.message, res.backend_errors)
    assert res.summary()["back_end"] == "minco" and res.backend_iterations > 0
    traj = res.trajectory
    assert isinstance(traj, MincoSpline)
    # at rest on the A* start and the goal
    assert np.allclose(traj.evaluate(np.array([0.0]))[0, :2], start[:2], atol=1e-9)
    assert np.allclose(traj.evaluate(np.array([traj.duration_s]))[0, :2], goal, atol=1e-9)
    for order in (1, 2):
        assert np.abs(traj.evaluate(np.array([0.0, traj.duration_s]), order)).max() < 1e-9
    # independent dense check, exact geometry: at most ~1 cm of footprint travel between samples
    s = sample_trajectory(traj, 0.01)
    assert footprint_clearance(planner.footprint, planner.obstacles, s[:, 1:4]).min() > 0.0
    speed = np.hypot(*traj.evaluate(s[:, 0], 1)[:, :2].T)
    assert speed.max() < 1.15 * planner.p.v_max_mps  # soft limit: a small overshoot at most


def test_ours_turns_less_than_svsdf_on_the_walls(walls_3x2):
    plans = walls_3x2[3]
    assert plans["ours"].total_yaw_rad < 0.5 * plans["svsdf"].total_yaw_rad
    assert plans["ours"].max_yaw_rate_radps < plans["svsdf"].max_yaw_rate_radps


def test_plan_command_reports_the_minco_back_end(tmp_path):
    from mars_link.apps.cli import main

    walls = tmp_path / "walls.csv"
    walls.write_text("cx,cy,length_m,thickness_m,height_m,yaw_deg\n-3.8,5,6,0.15,2.4,90\n3.8,5,6,0.15,2.4,90\n")
    out = tmp_path / "out"
    code = main(["plan", str(walls), "--layout", "XXX,XXX", "--fault", "2=0", "--start", "0,0,-2", "--goal", "10,0,-2",
                 "--out", str(out), "--quiet"])
    assert code == 0
    summary = json.loads((out / "plan.json").read_text())
    assert summary["success"] and summary["back_end"] == "minco"


def test_pipeline_retry_stiffens_only_the_obstacle_weight():
    """The pipeline's retry multiplies every field named like "obst": that must be w_obstacle alone."""
    import dataclasses

    from mars_link.planning.pipeline import _stiffer

    p = B.BackendParams()
    q = _stiffer(p)
    assert q.w_obstacle == 10 * p.w_obstacle
    assert {f.name for f in dataclasses.fields(p) if getattr(p, f.name) != getattr(q, f.name)} == {"w_obstacle"}
