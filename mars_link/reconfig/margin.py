"""The controllability margin of a structure and of a reconfiguration plan along its whole sequence.

MARS-Reconfig (Huang, Tang, Cai, Zhao, arXiv 2503.09376) measures how controllable a modular structure
is by its controllability margin: the signed distance from the hover wrench g = (n m g, 0, 0, 0) to the
boundary of the set of wrenches (thrust, roll, pitch, yaw moments) its rotors can produce within their
thrust limits, Omega = {B(eta) f : f_min <= f <= f_max}; positive means the structure can still push
at least that much in every direction of wrench space while it hovers (the measure TransforMARS, arXiv
2509.14025, §III, takes over as the minimum over the subassemblies of a stage). The paper plans to
maximise it at every intermediate stage of the sequence, not only at the end.

Omega is a zonotope (the image of a box), so its facets are spanned by three of its generators
(B's columns times the half thrust range) and the distance from an inside point to its boundary is the
smallest, over the facet normals n, of h(n) - n.g (h: the support function). The paper's axes mix N and
N·m; here (by default) each axis is the thrust that makes it (`controllability_margin`). Reported as
max(0, distance): 0 when the structure cannot hover or cannot produce every axis (rank of B < 4).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel, VehicleParams
from mars_link.reconfig.piece_shape import PieceShape, local_eta
from mars_link.reconfig.sequencing import ReconfigPlan

def controllability_margin(model: AssemblyModel, eta: np.ndarray | None = None, scaled: bool = True) -> float:
    """The structure's controllability margin with rotor efficiencies `eta` (default healthy): the
    smallest wrench it can still add to its hover wrench in every direction within its rotors' thrust
    range (`vehicle.command_range_n`); 0 when it cannot hover or is uncontrollable.

    `scaled` (default): each axis in the thrust that makes it (N): roll and pitch moments divided by the
    unit pitch, yaw by the yaw moment per thrust. Unscaled (the paper's N and N·m), the yaw axis, whose
    moment per thrust is a hundredth of an arm, bounds the distance for every placement of the same
    faults (plus-5 with one rotor out on each of three units: 0.4801 for all 120), so it cannot rank
    plans; scaled, it sees where the faulty units sit."""
    eta = model.nominal_eta() if eta is None else np.asarray(eta, dtype=float)
    return float(margins(model, eta[None, :], scaled)[0])


def margins(model: AssemblyModel, etas: np.ndarray, scaled: bool = True) -> np.ndarray:
    """`controllability_margin` of `model` for each row of `etas` (candidates, rotors) at once: a fault
    only shortens generators, so the facet normals of the healthy structure (cached per layout) hold
    every faulty one's, and each margin is a minimum over the same normals. (Working rotors spanning less
    than the four axes need no rank test: some normal is orthogonal to all of them, and it or its opposite
    finds the hover wrench on or outside the flat set: 0.)"""
    etas = np.atleast_2d(np.asarray(etas, dtype=float))
    _, n_b, n_half, n_hover = _facets(model, scaled)
    return np.maximum(0.0, np.min(etas @ (n_b + n_half).T - n_hover[None, :], axis=1))


_FACETS: dict[tuple, tuple] = {}


def _facets(model: AssemblyModel, scaled: bool) -> tuple:
    """(normals, normals . B mid, |normals . B| half, normals . hover) of the healthy structure's zonotope."""
    v = model.vehicle
    key = (model.layout, v, scaled)
    if key not in _FACETS:
        lo, hi = v.command_range_n
        b = model.effectiveness()
        if scaled:
            b = b / np.array([1.0, v.pitch_m, v.pitch_m, v.yaw_moment_per_thrust_m])[:, None]
        normals = _facet_normals(_distinct_directions(b))
        hover = np.array([model.mass_kg * GRAVITY_MPS2, 0.0, 0.0, 0.0])
        nb = normals @ b
        _FACETS[key] = (normals, nb * 0.5 * (hi + lo), np.abs(nb) * 0.5 * (hi - lo), normals @ hover)
    return _FACETS[key]


