"""Per-rotor thrust allocation and fault-tolerant reallocation modes (paper 000 §II).

`make_allocator(mode, model, eta, min_thrust_n, max_thrust_n)` builds one of `ALLOCATION_MODES`;
`check_controllable` refuses, before flight, a fault set the assembly cannot fly with.
"""

from __future__ import annotations

import numpy as np

from mars_link.allocation.base import Allocator
from mars_link.allocation.modes import Full, Hybrid, Partial, RedistributedPseudoInverse, UnitShares
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
    try:
        cls = _MODES[mode]
    except KeyError:
        raise UserInputError(f"unknown ftc mode {mode!r} (known: {', '.join(ALLOCATION_MODES)})") from None
    return cls(model, eta, min_thrust_n, max_thrust_n)


def check_controllable(
    model: AssemblyModel, eta: np.ndarray, bounds: tuple[float | None, float | None] = (None, None)
) -> None:
    """Refuse a fault set that leaves no way to produce every axis of the wrench, or to hover."""
    eta = np.asarray(eta, dtype=float)
    b = model.effectiveness(eta)
    if np.linalg.matrix_rank(b, tol=1e-9) < 4:
        dead = [f"u{r.unit_id}r{r.index}" for r, e in zip(model.rotors, eta) if e <= 0]
        raise UserInputError(
            f"the fault set leaves the assembly uncontrollable: the working rotors cannot produce "
            f"thrust, roll, pitch and yaw independently ({len(dead)} of {model.n_rotors} rotors dead)"
        )
    hover = np.array([model.mass_kg * GRAVITY_MPS2, 0.0, 0.0, 0.0])
    t = RedistributedPseudoInverse(model, eta, *bounds).allocate(hover)
    if np.abs(b @ t - hover).max() > 1e-3 * hover[0]:
        raise UserInputError(
            "the fault set leaves the assembly uncontrollable: it cannot hover within the rotor thrust limits"
        )


__all__ = ["ALLOCATION_MODES", "Allocator", "check_controllable", "make_allocator"]
