"""Flights of pieces (free units assembling, reconfiguration): the observer and the outputs.

The flight runs on the one engine (`mars_link.flight.engine.Engine`) with the parts `build.build_flight`
makes: a world of rigid bodies that split when latches open and merge when facing latches close
(`sitl.world`, momentum kept), every unit's firmware in the motor path, and a `PiecesCoordinator`
(`mars_link.coordination.pieces`) that flies every piece on its own EKF, detector, controller and allocator and runs
the reconfiguration executor. The coordinator learns splits and docks from the units' latch sensors,
never from the world's truth. Faults are told (`faults_known = true`: the plan for all of them is made
before flight) or found by the pieces' detectors (the plan is made from the believed faults).
Deterministic for a seed.

Outputs (like `mars_link.flight.runner`): summary.json keys mean_error_m, rmse_m, max_error_m,
force_integral_n2s (Σ rotors ∫ thrust² dt over every body), diverged, events (faults, detections, each
split and dock, reconfig start/done, mission resume); telemetry.csv (tracked point vs the mission, per
control step), units.csv (every unit's position, velocity and attitude at 20 Hz) and plots/.
The mission error is measured while the mission runs (before the pause and after the resume); the
time the manoeuvre took is `reconfig_time_s`.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.core.errors import UserInputError
from mars_link.flight.build import build_flight
from mars_link.flight.engine import Engine, Flight, StepView
from mars_link.flight.metrics import DIVERGENCE_ERROR_M, DIVERGENCE_TILT_DEG, TrackingMetrics, TrialResult
from mars_link.logs.outputs import write_json
from mars_link.runtime.pacing import Pacer
from mars_link.coordination.pieces import PiecesCoordinator
from mars_link.core.rotations import quat_to_euler, quat_to_rotmat, tilt_deg
from mars_link.config.scenario import Scenario

UNIT_LOG_HZ = 20.0
#: a lost unit that reaches the ground slower than this landed; faster, it fell (the world's truth)
LANDED_SPEED_MPS = 1.0
#: (a world that writes positions only) a unit's centre this close to its resting height touches the ground
GROUND_TOUCH_M = 0.02


@dataclass
class ReconfigResult(TrialResult):
    """A trial's figures plus the manoeuvre: whether it completed, how long it took, the plan."""

    reconfigured: bool = False
    logging: dict | None = None  # the CSVs' status (ReconfigRecorder.logging_status)
    reconfig_time_s: float = 0.0
    plan: dict | None = None
    unit_rows: list[list[float]] = field(default_factory=list)
    telemetry_rows: list[list[float]] = field(default_factory=list)
    assembled: bool = False  # a free start became the whole structure
    min_clearance_m: float = math.inf  # smallest gap between units of different bodies over the flight
    pieces_final: list[dict] = field(default_factory=list)  # each piece at the end: layout rows, unit ids
    detections: list[dict] = field(default_factory=list)  # the faults the pieces' detectors found (events)
    mission_force_integral_n2s: float = 0.0  # the force integral while the mission flies (manoeuvre excluded)
    units_lost: list[dict] = field(default_factory=list)  # each unit the coordinator lost, and its fate (truth)


