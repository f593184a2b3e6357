"""The flight recorder: one observer for every flight, one body or several (a docked assembly is a flight
of one piece).

While the mission flies it measures the tracked point (the tracked unit's centre, else the CoM of the
piece that carries the mission) against the reference its coordinator flies, on the world's truth
(metrics.TrackingMetrics); at every step it watches every piece's tilt and deviation (divergence), the
smallest gap between bodies, the force spent on the mission and, from the truth, what became of each
unit the coordinator lost. It writes the run's time series through `run_log.RunLog` (telemetry.csv,
rotors.csv, units.csv) and ends the flight on a divergence or a failed manoeuvre (unless told not to:
a vehicle a client flies reports a divergence and flies on).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.core.rotations import quat_to_euler, quat_to_rotmat, tilt_deg
from mars_link.flight.engine import Engine, Flight, StepView
from mars_link.flight.metrics import DIVERGENCE_ERROR_M, DIVERGENCE_TILT_DEG, TrackingMetrics
from mars_link.flight.run_log import UNIT_LOG_HZ, RunLog

#: a lost unit that reaches the ground slower than this landed; faster, it fell (the world's truth)
LANDED_SPEED_MPS = 1.0
#: (a world that writes positions only) a unit's centre this close to its resting height touches the ground
GROUND_TOUCH_M = 0.02


class FlightRecorder:
    """Observer: the tracked point's error and every piece's divergence on the world's truth, the run's
    time series, the lost units' fates. `log` None: figures only (a sweep's flight)."""

    def __init__(self, flight: Flight, log: RunLog | None = None, trial_index: int = 0,
                 ends_on_divergence: bool = True) -> None:
        self.flight = flight
        self.log = log
        self.trial_index = trial_index
        self.ends_on_divergence = ends_on_divergence
        self.metrics = TrackingMetrics()
        self.min_clearance_m = math.inf
        self.failed = False  # the coordinator's manoeuvre failed (the flight ends)
        self.mission_force_integral_n2s = 0.0  # Σ rotors ∫ thrust² dt while the mission flies (not the manoeuvre)
        self.units_lost: dict[int, dict] = {}  # unit -> when it was lost and, from the truth, how it came down
        self._divergence_told = False
        self._force_seen = 0.0
        self._next_unit_log = 0.0
        self._offsets: dict[int, tuple] = {}  # id(piece model) -> (model, its unit offsets)
        self._lost_prev: dict[int, tuple] = {}  # unit -> (t, its centre) the step before
        self._ground_down_m = -flight.model.vehicle.gear_depth_m
        self._flush_every = max(1, int(flight.scenario.sim.control_hz))
        model = flight.model
        self.coordinator = pieces_of(flight)
        self._slots = {u: model.unit_slots(u) for u in model.unit_ids}

    def on_step(self, engine: Engine, v: StepView) -> bool:
        coord = self.coordinator
        if coord is None:  # (a lone unit flown by a ground station: nothing to track)
            return False
        t = v.t_s
        if coord.failed and not self.failed:
            self.failed = True
            engine.events.append(event(t, EventKind.RECONFIG_FAILED, reason=coord.failed,
                                       text=f"Reconfig failed: {coord.failed}"[:50]))
            return True
        if coord.lost:
            self._watch_lost(t, coord)
        world, executor, pieces = self.flight.world, coord.executor, coord.pieces
        one_body = len(pieces) == 1 and v.truth is not None and len(world.bodies) == 1  # (truth: the first body's)
        states = {key: v.truth if one_body else world.body_state(p.units[0]) for key, p in pieces.items()}
        mission = executor.mission_active(t) and v.record is not None
        tracked_piece = coord.tracked_piece() if mission else None
        for key, p in pieces.items():
            if p is tracked_piece:  # (its tracked point's error and tilt are measured below)
                continue
            state = states[key]
            tilt = tilt_deg(state.quaternion_wxyz)
            self.metrics.max_tilt_deg = max(self.metrics.max_tilt_deg, tilt)
            last = p.coordinator.last
            if last is None:
                continue
            dev = float(np.linalg.norm(state.position_ned_m - last.reference.position_ned_m))
            if not (dev < DIVERGENCE_ERROR_M and tilt < DIVERGENCE_TILT_DEG):
                self.metrics.mark_diverged(t, dev, tilt, phase=executor.phase)
        if len(pieces) > 1:
            self.min_clearance_m = min(self.min_clearance_m, world.min_clearance_m())
        if mission:
            self.mission_force_integral_n2s += world.force_integral_n2s - self._force_seen
            self._track(t, v, tracked_piece, states[tracked_piece.shape.key], executor, len(pieces))
        self._force_seen = world.force_integral_n2s
        log = self.log
        if log is not None:
            if log.rotor_due(t):
                log.rotors(self.trial_index, t, self._commanded_n(pieces), world.rotor_thrust_n,
                           self.flight.units.eta(self.flight.model.unit_ids))
            if t + 1e-9 >= self._next_unit_log:
                self._next_unit_log = t + 1.0 / UNIT_LOG_HZ
                self._log_units(t, pieces, states)
            if v.index % self._flush_every == 0:
                log.flush()
        if self.metrics.diverged and not self._divergence_told:
            self._divergence_told = True
            d = self.metrics.divergence
            phase = executor.phase
            engine.events.append(d if phase == "mission" else dict(d, text=f"Diverged ({phase})"[:50]))
            return self.ends_on_divergence
        return False

    def _track(self, t: float, v: StepView, piece, state, executor, n_pieces: int) -> None:
        """The mission metric: the tracked point on the truth against the reference the piece flies."""
        rec = v.record
        r = quat_to_rotmat(state.quaternion_wxyz)
        tracked = state.position_ned_m + r @ executor.tracked_offset(piece.shape)
        failsafe = piece.coordinator.failsafe
        err, _ = self.metrics.add(t, tracked, rec.reference.position_ned_m, state.quaternion_wxyz,
                                  position_lost=failsafe is not None and failsafe.state != "normal")
        if self.log is not None:
            roll, pitch, yaw = quat_to_euler(state.quaternion_wxyz)
            er, ep, ey = quat_to_euler(rec.estimate.quaternion_wxyz)
            self.log.telemetry(
                [self.trial_index, t, *rec.reference.position_ned_m, *tracked,
                 math.degrees(roll), math.degrees(pitch), math.degrees(yaw), err,
                 *rec.estimate.position_ned_m, math.degrees(er), math.degrees(ep), math.degrees(ey),
                 *state.position_ned_m, executor.mission_time(t), n_pieces])

    def _commanded_n(self, pieces) -> np.ndarray:
        """Every piece's commanded thrusts in the model's rotor order (NaN for a rotor no piece commands)."""
        if len(pieces) == 1:
            p = next(iter(pieces.values()))
            if p.coordinator.last is not None and tuple(p.units) == tuple(self.flight.model.unit_ids):
                return p.coordinator.last.thrusts_n
        cmd = np.full(self.flight.model.n_rotors, math.nan)
        for p in pieces.values():
            last = p.coordinator.last
            if last is not None:
                for k, u in enumerate(p.units):
                    cmd[self._slots[u]] = last.thrusts_n[4 * k:4 * k + 4]
        return cmd

    def _watch_lost(self, t: float, coord) -> None:
        """The truth of every lost unit until it touches the ground (`touchdown`); one that stays up (in a
        body that flies on) is "airborne"."""
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

    def _log_units(self, t: float, pieces, states: dict) -> None:
        rows = []
        for p in pieces.values():
            s = states[p.shape.key]
            r = quat_to_rotmat(s.quaternion_wxyz)
            w = r @ s.angular_velocity_frd_radps
            roll, pitch, yaw = (math.degrees(a) for a in quat_to_euler(s.quaternion_wxyz))
            arms = self._unit_offsets(p) @ r.T  # every unit's centre from the CoM, NED
            positions = (s.position_ned_m + arms).tolist()
            velocities = (s.velocity_ned_mps + np.cross(w, arms)).tolist()
            for i, u in enumerate(p.units):
                rows.append([t, u, *positions[i], *velocities[i], roll, pitch, yaw, len(p.shape.cells)])
        self.log.units(self.trial_index, rows)


def pieces_of(flight: Flight):
    """The flight's coordinator as pieces: a `PiecesCoordinator` (every flight `build.build_flight` makes)
    as it is; the assembly vehicle's one-body `Coordinator` (mars_link.vehicles.assembly_vehicle) as
    `OnePiece`; None without a coordinator."""
    coord = flight.coordinator
    if coord is None or hasattr(coord, "pieces"):
        return coord
    return OnePiece(coord, flight)


@dataclass
class _OneMission:
    """The executor of a flight that stays one piece and always flies its reference."""

    tracked_offset_frd_m: np.ndarray
    phase: str = "mission"
    shift_s: float = 0.0
    events: list = field(default_factory=list)
    plan: SimpleNamespace = field(default_factory=lambda: SimpleNamespace(disassembly_layers=(), assembly_layers=()))

    def mission_active(self, t_s: float) -> bool:
        return True

    def mission_time(self, t_s: float) -> float:
        return t_s

    def tracked_offset(self, shape) -> np.ndarray:
        return self.tracked_offset_frd_m


class OnePiece:
    """A one-body `Coordinator` seen as a coordinator of one piece that never splits (what the recorder and
    `runner.trial_result` read of a `PiecesCoordinator`): the assembly vehicle's, until it flies pieces."""

    failed = None
    lost: tuple = ()

    def __init__(self, coordinator, flight: Flight) -> None:
        model = flight.model
        self.coordinator = coordinator
        self.executor = _OneMission(np.asarray(flight.tracked_offset_frd_m, dtype=float))
        self._piece = SimpleNamespace(units=tuple(model.unit_ids), model=model, coordinator=coordinator,
                                      shape=SimpleNamespace(key=0, cells=dict.fromkeys(model.unit_ids)))
        self.pieces = {0: self._piece}
        self._final = [{"layout": list(model.layout), "units": list(model.unit_ids)}]

    @property
    def events(self) -> list[dict]:
        return self.coordinator.events

    @property
    def detections(self) -> list:
        return self.coordinator.detections

    def tracked_piece(self):
        return self._piece

    def pieces_final(self) -> list[dict]:
        return self._final


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
