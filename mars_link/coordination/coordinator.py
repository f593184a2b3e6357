"""The coordinator as a sans-IO component: unit telemetry in, per-rotor commands out.

One control step: fuse the units' sensor packets into a rigid-body estimate (EKF; or the ground truth
the world provides when sensor noise is off), sample the trajectory, run the controller and its
allocator, and split the 4N rotor thrusts into one `RotorCommand` per unit. The same object runs in
the in-process runner and in the SITL coordinator process.

Faults reach the allocation three ways: told (`set_faults`), found in the residuals by the
`detector` (faults_known = false), or a unit that stops reporting (`unit_lost`, called by the
transport's heartbeat watch or by the optional telemetry timeout here). Each records an event whose
"text" fits one MAVLink STATUSTEXT (50 characters).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.core.assembly import GRAVITY_MPS2, ROTORS_PER_UNIT, AssemblyModel
from mars_link.control.base import Controller
from mars_link.core.errors import UserInputError
from mars_link.models.fault_detection import Detection
from mars_link.models.battery import thrust_scale
from mars_link.models.estimation_outdoor import step_estimator
from mars_link.core.messages import BatterySample, RotorCommand, SensorPacket, wire_thrust, wire_time
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import Trajectory, TrajectoryPoint


#: MAVLink STATUSTEXT carries 50 characters
TEXT_MAX = 50
#: a unit's available-thrust share must move this much before the allocator is set up again
AVAILABLE_STEP = 0.01


def short_text(text: str, limit: int = TEXT_MAX) -> str:
    """`text` as one STATUSTEXT frame: ASCII, one line, at most `limit` bytes ('...' marks a cut)."""
    text = " ".join(str(text).split()).encode("ascii", "replace").decode("ascii")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def fault_summary(model: AssemblyModel, eta: np.ndarray, unit_names: tuple[int, ...] | None = None) -> str:
    """Compact believed fault set, e.g. 'u2 dead, u4r1 .50' ('none' when healthy); `unit_names`: the id
    shown for each of the model's units (default: its own)."""
    parts = []
    for uid in model.unit_ids:
        e = np.asarray(eta)[model.unit_slots(uid)]
        name = uid if unit_names is None else unit_names[uid - 1]
        if np.all(e <= 0.0):
            parts.append(f"u{name} dead")
            continue
        parts += [f"u{name}r{r + 1} {x:.2f}".replace(" 0.", " .") for r, x in enumerate(e) if x < 1.0]
    return ", ".join(parts) if parts else "none"


@dataclass
class StepRecord:
    """What the coordinator decided at one step (for logs and metrics)."""

    t_s: float
    estimate: RigidBodyState
    reference: TrajectoryPoint
    thrusts_n: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)


