"""Leg planning against the control deadline: the damaged 3x2 (unit 2 failed, found by the detector) flies
the five-waypoint walls mission as `mars-link vehicle` does (VehicleSim in process, paced to real time), its legs
planned around paper 000's walls (the bundled paper000_walls.csv) in the worker process (mars_link.planning.mission_legs). Every
control period's compute time (sensing, EKF, vehicle tick, coordinator, motors, physics) is split by
whether a leg was being planned meanwhile, against the 10 ms deadline of 100 Hz; the planning times
come from the worker. One run measures both sides, so their ratio is of the same minutes.

    python benchmarks/bench_mission_legs.py [--json]

(The whole mission is flown in real time, about two minutes: there is no shorter version of it.)
"""

from __future__ import annotations

import argparse

import numpy as np

from record import Recorder, add_json_option
from mars_link.apps.planning_eval import walls_mission_flight

DEADLINE_MS = 10.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_json_option(ap)
    rec = Recorder.start("bench_mission_legs", ap.parse_args())
    planning_ms: list[float] = []
    other_ms: list[float] = []

    def on_step(sim, seconds: float) -> None:
        leg = sim.legs.leg
        busy = leg is not None and leg.plan is None  # a plan was being computed in the worker
        (planning_ms if busy else other_ms).append(seconds * 1e3)
        if len(planning_ms) + len(other_ms) in (1, 1000, 5000) or (len(planning_ms) + len(other_ms)) % 2000 == 0:
            print(f"  ... {sim.t_s:.0f} s simulated", flush=True)

    res = walls_mission_flight(True, 0.0, on_step, paced=True)
    legs = [leg for leg in res["legs"] if "kind" in leg]
    print(f"mission: {len([s for s, _ in res['reached']])} of 5 waypoints, {res['contacts']} wall contacts, "
          f"{res['sim_s']:.1f} s simulated")
    print("leg planning (worker process): " + ", ".join(f"{leg['plan_time_s']:.2f} s" for leg in legs)
          + "; waited " + ", ".join(f"{leg['wait_s']:.2f}" for leg in legs) + " s (the first includes the worker's start)")
    for name, ms in (("while a leg is planned", planning_ms), ("otherwise", other_ms)):
        a = np.array(ms)
        print(f"control period compute, {name}: {len(a)} periods, p50 {np.percentile(a, 50):.2f} ms, "
              f"p99 {np.percentile(a, 99):.2f} ms, max {a.max():.2f} ms, over {DEADLINE_MS:g} ms: {int((a > DEADLINE_MS).sum())}")
        key = "planning" if ms is planning_ms else "otherwise"
        rec.figure(f"control_compute_p99_{key}_ms", np.percentile(a, 99), "ms", f"control period compute, {name}, p99")
        rec.figure(f"deadline_misses_{key}", int((a > DEADLINE_MS).sum()), "periods", f"of {len(a)}, {name}")
    p99 = np.percentile(planning_ms, 99) / np.percentile(other_ms, 99)
    worst = max(leg["plan_time_s"] for leg in legs) * 1e3 / DEADLINE_MS
    print(f"p99 while planning / p99 otherwise: {p99:.2f}; the slowest leg plan is {worst:.0f} control deadlines long")
    rec.figure("waypoints_reached", len([s for s, _ in res["reached"]]), "of 5", "walls mission, damaged 3x2")
    rec.figure("slowest_leg_plan_s", max(leg["plan_time_s"] for leg in legs), "s", "in the worker process")
    rec.headline("p99_planning_vs_otherwise", p99, "ratio",
                 "control period compute p99 while a leg is planned / otherwise (same run)")
    rec.finish()


if __name__ == "__main__":
    main()
