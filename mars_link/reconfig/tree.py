"""Configuration tree: reconfiguration plans precomputed per fault sequence (paper 001 §I).

The root is the fault-free structure in its nominal allocation. Each child adds one fault event
and holds the plan from the parent's allocation to the new optimal one; after a feasible plan the
child flies in the new allocation, otherwise it stays where it was (the allocator copes). Plans are
cached by (allocation, health), so sequences that end in the same state share one solve.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from mars_link.core.assembly import ROTORS_PER_UNIT, AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.reconfig.flyability import Cell, FlyabilityRule
from mars_link.reconfig.placement import SnapWeights, nominal_cells


@dataclass(frozen=True)
class FaultEvent:
    """Rotor `rotor` (1..4, mars-link order; None = all four) of `unit` drops to efficiency `eta`."""

    unit: int
    rotor: int | None = None
    eta: float = 0.0

    def apply(self, health: np.ndarray) -> np.ndarray:
        out = health.copy()
        if self.rotor is None:
            out[self.unit - 1, :] = self.eta
        else:
            out[self.unit - 1, self.rotor - 1] = self.eta
        return out

    def label(self) -> str:
        return f"{self.unit}" + (f":{self.rotor}" if self.rotor else "") + f"={self.eta:g}"


@dataclass
class TreeNode:
    faults: tuple[FaultEvent, ...]
    health: np.ndarray
    allocation: dict[int, Cell]  # where units sit once this node's plan has been executed
    plan: object | None  # ReconfigPlan from the parent's allocation (None at the root)
    children: dict[FaultEvent, "TreeNode"] = field(default_factory=dict)


@dataclass
class ConfigurationTree:
    root: TreeNode
    n_nodes: int
    n_solves: int
    build_time_s: float

    def lookup(self, faults: Iterable[FaultEvent]) -> TreeNode:
        node = self.root
        for i, ev in enumerate(faults, 1):
            if ev not in node.children:
                raise UserInputError(f"fault sequence step {i} ({ev.label()}) is not in the configuration tree")
            node = node.children[ev]
        return node


def single_rotor_events(model: AssemblyModel, eta: float = 0.0) -> list[FaultEvent]:
    """Every rotor of every unit failing on its own: the paper's fault model."""
    return [FaultEvent(u, k, eta) for u in model.unit_ids for k in range(1, ROTORS_PER_UNIT + 1)]


def build_configuration_tree(
    model: AssemblyModel,
    depth: int = 1,
    events: Iterable[FaultEvent] | None = None,
    weights: SnapWeights = SnapWeights(),
    rule: FlyabilityRule = FlyabilityRule(),
) -> ConfigurationTree:
    """Plans for every sequence of up to `depth` distinct events (events that change nothing are skipped)."""
    from mars_link.reconfig.sequencing import plan_reconfiguration

    if depth < 0:
        raise UserInputError(f"configuration tree depth must be >= 0, got {depth}")
    events = single_rotor_events(model) if events is None else list(events)
    for ev in events:
        model.check_rotor(ev.unit, ev.rotor)
        if not 0.0 <= ev.eta <= 1.0:
            raise UserInputError(f"fault event {ev.label()}: eta must be in [0, 1]")
    t0 = time.perf_counter()
    cache: dict[tuple, object] = {}
    root = TreeNode((), np.ones((model.n_units, ROTORS_PER_UNIT)), nominal_cells(model), None)
    count = 1
    frontier = [root]
    for _ in range(depth):
        nxt = []
        for node in frontier:
            for ev in events:
                health = ev.apply(node.health)
                if np.array_equal(health, node.health):
                    continue
                key = (tuple(sorted(node.allocation.items())), health.tobytes())
                plan = cache.get(key)
                if plan is None:
                    plan = cache[key] = plan_reconfiguration(model, health, weights, node.allocation, rule=rule)
                allocation = dict(plan.target) if plan.feasible else dict(node.allocation)
                child = TreeNode(node.faults + (ev,), health, allocation, plan)
                node.children[ev] = child
                nxt.append(child)
                count += 1
        frontier = nxt
    return ConfigurationTree(root, count, len(cache), time.perf_counter() - t0)


def polyomino_layouts(n_cells: int) -> list[tuple[str, ...]]:
    """Every connected layout of exactly `n_cells` units (fixed polyominoes: rotations and mirror
    images count separately, because the front and the rotor geometry make them different).

    For exhaustive sweeps: 1, 2, 6, 19, 63, 216 layouts for 1..6 cells.
    """
    if n_cells < 1:
        raise UserInputError(f"a layout needs at least one unit, got {n_cells}")
    shapes = {frozenset([(0, 0)])}
    for _ in range(n_cells - 1):
        grown = set()
        for shape in shapes:
            for r, c in shape:
                for cell in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
                    if cell not in shape:
                        new = shape | {cell}
                        r0 = min(x for x, _ in new)
                        c0 = min(y for _, y in new)
                        grown.add(frozenset((x - r0, y - c0) for x, y in new))
        shapes = grown
    layouts = []
    for shape in shapes:
        n_rows = max(r for r, _ in shape) + 1
        n_cols = max(c for _, c in shape) + 1
        layouts.append(tuple("".join("X" if (r, c) in shape else "." for c in range(n_cols)) for r in range(n_rows)))
    return sorted(layouts)
