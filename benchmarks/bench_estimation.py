"""Cost of one AssemblyEstimator tick (all units' IMU + all units' positions) per layout.

Prints the median and 99th percentile of `step()` wall time over a synthetic hover with noise.
Run: python benchmarks/bench_estimation.py
"""

from __future__ import annotations

import time

import numpy as np

from mars_link.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.estimation import AssemblyEstimator
from mars_link.state import ImuSample, PositionSample

LAYOUTS = {"1x1": ["X"], "2x2": ["XX", "XX"], "3x2": ["XXX", "XXX"], "4x1": ["XXXX"], "3x3": ["XXX", "XXX", "XXX"]}


def ticks(model: AssemblyModel, n: int, rate_hz: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    for k in range(n):
        t = k / rate_hz
        imus = [
            ImuSample(t, u, rng.normal(0, 0.003, 3), np.array([0, 0, -GRAVITY_MPS2]) + rng.normal(0, 0.05, 3))
            for u in model.unit_ids
        ]
        poss = [
            PositionSample(t, u, np.array([*model.unit_position(u)[:2], -1.0]) + rng.normal(0, 0.01, 3))
            for u in model.unit_ids
        ]
        yield t, imus, poss


def bench(layout: list[str], n: int = 2000, rate_hz: float = 100.0) -> tuple[float, float]:
    model = AssemblyModel.from_layout(layout, "mars-ftcc")
    data = list(ticks(model, n, rate_hz))
    est = AssemblyEstimator(model)
    times = []
    for t, imus, poss in data:
        c = time.perf_counter()
        est.step(t, imus, poss)
        times.append(time.perf_counter() - c)
    us = np.array(times[100:]) * 1e6
    return float(np.median(us)), float(np.percentile(us, 99))


def main() -> None:
    print("AssemblyEstimator.step(), IMU + position of every unit each tick, 100 Hz synthetic hover")
    print(f"{'layout':>6} {'units':>5} {'median_us':>10} {'p99_us':>8} {'cpu_share_at_100Hz':>19}")
    for name, layout in LAYOUTS.items():
        med, p99 = bench(layout)
        n_units = sum(r.count("X") for r in layout)
        print(f"{name:>6} {n_units:>5} {med:>10.0f} {p99:>8.0f} {med * 100 / 1e6:>18.1%}")


if __name__ == "__main__":
    main()
