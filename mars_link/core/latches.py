"""Docking latches: one per side of every unit, as the world models them and the units sense them.

A unit has four latches, one per side, numbered as bits of a mask: bit 0 front (+x, FRD), bit 1 right
(+y), bit 2 back (-x), bit 3 left (-y). In the layout's cells (row -> -x, column -> +y) the neighbour
across side k sits at `cell + SIDE_STEPS[k]`.

Each latch has a setpoint from its unit (the coordinator's command, carried with the rotor commands):
set = engage (hold a closed latch, close on contact), clear = open. A link between two touching units
holds while both latches are set; opening either one releases it (a split). Two free bodies latch
when a pair of facing units, both set, come within the docking tolerance (a dock). What a unit reports
(its latch sensor) is the mask of its sides that hold a link: that is how the coordinator learns the
topology, never from the world's truth.
"""

from __future__ import annotations

from typing import Iterable

from mars_link.core.messages import LATCH_ALL

#: cell step (row, column) to the neighbour across each side: front, right, back, left
SIDE_STEPS: tuple[tuple[int, int], ...] = ((-1, 0), (0, 1), (1, 0), (0, -1))
SIDE_NAMES = ("front", "right", "back", "left")
ALL_SIDES = LATCH_ALL

Cell = tuple[int, int]
Link = frozenset  # {unit_a, unit_b}


def side_toward(cell_from: Cell, cell_to: Cell) -> int | None:
    """Which side of the unit at `cell_from` faces the unit at `cell_to` (None: not neighbours)."""
    step = (cell_to[0] - cell_from[0], cell_to[1] - cell_from[1])
    return SIDE_STEPS.index(step) if step in SIDE_STEPS else None


def opposite(side: int) -> int:
    return (side + 2) % 4


def neighbour_links(cells: dict[int, Cell]) -> dict[Link, tuple[int, int]]:
    """Every pair of neighbouring units in `cells` -> (side of the smaller id, side of the larger id)."""
    at = {c: u for u, c in cells.items()}
    links = {}
    for u, c in cells.items():
        for k, (dr, dc) in enumerate(SIDE_STEPS):
            v = at.get((c[0] + dr, c[1] + dc))
            if v is not None and u < v:
                links[Link((u, v))] = (k, opposite(k))
    return links


def components(units: Iterable[int], links: Iterable[Link]) -> list[set[int]]:
    """Connected groups of `units` joined by `links`."""
    parent = {u: u for u in units}

    def root(u: int) -> int:
        while parent[u] != u:
            parent[u] = parent[parent[u]]
            u = parent[u]
        return u

    for link in links:
        a, b = tuple(link)
        if a in parent and b in parent:
            parent[root(a)] = root(b)
    groups: dict[int, set[int]] = {}
    for u in parent:
        groups.setdefault(root(u), set()).add(u)
    return sorted(groups.values(), key=min)


class LatchBoard:
    """Every unit's latch setpoints and the links that hold (the world's side of the latches)."""

    def __init__(self, unit_ids: Iterable[int]) -> None:
        self.setpoint: dict[int, int] = {u: ALL_SIDES for u in unit_ids}  # engaged unless commanded open
        self.links: dict[Link, tuple[int, int]] = {}  # link -> (side of min unit, side of max unit)
        self._mask: dict[int, int] = dict.fromkeys(self.setpoint, 0)

    def add(self, links: dict[Link, tuple[int, int]]) -> None:
        self.links.update(links)
        self._remask()

    def mask(self, unit_id: int) -> int:
        """The unit's latch sensor: bit k set when side k holds a link."""
        return self._mask[unit_id]

    def command(self, unit_id: int, setpoint: int) -> list[Link]:
        """A unit drives its latches to `setpoint`; returns the links that open."""
        setpoint &= ALL_SIDES
        if self.setpoint.get(unit_id, setpoint) == setpoint:
            return []
        self.setpoint[unit_id] = setpoint
        opened = []
        for link, sides in self.links.items():
            if unit_id in link:
                side = sides[0] if unit_id == min(link) else sides[1]
                if not setpoint >> side & 1:
                    opened.append(link)
        for link in opened:
            del self.links[link]
        if opened:
            self._remask()
        return opened

    def engaged(self, unit_id: int, side: int) -> bool:
        return bool(self.setpoint[unit_id] >> side & 1)

    def _remask(self) -> None:
        self._mask = dict.fromkeys(self.setpoint, 0)
        for link, sides in self.links.items():
            a, b = sorted(link)
            self._mask[a] |= 1 << sides[0]
            self._mask[b] |= 1 << sides[1]
