"""The ESC fault monitor's cost per ESC sample (every unit's four rotors judged), 3x3 and 10x10.

    python benchmarks/bench_esc_monitor.py [--samples 500] [--quick] [--json]

Hover commands at 100 Hz and every unit's ESC sample at 50 Hz (noise as mars_link.models.esc), healthy, then
with three rotors believed faulty (a stop and two load losses: their windows keep being judged against the
belief). Prints the median of `observe` + `covered` per sample, ms, and per unit, us.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from record import Recorder, add_json_option, apply_quick  # noqa: E402

from mars_link.core.assembly import AssemblyModel, vehicle_preset  # noqa: E402
from mars_link.core.messages import wire_esc  # noqa: E402
from mars_link.models.esc import EscParams, MotorConstants  # noqa: E402
from mars_link.models.esc_monitor import EscMonitor  # noqa: E402


def per_sample_s(side: int, samples: int, faulty: bool) -> float:
    model = AssemblyModel.from_layout(["X" * side] * side, vehicle_preset("mars-real"))
    monitor, c, noise = EscMonitor(model), MotorConstants.for_vehicle(model.vehicle), EscParams()
    rng = np.random.default_rng(0)
    hover = np.full(model.n_rotors, 1.3)
    eta = np.ones(model.n_rotors)
    if faulty:
        eta[[1, 6, 13]] = [0.0, 0.3, 0.5]
    spent = []
    for k in range(2 * samples):
        t = k * 0.01
        if k % 2 == 0:
            rpm = c.rpm(hover) * np.where(eta > 0, 1.0, 0.0) + rng.normal(0, noise.rpm_noise, hover.size)
            current = np.where(eta > 0, c.no_load_current_a + eta * c.load_current_a(hover), 0.0)
            current = current + rng.normal(0, noise.current_noise_a, hover.size) * (current > 0)
            units = {u: wire_esc(t, rpm[4 * (u - 1):4 * u], current[4 * (u - 1):4 * u]) for u in model.unit_ids}
            t0 = time.perf_counter()
            monitor.observe(t, units)
            monitor.covered(t)
            spent.append(time.perf_counter() - t0)
        monitor.command(t, hover)
    assert len(monitor.beliefs()) == (3 if faulty else 0)
    return statistics.median(spent[samples // 2:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=500)
    ap.add_argument("--quick", action="store_true", help="100 samples per case")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, samples=100)
    rec = Recorder.start("bench_esc_monitor", args)
    for side in (3, 10):
        for faulty in (False, True):
            s = per_sample_s(side, args.samples, faulty)
            name = f"{side}x{side}_{'3_beliefs' if faulty else 'healthy'}"
            print(f"{name:20s}: {s * 1e3:.3f} ms per ESC sample ({s / side**2 * 1e6:.2f} us per unit)")
            rec.figure(f"per_sample_{name}", s * 1e3, "ms", "observe + covered, median")
    rec.finish()


if __name__ == "__main__":
    main()
