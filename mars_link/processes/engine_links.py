"""The parts of a flight that a process does not host, as proxies over its MAVLink links: what the engine
(mars_link.flight.engine.Engine, WorldPart / UnitsPart) steps in the SITL processes of mars_link.processes.lockstep.

The coordinator process sees the world and the units behind its link (`LinkedUnits`: their telemetry in,
its commands out); the world process sees the units behind its HIL link (`HilUnits`: their sensors out,
their motor outputs in). Here too the frames and checks of those links that only the lockstep uses: the
world's step-sent marker, the coordinator's shutdown of a flight of pieces, the take-over of a unit with
its first command, and what is dropped as untrusted input. A `stop` is the process's stop flag (requested:
SIGTERM/SIGINT; ended: the coordinator's shutdown reached the world).
"""

from __future__ import annotations

import math
import os
import select
import sys
import time

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.events import unit_died
from mars_link.core.messages import BatterySample, EscSample, SensorPacket
from mars_link.mavlink.wire import (
    LatchSensor,
    SensorPacketAssembler,
    actuator_output_from_message,
    battery_from_message,
    battery_report_message,
    latch_message,
    rotor_command_message,
    sensor_packet_messages,
    usec,
)
from mars_link.mavlink.esc_status import esc_from_message
from mars_link.processes.links import Link
from mars_link.runtime.pacing import Pacer, SilenceDeadline
from mars_link.runtime.scheduling import OverloadValve

WORLD_SYSID = 200
COORDINATOR_SYSID = 201
COORDINATOR_TIMEOUT_S = 1.0
WORLD_UNIT_TIMEOUT_S = 3.0
WORLD_IDLE_TIMEOUT_S = 30.0  # coordinator: no telemetry from any unit for this long = the world is gone
ANSWER_READ_PHASE = 0.5  # paced world: first read of the units' answers, as a fraction of the period
COORDINATOR_QUIET_S = 0.002  # coordinator: fault detection this long after the commands went out
PX4_TAKEOVER_WAIT_S = 2.0  # coordinator: longest wait for a unit's acks to arm and enter OFFBOARD
PX4_TAKEOVER_ROUND_S = 0.5  # coordinator: longest wait for one round of those acks
STOP_POLL_S = 0.2  # world: longest wait before it looks at its stop flag again (a SIGTERM ends it in time to
# write its summary within the launcher's 3 s grace, also while it waits for units that were stopped with it)


class LinksEnded(Exception):
    """A process's links end the flight before its end: stopped (SIGTERM), the coordinator's shutdown of a
    flight of pieces (the world), or the world gone silent (the coordinator)."""


def shutdown_message() -> mavlink.MAVLink_message:
    """The coordinator ends a flight of pieces: MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (param1 2 = shut down, as
    PX4's SITL ends) to the world, sent instead of the first step not to be flown: the world, waiting for
    that step's answers (which the units give only once the coordinator's commands are in), ends without
    stepping, whatever the transport's ordering."""
    return mavlink.MAVLink_command_long_message(WORLD_SYSID, 1, mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0,
                                                2, 0, 0, 0, 0, 0, 0)


