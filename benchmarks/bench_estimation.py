"""Cost per control tick of the estimation stack: AssemblyEstimator.step() and FaultDetector.update().

Synthetic noisy hover at 100 Hz, IMU and position of every unit each tick. The detector is timed
while watching (every tick) and while isolating (the few ticks after an alarm), the latter by
replaying one alarm state. The EKF step is split into its parts (IMU combination, propagation with
filterpy's predict, the stacked position update with the filter's Joseph-form update). Last, the real loop: the
runner's noisy 3x2 spiral (JSBSim), the estimator's cost per control step there and its accuracy
against the truth (issue 5: position RMS < 2 cm, attitude RMS < 0.5 deg).
The step split is the runner's rhythm: IMU every tick, positions with velocities every second tick
(50 Hz), so a "fusion" step propagates and fuses and a "plain" step only propagates; both are timed
hot (median of many; best of 3 runs for the synthetic hover) on the synthetic hover and on the
real spiral (hover_1x1, spiral_3x2 through the runner: JSBSim and the controller run between steps,
so caches are colder there).
Run: python benchmarks/bench_estimation.py [--no-flight] [--split-only] [--quick] [--json]
(`--quick`: no flights, the layouts 1x1 and 3x2 only.)
"""

from __future__ import annotations

import argparse
import copy
import time

import numpy as np

from record import Recorder, add_json_option
from mars_link.core.assembly import AssemblyModel
from mars_link.models.estimation import AssemblyEstimator
from mars_link.models.fault_detection import FaultDetector
from mars_link.core.state import ImuSample, PositionSample

LAYOUTS = {"1x1": ["X"], "2x2": ["XX", "XX"], "3x2": ["XXX", "XXX"], "4x1": ["XXXX"], "3x3": ["XXX", "XXX", "XXX"]}
RATE_HZ = 100.0


def ticks(model: AssemblyModel, n: int, seed: int = 0, lost_slot: int | None = None, t_fault: float = 1e9):
    """Hover: the thrust is exactly the weight until t_fault, then one rotor's thrust is missing."""
    rng = np.random.default_rng(seed)
    hover = model.hover_thrust_per_rotor_n()
    b = model.effectiveness()
    for k in range(n):
        t = k / RATE_HZ
        eta = model.nominal_eta()
        if lost_slot is not None and t >= t_fault:
            eta[lost_slot] = 0.5
        wrench = b @ (eta * hover)
        f_z = -wrench[0] / model.mass_kg
        alpha = np.linalg.solve(model.inertia_kgm2, wrench[1:])
        omega = alpha * max(0.0, t - t_fault)
        imus = [
            ImuSample(t, u, omega + rng.normal(0, 0.003, 3), np.array([0.0, 0.0, f_z]) + rng.normal(0, 0.05, 3))
            for u in model.unit_ids
        ]
        poss = [
            PositionSample(t, u, np.array([*model.unit_position(u)[:2], -1.0]) + rng.normal(0, 0.01, 3))
            for u in model.unit_ids
        ]
        yield t, imus, poss, np.full(model.n_rotors, hover)


def bench_estimator(model: AssemblyModel, n: int = 2000) -> np.ndarray:
    est = AssemblyEstimator(model)
    out = []
    for t, imus, poss, _ in ticks(model, n):
        c = time.perf_counter()
        est.step(t, imus, poss)
        out.append(time.perf_counter() - c)
    return np.array(out[100:]) * 1e6


def bench_step_split(model: AssemblyModel, n: int = 4000, repeats: int = 3) -> tuple[float, float]:
    """Median microseconds of a fusion step and of a plain (IMU only) step, positions at 50 Hz.

    The best median of `repeats` runs: other load on the machine only ever adds time.
    """
    rng = np.random.default_rng(0)
    offsets = np.array([model.unit_position(u) for u in model.unit_ids])
    best_fuse, best_plain = float("inf"), float("inf")
    for _ in range(repeats):
        est = AssemblyEstimator(model)
        fuse, plain = [], []
        for k in range(n):
            t = k / RATE_HZ
            imus = [ImuSample(t, u, rng.normal(0, 0.003, 3), np.array([0.0, 0.0, -9.81]) + rng.normal(0, 0.05, 3))
                    for u in model.unit_ids]
            poss = []
            if k % 2 == 0:
                poss = [PositionSample(t, u, np.array([*offsets[i, :2], -1.0]) + rng.normal(0, 0.01, 3),
                                       rng.normal(0, 0.02, 3)) for i, u in enumerate(model.unit_ids)]
            c = time.perf_counter()
            est.step(t, imus, poss)
            (fuse if poss else plain).append(time.perf_counter() - c)
        best_fuse = min(best_fuse, float(np.median(fuse[50:])) * 1e6)
        best_plain = min(best_plain, float(np.median(plain[50:])) * 1e6)
    return best_fuse, best_plain


