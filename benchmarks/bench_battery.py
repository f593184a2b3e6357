"""In-process real-time factor with the units' batteries on, against them off, in one run.

    python benchmarks/bench_battery.py [SCENARIO] [--repeats 4] [--duration S] [--quick] [--json]

The same scenario (default: spiral_3x2 on the realistic plant, mars-real, qp) flown alternately
`--repeats` times each way (so a busy machine slows both alike), compared by the median real-time factor:
* off: no simulated packs (`[battery] enabled = false`): the rotors' maximum is the preset's;
* on: a 4S 2.2 Ah pack per unit in the world (sitl.battery: charge, voltage under load, thrust cap at every
  exchange), BATTERY_STATUS samples at 10 Hz through the units (charge counting, levels) to the coordinator,
  whose allocator is set up again whenever a unit's available thrust moves by 1 %.
Prints each variant's median RTF (wall and per CPU second: the latter is steadier on a loaded machine), the
ratios on/off, and how often the allocator was set up again.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from record import Recorder, add_json_option, apply_quick  # noqa: E402

from mars_link.models.battery import battery_table  # noqa: E402
from mars_link.flight.build import build_flight  # noqa: E402
from mars_link.flight.engine import Engine
from mars_link.flight.recorder import FlightRecorder  # noqa: E402
from mars_link.config.scenario import load_scenario  # noqa: E402


def variants(name: str, duration_s: float | None) -> dict:
    on = load_scenario(name)
    if name == "spiral_3x2":
        on.preset, on.ftc = "mars-real", "qp"
    if on.battery is None:
        on.battery = battery_table({"enabled": True}, on.preset, "bench")
    if duration_s:
        on.sim.duration_s = duration_s
    off = copy.deepcopy(on)
    off.battery = None
    return {"off": off, "on": on}


def fly(sc) -> tuple[float, float, float, int]:
    """(RTF in wall time, RTF per CPU second, mean error m, allocator set-ups) of one in-process flight."""
    flight = build_flight(sc, sc.sim.seed)
    recorder = FlightRecorder(flight)
    setups = [0]
    coordinator = flight.coordinator  # (a flight of pieces: the docked structure is its one piece)
    if hasattr(coordinator, "tracked_piece"):
        coordinator = coordinator.tracked_piece().coordinator
    ctrl = coordinator.controller
    if hasattr(ctrl, "set_available"):
        inner = ctrl.set_available

        def counted(a):
            setups[0] += 1
            inner(a)
        ctrl.set_available = counted
    engine = Engine(flight, [recorder])
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        engine.run()
    finally:
        flight.world.close()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return flight.world.t_s / wall, flight.world.t_s / cpu, recorder.metrics.mean_error_m, setups[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", nargs="?", default="spiral_3x2")
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--quick", action="store_true", help="5 s flights, three of each (alternated)")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, duration=5.0, repeats=3)
    rec = Recorder.start("bench_battery", args)
    runs = variants(args.scenario, args.duration)
    rtf: dict[str, list[float]] = {k: [] for k in runs}
    cpu: dict[str, list[float]] = {k: [] for k in runs}
    setups = 0
    warm = copy.deepcopy(runs["on"])  # imports and first-use costs stay out of the first variant's figure
    warm.sim.duration_s = 0.5
    fly(warm)
    for i in range(args.repeats):
        for k, sc in runs.items():
            r, rc, err, n = fly(sc)
            rtf[k].append(r)
            cpu[k].append(rc)
            setups = max(setups, n)
            print(f"  repeat {i + 1} {k:3s}: RTF {r:.1f}x wall, {rc:.1f}x per CPU s (mean error {err * 1000:.1f} mm, "
                  f"allocator set-ups {n})", file=sys.stderr)
    med = {k: statistics.median(v) for k, v in rtf.items()}
    med_cpu = {k: statistics.median(v) for k, v in cpu.items()}
    print(f"{args.scenario} ({runs['on'].preset}, {runs['on'].ftc}), in-process, median of {args.repeats} alternated, "
          "noise on")
    for k in runs:
        print(f"  batteries {k:3s}: RTF {med[k]:6.1f}x wall, {med_cpu[k]:6.1f}x per CPU second")
    print(f"  ratio on/off: {med['on'] / med['off']:.3f} wall, {med_cpu['on'] / med_cpu['off']:.3f} CPU "
          f"(allocator set up again {setups} times in a flight)")
    for k in runs:
        rec.figure(f"rtf_batteries_{k}", med[k], "x real time", f"{args.scenario}, wall, median of {args.repeats}")
        rec.figure(f"rtf_cpu_batteries_{k}", med_cpu[k], "x real time", "per CPU second")
    rec.figure("on_vs_off_wall", med["on"] / med["off"], "ratio", "RTF with batteries / without, wall time")
    rec.headline("on_vs_off_cpu", med_cpu["on"] / med_cpu["off"], "ratio",
                 "RTF per CPU second with batteries / without (same run, alternated)")
    rec.figure("allocator_setups", setups, "per flight", "times the allocator was set up again")
    rec.finish()


if __name__ == "__main__":
    main()
