"""Reproduce paper 000's Table I (rotor degradation) and Fig. 3 (unit failures) on the 3x2 spiral.

Every case is flown with paper 000's own controller ("mars-ftcc-paper", at its 20 Hz control rate,
on perfect state like the paper's scenes) and with the "cascaded" controller under each FTC mode
(sensor noise on, EKF in the loop), over several seeds, and
compared with the paper's value. Fig. 3 has curves only, so its reference is the independent
re-simulation of specs/ftc.md §9 (marked "resim").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from mars_link.core.ftc import FTC_MODES
from mars_link.logs.outputs import write_json
from mars_link.flight.runner import run_trial
from mars_link.config.scenario import scenario_from_dict
from mars_link.apps.sweep_pool import PoolSpec, map_flights, values_or_raise

PAPER_NOMINAL_M = 0.2230


@dataclass(frozen=True)
class Case:
    name: str
    faults: tuple[tuple[int, int | None, float], ...]  # (unit, rotor or None, eta)
    paper_without_m: float | None
    paper_with_m: float | None
    source: str  # "Table I" or "resim" (specs/ftc.md §9)
    unit_failure: bool


CASES = (
    Case("T1 nominal", (), PAPER_NOMINAL_M, PAPER_NOMINAL_M, "Table I", False),
    Case("T1 u2 r2=0.5", ((2, 2, 0.5),), 0.9050, 0.2933, "Table I", False),
    Case("T1 u2 r1=r2=0.5", ((2, 1, 0.5), (2, 2, 0.5)), 4.3790, 0.3066, "Table I", False),
    Case("F3 units {2}", ((2, None, 0.0),), 16.0, 0.208, "resim", True),
    Case("F3 units {3}", ((3, None, 0.0),), 18.4, 0.188, "resim", True),
    Case("F3 units {2,4}", ((2, None, 0.0), (4, None, 0.0)), 6.2, 0.189, "resim", True),
    Case("F3 units {2,5}", ((2, None, 0.0), (5, None, 0.0)), 1.11, 0.205, "resim", True),
    Case("F3 units {3,4}", ((3, None, 0.0), (4, None, 0.0)), 0.83, 0.178, "resim", True),
)
CASCADED_MODES = FTC_MODES  # (the cascaded controller flies every mode)


def paper_ftc(case: Case) -> str:
    """The paper's "with FTC" for a case: unit shares for unit failures, hybrid for rotors."""
    return "unit" if case.unit_failure else "hybrid"


def scenario_for(
    case: Case, controller: str, ftc: str, duration_s: float | None = None, t_fault_s: float = 0.0,
    faults_known: bool = True, environment: dict | None = None, sensors: dict | None = None,
):
    """The case's scenario. Table I / Fig. 3 inject at t = 0 (the paper's scenes start faulty); the
    FDI evaluation injects at `t_fault_s` and, with `faults_known` false, does not tell the coordinator.
    `environment`: an [environment] table (wind, turbulence) to fly the case in; `sensors`: a [sensors]
    table (e.g. {"profile": "gps"})."""
    paper = controller == "mars-ftcc-paper"
    doc = {
        "name": f"{case.name} / {controller} / {ftc}",
        "vehicle": {"preset": "mars-ftcc"},
        "assembly": {"layout": ["XXX", "XXX"], "tracked": "unit:1"},
        "trajectory": {"kind": "mars-ftcc-spiral"},
        "control": {"controller": controller, "ftc": ftc, "faults_known": faults_known},
        "faults": [
            {"t": t_fault_s, "unit": u, "eta": eta} | ({} if r is None else {"rotor": r}) for u, r, eta in case.faults
        ],
        # the paper's scenes fly on perfect state; its per-step differences amplify sensor noise, so
        # the paper controller gets the truth (deterministic: its spread over seeds is 0)
        # physics at 1 kHz for it: at 200 Hz its result depends on the integrator (sitl/physics.py)
        "sim": {"physics_hz": 1000 if paper else 500, "control_hz": 20 if paper else 100, "noise": not paper},
    }
    if duration_s:
        doc["sim"]["duration_s"] = duration_s
    if environment:
        doc["environment"] = environment
    if sensors:
        doc["sensors"] = sensors
    return scenario_from_dict(doc, "reproduce")


