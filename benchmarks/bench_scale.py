"""Issue 16's in-process figures, measured in one run (ratios on the same machine state).

    python benchmarks/bench_scale.py [--quick] [--skip-flights] [--json]

1. The default scenario (`mars-link run`: 3x2 spiral, 500 Hz physics, noise on, run.mcap written) as
   wall-clock and CPU-time real-time factors, with bare JSBSim stepping of the same body (per-step rotor
   writes) timed in the same run beside it, and the same flight without run.mcap.
2. The helix, noise on, qp allocation, on 10x10 (100 units) and 20x20 (400 units): whole flights.
   The 10x10's units batched (the default) against the units taken one by one, alternated.
3. The estimator's cost per control step against the unit count N = 1, 9, 25, 49, 100, 400 (synthetic
   noisy hover at 100 Hz, positions with velocities at 50 Hz: the runner's rhythm) and the fitted
   log-log slope of cost against N.
No environment variable is needed: the project sets its BLAS pools itself (mars_link.runtime.blas_threads).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mars_link.core.assembly import AssemblyModel, parse_layout
from mars_link.runtime.blas_threads import single_blas_thread
from mars_link.flight.engine import InProcessUnits
from mars_link.models.estimation import AssemblyEstimator
from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario
from mars_link.core.state import ImuSample, PositionSample

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_inproc import bare_physics_steps_per_s  # noqa: E402  (a sibling script)
from record import Recorder, add_json_option  # noqa: E402

SIDES = {1: (1, 1), 9: (3, 3), 25: (5, 5), 49: (7, 7), 100: (10, 10), 400: (20, 20)}


def timed_flight(scenario, out: Path | None, mcap: bool) -> tuple[dict, float]:
    """(summary, CPU seconds) of one in-process flight."""
    cpu0 = time.process_time()
    summary = run_scenario(scenario, out, trials=1, plots=False, mcap=mcap)
    return summary, time.process_time() - cpu0


def default_scenario(duration_s: float | None, rec: Recorder) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        warm = load_scenario("spiral_3x2")
        warm.sim.duration_s = 0.5
        run_scenario(warm, Path(tmp) / "warm", plots=False)  # imports and first-use costs stay out
        sc = load_scenario("spiral_3x2")
        if duration_s:
            sc.sim.duration_s = duration_s
        with_mcap, cpu_mcap = timed_flight(sc, Path(tmp) / "run", mcap=True)
        no_mcap, cpu_plain = timed_flight(sc, Path(tmp) / "plain", mcap=False)
    bare = bare_physics_steps_per_s(sc) / sc.sim.physics_hz
    sim = with_mcap["sim_time_s"]
    print(f"default scenario (spiral_3x2, {sc.sim.physics_hz:g} Hz physics, noise on), {sim:.1f} s simulated:")
    print(f"  mars-link run (run.mcap on): {with_mcap['real_time_factor']:6.1f}x real time (wall), "
          f"{sim / cpu_mcap:6.1f}x per CPU second of this process")
    print(f"  without run.mcap:            {no_mcap['real_time_factor']:6.1f}x real time (wall), "
          f"{sim / cpu_plain:6.1f}x per CPU second")
    print(f"  bare JSBSim, same body:      {bare:6.1f}x real time; the full loop is "
          f"{bare / with_mcap['real_time_factor']:.2f}x slower (without run.mcap "
          f"{bare / no_mcap['real_time_factor']:.2f}x)")
    stages = no_mcap["stage_time_s"]
    steps = sim * sc.sim.control_hz
    print("  per control step (without run.mcap): " + ", ".join(
        f"{k} {1e6 * v / steps:.0f} us" for k, v in stages.items()))
    rec.figure("default_rtf_mcap", with_mcap["real_time_factor"], "x real time", f"spiral_3x2, {sim:.1f} s, run.mcap on")
    rec.figure("default_rtf_no_mcap", no_mcap["real_time_factor"], "x real time", "the same without run.mcap")
    rec.figure("bare_jsbsim_same_body", bare, "x real time", "bare JSBSim stepping of the same body, this run")
    rec.headline("default_loop_vs_bare_jsbsim", with_mcap["real_time_factor"] / bare, "ratio",
                 "default scenario as `mars-link run` flies it: its RTF / bare JSBSim's of the same body (same run)")


def helix(n: int, duration_s: float | None, rec: Recorder) -> None:
    sc = load_scenario("helix_plus5")
    sc.layout = parse_layout(",".join(["X" * n] * n))
    sc.ftc = "qp"
    sc.sim.noise = True
    if duration_s:
        sc.sim.duration_s = duration_s
    summary, cpu_s = timed_flight(sc, None, mcap=False)
    sim = summary["sim_time_s"]
    print(f"helix {n}x{n} ({n * n} units), noise on, qp, {sim:.1f} s simulated: "
          f"{summary['real_time_factor']:.2f}x real time (wall), {sim / cpu_s:.2f}x per CPU second "
          f"(setup included), completed {summary['completed']}, mean error {summary['mean_error_m'] * 1000:.1f} mm")
    steps = sim * sc.sim.control_hz
    print("  per control step: " + ", ".join(f"{k} {1e3 * v / steps:.2f} ms" for k, v in summary["stage_time_s"].items()))
    rec.figure(f"helix_{n}x{n}_rtf", summary["real_time_factor"], "x real time",
               f"{n * n} units, noise on, qp, {sim:.1f} s, wall; {sim / cpu_s:.2f}x per CPU second")


def batched_against_one_by_one(n: int, duration_s: float, runs: int, rec: Recorder) -> None:
    """The in-process units' batched steady state (InProcessUnits.batched) against the units taken one by
    one, flights alternated in one run: the motors stage (every unit's firmware, command in to motor
    outputs out) and the whole flight."""
    sc = load_scenario("helix_plus5")
    sc.layout = parse_layout(",".join(["X" * n] * n))
    sc.ftc = "qp"
    sc.sim.noise = True
    sc.sim.duration_s = duration_s
    figures: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
    try:
        for _ in range(runs):
            for batched in (False, True):
                InProcessUnits.batched = batched
                summary, _ = timed_flight(sc, None, mcap=False)
                figures[batched].append((summary["stage_time_s"]["motors"], summary["real_time_factor"]))
    finally:
        InProcessUnits.batched = True
    steps = duration_s * sc.sim.control_hz
    med = {b: (1e6 * float(np.median([m for m, _ in f])) / steps, float(np.median([r for _, r in f])))
           for b, f in figures.items()}
    print(f"helix {n}x{n}, units batched vs one by one ({runs} flights each of {duration_s:g} s, alternated): "
          f"motors {med[True][0]:.0f} vs {med[False][0]:.0f} us per control step "
          f"({med[True][0] / med[False][0]:.2f}x), real time {med[True][1]:.2f}x vs {med[False][1]:.2f}x")
    rec.figure(f"helix_{n}x{n}_batched_vs_one_by_one", med[True][1] / med[False][1], "ratio",
               f"RTF with the units batched / one by one, {runs} alternated flights of {duration_s:g} s")


def hover_ticks(model: AssemblyModel, n_ticks: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    offsets = np.array([model.unit_position(u) for u in model.unit_ids])
    for k in range(n_ticks):
        t = k / 100.0
        imus = [ImuSample(t, u, rng.normal(0, 0.003, 3), np.array([0.0, 0.0, -9.81]) + rng.normal(0, 0.05, 3))
                for u in model.unit_ids]
        poss = [PositionSample(t, u, np.array([*offsets[i, :2], -1.0]) + rng.normal(0, 0.01, 3),
                               rng.normal(0, 0.05, 3)) for i, u in enumerate(model.unit_ids)] if k % 2 == 0 else []
        yield t, imus, poss


def estimator_cost(n_units: int, n_ticks: int) -> float:
    """Mean microseconds of `AssemblyEstimator.step` per control step (best of 3 passes)."""
    rows, cols = SIDES[n_units]
    model = AssemblyModel.from_layout(["X" * cols] * rows, "mars-ftcc")
    ticks = list(hover_ticks(model, n_ticks + 50))
    best = float("inf")
    for _ in range(3):
        est = AssemblyEstimator(model)
        for t, imus, poss in ticks[:50]:
            est.step(t, imus, poss)
        t0 = time.perf_counter()
        for t, imus, poss in ticks[50:]:
            est.step(t, imus, poss)
        best = min(best, (time.perf_counter() - t0) / n_ticks)
    return best * 1e6


def estimator_scaling(n_ticks: int, rec: Recorder) -> None:
    ns = sorted(SIDES)
    costs = [estimator_cost(n, n_ticks if n <= 100 else max(40, n_ticks // 4)) for n in ns]
    print("estimator per control step (IMU every step, positions + velocities every 2nd):")
    for n, c in zip(ns, costs):
        print(f"  N = {n:4d}: {c:8.1f} us  ({c / n:6.2f} us per unit)")
    slope = np.polyfit(np.log(ns), np.log(costs), 1)[0]
    slope_big = np.polyfit(np.log(ns[2:]), np.log(costs[2:]), 1)[0]
    print(f"  fitted log-log slope over N = 1..400: {slope:.2f}; over N = 25..400: {slope_big:.2f} "
          "(1.0 = linear; the joint update it replaced grows as N^2 in memory and N^3 in its solve)")
    for n, c in zip(ns, costs):
        rec.figure(f"estimator_n{n}_us", c, "us", f"estimator per control step, {n} units")
    rec.figure("estimator_slope", slope, "log-log slope", "estimator cost against N = 1..400 (target <= 1.1)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter flights and fewer ticks (a look, not the figures)")
    ap.add_argument("--skip-flights", action="store_true", help="only the estimator's scaling")
    add_json_option(ap)
    args = ap.parse_args()
    single_blas_thread()
    rec = Recorder.start("bench_scale", args)
    if not args.skip_flights:
        default_scenario(10.0 if args.quick else None, rec)
        helix(10, 5.0 if args.quick else None, rec)
        batched_against_one_by_one(10, 2.0 if args.quick else 5.0, 3, rec)
        helix(20, 2.0 if args.quick else None, rec)
    estimator_scaling(100 if args.quick else 400, rec)
    rec.finish()


if __name__ == "__main__":
    main()
