"""FTC allocation modes: eq. 1 shares, wrench reproduction under faults, bounds, dead rotors, QP oracle."""

from __future__ import annotations

import numpy as np
import pytest

from mars_link.allocation import ALLOCATION_MODES, check_controllable, make_allocator
from mars_link.allocation.modes import RedistributedPseudoInverse, row_weights
from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.control.paper_tables import thrust_shares
from mars_link.core.errors import UserInputError

FTC_MODES = [m for m in ALLOCATION_MODES if m != "none"]

# specs/ftc.md §4.1: minimum-norm unit thrust shares the paper's code reproduces exactly
EQ1_ROWS = [
    (["XXX", "XXX"], {2}, [1.5, 0, 1.5, 1, 1, 1]),
    (["XXX", "XXX"], {3}, [1.2, 1.8, 0, 0.4, 1, 1.6]),
    (["XXX", "XXX"], {2, 5}, [1.5, 0, 1.5, 1.5, 0, 1.5]),
    (["XXX", "XXX"], {3, 4}, [1.5, 1.5, 0, 0, 1.5, 1.5]),
    (["XXXX"], {3}, [8 / 7, 9 / 7, 0, 11 / 7]),
    (["XXXX"], {4}, [1 / 3, 4 / 3, 7 / 3, 0]),
]


def eta_for(model, failed_units=(), rotors=()) -> np.ndarray:
    eta = model.nominal_eta()
    for u in failed_units:
        eta[model.unit_slots(u)] = 0.0
    for u, r, e in rotors:
        eta[model.rotor_slot(u, r)] = e
    return eta


