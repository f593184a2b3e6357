"""Cost of one cascaded-controller update (control law and allocation) and of a trajectory sample.

    python benchmarks/bench_cascaded.py [--steps N] [--quick] [--json]

Feeds a moving state along the paper's spiral (tracked point unit 1) so every branch runs; prints
median and 95th percentile per layout and allocator, in microseconds.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from record import Recorder, add_json_option, apply_quick
from mars_link.allocation import make_allocator
from mars_link.core.assembly import AssemblyModel
from mars_link.control.cascaded import CascadedController
from mars_link.core.rotations import euler_to_quat
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import TRAJECTORY_KINDS, build_trajectory

LAYOUTS = {"1x1": ["X"], "3x2": ["XXX", "XXX"], "plus-5": [".X.", "XXX", ".X."], "L-4": ["X..", "XXX"]}


def bench_controller(layout: list[str], mode: str, steps: int) -> tuple[float, float, float]:
    model = AssemblyModel.from_layout(layout)
    ctrl = CascadedController(model, make_allocator(mode, model), model.unit_position(1).copy())
    traj = build_trajectory("mars-ftcc-spiral", {}, model.vehicle.gear_depth_m)
    refs = [traj.sample(0.01 * k) for k in range(steps)]
    rng = np.random.default_rng(0)
    states = [
        RigidBodyState(0.01 * k, r.position_ned_m + rng.normal(0, 0.01, 3), r.velocity_ned_mps.copy(),
                       euler_to_quat(*rng.normal(0, 0.05, 3)), rng.normal(0, 0.1, 3))
        for k, r in enumerate(refs)
    ]
    total, control, alloc = [], [], []
    for k, (s, r) in enumerate(zip(states, refs)):
        t0 = time.perf_counter()
        out = ctrl.update(s.t_s, s, r)
        total.append(time.perf_counter() - t0)
        control.append(out.timings_s["control"])
        alloc.append(out.timings_s["allocation"])
    return np.median(total), np.percentile(total, 95), np.median(control)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--quick", action="store_true", help="500 steps")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, steps=500)
    rec = Recorder.start("bench_cascaded", args)
    print(f"{'layout':8} {'allocator':9} {'update median':>14} {'p95':>8} {'control law':>12}  (us)")
    for name, layout in LAYOUTS.items():
        for mode in ("none", "full"):
            med, p95, ctl = bench_controller(layout, mode, args.steps)
            print(f"{name:8} {mode:9} {med * 1e6:14.1f} {p95 * 1e6:8.1f} {ctl * 1e6:12.1f}")
            note = f"{name}, allocator {mode}: cascaded update (control law + allocation), median; p95 {p95 * 1e6:.1f} us"
            if (name, mode) == ("3x2", "full"):
                rec.headline(f"update_{name}_{mode}_us", med * 1e6, "us", note)
            else:
                rec.figure(f"update_{name}_{mode}_us", med * 1e6, "us", note)
    print()
    for kind in TRAJECTORY_KINDS:
        if kind == "csv":
            continue
        traj = build_trajectory(kind, {"points": [[0, 0, -1.5], [3, 2, -2.0], [0, 4, -1.0]]} if kind == "waypoints" else {}, 0.05)
        ts = np.linspace(0.0, traj.duration_s, args.steps)
        t0 = time.perf_counter()
        for t in ts:
            traj.sample(t)
        sample_us = (time.perf_counter() - t0) / len(ts) * 1e6
        print(f"{kind:17} sample {sample_us:6.1f} us")
        rec.figure(f"sample_{kind}_us", sample_us, "us", f"trajectory {kind}: one sample")
    rec.finish()


if __name__ == "__main__":
    main()
