"""JSBSim stepping rate of generated assembly models with per-rotor thrust writes.

Measures `JsbsimBody.step()` with `set_rotor_thrusts` (all rotors changed) every step or every 5th
step, with and without reading the full state each step, for a single unit and a 3x2 assembly.
Best of `--repeats` runs (the machine is shared). Spec target (specs/dependencies.md §1.4): ~45 k
steps/s for 6 units with per-step writes.

    python benchmarks/bench_physics.py [--seconds S] [--repeats N] [--quick] [--json]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from record import Recorder, add_json_option, apply_quick
from mars_link.core.assembly import AssemblyModel
from mars_link.core.rotations import euler_to_quat
from mars_link.core.state import RigidBodyState
from sitl.physics import JsbsimBody

PHYSICS_HZ = 500.0
LAYOUTS = (("1x1", ["X"]), ("3x2", ["XXX", "XXX"]))


def steps_per_s(layout: list[str], write_every: int, read_state: bool, seconds: float, repeats: int) -> float:
    model = AssemblyModel.from_layout(layout)
    start = RigidBodyState(0.0, np.array([0.0, 0.0, -10.0]), np.zeros(3), euler_to_quat(0, 0, 0), np.zeros(3))
    hover = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
    # two alternating thrust vectors, so every write really changes every rotor
    commands = [hover * (1.0 + 1e-4 * np.sin(np.arange(model.n_rotors) + k)) for k in range(2)]
    n = int(seconds * PHYSICS_HZ)
    best = 0.0
    with JsbsimBody(model, physics_hz=PHYSICS_HZ, state=start, rotor_thrusts_n=hover) as body:
        for _ in range(repeats):
            t0 = time.perf_counter()
            for i in range(n):
                if i % write_every == 0:
                    body.set_rotor_thrusts(commands[(i // write_every) % 2])
                body.step()
                if read_state:
                    body.state()
            best = max(best, n / (time.perf_counter() - t0))
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="simulated seconds per run")
    ap.add_argument("--repeats", type=int, default=3, help="runs per case; the best is reported")
    ap.add_argument("--quick", action="store_true", help="0.5 s per run, one run per case")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, seconds=0.5, repeats=1)
    rec = Recorder.start("bench_physics", args)
    rates = {}
    print(f"{'layout':<8}{'rotors':>7}  {'thrust writes':<16}{'state read':<12}{'steps/s':>10}"
          f"{'us/step':>9}{'x real time':>13}")
    for name, layout in LAYOUTS:
        rotors = 4 * sum(row.count("X") for row in layout)
        for every, label in ((1, "every step"), (5, "every 5th")):
            for read in (False, True):
                r = steps_per_s(layout, every, read, args.seconds, args.repeats)
                key = f"{name}_{'every' if every == 1 else 'every5'}_{'read' if read else 'noread'}"
                rates[key] = r
                rec.figure(f"steps_per_s_{key}", round(r), "steps/s",
                           f"{name}, thrust writes {label}, state read {'yes' if read else 'no'}")
                print(f"{name:<8}{rotors:>7}  {label:<16}{'yes' if read else 'no':<12}{r:>10,.0f}"
                      f"{1e6 / r:>9.1f}{r / PHYSICS_HZ:>13.1f}")
    rec.headline("state_read_cost_3x2", rates["3x2_every_read"] / rates["3x2_every_noread"], "ratio",
                 "3x2, writes every step: steps/s with a full state read every step / without (same run)")
    rec.finish()


if __name__ == "__main__":
    main()