class Coordinator:
    def __init__(
        self,
        model: AssemblyModel,
        trajectory: Trajectory,
        controller: Controller,
        estimator=None,
        detector=None,
        telemetry_timeout_s: float | None = None,
    ) -> None:
        """`telemetry_timeout_s`: a unit that sends no packet for this long while others do is
        declared lost (`unit_lost`); None (default) leaves that call to the transport's heartbeat
        watch, which knows its own link's loss and latency."""
        self.model = model
        self.trajectory = trajectory
        self.controller = controller
        self.estimator = estimator
        self.detector = detector  # None: faults are told (set_faults), not detected
        #: the ESC telemetry's monitor (mars_link.models.esc_monitor), beside `detector`: its beliefs take
        #: precedence on the rotors its telemetry covers (`_esc_step`); None: no ESC telemetry is used
        self.esc_monitor = None
        self._detector_untold = False  # the ESCs' beliefs changed since the motion detector was last told
        self._motion_claims: dict[int, tuple[float, float]] = {}  # motion beliefs the ESCs still test: slot -> (eta, t)
        self.detections: list = []  # fault_detection.Detection, from residuals and lost units
        self.eta_believed = model.nominal_eta()
        self.events: list[dict] = []  # every event has "t_s", "type" and "text" (<= 50 chars, STATUSTEXT)
        self.last: StepRecord | None = None
        if telemetry_timeout_s is not None and not (math.isfinite(telemetry_timeout_s) and telemetry_timeout_s > 0):
            raise UserInputError(f"telemetry_timeout_s must be a number > 0, got {telemetry_timeout_s!r}")
        self.telemetry_timeout_s = telemetry_timeout_s
        self.command_range_n = model.vehicle.command_range_n  # what a unit accepts: commands are saturated to it
        # a SensorGuard estimator (sensor_health) reports sensor failures; `failsafe` (position_failsafe) flies
        # the position-loss failsafe over the trajectory (set by the composition root for trajectory flights)
        self.guard = estimator if hasattr(estimator, "take_events") else None
        self.guard_events = True  # False: someone else (the assembly vehicle) reports the guard's findings
        self.failsafe = None
        self.lost_units: set[int] = set()
        # each unit's pack as its telemetry reports it (BATTERY_STATUS); with `battery_cells` set (unit ->
        # cells in series), the allocator's bounds follow the thrust each pack still gives
        self.battery_cells: dict[int, int] | None = None
        self.unit_battery: dict[int, BatterySample] = {}
        self.available = np.ones(model.n_units)  # per unit: the share of the rotors' maximum the allocator uses
        self.rejected: dict[str, int] = {}  # reason -> packets dropped here
        self._last_seen_s: dict[int, float] = {}
        self._to_detect: tuple | None = None  # (t, thrusts, estimate, IMU samples) for finish_step
        self._estimated: tuple[float, RigidBodyState | None] | None = None  # (t, this period's estimate)
        #: resting on the ground with the motors off (a piece parked during a manoeuvre on the ground): zero
        #: commands, and no fault detection (no thrust, nothing to learn about the rotors)
        self.motors_off = False
        #: False while the host sends the units zeros instead of these commands (a vehicle on the ground or
        #: disarmed): the ESCs then read what was sent, not what was computed, and the ESC monitor judges nothing
        self.rotors_driven = True
        #: the structure's id of each of the model's units (k + 1 -> id), as events and texts name them: a
        #: piece of a reconfiguring structure numbers its units 1..n; None: the model's ids are the structure's
        self.unit_names: tuple[int, ...] | None = None

    def name_of(self, unit_id: int) -> int:
        """The structure's id of the model's unit `unit_id`."""
        return unit_id if self.unit_names is None else self.unit_names[unit_id - 1]

    def _event(self, t_s: float, kind: str, text: str, **fields) -> dict:
        ev = event(t_s, kind, **fields, text=short_text(text))
        self.events.append(ev)
        return ev

    def set_faults(self, eta: np.ndarray, t_s: float, reason: str) -> None:
        """Switch the allocation to a new believed fault set (told, or detected)."""
        from mars_link.allocation import check_controllable

        self.eta_believed = np.asarray(eta, dtype=float).copy()
        try:
            v = self.model.vehicle
            check_controllable(self.model, self.eta_believed, (v.rotor_min_thrust_n, v.rotor_max_thrust_n))
        except UserInputError as exc:  # mid-flight: log it and allocate as well as possible, never stop
            self._event(t_s, EventKind.UNCONTROLLABLE, "Uncontrollable faults: best effort", reason=str(exc))
        self.controller.set_faults(self.eta_believed)
        self._event(t_s, EventKind.REALLOCATION,
                    "Realloc " + fault_summary(self.model, self.eta_believed, self.unit_names), reason=reason)

    def unit_lost(self, unit_id: int, t_s: float, reason: str = "telemetry lost") -> Detection | None:
        """A unit stopped reporting (its process died, its link broke): it is a failed unit.

        All its rotors are believed dead (eta 0), the allocation switches, a detection is recorded
        and an event raised. A unit already lost returns None and changes nothing. Unknown unit ids
        raise UserInputError (the caller names units from its own configuration).
        """
        self.model.check_rotor(unit_id, None)
        if unit_id in self.lost_units:
            return None
        self.lost_units.add(unit_id)
        det = None
        if self.detector is not None:
            det = self.detector.on_unit_silent(unit_id, t_s)
        if det is None:
            det = Detection(t_s, unit_id, None, 0.0, reason="silent")
        self.detections.append(det)
        name = self.name_of(unit_id)
        self._event(t_s, EventKind.UNIT_LOST, f"Unit {name} lost: {reason}", unit=name, reason=reason)
        eta = self.eta_believed.copy()
        eta[self.model.unit_slots(unit_id)] = 0.0
        self.set_faults(eta, t_s, f"unit {name} lost ({reason})")
        return det

    def _watch_telemetry(self, t_s: float, packets: list[SensorPacket]) -> None:
        for p in packets:
            if p.unit_id in self.model.unit_cells:  # unknown ids (untrusted input) are not remembered
                self._last_seen_s[p.unit_id] = t_s
        if not packets:  # nobody reported: our own input stalled, not the units
            return
        for uid in self.model.unit_ids:
            seen = self._last_seen_s.setdefault(uid, t_s)  # the clock starts at the first step
            if uid not in self.lost_units and t_s - seen > self.telemetry_timeout_s + 1e-9:
                self.unit_lost(uid, t_s, f"no telemetry for {t_s - seen:.2f} s")

    def step(self, t_s: float, packets: list[SensorPacket]) -> list[RotorCommand]:
        """One control period: `commands`, then `finish_step` (what the in-process runners call)."""
        commands = self.commands(t_s, packets)
        c = time.perf_counter()
        self.finish_step()
        self.last.timings_s["control"] += time.perf_counter() - c
        return commands

    def estimate(self, t_s: float, packets: list[SensorPacket]) -> RigidBodyState | None:
        """This period's estimate of the body from its units' telemetry: the estimator's, else the truth the
        packets carry (None: neither). Once a period: `commands` at the same `t_s` takes it, so that a vehicle
        in front of the coordinator reads it every period, also while the coordinator does not fly."""
        if self.lost_units:
            packets = [p for p in packets if p.unit_id not in self.lost_units]
        if self.estimator is None:
            estimate = next((p.truth for p in packets if p.truth is not None), None)
        else:
            estimate = step_estimator(self.estimator, t_s, packets)
        self._estimated = (t_s, estimate)
        return estimate

    def commands(self, t_s: float, packets: list[SensorPacket]) -> list[RotorCommand]:
        """Estimate, control and allocation: this period's rotor commands. Fault detection is left to
        `finish_step`, which a real-time runner calls once the commands are out: what it finds changes
        the allocation from the next period on, never this period's commands."""
        c0 = time.perf_counter()
        if self.telemetry_timeout_s is not None:
            self._watch_telemetry(t_s, packets)
        if self.lost_units:  # a lost unit's late or stray packets are not trusted: counted, dropped
            kept = [p for p in packets if p.unit_id not in self.lost_units]
            if len(kept) != len(packets):
                self.rejected["lost_unit"] = self.rejected.get("lost_unit", 0) + len(packets) - len(kept)
            packets = kept
        estimated = self._estimated
        estimate = estimated[1] if estimated is not None and estimated[0] == t_s else self.estimate(t_s, packets)
        if estimate is None:
            raise ValueError("no estimator and no ground truth in the sensor packets")
        if self.battery_cells is not None:
            self._watch_batteries(packets)
        c1 = time.perf_counter()
        guard = self.guard
        if guard is not None:
            self._sensor_health(t_s)
        if self.failsafe is None:
            reference = self.trajectory.sample(t_s)
        else:
            reference = self.failsafe.reference(t_s, estimate, self.trajectory, guard.lost_since_s)
            self.events += self.failsafe.events
            self.failsafe.events.clear()
        out = self.controller.update(t_s, estimate, reference)
        thrusts = np.asarray(out.rotor_thrusts_n, dtype=float)
        if self.failsafe is not None and self.failsafe.state != "normal":
            self._failsafe_motors(t_s, float(out.wrench_demand[0]))
            if self.failsafe.motors_off:
                thrusts = np.zeros_like(thrusts)
        if self.motors_off:
            thrusts = np.zeros_like(thrusts)
        elif self.detector is not None:
            # while explanations tie (e.g. units {2,5}, {1,6}, {3,4} of a 3x2: each a pure lift loss),
            # the detector asks for a probe with zero net wrench on the believed assembly
            probe = self.detector.excitation_n(t_s)
            if probe.any():
                thrusts = thrusts + probe
        lo, hi = self.command_range_n
        if thrusts.max() > hi or thrusts.min() < lo:  # what a unit accepts (rotor_intake), not more
            thrusts = np.clip(thrusts, lo, hi)
        if self.detector is not None and not self.motors_off and not self._landing_near_ground():
            imus = [p.imu for p in packets if p.imu is not None] if guard is None else guard.usable_imus
            self._to_detect = (t_s, thrusts.copy(), estimate, imus)
        if self.esc_monitor is not None:
            self.esc_monitor.observe(t_s, {p.unit_id: p.esc for p in packets if p.esc is not None})
            self.esc_monitor.command(t_s, thrusts if self.rotors_driven else np.zeros_like(thrusts))
        c2 = time.perf_counter()
        alloc = out.timings_s.get("allocation", 0.0)
        scale = self.model.vehicle.full_scale_thrust_n
        self.last = StepRecord(
            t_s, estimate, reference, thrusts,
            {"estimation": c1 - c0, "control": c2 - c1 - alloc, "allocation": alloc},
        )
        wired = wire_thrust(thrusts, scale)  # the whole vector at once: same rounding as RotorCommand.as_wire
        t_w = wire_time(t_s)
        per_unit = wired.reshape(-1, ROTORS_PER_UNIT)  # (row views, cheaper than slices)
        return [RotorCommand(t_w, uid, per_unit[uid - 1]) for uid in self.model.unit_ids]

    def _watch_batteries(self, packets: list[SensorPacket]) -> None:
        """The units' reported pack voltages -> the thrust each can still give (mars_link.models.battery.thrust_scale);
        the allocator's bounds move when a unit's share changed by AVAILABLE_STEP (a re-setup costs ~1 ms)."""
        fresh = False
        for p in packets:
            if p.battery is not None and p.unit_id in self.battery_cells:
                self.unit_battery[p.unit_id] = p.battery
                fresh = True
        if not fresh or not hasattr(self.controller, "set_available"):
            return
        scale = self.available.copy()
        for k, uid in enumerate(self.model.unit_ids):
            b = self.unit_battery.get(uid)
            if b is not None:
                scale[k] = float(thrust_scale(b.voltage_v, self.battery_cells[uid]))
        if np.max(np.abs(scale - self.available)) >= AVAILABLE_STEP:
            self.available = scale
            self.controller.set_available(np.repeat(scale, ROTORS_PER_UNIT))
            if getattr(self.detector, "max_thrust_n", None) is not None:  # its thrust model clips as the packs do
                self.detector.max_thrust_n = self.controller.allocator.upper_bounds()

    def _landing_near_ground(self) -> bool:
        """A failsafe landing within reach of the ground: contact forces are no rotor fault (the detector rests)."""
        fs = self.failsafe
        if fs is None or fs.state not in ("land", "landed"):
            return False
        return fs.near_ground(float(fs.estimate_point_ned_m[2]), self._vertical_sigma_m())

    def _vertical_sigma_m(self) -> float:
        """The guard's standard deviation of the estimated height (m)."""
        return math.sqrt(max(float(self.guard.covariance[2, 2]), 0.0))

    def _failsafe_motors(self, t_s: float, collective_n: float) -> None:
        """What the failsafe's land detector reads: the controller's collective thrust (PX4's land detector
        reads the thrust setpoint too: on the ground the rotors' sum also carries the moments the attitude
        loop asks against the ground) and the IMUs' mean specific force."""
        imus = self.guard.usable_imus
        f_down = float(np.mean([s.accel_frd_mps2[2] for s in imus])) if imus else None
        self.failsafe.observe(t_s, collective_n, f_down, self.model.mass_kg * GRAVITY_MPS2,
                              self._vertical_sigma_m())
        self.events += self.failsafe.events
        self.failsafe.events.clear()

    def _sensor_health(self, t_s: float) -> None:
        """The guard's findings into the record; a sensor part that failed restarts the fault detector's
        history (its residuals held that sensor's bad samples)."""
        if self.guard_events:
            self.events += self.guard.take_events()
        if self.guard.imu_changed and self.detector is not None:
            self.detector.restart()

    def finish_step(self) -> None:
        """Fault detection on the last period's commanded thrusts and IMU samples (and ESC telemetry); a
        finding is an event, a detection record and a reallocation (for the periods to come)."""
        found, gone = self._esc_changes()
        if self._to_detect is not None:
            t_s, thrusts, estimate, imus = self._to_detect
            self._to_detect = None
            motion = self.detector.update(t_s, thrusts, estimate, imus)
            accepted = [d for d in motion if not self._esc_overrules(d, t_s)] if self.esc_monitor else motion
            found += accepted
            self._detector_untold |= bool(motion) and self.esc_monitor is not None
            self._claim(accepted)
        gone += self._esc_refutes()
        self._detector_untold |= bool(found or gone) and self.esc_monitor is not None
        if found and self.detector is not None and self.detector.isolating:
            # the ESCs' findings during an alarm are known parts of the change it isolates (the rest is fitted)
            self.detector.assume(self._esc_believed(self.detector.eta_estimate))
        if self._detector_untold and self.detector is not None and not self.detector.isolating:
            # the motion detector judges its residuals against what the ESCs see; told between its alarms
            # (telling restarts it: an alarm in progress would be lost)
            self._detector_untold = False
            believed = self._believed_eta(self.last.t_s)
            if not np.array_equal(believed, np.clip(self.detector.eta_estimate, 0.0, 1.0)):
                self.detector.set_model(self.model, believed)
        if not found and not gone:
            return
        t_s = self.last.t_s
        self.detections.extend(found)
        for d in found:
            name = self.name_of(d.unit)
            where = f"Unit {name}" + (f" rotor {d.rotor}" if d.rotor else "")
            if d.retracted:  # a belief later evidence contradicts: withdrawn, the allocation uses it again
                kind, text = EventKind.FAULT_RETRACTED, f"Fault withdrawn: {where} eta {d.eta_estimated:.2f}"
            else:
                what = f"{where} eta {d.eta_estimated:.2f}" if d.rotor else f"{where} failed"
                kind, text = EventKind.FAULT_DETECTED, f"Fault found: {what}"
            extra = {"ambiguous_with": list(d.ambiguous_with)} if d.ambiguous_with else {}  # (look-alikes: reported)
            if d.reason.startswith("esc"):
                extra["source"] = "esc"
            self._event(t_s, kind, text, unit=name, rotor=d.rotor,
                        eta_estimated=round(float(d.eta_estimated), 4), t_onset=round(float(d.t_onset), 6), **extra)
        for unit, rotor in gone:
            name = self.name_of(unit)
            self._event(t_s, EventKind.FAULT_RETRACTED, f"Fault withdrawn: unit {name} rotor {rotor}", unit=name,
                        rotor=rotor, source="esc")
        what = ", ".join(
            ("withdrawn " if d.retracted else "")
            + f"unit {self.name_of(d.unit)}" + (f" rotor {d.rotor}" if d.rotor else "") + f" eta {d.eta_estimated:.2f}"
            for d in found
        ) or "withdrawn " + ", ".join(f"unit {self.name_of(u)} rotor {r}" for u, r in gone)
        self.set_faults(self._believed_eta(t_s), t_s, f"detected: {what}")

    def attach_esc_monitor(self, monitor) -> None:
        """The ESC telemetry's monitor beside the motion detector (None: no ESC telemetry). Its samples are rows
        of the detector's isolation fit (`FaultDetector.rotor_evidence`)."""
        self.esc_monitor = monitor
        if self.detector is not None:
            self.detector.rotor_evidence = None if monitor is None else monitor.evidence_since

    def _claim(self, motion: list) -> None:
        """The motion detector's rotor beliefs the ESC monitor tests from now on (`_esc_refutes`)."""
        if self.esc_monitor is None:
            return
        for d in motion:
            if d.rotor is None:
                continue
            slot = self.model.rotor_slot(d.unit, d.rotor)
            if d.retracted or d.eta_estimated >= 1.0 - self.detector.params.min_change:
                self._motion_claims.pop(slot, None)
            else:
                self._motion_claims[slot] = (float(d.eta_estimated), float(d.t_detected))

    def _esc_refutes(self) -> list[tuple[int, int]]:
        """Motion beliefs whose rotor's current since says healthy (the monitor's sequential test): withdrawn, and the
        detector told at once (between its alarms). (unit, rotor) of each."""
        if not self._motion_claims or self.detector is None or self.detector.isolating:
            return []
        beliefs = self.esc_monitor.beliefs()
        for slot in [s for s in self._motion_claims if s in beliefs]:  # (the ESCs' own belief stands there)
            del self._motion_claims[slot]
        refuted, settled = self.esc_monitor.refuted(self._motion_claims)
        for slot in refuted + settled:
            del self._motion_claims[slot]
        if not refuted:
            return []
        eta = self.detector.eta_estimate
        eta[refuted] = 1.0
        self.detector.set_model(self.model, eta)
        return [(slot // ROTORS_PER_UNIT + 1, slot % ROTORS_PER_UNIT + 1) for slot in refuted]

    def _esc_overrules(self, d, t_s: float) -> bool:
        """A motion detection on rotors the ESC telemetry covers (or has a belief on): the ESCs' word stands."""
        slots = np.arange(self.model.n_rotors)[self.model.unit_slots(d.unit)] if d.rotor is None \
            else [self.model.rotor_slot(d.unit, d.rotor)]
        covered, beliefs = self.esc_monitor.covered(t_s), self.esc_monitor.beliefs()
        return all(covered[j] or j in beliefs for j in slots)

    def _esc_changes(self) -> tuple[list, list]:
        """The ESC monitor's new and withdrawn beliefs since the last step."""
        if self.esc_monitor is None:
            return [], []
        return self.esc_monitor.take_changes()

    def _esc_believed(self, eta: np.ndarray) -> np.ndarray:
        """`eta` with the ESC monitor's beliefs in place."""
        out = np.array(eta, dtype=float)
        for slot, belief in self.esc_monitor.beliefs().items():
            out[slot] = belief
        return out

    def _believed_eta(self, t_s: float) -> np.ndarray:
        """Every rotor's believed efficiency: the motion detector's, but where the ESC telemetry covers a rotor
        or believes it faulty, the ESC monitor's."""
        eta = self.eta_believed.copy() if self.detector is None else np.clip(self.detector.eta_estimate, 0.0, 1.0)
        if self.esc_monitor is None:
            return eta
        esc = self._esc_believed(np.where(self.esc_monitor.covered(t_s), 1.0, eta))
        for uid in self.lost_units:  # (a lost unit stays failed whatever its last telemetry said)
            esc[self.model.unit_slots(uid)] = 0.0
        return esc
