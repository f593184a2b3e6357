"""This tree against an earlier commit, flight for flight: in-process and lockstep-SITL real-time factors of
both, flown alternately in one run, and (this tree only) `assemble_3x2` against `spiral_3x2` in process.

    python benchmarks/bench_before_after.py [--before COMMIT] [--repeats N] [--inproc-duration S]
        [--sitl-scenario hover_3x2] [--sitl-duration S] [--pair-duration S] [--no-feature-matched] [--no-mcap]
        [--quick] [--json]

Why flights as subprocesses: the earlier code has another package layout (before the restructuring of
December 2026, `mars_link/cli.py`, `mars_link/runner.py`, ...), so it cannot be imported beside this tree.
The earlier commit is unpacked into a temporary folder (`git archive`, removed at the end), and every
measured flight is `python -m <its cli> run SCENARIO --out DIR ...` with `PYTHONPATH` set to one tree or
the other and the working directory a scratch folder (`-m` puts the working directory first on the path:
run from the repository root, the earlier tree would import this one). Both trees fly the same way.

Why alternated: this machine is shared and its speed swings 2-3x within an hour, so an absolute real-time
factor (RTF) means little; the figures are ratios of flights flown next to each other. Pairs alternate
their order (earlier-then-this, this-then-earlier, ...), so a steady drift of the machine's speed
favours neither side over the run; the ratio is the median of the pairs' ratios.

Feature-matched (`--feature-matched`, on by default): the in-process and lockstep comparisons once more, this tree
flying the same scenarios with its units' ESC telemetry off (`[sensors] esc_telemetry = false`, a copy of the
bundled file). In lockstep this tree's units still sign their MAVLink and write their ULog, which the earlier
tree's did not.
Why: the earlier tree had no ESC model, and this tree's default flight samples every rotor's RPM and current at
50 Hz (issue 41); the pair tells the cost of the restructuring from the cost of that added work.

Where the figures come from: each flight's own summary.json. In process: `real_time_factor` (simulated
time / wall time of the flight loop, start-up and plots excluded). Lockstep SITL (`--mode sitl
--transport udp`): `sitl.world_real_time_factor` (the world's stepping loop, the processes' start-up
excluded); the whole run's `real_time_factor` (start-up included) is given beside it.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from record import ROOT, Recorder, add_json_option, apply_quick, bare_jsbsim_steps_per_s

DEFAULT_BEFORE = "30fcd0a"  # the last commit before the restructuring into subpackages began
#: the CLI module of a tree: the restructured layout first, then the flat one
CLI_MODULES = ("mars_link/apps/cli.py", "mars_link/cli.py")
FLIGHT_TIMEOUT_S = 1800.0


@dataclass(frozen=True)
class Tree:
    """One version of the code, as its flights see it: a folder on PYTHONPATH and its CLI module."""

    label: str  # "before" or "after"
    root: Path
    commit: str

    @property
    def cli(self) -> str:
        for rel in CLI_MODULES:
            if (self.root / rel).is_file():
                return rel.removesuffix(".py").replace("/", ".")
        raise SystemExit(f"{self.label} ({self.commit[:9]}): no CLI module among {CLI_MODULES}")


def rev_parse(rev: str) -> str:
    res = subprocess.run(["git", "rev-parse", "--verify", f"{rev}^{{commit}}"], cwd=ROOT, capture_output=True,
                         text=True)
    if res.returncode != 0:
        raise SystemExit(f"--before {rev}: not a commit of this repository ({res.stderr.strip()})")
    return res.stdout.strip()


@contextlib.contextmanager
def unpacked(commit: str) -> Iterator[Path]:
    """The commit's files in a temporary folder (git archive: no work-tree bookkeeping left behind if the
    run is killed); removed on exit."""
    with tempfile.TemporaryDirectory(prefix="bench_before_") as tmp:
        data = subprocess.run(["git", "archive", "--format=tar", commit], cwd=ROOT, capture_output=True,
                              check=True).stdout
        with tarfile.open(fileobj=io.BytesIO(data)) as tar:
            tar.extractall(tmp, filter="data")
        yield Path(tmp)


@dataclass
class Flight:
    tree: str
    scenario: str
    mode: str
    rtf: float  # the figure compared (in process: the flight loop's; SITL: the world's stepping loop's)
    rtf_whole: float  # summary.json's real_time_factor (SITL: with the processes' start-up)
    sim_s: float
    wall_s: float  # the subprocess, start-up, plots and all
    stage_us: dict[str, float]  # in process: each stage's wall time per physics step


def fly(tree: Tree, scenario: str, scratch: Path, *, mode: str = "inproc", duration_s: float | None = None,
        mcap: bool = True) -> Flight:
    """One flight of `tree` as a subprocess; its figures read from the summary.json it wrote."""
    with tempfile.TemporaryDirectory(dir=scratch) as tmp:
        out = Path(tmp) / "run"
        argv = [sys.executable, "-m", tree.cli, "run", scenario, "--out", str(out), "--quiet"]
        if duration_s is not None:
            argv += ["--duration", f"{duration_s:g}"]
        if mode == "sitl":
            argv += ["--mode", "sitl", "--transport", "udp"]
        if not mcap:
            argv.append("--no-mcap")
        env = {**os.environ, "PYTHONPATH": str(tree.root)}
        t0 = time.perf_counter()
        res = subprocess.run(argv, cwd=tmp, env=env, capture_output=True, text=True, timeout=FLIGHT_TIMEOUT_S)
        wall = time.perf_counter() - t0
        if res.returncode != 0 or not (out / "summary.json").is_file():
            tail = (res.stderr or res.stdout)[-2000:]
            raise SystemExit(f"{tree.label} {scenario} ({mode}): exit {res.returncode}\n{tail}")
        s = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    if not s.get("completed", False):
        raise SystemExit(f"{tree.label} {scenario} ({mode}): the flight did not complete")
    sim_s = float(s["sim_time_s"])
    whole = s.get("real_time_factor") or sim_s / float(s["wall_time_s"])
    rtf = float((s.get("sitl") or {}).get("world_real_time_factor") or whole) if mode == "sitl" else float(whole)
    steps = sim_s * float(s.get("physics_hz") or 500.0)
    stages = {k: 1e6 * float(v) / steps for k, v in (s.get("stage_time_s") or {}).items()} if mode == "inproc" else {}
    label = Path(scenario).stem if scenario.endswith(".toml") else scenario  # (a scratch copy: its name, not its path)
    return Flight(tree.label, label, mode, rtf, float(whole), sim_s, wall, stages)


def without_esc(tree: Tree, scenario: str, scratch: Path) -> str:
    """A copy of `tree`'s bundled `scenario` with `[sensors] esc_telemetry = false`: the path to fly."""
    text = (tree.root / "mars_link" / "scenarios" / f"{scenario}.toml").read_text(encoding="utf-8")
    line = "esc_telemetry = false\n"
    if "[sensors]\n" in text:
        text = text.replace("[sensors]\n", "[sensors]\n" + line, 1)
    else:
        text += "\n[sensors]\n" + line
    path = scratch / f"{scenario}_no_esc.toml"
    path.write_text(text, encoding="utf-8")
    return str(path)


