"""The assembly vehicle's side of sensor failures: findings as STATUSTEXT, the position-loss failsafe as
flight modes (PX4's hold, then land), and sensor failures injected on the vehicle routed to the units.

The trajectory flights' failsafe (mars_link.models.position_failsafe) pauses a trajectory; a vehicle has flight
modes instead, so here the same timing (`PositionFailsafeParams`) switches them: position lost for
`delay_s` (COM_POS_FS_DELAY) -> HOLD where the estimate says the assembly is; still lost `land_after_s`
after the last position -> LAND; landed (the autopilot's detector, or the IMU land detector of
position_failsafe: the rotors ask for under half the weight while the IMUs feel the ground carry it)
-> disarmed. Positions back during the hold: the vehicle stays in HOLD (as PX4: the pilot or the
client resumes), with "Position regained".
"""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle import MODE_HOLD, MODE_LAND
from mars_link.core.events import EventKind, event
from mars_link.core.assembly import GRAVITY_MPS2
from mars_link.models.position_failsafe import PositionFailsafeParams, past_ground

#: a guard event type -> STATUSTEXT severity
SEVERITY = {"position_lost": mavlink.MAV_SEVERITY_CRITICAL, "sensor_failed": mavlink.MAV_SEVERITY_WARNING,
            "position_drift": mavlink.MAV_SEVERITY_WARNING, "failsafe_hold": mavlink.MAV_SEVERITY_CRITICAL,
            "failsafe_land": mavlink.MAV_SEVERITY_CRITICAL}


def route_sensor_failure(vehicle, unit_vehicles: dict, sensor: str, kind: str, instance: int) -> list[int] | int:
    """The units a vehicle-level failure names (instance 0: every unit, i: the i-th unit), or a MAV_RESULT
    refusing it (an instance beyond the units: DENIED; a sensor some unit lacks: UNSUPPORTED)."""
    ids = list(unit_vehicles)
    if instance > len(ids):
        return mavlink.MAV_RESULT_DENIED
    units = ids if instance == 0 else [ids[instance - 1]]
    if not all(unit_vehicles[u].sensor_failures.supports(sensor, kind) for u in units):
        return mavlink.MAV_RESULT_UNSUPPORTED
    return units


class VehicleSensorWatch:
    """Reads the vehicle's SensorGuard after every estimate (`update`)."""

    def __init__(self, vehicle, guard, record: list[dict], params: PositionFailsafeParams | None = None) -> None:
        self.vehicle = vehicle
        self.guard = guard
        self.record = record  # the run's event list (VehicleFlight.events)
        self.params = params or PositionFailsafeParams()
        self.state = "normal"  # normal | hold | land
        self._supported_since: float | None = None
        vehicle.sensor_health = guard

    def watch(self, guard) -> None:
        """Another piece's guard from now on (the vehicle follows a piece a split or dock made)."""
        self.guard = guard
        self.vehicle.sensor_health = guard

    def _say(self, t_s: float, kind: str, text: str) -> None:
        ev = event(t_s, kind, text=text)
        self.record.append(ev)
        self.vehicle._text(text, SEVERITY.get(kind, mavlink.MAV_SEVERITY_INFO))

    def update(self, t_s: float) -> None:
        v, g, p = self.vehicle, self.guard, self.params
        for ev in g.take_events():
            self.record.append(ev)
            v._text(ev["text"], SEVERITY.get(ev["type"], mavlink.MAV_SEVERITY_INFO))
        lost = g.lost_since_s
        if self.state != "normal" and (not v.armed or v.autopilot.landed):
            self.state = "normal"  # landed (and disarmed) or the client took over after landing
        if lost is None:
            if self.state == "hold":
                self.state = "normal"
                if v.mode == MODE_HOLD and v.armed and not v.autopilot.landed:
                    # the estimate jumped by the drift: hold where the assembly is, not fly the jump back
                    # (PX4 likewise moves its setpoint by the EKF's reset delta)
                    v.autopilot.hold(v.state)
                self._say(t_s, "failsafe_resume", "Position regained: holding")
            return
        if not v.armed or v.landed or v.state is None:
            return
        if self.state == "normal" and t_s - lost >= p.delay_s - 1e-9:
            self.state = "hold"
            v.runner.pause()
            v.manual_service.orbit = None
            if v.source != "own":
                v.command_service.hand_back(v.state)
            v.autopilot.hold(v.state)
            v.mode = MODE_HOLD
            self._say(t_s, "failsafe_hold", "Position lost: holding")
        elif self.state == "hold" and t_s - lost >= p.land_after_s - 1e-9:
            self.state = "land"
            v.command_service.set_mode(MODE_LAND)
            self._say(t_s, "failsafe_land", "Position lost: landing")
        elif self.state == "land":
            self._land_detect(t_s)

    def _land_detect(self, t_s: float) -> None:
        """position_failsafe's land detectors: the estimate has been dead-reckoning for long."""
        v, p = self.vehicle, self.params
        imus = self.guard.usable_imus
        sigma_down = math.sqrt(max(float(self.guard.covariance[2, 2]), 0.0))
        if past_ground(float(v.state.position_ned_m[2]), v.autopilot.ground_z_m, sigma_down, p):
            self._landed(t_s, "Landed (estimate past ground): motors off")
            return
        if not imus:
            return
        weight = v.model.mass_kg * GRAVITY_MPS2
        f_down = float(np.mean([s.accel_frd_mps2[2] for s in imus]))
        supported = float(np.sum(v.rotor_thrusts_n())) < p.landed_thrust_fraction * weight and -f_down > 0.8 * GRAVITY_MPS2
        if not supported:
            self._supported_since = None
            return
        self._supported_since = t_s if self._supported_since is None else self._supported_since
        if t_s - self._supported_since >= p.landed_s:
            self._landed(t_s, "Landed: motors off")

    def _landed(self, t_s: float, text: str) -> None:
        self.state = "normal"
        self.vehicle.autopilot.idle()
        self.vehicle.command_service.disarm(text)
        self.record.append(event(t_s, EventKind.FAILSAFE_LANDED, text=text))