class ReconfigRecorder:
    """Observer of a flight of pieces: the mission error of the tracked point (while the mission runs),
    every piece's tilt and deviation from its reference (divergence), the smallest gap between bodies,
    and the telemetry.csv / units.csv time series. It ends the flight on divergence or a failed manoeuvre."""

    def __init__(self, flight: Flight, out_dir: Path | None) -> None:
        self.flight = flight
        self.coordinator: PiecesCoordinator = flight.coordinator
        self.metrics = TrackingMetrics()
        self.min_clearance_m = math.inf
        self.unit_rows: list[list[float]] = []
        self.telemetry_rows: list[list[float]] = []
        self.failed = False
        self.mission_force_integral_n2s = 0.0  # Σ rotors ∫ thrust² dt while the mission flies (not the manoeuvre)
        self._force_seen = 0.0
        self._next_unit_log = 0.0
        self._offsets: dict[int, tuple] = {}  # id(piece model) -> (model, its unit offsets)
        self.units_lost: dict[int, dict] = {}  # unit -> when it was lost and, from the truth, how it came down
        self._lost_prev: dict[int, tuple] = {}  # unit -> (t, its centre) the step before
        self._ground_down_m = -flight.model.vehicle.gear_depth_m
        self._flush_every = max(1, int(flight.scenario.sim.control_hz))
        self.tel_f = self.units_f = None
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            from mars_link.logs.outputs import SafeWriter  # (a full disk stops a log, never the flight)

            self.tel_f = SafeWriter.open(out_dir / "telemetry.csv")
            self.tel_f.write("t_s,mission_t_s,ref_n_m,ref_e_m,ref_d_m,pos_n_m,pos_e_m,pos_d_m,error_m,pieces\n")
            self.units_f = SafeWriter.open(out_dir / "units.csv")
            self.units_f.write("t_s,unit,n_m,e_m,d_m,vn_mps,ve_mps,vd_mps,roll_deg,pitch_deg,yaw_deg,piece_units\n")

    def close(self) -> None:
        for f in (self.tel_f, self.units_f):
            if f:
                f.close()

    def logging_status(self) -> dict:
        """summary.json "logging" (as run_log.RunLog.status): the CSVs whole, or why not."""
        files = [f.status() for f in (self.tel_f, self.units_f) if f is not None]
        reason = next((f["stopped_reason"] for f in files if f["stopped_reason"]), None)
        return {"complete": reason is None, "stopped_reason": reason, "files": files}

    def on_step(self, engine: Engine, v: StepView) -> bool:
        world, coord = self.flight.world, self.coordinator
        executor, metrics, t = coord.executor, self.metrics, v.t_s
        pieces = coord.pieces
        if coord.failed and not self.failed:
            self.failed = True
            engine.events.append(event(t, EventKind.RECONFIG_FAILED, reason=coord.failed,
                                       text=f"Reconfig failed: {coord.failed}"[:50]))
            return True
        if coord.lost:
            self._watch_lost(t, coord)
        states = {key: world.body_state(p.units[0]) for key, p in pieces.items()}
        for key, p in pieces.items():
            state = states[key]
            tilt = tilt_deg(state.quaternion_wxyz)
            metrics.max_tilt_deg = max(metrics.max_tilt_deg, tilt)
            dev = float(np.linalg.norm(state.position_ned_m - p.coordinator.last.reference.position_ned_m))
            if not (dev < DIVERGENCE_ERROR_M and tilt < DIVERGENCE_TILT_DEG):
                metrics.mark_diverged(t, dev, tilt, phase=executor.phase)
        self.min_clearance_m = min(self.min_clearance_m, world.min_clearance_m())
        if executor.mission_active(t):
            self.mission_force_integral_n2s += world.force_integral_n2s - self._force_seen
        self._force_seen = world.force_integral_n2s
        if executor.mission_active(t):  # the mission metric, on the truth
            p = coord.tracked_piece()
            s = states[p.shape.key]
            pos = s.position_ned_m + quat_to_rotmat(s.quaternion_wxyz) @ executor.tracked_offset(p.shape)
            ref = executor.mission.sample(executor.mission_time(t)).position_ned_m
            err = float(np.linalg.norm(pos - ref))
            metrics.add_error(err)
            if err >= DIVERGENCE_ERROR_M or not math.isfinite(err):
                metrics.mark_diverged(t, err, tilt_deg(s.quaternion_wxyz), phase=executor.phase)
            row = [t, executor.mission_time(t), *ref, *pos, err, len(pieces)]
            self.telemetry_rows.append(row)
            if self.tel_f:
                self.tel_f.write(",".join(f"{x:.6g}" for x in row) + "\n")
        if t + 1e-9 >= self._next_unit_log:
            self._next_unit_log = t + 1.0 / UNIT_LOG_HZ
            self._log_units(t, states)
        if v.index % self._flush_every == 0 and self.tel_f:
            self.tel_f.flush()
            self.units_f.flush()
        if metrics.diverged:
            engine.events.append(dict(metrics.divergence, text=f"Diverged ({executor.phase})"[:50]))
            return True
        return False

    def _watch_lost(self, t: float, coord: PiecesCoordinator) -> None:
        """The truth of every lost unit until it touches the ground (`touchdown`, the same test as SITL's
        world_truth.csv gets); one that stays up (in a body that flies on) is "airborne"."""
        for u in coord.lost:
            rec = self.units_lost.get(u)
            if rec is None:
                why = next((e.get("reason") for e in reversed(coord.events)
                            if e["type"] == "unit_lost" and e.get("unit") == u), None)
                rec = self.units_lost[u] = {"unit": u, "t_lost_s": round(t, 6), "reason": why, "fate": "airborne"}
            if rec["fate"] != "airborne":
                continue
            pos = self.flight.world.unit_truth(u).position_ned_m.copy()
            prev = self._lost_prev.get(u)
            self._lost_prev[u] = (t, pos)
            if prev is not None and t > rec["t_lost_s"]:
                rec.update(touchdown(prev, (t, pos), self._ground_down_m))

    def _unit_offsets(self, piece) -> np.ndarray:
        """The piece's unit centres from its CoM, FRD, in its order (one array per piece model, kept)."""
        offsets = self._offsets.get(id(piece.model))
        if offsets is None or offsets[0] is not piece.model:
            offsets = self._offsets[id(piece.model)] = (
                piece.model, np.array([piece.model.unit_position(k + 1) for k in range(len(piece.units))]))
        return offsets[1]

    def _log_units(self, t: float, states: dict) -> None:
        for p in self.coordinator.pieces.values():
            s = states[p.shape.key]
            r = quat_to_rotmat(s.quaternion_wxyz)
            w = r @ s.angular_velocity_frd_radps
            roll, pitch, yaw = (math.degrees(a) for a in quat_to_euler(s.quaternion_wxyz))
            arms = self._unit_offsets(p) @ r.T  # every unit's centre from the CoM, NED
            positions = (s.position_ned_m + arms).tolist()
            velocities = (s.velocity_ned_mps + np.cross(w, arms)).tolist()
            for i, u in enumerate(p.units):
                row = [t, u, *positions[i], *velocities[i], roll, pitch, yaw, len(p.shape.cells)]
                self.unit_rows.append(row)
                if self.units_f:
                    self.units_f.write(",".join(f"{x:.6g}" for x in row) + "\n")


