"""The coordinator as a sans-IO component: unit telemetry in, per-rotor commands out.

One control step: fuse the units' sensor packets into a rigid-body estimate (EKF; or the ground truth
the world provides when sensor noise is off), sample the trajectory, run the controller and its
allocator, and split the 4N rotor thrusts into one `RotorCommand` per unit. The same object runs in
the in-process runner and in the SITL coordinator process.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mars_link.assembly import ROTORS_PER_UNIT, AssemblyModel
from mars_link.control.base import Controller
from mars_link.messages import RotorCommand, SensorPacket, wire_thrust, wire_time
from mars_link.state import RigidBodyState
from mars_link.trajectories import Trajectory, TrajectoryPoint


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
    ) -> None:
        self.model = model
        self.trajectory = trajectory
        self.controller = controller
        self.estimator = estimator
        self.detector = detector  # None: faults are told (set_faults), not detected
        self.detections: list = []
        self.eta_believed = model.nominal_eta()
        self.events: list[dict] = []
        self.last: StepRecord | None = None

    def set_faults(self, eta: np.ndarray, t_s: float, reason: str) -> None:
        """Switch the allocation to a new believed fault set (told, or detected)."""
        from mars_link.allocation import check_controllable
        from mars_link.errors import UserInputError

        self.eta_believed = np.asarray(eta, dtype=float).copy()
        try:
            v = self.model.vehicle
            check_controllable(self.model, self.eta_believed, (v.rotor_min_thrust_n, v.rotor_max_thrust_n))
        except UserInputError as exc:  # mid-flight: log it and allocate as well as possible, never stop
            self.events.append({"t_s": round(t_s, 6), "type": "uncontrollable", "reason": str(exc)})
        self.controller.set_faults(self.eta_believed)
        self.events.append({"t_s": round(t_s, 6), "type": "reallocation", "reason": reason})

    def step(self, t_s: float, packets: list[SensorPacket]) -> list[RotorCommand]:
        c0 = time.perf_counter()
        if self.estimator is None:
            truth = next((p.truth for p in packets if p.truth is not None), None)
            if truth is None:
                raise ValueError("no estimator and no ground truth in the sensor packets")
            estimate = truth
        else:
            estimate = self.estimator.step(
                t_s, [p.imu for p in packets], [p.position for p in packets if p.position is not None]
            )
        c1 = time.perf_counter()
        reference = self.trajectory.sample(t_s)
        out = self.controller.update(t_s, estimate, reference)
        c2 = time.perf_counter()
        thrusts = np.asarray(out.rotor_thrusts_n, dtype=float)
        if self.detector is not None:
            found = self.detector.update(t_s, thrusts, estimate, [p.imu for p in packets])
            if found:
                self.detections.extend(found)
                what = ", ".join(
                    f"unit {d.unit}" + (f" rotor {d.rotor}" if d.rotor else "") + f" eta {d.eta_estimated:.2f}"
                    for d in found
                )
                self.set_faults(np.clip(self.detector.eta_estimate, 0.0, 1.0), t_s, f"detected: {what}")
            c2 = time.perf_counter()
        alloc = out.timings_s.get("allocation", 0.0)
        scale = self.model.vehicle.full_scale_thrust_n
        self.last = StepRecord(
            t_s, estimate, reference, thrusts,
            {"estimation": c1 - c0, "control": c2 - c1 - alloc, "allocation": alloc},
        )
        wired = wire_thrust(thrusts, scale)  # the whole vector at once: same rounding as RotorCommand.as_wire
        t_w = wire_time(t_s)
        return [
            RotorCommand(t_w, uid, wired[(uid - 1) * ROTORS_PER_UNIT : uid * ROTORS_PER_UNIT])
            for uid in self.model.unit_ids
        ]
