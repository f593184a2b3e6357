"""What the fault detector (mars_link/models/fault_detection.py) costs per control step, with no fault and with 3
active hypotheses, on a 3x3 and a 10x10 assembly, measured in one run (issue 41's speed item).

    python benchmarks/bench_detector.py [--layouts 3x3,10x10] [--watch-s 2] [--repeats 3] [--quick] [--json]

The detector is a sans-IO component: it is fed a hover at 100 Hz built from the assembly's own model (the
commands the allocator would send for the efficiencies in force, each unit's IMU with the detector's noise levels,
the body's rotation integrated from the wrench the rotors really make), so a 10x10 costs only the detector's own
work (a whole 10x10 flight in process takes minutes of wall time on a shared machine). Three cases per layout:

* `watch_0`: no fault, nothing believed: the CUSUM watch of every step.
* `watch_3`: three single-rotor faults on distinct units (etas 0, 0 and 0.3, as issue 41's 3x3 example) held as
  beliefs since the start, the commands allocated around them: the watch with 3 faults believed.
* `isolate_3`: the same three faults strike at once, not yet believed (the commands do not know): the steps
  from the alarm to the decision (or the detector's give-up), where the hypothesis library is fitted.

Prints each case's mean, median and dearest step in CPU time (the mean is the cost per control step: the watch's
noise memory and the isolation's fits run on a few steps only) and the ratios of the means within the run (3 against 0, isolating against
watching, 10x10 against 3x3); with --json, the results file (date, commit, the bare-JSBSim rate of the run).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from record import Recorder, add_json_option, apply_quick  # noqa: E402
from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel, parse_layout  # noqa: E402
from mars_link.core.rotations import euler_to_quat  # noqa: E402
from mars_link.core.state import ImuSample, RigidBodyState  # noqa: E402
from mars_link.models.fault_detection import FaultDetector, FaultDetectorParams  # noqa: E402

CONTROL_HZ = 100.0
HEIGHT_M = 5.0
#: the three faults, as issue 41's 3x3 example (unit 1 rotor 2 eta 0, unit 6 rotor 4 eta 0, unit 8 rotor 1
#: eta 0.3), the units placed at the same fractions of the unit count on larger assemblies
FAULT_UNIT_FRACTIONS = ((1 / 9, 2, 0.0), (6 / 9, 4, 0.0), (8 / 9, 1, 0.3))
ISOLATE_MAX_S = 1.0  # stop timing an isolation that has not decided by then


def three_faults(model: AssemblyModel) -> list[tuple[int, int, float]]:
    n = model.n_units
    return [(max(1, round(frac * n)), rotor, eta) for frac, rotor, eta in FAULT_UNIT_FRACTIONS]


def efficiencies(model: AssemblyModel, faults: list[tuple[int, int, float]]) -> np.ndarray:
    eta = model.nominal_eta()
    for unit, rotor, e in faults:
        eta[model.rotor_slot(unit, rotor)] = e
    return eta


def hover_commands(model: AssemblyModel, eta: np.ndarray) -> np.ndarray:
    """The least-norm rotor thrusts that hold the weight with no moment, for the efficiencies `eta`."""
    wrench = np.array([model.mass_kg * GRAVITY_MPS2, 0.0, 0.0, 0.0])
    return np.linalg.pinv(model.effectiveness() * eta) @ wrench


class HoverStream:
    """The detector's inputs of a hover, step by step: `commands` are sent, `eta_true` is what the rotors make."""

    def __init__(self, model: AssemblyModel, commands: np.ndarray, seed: int) -> None:
        self.model, self.commands = model, commands
        self.rng = np.random.default_rng(seed)
        self.params = FaultDetectorParams()
        self.b = model.effectiveness()
        self.j_inv = np.linalg.inv(np.array(model.inertia_kgm2, dtype=float))
        self.omega = np.zeros(3)
        self.k = 0

    def step(self, eta_true: np.ndarray) -> tuple[float, np.ndarray, RigidBodyState, list[ImuSample]]:
        t = self.k / CONTROL_HZ
        self.k += 1
        wrench = self.b @ (eta_true * self.commands)
        self.omega = self.omega + self.j_inv @ wrench[1:] / CONTROL_HZ
        accel = np.array([0.0, 0.0, -wrench[0] / self.model.mass_kg])
        p = self.params
        imus = [ImuSample(t, uid, self.omega + self.rng.normal(0, p.gyro_noise_radps, 3),
                          accel + self.rng.normal(0, p.accel_noise_mps2, 3)) for uid in self.model.unit_ids]
        state = RigidBodyState(t, np.array([0.0, 0.0, -HEIGHT_M]), np.zeros(3), euler_to_quat(0, 0, 0),
                               self.omega.copy())
        return t, self.commands.copy(), state, imus


def timed_update(detector: FaultDetector, inputs) -> tuple[float, list]:
    """The update's CPU time (not wall: on a shared machine a step preempted for milliseconds is not its cost)."""
    t0 = time.process_time()
    found = detector.update(*inputs)
    return time.process_time() - t0, found


def watch(model: AssemblyModel, faults: list[tuple[int, int, float]], watch_s: float, seed: int) -> list[float]:
    """Per-step times of the watch, `faults` believed since the start (and true), after one second's warm-up."""
    eta = efficiencies(model, faults)
    detector = FaultDetector(model)
    detector.set_model(model, eta)
    stream = HoverStream(model, hover_commands(model, eta), seed)
    times = []
    for k in range(int((1.0 + watch_s) * CONTROL_HZ)):
        spent, found = timed_update(detector, stream.step(eta))
        if found:
            raise RuntimeError(f"the detector found {found} in a steady hover: the stream is not consistent")
        if k >= CONTROL_HZ:
            times.append(spent)
    return times


