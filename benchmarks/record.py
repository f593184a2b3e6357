"""The benchmarks' results file: what every `benchmarks/bench_*.py --json` writes, so pages are generated from
measurements instead of prose copied out of a terminal.

Why a bare-JSBSim rate in every file: this machine's speed swings 2-3x from one hour to the next, so an
absolute figure means little on its own. Each run therefore steps a fixed bare JSBSim body (the 3x2
assembly at 500 Hz with per-step rotor writes, as `bench_physics.py` does) before and after the benchmark;
a figure is read as a ratio within its run or next to that rate.

One file per run, `benchmarks/results/<bench>-<UTC date and time>.json` (or the folder named by the
environment variable MARS_LINK_BENCH_RESULTS): runs never edit each other's files, so results from
different branches merge without conflicts, and the newest file of a benchmark is its latest result.

Use in a benchmark:

    ap = argparse.ArgumentParser(...)
    add_json_option(ap)
    args = ap.parse_args()
    rec = Recorder.start("bench_physics", args)    # times bare JSBSim when --json is given
    ...
    rec.figure("steps_3x2", 82_800, "steps/s", "3x2, per-step writes")
    rec.headline("loop_vs_bare", 0.12, "ratio", "...")  # the one figure the page shows first
    rec.finish()                                        # writes the file and prints its path
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from mars_link.config.scenario import SCENARIO_DIR

BENCH_DIR = Path(__file__).resolve().parent
ROOT = BENCH_DIR.parent
RESULTS_ENV = "MARS_LINK_BENCH_RESULTS"
SCHEMA = 1

#: the fixed bare-JSBSim reference: the 3x2 assembly of the default scenario, 500 Hz, rotor writes every step
BARE_LAYOUT = ("XXX", "XXX")
BARE_PHYSICS_HZ = 500.0
BARE_STEPS = 1000
BARE_REPEATS = 3


def results_dir() -> Path:
    return Path(os.environ.get(RESULTS_ENV) or BENCH_DIR / "results")


def add_json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true",
                        help=f"also write the figures, with the date, commit and machine figures (cores, a bare-JSBSim "
                             f"rate timed in this run), to benchmarks/results/ (or ${RESULTS_ENV}) and print the path")


def apply_quick(parser: argparse.ArgumentParser, args: argparse.Namespace, **quick: Any) -> None:
    """With `--quick`, the options the user left at their defaults take these smaller values."""
    if not getattr(args, "quick", False):
        return
    for name, value in quick.items():
        if getattr(args, name) == parser.get_default(name):
            setattr(args, name, value)


def portable(value: Any) -> Any:
    """An option value as a results file keeps it: a bundled scenario by its name, a path inside the repository
    relative to it, any other path by its file name alone. Results are committed and compared across machines,
    so no path of the machine that ran the benchmark lands in them. Lists and comma-separated lists item by item."""
    if isinstance(value, list):
        return [portable(v) for v in value]
    if not isinstance(value, str) or "/" not in value and os.sep not in value:
        return value  # (a word, a number: not a path)
    if "," in value:
        return ",".join(portable(part) for part in value.split(","))
    path = Path(value).expanduser()
    resolved = (path if path.is_absolute() else Path.cwd() / path).resolve()
    if resolved.suffix == ".toml" and resolved.parent == SCENARIO_DIR.resolve():
        return resolved.stem
    if resolved.is_relative_to(ROOT):
        return resolved.relative_to(ROOT).as_posix()
    return resolved.name


def portable_argv(argv: list[str]) -> list[str]:
    """The command line as a results file keeps it: every argument (and the value of `--option=value`) portable."""
    out = []
    for arg in argv:
        name, eq, value = arg.partition("=")
        out.append(f"{name}={portable(value)}" if arg.startswith("--") and eq else portable(arg))
    return out


@dataclasses.dataclass
class Figure:
    name: str
    value: float | int | str | bool | None
    unit: str
    note: str = ""
    headline: bool = False


def bare_jsbsim_steps_per_s() -> float:
    """Steps per second of a bare JSBSim 3x2 body with every rotor written each step (best of a few short
    runs: other load only ever adds time)."""
    import numpy as np

    from mars_link.core.assembly import AssemblyModel
    from mars_link.core.rotations import euler_to_quat
    from mars_link.core.state import RigidBodyState
    from sitl.physics import JsbsimBody

    model = AssemblyModel.from_layout(list(BARE_LAYOUT))
    start = RigidBodyState(0.0, np.array([0.0, 0.0, -10.0]), np.zeros(3), euler_to_quat(0, 0, 0), np.zeros(3))
    hover = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
    commands = [hover * (1.0 + 1e-4 * k) for k in range(2)]  # two thrust vectors: every write changes every rotor
    best = 0.0
    with JsbsimBody(model, physics_hz=BARE_PHYSICS_HZ, state=start, rotor_thrusts_n=hover) as body:
        for _ in range(BARE_REPEATS):
            t0 = time.perf_counter()
            for i in range(BARE_STEPS):
                body.set_rotor_thrusts(commands[i % 2])
                body.step()
            best = max(best, BARE_STEPS / (time.perf_counter() - t0))
    return best


def git_commit() -> tuple[str | None, bool | None]:
    """(HEAD's hash, whether the work tree has changes), or (None, None) outside a git checkout."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True,
                              timeout=10).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                                capture_output=True, text=True, check=True, timeout=10).stdout
        return head or None, bool(status.strip())
    except (OSError, subprocess.SubprocessError):
        return None, None


