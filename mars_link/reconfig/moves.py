"""Reconfiguration by single-piece moves: split one piece off, dock it back elsewhere, repeat.

Paper 001's plans (`sequencing`) disassemble first and then assemble, into the same layout with units
permuted; every piece of the plan must hover within the thrust limits. This module searches the other
family of manoeuvres: one piece at a time leaves the body along a straight break line and docks back at
another place on a straight line, so the body in between may take any shape. It answers whether a body
that paper 001's plans cannot improve has a reachable better arrangement, and which moves reach it.

A move is valid when the piece and the rest each hover alone and the docked result hovers, all within
the rotor thrust limits with the faults they carry (exact LP, `hover_thrust_share`). An arrangement's
cost is Σ T² of the flight's own allocator (`qp`, its bounds) at hover: the force integral's rate.
The search is breadth-first over arrangements up to translation (`best_moves`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mars_link.core.assembly import GRAVITY_MPS2, VehicleParams
from mars_link.core.latches import components, neighbour_links
from mars_link.reconfig.piece_shape import PieceShape, local_eta
from mars_link.reconfig.flyability import Cell

Arrangement = frozenset  # of (unit, cell): a rigid body up to translation (normalised: min row, col = 0)


def normalised(cells: dict[int, Cell]) -> Arrangement:
    r0 = min(r for r, _ in cells.values())
    c0 = min(c for _, c in cells.values())
    return frozenset((u, (r - r0, c - c0)) for u, (r, c) in cells.items())


@dataclass
class HoverCosts:
    """Hover figures of arrangements with fixed rotor healths (memoised: the search asks many times)."""

    vehicle: VehicleParams
    eta_of: dict[int, np.ndarray]  # unit -> its four rotor efficiencies
    _cache: dict = field(default_factory=dict)

    def share(self, cells: dict[int, Cell]) -> float:
        """The least largest rotor command with which the body hovers, as a share of the maximum (> 1: it cannot)."""
        return self._figures(normalised(cells))[0]

    def sum_sq_n2(self, cells: dict[int, Cell]) -> float:
        """Σ T² (N²) of the qp allocator's hover (inf when the body cannot hover)."""
        return self._figures(normalised(cells))[1]

    def _figures(self, key: Arrangement) -> tuple[float, float]:
        hit = self._cache.get(key)
        if hit is None:
            hit = self._cache[key] = self._compute(dict(key))
        return hit

    def _compute(self, cells: dict[int, Cell]) -> tuple[float, float]:
        from mars_link.allocation import hover_thrust_share, make_allocator

        v = self.vehicle
        shape = PieceShape(cells)
        model = shape.model(v)
        eta = local_eta(shape, self.eta_of)
        share = hover_thrust_share(model, eta, v.rotor_max_thrust_n)
        if not share <= 1.0:
            return share, float("inf")
        alloc = make_allocator("qp", model, eta, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
        thrusts = alloc.allocate(np.array([model.mass_kg * GRAVITY_MPS2, 0.0, 0.0, 0.0]))
        return share, float(thrusts @ thrusts)


@dataclass(frozen=True)
class Move:
    """`units` split off along a straight line and docked back so that they sit at `cells`."""

    units: tuple[int, ...]
    cells: tuple[Cell, ...]  # the units' cells after the dock, in the frame of the structure before it
    cut: tuple[int, int] = (0, 0)  # the break line it leaves along: (axis 0 rows / 1 columns, index)
    dock_axis: int = 0  # the axis it approaches along to dock


def splits(cells: dict[int, Cell]):
    """(piece, rest, (axis, index)) of a straight break line (axis 0: between rows index-1 and index, 1:
    between columns): the piece is a connected group of one side, the rest stays connected (the undock
    `sequencing` allows)."""
    links = neighbour_links(cells)
    seen = set()
    for axis in (0, 1):
        values = sorted({c[axis] for c in cells.values()})
        for line in values[1:]:
            low = [u for u, c in cells.items() if c[axis] < line]
            high = [u for u, c in cells.items() if c[axis] >= line]
            for side in (low, high):
                for group in components(side, links):
                    rest = set(cells) - group
                    key = frozenset(group)
                    if key in seen or len(components(rest, links)) != 1:
                        continue
                    seen.add(key)
                    yield sorted(group), sorted(rest), (axis, line)


def slots(piece: dict[int, Cell], body: dict[int, Cell]):
    """Every place where `piece` touches `body`: no overlap, at least one face in contact (from above, as on
    the ground, every such place is reachable; `docks` keeps those a straight level approach reaches).
    Yields the piece's cells there."""
    occupied = set(body.values())
    pr = [c[0] for c in piece.values()]
    pc = [c[1] for c in piece.values()]
    rr = [c[0] for c in occupied]
    rc = [c[1] for c in occupied]
    for dr in range(min(rr) - max(pr) - 1, max(rr) - min(pr) + 2):
        for dc in range(min(rc) - max(pc) - 1, max(rc) - min(pc) + 2):
            moved = {u: (r + dr, c + dc) for u, (r, c) in piece.items()}
            mine = set(moved.values())
            if not mine & occupied and any((r + a, c + b) in occupied for r, c in mine
                                           for a, b in ((1, 0), (-1, 0), (0, 1), (0, -1))):
                yield moved


def docks(piece: dict[int, Cell], rest: dict[int, Cell]):
    """Every place where `piece` docks to `rest` on a straight line: no overlap, at least one face in
    contact, and a grid line with the piece wholly on one side and the rest on the other (the approach
    is clear). Yields the piece's cells there and that line's axis (0: rows, 1: columns)."""
    occupied = set(rest.values())
    for moved in slots(piece, rest):
        mine = set(moved.values())
        for k in (0, 1):  # (face contact: at most one axis separates them)
            lo, hi = min(x[k] for x in mine), max(x[k] for x in mine)
            if hi < min(x[k] for x in occupied) or lo > max(x[k] for x in occupied):
                yield moved, k


def moves(cells: dict[int, Cell], costs: HoverCosts, max_piece_units: int | None = None):
    """Every valid single move from `cells`: (Move, the body after it)."""
    for piece_units, rest_units, cut in splits(cells):
        if max_piece_units is not None and len(piece_units) > max_piece_units:
            continue
        piece = {u: cells[u] for u in piece_units}
        rest = {u: cells[u] for u in rest_units}
        if costs.share(piece) > 1.0 or costs.share(rest) > 1.0:
            continue
        for moved, dock_axis in docks(piece, rest):
            after = {**rest, **moved}
            if costs.share(after) <= 1.0:
                yield Move(tuple(piece_units), tuple(moved[u] for u in piece_units), cut, dock_axis), after


@dataclass
class MoveSearch:
    start_sum_sq_n2: float
    best_sum_sq_n2: float
    moves: list[Move]
    final: dict[int, Cell]
    arrangements_seen: int
    first_moves: int  # valid moves from the start (0: no piece can leave and come back hovering)


def best_moves(cells: dict[int, Cell], costs: HoverCosts, depth: int = 2,
               max_piece_units: int | None = None) -> MoveSearch:
    """The lowest-Σ T² arrangement reachable in at most `depth` moves (breadth first; among equal costs the
    fewest units moved, then the fewest moves), and the moves that reach it."""
    best_cost = costs.sum_sq_n2(cells)
    best: tuple[list[Move], dict[int, Cell]] = ([], dict(cells))
    best_moved = 0  # units moved by the best sequence (among equal costs, the fewest win)
    frontier = [(dict(cells), [])]
    visited = {normalised(cells)}
    first = None
    for _ in range(depth):
        reached: dict[Arrangement, tuple[dict[int, Cell], list[Move], int]] = {}  # the fewest units moved to each
        for body, path in frontier:
            found = list(moves(body, costs, max_piece_units))
            if first is None:
                first = len(found)
            for move, after in found:
                key = normalised(after)
                moved = sum(len(m.units) for m in path) + len(move.units)
                if key not in visited and (key not in reached or moved < reached[key][2]):
                    reached[key] = (after, path + [move], moved)
        visited.update(reached)
        for after, path, moved in reached.values():
            cost = costs.sum_sq_n2(after)
            if cost < best_cost - 1e-9 * best_cost or (
                    cost <= best_cost + 1e-9 * best_cost and best[0] and moved < best_moved):
                best_cost, best, best_moved = cost, (path, after), moved
        frontier = [(after, path) for after, path, _ in reached.values()]
    return MoveSearch(costs.sum_sq_n2(cells), best_cost, best[0], best[1], len(visited), first or 0)


def move_plan(cells: dict[int, Cell], move: Move, sum_sq_n2: float) -> "ReconfigPlan":
    """One move as the executor's plan: one split layer (the piece leaves across its break line), one dock
    layer (it approaches the rest along `dock_axis`). Cells are shifted so both frames start at 0."""
    from mars_link.core.assembly import layout_of_cells
    from mars_link.reconfig.placement import Placement
    from mars_link.reconfig.sequencing import BreakLine, MergeStep, ReconfigPlan, SplitStep

    initial = dict(normalised(cells))
    shift = {k: min(c[k] for c in cells.values()) for k in (0, 1)}
    target = {**cells, **dict(zip(move.units, move.cells))}
    target = dict(normalised(target))
    mover = sorted(move.units)
    rest = sorted(set(cells) - set(mover))
    axis_name = ("row", "col")
    cut_axis, cut_index = move.cut
    split = SplitStep(1, sorted(cells), BreakLine(axis_name[cut_axis], cut_index - shift[cut_axis]), mover, rest)
    k = move.dock_axis
    mover_max = max(target[u][k] for u in mover)
    low = mover_max < min(target[u][k] for u in rest)  # the mover on the low side: it travels + along k
    index = mover_max + 1 if low else max(target[u][k] for u in rest) + 1
    merge = MergeStep(1, 0, rest, mover, BreakLine(axis_name[k], index), ("+" if low else "-") + axis_name[k])
    return ReconfigPlan(layout_of_cells(initial.values()), initial, Placement(target, sum_sq_n2, "moves", 0.0),
                        True, 1, 1, [split], [merge], [mover, rest],
                        reason=f"one move: units {mover} split off and dock elsewhere")


# ----------------------------------------------------------------------------- on the ground
@dataclass
class GroundSearch:
    """The best reconfiguration on the ground: the body lands, `lifts` take off one after the other (each
    a piece that flies alone, cut off the resting body along a straight line), then `placements` come
    down into their slots beside it, one after the other; the final body must hover."""

    start_sum_sq_n2: float
    best_sum_sq_n2: float
    lifts: list[tuple[tuple[int, ...], tuple[int, int]]]  # (piece units, cut (axis, index) of the body then)
    placements: list[tuple[tuple[int, ...], tuple[Cell, ...]]]  # (piece units, their cells, start frame)
    final: dict[int, Cell]
    searched: int  # final bodies evaluated
    exhaustive: bool = True  # False: the search stopped at its budget (the best found so far)


class _Budget(Exception):
    pass


def best_ground_moves(cells: dict[int, Cell], costs: HoverCosts, max_lifts: int = 2,
                      max_piece_units: int = 2, budget: int = 5_000) -> GroundSearch:
    """Lift up to `max_lifts` pieces (each of at most `max_piece_units` units, able to hover alone) off the
    landed body and put them back in the slots that give the lowest hover Σ T² of the final body (among
    equal costs, the fewest units moved). Each lifted piece waits straight above the cells it left, so no
    piece comes down into a slot under another one still waiting. The body on the ground need not hover in between: it rests.
    At most `budget` final bodies are evaluated (the plus-5: 216; the planner runs inside the control loop)."""
    start = costs.sum_sq_n2(cells)
    best = {"cost": start, "moved": 0, "lifts": [], "placements": [], "final": dict(cells)}
    searched = [0]

    def place(body, waiting, lifts, placed):
        if not waiting:
            if searched[0] >= budget:
                raise _Budget
            searched[0] += 1
            cost = costs.sum_sq_n2(body)
            moved = sum(len(u) for u, _ in placed)
            if cost < best["cost"] * (1 - 1e-9) or (cost <= best["cost"] * (1 + 1e-9) and best["lifts"]
                                                    and moved < best["moved"]):
                best.update(cost=cost, moved=moved, lifts=list(lifts), placements=list(placed), final=dict(body))
            return
        for i, (units, piece) in enumerate(waiting):  # (in any order: a slot may need a piece placed before)
            # the pieces still in the air wait over the cells they left: a piece comes down elsewhere
            below = {c for j, (_, other) in enumerate(waiting) if j != i for c in other.values()}
            for moved in slots(piece, body):
                if below.intersection(moved.values()):
                    continue
                place({**body, **moved}, waiting[:i] + waiting[i + 1:], lifts,
                      placed + [(units, tuple(moved[u] for u in units))])

    def lift(body, waiting, lifts):
        if waiting:
            place(body, waiting, lifts, [])
        if len(lifts) == max_lifts:
            return
        for piece_units, rest_units, cut in splits(body):
            if len(piece_units) > max_piece_units or len(rest_units) == 0:
                continue
            piece = {u: body[u] for u in piece_units}
            if costs.share(piece) > 1.0:
                continue
            lift({u: body[u] for u in rest_units}, waiting + [(tuple(piece_units), piece)],
                 lifts + [(tuple(piece_units), cut)])

    try:
        lift(dict(cells), [], [])
        exhaustive = True
    except _Budget:
        exhaustive = False
    return GroundSearch(start, best["cost"], best["lifts"], best["placements"], best["final"], searched[0],
                        exhaustive)


def ground_plan(cells: dict[int, Cell], found: GroundSearch) -> "ReconfigPlan":
    """A ground search's result as the executor's plan (`on_ground`): one split layer per lift, one dock
    layer per placement (approach "down": into its slot from above). Cells are shifted to start at 0."""
    from mars_link.core.assembly import layout_of_cells
    from mars_link.reconfig.placement import Placement
    from mars_link.reconfig.sequencing import BreakLine, MergeStep, ReconfigPlan, SplitStep

    initial = dict(normalised(cells))
    shift = {k: min(c[k] for c in cells.values()) for k in (0, 1)}
    body = set(cells)
    splits_, pieces = [], []
    for layer, (units, (axis, index)) in enumerate(found.lifts, 1):
        rest = body - set(units)
        splits_.append(SplitStep(layer, sorted(body), BreakLine(("row", "col")[axis], index - shift[axis]),
                                 sorted(units), sorted(rest)))
        pieces.append(sorted(units))
        body = rest
    pieces.append(sorted(body))
    target = {**cells}
    for units, where in found.placements:
        target.update(zip(units, where))
    target = dict(normalised(target))
    merges = []
    for layer, (units, _) in enumerate(found.placements, 1):
        merges.append(MergeStep(layer, 0, sorted(body), sorted(units), BreakLine("row", 0), "down"))
        body = body | set(units)
    moved = sorted(u for units, _ in found.lifts for u in units)
    return ReconfigPlan(layout_of_cells(initial.values()), initial,
                        Placement(target, found.best_sum_sq_n2, "ground moves", 0.0), True, len(splits_),
                        len(merges), splits_, merges, pieces, on_ground=True,
                        reason=f"on the ground: units {moved} lift off and come down elsewhere")
