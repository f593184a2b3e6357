"""Fault-free flights in wind with the fault detector on (issue 41): how many fault detections, per layout and ESC.

    python tools/fdi_quiet_eval.py [--seeds 1-10 | 2,3,7] [--layouts 3x3,3x2,plus5,donut] [--esc on,off]
                                   [--duration 60] [--wind 5,0,0] [--turbulence moderate] [--sensors gps]
                                   [--workers N] [--out runs/fdi_quiet_eval]

Every flight is fault-free, in-process (sensor noise, EKF, cascaded + qp), with `faults_known = false` so
the coordinator's FaultDetector runs, in `--wind` m/s NED steady wind with `--turbulence` Dryden turbulence,
on the `--sensors` [sensors] profile, with the units' ESC telemetry on and/or off (`[sensors]
esc_telemetry`). Each layout flies the trajectory of its bundled multi-fault scenario, with the faults
taken out: 3x3 and 3x2 on paper 000's spiral, plus5 on the spiral, donut (4x4 ring of paper 001) on its
helix. Every detection of such a flight is a false one. Prints a progress line per flight, then a
markdown table of `fault_detected` events (and `fault_retracted`, their later withdrawals) per layout x
ESC, with the seeds that had any; writes quiet.md and quiet.json to --out. Exit 0 when no flight
detected anything, 1 otherwise, 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mars_link.core.errors import UserInputError  # noqa: E402
from mars_link.apps.sweep_pool import map_flights, pool_from_args, values_or_raise  # noqa: E402
from mars_link.processes.cli_options import add_pool  # noqa: E402

# layout name -> the bundled scenario whose vehicle, assembly and trajectory it flies (faults removed)
LAYOUTS = {
    "3x3": "multifault_3x3_two",
    "3x2": "multifault_3x2_unit_and_rotor",
    "plus5": "plus5_multifault",
    "donut": "multifault_donut",
}


def quiet_scenario(layout: str, esc: bool, duration_s: float, environment: dict | None, sensors: str):
    """The fault-free scenario of `layout`: its bundled scenario's document without faults, in this air."""
    from mars_link.config.scenario import SCENARIO_DIR, read_toml_file, scenario_from_dict

    name = LAYOUTS[layout]
    doc = read_toml_file(SCENARIO_DIR / f"{name}.toml", f"{name}.toml")
    doc.pop("faults", None)
    doc["name"] = f"quiet_{layout}_esc_{'on' if esc else 'off'}"
    doc.setdefault("control", {})["faults_known"] = False
    doc.setdefault("sim", {})["duration_s"] = duration_s
    doc["sim"]["noise"] = True
    if environment:
        doc["environment"] = environment
    doc["sensors"] = {"esc_telemetry": esc} | ({} if sensors == "mocap" else {"profile": sensors})
    return scenario_from_dict(doc, f"{name}.toml")


def quiet_flight(layout: str, esc: bool, seed: int, duration_s: float, environment: dict | None,
                 sensors: str) -> dict:
    """One fault-free flight: its detections (each a false one) and whether it completed."""
    from mars_link.flight.runner import run_trial

    t0 = time.perf_counter()
    r = run_trial(quiet_scenario(layout, esc, duration_s, environment, sensors), seed)
    kinds = [e.get("type") for e in r.events]
    return {"layout": layout, "esc": esc, "seed": seed, "completed": bool(r.completed),
            "fault_detected": kinds.count("fault_detected"), "fault_retracted": kinds.count("fault_retracted"),
            "detections": [dict(d) for d in r.detections], "wall_s": time.perf_counter() - t0}


def parse_seeds(text: str) -> list[int]:
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part:
                a, b = (int(x) for x in part.split("-", 1))
                seeds += list(range(a, b + 1))
            else:
                seeds.append(int(part))
        except ValueError:
            raise UserInputError(f"--seeds must be numbers or ranges like 1-10, got {text!r}") from None
    if not seeds or any(not 1 <= s <= 10_000 for s in seeds):
        raise UserInputError(f"--seeds must name seeds in 1..10000, got {text!r}")
    return sorted(set(seeds))