def step_sent_message(t_us: int) -> mavlink.MAVLink_message:
    """The world to the coordinator, after it has sent every live unit its sensors for step `t_us`:
    SYSTEM_TIME stamped with the step's simulation time. The coordinator starts a step's silence deadline
    only once this is in, so a world stopped or descheduled between two units' sensor datagrams (the
    units it had not reached yet are silent through no fault of theirs) loses nobody."""
    return mavlink.MAVLink_system_time_message(t_us, t_us // 1000)


def step_sent_packer(link: Link):
    """t_us -> the world's step-sent frame, through the world link's own encoder: signed when the run is
    (one signing stream per sender and link id, so its time stamps only grow)."""

    def pack(t_us: int) -> bytes:
        return link.pack([step_sent_message(t_us)])
    return pack


#: test hook "T_S:SECONDS": the world sleeps SECONDS after sending the first unit its sensors of the first
#: step at or after T_S (a world stopped or descheduled between two units' datagrams; tests/processes/test_sitl_pause.py)
STALL_ENV = "MARS_LINK_TEST_WORLD_STALL"


def _stall_from_env() -> tuple[float, float] | None:
    at, _, seconds = os.environ.get(STALL_ENV, "").partition(":")
    try:
        return float(at), float(seconds)
    except ValueError:
        return None


def _step_sent_us(m) -> int | None:
    """The step a world's step-sent marker names (None: not one)."""
    if m.get_type() == "SYSTEM_TIME" and m.get_srcSystem() == WORLD_SYSID:
        return int(m.time_unix_usec)
    return None


def _is_shutdown(m) -> bool:
    return (m.get_type() == "COMMAND_LONG" and m.get_srcSystem() == COORDINATOR_SYSID
            and m.target_system == WORLD_SYSID and m.command == mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN
            and m.param1 == 2)


def telemetry_ok(p: SensorPacket) -> bool:
    """A unit's forwarded sensor packet is finite where it matters (IMU, position, truth)."""
    arrays = [p.imu.gyro_frd_radps, p.imu.accel_frd_mps2]
    if p.position is not None:
        arrays.append(p.position.position_ned_m)
    if p.truth is not None:
        arrays += [p.truth.position_ned_m, p.truth.quaternion_wxyz]
    return math.isfinite(p.t_s) and all(bool(np.isfinite(a).all()) for a in arrays)


def actuator_controls_ok(controls, control_min: float = 0.0) -> bool:
    """A unit's HIL_ACTUATOR_CONTROLS rotor outputs (controls[0..3]) are finite and within
    control_min..1 of full scale (the world never integrates a broken unit's NaN)."""
    c = controls[:4]
    return len(c) == 4 and all(math.isfinite(x) and control_min <= x <= 1.0 for x in c)


def unit_sensor_messages(world, p: SensorPacket, extra: list | None = None) -> list:
    """One unit's HIL datagram of a step, as the world sends it: ground truth for the unit's own telemetry
    at the mocap rate (when the sensor packet carries none), `extra` (the latch sensor), the power module's
    sample at the battery rate, the sensors."""
    from sitl.hil import hil_state_message

    msgs = [] if p.truth is not None or (p.position is None and p.gps is None) else [
        hil_state_message(world.unit_truth(p.unit_id), usec(p.t_s))]
    msgs += extra or []
    if p.battery is not None:
        msgs.append(battery_report_message(p.battery))
    return msgs + sensor_packet_messages(p)


class HilUnits:
    """The units as the world process sees them, behind its HIL link: the engine's units part
    (mars_link.flight.engine.UnitsPart) in the process that hosts the world.

    Taking the world's sensors is sending each live unit its HIL datagram (with the latch sensor on change
    in a flight of pieces), sampled and encoded before the pacing wait so that at t they only go out, then
    telling the coordinator every unit has the step (step_sent_message). The units' telemetry goes to the
    coordinator's process, not back here. Driving is receiving every live unit's HIL_ACTUATOR_CONTROLS for the
    step into the world (from mid-period on when paced, so the world is not woken once per unit while the units
    and the coordinator work on the step); a unit silent for `unit_timeout_s` is dead (`kill`: motors off, the
    flight goes on). A stop (SIGTERM) or the coordinator's shutdown ends the flight mid-step: LinksEnded."""

    def __init__(self, world, link: Link, unit_ids: list[int], stop, pacer: Pacer, scale_n: float,
                 control_min: float, coordinated: bool, latch_sensor: bool, feed=None,
                 unit_timeout_s: float = WORLD_UNIT_TIMEOUT_S, records=None) -> None:
        self.world, self.link, self.stop, self.pacer = world, link, stop, pacer
        self.scale_n, self.control_min, self.latch_sensor, self.feed = scale_n, control_min, latch_sensor, feed
        self.records = records  # the coordinator's step records (step_record.StepRecords), awaited each step
        self.unit_timeout_s = unit_timeout_s
        self.live = set(unit_ids)
        self.deaths: list[dict] = []
        self.dead: set[int] = set()
        self.latch_sent: dict[int, int] = {}  # the latch mask each unit last heard
        self.coordinator_addr = link.peers.get(COORDINATOR_SYSID) if coordinated else None
        self.step_sent = step_sent_packer(link)
        self.stall = _stall_from_env()
        self.valve = OverloadValve()  # (armed in SCHED_FIFO only)
        self.answer_after_s = ANSWER_READ_PHASE / world.config.exchange_hz

    def take_sensors(self, packets: list[SensorPacket]) -> list[SensorPacket]:
        link, world, pacer = self.link, self.world, self.pacer
        t = world.t_s
        datagrams = []
        for p in packets:
            if p.unit_id in self.live:
                latch = []
                if self.latch_sensor and self.latch_sent.get(p.unit_id) != p.latches:  # the latch sensor, on change
                    self.latch_sent[p.unit_id] = p.latches
                    latch = [latch_message(p.t_s, p.latches)]
                datagrams.append((link.pack(unit_sensor_messages(world, p, latch)), link.peers[p.unit_id]))
        pacer.wait(t)
        if self.valve.armed and self.valve.check(behind_s := -pacer.wait_s(t), t):
            print(f"world: {behind_s:.1f} s behind the wall clock at t={t:.2f}: leaving SCHED_FIFO, so that the "
                  "flight shares the machine", file=sys.stderr)
        for i, (data, addr) in enumerate(datagrams):
            link.send_bytes(data, addr)
            if i == 0 and self.stall is not None and t >= self.stall[0]:  # (test hook: stopped between two units)
                time.sleep(self.stall[1])
                self.stall = None
        if self.coordinator_addr is not None:  # every unit has its step: the coordinator may now time them
            link.send_bytes(self.step_sent(usec(t)), self.coordinator_addr)
        return []

    def drive(self, commands) -> None:
        """(`commands` is empty: the coordinator's go to the units directly.)"""
        link, world, stop = self.link, self.world, self.stop
        t = world.t_s
        if self.pacer.paced:
            time.sleep(max(0.0, self.pacer.wait_s(t + self.answer_after_s)))
        waiting = set(self.live)
        deadline = SilenceDeadline(self.unit_timeout_s)  # (time this process did not run is nobody's silence)
        t_us = usec(t)
        records = self.records
        while (waiting or records is not None and records.awaited(t_us)) and not (stop.requested or stop.ended):
            left = deadline.left_s()
            deadline.before_wait(min(left, STOP_POLL_S))
            msgs = link.receive(min(left, STOP_POLL_S))  # (a SIGTERM is seen within STOP_POLL_S)
            if not msgs and left == 0.0:  # (past the deadline, what was already queued is read first:
                break  # after this process itself was stopped, the answers wait in its socket)
            for m in msgs:
                if _is_shutdown(m):
                    stop.ended = True
                    break
                if m.get_type() != "HIL_ACTUATOR_CONTROLS":
                    if m.get_srcSystem() == COORDINATOR_SYSID and not (records is not None and records.take(m)) \
                            and self.feed is not None:
                        self.feed.take(m)
                    continue
                if m.time_usec != t_us or m.get_srcSystem() not in waiting:
                    link.drop("stale_actuator")
                    continue
                if not actuator_controls_ok(m.controls, self.control_min):
                    link.drop("bad_actuator")  # NaN/inf/out of range: never into the physics
                    continue
                world.actuate(actuator_output_from_message(m, self.scale_n))
                waiting.discard(m.get_srcSystem())
        if stop.requested or stop.ended:
            raise LinksEnded
        if records is not None and records.awaited(t_us):  # (recorded without it; awaited again once one comes)
            records.live = False
            print(f"world: no step record from the coordinator for {self.unit_timeout_s:.1f} s at t={t:.2f}",
                  file=sys.stderr)
        for unit in sorted(waiting):  # silent units are dead: motors off, the flight goes on
            self.kill(unit)
            self.deaths.append(unit_died(t, unit))
            print(f"world: unit {unit} silent for {self.unit_timeout_s:.1f} s at t={t:.2f}: declared dead", file=sys.stderr)

    def kill(self, unit_id: int) -> None:
        self.world.declare_dead(unit_id)
        self.live.discard(unit_id)
        self.dead.add(unit_id)


class LinkedUnits:
    """The world and the units as the coordinator process sees them, behind its link: the engine's world and
    units parts (mars_link.flight.engine.WorldPart, UnitsPart) in a process that hosts neither.

    The units forward the world's samples as their telemetry, so the step's sensing is receiving that
    telemetry, and the step's time is its time: reading `t_s` waits for it. A unit that stays silent for
    `unit_timeout_s` once the first telemetry of the step came in and the world said it had sent every unit
    the step (step_sent_message; a world that sends no such marker: from the first telemetry) is lost, told
    to the coordinator at sensing (`Coordinator.unit_lost`); before that, the world may be waiting for a
    dead unit (it drives the clock), or be stopped between two units' sensors. Driving is sending each live
    unit its rotor command (with the take-over until the unit acknowledged it, or over PX4's interface);
    advancing is the world's. `finish_step` (the coordinator's fault detection) runs COORDINATOR_QUIET_S
    after the commands went out, while the next step's telemetry is awaited: the units need the CPUs first."""

    def __init__(self, link: Link, unit_ids: list[int], scale_n: float, stop, on_lost,
                 unit_timeout_s: float = COORDINATOR_TIMEOUT_S, finish_step=None, hosted=None, px4=None,
                 commanders: dict | None = None) -> None:
        self.link, self.scale_n, self.stop, self.on_lost = link, scale_n, stop, on_lost
        self.unit_timeout_s, self.finish_step, self.hosted = unit_timeout_s, finish_step, hosted
        self.px4, self.commanders = px4, commanders
        self.live = set(unit_ids)
        self.lost: list[dict] = []
        self.accepted: dict[int, set[int]] = {u: set() for u in unit_ids}  # commands each unit acknowledged
        self.assembler, self.latches = SensorPacketAssembler(), LatchSensor()
        self.batteries: dict[int, BatterySample] = {}  # each unit's last BATTERY_STATUS, until its packet comes
        self.escs: dict[int, EscSample] = {}  # ... and ESC_STATUS
        self.world = link.peers[WORLD_SYSID]
        self.steps = 0
        self.next_hello = time.monotonic() + 0.2
        self.finish_at: float | None = None  # when the last period's fault detection runs
        self.t_last = -math.inf  # the last step's time: a packet not newer is a backlog (a paused unit resumed)
        self.world_marks, self.world_sent_us = False, -1  # the world's step-sent markers: seen any, the latest step
        self._t: float | None = None  # this step's time, once its telemetry is in
        self._packets: dict[int, SensorPacket] = {}
        # wall-clock times of the step (coordinator_timing.csv): first and last telemetry in, commands
        # computed and sent; CPU time of the step and of the sends
        self.first_wall = self.all_wall = self.computed_wall = self.sent_wall = 0.0
        self.step_cpu = self.send_cpu = self._cpu_mark = 0.0

    # -- the world part
    @property
    def t_s(self) -> float:
        if self._t is None:
            self._t = self._receive_step()
        return self._t

    def sense(self) -> list[SensorPacket]:
        """The step's telemetry, unit by unit; the units silent past their deadline lost."""
        t, packets = self.t_s, self._packets
        for unit in sorted(self.live - set(packets)):
            self.live.discard(unit)
            self.lost.append({"t_s": round(t, 6), "unit": unit})
            print(f"coordinator: unit {unit} silent for {self.unit_timeout_s:.1f} s at t={t:.2f}: lost", file=sys.stderr)
            self.on_lost(unit, t)
        return [packets[u] for u in sorted(packets)]

    def truth(self) -> None:
        return None  # (the world's, in its process)

    def advance(self) -> None:
        self._t = None
        self.steps += 1

    # -- the units part
    def take_sensors(self, packets: list[SensorPacket]) -> list[SensorPacket]:
        return packets  # (the units took the world's samples in their processes: this is their telemetry)

    def kill(self, unit_id: int) -> None:
        """(A unit process dies for real here: `sense` finds it silent.)"""

    def drive(self, commands) -> None:
        """Every live unit's command, all encoded first, then sent back to back (a woken unit may take the CPU)."""
        link, t, live, px4, hosted = self.link, self._t, self.live, self.px4, self.hosted
        self.computed_wall, send_cpu = time.time(), time.thread_time()
        self.step_cpu = send_cpu - self._cpu_mark
        datagrams, samples = [], []  # (PX4's interface: rmw_zenoh samples)
        if px4 is not None:
            _px4_take_over(px4, self.commanders, [c.unit_id for c in commands if c.unit_id in live], t, self.accepted)
        for cmd in commands:
            if cmd.unit_id not in live:
                continue
            if px4 is not None:
                samples += px4.encode(cmd.unit_id, self.commanders[cmd.unit_id].step(t, cmd.thrusts_n), t)
                msgs = []
            else:
                msgs = _with_takeover(cmd.unit_id, self.accepted[cmd.unit_id], rotor_command_message(cmd, self.scale_n))
            if hosted is not None:  # e.g. a failure injected on the vehicle, for this unit's motors
                msgs += hosted.unit_commands(cmd.unit_id)
            if msgs:
                datagrams.append((link.pack(msgs), link.peers[cmd.unit_id]))
        if samples:
            px4.send(samples)
        for data, addr in datagrams:
            link.send_bytes(data, addr)
        self.sent_wall, self.send_cpu = time.time(), time.thread_time() - send_cpu
        if self.finish_step is not None:
            self.finish_at = time.monotonic() + COORDINATOR_QUIET_S

    def finish(self) -> None:
        """The last period's fault detection, if it has not run yet."""
        if self.finish_at is not None:
            self.finish_at = None
            self.finish_step()

    # -- the link's I/O
    def _receive_step(self) -> float:
        """Telemetry until every live unit's packet of the step is in, or the silent ones' deadline passed."""
        link, live, stop = self.link, self.live, self.stop
        packets: dict[int, SensorPacket] = {}
        idle_deadline = time.monotonic() + WORLD_IDLE_TIMEOUT_S
        deadline = None
        t_expected = None
        final = False  # past the deadline: read what is already queued, then stop waiting (after this
        while set(packets) < live and not stop.requested:  # process was stopped, the telemetry waits in its socket)
            now = time.monotonic()
            left = None if deadline is None else deadline.left_s()
            final = final or left == 0.0 or now >= idle_deadline
            if self.steps == 0 and not packets and now >= self.next_hello:  # hello until the world starts
                link.heartbeat(self.world)
                self.next_hello = now + 0.2
            if self.finish_at is not None and now >= self.finish_at:
                self.finish()
            wait_s = 0.0 if final else min(0.2, idle_deadline - now if left is None else left,
                                           math.inf if self.finish_at is None else self.finish_at - now)
            if deadline is not None:
                deadline.before_wait(wait_s)
            if self.hosted is not None:  # client links and wall-clock heartbeats while the lockstep waits
                wait_s = self.hosted.wait(link, wait_s)
            msgs = link.receive(wait_s)
            if final and not msgs:
                break
            for m in msgs:
                p = self._take(m)
                if p is None:
                    continue
                if p.unit_id not in live or p.t_s <= self.t_last:  # a lost unit stays lost; a stale packet
                    link.drop("stale_telemetry")  # never sets the step's time (it would make every
                    continue  # live unit's packet look stale and lose them all)
                if t_expected is None:
                    t_expected = p.t_s
                    self.first_wall = time.time()
                if p.t_s == t_expected:
                    packets[p.unit_id] = p
                else:
                    link.drop("stale_telemetry")
            if deadline is None and t_expected is not None and (not self.world_marks
                                                                or self.world_sent_us >= usec(t_expected)):
                deadline = SilenceDeadline(self.unit_timeout_s)  # (time this process did not run: not the units')
        if stop.requested:  # stopped mid-step: the units stop too; none of them is lost
            raise LinksEnded
        if t_expected is None:  # no telemetry at all for WORLD_IDLE_TIMEOUT_S: the world is gone
            print(f"coordinator: no telemetry for {WORLD_IDLE_TIMEOUT_S:.0f} s: ending", file=sys.stderr)
            raise LinksEnded
        self.finish()  # (the last period's fault detection, if not done in the slack yet)
        self._packets = packets
        self.t_last = t_expected
        self.all_wall, self._cpu_mark = time.time(), time.thread_time()
        return t_expected

    def _take(self, m) -> SensorPacket | None:
        """One received frame: a unit's whole sensor packet once complete and finite; the rest noted or dropped."""
        link = self.link
        sent_us = _step_sent_us(m)
        if sent_us is not None:
            self.world_marks, self.world_sent_us = True, max(self.world_sent_us, sent_us)
            return None
        kind = m.get_type()
        if kind == "COMMAND_ACK":
            if m.result == mavlink.MAV_RESULT_ACCEPTED and m.get_srcSystem() in self.accepted:
                self.accepted[m.get_srcSystem()].add(m.command)
            return None
        if kind == "NAMED_VALUE_INT":
            if not self.latches.feed(m):
                link.drop("bad_named_value")
            return None
        if kind == "BATTERY_STATUS":  # the unit's pack, for its next sensor packet
            sample = battery_from_message(m)
            if sample is None:
                link.drop("bad_battery")
            else:
                self.batteries[m.get_srcSystem()] = sample
            return None
        if kind == "ESC_STATUS":  # the unit's ESC telemetry, for its next sensor packet
            esc = esc_from_message(m)
            if esc is None:
                link.drop("bad_esc_status")
            else:
                self.escs[m.get_srcSystem()] = esc
            return None
        p = self.assembler.feed(m)
        if p is None:
            return None
        p.latches = self.latches.mask.get(p.unit_id, 0)
        if self.batteries:
            p.battery = self.batteries.pop(p.unit_id, None)
        if self.escs:
            p.esc = self.escs.pop(p.unit_id, None)
        if not telemetry_ok(p):
            link.drop("bad_telemetry")  # non-finite: never into the estimator
            return None
        return p


class HostedFirmware:
    """The flight as a unit process sees it: the engine's world, units and coordinator parts
    (mars_link.flight.engine.WorldPart, UnitsPart, its command source) in the process that hosts K units'
    firmwares (`units`: objects with unit_id, vehicle, io, command_timeout_s, command_deadline; the
    firmwares set `hil_stepped_by_host`, so their frame handlers only receive).

    The world is the HIL link: the step's time is that of the HIL sensor frames received, so reading `t_s`
    waits for them (every unit's, or for `step_grace_s` after the first: a unit the world no longer steps
    is not waited for again until it is stepped); sensing is those frames. The units are the firmwares
    here: taking the sensors is each firmware's HIL step (its telemetry to the coordinator); driving is each
    one's HIL_ACTUATOR_CONTROLS answer, which is the world's actuation and advance. The coordinator is its
    link: its stage is waiting until each unit's command for the step (or its step skip) is in, over MAVLink
    or PX4's interface, into the firmware's intake (its checks, its signing); a unit without one for
    `command_timeout_s` is released (it answers with what it holds: MARS_CMD_MISS periods, then its
    fail-safe). Every wait is `serve(until_s)`: one wait of the process's I/O (each frame into its
    firmware; heartbeats, client links, status files), never a stage of the step. A stop: LinksEnded."""

    def __init__(self, units: list, serve, stop, step_grace_s: float = WORLD_UNIT_TIMEOUT_S) -> None:
        self.units = {u.unit_id: u for u in units}
        self.serve, self.stop, self.step_grace_s = serve, stop, step_grace_s
        self.awaited = set(self.units)  # the units whose next step is waited for
        self.stepping: list[int] = []  # the units in this step
        self._t: float | None = None

    # -- the world part: the HIL link
    @property
    def t_s(self) -> float:
        if self._t is None:
            self._t = self._receive_step()
        return self._t

    def sense(self) -> list:
        """The step's HIL sensor frames, (unit, SensorFrames) unit by unit."""
        return [(u, self.units[u].vehicle.hil_service.received) for u in self.stepping]

    def truth(self) -> None:
        return None  # (the world's, in its process)

    def advance(self) -> None:
        """(The world advances on the units' answers, sent when they drove their motors.)"""
        self._t = None
        self.stepping = []

    # -- the units part: the firmwares here
    def take_sensors(self, frames: list) -> list:
        """Each unit's HIL step; its telemetry goes to the coordinator over its own link."""
        for u, _ in frames:
            unit = self.units[u]
            unit.io.send(unit.vehicle.hil_service.take_step())
        return []

    def drive(self, commands) -> None:
        """(`commands` is empty: each command went into its unit's intake over the unit's link.)"""
        for u in self.stepping:
            unit = self.units[u]
            unit.command_deadline = None
            unit.io.send(unit.vehicle.hil_service.answer_step())

    def kill(self, unit_id: int) -> None:
        """(A unit process dies for real.)"""

    # -- the coordinator part: its link
    def commands(self, t: float, telemetry) -> list:
        """Wait until every unit of the step may answer it: its command is in, it does not wait for one,
        or its command timeout released it."""
        units, stop = self.units, self.stop
        while True:
            waiting = [units[u] for u in self.stepping if not units[u].vehicle.hil_service.command_in]
            for unit in waiting:
                if unit.command_deadline is None:
                    unit.command_deadline = SilenceDeadline(unit.command_timeout_s)
                elif unit.command_deadline.left_s() == 0.0:
                    print(f"unit {unit.unit_id}: no coordinator command for {unit.command_timeout_s:.1f} s at "
                          f"t={unit.vehicle.sim_s:.2f}: answering with the held command / fail-safe", file=sys.stderr)
                    unit.vehicle.release_hil(time.time())
            waiting = [unit for unit in waiting if not unit.vehicle.hil_service.command_in]
            if not waiting:
                return []
            if stop.requested:
                raise LinksEnded
            self.serve(min(unit.command_deadline.at_s for unit in waiting))

    def _receive_step(self) -> float:
        stop, units = self.stop, self.units
        first_at = None
        while not stop.requested:
            ready = {u for u, unit in units.items() if unit.vehicle.hil_service.received is not None}
            if ready and first_at is None:
                first_at = time.monotonic()
            if ready and (ready >= self.awaited or time.monotonic() >= first_at + self.step_grace_s):
                self.awaited = ready
                self.stepping = sorted(ready)
                return min(units[u].vehicle.hil_service.received.imu.time_usec for u in ready) / 1e6
            self.serve(math.inf if first_at is None else first_at + self.step_grace_s)
        raise LinksEnded


def _px4_take_over(px4, commanders: dict, units: list[int], t: float, accepted: dict[int, set[int]]) -> None:
    """PX4's interface: the acks received so far; then every unit not yet armed in OFFBOARD gets the
    keep-alive, DO_SET_MODE and ARM, and the coordinator waits (at most PX4_TAKEOVER_WAIT_S) for their
    acks before the step's ActuatorMotors go out. Samples on different keys may overtake each other: a
    DO_SET_MODE that arrived before its keep-alive is refused (TEMPORARILY_REJECTED) and sent again with
    a fresh keep-alive once every unit of the round has answered. The unit then runs its first commanded
    step armed and in OFFBOARD, as the in-process flight does."""
    from mars_link.px4.rmw_zenoh import VEHICLE_COMMAND

    answered: dict[int, int] = {}

    def take_acks() -> None:
        for u, ack in px4.acks():
            if u in commanders:
                answered[u] = answered.get(u, 0) + 1
                if commanders[u].take_ack(ack):
                    accepted[u].add(int(ack.command))

    take_acks()
    deadline = time.monotonic() + PX4_TAKEOVER_WAIT_S
    while time.monotonic() < deadline:
        waiting = [u for u in units if not commanders[u].taken_over]
        if not waiting:
            return
        answered.clear()
        rounds = {u: commanders[u].take_over(t) for u in waiting}
        px4.send([s for u, msgs in rounds.items() for s in px4.encode(u, msgs, t)])
        expected = {u: sum(topic is VEHICLE_COMMAND for topic, _ in msgs) for u, msgs in rounds.items()}
        round_end = min(deadline, time.monotonic() + PX4_TAKEOVER_ROUND_S)
        while any(answered.get(u, 0) < n for u, n in expected.items()) and time.monotonic() < round_end:
            select.select([px4], [], [], max(0.0, min(0.05, round_end - time.monotonic())))
            take_acks()


def _with_takeover(unit: int, accepted: set[int], rotor_cmd) -> list:
    """Until the unit acknowledged them: ARM before the rotor command, OFFBOARD after it (PX4 refuses
    OFFBOARD without a live setpoint stream); one datagram, so the unit runs the step with all three."""
    R = mavlink
    before, after = [], []
    if R.MAV_CMD_COMPONENT_ARM_DISARM not in accepted:
        before.append(R.MAVLink_command_long_message(unit, 1, R.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    if R.MAV_CMD_DO_SET_MODE not in accepted:
        after.append(R.MAVLink_command_long_message(unit, 1, R.MAV_CMD_DO_SET_MODE, 0,
                                                    R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6, 0, 0, 0, 0, 0))
    return before + [rotor_cmd] + after
