"""Fault-tolerant allocation modes of paper 000 §II for any layout (specs/ftc.md §4).

Each mode is a small Allocator over the one effectiveness matrix of `AssemblyModel`. Columns are
rotors (slot (unit-1)*4 + rotor-1); rows are (thrust N, roll, pitch, yaw) about the assembly CoM.
Commands are what the units are asked for; the rotors deliver eta times that.

The closed-form modes share one skeleton (`_Staged`): a first guess (eq. 1 shares, or the nominal
pseudo-inverse), an optional intra-unit stage for faulty units (eq. 6), then the residual wrench
to the healthy units (eq. 3-5) and, last resort, to every live rotor (so a fault set that leaves
no healthy unit, e.g. a single degraded quadrotor or noisy detected efficiencies, is still
served). Every stage is a precomputed matrix; without thrust bounds they fold into one 4N x 4
gain, so `allocate` is one product. With thrust bounds that product is still the answer whenever
it fits them; otherwise the stages run one by one, a faulty unit's own commands are clipped first
(what it cannot make moves on) and the result is clipped at the end, without redistributing among
saturated rotors: "qp" is the saturation-aware mode.
"""

from __future__ import annotations

import numpy as np

from mars_link.allocation.base import Allocator
from mars_link.core.assembly import GRAVITY_MPS2, ROTORS_PER_UNIT, AssemblyModel

_RCOND = 1e-9
#: relative priority of (thrust, roll, pitch, yaw) once each row is normalised to hover scale
#: (weights, so a soft priority: 1e4 between roll/pitch and thrust keeps the leak into roll/pitch
#: ~1e-4 of the thrust deficit; 1e2 lets yaw give way before thrust)
PRIORITY = np.array([1.0, 1e4, 1e4, 1e-2])


def failed_units(eta: np.ndarray) -> np.ndarray:
    """Per unit: True when all four rotors are dead."""
    return np.all(eta.reshape(-1, ROTORS_PER_UNIT) <= 0.0, axis=1)


def faulty_units(eta: np.ndarray) -> np.ndarray:
    """Per unit: True when any rotor is below nominal."""
    return np.any(eta.reshape(-1, ROTORS_PER_UNIT) < 1.0, axis=1)


def row_weights(model: AssemblyModel) -> np.ndarray:
    """Weights of the wrench rows: each row divided by its hover-scale magnitude (squared), times
    PRIORITY, so roll/pitch > thrust > yaw whatever the units and the assembly size."""
    weight_n = model.mass_kg * GRAVITY_MPS2
    arm = model.vehicle.pitch_m
    scale = np.array([weight_n, weight_n * arm, weight_n * arm, weight_n * model.vehicle.yaw_moment_per_thrust_m])
    return PRIORITY / scale**2


def clean_wrench(wrench: np.ndarray, weight_n: float) -> np.ndarray:
    """Best effort on a broken demand (allocate never raises): non-finite thrust -> the weight,
    non-finite moments -> 0."""
    w = np.asarray(wrench, dtype=float)
    if np.isfinite(w).all():
        return w
    return np.where(np.isfinite(w), w, np.array([weight_n, 0.0, 0.0, 0.0]))