def package_version() -> str | None:
    try:
        import mars_link

        return mars_link.__version__
    except (ImportError, AttributeError):
        return None


class Recorder:
    """Collects one run's figures; writes nothing unless `--json` was given."""

    def __init__(self, bench: str, enabled: bool, args: argparse.Namespace | None = None) -> None:
        self.bench = bench
        self.enabled = enabled
        self.quick = bool(getattr(args, "quick", False))
        self.options = {k: v for k, v in vars(args).items() if k != "json"} if args is not None else {}
        self.figures: list[Figure] = []
        self.started = datetime.datetime.now(datetime.timezone.utc)
        self._t0 = time.perf_counter()
        self._commit, self._dirty = git_commit() if enabled else (None, None)  # the code as the run started
        self._bare_before = bare_jsbsim_steps_per_s() if enabled else None

    @classmethod
    def start(cls, bench: str, args: argparse.Namespace) -> "Recorder":
        return cls(bench, bool(getattr(args, "json", False)), args)

    def figure(self, name: str, value: Any, unit: str, note: str = "", headline: bool = False) -> None:
        if hasattr(value, "item"):  # numpy scalars
            value = value.item()
        if isinstance(value, float) and value != value:  # NaN is not JSON
            value = None
        self.figures.append(Figure(name, value, unit, note, headline))

    def headline(self, name: str, value: Any, unit: str, note: str = "") -> None:
        self.figure(name, value, unit, note, headline=True)

    def document(self) -> dict:
        bare_after = bare_jsbsim_steps_per_s() if self.enabled else None
        rates = [r for r in (self._bare_before, bare_after) if r]
        mean = sum(rates) / len(rates) if rates else None
        commit, dirty = self._commit, self._dirty
        try:
            load = os.getloadavg()[0]
        except OSError:
            load = None
        return {
            "schema": SCHEMA,
            "benchmark": self.bench,
            "date": self.started.isoformat(timespec="seconds"),
            "commit": commit,
            "dirty": dirty,
            "version": package_version(),
            "command": " ".join(["python", f"benchmarks/{self.bench}.py", *portable_argv(sys.argv[1:])]),
            "quick": self.quick,
            "options": {k: portable(v) for k, v in self.options.items()
                        if isinstance(v, (str, int, float, bool, list, type(None)))},
            "wall_s": round(time.perf_counter() - self._t0, 3),
            "machine": {
                "cores": os.cpu_count(),
                "python": platform.python_version(),
                "platform": platform.platform(),
                "load_average_1m": load,
                "bare_jsbsim": {
                    "what": f"{len(BARE_LAYOUT[0])}x{len(BARE_LAYOUT)} assembly, {BARE_PHYSICS_HZ:g} Hz, every rotor "
                            f"written each step, best of {BARE_REPEATS} x {BARE_STEPS} steps, before and after the run",
                    "steps_per_s_before": self._bare_before,
                    "steps_per_s_after": bare_after,
                    "steps_per_s": mean,
                    "real_time_factor": mean / BARE_PHYSICS_HZ if mean else None,
                },
            },
            "figures": [dataclasses.asdict(f) for f in self.figures],
        }

    def finish(self) -> Path | None:
        """Write the results file (with `--json`) and print its path."""
        if not self.enabled:
            return None
        doc = self.document()
        folder = results_dir()
        folder.mkdir(parents=True, exist_ok=True)
        stamp = self.started.strftime("%Y%m%dT%H%M%SZ")
        path = folder / f"{self.bench}-{stamp}.json"
        path.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        print(f"results: {path}", flush=True)
        return path


def load_results(folder: Path | None = None) -> list[dict]:
    """Every results file in `folder` (default: benchmarks/results/), oldest first."""
    folder = folder or results_dir()
    docs = []
    for path in sorted(folder.glob("bench_*.json")):
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError):
            continue
        if isinstance(doc, dict) and doc.get("schema") == SCHEMA:
            doc["file"] = path.name
            docs.append(doc)
    return sorted(docs, key=lambda d: (d["benchmark"], d["date"]))


def latest(docs: list[dict]) -> dict[str, dict]:
    """The newest result of each benchmark."""
    out: dict[str, dict] = {}
    for doc in docs:
        if doc["benchmark"] not in out or doc["date"] >= out[doc["benchmark"]]["date"]:
            out[doc["benchmark"]] = doc
    return out
