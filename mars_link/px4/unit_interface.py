"""The unit side of PX4's per-rotor interface, without I/O: decoded uORB messages and the simulated time
in, motor outputs, command acks and VehicleStatus out. It behaves as PX4 v1.17's commander and output
module do for an off-board computer that drives the motors directly (PX4 commit
a64536802b5a5b6ba8fe6ef1b7dcb6a54a0a99ea; commander `offboardCheck.cpp`, `commander_params.yaml`,
mixer_module `FunctionMotors.hpp`):

- The offboard signal is present while the latest OffboardControlMode has at least one setpoint flag set
  and arrived less than COM_OF_LOSS_T (1.0 s) ago: lost when `now >= received + COM_OF_LOSS_T`.
- Motors run only when armed, the navigation state is OFFBOARD, the signal is present and its
  `direct_actuator` flag is set. PX4 does not time out ActuatorMotors itself, only the keep-alive.
- ActuatorMotors `control[i]`: NaN or +-inf stops motor i; below 0 stops a motor not marked reversible
  in `reversible_flags`; values above 1 (or below -1 for a reversible one) are clamped.
- Losing the signal while armed in OFFBOARD is a failsafe: the configured COM_OBL_RC_ACT action runs.
  This unit has no onboard position/altitude controller in this persona, so only the actions that need
  none are offered: Disarm (7, the default here) and Terminate (6). After a Disarm failsafe the motors
  stay off until a fresh arm command, even when the keep-alive comes back; after Terminate arming is
  refused until `reset()` (PX4: a reboot).
- VehicleCommand COMPONENT_ARM_DISARM (400) and DO_SET_MODE (176, custom main mode OFFBOARD = 6) are
  answered with a VehicleCommandAck; commands for another system or component are ignored (no ack).

Time is the simulation's: every call takes `time_s` (seconds since the unit's boot); message time
stamps are integer microseconds of that clock, as PX4's hrt time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from mars_link.px4.cdr import (
    ActuatorMotors, OffboardControlMode, VehicleCommand, VehicleCommandAck, VehicleStatus,
)

NUM_CONTROLS = int(ActuatorMotors.NUM_CONTROLS)
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_TYPE_QUADROTOR = 2


class Px4MainMode(IntEnum):
    """PX4's custom main modes (param2 of DO_SET_MODE; PX4 `px4_custom_mode.h`)."""
    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7


_NAV_STATE_OF_MAIN_MODE = {
    Px4MainMode.MANUAL: VehicleStatus.NAVIGATION_STATE_MANUAL,
    Px4MainMode.ALTCTL: VehicleStatus.NAVIGATION_STATE_ALTCTL,
    Px4MainMode.POSCTL: VehicleStatus.NAVIGATION_STATE_POSCTL,
    Px4MainMode.ACRO: VehicleStatus.NAVIGATION_STATE_ACRO,
    Px4MainMode.OFFBOARD: VehicleStatus.NAVIGATION_STATE_OFFBOARD,
    Px4MainMode.STABILIZED: VehicleStatus.NAVIGATION_STATE_STAB,
}


class OffboardLossAction(IntEnum):
    """COM_OBL_RC_ACT values this unit implements."""
    TERMINATE = 6
    DISARM = 7


@dataclass(frozen=True)
class Px4UnitParams:
    system_id: int                       # MAV_SYS_ID: the unit id
    component_id: int = 1                # MAV_COMP_ID of the autopilot
    motor_count: int = 4                 # motors driven (control[0 .. motor_count-1])
    offboard_loss_timeout_s: float = 1.0  # COM_OF_LOSS_T
    offboard_loss_action: OffboardLossAction = OffboardLossAction.DISARM  # COM_OBL_RC_ACT
    fallback_nav_state: int = VehicleStatus.NAVIGATION_STATE_POSCTL  # shown while the signal is lost
    # Test switch, never for flight: False makes a deliberately broken unit whose keep-alive never
    # times out (the conformance harness must catch it).
    keepalive_timeout_enabled: bool = True

    def __post_init__(self) -> None:
        if not 1 <= self.system_id <= 255:
            raise ValueError(f"system id {self.system_id}: expected 1..255")
        if not 1 <= self.motor_count <= NUM_CONTROLS:
            raise ValueError(f"motor count {self.motor_count}: expected 1..{NUM_CONTROLS}")
        if not self.offboard_loss_timeout_s > 0:
            raise ValueError(f"COM_OF_LOSS_T {self.offboard_loss_timeout_s} s: expected > 0")


