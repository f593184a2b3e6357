"""The coordinator of pieces: one rigid piece or several, each flown by its own coordinator, and the
reconfiguration executor over them.

It is a sans-IO component like `Coordinator`: unit telemetry in, rotor commands (with each unit's
latch setpoint) out, so the engine runs it where it runs a one-body coordinator. Each piece has its
own EKF (its estimate and covariance are moved, never the truth, when the piece splits or docks:
`AssemblyEstimator.set_model`), its own fault detector when faults are not told, its controller with
the FTC allocator and its reference from the executor.

The topology is learnt from the units' latch sensors (`SensorPacket.latches`, see mars_link.core.latches):
a split is commanded by opening the latches along the cut and is believed once both sides of every cut
link report open; a dock is believed once a facing pair of the requested dock reports latched. The
reconfiguration starts on faults told to it (`set_faults`, every scenario fault told), on faults its
detectors find (`faults_known = false`: the plan is made from the believed faults and the structure it
has), or at a given time; a commanded separation (`[[separations]]`) is a plan of one split and,
optionally, the dock back. A unit that stops reporting is lost: its piece reallocates and the executor
re-plans the docks left (`Executor.abandon`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.core.assembly import ROTORS_PER_UNIT, AssemblyModel, VehicleParams
from mars_link.coordination.coordinator import Coordinator, StepRecord
from mars_link.core.latches import LATCH_ALL, Link, neighbour_links
from mars_link.core.messages import RotorCommand, SensorPacket
from mars_link.reconfig.execution import Executor, SplitAction, TrackedPointReference, units_text
from mars_link.reconfig.piece_shape import Key, PieceShape, local_eta
from mars_link.reconfig.margin import controllability_margin
from mars_link.reconfig.plans import plan_event
from mars_link.reconfig.sequencing import ReconfigPlan
from mars_link.core.rotations import tilt_deg
from mars_link.core.state import ImuSample, PositionSample

#: a commanded split whose latches do not report open within this time fails the manoeuvre
SPLIT_CONFIRM_S = 1.0
#: a piece flying on its own (assembling, reconfiguring) whose estimate tilts past this is out of control: lost
LOST_TILT_DEG = 60.0
#: ... or whose controllability margin with the faults found is below this share of its healthy margin
LOST_MARGIN_SHARE = 0.1


@dataclass
class Piece:
    """A rigid piece as the coordinator flies it: its shape, model, units (world ids, model order) and
    its own coordinator (EKF, detector, controller and FTC allocation over the piece's rotors)."""

    shape: PieceShape
    model: AssemblyModel
    units: tuple[int, ...]
    coordinator: Coordinator
    detections_seen: int = 0


@dataclass
class _PendingSplit:
    action: SplitAction
    cut: dict[Link, tuple[int, int]]  # link -> (side of min unit, side of max unit)
    deadline_s: float


#: (piece shape, piece model, reference of its tracked point, the tracked unit's id in the piece or None,
#: believed eta of its rotors, time, estimator or None) -> the piece's coordinator
PieceCoordinatorFactory = Callable[[PieceShape, AssemblyModel, TrackedPointReference, int | None, np.ndarray, float,
                                    object], Coordinator]
#: (believed eta per unit, the structure's cells: unit -> cell of the layout) -> (a plan to execute, or None
#: and the reason there is none)
Planner = Callable[[dict[int, np.ndarray], dict], tuple[ReconfigPlan | None, str]]


def piece_can_fly(model: AssemblyModel, eta: np.ndarray) -> bool:
    """Whether a piece with these believed efficiencies keeps at least LOST_MARGIN_SHARE of its healthy
    controllability margin (mars_link.reconfig.margin): a rotor found at eta 0.003 is as dead as one at 0,
    which a rank test would not say."""
    return controllability_margin(model, eta) >= LOST_MARGIN_SHARE * controllability_margin(model)


def local_packet(packet: SensorPacket, local_id: int) -> SensorPacket:
    """A unit's telemetry as its piece's coordinator numbers the units (the piece model's ids)."""
    imu, pos = packet.imu, packet.position
    return SensorPacket(
        packet.t_s, local_id,
        None if imu is None else ImuSample(imu.t_s, local_id, imu.gyro_frd_radps, imu.accel_frd_mps2,
                                           imu.accel_ok, imu.gyro_ok),
        None if pos is None else PositionSample(pos.t_s, local_id, pos.position_ned_m, pos.velocity_ned_mps),
        packet.truth, packet.latches, *(None if s is None else dataclasses.replace(s, unit_id=local_id)
                                        for s in (packet.gps, packet.baro, packet.mag)), packet.battery, packet.esc)


class PiecesCoordinator:
    def __init__(self, executor: Executor, vehicle: VehicleParams, unit_ids, new_coordinator: PieceCoordinatorFactory,
                 *, tracked_unit: int | None = None, planner: Planner | None = None, told_faults: int = 0,
                 at_s: float | None = None, separations: list[tuple[float, ReconfigPlan, float | None]] = (),
                 telemetry_timeout_s: float | None = None) -> None:
        """`planner`: when set, a fault the detectors find starts a reconfiguration planned from the
        believed faults (at `at_s` instead, when given); `told_faults`: the reconfiguration starts once this
        many faults were told (executor's own plan); `at_s` without a planner: it starts at that time
        (executor's own plan). `separations`: (time, plan, re-dock time or None) of each commanded
        separation, started once the mission flies as one body. `telemetry_timeout_s`: a unit silent this
        long is lost (in-process flights; the SITL coordinator process watches its links itself)."""
        self.executor = executor
        self.vehicle = vehicle
        self.new_coordinator = new_coordinator
        self.tracked_unit = tracked_unit
        self.planner = planner
        self.told_faults_expected = told_faults
        self.told = 0
        self.at_s = at_s
        self.eta_believed: dict[int, np.ndarray] = {u: np.ones(ROTORS_PER_UNIT) for u in unit_ids}
        executor.unit_eta = self.eta_believed  # (shared: a re-plan without lost units places by what is believed)
        self.latch_setpoint: dict[int, int] = {u: LATCH_ALL for u in unit_ids}
        self.pieces: dict[Key, Piece] = {}
        self.pending_splits: list[_PendingSplit] = []
        self.events: list[dict] = []
        self.detections: list = []  # fault_detection.Detection of every piece, in the structure's unit ids
        self.failed: str | None = None
        self.last: StepRecord | None = None
        self._plan_at_s = math.inf
        self._at_done = False
        self.separations = list(separations)
        self.lost: set[int] = set()
        #: pieces found unable to fly this step (key -> why): their units are declared lost once the step is done
        self._cannot_fly: dict[Key, str] = {}
        self.telemetry_timeout_s = telemetry_timeout_s
        self._last_seen: dict[int, float] = {}
        #: False holds back what would start a manoeuvre (a separation, a plan from found faults, `at_s`)
        #: until it is True again: the assembly vehicle sets it while it is not flying
        self.manoeuvres_allowed = True
        self.rotors_driven = True  # False while the host holds every unit's rotors at zero (Coordinator.rotors_driven)
        self._told_trigger_s: float | None = None
        self._identity = {len(unit_ids): tuple(sorted(unit_ids))} if tuple(sorted(unit_ids)) == tuple(
            range(1, len(unit_ids) + 1)) else {}  # unit count -> (1..n): a piece whose local ids are the structure's
        for shape in executor.shapes.values():
            self.pieces[shape.key] = self._new_piece(shape, 0.0, None)

    # ----------------------------------------------------------------- pieces
    def _new_piece(self, shape: PieceShape, t_s: float, estimator) -> Piece:
        """A piece's coordinator flies its tracked point (the tracked unit's centre if it carries it, else its
        CoM) on the executor's reference: while it flies the mission, the mission itself."""
        m = shape.model(self.vehicle)
        units = tuple(shape.units_local_order())
        tracked = units.index(self.tracked_unit) + 1 if self.tracked_unit in units else None
        reference = TrackedPointReference(self.executor.refs[shape.key], self.executor.tracked_offset(shape))
        coord = self.new_coordinator(shape, m, reference, tracked, local_eta(shape, self.eta_believed), t_s,
                                     estimator)
        piece = Piece(shape, m, units, coord)
        self._take_events(piece, t_s)
        return piece

    def _take_events(self, piece: Piece, t_s: float) -> None:
        """The piece coordinator's events (they name the structure's units) into the record, and its new
        detections, in the structure's unit ids."""
        c = piece.coordinator
        withdrawn = False
        if c.events:
            withdrawn = any(e["type"] == EventKind.FAULT_RETRACTED for e in c.events)
            self.events += c.events
            c.events.clear()
        if len(c.detections) > piece.detections_seen:
            self._collect_detections(piece, t_s)
        elif withdrawn:  # (a belief withdrawn: the structure's beliefs follow the piece's)
            for k, u in enumerate(piece.units):
                self.eta_believed[u] = c.eta_believed[k * ROTORS_PER_UNIT:(k + 1) * ROTORS_PER_UNIT].copy()

    @staticmethod
    def _moved_estimate(piece: Piece, model: AssemblyModel, shift_frd_m: np.ndarray):
        """The piece's EKF (estimate and covariance) moved to a new body whose CoM sits at `shift_frd_m`
        in the piece's body frame; None when the piece flies on reported truth."""
        est = piece.coordinator.estimator
        if est is None:
            return None
        est = copy.deepcopy(est)
        est.set_model(model, shift_frd_m)
        return est

    def piece_of(self, unit_id: int) -> Piece:
        return next(p for p in self.pieces.values() if unit_id in p.units)

    def tracked_piece(self) -> Piece:
        """The piece carrying the tracked unit (else, or once that unit is lost, the one with the most units)."""
        if len(self.pieces) == 1:  # (a docked flight: every step asks)
            return next(iter(self.pieces.values()))
        if self.tracked_unit is not None and self.tracked_unit not in self.lost:
            return self.piece_of(self.tracked_unit)
        return max(self.pieces.values(), key=lambda p: (len(p.units), -min(p.units)))

    @property
    def failsafe(self):
        """The tracked piece's position-loss failsafe (None without one)."""
        return self.tracked_piece().coordinator.failsafe

    def estimates(self) -> dict[Key, object]:
        return {k: (None if p.coordinator.last is None else p.coordinator.last.estimate)
                for k, p in self.pieces.items()}

    # ----------------------------------------------------------------- faults
    def set_faults(self, eta: np.ndarray, t_s: float, reason: str) -> None:
        """Faults told (every rotor of the structure, the scenario's unit order): every piece reallocates;
        the reconfiguration starts once all the scenario's faults are told."""
        for u in self.eta_believed:
            self.eta_believed[u] = np.asarray(eta[(u - 1) * ROTORS_PER_UNIT:u * ROTORS_PER_UNIT], dtype=float).copy()
        for p in self.pieces.values():
            p.coordinator.set_faults(local_eta(p.shape, self.eta_believed), t_s, reason)
            self._take_events(p, t_s)
        self.told += 1
        if self.told_faults_expected and self.told == self.told_faults_expected:
            self._told_trigger_s = t_s  # (started in `_start_manoeuvres`: at once, or once flying)

    def _collect_detections(self, piece: Piece, t_s: float) -> None:
        c = piece.coordinator
        new = c.detections[piece.detections_seen:]
        if not new:
            return
        piece.detections_seen = len(c.detections)
        for k, u in enumerate(piece.units):
            self.eta_believed[u] = c.eta_believed[k * ROTORS_PER_UNIT:(k + 1) * ROTORS_PER_UNIT].copy()
        for d in new:  # (the piece's coordinator recorded each finding as an event)
            self.detections.append(dataclasses.replace(d, unit=piece.units[d.unit - 1]))
        if self._on_its_own(piece) and not piece_can_fly(piece.model, c.eta_believed):
            self._cannot_fly.setdefault(piece.shape.key, "cannot fly with the faults found")
        if self.planner is not None and self.at_s is None:  # (planned once the mission flies as one body)
            self._plan_at_s = min(self._plan_at_s, t_s + self.executor.params.trigger_delay_s)

    def _plan_from_belief(self, t_s: float) -> None:
        """The believed faults settled (the trigger delay after a detection): plan and start, or say why not."""
        self._plan_at_s = math.inf
        if len(self.executor.shapes) != 1:  # apart for good (a manoeuvre abandoned when a unit was lost): the
            self.events.append(event(t_s, EventKind.RECONFIG_REFUSED,  # planner plans from one structure
                                     reason=f"the structure is {len(self.executor.shapes)} pieces apart for good",
                                     text="Reconfig refused: in pieces"))
            return
        (shape,) = self.executor.shapes.values()  # the structure it has (after a manoeuvre: not the layout's order)
        r0 = min(r for r, _ in shape.cells.values())
        c0 = min(c for _, c in shape.cells.values())
        current = {u: (r - r0, c - c0) for u, (r, c) in shape.cells.items()}
        plan, reason = self.planner({u: e.copy() for u, e in self.eta_believed.items()}, current)
        if plan is None:
            self.events.append(event(t_s, EventKind.RECONFIG_REFUSED, reason=reason, text="Reconfig refused"))
            return
        self.events.append(plan_event(t_s, plan, self.vehicle, self.eta_believed))
        if not self.executor.replan(plan):
            self.events.append(event(t_s, EventKind.RECONFIG_REFUSED,
                                     reason="the structure is no longer the layout the plan starts from",
                                     text="Reconfig refused: structure changed"))
            return
        self.executor.trigger(t_s - self.executor.params.trigger_delay_s)

    def _separate(self, t_s: float) -> None:
        """A commanded separation comes due: the mission pauses and the units undock (once the structure
        flies the mission as one body; until then it waits)."""
        ex = self.executor
        t_sep, plan, redock_s = self.separations[0]
        if ex.phase != "mission" or ex.pause_t is not None or not ex.replan(plan):
            return
        self.separations.pop(0)
        ex.hold_until_s = math.inf if redock_s is None else redock_s
        ex.trigger(t_s - ex.params.trigger_delay_s)
        units = plan.splits[0].detached
        until = "" if redock_s is None else f" until {redock_s:g} s"
        self.events.append(event(t_s, EventKind.SEPARATION, units=units, redock_t_s=redock_s,
                                 text=f"Separation: u{units_text(units)}" + until))

    # ----------------------------------------------------------------- topology
    def _begin_split(self, t_s: float, action: SplitAction) -> None:
        """Open the latches along the cut between the children of `action`."""
        parent = self.pieces[action.parent]
        cells = parent.shape.cells
        first = set(action.children[0].cells)
        cut = {link: sides for link, sides in neighbour_links(cells).items() if len(link & first) == 1}
        for link, (side_a, side_b) in cut.items():
            a, b = sorted(link)
            self.latch_setpoint[a] &= ~(1 << side_a)
            self.latch_setpoint[b] &= ~(1 << side_b)
        self.pending_splits.append(_PendingSplit(action, cut, t_s + SPLIT_CONFIRM_S))

    def _learn_topology(self, t_s: float, latches: dict[int, int]) -> None:
        """Splits and docks as the units' latch sensors report them."""
        for pend in list(self.pending_splits):
            closed = any(latches.get(min(link), 0) >> sa & 1 or latches.get(max(link), 0) >> sb & 1
                         for link, (sa, sb) in pend.cut.items())
            if closed:
                if t_s > pend.deadline_s and self.failed is None:
                    self.failed = f"latches of {units_text(pend.action.parent)} did not open"
                continue
            self.pending_splits.remove(pend)
            parent = self.pieces.pop(pend.action.parent)
            for shape, offset in zip(pend.action.children, pend.action.offsets_frd_m):
                m = shape.model(self.vehicle)
                self.pieces[shape.key] = self._new_piece(shape, t_s, self._moved_estimate(parent, m, offset))
        for d in self.executor.docks:  # the units of every dock under way engage their latches
            for u in d.request.stationary | d.request.mover:
                self.latch_setpoint[u] = LATCH_ALL
        for req in self.executor.awaiting_docks():
            if req.stationary not in self.pieces or req.mover not in self.pieces:
                continue
            facing = [(link, sides) for link, sides in neighbour_links(req.merged.cells).items()
                      if len(link & req.stationary) == 1]
            if not any(latches.get(min(link), 0) >> sa & 1 and latches.get(max(link), 0) >> sb & 1
                       for link, (sa, sb) in facing):
                continue
            st, _ = self.pieces.pop(req.stationary), self.pieces.pop(req.mover)
            self.executor.on_docked(t_s, req)
            shift = req.merged.com_frd(self.vehicle.pitch_m) - st.shape.com_frd(self.vehicle.pitch_m)
            m = req.merged.model(self.vehicle)
            self.pieces[req.merged.key] = self._new_piece(req.merged, t_s, self._moved_estimate(st, m, shift))

    def unit_lost(self, unit_id: int, t_s: float, reason: str = "telemetry lost"):
        """A unit stopped reporting (its process died): its piece's coordinator believes it failed, and a
        manoeuvre under way is abandoned with the pieces there are (`Executor.abandon`): a piece of lost
        units alone is dropped, the mission resumes on the main piece, the others hold."""
        if unit_id in self.lost:
            return None
        self.lost.add(unit_id)
        piece = self.piece_of(unit_id)
        det = piece.coordinator.unit_lost(piece.units.index(unit_id) + 1, t_s, reason)
        self._take_events(piece, t_s)
        for key in self.executor.abandon(t_s, self.lost):
            self.pieces.pop(key, None)
        self.pending_splits = [p for p in self.pending_splits if p.action.parent in self.pieces]
        if self.executor.failed and self.failed is None:
            self.failed = self.executor.failed
        return det

    def _on_its_own(self, piece: Piece) -> bool:
        """Whether `piece` flies apart from other bodies (assembling, reconfiguring; not parked on the ground):
        one that cannot fly is lost then. A structure that is the only body flies on with the best
        allocation it has (or lands to be rebuilt)."""
        return len(self.pieces) > 1 and piece.shape.key not in self.executor.parked

    def _watch_control(self, piece: Piece) -> None:
        """A piece on its own whose estimate tilts past LOST_TILT_DEG is out of control (whatever the
        detector found): lost."""
        last = piece.coordinator.last
        if last is not None and self._on_its_own(piece) and tilt_deg(last.estimate.quaternion_wxyz) > LOST_TILT_DEG:
            self._cannot_fly.setdefault(piece.shape.key, f"out of control (tilt over {LOST_TILT_DEG:g} deg)")

    def _lose_pieces_that_cannot_fly(self, t_s: float) -> None:
        """The pieces found unable to fly: every unit lost (it lands or falls as its own fail-safe can), the
        manoeuvre re-planned from the units left (`unit_lost`)."""
        found, self._cannot_fly = self._cannot_fly, {}
        for key, why in found.items():
            for u in sorted(key):
                if u not in self.lost and key in self.pieces:
                    self.unit_lost(u, t_s, why)

    def _watch_telemetry(self, t_s: float, seen) -> None:
        for u in seen:
            self._last_seen[u] = t_s
        if not seen:
            return
        for u in self.eta_believed:
            last = self._last_seen.setdefault(u, t_s)
            if u not in self.lost and t_s - last > self.telemetry_timeout_s + 1e-9:
                self.unit_lost(u, t_s, f"no telemetry for {t_s - last:.2f} s")

    def all_events(self) -> list[dict]:
        """The coordinator's and the executor's events, in time order."""
        return sorted(self.events + self.executor.events, key=lambda e: e["t_s"])

    def pieces_final(self) -> list[dict]:
        return [{"layout": list(p.shape.layout()), "units": list(p.units)} for p in self.pieces.values()]

    # ----------------------------------------------------------------- the step
    def commands(self, t_s: float, packets: list[SensorPacket]) -> list[RotorCommand]:
        """The SITL coordinator's call (`step`: each piece's detection runs inside it)."""
        return self.step(t_s, packets)

    def finish_step(self) -> None:
        """(Nothing left: every piece's fault detection ran in `step`.)"""

    def _start_manoeuvres(self, t_s: float) -> None:
        """What comes due now: the given reconfiguration time, a plan from the faults found, a separation."""
        if self._told_trigger_s is not None:
            self.executor.trigger(max(self._told_trigger_s, t_s - self.executor.params.trigger_delay_s))
            self._told_trigger_s = None
        if self.at_s is not None and t_s >= self.at_s and not self._at_done:  # (once)
            self._at_done = True
            if self.planner is not None:  # planned now, from the faults found so far
                self._plan_at_s = t_s
            else:
                self.executor.trigger(t_s - self.executor.params.trigger_delay_s)
        if t_s >= self._plan_at_s and self.executor.phase == "mission" and self.executor.pause_t is None:
            self._plan_from_belief(t_s)
        if self.separations and t_s >= self.separations[0][0] - 1e-9:
            self._separate(t_s)

    def step(self, t_s: float, packets: list[SensorPacket]) -> list[RotorCommand]:
        """One control period over every piece; commands carry each unit's latch setpoint."""
        by_unit = {p.unit_id: p for p in packets}
        if self.telemetry_timeout_s is not None:
            self._watch_telemetry(t_s, by_unit)
        executor = self.executor
        if self.pending_splits or executor.docks:  # (the latches tell nothing new otherwise)
            self._learn_topology(t_s, {u: p.latches for u, p in by_unit.items()})
        if self.manoeuvres_allowed:
            self._start_manoeuvres(t_s)
        # (flying the mission, the executor only watches for its trigger: no estimates needed)
        for action in executor.step(t_s, {} if executor.phase == "mission" else self.estimates()):
            self._begin_split(t_s, action)
        commands = []
        parked = self.executor.parked
        latches = self.latch_setpoint
        for key, p in self.pieces.items():
            p.coordinator.motors_off = key in parked
            p.coordinator.rotors_driven = self.rotors_driven
            units = p.units
            if units == self._identity.get(len(units)):  # (the whole structure in its own order: ids kept)
                cmds = p.coordinator.step(t_s, packets if len(by_unit) == len(packets)
                                          else [by_unit[u] for u in units if u in by_unit])
                for c in cmds:
                    commands.append(c if c.latch_setpoint == latches[c.unit_id]
                                    else RotorCommand(c.t_s, c.unit_id, c.thrusts_n, latches[c.unit_id]))
            else:
                cmds = p.coordinator.step(t_s, [local_packet(by_unit[u], k + 1)
                                                for k, u in enumerate(units) if u in by_unit])
                for c in cmds:
                    u = units[c.unit_id - 1]
                    commands.append(RotorCommand(c.t_s, u, c.thrusts_n, latches[u]))
            self._take_events(p, t_s)
            self._watch_control(p)
        if self._cannot_fly:
            self._lose_pieces_that_cannot_fly(t_s)
        self.last = self.tracked_piece().coordinator.last
        if self.executor.failed and self.failed is None:
            self.failed = self.executor.failed
        return commands
