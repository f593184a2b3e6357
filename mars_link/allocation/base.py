"""Allocator interface, in the spirit of PX4's control_allocation library.

Geometry lives in `AssemblyModel.effectiveness()` (one place); an allocator takes that matrix,
rotor efficiencies (eta) and thrust bounds, and maps a wrench demand (thrust_n, L, M, N) to
per-rotor thrusts in newtons.
"""

from __future__ import annotations

import numpy as np

from mars_link.assembly import AssemblyModel


class Allocator:
    name = "base"

    def __init__(
        self,
        model: AssemblyModel,
        eta: np.ndarray | None = None,
        min_thrust_n: float | None = None,
        max_thrust_n: float | None = None,
    ) -> None:
        self.model = model
        self.min_thrust_n = min_thrust_n
        self.max_thrust_n = max_thrust_n
        self.eta = model.nominal_eta() if eta is None else np.asarray(eta, dtype=float).copy()
        self.set_eta(self.eta)

    def set_eta(self, eta: np.ndarray) -> None:
        """Switch to a new fault set (rotor efficiencies); subclasses precompute here."""
        self.eta = np.asarray(eta, dtype=float).copy()

    def allocate(self, wrench: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError
