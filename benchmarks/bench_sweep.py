"""What local parallel workers buy a sweep (mars-link sweep), measured in one invocation.

    python benchmarks/bench_sweep.py [--flights 200] [--workers 1,2] [--rounds 4] [--dask 2]
                                     [--scenario spiral_3x2] [--faults random:1] [--quick] [--json]

The same sweep (default: 200 flights of the bundled 3x2 spiral, full length, each with one random
rotor failure, eta 0, drawn from the sweep seed and the flight's slot) flown in full by each worker
count on local processes (mars_link.apps.sweep_pool). Why rounds: the machine is shared and its load drifts
over minutes, so the flights are cut into `--rounds` chunks and each chunk is flown by every worker
count in turn (the order reversed every round), each count on its own pool opened once (its start-up
counted in its first round). Printed per worker count: wall time (sum over rounds), flights per
second, the workers' CPU seconds (the same work whatever the count), the load average over its rounds;
then wall time / the first count's, and whether every flight's result columns (all but wall time) are
identical across the counts. `--dask N` then flies the whole sweep once more on a Dask LocalCluster of N
worker processes started here (loopback) and checks its rows too.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import sys
import time
from contextlib import ExitStack
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from record import Recorder, add_json_option, apply_quick  # noqa: E402
from mars_link.apps.sweep import RESULT_FIELDS, parse_faults, plan_sweep, read_scenario_doc  # noqa: E402
from mars_link.apps.sweep_cli import run_sweep  # noqa: E402
from mars_link.apps.sweep_pool import PoolSpec, open_pool  # noqa: E402
from mars_link.apps.sweep_report import cell  # noqa: E402


def children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def proc_cpu_s(pids: list[int]) -> float:
    """CPU seconds of live worker processes (a pool's workers are reaped only when it closes)."""
    import psutil

    total = 0.0
    for pid in pids:
        try:
            t = psutil.Process(pid).cpu_times()
            total += t.user + t.system
        except psutil.NoSuchProcess:
            pass
    return total


def autogroup_on() -> bool:
    """Linux's autogroup: CPU shared per session first, then per process inside it."""
    try:
        return Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1"
    except OSError:
        return False


def results(rows: list[dict]) -> list[tuple[str, ...]]:
    return [tuple(cell(r[k]) for k in RESULT_FIELDS) for r in rows]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=200)
    ap.add_argument("--workers", default="1,2", help="worker counts compared (the first is the reference)")
    ap.add_argument("--rounds", type=int, default=4, help="chunks of the sweep, each flown by every count in turn")
    ap.add_argument("--scenario", default="spiral_3x2")
    ap.add_argument("--faults", default="random:1")
    ap.add_argument("--dask", type=int, default=0, help="also on a Dask LocalCluster of this many worker processes")
    ap.add_argument("--quick", action="store_true", help="4 flights in 2 rounds")
    add_json_option(ap)
    args = ap.parse_args(argv)
    apply_quick(ap, args, flights=4, rounds=2)
    rec = Recorder.start("bench_sweep", args)
    counts = [int(w) for w in args.workers.split(",")]
    doc, src = read_scenario_doc(args.scenario)
    plan = plan_sweep(doc, src, args.flights, None, parse_faults(args.faults))
    n = len(plan.flights)
    print(f"{args.scenario}: {n} flights, faults {args.faults}, {os.cpu_count()} cores, {args.rounds} rounds, "
          f"load {os.getloadavg()[0]:.1f}", flush=True)
    stats = {w: {"wall_s": 0.0, "cpu_s": 0.0, "rows": [], "loads": []} for w in counts}
    chunk = -(-n // args.rounds)
    t_all = time.perf_counter()
    with ExitStack() as stack:
        pools = {}
        for k in range(args.rounds):
            part = dataclasses.replace(plan, flights=plan.flights[k * chunk:(k + 1) * chunk])
            if not part.flights:
                break
            for w in counts if k % 2 == 0 else counts[::-1]:
                s = stats[w]
                load0, t0 = os.getloadavg()[0], time.perf_counter()
                if w not in pools:  # opened in its first round: the start-up is part of its wall time
                    pools[w] = stack.enter_context(open_pool(PoolSpec(w)))
                cpu0 = proc_cpu_s(list(getattr(pools[w], "_processes", {}) or {}))
                s["rows"] += run_sweep(part, PoolSpec(w), executor=pools[w])
                s["wall_s"] += time.perf_counter() - t0
                s["cpu_s"] += proc_cpu_s(list(getattr(pools[w], "_processes", {}) or {})) - cpu0
                s["loads"] += [load0, os.getloadavg()[0]]
                print(f"  round {k + 1}/{args.rounds}: {w} worker(s) flew {len(part.flights)} flights in "
                      f"{time.perf_counter() - t0:.1f} s (load {load0:.1f} -> {os.getloadavg()[0]:.1f}); "
                      f"{time.perf_counter() - t_all:.0f} s in all", file=sys.stderr, flush=True)
    base = stats[counts[0]]
    runs = [(str(w), stats[w]) for w in counts]
    if args.dask:
        from distributed import LocalCluster

        load0, t0, cpu0 = os.getloadavg()[0], time.perf_counter(), children_cpu_s()
        with LocalCluster(n_workers=args.dask, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address=":0") as cluster:
            rows = run_sweep(plan, PoolSpec(None, cluster.scheduler_address))
        runs.append((f"dask {args.dask}", {"wall_s": time.perf_counter() - t0, "cpu_s": float("nan"), "rows": rows,
                                           "loads": [load0, os.getloadavg()[0]]}))
        print(f"  dask LocalCluster of {args.dask}: {n} flights in {runs[-1][1]['wall_s']:.1f} s", file=sys.stderr,
              flush=True)
    print()
    print(f"| workers | wall [s] | flights/s | workers' CPU [s] | cores used (CPU / wall) | load avg over its rounds "
          f"(min-max) | wall / {counts[0]} worker(s) |")
    print("|---|---|---|---|---|---|---|")
    for label, s in runs:
        print(f"| {label} | {s['wall_s']:.1f} | {len(s['rows']) / s['wall_s']:.2f} | {s['cpu_s']:.0f} | "
              f"{s['cpu_s'] / s['wall_s']:.2f} | {min(s['loads']):.1f}-{max(s['loads']):.1f} | "
              f"{s['wall_s'] / base['wall_s']:.3f} |")
        rec.figure(f"flights_per_s_{label.replace(' ', '_')}", len(s["rows"]) / s["wall_s"], "flights/s",
                   f"{label} worker(s), {n} flights of {args.scenario}; {s['cpu_s'] / s['wall_s']:.2f} cores used")
        if s is not base:
            (rec.headline if label == str(counts[-1]) else rec.figure)(
                f"wall_vs_{counts[0]}_{label.replace(' ', '_')}", s["wall_s"] / base["wall_s"], "ratio",
                f"sweep wall time with {label} worker(s) / with {counts[0]} (rounds alternated)")
    if autogroup_on():
        print("(Linux autogroup is on: this session's processes share one CPU share against other sessions, so on a "
              "machine other sessions keep busy, more workers get little more CPU: read 'cores used')")
    ref = results(base["rows"])
    same = all(results(s["rows"]) == ref for _, s in runs)
    raised = sum(row["error"] is not None for row in base["rows"])
    completed = sum(bool(row["completed"]) for row in base["rows"])
    print(f"\nidentical results per flight across {', '.join(label for label, _ in runs)} worker(s): {same} "
          f"({len(base['rows'])} flights; {completed} completed, {raised} raised)")
    rec.figure("identical_results", same, "", "every flight's result columns identical across the worker counts")
    rec.finish()
    if not same:
        for label, s in runs:
            for i, (a, b) in enumerate(zip(ref, results(s["rows"]))):
                if a != b:
                    print(f"  {label}: flight {i} differs: {a} vs {b}")
                    break
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
