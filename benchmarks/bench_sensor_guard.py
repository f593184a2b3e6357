"""What the EKF's sensor-health gate (mars_link/models/sensor_health.py) costs: the in-process 3x2 spiral with
the gate in front of the EKF (as every flight has it) against the bare EKF, alternated in one run.

    python benchmarks/bench_sensor_guard.py [--duration 20] [--runs 3] [--sensors mocap|gps|both] [--quick] [--json]

Prints the CPU time per simulated second of each, their medians and the ratio (guarded / bare), and the
gate's own share: the time inside SensorGuard.step minus the EKF's step it calls. `--sensors gps`: the
same spiral on the gps profile (the outdoor EKF's gate: GNSS fixes at 5 Hz, barometers and
magnetometers at 50 Hz screened per unit); `both`: one after the other in the same run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from record import Recorder, add_json_option, apply_quick  # noqa: E402
from mars_link.flight.build import build_flight  # noqa: E402
from mars_link.flight.engine import Engine  # noqa: E402
from mars_link.config.scenario import load_scenario  # noqa: E402
from mars_link.models.sensor_profiles import PROFILES  # noqa: E402


def fly(duration_s: float, guarded: bool, sensors: str = "mocap") -> tuple[float, float, float]:
    """(CPU s per simulated s of the whole flight, of the gate's own work, of the EKF's step)."""
    sc = load_scenario("spiral_3x2")
    sc.sim.duration_s = duration_s
    sc.sensors = PROFILES[sensors]
    flight = build_flight(sc, 1)
    coordinator = flight.coordinator  # (a flight of pieces: the docked structure is its one piece)
    if hasattr(coordinator, "tracked_piece"):
        coordinator = coordinator.tracked_piece().coordinator
    guard = coordinator.estimator
    ekf = guard.ekf
    spent = {"guard": 0.0, "ekf": 0.0}

    def timed(fn, key: str):
        def call(*a):
            t0 = time.process_time()
            try:
                return fn(*a)
            finally:
                spent[key] += time.process_time() - t0
        return call

    ekf.step = timed(ekf.step, "ekf")
    if guarded:
        coordinator.estimator = type("Timed", (), {"step": staticmethod(timed(guard.step, "guard")),
                                                   "home": getattr(ekf, "home", None)})()
    else:
        coordinator.estimator, coordinator.guard, coordinator.failsafe = ekf, None, None
    cpu0 = time.process_time()
    Engine(flight).run()
    cpu = time.process_time() - cpu0
    flight.world.close()
    return cpu / duration_s, (spent["guard"] - spent["ekf"]) / duration_s if guarded else 0.0, spent["ekf"] / duration_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--sensors", default="mocap", help="mocap | gps | both")
    ap.add_argument("--quick", action="store_true", help="5 s flights, two runs")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, duration=5.0, runs=2)
    if a.duration <= 0 or a.runs < 1:
        print("error: --duration must be > 0 and --runs >= 1", file=sys.stderr)
        sys.exit(2)
    if a.sensors not in ("mocap", "gps", "both"):
        print(f"error: --sensors must be mocap, gps or both, got {a.sensors!r}", file=sys.stderr)
        sys.exit(2)
    rec = Recorder.start("bench_sensor_guard", a)
    for sensors in (("mocap", "gps") if a.sensors == "both" else (a.sensors,)):
        compare(a.duration, a.runs, sensors, rec)
    rec.finish()


def compare(duration_s: float, runs: int, sensors: str, rec: Recorder) -> None:
    fly(1.0, True, sensors)  # warm-up: imports and first-use costs
    rows = {True: [], False: []}
    for k in range(runs):
        for guarded in (k % 2 == 0, k % 2 != 0):  # alternated, so a load change hits both
            rows[guarded].append(fly(duration_s, guarded, sensors))
            cpu, own, ekf = rows[guarded][-1]
            print(f"{sensors} run {k + 1} {'guarded' if guarded else 'bare   '}: {cpu * 1e3:7.1f} ms CPU per sim s "
                  f"(EKF step {ekf * 1e3:.1f} ms, gate's own {own * 1e3:.1f} ms)", flush=True)
    g = statistics.median(r[0] for r in rows[True])
    b = statistics.median(r[0] for r in rows[False])
    own = statistics.median(r[1] for r in rows[True])
    print(f"{sensors}: median CPU per simulated second: guarded {g * 1e3:.1f} ms, bare {b * 1e3:.1f} ms, "
          f"ratio {g / b:.3f}; the gate's own work {own * 1e3:.1f} ms ({own / g:.1%} of the guarded flight)", flush=True)
    what = f"spiral_3x2 on {sensors}, {duration_s:g} s, median of the runs"
    (rec.headline if not rec.figures else rec.figure)(f"guarded_vs_bare_{sensors}", g / b, "ratio",
                                                     f"{what}: CPU per simulated s with the sensor gate / bare EKF")
    rec.figure(f"gate_own_{sensors}_ms_per_sim_s", own * 1e3, "ms", f"{what}: the gate's own CPU per simulated s")


if __name__ == "__main__":
    main()
