"""JSBSim stepping rate of generated assembly models, with per-rotor force writes.

    python benchmarks/bench_physics.py [--seconds S]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mars_link.assembly import AssemblyModel
from mars_link.rotations import euler_to_quat
from mars_link.state import RigidBodyState
from sitl.physics import JsbsimBody


def rate(layout: list[str], write_every: int, seconds: float) -> float:
    model = AssemblyModel.from_layout(layout)
    start = RigidBodyState(0.0, np.array([0.0, 0.0, -10.0]), np.zeros(3), euler_to_quat(0, 0, 0), np.zeros(3))
    body = JsbsimBody(model, state=start)
    hover = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
    n = int(seconds * 500)
    t0 = time.perf_counter()
    for i in range(n):
        if i % write_every == 0:
            body.set_rotor_thrusts(hover * (1.0 + 1e-4 * ((i // write_every) % 2)))
        body.step()
        body.state()
    dt = time.perf_counter() - t0
    body.close()
    return n / dt


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=4.0, help="simulated seconds per case")
    args = ap.parse_args()
    print(f"{'layout':<8}{'writes':<16}{'steps/s':>10}{'x real time @500 Hz':>22}")
    for name, layout in (("1x1", ["X"]), ("3x2", ["XXX", "XXX"])):
        for every, label in ((1, "every step"), (5, "every 5th step")):
            r = rate(layout, every, args.seconds)
            print(f"{name:<8}{label:<16}{r:>10,.0f}{r / 500:>22.1f}")


if __name__ == "__main__":
    main()
