"""MINCO s = 3 (minimum jerk) in numpy: quintic pieces through waypoints q with durations T.

For fixed head/tail position-velocity-acceleration, waypoints q (N-1 of them) and durations T (N),
the jerk-optimal spline is C4 at the knots (snap continuous) and its coefficients c (6N x D) are the
solution of one banded 6N x 6N system A(T) c = b(q) (specs/planning.md §2.5, §6.5; Wang et al.,
T-RO 2022). Rows, per interior knot i: jerk and snap continuity, p_i(T_i) = q_i, then position,
velocity and acceleration continuity; head and tail PVA take 3 rows each. With this order every row
touches at most 6 columns either side of the diagonal, so one banded LU (LAPACK gbtrf) serves the
forward solve and the adjoint solve A^T lambda = dJ/dc that maps a cost gradient on c to q and T:
dJ/dq_i = lambda at knot i's position row, dJ/dT_i = explicit - lambda^T (dA/dT_i) c.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

BAND = 6  # lower = upper bandwidth of A
_FACT = np.array([[1, 1, 1, 1, 1, 1], [0, 1, 2, 3, 4, 5], [0, 0, 2, 6, 12, 20],
                  [0, 0, 0, 6, 24, 60], [0, 0, 0, 0, 24, 120], [0, 0, 0, 0, 0, 120]], dtype=float)


def bases(t: np.ndarray, orders: int) -> np.ndarray:
    """(orders, ..., 6): derivatives 0 .. orders-1 of [1, t, ..., t^5] at local times t."""
    t = np.asarray(t, dtype=float)
    pw = np.empty(t.shape + (6,))
    pw[..., 0] = 1.0
    for j in range(1, 6):
        pw[..., j] = pw[..., j - 1] * t
    out = np.zeros((orders,) + t.shape + (6,))
    for o in range(orders):
        out[o, ..., o:] = _FACT[o, o:] * pw[..., :6 - o]
    return out


def basis(t: np.ndarray, order: int) -> np.ndarray:
    """(..., 6) d^order/dt^order of [1, t, ..., t^5] at local times t."""
    return bases(t, order + 1)[order]


@dataclass
class MincoSpline:
    """Coefficients of a solved MINCO spline; `evaluate` gives exact derivatives at global time."""

    coeffs: np.ndarray  # (N, 6, D): piece i, power j, dimension
    durations_s: np.ndarray  # (N,)

    @property
    def duration_s(self) -> float:
        return float(self.durations_s.sum())

    @property
    def knots_s(self) -> np.ndarray:
        return np.concatenate([[0.0], np.cumsum(self.durations_s)])

    def locate(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Piece index and local time of global times (clamped to [0, duration])."""
        t = np.clip(np.asarray(t_s, dtype=float), 0.0, self.duration_s)
        knots = self.knots_s
        idx = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(self.durations_s) - 1)
        return idx, t - knots[idx]

    def evaluate(self, t_s, order: int = 0) -> np.ndarray:
        """(S, D) derivative `order` at global times (the SmoothedPath interface)."""
        scalar = np.ndim(t_s) == 0
        idx, tau = self.locate(np.atleast_1d(t_s))
        out = np.einsum("sj,sjd->sd", basis(tau, order), self.coeffs[idx])
        return out[0] if scalar else out


