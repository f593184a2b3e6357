"""Disassembly and assembly sequences (paper 001 Algorithms 1-3 with the spec's corrections).

Vocabulary: a *piece* is a rigid set of units; a *split* undocks one connected piece from the rest
along one straight break line between grid rows or columns (spec §6: the detached part is a
connected component of one side, the rest must stay connected); a *layer* is one round in which
every flying piece may split (disassembly) or every pair scheduled together docks (assembly).

* Algorithm 1 (full disassembly): cost = 1 + max over children (corrected from the printed sum);
  a piece with no flyable split is a leaf. Memoised on shape + health, translation-invariant.
* Algorithm 2 (partial disassembly): R(P) = 0 if P can be dropped as is into its target cells,
  else 1 + min over flyable splits of max(R(P1), R(P2)); memoised on the piece (its cells in the
  current structure fix shape, health and which unit is where). Pruned by the lower bound
  ceil(log2(number of distinct target translations in P)), with balanced splits tried first.
* Placeable = one translation takes every unit of the piece to its target cell, and no other
  target cell lies inside the bounding box of its target cells. That is the paper's
  "non-enclosure" made exact as a local test: two pieces can only ever be docked (directly or as
  parts of bigger bodies) if a straight grid line separates them, so a foreign cell inside the box
  could never join. The full condition is global: the final pieces must be re-assemblable by
  straight-line docks (Algorithm 3). If the DP's pieces are not, the tree search continues over all
  split trees of the same depth, then deeper, so the reported layers stay minimal.
* Algorithm 3 (assembly): straight-line docks of two connected bodies; cost = 1 + max (corrected:
  base case and +1 added). As in the spec, the body that docks lies wholly on one side of the line;
  as the mirror image of the §6 undock, the other body may extend past the line beside it if the
  slider's path is clear (see `_Assembler`).

Costs are reported in layers: 0 = nothing to do (the paper counts the root call as 1 more).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Iterator

import numpy as np

from mars_link.core.assembly import AssemblyModel, VehicleParams, layout_of_cells
from mars_link.core.errors import UserInputError
from mars_link.reconfig.flyability import Cell, CellMasks, FlyabilityChecker, FlyabilityRule
from mars_link.reconfig.placement import (
    Placement,
    SnapWeights,
    health_from_eta,
    nominal_cells,
    placement_costs,
    solve_placement,
)

INF = math.inf
#: leaf sets tried per depth when the DP's pieces cannot be re-assembled (rare; see module doc)
SEARCH_BUDGET = 20000
SEARCH_TIME_S = 10.0


@dataclass(frozen=True)
class BreakLine:
    """axis "row": the line between layout rows index-1 and index (front part | rear part);
    axis "col": the line between columns index-1 and index (left part | right part)."""

    axis: str
    index: int

    def to_json(self) -> dict:
        return {"axis": self.axis, "index": self.index}


@dataclass
class SplitStep:
    layer: int  # 1-based disassembly layer
    body: list[int]  # units of the piece that splits
    line: BreakLine  # in the current (pre-reconfiguration) layout frame
    detached: list[int]  # the connected part on one side of the line
    rest: list[int]


@dataclass
class MergeStep:
    layer: int  # 1-based assembly layer
    altitude_slot: int  # 0, 1, ...: each docking pair of a layer flies at its own altitude
    stationary: list[int]  # the larger body holds still
    mover: list[int]
    line: BreakLine  # in the target layout frame; the mover approaches across it
    approach: str  # direction the mover travels to dock: "+row" (rearwards), "-row", "+col" (right), "-col"


@dataclass
class Disassembly:
    layers: int | float  # INF when impossible
    splits: list[SplitStep]
    pieces: list[list[int]]
    states: int
    exhaustive: bool = True  # False when the tree search hit its budget (layers may be above the minimum)
    time_s: float = 0.0  # Algorithm 2 (and the tree search), without the assembly checks


@dataclass
class AssemblyPlan:
    layers: int | float
    merges: list[MergeStep]
    states: int
    time_s: float = 0.0  # every Algorithm 3 call made for this plan


@dataclass
class ReconfigPlan:
    """Everything the executor needs, plus how it was found."""

    layout: tuple[str, ...]
    initial: dict[int, Cell]
    placement: Placement
    feasible: bool
    disassembly_layers: int | None
    assembly_layers: int | None
    splits: list[SplitStep] = field(default_factory=list)
    merges: list[MergeStep] = field(default_factory=list)
    pieces: list[list[int]] = field(default_factory=list)
    fallback_used: bool = False
    reason: str | None = None
    optimal: bool = True
    states: int = 0
    timings_s: dict[str, float] = field(default_factory=dict)
    #: the manoeuvre happens on the ground: the body lands, the pieces that fly leave it and come down
    #: into their slots from above (approach "down"), the rest waits on the ground with its motors off
    on_ground: bool = False
    #: what chose the target: "force" (paper 001's placement) or "margin" (reconfig.plans.plan_for_margin)
    objective: str = "force"

    @property
    def target(self) -> dict[int, Cell]:
        return self.placement.unit_cells

    def steps(self) -> list[dict]:
        """Execution order: split layers, then per assembly layer a move and a dock per pair."""
        out: list[dict] = []
        for s in sorted(self.splits, key=lambda s: s.layer):
            out.append({"kind": "split", "layer": s.layer, "body": s.body, "line": s.line.to_json(),
                        "detached": s.detached, "rest": s.rest})
        for m in sorted(self.merges, key=lambda m: (m.layer, m.altitude_slot)):
            out.append({"kind": "move", "layer": m.layer, "body": m.mover, "altitude_slot": m.altitude_slot,
                        "to_cells": [[u, *self.target[u]] for u in m.mover], "beside": m.stationary})
            out.append({"kind": "dock", "layer": m.layer, "bodies": [m.stationary, m.mover],
                        "line": m.line.to_json(), "approach": m.approach,
                        "result": sorted(m.stationary + m.mover)})
        return out

    def to_json(self) -> dict:
        return {
            "layout": list(self.layout),
            "initial": [{"unit": u, "row": r, "col": c} for u, (r, c) in sorted(self.initial.items())],
            "placement": [{"unit": u, "row": r, "col": c} for u, (r, c) in sorted(self.target.items())],
            "placement_solver": self.placement.solver,
            "objective": self.placement.objective,
            "chosen_by": self.objective,
            "feasible": self.feasible,
            "cost_layers": self.disassembly_layers,
            "assembly_layers": self.assembly_layers,
            "optimal": self.optimal,
            "pieces": self.pieces,
            "fallback_used": self.fallback_used,
            "forced_blocks": self.placement.forced_blocks,
            "reason": self.reason,
            "states": self.states,
            "steps": self.steps(),
            "solve_time_s": self.timings_s.get("total", 0.0),
            "timings_s": self.timings_s,
        }


def _ceil_log2(k: int) -> int:
    return (k - 1).bit_length() if k > 1 else 0


def _cells_layout(model: AssemblyModel) -> CellMasks:
    n_rows = len(model.layout)
    n_cols = max(len(r) for r in model.layout)
    return CellMasks(n_rows, n_cols, model.unit_cells.values())


class Sequencer:
    """Split and assembly search on one structure with one current allocation and fixed health.

    Flyability, split lists and the Algorithm 1 memo do not depend on the target and are kept
    across `partial_disassembly` calls (the infinite-cost fallback and the configuration tree).
    """

    def __init__(self, model: AssemblyModel, health: np.ndarray, current: dict[int, Cell] | None = None,
                 rule: FlyabilityRule = FlyabilityRule()):
        self.model = model
        self.health = np.asarray(health, dtype=float)
        self.current = nominal_cells(model) if current is None else dict(current)
        self.grid = _cells_layout(model)
        self.grid_t = CellMasks(self.grid.n_cols, self.grid.n_rows, [(c, r) for r, c in model.unit_cells.values()])
        self.unit_at = {cell: u for u, cell in self.current.items()}
        self.fly = FlyabilityChecker(self.grid, model, self.health, self.unit_at, rule)
        self.root = self.grid.all
        self._splits: dict[int, list[tuple[BreakLine, int, int]]] = {}
        self._full: dict[tuple, tuple] = {}

    # ----------------------------------------------------------------- pieces
    def units(self, mask: int) -> list[int]:
        return sorted(self.unit_at[c] for c in self.grid.cells(mask))

    def mask_of_units(self, units) -> int:
        return self.grid.mask(self.current[u] for u in units)

    def splits(self, piece: int) -> list[tuple[BreakLine, int, int]]:
        """Flyable splits (line, detached, rest), most balanced first."""
        hit = self._splits.get(piece)
        if hit is not None:
            return hit
        seen = set()
        out = []
        for line, comps_a, comps_b in self.line_cuts(piece):
            for part, _ in self.detachable(line, comps_a, comps_b):
                rest = piece ^ part
                key = min(part, rest)
                if key not in seen:
                    seen.add(key)
                    if self.fly(part) and self.fly(rest):
                        out.append((line, part, rest))
        out.sort(key=lambda s: abs(s[1].bit_count() - s[2].bit_count()))
        self._splits[piece] = out
        return out

    def line_cuts(self, mask: int) -> list[tuple[BreakLine, list[int], list[int]]]:
        """Every break line through the mask's bounding box with the connected parts on each side
        (before the line = lower row or column indices)."""
        g, gt = self.grid, self.grid_t
        out = [(BreakLine("row", r), above, below) for r, above, below in g.row_line_components(mask)]
        for c, left, right in gt.row_line_components(g.transpose_to(mask, gt)):
            side = mask & g.cols_below[c]
            left = [side] if len(left) == 1 else [gt.transpose_to(m, g) for m in left]
            right = [mask ^ side] if len(right) == 1 else [gt.transpose_to(m, g) for m in right]
            out.append((BreakLine("col", c), left, right))
        return out

    def detachable(self, line: BreakLine, comps_a: list[int], comps_b: list[int]) -> list[tuple[int, bool]]:
        """(part, lies before the line) for the connected parts of either side whose removal leaves
        the rest connected (spec §6).

        The parts of the two sides form a bipartite graph (edges across the line); a part may leave
        iff it is not a cut vertex of that graph.
        """
        g = self.grid
        if len(comps_b) == 1:  # every part before the line leaves the rest joined through side b
            return [(m, True) for m in comps_a]
        if len(comps_a) == 1:
            return [(m, False) for m in comps_b]
        if line.axis == "row":  # side_a = rows above the line: its last row faces side_b's first
            edge = g.rows_below[line.index] & ~g.rows_below[line.index - 1]
            cross = lambda m: (m & edge) << g.stride  # noqa: E731
        else:
            edge = g.col[line.index - 1]
            cross = lambda m: (m & edge) << 1  # noqa: E731
        nodes = comps_a + comps_b
        na = len(comps_a)
        adj = [[] for _ in nodes]
        for i, a in enumerate(comps_a):
            ca = cross(a)
            for j, b in enumerate(comps_b):
                if ca & b:
                    adj[i].append(na + j)
                    adj[na + j].append(i)
        out = []
        for skip in range(len(nodes)):
            start = 1 if skip == 0 else 0
            seen = {skip, start}
            stack = [start]
            while stack:
                for nb in adj[stack.pop()]:
                    if nb not in seen:
                        seen.add(nb)
                        stack.append(nb)
            if len(seen) == len(nodes):
                out.append((nodes[skip], skip < na))
        return out

    def path_blocked(self, line: BreakLine, part: int, others: int, before: bool) -> bool:
        """Would `part`, sliding in perpendicular to the line from its own side, hit `others`?"""
        g = self.grid
        if line.axis == "col":  # work on columns as rows of the transposed grid
            g = self.grid_t
            part, others = self.grid.transpose_to(part, g), self.grid.transpose_to(others, g)
        c0, c1 = g.col_span(part)
        for c in range(c0, c1 + 1):
            in_col = part & g.col[c]
            if not in_col:
                continue
            if before:  # comes from low rows: nothing of the others may sit at a row below its last
                ahead = (1 << (in_col.bit_length() - 1)) - 1
            else:  # comes from high rows: nothing beyond its first row
                ahead = ~((1 << (in_col & -in_col).bit_length()) - 1)
            if others & g.col[c] & ahead:
                return True
        return False

    # ----------------------------------------------------------------- Algorithm 1
    def _shape_health_key(self, piece: int) -> tuple[tuple, int]:
        g = self.grid
        r0, _ = g.row_span(piece)
        c0, _ = g.col_span(piece)
        shift = r0 * g.stride + c0
        key = (piece >> shift, (self.fly.faulty & piece) >> shift,
               tuple((w & piece) >> shift for w in self.fly.working))
        return key, shift

    def _full_cost(self, piece: int) -> int:
        if piece.bit_count() == 1:
            return 0
        key, shift = self._shape_health_key(piece)
        hit = self._full.get(key)
        if hit is not None:
            return hit[0]
        best, choice = INF, None
        for line, part, rest in self.splits(piece):
            c = 1 + max(self._full_cost(part), self._full_cost(rest))
            if c < best:
                best, choice = c, (part >> shift, rest >> shift)
                if best == 1:
                    break
        if choice is None:
            best = 0  # no flyable split: a leaf block (it holds a faulty unit or cannot be cut)
        self._full[key] = (best, choice)
        return best

    def full_disassembly(self) -> Disassembly:
        """Algorithm 1 on the whole structure: the minimal rigid blocks and the fewest layers to reach them."""
        layers = self._full_cost(self.root)

        def choice(piece):
            key, shift = self._shape_health_key(piece)
            hit = self._full.get(key) if piece.bit_count() > 1 else None
            if hit is None or hit[1] is None:
                return None
            part, rest = hit[1][0] << shift, hit[1][1] << shift
            return self._line_between(part, rest), part, rest

        splits, pieces = self._unfold(self.root, choice)
        return Disassembly(layers, splits, pieces, len(self._full))

    def _line_between(self, part: int, rest: int) -> BreakLine:
        """The break line that detaches `part` from `rest` (first one found, as in `splits`)."""
        for line, a, b in self.splits(part | rest):
            if {a, b} == {part, rest}:
                return line
        raise AssertionError("split not found")  # pragma: no cover - internal consistency

    def _unfold(self, root: int, choice) -> tuple[list[SplitStep], list[list[int]]]:
        splits, pieces = [], []
        stack = [(root, 1)]
        while stack:
            piece, layer = stack.pop()
            ch = choice(piece)
            if ch is None:
                pieces.append(self.units(piece))
                continue
            line, part, rest = ch
            splits.append(SplitStep(layer, self.units(piece), line, self.units(part), self.units(rest)))
            stack += [(rest, layer + 1), (part, layer + 1)]
        splits.sort(key=lambda s: (s.layer, s.body))
        pieces.sort()
        return splits, pieces

    # ----------------------------------------------------------------- Algorithm 2
    def partial_disassembly(self, target: dict[int, Cell], budget: int = SEARCH_BUDGET,
                            prune: bool = True, budget_s: float = SEARCH_TIME_S) -> tuple[Disassembly, AssemblyPlan]:
        """Fewest split layers after which every piece drops into its target and the pieces re-assemble.

        `prune=False` evaluates every split of every state, as the paper's DP does (for timing
        comparisons only: the result is the same). `budget` (leaf sets per depth) and `budget_s`
        bound the rare search that runs when the DP's pieces cannot be docked back together; a
        result found after the count budget ran out, or none found in time, has exhaustive=False.
        """
        t_start = time.perf_counter()
        t_asm = 0.0

        def assemble(masks: list[int]) -> AssemblyPlan:
            nonlocal t_asm
            t0 = time.perf_counter()
            out = search.assemble(masks)
            t_asm += time.perf_counter() - t0
            return out

        def result(layers, splits, pieces, asm, exhaustive=True):
            asm.time_s = t_asm
            dis = Disassembly(layers, splits, pieces, len(search.memo), exhaustive,
                              time.perf_counter() - t_start - t_asm)
            return dis, asm

        search = _PartialSearch(self, target, prune)
        lower = search.cost(self.root)
        if lower == INF:
            return result(INF, [], [], AssemblyPlan(INF, [], 0))
        splits, pieces = self._unfold(self.root, search.choice)
        asm = assemble([self.mask_of_units(p) for p in pieces])
        if asm.layers < INF:
            return result(lower, splits, pieces, asm)
        exhaustive = True
        deadline = time.perf_counter() + budget_s
        for depth in range(int(lower), self.root.bit_count()):
            tried = set()
            for leaves, tree in search.leaf_sets(self.root, depth):
                if leaves in tried:
                    continue
                tried.add(leaves)
                asm = assemble(sorted(leaves))
                if asm.layers < INF:
                    splits, pieces = self._unfold(self.root, lambda p, t=tree: t.get(p))
                    return result(depth, splits, pieces, asm, exhaustive)
                if len(tried) >= budget:
                    exhaustive = False
                    break
                if time.perf_counter() > deadline:
                    return result(INF, [], [], AssemblyPlan(INF, [], 0), False)
        return result(INF, [], [], AssemblyPlan(INF, [], 0), exhaustive)


class _PartialSearch:
    """Algorithm 2 state for one target: translation classes, memo, assembly of leaf sets."""

    def __init__(self, seq: Sequencer, target: dict[int, Cell], prune: bool = True):
        self.seq = seq
        self.prune = prune
        g = seq.grid
        self.delta_of_bit: dict[int, tuple[int, int]] = {}
        classes: dict[tuple[int, int], int] = {}
        for u, (r, c) in seq.current.items():
            tr, tc = target[u]
            d = (tr - r, tc - c)
            b = g.bit(r, c)
            self.delta_of_bit[b.bit_length() - 1] = d
            classes[d] = classes.get(d, 0) | b
        self.classes = classes
        self.class_masks = list(classes.values())
        self.memo: dict[int, tuple] = {}
        self._placeable: dict[int, bool] = {}
        self._lower: dict[int, int | float] = {}

    def delta(self, piece: int) -> tuple[int, int]:
        return self.delta_of_bit[(piece & -piece).bit_length() - 1]

    def target_mask(self, piece: int) -> int:
        return self.seq.grid.shift(piece, *self.delta(piece))

    def placeable(self, piece: int) -> bool:
        hit = self._placeable.get(piece)
        if hit is None:
            d = self.delta(piece)
            if piece & ~self.classes[d]:
                hit = False
            else:  # no other piece may sit inside its bounding box (it could never dock to it)
                t = self.target_mask(piece)
                hit = not self.seq.grid.box(t) & self.seq.root & ~t
            self._placeable[piece] = hit
        return hit

    def lower_bound(self, piece: int) -> int:
        hit = self._lower.get(piece)
        if hit is None:
            hit = self.memo[piece][0] if piece in self.memo else (
                0 if self.placeable(piece) else max(1, _ceil_log2(sum(1 for m in self.class_masks if piece & m))))
            self._lower[piece] = hit
        return hit

    def cost(self, piece: int) -> int | float:
        hit = self.memo.get(piece)
        if hit is not None:
            return hit[0]
        if self.placeable(piece):
            self.memo[piece] = (0, None)
            return 0
        prune = self.prune
        lb = self.lower_bound(piece) if prune else 1
        best, choice = INF, None
        for line, part, rest in self.seq.splits(piece):
            if prune and 1 + max(self.lower_bound(part), self.lower_bound(rest)) >= best:
                continue
            c1 = self.cost(part)
            if prune and 1 + c1 >= best:
                continue
            c = 1 + max(c1, self.cost(rest))
            if c < best:
                best, choice = c, (line, part, rest)
                if prune and best <= lb:
                    break
        self.memo[piece] = (best, choice)
        return best

    def choice(self, piece: int):
        hit = self.memo.get(piece)
        return None if hit is None else hit[1]

    def leaf_sets(self, piece: int, depth: int) -> Iterator[tuple[frozenset, dict]]:
        """Every set of final pieces reachable from `piece` in at most `depth` layers, with its tree.

        Finer sets come first: smaller pieces are the likelier to dock back together.
        """
        if depth > 0:
            for line, part, rest in self.seq.splits(piece):
                if self.cost(part) > depth - 1 or self.cost(rest) > depth - 1:
                    continue
                for la, ta in self.leaf_sets(part, depth - 1):
                    for lb, tb in self.leaf_sets(rest, depth - 1):
                        yield la | lb, {**ta, **tb, piece: (line, part, rest)}
        if self.placeable(piece):
            yield frozenset([piece]), {}

    def assemble(self, pieces: list[int]) -> AssemblyPlan:
        seq = self.seq
        targets = {self.target_mask(p): p for p in pieces}
        asm = _Assembler(seq, list(targets))
        layers = asm.cost(seq.root)
        if layers == INF:
            return AssemblyPlan(INF, [], len(asm.memo))
        unit_of_target = {}
        for tmask, p in targets.items():
            for tc, pc in zip(seq.grid.cells(tmask), seq.grid.cells(p)):
                unit_of_target[tc] = seq.unit_at[pc]
        units = lambda m: sorted(unit_of_target[c] for c in seq.grid.cells(m))  # noqa: E731
        by_layer: dict[int, list] = {}
        stack = [seq.root]
        while stack:
            region = stack.pop()
            hit = asm.memo.get(region)
            if region in asm.pieces or hit is None:
                continue
            by_layer.setdefault(int(hit[0]), []).append(hit[1])
            stack += [hit[1][1], hit[1][2]]
        merges: list[MergeStep] = []
        for layer in sorted(by_layer):
            order = sorted(by_layer[layer], key=lambda m: min(units(m[1] | m[2])))
            for slot, (line, slider, other, before) in enumerate(order):
                us, uo = units(slider), units(other)
                towards = "+" if before else "-"  # the slider travels towards the line
                if (len(us), -min(us)) > (len(uo), -min(uo)):  # the larger body holds still
                    us, uo = uo, us
                    towards = "-" if before else "+"
                merges.append(MergeStep(layer, slot, uo, us, line, towards + line.axis))
        return AssemblyPlan(layers, merges, len(asm.memo))


class _Assembler:
    """Algorithm 3 over target-cell bitmasks: fewest docking layers for a set of pieces.

    A dock joins two bodies across one straight line: the body that lies wholly on one side of it
    (no piece of it crosses the line) slides in perpendicular to the line and touches the other
    only across it. The other body may reach past the line beside it, provided nothing of it lies
    in the slider's way: the time-reverse of the component undock of spec §6. Each body must be
    connected. With a single part on each side this is the spec's Algorithm 3 exactly.
    """

    def __init__(self, seq: Sequencer, pieces: list[int]):
        self.seq = seq
        grid = seq.grid
        self.pieces = set(pieces)
        self.reps = 0  # one bit per piece, to count pieces in a region with one popcount
        self.cross = {}
        for p in pieces:
            self.reps |= p & -p
            r0, r1 = grid.row_span(p)
            c0, c1 = grid.col_span(p)
            for r in range(r0 + 1, r1 + 1):
                self.cross[("row", r)] = self.cross.get(("row", r), 0) | p
            for c in range(c0 + 1, c1 + 1):
                self.cross[("col", c)] = self.cross.get(("col", c), 0) | p
        self.memo: dict[int, tuple] = {}

    def merges(self, region: int) -> list[tuple[BreakLine, int, int, bool]]:
        """(line, slider, other body, slider before the line), most balanced first."""
        seq = self.seq
        out, seen = [], set()
        for line, comps_a, comps_b in seq.line_cuts(region):
            crossing = region & self.cross.get((line.axis, line.index), 0)
            for part, before in seq.detachable(line, comps_a, comps_b):
                if part & crossing:
                    continue
                rest = region ^ part
                key = min(part, rest)
                if key in seen:
                    continue
                side = comps_a if before else comps_b
                if (len(side) > 1 or crossing) and seq.path_blocked(line, part, rest, before):
                    continue
                seen.add(key)
                out.append((line, part, rest, before))
        out.sort(key=lambda m: abs(2 * m[1].bit_count() - region.bit_count()))
        return out

    def cost(self, region: int) -> int | float:
        if region in self.pieces:
            return 0
        hit = self.memo.get(region)
        if hit is not None:
            return hit[0]
        lb = _ceil_log2((region & self.reps).bit_count())
        best, choice = INF, None
        for merge in self.merges(region):
            ca = self.cost(merge[1])
            if 1 + ca >= best:
                continue
            c = 1 + max(ca, self.cost(merge[2]))
            if c < best:
                best, choice = c, merge
                if best <= lb:
                    break
        self.memo[region] = (best, choice)
        return best


# ----------------------------------------------------------------------------- the pipeline
def _check_allocation(model: AssemblyModel, cells: dict[int, Cell], what: str) -> dict[int, Cell]:
    cells = {int(u): (int(c[0]), int(c[1])) for u, c in cells.items()}
    if sorted(cells) != model.unit_ids:
        raise UserInputError(f"{what} must name every unit 1..{model.n_units} once")
    if sorted(cells.values()) != sorted(model.unit_cells.values()):
        raise UserInputError(f"{what} must put the units in the cells of layout {','.join(model.layout)}")
    return cells


def _faulty_units(model: AssemblyModel, health: np.ndarray, rule: FlyabilityRule) -> list[int]:
    return [u for u in model.unit_ids if np.any(health[u - 1] < rule.faulty_below)]


def plan_reconfiguration(
    model: AssemblyModel,
    health: np.ndarray,
    weights: SnapWeights = SnapWeights(),
    current: dict[int, Cell] | None = None,
    target: dict[int, Cell] | None = None,
    rule: FlyabilityRule = FlyabilityRule(),
    sequencer: Sequencer | None = None,
) -> ReconfigPlan:
    """Target allocation (unless given), then the fewest disassembly layers and the assembly.

    If the optimal target cannot be reached (infinite cost), the multi-unit leaf blocks of
    Algorithm 1 are bound with forced adjacencies and the allocation is solved again, once. A
    caller-given target that cannot be reached is a UserInputError.
    """
    t_start = time.perf_counter()
    health = np.asarray(health, dtype=float)
    current = _check_allocation(model, nominal_cells(model) if current is None else current, "current allocation")
    timings: dict[str, float] = {}
    if target is None:
        placement = solve_placement(model, health, weights, current)
        timings["placement"] = placement.solve_time_s
    else:
        target = _check_allocation(model, target, "target allocation")
        cost = placement_costs(model, health, weights)
        cells = [model.unit_cells[u] for u in model.unit_ids]
        objective = float(sum(cost[cells.index(target[u]), u - 1] for u in model.unit_ids))
        placement = Placement(target, objective, "given", 0.0)
    seq = sequencer if sequencer is not None else Sequencer(model, health, current, rule)

    def attempt(pl: Placement) -> tuple[Disassembly, AssemblyPlan]:
        dis, asm = seq.partial_disassembly(pl.unit_cells)
        timings["disassembly"] = timings.get("disassembly", 0.0) + dis.time_s
        timings["assembly"] = timings.get("assembly", 0.0) + asm.time_s
        return dis, asm

    dis, asm = attempt(placement)
    fallback = False
    if dis.layers == INF and target is None:
        t0 = time.perf_counter()
        blocks = [p for p in seq.full_disassembly().pieces if len(p) > 1]
        timings["full_disassembly"] = time.perf_counter() - t0
        if blocks:
            placement = solve_placement(model, health, weights, current, forced_blocks=blocks)
            timings["placement"] = timings.get("placement", 0.0) + placement.solve_time_s
            dis, asm = attempt(placement)
            fallback = True
    timings["total"] = time.perf_counter() - t_start
    faulty = _faulty_units(model, health, rule)
    if dis.layers == INF:
        if target is not None:
            raise UserInputError(
                "target allocation is unreachable: no sequence of flyable splits and straight-line docks "
                f"puts every unit in its target cell (faulty units: {faulty or 'none'})"
            )
        reason = ("no flyable split sequence lets the pieces drop into the target and re-assemble "
                  f"(faulty units: {faulty or 'none'})")
        return ReconfigPlan(model.layout, current, placement, False, None, None, fallback_used=fallback,
                            reason=reason, optimal=dis.exhaustive, states=dis.states, timings_s=timings)
    return ReconfigPlan(
        model.layout, current, placement, True, int(dis.layers), int(asm.layers), dis.splits, asm.merges,
        dis.pieces, fallback, None, dis.exhaustive, dis.states, timings,
    )


def plan_assembly(model: AssemblyModel, rule: FlyabilityRule = FlyabilityRule()) -> ReconfigPlan:
    """Free units into `model`'s layout, every unit in its own cell: Algorithm 3's docking layers alone
    (fewest layers; ceil(log2 N) for a rectangle), no split. The plan's `pieces` are the single units."""
    t0 = time.perf_counter()
    cells = nominal_cells(model)
    seq = Sequencer(model, health_from_eta(model, model.nominal_eta()), cells, rule)
    asm = _PartialSearch(seq, cells).assemble([seq.mask_of_units([u]) for u in model.unit_ids])
    timings = {"assembly": time.perf_counter() - t0, "total": time.perf_counter() - t0}
    placement = Placement(cells, 0.0, "given", 0.0)
    if asm.layers == INF:
        return ReconfigPlan(model.layout, cells, placement, False, None, None, reason="no docking sequence builds "
                            "the layout from single units", states=asm.states, timings_s=timings)
    return ReconfigPlan(model.layout, cells, placement, True, 0, int(asm.layers), [], asm.merges,
                        [[u] for u in model.unit_ids], states=asm.states, timings_s=timings)


