"""Planning cost of `[trajectory] kind = "waypoints"` against the number of waypoints: 2,000 against 4,000
in one run, each built in a fresh child process (so each peak memory is its own), wall time of the build
(retiming included) and the child's peak RSS. The minimum-snap system is banded (mars_link.models.trajectories),
so both ratios should be near 2 (linear); a dense solve gave 8x the time and 4x the memory per doubling.

    python benchmarks/bench_planning_waypoints.py [--sizes 2000 4000] [--repeats 3] [--quick] [--json]

Each size is built `--repeats` times (each in its own child); the fastest build is reported (other load on
this shared machine only ever adds time).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

from record import Recorder, add_json_option, apply_quick

_CHILD = r"""
import json, resource, sys, time
import numpy as np
from mars_link.models.trajectories import build_trajectory
n = int(sys.argv[1])
rng = np.random.default_rng(7)
steps = rng.uniform(-1.5, 1.5, size=(n, 2)) + np.array([1.0, 0.0])
ne = np.cumsum(steps, axis=0)
down = -2.5 + rng.uniform(-0.3, 0.3, size=n)
points = [[float(a), float(b), float(d)] for (a, b), d in zip(ne, down)]
import scipy.linalg  # (imported before the clock starts: its import is not planning)
base_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter()
traj = build_trajectory("waypoints", {"points": points}, 0.1)
build_s = time.perf_counter() - t0
t0 = time.perf_counter()
for t in np.linspace(0.0, traj.duration_s, 20000):
    traj.sample(float(t))
sample_us = (time.perf_counter() - t0) / 20000 * 1e6
peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"waypoints": n, "build_s": build_s, "sample_us": sample_us, "peak_rss_mib": peak_kib / 1024,
                  "rss_before_build_mib": base_kib / 1024, "duration_s": traj.duration_s}))
"""


def measure(n: int) -> dict:
    out = subprocess.run([sys.executable, "-c", _CHILD, str(n)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[2000, 4000], help="waypoint counts (default 2000 4000)")
    ap.add_argument("--repeats", type=int, default=3, help="builds per size, each in a fresh child; the fastest counts")
    ap.add_argument("--quick", action="store_true", help="1000 and 2000 waypoints")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, sizes=[1000, 2000])
    rec = Recorder.start("bench_planning_waypoints", args)
    rows = []
    for n in args.sizes:
        row = min((measure(n) for _ in range(max(args.repeats, 1))), key=lambda r: r["build_s"])
        rows.append(row)
        print(f"{n:6d} waypoints: build {row['build_s']:.3f} s, peak RSS {row['peak_rss_mib']:.0f} MiB "
              f"(before the build {row['rss_before_build_mib']:.0f} MiB), sample {row['sample_us']:.1f} us, "
              f"flight {row['duration_s']:.0f} s", flush=True)
        rec.figure(f"build_{n}_s", row["build_s"], "s", f"{n} waypoints: minimum-snap build incl. retiming")
        rec.figure(f"peak_rss_{n}_mib", row["peak_rss_mib"], "MiB", f"{n} waypoints, child's peak RSS")
    ratios = {}
    if len(rows) >= 2:
        a, b = rows[0], rows[-1]
        first_growth_mib = a["peak_rss_mib"] - a["rss_before_build_mib"]  # below 1 MiB: lost in the RSS's noise
        grow = (b["peak_rss_mib"] - b["rss_before_build_mib"]) / first_growth_mib if first_growth_mib >= 1.0 else float("nan")
        ratios = {"waypoints": b["waypoints"] / a["waypoints"], "build_time": b["build_s"] / a["build_s"],
                  "build_memory": grow}
        print(f"{b['waypoints']} / {a['waypoints']} waypoints ({ratios['waypoints']:g}x): build time "
              f"{ratios['build_time']:.2f}x, memory grown by the build {ratios['build_memory']:.2f}x "
              f"(linear: about {ratios['waypoints']:g}x)")
        rec.headline("build_time_growth", ratios["build_time"], "ratio",
                     f"build time {b['waypoints']} / {a['waypoints']} waypoints (linear: {ratios['waypoints']:g})")
        rec.figure("build_memory_growth", ratios["build_memory"], "ratio", "memory grown by the build, same sizes")
    rec.finish()


if __name__ == "__main__":
    main()
