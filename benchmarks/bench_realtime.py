"""Real-time SITL: command age at the motor for the 6-unit 3x2 hover (world paced to the wall clock,
6 unit processes with the full firmware, coordinator with EKF and fault detection, MAVLink over
loopback UDP), run after run, with where the time goes.

    python benchmarks/bench_realtime.py [--runs 3] [--duration 30] [--transport udp|zenoh|px4-zenoh|zenoh,px4-zenoh]
        [--control-hz 100,250] [--png PATH] [--quick] [--json]

Command age at the motor = when a unit drives its motors with the coordinator's command for a step (its
HIL_ACTUATOR_CONTROLS leaves for the simulator) - that step's sensor sample time (PX4's timestamp_sample
sense: sensor -> unit -> coordinator -> unit -> motors). The stage columns are medians over steps of the
time from the sample to: the last unit reading its sensor datagram, the coordinator holding every unit's
telemetry, its rotor commands computed, sent, the last unit reading its command and the last unit's
motors driven (the units' command_age_unit<i>.csv and coordinator_timing.csv of each run).
`px4-zenoh`: the units commanded through PX4's own per-rotor interface over rmw_zenoh (ActuatorMotors,
with OffboardControlMode at 10 Hz) instead of SET_ACTUATOR_CONTROL_TARGET; the sensors still reach the
coordinator as MAVLink over Zenoh, so zenoh vs px4-zenoh isolates the command interface.
`--control-hz 100,250`: the same at each control rate (the scenario's physics rate kept); the jitter
figure is p99 - p50 of the command age. The machine is shared: compare runs of one invocation, not figures
across days.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from record import Recorder, add_json_option, apply_quick  # noqa: E402
from mars_link.core.errors import UserInputError  # noqa: E402
from mars_link.config.scenario import load_scenario  # noqa: E402
from mars_link.runtime.scheduling import describe_classes  # noqa: E402
from mars_link.processes.sitl_mode import run_sitl_scenario, stage_times  # noqa: E402
from mars_link.transport import LinkSpec  # noqa: E402

LINKS = {"udp": LinkSpec("udp"), "zenoh": LinkSpec("zenoh"), "px4-zenoh": LinkSpec("zenoh", unit_interface="px4-zenoh")}
STAGES = ("sensors_in", "telemetry_in", "computed", "sent", "commands_in", "at_motors")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--duration", type=float, default=30.0,
                    help="simulated (= wall) seconds per run (default 30: in a 5 s run, 1 %% of the commands is the "
                         "first 50 ms, so its p99 measures the start-up, not the control path)")
    ap.add_argument("--transport", default="udp",
                    help="udp, zenoh, px4-zenoh, or several (zenoh,udp: runs alternate, medians and their ratio printed)")
    ap.add_argument("--scenario", default="hover_3x2")
    ap.add_argument("--control-hz", default=None, metavar="HZ[,HZ]",
                    help="control rates to fly, comma-separated (default: the scenario's); each run of each rate alternates")
    ap.add_argument("--png", default=None, help="write the command-age distribution of every run here")
    ap.add_argument("--quick", action="store_true", help="one run of 8 s per transport")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, runs=1, duration=8.0)
    transports = a.transport.split(",")
    if a.runs < 1 or not a.duration > 0 or any(t not in LINKS for t in transports):
        ap.error(f"--runs must be >= 1, --duration > 0, --transport one or more of {', '.join(LINKS)}")
    try:
        sc = load_scenario(a.scenario)
    except UserInputError as e:
        ap.error(str(e))
    sc = dataclasses.replace(sc, sim=dataclasses.replace(sc.sim, duration_s=a.duration))
    try:
        rates = [float(x) for x in a.control_hz.split(",")] if a.control_hz else [sc.sim.control_hz]
    except ValueError:
        ap.error(f"--control-hz {a.control_hz!r}: expected rates in Hz separated by commas")
    if any(not 0 < hz <= sc.sim.physics_hz for hz in rates):
        ap.error(f"--control-hz: each rate in (0, {sc.sim.physics_hz:g}] (the scenario's physics rate)")
    cases = [(t, hz) for hz in rates for t in transports]
    label = {c: c[0] if a.control_hz is None else f"{c[0]}@{c[1]:g}Hz" for c in cases}
    rec = Recorder.start("bench_realtime", a)
    rows: dict[str, list] = {label[c]: [] for c in cases}
    ages_by_run = []
    print(f"{a.runs} runs of {a.scenario}, {a.duration:.0f} s each, {' and '.join(label.values())} (alternating), "
          "real time", flush=True)
    header = (f"{'link':>15} {'run':>3} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} {'misses':>10} {'p99 t>=1s':>9}   "
              + " ".join(f"{s:>12}" for s in STAGES))
    print(header)
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(a.runs):
            for transport, hz in cases:
                name = label[(transport, hz)]
                out = Path(tmp) / f"{transport}-{hz:g}-{i}"
                flown = dataclasses.replace(sc, sim=dataclasses.replace(sc.sim, control_hz=hz))
                s = run_sitl_scenario(flown, out, link=LINKS[transport], realtime=True, plots=False)
                age = s["sitl"]["command_age"]
                stages = stage_times(out)
                rows[name].append(age)
                ages_by_run.append(_ages(out))
                settled = _ages(out, after_s=1.0)  # the start-up (arming, the first exchanges) left out
                p99_settled = float(np.percentile(settled, 99)) if settled.size else float("nan")
                print(f"{name:>15} {i + 1:>3} {age['p50_ms']:>7.2f} {age['p99_ms']:>7.2f} {age['max_ms']:>7.1f} "
                      f"{age['deadline_misses']:>4}/{age['n']:<5} {p99_settled:>9.2f}   "
                      + " ".join(f"{stages.get(k, float('nan')):>12.2f}" for k in STAGES), flush=True)
        wake = s["sitl"].get("cpu_wake_latency")
        scheduling = describe_classes(s["sitl"].get("scheduling") or {})  # (the last run's: SCHED_FIFO or not)
    medians = {}
    for name, ages in rows.items():
        p50 = statistics.median(r["p50_ms"] for r in ages)
        p99 = statistics.median(r["p99_ms"] for r in ages)
        medians[name] = (p50, p99)
        print(f"{name}: median of runs p50 {p50:.2f} ms, p99 {p99:.2f} ms, jitter (p99 - p50) {p99 - p50:.2f} ms "
              "(target p99 < 5 ms)")
        what = f"real-time SITL {a.scenario}, {name}, {a.duration:g} s, median of {a.runs}"
        rec.figure(f"command_age_p50_{name}_ms", p50, "ms", what + ": command age at the motor, p50")
        (rec.headline if name == label[cases[0]] else rec.figure)(
            f"command_age_p99_{name}_ms", p99, "ms", what + ": command age at the motor, p99 (target < 5 ms)")
        rec.figure(f"command_age_jitter_{name}_ms", p99 - p50, "ms", what + ": command age p99 - p50")
        rec.figure(f"deadline_misses_{name}", sum(r["deadline_misses"] for r in ages), "commands",
                   f"of {sum(r['n'] for r in ages)} over the control period's deadline")
    pairs = [(label[(x, hz)], label[(y, hz)]) for hz in rates for x, y in (("zenoh", "udp"), ("px4-zenoh", "zenoh"))
             if (x, hz) in label and (y, hz) in label]
    for a_name, b_name in pairs:
        if a_name in medians and b_name in medians:
            (a50, a99), (b50, b99) = medians[a_name], medians[b_name]
            print(f"{a_name} / {b_name} (same minutes): p50 {a50 / b50:.2f}x, p99 {a99 / b99:.2f}x")
            rec.figure(f"{a_name}_vs_{b_name}_p99", a99 / b99, "ratio", f"command age p99, {a_name} / {b_name}, runs alternated")
    print(f"idle CPUs: {wake}; load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (the machine is shared)")
    print(f"scheduling: {scheduling}")
    if a.png:
        _plot(ages_by_run, Path(a.png))
        print(f"wrote {a.png}")
    rec.finish()
    return 0


def _ages(out: Path, after_s: float = 0.0) -> np.ndarray:
    """Every unit's command ages (ms) of the run in `out`, of the steps at sim time >= `after_s`."""
    ages = []
    for p in sorted(out.glob("command_age_unit*.csv")):
        d = np.atleast_1d(np.genfromtxt(p, delimiter=",", names=True, ndmin=1))
        ages.append(d["age_s"][d["t_s"] >= after_s])
    return np.concatenate(ages) * 1e3 if ages else np.array([])


def _plot(ages_by_run: list[np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for i, ages in enumerate(ages_by_run):
        x = np.sort(ages)
        ax.plot(x, 1.0 - np.arange(x.size) / max(x.size, 1), label=f"run {i + 1}")
    ax.axvline(5.0, color="k", ls="--", lw=1, label="5 ms target (p99)")
    ax.axhline(0.01, color="grey", ls=":", lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("command age at the motor [ms]")
    ax.set_ylabel("fraction of commands older")
    ax.set_title("Real-time SITL, 3x2 hover, 6 units, 100 Hz")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())
