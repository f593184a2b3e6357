"""Module-to-position allocation after faults (paper 001 §III, spec §4).

Maximise  sum_ij Pi_ij * c_ij,  c_ij = sum_k Gamma_jk * (w_x |x_ik| + w_y |y_ik|)
over permutations Pi (unit j at position i), with x_ik, y_ik the true rotor positions of position i
relative to the structure CoM (FRD, from the assembly's rotor table) and w_x, w_y the snap weights
of the planned trajectory. Without forced adjacencies this is a linear assignment problem, solved
exactly by `scipy.optimize.linear_sum_assignment`; forced adjacencies (constraint C3, used to keep
blocks with faulty modules rigid) need a MIP, solved by `scipy.optimize.milp` (HiGHS).

Ties are common (every healthy module is interchangeable), so the choice among optimal allocations
is made deterministic and useful: first keep as many units as possible in their current cell, then
move the rest as little as possible (total Manhattan distance in cells).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, linear_sum_assignment, milp

from mars_link.core.assembly import ROTORS_PER_UNIT, AssemblyModel
from mars_link.core.errors import UserInputError

Cell = tuple[int, int]


@dataclass(frozen=True)
class SnapWeights:
    """w_x, w_y = b_x / (b_x + b_y), b_y / (b_x + b_y); b = integral of |snap| along x (north) / y."""

    w_x: float = 0.5
    w_y: float = 0.5

    @classmethod
    def from_integrals(cls, b_x: float, b_y: float) -> "SnapWeights":
        if not (math.isfinite(b_x) and math.isfinite(b_y)) or b_x < 0 or b_y < 0:
            raise UserInputError(f"snap integrals must be finite and >= 0, got b_x={b_x!r}, b_y={b_y!r}")
        total = b_x + b_y
        if total == 0:  # purely vertical path: no preference (spec §4.3)
            return cls()
        return cls(b_x / total, b_y / total)

    @classmethod
    def from_trajectory(cls, trajectory, duration_s: float | None = None, dt_s: float = 0.01) -> "SnapWeights":
        """Full-length integrals (the paper's intent, not the code's 0.036 s window).

        The integral of |snap| is the total variation of jerk, summed from jerk samples, so no
        numerical differentiation is needed. `trajectory.sample(t)` returns a point with
        `jerk_ned_mps3` (mars_link.models.trajectories); x = north, y = east.
        """
        t_end = getattr(trajectory, "duration_s", None) if duration_s is None else duration_s
        if t_end is None or not t_end > 0:
            raise UserInputError("snap weights need a trajectory with a positive duration")
        ts = np.linspace(0.0, t_end, max(2, int(math.ceil(t_end / dt_s)) + 1))
        jerk = np.array([np.asarray(trajectory.sample(float(t)).jerk_ned_mps3, dtype=float)[:2] for t in ts])
        b = np.abs(np.diff(jerk, axis=0)).sum(axis=0)
        return cls.from_integrals(float(b[0]), float(b[1]))


@dataclass
class Placement:
    """Which unit sits in which layout cell, and how that was decided."""

    unit_cells: dict[int, Cell]
    objective: float  # sum of c_ij over the allocation (f_max omitted: it does not move the argmax)
    solver: str  # "lap" or "milp"
    solve_time_s: float
    forced_blocks: list[list[int]] = field(default_factory=list)

    def unit_at(self) -> dict[Cell, int]:
        return {cell: uid for uid, cell in self.unit_cells.items()}


def nominal_cells(model: AssemblyModel) -> dict[int, Cell]:
    """The layout as built: unit ids row-major from 1."""
    return dict(model.unit_cells)


def health_from_eta(model: AssemblyModel, eta: Iterable[float]) -> np.ndarray:
    """(N units, 4 rotors) health Gamma in mars-link rotor order from a per-rotor-slot vector."""
    gamma = np.asarray(list(eta), dtype=float)
    if gamma.shape != (model.n_rotors,):
        raise UserInputError(f"expected {model.n_rotors} rotor efficiencies, got {gamma.size}")
    if not np.all(np.isfinite(gamma)) or np.any(gamma < 0) or np.any(gamma > 1):
        raise UserInputError("rotor efficiencies must be in [0, 1]")
    return gamma.reshape(model.n_units, ROTORS_PER_UNIT)


def placement_costs(model: AssemblyModel, health: np.ndarray, weights: SnapWeights = SnapWeights()) -> np.ndarray:
    """c[i, j]: value of unit j in position i (positions = layout cells in row-major order)."""
    arm = np.abs(model.rotor_positions_m[:, :2]).reshape(model.n_units, ROTORS_PER_UNIT, 2)
    lever = weights.w_x * arm[:, :, 0] + weights.w_y * arm[:, :, 1]  # (positions, rotors)
    return lever @ np.asarray(health, dtype=float).T


def _check_current(model: AssemblyModel, current: dict[int, Cell]) -> None:
    if sorted(current) != model.unit_ids or sorted(current.values()) != sorted(model.unit_cells.values()):
        raise UserInputError("current allocation must put every unit in exactly one cell of the layout")


def _tie_scores(model: AssemblyModel, current: dict[int, Cell]) -> np.ndarray:
    """Secondary objective per (position, unit): a big bonus for staying, minus the cells moved."""
    cells = [model.unit_cells[u] for u in model.unit_ids]
    pos = np.array(cells)
    cur = np.array([current[u] for u in model.unit_ids])
    dist = np.abs(pos[:, None, :] - cur[None, :, :]).sum(axis=2)
    stay_bonus = model.n_units * int(dist.max(initial=0)) + 1
    return np.where(dist == 0, stay_bonus, 0) - dist


def forced_adjacencies(blocks: Iterable[Iterable[int]], current: dict[int, Cell]) -> list[tuple[int, int, int]]:
    """(j, j', d) for every adjacency inside each block in the current layout: d=0 j' right of j, d=1 below."""
    out = []
    for block in blocks:
        members = set(block)
        for j in members:
            r, c = current[j]
            for jj in members:
                if current[jj] == (r, c + 1):
                    out.append((j, jj, 0))
                elif current[jj] == (r + 1, c):
                    out.append((j, jj, 1))
    return out


def solve_placement(
    model: AssemblyModel,
    health: np.ndarray,
    weights: SnapWeights = SnapWeights(),
    current: dict[int, Cell] | None = None,
    forced_blocks: Iterable[Iterable[int]] = (),
    time_limit_s: float = 60.0,
) -> Placement:
    """Optimal allocation; `forced_blocks` (unit id groups) keep their current relative arrangement."""
    health = np.asarray(health, dtype=float)
    if health.shape != (model.n_units, ROTORS_PER_UNIT):
        raise UserInputError(f"health must be {model.n_units} x {ROTORS_PER_UNIT}, got {health.shape}")
    current = nominal_cells(model) if current is None else dict(current)
    _check_current(model, current)
    blocks = [sorted(set(b)) for b in forced_blocks if len(set(b)) > 1]
    for b in blocks:
        for u in b:
            model.check_rotor(u, None)
    cost = placement_costs(model, health, weights)
    tie = _tie_scores(model, current)
    t0 = time.perf_counter()
    adj = forced_adjacencies(blocks, current)
    if adj:
        rows_of_unit = _solve_milp(model, cost, tie, adj, time_limit_s)
        solver = "milp"
    else:
        rows_of_unit = _solve_lap(cost, tie)
        solver = "lap"
    dt = time.perf_counter() - t0
    cells = [model.unit_cells[u] for u in model.unit_ids]
    unit_cells = {u: cells[rows_of_unit[j]] for j, u in enumerate(model.unit_ids)}
    objective = float(sum(cost[rows_of_unit[j], j] for j in range(model.n_units)))
    return Placement(unit_cells, objective, solver, dt, blocks)


def _solve_lap(cost: np.ndarray, tie: np.ndarray) -> list[int]:
    """Lexicographic (cost, tie) maximum as one assignment with exactly representable integer weights."""
    n = cost.shape[0]
    tie_span = int(np.abs(tie).max(initial=0)) * n + 1
    scale = 2 * tie_span + 1
    cmax = float(np.abs(cost).max(initial=0.0))
    # quantum so that n * (max quantised cost * scale + tie) stays below 2**52 (exact in float64)
    quantum = max(cmax * scale * n / 2.0**52, 1e-12)
    combined = np.round(cost / quantum) * scale + tie
    rows, cols = linear_sum_assignment(combined, maximize=True)
    rows_of_unit = [0] * n
    for i, j in zip(rows, cols):
        rows_of_unit[j] = int(i)
    return rows_of_unit


def _solve_milp(
    model: AssemblyModel, cost: np.ndarray, tie: np.ndarray, adj: list[tuple[int, int, int]], time_limit_s: float
) -> list[int]:
    """Assignment + (C3) as a binary program: best cost first, then the best tie score at that cost."""
    n = model.n_units
    var = lambda i, j: i * n + j  # noqa: E731  position i, unit index j
    cells = [model.unit_cells[u] for u in model.unit_ids]
    index_of_cell = {c: i for i, c in enumerate(cells)}
    rows, lo, hi = [], [], []
    for i in range(n):  # each position holds one unit
        row = np.zeros(n * n)
        row[[var(i, j) for j in range(n)]] = 1
        rows.append(row), lo.append(1), hi.append(1)
    for j in range(n):  # each unit sits in one position
        row = np.zeros(n * n)
        row[[var(i, j) for i in range(n)]] = 1
        rows.append(row), lo.append(1), hi.append(1)
    for j, jj, d in adj:  # (C3) Pi_ij <= sum_i' P_{i,i',d} Pi_i'j'
        a, b = j - 1, jj - 1
        for i, (r, c) in enumerate(cells):
            row = np.zeros(n * n)
            row[var(i, a)] = 1
            nb = index_of_cell.get((r, c + 1) if d == 0 else (r + 1, c))
            if nb is not None:
                row[var(nb, b)] = -1
            rows.append(row), lo.append(-np.inf), hi.append(0)
    a_mat = np.array(rows)
    integrality = np.ones(n * n)
    bounds = Bounds(0, 1)
    opts = {"time_limit": time_limit_s, "mip_rel_gap": 0.0}
    first = milp(-cost.ravel(), constraints=LinearConstraint(a_mat, lo, hi), integrality=integrality,
                 bounds=bounds, options=opts)
    if first.x is None:
        blocks = sorted({(j, jj) for j, jj, _ in adj})
        raise UserInputError(f"no allocation keeps the forced blocks together (adjacencies {blocks})")
    best = -first.fun
    keep = LinearConstraint(cost.ravel()[None, :], best - 1e-9 * max(1.0, abs(best)), np.inf)
    second = milp(-tie.ravel().astype(float), constraints=[LinearConstraint(a_mat, lo, hi), keep],
                  integrality=integrality, bounds=bounds, options=opts)
    x = (second.x if second.x is not None else first.x).reshape(n, n)
    return [int(np.argmax(x[:, j])) for j in range(n)]
