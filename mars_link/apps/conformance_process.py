"""`mars-link conformance --target process`: the conformance checks against a unit process over the network.

The unit is the process `sitl up` and `run --mode sitl` start (`python -m mars_link.processes.lockstep
unit`, a 1x1 docked set-up, `--conformance-harness`), with its own firmware, links, logs and status
file. The harness plays the two parties it talks to, so the checks stay judged in simulated time:

  its world            the in-process world of `conformance_bench.Bench`, stepped by the engine with the unit
                       seen over its HIL link as the world process sees its units (engine_links.HilUnits):
                       each step's sensors go out as HIL datagrams, and the unit's HIL_ACTUATOR_CONTROLS
                       answer drives the world's motors and is the check's output
  its off-board computer  PX4's interface as rmw_zenoh samples on a Zenoh session (the unit's HIL link on the
                       same bus), or the MAVLink persona's frames on its coordinator link over UDP

In each step the sensors go out first; as a coordinator, the harness (the engine's command source) waits
until the unit forwards that step's IMU sample before it sends its messages, and closes a step it sent no
rotor command for with the coordinator's step skip: the unit dates every message with the step's clock
and answers once the step's messages are in, so the figures equal the in-process ones. What the unit says
of itself (armed, its drop counters) comes from its status file, written once a second of wall time: the
harness waits for a fresh one. The documented bounds (COM_OF_LOSS_T, MARS_CMD_MISS) are the firmware's
parameters as built for the same scenario.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mars_link.apps.conformance_bench import Bench
from mars_link.core.errors import EnvironmentFailure
from mars_link.mavlink.wire import usec
from mars_link.processes.engine_links import HilUnits, LinksEnded

UNIT_START_S = 60.0  # the longest a unit process may take to say hello (imports on a loaded machine)
ANSWER_WAIT_S = 10.0  # the longest a step waits for the unit's answer before the harness gives up
ACK_WAIT_S = 2.0  # the longest a command waits for its ack (None after it, as in process)
WARM_UP_STEPS = 10  # steps before a check: the unit has a state (its pre-arm checks need one)
STATUS_WAIT_S = 5.0  # the longest a fresh status file may take (the unit writes one a second)
SIGNING_KEY_ENV = "MARS_LINK_SIGNING_KEY"  # (not handed down: the harness's links are unsigned)


@dataclasses.dataclass
class UnitProcessStop:
    """The stop flag `HilUnits` watches while it waits for the unit's answer: requested once the unit
    process has ended (the step then ends at once, not after ANSWER_WAIT_S); `ended` is set by a
    coordinator's shutdown, which nobody sends here."""

    proc: subprocess.Popen
    ended: bool = False

    @property
    def requested(self) -> bool:
        return self.proc.poll() is not None


