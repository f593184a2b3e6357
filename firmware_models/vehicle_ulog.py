"""A vehicle's ULog: what one unit's firmware or the assembly vehicle logs, under PX4's topic names.

`VehicleUlog(vehicle, UlogConfig(path))` opens the file and writes the definitions; the vehicle calls
`sample()` once per control step (the recorder keeps the topics' rates, in simulated time) and `text()`
for each STATUSTEXT (a logged string, so failure events, detections and reallocations are in the log);
`close()` at the end. Time stamps are microseconds of simulated time, as PX4 SITL in lockstep logs them.

What is logged comes from the vehicle as it is (`firmware_models.vehicle.Vehicle` and its subclass
`mars_link.vehicles.assembly_vehicle.AssemblyVehicle`): its state (a unit's from the simulator's
HIL_STATE_QUATERNION, the assembly's from its estimator) as vehicle_local_position, vehicle_attitude,
vehicle_angular_velocity and vehicle_global_position; its guidance reference as
vehicle_local_position_setpoint; its IMU as sensor_combined; its rotor commands as actuator_motors and
actuator_outputs; mode and arming as vehicle_status; its pack as battery_status; and the rotors known to
have failed (a unit: its motor model's injected faults; the assembly: the coordinator's believed
efficiencies) as failure_detector_status plus one logged string per change.

Never flight-critical: the file is a `mars_link.logs.outputs.SafeWriter` with a size cap; a write error
(a full disk) or the cap stops this log with a reason (`status()`, and a STATUSTEXT through the vehicle's
`notify`), and every later call does nothing. Nothing here raises into the flight: an unexpected error
while sampling stops the log the same way.
"""

from __future__ import annotations

import math
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_models import px4_topics as T
from mars_link.logs.ulog import LEVEL_INFO, LEVEL_WARNING, UlogWriter

#: per .ulg file; then that log stops (one STATUSTEXT), the flight goes on
ULOG_MAX_BYTES = 200 * 2**20
SYNC_PERIOD_S = 1.0
SYS_NAME = "mars-link"
VER_HW = "MARS_LINK_SITL"
#: overrides the commit written as ver_sw (e.g. set once by a launcher for its child processes)
COMMIT_ENV = "MARS_LINK_COMMIT"


@dataclass
class UlogConfig:
    path: str | os.PathLike
    # state, IMU and actuator topics, per second of simulated time (PX4's default logging profile: 10-20 Hz)
    rate_hz: float = 25.0
    status_hz: float = 2.0  # vehicle_status, battery_status, failure_detector_status (and at once on a change)
    max_bytes: int | None = ULOG_MAX_BYTES
    # a thread of its own writes the file (SafeWriter background): for a unit process's real-time path
    background: bool = False

    def checked(self) -> "UlogConfig":
        from mars_link.core.errors import UserInputError

        for name in ("rate_hz", "status_hz"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.1 <= v <= 1000.0):
                raise UserInputError(f"ULog {name} must be 0.1..1000, got {v!r}")
        return self


_commit: str | None = None


def software_version() -> str:
    """The commit this code runs from ($MARS_LINK_COMMIT, else git), else the package version."""
    global _commit
    if _commit is None:
        import mars_link

        _commit = os.environ.get(COMMIT_ENV) or ""
        if not _commit:
            try:
                done = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=Path(mars_link.__file__).parent,
                                      capture_output=True, text=True, timeout=2.0)
                _commit = done.stdout.strip() if done.returncode == 0 else ""
            except (OSError, subprocess.SubprocessError):
                _commit = ""
        _commit = _commit or mars_link.__version__
    return _commit


def _usec(t_s: float) -> int:
    return max(0, int(round(t_s * 1e6)))


class VehicleUlog:
    """One vehicle's .ulg (see the module docstring)."""

    def __init__(self, vehicle, config: UlogConfig, role: str | None = None) -> None:
        from mars_link.logs.outputs import SafeWriter

        self.config = config.checked()
        self.path = Path(config.path)
        self.vehicle = vehicle
        self._period_us = int(1e6 / config.rate_hz)
        self._status_period_us = int(1e6 / config.status_hz)
        self._next_us = 0
        self._next_status_us = 0
        self._next_sync_us = 0
        self._last_status: tuple | None = None
        self._failed_seen: tuple = ()  # the rotors (0-based) last logged as failed
        self._param_values: dict[str, float] = {}
        self._last_battery_remaining: float | None = None
        self._params_version = None
        self._armed_us = 0
        self._takeoff_us = 0
        self._nav_since_us = 0
        self.samples = 0
        self._error: str | None = None
        self._sink: SafeWriter | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            f = open(self.path, "wb")  # (buffered: one write() per 8 kB; an error surfaces at a flush, stopping the log)
        except OSError as exc:
            self._error = f"{self.path.name}: {exc.strerror or exc} (logging stopped)"
            self._notify(self._error)
            return
        self._sink = SafeWriter(f, str(self.path), max_bytes=config.max_bytes, background=config.background,
                                on_stop=self._notify)
        self.role = role or ("assembly" if hasattr(vehicle, "believed_eta") else "unit")
        self._guarded(self._write_definitions)

    # ------------------------------------------------------------------ public
    @property
    def active(self) -> bool:
        return self._sink is not None and self._sink.active and self._error is None

    def due(self, t_s: float) -> bool:
        """Whether a sample at `t_s` would be written (the state topics' rate): the vehicle skips the call."""
        return self.active and _usec(t_s) >= self._next_us

    def sample(self, t_s: float) -> None:
        """The vehicle's topics at simulated time `t_s` (those due at their rates)."""
        if self.active:
            self._guarded(self._sample, _usec(t_s))

    def text(self, severity: int, message: str, t_s: float) -> None:
        """A logged string (MAVLink severity 0..7 = ULog level)."""
        if self.active:
            self._guarded(self.writer.text, severity, _usec(t_s), message)

    def flush(self) -> None:
        if self._sink is not None:
            self._sink.flush()

    def close(self) -> None:
        if self._sink is not None:
            self._sink.close()

    def status(self) -> dict:
        """{"file", "stopped_reason", "errors", "dropped_writes", "samples"}: a summary's account of this log."""
        if self._sink is None:
            return {"file": self.path.name, "stopped_reason": self._error, "errors": 1, "dropped_writes": 0,
                    "samples": 0}
        out = self._sink.status()
        out["stopped_reason"] = out["stopped_reason"] or self._error
        out["samples"] = self.samples
        return out

    @property
    def stopped_reason(self) -> str | None:
        return self.status()["stopped_reason"]

    # ------------------------------------------------------------------ internals
    def _notify(self, reason: str) -> None:
        notify = getattr(self.vehicle, "notify", None)
        if notify is not None:
            notify(f"ULog stopped: {reason}"[:50])

    def _guarded(self, fn, *args) -> None:
        """Run `fn` and write what it logged, in one write; any error stops this log with its reason
        (logging never raises into the flight)."""
        try:
            fn(*args)
            self.writer.commit()
        except Exception as exc:  # noqa: BLE001 (the flight goes on whatever the log's bug)
            self._error = f"{self.path.name}: {type(exc).__name__}: {exc} (logging stopped)"
            if self._sink is not None:
                self._sink.close()
            self._notify(self._error)

    def _write_definitions(self) -> None:
        v = self.vehicle
        t0 = _usec(getattr(v, "sim_s", 0.0))
        assert self._sink is not None
        self.writer = w = UlogWriter(self._sink.write, t0)
        w.batch = True  # (committed by _guarded: one write per sample)
        w.info("sys_name", SYS_NAME)
        w.info("ver_hw", VER_HW)
        w.info("ver_sw", software_version())
        w.info("sys_os_name", os.uname().sysname if hasattr(os, "uname") else os.name)
        w.info("sys_uuid", f"MARS{self.role.upper()}{v.sysid:04d}")
        w.info("sys_mars_role", self.role)
        w.info("time_ref_utc", 0, "int32_t")  # time stamps are simulated time; UTC offset 0
        self._write_parameters()
        for topic in T.ALL_TOPICS:
            w.define(topic)
        n = len(self._motor_commands())
        self._actuator_ids = [w.subscribe("actuator_motors", k) for k in range(-(-n // T.MOTORS_PER_INSTANCE))]
        self._output_ids = [w.subscribe("actuator_outputs", k) for k in range(-(-n // T.OUTPUTS_PER_INSTANCE))]
        self._failure_ids = [w.subscribe("failure_detector_status", k) for k in range(-(-n // T.FAILURE_MASK_BITS))]
        names = ("vehicle_local_position", "vehicle_local_position_setpoint", "vehicle_attitude",
                 "vehicle_angular_velocity", "vehicle_global_position", "sensor_combined", "vehicle_status",
                 "battery_status")
        self._id = {name: w.subscribe(name) for name in names}
        w.text(LEVEL_INFO, t0, f"{SYS_NAME} {self.role} {v.sysid}: logging started")

    def _write_parameters(self) -> None:
        from firmware_models.params import INT32

        params = getattr(self.vehicle, "params", None)
        if params is None:
            return
        for spec in params.specs:  # (all at first; then those changed, in the data section)
            value = params[spec.name]
            if self._param_values.get(spec.name) != value:
                self._param_values[spec.name] = value
                self.writer.parameter(spec.name, value, spec.kind == INT32)
        self._params_version = params.version

    def _motor_commands(self) -> np.ndarray:
        v = self.vehicle
        thrusts = getattr(v, "rotor_thrusts_n", None)
        cmd = thrusts() if thrusts is not None else (v.motor_commands_n if v.armed else np.zeros(len(v.motor_commands_n)))
        return np.asarray(cmd, dtype=float)

    def _failed_eta(self) -> np.ndarray:
        """Each rotor's efficiency as this vehicle knows it: the assembly's coordinator's belief
        (`believed_eta`), a unit's motor model (the faults injected into it)."""
        v = self.vehicle
        believed = getattr(v, "believed_eta", None)
        return np.asarray(v.motors.eta if believed is None else believed(), dtype=float)

    def _sample(self, t_us: int) -> None:
        w, v, ids = self.writer, self.vehicle, self._id
        self._status_step(t_us)
        if t_us < self._next_us:
            return
        self._next_us = max(self._next_us + self._period_us, t_us - self._period_us // 2)
        self.samples += 1
        s = v.state
        if s is not None:
            p, vel, acc, q = s.position_ned_m, s.velocity_ned_mps, s.acceleration_ned_mps2, s.quaternion_wxyz
            sample_us = _usec(s.t_s)
            origin = v.origin
            w.data(ids["vehicle_local_position"], {
                "timestamp": t_us, "timestamp_sample": min(sample_us, t_us),
                "xy_valid": True, "z_valid": True, "v_xy_valid": True, "v_z_valid": True,
                "x": p[0], "y": p[1], "z": p[2], "vx": vel[0], "vy": vel[1], "vz": vel[2], "z_deriv": vel[2],
                "ax": acc[0], "ay": acc[1], "az": acc[2], "heading": _heading(q), "heading_good_for_control": True,
                "xy_global": True, "z_global": True, "ref_timestamp": 0,
                "ref_lat": origin.lat_deg, "ref_lon": origin.lon_deg, "ref_alt": origin.amsl_m,
                "dead_reckoning": False})
            w.data(ids["vehicle_attitude"], {"timestamp": t_us, "timestamp_sample": min(sample_us, t_us), "q": q})
            w.data(ids["vehicle_angular_velocity"], {"timestamp": t_us, "timestamp_sample": min(sample_us, t_us),
                                                     "xyz": s.angular_velocity_frd_radps})
            lat, lon, alt = origin.to_global(p)
            w.data(ids["vehicle_global_position"], {"timestamp": t_us, "timestamp_sample": min(sample_us, t_us),
                                                    "lat": lat, "lon": lon, "alt": alt})
        ref = getattr(getattr(v, "autopilot", None), "reference", None)
        if ref is not None and getattr(v, "source", "own") == "own":
            rp, rv = ref.position_ned_m, ref.velocity_ned_mps
            w.data(ids["vehicle_local_position_setpoint"], {
                "timestamp": t_us, "x": rp[0], "y": rp[1], "z": rp[2], "vx": rv[0], "vy": rv[1], "vz": rv[2],
                "acceleration": ref.acceleration_ned_mps2, "yaw": ref.yaw_rad, "yawspeed": ref.yaw_rate_radps})
        imu = v.imu
        if imu is not None:
            dt_us = self._period_us
            w.data(ids["sensor_combined"], {
                "timestamp": t_us, "gyro_rad": imu.gyro_frd_radps, "gyro_integral_dt": dt_us,
                "accelerometer_timestamp_relative": 0, "accelerometer_m_s2": imu.accel_frd_mps2,
                "accelerometer_integral_dt": dt_us, "accelerometer_clipping": 0, "gyro_clipping": 0})
        self._actuators(t_us)
        if t_us >= self._next_sync_us:
            self._next_sync_us = t_us + int(SYNC_PERIOD_S * 1e6)
            w.sync()

    def _actuators(self, t_us: int) -> None:
        v, w = self.vehicle, self.writer
        full_scale = float(v.full_scale_n)
        control = self._motor_commands() / full_scale
        armed = bool(v.armed)
        for k, msg_id in enumerate(self._actuator_ids):
            part = control[k * T.MOTORS_PER_INSTANCE:(k + 1) * T.MOTORS_PER_INSTANCE]
            values = [float(x) if armed else math.nan for x in part]  # (PX4: NaN = disarmed, and for no motor)
            w.data(msg_id, {"timestamp": t_us, "timestamp_sample": t_us, "control": values})
        outputs = np.clip(control, 0.0, 1.0) if armed else np.zeros(len(control))
        for k, msg_id in enumerate(self._output_ids):
            part = outputs[k * T.OUTPUTS_PER_INSTANCE:(k + 1) * T.OUTPUTS_PER_INSTANCE]
            w.data(msg_id, {"timestamp": t_us, "noutputs": len(part), "output": part})

    def _status_step(self, t_us: int) -> None:
        """vehicle_status, battery_status and failure_detector_status at their rate and at once on a change;
        a logged string for each change of the failed rotors; changed parameters."""
        v, w = self.vehicle, self.writer
        armed = bool(v.armed)
        nav = T.nav_state(*v.mode)
        eta = self._failed_eta()
        failed: tuple[int, ...] = ()
        stopped: tuple[int, ...] = ()
        if eta.min() < 1.0 - 1e-9:  # (not on every step of a healthy flight)
            failed = tuple(int(i) for i in np.flatnonzero(eta < 1.0 - 1e-9))
            stopped = tuple(int(i) for i in np.flatnonzero(eta <= 1e-9))
        key = (armed, nav, failed, stopped)
        if failed != self._failed_seen:
            self._failed_seen = failed
            named = ", ".join(f"{i + 1} eta {eta[i]:.2f}" for i in failed) or "none"
            w.text(LEVEL_WARNING, t_us, f"Rotor failures: {named}")
        if self._last_status is not None and key == self._last_status and t_us < self._next_status_us:
            return
        if self._last_status is None or armed != self._last_status[0]:
            self._armed_us = t_us if armed else self._armed_us
        if self._last_status is None or nav != self._last_status[1]:
            self._nav_since_us = t_us
        if armed and not self._takeoff_us and not getattr(v, "landed", True):
            self._takeoff_us = t_us
        self._last_status = key
        self._next_status_us = t_us + self._status_period_us
        w.data(self._id["vehicle_status"], {
            "timestamp": t_us, "armed_time": self._armed_us if armed else 0, "takeoff_time": self._takeoff_us,
            "arming_state": T.ARMING_STATE_ARMED if armed else T.ARMING_STATE_DISARMED,
            "nav_state_timestamp": self._nav_since_us, "nav_state_user_intention": nav, "nav_state": nav,
            "failure_detector_status": T.FAILURE_MOTOR if failed else 0, "hil_state": T.HIL_STATE_ON,
            "vehicle_type": T.VEHICLE_TYPE_ROTARY_WING, "failsafe": False, "is_vtol": False,
            "in_transition_mode": False, "system_type": T.MAV_TYPE_QUADROTOR, "system_id": v.sysid & 0xFF,
            "component_id": v.compid & 0xFF})
        for k, msg_id in enumerate(self._failure_ids):
            lo, hi = k * T.FAILURE_MASK_BITS, (k + 1) * T.FAILURE_MASK_BITS
            w.data(msg_id, {"timestamp": t_us, "fd_roll": False, "fd_pitch": False, "fd_alt": False, "fd_ext": False,
                            "fd_arm_escs": False, "fd_battery": False, "fd_imbalanced_prop": False,
                            "fd_motor": any(lo <= i < hi for i in failed), "imbalanced_prop_metric": 0.0,
                            "motor_failure_mask": sum(1 << (i - lo) for i in failed if lo <= i < hi),
                            "motor_stop_mask": sum(1 << (i - lo) for i in stopped if lo <= i < hi)})
        b = v.battery
        if math.isfinite(b.voltage_v):
            w.data(self._id["battery_status"], {
                "timestamp": t_us, "connected": True, "voltage_v": b.voltage_v, "current_a": b.current_a,
                "discharged_mah": b.used_c / 3.6, "remaining": b.remaining if math.isfinite(b.remaining) else -1.0,
                "id": 1, "warning": int(b.level)})
        params = getattr(v, "params", None)
        if params is not None and params.version != self._params_version:
            self._write_parameters()


def _heading(q: np.ndarray) -> float:
    """Yaw (rad, -pi..pi) of a body FRD -> NED quaternion (w, x, y, z)."""
    w, x, y, z = (float(c) for c in q)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def attach_ulogs(vehicles: dict, out_dir, name: str = "unit{unit}.ulg", **config) -> list:
    """Start a .ulg for each unit of an in-process flight (`flight.units.vehicles`: unit id -> Vehicle),
    named `name` (with {unit}) in `out_dir`; returns the recorders. `config`: UlogConfig's fields."""
    from pathlib import Path

    out = Path(out_dir)
    return [v.start_ulog(UlogConfig(out / name.format(unit=u), **config)) for u, v in vehicles.items()]


def close_ulogs(vehicles: dict) -> list[dict]:
    """Close every unit's .ulg; their status (file, stopped_reason, errors, ...) for a summary."""
    return [s for s in (v.stop_ulog() for v in vehicles.values()) if s is not None]