@dataclass(frozen=True)
class Px4MotorOutput:
    """What the motors do at `time_s`."""
    time_s: float
    thrust_fraction: np.ndarray          # (motor_count,) normalised in [0, 1] (reversible: [-1, 1]); 0: stopped
    running: np.ndarray                  # (motor_count,) bool: the motor is driven (False: stopped / disarmed)
    armed: bool
    nav_state: int                       # VehicleStatus.NAVIGATION_STATE_*
    offboard_signal: bool                # the keep-alive is present
    failsafe: bool


@dataclass(frozen=True)
class Px4UnitEvent:
    """A state change worth a log line: armed, disarmed, mode, offboard_lost, offboard_regained, failsafe."""
    time_s: float
    kind: str
    detail: str = ""


def time_us(time_s: float) -> int:
    return int(round(time_s * 1e6))


@dataclass
class _State:
    armed: bool = False
    armed_time_us: int = 0
    arming_reason: int = 0
    disarming_reason: int = 0
    user_nav_state: int = VehicleStatus.NAVIGATION_STATE_POSCTL
    nav_state: int = VehicleStatus.NAVIGATION_STATE_POSCTL
    nav_state_time_us: int = 0
    failsafe: bool = False
    terminated: bool = False
    keepalive: OffboardControlMode | None = None
    keepalive_time_us: int | None = None
    signal_present: bool = False
    motors: ActuatorMotors | None = None
    events: list[Px4UnitEvent] = field(default_factory=list)


