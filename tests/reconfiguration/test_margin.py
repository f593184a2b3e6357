"""The controllability margin (MARS-Reconfig, arXiv 2503.09376) of a structure and of a plan's every stage,
the plans that report it beside paper 001's force objective, and the re-plan without lost units."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linprog

from mars_link.config.scenario import load_scenario
from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.reconfig.flyability import FlyabilityRule
from mars_link.reconfig.margin import _facets, controllability_margin, plan_figures, plan_stages
from mars_link.reconfig.placement import SnapWeights, health_from_eta
from mars_link.reconfig.plans import plan_event, plan_for_margin
from mars_link.reconfig.replan import replan_assembly
from mars_link.reconfig.sequencing import plan_reconfiguration


def _eta(model: AssemblyModel, faults) -> np.ndarray:
    eta = model.nominal_eta()
    for unit, rotor, value in faults:
        eta[model.rotor_slot(unit, rotor)] = value
    return eta


def _ray_reach(model: AssemblyModel, eta: np.ndarray, direction: np.ndarray) -> float:
    """How far the scaled wrench can go from hover along `direction` (an LP over the rotor thrusts): an
    independent check of the facet formula."""
    v = model.vehicle
    lo, hi = v.command_range_n
    b = model.effectiveness(eta) / np.array([1.0, v.pitch_m, v.pitch_m, v.yaw_moment_per_thrust_m])[:, None]
    hover = np.array([model.mass_kg * GRAVITY_MPS2, 0.0, 0.0, 0.0])
    n = model.n_rotors  # variables: thrusts, then the reach s; maximise s with B f = hover + s d
    res = linprog(np.r_[np.zeros(n), -1.0], A_eq=np.hstack([b, -direction[:, None]]), b_eq=hover,
                  bounds=[(lo, hi)] * n + [(0, None)], method="highs")
    return -res.fun if res.status == 0 else 0.0


@pytest.mark.parametrize("layout", [["X"], [".X.", "XXX", ".X."], ["XXX", "XXX"]])
def test_margin_is_the_distance_from_hover_to_the_edge_of_the_wrenches_the_rotors_can_make(layout) -> None:
    """Positive when healthy, smaller with a weaker rotor, smaller still with it dead; 0 for a lone unit
    that lost a rotor (it cannot hold its yaw and attitude together). Along the normal of the nearest
    facet the LP reaches exactly the margin; along any other direction at least the margin."""
    model = AssemblyModel.from_layout(layout, "mars-ftcc")
    healthy = controllability_margin(model)
    weak = controllability_margin(model, _eta(model, [(1, 2, 0.5)]))
    dead = controllability_margin(model, _eta(model, [(1, 2, 0.0)]))
    assert healthy > weak > dead >= 0.0
    assert (dead == 0.0) == (len(layout) == 1)
    eta = _eta(model, [(1, 2, 0.5)])
    normals, n_b, n_half, n_hover = _facets(model, True)
    nearest = normals[np.argmin((n_b + n_half) @ eta - n_hover)]
    assert _ray_reach(model, eta, nearest) == pytest.approx(weak, rel=1e-6)
    rng = np.random.default_rng(0)
    for d in rng.normal(size=(20, 4)):
        assert _ray_reach(model, eta, d / np.linalg.norm(d)) >= weak - 1e-6


def test_a_structure_that_cannot_hover_has_zero_margin() -> None:
    pair = AssemblyModel.from_layout(["XX"], "mars-ftcc")
    assert controllability_margin(pair, _eta(pair, [(1, r, 0.0) for r in (1, 2, 3, 4)])) == 0.0  # thrust off-centre
    assert controllability_margin(pair, _eta(pair, [(u, r, 0.0) for u in (1, 2) for r in (1, 3)])) == 0.0  # no yaw


def test_every_plan_reports_both_objectives_and_the_margin_objective_keeps_the_weakest_stage_stronger() -> None:
    """2x2 with a rotor out on unit 1: paper 001's placement splits it in two and docks it back (weakest
    stage: a half with the dead rotor), the margin objective keeps the structure (its worst stage is the
    structure itself, more than twice as strong); both plans report both numbers. (The same for 3x3 with
    rotors out on units 1, 6, 8: 3+3 layers and lone units, 2.75, against staying, 82.9.)"""
    model = AssemblyModel.from_layout(["XX", "XX"], "mars-ftcc")
    eta = _eta(model, [(1, 2, 0.0)])
    health = health_from_eta(model, eta)
    eta_of = {u: health[u - 1] for u in model.unit_ids}
    rule = FlyabilityRule(hover_thrust_limits_n=(None, None))
    force = plan_reconfiguration(model, health, SnapWeights(), rule=rule)
    margin = plan_for_margin(model, eta, SnapWeights(), rule=rule)
    f, m = plan_figures(force, model.vehicle, eta_of), plan_figures(margin, model.vehicle, eta_of)
    assert force.objective == "force" and margin.objective == "margin"
    assert f["force_objective"] >= m["force_objective"]  # paper 001's plan is best on its own objective
    assert m["worst_stage_margin"] > 2 * f["worst_stage_margin"] > 0.0
    half = AssemblyModel.from_layout(["XX"], "mars-ftcc")
    assert f["worst_stage_margin"] == pytest.approx(controllability_margin(half, _eta(half, [(1, 2, 0.0)])), abs=1e-5)
    assert force.disassembly_layers == 1 and margin.disassembly_layers == 0
    assert len(plan_stages(force)) > len(plan_stages(margin)) == 1
    ev = plan_event(3.0, margin, model.vehicle, eta_of)
    assert ev["type"] == "plan" and ev["chosen_by"] == "margin"
    assert {k: ev[k] for k in f} == m


def test_objective_switch_is_checked(tmp_path) -> None:
    path = tmp_path / "s.toml"
    path.write_text('name = "t"\n[assembly]\nlayout = ["XX"]\n[reconfig]\nenabled = true\nobjective = "speed"\n')
    with pytest.raises(UserInputError, match="objective must be one of force, margin"):
        load_scenario(str(path))
    path.write_text(path.read_text().replace('"speed"', '"margin"'))
    assert load_scenario(str(path)).reconfig["objective"] == "margin"


def test_replan_without_lost_units_places_the_units_left_on_the_target_cells() -> None:
    """Paper 001's placement with the lost units' cells to spare: the plus without its top keeps the T (the
    lost cell empty: nothing gained elsewhere); without its centre no four of its cells are connected
    but the T through the centre, and a lone unit takes the centre; a docked piece keeps its cells."""
    vehicle = AssemblyModel.from_layout(["X"], "mars-ftcc").vehicle
    plus = {1: (0, 1), 2: (1, 0), 3: (1, 1), 4: (1, 2), 5: (2, 1)}
    eta = {u: np.ones(4) for u in plus}
    top = replan_assembly(vehicle, plus, [[2, 3, 4], [5]], eta)
    assert top.feasible and _shape(top.target) == _shape({u: plus[u] for u in (2, 3, 4, 5)})
    assert top.assembly_layers == 1
    centre = replan_assembly(vehicle, plus, [[1], [2], [4], [5]], eta)
    assert centre.feasible and len(set(centre.target.values())) == 4 and (1, 1) in centre.target.values()
    faulty = {**eta, 3: np.array([1.0, 0.0, 1.0, 1.0])}
    by_force = replan_assembly(vehicle, plus, [[2], [3], [4], [5]], faulty)
    by_margin = replan_assembly(vehicle, plus, [[2], [3], [4], [5]], faulty, objective="margin")
    assert _neighbours(by_force.target, 3) == 3  # paper 001: the faulty unit in the T's centre, least lever
    assert _neighbours(by_margin.target, 3) == 1 and by_margin.objective == "margin"  # the margin: at a tip
    lone = replan_assembly(vehicle, plus, [[2, 3, 4], [1]], eta)  # unit 5 lost: only the lost cell is free
    assert _shape(lone.target) == _shape({u: plus[u] for u in (1, 2, 3, 4)})


def _neighbours(cells: dict, unit: int) -> int:
    r, c = cells[unit]
    return sum(abs(r - rr) + abs(c - cc) == 1 for rr, cc in cells.values())


def _shape(cells: dict) -> dict:
    """Cells from the structure's top-left corner (plans number them so)."""
    r0, c0 = min(r for r, _ in cells.values()), min(c for _, c in cells.values())
    return {u: (r - r0, c - c0) for u, (r, c) in cells.items()}