@dataclass
class Row:
    case: Case
    controller: str
    ftc: str
    errors_m: list[float]
    diverged: int

    @property
    def paper_m(self) -> float | None:
        if not self.case.faults:
            return self.case.paper_with_m
        fault_tolerant = self.ftc != "none"
        return self.case.paper_with_m if fault_tolerant else self.case.paper_without_m

    @property
    def mean_m(self) -> float:
        return float(np.mean(self.errors_m))

    @property
    def std_m(self) -> float:
        return float(np.std(self.errors_m))


def plan_runs(controllers: tuple[str, ...], modes: tuple[str, ...]) -> list[tuple[Case, str, str]]:
    runs = []
    for case in CASES:
        if "mars-ftcc-paper" in controllers:
            runs.append((case, "mars-ftcc-paper", "none"))
            if case.faults:
                runs.append((case, "mars-ftcc-paper", paper_ftc(case)))
        if "cascaded" in controllers:
            for mode in modes if case.faults else ("none",):
                runs.append((case, "cascaded", mode))
    return runs


def table1_flight(case: Case, controller: str, ftc: str, duration_s: float | None, seed: int) -> tuple[float, bool]:
    """One flight of Table I / Fig. 3 (in a sweep worker): (mean error m, diverged)."""
    result = run_trial(scenario_for(case, controller, ftc, duration_s), seed)
    return result.mean_error_m, bool(result.diverged)


def reproduce_table1(
    seeds: int = 10,
    controllers: tuple[str, ...] = ("mars-ftcc-paper", "cascaded"),
    modes: tuple[str, ...] = CASCADED_MODES,
    duration_s: float | None = None,
    on_progress: Callable[[int, int, str], None] | None = None,
    pool: PoolSpec | None = None,
) -> list[Row]:
    """Every case x controller x mode x seed, flown on the sweep's executor (`pool`: local cores by default, or
    a Dask cluster); a flight that raises stops the table with its error (every cell needs its flights)."""
    runs = plan_runs(controllers, modes)
    flights = [(case, controller, ftc, duration_s, seed) for case, controller, ftc in runs
               for seed in range(1, seeds + 1)]
    done = [0]

    def on_done(i: int, outcome) -> None:
        done[0] += 1
        if on_progress:
            case, controller, ftc = flights[i][:3]
            on_progress(done[0], len(flights), f"{case.name} / {controller} / {ftc}")

    results = values_or_raise(map_flights(table1_flight, flights, pool, on_done), "reproduce table1 flight")
    rows = []
    for k, (case, controller, ftc) in enumerate(runs):
        mine = results[k * seeds:(k + 1) * seeds]
        rows.append(Row(case, controller, ftc, [e for e, _ in mine], sum(d for _, d in mine)))
    return rows


