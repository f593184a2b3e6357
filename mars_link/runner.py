"""In-process runner ("inproc" mode): world, unit motors and coordinator wired by direct calls.

Lockstep and deterministic: physics steps at `physics_hz`; every `physics_hz / control_hz` steps the
sensors are sampled, the coordinator estimates, controls and allocates, and the units' motor models
take the new per-rotor commands. No sockets, no sleeps: this is the fast path used by tests, batch
evaluation and the paper reproductions, and the multi-process SITL must reproduce it.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from mars_link.assembly import AssemblyModel
from mars_link.control.base import Controller
from mars_link.coordinator import Coordinator
from mars_link.errors import UserInputError
from mars_link.rotations import quat_to_euler, quat_to_rotmat, tilt_deg
from mars_link.scenario import FaultSpec, Scenario
from mars_link.trajectories import Trajectory, build_trajectory

#: a run is declared diverged when the tracked point is this far from its reference...
DIVERGENCE_ERROR_M = 5.0
#: ...or the assembly tilts beyond this
DIVERGENCE_TILT_DEG = 80.0
#: rotors.csv rows per second (telemetry.csv has every control step)
ROTOR_LOG_HZ = 20.0
#: position (mocap) samples per second; the IMU comes at every control step
POSITION_RATE_HZ = 50.0
#: a unit silent for this many control periods is declared lost (only with `unit_deaths`)
UNIT_TIMEOUT_PERIODS = 5
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


# ----------------------------------------------------------------------------- construction
def tracked_offset(model: AssemblyModel, scenario: Scenario) -> np.ndarray:
    unit = scenario.tracked_unit()
    return np.zeros(3) if unit is None else model.unit_position(unit).copy()


def make_trajectory(scenario: Scenario, model: AssemblyModel) -> Trajectory:
    params = {k: v for k, v in scenario.trajectory.items() if k != "kind"}
    return build_trajectory(
        scenario.trajectory["kind"], params, rest_height_m=model.vehicle.gear_depth_m
    )


def make_controller(scenario: Scenario, model: AssemblyModel, eta: np.ndarray) -> Controller:
    v = model.vehicle
    if scenario.controller == "cascaded":
        from mars_link.allocation import make_allocator
        from mars_link.control.cascaded import CascadedController

        allocator = make_allocator(
            scenario.ftc,
            model,
            eta=eta,
            min_thrust_n=v.rotor_min_thrust_n,
            max_thrust_n=v.rotor_max_thrust_n,
        )
        return CascadedController(
            model, allocator, tracked_offset_frd_m=tracked_offset(model, scenario),
            control_hz=scenario.sim.control_hz,
        )
    if scenario.controller == "mars-ftcc-paper":
        from mars_link.control.paper import PaperController

        return PaperController(
            model,
            tracked_unit_id=scenario.tracked_unit(),
            control_hz=scenario.sim.control_hz,
            ftc=scenario.ftc,
            eta=eta,
        )
    raise UserInputError(f"unknown controller {scenario.controller!r}")


def eta_after(model: AssemblyModel, faults: list[FaultSpec], t_s: float) -> np.ndarray:
    eta = model.nominal_eta()
    for f in faults:
        if f.t_s <= t_s:
            sl = model.unit_slots(f.unit) if f.rotor is None else model.rotor_slot(f.unit, f.rotor)
            eta[sl] = f.eta
    return eta


# ----------------------------------------------------------------------------- logging
class RunLog:
    """CSV time series written as the flight goes (flushed), so a crash loses nothing flown."""

    def __init__(self, out_dir: Path | None, model: AssemblyModel, rotor_log_hz: float) -> None:
        self.out_dir = out_dir
        self.model = model
        self.rotor_log_period_s = 1.0 / rotor_log_hz
        self._next_rotor_t = 0.0
        self._tel = self._rot = None
        self.telemetry_rows: list[list[float]] = []
        self.rotor_rows: list[np.ndarray] = []
        if out_dir is None:
            return
        out_dir.mkdir(parents=True, exist_ok=True)
        self._tel = open(out_dir / "telemetry.csv", "w", encoding="utf-8")
        self._tel.write(
            "trial,t_s,ref_n_m,ref_e_m,ref_d_m,pos_n_m,pos_e_m,pos_d_m,roll_deg,pitch_deg,yaw_deg,"
            "error_m,est_n_m,est_e_m,est_d_m,est_roll_deg,est_pitch_deg,est_yaw_deg,com_n_m,com_e_m,com_d_m\n"
        )
        self._tel_format = ",".join(["%.6g"] * 18 + ["%.9f"] * 3) + "\n"
        self._rot = open(out_dir / "rotors.csv", "w", encoding="utf-8")
        cols = []
        for kind in ("cmd", "thrust", "eta"):
            cols += [f"{kind}_u{r.unit_id}r{r.index}" for r in model.rotors]
        self._rot.write("trial,t_s," + ",".join(cols) + "\n")

    def telemetry(self, row: list[float]) -> None:
        self.telemetry_rows.append(row)
        if self._tel:
            self._tel.write(self._tel_format % tuple(row))

    def rotors(self, trial: int, t_s: float, cmd, thrust, eta) -> None:
        if t_s + 1e-9 < self._next_rotor_t:
            return
        self._next_rotor_t = t_s + self.rotor_log_period_s
        row = np.concatenate(([trial, t_s], cmd, thrust, eta))
        self.rotor_rows.append(row)
        if self._rot:
            self._rot.write(",".join(f"{x:.5g}" for x in row) + "\n")

    def new_trial(self) -> None:
        self._next_rotor_t = 0.0

    def flush(self) -> None:
        for f in (self._tel, self._rot):
            if f:
                f.flush()

    def close(self) -> None:
        for f in (self._tel, self._rot):
            if f:
                f.close()
        self._tel = self._rot = None


# ----------------------------------------------------------------------------- one trial
def run_trial(
    scenario: Scenario,
    seed: int,
    trial_index: int = 0,
    log: RunLog | None = None,
    on_progress: Callable[[float], None] | None = None,
    unit_deaths: dict[int, float] | None = None,
) -> TrialResult:
    """World, units and coordinator wired by direct calls, one exchange per control period.

    `unit_deaths` (unit -> time): that unit's process dies then (no more telemetry, motors stop); the
    coordinator, not told, declares it lost after `UNIT_TIMEOUT_PERIODS` silent control periods.
    """
    from firmware_models.unit import UnitCore, UnitCoreParams
    from sitl.world import World, WorldConfig

    model = scenario.model()
    trajectory = make_trajectory(scenario, model)
    duration = scenario.sim.duration_s or trajectory.duration_s
    control_hz = scenario.sim.control_hz
    n_exchanges = int(round(duration * control_hz))

    faults = sorted(scenario.faults, key=lambda f: f.t_s)
    eta_known = eta_after(model, faults, 0.0) if scenario.faults_known else model.nominal_eta()
    controller = make_controller(scenario, model, eta_known)
    estimator = None
    if scenario.sim.noise:
        from mars_link.estimation import AssemblyEstimator

        estimator = AssemblyEstimator(model)
    offset = tracked_offset(model, scenario)
    start = trajectory.sample(0.0)
    com_start = start.position_ned_m - quat_to_rotmat(_yaw_quat(start.yaw_rad)) @ offset
    detector = None
    if not scenario.faults_known:
        from mars_link.fault_detection import FaultDetector

        detector = FaultDetector(model, ground_down_m=float(com_start[2]))  # every flight starts landed
    deaths = sorted((t_d, u) for u, t_d in (unit_deaths or {}).items())
    for _, u in deaths:
        model.check_rotor(u, None)
    timeout = UNIT_TIMEOUT_PERIODS / control_hz if deaths else None
    coordinator = Coordinator(model, trajectory, controller, estimator, detector, telemetry_timeout_s=timeout)
    world = World(
        model,
        WorldConfig(
            physics_hz=scenario.sim.physics_hz, exchange_hz=control_hz, seed=seed, noise=scenario.sim.noise,
            position_every=max(1, round(control_hz / POSITION_RATE_HZ)),
        ),
        com_start,
        start.yaw_rad,
    )
    unit_params = UnitCoreParams(control_period_s=1.0 / control_hz)
    units = {u: UnitCore(u, model.vehicle, unit_params) for u in model.unit_ids}

    stage = dict.fromkeys(STAGES, 0.0)
    events: list[dict] = []
    next_fault = 0
    errors_sum = errors_sq = max_err = max_tilt = 0.0
    n_err = 0
    diverged = False
    clock = time.perf_counter
    wall0 = clock()
    progress_every = max(1, n_exchanges // 200)
    k = 0
    for k in range(n_exchanges):
        t = world.t_s
        # faults act in the units' motor path at the first exchange at or after their time
        while next_fault < len(faults) and faults[next_fault].t_s <= t + 1e-9:
            f = faults[next_fault]
            next_fault += 1
            units[f.unit].inject_fault(f.rotor, f.eta)
            events.append({"t_s": round(t, 6), "type": "fault", "unit": f.unit, "rotor": f.rotor, "eta": f.eta,
                           "text": f.event_text()})
            if scenario.faults_known:
                coordinator.set_faults(eta_after(model, faults[:next_fault], t), t, "fault told to the coordinator")
        while deaths and deaths[0][0] <= t + 1e-9:
            _, u = deaths.pop(0)
            world.declare_dead(u)
            events.append({"t_s": round(t, 6), "type": "unit_died", "unit": u, "text": f"Unit {u} process died"})
        c0 = clock()
        packets = world.sense()
        c1 = clock()
        commands = coordinator.step(t, [units[p.unit_id].on_sensors(p) for p in packets])
        c2 = clock()
        for cmd in commands:
            units[cmd.unit_id].on_rotor_command(cmd)
            world.actuate(units[cmd.unit_id].motor_output(t))
        c3 = clock()
        rec = coordinator.last
        stage["sensors"] += c1 - c0
        for name in ("estimation", "control", "allocation"):
            stage[name] += rec.timings_s[name]
        stage["motors"] += c3 - c2
        # metrics on the truth
        truth = world.truth()
        tracked = world.tracked_point(offset, truth)
        err = float(np.linalg.norm(tracked - rec.reference.position_ned_m))
        tilt = tilt_deg(truth.quaternion_wxyz)
        errors_sum += err
        errors_sq += err * err
        n_err += 1
        max_err = max(max_err, err)
        max_tilt = max(max_tilt, tilt)
        if log is not None:
            roll, pitch, yaw = quat_to_euler(truth.quaternion_wxyz)
            er, ep, ey = quat_to_euler(rec.estimate.quaternion_wxyz)
            log.telemetry(
                [trial_index, t, *rec.reference.position_ned_m, *tracked,
                 math.degrees(roll), math.degrees(pitch), math.degrees(yaw), err,
                 *rec.estimate.position_ned_m, math.degrees(er), math.degrees(ep), math.degrees(ey),
                 *truth.position_ned_m]
            )
            log.rotors(trial_index, t, rec.thrusts_n, world.rotor_thrust_n, _eta_of(units, model))
            if k % int(control_hz) == 0:
                log.flush()
        c4 = clock()
        stage["logging"] += c4 - c3
        if not (err < DIVERGENCE_ERROR_M and tilt < DIVERGENCE_TILT_DEG and math.isfinite(err)):
            diverged = True
            events.append({"t_s": round(t, 6), "type": "diverged", "error_m": err, "tilt_deg": tilt})
            break
        world.advance()
        stage["physics"] += clock() - c4
        if on_progress is not None and k % progress_every == 0:
            on_progress(t / duration)
    wall = clock() - wall0
    sim_time = world.t_s
    force_integral = world.force_integral_n2s
    world.close()
    if log is not None:
        log.flush()
    events = sorted(events + coordinator.events, key=lambda e: e["t_s"])
    detections = [
        {
            "t_fault": _fault_time(faults, d.unit, d.rotor, unit_deaths),
            "t_detected": round(d.t_detected, 6),
            "unit": d.unit,
            "rotor": d.rotor,
            "eta_estimated": round(float(d.eta_estimated), 4),
        }
        for d in coordinator.detections
    ]
    return TrialResult(
        seed=seed,
        completed=not diverged,
        diverged=diverged,
        mean_error_m=errors_sum / max(n_err, 1),
        rmse_m=math.sqrt(errors_sq / max(n_err, 1)),
        max_error_m=max_err,
        sim_time_s=sim_time,
        wall_time_s=wall,
        force_integral_n2s=force_integral,
        max_tilt_deg=max_tilt,
        events=events,
        stage_time_s=stage,
        physics_steps=world.exchange_index * world.substeps,
        control_steps=n_err,
        detections=detections,
    )


def _fault_time(
    faults: list[FaultSpec], unit: int, rotor: int | None, deaths: dict[int, float] | None = None
) -> float | None:
    """When the injected fault that a detection names happened (None: a false alarm)."""
    times = [f.t_s for f in faults if f.unit == unit and (rotor is None or f.rotor in (None, rotor))]
    times += [t for u, t in (deaths or {}).items() if u == unit]
    return min(times) if times else None


def _eta_of(units: dict, model: AssemblyModel) -> np.ndarray:
    return np.concatenate([units[u].eta for u in model.unit_ids])


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


# ----------------------------------------------------------------------------- whole run
def summarize(scenario: Scenario, results: list[TrialResult], seed: int) -> dict:
    def mean(attr: str) -> float:
        return float(np.mean([getattr(r, attr) for r in results]))

    sim_time = sum(r.sim_time_s for r in results)
    wall_time = sum(r.wall_time_s for r in results)
    stage = {k: sum(r.stage_time_s.get(k, 0.0) for r in results) for k in STAGES}
    return {
        "scenario": scenario.name,
        "source": scenario.source,
        "mode": "inproc",
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
        "per_trial": [
            {"seed": r.seed, "mean_error_m": r.mean_error_m, "rmse_m": r.rmse_m,
             "max_error_m": r.max_error_m, "diverged": r.diverged}
            for r in results
        ],
    }


def run_scenario(
    scenario: Scenario,
    out_dir: Path | None = None,
    trials: int = 1,
    seed: int | None = None,
    on_progress: Callable[[int, float], None] | None = None,
    plots: bool = True,
) -> dict:
    """Fly `trials` trials (seeds seed, seed+1, ...); write the run directory if `out_dir` is given."""
    seed = scenario.sim.seed if seed is None else seed
    log = RunLog(out_dir, scenario.model(), rotor_log_hz=min(scenario.sim.control_hz, ROTOR_LOG_HZ))
    results = []
    try:
        for i in range(trials):
            log.new_trial()
            cb = None if on_progress is None else (lambda frac, i=i: on_progress(i, frac))
            results.append(run_trial(scenario, seed + i, i, log, cb))
            if on_progress is not None:
                on_progress(i, 1.0)
    finally:
        log.close()
    summary = summarize(scenario, results, seed)
    if out_dir is not None:
        (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
        if plots:
            from mars_link.plots import write_run_plots

            write_run_plots(out_dir, log.telemetry_rows, log.rotor_rows, scenario.model())
    return summary
