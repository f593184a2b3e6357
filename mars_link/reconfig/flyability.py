"""Can a (sub)structure stay aloft on its own? The four-quadrant rule of paper 001 (spec §5).

A piece is flyable iff each open quadrant around the piece's *own* CoM holds at least one working
rotor (health > `working_threshold`); a rotor exactly on an axis counts for no quadrant. A lone
module that has any degraded rotor is never flyable ("never isolate a faulty module"), even if the
degraded rotor still counts as working for the quadrant rule.

Two implementations: `is_flyable` is the plain, exact (rational arithmetic) one for checking plans;
`CellMasks` + `FlyabilityChecker` do the same test on cell bitmasks in a few big-integer
operations, which the sequencing DPs call hundreds of thousands of times.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from typing import Iterable

import numpy as np

from mars_link.core.assembly import ROTORS_PER_UNIT, AssemblyModel

Cell = tuple[int, int]  # (row, col) in the layout; row 0 = front, col grows to the right


@dataclass(frozen=True)
class FlyabilityRule:
    """Which rotors count and which modules must never fly alone."""

    working_threshold: float = 0.0  # a rotor counts for its quadrant iff health > this
    faulty_below: float = 1.0  # a module with any rotor health below this is "faulty"
    # Flight planning: also require an exact hover of the piece within these rotor thrust limits [N]
    # (the LP of `check_controllable`). The quadrant rule is necessary only: a 1x3 piece with a dead
    # end module passes it and still cannot balance its roll when thrust is bounded. None = paper 001.
    hover_thrust_limits_n: tuple[float | None, float | None] | None = None


def rotor_offsets_cells(model: AssemblyModel) -> list[tuple[Fraction, Fraction]]:
    """Rotor k (0..3) offset from its unit centre in grid units (x forward = -row, y right = col).

    Read from the assembly's rotor table, so the quadrant rule uses the same geometry as the mixer,
    and snapped to the nearest fraction with denominator <= 10**6 so that float noise in the table
    cannot decide a rotor that sits exactly on a CoM axis (e.g. rotors at a quarter pitch).
    """
    hit = model._cache.get("reconfig_rotor_offsets")  # the model's own cache of derived tables
    if hit is not None:
        return hit
    pitch = model.vehicle.pitch_m
    uid = model.unit_ids[0]
    centre = model.unit_position(uid)
    offsets = []
    for rotor in model.rotors[:ROTORS_PER_UNIT]:
        d = (rotor.position_m - centre) / pitch
        offsets.append((Fraction(float(d[0])).limit_denominator(10**6),
                        Fraction(float(d[1])).limit_denominator(10**6)))
    model._cache["reconfig_rotor_offsets"] = offsets
    return offsets


def is_flyable(
    model: AssemblyModel,
    health: np.ndarray,
    cells: dict[int, Cell],
    rule: FlyabilityRule = FlyabilityRule(),
) -> bool:
    """Exact four-quadrant test of the piece {unit id: layout cell}; `health` is (N units, 4)."""
    if len(cells) == 1:
        (uid,) = cells
        return bool(np.all(health[uid - 1] >= rule.faulty_below))
    offsets = rotor_offsets_cells(model)
    n = len(cells)
    cx = Fraction(sum(-r for r, _ in cells.values()), n)
    cy = Fraction(sum(c for _, c in cells.values()), n)
    quadrants = set()
    for uid, (r, c) in cells.items():
        for k, (ox, oy) in enumerate(offsets):
            if health[uid - 1][k] <= rule.working_threshold:
                continue
            x, y = -r + ox - cx, c + oy - cy
            if x != 0 and y != 0:
                quadrants.add((x > 0, y > 0))
    return len(quadrants) == 4


# ----------------------------------------------------------------------------- bitmask machinery
def _runs(bits: int) -> Iterable[int]:
    """Maximal runs of consecutive set bits, lowest first."""
    while bits:
        low = bits & -bits
        run = bits & ~(bits + low)
        yield run
        bits ^= run


class CellMasks:
    """Cells of a layout as bits of a Python int: bit = row * (cols + 1) + col.

    The spare column keeps a one-bit shift from wrapping into the next row. Masks for rows, columns
    and half-planes are precomputed so that sides of a break line, bounding boxes, connected
    components and translations are a few integer operations.
    """

    def __init__(self, n_rows: int, n_cols: int, cells: Iterable[Cell]):
        self.n_rows, self.n_cols = n_rows, n_cols
        self.stride = n_cols + 1
        self.row_bits = (1 << n_cols) - 1
        self.all = 0
        for r, c in cells:
            self.all |= self.bit(r, c)
        col_one = sum(1 << (r * self.stride) for r in range(n_rows))
        self.col = [col_one << c for c in range(n_cols)]
        #: cells in columns < c (index c = 0..n_cols)
        self.cols_below = [sum(self.col[:c]) for c in range(n_cols + 1)]
        #: cells in rows < r
        self.rows_below = [(1 << (r * self.stride)) - 1 for r in range(n_rows + 1)]
        nbits_r = max(1, (n_rows - 1).bit_length())
        nbits_c = max(1, (n_cols - 1).bit_length())
        self.row_planes = [
            sum(self.row_bits << (r * self.stride) for r in range(n_rows) if r >> b & 1)
            for b in range(nbits_r)
        ]
        self.col_planes = [sum(self.col[c] for c in range(n_cols) if c >> b & 1) for b in range(nbits_c)]

    # -- cells <-> bits
    def bit(self, r: int, c: int) -> int:
        return 1 << (r * self.stride + c)

    def mask(self, cells: Iterable[Cell]) -> int:
        m = 0
        for r, c in cells:
            m |= self.bit(r, c)
        return m

    def cells(self, mask: int) -> list[Cell]:
        out = []
        while mask:
            low = mask & -mask
            i = low.bit_length() - 1
            out.append(divmod(i, self.stride))
            mask ^= low
        return out

    # -- geometry
    def row_span(self, mask: int) -> tuple[int, int]:
        return ((mask & -mask).bit_length() - 1) // self.stride, (mask.bit_length() - 1) // self.stride

    def col_span(self, mask: int) -> tuple[int, int]:
        r0, r1 = self.row_span(mask)
        fold = 0
        for r in range(r0, r1 + 1):
            fold |= mask >> (r * self.stride)
        fold &= self.row_bits
        return (fold & -fold).bit_length() - 1, fold.bit_length() - 1

    def sums(self, mask: int) -> tuple[int, int, int]:
        """(number of cells, sum of rows, sum of cols)."""
        n = mask.bit_count()
        sr = sum((mask & p).bit_count() << b for b, p in enumerate(self.row_planes))
        sc = sum((mask & p).bit_count() << b for b, p in enumerate(self.col_planes))
        return n, sr, sc

    def rows_le(self, r: int) -> int:
        return self.rows_below[min(max(r + 1, 0), self.n_rows)]

    def cols_le(self, c: int) -> int:
        return self.cols_below[min(max(c + 1, 0), self.n_cols)]

    def shift(self, mask: int, d_row: int, d_col: int) -> int:
        s = d_row * self.stride + d_col
        return mask << s if s >= 0 else mask >> -s

    def row_line_components(self, mask: int) -> list[tuple[int, list[int], list[int]]]:
        """For every line between rows r-1 | r inside the mask's rows: (r, parts above, parts below).

        Two sweeps (top-down, bottom-up) give all lines at the cost of two component searches.
        """
        r0, r1 = self.row_span(mask)
        down = self._sweep(mask, range(r0, r1 + 1))
        up = self._sweep(mask, range(r1, r0 - 1, -1))
        return [(r, down[r - 1 - r0], up[r1 - r]) for r in range(r0 + 1, r1 + 1)]

    def _sweep(self, mask: int, rows: range) -> list[list[int]]:
        """Components of the rows seen so far, after each row of `rows` (row runs joined when they
        overlap a run of the previous row; union-find with the newest run as the root)."""
        parent: list[int] = []
        comp: list[int] = []
        roots: dict[int, int] = {}
        prev: list[tuple[int, int]] = []  # (run bits in row coordinates, run id) of the previous row
        snapshots = []
        for r in rows:
            shift = r * self.stride
            bits = (mask >> shift) & self.row_bits
            cur = []
            j = 0
            for run in _runs(bits):
                rid = len(parent)
                parent.append(rid)
                comp.append(run << shift)
                roots[rid] = 0
                low = run & -run
                while j < len(prev) and prev[j][0] < low and not prev[j][0] & run:
                    j += 1  # runs that end left of this run cannot touch it or the later ones
                k = j
                while k < len(prev) and prev[k][0] & run:
                    a = prev[k][1]
                    while parent[a] != a:
                        a = parent[a]
                    if a != rid:
                        parent[a] = rid
                        comp[rid] |= comp[a]
                        del roots[a]
                    k += 1
                cur.append((run, rid))
            prev = cur
            snapshots.append([comp[i] for i in roots])
        return snapshots

    def transpose_to(self, mask: int, other: "CellMasks") -> int:
        """The same cells in `other`, a grid with rows and columns swapped."""
        out = 0
        while mask:
            low = mask & -mask
            r, c = divmod(low.bit_length() - 1, self.stride)
            out |= other.bit(c, r)
            mask ^= low
        return out

    def box(self, mask: int) -> int:
        """All grid cells of the mask's bounding box."""
        r0, r1 = self.row_span(mask)
        c0, c1 = self.col_span(mask)
        rows = self.rows_below[r1 + 1] & ~self.rows_below[r0]
        return rows & self.cols_below[c1 + 1] & ~self.cols_below[c0]


