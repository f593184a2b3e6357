"""Fault-tolerant allocation modes of paper 000 §II for any layout (specs/ftc.md §4).

Each mode is a small Allocator over the one effectiveness matrix of `AssemblyModel`. Columns are
rotors (slot (unit-1)*4 + rotor-1); rows are (thrust N, roll, pitch, yaw) about the assembly CoM.
Commands are what the units are asked for; the rotors deliver eta times that.
"""

from __future__ import annotations

import numpy as np

from mars_link.allocation.base import Allocator
from mars_link.assembly import ROTORS_PER_UNIT

_RANK_TOL = 1e-9


def unit_groups(n_rotors: int) -> list[slice]:
    return [slice(i, i + ROTORS_PER_UNIT) for i in range(0, n_rotors, ROTORS_PER_UNIT)]


def failed_units(eta: np.ndarray) -> np.ndarray:
    """Per unit: True when all four rotors are dead."""
    return np.all(eta.reshape(-1, ROTORS_PER_UNIT) <= 0.0, axis=1)


def faulty_units(eta: np.ndarray) -> np.ndarray:
    """Per unit: True when any rotor is below nominal."""
    return np.any(eta.reshape(-1, ROTORS_PER_UNIT) < 1.0, axis=1)


def clip(thrusts: np.ndarray, lo: float | None, hi: float | None, eta: np.ndarray | None = None) -> np.ndarray:
    """Respect the thrust bounds; dead rotors (eta 0) are commanded exactly 0."""
    if lo is not None or hi is not None:
        thrusts = np.clip(thrusts, lo, hi)
    if eta is not None:
        thrusts = np.where(eta > 0.0, thrusts, 0.0)
    return thrusts


class UnitShares(Allocator):
    """Eq. 1 generalised: minimum-norm unit thrusts over the healthy units for (thrust, roll, pitch),
    each unit's share split equally over its four rotors; yaw from the (+,-,+,-) rotor differential
    of every healthy unit, which adds no force or roll/pitch moment. For hover this gives exactly the
    minimum-variance shares of eq. 1. Rotor degradations inside a unit are not compensated."""

    name = "unit"

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        m = self.model
        healthy = ~failed_units(self.eta)
        self._healthy_rotor = np.repeat(healthy, ROTORS_PER_UNIT).astype(float)
        pos = m.unit_positions_m
        a = np.vstack([np.ones(m.n_units), -pos[:, 1], pos[:, 0]])[:, healthy]  # unit-level (T, L, M)
        self._unit_pinv = np.zeros((m.n_units, 3))
        self._unit_pinv[healthy] = np.linalg.pinv(a, rcond=1e-9)
        kq = m.vehicle.yaw_moment_per_thrust_m
        n_h = max(int(healthy.sum()), 1)
        self._yaw_pattern = m.rotor_yaw_signs * self._healthy_rotor / (ROTORS_PER_UNIT * kq * n_h)

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        w = np.asarray(wrench, dtype=float)
        unit_force = self._unit_pinv @ w[:3]
        thrusts = np.repeat(unit_force / ROTORS_PER_UNIT, ROTORS_PER_UNIT) + self._yaw_pattern * w[3]
        return clip(thrusts, self.min_thrust_n, self.max_thrust_n, self.eta)


class Partial(Allocator):
    """Eq. 3-5: faulty units keep the commands they would get if healthy; the fully healthy units take
    the force and moments the faulty rotors fail to deliver (minimum norm)."""

    name = "partial"

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        b = self.model.effectiveness()
        self._pinv_nominal = np.linalg.pinv(b)
        self._b_eta = self.model.effectiveness(self.eta)
        healthy_rotor = np.repeat(~faulty_units(self.eta), ROTORS_PER_UNIT)
        self._pinv_healthy = np.zeros((b.shape[1], 4))
        if healthy_rotor.any():
            self._pinv_healthy[healthy_rotor] = np.linalg.pinv(b[:, healthy_rotor], rcond=1e-9)

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        w = np.asarray(wrench, dtype=float)
        t = self._pinv_nominal @ w
        missing = w - self._b_eta @ t
        t = t + self._pinv_healthy @ missing
        return clip(t, self.min_thrust_n, self.max_thrust_n, self.eta)


