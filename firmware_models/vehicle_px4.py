"""PX4's own per-rotor interface (uORB over rmw_zenoh, PX4 v1.17), the unit's second command intake
beside SET_ACTUATOR_CONTROL_TARGET.

A mixin of `firmware_models.vehicle.Vehicle`. `mars_link.px4.Px4UnitInterface` holds PX4's commander
semantics (keep-alive, COM_OF_LOSS_T failsafe, arming and mode gating, NaN = motor off); this module
plugs it into the one firmware:

- Arming: a VehicleCommand ARM first passes the firmware's own pre-arm checks (a known state, on the
  ground), then the interface's; once the interface is armed the firmware is armed, and whichever of
  the two disarms (a failsafe, a disarm on either persona, the land detector) disarms the other.
- Motors: while the interface lets the motors run (armed, OFFBOARD, keep-alive present with
  direct_actuator, an ActuatorMotors received), its thrust fractions x full scale drive the motor model
  exactly as the coordinator's held command does on the MAVLink path (`source` "coordinator"). Leaving
  OFFBOARD for another mode hands the unit to its own controller, holding position.
- Lockstep: an ActuatorMotors whose time stamp is the pending HIL step's answers that step, as the
  MAVLink rotor command does.
- Telemetry: `px4_telemetry` gives the `/fmu/out` messages for the runner to publish.

Transports: `px4_sample` takes a received rmw_zenoh sample (key, CDR payload, attachment) and returns
the samples to publish; `px4_take` takes the decoded message (the in-process path, objects)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle_links import Outgoing
from firmware_models.vehicle_modes import MODE_OFFBOARD, MODE_POSCTL
from mars_link.px4 import rmw_zenoh as rz
from mars_link.px4 import telemetry as px4_telemetry
from mars_link.px4.cdr import VehicleCommand, VehicleCommandAck, VehicleStatus
from mars_link.px4.endpoint import Px4UnitEndpoint
from mars_link.px4.unit_interface import Px4UnitInterface, Px4UnitParams, time_us

Sample = tuple[str, bytes, bytes]  # (key, payload, attachment) of one rmw_zenoh sample


class Px4Mixin:
    def _init_px4(self) -> None:
        self.px4: Px4UnitInterface | None = None  # made on first use (an in-process unit beyond id 255 never needs one)
        self.px4_endpoint: Px4UnitEndpoint | None = None
        self.px4_keepalive_timeout = True  # test switch (conformance harness): False = a broken keep-alive
        self._px4_armed = False
        self._px4_nav = VehicleStatus.NAVIGATION_STATE_POSCTL

    def px4_interface(self) -> Px4UnitInterface:
        if self.px4 is None:
            self.px4 = Px4UnitInterface(Px4UnitParams(
                system_id=self.sysid, component_id=self.compid,
                offboard_loss_timeout_s=float(self.params["COM_OF_LOSS_T"]),
                keepalive_timeout_enabled=self.px4_keepalive_timeout))
            self.px4_endpoint = Px4UnitEndpoint(self.sysid)
        return self.px4

    # ----------------------------------------------------------------- input
    def px4_take(self, topic: rz.Px4Topic, message: Any) -> list[tuple[rz.Px4Topic, Any]]:
        """One decoded `/fmu/in` message at the unit's sim time; returns what the unit publishes in answer
        (VehicleCommandAck, then VehicleStatus)."""
        unit = self.px4_interface()
        t = self.sim_s
        replies: list[tuple[rz.Px4Topic, Any]] = []
        if topic is rz.ACTUATOR_MOTORS:
            unit.on_actuator_motors(message, t)
            stats = self.stats
            stats["px4.actuator_motors"] = stats.get("px4.actuator_motors", 0) + 1
            self.hil_service.last_rotor_usec = int(message.timestamp)  # (lockstep: answers the HIL step of that time)
            if self.config.hil_await_coordinator:
                self.hil_service.await_coordinator = True
        elif topic is rz.OFFBOARD_CONTROL_MODE:
            unit.on_offboard_control_mode(message, t)
            self._count("px4.offboard_control_mode")
        elif topic is rz.VEHICLE_COMMAND:
            self.run_deferred()  # (the pre-arm checks read the unit's own state)
            self._count("px4.vehicle_command")
            ack = self._px4_prearm_refusal(message)
            if ack is None:
                ack = unit.on_vehicle_command(message, t)
            if ack is not None:
                replies.append((rz.VEHICLE_COMMAND_ACK, ack))
        else:
            self._drop("px4.not_an_input")
            return replies
        self._px4_sync()
        if replies:
            replies.append((rz.VEHICLE_STATUS, unit.vehicle_status(t)))
        return replies

    def px4_sample(self, key: str, payload: bytes, attachment: bytes | None,
                   wall_time_s: float) -> tuple[list[Outgoing], list[Sample]]:
        """One received rmw_zenoh sample: (MAVLink frames to send: the HIL answer when this sample
        completes a lockstep step, rmw_zenoh samples to publish). A sample that is not one of this unit's
        inputs or does not decode is dropped and counted (px4.bad_sample)."""
        self.wall_s = max(self.wall_s, wall_time_s)
        self.px4_interface()
        endpoint = self.px4_endpoint
        assert endpoint is not None
        try:
            got = endpoint.decode(key, payload, attachment)
        except ValueError:
            self._drop("px4.bad_sample")
            return [], []
        if endpoint.reordered:  # (in the status file too: a harness that reaches the unit over a network reads it)
            self.stats["px4.reordered"] = endpoint.reordered
        replies = self.px4_take(got.topic, got.message)
        out: list[Outgoing] = []
        pending = self.hil_service.pending
        if pending is not None and self.hil_service.last_rotor_usec == pending[0] and not self.hil_stepped_by_host:
            self.hil_service.answer(out)
        return out, [endpoint.encode(topic, msg, self.sim_s) for topic, msg in replies]

    def _px4_prearm_refusal(self, cmd: Any) -> VehicleCommandAck | None:
        """The firmware's own pre-arm checks for an ARM addressed to this unit (PX4 runs its own before
        arming): a refusal ack, or None to let the interface decide."""
        if int(cmd.command) != VehicleCommand.VEHICLE_CMD_COMPONENT_ARM_DISARM or self.armed:
            return None
        if int(cmd.target_system) not in (0, self.sysid) or int(cmd.target_component) not in (0, self.compid):
            return None
        if not (abs(float(cmd.param1) - 1.0) < 0.5):
            return None
        if self.state is None:
            result = VehicleCommandAck.VEHICLE_CMD_RESULT_TEMPORARILY_REJECTED
        elif not self.autopilot.touching(self.state):
            result = VehicleCommandAck.VEHICLE_CMD_RESULT_DENIED
        else:
            return None
        return VehicleCommandAck(timestamp=time_us(self.sim_s), command=int(cmd.command), result=result,
                                 target_system=int(cmd.source_system), target_component=int(cmd.source_component))

    # ----------------------------------------------------------------- the two personas, one unit
    def _px4_sync(self) -> None:
        """Carry the interface's arming and mode changes over to the firmware."""
        unit = self.px4
        if unit is None:
            return
        for e in unit.take_events():
            if e.kind == "failsafe":
                self._text(f"PX4 offboard lost: {e.detail}", mavlink.MAV_SEVERITY_CRITICAL)
        armed = unit.armed
        if armed != self._px4_armed:
            self._px4_armed = armed
            if armed and not self.armed:
                self.command_service.arm_disarm(1.0, 0.0)
                if not self.armed:  # (refused after all: the interface follows the firmware)
                    self._px4_armed = False
                    unit.disarm(self.sim_s)
            elif not armed and self.armed:
                self.command_service.disarm("PX4 interface: disarmed")
        nav = unit.nav_state
        if nav != self._px4_nav:
            self._px4_nav = nav
            if (nav != VehicleStatus.NAVIGATION_STATE_OFFBOARD and self.armed and self.source == "coordinator"
                    and not self.intake.is_live(self.sim_s)):
                self.command_service.set_mode(MODE_POSCTL)  # the unit's own controller holds where it is

    def _px4_disarmed(self) -> None:
        """The firmware disarmed (any reason): so is the interface."""
        if self.px4 is not None and self._px4_armed:
            self._px4_armed = False
            self.px4.disarm(self.sim_s)
            self.px4.take_events()

    def _px4_command_n(self, t_s: float) -> np.ndarray | None:
        """The rotor thrusts (N) the interface drives at `t_s`, or None while it drives none."""
        unit = self.px4
        if unit is None:
            return None
        out = unit.update(t_s)
        self._px4_sync()
        if not (self.armed and unit.motors_enabled):
            return None
        self.mode = MODE_OFFBOARD
        return out.thrust_fraction * self.full_scale_n

    # ----------------------------------------------------------------- output
    def px4_telemetry(self) -> list[tuple[rz.Px4Topic, Any]]:
        """The `/fmu/out` messages at the unit's sim time: status, odometry, local position, IMU, battery
        (what the unit knows of itself; nothing until it has a state)."""
        unit = self.px4_interface()
        t = self.sim_s
        out: list[tuple[rz.Px4Topic, Any]] = [(rz.VEHICLE_STATUS, unit.vehicle_status(t))]
        s = self.state
        if s is not None:
            p, v, q, w = s.position_ned_m, s.velocity_ned_mps, s.quaternion_wxyz, s.angular_velocity_frd_radps
            out.append((rz.VEHICLE_ODOMETRY, px4_telemetry.vehicle_odometry(t, p, q, v, w)))
            qw, qx, qy, qz = (float(x) for x in q)
            heading = float(np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz)))
            out.append((rz.VEHICLE_LOCAL_POSITION, px4_telemetry.vehicle_local_position(
                t, p, v, s.acceleration_ned_mps2, heading, ref_lat_deg=self.origin.lat_deg, ref_lon_deg=self.origin.lon_deg,
                ref_alt_m=self.origin.amsl_m)))
        if self.imu is not None:
            out.append((rz.SENSOR_COMBINED, px4_telemetry.sensor_combined(
                t, self.imu.gyro_frd_radps, self.imu.accel_frd_mps2, integral_dt_s=self.control_dt_s)))
        b = self.battery
        if b.measured:
            out.append((rz.BATTERY_STATUS, px4_telemetry.battery_status(t, b.voltage_v, b.current_a, b.remaining)))
        return out

    def px4_telemetry_samples(self) -> list[Sample]:
        self.px4_interface()
        endpoint = self.px4_endpoint
        assert endpoint is not None
        return [endpoint.encode(topic, msg, self.sim_s) for topic, msg in self.px4_telemetry()]