def touchdown(before: tuple, now: tuple, ground_down_m: float) -> dict:
    """A lost unit's fate from two samples of its centre's truth, (t, NED position) one control period apart:
    once its centre is within GROUND_TOUCH_M of its resting height it touched the ground, landed (slower
    than LANDED_SPEED_MPS) or fell; {} before that."""
    (t0, p0), (t1, p1) = before, now
    if p1[2] < ground_down_m - GROUND_TOUCH_M:
        return {}
    speed = float(np.linalg.norm((np.asarray(p1) - np.asarray(p0)) / (t1 - t0)))
    return {"fate": "landed" if speed <= LANDED_SPEED_MPS else "fell", "t_ground_s": round(float(t1), 6),
            "impact_speed_mps": round(speed, 4), "ground_ned_m": [round(float(x), 4) for x in p1]}


def units_lost_from_truth(events: list[dict], truth, ground_down_m: float) -> list[dict]:
    """`units_lost` of a run whose world wrote each unit's truth as columns (SITL's world_truth.csv: t_s,
    u<id>_n_m, _e_m, _d_m, one row per control period): each `unit_lost` event's unit and its `touchdown`."""
    out = []
    for e in (e for e in events if e["type"] == "unit_lost"):
        u = e["unit"]
        rec = {"unit": u, "t_lost_s": e["t_s"], "reason": e.get("reason"), "fate": "airborne"}
        if f"u{u}_d_m" in truth.dtype.names:
            t = truth["t_s"]
            pos = np.column_stack([truth[f"u{u}_n_m"], truth[f"u{u}_e_m"], truth[f"u{u}_d_m"]])
            for k in np.flatnonzero(t > e["t_s"] + 1e-9):
                found = touchdown((t[k - 1], pos[k - 1]), (t[k], pos[k]), ground_down_m)
                if found:
                    rec.update(found)
                    break
        out.append(rec)
    return out


def run_reconfig_trial(
    scenario: Scenario, seed: int, out_dir: Path | None = None,
    on_progress: Callable[[float], None] | None = None, realtime_rate: float = 0.0,
    unit_deaths: dict[int, float] | None = None, view: Callable | None = None,
) -> ReconfigResult:
    """One flight of pieces on the engine (`build.build_flight`); `unit_deaths` (unit -> time): that
    unit's process dies then. `view(flight)`: its run.mcap / live Foxglove view (flight_view.pieces_view)."""
    flight = build_flight(scenario, seed, unit_deaths)
    coord: PiecesCoordinator = flight.coordinator
    executor = coord.executor
    recorder = ReconfigRecorder(flight, out_dir)
    view = view(flight) if view is not None else None
    engine = Engine(flight, [recorder] + ([view] if view is not None else []), Pacer(realtime_rate))
    wall0 = time.perf_counter()
    interrupted: KeyboardInterrupt | None = None
    try:
        step_every = 50
        while engine.step():
            if on_progress is not None and engine.steps % step_every == 0:
                on_progress(min(1.0, flight.world.t_s / max(flight.duration_s + executor.shift_s, 1e-9)))
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: the part flown is the result (runner.FlightInterrupted)
        interrupted = exc
    finally:
        flight.world.close()
        recorder.close()
        if view is not None:
            view.finish(engine)
    from mars_link.flight.runner import FlightInterrupted, _signal_name

    t = flight.world.t_s
    end_reason = (f"diverged at {t:.2f} s" if recorder.metrics.diverged else f"reconfiguration failed at {t:.2f} s"
                  if recorder.failed else f"interrupted by {_signal_name(interrupted)} at {t:.2f} s"
                  if interrupted is not None else None)
    result = reconfig_result(flight, engine, recorder, seed, time.perf_counter() - wall0, end_reason)
    if interrupted is not None:
        raise FlightInterrupted(result, interrupted)
    return result


