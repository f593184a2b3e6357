"""Flight metrics, one implementation for every mode: the tracking error of a point against its
reference, tilt, divergence, and the run summary built from per-trial results.

The in-process runner feeds `TrackingMetrics` every control step; the SITL summary feeds it the world's
truth log row by row; reconfiguration flights feed it while the mission runs. All of them then report
the same figures under the same names in summary.json.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.core.rotations import tilt_deg
from mars_link.flight.fault_scoring import score_flight

#: a run is declared diverged when the tracked point is this far from its reference...
DIVERGENCE_ERROR_M = 5.0
#: ...or the assembly tilts beyond this
DIVERGENCE_TILT_DEG = 80.0
STAGES = ("physics", "sensors", "estimation", "control", "allocation", "motors", "logging")


@dataclass
class TrialResult:
    seed: int
    completed: bool
    diverged: bool
    mean_error_m: float
    rmse_m: float
    max_error_m: float
    sim_time_s: float
    wall_time_s: float
    force_integral_n2s: float
    max_tilt_deg: float
    events: list[dict] = field(default_factory=list)
    stage_time_s: dict[str, float] = field(default_factory=dict)
    physics_steps: int = 0
    control_steps: int = 0
    detections: list[dict] = field(default_factory=list)
    end_reason: str | None = None  # why the flight ended before its duration (None: flown to the end)
    # what the flight did with its pieces (a docked flight that stayed one piece: the defaults and one piece)
    reconfigured: bool = False  # a reconfiguration was done
    reconfig_time_s: float = 0.0  # how long the manoeuvre took
    plan: dict | None = None  # the executor's plan, when it had moves
    assembled: bool = False  # a free start became the whole structure
    min_clearance_m: float = math.inf  # smallest gap between units of different bodies over the flight
    pieces_final: list[dict] = field(default_factory=list)  # each piece at the end: layout rows, unit ids
    mission_force_integral_n2s: float = 0.0  # the force integral while the mission flies (manoeuvre excluded)
    units_lost: list[dict] = field(default_factory=list)  # each unit the coordinator lost, and its fate (truth)
    unit_rows: list[list[float]] = field(default_factory=list)  # units.csv's rows (run_log.UNIT_COLUMNS)
    telemetry_rows: list[list[float]] = field(default_factory=list)  # telemetry.csv's (run_log.TELEMETRY_COLUMNS)
    logging: dict | None = None  # the time series' status (run_log.RunLog.status)


def ended_early_reason(sim_time_s: float, duration_s: float, control_hz: float, why: str) -> str | None:
    """The end reason of a flight that stopped more than one control period before `duration_s`, else None.
    Why: a flight cut short (a signal, a shutdown, a dead process) must never read as completed."""
    if sim_time_s + 1.5 / control_hz >= duration_s:
        return None
    return f"{why} at {sim_time_s:.2f} s of {duration_s:.2f} s"


class TrackingMetrics:
    """Running error statistics of a tracked point; `add` says when the flight diverged."""

    def __init__(self) -> None:
        self.n = 0
        self.error_sum_m = 0.0
        self.error_sq_m2 = 0.0
        self.max_error_m = 0.0
        self.max_tilt_deg = 0.0
        self.diverged = False
        self.divergence: dict | None = None  # the "diverged" event, once

    def add(self, t_s: float, tracked_ned_m: np.ndarray, reference_ned_m: np.ndarray,
            quaternion_wxyz: np.ndarray, position_lost: bool = False) -> tuple[float, float]:
        """One sample: (error m, tilt deg). Sets `diverged` (and its event) the first time the error or
        the tilt passes its limit, or the error is not finite. `position_lost`: the flight flies on a
        dead-reckoned estimate (the position failsafe), so its error against the truth measures the
        estimate's drift, not the control: only the tilt and a non-finite error end it then."""
        err = float(np.linalg.norm(tracked_ned_m - reference_ned_m))
        tilt = tilt_deg(quaternion_wxyz)
        self.add_error(err)
        self.max_tilt_deg = max(self.max_tilt_deg, tilt)
        if not ((err < DIVERGENCE_ERROR_M or position_lost) and tilt < DIVERGENCE_TILT_DEG and math.isfinite(err)):
            self.mark_diverged(t_s, err, tilt)
        return err, tilt

    def add_error(self, err_m: float) -> None:
        self.n += 1
        self.error_sum_m += err_m
        self.error_sq_m2 += err_m * err_m
        self.max_error_m = max(self.max_error_m, err_m)

    def mark_diverged(self, t_s: float, err_m: float, tilt_deg_: float, **fields) -> None:
        if not self.diverged:
            self.diverged = True
            self.divergence = event(t_s, EventKind.DIVERGED, error_m=err_m, tilt_deg=tilt_deg_, **fields)

    @property
    def mean_error_m(self) -> float:
        return self.error_sum_m / max(self.n, 1)

    @property
    def rmse_m(self) -> float:
        return math.sqrt(self.error_sq_m2 / max(self.n, 1))


def fault_time(faults, unit: int, rotor: int | None, deaths: dict[int, float] | None = None) -> float | None:
    """When the injected fault that a detection names happened (None: a false alarm)."""
    times = [f.t_s for f in faults if f.unit == unit and (rotor is None or f.rotor in (None, rotor))]
    times += [t for u, t in (deaths or {}).items() if u == unit]
    return min(times) if times else None


