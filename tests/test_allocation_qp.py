"""qp mode: its answer is the exact optimum of its own objective (not just a good wrench), hover
splits evenly, and the answer moves continuously as a demand crosses into saturation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from mars_link.allocation import make_allocator
from mars_link.allocation.modes import row_weights
from mars_link.allocation.qp import VARIANCE_WEIGHT
from mars_link.assembly import GRAVITY_MPS2, AssemblyModel


def faulted(model: AssemblyModel) -> np.ndarray:
    """Unit 3 dead, two degraded rotors in the last unit."""
    eta = model.nominal_eta()
    eta[model.unit_slots(3)] = 0.0
    eta[[model.rotor_slot(model.n_units, 2), model.rotor_slot(model.n_units, 4)]] = (0.4, 0.7)
    return eta


def exact_optimum(model: AssemblyModel, eta: np.ndarray, bounds, demand: np.ndarray) -> np.ndarray:
    """The qp objective ||W^1/2 (B t - w)||^2 + lambda * sum (t - mean t)^2 (mean over all rotor
    slots, dead ones at 0), solved independently as a bounded least-squares problem (BVLS)."""
    w = row_weights(model)
    n = model.n_rotors
    lam = VARIANCE_WEIGHT * w[3] * model.vehicle.yaw_moment_per_thrust_m ** 2 * n
    live = eta > 0.0
    b = model.effectiveness(eta)[:, live]
    k = b.shape[1]
    centring = np.eye(k) - np.ones((k, k)) / n  # symmetric PSD: its own square root up to eigh
    vals, vecs = np.linalg.eigh(centring)
    root = (vecs * np.sqrt(np.clip(vals, 0.0, None))).T
    a = np.vstack([np.sqrt(w)[:, None] * b, np.sqrt(lam) * root])
    rhs = np.concatenate([np.sqrt(w) * demand, np.zeros(k)])
    lo = -np.inf if bounds[0] is None else bounds[0]
    hi = np.inf if bounds[1] is None else bounds[1]
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