def _distinct_directions(gens: np.ndarray) -> np.ndarray:
    """Parallel generators merged into one (the normals only need their directions): fewer triples."""
    unit = gens / np.linalg.norm(gens, axis=0)
    sign = np.sign(unit[np.argmax(np.abs(unit) > 1e-9, axis=0), np.arange(unit.shape[1])])
    keys = np.round(unit * sign, 9)
    merged: dict[tuple, np.ndarray] = {}
    for k in range(gens.shape[1]):
        merged.setdefault(tuple(keys[:, k]), unit[:, k] * sign[k])
    return np.column_stack(list(merged.values()))


def _facet_normals(gens: np.ndarray) -> np.ndarray:
    """Unit normals (both signs) of the hyperplanes through every triple of independent generators in R^4:
    each the generalised cross product (the 3x3 cofactors)."""
    triples = np.array(list(itertools.combinations(range(gens.shape[1]), 3)))
    m = np.transpose(gens[:, triples], (1, 0, 2))  # (triples, 4, 3)
    cof = np.stack([(-1) ** r * np.linalg.det(np.delete(m, r, axis=1)) for r in range(4)], axis=1)
    norm = np.linalg.norm(cof, axis=1)
    keep = norm > 1e-9 * max(1.0, float(norm.max(initial=0.0)))
    n = cof[keep] / norm[keep, None]
    n = np.unique(np.round(n * np.sign(n[np.arange(len(n)), np.argmax(np.abs(n) > 1e-9, axis=1)])[:, None], 12),
                  axis=0)  # (triples on one hyperplane give one normal)
    return np.vstack([n, -n])


def piece_margin(vehicle: VehicleParams, cells: dict[int, tuple[int, int]], eta_of: dict[int, np.ndarray]) -> float:
    """The margin of the rigid piece whose units sit in `cells` (unit -> cell), with each unit's efficiencies."""
    shape = PieceShape(dict(cells))
    return controllability_margin(shape.model(vehicle), local_eta(shape, eta_of))


def plan_stages(plan: ReconfigPlan) -> list[dict[int, tuple[int, int]]]:
    """Every rigid piece the plan flies at some stage (unit -> cell): the structure it starts from, both
    sides of every split, each piece a dock joins and each docked result, and the final structure."""
    initial, target = plan.initial, plan.target
    pieces: list[list[int]] = [sorted(initial)] if plan.splits else []
    pieces += [list(p) for s in plan.splits for p in (s.detached, s.rest)]
    placed = [list(p) for m in plan.merges for p in (m.stationary, m.mover, m.stationary + m.mover)]
    out = [{u: initial[u] for u in p} for p in pieces] + [{u: target[u] for u in p} for p in placed]
    out.append(dict(target))
    seen, unique = set(), []
    for cells in out:
        key = tuple(sorted(cells.items()))
        if key not in seen:
            seen.add(key)
            unique.append(cells)
    return unique


def worst_stage_margin(plan: ReconfigPlan, vehicle: VehicleParams, eta_of: dict[int, np.ndarray]) -> float:
    """The smallest controllability margin of any piece the plan flies, at any stage (MARS-Reconfig's
    objective is to make this large); `eta_of`: each unit's believed rotor efficiencies."""
    stages = plan_stages(plan)
    return min((piece_margin(vehicle, cells, eta_of) for cells in stages), default=math.inf)


def plan_figures(plan: ReconfigPlan, vehicle: VehicleParams, eta_of: dict[int, np.ndarray]) -> dict:
    """Both objectives of a plan, as events and summaries report them: paper 001's force objective (the
    placement's sum of c_ij) and the worst-stage controllability margin, with the final structure's."""
    final = piece_margin(vehicle, plan.target, eta_of) if plan.target else 0.0
    return {"force_objective": round(float(plan.placement.objective), 6) if plan.placement is not None else None,
            "worst_stage_margin": round(worst_stage_margin(plan, vehicle, eta_of), 6),
            "final_margin": round(final, 6)}
