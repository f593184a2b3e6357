"""Per-rotor thrust allocation and fault-tolerant reallocation modes (paper 000 §II).

`make_allocator(mode, model, eta, min_thrust_n, max_thrust_n)` builds one of `ALLOCATION_MODES`;
`check_controllable` refuses, before flight, a fault set the assembly cannot fly with.
"""

from __future__ import annotations

import math

import numpy as np

from mars_link.allocation.base import Allocator
from mars_link.allocation.modes import Full, Hybrid, Partial, UnitShares
from mars_link.allocation.pseudo_inverse import NominalPseudoInverse
from mars_link.allocation.qp import QpAllocator
from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.core.ftc import FTC_MODES

_MODES: dict[str, type[Allocator]] = {
    "none": NominalPseudoInverse,
    "unit": UnitShares,
    "partial": Partial,
    "full": Full,
    "hybrid": Hybrid,
    "qp": QpAllocator,
}
ALLOCATION_MODES = tuple(_MODES)
assert ALLOCATION_MODES == FTC_MODES, "an FTC mode without its allocator (or the other way round)"


def make_allocator(
    mode: str,
    model: AssemblyModel,
    eta: np.ndarray | None = None,
    min_thrust_n: float | None = None,
    max_thrust_n: float | None = None,
) -> Allocator:
    """Allocator for `mode` (one of ALLOCATION_MODES); bounds None = unbounded (paper 000 plant)."""
    try:
        cls = _MODES[mode]
    except KeyError:
        raise UserInputError(f"unknown ftc mode {mode!r} (known: {', '.join(ALLOCATION_MODES)})") from None
    if eta is not None:
        eta = _checked_eta(model, eta)
    if min_thrust_n is not None and max_thrust_n is not None and min_thrust_n > max_thrust_n:
        raise UserInputError(f"rotor thrust bounds are reversed: min {min_thrust_n} N > max {max_thrust_n} N")
    return cls(model, eta, min_thrust_n, max_thrust_n)


def _checked_eta(model: AssemblyModel, eta: np.ndarray) -> np.ndarray:
    eta = np.asarray(eta, dtype=float)
    if eta.shape != (model.n_rotors,) or not np.all((eta >= 0.0) & (eta <= 1.0)):
        raise UserInputError(
            f"rotor efficiencies must be {model.n_rotors} values in [0, 1] (4 per unit), got shape {eta.shape}"
        )
    return eta


def check_controllable(
    model: AssemblyModel, eta: np.ndarray, bounds: tuple[float | None, float | None] = (None, None)
) -> None:
    """Refuse, before flight, a fault set that leaves no way to produce every axis of the wrench
    independently (rank of B(eta) < 4), or to hover within the rotor thrust bounds (exact LP)."""
    eta = _checked_eta(model, eta)
    b = model.effectiveness(eta)
    if np.linalg.matrix_rank(b, tol=1e-9) < 4:
        dead = int(np.sum(eta <= 0.0))
        raise UserInputError(
            f"the fault set leaves the assembly uncontrollable: the working rotors cannot produce "
            f"thrust, roll, pitch and yaw independently ({dead} of {model.n_rotors} rotors dead)"
        )
    from scipy.optimize import linprog  # slow import, only needed before flight

    lo, hi = bounds
    hover = np.array([model.mass_kg * GRAVITY_MPS2, 0.0, 0.0, 0.0])
    alive = eta > 0.0
    res = linprog(
        np.zeros(int(alive.sum())), A_eq=b[:, alive], b_eq=hover, bounds=(lo, hi), method="highs"
    )
    if res.status != 0:
        raise UserInputError(
            "the fault set leaves the assembly uncontrollable: it cannot hover within the rotor thrust "
            f"limits [{lo}, {hi}] N ({int(np.sum(~alive))} of {model.n_rotors} rotors dead)"
        )


def hover_thrust_share(model: AssemblyModel, eta: np.ndarray, max_thrust_n: float) -> float:
    """The least largest rotor command, as a share of `max_thrust_n`, with which the assembly hovers
    (exact LP; rotors push, never pull): above 1 it cannot hover within its limits; math.inf: at no
    thrust (e.g. every live rotor on one side of the CoM). Tells how far from hovering a piece is."""
    from scipy.optimize import linprog

    eta = _checked_eta(model, eta)
    alive = eta > 0.0
    b = model.effectiveness(eta)[:, alive]
    n = int(alive.sum())
    if n == 0:
        return math.inf
    hover = np.array([model.mass_kg * GRAVITY_MPS2, 0.0, 0.0, 0.0])
    cost = np.zeros(n + 1)
    cost[-1] = 1.0  # minimise s subject to B f = hover, 0 <= f <= s * max_thrust_n
    res = linprog(cost, A_ub=np.hstack([np.eye(n), -np.full((n, 1), max_thrust_n)]), b_ub=np.zeros(n),
                  A_eq=np.hstack([b, np.zeros((4, 1))]), b_eq=hover, bounds=(0, None), method="highs")
    return float(res.x[-1]) if res.status == 0 else math.inf


__all__ = ["ALLOCATION_MODES", "Allocator", "check_controllable", "hover_thrust_share", "make_allocator"]
