"""What run.mcap and the live Foxglove view cost (mars_link.flight.flight_view), measured in one invocation.

    python benchmarks/bench_mcap.py [--runs 3] [--duration S] [--size-duration 10] [--rt-runs 2] [--rt-duration 8]
        [--quick] [--json]

1. In-process real-time factor of the default scenario (3x2 spiral, its whole flight unless --duration) with run.mcap on and off, runs alternated
   (off, on, off, on, ...); wall time of the whole run (the writer process finishing its file included);
   ratio = median RTF on / median RTF off.
2. run.mcap size per simulated minute: the 3x2 spiral and a 10x10 hover (default rates).
3. Real-time SITL (`run --mode sitl --realtime`, 3x2 hover, world paced at 1x): command age at the motor
   and deadline misses with run.mcap and no server, and with the live server and a Foxglove WebSocket client
   subscribed to every topic (mars_link.apps.foxglove_probe), runs alternated.
The machine is shared: compare the figures of one invocation, not across days.
"""

from __future__ import annotations

import argparse
import asyncio
import copy
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from record import Recorder, add_json_option, apply_quick  # noqa: E402
from mars_link.flight.runner import run_scenario  # noqa: E402
from mars_link.config.scenario import load_scenario  # noqa: E402


def inproc_rtf(duration_s: float, runs: int, tmp: Path, rec: Recorder) -> None:
    sc = load_scenario("spiral_3x2")
    if duration_s is not None:
        sc.sim.duration_s = duration_s
    else:  # the default scenario as `mars-link run` flies it: the whole spiral
        from mars_link.flight.build import flight_duration_s

        duration_s = flight_duration_s(sc)
    import resource

    rtf = {True: [], False: []}
    cpu = {True: [], False: []}
    print(f"1. in-process RTF, spiral_3x2, {duration_s:.0f} s simulated, {runs} runs each (alternated); CPU: the run's "
          "process + its writer process")
    for i in range(runs):
        for on in (False, True):
            out = tmp / f"rtf{i}{'on' if on else 'off'}"
            s0, c0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            run_scenario(copy.deepcopy(sc), out, plots=False, mcap=on)
            wall = time.perf_counter() - t0
            s1, c1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
            own = s1.ru_utime + s1.ru_stime - s0.ru_utime - s0.ru_stime
            child = c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime
            rtf[on].append(duration_s / wall)
            cpu[on].append(own + child)
            size = (out / "run.mcap").stat().st_size if on else 0
            print(f"   run {i + 1} mcap {'on ' if on else 'off'}: RTF {rtf[on][-1]:6.1f}x  CPU {own:5.2f} s"
                  + (f" + writer {child:4.2f} s  ({size / 1e6:.2f} MB)" if on else ""), flush=True)
    on, off = statistics.median(rtf[True]), statistics.median(rtf[False])
    print(f"   median RTF: off {off:.1f}x, on {on:.1f}x -> on/off = {on / off:.3f} (target >= 0.90)")
    c_on, c_off = statistics.median(cpu[True]), statistics.median(cpu[False])
    print(f"   median CPU per run: off {c_off:.2f} s, on {c_on:.2f} s -> CPU-bound RTF on/off = {c_off / c_on:.3f} "
          "(what a fully loaded machine would see)")
    rec.figure("rtf_mcap_off", off, "x real time", f"spiral_3x2, {duration_s:.0f} s, median of {runs}")
    rec.figure("rtf_mcap_on", on, "x real time", f"spiral_3x2, {duration_s:.0f} s, median of {runs}")
    rec.headline("mcap_on_vs_off", on / off, "ratio", "in-process RTF with run.mcap / without (alternated; target >= 0.90)")
    rec.figure("mcap_on_vs_off_cpu", c_off / c_on, "ratio", "CPU-bound RTF with run.mcap / without")


def mcap_size(duration_s: float, tmp: Path, rec: Recorder) -> None:
    print(f"2. run.mcap size per simulated minute ({duration_s:.0f} s flights)")
    cases = [("3x2 spiral", "spiral_3x2", None), ("10x10 hover", "hover_3x2", ["X" * 10] * 10)]
    for name, scenario, layout in cases:
        sc = load_scenario(scenario)
        sc.sim.duration_s = duration_s
        if layout is not None:
            sc.layout = tuple(layout)
            sc.tracked = "com"
        out = tmp / f"size_{scenario}_{len(sc.layout)}"
        t0 = time.perf_counter()
        s = run_scenario(sc, out, plots=False)
        wall = time.perf_counter() - t0
        size = (out / "run.mcap").stat().st_size
        print(f"   {name:12}: {size / 1e6:6.2f} MB for {s['sim_time_s']:.0f} s -> "
              f"{size / 1e6 * 60.0 / s['sim_time_s']:6.2f} MB per simulated minute (run {wall:.1f} s wall)", flush=True)
        rec.figure(f"mcap_mb_per_min_{name.replace(' ', '_')}", size / 1e6 * 60.0 / s["sim_time_s"], "MB/min",
                   f"run.mcap per simulated minute, {name}")


