"""Nominal allocation: minimum-norm pseudo-inverse of the fault-free effectiveness, then clipping.

This is the "none" FTC mode: it ignores rotor efficiencies on purpose (the baseline that shows
what faults do to an allocator that does not know about them).
"""

from __future__ import annotations

import numpy as np

from mars_link.allocation.base import Allocator


class NominalPseudoInverse(Allocator):
    name = "none"

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        if not hasattr(self, "_pinv"):
            self._pinv = np.linalg.pinv(self.model.effectiveness())

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        thrusts = self._pinv @ np.asarray(wrench, dtype=float)
        if self.min_thrust_n is not None or self.max_thrust_n is not None:
            hi = self.max_thrust_n if self.available is None else self.upper_bounds()
            thrusts = np.clip(thrusts, self.min_thrust_n, hi)
        return thrusts
