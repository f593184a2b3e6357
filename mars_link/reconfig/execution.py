"""Executing a reconfiguration plan in flight, sans-IO: time and piece states in, actions out.

The executor turns a `ReconfigPlan` (paper 001: disassembly layers, then docking layers) into timed
references for every rigid piece and into split requests; the world (sitl/docking.py) closes a dock
when the mover reaches its dock pose within the tolerance. Sequence (spec §10-§11):

1. mission: the whole assembly follows the mission reference (as a CoM reference);
2. stop: at the trigger (a fault known + `trigger_delay_s`) the mission clock pauses; the assembly
   comes to rest on a smooth quintic and settles;
3. disassembly, layer by layer: every split of the layer at once; the rest holds, the detached piece
   moves `separation_m` away across the break line and climbs to an altitude level of its own
   (each piece flies at its own altitude, so transits never cross another piece's level);
4. assembly, layer by layer: every stationary piece holds; each mover flies at its own level to a
   pre-dock point `predock_m` behind its dock pose, descends to the stationary's altitude, then
   approaches at `approach_speed_mps` on a reference that follows the stationary piece's actual
   pose and yaw (paper 000 §5 does the same); the world latches the dock;
5. return: the final body flies back to where the mission paused, arriving with the mission's
   velocity and acceleration, and the mission resumes, shifted by the time the reconfiguration took.

Pieces are named by the frozenset of their global unit ids. Every piece is flown by its own
AssemblyModel/Coordinator (built by the runner); references here are for the piece's CoM.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.core.assembly import VehicleParams
from mars_link.core.errors import UserInputError
from mars_link.reconfig.placement import SnapWeights
from mars_link.reconfig.piece_shape import Key, PieceShape
from mars_link.reconfig.replan import replan_assembly
from mars_link.reconfig.sequencing import ReconfigPlan
from mars_link.core.rotations import quat_to_euler
from mars_link.models.trajectories import Trajectory, TrajectoryPoint, smoothstep


def units_text(units) -> str:
    """Unit ids as compact ranges ("1-4,9") for the <= 50-character event texts (MAVLink STATUSTEXT)."""
    ids = sorted(units)
    parts, start = [], None
    for i, u in enumerate(ids):
        if start is None:
            start = u
        if i + 1 == len(ids) or ids[i + 1] != u + 1:
            parts.append(str(start) if start == u else f"{start}-{u}")
            start = None
    return ",".join(parts)


# ----------------------------------------------------------------------------- references
def _quintic(p0, v0, a0, p1, v1, a1, T: float) -> np.ndarray:
    """(6, 3) coefficients c0..c5 of p(s) = sum c_k s^k on [0, T] meeting both end states."""
    p0, v0, a0, p1, v1, a1 = (np.asarray(x, dtype=float) for x in (p0, v0, a0, p1, v1, a1))
    T2, T3, T4, T5 = T * T, T**3, T**4, T**5
    m = np.array([[T3, T4, T5], [3 * T2, 4 * T3, 5 * T4], [6 * T, 12 * T2, 20 * T3]])
    rhs = np.vstack([p1 - p0 - v0 * T - 0.5 * a0 * T2, v1 - v0 - a0 * T, a1 - a0])
    c345 = np.linalg.solve(m, rhs)
    return np.vstack([p0, v0, 0.5 * a0, c345])


@dataclass
class _Segment:
    t0: float
    t1: float
    coeffs: np.ndarray

    def sample(self, t: float) -> tuple[np.ndarray, ...]:
        s = min(max(t - self.t0, 0.0), self.t1 - self.t0)
        c = self.coeffs
        pw = np.array([1, s, s**2, s**3, s**4, s**5])
        p = pw @ c
        v = np.array([0, 1, 2 * s, 3 * s**2, 4 * s**3, 5 * s**4]) @ c
        a = np.array([0, 0, 2, 6 * s, 12 * s**2, 20 * s**3]) @ c
        j = np.array([0, 0, 0, 6, 24 * s, 60 * s**2]) @ c
        return p, v, a, j


class ComMission(Trajectory):
    """The mission reference (for the tracked point) turned into a CoM reference for one model:
    p_com = p_ref - Rz(yaw) offset, with the yaw-rate terms (as the cascaded controller does)."""

    def __init__(self, mission: Trajectory, offset_frd_m: np.ndarray) -> None:
        self.mission = mission
        self.offset = np.asarray(offset_frd_m, dtype=float)
        self.duration_s = mission.duration_s

    def sample(self, t_s: float) -> TrajectoryPoint:
        r = self.mission.sample(t_s)
        cy, sy = math.cos(r.yaw_rad), math.sin(r.yaw_rad)
        ox, oy, oz = self.offset
        dx, dy = cy * ox - sy * oy, sy * ox + cy * oy
        w = r.yaw_rate_radps
        p = r.position_ned_m - np.array([dx, dy, oz])
        v = r.velocity_ned_mps + np.array([w * dy, -w * dx, 0.0])
        a = r.acceleration_ned_mps2 + np.array([w * w * dx, w * w * dy, 0.0])
        return TrajectoryPoint(p, v, a, r.jerk_ned_mps3, r.yaw_rad, w)


class PieceReference(Trajectory):
    """A piece's CoM reference: quintic segments, then optionally a mission tail (time-shifted), or a
    live point the executor sets every step (docking approach)."""

    def __init__(self, start: TrajectoryPoint, duration_s: float = math.inf) -> None:
        self._hold = start
        self.segments: list[_Segment] = []
        self.tail: tuple[Trajectory, float, float] | None = None  # (trajectory, from_t, shift)
        self.live: TrajectoryPoint | None = None
        self.yaw_rad = start.yaw_rad
        self.duration_s = duration_s

    def end_time(self) -> float:
        return self.segments[-1].t1 if self.segments else -math.inf

    def end_position(self) -> np.ndarray:
        return self.segments[-1].sample(self.segments[-1].t1)[0] if self.segments else self._hold.position_ned_m

    def move(self, t0: float, target, speed_mps: float, min_s: float = 1.0, start: TrajectoryPoint | None = None,
             end: TrajectoryPoint | None = None) -> float:
        """Quintic from the current reference (or `start`) at t0 to `target` (or `end`, with its velocity
        and acceleration); the duration gives a mean speed of `speed_mps`. Returns the end time."""
        s = start or self.sample(t0)
        target = end.position_ned_m if end is not None else np.asarray(target, dtype=float)
        v1 = end.velocity_ned_mps if end is not None else np.zeros(3)
        a1 = end.acceleration_ned_mps2 if end is not None else np.zeros(3)
        dist = float(np.linalg.norm(target - s.position_ned_m))
        T = max(min_s, dist / speed_mps)
        self.segments = [_Segment(t0, t0 + T, _quintic(s.position_ned_m, s.velocity_ned_mps,
                                                        s.acceleration_ned_mps2, target, v1, a1, T))]
        self.tail = None
        self.live = None
        return t0 + T

    def sample(self, t_s: float) -> TrajectoryPoint:
        if self.live is not None:
            return self.live
        if self.tail is not None and t_s >= self.tail[1]:
            traj, _, shift = self.tail
            return traj.sample(t_s - shift)
        if self.segments:
            seg = self.segments[-1]
            p, v, a, j = seg.sample(t_s)
            if t_s >= seg.t1:
                v, a, j = np.zeros(3), np.zeros(3), np.zeros(3)
            return TrajectoryPoint(p, v, a, j, self.yaw_rad)
        return TrajectoryPoint(self._hold.position_ned_m.copy(), yaw_rad=self.yaw_rad)


class TrackedPointReference(Trajectory):
    """What a piece's coordinator flies: the reference of the point it tracks, `offset_frd_m` from the
    piece's CoM (the tracked unit's centre; zero: the CoM). While the piece flies the mission it is the
    mission itself, sampled as a one-body flight samples it; otherwise the executor's CoM reference moved
    out to that point (ComMission's terms, inverted)."""

    def __init__(self, com_reference: PieceReference, offset_frd_m: np.ndarray) -> None:
        self.com_reference = com_reference
        self.offset = np.asarray(offset_frd_m, dtype=float)
        self._moved = bool(self.offset.any())
        self._tail: object = None  # the last mission tail found to be for this point (ComMission, same offset)

    @property
    def duration_s(self) -> float:  # type: ignore[override]
        return self.com_reference.duration_s

    def sample(self, t_s: float) -> TrajectoryPoint:
        ref = self.com_reference
        tail = ref.tail
        if ref.live is None and tail is not None and t_s >= tail[1]:
            traj = tail[0]
            if traj is self._tail or (isinstance(traj, ComMission) and np.array_equal(traj.offset, self.offset)):
                self._tail = traj
                return traj.mission.sample(t_s - tail[2])
        r = ref.sample(t_s)
        if not self._moved:
            return r
        cy, sy = math.cos(r.yaw_rad), math.sin(r.yaw_rad)
        ox, oy, oz = self.offset
        dx, dy = cy * ox - sy * oy, sy * ox + cy * oy
        w = r.yaw_rate_radps
        return TrajectoryPoint(r.position_ned_m + np.array([dx, dy, oz]),
                               r.velocity_ned_mps - np.array([w * dy, -w * dx, 0.0]),
                               r.acceleration_ned_mps2 - np.array([w * w * dx, w * w * dy, 0.0]),
                               r.jerk_ned_mps3, r.yaw_rad, w)


# ----------------------------------------------------------------------------- parameters and actions
#: the final body resumes the mission once its estimate holds within these of its point for settle_s
STEADY_POSITION_M = 0.03
STEADY_SPEED_MPS = 0.03


@dataclass
class ExecutionParams:
    """Timing and geometry of the manoeuvre; distances default to multiples of the unit pitch."""

    trigger_delay_s: float = 1.0  # after the fault is known
    speed_mps: float = 0.4  # mean speed of every transit
    approach_speed_mps: float = 0.1  # final docking approach
    stop_s: float = 2.0  # mission -> rest
    settle_s: float = 1.5  # after every move, before the next step
    altitude_step_m: float | None = None  # default max(0.3, 2 pitch)
    separation_m: float | None = None  # default 3 pitch
    predock_m: float | None = None  # default 2 pitch
    dock_timeout_s: float = 30.0
    #: what a re-plan without lost units maximises: "force" (paper 001) or "margin" (worst-stage margin)
    objective: str = "force"

    def resolved(self, pitch_m: float) -> "ExecutionParams":
        return ExecutionParams(
            self.trigger_delay_s, self.speed_mps, self.approach_speed_mps, self.stop_s, self.settle_s,
            max(0.3, 2 * pitch_m) if self.altitude_step_m is None else self.altitude_step_m,
            3 * pitch_m if self.separation_m is None else self.separation_m,
            2 * pitch_m if self.predock_m is None else self.predock_m,
            self.dock_timeout_s, self.objective,
        )


@dataclass(frozen=True)
class FreeStart:
    """Units apart on the ground, assembled in the air before the mission: where each unit's CoM rests
    (NED m) and how far above the ground the structure is built."""

    ground_ned_m: dict[int, np.ndarray]
    height_m: float = 1.5


@dataclass
class SplitAction:
    parent: Key
    children: list[PieceShape]  # [detached, rest]
    offsets_frd_m: list[np.ndarray]  # child CoM from the parent CoM


@dataclass
class DockRequest:
    stationary: Key
    mover: Key
    offset_frd_m: np.ndarray  # mover CoM from stationary CoM, stationary body frame
    merged: PieceShape


_APPROACH = {"+row": np.array([-1.0, 0, 0]), "-row": np.array([1.0, 0, 0]),
             "+col": np.array([0, 1.0, 0]), "-col": np.array([0, -1.0, 0]),
             "down": np.array([0, 0, 1.0])}  # (on the ground: into the slot from above)

#: a landing's reference ends this far below the CoM's resting height (m): the body sits firmly on its feet
LAND_PRESS_M = 0.01


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class _Docking:
    request: DockRequest
    stage: str  # "transit", "descend", "approach"
    stage_end_t: float
    approach_dir: np.ndarray
    started_t: float
    started_approach: float = 0.0


class Executor:
    """State machine over phases mission -> stop -> disassembly layers -> assembly layers -> return -> mission."""

    def __init__(self, plan: ReconfigPlan, vehicle: VehicleParams, mission: Trajectory,
                 tracked_unit: int | None, params: ExecutionParams = ExecutionParams(),
                 free_start: FreeStart | None = None, defer_take_off: bool = False) -> None:
        """`free_start`: the plan's pieces start as separate bodies on the ground (`plan_assembly`); they take
        off, dock layer by layer into the plan's target, and the mission's clock starts once the
        structure is complete (`shift_s`). `defer_take_off`: they wait on the ground (phase "grounded")
        until `begin_take_off` (the assembly vehicle: when a ground station takes it off)."""
        if not plan.feasible:
            raise UserInputError(f"reconfiguration plan is not feasible: {plan.reason}")
        self.plan = plan
        self.vehicle = vehicle
        self.pitch = vehicle.pitch_m
        self.params = params.resolved(self.pitch)
        self.mission = mission
        self.tracked_unit = tracked_unit
        self._offsets: dict[tuple, np.ndarray] = {}  # the piece's cells -> the tracked unit's offset
        whole = PieceShape(dict(plan.initial))
        self.shapes: dict[Key, PieceShape] = {whole.key: whole}
        self.refs: dict[Key, PieceReference] = {}
        self.levels: dict[Key, int] = {whole.key: 0}
        self.phase = "mission"
        self.layer = 0
        self.phase_end_t = math.inf
        self.trigger_t = math.inf
        self.pause_t: float | None = None  # mission time at which the mission paused
        self.shift_s = 0.0
        self.hold_down_m = 0.0
        self.yaw = 0.0
        self.docks: list[_Docking] = []
        self.events: list[dict] = []
        self.failed: str | None = None
        self.refs[whole.key] = self._mission_reference(whole, 0.0)
        self._snap: SnapWeights | None = None  # the mission's snap weights (paper 001), once a re-plan needs them
        self._replan_lost: set[int] = set()  # units lost during the docking layers: re-plan before the next one
        self.hold_until_s = -math.inf  # a commanded separation: the pieces fly apart until then (inf: for good)
        self._steady_since: float | None = None  # the final body has held its point since (the return waits)
        #: pieces resting on the ground with their motors off (a manoeuvre on the ground, `plan.on_ground`)
        self.parked: set[Key] = set()
        self.ground_down_m = -vehicle.gear_depth_m  # the CoM's down coordinate at rest on the ground (NED 0)
        self._lift_down_m = 0.0  # where the final body of a manoeuvre on the ground climbs back to
        #: each unit's believed rotor efficiencies (the coordinator's, shared): what a re-plan places by
        self.unit_eta: dict[int, np.ndarray] = {}
        self.free_start = free_start
        self.assembling = free_start is not None  # the first manoeuvre builds the structure from free units
        if free_start is not None:
            self._take_off(free_start, None if defer_take_off else 0.0)

    # ----------------------------------------------------------------- helpers
    def tracked_offset(self, shape: PieceShape) -> np.ndarray:
        """The tracked unit's centre from `shape`'s CoM, FRD (zero when the piece does not carry it)."""
        if self.tracked_unit is None or self.tracked_unit not in shape.cells:
            return np.zeros(3)
        cells = tuple(sorted(shape.cells.items()))
        offset = self._offsets.get(cells)
        if offset is None:  # (a model per call cost a tenth of a flight of pieces: the recorder asks every step)
            local = shape.units_local_order().index(self.tracked_unit) + 1
            offset = self._offsets[cells] = shape.model(self.vehicle).unit_position(local).copy()
        return offset.copy()

    def _mission_reference(self, shape: PieceShape, shift: float) -> PieceReference:
        com = ComMission(self.mission, self.tracked_offset(shape))
        ref = PieceReference(com.sample(0.0))
        ref.tail = (com, -math.inf, shift)
        return ref

    def mission_active(self, t_s: float) -> bool:
        """Whether the mission metric applies now (before the pause, and after the resume)."""
        return self.phase == "mission"

    def mission_time(self, t_s: float) -> float:
        return t_s - self.shift_s

    def _altitude(self, level: int) -> float:
        return self.hold_down_m - level * self.params.altitude_step_m

    def main_key(self) -> Key:
        """The piece that flies the mission: the tracked unit's, else the one with the most units."""
        for key in self.shapes:
            if self.tracked_unit is not None and self.tracked_unit in key:
                return key
        return max(self.shapes, key=lambda k: (len(k), -min(k)))

    def abandon(self, t_s: float, lost: set[int]) -> list[Key]:
        """Units lost (their processes died) during a manoeuvre: the pieces made only of lost units are
        dropped (they fall). In the docking layers, the docks of whole pieces go on and the layers after
        them are re-planned from the pieces there are (`_replan_docks`); otherwise, or if no docking
        sequence builds the rest, the manoeuvre ends with the pieces there are: the mission resumes on the
        main piece while the others hold where they are (`_give_up`). A rebuild on the ground ends there
        instead, landed (`_stay_landed`). Returns the dropped pieces. During the mission nothing changes
        here (FTC flies on with the unit lost)."""
        if self.phase == "mission" and self.trigger_t == math.inf:
            return []
        dropped = [k for k in self.shapes if k <= lost]
        for k in dropped:
            self.shapes.pop(k)
            self.refs.pop(k)
            self.levels.pop(k)
        self.trigger_t = math.inf
        if not self.shapes:
            self.failed = "every unit of the structure was lost"
            return dropped
        if self.plan.on_ground and self.phase in ("land", "disassembly", "assembly"):
            self._stay_landed(t_s, lost)
            return dropped
        if self.phase in ("assembly", "grounded"):  # the docks of whole pieces go on; the next layers are re-planned
            self.docks = [d for d in self.docks if d.request.stationary in self.shapes and d.request.mover in self.shapes]
            self._replan_lost = set(lost)
            return dropped
        self.docks = []
        if self.phase == "mission":  # (a trigger pending, nothing moved yet)
            self.events.append(event(t_s, EventKind.RECONFIG_ABANDONED, lost=sorted(lost),
                                     pieces=[sorted(k) for k in self.shapes], text="Reconfig off: unit lost"))
            return dropped
        self._replan_lost = set(lost)
        self._give_up(t_s)
        return dropped

    def _give_up(self, t_s: float) -> None:
        """The manoeuvre ends with the pieces there are: the mission resumes on the main piece, the others
        hold where they are."""
        lost = sorted(self._replan_lost or ())
        self._replan_lost = set()
        what = "assembly" if self.assembling else "reconfig"
        self.events.append(event(t_s, f"{what}_abandoned", lost=lost, pieces=[sorted(k) for k in self.shapes],
                                 text=f"{what.capitalize()} off: u{units_text(lost)} lost"[:50]))
        self.assembling = False
        if self.pause_t is None:
            self.pause_t = t_s - self.shift_s
        self._return(t_s, abandoned=True)

    def _stay_landed(self, t_s: float, lost: set[int]) -> None:
        """A unit lost while the structure rebuilds itself on the ground: the manoeuvre ends there. A piece
        already over its slot (coming down to it) docks (the latches would close anyway), the other pieces in the
        air hold where they are (as `_give_up` leaves them), and what rests stays landed: it may be unable
        to hover, so no piece takes the mission up again on its own."""
        self.docks = [d for d in self.docks if d.stage in ("descend", "approach")
                      and d.request.stationary in self.shapes and d.request.mover in self.shapes]
        coming = {d.request.mover for d in self.docks}
        for key, ref in self.refs.items():
            if key not in self.parked and key not in coming:
                ref.move(t_s, ref.sample(t_s).position_ned_m, self.params.speed_mps)
        self.phase, self.phase_end_t = "landed", math.inf
        if self.pause_t is not None:  # (the flight ends when the paused mission would have: `shift_s` on)
            self.shift_s = t_s - self.pause_t
        self.events.append(event(t_s, EventKind.RECONFIG_ABANDONED, lost=sorted(lost),
                                 pieces=[sorted(k) for k in self.shapes],
                                 text=f"Reconfig off: u{units_text(sorted(lost))} lost, landed"[:50]))

    def _replan_docks(self, t_s: float) -> bool:
        """Between docking layers, after units were lost: the best structure the pieces there are can build on
        the target's cells (paper 001's placement with the lost units' cells to spare, `replan_assembly`) and
        its docks (Algorithm 3 again); False if no docking sequence builds one."""

        lost, what = self._replan_lost, ("assembly" if self.assembling else "reconfig")
        self._replan_lost = set()
        eta_of = {u: self.unit_eta.get(u, np.ones(4)) for u in self.plan.target}
        if self._snap is None:
            try:
                self._snap = SnapWeights.from_trajectory(self.mission)
            except UserInputError:  # (a mission of setpoints, no duration: no preference)
                self._snap = SnapWeights()
        plan = replan_assembly(self.vehicle, dict(self.plan.target), [sorted(k) for k in self.shapes], eta_of,
                               self._snap, self.params.objective)
        if not plan.feasible:
            return False
        self.plan = dataclasses.replace(self.plan, merges=plan.merges, assembly_layers=plan.assembly_layers,
                                        placement=plan.placement, objective=plan.objective)
        self.layer = 0
        self.phase_end_t = t_s + self.params.settle_s
        self.events.append(event(t_s, f"{what}_replanned", lost=sorted(lost), assembly_layers=plan.assembly_layers,
                                 pieces=[sorted(k) for k in self.shapes],
                                 cells={str(u): list(c) for u, c in sorted(plan.target.items())},
                                 chosen_by=plan.objective, force_objective=round(plan.placement.objective, 6),
                                 text=f"Re-planned without u{units_text(sorted(lost))}: {plan.assembly_layers} layers"[:50]))
        return True

    def trigger(self, t_s: float) -> None:
        """A fault became known: start the manoeuvre after the trigger delay (once)."""
        if self.phase == "mission" and self.trigger_t == math.inf and self.pause_t is None and len(self.shapes) == 1:
            self.trigger_t = t_s + self.params.trigger_delay_s

    def replan(self, plan: ReconfigPlan) -> bool:
        """A plan made in flight (from the faults found) replaces the one given, while the mission flies
        as one body whose cells are the plan's start (up to a shift); False (kept) otherwise."""
        if not plan.feasible or self.phase != "mission" or self.pause_t is not None or len(self.shapes) != 1:
            return False
        (shape,) = self.shapes.values()
        start = PieceShape(dict(plan.initial))
        if shape.key != start.key or shape.layout() != start.layout() or (
                shape.units_local_order() != start.units_local_order()):
            return False
        self.plan = plan
        self.shapes = {start.key: start}
        return True

    def _take_off(self, free: FreeStart, t0_s: float | None) -> None:
        """Every piece of the plan climbs from where it rests to the assembly height, from `t0_s` on (None:
        they rest until `begin_take_off`); docking starts once all of them hover there."""
        self.shapes, self.refs, self.levels = {}, {}, {}
        self.hold_down_m = max(float(g[2]) for g in free.ground_ned_m.values()) - free.height_m
        for units in self.plan.pieces:
            shape = PieceShape({u: self.plan.initial[u] for u in units})
            ground = np.mean([free.ground_ned_m[u] for u in units], axis=0)
            self.shapes[shape.key], self.levels[shape.key] = shape, 0
            self.refs[shape.key] = PieceReference(TrajectoryPoint(ground, yaw_rad=self.yaw))
        self.pause_t = 0.0  # the mission has not begun: it starts at its own t = 0
        self.phase = "grounded"
        if t0_s is not None:
            self.begin_take_off(t0_s)

    def begin_take_off(self, t_s: float) -> None:
        """The resting pieces of a free start take off now (once)."""
        if self.phase != "grounded":
            return
        p = self.params
        end = t_s
        for key, ref in self.refs.items():
            ground = ref.sample(t_s).position_ned_m
            end = max(end, ref.move(t_s, [ground[0], ground[1], self._altitude(0)], p.speed_mps, min_s=3.0))
        self.phase, self.layer, self.phase_end_t = "assembly", 0, end + p.settle_s
        self.events.append(event(t_s, EventKind.ASSEMBLY_START, assembly_layers=self.plan.assembly_layers,
                                 text=f"Assembly: {len(self.plan.pieces)} pieces, {self.plan.assembly_layers} dock layers"))

    # ----------------------------------------------------------------- main step
    def step(self, t_s: float, states: dict[Key, object]) -> list[SplitAction]:
        """Advance the phase machine; returns the splits the world must perform now."""
        if self.phase == "mission":
            if t_s >= self.trigger_t:
                self._stop(t_s)
            return []
        if self.phase == "stop" and t_s >= self.phase_end_t:
            if self.plan.on_ground:
                self._land(t_s)
                return []
            self.phase, self.layer = "disassembly", 0
            return self._next_split_layer(t_s)
        if self.phase == "land" and t_s >= self.phase_end_t:
            self.parked = set(self.shapes)  # (landed: motors off)
            self.phase, self.layer = "disassembly", 0
            return self._next_split_layer(t_s)
        if self.phase == "disassembly" and t_s >= self.phase_end_t:
            return self._next_split_layer(t_s)
        if self.phase == "landed":  # (a rebuild on the ground that ended early: its last docks finish)
            self._advance_docks(t_s, states)
        if self.phase == "assembly":
            self._advance_docks(t_s, states)
            if not self.docks and t_s >= max(self.phase_end_t, self.hold_until_s):
                if self._replan_lost and not self._replan_docks(t_s):
                    self._give_up(t_s)
                elif self._last_layer_done() and not self._steady(t_s, states):
                    pass  # the docked body is still moving: the mission does not resume on it yet
                else:
                    self._next_dock_layer(t_s)
        if self.phase == "return" and t_s >= self.phase_end_t:
            key = self.main_key()
            shape = self.shapes[key]
            ref = self.refs[key]
            com = ComMission(self.mission, self.tracked_offset(shape))
            ref.tail = (com, t_s, self.shift_s)
            self.phase = "mission"
            self.pause_t = None  # (a later fault may start another manoeuvre)
            self.hold_until_s = -math.inf
            self.events.append(event(t_s, EventKind.MISSION_RESUMED, shift_s=round(self.shift_s, 4),
                                     text=self._resume_text))
        return []

    def _last_layer_done(self) -> bool:
        return not any(m.layer > self.layer for m in self.plan.merges)

    def _steady(self, t_s: float, states: dict) -> bool:
        """The body about to fly the mission has held its point (estimate within STEADY_POSITION_M of it,
        slower than STEADY_SPEED_MPS) for `settle_s`, or it has tried for `dock_timeout_s`. A dock is an
        impact the pieces' merged estimate did not see: the body drifts and its estimate's velocity is
        off by centimetres per second for seconds; resuming at once carried that into the mission."""
        key = self.main_key()
        s = states.get(key)
        near = s is not None and (
            float(np.linalg.norm(s.position_ned_m - self.refs[key].end_position())) < STEADY_POSITION_M
            and float(np.linalg.norm(s.velocity_ned_mps)) < STEADY_SPEED_MPS)
        if not near:
            self._steady_since = None
        elif self._steady_since is None:
            self._steady_since = t_s
        held = self._steady_since is not None and t_s - self._steady_since >= self.params.settle_s - 1e-9
        if held or t_s - self.phase_end_t >= self.params.dock_timeout_s:
            self._steady_since = None
            return True
        return False

    def _stop(self, t_s: float) -> None:
        (key,) = self.shapes
        ref = self.refs[key]
        start = ref.sample(t_s)
        self.trigger_t = math.inf
        self.pause_t = t_s - self.shift_s
        self.yaw = start.yaw_rad
        stop_at = start.position_ned_m + start.velocity_ned_mps * self.params.stop_s / 2
        ref.yaw_rad = self.yaw
        end = ref.move(t_s, stop_at, math.inf, self.params.stop_s, start=start)
        self.hold_down_m = float(stop_at[2])
        self.phase, self.phase_end_t = "stop", end + self.params.settle_s
        self.events.append(event(t_s, EventKind.RECONFIG_START, disassembly_layers=self.plan.disassembly_layers,
                                 assembly_layers=self.plan.assembly_layers,
                                 text=f"Reconfig: {self.plan.disassembly_layers} split, {self.plan.assembly_layers} dock layers"))

    def _land(self, t_s: float) -> None:
        """A manoeuvre on the ground: the stopped body descends straight down and rests on its feet; the
        pieces' altitude levels count from the ground, and the final body climbs back to this height."""
        (key,) = self.shapes
        ref = self.refs[key]
        here = ref.end_position()
        self._lift_down_m = float(here[2])
        self.hold_down_m = self.ground_down_m + LAND_PRESS_M
        end = ref.move(t_s, [here[0], here[1], self.hold_down_m], self.params.speed_mps, min_s=3.0)
        self.phase, self.phase_end_t = "land", end + self.params.settle_s
        self.events.append(event(t_s, EventKind.LANDING, text="Reconfig: landing to rebuild"))

    def _next_split_layer(self, t_s: float) -> list[SplitAction]:
        self.layer += 1
        splits = [s for s in self.plan.splits if s.layer == self.layer]
        if not splits:
            self.phase, self.layer = "assembly", 0
            self.phase_end_t = t_s
            if t_s >= self.hold_until_s:
                self._next_dock_layer(t_s)
            return []
        p = self.params
        actions = []
        end = t_s
        rz = _rz(self.yaw)
        for s in splits:
            parent = self.shapes.pop(Key(s.body))
            pref = self.refs.pop(parent.key)
            plevel = self.levels.pop(parent.key)
            hold = pref.end_position()
            det, rest = parent.subset(s.detached), parent.subset(s.rest)
            com_p = parent.com_frd(self.pitch)
            offsets = [det.com_frd(self.pitch) - com_p, rest.com_frd(self.pitch) - com_p]
            # away from the rest, across the break line
            axis = 0 if s.line.axis == "row" else 1
            away = np.zeros(3)
            away[axis] = math.copysign(1.0, offsets[0][axis] - offsets[1][axis])
            level = max(self.levels.values(), default=plevel) + 1
            level = max(level, plevel + 1)
            for shape, off, lvl in ((det, offsets[0], level), (rest, offsets[1], plevel)):
                start = hold + rz @ off
                ref = PieceReference(TrajectoryPoint(start, yaw_rad=self.yaw))
                self.shapes[shape.key], self.refs[shape.key], self.levels[shape.key] = shape, ref, lvl
            target = hold + rz @ (offsets[0] + (0.0 if self.plan.on_ground else p.separation_m) * away)
            target[2] = self._altitude(level)  # (on the ground: straight up, out of the resting body's way)
            if parent.key in self.parked:
                self.parked.discard(parent.key)
                self.parked.add(rest.key)
            end = max(end, self.refs[det.key].move(t_s, target, p.speed_mps, start=TrajectoryPoint(
                hold + rz @ offsets[0], yaw_rad=self.yaw)))
            actions.append(SplitAction(parent.key, [det, rest], offsets))
            self.events.append(event(t_s, EventKind.SPLIT, layer=self.layer, body=sorted(s.body),
                                     detached=sorted(s.detached), rest=sorted(s.rest),
                                     text=f"Split L{self.layer}: u{units_text(s.detached)} off"[:50]))
        self.phase_end_t = end + p.settle_s
        return actions

    def _next_dock_layer(self, t_s: float) -> None:
        self.layer += 1
        merges = [m for m in self.plan.merges if m.layer == self.layer]
        if not merges:
            self._return(t_s)
            return
        p = self.params
        rz = _rz(self.yaw)
        target = self.plan.target
        for m in merges:
            st, mv = self.shapes[Key(m.stationary)], self.shapes[Key(m.mover)]
            u0 = m.stationary[0]
            dr, dc = st.cells[u0][0] - target[u0][0], st.cells[u0][1] - target[u0][1]
            moved = PieceShape({u: (target[u][0] + dr, target[u][1] + dc) for u in m.mover})
            merged = PieceShape({**st.cells, **moved.cells})
            offset = moved.com_frd(self.pitch) - st.com_frd(self.pitch)
            direction = _APPROACH[m.approach]
            s_hold = self.refs[st.key].end_position()
            predock = s_hold + rz @ (offset - direction * p.predock_m)
            transit = predock.copy()
            transit[2] = self._altitude(self.levels[mv.key])
            end = self.refs[mv.key].move(t_s, transit, p.speed_mps)
            req = DockRequest(st.key, mv.key, offset, merged)
            self.docks.append(_Docking(req, "transit", end + 0.5, direction, t_s))
            self.events.append(event(t_s, EventKind.DOCK_START, layer=self.layer, stationary=sorted(st.key),
                                     mover=sorted(mv.key), approach=m.approach,
                                     text=f"Dock L{self.layer}: u{units_text(mv.key)} to u{units_text(st.key)}"[:50]))

    def _advance_docks(self, t_s: float, states: dict) -> None:
        p = self.params
        rz = _rz(self.yaw)
        for d in self.docks:
            req = d.request
            ref = self.refs[req.mover]
            if d.stage == "transit" and t_s >= d.stage_end_t:
                s_hold = self.refs[req.stationary].end_position()
                predock = s_hold + rz @ (req.offset_frd_m - d.approach_dir * p.predock_m)
                d.stage, d.stage_end_t = "descend", ref.move(t_s, predock, p.speed_mps) + p.settle_s
            elif d.stage == "descend" and t_s >= d.stage_end_t:
                d.stage = "approach"
                d.started_approach = t_s
                d.stage_end_t = t_s + max(2.0, p.predock_m / p.approach_speed_mps)
            if d.stage == "approach":
                st = states.get(req.stationary)
                if st is None:
                    continue
                yaw = quat_to_euler(st.quaternion_wxyz)[2]
                u = min(1.0, (t_s - d.started_approach) / (d.stage_end_t - d.started_approach))
                s, ds, _, _ = smoothstep(u)
                T = d.stage_end_t - d.started_approach
                rs = _rz(yaw)
                back = (1.0 - s) * p.predock_m
                pos = st.position_ned_m + rs @ (req.offset_frd_m - d.approach_dir * back)
                vel = st.velocity_ned_mps + rs @ (d.approach_dir * p.predock_m * ds / T)
                ref.live = TrajectoryPoint(pos, vel, yaw_rad=yaw)
                if t_s - d.started_t > p.dock_timeout_s + (d.stage_end_t - d.started_approach):
                    self.failed = f"dock of {sorted(req.mover)} to {sorted(req.stationary)} timed out"

    def awaiting_docks(self) -> list[DockRequest]:
        """Docks the world should latch as soon as the tolerance holds."""
        return [d.request for d in self.docks if d.stage == "approach"]

    def on_docked(self, t_s: float, req: DockRequest) -> None:
        """The world latched `req`: one piece now, holding the stationary's reference point."""
        self.docks = [d for d in self.docks if d.request is not req]
        st_shape = self.shapes.pop(req.stationary)
        self.shapes.pop(req.mover)
        st_ref = self.refs.pop(req.stationary)
        self.refs.pop(req.mover)
        level = self.levels.pop(req.stationary)
        self.levels.pop(req.mover)
        merged = req.merged
        shift = merged.com_frd(self.pitch) - st_shape.com_frd(self.pitch)
        hold = st_ref.end_position() + _rz(self.yaw) @ shift
        ref = PieceReference(TrajectoryPoint(hold, yaw_rad=self.yaw))
        self.shapes[merged.key], self.refs[merged.key], self.levels[merged.key] = merged, ref, level
        self.phase_end_t = max(self.phase_end_t, t_s + self.params.settle_s)
        if req.stationary in self.parked:
            self.parked.discard(req.stationary)
            if self.docks or not self._last_layer_done() or self.phase == "landed":
                self.parked.add(merged.key)
            else:  # the final body: motors on, it climbs back to where the structure stopped
                end = ref.move(t_s, [hold[0], hold[1], self._lift_down_m], self.params.speed_mps, min_s=3.0)
                self.phase_end_t = max(self.phase_end_t, end)
        self.events.append(event(t_s, EventKind.DOCK, layer=self.layer, stationary=sorted(req.stationary),
                                 mover=sorted(req.mover), result=sorted(merged.key),
                                 text=f"Docked L{self.layer}: u{units_text(merged.key)}"[:50]))

    def _return(self, t_s: float, abandoned: bool = False) -> None:
        key = self.main_key()  # (several pieces only when a manoeuvre was abandoned: the others hold)
        shape = self.shapes[key]
        com = ComMission(self.mission, self.tracked_offset(shape))
        resume = com.sample(self.pause_t)
        ref = self.refs[key]
        end = ref.move(t_s, None, self.params.speed_mps, min_s=2.0, end=resume)
        self.shift_s = end - self.pause_t
        self.phase, self.phase_end_t = "return", end
        self._resume_text = "Assembled: mission starts" if self.assembling else "Reconfig: mission resumed"
        if abandoned:
            return
        kind, text = (("assembly_done", "Assembled: flying to the mission start") if self.assembling
                      else ("reconfig_done", "Reconfig done: returning to the mission"))
        self.assembling = False
        self.events.append(event(t_s, kind, cells={str(u): list(c) for u, c in sorted(shape.cells.items())}, text=text))
