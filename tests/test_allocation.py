"""FTC allocation modes: eq. 1 shares, wrench reproduction under faults, bounds, dead rotors, QP oracle."""

from __future__ import annotations

import numpy as np
import pytest

from mars_link.allocation import ALLOCATION_MODES, check_controllable, make_allocator
from mars_link.allocation.modes import RedistributedPseudoInverse
from mars_link.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.errors import UserInputError

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