class _Client(threading.Thread):
    """A Foxglove WebSocket client subscribed to every topic for the whole run (retries until the server is up)."""

    def __init__(self, url: str, seconds: float) -> None:
        super().__init__(daemon=True)
        self.url, self.seconds, self.got = url, seconds, {}

    def run(self) -> None:
        from mars_link.apps.foxglove_probe import listen

        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not self.got:
            try:
                self.got = asyncio.run(listen(self.url, None, self.seconds))
            except OSError:
                time.sleep(0.2)


def realtime_deadlines(runs: int, duration_s: float, tmp: Path, rec: Recorder) -> None:
    import socket

    from mars_link.apps.foxglove_probe import rates
    from mars_link.processes.sitl_mode import run_sitl_scenario
    from mars_link.transport import LinkSpec

    sc = load_scenario("hover_3x2")
    sc.sim.duration_s = duration_s
    print(f"3. real-time SITL, hover_3x2, {duration_s:.0f} s, udp: command age at the motor, runs alternated")
    stats = {"mcap, no server": [], "mcap + server + client": []}
    for i in range(runs):
        for name in stats:
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                port = s.getsockname()[1]
            view = ("--mcap",) if name == "mcap, no server" else ("--mcap", "--foxglove", f"127.0.0.1:{port}")
            client = None
            if len(view) > 1:
                client = _Client(f"ws://127.0.0.1:{port}", duration_s)
                client.start()
            summary = run_sitl_scenario(copy.deepcopy(sc), tmp / f"rt{i}_{len(view)}", link=LinkSpec("udp"),
                                        realtime=True, plots=False, view=view)
            age = summary["sitl"]["command_age"]
            stats[name].append(age)
            seen = ""
            if client is not None:
                client.join(5)
                r = rates(client.got)
                seen = "  client: " + ", ".join(f"{t} {v['rate_hz']:.0f} Hz" for t, v in sorted(r.items())
                                                if t in ("/tf", "/scene"))
            print(f"   run {i + 1} {name:24}: p50 {age['p50_ms']:5.2f} ms  p99 {age['p99_ms']:5.2f} ms  "
                  f"max {age['max_ms']:6.1f} ms  misses {age['deadline_misses']}/{age['n']}{seen}", flush=True)
    base = stats["mcap, no server"]
    for name, rows in stats.items():
        p50 = statistics.median(r["p50_ms"] for r in rows)
        p99 = statistics.median(r["p99_ms"] for r in rows)
        misses = sum(r["deadline_misses"] for r in rows)
        n = sum(r["n"] for r in rows)
        ratio = "" if rows is base else (f" -> p99 {p99 / statistics.median(r['p99_ms'] for r in base):.2f}x"
                                         f" of no server")
        print(f"   median {name:24}: p50 {p50:5.2f} ms  p99 {p99:5.2f} ms  misses {misses}/{n}{ratio}")
        rec.figure(f"command_age_p99_{'live_view' if rows is not base else 'no_server'}_ms", p99, "ms",
                   f"real-time SITL hover_3x2, {name}: command age at the motor, p99, median of {runs}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--duration", type=float, default=None, help="simulated s (default: the scenario's own)")
    ap.add_argument("--size-duration", type=float, default=10.0)
    ap.add_argument("--rt-runs", type=int, default=2)
    ap.add_argument("--rt-duration", type=float, default=8.0)
    ap.add_argument("--skip-realtime", action="store_true")
    ap.add_argument("--only", choices=("rtf", "size", "realtime"), default=None, help="one part only")
    ap.add_argument("--quick", action="store_true", help="two runs of each in-process flight (5 s), 3 s size runs, one 3 s real-time run of each")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, runs=2, duration=5.0, size_duration=3.0, rt_runs=1, rt_duration=3.0)
    if a.runs < 1 or a.rt_runs < 1 or not ((a.duration is None or a.duration > 0) and a.size_duration > 0 and a.rt_duration > 0):
        ap.error("--runs/--rt-runs must be >= 1 and durations > 0")
    rec = Recorder.start("bench_mcap", a)
    with tempfile.TemporaryDirectory() as tmp:
        if a.only in (None, "rtf"):
            inproc_rtf(a.duration, a.runs, Path(tmp), rec)
        if a.only in (None, "size"):
            mcap_size(a.size_duration, Path(tmp), rec)
        if a.only in (None, "realtime") and not a.skip_realtime:
            realtime_deadlines(a.rt_runs, a.rt_duration, Path(tmp), rec)
    rec.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
