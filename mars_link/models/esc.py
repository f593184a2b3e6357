"""ESC telemetry: what a unit's four ESCs report of their rotors (RPM and current), and what they should.

Why: a real unit's ESCs report each motor's speed and current (bidirectional DShot eRPM, the ESC's
telemetry wire; PX4 publishes them as esc_status, MAVLink carries them as ESC_STATUS), and that telemetry
tells a stopped motor or a damaged propeller apart within a few samples, which the rigid body's motion
alone often cannot (mirrored rotor sets look alike). This module is sans-IO: the unit's firmware
(firmware_models.vehicle) owns an `EscSensor`, the coordinator's `EscMonitor` (mars_link.models.esc_monitor)
uses the same `MotorConstants` to predict what a healthy rotor reports.

Motor model (per rotor): thrust T = k_T w^2, aerodynamic torque Q = k_Q w^2 = (k_Q/k_T) T (the vehicle's
yaw_moment_per_thrust_m), motor current I = Q / K_t + I_0, K_t = 60 / (2 pi KV) N m/A. The speed follows
the command through the vehicle's first-order motor lag (the world's thrust lag, the same discretisation).
What the ESC sees for each fault kind (mars_link.config.scenario FAULT_KINDS; eta = the remaining thrust):

* "eta" (default: a damaged propeller): the speed as commanded, the load current eta times a healthy one's;
  eta 0 is a motor off (firmware_models.motor's meaning of it, a dead unit's four rotors): seen as motor-stop.
* "prop-loss" (a propeller lost or broken): the motor, unloaded, spins faster than commanded (by
  `overspeed_unloaded` times the share of the load lost) and draws only the remaining load's current.
* "motor-stop" (the motor or its ESC stopped): the rotor coasts down through the motor lag, current 0.

The constants are stated, not measured on a unit: a 3-inch propeller on a 2600 KV motor reaching 26,000 rpm
at the preset's full-scale thrust (3.83 N on mars-real) draws about 3 A per rotor in a 0.52 kg unit's hover
and 9 A at full thrust, in the range such motors are sold for. The sample rate is 50 Hz (bidirectional DShot
returns eRPM with every frame, at the loop rate; current comes over the slower telemetry wire); noise 50 rpm
and 0.1 A (1 sigma), quantised to ESC_STATUS's whole rpm and float32 amperes in both modes (`wire_esc`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mars_link.core.assembly import ROTORS_PER_UNIT, VehicleParams
from mars_link.core.messages import EscSample, wire_esc, wire_time

#: rotor fault kinds ([[faults]] kind)
FAULT_KINDS = ("eta", "motor-stop", "prop-loss")
#: ESC telemetry failures ([[sensor_faults]] sensor = "esc"): no more samples, or the last one repeated
ESC_FAILURES = ("ok", "off", "stuck")
#: ESC_STATUS's rpm field is an int32
_INT32_MAX = 2**31 - 1
#: every distinct MotorConstants and EscParams the sensors use (frozen, hashable), one object each
_SHARED: dict = {}


@dataclass(frozen=True)
class EscParams:
    """The motor's constants and the telemetry's rate and noise (see the module docstring)."""

    rpm_at_full_scale: float = 26000.0
    kv_rpm_per_v: float = 2600.0
    no_load_current_a: float = 0.5
    overspeed_unloaded: float = 0.15  # prop-loss: speed gained per unit of load lost, share of the commanded
    rate_hz: float = 50.0
    rpm_noise: float = 50.0  # 1 sigma, rpm
    current_noise_a: float = 0.1  # 1 sigma


@dataclass(frozen=True)
class MotorConstants:
    """One rotor's thrust -> speed and load current, for a vehicle preset."""

    full_scale_n: float
    rpm_at_full_scale: float
    torque_per_thrust_m: float  # k_Q / k_T
    torque_constant_nm_per_a: float  # K_t
    no_load_current_a: float
    time_constant_s: float
    min_thrust_n: float | None
    max_thrust_n: float | None

    @classmethod
    def for_vehicle(cls, vehicle: VehicleParams, params: EscParams | None = None) -> "MotorConstants":
        p = params or EscParams()
        return cls(vehicle.full_scale_thrust_n, p.rpm_at_full_scale, vehicle.yaw_moment_per_thrust_m,
                   60.0 / (2.0 * math.pi * p.kv_rpm_per_v), p.no_load_current_a, vehicle.motor_time_constant_s,
                   vehicle.rotor_min_thrust_n, vehicle.rotor_max_thrust_n)

    def rpm(self, thrust_n) -> np.ndarray:
        """Speed (rpm, negative = reversed) of a healthy rotor making `thrust_n` (a number or an array)."""
        t = np.asarray(thrust_n, dtype=float)
        return np.sign(t) * self.rpm_at_full_scale * np.sqrt(np.abs(t) / self.full_scale_n)

    def load_current_a(self, thrust_n) -> np.ndarray:
        """The current a healthy rotor's aerodynamic torque draws at `thrust_n` (without the no-load current)."""
        return self.torque_per_thrust_m * np.abs(np.asarray(thrust_n, dtype=float)) / self.torque_constant_nm_per_a

    def clamp(self, commands_n: np.ndarray) -> np.ndarray:
        """What the motor is driven towards: non-finite -> 0, within the rotor's thrust limits."""
        c = np.where(np.isfinite(commands_n), commands_n, 0.0)
        lo = -math.inf if self.min_thrust_n is None else self.min_thrust_n
        hi = math.inf if self.max_thrust_n is None else self.max_thrust_n
        return np.clip(c, lo, hi)

    def lag(self, state_n: np.ndarray, setpoint_n: np.ndarray, dt_s: float) -> np.ndarray:
        """The first-order lag over dt_s (exact for a setpoint held over it, as the world's motors)."""
        if self.time_constant_s <= 0.0:
            return np.array(setpoint_n, dtype=float)
        alpha = 1.0 - math.exp(-dt_s / self.time_constant_s)
        return state_n + alpha * (setpoint_n - state_n)


