"""Planning evidence (issue 7): walls-map table, replay of the published planner CSVs, forest sweep.

    python tools/planning_eval.py [--what walls,replay,forest] [--seeds 20] [--density 10] [--flight-seeds 3] [--out runs/planning_eval]

Walls: for 4x1 (unit 3 failed), 4x1 (unit 4 failed), 3x2 (unit 2 failed) both planners plan on the
paper's walls at 2.3 m; each plan is flown with FTC (cascaded + hybrid allocation with sensor noise,
the same without noise, and the paper's own controller + hybrid) and the true footprint is checked against the walls.
Replay: the four published planner CSVs flown the same way (`--published DIR`: they are not shipped;
mars_link.apps.planning_eval.PUBLISHED_SOURCE says where to get them). Forest: seeded random
forests, success / clearance / time per stage. Prints markdown tables; writes results.json and PNGs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mars_link.core.assembly import AssemblyModel  # noqa: E402
from mars_link.logs.outputs import write_json  # noqa: E402
from mars_link.apps.planning_eval import (  # noqa: E402
    PAPER_CASES, WALLS_CSV, WALLS_GOAL, WALLS_START, fly, forest_sweep, published_csv, replay_published, walls_map,
)
from mars_link.core.errors import UserInputError  # noqa: E402
from mars_link.planning.maps import ForestParams  # noqa: E402
from mars_link.planning.pipeline import Planner, PlanParams  # noqa: E402
from mars_link.planning.plots import plot_plan  # noqa: E402
from mars_link.apps.sweep_pool import (  # noqa: E402
    PoolSpec, map_flights, pool_from_args, print_progress, values_or_raise,
)
from mars_link.processes.cli_options import add_pool  # noqa: E402

CONTROLLERS = (("cascaded", True), ("mars-ftcc-paper", False))  # (controller, sensor noise)
#: walls plans are also flown noise-free with cascaded: with sensor noise its error is the estimator's
#: floor (a few mm for any smooth plan), without it what is left is the plan's own demand
WALLS_CONTROLLERS = CONTROLLERS + (("cascaded", False),)
KEYS = {("cascaded", True): "casc", ("mars-ftcc-paper", False): "paper", ("cascaded", False): "cascnf"}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def fly_plan(traj: dict, layout: str, unit: int, obstacles, controller: str, noise: bool, seed: int):
    """One walls flight in a sweep worker (mars_link.apps.planning_eval.fly)."""
    return fly(traj, layout, unit, obstacles, controller=controller, noise=noise, seed=seed)


def walls(out: Path, margin: float, seeds: int, pool: PoolSpec) -> list[dict]:
    """Plan every case here, then fly every plan's flights on the sweep's executor."""
    obstacles = walls_map()
    rows, tasks, slots = [], [], []
    for layout, unit in PAPER_CASES:
        model = AssemblyModel.from_layout(layout)
        eta = model.nominal_eta()
        eta[model.unit_slots(unit)] = 0.0
        params = PlanParams(margin_m=margin)
        planner = Planner(obstacles, model, eta, params)
        start = np.array([WALLS_START[0], WALLS_START[1], 0.0])
        results = []
        for method in ("ours", "svsdf"):
            res = planner.plan(start, np.array(WALLS_GOAL[:2]), method, WALLS_START[2])
            results.append(res)
            rows.append({"layout": layout, "failed_unit": unit, "method": method, **res.summary()})
            traj = {"kind": "plan", "map": WALLS_CSV, "start": list(WALLS_START), "goal": list(WALLS_GOAL),
                    "method": method, "margin_m": margin}
            for controller, noise in WALLS_CONTROLLERS if res.success else ():
                for s in range(1, (seeds if noise else 1) + 1):
                    tasks.append((traj, layout, unit, obstacles, controller, noise, s))
                    slots.append((len(rows) - 1, KEYS[controller, noise]))
        plot_plan(out / f"walls_{layout.replace(',', '_')}_u{unit}.png", obstacles, planner.footprint, results,
                  f"{layout} unit {unit} failed: ours (blue) vs svsdf (orange), margin {margin} m")
    flights = values_or_raise(map_flights(fly_plan, tasks, pool, print_progress(len(tasks), "walls flights")),
                              "walls flight")
    for k, row in enumerate(rows):
        for key in dict.fromkeys(key for i, key in slots if i == k):
            fs = [f for (i, kk), f in zip(slots, flights) if i == k and kk == key]
            row[f"{key}_mean_error_m"] = float(np.mean([f.mean_error_m for f in fs]))
            row[f"{key}_max_error_m"] = float(max(f.max_error_m for f in fs))
            row[f"{key}_collisions"] = int(sum(f.collisions for f in fs))
            row[f"{key}_min_clearance_m"] = float(min(f.min_clearance_m for f in fs))
            row[f"{key}_diverged"] = any(f.diverged for f in fs)
        log(f"walls {row['layout']} u{row['failed_unit']} {row['method']}: "
            f"{json.dumps({k: v for k, v in row.items() if k != 'stage_time_s'})}")
    return rows


def walls_table(rows: list[dict]) -> str:
    head = ("| case | method | success (back end) | total yaw [deg] | max yaw rate [deg/s] | min clearance [m] | length / duration | "
            "plan time [s] | cascaded+hybrid mean / max err [m] | collisions | cascaded noise-free mean err [mm] | "
            "paper ctrl+hybrid mean err [m] | collisions |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        lines.append(
            f"| {r['layout']} u{r['failed_unit']} | {r['method']} | {r['success']} ({r['back_end']}) | {r['total_yaw_deg']:.0f} | "
            f"{math.degrees(r['max_yaw_rate_radps']):.1f} | {r['min_clearance_m']:.3f} | {r['length_m']:.1f} m / {r['duration_s']:.1f} s | "
            f"{r['stage_time_s']['total']:.2f} | {r.get('casc_mean_error_m', float('nan')):.5f} / {r.get('casc_max_error_m', float('nan')):.4f} | "
            f"{r.get('casc_collisions', '-')} | {1e3 * r.get('cascnf_mean_error_m', float('nan')):.3f} | "
            f"{r.get('paper_mean_error_m', float('nan')):.3f} | {r.get('paper_collisions', '-')}"
            f"{' (diverged)' if r.get('paper_diverged') else ''} |")
    return head + "\n".join(lines)


def replay_flight(layout: str, unit: int, method: str, work_dir: Path, controller: str, noise: bool,
                  published_dir: str | None = None):
    """One published CSV flown in a sweep worker (mars_link.apps.planning_eval.replay_published); each controller
    converts into its own directory (two flights of one CSV may run at once)."""
    return replay_published(layout, unit, method, work_dir / KEYS[controller, noise], published_dir,
                            controller=controller, noise=noise)


def replay(out: Path, pool: PoolSpec, published_dir: str | None = None) -> list[dict]:
    for layout, _ in PAPER_CASES:  # all there, or one line saying where to get them, before any flight
        for method in ("ours", "svsdf"):
            published_csv(layout, method, published_dir)
    tasks = [(layout, unit, method, out / "paper_csv", controller, noise, published_dir)
             for layout, unit in PAPER_CASES for method in ("ours", "svsdf") for controller, noise in CONTROLLERS]
    flights = iter(values_or_raise(map_flights(replay_flight, tasks, pool, print_progress(len(tasks), "replay flights")),
                                   "replay flight"))
    rows = []
    for layout, unit in PAPER_CASES:
        for method in ("ours", "svsdf"):
            row = {"layout": layout, "failed_unit": unit, "method": method}
            for controller, noise in CONTROLLERS:
                metrics, f = next(flights)
                key = "casc" if controller == "cascaded" else "paper"
                row.update(metrics)
                row.update({f"{key}_mean_error_m": f.mean_error_m, f"{key}_max_error_m": f.max_error_m,
                            f"{key}_collisions": f.collisions, f"{key}_min_clearance_m": f.min_clearance_m,
                            f"{key}_diverged": f.diverged})
            rows.append(row)
            log(f"replay {layout} u{unit} {method}: {json.dumps(row)}")
    return rows


def replay_table(rows: list[dict]) -> str:
    head = ("| case | published path | total yaw [deg] | max yaw rate [deg/s] | paper ctrl+hybrid mean / max err [m] | "
            "wall contacts (min clearance) | cascaded+hybrid mean err [m] | wall contacts |\n|---|---|---|---|---|---|---|---|\n")
    return head + "\n".join(
        f"| {r['layout']} u{r['failed_unit']} | {r['method']} | {r['total_yaw_deg']:.0f} | {r['max_yaw_rate_degps']:.1f} | "
        f"{r['paper_mean_error_m']:.3f} / {r['paper_max_error_m']:.2f}{' (diverged)' if r['paper_diverged'] else ''} | "
        f"{r['paper_collisions']} ({r['paper_min_clearance_m']:.3f}) | {r['casc_mean_error_m']:.4f} | {r['casc_collisions']} |"
        for r in rows)


def forest(out: Path, seeds: int, density: float, margin: float) -> list[dict]:
    params = PlanParams(margin_m=margin)
    forest_params = ForestParams(density_per_100m2=density)
    return forest_sweep(range(seeds), params=params, forest=forest_params,
                        on_result=lambda r: log(f"forest seed {r['seed']} {r['method']}: success {r['success']} "
                                                f"clearance {r['min_clearance_m']:.3f} total {r['t_total']:.2f} s"))


def forest_table(rows: list[dict], density: float) -> str:
    out = [f"Forest 50 x 20 m, {density:g} trunks per 100 m² (radius 0.15-0.4 m), 3x2 unit 2 failed, {len(rows) // 2} seeds:\n",
           "| method | success | by MINCO | min clearance [m] (median / worst of successes) | total yaw [deg] (median) | sdf [s] | table [s] | A* [s] | back end [s] | validation [s] | total [s] (median / max) |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for method in ("ours", "svsdf"):
        rs = [r for r in rows if r["method"] == method]
        ok = [r for r in rs if r["success"]]
        clr = [r["min_clearance_m"] for r in ok]

        def med(key):
            vals = [r.get(key, 0.0) for r in rs]
            return f"{np.median(vals):.3f}"
        minco = sum(r.get("back_end") == "minco" for r in ok)
        yaw = np.median([r["total_yaw_deg"] for r in ok]) if ok else float("nan")
        out.append(f"| {method} | {len(ok)}/{len(rs)} | {minco} | {np.median(clr) if clr else float('nan'):.3f} / {min(clr) if clr else float('nan'):.3f} | {yaw:.0f} | "
                   f"{med('t_sdf')} | {med('t_clearance_table')} | {med('t_front_end')} | {med('t_back_end')} | {med('t_validation')} | "
                   f"{med('t_total')} / {max(r.get('t_total', 0.0) for r in rs):.2f} |")
    return "\n".join(out)


def forest_plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    for k, method in enumerate(("ours", "svsdf")):
        rs = [r for r in rows if r["method"] == method]
        seeds = [r["seed"] + (k - 0.5) * 0.3 for r in rs]
        ax[0].bar(seeds, [r["min_clearance_m"] if r["success"] else 0 for r in rs], width=0.3, label=method)
        ax[1].bar(seeds, [r["t_total"] for r in rs], width=0.3, label=method)
    ax[0].set_ylabel("min clearance [m] (0 = failed)")
    ax[1].set_ylabel("planning time [s]")
    for a in ax:
        a.set_xlabel("forest seed")
        a.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--what", default="walls,replay,forest")
    ap.add_argument("--seeds", type=int, default=20, help="forest seeds")
    ap.add_argument("--flight-seeds", type=int, default=3, help="noisy closed-loop flights per walls plan")
    ap.add_argument("--density", type=float, default=10.0, help="forest trunks per 100 m²")
    ap.add_argument("--margin", type=float, default=0.3, help="planning margin on the walls [m]")
    ap.add_argument("--out", default="runs/planning_eval")
    ap.add_argument("--published", metavar="DIR", default=None,
                    help="folder of the published planner CSVs for --what replay (not shipped; default: "
                         "$MARS_LINK_PUBLISHED_PLANS). Where to get them: mars_link.apps.planning_eval.PUBLISHED_SOURCE")
    add_pool(ap)  # --workers / --scheduler: the walls and replay flights go through the sweep's executor
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    what = set(args.what.split(","))
    results = {}
    t0 = time.perf_counter()
    if "walls" in what:
        results["walls"] = walls(out, args.margin, args.flight_seeds, pool_from_args(args))
        print(f"\n### Walls map (margin {args.margin} m)\n\n" + walls_table(results["walls"]))
    if "replay" in what:
        try:
            results["replay"] = replay(out, pool_from_args(args), args.published)
        except UserInputError as exc:
            log(f"planning_eval: {exc}")
            return 2
        print("\n### Published planner CSVs replayed\n\n" + replay_table(results["replay"]))
    if "forest" in what:
        results["forest"] = forest(out, args.seeds, args.density, 0.1)
        forest_plot(results["forest"], out / "forest.png")
        print("\n### Random forests\n\n" + forest_table(results["forest"], args.density))
    write_json(out / "results.json", results, indent=1)
    log(f"done in {time.perf_counter() - t0:.0f} s; results and PNGs in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
