"""Paper 001 Fig. 1 / Fig. 5 on the helix: reconfigured (R) vs not reconfigured (NR).

    python tools/reconfig_eval.py [--out runs/reconfig_eval] [--ftc none,qp] [--no-inflight]

Protocol (specs/reconfig.md §12.1): ModQuad modules (preset modquad-cf2, thrust limits on), the
helix of paper 001 (radius 2.5 m, 1.25 m/s, 2 turns, 3 m rise; mars-link's smooth `helix` kind after
a vertical take-off to 1 m), sensor noise off. Faults follow the driver's deterministic pattern:
fault q hits module 0, rotor q for q < 4, then module 1, rotor q - 4 (modules 0, 1 = units 1, 2 here;
paper-001 rotor q+1 mapped to mars-link numbering). NR: the faults on the nominal allocation. R: the
same layout with the units in the MILP-optimal allocation for those faults (the paper's R runs start
reconfigured). Both flown with the cascaded controller and allocation mode `none` (the paper's
fault-unaware ModQuad baseline: the controller does not know the faults) and, as a second column,
`qp` (our FTC).

Metrics: RMSE = mean over north/east/down of each axis' RMS error (paper) and the 3-D RMS error;
force integral = Σ rotors ∫ thrust² dt (N²·s); diverged = the runner's flag (error > 5 m or tilt > 80
deg) or a maximum error above 2 m (spec §12.1's benchmark definition). A diverged run stops at
divergence, so its RMSE and force integral cover less time: read them as "failed", not as figures.

In flight: the donut cases are also flown with the manoeuvre executed mid-mission (faults at t = 5 s,
every piece flown with `qp`); RMSE excludes the paused manoeuvre, the force integral includes it.
With 4 faults, paper 001's quadrant rule alone would plan an intermediate piece (the dead module
with its two row neighbours) that cannot hover within the thrust limits; the flight planner also
requires an exact hover of every piece, finds no reachable allocation better than the current one
(0 layers) and the assembly flies on with FTC; with 3 faults it is executed.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mars_link.logs.outputs import write_json  # noqa: E402
from mars_link.reconfig import HelixReference, rotor_from_paper001  # noqa: E402
from mars_link.reconfig.placement import SnapWeights, health_from_eta, nominal_cells, solve_placement  # noqa: E402
from mars_link.flight.build import make_trajectory  # noqa: E402
from mars_link.config.scenario import eta_after  # noqa: E402
from mars_link.flight.run_log import RunLog  # noqa: E402
from mars_link.flight.runner import run_trial  # noqa: E402
from mars_link.config.scenario import FaultSpec, scenario_from_dict  # noqa: E402
from mars_link.apps.sweep_pool import call, map_flights, pool_from_args, print_progress, values_or_raise  # noqa: E402

from mars_link.processes.cli_options import add_pool  # noqa: E402
CASES = [
    ("plus-5", [".X.", "XXX", ".X."], 3),
    ("plus-5", [".X.", "XXX", ".X."], 4),
    ("plus-5", [".X.", "XXX", ".X."], 6),
    ("donut-4x4", ["XXXX", "X..X", "X..X", "XXXX"], 3),
    ("donut-4x4", ["XXXX", "X..X", "X..X", "XXXX"], 4),
]
#: flown with the manoeuvre executed mid-mission (index into CASES)
INFLIGHT = (3, 4)
DIVERGED_MAX_ERROR_M = 2.0
#: RMSE differences below this are float noise (qp tracks both allocations to 0.6 mm, equal to 1e-8 m)
SAME_M = 1e-6


def paper_faults(n: int) -> list[FaultSpec]:
    """Fault q: module q // 4 (unit 1, then 2), paper-001 rotor q % 4 + 1."""
    return [FaultSpec(unit=q // 4 + 1, rotor=rotor_from_paper001(q % 4 + 1), eta=0.0, t_s=0.0) for q in range(n)]


def scenario(layout, faults: list[FaultSpec], ftc: str, reconfig: dict | None = None):
    doc = {
        "name": "reconfig-eval", "vehicle": {"preset": "modquad-cf2"},
        "assembly": {"layout": list(layout), "tracked": "com"},
        "trajectory": {"kind": "helix", **HelixReference().trajectory_params()},
        "control": {"controller": "cascaded", "ftc": ftc},
        "faults": [{"t": f.t_s, "unit": f.unit, **({"rotor": f.rotor} if f.rotor else {}), "eta": f.eta}
                   for f in faults],
        "sim": {"noise": False, "seed": 1},
    }
    if reconfig:
        doc["reconfig"] = reconfig
    return scenario_from_dict(doc, "reconfig-eval")


def relabel(layout, faults: list[FaultSpec]) -> tuple[list[FaultSpec], dict]:
    """The faults as they sit after reconfiguration: unit u's faults move to the unit id of its target cell."""
    sc = scenario(layout, faults, "none")
    model = sc.model()
    eta = eta_after(model, faults, math.inf)
    weights = SnapWeights.from_trajectory(make_trajectory(sc, model))
    placement = solve_placement(model, health_from_eta(model, eta), weights, nominal_cells(model))
    cell_to_id = {c: u for u, c in model.unit_cells.items()}
    moved = [FaultSpec(cell_to_id[placement.unit_cells[f.unit]], f.rotor, f.eta, f.t_s) for f in faults]
    return moved, placement.unit_cells


def fly(sc) -> dict:
    model = sc.model()
    log = RunLog(None, model, 20.0)
    r = run_trial(sc, sc.sim.seed, 0, log)
    tel = np.array(log.telemetry_rows)
    err = tel[:, 5:8] - tel[:, 2:5]
    axis_rmse = float(np.mean(np.sqrt(np.mean(err**2, axis=0))))
    diverged = r.diverged or r.max_error_m > DIVERGED_MAX_ERROR_M
    return {"rmse_axes_m": axis_rmse, "rmse_3d_m": r.rmse_m, "max_error_m": r.max_error_m,
            "force_integral_n2s": r.force_integral_n2s, "diverged": bool(diverged), "sim_time_s": r.sim_time_s,
            "telemetry": tel}


def fly_row(layout, faults: list[FaultSpec], mode: str) -> dict:
    """One NR/R flight in a sweep worker: its figures without the telemetry."""
    res = fly(scenario(layout, faults, mode))
    res.pop("telemetry")
    return res


def fly_inflight(layout, faults: list[FaultSpec], out: Path) -> dict:
    from mars_link.flight.run_log import ROTOR_LOG_HZ, RunLog
    from mars_link.flight.runner import run_trial

    late = [FaultSpec(f.unit, f.rotor, f.eta, 5.0) for f in faults]
    sc = scenario(layout, late, "qp", {"enabled": True})
    r = run_trial(sc, 1, log=RunLog(out, sc.model(), ROTOR_LOG_HZ))
    tel = np.array(r.telemetry_rows)
    err = tel[:, 5:8] - tel[:, 2:5]
    return {"rmse_axes_m": float(np.mean(np.sqrt(np.mean(err**2, axis=0)))), "rmse_3d_m": r.rmse_m,
            "max_error_m": r.max_error_m, "force_integral_n2s": r.force_integral_n2s,
            "diverged": bool(r.diverged or r.max_error_m > DIVERGED_MAX_ERROR_M), "reconfigured": r.reconfigured,
            "reconfig_time_s": r.reconfig_time_s, "splits": sum(e["type"] == "split" for e in r.events),
            "docks": sum(e["type"] == "dock" for e in r.events), "sim_time_s": r.sim_time_s,
            "refused": next((e["reason"] for e in r.events if e["type"] == "reconfig_refused"), None)}


def fmt(res: dict) -> str:
    if res["diverged"]:
        return f"diverged (max {res['max_error_m']:.1f} m at {res['sim_time_s']:.1f} s)"
    return f"{res['rmse_axes_m']:.4f} / {res['rmse_3d_m']:.4f}"


def plot(rows: list[dict], modes: list[str], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(modes), 2, figsize=(11, 3.6 * len(modes)), squeeze=False)
    labels = [f"{r['shape']}\n{r['faults']} faults" for r in rows]
    x = np.arange(len(rows))
    for i, mode in enumerate(modes):
        for j, (metric, title) in enumerate((("rmse_axes_m", "RMSE (mean of axes) [m]"),
                                             ("force_integral_n2s", "force integral [N²s]"))):
            ax = axes[i][j]
            for k, which in enumerate(("NR", "R")):
                vals = [r[mode][which][metric] for r in rows]
                div = [r[mode][which]["diverged"] for r in rows]
                bars = ax.bar(x + (k - 0.5) * 0.38, vals, 0.38, label=which, color=f"C{k}")
                for b, d in zip(bars, div):
                    if d:
                        b.set_hatch("//")
                        ax.text(b.get_x() + b.get_width() / 2, b.get_height(), "div.", ha="center", va="bottom",
                                fontsize=7)
            ax.set_xticks(x, labels, fontsize=8)
            ax.set_title(f"{title}, controller allocation '{mode}'", fontsize=9)
            if metric == "rmse_axes_m" and max(r[mode]["NR"][metric] for r in rows) > 0.01:
                ax.set_yscale("log")  # divergence and sub-metre errors on one axis
            else:
                ax.set_ylim(bottom=0)
            ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "reconfig_eval.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="runs/reconfig_eval")
    ap.add_argument("--ftc", default="none,qp", help="allocation modes to compare (comma separated)")
    ap.add_argument("--no-inflight", action="store_true", help="skip the donut flight with the manoeuvre executed")
    add_pool(ap)  # --workers / --scheduler: the flights go through the sweep's executor
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    modes = args.ftc.split(",")
    rows = []
    t0 = time.perf_counter()
    tasks, slots = [], []  # every flight on the sweep's executor; slots: where each result goes
    for shape, layout, n in CASES:
        faults = paper_faults(n)
        moved, cells = relabel(layout, faults)
        rows.append({"shape": shape, "layout": layout, "faults": n,
                     "fault_list": [f.describe() for f in faults],
                     "target": {str(u): list(c) for u, c in sorted(cells.items())}})
        for mode in modes:
            rows[-1][mode] = {}
            for which, fs in (("NR", faults), ("R", moved)):
                tasks.append((fly_row, (layout, fs, mode)))
                slots.append((len(rows) - 1, mode, which))
    inflight_cases = [] if args.no_inflight else list(INFLIGHT)
    for idx in inflight_cases:
        shape, layout, n = CASES[idx]
        tasks.append((fly_inflight, (layout, paper_faults(n), out / f"{shape}_{n}_inflight")))
    print(f"{len(tasks)} flights ({len(inflight_cases)} with the manoeuvre executed in flight, faults at t = 5 s)",
          flush=True)
    results = values_or_raise(map_flights(call, tasks, pool_from_args(args), print_progress(len(tasks))),
                              "reconfig_eval flight")
    for (k, mode, which), res in zip(slots, results):
        rows[k][mode][which] = res
        r = rows[k]
        print(f"{r['shape']} {r['faults']} faults {mode} {which}: {fmt(res)}  "
              f"force {res['force_integral_n2s']:.2f} N²s", flush=True)
    inflight = []
    for idx, res in zip(inflight_cases, results[len(slots):]):
        shape, layout, n = CASES[idx]
        res.update(shape=shape, faults=n)
        inflight.append(res)
        print(f"in flight: {shape} {n} faults: reconfigured={res['reconfigured']} refused={res['refused']} "
              f"splits={res['splits']} docks={res['docks']} manoeuvre {res['reconfig_time_s']:.1f} s, RMSE {fmt(res)}, "
              f"force {res['force_integral_n2s']:.2f} N²s", flush=True)
    print(f"wall time {time.perf_counter() - t0:.0f} s", flush=True)

    lines = ["| shape | faults | ftc | NR RMSE axes / 3-D [m] | R RMSE axes / 3-D [m] | NR force [N²s] | R force [N²s] "
             "| R <= NR | R force < NR |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for mode in modes:
            nr, rr = r[mode]["NR"], r[mode]["R"]
            better = nr["diverged"] and not rr["diverged"] or (not rr["diverged"] and rr["rmse_axes_m"] <= nr["rmse_axes_m"] + SAME_M)
            less = nr["diverged"] and not rr["diverged"] or rr["force_integral_n2s"] < nr["force_integral_n2s"]
            lines.append(f"| {r['shape']} | {r['faults']} | {mode} | {fmt(nr)} | {fmt(rr)} | "
                         f"{nr['force_integral_n2s']:.2f} | {rr['force_integral_n2s']:.2f} | "
                         f"{'yes' if better else 'NO'} | {'yes' if less else 'NO'} |")
    table = "\n".join(lines)
    print(table)
    (out / "reconfig_eval.md").write_text(table + "\n", encoding="utf-8")
    write_json(out / "reconfig_eval.json", {"rows": rows, "inflight": inflight})
    print(f"plot: {plot(rows, modes, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
