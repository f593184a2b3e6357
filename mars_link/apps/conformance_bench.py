"""The conformance harness's bench: one unit's firmware on the ground in the in-process world, commanded
with wire bytes (the checks: mars_link.apps.conformance; the same bench with the unit in its own process:
mars_link.apps.conformance_process).

The flight's one loop steps it (mars_link.flight.engine.Engine): the harness's messages of a step are the
engine's command source, which returns no rotor command (the unit takes its commands from the harness's
wire bytes, and the units part drives it on what it holds), and the bench, an observer, records what the
unit drove its motors to."""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from mars_link.mavlink.codec import decode_frames
from mars_link.mavlink.wire import new_mav

if TYPE_CHECKING:
    from mars_link.core.messages import RotorCommand, SensorPacket
    from mars_link.flight.engine import Engine, Flight, StepView

CONTROL_HZ = 100.0
CONTROLS = (0.20, 0.25, 0.30, 0.35)  # below hover: the unit stays on the ground with its rotors spinning
TEMPORARILY_REJECTED = 1  # MAV_RESULT / VehicleCommandAck result: refused for now, may be sent again
MODE_RETRIES = 5  # DO_SET_MODE sent again (with a fresh keep-alive) while the unit refuses it for now


class Bench:
    """One unit on the ground in lockstep, commanded over `interface` with wire bytes."""

    def __init__(self, interface: str, broken_keepalive: bool = False) -> None:
        from mars_link.config.scenario import Scenario
        from mars_link.flight.build import build_flight

        self.interface = interface
        sc = Scenario(name="conformance", layout=("X",), source="<conformance>")
        sc.sim.control_hz = CONTROL_HZ
        sc.sim.duration_s = 600.0
        self.scenario = sc
        self.flight = build_flight(sc, 0)
        self.world = self.flight.world
        self.unit_id = 1
        self.vehicle = self.flight.units.vehicles[self.unit_id]
        self.vehicle.px4_service.keepalive_timeout = not broken_keepalive
        self.full_scale_n = self.vehicle.full_scale_n
        self.dt_s = 1.0 / CONTROL_HZ
        self.t_s = 0.0
        self.outputs: list[tuple[float, np.ndarray]] = []  # (t, motor setpoint N) of every step
        self.recorded: list[tuple[int, str, bytes, bytes | None]] = []  # (step, key, payload, attachment) sent
        self.acks: list[tuple[int, int]] = []  # (command, result)
        if interface == "px4-zenoh":
            from mars_link.px4 import rmw_zenoh as rz

            self._rz = rz
            self._seq: dict[str, object] = {}
            self.vehicle.px4_service.ensure_interface()
        else:
            self._mav = new_mav(201)
        self.step_index = 0
        self.last_keepalive_s: float | None = None  # when the unit last heard its keep-alive
        self._rotor_slots = self.flight.model.unit_slots(self.unit_id)  # the unit's rotors in the world
        self._actions: Callable[["Bench"], None] | None = None  # the harness's messages of the step under way
        self.engine = self._engine(self.flight)

    # ----------------------------------------------------------------- the loop
    def _engine(self, flight: "Flight") -> "Engine":
        """The flight's one loop over `flight`'s world and units: the harness's messages its command source,
        the bench its observer."""
        from mars_link.flight.engine import Engine

        return Engine(flight, [self], command_source=self._command_source)

    def step(self, actions: Callable[["Bench"], None] | None = None) -> np.ndarray:
        """One control period of the engine: sensors into the unit, the harness's messages (`actions`), the
        unit's motors, physics; what the unit drove its motors to."""
        self._actions = actions
        try:
            if not self.engine.step():
                raise RuntimeError(f"conformance: the bench's flight is over at t={self.t_s:.2f} s")
        finally:
            self._actions = None
        self.step_index += 1
        return self.outputs[-1][1]

    def _command_source(self, t_s: float, telemetry: "list[SensorPacket]") -> "list[RotorCommand]":
        """The engine's command stage: the harness's messages of the step, as wire bytes into the unit. No
        rotor command: the units part drives the unit on what it took (as every unit answers every step)."""
        self.t_s = t_s
        if self._actions is not None:
            self._actions(self)
        return []

    def on_step(self, engine: "Engine", view: "StepView") -> bool:
        """Observer: the step's output, what the unit drove its motors to (the world's setpoints of its
        rotors, as its answer set them)."""
        self.outputs.append((view.t_s, self.world.rotor_setpoint_n[self._rotor_slots].copy()))
        return False

    def run(self, seconds: float, actions: Callable[["Bench"], None] | None = None) -> None:
        for _ in range(int(round(seconds * CONTROL_HZ))):
            self.step(actions)

    # ----------------------------------------------------------------- messages (wire bytes)
    def _px4_send(self, topic, message) -> None:
        from mars_link.px4 import cdr
        from mars_link.px4.rmw_zenoh import PublisherSequence, data_key, unit_gid, vehicle_namespace

        key = data_key(topic, vehicle_namespace(self.unit_id))
        seq = self._seq.setdefault(key, PublisherSequence(unit_gid(201, key)))
        self.send_raw(key, cdr.encode(message), seq.next(int(round(self.t_s * 1e9))))  # type: ignore[attr-defined]

    def send_raw(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        """One rmw_zenoh sample into the unit, recorded for a replay."""
        from mars_link.px4 import cdr

        self.recorded.append((self.step_index, key, payload, attachment))
        _, replies = self.vehicle.px4_service.sample(key, payload, attachment, self.t_s)
        for reply_key, reply_payload, _ in replies:
            if "/fmu/out/vehicle_command_ack/" in reply_key:
                ack = cdr.decode("VehicleCommandAck", reply_payload)
                self.acks.append((int(ack.command), int(ack.result)))

    def _mavlink_send(self, msgs: list) -> None:
        from firmware_models.vehicle import LINK_COORDINATOR
        from mars_link.mavlink import codec

        data = b"".join(codec.encode(m, self._mav) for m in msgs)
        self.recorded.append((self.step_index, LINK_COORDINATOR, data, None))
        self._mavlink_receive(self.vehicle.handle(data, self.t_s, link=LINK_COORDINATOR))

    def _mavlink_receive(self, out) -> None:
        parser = new_mav(255)
        for o in out:
            for m in decode_frames(o.data, parser):
                if m.get_type() == "COMMAND_ACK":
                    self.acks.append((int(m.command), int(m.result)))

    def keepalive(self) -> None:
        """PX4: OffboardControlMode(direct_actuator). MAVLink: none of its own (the command is the keep-alive)."""
        if self.interface == "px4-zenoh":
            from mars_link.px4.cdr import OffboardControlMode

            self._px4_send(self._rz.OFFBOARD_CONTROL_MODE,
                           OffboardControlMode(timestamp=int(round(self.t_s * 1e6)), direct_actuator=True))
            self.last_keepalive_s = self.t_s

    def motors(self, controls) -> None:
        """The per-rotor command: ActuatorMotors / SET_ACTUATOR_CONTROL_TARGET, controls = thrust / full scale."""
        if self.interface == "px4-zenoh":
            from mars_link.px4.cdr import ActuatorMotors

            control = np.full(12, np.nan, dtype=np.float32)
            control[:4] = controls
            stamp = int(round(self.t_s * 1e6))
            self._px4_send(self._rz.ACTUATOR_MOTORS, ActuatorMotors(timestamp=stamp, timestamp_sample=stamp,
                                                                    control=control))
        else:
            from pymavlink.dialects.v20 import common as mavlink

            self._mavlink_send([mavlink.MAVLink_set_actuator_control_target_message(
                int(round(self.t_s * 1e6)), 0, self.unit_id, 1, [*map(float, controls), 0.0, 0.0, 0.0, 0.0])])
            self.last_keepalive_s = self.t_s

    def command(self, command: int, param1: float, param2: float = 0.0) -> int | None:
        """ARM (400) or DO_SET_MODE (176); the result of its ack (None: no ack)."""
        self.acks.clear()
        if self.interface == "px4-zenoh":
            from mars_link.px4.commander import Px4Commander

            msg = Px4Commander(self.unit_id, self.full_scale_n)._command(
                int(round(self.t_s * 1e6)), command, param1, param2)
            self._px4_send(self._rz.VEHICLE_COMMAND, msg)
        else:
            from pymavlink.dialects.v20 import common as mavlink

            self._mavlink_send([mavlink.MAVLink_command_long_message(self.unit_id, 1, command, 0, param1, param2,
                                                                     0, 0, 0, 0, 0)])
        return next((r for c, r in self.acks if c == command), None)

    def take_over(self, controls=CONTROLS) -> bool:
        """Keep-alive, OFFBOARD, ARM (PX4; the MAVLink persona needs its rotor command before OFFBOARD),
        and a first command; True if both were accepted."""
        self.keepalive()
        if self.interface == "px4-zenoh":
            mode = self.command(176, 1.0, 6.0)
            for _ in range(MODE_RETRIES):  # (over a network only: samples on different keys may overtake each
                # other, as over DDS; a DO_SET_MODE that arrived before its keep-alive is refused for now, and an
                # off-board computer sends both again, as the coordinator does. Simulated time stands still.)
                if mode != TEMPORARILY_REJECTED:
                    break
                self.keepalive()
                mode = self.command(176, 1.0, 6.0)
            arm = self.command(400, 1.0)
            self.motors(controls)
        else:
            arm = self.command(400, 1.0)
            self.motors(controls)
            mode = self.command(176, 1.0, 6.0)
        return mode == 0 and arm == 0

    def stream(self, controls=CONTROLS) -> Callable[["Bench"], None]:
        """Per-step actions of a live off-board computer: the keep-alive at 10 Hz and the command."""
        def act(b: "Bench") -> None:
            if b.step_index % 10 == 0:
                b.keepalive()
            b.motors(controls)
        return act

    def commanded_n(self, controls=CONTROLS) -> np.ndarray:
        return np.array(controls, dtype=np.float32).astype(float) * self.full_scale_n

    def follows(self, thrust_n: np.ndarray, controls=CONTROLS) -> bool:
        return bool(np.allclose(thrust_n, self.commanded_n(controls), rtol=1e-5, atol=1e-6))

    @property
    def loss_bound_s(self) -> float:
        p = self.vehicle.params
        if self.interface == "px4-zenoh":
            return float(p["COM_OF_LOSS_T"])
        return float(p["MARS_CMD_MISS"]) / float(p["MARS_CMD_HZ"])

    @property
    def failed_safe(self) -> bool:
        """PX4: disarmed. MAVLink persona: disarmed or landing under its own control (MARS_FS_ACT)."""
        v = self.vehicle
        return not v.armed or (self.interface == "mavlink" and v.source == "own")

    # ----------------------------------------------------------------- what the unit says of itself
    def drops(self, reason: str) -> int:
        """How many inputs the unit dropped for `reason` (its drop counters, e.g. intake.non_finite)."""
        return int(self.vehicle.drop_counts().get(reason, 0))

    def reordered(self) -> int:
        """PX4 samples the unit counted as stale or reordered (its endpoint; as PX4, handed on)."""
        endpoint = self.vehicle.px4_service.endpoint
        return 0 if endpoint is None else int(endpoint.reordered)

    def motor_ceiling_n(self) -> float:
        """The most thrust the unit's motor model gives a rotor (what an over-range control is clamped to)."""
        return float(self.vehicle.motors.setpoint(np.full(4, 2.0 * self.full_scale_n))[0])

    def replay(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        """One recorded message again, as it was sent (PX4: the sample; MAVLink: the frames on `key`'s link)."""
        if self.interface == "px4-zenoh":
            self.send_raw(key, payload, attachment)
        else:
            self._mavlink_receive(self.vehicle.handle(payload, self.t_s, link=key))

    def close(self) -> None:
        """Nothing to end in process (a unit process ends here: conformance_process)."""
