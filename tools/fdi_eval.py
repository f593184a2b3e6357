"""Fault detection and isolation on paper 000's 3x2 spiral: Table I rotor faults and Fig. 3 unit failures.

    python tools/fdi_eval.py [--out runs/fdi_eval] [--seeds 3] [--ftc qp] [--t-fault 10] [--false-alarm-seeds 5]
                             [--controller cascaded | mars-ftcc-paper] [--cases "{2,5};r2=0.5"] [--lost]
                             [--turbulence none|light|moderate|severe|W20] [--wind N,E,D] [--sensors mocap|rtk|gps]
                             [--esc on|off]

Every case is flown twice per seed with the in-process runner (JSBSim, sensor noise, EKF, cascaded
controller): the faults act in the units' motor paths at `--t-fault` and are told to the coordinator
(`faults_known = true`), then the same flight with `faults_known = false`, where the coordinator's
FaultDetector has to find them. Per case: detection delay (fault -> the detection that completed the
identification), the largest |eta believed - eta true| over all 24 rotors at the end, false alarms,
and the mean tracking error of unit 1 over the whole flight, told vs detected. Acceptance (issue 5):
delay < 0.5 s, eta within 0.1, flight completed, detected error <= 1.5 x told. Fault-free flights
with the detector on count false alarms. `--ftc paper` uses the paper's own mode per case (unit
shares for unit failures, hybrid for rotor faults). `--lost` adds the Fig. 3 unit failures as process
deaths ("lost units {2}" ...): the units stop reporting and their motors stop at the fault time, and
the coordinator must notice the silence (5 control periods) instead of the residuals. `--controller mars-ftcc-paper` flies paper 000's
own controller instead, as `mars-link reproduce table1` does (20 Hz, physics 1 kHz, sensor noise off:
the controller flies on the true state, the detector reads the noise-free unit IMUs at 20 Hz).
`--turbulence` and `--wind` fly every flight in that air (scenario [environment]: Dryden turbulence of
that severity, steady wind in m/s NED; the units' drag on): does the detector mistake the air for a
rotor fault, and does it still find the real ones? `--sensors` flies every flight on that [sensors]
profile (default mocap; gps: delayed GNSS, barometer and magnetometer in the EKF). `--esc off` flies the
units without ESC telemetry ([sensors] esc_telemetry = false): the motion detector alone finds the faults.

Writes fdi.md, fdi.json and fdi.png (detection delay and eta error per case; told vs detected error)
to --out. Exit 0 when every case passed, 1 otherwise, 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mars_link.core.errors import UserInputError  # noqa: E402
from mars_link.logs.outputs import write_json  # noqa: E402
from mars_link.apps.reproduce import (  # noqa: E402
    CASES, FDI_MAX_DELAY_S, FDI_MAX_ETA_ERROR, FDI_MAX_ERROR_RATIO, FdiTrial, fdi_false_alarm_flight, fdi_lost_trial,
    fdi_trial,
)
from mars_link.apps.sweep_pool import call, map_flights, pool_from_args, print_progress, values_or_raise  # noqa: E402

from mars_link.processes.cli_options import add_pool  # noqa: E402
FTC_CHOICES = ("qp", "paper", "unit", "partial", "full", "hybrid")
CONTROLLERS = ("cascaded", "mars-ftcc-paper")


def parse(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/fdi_eval")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--ftc", default="qp")
    ap.add_argument("--t-fault", type=float, default=10.0)
    ap.add_argument("--false-alarm-seeds", type=int, default=5)
    ap.add_argument("--cases", default="", help="';'-separated case-name fragments, e.g. '{2,5};r2=0.5' (default: all faulty cases)")
    ap.add_argument("--controller", default="cascaded")
    ap.add_argument("--lost", action="store_true", help="also fly the unit failures as process deaths")
    ap.add_argument("--no-plot", action="store_true")
    ap.add_argument("--turbulence", default="none", help="none | light | moderate | severe, or W20 in m/s")
    ap.add_argument("--wind", default="0,0,0", help="steady wind N,E,D in m/s (the air's velocity)")
    ap.add_argument("--sensors", default="mocap", help="[sensors] profile: mocap | rtk | gps")
    ap.add_argument("--esc", default="on",
                    help="the units' ESC telemetry (default on; off: the motion detector alone)")
    add_pool(ap)  # --workers / --scheduler: the flights go through the sweep's executor
    args = ap.parse_args(argv)
    args.environment = air_table(args.turbulence, args.wind)
    from mars_link.models.sensor_profiles import PROFILES

    if args.sensors not in PROFILES:
        raise UserInputError(f"unknown --sensors profile {args.sensors!r} (known: {', '.join(PROFILES)})")
    args.sensor_table = None if args.sensors == "mocap" else {"profile": args.sensors}
    if args.esc not in ("on", "off"):
        raise UserInputError(f"--esc must be on or off, got {args.esc!r}")
    if args.esc == "off":
        args.sensor_table = {**(args.sensor_table or {}), "esc_telemetry": False}
    if not 1 <= args.seeds <= 100 or not 0 <= args.false_alarm_seeds <= 100:
        raise UserInputError("--seeds must be in 1..100 and --false-alarm-seeds in 0..100")
    if args.ftc not in FTC_CHOICES:
        raise UserInputError(f"--ftc must be one of {', '.join(FTC_CHOICES)}, got {args.ftc!r}")
    if args.controller not in CONTROLLERS:
        raise UserInputError(f"--controller must be one of {', '.join(CONTROLLERS)}, got {args.controller!r}")
    if args.controller == "mars-ftcc-paper" and args.ftc not in ("paper", "unit", "hybrid"):
        raise UserInputError("--controller mars-ftcc-paper flies --ftc paper, unit or hybrid")
    if not (math.isfinite(args.t_fault) and 1.0 <= args.t_fault <= 45.0):
        raise UserInputError(f"--t-fault must be between 1 and 45 s (the spiral lasts 50.27 s), got {args.t_fault}")
    return args


def air_table(turbulence: str, wind: str) -> dict | None:
    """The [environment] table of --turbulence / --wind (None: still air), checked as a scenario's."""
    from mars_link.config.scenario_environment import environment_table

    try:
        turb: str | float = float(turbulence)
    except ValueError:
        turb = turbulence
    try:
        vector = [float(x) for x in wind.split(",")]
    except ValueError:
        raise UserInputError(f"--wind must be N,E,D in m/s, got {wind!r}") from None
    table = {"wind_ned_mps": vector, "turbulence": turb}
    return table if environment_table(table, "--turbulence/--wind").moves_air else None


