"""Module-to-position allocation (paper 001 §III): exact optimum against brute force."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from mars_link.core.assembly import AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.reconfig import HelixReference, SnapWeights, rotor_from_paper001, solve_placement
from mars_link.reconfig.placement import health_from_eta, nominal_cells
from mars_link.reconfig.tree import polyomino_layouts

PRESET = "modquad-cf2"


def brute_costs(model: AssemblyModel, health: np.ndarray, w: SnapWeights) -> np.ndarray:
    """c[i, j] from first principles: cell centres about their mean, rotors at (+-a, +-a) FRD."""
    cells = [model.unit_cells[u] for u in model.unit_ids]
    p = model.vehicle.pitch_m
    a = model.vehicle.rotor_offset_m
    centres = np.array([[-r * p, c * p] for r, c in cells])
    centres -= centres.mean(axis=0)
    signs = [(1, 1), (1, -1), (-1, -1), (-1, 1)]  # FR, FL, RL, RR
    c = np.zeros((len(cells), len(cells)))
    for i, (x, y) in enumerate(centres):
        lever = [w.w_x * abs(x + sx * a) + w.w_y * abs(y + sy * a) for sx, sy in signs]
        c[i] = health @ np.array(lever)
    return c


def brute_best(model, health, w, current, allowed=None):
    """Max objective over all permutations, then the tie-break (stay, then move least)."""
    n = model.n_units
    c = brute_costs(model, health, w)
    cells = [model.unit_cells[u] for u in model.unit_ids]
    perms = np.array(list(itertools.permutations(range(n))))  # perms[p][j] = position of unit j
    if allowed is not None:
        perms = perms[[allowed(p) for p in perms]]
    values = c[perms, np.arange(n)].sum(axis=1)
    best = values.max()
    near = perms[values >= best - 1e-9]
    cur = np.array([current[u] for u in model.unit_ids])
    pos = np.array(cells)
    moved = np.abs(pos[near] - cur[None]).sum(axis=2)
    key = [((m == 0).sum(), -m.sum()) for m in moved]
    top = max(key)
    return best, [p for p, k in zip(near, key) if k == top]


def single_rotor_faults(n):
    for u in range(1, n + 1):
        for k in range(4):
            h = np.ones((n, 4))
            h[u - 1, k] = 0.0
            yield (u, k + 1), h


def check_layouts(sizes, weights):
    checked = 0
    for n in sizes:
        for layout in polyomino_layouts(n):
            model = AssemblyModel.from_layout(layout, PRESET)
            cur = nominal_cells(model)
            cells = [model.unit_cells[u] for u in model.unit_ids]
            for fault, health in single_rotor_faults(n):
                for w in weights:
                    pl = solve_placement(model, health, w)
                    best, winners = brute_best(model, health, w, cur)
                    assert pl.solver == "lap"
                    assert pl.objective == pytest.approx(best, rel=1e-9, abs=1e-12), (layout, fault)
                    chosen = [cells.index(pl.unit_cells[u]) for u in model.unit_ids]
                    assert any(list(p) == chosen for p in winners), (layout, fault, chosen)
                    checked += 1
    return checked


def test_lap_is_optimal_for_every_layout_up_to_5_and_every_single_rotor_fault():
    assert check_layouts(range(1, 6), [SnapWeights(), SnapWeights(0.8, 0.2)]) == 2 * (
        4 * 1 + 8 * 2 + 12 * 6 + 16 * 19 + 20 * 63)


@pytest.mark.slow
@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_lap_is_optimal_for_every_6_unit_layout_and_every_single_rotor_fault():
    assert check_layouts([6], [SnapWeights(), SnapWeights(0.3, 0.7)]) == 2 * 24 * 216


def test_milp_with_forced_blocks_matches_brute_force():
    rng = np.random.default_rng(3)
    cases = 0
    for layout in polyomino_layouts(4) + polyomino_layouts(5)[::4]:
        model = AssemblyModel.from_layout(layout, PRESET)
        cur = nominal_cells(model)
        n = model.n_units
        # bind a random adjacent pair (one of them faulty), as the infinite-cost fallback does
        pairs = [(a, b) for a in model.unit_ids for b in model.unit_ids
                 if a < b and abs(cur[a][0] - cur[b][0]) + abs(cur[a][1] - cur[b][1]) == 1]
        a, b = pairs[rng.integers(len(pairs))]
        health = np.ones((n, 4))
        health[a - 1, rng.integers(4)] = 0.0
        w = SnapWeights(0.6, 0.4)
        pl = solve_placement(model, health, w, forced_blocks=[[a, b]])
        cells = [model.unit_cells[u] for u in model.unit_ids]
        d = (cur[b][0] - cur[a][0], cur[b][1] - cur[a][1])

        def keeps(p):
            ra, rb = cells[p[a - 1]], cells[p[b - 1]]
            return (rb[0] - ra[0], rb[1] - ra[1]) == d

        best, winners = brute_best(model, health, w, cur, allowed=keeps)
        assert pl.solver == "milp"
        assert pl.objective == pytest.approx(best, rel=1e-9)
        ta, tb = pl.unit_cells[a], pl.unit_cells[b]
        assert (tb[0] - ta[0], tb[1] - ta[1]) == d
        chosen = [cells.index(pl.unit_cells[u]) for u in model.unit_ids]
        assert any(list(p) == chosen for p in winners)
        cases += 1
    assert cases >= 25


def test_dead_unit_goes_to_the_middle_and_dead_rotor_points_inwards():
    line = AssemblyModel.from_layout(["XXX"], PRESET)
    h = np.ones((3, 4))
    h[0] = 0.0
    pl = solve_placement(line, h)
    assert pl.unit_cells[1] == (0, 1)
    # 2x2: unit 1 (front-left cell) loses its FR rotor -> it moves to the rear-left cell, where
    # its FR rotor sits nearest to the CoM; the unit that was there swaps with it
    sq = AssemblyModel.from_layout(["XX", "XX"], PRESET)
    h = np.ones((4, 4))
    h[0, 0] = 0.0
    pl = solve_placement(sq, h)
    assert pl.unit_cells[1] == (1, 0)
    assert pl.unit_cells[3] == (0, 0)
    assert pl.unit_cells[2] == (0, 1) and pl.unit_cells[4] == (1, 1)


def test_fault_free_keeps_everyone_in_place():
    model = AssemblyModel.from_layout([".X.", "XXX", ".X."], PRESET)
    pl = solve_placement(model, np.ones((5, 4)))
    assert pl.unit_cells == nominal_cells(model)


def test_snap_weights_follow_the_trajectory():
    assert SnapWeights.from_integrals(3.0, 1.0) == SnapWeights(0.75, 0.25)
    assert SnapWeights.from_integrals(0.0, 0.0) == SnapWeights(0.5, 0.5)

    class Sway:  # oscillates along x only: all snap is in x
        duration_s = 10.0

        def sample(self, t):
            from types import SimpleNamespace

            return SimpleNamespace(jerk_ned_mps3=np.array([-math.cos(t), 0.0, 0.3]))

    w = SnapWeights.from_trajectory(Sway())
    assert w.w_x == pytest.approx(1.0) and w.w_y == pytest.approx(0.0)

    class Circle(Sway):
        def sample(self, t):
            from types import SimpleNamespace

            return SimpleNamespace(jerk_ned_mps3=np.array([math.sin(t), -math.cos(t), 0.0]))

    w = SnapWeights.from_trajectory(Circle(), duration_s=8 * math.pi)
    assert w.w_x == pytest.approx(0.5, abs=1e-3)
    with pytest.raises(UserInputError):
        SnapWeights.from_integrals(-1.0, 1.0)


def test_weights_change_the_answer():
    # 1x3 line along y, unit 1 loses its FR rotor: with all snap along y the lost lever arm |y|
    # is smallest in the middle cell; with all snap along x every cell loses the same |x| = a,
    # so the tie-break keeps everyone in place.
    model = AssemblyModel.from_layout(["XXX"], PRESET)
    h = np.ones((3, 4))
    h[0, 0] = 0.0
    along_y = solve_placement(model, h, SnapWeights(0.0, 1.0))
    along_x = solve_placement(model, h, SnapWeights(1.0, 0.0))
    assert along_y.unit_cells[1] == (0, 1)
    assert along_x.unit_cells == nominal_cells(model)


def test_bad_input_is_one_line():
    model = AssemblyModel.from_layout(["XX"], PRESET)
    with pytest.raises(UserInputError, match="health must be 2 x 4"):
        solve_placement(model, np.ones((3, 4)))
    with pytest.raises(UserInputError, match="unit 7 does not exist"):
        solve_placement(model, np.ones((2, 4)), forced_blocks=[[1, 7]])
    with pytest.raises(UserInputError, match=r"\[0, 1\]"):
        health_from_eta(model, [1, 1, 1, 1, 1, 1, 1, 2])
    with pytest.raises(UserInputError, match="current allocation"):
        solve_placement(model, np.ones((2, 4)), current={1: (0, 0), 2: (0, 0)})


def test_paper001_rotor_numbers_map_once():
    # paper: 1 top-right, clockwise seen from above -> FR, RR, RL, FL; mars-link: FR, FL, RL, RR
    assert [rotor_from_paper001(k) for k in (1, 2, 3, 4)] == [1, 4, 3, 2]
    with pytest.raises(UserInputError):
        rotor_from_paper001(5)


def test_helix_reference():
    h = HelixReference()
    p = h.waypoints_paper()
    assert np.allclose(p[0], 0.0) and np.allclose(p[1], [2.5, 0.0, 0.0])
    assert p[-1][2] == pytest.approx(3.0)
    assert np.allclose(np.hypot(p[1:, 0], p[1:, 1]), 2.5)
    assert len(p) == 1 + 144 + 1
    ned = h.waypoints_ned(ground_down_m=0.0)
    assert ned[-1][2] == pytest.approx(-3.0) and np.allclose(ned[:, 1], -p[:, 1])
    assert h.duration_s() == pytest.approx(h.path_length_m() / 1.25)
    assert 33.0 < h.path_length_m() < 36.0