def bench_flight_split(scenario_name: str = "spiral_3x2", seed: int = 1) -> tuple[float, float, int]:
    """The real loop: median microseconds of AssemblyEstimator.step on fusion and plain steps."""
    from mars_link.flight.runner import run_trial
    from mars_link.config.scenario import load_scenario

    fuse, plain = [], []
    original = AssemblyEstimator.step

    def timed_step(self, t_s, imu_samples, position_samples, stacked=None):
        c = time.perf_counter()
        out = original(self, t_s, imu_samples, position_samples, stacked)
        (fuse if position_samples else plain).append(time.perf_counter() - c)
        return out

    AssemblyEstimator.step = timed_step
    try:
        run_trial(load_scenario(scenario_name), seed)
    finally:
        AssemblyEstimator.step = original
    return float(np.median(fuse)) * 1e6, float(np.median(plain)) * 1e6, len(fuse) + len(plain)


def print_split(flight: bool, rec: Recorder) -> None:
    print("AssemblyEstimator.step, hot, median microseconds (fusion = propagate + stacked position/velocity")
    print("update of every unit; plain = IMU propagation only; positions at 50 Hz, IMU at 100 Hz)")
    print(f"{'case':>22} {'fusion':>7} {'plain':>7} {'mean':>7}")
    for name in ("1x1", "3x2"):
        fuse, plain = bench_step_split(AssemblyModel.from_layout(LAYOUTS[name], "mars-ftcc"))
        print(f"{'synthetic hover ' + name:>22} {fuse:>7.0f} {plain:>7.0f} {(fuse + plain) / 2:>7.0f}")
        rec.figure(f"ekf_fusion_step_{name}_us", fuse, "us", f"synthetic hover {name}: propagate + stacked position update, hot median")
        rec.figure(f"ekf_plain_step_{name}_us", plain, "us", f"synthetic hover {name}: IMU propagation only, hot median")
    if flight:
        for scenario in ("hover_1x1", "spiral_3x2"):
            fuse, plain, steps = bench_flight_split(scenario)
            print(f"{scenario + ' (runner)':>22} {fuse:>7.0f} {plain:>7.0f} {(fuse + plain) / 2:>7.0f}")
            rec.figure(f"ekf_fusion_step_{scenario}_us", fuse, "us", f"{scenario} through the runner, median")
            rec.figure(f"ekf_plain_step_{scenario}_us", plain, "us", f"{scenario} through the runner, median")