class Px4UnitInterface:
    """PX4's commander and motor output for one unit, driven by decoded messages and simulated time.
    Feed it every received message with the time it arrived; call `update(time_s)` once per control
    step (before reading the motors) so that a silent keep-alive is noticed at the right time."""

    def __init__(self, params: Px4UnitParams):
        self.params = params
        self._s = _State()

    def reset(self) -> None:
        """As after a reboot: disarmed, no setpoints, termination cleared."""
        self._s = _State()

    # --- inputs -----------------------------------------------------------------------------------

    def on_offboard_control_mode(self, msg: OffboardControlMode, time_s: float) -> None:
        self._s.keepalive = msg
        self._s.keepalive_time_us = time_us(time_s)
        self._evaluate(time_s)

    def on_actuator_motors(self, msg: ActuatorMotors, time_s: float) -> None:
        self._s.motors = msg
        self._evaluate(time_s)

    def on_vehicle_command(self, cmd: VehicleCommand, time_s: float) -> VehicleCommandAck | None:
        """The ack to publish on /fmu/out/vehicle_command_ack, or None for a command that is not
        addressed to this unit."""
        p = self.params
        if int(cmd.target_system) not in (0, p.system_id) or int(cmd.target_component) not in (0, p.component_id):
            return None
        self._evaluate(time_s)
        command = int(cmd.command)
        if command == VehicleCommand.VEHICLE_CMD_COMPONENT_ARM_DISARM:
            result = self._arm_disarm(cmd, time_s)
        elif command == VehicleCommand.VEHICLE_CMD_DO_SET_MODE:
            result = self._set_mode(cmd, time_s)
        else:
            result = VehicleCommandAck.VEHICLE_CMD_RESULT_UNSUPPORTED
        return VehicleCommandAck(
            timestamp=time_us(time_s), command=command, result=result, result_param1=0, result_param2=0,
            target_system=int(cmd.source_system), target_component=int(cmd.source_component),
            from_external=False)

    def disarm(self, time_s: float) -> None:
        """Disarm from inside the unit (its own firmware disarmed it: a ground station's command on the
        other persona, the land detector), as PX4's commander does for an internal request."""
        self._evaluate(time_s)
        self._disarm(time_s, VehicleStatus.ARM_DISARM_REASON_COMMAND_INTERNAL)

    # --- outputs ----------------------------------------------------------------------------------

    def update(self, time_s: float) -> Px4MotorOutput:
        self._evaluate(time_s)
        s, n = self._s, self.params.motor_count
        thrust = np.zeros(n)
        running = np.zeros(n, dtype=bool)
        if self.motors_enabled:
            thrust, running = motor_commands(s.motors, n)
        return Px4MotorOutput(time_s=time_s, thrust_fraction=thrust, running=running, armed=s.armed,
                              nav_state=s.nav_state, offboard_signal=s.signal_present, failsafe=s.failsafe)

    @property
    def motors_enabled(self) -> bool:
        """Armed, in OFFBOARD, the keep-alive present and asking for direct actuator control, and an
        ActuatorMotors received."""
        s = self._s
        return (s.armed and s.nav_state == VehicleStatus.NAVIGATION_STATE_OFFBOARD and s.signal_present
                and bool(s.keepalive.direct_actuator) and s.motors is not None)

    @property
    def armed(self) -> bool:
        return self._s.armed

    @property
    def nav_state(self) -> int:
        return self._s.nav_state

    def take_events(self) -> list[Px4UnitEvent]:
        events, self._s.events = self._s.events, []
        return events

    def vehicle_status(self, time_s: float) -> VehicleStatus:
        """The message for /fmu/out/vehicle_status at `time_s`."""
        self._evaluate(time_s)
        s, p = self._s, self.params
        offboard_bit = 1 << VehicleStatus.NAVIGATION_STATE_OFFBOARD
        return VehicleStatus(
            timestamp=time_us(time_s),
            armed_time=s.armed_time_us if s.armed else 0,
            arming_state=VehicleStatus.ARMING_STATE_ARMED if s.armed else VehicleStatus.ARMING_STATE_DISARMED,
            latest_arming_reason=s.arming_reason, latest_disarming_reason=s.disarming_reason,
            nav_state_timestamp=s.nav_state_time_us, nav_state_user_intention=s.user_nav_state,
            nav_state=s.nav_state,
            valid_nav_states_mask=offboard_bit if s.signal_present else 0, can_set_nav_states_mask=offboard_bit,
            failure_detector_status=VehicleStatus.FAILURE_NONE,
            vehicle_type=VehicleStatus.VEHICLE_TYPE_ROTARY_WING,
            failsafe=s.failsafe, system_type=MAV_TYPE_QUADROTOR,
            system_id=p.system_id, component_id=p.component_id,
            safety_off=True, power_input_valid=True, pre_flight_checks_pass=not s.terminated)

    # --- internals --------------------------------------------------------------------------------

    def _event(self, time_s: float, kind: str, detail: str = "") -> None:
        self._s.events.append(Px4UnitEvent(time_s, kind, detail))

    def _signal_present(self, now_us: int) -> bool:
        s = self._s
        if s.keepalive is None or s.keepalive_time_us is None:
            return False
        k = s.keepalive
        any_flag = (k.position or k.velocity or k.acceleration or k.attitude or k.body_rate
                    or k.thrust_and_torque or k.direct_actuator)
        if not self.params.keepalive_timeout_enabled:
            return bool(any_flag)
        timeout_us = time_us(self.params.offboard_loss_timeout_s)
        return bool(any_flag) and now_us < s.keepalive_time_us + timeout_us

    def _evaluate(self, time_s: float) -> None:
        """Keep-alive bookkeeping, the failsafe, and the navigation state in force."""
        s = self._s
        now_us = time_us(time_s)
        present = self._signal_present(now_us)
        if present != s.signal_present:
            s.signal_present = present
            self._event(time_s, "offboard_regained" if present else "offboard_lost")
            wants_offboard = s.user_nav_state == VehicleStatus.NAVIGATION_STATE_OFFBOARD
            if not present and wants_offboard and s.armed:
                self._failsafe(time_s)
            if not s.terminated:
                if wants_offboard:
                    self._set_nav_state(VehicleStatus.NAVIGATION_STATE_OFFBOARD if present
                                        else self.params.fallback_nav_state, now_us)
                if present:
                    s.failsafe = False

    def _failsafe(self, time_s: float) -> None:
        s = self._s
        s.failsafe = True
        action = self.params.offboard_loss_action
        self._event(time_s, "failsafe", f"offboard signal lost for {self.params.offboard_loss_timeout_s} s: "
                                        f"{action.name.lower()}")
        if action is OffboardLossAction.TERMINATE:
            s.terminated = True
            self._set_nav_state(VehicleStatus.NAVIGATION_STATE_TERMINATION, time_us(time_s))
        self._disarm(time_s, VehicleStatus.ARM_DISARM_REASON_COMMAND_INTERNAL)  # (the msg lists no failsafe reason)

    def _set_nav_state(self, nav_state: int, now_us: int) -> None:
        if nav_state != self._s.nav_state:
            self._s.nav_state = nav_state
            self._s.nav_state_time_us = now_us
            self._event(now_us / 1e6, "mode", f"nav_state {nav_state}")

    def _disarm(self, time_s: float, reason: int) -> None:
        s = self._s
        if s.armed:
            s.armed = False
            s.disarming_reason = reason
            self._event(time_s, "disarmed", f"reason {reason}")

    def _arm_disarm(self, cmd: VehicleCommand, time_s: float) -> int:
        s = self._s
        action = _round_half_away(float(cmd.param1))  # as PX4's lroundf
        reason = (VehicleStatus.ARM_DISARM_REASON_COMMAND_EXTERNAL if cmd.from_external
                  else VehicleStatus.ARM_DISARM_REASON_COMMAND_INTERNAL)
        if action == VehicleCommand.ARMING_ACTION_DISARM:
            self._disarm(time_s, reason)
            return VehicleCommandAck.VEHICLE_CMD_RESULT_ACCEPTED
        if action != VehicleCommand.ARMING_ACTION_ARM:
            return VehicleCommandAck.VEHICLE_CMD_RESULT_UNSUPPORTED
        if s.armed:
            return VehicleCommandAck.VEHICLE_CMD_RESULT_ACCEPTED
        if s.terminated:
            return VehicleCommandAck.VEHICLE_CMD_RESULT_DENIED
        if s.user_nav_state == VehicleStatus.NAVIGATION_STATE_OFFBOARD and not s.signal_present:
            return VehicleCommandAck.VEHICLE_CMD_RESULT_TEMPORARILY_REJECTED
        s.armed = True
        s.armed_time_us = time_us(time_s)
        s.arming_reason = reason
        s.failsafe = False
        self._event(time_s, "armed")
        return VehicleCommandAck.VEHICLE_CMD_RESULT_ACCEPTED

    def _set_mode(self, cmd: VehicleCommand, time_s: float) -> int:
        s = self._s
        base_mode = int(cmd.param1) if math.isfinite(cmd.param1) else 0
        main_mode = int(cmd.param2) if math.isfinite(cmd.param2) else 0
        if not base_mode & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return VehicleCommandAck.VEHICLE_CMD_RESULT_UNSUPPORTED
        nav_state = _NAV_STATE_OF_MAIN_MODE.get(main_mode)
        if nav_state is None or s.terminated:
            return VehicleCommandAck.VEHICLE_CMD_RESULT_TEMPORARILY_REJECTED
        if nav_state == VehicleStatus.NAVIGATION_STATE_OFFBOARD and not s.signal_present:
            return VehicleCommandAck.VEHICLE_CMD_RESULT_TEMPORARILY_REJECTED
        s.user_nav_state = nav_state
        self._set_nav_state(nav_state, time_us(time_s))
        return VehicleCommandAck.VEHICLE_CMD_RESULT_ACCEPTED


def _round_half_away(value: float) -> int | None:
    if not math.isfinite(value):
        return None
    return int(math.floor(abs(value) + 0.5)) * (1 if value >= 0 else -1)


def motor_commands(msg: ActuatorMotors, motor_count: int) -> tuple[np.ndarray, np.ndarray]:
    """PX4's output mapping of ActuatorMotors.control (THR_MDL_FAC = 0): (command, running) per motor.
    Non-finite stops a motor; a negative value stops one not marked reversible; the rest is clamped
    to [0, 1] ([-1, 1] if reversible)."""
    control = np.asarray(msg.control, dtype=np.float64)[:motor_count]
    reversible = np.array([(int(msg.reversible_flags) >> i) & 1 == 1 for i in range(motor_count)])
    finite = np.isfinite(control)
    running = finite & (reversible | (control >= -np.finfo(np.float32).eps))
    low = np.where(reversible, -1.0, 0.0)
    command = np.where(running, np.clip(np.where(finite, control, 0.0), low, 1.0), 0.0)
    return command, running
