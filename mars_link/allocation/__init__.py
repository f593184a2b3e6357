"""Per-rotor thrust allocation and fault-tolerant reallocation modes (paper 000 §II).

`make_allocator(mode, model, eta, min_thrust_n, max_thrust_n)` builds one of `ALLOCATION_MODES`;
`check_controllable` refuses, before flight, a fault set the assembly cannot fly with.
"""

from __future__ import annotations

import numpy as np

from mars_link.allocation.base import Allocator
from mars_link.allocation.modes import Full, Hybrid, Partial, UnitShares
from mars_link.allocation.pseudo_inverse import NominalPseudoInverse
from mars_link.allocation.qp import QpAllocator
from mars_link.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.errors import UserInputError

_MODES: dict[str, type[Allocator]] = {
    "none": NominalPseudoInverse,
    "unit": UnitShares,
    "partial": Partial,
    "full": Full,
    "hybrid": Hybrid,
    "qp": QpAllocator,
}
ALLOCATION_MODES = tuple(_MODES)


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


__all__ = ["ALLOCATION_MODES", "Allocator", "check_controllable", "make_allocator"]
