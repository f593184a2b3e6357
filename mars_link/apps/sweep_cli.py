"""`mars-link sweep SCENARIO [--seeds N] [--faults random:A-B[,units|rotors|whole-units][,eta=..]] [--param KEY=V1,V2,...]
[--workers W] [--scheduler ADDRESS] [--out DIR] [--mcap]`: the verb (its options: mars_link.apps.cli), and
`run_sweep` for scripts.

Why rows are appended to sweep.partial.csv as flights finish: a sweep of hours that is stopped keeps
every flight it flew; sweep.csv (in flight order) replaces it at the end.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import Executor
from pathlib import Path
from typing import Callable

from mars_link.apps.sweep import FlightSpec, SweepPlan, error_row, fly_flight
from mars_link.apps.sweep_pool import Outcome, PoolSpec, open_pool, run_all
from mars_link.apps.sweep_report import ROW_FIELDS, cell, csv_header
from mars_link.flight.fault_scoring import ISOLATION_DEADLINE_S


def run_sweep(plan: SweepPlan, pool: PoolSpec, out_dir: Path | None = None, mcap: bool = False,
              on_done: Callable[[int, dict], None] | None = None, executor: Executor | None = None) -> list[dict]:
    """Fly every flight of `plan` on `pool`; the rows in flight order. A flight that raises is a row with its
    error. `out_dir`: rows appended to sweep.partial.csv as they come; with `mcap`, flight i writes
    flights/<i>/run.mcap there. `executor`: an open one to use instead of opening `pool` (benchmarks)."""
    if mcap and out_dir is None:
        raise ValueError("mcap needs an out_dir")
    flights_dir = None if out_dir is None else out_dir / "flights"
    args = [(plan.doc, plan.src, spec, None if not mcap else str(flights_dir / f"{spec.index:04d}"))
            for spec in plan.flights]
    rows: list[dict | None] = [None] * len(plan.flights)
    partial = None if out_dir is None else (out_dir / "sweep.partial.csv").open("w", newline="", encoding="utf-8")
    writer = None if partial is None else csv_header(partial)

    def done(i: int, outcome: Outcome) -> None:
        spec: FlightSpec = plan.flights[i]
        row = outcome.value if outcome.error is None else error_row(spec, outcome.error, outcome.wall_s)
        rows[i] = row
        if writer is not None:
            writer.writerow([cell(row.get(k)) for k in ROW_FIELDS])
            partial.flush()
        if on_done is not None:
            on_done(i, row)

    try:
        if executor is not None:
            run_all(executor, fly_flight, args, done)
        else:
            with open_pool(pool) as opened:
                run_all(opened, fly_flight, args, done)
    finally:
        if partial is not None:
            partial.close()
    return [r for r in rows if r is not None]


def sweep_command(args: argparse.Namespace, default_out: Callable[[str], Path]) -> int:
    """The verb: everything checked before the first flight (one line, exit 2), then the flights with a
    progress bar, then sweep.csv, sweep.md, sweep.json and plots/. Exit 0 when every flight flew (diverged
    or not), 1 when one raised."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from mars_link.core import validation as v
    from mars_link.logs.outputs import write_json
    from mars_link.apps.sweep import parse_faults, parse_param, plan_sweep, read_scenario_doc
    from mars_link.apps.sweep_pool import check_workers, connect
    from mars_link.apps.sweep_report import (isolation, markdown, plot_distributions, plot_isolation_delays, totals,
                                             write_csv, write_faults_csv)

    check_workers(args.workers)
    faults = parse_faults(args.faults)
    params = [parse_param(t) for t in args.param]
    doc, src = read_scenario_doc(args.scenario)
    plan = plan_sweep(doc, src, args.seeds, args.seed, faults, params)
    pool = PoolSpec(args.workers, args.scheduler)
    if args.scheduler:  # an unreachable scheduler: one line, exit 2, before the sweep directory exists
        connect(args.scheduler).close()
    out = v.claim_out_dir(args.out or default_out(plan.name + "-sweep"), force=args.force)
    console = Console(stderr=True)
    console.print(f"sweep {plan.name}: {len(plan.flights)} flights on {pool.describe()} -> {out}")
    t0 = time.perf_counter()
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=console, disable=args.quiet) as progress:
        task = progress.add_task(plan.name, total=len(plan.flights))
        failed = [0]

        def on_done(i: int, row: dict) -> None:
            failed[0] += row.get("error") is not None
            progress.update(task, advance=1, description=f"{plan.name} ({failed[0]} raised)" if failed[0] else plan.name)

        rows = run_sweep(plan, pool, out, args.mcap, on_done)
    wall = time.perf_counter() - t0
    write_csv(out / "sweep.csv", rows)
    if faults is not None:
        write_faults_csv(out / "faults.csv", rows)
    (out / "sweep.partial.csv").unlink(missing_ok=True)
    title = f"sweep {plan.name}: {len(rows)} flights, sweep seed {plan.sweep_seed}" + (
        f", faults {args.faults}" if args.faults else "")
    (out / "sweep.md").write_text(markdown(rows, title), encoding="utf-8")
    summary = {"scenario": plan.name, "source": plan.src, "sweep_seed": plan.sweep_seed, "seeds": args.seeds,
               "faults": args.faults, "params": args.param, "pool": pool.describe(), "wall_time_s": wall,
               **totals(rows), **({"isolation": isolation(rows)} if faults is not None else {})}
    write_json(out / "sweep.json", summary)
    if not args.no_plots:
        plot_distributions(rows, out / "plots", title)
        if faults is not None:
            plot_isolation_delays(rows, out / "plots", title)
    print(f"{summary['flights']} flights in {wall:.1f} s: {summary['completed']} completed, {summary['diverged']} "
          f"diverged, {summary['raised']} raised" + ("" if summary["median_mean_error_m"] is None else
                                                       f"; median mean error {summary['median_mean_error_m']:.4f} m"))
    if faults is not None:
        iso = summary["isolation"]
        print(f"{iso['faults']} faults: " + ", ".join(
            f"{label} {'—' if iso[key] is None else f'{100 * iso[key]:.0f} %'}" for key, label in (
                ("isolated_in_time_fraction", f"isolated correctly within {ISOLATION_DEADLINE_S:g} s"),
                ("false_belief_rate", "flights with a false belief"), ("divergence_rate", "diverged"))))
    print(f"results: {out / 'sweep.csv'}, {out / 'sweep.md'}" + (f", {out / 'faults.csv'}" if faults else ""))
    return 0 if summary["raised"] == 0 else 1