def detection_rows(detections, faults, deaths: dict[int, float] | None = None) -> list[dict]:
    """summary.json `detections`: each detection with the time of the fault it names."""
    return [
        {
            "t_fault": fault_time(faults, d.unit, d.rotor, deaths),
            "t_detected": round(d.t_detected, 6),
            "unit": d.unit,
            "rotor": d.rotor,
            "eta_estimated": round(float(d.eta_estimated), 4),
        }
        for d in detections
    ]


def summarize(scenario, results: list[TrialResult], seed: int, mode: str = "inproc") -> dict:
    """summary.json of a run of one or more trials (every mode writes these keys)."""
    def mean(attr: str) -> float:
        return float(np.mean([getattr(r, attr) for r in results]))

    sim_time = sum(r.sim_time_s for r in results)
    wall_time = sum(r.wall_time_s for r in results)
    stage = {k: sum(r.stage_time_s.get(k, 0.0) for r in results) for k in STAGES}
    first = results[0]
    from mars_link.provenance import provenance

    return {
        "scenario": scenario.name,
        "source": scenario.source,
        "mode": mode,
        "layout": list(scenario.layout),
        "preset": scenario.preset,
        "controller": scenario.controller,
        "ftc": scenario.ftc,
        "seed": seed,
        "trials": len(results),
        "noise": scenario.sim.noise,
        "physics_hz": scenario.sim.physics_hz,
        "control_hz": scenario.sim.control_hz,
        "completed": all(r.completed for r in results),
        "end_reason": next((r.end_reason for r in results if r.end_reason), None),
        "diverged": any(r.diverged for r in results),
        "mean_error_m": mean("mean_error_m"),
        "mean_error_std_m": float(np.std([r.mean_error_m for r in results])),
        "rmse_m": mean("rmse_m"),
        "max_error_m": float(max(r.max_error_m for r in results)),
        "sim_time_s": mean("sim_time_s"),
        "wall_time_s": wall_time,
        "real_time_factor": sim_time / wall_time if wall_time > 0 else float("inf"),
        "force_integral_n2s": mean("force_integral_n2s"),
        "max_tilt_deg": float(max(r.max_tilt_deg for r in results)),
        "stage_time_s": stage,
        "events": [dict(e, trial=i) for i, r in enumerate(results) for e in r.events],
        "detections": [dict(d, trial=i) for i, r in enumerate(results) for d in r.detections],
        # each trial's beliefs scored against its injected faults (mars_link.flight.fault_scoring)
        "fault_isolation": [score_flight(r.events, r.sim_time_s, r.diverged).as_dict() for r in results],
        "per_trial": [
            {"seed": r.seed, "mean_error_m": r.mean_error_m, "rmse_m": r.rmse_m,
             "max_error_m": r.max_error_m, "diverged": r.diverged}
            for r in results
        ],
        "provenance": provenance(scenario),  # version, commit, the scenario as resolved
        # the pieces (trial 0's: a flight of several bodies is flown once)
        "faults_known": scenario.faults_known,
        "start": scenario.start,
        "reconfigured": first.reconfigured,
        "reconfig_time_s": first.reconfig_time_s,
        "plan": first.plan,
        "plans": plan_records(first.events),
        "assembled": first.assembled,
        "min_clearance_m": first.min_clearance_m,
        "pieces_final": first.pieces_final,
        "units_lost": first.units_lost,
        "mission_force_integral_n2s": first.mission_force_integral_n2s,
    }


def plan_records(events: list[dict]) -> list[dict]:
    """summary.json "plans": each plan of the flight with both objectives (whatever chose it): paper 001's
    force objective and the worst-stage controllability margin (mars_link.reconfig.margin)."""
    keys = ("t_s", "feasible", "chosen_by", "force_objective", "worst_stage_margin", "final_margin",
            "disassembly_layers", "assembly_layers")
    return [{k: e.get(k) for k in keys} for e in events if e["type"] == "plan"]


def gust_response(t_s, error_m, onset_s: float, tolerance_m: float = 0.05) -> dict:
    """How a hold rides out a disturbance that starts at `onset_s`: the peak deviation after it, when,
    and the recovery time (from the onset until the error stays within `tolerance_m` for good; inf if
    it never does before the end)."""
    t, e = np.asarray(t_s, dtype=float), np.asarray(error_m, dtype=float)
    after = t >= onset_s
    if not after.any():
        raise ValueError(f"no sample after the onset at {onset_s:g} s")
    k = int(np.argmax(np.where(after, e, -np.inf)))
    outside = np.flatnonzero(after & (e > tolerance_m))
    recovered = len(outside) == 0 or outside[-1] + 1 < len(t)
    return {
        "peak_deviation_m": float(e[k]), "peak_after_s": float(t[k] - onset_s),
        "recovery_s": (0.0 if len(outside) == 0 else float(t[outside[-1] + 1] - onset_s)) if recovered else math.inf,
        "tolerance_m": tolerance_m, "before_onset_max_m": float(e[~after].max()) if (~after).any() else 0.0,
    }
