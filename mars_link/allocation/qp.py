"""Constrained allocation over all rotor thrusts with OSQP (specs/dependencies.md §4).

    minimise  ||W^1/2 (B(eta) t - w)||^2 + lambda * sum_i (t_i - mean t)^2     s.t.  lo <= t <= hi

with dead rotors pinned at 0. Priorities roll/pitch > thrust > yaw come from W (`row_weights`);
the variance term (eq. 1's minimum-variance idea) only picks among equally good answers, so it is
kept orders of magnitude below the yaw weight.

Written sparse so one ADMM iteration is O(rotors), not O(rotors^2): the weighted residual e and the
mean mu are variables,

    x = [t, mu, e],   minimise e'e + lambda * ||t - mu 1||^2,   W^1/2 B t - e = W^1/2 w,

(minimising over mu gives exactly the variance). Per call only the equality bounds change. Set up
once per fault set, warm-started; the redistributed pseudo-inverse takes over if OSQP does not
solve (or raises).
"""

from __future__ import annotations

import numpy as np
import osqp
import scipy.sparse as sp

from mars_link.allocation.base import Allocator
from mars_link.allocation.modes import RedistributedPseudoInverse, row_weights

#: variance weight relative to what producing a yaw moment by rotor differentials costs in the
#: yaw row: small enough not to bias any wrench axis, large enough to make the optimum unique
VARIANCE_WEIGHT = 1e-4
SETTINGS = dict(
    verbose=False, warm_starting=True, polishing=False, eps_abs=1e-6, eps_rel=1e-6,
    max_iter=400, check_termination=10,
)
_OK = (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE)


class QpAllocator(Allocator):
    name = "qp"

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        m = self.model
        b = m.effectiveness(self.eta)
        n = b.shape[1]
        w = row_weights(m)
        self._sqrt_w = np.sqrt(w)
        kq = m.vehicle.yaw_moment_per_thrust_m
        lam = VARIANCE_WEIGHT * w[3] * kq**2 * n
        idx = np.arange(n)
        # upper-triangular P over x = [t (n), mu, e (4)]
        rows = np.concatenate([idx, idx, [n], n + 1 + np.arange(4)])
        cols = np.concatenate([idx, np.full(n, n), [n], n + 1 + np.arange(4)])
        vals = np.concatenate([np.full(n, 2 * lam), np.full(n, -2 * lam), [2 * lam * n], np.full(4, 2.0)])
        p = sp.csc_matrix((vals, (rows, cols)), shape=(n + 5, n + 5))
        a = sp.vstack([
            sp.hstack([sp.identity(n), sp.csc_matrix((n, 5))]),
            sp.hstack([sp.csc_matrix(self._sqrt_w[:, None] * b), sp.csc_matrix((4, 1)), -sp.identity(4)]),
        ], format="csc")
        alive = self.eta > 0.0
        lo = -np.inf if self.min_thrust_n is None else self.min_thrust_n
        hi = np.inf if self.max_thrust_n is None else self.max_thrust_n
        self._n = n
        self._b = b
        self._l = np.concatenate([np.where(alive, lo, 0.0), np.zeros(4)])
        self._u = np.concatenate([np.where(alive, hi, 0.0), np.zeros(4)])
        self._lo, self._hi = self._l[:n].copy(), self._u[:n].copy()
        self._solver = osqp.OSQP()
        self._solver.setup(p, np.zeros(n + 5), a, self._l, self._u, **SETTINGS)
        self._fallback = RedistributedPseudoInverse(m, self.eta, self.min_thrust_n, self.max_thrust_n)
        self.fallbacks = 0  # calls where OSQP did not solve since the last set_eta

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        w = np.asarray(wrench, dtype=float)
        try:
            if not np.all(np.isfinite(w)):
                raise ValueError("non-finite demand")
            target = self._sqrt_w * w
            self._l[self._n:] = target
            self._u[self._n:] = target
            self._solver.update(l=self._l, u=self._u)
            res = self._solver.solve(raise_error=False)
            x = res.x
            if x is not None and np.all(np.isfinite(x)):
                t = np.minimum(np.maximum(x[: self._n], self._lo), self._hi)  # ADMM overshoots ~1e-5
                if res.info.status_val in _OK:
                    return t
                # not converged (hard saturation, e.g. iteration cap): the iterate is usually far
                # better than the greedy fallback, so keep whichever meets the weighted demand best
                self.fallbacks += 1
                alt = self._fallback.allocate(w)
                return t if self._cost(t, target) <= self._cost(alt, target) else alt
        except Exception:  # noqa: BLE001 - the hot path must answer; the oracle does
            pass
        self.fallbacks += 1
        return self._fallback.allocate(w)

    def _cost(self, t: np.ndarray, target: np.ndarray) -> float:
        r = self._sqrt_w * (self._b @ t) - target
        return float(r @ r)
