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

The variance weight is so small that ADMM's tolerances cannot resolve it: left alone, OSQP returns
the right wrench but an arbitrary split between rotors (a fresh allocator asked to hover a
nominal 3x2 spread its rotors over 60-110 % of the hover thrust), and that split jumps as a
demand crosses into saturation. So the answer is the exact optimum:
* no bound active: the optimum is linear in w, `gain @ w`, precomputed per fault set; returned
  when it fits the bounds (always for the unbounded paper plant);
* a bound active: a primal active-set method on the same objective (`box_qp_active_set`) starts
  from that optimum clipped to the bounds (a better seed than OSQP's answer, measured) and takes
  at most one step per live rotor; only if it does not settle does OSQP (warm-started) answer.
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
        # the variance is of each rotor's thrust over what its pack allows (d = 1 / available): equal
        # packs give today's equal split, a sagging pack's rotors take a smaller share
        d = np.ones(n) if self.available is None else 1.0 / np.maximum(self.available, 1e-3)
        # upper-triangular P over x = [t (n), mu, e (4)]
        rows = np.concatenate([idx, idx, [n], n + 1 + np.arange(4)])
        cols = np.concatenate([idx, np.full(n, n), [n], n + 1 + np.arange(4)])
        vals = np.concatenate([2 * lam * d**2, -2 * lam * d, [2 * lam * n], np.full(4, 2.0)])
        p = sp.csc_matrix((vals, (rows, cols)), shape=(n + 5, n + 5))
        a = sp.vstack([
            sp.hstack([sp.identity(n), sp.csc_matrix((n, 5))]),
            sp.hstack([sp.csc_matrix(self._sqrt_w[:, None] * b), sp.csc_matrix((4, 1)), -sp.identity(4)]),
        ], format="csc")
        alive = self.eta > 0.0
        lo = -np.inf if self.min_thrust_n is None else self.min_thrust_n
        hi = self.upper_bounds()
        self._n = n
        self._b = b
        self._l = np.concatenate([np.where(alive, lo, 0.0), np.zeros(4)])
        self._u = np.concatenate([np.where(alive, hi, 0.0), np.zeros(4)])
        self._lo, self._hi = self._l[:n].copy(), self._u[:n].copy()
        self._solver = osqp.OSQP()
        self._solver.setup(p, np.zeros(n + 5), a, self._l, self._u, **SETTINGS)
        self._fallback = RedistributedPseudoInverse(m, self.eta, self.min_thrust_n, self.max_thrust_n)
        if self.available is not None:
            self._fallback.set_available(self.available)
        self.fallbacks = 0  # calls where OSQP did not solve since the last set_eta
        self.saturated = 0  # calls with some bound active at the unconstrained optimum
        self.solves = 0  # of those, calls the active-set method left to OSQP
        # the same objective over the live rotors, dense, for the exact paths
        self._live = alive
        bl = b[:, alive]
        k = bl.shape[1]
        dl = d[alive]
        self._hess = bl.T @ (w[:, None] * bl) + lam * (np.diag(dl**2) - np.outer(dl, dl) / n)
        self._bw = bl.T * w
        # resolves 0.1 % of a hover thrust in the variance term's gradient 2 lam (t - mean)
        self._grad_tol = 1e-3 * lam * m.hover_thrust_per_rotor_n()
        self._gain = np.zeros((n, 4))
        if k:
            self._gain[alive] = np.linalg.solve(self._hess, self._bw)

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        w = np.asarray(wrench, dtype=float)
        if np.isfinite(w).all():
            t = self._gain @ w
            if np.all((t >= self._lo) & (t <= self._hi)):
                return t
            self.saturated += 1
            live = self._live
            x, done = box_qp_active_set(
                self._hess, self._bw @ w, t[live], self._lo[live], self._hi[live], int(live.sum()),
                self._grad_tol,
            )
            if done:
                t[live] = x
                return t
            self.solves += 1
        return self._solve(w)

    def _solve(self, wrench: np.ndarray) -> np.ndarray:
        """OSQP on the sparse form; the fallback when it does not solve (or raises)."""
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


def box_qp_active_set(
    h: np.ndarray, g: np.ndarray, x: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_steps: int,
    grad_tol: float,
) -> tuple[np.ndarray, bool]:
    """Exact minimiser of x'Hx/2 - g'x over lo <= x <= hi (H positive definite) by a primal
    active-set method: one bound held or released per step, so it cannot cycle. Starts at the
    feasible point clip(x) with the bounds it touches held; a held bound is released when the
    gradient pulls away from it by more than grad_tol. Returns (x, converged)."""
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    x = np.clip(x, lo, hi)
    at_lo = x <= lo + 1e-6 * span
    at_hi = ~at_lo & (x >= hi - 1e-6 * span)
    x = np.where(at_lo, lo, np.where(at_hi, hi, x))
    for _ in range(max_steps + 1):
        grad = h @ x - g
        free = np.flatnonzero(~(at_lo | at_hi))
        if free.size:
            xf = x[free]
            d = np.linalg.solve(h[free[:, None], free], -grad[free])  # to the optimum over the free
            new = xf + d
            above, below = new > hi[free], new < lo[free]
            if above.any() or below.any():  # a free rotor reaches its bound first: hold it there
                frac = np.full(free.size, np.inf)
                frac[above] = (hi[free][above] - xf[above]) / d[above]
                frac[below] = (lo[free][below] - xf[below]) / d[below]
                i = int(np.argmin(frac))
                x[free] = xf + max(float(frac[i]), 0.0) * d
                j = free[i]
                if above[i]:
                    at_hi[j], x[j] = True, hi[j]
                else:
                    at_lo[j], x[j] = True, lo[j]
                continue
            x[free] = new
            grad = h @ x - g
        # optimal when the gradient is >= 0 at every held lower bound and <= 0 at every upper one
        pull = np.where(at_lo, -grad, np.where(at_hi, grad, 0.0))
        k = int(np.argmax(pull))
        if pull[k] <= grad_tol:
            return x, True
        at_lo[k] = at_hi[k] = False  # release the bound that holds the optimum back most
    return x, False