def hover(model) -> np.ndarray:
    return np.array([model.mass_kg * GRAVITY_MPS2, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("layout,failed,shares", EQ1_ROWS)
def test_unit_mode_hover_shares_equal_the_published_eq1_rows(layout, failed, shares) -> None:
    model = AssemblyModel.from_layout(layout)
    t = make_allocator("unit", model, eta_for(model, failed)).allocate(hover(model))
    per_unit = t.reshape(-1, 4).sum(axis=1) / (model.mass_kg * GRAVITY_MPS2 / model.n_units)
    np.testing.assert_allclose(per_unit, shares, atol=1e-9)


FAULT_SETS = {
    "3x2 unit 2 dead": (["XXX", "XXX"], [2], []),
    "3x2 Table I row 4": (["XXX", "XXX"], [], [(2, 1, 0.5), (2, 2, 0.5)]),
    "3x2 two dead units": (["XXX", "XXX"], [2, 4], []),
    "3x2 rotor dead and degraded": (["XXX", "XXX"], [], [(1, 3, 0.0), (1, 1, 0.3), (6, 2, 0.6)]),
    "4x1 unit 3 dead, unit 1 two rotors degraded": (["XXXX"], [3], [(1, 1, 0.4), (1, 4, 0.7)]),
    "plus": ([".X.", "XXX", ".X."], [], [(3, 2, 0.4), (3, 4, 0.7)]),
    "L": (["X..", "XXX"], [4], [(1, 1, 0.5)]),
    "5x5": (["XXXXX"] * 5, [7, 13, 19], [(1, 1, 0.0), (25, 3, 0.2)]),
}


@pytest.mark.parametrize("mode", FTC_MODES)
@pytest.mark.parametrize("case", list(FAULT_SETS))
def test_produced_wrench_equals_a_feasible_demand_and_dead_rotors_get_zero(mode, case) -> None:
    layout, failed, rotors = FAULT_SETS[case]
    model = AssemblyModel.from_layout(layout)
    eta = eta_for(model, failed, rotors)
    b = model.effectiveness(eta)
    alloc = make_allocator(mode, model, eta)
    rng = np.random.default_rng(4)
    scale = np.array([model.mass_kg * GRAVITY_MPS2, 0.3, 0.3, 0.05]) * 0.2
    for _ in range(20):
        demand = hover(model) + rng.normal(size=4) * scale
        t = alloc.allocate(demand)
        assert np.all(t[eta == 0] == 0.0)
        if mode == "unit" and rotors:
            continue  # eq. 1 does not compensate degraded rotors (by definition)
        np.testing.assert_allclose(b @ t, demand, rtol=0, atol=2e-4 * scale[0] * 5)


def test_none_mode_ignores_faults_and_misses_the_demand() -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"])
    eta = eta_for(model, [2])
    t = make_allocator("none", model, eta).allocate(hover(model))
    assert abs(model.effectiveness(eta) @ t - hover(model)).max() > 1.0


@pytest.mark.parametrize("mode", FTC_MODES)
def test_bounds_are_respected(mode) -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"], "modquad-cf2")
    v = model.vehicle
    eta = eta_for(model, [], [(2, 1, 0.5)])
    alloc = make_allocator(mode, model, eta, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
    rng = np.random.default_rng(1)
    for _ in range(50):
        demand = hover(model) * [rng.uniform(0.5, 2.0), 1, 1, 1] + rng.normal(size=4) * [0, 0.01, 0.01, 0.001]
        t = alloc.allocate(demand)
        assert t.min() >= v.rotor_min_thrust_n - 1e-9 and t.max() <= v.rotor_max_thrust_n + 1e-9


def test_qp_matches_the_redistributed_oracle_when_saturating() -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"], "modquad-cf2")
    v = model.vehicle
    eta = eta_for(model, [3], [(1, 2, 0.4)])
    qp = make_allocator("qp", model, eta, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
    rpi = RedistributedPseudoInverse(model, eta, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
    b = model.effectiveness(eta)
    rng = np.random.default_rng(2)
    for _ in range(30):
        demand = hover(model) * [1.3, 1, 1, 1] + rng.normal(size=4) * [0.2, 0.004, 0.004, 0.0]
        tq, tr = qp.allocate(demand), rpi.allocate(demand)
        if np.abs(b @ tr - demand).max() < 1e-6:  # feasible: both must meet it
            np.testing.assert_allclose(b @ tq, demand, atol=2e-3)
    assert qp.fallbacks == 0


def test_uncontrollable_fault_sets_are_refused_before_flight() -> None:
    single = AssemblyModel.from_layout(["X"])
    with pytest.raises(UserInputError, match="uncontrollable"):  # two rotors cannot set four axes
        check_controllable(single, eta_for(single, [], [(1, 1, 0.0), (1, 2, 0.0)]))
    model = AssemblyModel.from_layout(["XX"])
    with pytest.raises(UserInputError, match="cannot hover"):  # CoM outside the live unit's rotors
        check_controllable(model, eta_for(model, [1]), (0.0, None))
    cf = AssemblyModel.from_layout(["XXX", "XXX"], "modquad-cf2")
    with pytest.raises(UserInputError, match="cannot hover"):
        check_controllable(cf, eta_for(cf, [1, 2, 3, 4]), (0.0, cf.vehicle.rotor_max_thrust_n))
    check_controllable(model, model.nominal_eta())


def test_unknown_mode_is_a_user_error() -> None:
    with pytest.raises(UserInputError, match="unknown ftc mode 'magic'"):
        make_allocator("magic", AssemblyModel.from_layout(["X"]))


@pytest.mark.parametrize(
    "layout,failed",
    [(["XXXXX"] * 5, {7, 13, 19}), (["X..", "XXX"], {4}), ([".X.", "XXX", ".X."], {1, 3}), (["XXX", "XXX"], {2, 4})],
)
def test_unit_mode_hover_is_the_eq1_closed_form_on_other_layouts(layout, failed) -> None:
    model = AssemblyModel.from_layout(layout)
    k_f, balanced = thrust_shares(model, frozenset(failed))
    assert balanced
    t = make_allocator("unit", model, eta_for(model, failed)).allocate(hover(model))
    per_unit = t.reshape(-1, 4).sum(axis=1) / (model.mass_kg * GRAVITY_MPS2 / model.n_units)
    np.testing.assert_allclose(per_unit, k_f, atol=1e-9)
    # each surviving unit's share is split evenly over its rotors at hover
    np.testing.assert_allclose(t.reshape(-1, 4), np.repeat(t.reshape(-1, 4).mean(axis=1, keepdims=True), 4, axis=1), atol=1e-9)


def test_unit_mode_serves_collinear_survivors_through_their_rotors() -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"])
    eta = eta_for(model, [1, 2, 3])  # the survivors are one row behind the CoM
    t = make_allocator("unit", model, eta).allocate(hover(model) + [0, 0.1, -0.2, 0.01])
    np.testing.assert_allclose(model.effectiveness(eta) @ t, hover(model) + [0, 0.1, -0.2, 0.01], atol=1e-6)


@pytest.mark.parametrize("mode", ["partial", "full", "hybrid", "qp"])
@pytest.mark.parametrize(
    "layout,eta_value",
    [(["X"], [1, 0.6, 1, 1]), (["XXX", "XXX"], [0.97, 1, 0.98, 1] * 6)],  # no fully healthy unit left
)
def test_rotor_modes_work_when_no_unit_is_healthy(mode, layout, eta_value) -> None:
    model = AssemblyModel.from_layout(layout)
    eta = np.array(eta_value, dtype=float)
    demand = hover(model) + [0.5, 0.02, -0.03, 0.001]
    t = make_allocator(mode, model, eta).allocate(demand)
    np.testing.assert_allclose(model.effectiveness(eta) @ t, demand, atol=1e-3)


def test_full_doubles_a_half_thrust_rotor_and_leaves_the_other_units_alone() -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"])
    eta = eta_for(model, [], [(2, 3, 0.5)])
    t = make_allocator("full", model, eta).allocate(hover(model))
    h = model.hover_thrust_per_rotor_n()
    expected = np.full(model.n_rotors, h)
    expected[model.rotor_slot(2, 3)] = 2 * h
    np.testing.assert_allclose(t, expected, rtol=1e-9)


def test_full_with_a_dead_rotor_keeps_the_unit_balanced_and_hands_only_yaw_on() -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"])
    eta = eta_for(model, [], [(5, 1, 0.0)])
    t = make_allocator("full", model, eta).allocate(hover(model))
    g = model.unit_slots(5)
    unit = model.effectiveness(eta)[:, g] @ t[g]
    share = model.effectiveness()[:, g] @ np.full(4, model.hover_thrust_per_rotor_n())
    np.testing.assert_allclose(unit[:3], share[:3], atol=1e-9)  # its own thrust, roll, pitch
    assert abs(unit[3]) > 1e-3  # three rotors cannot also cancel yaw: the neighbours do
    others = np.delete(t.reshape(-1, 4), 4, axis=0)
    assert np.ptp(others.sum(axis=1)) < 1e-9  # only a yaw differential, no change of unit thrust


def test_hybrid_falls_back_to_partial_for_a_unit_that_cannot_balance_itself() -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"])
    eta = eta_for(model, [], [(5, 1, 0.0), (2, 2, 0.5)])
    demand = hover(model) + [1.0, 0.05, 0.02, 0.003]
    hybrid = make_allocator("hybrid", model, eta).allocate(demand)
    partial = make_allocator("partial", model, eta).allocate(demand)
    full = make_allocator("full", model, eta).allocate(demand)
    g5, g2 = model.unit_slots(5), model.unit_slots(2)
    np.testing.assert_allclose(hybrid[g5], partial[g5], atol=1e-12)  # dead rotor: commands unchanged
    np.testing.assert_allclose(hybrid[g2], full[g2], atol=1e-12)  # degraded only: rebalanced itself


def test_hybrid_keeps_commands_of_a_unit_whose_rebalance_would_saturate() -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"], "modquad-cf2")
    v = model.vehicle
    eta = eta_for(model, [], [(2, 2, 0.2)])  # 5x the hover command would exceed the rotor limit
    args = (model, eta, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
    hybrid = make_allocator("hybrid", *args).allocate(hover(model))
    partial = make_allocator("partial", *args).allocate(hover(model))
    g = model.unit_slots(2)
    np.testing.assert_allclose(hybrid[g], partial[g], atol=1e-12)
    np.testing.assert_allclose(model.effectiveness(eta) @ hybrid, hover(model), atol=1e-6)


def test_qp_gives_up_thrust_before_roll_and_pitch_when_saturated() -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"], "modquad-cf2")
    v = model.vehicle
    eta = eta_for(model, [2])
    alloc = make_allocator("qp", model, eta, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
    demand = np.array([v.rotor_max_thrust_n * model.n_rotors, 0.002, -0.002, 0.0])  # beyond what 5 units lift
    produced = model.effectiveness(eta) @ alloc.allocate(demand)
    assert produced[0] < 0.8 * demand[0]  # 26 % of the thrust given up ...
    np.testing.assert_allclose(produced[1:3], demand[1:3], rtol=0.02)  # ... roll/pitch within 2 % (soft weights)


@pytest.mark.parametrize("lo,hi", [(1.2, 1.8), (1.5, 2.5)])  # mostly feasible; mostly infeasible
def test_qp_meets_the_weighted_demand_at_least_as_well_as_the_redistributed_oracle(lo, hi) -> None:
    model = AssemblyModel.from_layout(["XXXXX"] * 5, "modquad-cf2")
    v = model.vehicle
    eta = eta_for(model, [7, 8], [(1, 1, 0.0), (20, 3, 0.3)])
    args = (model, eta, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
    qp, rpi = make_allocator("qp", *args), RedistributedPseudoInverse(*args)
    b, w = model.effectiveness(eta), row_weights(model)
    hover_cost = w[0] * (model.mass_kg * GRAVITY_MPS2) ** 2  # = 1: the weighted cost of missing the whole weight
    rng = np.random.default_rng(5)
    for _ in range(30):
        demand = hover(model) * [rng.uniform(lo, hi), 1, 1, 1] + rng.normal(size=4) * [0, 0.02, 0.02, 0.001]
        tq, tr = qp.allocate(demand), rpi.allocate(demand)
        assert tq.min() >= v.rotor_min_thrust_n and tq.max() <= v.rotor_max_thrust_n and np.all(tq[eta == 0] == 0)
        err_qp = w @ (b @ tq - demand) ** 2
        err_rpi = w @ (b @ tr - demand) ** 2
        assert err_qp <= 1.01 * err_rpi + 1e-6 * hover_cost


@pytest.mark.parametrize("mode", ALLOCATION_MODES)
def test_set_eta_switches_the_fault_set_like_a_fresh_allocator(mode) -> None:
    model = AssemblyModel.from_layout(["X..", "XXX"])
    before, after = eta_for(model, [], [(1, 1, 0.5)]), eta_for(model, [3], [(2, 4, 0.0)])
    alloc = make_allocator(mode, model, before)
    demand = hover(model) + [0.3, 0.01, 0.02, 0.001]
    alloc.allocate(demand)
    alloc.set_eta(after)
    np.testing.assert_allclose(alloc.allocate(demand), make_allocator(mode, model, after).allocate(demand), atol=1e-5)


@pytest.mark.parametrize("mode", ALLOCATION_MODES)
def test_allocate_never_raises_even_for_nonsense(mode) -> None:
    model = AssemblyModel.from_layout(["XX"])
    for eta in (np.zeros(8), eta_for(model, [1])):
        alloc = make_allocator(mode, model, eta, 0.0, 5.0)
        for demand in (np.full(4, np.nan), np.array([1e9, 1e9, -1e9, 1e9]), hover(model)):
            t = alloc.allocate(demand)
            assert t.shape == (8,)
            if mode != "none":  # "none" ignores faults on purpose
                assert np.all(t[eta == 0] == 0.0) and np.all(np.isfinite(t))


def test_bad_efficiencies_and_bounds_are_user_errors() -> None:
    model = AssemblyModel.from_layout(["XX"])
    with pytest.raises(UserInputError, match="8 values in"):
        make_allocator("qp", model, np.ones(4))
    with pytest.raises(UserInputError, match="8 values in"):
        check_controllable(model, np.full(8, 1.5))
    with pytest.raises(UserInputError, match="reversed"):
        make_allocator("unit", model, None, 2.0, 1.0)


@pytest.mark.parametrize("mode", ["unit", "partial", "full", "hybrid"])
def test_folded_unbounded_gain_equals_the_staged_path(mode) -> None:
    model = AssemblyModel.from_layout([".X.", "XXX", ".X."])
    eta = eta_for(model, [2], [(3, 1, 0.0), (4, 2, 0.5), (5, 4, 0.8)])
    demand = hover(model) + [0.4, 0.03, -0.02, 0.002]
    folded = make_allocator(mode, model, eta).allocate(demand)
    staged = make_allocator(mode, model, eta, -1e9, 1e9).allocate(demand)
    np.testing.assert_allclose(folded, staged, atol=1e-9)
