"""PX4's own per-rotor interface (uORB over rmw_zenoh, PX4 v1.17), the unit's second command intake
beside SET_ACTUATOR_CONTROL_TARGET.

`mars_link.px4.Px4UnitInterface` holds PX4's commander
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
- Telemetry: `telemetry` gives the `/fmu/out` messages for the runner to publish.

Transports: `sample` takes a received rmw_zenoh sample (key, CDR payload, attachment) and returns
the samples to publish; `take` takes the decoded message (the in-process path, objects)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle_links import Outgoing
from firmware_models.vehicle_modes import MODE_OFFBOARD, MODE_POSCTL
from mars_link.px4 import rmw_zenoh as rz
from mars_link.px4 import telemetry as px4_telemetry
from mars_link.px4.cdr import VehicleCommand, VehicleCommandAck, VehicleStatus
from mars_link.px4.endpoint import Px4UnitEndpoint
from mars_link.px4.unit_interface import Px4UnitInterface, Px4UnitParams, time_us

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle

Sample = tuple[str, bytes, bytes]  # (key, payload, attachment) of one rmw_zenoh sample


class Px4Service:
    """PX4's own interface beside the MAVLink persona. Owns the interface and its rmw_zenoh endpoint (made on
    first use), the keep-alive test switch, and the interface's arming and navigation state as last carried
    over to the firmware. Asks of the vehicle: its ids, `params`, sim and wall time, state, IMU and battery,
    the intake, the mode machine, the HIL service (a lockstep step answered), `run_deferred`, `stats`,
    `_count`, `_drop`, `_text`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.interface: Px4UnitInterface | None = None  # made on first use (a unit beyond id 255 never needs one)
        self.endpoint: Px4UnitEndpoint | None = None
        self.keepalive_timeout = True  # test switch (conformance harness): False = a broken keep-alive
        self.interface_armed = False
        self.interface_nav = VehicleStatus.NAVIGATION_STATE_POSCTL

    def ensure_interface(self) -> Px4UnitInterface:
        if self.interface is None:
            self.interface = Px4UnitInterface(Px4UnitParams(
                system_id=self.v.sysid, component_id=self.v.compid,
                offboard_loss_timeout_s=float(self.v.params["COM_OF_LOSS_T"]),
                keepalive_timeout_enabled=self.keepalive_timeout))
            self.endpoint = Px4UnitEndpoint(self.v.sysid)
        return self.interface

    # ----------------------------------------------------------------- input
    def take(self, topic: rz.Px4Topic, message: Any) -> list[tuple[rz.Px4Topic, Any]]:
        """One decoded `/fmu/in` message at the unit's sim time; returns what the unit publishes in answer
        (VehicleCommandAck, then VehicleStatus)."""
        unit = self.ensure_interface()
        t = self.v.sim_s
        replies: list[tuple[rz.Px4Topic, Any]] = []
        if topic is rz.ACTUATOR_MOTORS:
            unit.on_actuator_motors(message, t)
            stats = self.v.stats
            stats["px4.actuator_motors"] = stats.get("px4.actuator_motors", 0) + 1
            hil = self.v.hil_service
            hil.last_rotor_usec = int(message.timestamp)  # (lockstep: answers the HIL step of that time)
            if self.v.config.hil_await_coordinator:
                hil.await_coordinator = True
        elif topic is rz.OFFBOARD_CONTROL_MODE:
            unit.on_offboard_control_mode(message, t)
            self.v._count("px4.offboard_control_mode")
        elif topic is rz.VEHICLE_COMMAND:
            self.v.run_deferred()  # (the pre-arm checks read the unit's own state)
            self.v._count("px4.vehicle_command")
            ack = self._prearm_refusal(message)
            if ack is None:
                ack = unit.on_vehicle_command(message, t)
            if ack is not None:
                replies.append((rz.VEHICLE_COMMAND_ACK, ack))
        else:
            self.v._drop("px4.not_an_input")
            return replies
        self._sync()
        if replies:
            replies.append((rz.VEHICLE_STATUS, unit.vehicle_status(t)))
        return replies

    def sample(self, key: str, payload: bytes, attachment: bytes | None,
               wall_time_s: float) -> tuple[list[Outgoing], list[Sample]]:
        """One received rmw_zenoh sample: (MAVLink frames to send: the HIL answer when this sample
        completes a lockstep step, rmw_zenoh samples to publish). A sample that is not one of this unit's
        inputs or does not decode is dropped and counted (px4.bad_sample)."""
        self.v.wall_s = max(self.v.wall_s, wall_time_s)
        self.ensure_interface()
        endpoint = self.endpoint
        assert endpoint is not None
        try:
            got = endpoint.decode(key, payload, attachment)
        except ValueError:
            self.v._drop("px4.bad_sample")
            return [], []
        if endpoint.reordered:  # (in the status file too: a harness that reaches the unit over a network reads it)
            self.v.stats["px4.reordered"] = endpoint.reordered
        replies = self.take(got.topic, got.message)
        out: list[Outgoing] = []
        hil = self.v.hil_service
        pending = hil.pending
        if pending is not None and hil.last_rotor_usec == pending[0] and not self.v.hil_stepped_by_host:
            hil.answer(out)
        return out, [endpoint.encode(topic, msg, self.v.sim_s) for topic, msg in replies]

    def _prearm_refusal(self, cmd: Any) -> VehicleCommandAck | None:
        """The firmware's own pre-arm checks for an ARM addressed to this unit (PX4 runs its own before
        arming): a refusal ack, or None to let the interface decide."""
        if int(cmd.command) != VehicleCommand.VEHICLE_CMD_COMPONENT_ARM_DISARM or self.v.armed:
            return None
        if int(cmd.target_system) not in (0, self.v.sysid) or int(cmd.target_component) not in (0, self.v.compid):
            return None
        if not (abs(float(cmd.param1) - 1.0) < 0.5):
            return None
        if self.v.state is None:
            result = VehicleCommandAck.VEHICLE_CMD_RESULT_TEMPORARILY_REJECTED
        elif not self.v.autopilot.may_arm(self.v.state):
            result = VehicleCommandAck.VEHICLE_CMD_RESULT_DENIED
        else:
            return None
        return VehicleCommandAck(timestamp=time_us(self.v.sim_s), command=int(cmd.command), result=result,
                                 target_system=int(cmd.source_system), target_component=int(cmd.source_component))

    # ----------------------------------------------------------------- the two personas, one unit
    def _sync(self) -> None:
        """Carry the interface's arming and mode changes over to the firmware."""
        unit = self.interface
        if unit is None:
            return
        for e in unit.take_events():
            if e.kind == "failsafe":
                self.v._text(f"PX4 offboard lost: {e.detail}", mavlink.MAV_SEVERITY_CRITICAL)
        armed = unit.armed
        if armed != self.interface_armed:
            self.interface_armed = armed
            if armed and not self.v.armed:
                self.v.command_service.arm_disarm(1.0, 0.0)
                if not self.v.armed:  # (refused after all: the interface follows the firmware)
                    self.interface_armed = False
                    unit.disarm(self.v.sim_s)
            elif not armed and self.v.armed:
                self.v.command_service.disarm("PX4 interface: disarmed")
        nav = unit.nav_state
        if nav != self.interface_nav:
            self.interface_nav = nav
            if (nav != VehicleStatus.NAVIGATION_STATE_OFFBOARD and self.v.armed and self.v.source == "coordinator"
                    and not self.v.intake.is_live(self.v.sim_s)):
                self.v.command_service.set_mode(MODE_POSCTL)  # the unit's own controller holds where it is

    def disarmed(self) -> None:
        """The firmware disarmed (any reason): so is the interface."""
        if self.interface is not None and self.interface_armed:
            self.interface_armed = False
            self.interface.disarm(self.v.sim_s)
            self.interface.take_events()

    def command_n(self, t_s: float) -> np.ndarray | None:
        """The rotor thrusts (N) the interface drives at `t_s`, or None while it drives none."""
        unit = self.interface
        if unit is None:
            return None
        out = unit.update(t_s)
        self._sync()
        if not (self.v.armed and unit.motors_enabled):
            return None
        self.v.mode = MODE_OFFBOARD
        return out.thrust_fraction * self.v.full_scale_n

    # ----------------------------------------------------------------- output
    def telemetry(self) -> list[tuple[rz.Px4Topic, Any]]:
        """The `/fmu/out` messages at the unit's sim time: status, odometry, local position, IMU, battery
        (what the unit knows of itself; nothing until it has a state)."""
        unit = self.ensure_interface()
        t = self.v.sim_s
        out: list[tuple[rz.Px4Topic, Any]] = [(rz.VEHICLE_STATUS, unit.vehicle_status(t))]
        s = self.v.state
        if s is not None:
            p, v, q, w = s.position_ned_m, s.velocity_ned_mps, s.quaternion_wxyz, s.angular_velocity_frd_radps
            out.append((rz.VEHICLE_ODOMETRY, px4_telemetry.vehicle_odometry(t, p, q, v, w)))
            qw, qx, qy, qz = (float(x) for x in q)
            heading = float(np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz)))
            origin = self.v.origin
            out.append((rz.VEHICLE_LOCAL_POSITION, px4_telemetry.vehicle_local_position(
                t, p, v, s.acceleration_ned_mps2, heading, ref_lat_deg=origin.lat_deg, ref_lon_deg=origin.lon_deg,
                ref_alt_m=origin.amsl_m)))
        if self.v.imu is not None:
            out.append((rz.SENSOR_COMBINED, px4_telemetry.sensor_combined(
                t, self.v.imu.gyro_frd_radps, self.v.imu.accel_frd_mps2, integral_dt_s=self.v.control_dt_s)))
        b = self.v.battery
        if b.measured:
            out.append((rz.BATTERY_STATUS, px4_telemetry.battery_status(t, b.voltage_v, b.current_a, b.remaining)))
        return out

    def telemetry_samples(self) -> list[Sample]:
        self.ensure_interface()
        endpoint = self.endpoint
        assert endpoint is not None
        return [endpoint.encode(topic, msg, self.v.sim_s) for topic, msg in self.telemetry()]
