"""What a flight of pieces plans: the reconfiguration for its faults, a commanded separation, where free
units rest, and the checks made before flight. `mars_link.flight.build` puts the executor and the flight
together (`make_executor`, `build_flight`); `mars_link.flight.runner` flies it and `mars_link.flight.recorder` records it.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
from scipy.optimize import linear_sum_assignment

from mars_link.core.assembly import AssemblyModel
from mars_link.core.events import EventKind, event
from mars_link.core.errors import UserInputError
from mars_link.reconfig.execution import ExecutionParams
from mars_link.reconfig.piece_shape import PieceShape, local_eta
from mars_link.reconfig.flyability import FlyabilityRule
from mars_link.reconfig.placement import SnapWeights, health_from_eta, nominal_cells
from mars_link.reconfig.sequencing import ReconfigPlan, plan_reconfiguration
from mars_link.config.scenario import Scenario, eta_after


def execution_params(scenario: Scenario) -> ExecutionParams:
    keys = ExecutionParams.__dataclass_fields__
    return ExecutionParams(**{k: v for k, v in scenario.reconfig.items() if k in keys})


def check_reconfig_scenario(scenario: Scenario, faults_may_come: bool = False) -> None:
    """What this runner cannot fly, refused before flight (one line each). `faults_may_come`: a ground
    station may inject faults (the assembly vehicle), so [reconfig] without [[faults]] is meaningful."""
    src = scenario.source
    if scenario.controller != "cascaded":
        raise UserInputError(f"{src}: [reconfig] flights need [control] controller = \"cascaded\"")
    if scenario.separations and (scenario.starts_free or scenario.reconfig.get("enabled")):
        raise UserInputError(f"{src}: [[separations]] cannot be combined with [reconfig] or a free start yet")
    model = scenario.model()
    for i, sep in enumerate(scenario.separations, 1):
        try:
            plan = plan_separation(model, sep.units, sep.redock_t_s is not None)
        except UserInputError as exc:
            raise UserInputError(f"{src}: [[separations]] #{i}: {exc}") from None
        bad = unhoverable_pieces(plan, model, eta_after(model, sorted(scenario.faults, key=lambda f: f.t_s),
                                                            math.inf))
        if bad:
            raise UserInputError(f"{src}: [[separations]] #{i}: {bad[0]}")
    if scenario.separations:
        return
    if scenario.starts_free:
        if scenario.faults and scenario.faults_known:
            raise UserInputError(f"{src}: [assembly] start = \"free\" with [[faults]] needs [control] faults_known = "
                                 "false (the pieces' detectors find them; told faults are planned before flight)")
        if scenario.reconfig.get("at_s") is not None:
            raise UserInputError(f"{src}: [reconfig] at_s cannot be combined with [assembly] start = \"free\"")
        return
    if not scenario.faults and not faults_may_come:
        raise UserInputError(f"{src}: [reconfig] enabled but the scenario has no [[faults]] to react to")


def free_ground_positions(scenario: Scenario, model: AssemblyModel, com_ned_m: np.ndarray,
                          yaw_rad: float) -> dict[int, np.ndarray]:
    """Where each unit of a free start rests: the assembled layout around the docked start's CoM
    (`com_ned_m`, `yaw_rad`), stretched from the unit pitch to `free_spacing_m` between neighbours (NED,
    CoM at rest height)."""
    com, yaw = com_ned_m, yaw_rad
    stretch = scenario.free_spacing_m / model.vehicle.pitch_m
    c, s_ = math.cos(yaw), math.sin(yaw)
    out = {}
    for u in model.unit_ids:
        x, y = model.unit_position(u)[:2] * stretch
        out[u] = np.array([com[0] + c * x - s_ * y, com[1] + s_ * x + c * y, -model.vehicle.gear_depth_m])
    return out


def make_plan(scenario: Scenario, model: AssemblyModel, mission, eta: np.ndarray | None = None,
              current: dict | None = None) -> ReconfigPlan:
    """The plan for the faults `eta` (default: all the scenario's faults, precomputed like paper 001's
    configuration tree; in flight: the faults the detectors found), from the structure `current` (unit ->
    cell of the layout; default: the layout's own numbering). `[reconfig] target` applies to a structure
    in the layout's own numbering (the first manoeuvre).

    A given `[reconfig] target` that cannot be reached is a UserInputError (exit 2)."""
    if eta is None:
        eta = eta_after(model, sorted(scenario.faults, key=lambda f: f.t_s), math.inf)
    if current is not None and current == nominal_cells(model):
        current = None
    target = scenario.reconfig.get("target") if current is None else None
    cells = None
    if target is not None:
        order = [model.unit_cells[u] for u in model.unit_ids]
        cells = {u: c for u, c in zip(target, order)}
    weights = SnapWeights.from_trajectory(mission)  # (the mission weighs where units go, paper 001)
    v = model.vehicle  # pieces must hover within the real thrust limits, not only pass the quadrant rule
    rule = FlyabilityRule(hover_thrust_limits_n=(v.rotor_min_thrust_n, v.rotor_max_thrust_n))
    try:
        if cells is None and scenario.reconfig.get("objective", "force") == "margin":
            return plan_for_margin(model, eta, weights, current, rule)
        return plan_reconfiguration(model, health_from_eta(model, eta), weights, current=current, target=cells,
                                    rule=rule)
    except UserInputError as exc:
        raise UserInputError(f"{scenario.source}: [reconfig] {exc}") from None


#: the margin objective plans the sequences of this many targets (those whose final structure has the largest
#: margin, and paper 001's) and keeps the one whose weakest stage has the largest margin
MARGIN_TARGETS_PLANNED = 4
#: ... among this many, best final margin first (most are unreachable: no flyable split sequence gets there)
MARGIN_TARGETS_TRIED = 60
#: at most this many placements of the faulty units are weighed by their final margin (more: a fixed sample)
MARGIN_CANDIDATES = 2_000


def plan_for_margin(model: AssemblyModel, eta: np.ndarray, weights: SnapWeights, current: dict | None = None,
                    rule: FlyabilityRule = FlyabilityRule()) -> ReconfigPlan:
    """MARS-Reconfig's objective (arXiv 2503.09376): the plan whose weakest piece, at any stage of the
    sequence, has the largest controllability margin (`margin.worst_stage_margin`). Every placement of
    the faulty units is weighed by its final structure's margin (the healthy ones fill the other cells,
    moving as little as possible); the sequences of the best few and of paper 001's placement are planned
    and compared stage by stage. Ties (the weakest stage is often a lone unit, the same for every plan that
    flies one): the final structure's margin, then fewer layers, then paper 001's force objective."""
    from mars_link.reconfig.margin import margins, piece_margin, worst_stage_margin

    cur = dict(current) if current is not None else nominal_cells(model)
    health = health_from_eta(model, eta)
    eta_of = {u: health[u - 1] for u in model.unit_ids}
    faulty = [u for u in model.unit_ids if np.any(health[u - 1] < 1.0)]
    healthy = [u for u in model.unit_ids if u not in faulty]
    cells = [model.unit_cells[u] for u in model.unit_ids]  # (row-major: the model's slot order)
    targets = []
    every = math.perm(len(cells), len(faulty))
    if every <= MARGIN_CANDIDATES:
        placements = list(itertools.permutations(range(len(cells)), len(faulty)))
    else:  # (deterministic: the same faults give the same plan)
        rng = np.random.default_rng(0)
        placements = [tuple(rng.choice(len(cells), len(faulty), replace=False)) for _ in range(MARGIN_CANDIDATES)]
    for spots in placements:
        target = {u: cells[k] for u, k in zip(faulty, spots)}
        free = [c for k, c in enumerate(cells) if k not in spots]
        dist = np.array([[abs(c[0] - cur[u][0]) + abs(c[1] - cur[u][1]) for c in free] for u in healthy])
        rows, cols = linear_sum_assignment(dist) if healthy else ((), ())
        target.update({healthy[r]: free[c] for r, c in zip(rows, cols)})
        targets.append(target)
    at = [{c: u for u, c in t.items()} for t in targets]
    final = margins(model, np.array([np.concatenate([eta_of[a[c]] for c in cells]) for a in at]))
    plans = [plan_reconfiguration(model, health, weights, current=cur, rule=rule)]
    reached = 0
    for k in np.argsort(-final, kind="stable")[:MARGIN_TARGETS_TRIED]:
        try:
            plans.append(plan_reconfiguration(model, health, weights, current=cur, target=targets[k], rule=rule))
        except UserInputError:  # (this target cannot be reached: the next)
            continue
        reached += 1
        if reached == MARGIN_TARGETS_PLANNED:
            break
    feasible = [dataclasses.replace(p, objective="margin") for p in plans if p.feasible]
    if not feasible:
        return dataclasses.replace(plans[0], objective="margin")
    return max(feasible, key=lambda p: (round(worst_stage_margin(p, model.vehicle, eta_of), 9),
                                        round(piece_margin(model.vehicle, p.target, eta_of), 9),
                                        -(p.disassembly_layers + p.assembly_layers), p.placement.objective))


def plan_event(t_s: float, plan: ReconfigPlan, vehicle, eta_of: dict[int, np.ndarray]) -> dict:
    """The `plan` event: feasible, layers, why not, what chose it and both objectives (paper 001's force
    objective and the worst-stage controllability margin, `margin.plan_figures`), whatever chose it."""
    from mars_link.reconfig.margin import plan_figures

    figures = plan_figures(plan, vehicle, eta_of) if plan.feasible else {}
    text = (f"Reconfig plan: {plan.disassembly_layers}+{plan.assembly_layers} layers" if plan.feasible
            else "Reconfig: no feasible plan")
    return event(t_s, EventKind.PLAN, feasible=plan.feasible, disassembly_layers=plan.disassembly_layers,
                 assembly_layers=plan.assembly_layers, fallback_used=plan.fallback_used, reason=plan.reason,
                 chosen_by=plan.objective, **figures, text=text)


def unhoverable_pieces(plan: ReconfigPlan, model: AssemblyModel, eta: np.ndarray) -> list[str]:
    """Pieces of the plan that cannot hover within the rotor limits with their faults.

    The planner's four-quadrant rule (paper 001) is necessary, not sufficient (spec §5): e.g. a
    1x3 piece with a dead end module passes it but, with thrust limits, cannot balance its roll.
    Each piece the plan creates (both sides of every split, every docked result) gets the exact LP
    hover test of `check_controllable`; the manoeuvre is refused if one fails.
    """
    from mars_link.allocation import check_controllable

    eta_of = {u: eta[model.unit_slots(u)] for u in model.unit_ids}
    pieces = [s.detached for s in plan.splits] + [s.rest for s in plan.splits]
    pieces += [m.stationary + m.mover for m in plan.merges]
    bad = []
    for units in pieces:
        cells = plan.initial if any(set(units) == set(s.detached) or set(units) == set(s.rest)
                                    for s in plan.splits) else plan.target
        shape = PieceShape({u: cells[u] for u in units})
        piece = shape.model(model.vehicle)
        try:
            check_controllable(piece, local_eta(shape, eta_of),
                               (piece.vehicle.rotor_min_thrust_n, piece.vehicle.rotor_max_thrust_n))
        except UserInputError as exc:
            bad.append(f"piece {sorted(units)}: {exc}")
    return bad


def plan_separation(model: AssemblyModel, units, redock: bool) -> ReconfigPlan:
    """A commanded separation: `units` undock along one straight cut and, with `redock`, dock back into
    their cells (one split layer, one dock layer). A set of units that no straight cut separates, or that
    leaves either side in several parts, is a UserInputError."""
    from mars_link.core.latches import components, neighbour_links
    from mars_link.reconfig.placement import Placement
    from mars_link.reconfig.sequencing import BreakLine, MergeStep, SplitStep

    cells = nominal_cells(model)
    detached = sorted(units)
    rest = sorted(set(model.unit_ids) - set(detached))
    for axis, k in (("row", 0), ("col", 1)):
        for index in range(1, 1 + max(c[k] for c in cells.values())):
            low = sorted(u for u, c in cells.items() if c[k] < index)
            if detached not in (low, sorted(set(cells) - set(low))):
                continue
            for part in (detached, rest):
                links = neighbour_links({u: cells[u] for u in part})
                if len(components(part, links)) != 1:
                    raise UserInputError(f"separation of units {detached}: the cut leaves units {part} in pieces")
            line = BreakLine(axis, index)
            approach = ("+" if detached == low else "-") + axis
            split = SplitStep(1, sorted(model.unit_ids), line, detached, rest)
            merges = [MergeStep(1, 0, rest, detached, line, approach)] if redock else []
            return ReconfigPlan(model.layout, cells, Placement(cells, 0.0, "given", 0.0), True, 1,
                                1 if redock else 0, [split], merges, [detached, rest])
    raise UserInputError(f"separation of units {detached}: no straight cut of layout {','.join(model.layout)} "
                         "separates exactly these units")


#: a single move is flown only if it lowers the hover Σ T² by at least this share (a manoeuvre has its risks)
MOVE_MIN_GAIN = 0.01


def plan_or_reason(scenario: Scenario, model: AssemblyModel, mission, eta: np.ndarray,
                   current: dict | None = None) -> tuple[ReconfigPlan | None, str]:
    """A plan worth executing for the faults `eta` from the structure `current` (feasible, with something
    to split, every piece able to hover), else None and why not. Paper 001's plan first; where it finds
    nothing to fly, the best single move (`mars_link.reconfig.moves`) if it saves MOVE_MIN_GAIN of the
    hover Σ T²; where no move does, the best rebuild on the ground (`best_ground_plan`), on the same gain."""
    try:
        plan = make_plan(scenario, model, mission, eta, current)
    except UserInputError as exc:
        return None, str(exc)
    if not plan.feasible:
        reason = f"no feasible plan: {plan.reason}"
    elif not plan.disassembly_layers:
        reason = "the structure is already the best one for these faults"
    else:
        bad = unhoverable_pieces(plan, model, eta)
        if not bad:
            return plan, ""
        reason = "; ".join(bad)
    if scenario.reconfig.get("moves", True):
        move, why_not = best_single_move(model, eta, current)
        if move is not None:
            return move, ""
        reason = f"{reason}; {why_not}"
    if scenario.reconfig.get("ground", True):
        plan, why_not = best_ground_plan(model, eta, current)
        if plan is not None:
            return plan, ""
        reason = f"{reason}; on the ground: {why_not}"
    return None, reason


def best_single_move(model: AssemblyModel, eta: np.ndarray,
                     current: dict | None = None) -> tuple[ReconfigPlan | None, str]:
    """The single move with the lowest hover Σ T², as a plan, if it saves MOVE_MIN_GAIN of it; else None
    and why not."""
    from mars_link.reconfig.moves import HoverCosts, best_moves, move_plan

    cells = dict(current) if current is not None else nominal_cells(model)
    costs = HoverCosts(model.vehicle, {u: eta[model.unit_slots(u)] for u in model.unit_ids})
    found = best_moves(cells, costs, depth=1)
    if found.first_moves == 0:
        return None, "no piece can split off and dock back with every body hovering"
    if not found.moves or found.best_sum_sq_n2 > (1.0 - MOVE_MIN_GAIN) * found.start_sum_sq_n2:
        return None, f"no single move saves {100 * MOVE_MIN_GAIN:.0f} % of the hover force"
    return move_plan(cells, found.moves[0], found.best_sum_sq_n2), ""


def best_ground_plan(model: AssemblyModel, eta: np.ndarray,
                     current: dict | None = None) -> tuple[ReconfigPlan | None, str]:
    """The best rebuild on the ground (`moves.best_ground_moves`: land, lift up to two pieces that fly alone
    off the resting body, put them down in better slots, take off) as a plan, if it saves MOVE_MIN_GAIN of
    the hover Σ T²; else None and why not. For a body no move in the air improves: one that can hover
    only whole (paper 001's plus with 6 faults)."""
    from mars_link.reconfig.moves import HoverCosts, best_ground_moves, ground_plan

    cells = dict(current) if current is not None else nominal_cells(model)
    costs = HoverCosts(model.vehicle, {u: eta[model.unit_slots(u)] for u in model.unit_ids})
    found = best_ground_moves(cells, costs)
    if not found.lifts or found.best_sum_sq_n2 > (1.0 - MOVE_MIN_GAIN) * found.start_sum_sq_n2:
        return None, f"no rebuild saves {100 * MOVE_MIN_GAIN:.0f} % of the hover force"
    return ground_plan(cells, found), ""
