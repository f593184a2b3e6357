"""Constrained allocation over all rotor thrusts with OSQP (specs/dependencies.md §4).

    minimise  ||W^1/2 (B(eta) t - w)||^2 + lambda * t^T (I - 11^T/n) t      subject to lo <= t <= hi

with dead rotors pinned at 0. Priorities roll/pitch > thrust > yaw come from W (rows normalised by
their hover-scale magnitudes), the variance term spreads thrust evenly. Set up once per fault set,
warm-started every call; the redistributed pseudo-inverse takes over if OSQP does not solve.
"""

from __future__ import annotations

import numpy as np
import osqp
import scipy.sparse as sp

from mars_link.allocation.base import Allocator
from mars_link.allocation.modes import RedistributedPseudoInverse, row_weights

VARIANCE_WEIGHT = 1e-4
UNBOUNDED = 1e6  # N: stands for "no limit" (the paper plant) while keeping the problem well scaled


class QpAllocator(Allocator):
    name = "qp"

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        m = self.model
        b = m.effectiveness(self.eta)
        n = b.shape[1]
        self._w = row_weights(m)
        hover = m.hover_thrust_per_rotor_n()
        lam = VARIANCE_WEIGHT * float(self._w[0]) * n
        p = 2.0 * (b.T @ (self._w[:, None] * b) + lam * (np.eye(n) - np.ones((n, n)) / n))
        p += 1e-9 * np.eye(n)
        self._bw = 2.0 * (b.T * self._w)  # q = -bw @ w
        lo = -UNBOUNDED if self.min_thrust_n is None else self.min_thrust_n
        hi = UNBOUNDED if self.max_thrust_n is None else self.max_thrust_n
        alive = self.eta > 0.0
        self._lo = np.where(alive, lo, 0.0)
        self._hi = np.where(alive, hi, 0.0)
        self._solver = osqp.OSQP()
        self._solver.setup(
            sp.csc_matrix(np.triu(p)), np.zeros(n), sp.identity(n, format="csc"), self._lo, self._hi,
            verbose=False, warm_starting=True, polishing=False, eps_abs=1e-6, eps_rel=1e-6,
            max_iter=200, check_termination=25,
        )
        self._fallback = RedistributedPseudoInverse(m, self.eta, self.min_thrust_n, self.max_thrust_n)
        self.fallbacks = 0
        self._hover = hover

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        w = np.asarray(wrench, dtype=float)
        self._solver.update(q=-(self._bw @ w))
        res = self._solver.solve(raise_error=False)
        if res.info.status_val not in (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE) or res.x is None or not np.all(np.isfinite(res.x)):
            self.fallbacks += 1
            return self._fallback.allocate(w)
        return np.clip(res.x, self._lo, self._hi)
