"""`mars-link plan MAP --layout ROWS --start N,E,D --goal N,E,D [...] --out DIR` (options: mars_link.apps.cli).

Writes trajectory.csv (t_s, n_m, e_m, d_m, yaw_rad: the "csv" trajectory kind replays it), plan.json
and plan.png. Exit 0 = collision-free plan, 1 = no plan (reason on stderr and in plan.json),
2 = bad input (one line on stderr).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from mars_link.core.errors import UserInputError
from mars_link.core.validation import check_out_dir, prepare_out_dir


def parse_point(text: str, what: str) -> np.ndarray:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise UserInputError(f"{what} {text!r}: expected N,E,D numbers, e.g. 0,0,-2") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise UserInputError(f"{what} {text!r}: expected three finite numbers N,E,D")
    return np.array(values)


def plan_from_args(args) -> tuple:
    """Validate everything, then plan: (planner, result, obstacles)."""
    from mars_link.core.assembly import AssemblyModel, parse_layout, vehicle_preset
    from mars_link.planning.maps import load_map
    from mars_link.planning.pipeline import METHODS, Planner, PlanParams
    from mars_link.config.scenario import eta_after
    from mars_link.config.scenario import parse_fault_arg, validate_fault

    if args.method not in METHODS:
        raise UserInputError(f"--method {args.method!r}: known methods are {', '.join(METHODS)}")
    model = AssemblyModel.from_layout(parse_layout(args.layout), vehicle_preset(args.preset))
    faults = []
    for text in args.fault:
        f = parse_fault_arg(text)
        validate_fault(f, model, f"--fault {text}")
        faults.append(f)
    start, goal = parse_point(args.start, "--start"), parse_point(args.goal, "--goal")
    if abs(start[2] - goal[2]) > 1e-6:
        raise UserInputError(f"--start and --goal must have the same D (planar planning), got {start[2]:g} and {goal[2]:g}")
    if start[2] >= 0:
        raise UserInputError(f"--start D {start[2]:g}: must be < 0 (above the ground, NED)")
    if not math.isfinite(args.start_yaw):
        raise UserInputError("--start-yaw must be finite")
    params = PlanParams()
    if args.margin is not None:
        if not (math.isfinite(args.margin) and 0 <= args.margin <= 2):
            raise UserInputError(f"--margin {args.margin:g}: must be in [0, 2] m")
        params.margin_m = args.margin
    from mars_link.planning.pipeline import resolve_data_path

    # a path, or a bundled map's name
    obstacles = load_map(resolve_data_path(args.map), altitude_m=-start[2]).with_bounds_around(start, goal, pad_m=params.map_pad_m)
    planner = Planner(obstacles, model, eta_after(model, faults, math.inf), params)
    s = np.array([start[0], start[1], math.radians(args.start_yaw)])
    return planner, planner.plan(s, goal[:2], args.method, start[2]), obstacles


def write_outputs(out: Path, planner, result, obstacles, title: str, force: bool = False) -> None:
    from mars_link.logs.outputs import write_json
    from mars_link.planning.plots import plot_plan

    prepare_out_dir(out, force=force)
    if len(result.samples):
        s = result.samples
        rows = np.column_stack([s[:, 0], s[:, 1], s[:, 2], np.full(len(s), result.down_m), s[:, 3]])
        np.savetxt(out / "trajectory.csv", rows, delimiter=",", fmt="%.5f", header="t_s,n_m,e_m,d_m,yaw_rad", comments="")
    summary = result.summary()
    summary.update({"layout": list(planner.model.layout), "preset": planner.model.vehicle.name,
                    "eta": [round(float(e), 4) for e in planner.eta], "map": obstacles.name,
                    "obstacles": obstacles.n_obstacles, "margin_m": planner.p.margin_m,
                    "optimal_yaw": planner.yaw_star.describe()})
    write_json(out / "plan.json", summary)  # strict JSON: a NaN/inf figure is null
    plot_plan(out / "plan.png", obstacles, planner.footprint, [result], title)


def plan_command_args(args: argparse.Namespace) -> int:
    """The verb, its options parsed by mars_link.apps.cli; a bad input raises (one line there, exit 2)."""
    out = check_out_dir(args.out, force=args.force)  # before planning: a bad --out costs nothing
    if not args.quiet:
        print(f"planning {args.method} for {args.layout} on {args.map} ...", file=sys.stderr)
    planner, result, obstacles = plan_from_args(args)
    write_outputs(out, planner, result, obstacles,
                  f"{args.layout} {' '.join(args.fault)} {args.method}: {result.message}", args.force)
    if not args.quiet:
        st = result.stage_time_s
        print("  " + ", ".join(f"{k} {v:.3f} s" for k, v in st.items()), file=sys.stderr)
    if not result.success:
        print(f"mars-link: plan failed: {result.message}", file=sys.stderr)
        return 1
    print(f"plan ok: {result.length_m:.2f} m, {result.duration_s:.2f} s, min clearance {result.min_clearance_m:.3f} m, "
          f"total yaw {math.degrees(result.total_yaw_rad):.0f} deg -> {out}")
    return 0
