"""The HIL link (lockstep sensors in, actuator controls out) and its in-process twin (message objects).

A mixin of `firmware_models.vehicle.Vehicle`: it uses the Vehicle's state and plumbing (_reply, _text, ...).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle_modes import MODE_OFFBOARD
from mars_link.core.messages import ActuatorOutput, RotorCommand, SensorPacket, wire_thrust
from mars_link.core.state import ImuSample, RigidBodyState
from mars_link.mavlink.esc_status import esc_status_message
from mars_link.mavlink.wire import (BARO_FIELDS, MAG_FIELDS, SensorFrames, battery_from_message, battery_report_message,
                            hil_state_from_fields, latch_from_message, latch_message, latches_open,
                            sensor_packet_messages)
from firmware_models.vehicle_links import Link, Outgoing, finite as _finite


class HilMixin:
    # ----------------------------------------------------------------- HIL link (lockstep)
    def _on_hil(self, msg, t: str, lk: Link, out: list[Outgoing]) -> None:
        if t == "HIL_STATE_QUATERNION":
            if self.defer_own_state:
                self._deferred.append(lambda: self._apply_hil_state(msg))
            else:
                self._apply_hil_state(msg)
            return
        if t == "NAMED_VALUE_INT":
            mask = latch_from_message(msg)
            if mask is None:
                self._count(f"ignored.{t}")
                return
            self.latches = mask  # the latch sensor, forwarded to the coordinator before this step's IMU frame
            for name, other in self.links.items():
                if other.policy.forward_sensors:
                    out.append(Outgoing(name, self._pack(other, latch_message(msg.time_boot_ms / 1000.0, mask))))
            return
        if t == "BATTERY_STATUS":  # the power module's sample, measured with this step's IMU frame (its time)
            sample = battery_from_message(msg)
            if sample is None:
                self._drop("hil_bad_battery")
            self._battery_pending = sample
            return
        if t not in ("HIL_SENSOR", "ODOMETRY", "HIL_GPS"):
            self._count(f"ignored.{t}")
            return
        if t == "HIL_GPS":  # integer fields: always finite; kept with its packet's IMU frame
            self.assembler.feed_frames(msg)
            return
        values = ([msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro, msg.zgyro, msg.xmag, msg.ymag, msg.zmag,
                   msg.abs_pressure, msg.pressure_alt] if t == "HIL_SENSOR"
                  else [msg.x, msg.y, msg.z, *msg.q, msg.vx, msg.vy, msg.vz])
        if not _finite(*values):
            self._drop("hil_non_finite")
            return
        frames = self.assembler.feed_frames(msg)
        if frames is None:
            return
        if self.hil_stepped_by_host:  # the host's engine takes the step (take_hil_step), in its order
            self._hil_received = (frames, int(msg.time_usec), lk.name)
            return
        self._take_hil_frames(frames, int(msg.time_usec), lk.name, out)
        if self._await_coordinator and int(msg.time_usec) not in (self._last_rotor_usec, self._step_skipped_usec):
            return  # answered when the coordinator's command for this step arrives (or on release); one that
            # came before its sensors (another link, read first) answers it now
        self._answer_hil(out)

    def _take_hil_frames(self, frames: SensorFrames, time_usec: int, link: str, out: list[Outgoing]) -> None:
        """A HIL step's sensors into the unit: due sensor failures, the battery measured, the sensors
        forwarded to the coordinator, the unit's own state (now or deferred); the step is then pending."""
        if self._scheduled_sensor_failures:
            self._sensor_failures_due(frames.imu.time_usec / 1e6)
        forward = [name for name, other in self.links.items() if other.policy.forward_sensors]
        esc = self._esc_sample(frames.imu.time_usec / 1e6)  # (every step: its noise draws as in-process)
        report = None
        if self._battery_pending is not None:
            report = self._measure_battery(self._battery_pending, frames.imu.time_usec / 1e6)
            self._battery_pending = None
        flags = frames.imu.fields_updated
        if flags & (BARO_FIELDS | MAG_FIELDS):
            self.sensor_failures.note_carried(flags & BARO_FIELDS == BARO_FIELDS, flags & MAG_FIELDS == MAG_FIELDS)
        if forward:  # (on the real-time path: straight from the received fields, unless a sensor failed)
            if self.sensor_failures.any:  # the failed sensors' packet (sensor_failures)
                upstream = sensor_packet_messages(self.sensor_failures.apply(frames.packet()), upstream=True)
            else:
                upstream = frames.upstream_messages()
            if report is not None:  # before the IMU frame: the coordinator attaches it to this packet
                upstream.insert(0, battery_report_message(report))
            if esc is not None:  # (likewise)
                upstream.insert(0, esc_status_message(esc))
            for name in forward:
                other = self.links[name]
                out.extend(Outgoing(name, self._pack(other, m)) for m in upstream)
        if self.defer_own_state:
            self._deferred.append(lambda: self._apply_sensors(frames))
        else:
            self._apply_sensors(frames)
        # lockstep: the sensor time stamps the step; answer with the motor outputs for it
        t_s = frames.imu.time_usec / 1e6
        self.sim_s = t_s
        self._next_control = t_s + self.control_dt_s
        self._hil_pending = (time_usec, link)

    # ----------------------------------------------------------------- HIL steps taken by a host's engine
    # With `hil_stepped_by_host` the frame handlers only receive: a HIL step's sensors wait in
    # `hil_received`, the coordinator's command (or its step skip) in the intake, and the host's engine
    # (mars_link.processes.engine_links.HostedFirmware) runs the stages in the engine's order.
    @property
    def hil_received(self) -> SensorFrames | None:
        """The sensor frames of a HIL step received and not taken yet."""
        return None if self._hil_received is None else self._hil_received[0]

    def take_hil_step(self) -> list[Outgoing]:
        """The sensors stage of the received HIL step; returns the telemetry to send (to the coordinator)."""
        out: list[Outgoing] = []
        if self._hil_received is not None:
            frames, time_usec, link = self._hil_received
            self._hil_received = None
            self._take_hil_frames(frames, time_usec, link, out)
        return out

    @property
    def hil_command_in(self) -> bool:
        """The pending HIL step may be answered: the unit does not wait for the coordinator, or its command
        for the step (or its step skip) is in."""
        pending = self._hil_pending
        return pending is not None and (not self._await_coordinator
                                        or pending[0] in (self._last_rotor_usec, self._step_skipped_usec))

    def answer_hil_step(self) -> list[Outgoing]:
        """The motors stage: the pending HIL step's motor outputs (HIL_ACTUATOR_CONTROLS)."""
        out: list[Outgoing] = []
        if self._hil_pending is not None:
            self._answer_hil(out)
        return out

    def _apply_hil_state(self, msg) -> None:
        """HIL_STATE_QUATERNION: the unit centre's ground truth, for its own telemetry and checks."""
        q = np.array(msg.attitude_quaternion, dtype=float)
        values = [*q, msg.rollspeed, msg.pitchspeed, msg.yawspeed]
        if not _finite(*values) or not 0.5 < np.linalg.norm(q) < 1.5:
            self._drop("hil_non_finite")
            return
        self.set_state(hil_state_from_fields(msg.time_usec, q, values[4:], msg.lat, msg.lon, msg.alt, msg.vx, msg.vy,
                                             msg.vz))

    def _apply_sensors(self, frames: SensorFrames) -> None:
        packet = frames.packet()
        self.imu = ImuSample(packet.t_s, self.sysid, packet.imu.gyro_frd_radps, packet.imu.accel_frd_mps2)
        if packet.truth is not None:
            self.set_state(packet.truth)

    def _answer_hil(self, out: list[Outgoing]) -> None:
        time_usec, name = self._hil_pending
        self._hil_pending = None
        if self.config.hil_await_coordinator:  # (lockstep: the watchdogs judged at each step in sim time too,
            self._watchdogs()  # not only on the wall-clock tick: a step's outcome never hangs on when it ticked)
        lk = self.links[name]
        sp = self._motor_setpoint_n() / self.full_scale_n
        mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        controls = [float(x) for x in sp] + [latches_open(self.latch_setpoint)] + [0.0] * 11
        out.append(Outgoing(lk.name, self._pack(lk, mavlink.MAVLink_hil_actuator_controls_message(
            time_usec, controls, mode, 1))))

    def _failure_due(self) -> bool:
        """A scenario fault scheduled in the motor model is due at this step."""
        f = self._scheduled_failures
        return bool(f) and f[0][0] <= self.sim_s + 1e-9

    def _motor_setpoint_n(self) -> np.ndarray:
        """One HIL step's motor outputs (N): due scenario faults enter the motor model, the control step
        runs, and the motors are driven to the clamped, eta-scaled command."""
        while self._failure_due():
            _, rotor, eta, kind = self._scheduled_failures.pop(0)
            self.inject_failure(rotor, eta, kind)
        stats = self.stats  # (_count, inlined: every step)
        stats["hil_steps"] = stats.get("hil_steps", 0) + 1
        self._control_step()
        if self.ulog is not None:
            self._ulog_sample()
        if not self.armed:
            return self.motors.setpoint(np.zeros(4))
        cmd = self.motor_commands_n  # the intake's held command is finite and of 4 values (rotor_intake.accept)
        return self.motors.setpoint(cmd, checked=cmd is self.intake.thrusts_n)

    # ================================================================= in-process messages
    # The same steps as the HIL and coordinator links, with the messages as objects instead of MAVLink
    # bytes: what the in-process engine calls. The values are already at wire precision (float32,
    # microseconds), so a unit driven this way moves its motors exactly as over MAVLink.
    def take_sensors(self, packet: SensorPacket, unit_truth: RigidBodyState | None = None) -> SensorPacket:
        """A HIL step: the unit's sensors (HIL_SENSOR/ODOMETRY) and, when given, its centre's truth
        (HIL_STATE_QUATERNION). Returns the telemetry it forwards to the coordinator (HIGHRES_IMU and
        ODOMETRY carry exactly these fields)."""
        if unit_truth is not None:
            self.set_state(unit_truth)
        if self._scheduled_sensor_failures:
            self._sensor_failures_due(packet.t_s)
        failures = self.sensor_failures
        if packet.baro is not None or packet.mag is not None:
            failures.note_carried(packet.baro is not None, packet.mag is not None)
        if failures.active:  # (failures.any without the property call: every unit, every step)
            packet = failures.apply(packet)
        self.latches = packet.latches
        self.imu = packet.imu
        if packet.truth is not None:
            self.set_state(packet.truth)
        self.sim_s = packet.t_s
        self._next_control = packet.t_s + self.control_dt_s
        esc = self._esc_sample(packet.t_s)
        if packet.battery is not None:  # forwarded with the unit's remaining-charge estimate
            return dataclasses.replace(packet, battery=self._measure_battery(packet.battery, packet.t_s), esc=esc)
        return packet if esc is None else dataclasses.replace(packet, esc=esc)

    def take_rotor_command(self, cmd: RotorCommand) -> bool:
        """A coordinator command (SET_ACTUATOR_CONTROL_TARGET's values); True if it is now held."""
        if cmd.unit_id != self.sysid:
            return self.intake.drop("wrong_target")
        return self._accept_rotor_command(cmd)

    def _accept_rotor_command(self, cmd: RotorCommand) -> bool:
        """The intake's checks on a command addressed to this unit; True if it is now held."""
        # cmd.thrusts_n are wire values (float32 controls x full scale): x / full scale is the control back
        s = self.full_scale_n
        a, b, c, d = cmd.thrusts_n.tolist()
        t_usec = round(cmd.t_s * 1e6)
        if not self.intake.accept(a / s, b / s, c / s, d / s, t_usec, self.sim_s, cmd.thrusts_n):
            return False
        self._note_rotor_command(t_usec, cmd.latch_setpoint)
        return True

    def _note_rotor_command(self, t_usec: int, latch_setpoint: int) -> None:
        stats = self.stats  # (_count, inlined: every step)
        stats["rotor_commands"] = stats.get("rotor_commands", 0) + 1
        self._last_rotor_usec = t_usec
        self.latch_setpoint = latch_setpoint

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
        f = self._scheduled_failures
        if not (self.armed and self.source == "coordinator" and self.mode == MODE_OFFBOARD and self.motors.plain
                and not (f and f[0][0] <= self.sim_s + 1e-9)):  # (_failure_due, inlined: every unit, every step)
            return None
        if not self.intake.accept_bounded(least, greatest, t_usec, self.sim_s, thrusts_n):
            return False
        self._note_rotor_command(t_usec, latch_setpoint)
        stats = self.stats
        stats["hil_steps"] = stats.get("hil_steps", 0) + 1  # (_motor_setpoint_n's count)
        self._drive_from_coordinator(thrusts_n)
        if self.ulog is not None:
            self._ulog_sample()
        return True

    def drive_motors(self) -> ActuatorOutput:
        """The HIL answer (HIL_ACTUATOR_CONTROLS' values): what the motors are driven to for this step."""
        sp = self._motor_setpoint_n()
        if sp is not self.intake.thrusts_n:  # (the held command itself is at wire precision already)
            sp = wire_thrust(sp, self.full_scale_n)
        return ActuatorOutput(self.sim_s, self.sysid, sp, self.latch_setpoint)

    def arm(self) -> int:
        """MAV_CMD_COMPONENT_ARM_DISARM (arm) as the coordinator sends it; returns the MAV_RESULT."""
        return self.command_service.arm_disarm(1.0, 0.0)

    def set_mode(self, mode: tuple[int, int]) -> int:
        """MAV_CMD_DO_SET_MODE to a PX4 (main, sub) mode; returns the MAV_RESULT."""
        return self.command_service.set_mode(mode)

