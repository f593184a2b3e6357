"""Allocation cost per call for every FTC mode, 3x2 and 5x5, nominal and faulted, without and
with rotor thrust bounds; plus how well each mode meets the demand (max |B(eta) t - w| relative
to the weight, over the same calls).

    python benchmarks/bench_allocation.py [--calls N] [--quick] [--json]

Demands are hover plus random moments, drawn independently each call (harder on a warm-started
solver than a flight, where successive demands are close).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from record import Recorder, add_json_option, apply_quick
from mars_link.allocation import ALLOCATION_MODES, make_allocator
from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel

REPEATS = 5
LAYOUTS = (("3x2", ["XXX", "XXX"]), ("5x5", ["XXXXX"] * 5))


def fault_eta(model: AssemblyModel) -> np.ndarray:
    """Unit 2 dead, unit 1 rotor 1 at 50 %, last unit rotor 3 at 30 %."""
    eta = model.nominal_eta()
    eta[model.unit_slots(2)] = 0.0
    eta[model.rotor_slot(1, 1)] = 0.5
    eta[model.rotor_slot(model.n_units, 3)] = 0.3
    return eta


def demands(model: AssemblyModel, calls: int) -> np.ndarray:
    weight = model.mass_kg * GRAVITY_MPS2
    arm = model.vehicle.pitch_m
    kq = model.vehicle.yaw_moment_per_thrust_m
    rng = np.random.default_rng(0)
    scale = np.array([0.05 * weight, 0.02 * weight * arm, 0.02 * weight * arm, 0.05 * weight * kq])
    return np.array([weight, 0.0, 0.0, 0.0]) + rng.normal(size=(calls, 4)) * scale


def measure(mode: str, model: AssemblyModel, eta: np.ndarray, bounds, wrenches: np.ndarray):
    alloc = make_allocator(mode, model, eta, *bounds)
    for w in wrenches[:20]:
        alloc.allocate(w)  # warm up (and warm start)
    out = np.empty((len(wrenches), model.n_rotors))
    chunk_us = []  # the machine is shared: report the quietest of REPEATS chunks
    for chunk in np.array_split(np.arange(len(wrenches)), REPEATS):
        t0 = time.perf_counter()
        for i in chunk:
            out[i] = alloc.allocate(wrenches[i])
        chunk_us.append(1e6 * (time.perf_counter() - t0) / len(chunk))
    cost_us = min(chunk_us)
    err = np.abs(out @ model.effectiveness(eta).T - wrenches).max() / (model.mass_kg * GRAVITY_MPS2)
    return cost_us, err, getattr(alloc, "fallbacks", None)


def qp_saturation_rows(calls: int, rec: Recorder | None = None) -> list[str]:
    """qp when rotors saturate (bounded preset, moments of about a third of weight x assembly
    half-width): how many calls hit a bound, how many of those the active-set step left to OSQP,
    and the cost per call over all calls."""
    rows = []
    for name, layout in LAYOUTS:
        model = AssemblyModel.from_layout(layout, "modquad-cf2")
        v = model.vehicle
        weight = model.mass_kg * GRAVITY_MPS2
        arm = 0.1 * len(layout[0]) * v.pitch_m
        rng = np.random.default_rng(1)
        scale = np.array([0.1 * weight, weight * arm, weight * arm, 0.1 * weight * v.yaw_moment_per_thrust_m])
        wrenches = np.array([weight, 0.0, 0.0, 0.0]) + rng.normal(size=(calls, 4)) * scale
        for label, eta in (("nominal", model.nominal_eta()), ("faulted", fault_eta(model))):
            bounds = (v.rotor_min_thrust_n, v.rotor_max_thrust_n)
            cost_us, _, _ = measure("qp", model, eta, bounds, wrenches)
            alloc = make_allocator("qp", model, eta, *bounds)
            for w in wrenches:
                alloc.allocate(w)
            rows.append(f"{name:<7}{label:<9}{cost_us:>9.1f}{alloc.saturated:>8}/{calls:<6}{alloc.solves:>6}")
            if rec is not None:
                rec.figure(f"qp_saturated_{name}_{label}_us", cost_us, "us",
                           f"qp per call under heavy saturation, modquad-cf2; {alloc.saturated}/{calls} calls saturated")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--calls", type=int, default=2000)
    ap.add_argument("--quick", action="store_true", help="500 calls per case")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, calls=500)
    rec = Recorder.start("bench_allocation", args)
    modes = ALLOCATION_MODES
    header = f"{'preset':<13}{'layout':<7}{'faults':<9}" + "".join(f"{m:>9}" for m in modes)
    rows_cost, rows_err, notes = [], [], []
    for preset, bounded in (("mars-ftcc", False), ("modquad-cf2", True)):
        for name, layout in LAYOUTS:
            model = AssemblyModel.from_layout(layout, preset)
            v = model.vehicle
            bounds = (v.rotor_min_thrust_n, v.rotor_max_thrust_n) if bounded else (None, None)
            wrenches = demands(model, args.calls)
            for label, eta in (("nominal", model.nominal_eta()), ("faulted", fault_eta(model))):
                cells = [measure(m, model, eta, bounds, wrenches) for m in modes]
                lead = f"{preset:<13}{name:<7}{label:<9}"
                rows_cost.append(lead + "".join(f"{c:>9.1f}" for c, _, _ in cells))
                rows_err.append(lead + "".join(f"{e:>9.0e}" for _, e, _ in cells))
                for m, (c, e, _) in zip(modes, cells):
                    note = f"{preset} {name} {label}, per allocate() call; max wrench error / weight {e:.0e}"
                    if (m, preset, name, label) == ("qp", "mars-ftcc", "3x2", "nominal"):
                        rec.headline(f"{m}_{preset}_{name}_{label}_us", c, "us", note + " (target < 200 us)")
                    else:
                        rec.figure(f"{m}_{preset}_{name}_{label}_us", c, "us", note)
                fb = cells[modes.index("qp")][2]
                if fb:
                    notes.append(f"{preset} {name} {label}: qp did not converge on {fb}/{args.calls} calls")
    print(f"cost per allocate() call, us: best of {REPEATS} chunks of {args.calls // REPEATS} calls")
    print("(mars-ftcc: no thrust bounds, as paper 000's plant; modquad-cf2: bounded rotors)")
    print(header)
    print("\n".join(rows_cost))
    print("\nmax |B(eta) t - w| / weight over the same calls ('none' ignores faults; 'unit' does not")
    print("compensate degraded rotors; bounded closed forms clip)")
    print(header)
    print("\n".join(rows_err))
    print("\n".join(notes) if notes else "\nqp converged on every call")
    calls = max(args.calls // 4, REPEATS)
    print(f"\nqp under heavy saturation (modquad-cf2, {calls} calls): us per call, calls with a bound")
    print("active, calls the active-set step left to OSQP")
    print(f"{'layout':<7}{'faults':<9}{'us':>9}{'saturated':>14}{'osqp':>6}")
    print("\n".join(qp_saturation_rows(calls, rec)))
    rec.finish()


if __name__ == "__main__":
    main()