class Full(Allocator):
    """Eq. 6, two stages: every faulty unit re-produces its own nominal share of the wrench with its
    remaining rotors (least squares over its effective columns); whatever it cannot produce goes to
    the fully healthy units (minimum norm)."""

    name = "full"
    #: a faulty unit whose own least-squares leaves more than this fraction of its share unbalanced
    #: "cannot balance itself" (used by Hybrid)
    balance_tolerance = 1e-6

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        b = self.model.effectiveness()
        self._pinv_nominal = np.linalg.pinv(b)
        self._b = b
        self._b_eta = self.model.effectiveness(self.eta)
        faulty = faulty_units(self.eta)
        self._faulty_groups = [g for g, f in zip(unit_groups(b.shape[1]), faulty) if f]
        self._self_pinv = {}
        self._self_balanced = {}
        for g in self._faulty_groups:
            be = self._b_eta[:, g]
            p = np.linalg.pinv(be, rcond=1e-9)
            self._self_pinv[g.start] = p
            # can this unit reproduce any of its nominal wrenches on its own? (projection is identity)
            proj = be @ p
            self._self_balanced[g.start] = np.allclose(proj @ b[:, g], b[:, g], atol=1e-9)
        healthy_rotor = np.repeat(~faulty, ROTORS_PER_UNIT)
        self._pinv_healthy = np.zeros((b.shape[1], 4))
        if healthy_rotor.any():
            self._pinv_healthy[healthy_rotor] = np.linalg.pinv(b[:, healthy_rotor], rcond=1e-9)

    def _stage_one(self, t: np.ndarray, only_balanced: bool) -> np.ndarray:
        for g in self._faulty_groups:
            if only_balanced and not self._self_balanced[g.start]:
                continue  # hybrid: this unit cannot balance itself; keep its commands (partial)
            share = self._b[:, g] @ t[g]
            t[g] = self._self_pinv[g.start] @ share
        return t

    def allocate(self, wrench: np.ndarray, only_balanced: bool = False) -> np.ndarray:
        w = np.asarray(wrench, dtype=float)
        t = self._stage_one(self._pinv_nominal @ w, only_balanced)
        residual = w - self._b_eta @ t
        t = t + self._pinv_healthy @ residual
        return clip(t, self.min_thrust_n, self.max_thrust_n, self.eta)


class Hybrid(Full):
    """Our reading of the paper's undefined "hybrid": full (intra-unit) reallocation inside every faulty
    unit that can balance itself, partial (commands unchanged) for those that cannot, then the
    residual to the healthy units."""

    name = "hybrid"

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        return super().allocate(wrench, only_balanced=True)


class RedistributedPseudoInverse(Allocator):
    """Fault-aware pseudo-inverse that fixes saturated rotors at their bound and re-solves for the rest
    (at most one pass per rotor). Dependency-free fallback of "qp" and its test oracle."""

    name = "rpi"

    def set_eta(self, eta: np.ndarray) -> None:
        super().set_eta(eta)
        self._b_eta = self.model.effectiveness(self.eta)
        self._alive = self.eta > 0.0

    def allocate(self, wrench: np.ndarray) -> np.ndarray:
        w = np.asarray(wrench, dtype=float)
        b = self._b_eta
        n = b.shape[1]
        lo = -np.inf if self.min_thrust_n is None else self.min_thrust_n
        hi = np.inf if self.max_thrust_n is None else self.max_thrust_n
        t = np.zeros(n)
        free = self._alive.copy()
        for _ in range(n):
            if not free.any():
                break
            rest = w - b[:, ~free] @ t[~free]
            t[free] = np.linalg.pinv(b[:, free], rcond=1e-9) @ rest
            low, high = free & (t < lo), free & (t > hi)
            if not (low.any() or high.any()):
                break
            t[low], t[high] = lo, hi
            free &= ~(low | high)
        t[~self._alive] = 0.0
        return t
