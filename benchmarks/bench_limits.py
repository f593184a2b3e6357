"""What a run allocates, against the caps of mars_link/core/limits.py and run_log.PLOT_ROWS_MAX.

    python benchmarks/bench_limits.py [--quick] [--json]

Each case runs in a fresh interpreter (so one case's memory does not hide in another's) and reports
the peak of Python allocations (tracemalloc) and the peak resident size:
  * memory per trial: `run_scenario` on hover_1x1 with 2 and 12 trials of 2 s; the difference / 10;
  * memory per simulated second: hover_3x2 (perfect sensors) for 20, 80 and 320 s (flat once the
    plot rows reach PLOT_ROWS_MAX, 40 s at 100 Hz);
  * memory in the unit count: an in-process flight of 0.05 s on square layouts up to 20x20 (400
    units), against the byte budget's model of mars_link/core/limits.py (its linear cost per unit).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

from record import Recorder, add_json_option

CASE = r"""
import json, resource, sys, time, tracemalloc
from mars_link.core.assembly import parse_layout
from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario
kind, arg = sys.argv[1], float(sys.argv[2])
tracemalloc.start()
t0 = time.perf_counter()
if kind == "trials":
    sc = load_scenario("hover_1x1"); sc.sim.duration_s = 2.0
    run_scenario(sc, None, trials=int(arg), plots=False)
elif kind == "duration":
    sc = load_scenario("hover_3x2"); sc.sim.duration_s = arg; sc.sim.noise = False
    run_scenario(sc, None, plots=False)
else:
    n = int(arg)
    sc = load_scenario("hover_3x2"); sc.layout = parse_layout(",".join(["X" * n] * n)); sc.sim.duration_s = 0.05
    sc.ftc = "qp"; sc.sim.noise = True  # (the largest: the QP's dense Hessian, the estimator's rows)
    run_scenario(sc, None, plots=False)
print(json.dumps({"peak_mb": tracemalloc.get_traced_memory()[1] / 1e6,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
                  "wall_s": time.perf_counter() - t0}))
"""


def case(kind: str, arg: float) -> dict:
    out = subprocess.run([sys.executable, "-c", CASE, kind, str(arg)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller cases (a look, not the documented numbers)")
    add_json_option(ap)
    args = ap.parse_args()
    rec = Recorder.start("bench_limits", args)
    lo_t, hi_t = (2, 6) if args.quick else (2, 12)
    a, b = case("trials", lo_t), case("trials", hi_t)
    print(f"trials {lo_t}: peak {a['peak_mb']:.2f} MB; {hi_t}: {b['peak_mb']:.2f} MB -> "
          f"{(b['peak_mb'] - a['peak_mb']) / (hi_t - lo_t) * 1e3:.1f} KB per trial")
    rec.figure("memory_per_trial_kb", (b['peak_mb'] - a['peak_mb']) / (hi_t - lo_t) * 1e3, "KB",
               f"hover_1x1, 2 s trials, {lo_t} -> {hi_t} trials, peak Python allocations")
    durations = (10.0, 40.0, 80.0) if args.quick else (20.0, 80.0, 320.0)
    runs = [case("duration", d) for d in durations]
    for (d0, r0), (d1, r1) in zip(zip(durations, runs), zip(durations[1:], runs[1:])):
        print(f"duration {d0:.0f} -> {d1:.0f} s: peak {r0['peak_mb']:.2f} -> {r1['peak_mb']:.2f} MB, "
              f"{(r1['peak_mb'] - r0['peak_mb']) / (d1 - d0) * 1e3:.1f} KB per simulated second "
              f"({d1 / r1['wall_s']:.1f}x real time)")
        rec.figure(f"memory_per_sim_s_{d0:.0f}_{d1:.0f}_kb", (r1['peak_mb'] - r0['peak_mb']) / (d1 - d0) * 1e3, "KB",
                   f"hover_3x2 perfect sensors, {d0:.0f} -> {d1:.0f} s simulated, per simulated second")
    from mars_link.core.limits import BYTES_PER_UNIT_SQUARED, MAX_UNITS_PER_RUN, RUN_BUDGET_BYTES, run_bytes

    sides = (2, 4, 8) if args.quick else (2, 4, 8, 12, 14, 20)
    peaks = {}
    for n in sides:
        r = case("units", n)
        peaks[n * n] = r["peak_mb"] * 1e6
        print(f"{n}x{n} = {n * n:3d} units: peak {r['peak_mb']:7.2f} MB of Python allocations, "
              f"resident {r['rss_mb']:6.1f} MB, {r['wall_s']:.1f} s; the cap's model says "
              f"{run_bytes(n * n) / 1e6:7.2f} MB")
        rec.figure(f"peak_{n}x{n}_mb", r["peak_mb"], "MB", f"{n * n} units, 0.05 s, qp, noise on; the cap's model "
                   f"{run_bytes(n * n) / 1e6:.2f} MB")
    lo, hi = min(peaks), max(peaks)  # the linear part per unit, the QP's dense Hessian taken out
    linear = [(peaks[n] - BYTES_PER_UNIT_SQUARED * n * n) for n in (lo, hi)]
    print(f"linear part: {(linear[1] - linear[0]) / (hi - lo) / 1e3:.0f} KB per unit ({lo} -> {hi} units); "
          f"the cap: {MAX_UNITS_PER_RUN} units within {RUN_BUDGET_BYTES / 2**20:.0f} MiB (mars_link/core/limits.py)")
    rec.headline("memory_per_unit_kb", (linear[1] - linear[0]) / (hi - lo) / 1e3, "KB",
                 f"linear part of the peak per unit, {lo} -> {hi} units (the QP's dense Hessian taken out)")
    rec.finish()


if __name__ == "__main__":
    main()
