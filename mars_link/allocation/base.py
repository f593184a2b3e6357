"""Allocator interface, in the spirit of PX4's control_allocation library.

Geometry lives in `AssemblyModel.effectiveness()` (one place); an allocator takes that matrix,
rotor efficiencies (eta) and thrust bounds, and maps a wrench demand (thrust_n, L, M, N) to
per-rotor thrusts in newtons.
"""

from __future__ import annotations

import numpy as np

from mars_link.core.assembly import AssemblyModel


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
        self.available: np.ndarray | None = None  # per rotor: the fraction of max_thrust_n its pack allows
        self.eta = model.nominal_eta() if eta is None else np.asarray(eta, dtype=float).copy()
        self.set_eta(self.eta)

    def set_eta(self, eta: np.ndarray) -> None:
        """Switch to a new fault set (rotor efficiencies); subclasses precompute here."""
        self.eta = np.asarray(eta, dtype=float).copy()

    def set_available(self, available: np.ndarray | None) -> None:
        """Each rotor's share of `max_thrust_n` that its unit's battery still gives (None: all of it); the
        upper bounds follow it, and the same precomputation as a fault set change runs."""
        self.available = None if available is None else np.clip(np.asarray(available, dtype=float), 0.0, 1.0)
        self.set_eta(self.eta)

    def upper_bounds(self) -> np.ndarray:
        """Per-rotor upper thrust bounds (N): max_thrust_n times what the packs allow (inf: unbounded)."""
        n = self.model.n_rotors
        if self.max_thrust_n is None:
            return np.full(n, np.inf)
        return self.max_thrust_n * (np.ones(n) if self.available is None else self.available)

    def allocate(self, wrench: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError
