"""The HIL link (lockstep sensors in, actuator controls out) and its in-process twin (message objects)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle_modes import MODE_OFFBOARD
from mars_link.core.messages import ActuatorOutput, EscSample, RotorCommand, SensorPacket, wire_thrust
from mars_link.core.state import ImuSample, RigidBodyState
from mars_link.mavlink.esc_status import esc_status_message
from mars_link.mavlink.wire import (BARO_FIELDS, MAG_FIELDS, SensorFrames, battery_from_message, battery_report_message,
                            hil_state_from_fields, latch_from_message, latch_message, latches_open,
                            sensor_packet_messages)
from firmware_models.vehicle_links import Link, Outgoing, finite as _finite
from mars_link.mavlink.wire import SensorFrameAssembler

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle


class HilService:
    """The HIL link and its in-process twin: a lockstep step's sensors in, its motor outputs out. Owns the
    lockstep state: the sensor frames being assembled, the step waiting for its answer (and one received
    for a host's engine to take), the times of the coordinator's last command and step skip, whether the
    unit waits for the coordinator, and a battery sample waiting for its IMU frame. Asks of the vehicle:
    its links and `_pack`, state and `set_state`, the intake and motors, the control step and watchdogs,
    the sensor failures, ESCs and battery, the deferred work, `stats`, `_count`, `_drop`. In-process
    flights call it every step: each method looks the vehicle up once."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.assembler = SensorFrameAssembler()  # HIL_SENSOR/ODOMETRY/HIL_GPS -> one step's SensorFrames
        self.battery_pending = None  # a BATTERY_STATUS from the world, measured with the next IMU frame
        self.pending: tuple[int, str] | None = None  # (time_usec, link) of an unanswered HIL step
        self.received_step: tuple | None = None  # (SensorFrames, time_usec, link) of a HIL step not taken yet
        self.last_rotor_usec: int | None = None  # time of the last accepted coordinator command
        self.step_skipped_usec: int | None = None  # the last step the coordinator said it sends no command for
        self.await_coordinator = vehicle.config.hil_await_coordinator

    # ----------------------------------------------------------------- HIL link (lockstep)
    def on_hil(self, msg, t: str, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if t == "HIL_STATE_QUATERNION":
            if v.defer_own_state:
                v._deferred.append(lambda: self._apply_state(msg))
            else:
                self._apply_state(msg)
            return
        if t == "NAMED_VALUE_INT":
            mask = latch_from_message(msg)
            if mask is None:
                v._count(f"ignored.{t}")
                return
            v.latches = mask  # the latch sensor, forwarded to the coordinator before this step's IMU frame
            for name, other in v.links.items():
                if other.policy.forward_sensors:
                    out.append(Outgoing(name, v._pack(other, latch_message(msg.time_boot_ms / 1000.0, mask))))
            return
        if t == "BATTERY_STATUS":  # the power module's sample, measured with this step's IMU frame (its time)
            sample = battery_from_message(msg)
            if sample is None:
                v._drop("hil_bad_battery")
            self.battery_pending = sample
            return
        if t not in ("HIL_SENSOR", "ODOMETRY", "HIL_GPS"):
            v._count(f"ignored.{t}")
            return
        if t == "HIL_GPS":  # integer fields: always finite; kept with its packet's IMU frame
            self.assembler.feed_frames(msg)
            return
        values = ([msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro, msg.zgyro, msg.xmag, msg.ymag, msg.zmag,
                   msg.abs_pressure, msg.pressure_alt] if t == "HIL_SENSOR"
                  else [msg.x, msg.y, msg.z, *msg.q, msg.vx, msg.vy, msg.vz])
        if not _finite(*values):
            v._drop("hil_non_finite")
            return
        frames = self.assembler.feed_frames(msg)
        if frames is None:
            return
        if v.hil_stepped_by_host:  # the host's engine takes the step (take_step), in its order
            self.received_step = (frames, int(msg.time_usec), lk.name)
            return
        self._take_frames(frames, int(msg.time_usec), lk.name, out)
        if self.await_coordinator and int(msg.time_usec) not in (self.last_rotor_usec, self.step_skipped_usec):
            return  # answered when the coordinator's command for this step arrives (or on release); one that
            # came before its sensors (another link, read first) answers it now
        self.answer(out)

    def _take_frames(self, frames: SensorFrames, time_usec: int, link: str, out: list[Outgoing]) -> None:
        """A HIL step's sensors into the unit: due sensor failures, the battery measured, the sensors
        forwarded to the coordinator, the unit's own state (now or deferred); the step is then pending."""
        v = self.v
        if v._scheduled_sensor_failures:
            v._sensor_failures_due(frames.imu.time_usec / 1e6)
        forward = [name for name, other in v.links.items() if other.policy.forward_sensors]
        esc = v._esc_sample(frames.imu.time_usec / 1e6)  # (every step: its noise draws as in-process)
        report = None
        if self.battery_pending is not None:
            report = v._measure_battery(self.battery_pending, frames.imu.time_usec / 1e6)
            self.battery_pending = None
        flags = frames.imu.fields_updated
        if flags & (BARO_FIELDS | MAG_FIELDS):
            v.sensor_failures.note_carried(flags & BARO_FIELDS == BARO_FIELDS, flags & MAG_FIELDS == MAG_FIELDS)
        if forward:  # (on the real-time path: straight from the received fields, unless a sensor failed)
            if v.sensor_failures.any:  # the failed sensors' packet (sensor_failures)
                upstream = sensor_packet_messages(v.sensor_failures.apply(frames.packet()), upstream=True)
            else:
                upstream = frames.upstream_messages()
            if report is not None:  # before the IMU frame: the coordinator attaches it to this packet
                upstream.insert(0, battery_report_message(report))
            if esc is not None:  # (likewise)
                upstream.insert(0, esc_status_message(esc))
            for name in forward:
                other = v.links[name]
                out.extend(Outgoing(name, v._pack(other, m)) for m in upstream)
        if v.defer_own_state:
            v._deferred.append(lambda: self._apply_sensors(frames))
        else:
            self._apply_sensors(frames)
        # lockstep: the sensor time stamps the step; answer with the motor outputs for it
        t_s = frames.imu.time_usec / 1e6
        v.sim_s = t_s
        v._next_control = t_s + v.control_dt_s
        self.pending = (time_usec, link)

    # ----------------------------------------------------------------- HIL steps taken by a host's engine
    # With the vehicle's `hil_stepped_by_host` the frame handlers only receive: a HIL step's sensors wait in
    # `received`, the coordinator's command (or its step skip) in the intake, and the host's engine
    # (mars_link.processes.engine_links.HostedFirmware) runs the stages in the engine's order.
    @property
    def received(self) -> SensorFrames | None:
        """The sensor frames of a HIL step received and not taken yet."""
        return None if self.received_step is None else self.received_step[0]

    def take_step(self) -> list[Outgoing]:
        """The sensors stage of the received HIL step; returns the telemetry to send (to the coordinator)."""
        out: list[Outgoing] = []
        if self.received_step is not None:
            frames, time_usec, link = self.received_step
            self.received_step = None
            self._take_frames(frames, time_usec, link, out)
        return out

    @property
    def command_in(self) -> bool:
        """The pending HIL step may be answered: the unit does not wait for the coordinator, or its command
        for the step (or its step skip) is in."""
        pending = self.pending
        return pending is not None and (not self.await_coordinator
                                        or pending[0] in (self.last_rotor_usec, self.step_skipped_usec))

    def answer_step(self) -> list[Outgoing]:
        """The motors stage: the pending HIL step's motor outputs (HIL_ACTUATOR_CONTROLS)."""
        out: list[Outgoing] = []
        if self.pending is not None:
            self.answer(out)
        return out

    def _apply_state(self, msg) -> None:
        """HIL_STATE_QUATERNION: the unit centre's ground truth, for its own telemetry and checks."""
        v = self.v
        q = np.array(msg.attitude_quaternion, dtype=float)
        values = [*q, msg.rollspeed, msg.pitchspeed, msg.yawspeed]
        if not _finite(*values) or not 0.5 < np.linalg.norm(q) < 1.5:
            v._drop("hil_non_finite")
            return
        v.set_state(hil_state_from_fields(msg.time_usec, q, values[4:], msg.lat, msg.lon, msg.alt, msg.vx, msg.vy,
                                          msg.vz))

    def _apply_sensors(self, frames: SensorFrames) -> None:
        v = self.v
        packet = frames.packet()
        v.imu = ImuSample(packet.t_s, v.sysid, packet.imu.gyro_frd_radps, packet.imu.accel_frd_mps2)
        if packet.truth is not None:
            v.set_state(packet.truth)

    def answer(self, out: list[Outgoing]) -> None:
        v = self.v
        time_usec, name = self.pending
        self.pending = None
        if v.config.hil_await_coordinator:  # (lockstep: the watchdogs judged at each step in sim time too,
            v._watchdogs()  # not only on the wall-clock tick: a step's outcome never hangs on when it ticked)
        lk = v.links[name]
        sp = self._motor_setpoint_n() / v.full_scale_n
        mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if v.armed else 0)
        controls = [float(x) for x in sp] + [latches_open(v.latch_setpoint)] + [0.0] * 11
        out.append(Outgoing(lk.name, v._pack(lk, mavlink.MAVLink_hil_actuator_controls_message(
            time_usec, controls, mode, 1))))

    def _failure_due(self) -> bool:
        """A scenario fault scheduled in the motor model is due at this step."""
        v = self.v
        f = v._scheduled_failures
        return bool(f) and f[0][0] <= v.sim_s + 1e-9

    def _motor_setpoint_n(self) -> np.ndarray:
        """One HIL step's motor outputs (N): due scenario faults enter the motor model, the control step
        runs, and the motors are driven to the clamped, eta-scaled command."""
        v = self.v
        while self._failure_due():
            _, rotor, eta, kind = v._scheduled_failures.pop(0)
            v.inject_failure(rotor, eta, kind)
        stats = v.stats  # (_count, inlined: every step)
        stats["hil_steps"] = stats.get("hil_steps", 0) + 1
        v._control_step()
        if v.ulog is not None:
            v._ulog_sample()
        if not v.armed:
            return v.motors.setpoint(np.zeros(4))
        cmd = v.motor_commands_n  # the intake's held command is finite and of 4 values (rotor_intake.accept)
        return v.motors.setpoint(cmd, checked=cmd is v.intake.thrusts_n)

    # ================================================================= in-process messages
    # The same steps as the HIL and coordinator links, with the messages as objects instead of MAVLink
    # bytes: what the in-process engine calls. The values are already at wire precision (float32,
    # microseconds), so a unit driven this way moves its motors exactly as over MAVLink.
    def take_sensors(self, packet: SensorPacket, unit_truth: RigidBodyState | None = None,
                     esc_sampled: bool = False, esc: EscSample | None = None) -> SensorPacket:
        """A HIL step: the unit's sensors (HIL_SENSOR/ODOMETRY) and, when given, its centre's truth
        (HIL_STATE_QUATERNION). Returns the telemetry it forwards to the coordinator (HIGHRES_IMU and
        ODOMETRY carry exactly these fields). `esc_sampled`: the step's ESC sample is `esc`, already taken
        with every unit's at once (mars_link.models.esc.sample_steady)."""
        v = self.v
        if unit_truth is not None:
            v.set_state(unit_truth)
        if v._scheduled_sensor_failures:
            v._sensor_failures_due(packet.t_s)
        failures = v.sensor_failures
        if packet.baro is not None or packet.mag is not None:
            failures.note_carried(packet.baro is not None, packet.mag is not None)
        if failures.active:  # (failures.any without the property call: every unit, every step)
            packet = failures.apply(packet)
        v.latches = packet.latches
        v.imu = packet.imu
        if packet.truth is not None:
            v.set_state(packet.truth)
        v.sim_s = packet.t_s
        v._next_control = packet.t_s + v.control_dt_s
        if not esc_sampled:
            esc = v._esc_sample(packet.t_s)
        if packet.battery is not None:  # forwarded with the unit's remaining-charge estimate
            return packet.replaced(battery=v._measure_battery(packet.battery, packet.t_s), esc=esc)
        return packet if esc is None else packet.replaced(esc=esc)

    def take_rotor_command(self, cmd: RotorCommand) -> bool:
        """A coordinator command (SET_ACTUATOR_CONTROL_TARGET's values); True if it is now held."""
        v = self.v
        if cmd.unit_id != v.sysid:
            return v.intake.drop("wrong_target")
        return self._accept_rotor_command(cmd)

    def _accept_rotor_command(self, cmd: RotorCommand) -> bool:
        """The intake's checks on a command addressed to this unit; True if it is now held."""
        v = self.v
        # cmd.thrusts_n are wire values (float32 controls x full scale): x / full scale is the control back
        s = v.full_scale_n
        a, b, c, d = cmd.thrusts_n.tolist()
        t_usec = round(cmd.t_s * 1e6)
        if not v.intake.accept(a / s, b / s, c / s, d / s, t_usec, v.sim_s, cmd.thrusts_n):
            return False
        self._note_rotor_command(t_usec, cmd.latch_setpoint)
        return True

    def _note_rotor_command(self, t_usec: int, latch_setpoint: int) -> None:
        v = self.v
        stats = v.stats  # (_count, inlined: every step)
        stats["rotor_commands"] = stats.get("rotor_commands", 0) + 1
        self.last_rotor_usec = t_usec
        v.latch_setpoint = latch_setpoint

    def drive_steady(self, thrusts_n: np.ndarray, least: float, greatest: float, t_usec: int,
                     latch_setpoint: int) -> bool | None:
        """`take_rotor_command` then `drive_motors`, batched by the in-process engine (InProcessUnits.drive)
        for a unit in the steady state: armed, OFFBOARD under the coordinator, motors that pass a command as
        it is, no scheduled fault due. It takes the command's wire thrusts (all four known finite), bounds
        on its controls (RotorIntake.accept_bounded) and its wire time, and makes the same checks and state
        changes.
        True: the command is held and is this step's motor setpoint as it is. False: the intake dropped it
        (counted); the caller takes `drive_motors`' answer, as after any dropped command. None: the unit is
        not in the steady state and nothing changed; the caller takes the general path."""
        v = self.v
        f = v._scheduled_failures
        if not (v.armed and v.source == "coordinator" and v.mode == MODE_OFFBOARD and v.motors.plain
                and not (f and f[0][0] <= v.sim_s + 1e-9)):  # (_failure_due, inlined: every unit, every step)
            return None
        if not v.intake.accept_bounded(least, greatest, t_usec, v.sim_s, thrusts_n):
            return False
        self._note_rotor_command(t_usec, latch_setpoint)
        stats = v.stats
        stats["hil_steps"] = stats.get("hil_steps", 0) + 1  # (_motor_setpoint_n's count)
        v._drive_from_coordinator(thrusts_n)
        if v.ulog is not None:
            v._ulog_sample()
        return True

    def drive_motors(self) -> ActuatorOutput:
        """The HIL answer (HIL_ACTUATOR_CONTROLS' values): what the motors are driven to for this step."""
        v = self.v
        sp = self._motor_setpoint_n()
        if sp is not v.intake.thrusts_n:  # (the held command itself is at wire precision already)
            sp = wire_thrust(sp, v.full_scale_n)
        return ActuatorOutput(v.sim_s, v.sysid, sp, v.latch_setpoint)
