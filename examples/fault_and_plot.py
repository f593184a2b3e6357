"""One flight with a rotor failure, flown in this process through mars-link's Python API, and a plot of it.

Nothing needs to run beside it. The scenario (paper 000's spiral by default) loses a rotor mid-flight;
the coordinator reallocates thrust around it. The run directory gets mars-link's usual outputs
(summary.json, telemetry.csv, ...) and this script's own figure, fault_and_plot.png: the tracking
error over time with the fault and the reallocation marked, and the path seen from above.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # draw to a file, no window
import matplotlib.pyplot as plt  # noqa: E402

from mars_link.config.scenario import FTC_MODES, load_scenario, parse_fault_arg  # noqa: E402
from mars_link.core.errors import UserInputError  # noqa: E402
from mars_link.flight.runner import run_scenario  # noqa: E402


def read_telemetry(path: Path) -> dict[str, list[float]]:
    """telemetry.csv as columns (the columns are listed in the docs' run-outputs reference)."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {key: [float(r[key]) for r in rows] for key in rows[0]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="spiral_3x2", help="bundled scenario name or TOML file (default: %(default)s)")
    parser.add_argument("--fault", default="2:2=0@5", metavar="UNIT[:ROTOR]=ETA[@T]",
                        help="the failure, as `mars-link run --fault` (default: %(default)s: unit 2 rotor 2 off at 5 s)")
    parser.add_argument("--ftc", choices=FTC_MODES, default="qp", help="allocation mode (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=20.0, help="simulated seconds (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("runs/fault_and_plot"), help="run directory (default: %(default)s)")
    args = parser.parse_args()
    if not args.duration > 0:
        print("fault_and_plot: --duration must be positive", file=sys.stderr)
        return 2

    try:
        scenario = load_scenario(args.scenario)
        fault = parse_fault_arg(args.fault)
        scenario.faults = [fault]
        scenario.ftc = args.ftc
        scenario.sim.duration_s = args.duration
        args.out.mkdir(parents=True, exist_ok=True)
        summary = run_scenario(scenario, out_dir=args.out, plots=False, mcap=False)
    except UserInputError as exc:  # a misspelled scenario, a bad --fault: one line, as the CLI does
        print(f"fault_and_plot: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"fault_and_plot: cannot write {args.out}: {exc.strerror}", file=sys.stderr)
        return 1

    tel = read_telemetry(args.out / "telemetry.csv")
    fig, (ax_error, ax_path) = plt.subplots(1, 2, figsize=(11, 4.5), dpi=150)
    ax_error.plot(tel["t_s"], tel["error_m"], color="tab:blue", label="tracking error")
    for event in summary["events"]:  # the fault and what the coordinator did about it
        if event["type"] in ("fault", "reallocation"):
            style = {"fault": ("tab:red", "--"), "reallocation": ("tab:green", ":")}[event["type"]]
            ax_error.axvline(event["t_s"], color=style[0], linestyle=style[1], label=event["text"])
    ax_error.set(xlabel="time (s)", ylabel="position error (m)", title=f"{scenario.name}: {fault.describe()}, ftc {args.ftc}")
    ax_error.legend(fontsize="small")
    ax_error.grid(alpha=0.3)
    ax_path.plot(tel["ref_e_m"], tel["ref_n_m"], color="0.5", linestyle="--", label="reference")
    ax_path.plot(tel["pos_e_m"], tel["pos_n_m"], color="tab:blue", label="flown")
    ax_path.set(xlabel="east (m)", ylabel="north (m)", title="path from above")
    ax_path.set_aspect("equal", adjustable="datalim")
    ax_path.legend(fontsize="small")
    ax_path.grid(alpha=0.3)
    fig.tight_layout()
    png = args.out / "fault_and_plot.png"
    fig.savefig(png)
    plt.close(fig)

    before = [e for t, e in zip(tel["t_s"], tel["error_m"]) if t < fault.t_s]
    after = [e for t, e in zip(tel["t_s"], tel["error_m"]) if t >= fault.t_s]
    print(f"diverged: {'yes' if summary['diverged'] else 'no'}")
    print(f"max error before the fault: {max(before, default=float('nan')):.3f} m")
    print(f"max error after the fault:  {max(after, default=float('nan')):.3f} m")
    for event in summary["events"]:
        print(f"event at {event['t_s']:.2f} s: {event['text']}")
    print(f"plot: {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
