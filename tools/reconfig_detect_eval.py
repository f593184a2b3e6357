"""Paper 001's reconfiguration cases with the faults found in flight, not told: R vs NR on one engine.

    python tools/reconfig_detect_eval.py [--out runs/reconfig_detect_eval] [--workers 2 | --scheduler ADDRESS] [--cases 0,1,2,3,4]

Each case of `reconfig_eval.CASES` (plus-5 with 3, 4, 6 faults; 4x4 donut with 3, 4) is flown twice on
paper 001's helix with ModQuad modules, sensor noise on (every piece on its own EKF) and
`faults_known = false`: the faults (paper 001's pattern) hit at t = 5 s and only the units' motor
models know them. NR: the pieces' detector finds them and the qp allocator flies on as one body.
R: the same, and the coordinator plans a reconfiguration from the faults it found and executes it
(paper 001's plan, else one move in the air, else a rebuild on the ground), then resumes the helix. Reported: detection latency (first detection after the
fault), RMSE and max error of the tracked point while the mission flies, the force integral
(Σ rotors ∫ thrust² dt) over the whole flight and while the mission flies (the manoeuvre excluded,
so R and NR cover the same mission time), and whether the flight diverged.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from mars_link.logs.outputs import write_json  # noqa: E402
from mars_link.config.scenario import FaultSpec  # noqa: E402
from mars_link.apps.sweep_pool import map_flights, pool_from_args, values_or_raise  # noqa: E402
from mars_link.processes.cli_options import add_pool  # noqa: E402
from reconfig_eval import CASES, DIVERGED_MAX_ERROR_M, paper_faults, scenario  # noqa: E402

FAULT_T_S = 5.0


def detected_scenario(layout, n_faults: int, reconfigure: bool):
    faults = [FaultSpec(f.unit, f.rotor, f.eta, FAULT_T_S) for f in paper_faults(n_faults)]
    sc = scenario(layout, faults, "qp", {"enabled": reconfigure})
    return dataclasses.replace(sc, faults_known=False, sim=dataclasses.replace(sc.sim, noise=True))


def fly(idx: int, which: str) -> dict:
    from mars_link.flight.runner import run_trial

    shape, layout, n = CASES[idx]
    t0 = time.perf_counter()
    r = run_trial(detected_scenario(layout, n, which == "R"), 1)
    found = [e for e in r.events if e["type"] == "fault_detected" and e["t_s"] >= FAULT_T_S - 1e-9]
    return {
        "case": idx, "shape": shape, "faults": n, "which": which,
        "detection_s": (found[0]["t_s"] - FAULT_T_S) if found else None,
        "detected": [(e["unit"], e["rotor"], e["eta_estimated"]) for e in found],
        "false_alarms": sum(e["type"] == "fault_detected" and e["t_s"] < FAULT_T_S for e in r.events),
        "rmse_m": r.rmse_m, "max_error_m": r.max_error_m, "force_integral_n2s": r.force_integral_n2s,
        "mission_force_integral_n2s": r.mission_force_integral_n2s,
        "diverged": bool(r.diverged or r.max_error_m > DIVERGED_MAX_ERROR_M), "completed": r.completed,
        "reconfigured": r.reconfigured, "reconfig_time_s": r.reconfig_time_s,
        "refused": next((e.get("reason") for e in r.events if e["type"] == "reconfig_refused"), None),
        "manoeuvre": manoeuvre(r.events),
        "sim_time_s": r.sim_time_s, "wall_s": time.perf_counter() - t0,
    }


def manoeuvre(events: list[dict]) -> str | None:
    """What the coordinator flew: paper 001's plan, one move in the air, or a rebuild on the ground."""
    plan = next((e for e in events if e["type"] == "plan"), None)
    if plan is None:
        return None
    reason = plan.get("reason") or ""
    if reason.startswith("on the ground"):
        return f"rebuilt on the ground ({plan['disassembly_layers']} lifts, {plan['assembly_layers']} docks)"
    if reason.startswith("one move"):
        return "one move in the air"
    return f"paper 001's plan ({plan['disassembly_layers']} split, {plan['assembly_layers']} dock layers)"


def cell(res: dict) -> str:
    if res["diverged"]:
        return f"diverged (max {res['max_error_m']:.1f} m)"
    return f"{res['rmse_m'] * 1000:.1f} / {res['max_error_m'] * 1000:.0f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="runs/reconfig_detect_eval")
    add_pool(ap)  # --workers (--jobs) / --scheduler: the flights go through the sweep's executor
    ap.add_argument("--cases", default=",".join(str(i) for i in range(len(CASES))),
                    help="indices into the case list (0..4)")
    args = ap.parse_args(argv)
    try:
        cases = [int(x) for x in args.cases.split(",")]
        if not cases or any(not 0 <= c < len(CASES) for c in cases):
            raise ValueError
    except ValueError:
        print(f"error: --cases takes indices 0..{len(CASES) - 1}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(c, w) for c in cases for w in ("NR", "R")]
    t0 = time.perf_counter()
    done = [0]

    def on_done(i: int, outcome) -> None:
        done[0] += 1
        res = outcome.value
        if res is None:
            print(f"[{done[0]}/{len(jobs)}] flight {jobs[i]} raised: {outcome.error}", flush=True)
            return
        print(f"[{done[0]}/{len(jobs)}] {res['shape']} {res['faults']} faults {res['which']}: "
              f"detected in {res['detection_s']} s, RMSE/max {cell(res)} mm, "
              f"force {res['force_integral_n2s']:.1f} (mission {res['mission_force_integral_n2s']:.1f}) N²s, "
              f"reconfigured={res['reconfigured']} ({time.perf_counter() - t0:.0f} s)", flush=True)

    outcomes = map_flights(fly, jobs, pool_from_args(args), on_done)
    results = dict(zip(jobs, values_or_raise(outcomes, "reconfig_detect_eval flight")))
    lines = ["| shape | faults | detection [s] | NR RMSE / max [mm] | R RMSE / max [mm] | NR force, mission [N²s] "
             "| R force, mission [N²s] | R executed | R RMSE <= NR | R mission force < NR |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        nr, rr = results[(c, "NR")], results[(c, "R")]
        det = max((x["detection_s"] for x in (nr, rr) if x["detection_s"] is not None), default=None)
        executed = f"yes: {rr['manoeuvre']}" if rr["reconfigured"] else f"no: {rr['refused'] or 'not planned'}"
        better = (nr["diverged"] and not rr["diverged"]) or (not rr["diverged"] and rr["rmse_m"] <= nr["rmse_m"])
        less = (nr["diverged"] and not rr["diverged"]) or rr["mission_force_integral_n2s"] < nr["mission_force_integral_n2s"]
        lines.append(f"| {nr['shape']} | {nr['faults']} | {'-' if det is None else f'{det:.2f}'} | {cell(nr)} | "
                     f"{cell(rr)} | {nr['mission_force_integral_n2s']:.2f} | {rr['mission_force_integral_n2s']:.2f} | "
                     f"{executed} | {'yes' if better else 'NO'} | {'yes' if less else 'NO'} |")
    table = "\n".join(lines)
    print(table)
    (out / "reconfig_detect_eval.md").write_text(table + "\n", encoding="utf-8")
    write_json(out / "reconfig_detect_eval.json", {"results": [results[k] for k in jobs]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
