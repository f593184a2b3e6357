"""What the closed Zenoh bus costs: mutual TLS + access control (the default) against `--insecure` (plain
TCP), alternated within one invocation, on the SITL's two clocks:

- real time (`--realtime`, the world paced to the wall clock): command age at the motor, p50 and p99
  (sensor sample -> unit -> coordinator -> unit -> motors; mars_link.processes.sitl_mode's command_age);
- lockstep (as fast as the processes go): the world's real-time factor (simulated s per wall s).

    python benchmarks/bench_tls.py [--runs 2] [--scenario hover_3x2] [--realtime-s 10] [--lockstep-s 4] [--quick] [--json]

Both sides sign every internal MAVLink link with the run's key (the default either way): the difference
is the bus alone. The machine is shared: compare the two columns of one invocation (their ratio), not
figures across days.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from mars_link.config.scenario import load_scenario  # noqa: E402
from mars_link.core.errors import UserInputError  # noqa: E402
from mars_link.processes.sitl_mode import run_sitl_scenario  # noqa: E402
from mars_link.transport import LinkSpec  # noqa: E402
from record import Recorder, add_json_option, apply_quick  # noqa: E402

BUSES = {"tls+acl": LinkSpec("zenoh"), "insecure": LinkSpec("zenoh", insecure=True)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=2, help="rounds; each flies both buses on both clocks")
    ap.add_argument("--scenario", default="hover_3x2")
    ap.add_argument("--realtime-s", type=float, default=10.0, help="simulated (= wall) seconds per real-time run")
    ap.add_argument("--lockstep-s", type=float, default=4.0, help="simulated seconds per lockstep run")
    ap.add_argument("--quick", action="store_true", help="one round of 4 s real time and 2 s lockstep")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, runs=1, realtime_s=4.0, lockstep_s=2.0)
    if a.runs < 1 or not (a.realtime_s > 0 and a.lockstep_s > 0):
        ap.error("--runs must be >= 1, durations > 0")
    try:
        base = load_scenario(a.scenario)
    except UserInputError as e:
        ap.error(str(e))

    def scenario(duration_s: float):
        return dataclasses.replace(base, sim=dataclasses.replace(base.sim, duration_s=duration_s))

    rec = Recorder.start("bench_tls", a)
    figures: dict[str, dict[str, list[float]]] = {b: {"p50_ms": [], "p99_ms": [], "rtf": []} for b in BUSES}
    print(f"{a.runs} rounds of {a.scenario}: real time {a.realtime_s:.0f} s, lockstep {a.lockstep_s:.0f} s; "
          f"{' and '.join(BUSES)} alternating", flush=True)
    print(f"{'bus':>9} {'round':>5} {'age p50 ms':>10} {'age p99 ms':>10} {'lockstep RTF':>12}")
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(a.runs):
            for bus, link in BUSES.items():
                rt = run_sitl_scenario(scenario(a.realtime_s), Path(tmp) / f"rt-{bus}-{i}", link=link, realtime=True,
                                       plots=False, view=())
                ls = run_sitl_scenario(scenario(a.lockstep_s), Path(tmp) / f"ls-{bus}-{i}", link=link, plots=False,
                                       view=())
                assert rt["sitl"]["bus"] == ls["sitl"]["bus"] == bus, (rt["sitl"]["bus"], bus)
                age = rt["sitl"]["command_age"]
                rtf = float(ls["sitl"]["world_real_time_factor"])
                for key, value in (("p50_ms", age["p50_ms"]), ("p99_ms", age["p99_ms"]), ("rtf", rtf)):
                    figures[bus][key].append(float(value))
                print(f"{bus:>9} {i + 1:>5} {age['p50_ms']:>10.2f} {age['p99_ms']:>10.2f} {rtf:>12.3f}", flush=True)
    med = {b: {k: statistics.median(v) for k, v in f.items()} for b, f in figures.items()}
    print("medians:")
    for bus, m in med.items():
        print(f"{bus:>9} {'':>5} {m['p50_ms']:>10.2f} {m['p99_ms']:>10.2f} {m['rtf']:>12.3f}")
    t, o = med["tls+acl"], med["insecure"]
    print(f"tls+acl / insecure: age p50 x{t['p50_ms'] / o['p50_ms']:.2f}, p99 x{t['p99_ms'] / o['p99_ms']:.2f}, "
          f"lockstep RTF x{t['rtf'] / o['rtf']:.2f}")
    for bus, m in med.items():
        rec.figure(f"command_age_p50_{bus}_ms", m["p50_ms"], "ms", f"real time, {a.scenario}, median of {a.runs}")
        rec.figure(f"command_age_p99_{bus}_ms", m["p99_ms"], "ms", f"real time, {a.scenario}, median of {a.runs}")
        rec.figure(f"lockstep_rtf_{bus}", m["rtf"], "x", f"lockstep, {a.scenario}, median of {a.runs}")
    rec.headline("command_age_p50_tls_vs_insecure", t["p50_ms"] / o["p50_ms"], "ratio",
                 "command age p50, closed bus / --insecure (same run)")
    rec.figure("command_age_p99_tls_vs_insecure", t["p99_ms"] / o["p99_ms"], "ratio",
               "command age p99, closed bus / --insecure (same run)")
    rec.figure("lockstep_rtf_tls_vs_insecure", t["rtf"] / o["rtf"], "ratio",
               "lockstep real-time factor, closed bus / --insecure (same run)")
    rec.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
