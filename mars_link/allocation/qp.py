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
  when it fits the bounds (always for an unbounded allocator);
* a bound active: yaw gets only what remains (`allocate`), in two exact solves by a primal
  active-set method (`box_qp_active_set`): first thrust, roll and pitch alone (the same weights and
  variance term, the yaw row left out), started from their own unbounded optimum clipped to the
  bounds (a better seed than OSQP's answer, measured), then the yaw row and the variance term with
  the first solve's thrust, roll and pitch held as equalities; only if the first does not settle
  does OSQP (warm-started, the weighted objective above) answer.

Why two solves and not the weights alone: a weight is a price, and a yaw demand the rotors cannot meet
buys thrust with it. W prices 1 N·m of missed yaw on the paper 3x2 like 11.7 N of missed thrust, and a
rotor at its bound trades k_q N·m of yaw per newton, so the weighted optimum gave up 1.17 N of collective
per N·m of yaw it could not make (a dead corner unit in wind asks for more than 1 N·m). PX4's sequential
desaturation likewise mixes yaw last and desaturates it along its own column only (mixYaw in
src/modules/control_allocator/ControlAllocation/ControlAllocationSequentialDesaturation.cpp).
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
        spread = lam * (np.diag(dl**2) - np.outer(dl, dl) / n)
        self._hess = bl.T @ (w[:, None] * bl) + spread
        self._bw = bl.T * w
        # saturated: thrust, roll, pitch first (yaw row left out), then yaw with those held (module docstring)
        w_first = w * np.array([1.0, 1.0, 1.0, 0.0])
        self._hess_first = bl.T @ (w_first[:, None] * bl) + spread
        self._bw_first = bl.T * w_first
        self._hess_yaw = w[3] * np.outer(bl[3], bl[3]) + spread
        self._bw_yaw = w[3] * bl[3]
        self._held_rows = bl[:3]
        # resolves 0.1 % of a hover thrust in the variance term's gradient 2 lam (t - mean)
        self._grad_tol = 1e-3 * lam * m.hover_thrust_per_rotor_n()
        self._gain = np.zeros((n, 4))
        self._gain_first = np.zeros((k, 4))
        if k:
            self._gain[alive] = np.linalg.solve(self._hess, self._bw)
            self._gain_first = np.linalg.solve(self._hess_first, self._bw_first)

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        w = np.asarray(wrench, dtype=float)
        if np.isfinite(w).all():
            t = self._gain @ w
            if np.all((t >= self._lo) & (t <= self._hi)):
                return t
            self.saturated += 1
            live = self._live
            lo, hi, k = self._lo[live], self._hi[live], int(live.sum())
            x, done = box_qp_active_set(
                self._hess_first, self._bw_first @ w, self._gain_first @ w, lo, hi, k, self._grad_tol,
            )
            if done:  # yaw with what remains: any answer of the second solve keeps the first's rows and bounds
                t[live], _ = box_qp_active_set(
                    self._hess_yaw, self._bw_yaw * w[3], x, lo, hi, 2 * k, self._grad_tol, held_rows=self._held_rows,
                )
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
    grad_tol: float, held_rows: np.ndarray | None = None,
) -> tuple[np.ndarray, bool]:
    """Exact minimiser of x'Hx/2 - g'x over lo <= x <= hi (H positive definite) by a primal
    active-set method: one bound held or released per step, so it cannot cycle. Starts at the
    feasible point clip(x) with the bounds it touches held; a held bound is released when the
    gradient pulls away from it by more than grad_tol. `held_rows` A: also keep A x at its value at
    the start (each step moves the free variables within A's null space; the bounds are judged on
    the gradient plus A' times the equalities' multipliers). The objective never rises from the start,
    so x is feasible and no worse whatever happens. Returns (x, converged)."""
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    x = np.clip(x, lo, hi)
    at_lo = x <= lo + 1e-6 * span
    at_hi = ~at_lo & (x >= hi - 1e-6 * span)
    x = np.where(at_lo, lo, np.where(at_hi, hi, x))
    for _ in range(max_steps + 1):
        grad = h @ x - g
        free = np.flatnonzero(~(at_lo | at_hi))
        nu = None
        if free.size:
            xf = x[free]
            if held_rows is None:
                d = np.linalg.solve(h[free[:, None], free], -grad[free])  # to the optimum over the free
            else:
                d, nu = _equality_step(h[free[:, None], free], held_rows[:, free], grad[free])
                if d is None:
                    return x, False
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
        if held_rows is not None:  # the bounds see the gradient the equalities leave
            if nu is None:  # nothing free: least-squares multipliers
                nu = np.linalg.lstsq(held_rows.T, -grad, rcond=None)[0]
            grad = grad + held_rows.T @ nu
        # optimal when the gradient is >= 0 at every held lower bound and <= 0 at every upper one
        pull = np.where(at_lo, -grad, np.where(at_hi, grad, 0.0))
        k = int(np.argmax(pull))
        if pull[k] <= grad_tol:
            return x, True
        at_lo[k] = at_hi[k] = False  # release the bound that holds the optimum back most
    return x, False


def _equality_step(h: np.ndarray, a: np.ndarray, grad: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """The step d to the optimum over the free variables with a d = 0, and the equalities' multipliers
    (the KKT system; least squares, minimum-norm multipliers, when a's free columns do not span its rows)."""
    nf, m = a.shape[1], a.shape[0]
    kkt = np.zeros((nf + m, nf + m))
    kkt[:nf, :nf], kkt[:nf, nf:], kkt[nf:, :nf] = h, a.T, a
    rhs = np.zeros(nf + m)
    rhs[:nf] = -grad
    gram = a @ a.T
    try:  # the rows independent on the free columns (a well-conditioned Gram): the exact solve
        chol = np.diag(np.linalg.cholesky(gram))
        spans = nf >= m and chol.min() ** 2 > 1e-12 * np.trace(gram)
    except np.linalg.LinAlgError:
        spans = False
    sol = np.linalg.solve(kkt, rhs) if spans else np.linalg.lstsq(kkt, rhs, rcond=None)[0]
    if not np.all(np.isfinite(sol)):
        return None, np.zeros(m)
    return sol[:nf], sol[nf:]