def plan_assembly_of_pieces(vehicle: VehicleParams, cells: dict[int, Cell], pieces: list[list[int]],
                            rule: FlyabilityRule = FlyabilityRule()) -> ReconfigPlan:
    """The pieces there are (each a list of unit ids) docked into the structure `cells` (unit id -> cell)
    describes: Algorithm 3 from those pieces, in the unit ids given (e.g. an assembly re-planned without
    a unit that was lost). Not feasible when no docking sequence builds it (e.g. `cells` not connected)."""
    t0 = time.perf_counter()
    order = sorted(cells, key=cells.get)  # (the layout's row-major order: its model's unit ids 1..n)
    layout = layout_of_cells(cells.values())
    try:
        model = AssemblyModel.from_layout(layout, vehicle)
    except UserInputError as exc:
        return ReconfigPlan(layout, dict(cells), Placement(dict(cells), 0.0, "given", 0.0), False, None, None,
                            reason=str(exc))
    local = {u: k + 1 for k, u in enumerate(order)}
    local_cells = nominal_cells(model)
    seq = Sequencer(model, health_from_eta(model, model.nominal_eta()), local_cells, rule)
    asm = _PartialSearch(seq, local_cells).assemble([seq.mask_of_units([local[u] for u in p]) for p in pieces])
    target = {order[k - 1]: c for k, c in local_cells.items()}
    placement = Placement(target, 0.0, "given", 0.0)
    timings = {"assembly": time.perf_counter() - t0, "total": time.perf_counter() - t0}
    if asm.layers == INF:
        return ReconfigPlan(layout, target, placement, False, None, None, reason="no docking sequence builds the "
                            "structure from these pieces", states=asm.states, timings_s=timings)
    glob = [None] + order
    merges = [replace(m, stationary=[glob[u] for u in m.stationary], mover=[glob[u] for u in m.mover])
              for m in asm.merges]
    return ReconfigPlan(layout, target, placement, True, 0, int(asm.layers), [], merges,
                        [sorted(p) for p in pieces], states=asm.states, timings_s=timings)


__all__ = [
    "AssemblyPlan", "BreakLine", "Disassembly", "MergeStep", "ReconfigPlan", "Sequencer", "SplitStep",
    "health_from_eta", "plan_assembly", "plan_assembly_of_pieces", "plan_reconfiguration",
]
