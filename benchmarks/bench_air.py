"""In-process real-time factor of the default scenario with the air on, against still air, in one run.

    python benchmarks/bench_air.py [SCENARIO] [--repeats 3] [--duration S] [--quick] [--json]

Three variants of the same scenario, flown alternately `--repeats` times each (so a busy machine
slows them alike) and compared by the median real-time factor:
* still: the scenario as it is (the paper plant, no drag);
* drag: the preset's drag on (mars_link.models.aerodynamics), still air: the cost of the generated
  aerodynamics functions;
* air: drag on, 5 m/s steady wind and moderate Milspec turbulence (JSBSim's FGWinds every step).
Prints each variant's median RTF and the ratios to still air.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from record import Recorder, add_json_option, apply_quick  # noqa: E402

from mars_link.models.aerodynamics import AERO_PRESETS  # noqa: E402
from mars_link.models.environment import SEVERITIES, EnvironmentParams  # noqa: E402
from mars_link.flight.runner import run_scenario  # noqa: E402
from mars_link.config.scenario import load_scenario  # noqa: E402


def variants(name: str, duration_s: float | None) -> dict:
    still = load_scenario(name)
    if duration_s:
        still.sim.duration_s = duration_s
    drag = copy.deepcopy(still)
    drag.vehicle_options.update(AERO_PRESETS[drag.preset])
    air = copy.deepcopy(drag)
    w20, index = SEVERITIES["moderate"]
    air.environment = EnvironmentParams(wind_ned_mps=(5.0, 0.0, 0.0), turbulence_w20_mps=w20, turbulence_severity=index)
    return {"still": still, "drag": drag, "air": air}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", nargs="?", default="spiral_3x2")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--quick", action="store_true", help="5 s flights, three of each (alternated)")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, duration=5.0, repeats=3)
    rec = Recorder.start("bench_air", args)
    runs = variants(args.scenario, args.duration)
    rtf: dict[str, list[float]] = {k: [] for k in runs}
    warm = copy.deepcopy(runs["air"])  # imports and first-use costs stay out of the first variant's figure
    warm.sim.duration_s = 0.5
    run_scenario(warm, None, plots=False)
    for i in range(args.repeats):
        for k, sc in runs.items():
            s = run_scenario(sc, None, plots=False)
            rtf[k].append(s["real_time_factor"])
            print(f"  repeat {i + 1} {k:5s}: RTF {s['real_time_factor']:.1f}x (mean error {s['mean_error_m']:.3f} m)",
                  file=sys.stderr)
    med = {k: statistics.median(v) for k, v in rtf.items()}
    print(f"{args.scenario}, in-process, median of {args.repeats} (noise on, EKF in the loop)")
    for k in runs:
        print(f"  {k:5s}: RTF {med[k]:6.1f}x   ratio to still air {med[k] / med['still']:.3f}")
        rec.figure(f"rtf_{k}", med[k], "x real time", f"{args.scenario}, median of {args.repeats}")
    rec.figure("drag_vs_still", med["drag"] / med["still"], "ratio", "RTF with drag on / still air")
    rec.headline("air_vs_still", med["air"] / med["still"], "ratio",
                 "RTF with drag, 5 m/s wind and moderate turbulence / still air (same run, alternated)")
    rec.finish()


if __name__ == "__main__":
    main()