def select_cases(spec: str):
    faulty = [c for c in CASES if c.faults]
    if not spec:
        return faulty
    wanted = [w.strip() for w in spec.split(";") if w.strip()]
    chosen = [c for c in faulty if any(w in c.name for w in wanted)]
    if not chosen:
        raise UserInputError(f"--cases {spec!r} matches none of: {'; '.join(c.name for c in faulty)}")
    return chosen


def summarize(trials: list[FdiTrial]) -> dict:
    import numpy as np

    delays = [t.delay_s for t in trials]
    return {
        "case": trials[0].case.name,
        "controller": trials[0].controller,
        "ftc": trials[0].ftc,
        "seeds": [t.seed for t in trials],
        "delay_s_max": float(max(delays)),
        "delay_s_mean": float(np.mean(delays)),
        "eta_error_max": float(max(t.eta_error for t in trials)),
        "false_alarms": int(sum(t.false_alarms for t in trials)),
        "error_told_m": float(np.mean([t.error_told_m for t in trials])),
        "error_detected_m": float(np.mean([t.error_detected_m for t in trials])),
        "error_ratio_max": float(max(t.error_ratio for t in trials)),
        "completed": all(t.completed_told and t.completed_detected for t in trials),
        "passed": all(t.passed for t in trials),
        "detections": [t.detections for t in trials],
    }


