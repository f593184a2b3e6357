"""Issue 41's simultaneous-fault cases flown in process and in lockstep SITL: are the results equal?

    python tools/multifault_sitl_parity.py [--seeds 1-10 | 2,3,7] [--cases multifault_3x3_two,...]
                                           [--esc on,off] [--transport udp|zenoh] [--out runs/multifault_sitl_parity]

Each bundled multi-fault scenario (noise on, faults not told: the coordinator's detectors must find them) is
flown twice per seed and ESC setting with `mars-link run`: in one process, and with `--mode sitl` (the world,
every unit and the coordinator in processes of their own, MAVLink between them). The ESC setting is the
scenario's `[sensors] esc_telemetry`, written into a copy of it in --out. Compared per flight: the belief
events (`fault_detected`, `fault_retracted`, `unit_lost`: unit, rotor, time, eta, onset) and summary.json's mean
error and divergence. Prints a progress line per pair, then a markdown table per case and ESC setting;
writes parity.md and parity.json to --out (parity.partial.jsonl as pairs finish, seed by seed). Exit 0 when every pair is equal, 1 otherwise, 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mars_link.core.errors import UserInputError  # noqa: E402

#: the table's rows (docs/results/2026-12-sweeps.md, "Simultaneous faults, case by case")
CASES = ("multifault_3x3_two", "spiral_3x3_multifault", "multifault_3x2_unit_and_rotor", "plus5_multifault",
         "multifault_donut")
BELIEF_EVENTS = ("fault_detected", "fault_retracted", "unit_lost")


def parse(argv: list[str] | None) -> argparse.Namespace:
    sys.path.insert(0, str(ROOT / "tools"))
    from fdi_quiet_eval import parse_seeds

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1-10", help="seeds: a list and/or ranges, e.g. 1-10 or 2,3,7")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated of {', '.join(CASES)}")
    ap.add_argument("--esc", default="on,off", help="ESC telemetry: on, off or on,off")
    ap.add_argument("--transport", default="udp", choices=("udp", "zenoh"))
    ap.add_argument("--out", default="runs/multifault_sitl_parity")
    args = ap.parse_args(argv)
    args.seed_list = parse_seeds(args.seeds)
    args.case_list = [x.strip() for x in args.cases.split(",") if x.strip()]
    if not args.case_list or any(x not in CASES for x in args.case_list):
        raise UserInputError(f"--cases must name some of {', '.join(CASES)}, got {args.cases!r}")
    args.esc_list = [x.strip() for x in args.esc.split(",") if x.strip()]
    if not args.esc_list or any(x not in ("on", "off") for x in args.esc_list):
        raise UserInputError(f"--esc must be on, off or on,off, got {args.esc!r}")
    return args


def scenario_file(case: str, esc: str, out: Path) -> Path:
    """The bundled scenario with `[sensors] esc_telemetry` set, as a file in `out`."""
    from mars_link.config.scenario import SCENARIO_DIR

    text = (SCENARIO_DIR / f"{case}.toml").read_text(encoding="utf-8")
    value = "true" if esc == "on" else "false"
    if re.search(r"^\[sensors\]$", text, re.M):
        text = re.sub(r"^\[sensors\]$", f"[sensors]\nesc_telemetry = {value}", text, count=1, flags=re.M)
    else:
        text += f"\n[sensors]\nesc_telemetry = {value}\n"
    path = out / "scenarios" / f"{case}_esc_{esc}.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def fly(scenario: Path, seed: int, run_dir: Path, sitl: bool, transport: str) -> dict:
    """One flight with `mars-link run`; its belief events and figures."""
    argv = [sys.executable, "-m", "mars_link.apps.cli", "run", str(scenario), "--out", str(run_dir), "--force",
            "--quiet", "--no-mcap", "--seed", str(seed)]
    if sitl:
        argv += ["--mode", "sitl", "--transport", transport]
    proc = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT)
    summary_path = run_dir / "summary.json"
    if not summary_path.is_file():
        return {"rc": proc.returncode, "error": (proc.stderr or proc.stdout)[-500:]}
    s = json.loads(summary_path.read_text(encoding="utf-8"))
    from mars_link.config.scenario import load_scenario

    return {"rc": proc.returncode, "mean_error_m": s.get("mean_error_m"), "diverged": s.get("diverged"),
            "events": belief_events(s), "eta_errors": eta_errors(s, load_scenario(str(scenario)).faults)}


def eta_errors(summary: dict, faults) -> list[list[float]]:
    """Per scenario fault that a belief names (its unit and rotor, none for a whole unit, at or after the fault):
    |eta believed - eta| of the first such belief and of the last."""
    found = [e for e in summary.get("events", []) if e["type"] == "fault_detected"]
    out = []
    for fault in faults:
        named = [e["eta_estimated"] for e in found
                 if e.get("unit") == fault.unit and e.get("rotor") == fault.rotor and e["t_s"] >= fault.t_s - 1e-9]
        if named:
            out.append([abs(named[0] - fault.eta), abs(named[-1] - fault.eta)])
    return out


def belief_events(summary: dict) -> list[list]:
    """The flight's beliefs as compared: type, unit, rotor, time, eta (`eta_estimated` in summary.json's
    events) and onset."""
    return [[e["type"], e.get("unit"), e.get("rotor"), e["t_s"], e.get("eta_estimated"), e.get("t_onset")]
            for e in summary.get("events", []) if e["type"] in BELIEF_EVENTS]


def markdown(rows: list[dict], args: argparse.Namespace) -> str:
    lines = [f"In process against lockstep SITL ({args.transport}), seeds {args.seeds}, noise on, faults not told.", "",
             "| case | ESC telemetry | pairs | equal | belief events per flight | largest mean-error difference [m] "
             "| diverged (in process / SITL) | eta error max, first / last belief | mean error, mean [m] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for case in args.case_list:
        for esc in args.esc_list:
            rs = [r for r in rows if r["case"] == case and r["esc"] == esc]
            diffs = [r["mean_error_diff_m"] for r in rs if r["mean_error_diff_m"] is not None]
            if not (rs and diffs):
                lines.append(f"| {case} | {esc} | {len(rs)} | 0 | - | - | - | - | - |")
                continue
            errors = [e for r in rs for e in r["inproc"].get("eta_errors", [])]
            eta = f"{max(e[0] for e in errors):.3f} / {max(e[1] for e in errors):.3f}" if errors else "-"
            means = [r["inproc"]["mean_error_m"] for r in rs if r["inproc"].get("mean_error_m") is not None]
            lines.append(f"| {case} | {esc} | {len(rs)} | {sum(r['equal'] for r in rs)} "
                         f"| {min(r['n_events'] for r in rs)}-{max(r['n_events'] for r in rs)} "
                         f"| {max(diffs):.3g} | {sum(bool(r['diverged'][0]) for r in rs)} / "
                         f"{sum(bool(r['diverged'][1]) for r in rs)} | {eta} | {statistics.mean(means):.4f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse(argv)
    except UserInputError as exc:
        print(f"multifault_sitl_parity: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out).resolve()
    # seed by seed: a run stopped early has every case's first seeds (parity.partial.jsonl, a line per pair)
    plan = [(case, esc, seed) for seed in args.seed_list for case in args.case_list for esc in args.esc_list]
    out.mkdir(parents=True, exist_ok=True)
    partial = open(out / "parity.partial.jsonl", "w", encoding="utf-8")
    rows = []
    t0 = time.perf_counter()
    for i, (case, esc, seed) in enumerate(plan):
        scenario = scenario_file(case, esc, out)
        base = out / "runs" / f"{case}_esc_{esc}_seed{seed}"
        a = fly(scenario, seed, base / "inproc", False, args.transport)
        b = fly(scenario, seed, base / "sitl", True, args.transport)
        flown = "error" not in a and "error" not in b
        diff = (abs(a["mean_error_m"] - b["mean_error_m"])
                if flown and None not in (a["mean_error_m"], b["mean_error_m"]) else None)
        equal = flown and a["events"] == b["events"] and diff == 0.0 and a["diverged"] == b["diverged"]
        row = {"case": case, "esc": esc, "seed": seed, "equal": equal, "mean_error_diff_m": diff,
               "n_events": len(a.get("events", [])), "diverged": [a.get("diverged"), b.get("diverged")],
               "inproc": a, "sitl": b}
        rows.append(row)
        partial.write(json.dumps(row) + "\n")
        partial.flush()
        print(f"[{i + 1}/{len(plan)} {time.perf_counter() - t0:.0f} s] {case} esc {esc} seed {seed}: "
              + ("equal" if equal else f"DIFFERENT ({a.get('error') or b.get('error') or 'events or figures'})")
              + f", {row['n_events']} belief events", file=sys.stderr, flush=True)
    partial.close()
    table = markdown(rows, args)
    print(table)
    (out / "parity.md").write_text(table, encoding="utf-8")
    (out / "parity.json").write_text(json.dumps({"seeds": args.seeds, "transport": args.transport, "flights": rows},
                                                indent=1), encoding="utf-8")
    return 0 if all(r["equal"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
