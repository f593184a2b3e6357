"""What the EKF's sensor-health gate (mars_link/sensor_health.py) costs: the in-process 3x2 spiral with
the gate in front of the EKF (as every flight has it) against the bare EKF, alternated in one run.

    python benchmarks/bench_sensor_guard.py [--duration 20] [--runs 3]

Prints the CPU time per simulated second of each, their medians and the ratio (guarded / bare), and the
gate's own share: the time inside SensorGuard.step minus the EKF's step it calls.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mars_link.build import build_flight  # noqa: E402
from mars_link.engine import Engine  # noqa: E402
from mars_link.scenario import load_scenario  # noqa: E402


def fly(duration_s: float, guarded: bool) -> tuple[float, float, float]:
    """(CPU s per simulated s of the whole flight, of the gate's own work, of the EKF's step)."""
    sc = load_scenario("spiral_3x2")
    sc.sim.duration_s = duration_s
    flight = build_flight(sc, 1)
    guard = flight.coordinator.estimator
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
        flight.coordinator.estimator = type("Timed", (), {"step": staticmethod(timed(guard.step, "guard"))})()
    else:
        flight.coordinator.estimator, flight.coordinator.guard, flight.coordinator.failsafe = ekf, None, None
    cpu0 = time.process_time()
    Engine(flight).run()
    cpu = time.process_time() - cpu0
    flight.world.close()
    return cpu / duration_s, (spent["guard"] - spent["ekf"]) / duration_s if guarded else 0.0, spent["ekf"] / duration_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--runs", type=int, default=3)
    a = ap.parse_args()
    if a.duration <= 0 or a.runs < 1:
        print("error: --duration must be > 0 and --runs >= 1", file=sys.stderr)
        sys.exit(2)
    fly(1.0, True)  # warm-up: imports and first-use costs
    rows = {True: [], False: []}
    for k in range(a.runs):
        for guarded in (k % 2 == 0, k % 2 != 0):  # alternated, so a load change hits both
            rows[guarded].append(fly(a.duration, guarded))
            cpu, own, ekf = rows[guarded][-1]
            print(f"run {k + 1} {'guarded' if guarded else 'bare   '}: {cpu * 1e3:7.1f} ms CPU per sim s "
                  f"(EKF step {ekf * 1e3:.1f} ms, gate's own {own * 1e3:.1f} ms)", flush=True)
    g = statistics.median(r[0] for r in rows[True])
    b = statistics.median(r[0] for r in rows[False])
    own = statistics.median(r[1] for r in rows[True])
    print(f"median CPU per simulated second: guarded {g * 1e3:.1f} ms, bare {b * 1e3:.1f} ms, ratio {g / b:.3f}; "
          f"the gate's own work {own * 1e3:.1f} ms ({own / g:.1%} of the guarded flight)")


if __name__ == "__main__":
    main()