def markdown(rows: list[dict], fa: dict, args: argparse.Namespace) -> str:
    air = "still air" if args.environment is None else (
        f"wind {args.wind} m/s NED, turbulence {args.turbulence}")
    air += f", sensors {args.sensors}" + ("" if args.esc == "on" else ", no ESC telemetry")
    lines = [
        f"Faults at t = {args.t_fault:g} s, {args.seeds} seed(s), {args.controller}, ftc {args.ftc}, {air}; acceptance: delay < "
        f"{FDI_MAX_DELAY_S} s, eta error <= {FDI_MAX_ETA_ERROR}, detected/told error <= {FDI_MAX_ERROR_RATIO}.",
        "",
        "| case | ftc | delay mean / max [s] | eta error max | false alarms | told error [m] | detected error [m] "
        "| ratio max | pass |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['ftc']} | {r['delay_s_mean']:.2f} / {r['delay_s_max']:.2f} | {r['eta_error_max']:.3f} "
            f"| {r['false_alarms']} | {r['error_told_m']:.4f} | {r['error_detected_m']:.4f} | {r['error_ratio_max']:.2f} "
            f"| {'yes' if r['passed'] else 'NO'} |"
        )
    lines += ["", f"Fault-free spiral with the detector on: {fa['false_alarms']} false alarm(s) in {fa['flights']} "
              f"flight(s) (seeds {fa['seeds']})."]
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    names = [r["case"].replace("T1 ", "").replace("F3 ", "") for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    delays = [min(r["delay_s_max"], 1.0) for r in rows]
    axes[0].bar(x, delays, color=["tab:green" if d < FDI_MAX_DELAY_S else "tab:red" for d in delays])
    axes[0].axhline(FDI_MAX_DELAY_S, color="k", ls="--", lw=1, label="limit")
    axes[0].set_ylabel("detection delay, worst seed [s]")
    errs = [r["eta_error_max"] for r in rows]
    axes[1].bar(x, errs, color=["tab:green" if e <= FDI_MAX_ETA_ERROR else "tab:red" for e in errs])
    axes[1].axhline(FDI_MAX_ETA_ERROR, color="k", ls="--", lw=1, label="limit")
    axes[1].set_ylabel("max |eta believed - eta true|")
    w = 0.38
    axes[2].bar(x - w / 2, [r["error_told_m"] * 100 for r in rows], w, label="faults told")
    axes[2].bar(x + w / 2, [r["error_detected_m"] * 100 for r in rows], w, label="faults detected")
    axes[2].set_ylabel("mean tracking error of unit 1 [cm]")
    for ax in axes:
        ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
        ax.legend(fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"FDI on the 3x2 spiral ({rows[0]['controller']}), faults at {rows[0].get('t_fault_s', 10):g} s, "
                 "not told to the coordinator")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse(argv)
        cases = select_cases(args.cases)
    except UserInputError as exc:
        print(f"fdi_eval: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    rows = []
    t0 = time.perf_counter()
    print(f"{'case':<18} {'seed':>4} {'delay_s':>7} {'eta_err':>7} {'false':>5} {'told_m':>8} {'found_m':>8} "
          f"{'ratio':>5}  detections")
    plan = [(case, fdi_trial) for case in cases]
    if args.lost:
        plan += [(case, fdi_lost_trial) for case in cases if case.unit_failure]
    fa_seeds = list(range(1, args.false_alarm_seeds + 1))
    fa_ftc = ("hybrid" if args.controller == "mars-ftcc-paper" else "qp") if args.ftc == "paper" else args.ftc
    # every flight on the sweep's executor: (fn, args) per case and seed, then the fault-free spirals
    tasks = [(fly, (case, args.ftc, seed, args.t_fault, None, args.controller, args.environment, args.sensor_table))
             for case, fly in plan for seed in range(1, args.seeds + 1)]
    tasks += [(fdi_false_alarm_flight, (s, fa_ftc, None, args.controller, args.environment, args.sensor_table))
              for s in fa_seeds]
    results = values_or_raise(map_flights(call, tasks, pool_from_args(args), print_progress(len(tasks))), "fdi flight")
    trials_all, fa_found = results[:len(results) - len(fa_seeds)], results[len(results) - len(fa_seeds):]
    for k, (case, fly) in enumerate(plan):
        trials = trials_all[k * args.seeds:(k + 1) * args.seeds]
        for t in trials:
            found = ", ".join(f"u{d['unit']}" + (f"r{d['rotor']}" if d["rotor"] else "") + f"={d['eta_estimated']:.2f}"
                              f"@{d['t_detected']:.2f}" for d in t.detections)
            print(f"{t.case.name:<18} {t.seed:>4} {t.delay_s:>7.2f} {t.eta_error:>7.3f} {t.false_alarms:>5} "
                  f"{t.error_told_m:>8.4f} {t.error_detected_m:>8.4f} {t.error_ratio:>5.2f}  {found}", flush=True)
        row = summarize(trials)
        row["t_fault_s"] = args.t_fault
        rows.append(row)
    for s, found in zip(fa_seeds, fa_found):
        print(f"fault-free seed {s}: {len(found)} false alarm(s)", flush=True)
    fa = {"flights": len(fa_seeds), "seeds": fa_seeds, "false_alarms": sum(len(f) for f in fa_found),
          "detections": fa_found}
    table = markdown(rows, fa, args)
    print()
    print(table)
    print(f"wall time {time.perf_counter() - t0:.0f} s")
    out.mkdir(parents=True, exist_ok=True)
    (out / "fdi.md").write_text(table, encoding="utf-8")
    write_json(out / "fdi.json", {"cases": rows, "fault_free": fa, "ftc": args.ftc, "controller": args.controller,
                                  "t_fault_s": args.t_fault, "environment": args.environment,
                                  "sensors": args.sensors, "esc_telemetry": args.esc == "on"})
    if not args.no_plot:
        plot(rows, out / "fdi.png")
        print(f"wrote {out / 'fdi.md'}, {out / 'fdi.json'}, {out / 'fdi.png'}")
    ok = all(r["passed"] for r in rows) and fa["false_alarms"] == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
