"""The flight-relevant core of one unit, sans-IO: sensor packets in -> telemetry out; rotor commands in
-> motor outputs out, with the unit's own thrust limits, injected faults and command watchdog.

Injected faults (eta) live here, in the unit's motor path: the coordinator is never told them.

This is the unit model of the in-process runner. The multi-process lockstep SITL runs each unit's full
firmware instead (`firmware_models.vehicle.Vehicle` on its HIL and coordinator links); on the
coordinator-driven path both apply the same limits, eta and float32 wire rounding, so the two flights
agree to the bit (tests/test_sitl_lockstep.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mars_link.assembly import ROTORS_PER_UNIT, VehicleParams
from mars_link.messages import ActuatorOutput, RotorCommand, SensorPacket


@dataclass
class UnitCoreParams:
    command_timeout_periods: int = 3  # hold the last command this many control periods, then fail safe
    control_period_s: float = 0.01


@dataclass
class UnitCounters:
    accepted: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    failsafe_entries: int = 0

    def reject(self, reason: str) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1


class UnitCore:
    def __init__(self, unit_id: int, vehicle: VehicleParams, params: UnitCoreParams | None = None) -> None:
        self.unit_id = unit_id
        self.vehicle = vehicle
        self.params = params or UnitCoreParams()
        self.eta = np.ones(ROTORS_PER_UNIT)
        self.command_n = np.zeros(ROTORS_PER_UNIT)
        self.last_command_t_s: float | None = None
        self.failsafe = False
        self.counters = UnitCounters()

    # ----------------------------------------------------------------- faults
    def inject_fault(self, rotor: int | None, eta: float) -> None:
        """rotor 1..4, or None for all four (a unit failure)."""
        if rotor is None:
            self.eta[:] = eta
        else:
            self.eta[rotor - 1] = eta

    # ----------------------------------------------------------------- messages
    def on_sensors(self, packet: SensorPacket) -> SensorPacket:
        """Forward what the unit measured to the coordinator (the unit's telemetry)."""
        return packet

    def on_rotor_command(self, cmd: RotorCommand) -> bool:
        """Accept a command if it is for us, newer than the last one and finite; count drops."""
        if cmd.unit_id != self.unit_id:
            self.counters.reject("wrong_unit")
            return False
        thrusts = cmd.thrusts_n
        if (
            len(thrusts) != ROTORS_PER_UNIT
            or not all(math.isfinite(x) for x in thrusts)
            or not math.isfinite(cmd.t_s)
        ):
            self.counters.reject("malformed")
            return False
        if self.last_command_t_s is not None and cmd.t_s <= self.last_command_t_s:
            self.counters.reject("stale")
            return False
        self.command_n = thrusts
        self.last_command_t_s = cmd.t_s
        self.failsafe = False
        self.counters.accepted += 1
        return True

    def motor_output(self, t_s: float) -> ActuatorOutput:
        """What the motors are driven to for the step starting at t_s (limits, faults, watchdog)."""
        p = self.params
        age = math.inf if self.last_command_t_s is None else t_s - self.last_command_t_s
        if age > p.command_timeout_periods * p.control_period_s + 1e-9:
            if not self.failsafe and self.last_command_t_s is not None:
                self.counters.failsafe_entries += 1
            self.failsafe = True
        v = self.vehicle
        if self.failsafe:
            thrust = np.zeros(ROTORS_PER_UNIT)
        elif v.rotor_min_thrust_n is not None or v.rotor_max_thrust_n is not None:
            thrust = np.clip(self.command_n, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
        else:
            thrust = self.command_n
        return ActuatorOutput(t_s, self.unit_id, thrust * self.eta).as_wire(v.full_scale_thrust_n)
