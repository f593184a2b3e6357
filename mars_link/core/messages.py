"""Messages exchanged between the world, the units and the coordinator.

The in-process runner passes these objects by direct call; the SITL runners carry the same content
as MAVLink frames (HIL_SENSOR / LOCAL_POSITION_NED up, SET_ACTUATOR_CONTROL_TARGET / HIL_ACTUATOR_CONTROLS
down). MAVLink carries float32, so every message is rounded to float32 at its boundary *in both modes*
(`as_wire`): that is what lets an in-process flight and a multi-process flight agree to the bit.
"""

from __future__ import annotations

import struct

from dataclasses import dataclass

import numpy as np

from mars_link.core.state import BaroSample, GpsSample, ImuSample, MagSample, PositionSample, RigidBodyState


def f32(v) -> np.ndarray:
    """Round to float32 and back: the precision of a MAVLink float field."""
    return np.asarray(v, dtype=np.float32).astype(np.float64)


def wire_time(t_s: float) -> float:
    """Sim time as carried on the wire (integer microseconds, MAVLink time_usec)."""
    return round(t_s * 1e6) / 1e6


#: a unit's four docking latches all engaged (bit k = side k: front, right, back, left; sitl.latches)
LATCH_ALL = 0b1111

#: float32 packers for one unit's few rotors (struct rounds double -> float32 as numpy does)
_F32_PACKERS = {n: struct.Struct(f"<{n}f") for n in range(1, 9)}


def wire_thrust(thrusts_n, full_scale_n: float) -> np.ndarray:
    """Thrust as carried in MAVLink actuator controls: float32 fraction of the unit's full scale."""
    t = np.asarray(thrusts_n, dtype=float)
    packer = _F32_PACKERS.get(t.size) if t.ndim == 1 else None
    if packer is not None:  # one unit's rotors, every control step: 4x cheaper than numpy's casts
        try:
            return np.array(packer.unpack(packer.pack(*[x / full_scale_n for x in t.tolist()]))) * full_scale_n
        except OverflowError:  # beyond float32's range: numpy's cast gives inf
            pass
    return f32(t / full_scale_n) * full_scale_n


def wire_state(s: RigidBodyState) -> RigidBodyState:
    """Ground truth as carried by ODOMETRY (float32 fields, microsecond time)."""
    return RigidBodyState(
        wire_time(s.t_s), f32(s.position_ned_m), f32(s.velocity_ned_mps), f32(s.quaternion_wxyz),
        f32(s.angular_velocity_frd_radps), f32(s.acceleration_ned_mps2), s.on_ground,
    )


@dataclass(frozen=True)
class BatterySample:
    """A pack's voltage and current as a power module measures them (world -> unit), and with the unit's
    remaining-charge estimate (unit -> coordinator); at BATTERY_STATUS precision (mV, cA, whole %)."""

    voltage_v: float
    current_a: float
    remaining: float = -1.0  # fraction 0..1 at 1 % steps; -1 = not estimated (the world's sample)


def wire_battery(voltage_v: float, current_a: float, remaining: float = -1.0) -> BatterySample:
    """A BatterySample at the precision of BATTERY_STATUS (voltages[0] in mV, current in cA, remaining in %)."""
    mv = min(max(round(voltage_v * 1000.0), 0), 65534)
    ca = min(max(round(current_a * 100.0), 0), 32767)
    pct = -1 if remaining < 0 else min(max(round(remaining * 100.0), 0), 100)
    return BatterySample(mv / 1000.0, ca / 100.0, -1.0 if pct < 0 else pct / 100.0)


#: ESC_STATUS carries int32 rpm
_INT32_MAX = 2**31 - 1


@dataclass(frozen=True)
class EscSample:
    """One unit's four ESCs as their telemetry reports them (unit -> coordinator), at ESC_STATUS precision:
    whole rpm (int32, negative = reversed) and current in A (float32). Made by `wire_esc` in both modes."""

    t_s: float
    rpm: tuple[int, ...]
    current_a: tuple[float, ...]