class EscSensor:
    """A unit's four ESCs: `sample(t_s, commands_n, eta)` once per control step, before the step's command
    (what the motors did over the last period); returns an EscSample when one is due (at `rate_hz`), else None.
    `set_kind` records a fault's kind per rotor; `fail` the telemetry's own failure ("off", "stuck", "ok")."""

    def __init__(self, constants: MotorConstants, params: EscParams | None = None, seed: int = 0,
                 unit_id: int = 1, noise: bool = True) -> None:
        # (equal constants and parameters as one object each: `sample_steady` batches the sensors that share them)
        self.constants = _SHARED.setdefault(constants, constants)
        self.params = _SHARED.setdefault(params or EscParams(), params or EscParams())
        self.rng = np.random.default_rng([int(seed), int(unit_id), 0xE5C])
        self.noise = noise
        self.kind = ["eta"] * ROTORS_PER_UNIT
        self._speed = [0.0] * ROTORS_PER_UNIT  # each motor's speed, as the thrust a whole prop makes at it
        self.failure = "ok"
        self._held: EscSample | None = None
        self._t_last: float | None = None
        self._next_s = -math.inf
        # (every control step runs the motors' lag on four plain floats: numpy's per-call cost on arrays of
        # four was most of a flight's sensors stage; the same IEEE operations, so the same numbers)
        self._lo = -math.inf if constants.min_thrust_n is None else constants.min_thrust_n
        self._hi = math.inf if constants.max_thrust_n is None else constants.max_thrust_n
        self._alpha_of: tuple[float, float] = (math.nan, 1.0)  # (dt, the lag's alpha over it)

    @property
    def speed_n(self) -> np.ndarray:
        """Each motor's speed, as the thrust a whole propeller makes at it (N)."""
        return np.array(self._speed)

    def set_kind(self, rotor: int, kind: str) -> None:
        """A fault's kind on rotor 1..4 (0 = all four)."""
        for r in range(ROTORS_PER_UNIT) if rotor == 0 else [rotor - 1]:
            self.kind[r] = kind

    def fail(self, kind: str) -> None:
        self.failure = kind

    def _alpha(self, dt_s: float) -> float:
        """MotorConstants.lag's alpha over dt_s (kept for the last dt: the control period repeats)."""
        if dt_s != self._alpha_of[0]:
            tau = self.constants.time_constant_s
            self._alpha_of = (dt_s, 1.0 if tau <= 0.0 else 1.0 - math.exp(-dt_s / tau))
        return self._alpha_of[1]

    def sample(self, t_s: float, commands_n: np.ndarray, eta: np.ndarray) -> EscSample | None:
        c = self.constants
        dt = 0.0 if self._t_last is None else max(t_s - self._t_last, 0.0)
        self._t_last = t_s
        etas = eta.tolist() if isinstance(eta, np.ndarray) else [float(e) for e in eta]
        commands = commands_n.tolist() if isinstance(commands_n, np.ndarray) else [float(x) for x in commands_n]
        kind = self.kind
        # eta 0 of the default kind is a motor off (firmware_models.motor): the ESC sees it stopped
        # (the usual step: every rotor of the default kind and eta > 0, none stopped: judged at once)
        if kind == _ALL_ETA and min(etas) > 0.0:
            stopped = _NONE_STOPPED
        else:
            stopped = [k == "motor-stop" or (k == "eta" and e <= 0.0) for k, e in zip(kind, etas)]
        alpha, lo, hi, speed = self._alpha(dt), self._lo, self._hi, self._speed
        if c.time_constant_s > 0.0 and stopped is _NONE_STOPPED and math.isfinite(sum(commands)):
            # MotorConstants.clamp, then .lag, on four finite commands (the same operations as below)
            s0, s1, s2, s3 = speed
            x0, x1, x2, x3 = commands
            speed[0] = s0 + alpha * (min(max(x0, lo), hi) - s0)
            speed[1] = s1 + alpha * (min(max(x1, lo), hi) - s1)
            speed[2] = s2 + alpha * (min(max(x2, lo), hi) - s2)
            speed[3] = s3 + alpha * (min(max(x3, lo), hi) - s3)
        else:
            lagged = c.time_constant_s > 0.0
            for i in range(ROTORS_PER_UNIT):  # MotorConstants.clamp, then .lag, on each motor
                x = commands[i]
                setpoint = 0.0 if stopped[i] else min(max(x if math.isfinite(x) else 0.0, lo), hi)
                speed[i] = speed[i] + alpha * (setpoint - speed[i]) if lagged else setpoint
        if t_s < self._next_s - 1e-9 or self.failure == "off":
            return None
        self._next_s = max(self._next_s + 1.0 / self.params.rate_hz, t_s)
        if self.failure == "stuck" and self._held is not None:
            return EscSample(t_s, self._held.rpm, self._held.current_a)
        # (MotorConstants.rpm and .load_current_a, on four floats; the noise of all eight values drawn at once:
        # `normal(0, sigma, 4)` twice is sigma times the same eight standard normals, the same numbers)
        p = self.params
        rpm_fs, fs, per_a, kt = c.rpm_at_full_scale, c.full_scale_n, c.torque_per_thrust_m, c.torque_constant_nm_per_a
        i0, sqrt, over_p = c.no_load_current_a, math.sqrt, p.overspeed_unloaded
        z = self.rng.standard_normal(2 * ROTORS_PER_UNIT).tolist() if self.noise else None
        rpm_sigma, amp_sigma = p.rpm_noise, p.current_noise_a
        rpm, current = [], []
        for i in range(ROTORS_PER_UNIT):
            x = speed[i]
            lost = 1.0 - min(max(etas[i], 0.0), 1.0)
            sign = (x > 0.0) - (x < 0.0)
            over = over_p if kind[i] == "prop-loss" else 0.0
            r = sign * rpm_fs * sqrt(abs(x) / fs) * (1.0 + over * lost)
            a = 0.0 if stopped[i] else i0 + (1.0 - lost) * (per_a * abs(x) / kt)
            if z is not None:  # (a stopped motor reports no noise)
                r = r + rpm_sigma * z[i] * (1.0 if r != 0.0 else 0.0)
                a = a + amp_sigma * z[ROTORS_PER_UNIT + i] * (1.0 if a != 0.0 else 0.0)
            rpm.append(r)
            current.append(0.0 if 0.0 > a else a)  # (max(a, 0.0))
        self._held = wire_esc(t_s, rpm, current)
        return self._held


