"""What local parallel workers buy a sweep (mars-link sweep), measured in one invocation.

    python benchmarks/bench_sweep.py [--flights 200] [--workers 1,2] [--dask 2] [--scenario spiral_3x2] [--faults random:1]

The same sweep (default: 200 flights of the bundled 3x2 spiral, full length, each with one random
rotor failure, eta 0, drawn from the sweep seed and the flight's slot) flown once per worker count on
local processes (mars_link.sweep_pool), one after the other. Printed per worker count: wall time,
flights per second, the workers' CPU seconds (the same work whatever the count), the load average
before and after; then wall time of W workers / wall time of the first count, and whether every
flight's result columns (all but wall time) are identical across the counts. The machine is shared:
compare the figures of one invocation, and read the load averages beside them. `--dask N` also flies the
sweep on a Dask LocalCluster of N worker processes started here (loopback), after the local counts.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mars_link.sweep import RESULT_FIELDS, parse_faults, plan_sweep, read_scenario_doc  # noqa: E402
from mars_link.sweep_cli import run_sweep  # noqa: E402
from mars_link.sweep_pool import PoolSpec  # noqa: E402
from mars_link.sweep_report import cell  # noqa: E402


def children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def fly(plan, workers: int, scheduler: str | None = None) -> dict:
    n = len(plan.flights)
    label = f"dask {workers}" if scheduler else str(workers)
    t0, cpu0, load0 = time.perf_counter(), children_cpu_s(), os.getloadavg()[0]
    done = [0]

    def on_done(i: int, row: dict) -> None:
        done[0] += 1
        if done[0] % 20 == 0 or done[0] == n:
            print(f"  {label} worker(s): {done[0]}/{n} flights, {time.perf_counter() - t0:.0f} s", file=sys.stderr,
                  flush=True)

    rows = run_sweep(plan, PoolSpec(workers, scheduler), on_done=on_done)
    wall = time.perf_counter() - t0
    return {"workers": label, "wall_s": wall, "cpu_s": children_cpu_s() - cpu0, "load": (load0, os.getloadavg()[0]),
            "rows": rows, "results": [tuple(cell(r[k]) for k in RESULT_FIELDS) for r in rows]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=200)
    ap.add_argument("--workers", default="1,2", help="worker counts, flown in this order")
    ap.add_argument("--scenario", default="spiral_3x2")
    ap.add_argument("--faults", default="random:1")
    ap.add_argument("--dask", type=int, default=0, help="also on a Dask LocalCluster of this many worker processes")
    args = ap.parse_args(argv)
    counts = [int(w) for w in args.workers.split(",")]
    doc, src = read_scenario_doc(args.scenario)
    plan = plan_sweep(doc, src, args.flights, None, parse_faults(args.faults))
    print(f"{args.scenario}: {len(plan.flights)} flights, faults {args.faults}, {os.cpu_count()} cores", flush=True)
    runs = [fly(plan, w) for w in counts]
    if args.dask:
        from distributed import LocalCluster

        with LocalCluster(n_workers=args.dask, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address=":0") as cluster:
            runs.append(fly(plan, args.dask, cluster.scheduler_address))
    base = runs[0]
    print()
    print("| workers | wall [s] | flights/s | workers' CPU [s] | load avg before / after | wall / "
          f"{base['workers']} worker(s) |")
    print("|---|---|---|---|---|---|")
    for r in runs:
        print(f"| {r['workers']} | {r['wall_s']:.1f} | {len(r['rows']) / r['wall_s']:.2f} | {r['cpu_s']:.0f} | "
              f"{r['load'][0]:.1f} / {r['load'][1]:.1f} | {r['wall_s'] / base['wall_s']:.3f} |")
    same = all(r["results"] == base["results"] for r in runs)
    raised = sum(row["error"] is not None for row in base["rows"])
    completed = sum(bool(row["completed"]) for row in base["rows"])
    print(f"\nidentical results per flight across {', '.join(str(r['workers']) for r in runs)} worker(s): {same} ({len(base['rows'])} flights; "
          f"{completed} completed, {raised} raised)")
    if not same:
        for i, rows in enumerate(zip(*(r["results"] for r in runs))):
            if len(set(rows)) > 1:
                print(f"  flight {i} differs: {rows}")
                break
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
