"""The off-board computer's side of PX4's per-rotor interface, without I/O: what the coordinator sends one
unit each control step so that a PX4 v1.17 unit flies its per-rotor thrusts, and how it learns that the
unit took over (VehicleCommandAck).

Each step, for unit n at time `t_s` (the coordinator's clock; message time stamps in microseconds):

  OffboardControlMode(direct_actuator)   the keep-alive, every `keepalive_every` steps (PX4 wants >= 2 Hz;
                                         COM_OF_LOSS_T 1 s), and always while the take-over is not acked
  VehicleCommand DO_SET_MODE OFFBOARD    until acked ACCEPTED (PX4 refuses it without the keep-alive:
                                         hence after the first keep-alive)
  VehicleCommand COMPONENT_ARM_DISARM 1  until acked ACCEPTED
  ActuatorMotors                         control[i] = thrust_i / full scale (float32); NaN for the unused
                                         motors; reversible_flags set when the plant takes reversed thrust

All in that order, so a unit that handles them in order runs the step armed, in OFFBOARD, with the
command. The same messages go out as objects in process and as CDR samples over rmw_zenoh."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mars_link.px4 import rmw_zenoh as rz
from mars_link.px4.cdr import ActuatorMotors, OffboardControlMode, VehicleCommand, VehicleCommandAck
from mars_link.px4.unit_interface import MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, NUM_CONTROLS, Px4MainMode, time_us

COORDINATOR_SYSTEM_ID = 201  # the coordinator's MAVLink system id (ARCHITECTURE.md), its VehicleCommand source
COORDINATOR_COMPONENT_ID = 1


@dataclass
class Px4Commander:
    """One unit's command stream from the coordinator."""

    unit_id: int
    full_scale_thrust_n: float
    reversible: bool = False             # the plant takes reversed thrust (no rotor minimum): flag every motor
    keepalive_every: int = 10            # control steps between two keep-alives (100 Hz control: 10 Hz)
    acked: set[int] = field(default_factory=set)   # VehicleCommand ids the unit accepted
    _step: int = 0

    @property
    def taken_over(self) -> bool:
        return {VehicleCommand.VEHICLE_CMD_DO_SET_MODE, VehicleCommand.VEHICLE_CMD_COMPONENT_ARM_DISARM} <= self.acked

    def step(self, t_s: float, thrusts_n: np.ndarray, *, count: bool = True) -> list[tuple[rz.Px4Topic, Any]]:
        """The messages of one control step, in the order they must be handled."""
        stamp = time_us(t_s)
        out: list[tuple[rz.Px4Topic, Any]] = []
        if self._step % self.keepalive_every == 0 or not self.taken_over:
            out.append((rz.OFFBOARD_CONTROL_MODE, OffboardControlMode(timestamp=stamp, direct_actuator=True)))
        self._step += int(count)
        if VehicleCommand.VEHICLE_CMD_DO_SET_MODE not in self.acked:
            out.append((rz.VEHICLE_COMMAND, self._command(stamp, VehicleCommand.VEHICLE_CMD_DO_SET_MODE,
                                                          MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, Px4MainMode.OFFBOARD)))
        if VehicleCommand.VEHICLE_CMD_COMPONENT_ARM_DISARM not in self.acked:
            out.append((rz.VEHICLE_COMMAND, self._command(stamp, VehicleCommand.VEHICLE_CMD_COMPONENT_ARM_DISARM,
                                                          VehicleCommand.ARMING_ACTION_ARM, 0)))
        out.append((rz.ACTUATOR_MOTORS, self.motors(stamp, thrusts_n)))
        return out

    def take_over(self, t_s: float) -> list[tuple[rz.Px4Topic, Any]]:
        """The keep-alive and the commands not acked yet, without motors: what a sender that waits for
        the acks before the first ActuatorMotors sends first (samples on different keys may overtake
        each other on the way)."""
        return [m for m in self.step(t_s, np.zeros(0), count=False) if m[0] is not rz.ACTUATOR_MOTORS]

    def motors(self, stamp_us: int, thrusts_n: np.ndarray) -> ActuatorMotors:
        control = np.full(NUM_CONTROLS, np.nan, dtype=np.float32)
        values = np.asarray(thrusts_n, dtype=np.float64) / self.full_scale_thrust_n
        control[:len(values)] = values
        flags = (1 << len(values)) - 1 if self.reversible else 0
        return ActuatorMotors(timestamp=stamp_us, timestamp_sample=stamp_us, reversible_flags=flags, control=control)

    def take_ack(self, ack: VehicleCommandAck) -> bool:
        """An ack from /fmu/out/vehicle_command_ack; True if it is this commander's and accepted."""
        if int(ack.target_system) != COORDINATOR_SYSTEM_ID or int(ack.result) != VehicleCommandAck.VEHICLE_CMD_RESULT_ACCEPTED:
            return False
        self.acked.add(int(ack.command))
        return True

    def _command(self, stamp_us: int, command: int, param1: float, param2: float) -> VehicleCommand:
        return VehicleCommand(timestamp=stamp_us, param1=float(param1), param2=float(param2), param3=math.nan,
                              param4=math.nan, param5=math.nan, param6=math.nan, param7=math.nan,
                              command=command, target_system=self.unit_id, target_component=1,
                              source_system=COORDINATOR_SYSTEM_ID, source_component=COORDINATOR_COMPONENT_ID,
                              confirmation=0, from_external=True)
