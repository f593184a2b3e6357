"""Flights in the air (issue 15): the 3x2 spiral in wind and turbulence, and the 3x2 hover in a gust.

    python tools/air_eval.py [--out runs/air_eval] [--seeds 5] [--tolerance 0.05] [--sensors PROFILE]
                             [--flights spiral,gust]

Flies, in-process with sensor noise on (EKF in the loop), cascaded + qp:
* `spiral_3x2_wind`: paper 000's spiral in a 5 m/s steady wind with moderate Dryden turbulence, one
  flight per seed: completed, mean / max error of unit 1, max tilt;
* `hover_3x2_gust`: the 3x2 holding 2 m meets a 5 m/s 1-cosine gust; peak deviation of the CoM from
  its hold point after the gust's onset, and the recovery time (onset until the error stays within
  --tolerance for good), per seed.
`--sensors mocap|rtk|gps` flies them on that [sensors] profile (default: the scenarios' own, mocap);
`--flights` picks which. Prints a markdown table and writes air.md and air.json to --out. Exit 0 when
every flight completed.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mars_link.core.errors import UserInputError  # noqa: E402
from mars_link.flight.metrics import gust_response  # noqa: E402
from mars_link.flight.runner import run_scenario  # noqa: E402
from mars_link.config.scenario import load_scenario  # noqa: E402
from mars_link.models.sensor_profiles import PROFILES  # noqa: E402

FLIGHTS = ("spiral", "gust")


def scenario(name: str, sensors: str | None):
    sc = load_scenario(name)
    if sensors is not None:
        sc.sensors = PROFILES[sensors]
    return sc


def spiral_rows(seeds: int, sensors: str | None = None) -> list[dict]:
    sc = scenario("spiral_3x2_wind", sensors)
    rows = []
    for seed in range(1, seeds + 1):
        s = run_scenario(sc, None, seed=seed, plots=False)
        rows.append({"seed": seed, "completed": s["completed"], "mean_error_m": s["mean_error_m"],
                     "max_error_m": s["max_error_m"], "max_tilt_deg": s["max_tilt_deg"]})
        print(f"  spiral_3x2_wind seed {seed}: mean {s['mean_error_m']:.3f} m, max {s['max_error_m']:.3f} m",
              file=sys.stderr)
    return rows


def gust_rows(seeds: int, tolerance_m: float, sensors: str | None = None) -> list[dict]:
    sc = scenario("hover_3x2_gust", sensors)
    onset = sc.environment.gusts[0].t_s
    rows = []
    for seed in range(1, seeds + 1):
        with tempfile.TemporaryDirectory() as tmp:
            s = run_scenario(sc, Path(tmp), seed=seed, plots=False)
            a = np.genfromtxt(Path(tmp) / "telemetry.csv", delimiter=",", names=True)
        rows.append({"seed": seed, "completed": s["completed"], **gust_response(a["t_s"], a["error_m"], onset, tolerance_m)})
        print(f"  hover_3x2_gust seed {seed}: peak {rows[-1]['peak_deviation_m']:.3f} m, "
              f"recovery {rows[-1]['recovery_s']:.2f} s", file=sys.stderr)
    return rows


def markdown(spiral: list[dict], gust: list[dict]) -> str:
    def ms(key: str, rows: list[dict]) -> str:
        v = np.array([r[key] for r in rows])
        return f"{v.mean():.3f} ± {v.std():.3f}"

    lines = ["| flight | seeds | completed | figure | value (mean ± std over seeds) | worst seed |",
             "|---|---|---|---|---|---|"]
    if spiral:
        lines += [
            f"| spiral_3x2_wind | {len(spiral)} | {sum(r['completed'] for r in spiral)}/{len(spiral)} | mean error [m] | "
            f"{ms('mean_error_m', spiral)} | {max(r['mean_error_m'] for r in spiral):.3f} |",
            f"| | | | max error [m] | {ms('max_error_m', spiral)} | {max(r['max_error_m'] for r in spiral):.3f} |",
            f"| | | | max tilt [deg] | {ms('max_tilt_deg', spiral)} | {max(r['max_tilt_deg'] for r in spiral):.1f} |"]
    if gust:
        lines += [
            f"| hover_3x2_gust | {len(gust)} | {sum(r['completed'] for r in gust)}/{len(gust)} | peak deviation [m] | "
            f"{ms('peak_deviation_m', gust)} | {max(r['peak_deviation_m'] for r in gust):.3f} |",
            f"| | | | peak after onset [s] | {ms('peak_after_s', gust)} | {max(r['peak_after_s'] for r in gust):.2f} |",
            f"| | | | recovery to {gust[0]['tolerance_m']:g} m [s] | {ms('recovery_s', gust)} | "
            f"{max(r['recovery_s'] for r in gust):.2f} |"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/air_eval")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--tolerance", type=float, default=0.05, help="recovery band around the hold point, m")
    ap.add_argument("--sensors", default=None, help=f"[sensors] profile to fly on ({', '.join(PROFILES)})")
    ap.add_argument("--flights", default=",".join(FLIGHTS), help="which flights, comma-separated: spiral, gust")
    args = ap.parse_args(argv)
    if not 1 <= args.seeds <= 100 or not 0 < args.tolerance < 10:
        raise UserInputError("--seeds must be in 1..100 and --tolerance in (0, 10) m")
    if args.sensors is not None and args.sensors not in PROFILES:
        raise UserInputError(f"unknown --sensors profile {args.sensors!r} (known: {', '.join(PROFILES)})")
    flights = [f.strip() for f in args.flights.split(",") if f.strip()]
    if not flights or any(f not in FLIGHTS for f in flights):
        raise UserInputError(f"--flights must name some of {', '.join(FLIGHTS)}, got {args.flights!r}")
    spiral = spiral_rows(args.seeds, args.sensors) if "spiral" in flights else []
    gust = gust_rows(args.seeds, args.tolerance, args.sensors) if "gust" in flights else []
    table = markdown(spiral, gust)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "air.md").write_text(table, encoding="utf-8")
    (out / "air.json").write_text(json.dumps({"sensors": args.sensors or "scenario", "spiral_3x2_wind": spiral,
                                                         "hover_3x2_gust": gust}, indent=1), encoding="utf-8")
    print(table)
    return 0 if all(r["completed"] for r in spiral + gust) else 1


if __name__ == "__main__":
    try:
        sys.exit(main())
    except UserInputError as exc:
        print(f"air_eval: {exc}", file=sys.stderr)
        sys.exit(2)
