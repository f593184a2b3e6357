"""The target re-planned when units are lost during an assembly or a manoeuvre: paper 001's placement on
the target's layout with the lost units' cells to spare.

The units left must fill as many of the target's cells; which cells stay empty is chosen here. The pieces
already docked keep their cells (they are rigid); every lone unit may take any free cell. Each choice of
empty cells whose structure the pieces there are can still build (Algorithm 3, `plan_assembly_of_pieces`:
connected, straight-line docks) is scored by the objective: "force", paper 001's sum of c_ij (health times
lever arm, weighted by the mission's snap) over the new structure, or "margin", the worst-stage
controllability margin of the docking sequence (`margin.worst_stage_margin`). Ties: the fewest lone units
moved from their cells (the lost units' cells stay empty when nothing is gained).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy.optimize import linear_sum_assignment

from mars_link.core.assembly import AssemblyModel, VehicleParams, layout_of_cells
from mars_link.core.errors import UserInputError
from mars_link.reconfig.flyability import Cell
from mars_link.reconfig.margin import worst_stage_margin
from mars_link.reconfig.placement import SnapWeights, placement_costs
from mars_link.reconfig.sequencing import ReconfigPlan, plan_assembly_of_pieces

#: at most this many choices of the cells left empty are weighed (more: only the lost units' cells)
REPLAN_CHOICES = 200


def replan_assembly(vehicle: VehicleParams, target: dict[int, Cell], pieces: list[list[int]],
                    eta_of: dict[int, np.ndarray], weights: SnapWeights = SnapWeights(),
                    objective: str = "force") -> ReconfigPlan:
    """The docking plan of `pieces` (unit ids; every unit in them is kept) into the best structure on the
    cells of `target` (unit -> cell, the units lost included): not feasible when no choice builds one."""
    keep = sorted(u for p in pieces for u in p)
    fixed = {u: target[u] for p in pieces if len(p) > 1 for u in p}
    lone = [u for u in keep if u not in fixed]
    open_cells = sorted(set(target.values()) - set(fixed.values()))
    lost_cells = {target[u] for u in target if u not in keep}
    empty_count = len(open_cells) - len(lone)
    if math.comb(len(open_cells), empty_count) > REPLAN_CHOICES:  # (a large structure: only the lost cells)
        ranked = [tuple(c for c in open_cells if c in lost_cells)] if len(lost_cells) == empty_count else []
    else:
        ranked = sorted(itertools.combinations(open_cells, empty_count), key=lambda e: -len(lost_cells & set(e)))
    best, best_key = None, None
    for empty in ranked:
        free = [c for c in open_cells if c not in empty]
        try:
            cells = {**fixed, **_place_lone(vehicle, fixed, lone, free, target, eta_of, weights)}
        except UserInputError:  # (these cells are not one connected structure)
            continue
        plan = plan_assembly_of_pieces(vehicle, cells, pieces)
        if not plan.feasible:
            continue
        moved = sum(abs(cells[u][0] - target[u][0]) + abs(cells[u][1] - target[u][1]) for u in lone)
        force = _force_objective(vehicle, cells, eta_of, weights)
        score = worst_stage_margin(plan, vehicle, eta_of) if objective == "margin" else force
        key = (round(score, 9), -moved)
        if best_key is None or key > best_key:
            plan.placement.objective = force
            best, best_key = plan, key
    if best is None:
        return plan_assembly_of_pieces(vehicle, {u: target[u] for u in keep}, pieces)
    best.objective = objective
    return best


def _model_of(vehicle: VehicleParams, cells) -> tuple[AssemblyModel, list[Cell]]:
    """The structure on `cells` and its cells in the model's (row-major) order."""
    model = AssemblyModel.from_layout(layout_of_cells(cells), vehicle)
    r0, c0 = min(r for r, _ in cells), min(c for _, c in cells)
    return model, sorted(cells, key=lambda c: (c[0] - r0, c[1] - c0))


def _place_lone(vehicle: VehicleParams, fixed: dict[int, Cell], lone: list[int], free: list[Cell],
                target: dict[int, Cell], eta_of: dict[int, np.ndarray], weights: SnapWeights) -> dict[int, Cell]:
    """Paper 001's assignment of the lone units to the free cells (largest sum of c_ij), ties to the
    fewest cells moved."""
    if not lone:
        return {}
    model, order = _model_of(vehicle, list(fixed.values()) + free)
    health = np.array([eta_of[u] for u in lone])  # (lone units, rotors)
    cost = placement_costs(model, health, weights)  # (positions of the model, lone units)
    rows = [order.index(c) for c in free]
    dist = np.array([[abs(c[0] - target[u][0]) + abs(c[1] - target[u][1]) for u in lone] for c in free])
    value = cost[rows, :] * 1e6 - dist  # (c_ij first; then stay close)
    r, c = linear_sum_assignment(value, maximize=True)
    return {lone[j]: free[i] for i, j in zip(r, c)}


def _force_objective(vehicle: VehicleParams, cells: dict[int, Cell], eta_of: dict[int, np.ndarray],
                     weights: SnapWeights) -> float:
    """Paper 001's objective of the structure `cells`: sum over units of c_ij in their cells."""
    model, order = _model_of(vehicle, list(cells.values()))
    units = list(cells)
    cost = placement_costs(model, np.array([eta_of[u] for u in units]), weights)
    return float(sum(cost[order.index(cells[u]), j] for j, u in enumerate(units)))
