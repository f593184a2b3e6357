"""qp mode: its answer is the exact optimum of its own objective (not just a good wrench), hover
splits evenly, the answer moves continuously as a demand crosses into saturation, and a saturated
demand gives up yaw, not thrust, roll or pitch."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from mars_link.allocation import make_allocator
from mars_link.allocation.modes import row_weights
from mars_link.allocation.qp import VARIANCE_WEIGHT
from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel


def faulted(model: AssemblyModel) -> np.ndarray:
    """Unit 3 dead, two degraded rotors in the last unit."""
    eta = model.nominal_eta()
    eta[model.unit_slots(3)] = 0.0
    eta[[model.rotor_slot(model.n_units, 2), model.rotor_slot(model.n_units, 4)]] = (0.4, 0.7)
    return eta


def exact_optimum(model: AssemblyModel, eta: np.ndarray, bounds, demand: np.ndarray) -> np.ndarray:
    """The qp objective ||W^1/2 (B t - w)||^2 + lambda * sum (t - mean t)^2 (mean over all rotor
    slots, dead ones at 0) in its two stages, solved independently as bounded least-squares problems
    (BVLS): thrust, roll and pitch first (the yaw row left out), then the yaw row with the first
    stage's thrust, roll and pitch held (as rows weighted far above the rest)."""
    w = row_weights(model)
    n = model.n_rotors
    lam = VARIANCE_WEIGHT * w[3] * model.vehicle.yaw_moment_per_thrust_m ** 2 * n
    live = eta > 0.0
    b = model.effectiveness(eta)[:, live]
    k = b.shape[1]
    centring = np.eye(k) - np.ones((k, k)) / n  # symmetric PSD: its own square root up to eigh
    vals, vecs = np.linalg.eigh(centring)
    root = (vecs * np.sqrt(np.clip(vals, 0.0, None))).T
    lo = -np.inf if bounds[0] is None else bounds[0]
    hi = np.inf if bounds[1] is None else bounds[1]
    first = np.sqrt(w[:3])[:, None] * b[:3]
    a = np.vstack([first, np.sqrt(lam) * root])
    rhs = np.concatenate([np.sqrt(w[:3]) * demand[:3], np.zeros(k)])
    t1 = lsq_linear(a, rhs, bounds=(lo, hi), method="bvls", tol=1e-14).x
    held = 1e3 * first  # the first stage's rows, weighted 1e6 above themselves (BVLS: 1e5 lost the yaw's digits)
    a = np.vstack([np.sqrt(w[3]) * b[3], np.sqrt(lam) * root, held])
    rhs = np.concatenate([[np.sqrt(w[3]) * demand[3]], np.zeros(k), held @ t1])
    sol = lsq_linear(a, rhs, bounds=(lo, hi), method="bvls", tol=1e-14)
    t = np.zeros(n)
    t[live] = sol.x
    return t