def parse(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1-10", help="seeds: a list and/or ranges, e.g. 1-10 or 2,3,7")
    ap.add_argument("--layouts", default=",".join(LAYOUTS), help=f"comma-separated of {', '.join(LAYOUTS)}")
    ap.add_argument("--esc", default="on,off", help="ESC telemetry: on, off or on,off")
    ap.add_argument("--duration", type=float, default=60.0, help="flight length, s")
    ap.add_argument("--wind", default="5,0,0", help="steady wind N,E,D in m/s")
    ap.add_argument("--turbulence", default="moderate", help="none | light | moderate | severe, or W20 in m/s")
    ap.add_argument("--sensors", default="gps", help="[sensors] profile: mocap | rtk | gps")
    ap.add_argument("--out", default="runs/fdi_quiet_eval")
    add_pool(ap)
    args = ap.parse_args(argv)
    args.seed_list = parse_seeds(args.seeds)
    args.layout_list = [x.strip() for x in args.layouts.split(",") if x.strip()]
    if not args.layout_list or any(x not in LAYOUTS for x in args.layout_list):
        raise UserInputError(f"--layouts must name some of {', '.join(LAYOUTS)}, got {args.layouts!r}")
    esc = [x.strip() for x in args.esc.split(",") if x.strip()]
    if not esc or any(x not in ("on", "off") for x in esc):
        raise UserInputError(f"--esc must be on, off or on,off, got {args.esc!r}")
    args.esc_list = [x == "on" for x in esc]
    if not 0.5 <= args.duration <= 600:
        raise UserInputError(f"--duration must be in 0.5..600 s, got {args.duration}")
    from mars_link.models.sensor_profiles import PROFILES

    if args.sensors not in PROFILES:
        raise UserInputError(f"unknown --sensors profile {args.sensors!r} (known: {', '.join(PROFILES)})")
    sys.path.insert(0, str(ROOT / "tools"))
    from fdi_eval import air_table

    args.environment = air_table(args.turbulence, args.wind)
    return args


def describe(d: dict) -> str:
    rotor = d.get("rotor")
    return f"u{d['unit']}" + (f"r{rotor}" if rotor else "") + f"={d.get('eta_estimated', float('nan')):.2f}" \
        f"@{d.get('t_detected', float('nan')):.2f}"


def markdown(rows: list[dict], args: argparse.Namespace) -> str:
    lines = [f"Fault-free flights of {args.duration:g} s, wind {args.wind} m/s NED, turbulence {args.turbulence}, "
             f"sensors {args.sensors}, seeds {args.seeds}.", "",
             "| layout | ESC telemetry | flights | completed | fault_detected | fault_retracted | seeds with detections |",
             "|---|---|---|---|---|---|---|"]
    for layout in args.layout_list:
        for esc in args.esc_list:
            rs = [r for r in rows if r["layout"] == layout and r["esc"] == esc]
            bad = [f"{r['seed']} ({r['fault_detected']})" for r in rs if r["fault_detected"]]
            lines.append(f"| {layout} | {'on' if esc else 'off'} | {len(rs)} | {sum(r['completed'] for r in rs)} "
                         f"| {sum(r['fault_detected'] for r in rs)} | {sum(r['fault_retracted'] for r in rs)} "
                         f"| {', '.join(bad) or '-'} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse(argv)
    except UserInputError as exc:
        print(f"fdi_quiet_eval: {exc}", file=sys.stderr)
        return 2
    from mars_link.apps.sweep_pool import call

    plan = [(layout, esc, seed) for layout in args.layout_list for esc in args.esc_list for seed in args.seed_list]
    tasks = [(quiet_flight, (layout, esc, seed, args.duration, args.environment, args.sensors))
             for layout, esc, seed in plan]
    t0 = time.perf_counter()
    done = [0]

    def on_done(i: int, outcome) -> None:
        done[0] += 1
        layout, esc, seed = plan[i]
        head = f"[{done[0]}/{len(plan)} {time.perf_counter() - t0:.0f} s] {layout} esc {'on' if esc else 'off'} seed {seed}"
        if outcome.error is not None:
            print(f"{head}: raised {outcome.error}", file=sys.stderr, flush=True)
            return
        r = outcome.value
        found = ", ".join(describe(d) for d in r["detections"]) or "none"
        print(f"{head}: {r['fault_detected']} fault_detected, {r['fault_retracted']} fault_retracted ({found}); "
              f"completed {r['completed']}, "
              f"{r['wall_s']:.0f} s wall", file=sys.stderr, flush=True)

    rows = values_or_raise(map_flights(call, tasks, pool_from_args(args), on_done), "quiet flight")
    table = markdown(rows, args)
    print(table)
    print(f"wall time {time.perf_counter() - t0:.0f} s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "quiet.md").write_text(table, encoding="utf-8")
    (out / "quiet.json").write_text(json.dumps({"args": {k: v for k, v in vars(args).items()
                                                         if isinstance(v, (str, int, float, list, dict, type(None)))},
                                                "flights": rows}, indent=1, default=str), encoding="utf-8")
    return 0 if all(not r["fault_detected"] and not r["detections"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
