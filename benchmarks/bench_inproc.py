"""In-process real-time factor of a scenario, with a per-stage breakdown.

    python benchmarks/bench_inproc.py [SCENARIO] [--duration S] [--no-log] [--no-noise] [--quick] [--json]

Default: the bundled 3x2 spiral at 500 Hz physics / 100 Hz control, noise on (EKF in the loop).
Also times bare JSBSim stepping of the same assembly in the same run, so the ratio to the physics
bound is measured on the same (shared, noisy) machine state.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from record import Recorder, add_json_option, apply_quick
from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario


def bare_physics_steps_per_s(scenario, seconds: float = 2.0) -> float:
    from sitl.physics import JsbsimBody

    model = scenario.model()
    body = JsbsimBody(model, physics_hz=scenario.sim.physics_hz)
    hover = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
    n = int(seconds * scenario.sim.physics_hz)
    t0 = time.perf_counter()
    for i in range(n):
        body.set_rotor_thrusts(hover * (1.0 + 1e-3 * (i % 2)))
        body.step()
    dt = time.perf_counter() - t0
    body.close()
    return n / dt


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenario", nargs="?", default="spiral_3x2")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--no-log", action="store_true", help="do not write the run directory")
    ap.add_argument("--no-noise", action="store_true", help="perfect sensors: the controller flies on the truth")
    ap.add_argument("--quick", action="store_true", help="a 5 s flight")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, duration=5.0)
    rec = Recorder.start("bench_inproc", args)
    sc = load_scenario(args.scenario)
    if args.duration:
        sc.sim.duration_s = args.duration
    if args.no_noise:
        sc.sim.noise = False
    with tempfile.TemporaryDirectory() as tmp:  # warm-up: imports and first-use costs stay out of the figure
        warm = load_scenario(args.scenario)
        warm.sim.duration_s = 0.5
        run_scenario(warm, Path(tmp) / "warm", plots=False)
    phys_before = bare_physics_steps_per_s(sc)  # (before and after the flight: the machine's speed drifts)
    with tempfile.TemporaryDirectory() as tmp:
        out = None if args.no_log else Path(tmp) / "run"
        cpu0 = time.process_time()
        summary = run_scenario(sc, out, trials=1, plots=False)
        cpu_s = time.process_time() - cpu0
    phys_rate = 0.5 * (phys_before + bare_physics_steps_per_s(sc))
    sim_t, wall = summary["sim_time_s"], summary["wall_time_s"]
    steps = sim_t * sc.sim.physics_hz
    print(f"scenario {sc.name}: {','.join(sc.layout)}, physics {sc.sim.physics_hz:g} Hz, "
          f"control {sc.sim.control_hz:g} Hz, noise {sc.sim.noise}")
    print(f"sim time {sim_t:.2f} s, wall {wall:.2f} s, real-time factor {summary['real_time_factor']:.1f}x "
          f"(mean error {summary['mean_error_m']:.4f} m)")
    print(f"CPU time {cpu_s:.2f} s: {sim_t / cpu_s:.1f}x real time per CPU second (steadier than wall time on a "
          "shared machine)")
    bound = phys_rate / sc.sim.physics_hz
    print(f"bare JSBSim stepping with per-step rotor writes (mean of before and after): {phys_rate:,.0f} steps/s "
          f"= {bound:.1f}x real time; full loop is {bound / summary['real_time_factor']:.2f}x slower")
    print(f"{'stage':<12}{'total s':>9}{'share':>8}{'us/physics step':>17}")
    stage = summary["stage_time_s"]
    accounted = sum(stage.values())
    for name, sec in stage.items():
        print(f"{name:<12}{sec:>9.3f}{sec / wall:>8.1%}{1e6 * sec / steps:>17.1f}")
    print(f"{'other':<12}{wall - accounted:>9.3f}{(wall - accounted) / wall:>8.1%}"
          f"{1e6 * (wall - accounted) / steps:>17.1f}")
    # what the world and the units' firmware cost on their own: the loop cannot be faster than this even
    # if the coordinator (estimation, control, allocation, fault detection) and the logging cost nothing
    plant_s = stage["physics"] + stage["sensors"] + stage["motors"]
    plant_us = 1e6 * plant_s / steps
    print(f"world and units alone (physics + sensors + motors): {plant_us:.1f} us per physics step, "
          f"{plant_us * phys_rate / 1e6:.2f}x bare JSBSim's step: at most {sim_t / plant_s:.1f}x real time with "
          "the coordinator and logging free")
    what = f"{sc.name}, {sim_t:.1f} s, noise {sc.sim.noise}, run directory {'off' if args.no_log else 'on'}"
    rec.figure("rtf_wall", summary["real_time_factor"], "x real time", what)
    rec.figure("rtf_cpu", sim_t / cpu_s, "x real time", "per CPU second")
    rec.figure("bare_jsbsim_same_body", bound, "x real time", "bare JSBSim stepping of the same assembly, this run")
    rec.headline("loop_vs_bare_jsbsim", summary["real_time_factor"] / bound, "ratio",
                 f"{what}: the full loop's RTF / bare JSBSim's of the same body (same run)")
    for name, sec in stage.items():
        rec.figure(f"stage_{name}_us", 1e6 * sec / steps, "us", "per physics step")
    rec.figure("plant_vs_bare_step", plant_us * phys_rate / 1e6, "bare JSBSim steps",
               "physics + sensors + motors per physics step")
    rec.finish()


if __name__ == "__main__":
    main()
