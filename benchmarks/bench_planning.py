"""Planning time per stage: walls map (paper 000 scene) and a 50 m random forest.

    python benchmarks/bench_planning.py [--repeats 5] [--quick] [--json]

End to end = map file loaded, SDF, clearance table, A*, back end, exact validation (in process,
median of the repeats; wall clock, and this process's CPU time, which a busy machine inflates less),
plus the whole `mars-link plan` command as a subprocess (Python start-up and imports included) once
per method. Target: under 1 s end to end for a 3x2 (in process).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from record import Recorder, add_json_option, apply_quick  # noqa: E402
from mars_link.core.assembly import AssemblyModel  # noqa: E402
from mars_link.apps.planning_eval import WALLS_CSV, WALLS_GOAL, WALLS_START  # noqa: E402
from mars_link.planning.maps import ForestParams, load_map, random_forest  # noqa: E402
from mars_link.planning.pipeline import Planner, resolve_data_path  # noqa: E402

STAGES = ("map", "sdf", "clearance_table", "front_end", "back_end", "validation", "total", "cpu")


def model_for(layout: str, unit: int) -> tuple[AssemblyModel, np.ndarray]:
    model = AssemblyModel.from_layout(layout)
    eta = model.nominal_eta()
    eta[model.unit_slots(unit)] = 0.0
    return model, eta


def walls_once(layout: str, unit: int, method: str) -> dict:
    model, eta = model_for(layout, unit)
    t0, c0 = time.perf_counter(), time.process_time()
    obstacles = load_map(resolve_data_path(WALLS_CSV), altitude_m=-WALLS_START[2]).with_bounds_around(
        np.array(WALLS_START), np.array(WALLS_GOAL))
    t_map = time.perf_counter() - t0
    res = Planner(obstacles, model, eta).plan(np.array([*WALLS_START[:2], 0.0]), np.array(WALLS_GOAL[:2]), method, WALLS_START[2])
    st = dict(res.stage_time_s, map=t_map)
    st["total"], st["cpu"] = time.perf_counter() - t0, time.process_time() - c0
    st["success"], st["back_end_name"] = res.success, res.backend
    return st


def forest_once(seed: int, method: str, density: float) -> dict:
    model, eta = model_for("XXX,XXX", 2)
    t0, c0 = time.perf_counter(), time.process_time()
    obstacles, start, goal = random_forest(seed, ForestParams(density_per_100m2=density))
    t_map = time.perf_counter() - t0
    res = Planner(obstacles, model, eta).plan(np.array([start[0], start[1], 0.0]), goal, method, -2.0)
    st = dict(res.stage_time_s, map=t_map)
    st["total"], st["cpu"] = time.perf_counter() - t0, time.process_time() - c0
    st["success"], st["back_end_name"] = res.success, res.backend
    return st


def report(name: str, runs: list[dict], rec: Recorder, headline: bool = False) -> None:
    med = {k: float(np.median([r.get(k, 0.0) for r in runs])) for k in STAGES}
    ok = sum(bool(r["success"]) for r in runs)
    minco = sum(r.get("back_end_name") == "minco" for r in runs)
    print(f"{name:<34} " + " ".join(f"{k} {med[k] * 1e3:7.1f} ms" for k in STAGES)
          + f"  ({ok}/{len(runs)} ok, {minco} by the MINCO back end)")
    note = f"{name}: end to end in process, median of {len(runs)} ({ok} ok); CPU {med['cpu']:.3f} s"
    key = name.replace("XXX,XXX", "3x2").replace("XXXX", "4x1").replace(" ", "_")
    (rec.headline if headline else rec.figure)(key + "_total_s", med["total"], "s", note)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--density", type=float, default=10.0)
    ap.add_argument("--quick", action="store_true", help="one run per line, no `mars-link plan` subprocess")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, repeats=1)
    rec = Recorder.start("bench_planning", args)
    print(f"median of {args.repeats} runs per line, in process, OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (cpu = this process's CPU time)")
    for layout, unit in (("XXX,XXX", 2), ("XXXX", 3)):
        for method in ("ours", "svsdf"):
            report(f"walls {layout} u{unit} {method}", [walls_once(layout, unit, method) for _ in range(args.repeats)],
                   rec, headline=(layout, method) == ("XXX,XXX", "ours"))
    for method in ("ours", "svsdf"):
        report(f"forest 50x20 m d={args.density:g} {method}",
               [forest_once(seed, method, args.density) for seed in range(args.repeats)], rec)
    for method in () if args.quick else ("ours", "svsdf"):
        out = ROOT / "runs" / f"bench_plan_{method}"
        cmd = [sys.executable, "-m", "mars_link.apps.cli", "plan", str(resolve_data_path(WALLS_CSV)), "--layout", "XXX,XXX",
               "--fault", "2=0", "--start", ",".join(map(str, WALLS_START)), "--goal", ",".join(map(str, WALLS_GOAL)),
               "--method", method, "--out", str(out), "--quiet"]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
        print(f"mars-link plan (subprocess, walls 3x2 u2 {method}): {time.perf_counter() - t0:.2f} s wall, exit {proc.returncode}")
        rec.figure(f"cli_plan_{method}_s", time.perf_counter() - t0, "s", "whole `mars-link plan`, walls 3x2 u2, subprocess")
    rec.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