def restricted_pinv(b: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Minimum-norm right inverse using only `columns` (bool mask); other rows are zero."""
    out = np.zeros((b.shape[1], b.shape[0]))
    if columns.any():
        out[columns] = np.linalg.pinv(b[:, columns], rcond=_RCOND)
    return out


def prioritised_pinv(b: np.ndarray, groups: list[list[int]], row_scale: np.ndarray) -> np.ndarray:
    """X with t = X w meeting the row groups of b t = w lexicographically (earlier groups first,
    least squares within a group after scaling by row_scale, minimum norm overall). Why: a rotor
    set that cannot meet every row should drop the least important one (yaw), not smear the error."""
    n, m = b.shape[1], b.shape[0]
    x = np.zeros((n, m))
    null = np.eye(n)
    for rows in groups:
        s = row_scale[rows][:, None]
        bk = s * (b[rows] @ null)
        pk = _pinv_abs(bk, _RCOND * max(np.linalg.norm(s * b[rows], 2), 1e-300))
        select = np.zeros((len(rows), m))
        select[np.arange(len(rows)), rows] = 1.0
        x = x + null @ pk @ (s * (select - b[rows] @ x))
        null = null @ (np.eye(n) - pk @ bk)
    return x


def _pinv_abs(a: np.ndarray, tol: float) -> np.ndarray:
    """Pseudo-inverse dropping singular values below an absolute tol (a projected matrix can be
    numerically zero, where a relative cutoff would invert rounding noise)."""
    u, sv, vt = np.linalg.svd(a, full_matrices=False)
    keep = sv > tol
    return (vt[keep].T / sv[keep]) @ u[:, keep].T


class _Staged(Allocator):
    """Skeleton of the closed-form modes (see the module docstring)."""

    #: intra-unit stage for faulty units: None (partial), "always" (full), "when_balanced" (hybrid)
    intra_unit: str | None = None

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        m = self.model
        b = m.effectiveness()
        self._b = b
        self._b_eta = m.effectiveness(self.eta)
        self._alive = self.eta > 0.0
        self._weight_n = m.mass_kg * GRAVITY_MPS2
        lo = -np.inf if self.min_thrust_n is None else self.min_thrust_n
        hi = self.upper_bounds() if self.available is not None else (
            np.inf if self.max_thrust_n is None else self.max_thrust_n)
        self._lo, self._hi = lo, hi
        self._is_bounded = self.min_thrust_n is not None or self.max_thrust_n is not None
        self._dead_idx = np.flatnonzero(~self._alive)
        self._lo_live = np.where(self._alive, lo, -np.inf)  # dead rotors are zeroed, not checked
        self._hi_live = np.where(self._alive, hi, np.inf)
        faulty = faulty_units(self.eta)
        self._first = self._first_guess()
        self._to_healthy = restricted_pinv(self._b_eta, np.repeat(~faulty, ROTORS_PER_UNIT))
        self._to_live = restricted_pinv(self._b_eta, self._alive)
        self._stage_one = None
        if self.intra_unit is not None and faulty.any():
            self._setup_intra_unit(faulty)
        self._fold()

    def _fold(self) -> None:
        """Without bounds every stage is linear: fold them into one gain (one product per call)."""
        eye = np.eye(4)
        g = self._first.copy()
        if self._stage_one is not None:
            g[self._intra_rotors] = self._stage_one[self._intra_rotors]
        g = g + self._to_healthy @ (eye - self._b_eta @ g)
        self._gain = g + self._to_live @ (eye - self._b_eta @ g)

    def _first_guess(self) -> np.ndarray:
        """n x 4 map from the wrench to the commands each unit would get if it were healthy."""
        return np.linalg.pinv(self._b, rcond=_RCOND)

    def _setup_intra_unit(self, faulty: np.ndarray) -> None:
        """Eq. 6 stage one as matrices: each faulty unit maps its nominal share of the wrench to
        its own live rotors, in its own frame, priority (thrust, roll, pitch) then yaw."""
        m = self.model
        a = m.vehicle.rotor_offset_m
        own_scale = np.array([1.0, 1.0 / a, 1.0 / a, 1.0 / m.vehicle.yaw_moment_per_thrust_m])
        stage = self._first.copy()
        units = np.flatnonzero(faulty)
        balanced = np.zeros(m.n_units, dtype=bool)
        for u in units:
            g = slice(u * ROTORS_PER_UNIT, (u + 1) * ROTORS_PER_UNIT)
            x, y = m.unit_positions_m[u, :2]
            # assembly-CoM wrench -> wrench about the unit's own centre (eq. 6b)
            to_own = np.array([[1.0, 0, 0, 0], [y, 1.0, 0, 0], [-x, 0, 1.0, 0], [0, 0, 0, 1.0]])
            b_own = to_own @ self._b_eta[:, g]
            solve = prioritised_pinv(b_own, [[0, 1, 2], [3]], own_scale) @ to_own
            share = self._b[:, g] @ self._first[g]  # 4 x 4: wrench -> this unit's nominal share
            stage[g] = solve @ share
            # "can balance itself": reproduces any nominal share with its live rotors alone
            balanced[u] = np.linalg.matrix_rank(self._b_eta[:, g], tol=_RCOND) == 4
        self._stage_one = stage
        use = balanced if self.intra_unit == "when_balanced" else np.ones(m.n_units, dtype=bool)
        self._intra_units = units[use[units]]
        self._intra_rotors = np.zeros(m.n_rotors, dtype=bool)
        for u in self._intra_units:
            self._intra_rotors[u * ROTORS_PER_UNIT:(u + 1) * ROTORS_PER_UNIT] = True
        self._intra_idx = np.flatnonzero(self._intra_rotors)
        self._hi_intra = self._hi[self._intra_idx] if np.ndim(self._hi) else self._hi
        self._stage_intra = stage[self._intra_idx]  # hot path: no fancy indexing of the full map

    def _apply_intra_unit(self, w: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Full: every faulty unit rebalances, clipped to the bounds (what it cannot make goes on)."""
        own = self._stage_intra @ w
        t[self._intra_idx] = np.minimum(np.maximum(own, self._lo), self._hi_intra)
        return t

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        w = clean_wrench(wrench, self._weight_n)
        t = self._gain @ w
        if not self._is_bounded or ((t >= self._lo_live).all() and (t <= self._hi_live).all()):
            t[self._dead_idx] = 0.0  # the linear answer fits the bounds: it is the answer
            return t
        # a bound bites: run the stages, so what a saturated stage cannot make moves on
        t = self._first @ w
        if self._stage_one is not None and len(self._intra_idx):
            t = self._apply_intra_unit(w, t)
        t += self._to_healthy @ (w - self._b_eta @ t)
        t += self._to_live @ (w - self._b_eta @ t)
        t = np.minimum(np.maximum(t, self._lo), self._hi)
        t[self._dead_idx] = 0.0
        return t


class UnitShares(_Staged):
    """Eq. 1 generalised: minimum-norm unit thrusts over the non-failed units for (thrust, roll,
    pitch), each unit's share split equally over its four rotors; yaw from the (+,-,+,-) rotor
    differential of those units, which adds no force or roll/pitch moment. For hover this is
    exactly the minimum-variance shares of eq. 1 (`paper_tables.thrust_shares`). What the unit
    level cannot make (e.g. collinear survivors) goes to their rotors by pseudo-inverse. Rotor
    degradations inside a unit are not compensated (by definition of eq. 1)."""

    name = "unit"

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        # eq. 1 knows units as alive or failed: the residual uses the nominal columns of the
        # survivors, so degraded rotors stay uncompensated; the live-rotor stage is not used
        alive_units = np.repeat(~failed_units(self.eta), ROTORS_PER_UNIT)
        self._to_healthy = restricted_pinv(self._b, alive_units)
        self._b_eta = self._b * alive_units
        self._to_live = np.zeros_like(self._to_live)
        self._fold()

    def _first_guess(self) -> np.ndarray:
        m = self.model
        healthy = ~failed_units(self.eta)
        pos = m.unit_positions_m
        a = np.vstack([np.ones(m.n_units), -pos[:, 1], pos[:, 0]])[:, healthy]  # unit (T, L, M)
        unit_pinv = np.zeros((m.n_units, 4))
        if healthy.any():
            unit_pinv[healthy, :3] = np.linalg.pinv(a, rcond=_RCOND)
        first = np.repeat(unit_pinv / ROTORS_PER_UNIT, ROTORS_PER_UNIT, axis=0)
        kq = m.vehicle.yaw_moment_per_thrust_m
        n_h = max(int(healthy.sum()), 1)
        first[:, 3] = m.rotor_yaw_signs * np.repeat(healthy, ROTORS_PER_UNIT) / (ROTORS_PER_UNIT * kq * n_h)
        return first


class Partial(_Staged):
    """Eq. 3-5: faulty units keep the commands they would get if healthy; the fully healthy units take
    the force and moments the faulty rotors fail to deliver (minimum norm)."""

    name = "partial"


class Full(_Staged):
    """Eq. 6, two stages: every faulty unit re-produces its own nominal share of the wrench with its
    remaining rotors (about its own centre: thrust, roll, pitch first, yaw last, within the thrust
    bounds); whatever it cannot produce goes to the fully healthy units (minimum norm)."""

    name = "full"
    intra_unit = "always"


class Hybrid(_Staged):
    """Our reading of the paper's undefined "hybrid" (ftc.md §4.3 [R]): full (intra-unit)
    reallocation inside every faulty unit that can balance itself, i.e. whose live rotors span all
    four wrench axes and whose rebalanced commands fit the thrust bounds on this call; partial
    (commands unchanged) for the others; then the residual to the healthy units."""

    name = "hybrid"
    intra_unit = "when_balanced"

    def _apply_intra_unit(self, w: np.ndarray, t: np.ndarray) -> np.ndarray:
        own = self._stage_intra @ w
        fits = ((own >= self._lo) & (own <= self._hi_intra)).reshape(-1, ROTORS_PER_UNIT).all(axis=1)
        if fits.all():
            t[self._intra_idx] = own
        else:  # a unit whose rebalance would saturate keeps its commands (partial) on this call
            keep = np.repeat(fits, ROTORS_PER_UNIT)
            t[self._intra_idx[keep]] = own[keep]
        return t


class RedistributedPseudoInverse(Allocator):
    """Fault-aware weighted pseudo-inverse that fixes saturated rotors at their bound and re-solves
    for the rest (at most one pass per rotor). Rows weighted as in "qp" (roll/pitch > thrust > yaw).
    Dependency-free fallback of "qp" and its test oracle."""

    name = "rpi"

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        self._sqrt_w = np.sqrt(row_weights(self.model))
        self._b_eta = self.model.effectiveness(self.eta)
        self._bw = self._sqrt_w[:, None] * self._b_eta
        self._alive = self.eta > 0.0
        self._pinv_alive = restricted_pinv(self._bw, self._alive)
        self._weight_n = self.model.mass_kg * GRAVITY_MPS2

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        ww = self._sqrt_w * clean_wrench(wrench, self._weight_n)
        t = self._pinv_alive @ ww
        lo = -np.inf if self.min_thrust_n is None else self.min_thrust_n
        hi = self.upper_bounds()
        free = self._alive.copy()
        bw = self._bw
        for _ in range(len(t)):
            low, high = free & (t < lo), free & (t > hi)
            if not (low.any() or high.any()):
                break
            t[low], t[high] = lo, hi[high]
            free &= ~(low | high)
            if not free.any():
                break
            rest = ww - bw[:, ~free] @ t[~free]
            t[free] = np.linalg.pinv(bw[:, free], rcond=_RCOND) @ rest
        t[~self._alive] = 0.0
        return t
