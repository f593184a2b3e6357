"""Single-piece moves (mars_link.reconfig.moves) on paper 001's plus-5: where paper 001's plans find nothing
better, moves can; with 6 faults nothing can leave the body and come back hovering in the air, and the
structure rebuilds itself on the ground instead."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))

from reconfig_detect_eval import detected_scenario  # noqa: E402
from reconfig_eval import paper_faults, scenario  # noqa: E402

from mars_link.allocation import hover_thrust_share  # noqa: E402
from mars_link.reconfig.piece_shape import PieceShape, local_eta  # noqa: E402
from mars_link.flight.runner import run_trial  # noqa: E402
from mars_link.reconfig.moves import (  # noqa: E402
    HoverCosts, best_ground_moves, best_moves, docks, ground_plan, moves, slots, splits)
from mars_link.reconfig.placement import nominal_cells  # noqa: E402
from mars_link.config.scenario import eta_after, load_scenario  # noqa: E402

PLUS = [".X.", "XXX", ".X."]


def plus_case(n_faults: int):
    model = scenario(PLUS, paper_faults(n_faults), "qp").model()
    eta = eta_after(model, paper_faults(n_faults), math.inf)
    eta_of = {u: eta[model.unit_slots(u)] for u in model.unit_ids}
    return model, eta_of, HoverCosts(model.vehicle, eta_of)


def test_splits_and_docks_of_a_plus_follow_straight_lines():
    cells = {1: (0, 1), 2: (1, 0), 3: (1, 1), 4: (1, 2), 5: (2, 1)}
    pieces = {tuple(p) for p, _, _ in splits(cells)}
    # every tip alone, and its complement; never the centre alone (the rest would fall apart)
    assert {(1,), (2,), (4,), (5,), (2, 3, 4, 5), (1, 2, 3, 4)} <= pieces
    assert (3,) not in pieces
    rest = {u: c for u, c in cells.items() if u != 5}
    places = [m[5] for m, _ in docks({5: cells[5]}, rest)]
    assert (2, 1) in places and (-1, 1) in places  # back where it was, or beyond unit 1
    assert (3, 1) not in places  # no face in contact
    assert (0, 0) not in places  # the corner between units 1 and 2: no straight approach
    assert all(p not in rest.values() for p in places)


def test_plus5_three_and_four_faults_have_better_arrangements_reachable_by_moves():
    for n_faults, min_gain in ((3, 0.05), (4, 0.15)):
        model, eta_of, costs = plus_case(n_faults)
        found = best_moves(nominal_cells(model), costs, depth=2, max_piece_units=1)
        assert found.moves, n_faults
        assert found.best_sum_sq_n2 < (1.0 - min_gain) * found.start_sum_sq_n2
        # replay the moves: every piece, rest and result hovers within the limits (exact LP, checked anew)
        body = nominal_cells(model)
        for move in found.moves:
            piece = {u: body[u] for u in move.units}
            rest = {u: c for u, c in body.items() if u not in move.units}
            after = {**rest, **dict(zip(move.units, move.cells))}
            for part in (piece, rest, after):
                shape = PieceShape(part)
                share = hover_thrust_share(shape.model(model.vehicle), local_eta(shape, eta_of),
                                           model.vehicle.rotor_max_thrust_n)
                assert share <= 1.0, (move, part, share)
            body = after
        assert body == found.final


def test_plus5_six_faults_no_piece_can_move():
    model, eta_of, costs = plus_case(6)
    cells = nominal_cells(model)
    assert list(moves(cells, costs)) == []
    found = best_moves(cells, costs, depth=2)
    assert found.moves == [] and found.first_moves == 0
    assert np.isclose(found.best_sum_sq_n2, found.start_sum_sq_n2)


def test_plus5_three_faults_found_in_flight_the_coordinator_flies_one_move_and_saves_force():
    """Faults hit at 5 s, found by the detector (not told), noise on: paper 001's plan has nothing to fly,
    so the coordinator moves one healthy unit; the mission after it needs less force and tracks no worse."""
    runs = {which: run_trial(detected_scenario(PLUS, 3, which == "R"), 1) for which in ("NR", "R")}
    nr, r = runs["NR"], runs["R"]
    assert not nr.reconfigured and r.reconfigured
    assert not (nr.diverged or r.diverged) and r.completed
    plan = next(e for e in r.events if e["type"] == "plan")
    assert plan["disassembly_layers"] == 1 and plan["assembly_layers"] == 1 and "one move" in plan["reason"]
    split = next(e for e in r.events if e["type"] == "split")
    assert len(split["detached"]) == 1 and 1 not in split["detached"]  # a healthy unit moves, not the faulty one
    assert any(e["type"] == "dock" for e in r.events)
    assert r.mission_force_integral_n2s < 0.97 * nr.mission_force_integral_n2s
    assert r.rmse_m <= nr.rmse_m


def hover_share(cells: dict, model, eta_of) -> float:
    shape = PieceShape(cells)
    return hover_thrust_share(shape.model(model.vehicle), local_eta(shape, eta_of), model.vehicle.rotor_max_thrust_n)


def test_plus5_six_faults_a_rebuild_on_the_ground_saves_a_fifth_of_the_hover_force():
    """Landed, the body need not hover: healthy units lift off it and come down into better slots. Replayed:
    each lifted piece hovers alone, each slot touches the body and overlaps nothing, the result hovers."""
    model, eta_of, costs = plus_case(6)
    cells = nominal_cells(model)
    found = best_ground_moves(cells, costs)
    assert found.best_sum_sq_n2 < 0.8 * found.start_sum_sq_n2
    lifted = {u for units, _ in found.lifts for u in units}
    assert lifted and not lifted & {1, 2}  # the dead unit and the one with two dead rotors stay on the ground
    body = dict(cells)
    for units, _ in found.lifts:
        piece = {u: body.pop(u) for u in units}
        assert hover_share(piece, model, eta_of) <= 1.0
    assert hover_share(body, model, eta_of) > 1.0  # what rests on the ground could not hover
    for units, where in found.placements:
        piece = dict(zip(units, where))
        assert piece in [m for m in slots({u: cells[u] for u in units}, body)]
        body.update(piece)
    assert body == found.final
    assert hover_share(body, model, eta_of) <= 1.0
    plan = ground_plan(cells, found)
    assert plan.on_ground and plan.feasible and all(m.approach == "down" for m in plan.merges)
    assert [s.detached for s in plan.splits] == [sorted(units) for units, _ in found.lifts]


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_plus5_six_faults_found_in_flight_the_structure_lands_rebuilds_and_flies_on_better():
    """Faults hit at 5 s, found (not told), noise on: no move exists in the air, so the structure lands,
    units 1-3 (which cannot hover without the others) rest on the ground with their motors off while two
    healthy units move, and the rebuilt body takes off and resumes the mission with less force."""
    runs = {which: run_trial(detected_scenario(PLUS, 6, which == "R"), 1) for which in ("NR", "R")}
    nr, r = runs["NR"], runs["R"]
    assert not nr.reconfigured and r.reconfigured
    assert not (nr.diverged or r.diverged) and r.completed
    kinds = [e["type"] for e in r.events]
    assert kinds.count("split") == 2 and kinds.count("dock") == 2 and "landing" in kinds
    first_split = next(e["t_s"] for e in r.events if e["type"] == "split")
    last_dock = [e["t_s"] for e in r.events if e["type"] == "dock"][-1]
    rows = np.array(r.unit_rows, dtype=float)
    resting = rows[(rows[:, 0] >= first_split) & (rows[:, 0] <= last_dock) & np.isin(rows[:, 1], [1, 2, 3])]
    assert len(resting) and np.all(np.abs(resting[:, 4] + model_gear_depth()) < 0.005)  # on its feet throughout
    flew = rows[(rows[:, 0] > first_split) & (rows[:, 0] < last_dock) & np.isin(rows[:, 1], [4, 5])]
    assert flew[:, 4].min() < -0.25  # the movers left the ground
    assert r.min_clearance_m > -1e-3  # no two bodies overlap
    assert r.rmse_m <= nr.rmse_m
    assert r.mission_force_integral_n2s < 0.9 * nr.mission_force_integral_n2s


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_a_unit_lost_while_the_structure_rebuilds_on_the_ground_it_stays_landed():
    """reconfig_plus_ground, unit 4's firmware dies at 22 s (lifted, at its altitude level) while unit 5
    comes down to its slot: unit 5 still docks, unit 4 falls, and what rests stays on the ground with its
    motors off (units 1-3 cannot hover alone, and 1-3 + 5 is not the body the plan would take up)."""
    r = run_trial(load_scenario("reconfig_plus_ground"), 1, unit_deaths={4: 22.0})
    assert r.completed and not r.diverged
    kinds = [e["type"] for e in r.events]
    assert "reconfig_abandoned" in kinds and "mission_resumed" not in kinds
    assert kinds.index("unit_lost") < kinds.index("dock")  # unit 5's dock went on
    assert r.pieces_final == [{"layout": ["XX", "XX"], "units": [5, 1, 2, 3]}]
    rows = np.array(r.unit_rows, dtype=float)
    last = rows[(rows[:, 0] == rows[-1, 0]) & np.isin(rows[:, 1], [1, 2, 3, 5])]
    assert len(last) == 4 and np.all(np.abs(last[:, 4] + model_gear_depth()) < 0.005)  # landed


def model_gear_depth() -> float:
    return plus_case(0)[0].vehicle.gear_depth_m
