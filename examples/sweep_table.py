"""A small sweep through mars-link's Python API: every fault-tolerant allocation mode against one rotor
failure, a few seeds each, as a results table.

Nothing needs to run beside it: every flight is flown in this process (world, unit firmware and
coordinator wired by direct calls, faster than real time). For big sweeps (many seeds, parameter grids,
every core or a Dask cluster) use `mars-link sweep`, which writes sweep.csv and sweep.md.
"""

from __future__ import annotations

import argparse
import statistics
import sys

from mars_link.config.scenario import FTC_MODES, load_scenario, parse_fault_arg
from mars_link.core.errors import UserInputError
from mars_link.flight.runner import run_scenario


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="spiral_3x2", help="bundled scenario name or TOML file (default: %(default)s)")
    parser.add_argument("--ftc", default="none,partial,qp",
                        help=f"comma-separated allocation modes to compare, of {', '.join(FTC_MODES)} (default: %(default)s)")
    parser.add_argument("--fault", default="2:2=0@2", metavar="UNIT[:ROTOR]=ETA[@T]",
                        help="the failure every flight meets, as `mars-link run --fault` (default: %(default)s)")
    parser.add_argument("--seeds", type=int, default=3, help="flights per mode (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=10.0, help="simulated seconds per flight (default: %(default)s)")
    args = parser.parse_args()
    modes = [m.strip() for m in args.ftc.split(",") if m.strip()]
    unknown = [m for m in modes if m not in FTC_MODES]
    if unknown or not modes or args.seeds < 1 or not args.duration > 0:
        what = f"unknown --ftc {', '.join(unknown)}" if unknown or not modes else "--seeds and --duration must be positive"
        print(f"sweep_table: {what}", file=sys.stderr)
        return 2

    rows = []
    try:
        fault = parse_fault_arg(args.fault)
        for mode in modes:
            for seed in range(1, args.seeds + 1):
                scenario = load_scenario(args.scenario)  # a fresh copy per flight
                scenario.ftc = mode
                scenario.faults = [fault]
                scenario.sim.duration_s = args.duration
                summary = run_scenario(scenario, out_dir=None, seed=seed, plots=False, mcap=False)
                rows.append((mode, seed, summary["diverged"], summary["rmse_m"], summary["max_error_m"],
                             summary["max_tilt_deg"]))
                print(f"flown: ftc {mode}, seed {seed}", file=sys.stderr, flush=True)
    except UserInputError as exc:  # a misspelled scenario, a bad --fault: one line, as the CLI does
        print(f"sweep_table: {exc}", file=sys.stderr)
        return 2

    print(f"\n{args.scenario}, fault {fault.describe()}, {args.duration:g} s per flight\n")
    print("| ftc | seed | diverged | rmse (m) | max error (m) | max tilt (deg) |")
    print("|---|---|---|---|---|---|")
    for mode, seed, diverged, rmse, max_error, tilt in rows:
        print(f"| {mode} | {seed} | {'yes' if diverged else 'no'} | {rmse:.3f} | {max_error:.3f} | {tilt:.1f} |")
    print("\n| ftc | mean rmse (m) |")
    print("|---|---|")
    for mode in modes:
        print(f"| {mode} | {statistics.mean(r[3] for r in rows if r[0] == mode):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