def alternate(a: Tree | str, b: Tree | str, repeats: int, flight) -> list[tuple[Flight, Flight]]:
    """`repeats` pairs (a's flight, b's flight), flown a-b, b-a, a-b, ... (drift favours neither side)."""
    pairs = []
    for i in range(repeats):
        if i % 2 == 0:
            fa = flight(a)
            fb = flight(b)
        else:
            fb = flight(b)
            fa = flight(a)
        pairs.append((fa, fb))
        print(f"  pair {i + 1}: {fa.tree} {fa.scenario} {fa.rtf:.2f}x, {fb.tree} {fb.scenario} {fb.rtf:.2f}x "
              f"-> {fb.rtf / fa.rtf:.3f}", flush=True)
    return pairs


def ratio_figures(rec: Recorder, name: str, pairs: list[tuple[Flight, Flight]], what: str) -> float:
    """The headline ratio (median of b/a over the pairs) and every flight's RTF as its own figure."""
    ratios = [fb.rtf / fa.rtf for fa, fb in pairs]
    med = statistics.median(ratios)
    by_tree = pairs[0][0].tree != pairs[0][1].tree  # (else two scenarios of one tree)
    rec.headline(name, med, "ratio", f"{what}: median of {len(pairs)} alternated pairs "
                                     f"(pairs: {', '.join(f'{r:.3f}' for r in ratios)})")
    for flights in ([p[0] for p in pairs], [p[1] for p in pairs]):
        label = flights[0].tree if by_tree else flights[0].scenario
        for k, f in enumerate(flights, 1):
            rec.figure(f"{name}_rtf_{label}_{k}", f.rtf, "x real time",
                       f"{f.scenario} ({f.mode}), {f.sim_s:.1f} s simulated, {f.tree}; subprocess wall {f.wall_s:.1f} s")
    return med


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", default=DEFAULT_BEFORE, help="the earlier commit (default: %(default)s)")
    ap.add_argument("--repeats", type=int, default=3, help="alternated pairs per comparison (default: %(default)s)")
    ap.add_argument("--scenario", default="spiral_3x2",
                    help="the in-process comparison's scenario (default: %(default)s, what `mars-link run` flies)")
    ap.add_argument("--inproc-duration", type=float, default=30.0, help="its flights' length [simulated s]")
    ap.add_argument("--sitl-scenario", default="hover_3x2", help="the lockstep SITL comparison's scenario")
    ap.add_argument("--sitl-duration", type=float, default=10.0, help="its flights' length [simulated s]")
    ap.add_argument("--pair-duration", type=float, default=None,
                    help="assemble_3x2 against spiral_3x2: the spiral's length [simulated s] (assemble_3x2 docks "
                         "first; default: both whole)")
    ap.add_argument("--feature-matched", action=argparse.BooleanOptionalAction, default=True,
                    help="also fly the in-process comparison with this tree's ESC telemetry off (default: on)")
    ap.add_argument("--no-mcap", action="store_true", help="flights without run.mcap (default: as `mars-link run`)")
    ap.add_argument("--quick", action="store_true",
                    help="one pair each, short flights (in process 5 s, SITL 3 s, the spiral after docking 15 s)")
    add_json_option(ap)
    args = ap.parse_args()
    apply_quick(ap, args, repeats=1, inproc_duration=5.0, sitl_duration=3.0, pair_duration=15.0)
    rec = Recorder.start("bench_before_after", args)
    bare_before = bare_jsbsim_steps_per_s()
    head = rev_parse("HEAD")
    before_commit = rev_parse(args.before)
    mcap = not args.no_mcap
    with unpacked(before_commit) as old_root, tempfile.TemporaryDirectory(prefix="bench_flights_") as scratch_dir:
        scratch = Path(scratch_dir)
        old, new = Tree("before", old_root, before_commit), Tree("after", ROOT, head)
        print(f"before: {before_commit[:9]} ({old.cli}); after: this tree at {head[:9]} ({new.cli})", flush=True)
        for tree in (old, new):  # warm-up: byte-compiling the earlier tree, disk caches; not measured
            fly(tree, args.scenario, scratch, duration_s=1.0, mcap=False)

        print(f"in process: {args.scenario}, {args.inproc_duration:g} s", flush=True)
        inproc = alternate(old, new, args.repeats, lambda t: fly(t, args.scenario, scratch,
                                                                  duration_s=args.inproc_duration, mcap=mcap))
        matched: list[tuple[Flight, Flight]] = []
        if args.feature_matched:
            no_esc = without_esc(new, args.scenario, scratch)
            print(f"in process, this tree without ESC telemetry: {args.scenario}, {args.inproc_duration:g} s", flush=True)
            matched = alternate(old, new, args.repeats, lambda t: fly(
                t, args.scenario if t is old else no_esc, scratch, duration_s=args.inproc_duration, mcap=mcap))
        print(f"lockstep SITL (udp): {args.sitl_scenario}, {args.sitl_duration:g} s", flush=True)
        sitl = alternate(old, new, args.repeats, lambda t: fly(t, args.sitl_scenario, scratch, mode="sitl",
                                                                duration_s=args.sitl_duration, mcap=mcap))
        sitl_matched: list[tuple[Flight, Flight]] = []
        if args.feature_matched:
            no_esc = without_esc(new, args.sitl_scenario, scratch)
            print(f"lockstep SITL (udp), this tree without ESC telemetry: {args.sitl_scenario}, "
                  f"{args.sitl_duration:g} s", flush=True)
            sitl_matched = alternate(old, new, args.repeats, lambda t: fly(
                t, args.sitl_scenario if t is old else no_esc, scratch, mode="sitl", duration_s=args.sitl_duration,
                mcap=mcap))
        length = "whole flights" if args.pair_duration is None else f"spiral {args.pair_duration:g} s (after docking)"
        print(f"this tree, in process: assemble_3x2 against spiral_3x2, {length}", flush=True)
        pair = alternate("spiral_3x2", "assemble_3x2", args.repeats,
                         lambda s: fly(new, s, scratch, duration_s=args.pair_duration, mcap=mcap))
    bare_after = bare_jsbsim_steps_per_s()

    r_in = ratio_figures(rec, "inproc_after_vs_before", inproc,
                         f"{args.scenario} in process, {args.inproc_duration:g} s: RTF of this tree / {args.before}'s")
    r_matched = None
    if matched:
        r_matched = ratio_figures(rec, "inproc_no_esc_vs_before", matched,
                                  f"{args.scenario} in process, {args.inproc_duration:g} s, this tree's ESC telemetry "
                                  f"off: RTF of this tree / {args.before}'s")
    r_sitl = ratio_figures(rec, "sitl_after_vs_before", sitl,
                           f"{args.sitl_scenario} lockstep SITL (udp), {args.sitl_duration:g} s: the world loop's RTF "
                           f"of this tree / {args.before}'s")
    r_sitl_matched = None
    if sitl_matched:
        r_sitl_matched = ratio_figures(rec, "sitl_no_esc_vs_before", sitl_matched,
                                       f"{args.sitl_scenario} lockstep SITL (udp), {args.sitl_duration:g} s, this "
                                       f"tree's ESC telemetry off: the world loop's RTF of this tree / {args.before}'s")
    r_pair = ratio_figures(rec, "assemble_vs_spiral", pair,
                           f"this tree in process, {length}: assemble_3x2's RTF / spiral_3x2's")
    for label, side in (("before", 0), ("after", 1)):
        rec.figure(f"sitl_whole_rtf_{label}", statistics.median(p[side].rtf_whole for p in sitl), "x real time",
                   "lockstep SITL, the whole run (processes' start-up included), median")
    stages = list(inproc[0][0].stage_us)
    for stage in stages:
        for label, side in (("before", 0), ("after", 1)):
            rec.figure(f"stage_{stage}_us_{label}", statistics.median(p[side].stage_us.get(stage, 0.0) for p in inproc),
                       "us", f"{args.scenario} in process: wall time per physics step, median")
    bare_rtf = 0.5 * (bare_before + bare_after) / 500.0
    rec.figure("bare_jsbsim_rtf", bare_rtf, "x real time",
               "bare JSBSim 3x2 at 500 Hz, every rotor written each step, timed just before and after the flights "
               "(mean; machine.bare_jsbsim is timed at the run's start and end)")

    print(f"\nbare JSBSim (3x2, 500 Hz): {bare_rtf:.0f}x real time (before {bare_before / 500:.0f}x, "
          f"after {bare_after / 500:.0f}x)")
    print(f"{'comparison':<44}{'median ratio':>13}{'target':>9}  {'median':<12}pairs")
    for name, value, target, pairs in (("in process, this tree / before", r_in, 1.0, inproc),
                                       ("  the same, this tree without ESC telemetry", r_matched, 1.0, matched),
                                       ("lockstep SITL world, this tree / before", r_sitl, 1.0, sitl),
                                       ("  the same, this tree without ESC telemetry", r_sitl_matched, 1.0,
                                        sitl_matched),
                                       ("this tree: assemble_3x2 / spiral_3x2", r_pair, 0.5, pair)):
        if value is None:
            continue
        spread = ", ".join(f"{fb.rtf / fa.rtf:.3f}" for fa, fb in pairs)
        verdict = "meets it" if value >= target else "misses it"
        print(f"{name:<44}{value:>13.3f}{'>= ' + format(target, 'g'):>9}  {verdict:<12}{spread}")
    if stages:
        print(f"\n{args.scenario} in process, us per physics step (median): {'stage':<12}{'before':>9}{'after':>9}")
        for stage in stages:
            b = statistics.median(p[0].stage_us.get(stage, 0.0) for p in inproc)
            a = statistics.median(p[1].stage_us.get(stage, 0.0) for p in inproc)
            print(f"{'':<50}{stage:<12}{b:>9.1f}{a:>9.1f}")
    rec.finish()


if __name__ == "__main__":
    main()