@pytest.mark.parametrize("preset", ["mars-ftcc", "modquad-cf2"])
def test_fresh_qp_hovers_a_nominal_assembly_on_equal_rotor_thrusts(preset) -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"], preset)
    v = model.vehicle
    qp = make_allocator("qp", model, None, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
    t = qp.allocate(np.array([model.mass_kg * GRAVITY_MPS2, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(t, model.hover_thrust_per_rotor_n(), rtol=1e-6)
    assert qp.saturated == 0  # no bound active: answered in closed form


@pytest.mark.parametrize("fault", [False, True])
@pytest.mark.parametrize("size", [(3, 2), (4, 4)])
def test_qp_is_the_exact_optimum_of_its_objective_with_and_without_saturation(fault, size) -> None:
    cols, rows = size
    model = AssemblyModel.from_layout(["X" * cols] * rows, "modquad-cf2")
    v = model.vehicle
    bounds = (v.rotor_min_thrust_n, v.rotor_max_thrust_n)
    eta = faulted(model) if fault else model.nominal_eta()
    qp = make_allocator("qp", model, eta, *bounds)
    weight = model.mass_kg * GRAVITY_MPS2
    arm = 0.1 * cols * v.pitch_m  # moments that saturate some rotors on about half the calls
    scale = np.array([0.15 * weight, weight * arm, weight * arm, 0.15 * weight * v.yaw_moment_per_thrust_m])
    rng = np.random.default_rng(7)
    for _ in range(25):
        demand = np.array([weight, 0.0, 0.0, 0.0]) + rng.normal(size=4) * scale
        t = qp.allocate(demand)
        ref = exact_optimum(model, eta, bounds, demand)
        np.testing.assert_allclose(t, ref, rtol=0, atol=1e-4 * model.hover_thrust_per_rotor_n())
    assert qp.saturated > 5, "the demands should saturate some rotors"
    assert qp.solves == 0  # the active-set method settled every time: OSQP not needed


def test_qp_answer_does_not_jump_where_rotors_start_to_saturate() -> None:
    """Sweep a roll demand through the onset of saturation: the step in the answer where a rotor
    reaches its bound is no larger than the steps before it (the closed form below and a solver
    above the onset must agree there)."""
    model = AssemblyModel.from_layout(["XXX", "XXX"], "modquad-cf2")
    v = model.vehicle
    eta = faulted(model)
    qp = make_allocator("qp", model, eta, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
    weight = model.mass_kg * GRAVITY_MPS2
    rolls = np.linspace(-0.6, 0.6, 400) * weight * v.pitch_m
    out = np.array([qp.allocate(np.array([weight, r, 0.0, 0.0])) for r in rolls])
    at_bound = (out >= v.rotor_max_thrust_n - 1e-12) | ((out <= 1e-12) & (eta > 0))
    steps = np.abs(np.diff(out, axis=0)).max(axis=1)
    onset = np.flatnonzero(at_bound.any(axis=1)[1:] != at_bound.any(axis=1)[:-1])
    plain = ~at_bound.any(axis=1)[1:] & ~at_bound.any(axis=1)[:-1]
    assert len(onset) >= 1 and plain.sum() > 50
    assert steps[onset].max() < 3 * np.median(steps[plain])


def test_saturated_qp_keeps_thrust_roll_and_pitch_and_gives_yaw_only_what_remains() -> None:
    """The dead corner unit's yaw (issue 15): the 20 live rotors of the paper 3x2 cannot make the yaw the
    controller asks after the fault in wind. The bounds are the composition root's (the paper plant has
    none; qp gets the +-5.1 N every command is clipped to), the effectiveness the real one. Asked thrust,
    roll and pitch are met exactly and yaw is the most any answer meeting them can make (exact LP); the
    unbounded answer clipped to the same range (what flew before) keeps almost none of the thrust."""
    from scipy.optimize import linprog

    from mars_link.flight.build import allocator_bounds
    from mars_link.apps.reproduce import CASES, scenario_for

    case = next(c for c in CASES if c.name == "F3 units {3}")
    scenario = scenario_for(case, "cascaded", "qp", t_fault_s=10.0)
    model = scenario.model()
    lo, hi = allocator_bounds(scenario, model)
    assert (lo, hi) == pytest.approx((-5.0995, 5.0995), abs=1e-4)  # the wire's full scale: 0.52 kg x g
    eta = model.nominal_eta()
    eta[model.unit_slots(3)] = 0.0
    qp = make_allocator("qp", model, eta, lo, hi)
    clipped = make_allocator("qp", model, eta)  # before: unbounded, then the coordinator's clip
    b = model.effectiveness(eta)
    live = eta > 0.0
    weight = model.mass_kg * GRAVITY_MPS2
    for yaw in (-0.6, -1.25, -6.0):  # N·m; -1.25: what the controller asked 0.4 s after the fault
        demand = np.array([weight, 0.3, -0.2, yaw])
        t = qp.allocate(demand)
        best = linprog(b[3, live], A_eq=b[:3, live], b_eq=demand[:3], bounds=(lo, hi), method="highs")
        assert best.status == 0
        produced = b @ t
        assert t.min() >= lo - 1e-12 and t.max() <= hi + 1e-12 and np.all(t[~live] == 0.0)
        np.testing.assert_allclose(produced[:3], demand[:3], rtol=0, atol=1e-4)  # (the variance term: 1e-5 N)
        assert produced[3] == pytest.approx(max(yaw, best.fun), abs=1e-4)  # all the yaw there is
        if yaw <= -1.25:
            assert (b @ np.clip(clipped.allocate(demand), lo, hi))[0] < 0.05 * weight  # the old collective
    assert qp.saturated == 3 and qp.solves == 0
