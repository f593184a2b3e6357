"""Allocation cost per call for every FTC mode, 3x2 and 5x5, nominal and faulted.

    python benchmarks/bench_allocation.py [--calls N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mars_link.allocation import ALLOCATION_MODES, make_allocator
from mars_link.assembly import GRAVITY_MPS2, AssemblyModel


def fault_eta(model: AssemblyModel) -> np.ndarray:
    eta = model.nominal_eta()
    eta[model.unit_slots(2)] = 0.0
    eta[model.rotor_slot(1, 1)] = 0.5
    eta[model.rotor_slot(model.n_units, 3)] = 0.3
    return eta


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--calls", type=int, default=2000)
    args = ap.parse_args()
    print(f"{'layout':<8}{'faults':<9}" + "".join(f"{m:>10}" for m in ALLOCATION_MODES) + "   (us per call)")
    for name, layout in (("3x2", ["XXX", "XXX"]), ("5x5", ["XXXXX"] * 5)):
        model = AssemblyModel.from_layout(layout)
        rng = np.random.default_rng(0)
        demands = np.array([model.mass_kg * GRAVITY_MPS2, 0, 0, 0]) + rng.normal(size=(args.calls, 4)) * [1, 0.05, 0.05, 0.01]
        for label, eta in (("nominal", model.nominal_eta()), ("faulted", fault_eta(model))):
            cells = []
            for mode in ALLOCATION_MODES:
                alloc = make_allocator(mode, model, eta)
                alloc.allocate(demands[0])
                t0 = time.perf_counter()
                for d in demands:
                    alloc.allocate(d)
                cells.append(1e6 * (time.perf_counter() - t0) / len(demands))
            print(f"{name:<8}{label:<9}" + "".join(f"{c:>10.1f}" for c in cells))


if __name__ == "__main__":
    main()