def bench_detector(model: AssemblyModel, n: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    det = FaultDetector(model)
    watch = []
    for t, imus, _, cmd in ticks(model, n):
        c = time.perf_counter()
        det.update(t, cmd, None, imus)
        watch.append(time.perf_counter() - c)
    # isolation: fly into a rotor loss and time the decisions after the alarm from a saved state
    det = FaultDetector(model)
    saved = None
    for t, imus, _, cmd in ticks(model, 300, seed=1, lost_slot=1, t_fault=2.0):
        if det.isolating and saved is None:
            saved = (copy.deepcopy(det), t, imus, cmd)
        det.update(t, cmd, None, imus)
    if saved is None:
        return np.array(watch[100:]) * 1e6, np.array([np.nan])
    iso = []
    for _ in range(30):
        d, t, imus, cmd = copy.deepcopy(saved[0]), saved[1], saved[2], saved[3]
        d._onset = d._onset - d.params.min_isolation_s  # force a decision attempt on this tick
        c = time.perf_counter()
        d.update(t, cmd, None, imus)
        iso.append(time.perf_counter() - c)
    return np.array(watch[100:]) * 1e6, np.array(iso) * 1e6


def bench_parts(model: AssemblyModel, n: int = 2000) -> dict[str, np.ndarray]:
    """Per-tick time of the EKF's parts, by wrapping the instance's methods (microseconds)."""
    est = AssemblyEstimator(model)
    spent = {"combine": 0.0, "propagate": 0.0, "update": 0.0}
    per_tick: dict[str, list[float]] = {k: [] for k in spent}

    def timed(name, fn):
        def wrapper(*args, **kwargs):
            c = time.perf_counter()
            out = fn(*args, **kwargs)
            spent[name] += time.perf_counter() - c
            return out
        return wrapper

    est.combiner.combine_arrays = timed("combine", est.combiner.combine_arrays)  # what step() calls
    est._propagate_once = timed("propagate", est._propagate_once)
    est._fuse_positions = timed("update", est._fuse_positions)
    for t, imus, poss, _ in ticks(model, n):
        for k in spent:
            spent[k] = 0.0
        est.step(t, imus, poss)
        for k, v in spent.items():
            per_tick[k].append(v)
    return {k: np.array(v[100:]) * 1e6 for k, v in per_tick.items()}


def bench_flight(rec: Recorder, seed: int = 1) -> None:
    from mars_link.apps.reproduce import ekf_accuracy

    c = time.perf_counter()
    acc = ekf_accuracy("spiral_3x2", seed)
    wall = time.perf_counter() - c
    print()
    print(f"real loop: 3x2 spiral (runner, JSBSim, default sensor noise, seed {seed}, {acc['control_steps']} steps, "
          f"{wall:.1f} s wall)")
    print(f"  estimator per control step  {acc['estimation_s_per_step'] * 1e6:.0f} us (mean, incl. IMU combination)")
    print(f"  position error (CoM)        RMS {acc['position_rms_m'] * 100:.2f} cm, max {acc['position_max_m'] * 100:.2f} cm"
          "   (target RMS < 2 cm)")
    print(f"  attitude error              RMS {acc['attitude_rms_deg']:.3f} deg, max {acc['attitude_max_deg']:.3f} deg"
          "   (target RMS < 0.5 deg)")
    rec.figure("flight_estimator_per_control_step_us", acc["estimation_s_per_step"] * 1e6, "us",
               "3x2 spiral through the runner, mean incl. IMU combination")
    rec.figure("flight_position_rms_cm", acc["position_rms_m"] * 100, "cm", "CoM, target < 2 cm")
    rec.figure("flight_attitude_rms_deg", acc["attitude_rms_deg"], "deg", "target < 0.5 deg")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-flight", action="store_true", help="no JSBSim flights (synthetic hovers only)")
    ap.add_argument("--split-only", action="store_true", help="only the fusion / plain step split")
    ap.add_argument("--quick", action="store_true", help="no flights, layouts 1x1 and 3x2 only")
    add_json_option(ap)
    args = ap.parse_args()
    rec = Recorder.start("bench_estimation", args)
    flight = not (args.no_flight or args.quick)
    print_split(flight, rec)
    if args.split_only:
        rec.finish()
        return
    print()
    print(f"per control tick at {RATE_HZ:.0f} Hz, every unit's IMU and position each tick (microseconds)")
    print(f"{'layout':>6} {'units':>5} {'est_median':>10} {'est_p99':>8} {'fdi_watch':>9} {'fdi_isolate':>11} {'cpu_share':>9}")
    for name, layout in LAYOUTS.items():
        if args.quick and name not in ("1x1", "3x2"):
            continue
        model = AssemblyModel.from_layout(layout, "mars-ftcc")
        est = bench_estimator(model)
        watch, iso = bench_detector(model)
        share = (np.median(est) + np.median(watch)) * RATE_HZ / 1e6
        print(
            f"{name:>6} {model.n_units:>5} {np.median(est):>10.0f} {np.percentile(est, 99):>8.0f} "
            f"{np.median(watch):>9.0f} {np.median(iso):>11.0f} {share:>9.1%}"
        )
        note = f"{name}, every unit's IMU and position each tick at {RATE_HZ:.0f} Hz, median"
        if name == "3x2":
            rec.headline(f"estimator_step_{name}_us", np.median(est), "us", note)
        else:
            rec.figure(f"estimator_step_{name}_us", np.median(est), "us", note)
        rec.figure(f"detector_watch_{name}_us", np.median(watch), "us", f"{name}, fault detector watching, median")
        rec.figure(f"detector_isolate_{name}_us", np.median(iso), "us", f"{name}, fault detector deciding, median")
        rec.figure(f"cpu_share_{name}", share, "fraction of a core", f"{name}: (estimator + detector watching) x rate")
    print("cpu_share = (estimator + detector watching) x rate, of one core; isolation runs only for")
    print("the <= 0.3 s after an alarm")
    print()
    print("EKF step split (median microseconds per tick; update = one stacked position update of every unit)")
    print(f"{'layout':>6} {'combine':>8} {'propagate':>9} {'update':>7}")
    for name in ("1x1", "3x2") if args.quick else ("1x1", "3x2", "3x3"):
        parts = bench_parts(AssemblyModel.from_layout(LAYOUTS[name], "mars-ftcc"))
        print(f"{name:>6} {np.median(parts['combine']):>8.0f} {np.median(parts['propagate']):>9.0f} "
              f"{np.median(parts['update']):>7.0f}")
    if flight:
        bench_flight(rec)
    rec.finish()


if __name__ == "__main__":
    main()