def wire_esc(t_s: float, rpm, current_a) -> EscSample:
    """An EscSample at ESC_STATUS precision: rpm rounded to int32, current to float32, time to microseconds."""
    rpm = rpm.tolist() if isinstance(rpm, np.ndarray) else rpm
    whole = tuple([round(float(x)) for x in rpm])
    if whole and (min(whole) < -_INT32_MAX - 1 or max(whole) > _INT32_MAX):  # (clamped only when needed)
        whole = tuple([min(max(x, -_INT32_MAX - 1), _INT32_MAX) for x in whole])
    amps = current_a.tolist() if isinstance(current_a, np.ndarray) and current_a.ndim == 1 else current_a
    packer = _F32_PACKERS.get(len(amps)) if isinstance(amps, (list, tuple)) else None
    if packer is not None:  # every unit's ESC sample: struct's float32 rounding, 4x cheaper than numpy's casts
        try:
            return EscSample(wire_time(t_s), whole, packer.unpack(packer.pack(*amps)))
        except (OverflowError, struct.error):  # beyond float32's range (numpy's cast gives inf), or not numbers
            pass
    return EscSample(wire_time(t_s), whole, tuple(float(x) for x in f32(current_a)))


@dataclass
class SensorPacket:
    """World -> unit (HIL link) and, forwarded, unit -> coordinator (telemetry)."""

    t_s: float
    unit_id: int
    imu: ImuSample
    position: PositionSample | None
    truth: RigidBodyState | None = None  # ground truth (HIL_STATE_QUATERNION), only with noise off
    latches: int = 0  # the unit's latch sensor: bit k set when side k holds a docked neighbour
    gps: GpsSample | None = None  # [sensors] profile "gps": HIL_GPS (already at wire precision)
    baro: BaroSample | None = None  # ... HIL_SENSOR's pressure fields
    mag: MagSample | None = None  # ... HIL_SENSOR's magnetometer fields
    battery: BatterySample | None = None  # the pack's measurement, at the battery rate (None between)
    esc: EscSample | None = None  # the unit's ESC telemetry (ESC_STATUS), at its rate (None between)

    def as_wire(self) -> "SensorPacket":
        t = wire_time(self.t_s)
        imu = ImuSample(t, self.unit_id, f32(self.imu.gyro_frd_radps), f32(self.imu.accel_frd_mps2),
                        self.imu.accel_ok, self.imu.gyro_ok)
        pos = None
        if self.position is not None:
            vel = self.position.velocity_ned_mps
            pos = PositionSample(
                t, self.unit_id, f32(self.position.position_ned_m), None if vel is None else f32(vel)
            )
        truth = None if self.truth is None else wire_state(self.truth)
        baro = None if self.baro is None else BaroSample(t, self.unit_id, float(f32(self.baro.pressure_hpa)),
                                                          float(f32(self.baro.altitude_amsl_m)))
        mag = None if self.mag is None else MagSample(t, self.unit_id, f32(self.mag.field_frd_gauss))
        return SensorPacket(t, self.unit_id, imu, pos, truth, self.latches, self.gps, baro, mag, self.battery, self.esc)

    def replaced(self, **changes) -> "SensorPacket":
        """`dataclasses.replace(self, **changes)` for the hot path (a unit's packet with its ESC sample, every
        other step): a copy of the fields, without replace's per-call look-up of them (2.1 us -> 0.6 us)."""
        new = object.__new__(type(self))
        fields = new.__dict__
        fields.update(self.__dict__)
        for name in changes:
            if name not in fields:
                raise TypeError(f"SensorPacket has no field {name!r}")
        fields.update(changes)
        return new


@dataclass
class RotorCommand:
    """Coordinator -> unit: commanded thrust of the unit's four rotors (N), for sim time t_s."""

    t_s: float
    unit_id: int
    thrusts_n: np.ndarray  # (4,)
    latch_setpoint: int = LATCH_ALL  # the unit's latches: bit k set = side k engaged, clear = open

    def as_wire(self, full_scale_n: float) -> "RotorCommand":
        return RotorCommand(wire_time(self.t_s), self.unit_id, wire_thrust(self.thrusts_n, full_scale_n),
                            self.latch_setpoint)


@dataclass
class ActuatorOutput:
    """Unit -> world (HIL link): thrust the unit's motors are driven to (N), after its own limits and
    injected faults, for the world step that starts at t_s."""

    t_s: float
    unit_id: int
    thrusts_n: np.ndarray  # (4,)
    latch_setpoint: int = LATCH_ALL  # what the unit drives its latches to (from the coordinator's command)

    def as_wire(self, full_scale_n: float) -> "ActuatorOutput":
        return ActuatorOutput(wire_time(self.t_s), self.unit_id, wire_thrust(self.thrusts_n, full_scale_n),
                              self.latch_setpoint)
