"""In-process runner for reconfiguration flights: several rigid bodies at once, split and docked.

The whole assembly flies its mission with the scenario's controller and FTC mode; once the faults are
known (and after `[reconfig] trigger_delay_s`, or at `[reconfig] at_s`) the plan of
`plan_reconfiguration` is executed by `Executor`: every piece is its own rigid body of the world
(`sitl.world.World.split` / `merge`, momentum kept) flown by its own AssemblyModel, cascaded
controller, allocator (FTC on the piece's known faults) and Coordinator (`build.make_piece_coordinator`).
Every unit is its firmware (`firmware_models.vehicle.Vehicle`, as in every other mode), so faults act in
the unit's motor model and the commands go through its rotor intake.

Each piece's coordinator flies on its own EKF when sensor noise is on (on the truth its units report
when off): a split hands each child the parent's estimate moved to the child's CoM, a dock hands the
new piece the stationary piece's estimate moved to the new CoM (`AssemblyEstimator.set_model`), so the
coordinator side never reads the truth; the world latches on the truth. Faults must be told
(`faults_known = true`) for now. Deterministic for a seed.

Outputs (like `mars_link.runner`): summary.json keys mean_error_m, rmse_m, max_error_m,
force_integral_n2s (Σ rotors ∫ thrust² dt over every body), diverged, events (faults, each split and
dock, reconfig start/done, mission resume); telemetry.csv (tracked point vs the mission, per control
step), units.csv (every unit's position, velocity and attitude at 20 Hz) and plots/.
The mission error is measured while the mission runs (before the pause and after the resume); the
time the manoeuvre took is `reconfig_time_s`.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from mars_link.assembly import AssemblyModel
from mars_link.build import (make_estimator, make_piece_coordinator, make_trajectory, make_unit, make_world,
                             start_pose)
from mars_link.coordinator import Coordinator
from mars_link.engine import InProcessUnits
from mars_link.errors import UserInputError
from mars_link.flight_view import mission_point, open_view
from mars_link.messages import RotorCommand, SensorPacket
from mars_link.state import ImuSample, PositionSample
from mars_link.reconfig.flyability import FlyabilityRule
from mars_link.reconfig.execution import ExecutionParams, Executor, FreeStart, Key, PieceShape, local_eta
from mars_link.reconfig.placement import SnapWeights, health_from_eta
from mars_link.reconfig.sequencing import ReconfigPlan, plan_assembly, plan_reconfiguration
from mars_link.metrics import DIVERGENCE_ERROR_M, DIVERGENCE_TILT_DEG, TrackingMetrics, TrialResult
from mars_link.outputs import write_json
from mars_link.rotations import quat_to_euler, quat_to_rotmat, tilt_deg
from mars_link.scenario import Scenario, eta_after

UNIT_LOG_HZ = 20.0
#: cap on the manoeuvre: the flight ends this long after the mission would have
MAX_RECONFIG_S = 600.0


@dataclass
class _Piece:
    """A rigid piece as the coordinator flies it: its shape, model, units (world ids, model order) and
    its own coordinator (controller and FTC allocation over the piece's rotors)."""

    shape: PieceShape
    model: AssemblyModel
    units: tuple[int, ...]
    coordinator: Coordinator


@dataclass
class ReconfigResult(TrialResult):
    """A trial's figures plus the manoeuvre: whether it completed, how long it took, the plan."""

    reconfigured: bool = False
    reconfig_time_s: float = 0.0
    plan: dict | None = None
    unit_rows: list[list[float]] = field(default_factory=list)
    telemetry_rows: list[list[float]] = field(default_factory=list)
    assembled: bool = False  # a free start became the whole structure
    min_clearance_m: float = math.inf  # smallest gap between units of different bodies over the flight
    pieces_final: list[dict] = field(default_factory=list)  # each piece at the end: layout rows, unit ids


def execution_params(scenario: Scenario) -> ExecutionParams:
    keys = ExecutionParams.__dataclass_fields__
    return ExecutionParams(**{k: v for k, v in scenario.reconfig.items() if k in keys})


def check_reconfig_scenario(scenario: Scenario) -> None:
    """What this runner cannot fly, refused before flight (one line each)."""
    src = scenario.source
    if not scenario.faults_known:
        raise UserInputError(f"{src}: [reconfig] flights need [control] faults_known = true")
    if scenario.controller != "cascaded":
        raise UserInputError(f"{src}: [reconfig] flights need [control] controller = \"cascaded\"")
    if scenario.starts_free:
        if scenario.faults:
            raise UserInputError(f"{src}: [assembly] start = \"free\" with [[faults]] is not supported yet "
                                 "(assemble first, then reconfigure: not wired)")
        if scenario.reconfig.get("enabled"):
            raise UserInputError(f"{src}: [assembly] start = \"free\" and [reconfig] enabled cannot be combined yet")
        return
    if not scenario.faults:
        raise UserInputError(f"{src}: [reconfig] enabled but the scenario has no [[faults]] to react to")


def estimate_of(piece: "_Piece"):
    """What the piece's coordinator believes of its body (None before its first step)."""
    last = piece.coordinator.last
    return None if last is None else last.estimate


def local_packet(packet: SensorPacket, local_id: int) -> SensorPacket:
    """A unit's telemetry as its piece's coordinator numbers the units (the piece model's ids)."""
    imu, pos = packet.imu, packet.position
    return SensorPacket(
        packet.t_s, local_id,
        None if imu is None else ImuSample(imu.t_s, local_id, imu.gyro_frd_radps, imu.accel_frd_mps2),
        None if pos is None else PositionSample(pos.t_s, local_id, pos.position_ned_m, pos.velocity_ned_mps),
        packet.truth)


def free_ground_positions(scenario: Scenario, model: AssemblyModel, mission) -> dict[int, np.ndarray]:
    """Where each unit of a free start rests: the assembled layout around the docked start's CoM,
    stretched from the unit pitch to `free_spacing_m` between neighbours (NED, CoM at rest height)."""
    com, yaw = start_pose(scenario, model, mission)
    stretch = scenario.free_spacing_m / model.vehicle.pitch_m
    c, s_ = math.cos(yaw), math.sin(yaw)
    out = {}
    for u in model.unit_ids:
        x, y = model.unit_position(u)[:2] * stretch
        out[u] = np.array([com[0] + c * x - s_ * y, com[1] + s_ * x + c * y, -model.vehicle.gear_depth_m])
    return out


def make_plan(scenario: Scenario, model: AssemblyModel) -> ReconfigPlan:
    """The plan for all the scenario's faults (precomputed, like paper 001's configuration tree).

    A given `[reconfig] target` that cannot be reached is a UserInputError (exit 2)."""
    eta = eta_after(model, sorted(scenario.faults, key=lambda f: f.t_s), math.inf)
    target = scenario.reconfig.get("target")
    cells = None
    if target is not None:
        order = [model.unit_cells[u] for u in model.unit_ids]
        cells = {u: c for u, c in zip(target, order)}
    weights = SnapWeights.from_trajectory(make_trajectory(scenario, model))
    v = model.vehicle  # pieces must hover within the real thrust limits, not only pass the quadrant rule
    rule = FlyabilityRule(hover_thrust_limits_n=(v.rotor_min_thrust_n, v.rotor_max_thrust_n))
    try:
        return plan_reconfiguration(model, health_from_eta(model, eta), weights, target=cells, rule=rule)
    except UserInputError as exc:
        raise UserInputError(f"{scenario.source}: [reconfig] {exc}") from None


def unhoverable_pieces(plan: ReconfigPlan, model: AssemblyModel, eta: np.ndarray) -> list[str]:
    """Pieces of the plan that cannot hover within the rotor limits with their faults.

    The planner's four-quadrant rule (paper 001) is necessary, not sufficient (spec §5): e.g. a
    1x3 piece with a dead end module passes it but, with thrust limits, cannot balance its roll.
    Each piece the plan creates (both sides of every split, every docked result) gets the exact LP
    hover test of `check_controllable`; the manoeuvre is refused if one fails.
    """
    from mars_link.allocation import check_controllable

    eta_of = {u: eta[model.unit_slots(u)] for u in model.unit_ids}
    pieces = [s.detached for s in plan.splits] + [s.rest for s in plan.splits]
    pieces += [m.stationary + m.mover for m in plan.merges]
    bad = []
    for units in pieces:
        cells = plan.initial if any(set(units) == set(s.detached) or set(units) == set(s.rest)
                                    for s in plan.splits) else plan.target
        shape = PieceShape({u: cells[u] for u in units})
        piece = shape.model(model.vehicle)
        try:
            check_controllable(piece, local_eta(shape, eta_of),
                               (piece.vehicle.rotor_min_thrust_n, piece.vehicle.rotor_max_thrust_n))
        except UserInputError as exc:
            bad.append(f"piece {sorted(units)}: {exc}")
    return bad


def run_reconfig_trial(
    scenario: Scenario, seed: int, out_dir: Path | None = None,
    on_progress: Callable[[float], None] | None = None, view=None,
) -> ReconfigResult:
    from sitl.docking import DockTolerance, dock_check
    from sitl.physics import JsbsimBody

    check_reconfig_scenario(scenario)
    model = scenario.model()
    vehicle = model.vehicle
    mission = make_trajectory(scenario, model)
    duration = scenario.sim.duration_s or mission.duration_s
    control_hz = scenario.sim.control_hz
    dt = 1.0 / control_hz
    faults = sorted(scenario.faults, key=lambda f: f.t_s)
    enabled = scenario.reconfig.get("enabled", False)
    plan = make_plan(scenario, model) if enabled else None
    can_reconfigure = bool(plan is not None and plan.feasible and plan.disassembly_layers)
    refused = []
    if can_reconfigure:
        refused = unhoverable_pieces(plan, model, eta_after(model, faults, math.inf))
        can_reconfigure = not refused
    if scenario.starts_free:  # free units on the ground: assemble in the air (Algorithm 3), then the mission
        plan = plan_assembly(model)
        free = FreeStart(free_ground_positions(scenario, model, mission))
        executor = Executor(plan, vehicle, mission, scenario.tracked_unit(), execution_params(scenario), free)
    elif can_reconfigure:
        executor = Executor(plan, vehicle, mission, scenario.tracked_unit(), execution_params(scenario))
    else:  # nothing to execute: fly the mission as one body (still through the executor's references)
        from mars_link.reconfig.placement import nominal_cells

        stub = ReconfigPlan(model.layout, nominal_cells(model), None, True, 0, 0)  # type: ignore[arg-type]
        executor = Executor(stub, vehicle, mission, scenario.tracked_unit(), execution_params(scenario))
    tolerance = DockTolerance()

    eta_true = {u: np.ones(4) for u in model.unit_ids}
    pieces: dict[Key, _Piece] = {}

    def new_piece(shape: PieceShape, t_s: float, estimator=None) -> _Piece:
        """A piece and its coordinator; with sensor noise its EKF is `estimator` (a parent's or a docked
        piece's estimate moved to the new CoM), else a new one that initialises on the piece's sensors."""
        m = shape.model(vehicle)
        if estimator is None:
            estimator = make_estimator(scenario, m)
        coord = make_piece_coordinator(scenario, m, executor.refs[shape.key], local_eta(shape, eta_true), t_s,
                                       estimator)
        return _Piece(shape, m, tuple(shape.units_local_order()), coord)

    def moved_estimate(piece: _Piece, model: AssemblyModel, shift_frd_m: np.ndarray):
        """The piece's EKF, moved to a new body (`shift_frd_m`: its CoM in the piece's body frame)."""
        est = piece.coordinator.estimator
        if est is None:
            return None
        est = copy.deepcopy(est)
        est.set_model(model, shift_frd_m)
        return est

    # the world of bodies (split and merged by it, momentum kept): one per piece the executor starts with
    bodies = []
    for shape in executor.shapes.values():
        start = executor.refs[shape.key].sample(0.0)
        body_model = shape.model(vehicle)
        bodies.append((body_model, tuple(shape.units_local_order()), JsbsimBody(
            body_model, physics_hz=scenario.sim.physics_hz,
            position_ned_m=(float(start.position_ned_m[0]), float(start.position_ned_m[1]), 0.0), yaw_rad=start.yaw_rad)))
    world = make_world(scenario, model, seed, bodies=bodies)
    # every unit's firmware in the motor path
    units = InProcessUnits({u: make_unit(scenario, model, u) for u in model.unit_ids}, world)
    for shape in executor.shapes.values():
        pieces[shape.key] = new_piece(shape, 0.0)

    events: list[dict] = []
    if plan is not None:
        events.append({"t_s": 0.0, "type": "plan", "feasible": plan.feasible,
                       "disassembly_layers": plan.disassembly_layers, "assembly_layers": plan.assembly_layers,
                       "fallback_used": plan.fallback_used, "reason": plan.reason,
                       "text": (f"Reconfig plan: {plan.disassembly_layers}+{plan.assembly_layers} layers"
                                if plan.feasible else "Reconfig: no feasible plan")})
        if refused:
            events.append({"t_s": 0.0, "type": "reconfig_refused", "reason": "; ".join(refused),
                           "text": "Reconfig refused: a piece cannot hover"})
    next_fault = 0
    at_s = scenario.reconfig.get("at_s")
    metrics = TrackingMetrics()  # the mission error (while the mission runs); tilt and divergence of every piece
    failed = False
    min_clearance = math.inf
    unit_rows: list[list[float]] = []
    tel_rows: list[list[float]] = []
    next_unit_log = 0.0
    tel_f = units_f = None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        tel_f = open(out_dir / "telemetry.csv", "w", encoding="utf-8")
        tel_f.write("t_s,mission_t_s,ref_n_m,ref_e_m,ref_d_m,pos_n_m,pos_e_m,pos_d_m,error_m,pieces\n")
        units_f = open(out_dir / "units.csv", "w", encoding="utf-8")
        units_f.write("t_s,unit,n_m,e_m,d_m,vn_mps,ve_mps,vd_mps,roll_deg,pitch_deg,yaw_deg,piece_units\n")
    wall0 = time.perf_counter()
    k = 0
    t = 0.0
    try:
        while True:
            t = k * dt
            end_t = duration + executor.shift_s if executor.phase == "mission" else duration + MAX_RECONFIG_S
            if t >= end_t - 1e-9:
                break
            # faults: in the motor path; told to every piece's coordinator; they trigger the manoeuvre
            while next_fault < len(faults) and faults[next_fault].t_s <= t + 1e-9:
                f = faults[next_fault]
                next_fault += 1
                if f.rotor is None:
                    eta_true[f.unit][:] = f.eta
                else:
                    eta_true[f.unit][f.rotor - 1] = f.eta
                events.append({"t_s": round(t, 6), "type": "fault", "unit": f.unit, "rotor": f.rotor, "eta": f.eta,
                               "text": f.event_text()})
                for p in pieces.values():
                    p.coordinator.set_faults(local_eta(p.shape, eta_true), t, "fault told to the coordinator")
                if can_reconfigure and at_s is None and next_fault == len(faults):
                    executor.trigger(t)
            if can_reconfigure and at_s is not None and t >= at_s:
                executor.trigger(t - executor.params.trigger_delay_s)
            # the executor (coordinator side) sees the pieces' estimates, the world latches on the truth
            for action in executor.step(t, {key: estimate_of(p) for key, p in pieces.items()}):
                parent = pieces.pop(action.parent)
                world.split(parent.units, [(shape.model(vehicle), tuple(shape.units_local_order()), offset)
                                           for shape, offset in zip(action.children, action.offsets_frd_m)])
                for shape, offset in zip(action.children, action.offsets_frd_m):
                    pieces[shape.key] = new_piece(shape, t, moved_estimate(parent, shape.model(vehicle), offset))
            states = {key: world.body_state(p.units[0]) for key, p in pieces.items()}
            if executor.failed and not failed:
                failed = True
                events.append({"t_s": round(t, 6), "type": "reconfig_failed", "reason": executor.failed,
                               "text": f"Reconfig failed: {executor.failed}"[:50]})
                break
            # every piece's coordinator on its units' telemetry (EKF with sensor noise, else the truth they
            # report); the units drive their motors (limits, their own faults) and the world takes the outputs
            telemetry: dict[int, SensorPacket] = {pk.unit_id: pk for pk in units.take_sensors(world.sense())}
            commands = []
            for p in pieces.values():
                state = states[p.shape.key]
                piece_cmds = p.coordinator.step(t, [local_packet(telemetry[u], k + 1)
                                                    for k, u in enumerate(p.units) if u in telemetry])
                commands += [RotorCommand(c.t_s, p.units[c.unit_id - 1], c.thrusts_n) for c in piece_cmds]
                ref = p.coordinator.last.reference.position_ned_m
                tilt = tilt_deg(state.quaternion_wxyz)
                metrics.max_tilt_deg = max(metrics.max_tilt_deg, tilt)
                dev = float(np.linalg.norm(state.position_ned_m - ref))
                if not (dev < DIVERGENCE_ERROR_M and tilt < DIVERGENCE_TILT_DEG):
                    metrics.mark_diverged(t, dev, tilt, phase=executor.phase)
            units.drive(commands)
            min_clearance = min(min_clearance, world.min_clearance_m())
            # docks the world latches
            for req in executor.awaiting_docks():
                chk = dock_check(states[req.stationary], states[req.mover], req.offset_frd_m, tolerance)
                if chk.ready:
                    st, mv = pieces.pop(req.stationary), pieces.pop(req.mover)
                    world.merge(st.units[0], mv.units[0], req.merged.model(vehicle),
                                tuple(req.merged.units_local_order()))
                    executor.on_docked(t, req)
                    shift = req.merged.com_frd(vehicle.pitch_m) - st.shape.com_frd(vehicle.pitch_m)
                    pieces[req.merged.key] = new_piece(req.merged, t, moved_estimate(st, req.merged.model(vehicle), shift))
                    events.append({"t_s": round(t, 6), "type": "dock_latched",
                                   "position_error_m": round(chk.position_error_m, 4),
                                   "speed_mps": round(chk.speed_mps, 4), "yaw_deg": round(chk.yaw_deg, 3),
                                   "text": f"Dock latched: {chk.position_error_m * 100:.1f} cm"})
                    states = {key: world.body_state(p.units[0]) for key, p in pieces.items()}
            # mission metric on the truth
            view_point = None
            if executor.mission_active(t):
                tracked = scenario.tracked_unit()
                key = next(kk for kk in pieces if tracked is None or tracked in kk)
                p = pieces[key]
                s = states[key]
                off = executor.tracked_offset(p.shape)
                pos = s.position_ned_m + quat_to_rotmat(s.quaternion_wxyz) @ off
                ref = mission.sample(executor.mission_time(t)).position_ned_m
                err = float(np.linalg.norm(pos - ref))
                metrics.add_error(err)
                if err >= DIVERGENCE_ERROR_M or not math.isfinite(err):
                    metrics.mark_diverged(t, err, tilt_deg(s.quaternion_wxyz), phase=executor.phase)
                if view is not None:
                    view_point = mission_point(mission.sample(executor.mission_time(t)), p.coordinator.last, off,
                                               commands, model)
                row = [t, executor.mission_time(t), *ref, *pos, err, len(pieces)]
                tel_rows.append(row)
                if tel_f:
                    tel_f.write(",".join(f"{x:.6g}" for x in row) + "\n")
            if t + 1e-9 >= next_unit_log:
                next_unit_log = t + 1.0 / UNIT_LOG_HZ
                for p in pieces.values():
                    s = states[p.shape.key]
                    r = quat_to_rotmat(s.quaternion_wxyz)
                    w = r @ s.angular_velocity_frd_radps
                    roll, pitch, yaw = (math.degrees(a) for a in quat_to_euler(s.quaternion_wxyz))
                    for i, u in enumerate(p.shape.units_local_order()):
                        rr = r @ p.model.unit_position(i + 1)
                        row = [t, u, *(s.position_ned_m + rr), *(s.velocity_ned_mps + np.cross(w, rr)),
                               roll, pitch, yaw, len(p.shape.cells)]
                        unit_rows.append(row)
                        if units_f:
                            units_f.write(",".join(f"{x:.6g}" for x in row) + "\n")
            if view is not None:  # run.mcap / the live view (mars_link.flight_view)
                view.write_step(t, world, view_point, units.eta(model.unit_ids), [events, executor.events], units.dead)
            if metrics.diverged:
                events.append(dict(metrics.divergence, text=f"Diverged ({executor.phase})"[:50]))
                break
            world.advance()
            k += 1
            if on_progress is not None and k % 50 == 0:
                on_progress(min(1.0, t / max(duration + executor.shift_s, 1e-9)))
            if tel_f and k % int(control_hz) == 0:
                tel_f.flush()
                units_f.flush()
    finally:
        world.close()
        if view is not None:
            view.finish(event_lists=[events, executor.events])
        for f in (tel_f, units_f):
            if f:
                f.close()
    events = sorted(events + executor.events, key=lambda e: e["t_s"])
    done = [e for e in events if e["type"] == "reconfig_done"]
    begun = [e for e in events if e["type"] == "reconfig_start"]
    reconfigured = bool(done)
    return ReconfigResult(
        seed=seed, completed=not (metrics.diverged or failed), diverged=metrics.diverged, reconfigured=reconfigured,
        mean_error_m=metrics.mean_error_m, rmse_m=metrics.rmse_m, max_error_m=metrics.max_error_m,
        sim_time_s=t, wall_time_s=time.perf_counter() - wall0, force_integral_n2s=world.force_integral_n2s,
        max_tilt_deg=metrics.max_tilt_deg,
        reconfig_time_s=executor.shift_s if reconfigured else (t - begun[0]["t_s"] if begun else 0.0),
        plan=None if plan is None else plan.to_json(), events=events, unit_rows=unit_rows, telemetry_rows=tel_rows,
        assembled=any(e["type"] == "assembly_done" for e in events), min_clearance_m=min_clearance,
        pieces_final=[{"layout": list(p.shape.layout()), "units": list(p.units)} for p in pieces.values()],
    )


def run_reconfig_scenario(
    scenario: Scenario, out_dir: Path | None = None, trials: int = 1, seed: int | None = None,
    on_progress: Callable[[int, float], None] | None = None, plots: bool = True, mcap: bool = True, live=None,
) -> dict:
    """One reconfiguration flight; the run directory gets summary.json, CSVs, plots/ and run.mcap (unless not
    `mcap`; `live`: HOST:PORT of a live Foxglove view)."""
    seed = scenario.sim.seed if seed is None else seed
    cb = None if on_progress is None else (lambda frac: on_progress(0, frac))
    view = None
    if (mcap and out_dir is not None) or live is not None:
        model = scenario.model()
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
        view = open_view(out_dir, model, scenario, scenario.sim.control_hz, make_trajectory(scenario, model),
                         scenario.sim.duration_s or math.inf, live, scenario.tracked_unit(), mcap)
    r = run_reconfig_trial(scenario, seed, out_dir, cb, view)
    summary = {
        "scenario": scenario.name, "source": scenario.source, "mode": "inproc-reconfig",
        "layout": list(scenario.layout), "preset": scenario.preset, "controller": scenario.controller,
        "ftc": scenario.ftc, "seed": seed, "trials": 1, "noise": False,
        "physics_hz": scenario.sim.physics_hz, "control_hz": scenario.sim.control_hz,
        "completed": r.completed, "diverged": r.diverged, "reconfigured": r.reconfigured,
        "mean_error_m": r.mean_error_m, "mean_error_std_m": 0.0, "rmse_m": r.rmse_m, "max_error_m": r.max_error_m,
        "sim_time_s": r.sim_time_s, "wall_time_s": r.wall_time_s,
        "real_time_factor": r.sim_time_s / r.wall_time_s if r.wall_time_s > 0 else float("inf"),
        "force_integral_n2s": r.force_integral_n2s, "max_tilt_deg": r.max_tilt_deg,
        "reconfig_time_s": r.reconfig_time_s, "plan": r.plan, "start": scenario.start, "assembled": r.assembled,
        "min_clearance_m": r.min_clearance_m, "pieces_final": r.pieces_final,
        "events": [dict(e, trial=0) for e in r.events],
        "per_trial": [{"seed": seed, "mean_error_m": r.mean_error_m, "mean_error_std_m": 0.0, "rmse_m": r.rmse_m,
                       "max_error_m": r.max_error_m, "diverged": r.diverged}],
    }
    if out_dir is not None:
        write_json(out_dir / "summary.json", summary)
        if plots:
            write_reconfig_plots(out_dir, r)
            from mars_link.replay_gif import write_flight_gif

            write_flight_gif(out_dir / "plots" / "flight.gif", r.unit_rows, r.events)  # the animated replay
    return summary


def write_reconfig_plots(out_dir: Path, r: ReconfigResult) -> list[Path]:
    """Top view of every unit's path (split/dock events marked) and the mission error vs time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plots = out_dir / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    written = []
    rows = np.array(r.unit_rows) if r.unit_rows else np.zeros((0, 12))
    fig, (ax, az) = plt.subplots(1, 2, figsize=(12, 5))
    for u in sorted(set(rows[:, 1].astype(int))) if len(rows) else []:
        m = rows[:, 1] == u
        ax.plot(rows[m, 3], rows[m, 2], lw=1, label=f"unit {u}")
        az.plot(rows[m, 0], -rows[m, 4], lw=1, label=f"unit {u}")
    for e in r.events:
        if e["type"] in ("split", "dock"):
            az.axvline(e["t_s"], color="k", ls=":", lw=0.8)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("units, top view")
    az.set_xlabel("time [s]")
    az.set_ylabel("up [m]")
    az.set_title("altitude (dotted: split / dock)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = plots / "units.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    if r.telemetry_rows:
        tel = np.array(r.telemetry_rows)
        fig, ax = plt.subplots(figsize=(8, 3.5))
        ax.plot(tel[:, 0], tel[:, 8], lw=1)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("mission error [m]")
        ax.set_title("tracked point vs mission reference (paused during the reconfiguration)")
        fig.tight_layout()
        path = plots / "error.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written
