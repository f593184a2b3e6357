"""The geometry of one rigid piece of a flight of pieces: which unit sits in which cell, its model, its CoM,
and its rotors' efficiencies in the piece model's slot order. Below the executor (execution), the margin
(margin) and the re-plan (replan), which all use it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mars_link.core.assembly import AssemblyModel, VehicleParams, layout_of_cells
from mars_link.reconfig.flyability import Cell

Key = frozenset


@dataclass
class PieceShape:
    """Which unit sits in which cell of a piece (cells in any frame: only differences matter)."""

    cells: dict[int, Cell]

    @property
    def key(self) -> Key:
        return frozenset(self.cells)

    def units_local_order(self) -> list[int]:
        """Global unit ids in the piece model's row-major order (= local ids 1..k)."""
        return sorted(self.cells, key=lambda u: self.cells[u])

    def layout(self) -> tuple[str, ...]:
        return layout_of_cells(self.cells.values())

    def model(self, vehicle: VehicleParams) -> AssemblyModel:
        return AssemblyModel.from_layout(self.layout(), vehicle)

    def com_frd(self, pitch_m: float) -> np.ndarray:
        """CoM in the cells' frame, FRD (row -> -x, column -> +y), identical units."""
        cells = np.array(list(self.cells.values()), dtype=float)
        return np.array([-cells[:, 0].mean() * pitch_m, cells[:, 1].mean() * pitch_m, 0.0])

    def subset(self, units) -> "PieceShape":
        return PieceShape({u: self.cells[u] for u in units})


def local_eta(shape: PieceShape, eta_global: dict[int, np.ndarray]) -> np.ndarray:
    """Per-rotor efficiencies in the piece model's slot order."""
    return np.concatenate([eta_global[u] for u in shape.units_local_order()])