class UnitProcessBench(Bench):
    """`Bench` with the unit in its own process: the same steps, checks and figures, over the network."""

    def __init__(self, interface: str, broken_keepalive: bool = False) -> None:
        super().__init__(interface, broken_keepalive)
        from mars_link.processes.links import LOOPBACK, Link, Ports
        from mars_link.processes.engine_links import COORDINATOR_SYSID, WORLD_SYSID
        from mars_link.processes.lockstep import BROKEN_KEEPALIVE_ENV, _await_peers
        from mars_link.processes.parent_watch import child_env
        from mars_link.processes.sitl_mode import write_scenario_copy
        from mars_link.transport import LinkSpec

        from mars_link.mavlink.wire import new_mav

        self._mav_skip = new_mav(COORDINATOR_SYSID)  # (its own sequence numbers: the recorded stream stays as sent)
        self._rotor_stamped = False
        self._pending_frames: list[bytes] = []  # the step's MAVLink frames not sent yet
        self._telemetry_usec = -1  # the last step the unit forwarded its IMU sample of
        self.proc: subprocess.Popen | None = None
        self.ports: Ports | None = None
        self.px4_acks = None
        self._pubs: dict[str, object] = {}
        self.dir = Path(tempfile.mkdtemp(prefix="mars-link-conformance-"))
        try:
            path = write_scenario_copy(self.scenario, self.dir / "scenario.toml")  # (the unit builds the same one)
            if interface == "px4-zenoh":  # the unit connects to the harness's session (loopback, plain TCP)
                from mars_link.transport.zenoh_link import free_tcp_port

                endpoint = f"tcp/{LOOPBACK}:{free_tcp_port()}"
                mine = LinkSpec("zenoh", zenoh_mode="peer", listen=(endpoint,), insecure=True, unit_interface=interface)
                theirs = LinkSpec("zenoh", zenoh_mode="peer", connect=(endpoint,), insecure=True,
                                  unit_interface=interface)
                self.ports = Ports(link=mine)
                ports_args = ["--world-port", "0", "--coordinator-port", "0"]
            else:  # UDP: the harness binds the world's and the coordinator's ports, the unit sends to them
                socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
                for s in socks:
                    s.bind((LOOPBACK, 0))
                world_port, coordinator_port = (s.getsockname()[1] for s in socks)
                theirs = LinkSpec("udp", unit_interface=interface)
                self.ports = Ports(world_port, coordinator_port, socks[0].detach(), socks[1].detach(), LinkSpec("udp"))
                ports_args = ["--world-port", str(world_port), "--coordinator-port", str(coordinator_port)]
            self.world_link = Link(self.ports.open("world"), WORLD_SYSID)
            self.coordinator_link = Link(self.ports.open("coordinator"), COORDINATOR_SYSID)
            env = {k: v for k, v in child_env().items() if k != SIGNING_KEY_ENV}
            if broken_keepalive:
                env[BROKEN_KEEPALIVE_ENV] = "1"  # the test switch, in the unit process itself
            argv = [sys.executable, "-m", "mars_link.processes.lockstep", "unit", str(path), *ports_args,
                    "--out", str(self.dir), "--unit", str(self.unit_id), "--steps", str(10**7), "--no-clients",
                    *theirs.to_args()]
            with open(self.dir / "unit.log", "w") as log:
                self.proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                             env=env)
            _await_peers(self.world_link, {self.unit_id}, UNIT_START_S)
            _await_peers(self.coordinator_link, {self.unit_id}, UNIT_START_S)
            self.world_link.prepare_peers([self.unit_id])
            if interface == "px4-zenoh":
                from mars_link.processes.px4_link import Px4CoordinatorLink

                self.px4_acks = Px4CoordinatorLink(self.ports.zenoh_session(), [self.unit_id])
                self.px4_acks.prepare(self.unit_id)  # (waits until the unit's subscribers match)
                from mars_link.px4.rmw_zenoh import data_key, vehicle_namespace

                for topic in (self._rz.OFFBOARD_CONTROL_MODE, self._rz.VEHICLE_COMMAND, self._rz.ACTUATOR_MOTORS):
                    self._publisher(data_key(topic, vehicle_namespace(self.unit_id)))
            self.hil_units = self._hil_units(self.proc)
            self.engine = self._engine(dataclasses.replace(self.flight, units=self.hil_units, coordinator=None))
            for _ in range(WARM_UP_STEPS):
                self.step()
        except SystemExit as exc:  # (_await_peers: the unit never said hello)
            self.close()
            raise EnvironmentFailure(f"conformance: the unit process did not start ({exc}); {self._log_tail()}") from None
        except BaseException:
            self.close()
            raise
        self.outputs.clear()
        self.recorded.clear()
        self.step_index = 0

    # ----------------------------------------------------------------- the loop
    def _hil_units(self, proc: subprocess.Popen) -> HilUnits:
        """The engine's units part: the unit behind the world link, as the world process sees its units
        (lockstep.run_world), unpaced; silent for ANSWER_WAIT_S, it is declared dead and the check ends."""
        from mars_link.runtime.pacing import Pacer

        vehicle = self.flight.model.vehicle
        return HilUnits(self.world, self.world_link, [self.unit_id], UnitProcessStop(proc), Pacer(0.0),
                        self.full_scale_n, 0.0 if vehicle.rotor_min_thrust_n is not None else -1.0,  # (as run_world)
                        coordinated=False, latch_sensor=False, unit_timeout_s=ANSWER_WAIT_S)

    def step(self, actions=None) -> np.ndarray:
        """One control period of the engine: the sensors out (HIL), the harness's messages, the unit's
        answer into the world's motors, physics."""
        try:
            return super().step(actions)
        except LinksEnded:  # (the unit process ended while the step waited for it)
            raise EnvironmentFailure(f"conformance: the unit process ended at t={self.t_s:.2f} s; "
                                     f"{self._log_tail()}") from None

    def _command_source(self, t_s: float, telemetry: list) -> list:
        """As a coordinator: once the unit has the step's sensors, the harness's messages, then the word
        that the step has no rotor command if none of them ran it; a step's MAVLink frames in one datagram."""
        t_us = usec(t_s)
        self._await_telemetry(t_us)  # the unit has taken the step's sensors before any command
        self._rotor_stamped = False
        super()._command_source(t_s, telemetry)
        if not self._rotor_stamped or self.interface == "mavlink":  # (a MAVLink command may be dropped: say
            # it anyway, in the same datagram after it; a command that ran the step leaves nothing to skip)
            self._skip_step(t_us)
        self._flush_mavlink()
        return []

    def on_step(self, engine, view) -> bool:
        """Observer: what came with the unit's answer (telemetry, acks), then the step's output. A unit the
        world declared dead (silent for ANSWER_WAIT_S) ends the check."""
        if self.unit_id in self.hil_units.dead:
            raise EnvironmentFailure(f"conformance: no answer from the unit process for t={view.t_s:.2f} s; "
                                     f"{self._log_tail()}")
        self._drain_coordinator(0.0)
        return super().on_step(engine, view)

    # ----------------------------------------------------------------- messages over the network
    def _skip_step(self, t_us: int) -> None:
        """The coordinator's word that it sends no rotor command for the step `t_us` (firmware
        `_on_step_skip`): the unit runs the step with what it holds, and keeps waiting for the next ones."""
        from pymavlink.dialects.v20 import common as mavlink

        from mars_link.mavlink import codec

        self._pending_frames.append(codec.encode(mavlink.MAVLink_system_time_message(t_us, t_us // 1000), self._mav_skip))

    def _flush_mavlink(self) -> None:
        """The step's MAVLink frames so far, in one datagram: as the coordinator sends a step's commands, so
        the unit runs the step after all of them (a rotor command alone would run it at once)."""
        if self._pending_frames:
            data, self._pending_frames = b"".join(self._pending_frames), []
            self.coordinator_link.send_bytes(data, self.coordinator_link.peers[self.unit_id])

    def send_raw(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        """One rmw_zenoh sample to the unit, recorded for a replay (its acks arrive on their own)."""
        if "/fmu/in/actuator_motors/" in key:
            from mars_link.px4 import cdr

            try:  # (an ActuatorMotors of this step runs it; an older one, replayed, does not)
                self._rotor_stamped |= int(cdr.decode("ActuatorMotors", payload).timestamp) == int(round(self.t_s * 1e6))
            except ValueError:
                pass
        self.recorded.append((self.step_index, key, payload, attachment))
        self._publisher(key).put(payload, attachment=attachment)  # type: ignore[attr-defined]

    def _publisher(self, key: str):
        """The harness's publisher on `key`, declared once and matched by the unit's subscriber (the unit's
        three inputs are declared before the first step: a step never waits on it, so the unit's own
        command timeout never runs out while the harness holds a step)."""
        pub = self._pubs.get(key)
        if pub is None:
            import zenoh

            assert self.ports is not None
            pub = self._pubs[key] = self.ports.zenoh_session().declare_publisher(
                key, express=True, congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + UNIT_START_S
            while not pub.matching_status.matching and time.monotonic() < deadline:  # type: ignore[attr-defined]
                time.sleep(0.005)
        return pub

    def _mavlink_send(self, msgs: list) -> None:
        from firmware_models.vehicle import LINK_COORDINATOR
        from mars_link.mavlink import codec

        data = b"".join(codec.encode(m, self._mav) for m in msgs)
        self.recorded.append((self.step_index, LINK_COORDINATOR, data, None))
        self._pending_frames.append(data)  # (sent with the step's last frames, or before a command's ack)

    def replay(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        if self.interface == "px4-zenoh":
            self.send_raw(key, payload, attachment)
        else:
            self._pending_frames.append(payload)

    def _await_telemetry(self, t_us: int) -> None:
        """Until the unit forwards the step's IMU sample (HIGHRES_IMU of that time) on its coordinator link:
        then it holds the step's sensors and its clock reads the step, so what the harness sends next is
        dated as in process, whichever of its links the unit reads first."""
        deadline = time.monotonic() + ANSWER_WAIT_S
        while not self._telemetry_usec >= t_us:
            if time.monotonic() > deadline or (self.proc is not None and self.proc.poll() is not None):
                raise EnvironmentFailure(f"conformance: no telemetry from the unit process for t={t_us / 1e6:.2f} s; "
                                         f"{self._log_tail()}")
            self._drain_coordinator(0.5)

    def _drain_coordinator(self, timeout_s: float) -> None:
        """Every frame waiting on the unit's coordinator link (telemetry, COMMAND_ACK; the first wait up to
        `timeout_s`) and PX4's acks."""
        msgs = self.coordinator_link.receive(timeout_s)
        while msgs:
            for m in msgs:
                if m.get_type() == "COMMAND_ACK":
                    self.acks.append((int(m.command), int(m.result)))
                elif m.get_type() == "HIGHRES_IMU":
                    self._telemetry_usec = max(self._telemetry_usec, int(m.time_usec))
            msgs = self.coordinator_link.receive(0.0)
        if self.px4_acks is not None:
            self.acks += [(int(a.command), int(a.result)) for _, a in self.px4_acks.acks()]

    def command(self, command: int, param1: float, param2: float = 0.0) -> int | None:
        """As in process; the ack comes over the network (the unit answers a command on receipt)."""
        self._drain_coordinator(0.0)
        self.acks.clear()
        if self.interface == "px4-zenoh":
            from mars_link.px4.commander import Px4Commander

            msg = Px4Commander(self.unit_id, self.full_scale_n)._command(int(round(self.t_s * 1e6)), command, param1, param2)
            self._px4_send(self._rz.VEHICLE_COMMAND, msg)
        else:
            from pymavlink.dialects.v20 import common as mavlink

            self._mavlink_send([mavlink.MAVLink_command_long_message(self.unit_id, 1, command, 0, param1, param2,
                                                                     0, 0, 0, 0, 0)])
            self._flush_mavlink()  # (with the step's earlier frames: its answer is awaited now)
        deadline = time.monotonic() + ACK_WAIT_S
        while time.monotonic() < deadline:
            found = next((r for c, r in self.acks if c == command), None)
            if found is not None:
                return found
            self._drain_coordinator(0.01)
        return None

    # ----------------------------------------------------------------- what the unit says of itself
    def _status(self) -> dict:
        """The unit's status file, written after now (it holds every step so far: the unit waits for the next)."""
        path = self.dir / f"unit{self.unit_id}_status.json"
        asked = time.time()
        deadline = time.monotonic() + STATUS_WAIT_S
        while time.monotonic() < deadline:
            try:
                doc = json.loads(path.read_text())
                if doc.get("wall_time_s", 0.0) > asked:
                    return doc
            except (OSError, ValueError):
                pass
            self._drain_coordinator(0.05)
        raise EnvironmentFailure(f"conformance: no fresh status from the unit process in {STATUS_WAIT_S:.0f} s")

    @property
    def failed_safe(self) -> bool:
        status = self._status()
        return not status["armed"] or (self.interface == "mavlink" and status["source"] == "own")

    def drops(self, reason: str) -> int:
        return int(self._status().get("drops", {}).get(reason, 0))

    def reordered(self) -> int:
        return int(self._status().get("stats", {}).get("px4.reordered", 0))

    def _log_tail(self) -> str:
        try:
            lines = [ln for ln in (self.dir / "unit.log").read_text(errors="replace").splitlines() if ln.strip()]
        except OSError:
            return "no unit log"
        return f"unit log: {lines[-1][:300]}" if lines else "unit log empty"

    def close(self) -> None:
        """End the unit process (by its PID: SIGTERM, then SIGKILL), the links, the temporary directory."""
        proc, self.proc = self.proc, None
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for name in ("world_link", "coordinator_link"):
            link = self.__dict__.pop(name, None)
            if link is not None:
                link.close()
        if self.px4_acks is not None:
            self.px4_acks.close()
            self.px4_acks = None
        for pub in self._pubs.values():
            try:
                pub.undeclare()  # type: ignore[attr-defined]
            except Exception:  # (a session already closing)
                pass
        self._pubs.clear()
        if self.ports is not None:
            self.ports.close()
            self.ports = None
        shutil.rmtree(self.dir, ignore_errors=True)