#: `EscSensor.sample`'s usual step: every rotor of the default fault kind, none stopped
_ALL_ETA = ["eta"] * ROTORS_PER_UNIT
_NONE_STOPPED = [False] * ROTORS_PER_UNIT


def sample_steady(sensors: list[EscSensor], t_s: float, commands_n: np.ndarray,
                  eta: np.ndarray) -> list[EscSample | None] | None:
    """`EscSensor.sample` of several units' ESCs at one step, as arrays: what the in-process engine calls
    for every unit at once (mars_link.flight.engine.InProcessUnits). Why: per unit, the sample is a few
    dozen float operations, and Python's per-call cost on them was the largest part of a flight's sensors
    stage; here each operation runs once over every rotor. The same IEEE operations in the same order
    as `sample` (numpy's elementwise +, -, *, /, sqrt and rounding are those of Python's floats), each
    sensor's own random stream and state: the same samples, bit for bit (tests/engine/test_engine_batched.py).

    Only for the usual step: every sensor with the same constants, parameters, noise and last sample
    time, telemetry healthy, every rotor of the default fault kind and eta > 0, and finite `commands_n`
    (units x 4, N). Returns None (nothing changed) otherwise: the caller samples unit by unit."""
    first = sensors[0]
    c, p = first.constants, first.params
    t_last = first._t_last
    for s in sensors:
        if (s.constants is not c or s.params is not p or s.noise != first.noise or s._t_last != t_last
                or s.failure != "ok" or s.kind != _ALL_ETA):
            return None
    if not (eta.min() > 0.0) or not np.isfinite(commands_n).all():
        return None
    setpoint = np.minimum(np.maximum(commands_n, first._lo), first._hi)
    if c.time_constant_s > 0.0:  # (else the speed is the setpoint at once)
        alpha = first._alpha(0.0 if t_last is None else max(t_s - t_last, 0.0))
        speed = np.array([s._speed for s in sensors])
        speed = speed + alpha * (setpoint - speed)
    else:
        speed = setpoint
    rows = speed.tolist()
    out: list[EscSample | None] = [None] * len(sensors)
    due = []
    for k, s in enumerate(sensors):
        s._speed[:] = rows[k]
        s._t_last = t_s
        if not t_s < s._next_s - 1e-9:
            s._next_s = max(s._next_s + 1.0 / p.rate_hz, t_s)
            due.append(k)
    if not due:
        return out
    x = speed[due] if len(due) < len(sensors) else speed
    lost = 1.0 - np.minimum(np.maximum(eta[due] if len(due) < len(sensors) else eta, 0.0), 1.0)
    # (`sample`'s r = sign * rpm_fs * sqrt(|x| / fs) * (1 + 0 * lost): the default kind's factor is 1.0 exactly)
    rpm = np.sign(x) * c.rpm_at_full_scale * np.sqrt(np.abs(x) / c.full_scale_n)
    amps = c.no_load_current_a + (1.0 - lost) * (c.torque_per_thrust_m * np.abs(x) / c.torque_constant_nm_per_a)
    if first.noise:  # each unit's own stream, drawn as `sample` draws it
        z = np.array([sensors[k].rng.standard_normal(2 * ROTORS_PER_UNIT) for k in due])
        rpm = rpm + p.rpm_noise * z[:, :ROTORS_PER_UNIT] * (rpm != 0.0)
        amps = amps + p.current_noise_a * z[:, ROTORS_PER_UNIT:] * (amps != 0.0)
    amps = np.where(amps < 0.0, 0.0, amps)
    whole = np.rint(rpm)  # (`wire_esc`: round half to even, as Python's round)
    if not (np.abs(whole) < _INT32_MAX).all():
        return _sample_each(sensors, due, out, t_s, rpm, amps)
    t_wire = wire_time(t_s)
    for k, rpm_k, amps_k in zip(due, whole.astype(np.int64).tolist(), amps.astype(np.float32).tolist()):
        sensors[k]._held = out[k] = EscSample(t_wire, tuple(rpm_k), tuple(amps_k))
    return out


def _sample_each(sensors: list[EscSensor], due: list[int], out: list, t_s: float, rpm: np.ndarray,
                 amps: np.ndarray) -> list[EscSample | None]:
    """The rare values beyond int32 rpm: quantised one by one (`wire_esc` clamps them)."""
    for row, k in enumerate(due):
        sensors[k]._held = out[k] = wire_esc(t_s, rpm[row], amps[row])
    return out
