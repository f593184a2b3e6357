"""Single-piece moves (mars_link.reconfig.moves) on paper 001's plus-5: where paper 001's plans find nothing
better, moves can; with 6 faults nothing can leave the body and come back hovering."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))

from reconfig_detect_eval import detected_scenario  # noqa: E402
from reconfig_eval import paper_faults, scenario  # noqa: E402

from mars_link.allocation import hover_thrust_share  # noqa: E402
from mars_link.reconfig.execution import PieceShape, local_eta  # noqa: E402
from mars_link.reconfig.flight import run_reconfig_trial  # noqa: E402
from mars_link.reconfig.moves import HoverCosts, best_moves, docks, moves, splits  # noqa: E402
from mars_link.reconfig.placement import nominal_cells  # noqa: E402
from mars_link.scenario import eta_after  # noqa: E402

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
    runs = {which: run_reconfig_trial(detected_scenario(PLUS, 3, which == "R"), 1) for which in ("NR", "R")}
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