def markdown_table(rows: list[Row], seeds: int) -> str:
    lines = [
        f"| case | controller | ftc | paper [m] | ours [m] (mean ± std, {seeds} seeds) | ratio to paper | diverged |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        paper = r.paper_m
        ref = "—" if paper is None else f"{paper:.4f}" + (" (resim)" if r.case.source == "resim" else "")
        ratio = "—" if paper is None or not math.isfinite(r.mean_m) else f"{r.mean_m / paper:.2f}"
        lines.append(
            f"| {r.case.name} | {r.controller} | {r.ftc} | {ref} | {r.mean_m:.4f} ± {r.std_m:.4f} | {ratio} | "
            f"{r.diverged}/{len(r.errors_m)} |"
        )
    return "\n".join(lines) + "\n"


def write_results(rows: list[Row], seeds: int, out_dir: Path) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    table = markdown_table(rows, seeds)
    (out_dir / "table1.md").write_text(table, encoding="utf-8")
    data = [
        {"case": r.case.name, "controller": r.controller, "ftc": r.ftc, "paper_m": r.paper_m,
         "paper_source": r.case.source, "errors_m": r.errors_m, "mean_m": r.mean_m, "std_m": r.std_m,
         "diverged": r.diverged}
        for r in rows
    ]
    write_json(out_dir / "table1.json", data)  # strict JSON: NaN/inf -> null
    return out_dir / "table1.md"



# ----------------------------------------------------------------------------- before: how long; after: Fig. 3
#: simulated seconds of the calibration flight that times each controller before the table starts
CALIBRATION_SIM_S = 1.0


@dataclass(frozen=True)
class TableEstimate:
    """How much `reproduce table1` will fly, and roughly how long it takes on this machine."""

    flights: int
    sim_s: float  # simulated seconds, all flights together
    wall_s: float  # estimated wall time on `workers` local processes
    workers: int

    def text(self) -> str:
        minutes = self.wall_s / 60.0
        took = f"{minutes:.0f} min" if minutes >= 1.5 else f"{self.wall_s:.0f} s"
        return (f"{self.flights} flights, {self.sim_s / 60.0:.0f} simulated minutes: about {took} on "
                f"{self.workers} worker(s) (timed on a {CALIBRATION_SIM_S:g} s flight of each controller)")


def estimate_table1(
    seeds: int, controllers: tuple[str, ...], modes: tuple[str, ...], duration_s: float | None, workers: int,
) -> TableEstimate:
    """Count the flights and time a short flight of each controller here: wall seconds per simulated second
    times the simulated seconds to fly, shared among the workers (a guess: faults and noise change it)."""
    import time

    from mars_link.flight.build import flight_duration_s

    runs = plan_runs(controllers, modes)
    wall_per_sim: dict[str, float] = {}
    for controller in sorted({c for _, c, _ in runs}):
        started = time.perf_counter()
        run_trial(scenario_for(CASES[0], controller, "none", CALIBRATION_SIM_S), 1)
        wall_per_sim[controller] = (time.perf_counter() - started) / CALIBRATION_SIM_S
    sim_total = wall_total = 0.0
    for case, controller, ftc in runs:
        flight_s = duration_s or flight_duration_s(scenario_for(case, controller, ftc))
        sim_total += flight_s * seeds
        wall_total += flight_s * seeds * wall_per_sim[controller]
    workers = max(1, workers)
    return TableEstimate(len(runs) * seeds, sim_total, wall_total / min(workers, len(runs) * seeds), workers)


def write_fig3(rows: list[Row], out_dir: Path, plot_format: str = "png") -> Path | None:
    """Paper 000's Fig. 3 cases (unit failures) as bars: our mean error (± std over seeds) per controller and
    FTC mode, the paper's value (its Fig. 3 curves re-simulated, specs: "resim") marked beside each, log scale
    (errors span 0.2 m to 18 m). None when no Fig. 3 case was flown."""
    from mars_link.flight.plots import pyplot, save_figure

    fig3 = [r for r in rows if r.case.unit_failure]
    if not fig3:
        return None
    plt = pyplot()
    cases = list(dict.fromkeys(r.case.name for r in fig3))
    kinds = list(dict.fromkeys((r.controller, r.ftc) for r in fig3))
    width = 0.8 / len(kinds)
    fig, ax = plt.subplots(figsize=(max(7.0, 1.4 * len(cases) + 2.0), 4.2))
    paper_labelled = False
    for k, (controller, ftc) in enumerate(kinds):
        xs, means, stds, papers = [], [], [], []
        for i, name in enumerate(cases):
            row = next((r for r in fig3 if r.case.name == name and (r.controller, r.ftc) == (controller, ftc)), None)
            if row is None:
                continue
            xs.append(i - 0.4 + width * (k + 0.5))
            means.append(row.mean_m if math.isfinite(row.mean_m) else np.nan)
            stds.append(row.std_m if math.isfinite(row.std_m) else 0.0)
            papers.append(np.nan if row.paper_m is None else row.paper_m)
        ax.bar(xs, means, width * 0.9, yerr=stds, capsize=2, label=f"{controller} / FTC {ftc}", color=f"C{k}")
        ax.scatter(xs, papers, marker="_", s=180, color="k", zorder=3, linewidths=2,
                   label=None if paper_labelled else "paper (Fig. 3, re-simulated)")
        paper_labelled = True
    ax.set_xticks(range(len(cases)), [c.removeprefix("F3 ") for c in cases])
    ax.set_yscale("log")
    ax.set_ylabel("mean tracking error [m]")
    ax.set_title("paper 000, Fig. 3: unit failures on the 3x2 spiral")
    ax.grid(axis="y", alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    out_dir.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, out_dir, "fig3", plot_format)

# ----------------------------------------------------------------------------- fault detection (FDI)
#: issue 5 acceptance: detection delay, eta accuracy, tracking with detected vs told faults
FDI_MAX_DELAY_S = 0.5
FDI_MAX_ETA_ERROR = 0.1
FDI_MAX_ERROR_RATIO = 1.5
FDI_T_FAULT_S = 10.0


def fdi_ftc(case: Case, ftc: str) -> str:
    """`ftc` for a case; "paper" = the paper's own choice (unit shares / hybrid)."""
    return paper_ftc(case) if ftc == "paper" else ftc


def eta_from_detections(n_rotors: int, detections: list[dict]) -> np.ndarray:
    """The coordinator's final belief rebuilt from summary.json-style detection records, in order."""
    eta = np.ones(n_rotors)
    for d in detections:
        base = (d["unit"] - 1) * 4
        if d["rotor"] is None:
            eta[base : base + 4] = d["eta_estimated"]
        else:
            eta[base + d["rotor"] - 1] = d["eta_estimated"]
    return eta


def true_eta(case: Case, n_rotors: int = 24) -> np.ndarray:
    eta = np.ones(n_rotors)
    for u, r, e in case.faults:
        base = (u - 1) * 4
        if r is None:
            eta[base : base + 4] = e
        else:
            eta[base + r - 1] = e
    return eta


@dataclass
class FdiTrial:
    """One seed of one case: the detected-fault flight scored against the told-fault flight."""

    case: Case
    ftc: str
    seed: int
    t_fault_s: float
    detections: list[dict]
    error_told_m: float
    error_detected_m: float
    completed_told: bool
    completed_detected: bool
    controller: str = "cascaded"

    @property
    def false_alarms(self) -> int:
        """Detections before the fault, or naming a unit/rotor that has no fault."""
        truth = true_eta(self.case)
        bad = 0
        for d in self.detections:
            base = (d["unit"] - 1) * 4
            sl = slice(base, base + 4) if d["rotor"] is None else slice(base + d["rotor"] - 1, base + d["rotor"])
            if d["t_detected"] < self.t_fault_s - 1e-9 or np.all(truth[sl] == 1.0):
                bad += 1
        return bad

    @property
    def delay_s(self) -> float:
        """From the fault to the detection that completed the identification (inf: never)."""
        truth = true_eta(self.case)
        faulty = set(np.flatnonzero(truth < 1.0))
        seen: set[int] = set()
        for d in sorted(self.detections, key=lambda d: d["t_detected"]):
            if d["t_detected"] < self.t_fault_s - 1e-9:
                continue
            base = (d["unit"] - 1) * 4
            seen |= set(range(base, base + 4)) if d["rotor"] is None else {base + d["rotor"] - 1}
            if faulty <= seen:
                return d["t_detected"] - self.t_fault_s
        return float("inf") if faulty else 0.0

    @property
    def eta_error(self) -> float:
        """Largest |eta believed - eta true| over all rotors at the end of the flight."""
        truth = true_eta(self.case)
        return float(np.max(np.abs(eta_from_detections(len(truth), self.detections) - truth)))

    @property
    def error_ratio(self) -> float:
        return self.error_detected_m / self.error_told_m if self.error_told_m > 0 else float("inf")

    @property
    def passed(self) -> bool:
        return (
            self.completed_told and self.completed_detected and self.false_alarms == 0
            and self.delay_s < FDI_MAX_DELAY_S and self.eta_error <= FDI_MAX_ETA_ERROR
            and self.error_ratio <= FDI_MAX_ERROR_RATIO
        )


def fdi_trial(case: Case, ftc: str = "qp", seed: int = 1, t_fault_s: float = FDI_T_FAULT_S,
              duration_s: float | None = None, controller: str = "cascaded", environment: dict | None = None,
              sensors: dict | None = None) -> FdiTrial:
    """Fly `case` twice with the same seed: faults told at `t_fault_s`, then detected (not told)."""
    mode = fdi_ftc(case, ftc)
    told = run_trial(scenario_for(case, controller, mode, duration_s, t_fault_s, True, environment, sensors), seed)
    found = run_trial(scenario_for(case, controller, mode, duration_s, t_fault_s, False, environment, sensors), seed)
    return FdiTrial(case, mode, seed, t_fault_s, found.detections, told.mean_error_m, found.mean_error_m,
                    told.completed, found.completed, controller)


def fdi_lost_trial(case: Case, ftc: str = "qp", seed: int = 1, t_fault_s: float = FDI_T_FAULT_S,
                   duration_s: float | None = None, controller: str = "cascaded",
                   environment: dict | None = None, sensors: dict | None = None) -> FdiTrial:
    """A Fig. 3 unit-failure case as process deaths: the units stop reporting and their motors stop
    at `t_fault_s` (runner `unit_deaths`), scored against the same failure told to the coordinator."""
    if not case.unit_failure:
        raise ValueError(f"{case.name}: only unit failures can be flown as lost units")
    mode = fdi_ftc(case, ftc)
    told = run_trial(scenario_for(case, controller, mode, duration_s, t_fault_s, True, environment, sensors), seed)
    healthy = Case(case.name, (), None, None, case.source, True)
    sc = scenario_for(healthy, controller, mode, duration_s, t_fault_s, False, environment, sensors)
    found = run_trial(sc, seed, unit_deaths={u: t_fault_s for u, _, _ in case.faults})
    return FdiTrial(Case("lost " + case.name.replace("F3 ", ""), case.faults, None, None, case.source, True), mode,
                    seed, t_fault_s, found.detections, told.mean_error_m, found.mean_error_m, told.completed,
                    found.completed, controller)


def fdi_false_alarm_flight(seed: int, ftc: str = "qp", duration_s: float | None = None,
                           controller: str = "cascaded", environment: dict | None = None,
                           sensors: dict | None = None) -> list[dict]:
    """A fault-free spiral with the detector on: its detections (all false alarms)."""
    sc = scenario_for(CASES[0], controller, ftc, duration_s, faults_known=False, environment=environment,
                      sensors=sensors)
    return run_trial(sc, seed).detections


# ----------------------------------------------------------------------------- EKF accuracy
def ekf_accuracy(scenario_name: str = "spiral_3x2", seed: int = 1, after_s: float = 1.0) -> dict:
    """Fly a scenario (sensor noise on, EKF in the loop) and compare the estimate with the truth.

    Position: estimated CoM vs true CoM; attitude: angle of R_true^T R_est. Both as RMS and maximum
    over the control steps after `after_s` (the first second is the filter settling on the ground).
    Also the estimator's cost per control step (the runner's stage timer).
    """
    from mars_link.core.rotations import euler_to_quat, quat_to_rotmat
    from mars_link.flight.run_log import RunLog
    from mars_link.config.scenario import load_scenario

    scenario = load_scenario(scenario_name)
    if not scenario.sim.noise:
        raise ValueError(f"scenario {scenario_name} flies without sensor noise: no estimator to check")
    log = RunLog(None, scenario.model(), rotor_log_hz=1.0)
    result = run_trial(scenario, seed, log=log)
    rows = np.array(log.telemetry_rows)
    rows = rows[rows[:, 1] > after_s]
    pos_err = np.linalg.norm(rows[:, 12:15] - rows[:, 18:21], axis=1)
    att_err = []
    for row in rows:
        r_true = quat_to_rotmat(euler_to_quat(*np.radians(row[8:11])))
        r_est = quat_to_rotmat(euler_to_quat(*np.radians(row[15:18])))
        c = (np.trace(r_true.T @ r_est) - 1.0) / 2.0
        att_err.append(math.degrees(math.acos(min(1.0, max(-1.0, c)))))
    att = np.array(att_err)
    return {
        "scenario": scenario_name,
        "seed": seed,
        "completed": result.completed,
        "position_rms_m": float(np.sqrt(np.mean(pos_err**2))),
        "position_max_m": float(pos_err.max()),
        "attitude_rms_deg": float(np.sqrt(np.mean(att**2))),
        "attitude_max_deg": float(att.max()),
        "estimation_s_per_step": result.stage_time_s["estimation"] / max(result.control_steps, 1),
        "control_steps": result.control_steps,
    }