class Minco:
    """MINCO s = 3 with fixed head/tail PVA ((3, D) each). `solve(q, T)` fills coefficients;
    `grad(dc, dT)` turns gradients w.r.t. (c, T) into gradients w.r.t. (q, T)."""

    def __init__(self, head_pva: np.ndarray, tail_pva: np.ndarray):
        self.head = np.asarray(head_pva, dtype=float)
        self.tail = np.asarray(tail_pva, dtype=float)
        self.dim = self.head.shape[1]

    # ------------------------------------------------------------------ forward
    def solve(self, q: np.ndarray, durations_s: np.ndarray) -> MincoSpline:
        q = np.asarray(q, dtype=float).reshape(-1, self.dim)
        T = np.asarray(durations_s, dtype=float)
        n = len(T)
        if len(q) != n - 1:
            raise ValueError(f"{n} pieces need {n - 1} waypoints, got {len(q)}")
        self.n, self.T = n, T
        rows, cols, vals = self._entries(T)
        m = 6 * n
        ab = np.zeros((3 * BAND + 1, m))
        ab[2 * BAND + rows - cols, cols] = vals
        lu, piv, info = lapack.dgbtrf(ab, BAND, BAND)
        if info != 0:
            raise np.linalg.LinAlgError(f"MINCO system singular (dgbtrf info {info})")
        self._lu, self._piv = lu, piv
        b = np.zeros((m, self.dim))
        b[0:3] = self.head
        b[6 * np.arange(n - 1) + 5] = q
        b[m - 3:] = self.tail
        c, info = lapack.dgbtrs(lu, BAND, BAND, b, piv)
        self.c = c
        self.spline = MincoSpline(c.reshape(n, 6, self.dim), T.copy())
        return self.spline

    def _entries(self, T: np.ndarray):
        """Triplets (row, col, value) of A(T); the pattern is built once per piece count."""
        n = len(T)
        if getattr(self, "_pattern_n", None) != n:
            self._pattern(n)
        b_end = bases(T, 5)  # (5, N, 6) at the end of every piece
        knot = b_end[:, :-1][list(self._knot_orders)]  # (6, N-1, 6): rows jerk, snap, q, p, v, a
        vals = np.concatenate([self._head_vals, np.transpose(knot, (1, 0, 2)).ravel(), self._cont_vals,
                               b_end[:3, -1].ravel()])
        return self._rows, self._cols, vals[self._in_band]

    _knot_orders = (3, 4, 0, 0, 1, 2)

    def _pattern(self, n: int) -> None:
        """Row/column indices of A for n pieces (values at T filled by `_entries`)."""
        six = np.arange(6)
        b0 = bases(np.zeros(1), 5)[:, 0]  # (5, 6) at t = 0
        rows = [np.repeat(np.arange(3), 6)]
        cols = [np.tile(six, 3)]
        self._head_vals = b0[:3].ravel()
        i = np.arange(n - 1)
        # piece i's end, rows 6i+3 .. 6i+8 (order of _knot_orders), in (knot, row, coeff) order
        rows.append(np.repeat((6 * i[:, None] + 3 + six[None, :]).ravel(), 6))
        cols.append(np.broadcast_to(6 * i[:, None, None] + six[None, None, :], (n - 1, 6, 6)).ravel())
        # piece i+1's start (minus): jerk, snap rows and the three continuity rows
        cont_rows, cont_orders = (0, 1, 3, 4, 5), (3, 4, 0, 1, 2)
        r = 6 * i[:, None] + 3 + np.array(cont_rows)[None, :]
        rows.append(np.repeat(r.ravel(), 6))
        cols.append(np.broadcast_to(6 * (i[:, None, None] + 1) + six[None, None, :], (n - 1, 5, 6)).ravel())
        self._cont_vals = np.tile(-b0[list(cont_orders)].ravel(), n - 1)
        rows.append(np.repeat(6 * n - 3 + np.arange(3), 6))
        cols.append(np.tile(6 * (n - 1) + six, 3))
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        self._in_band = np.abs(rows - cols) <= BAND  # the rest are structural zeros
        self._rows, self._cols = rows[self._in_band], cols[self._in_band]
        self._pattern_n = n

    # ------------------------------------------------------------------ energy
    def jerk_energy(self, weights: np.ndarray | None = None) -> tuple[float, np.ndarray, np.ndarray]:
        """sum_i int ||w * jerk||^2 dt and its partials w.r.t. c (6N x D) and T (N)."""
        c = self.c.reshape(self.n, 6, self.dim)
        w = np.ones(self.dim) if weights is None else np.asarray(weights, dtype=float)
        c3, c4, c5 = c[:, 3] * w, c[:, 4] * w, c[:, 5] * w
        T = self.T[:, None]
        T2, T3, T4, T5 = T ** 2, T ** 3, T ** 4, T ** 5
        e = (36 * c3 * c3 * T + 144 * c3 * c4 * T2 + 192 * c4 * c4 * T3 + 240 * c3 * c5 * T3
             + 720 * c4 * c5 * T4 + 720 * c5 * c5 * T5)
        dc = np.zeros_like(c)
        dc[:, 3] = (72 * c3 * T + 144 * c4 * T2 + 240 * c5 * T3) * w
        dc[:, 4] = (144 * c3 * T2 + 384 * c4 * T3 + 720 * c5 * T4) * w
        dc[:, 5] = (240 * c3 * T3 + 720 * c4 * T4 + 1440 * c5 * T5) * w
        dT = (36 * c3 * c3 + 288 * c3 * c4 * T + 576 * c4 * c4 * T2 + 720 * c3 * c5 * T2
              + 2880 * c4 * c5 * T3 + 3600 * c5 * c5 * T4).sum(axis=1)
        return float(e.sum()), dc.reshape(6 * self.n, self.dim), dT

    # ------------------------------------------------------------------ adjoint
    def grad(self, dJ_dc: np.ndarray, dJ_dT: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dJ/dq (N-1, D), dJ/dT (N,)) of a cost J(c(q, T), T) from its partials (after `solve`)."""
        n = self.n
        lam, info = lapack.dgbtrs(self._lu, BAND, BAND, np.asarray(dJ_dc, dtype=float).reshape(6 * n, self.dim),
                                  self._piv, trans=1)
        gq = lam[6 * np.arange(n - 1) + 5]
        c = self.c.reshape(n, 6, self.dim)
        gT = np.array(dJ_dT, dtype=float, copy=True)
        # d(A c)/dT_i: row of derivative o at piece i's end becomes derivative o + 1 there
        ends = np.einsum("onj,njd->ond", bases(self.T, 6)[1:], c)  # derivative o+1 at each piece end
        if n > 1:
            lam_rows = lam[3:3 + 6 * (n - 1)].reshape(n - 1, 6, self.dim)
            for k, o in enumerate(self._knot_orders):
                gT[:-1] -= np.einsum("id,id->i", lam_rows[:, k], ends[o, :-1])
        for k in range(3):
            gT[-1] -= lam[6 * n - 3 + k] @ ends[k, -1]
        return gq, gT