def _last_int_below(total: int, n: int, off: Fraction) -> int:
    """Largest integer v with n*v < total + n*off (exact)."""
    t = total * off.denominator + n * off.numerator
    return (t - 1) // (n * off.denominator)


def _first_int_above(total: int, n: int, off: Fraction) -> int:
    """Smallest integer v with n*v > total + n*off (exact)."""
    t = total * off.denominator + n * off.numerator
    return t // (n * off.denominator) + 1


class FlyabilityChecker:
    """Memoised four-quadrant test on cell bitmasks of one structure with fixed health.

    `unit_at` maps each occupied layout cell to the unit sitting there (the current allocation).
    """

    def __init__(
        self,
        grid: CellMasks,
        model: AssemblyModel,
        health: np.ndarray,
        unit_at: dict[Cell, int],
        rule: FlyabilityRule = FlyabilityRule(),
    ):
        self.grid = grid
        self.rule = rule
        offsets = rotor_offsets_cells(model)
        self.working = [0] * ROTORS_PER_UNIT  # cells whose rotor k works
        self.faulty = 0
        for cell, uid in unit_at.items():
            b = grid.bit(*cell)
            h = health[uid - 1]
            for k in range(ROTORS_PER_UNIT):
                if h[k] > rule.working_threshold:
                    self.working[k] |= b
            if np.any(h < rule.faulty_below):
                self.faulty |= b
        # x = -row, so "x_rotor > cx" is a condition on rows from above, and vice versa
        self.row_off = [-ox for ox, _ in offsets]  # x offset expressed along +row
        self.col_off = [oy for _, oy in offsets]
        self._vehicle = model.vehicle
        self._health = health
        self._unit_at = unit_at
        self._cache: dict[int, bool] = {}

    def __call__(self, mask: int) -> bool:
        hit = self._cache.get(mask)
        if hit is None:
            hit = self._cache[mask] = self._check(mask)
        return hit

    def _check(self, mask: int) -> bool:
        if not self._quadrants(mask):
            return False
        return self.rule.hover_thrust_limits_n is None or self._hovers(mask)

    def _hovers(self, mask: int) -> bool:
        """Exact hover LP of the piece (its own model, rotor healths in its row-major slot order)."""
        from mars_link.allocation import check_controllable
        from mars_link.core.errors import UserInputError

        cells = sorted(self.grid.cells(mask))
        r0, c0 = min(r for r, _ in cells), min(c for _, c in cells)
        rows = max(r for r, _ in cells) - r0 + 1
        cols = max(c for _, c in cells) - c0 + 1
        occupied = {(r - r0, c - c0) for r, c in cells}
        layout = tuple("".join("X" if (r, c) in occupied else "." for c in range(cols)) for r in range(rows))
        piece = AssemblyModel.from_layout(layout, self._vehicle)
        eta = np.concatenate([self._health[self._unit_at[c] - 1] for c in cells])
        try:
            check_controllable(piece, eta, self.rule.hover_thrust_limits_n)
        except UserInputError:
            return False
        return True

    def _quadrants(self, mask: int) -> bool:
        g = self.grid
        n, sr, sc = g.sums(mask)
        if n == 1:
            return not mask & self.faulty
        found = [False] * 4  # quadrants (front, right) as index 2*front + right
        for k in range(ROTORS_PER_UNIT):
            cand = mask & self.working[k]
            if not cand:
                continue
            ro, co = self.row_off[k], self.col_off[k]
            # rotor row coordinate = row + ro; front of the CoM iff n*(row + ro) < sr
            front = g.rows_le(_last_int_below(sr, n, -ro))
            rear = ~g.rows_le(_first_int_above(sr, n, -ro) - 1)
            right = ~g.cols_le(_first_int_above(sc, n, -co) - 1)
            left = g.cols_le(_last_int_below(sc, n, -co))
            for q, (xm, ym) in enumerate(((rear, left), (rear, right), (front, left), (front, right))):
                if not found[q] and cand & xm & ym:
                    found[q] = True
            if all(found):
                return True
        return False