def reconfig_result(flight: Flight, engine: Engine, recorder: ReconfigRecorder, seed: int, wall_s: float,
                    end_reason: str | None) -> ReconfigResult:
    """The flight of pieces' result, from its engine and recorder (`end_reason` None: completed)."""
    coord: PiecesCoordinator = flight.coordinator
    executor = coord.executor
    t = flight.world.t_s
    latched = [e for e in flight.world.latch_events if e["type"] == "dock_latched"]
    events = sorted(engine.events + coord.events + executor.events + latched, key=lambda e: e["t_s"])
    done = [e for e in events if e["type"] == "reconfig_done"]
    begun = [e for e in events if e["type"] == "reconfig_start"]
    reconfigured = bool(done)
    metrics = recorder.metrics
    result = ReconfigResult(
        seed=seed, completed=end_reason is None, end_reason=end_reason, diverged=metrics.diverged,
        reconfigured=reconfigured, mean_error_m=metrics.mean_error_m, rmse_m=metrics.rmse_m,
        max_error_m=metrics.max_error_m, sim_time_s=t, wall_time_s=wall_s,
        force_integral_n2s=flight.world.force_integral_n2s, max_tilt_deg=metrics.max_tilt_deg,
        reconfig_time_s=executor.shift_s if reconfigured else (t - begun[0]["t_s"] if begun else 0.0),
        plan=executor.plan.to_json() if executor.plan.disassembly_layers or executor.plan.assembly_layers else None,
        events=events, unit_rows=recorder.unit_rows, telemetry_rows=recorder.telemetry_rows,
        assembled=any(e["type"] == "assembly_done" for e in events), min_clearance_m=recorder.min_clearance_m,
        pieces_final=[{"layout": list(p.shape.layout()), "units": list(p.units)} for p in coord.pieces.values()],
        detections=[e for e in events if e["type"] == "fault_detected"],
        mission_force_integral_n2s=recorder.mission_force_integral_n2s,
        units_lost=[recorder.units_lost[u] for u in sorted(recorder.units_lost)],
    )
    result.logging = recorder.logging_status()
    return result


def reconfig_summary(scenario: Scenario, r: ReconfigResult, seed: int, mode: str = "inproc-reconfig") -> dict:
    """summary.json of one flight of pieces."""
    summary = {
        "scenario": scenario.name, "source": scenario.source, "mode": mode,
        "layout": list(scenario.layout), "preset": scenario.preset, "controller": scenario.controller,
        "ftc": scenario.ftc, "seed": seed, "trials": 1, "noise": scenario.sim.noise,
        "faults_known": scenario.faults_known,
        "physics_hz": scenario.sim.physics_hz, "control_hz": scenario.sim.control_hz,
        "completed": r.completed, "end_reason": r.end_reason, "diverged": r.diverged, "reconfigured": r.reconfigured,
        "mean_error_m": r.mean_error_m, "mean_error_std_m": 0.0, "rmse_m": r.rmse_m, "max_error_m": r.max_error_m,
        "sim_time_s": r.sim_time_s, "wall_time_s": r.wall_time_s,
        "real_time_factor": r.sim_time_s / r.wall_time_s if r.wall_time_s > 0 else float("inf"),
        "force_integral_n2s": r.force_integral_n2s, "mission_force_integral_n2s": r.mission_force_integral_n2s,
        "max_tilt_deg": r.max_tilt_deg, "reconfig_time_s": r.reconfig_time_s, "plan": r.plan, "start": scenario.start, "assembled": r.assembled,
        "min_clearance_m": r.min_clearance_m, "pieces_final": r.pieces_final, "units_lost": r.units_lost,
        "plans": plan_records(r.events),
        "events": [dict(e, trial=0) for e in r.events],
        "per_trial": [{"seed": seed, "mean_error_m": r.mean_error_m, "mean_error_std_m": 0.0, "rmse_m": r.rmse_m,
                       "max_error_m": r.max_error_m, "diverged": r.diverged}],
    }
    summary["logging"] = r.logging
    return summary