def isolate(model: AssemblyModel, faults: list[tuple[int, int, float]], seed: int) -> tuple[list[float], list]:
    """Per-step times from the alarm on the three faults (striking at once after 2 s of watch) to the decision."""
    detector = FaultDetector(model)
    healthy = model.nominal_eta()
    stream = HoverStream(model, hover_commands(model, healthy), seed)
    for _ in range(int(2.0 * CONTROL_HZ)):
        detector.update(*stream.step(healthy))
    eta = efficiencies(model, faults)
    times: list[float] = []
    found: list = []
    for _ in range(int(ISOLATE_MAX_S * CONTROL_HZ)):
        was_isolating = detector.isolating
        spent, found = timed_update(detector, stream.step(eta))
        if was_isolating or detector.isolating or found:
            times.append(spent)
        if found:
            break
    return times, found


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layouts", default="3x3,10x10", help="square assemblies COLSxROWS, comma-separated")
    ap.add_argument("--watch-s", type=float, default=2.0, help="seconds of watch timed per case and repeat")
    ap.add_argument("--repeats", type=int, default=3, help="streams per case (seeds), alternated across the cases")
    ap.add_argument("--quick", action="store_true", help="1 s of watch, one repeat")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, watch_s=1.0, repeats=1)
    try:
        shapes = [tuple(int(v) for v in s.lower().split("x")) for s in a.layouts.split(",")]
        if not shapes or any(len(s) != 2 or min(s) < 1 or max(s) > 20 for s in shapes):
            raise ValueError
    except ValueError:
        print(f"error: --layouts {a.layouts!r}: expected COLSxROWS[,...] with 1..20 each, e.g. 3x3,10x10",
              file=sys.stderr)
        sys.exit(2)
    if a.watch_s <= 0 or a.repeats < 1:
        print("error: --watch-s must be > 0 and --repeats >= 1", file=sys.stderr)
        sys.exit(2)
    rec = Recorder.start("bench_detector", a)
    per_layout = {}
    for cols, rows in shapes:
        name = f"{cols}x{rows}"
        model = AssemblyModel.from_layout(parse_layout(",".join(["X" * cols] * rows)))
        if model.n_units < 9:
            print(f"error: --layouts {name}: the three faults need at least 9 units", file=sys.stderr)
            sys.exit(2)
        faults = three_faults(model)
        watch(model, [], 0.2, 0)  # warm-up: first-use costs stay out
        cases: dict[str, list[float]] = {"watch_0": [], "watch_3": [], "isolate_3": []}
        decided = []
        for r in range(a.repeats):
            order = ("watch_0", "watch_3", "isolate_3") if r % 2 == 0 else ("isolate_3", "watch_3", "watch_0")
            for case in order:  # alternated, so a change of the machine's load hits every case
                if case == "isolate_3":
                    times, found = isolate(model, faults, seed=r + 1)
                    decided.append(found)
                else:
                    times = watch(model, faults if case == "watch_3" else [], a.watch_s, seed=r + 1)
                cases[case] += times
        means = {c: statistics.fmean(v) for c, v in cases.items()}
        per_layout[name] = means
        found_text = "; ".join(", ".join(f"u{d.unit}" + (f"r{d.rotor}" if d.rotor else "") +
                                         f" {d.eta_estimated:.2f}" for d in f) or "none" for f in decided)
        print(f"{name} ({model.n_units} units), faults {', '.join(f'u{u}r{r}={e:g}' for u, r, e in faults)}:")
        for case, times in cases.items():
            print(f"  {case:9s}: mean {means[case] * 1e6:9.1f} us, median {statistics.median(times) * 1e6:9.1f} us, "
                  f"max {max(times) * 1e6:9.1f} us per step over {len(times)} steps")
        print(f"  isolate_3 decided: {found_text}")
        print(f"  ratios of the means: watch_3 / watch_0 {means['watch_3'] / means['watch_0']:.2f}, "
              f"isolate_3 / watch_0 {means['isolate_3'] / means['watch_0']:.1f}", flush=True)
        for case, times in cases.items():
            rec.figure(f"{case}_{name}_mean_us", means[case] * 1e6, "us",
                       f"{name}, {case} (bench docstring): mean per control step over {len(times)} steps")
            rec.figure(f"{case}_{name}_max_us", max(times) * 1e6, "us", f"{name}, {case}: the dearest step")
        rec.figure(f"watch_3_vs_0_{name}", means["watch_3"] / means["watch_0"], "ratio",
                   f"{name}, mean per control step: watching with 3 faults believed / with none")
        (rec.headline if name == "3x3" else rec.figure)(
            f"isolate_3_vs_watch_0_{name}", means["isolate_3"] / means["watch_0"], "ratio",
            f"{name}, mean per control step: isolating 3 simultaneous faults / watching with none")
    if "3x3" in per_layout and "10x10" in per_layout:
        for case in ("watch_0", "watch_3", "isolate_3"):
            ratio = per_layout["10x10"][case] / per_layout["3x3"][case]
            print(f"10x10 / 3x3, {case}: {ratio:.1f} (means)")
            rec.figure(f"{case}_10x10_vs_3x3", ratio, "ratio", f"mean per control step, {case}: 10x10 / 3x3")
    rec.finish()


if __name__ == "__main__":
    main()