def plan_records(events: list[dict]) -> list[dict]:
    """summary.json "plans": each plan of the flight with both objectives (whatever chose it): paper 001's
    force objective and the worst-stage controllability margin (mars_link.reconfig.margin)."""
    keys = ("t_s", "feasible", "chosen_by", "force_objective", "worst_stage_margin", "final_margin",
            "disassembly_layers", "assembly_layers")
    return [{k: e.get(k) for k in keys} for e in events if e["type"] == "plan"]


def run_reconfig_scenario(
    scenario: Scenario, out_dir: Path | None = None, trials: int = 1, seed: int | None = None,
    on_progress: Callable[[int, float], None] | None = None, plots: bool = True, realtime_rate: float = 0.0,
    mcap: bool = True, live: str | None = None, plot_format: str = "png",
) -> dict:
    """One flight of pieces; the run directory gets summary.json, CSVs, plots/ and run.mcap (unless not `mcap`;
    `live`: HOST:PORT of a live Foxglove view). `realtime_rate`: the engine's pacing (0 as fast as possible,
    1 real time)."""
    from mars_link.flight.flight_view import pieces_view

    from mars_link.flight.runner import FlightInterrupted, write_starting_summary, write_summary

    seed = scenario.sim.seed if seed is None else seed
    cb = None if on_progress is None else (lambda frac: on_progress(0, frac))
    if out_dir is not None:  # first, small: whatever ends this process, a summary.json is there
        write_starting_summary(out_dir, scenario, seed, 1)
    interrupted = None
    try:
        r = run_reconfig_trial(scenario, seed, out_dir, cb, realtime_rate=realtime_rate,
                               view=lambda flight: pieces_view(flight, out_dir if mcap else None, live))
    except FlightInterrupted as exc:
        r, interrupted = exc.result, exc.cause
    except UserInputError:  # refused before the flight (the pieces' checks): no run directory is left
        if out_dir is not None:
            (out_dir / "summary.json").unlink(missing_ok=True)
        raise
    summary = reconfig_summary(scenario, r, seed)
    if out_dir is not None:
        write_summary(out_dir, summary)
        if plots and interrupted is None:
            try:
                write_reconfig_plots(out_dir, r, scenario.name, plot_format)
                from mars_link.flight.replay_gif import write_flight_gif

                write_flight_gif(out_dir / "plots" / "flight.gif", r.unit_rows, r.events)  # the animated replay
            except OSError as exc:  # (a full disk: one line; the summary is written)
                print(f"mars-link: plots: {exc.strerror or exc} (logging stopped)", file=sys.stderr)
    if interrupted is not None:
        raise interrupted
    return summary


def write_reconfig_plots(out_dir: Path, r: ReconfigResult, name: str = "", plot_format: str = "png") -> list[Path]:
    """Top view of every unit's path and the altitudes and mission error vs time with the flight's events
    marked (mars_link.flight.plots: format, dpi, markers)."""
    from mars_link.flight.plots import mark_events, pyplot, save_figure

    plt = pyplot()
    title = (lambda what: f"{name}: {what}") if name else (lambda what: what)

    plots = out_dir / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    written = []
    rows = np.array(r.unit_rows) if r.unit_rows else np.zeros((0, 12))
    fig, (ax, az) = plt.subplots(1, 2, figsize=(12, 5))
    for u in sorted(set(rows[:, 1].astype(int))) if len(rows) else []:
        m = rows[:, 1] == u
        ax.plot(rows[m, 3], rows[m, 2], lw=1, label=f"unit {u}")
        az.plot(rows[m, 0], -rows[m, 4], lw=1, label=f"unit {u}")
    mark_events(az, r.events)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title("units, top view"))
    az.set_xlabel("time [s]")
    az.set_ylabel("up [m]")
    az.set_title(title("altitude"))
    ax.legend(fontsize=7)
    az.legend(fontsize=7)
    fig.tight_layout()
    written.append(save_figure(fig, plots, "units", plot_format))
    if r.telemetry_rows:
        tel = np.array(r.telemetry_rows)
        fig, ax = plt.subplots(figsize=(8, 3.5))
        ax.plot(tel[:, 0], tel[:, 8], lw=1, label="mission error")
        mark_events(ax, r.events)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("mission error [m]")
        ax.set_title(title("tracked point vs mission reference (paused while reconfiguring)"))
        ax.legend(fontsize=7)
        fig.tight_layout()
        written.append(save_figure(fig, plots, "error", plot_format))
    return written
