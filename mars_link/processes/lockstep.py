"""Multi-process lockstep SITL: the same World and Coordinator as `inproc`, and each unit's full
firmware (`firmware_models.vehicle.Vehicle`), one process each, exchanging real MAVLink frames over
loopback UDP (default) or Zenoh (`--transport zenoh`).

Contract per exchange k (PX4's simulator lockstep, specs/mavlink.md §1.1):
  world --[HIL_STATE_QUATERNION] ODOMETRY.. HIL_SENSOR--> unit i   (one datagram; sensor time stamps the step)
  world --SYSTEM_TIME--> coordinator                                 (docked: every unit has the step)
  unit i --HIGHRES_IMU (+ODOMETRY)--> coordinator                   (docked assembly only)
  coordinator --SET_ACTUATOR_CONTROL_TARGET--> unit i               (per-rotor thrust for that time)
  unit i --HIL_ACTUATOR_CONTROLS (LOCKSTEP)--> world
The world steps only when every live unit has answered for step k; a unit that stays silent for
`unit_timeout_s` of wall time is declared dead (motors off, the flight goes on). HIL_STATE_QUATERNION
(the unit centre's ground truth, as PX4's simulators send it) goes only when the sensor packet carries
no truth (sensor noise on): the unit uses it for its own telemetry and arming checks; the coordinator
never sees it.

Two set-ups (`SitlSetup`):
  docked   one rigid assembly (the scenario's layout or --layout ROWS) and a coordinator process; at
           the first step the coordinator arms every unit and switches it to OFFBOARD with
           COMMAND_LONGs on its link, in the same datagram as the first rotor command; each unit
           answers a HIL step only once the coordinator's command for that step is in
           (`VehicleConfig.hil_await_coordinator`), or after `command_timeout_s`.
           With --vehicle (mars_link.processes.vehicle_host) the coordinator also serves the assembly as ONE MAVLink
           vehicle (system 202, API 14539, GCS 14550): its guidance is the coordinator's reference,
           the run goes on until stopped (--forever) and the world is paced to real time.
  pieces   a flight of several bodies (`[assembly] start = "free"`, `[reconfig]`): the world starts with
           one body per piece of the executor's start (`build.make_pieces_world`), splits a body when a
           latch opens and merges two when facing latches close, and sends each unit its latch sensor
           (NAMED_VALUE_INT "LATCH", on change), which the unit forwards to the coordinator; the
           coordinator runs the `PiecesCoordinator` (latch setpoints in its rotor commands, controls[4])
           and ends the flight: instead of the first step not to be flown it sends the world
           MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, and the world, still waiting for that step's answers, ends
           without stepping. Each step it logs the mission's clock, reference and tracked units
           (pieces_steps.csv); the world logs every unit's centre (world_truth.csv).
  free     --units N: N separate 1x1 bodies side by side on the ground, no coordinator; each unit
           flies itself (takeoff, offboard, land from MAVSDK/QGC/MAVProxy), the world paced to
           real time (--speed).
Every unit also serves PX4's client links: GCS to UDP 14550 (bound 18570+i), API to 14540+i (bound
14580+i), i = unit index from 0, and logs every frame it sends or receives to unit<id>.tlog.

Signing: with a key (--signing-key-file, else $MARS_LINK_SIGNING_KEY; `run --mode sitl` and `sitl up`
always pass one, the user's or a per-run key) every link between the run's own processes is MAVLink-2
signed both ways and verified HMAC-first (mars_link.mavlink.signing): the coordinator <-> unit links,
the HIL links (sensors in, HIL_ACTUATOR_CONTROLS out) and the coordinator -> world frames (the step
marker, the shutdown); a frame without a genuine signature is dropped and counted (signing.<reason>).
Client links check signed frames (a signed client has full control) and, with --require-signing, let
unsigned clients only read (firmware_models.control_policy).

Timeouts (wall time): coordinator 1 s < unit 2 s < world 3 s, so that when a unit process dies the
coordinator gives up on it first, the other units still get their commands, and only the dead unit is
declared dead by the world. Each counts only the time its own process ran (mars_link.runtime.pacing.
SilenceDeadline): after a host-wide stall the first process to run again must not judge the others by
time in which none of them ran.

Real time (the world paced, `--speed` > 0): the world samples and encodes a step before the pacing
wait and reads the units' answers from mid-period on; each unit forwards its sensors at once and
leaves its own bookkeeping (state, heartbeats, streams, status) until it has answered the step; the
coordinator sends the commands before it runs fault detection (Coordinator.finish_step, 2 ms later);
with --sched-realtime (what `--realtime` runs pass) every process takes SCHED_FIFO where it may, or else
the world and units are SCHED_BATCH so that only the coordinator's wake-ups preempt
(mars_link.runtime.scheduling). The path sensor -> unit -> coordinator -> unit -> motors is then
mostly Python work shared by 8 processes; --timing-log and the units' command-age logs show where it goes.

Links: every process builds its links once at start from `--transport udp|zenoh` (`mars_link.processes.links.Ports`)
and hands each to its I/O as a `mars_link.transport.Transport`: the world's and the coordinator's `Link`
(MAVLink parser, peer table, counters), a unit's HIL and coordinator links in
`mars_link.processes.vehicle_io.VehicleSockets` (its GCS/API client links stay UDP, as ground stations expect).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import select
import selectors
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mars_link.mavlink.signing import signing_from_args
from mars_link.processes.cli_options import add_lockstep_options
from mars_link.processes.parent_watch import die_with_parent
from mars_link.core.events import unit_died
from mars_link.core.errors import EnvironmentFailure, UserInputError
from mars_link.runtime.machine_load import IdleMeter, LoopMeter
from mars_link.core.messages import BatterySample, EscSample, SensorPacket
from mars_link.mavlink.esc_status import esc_from_message
from mars_link.logs.outputs import SafeWriter, write_json
from mars_link.runtime.pacing import Pacer, SilenceDeadline
from mars_link.runtime.scheduling import OverloadValve, take_realtime_class
from mars_link.transport import LinkSpec, spec_from_args
from mars_link.mavlink.wire import (
    LatchSensor,
    SensorPacketAssembler,
    latch_message,
    battery_from_message,
    battery_report_message,
    actuator_output_from_message,
    rotor_command_message,
    sensor_packet_messages,
    usec,
)
from mars_link.processes.links import Link, Ports

if TYPE_CHECKING:
    from mars_link.core.assembly import AssemblyModel
    from mars_link.config.scenario import Scenario

WORLD_SYSID = 200
COORDINATOR_SYSID = 201
MAX_FREE_UNITS = 10  # API ports 14540..14549 (14550 is the GCS port)
COORDINATOR_TIMEOUT_S = 1.0
UNIT_COMMAND_TIMEOUT_S = 2.0
WORLD_UNIT_TIMEOUT_S = 3.0
WORLD_IDLE_TIMEOUT_S = 30.0  # coordinator: no telemetry from any unit for this long = the world is gone
STATUS_PERIOD_S = 0.2  # world status (truth) file
ANSWER_READ_PHASE = 0.5  # paced world: first read of the units' answers, as a fraction of the period
UNIT_STATUS_PERIOD_S = 1.0  # unit status files (a file replace costs milliseconds here)
TICK_PERIOD_S = 0.02  # unit: heartbeats and streams (<= 20 Hz) served on this wall-clock grid
HOUSEKEEPING_DEFER_S = 0.02  # unit: housekeeping waits at most this long past its time for a step in flight
COORDINATOR_QUIET_S = 0.002  # coordinator: fault detection this long after the commands went out
PX4_KEEPALIVE_HZ = 10.0  # coordinator: OffboardControlMode rate on PX4's interface (PX4 wants >= 2 Hz)
PX4_TAKEOVER_WAIT_S = 2.0  # coordinator: longest wait for a unit's acks to arm and enter OFFBOARD
PX4_TAKEOVER_ROUND_S = 0.5  # coordinator: longest wait for one round of those acks
PX4_TELEMETRY_PERIOD_S = 0.1  # unit: /fmu/out telemetry at 10 Hz of wall time (vehicle_status also answers
# every command); what PX4's dds_topics.yaml allows is more, but it is CPU the lockstep shares
PX4_LINK = "px4"  # a unit's rmw_zenoh endpoint in the unit loop's selector (mars_link.processes.px4_link)
ACTUATOR_MOTORS_TOPIC = "/fmu/in/actuator_motors/"  # (in a unit's data key: a per-rotor command)
#: set (to anything) in a unit process's environment: its PX4 keep-alive never times out. A test switch for the
#: conformance harness's red run, never for flight (mars_link.px4.unit_interface keepalive_timeout_enabled)
BROKEN_KEEPALIVE_ENV = "MARS_LINK_TEST_BROKEN_PX4_KEEPALIVE"
STOP_POLL_S = 0.2  # world: longest wait before it looks at its stop flag again (a SIGTERM ends it in time to
# write its summary within the launcher's 3 s grace, also while it waits for units that were stopped with it)


# ----------------------------------------------------------------------------- set-up
@dataclass
class SitlSetup:
    scenario: Scenario
    model: AssemblyModel  # of the docked assembly, or of one free unit
    free_units: int | None  # N free units (no coordinator), or None for a docked assembly
    steps: int | None  # exchanges to run; None = until stopped (or, with pieces, until the coordinator ends it)
    position_every: int | None = None  # filled in by `position_every()`
    pieces: bool = False  # a flight of several bodies (free start, reconfiguration): its coordinator ends it
    external_offboard: bool = False  # docked, no coordinator: an off-board computer outside the run drives the
    # units (`run --mode sitl --external-offboard`); each unit answers its step at once with what it drives


    @property
    def coordinated(self) -> bool:
        """A coordinator drives the units in lockstep (the run's, or a harness playing one: mars-link conformance)."""
        return self.docked and not self.external_offboard

    @property
    def docked(self) -> bool:
        return self.free_units is None

    @property
    def unit_ids(self) -> list[int]:
        return list(range(1, self.free_units + 1)) if self.free_units else list(self.model.unit_ids)


def load_setup(scenario: str | None, units: int | None = None, layout: str | None = None,
               steps: int | None = None) -> SitlSetup:
    """The run's set-up from a scenario (None or "-": built-in defaults) and the CLI overrides.
    `steps` given (the launcher computed it once) spares a unit process building the trajectory
    (importing the whole coordinator stack costs each process over a second)."""
    from mars_link.core.assembly import AssemblyModel, parse_layout
    from mars_link.config.scenario import DEFAULT_PRESET, Scenario, load_scenario, validate_fault

    if units is not None and layout is not None:
        raise UserInputError("--units and --layout exclude each other")
    sc = Scenario(name="free-units", preset=DEFAULT_PRESET) if scenario in (None, "-") else load_scenario(scenario)
    if scenario in (None, "-"):  # the built-in free units fly the default plant, packs included
        from mars_link.models.battery import battery_table

        sc.battery = battery_table({}, sc.preset, "free-units")
    if sc.has_pieces:
        if units is not None or layout is not None:
            raise UserInputError(f"{sc.source}: --units and --layout do not apply to a flight of several bodies")
        from mars_link.reconfig.plans import check_reconfig_scenario

        check_reconfig_scenario(sc)
        model = sc.model()
        for f in sc.faults:
            validate_fault(f, model, sc.source)
        return SitlSetup(sc, model, None, None, pieces=True)
    if units is not None:
        if not 1 <= units <= MAX_FREE_UNITS:
            raise UserInputError(f"--units must be 1..{MAX_FREE_UNITS}, got {units}")
        if sc.faults:
            sc = dataclasses.replace(sc, faults=[f for f in sc.faults if f.unit <= units])
        model = AssemblyModel.from_layout(["X"], sc.model().vehicle)
        steps = None if sc.sim.duration_s is None else int(round(sc.sim.duration_s * sc.sim.control_hz))
        return SitlSetup(sc, model, units, steps)
    if layout is not None:
        rows = parse_layout(layout)
        tracked = sc.tracked
        if tracked != "com" and sc.tracked_unit() > sum(r.count("X") for r in rows):
            tracked = "com"
        sc = dataclasses.replace(sc, layout=rows, tracked=tracked)
    model = sc.model()
    from mars_link.core.limits import check_sitl_processes

    check_sitl_processes(model.n_units)
    for f in sc.faults:
        validate_fault(f, model, sc.source)
    if steps is None:
        steps = int(round((sc.sim.duration_s or _trajectory(sc, model).duration_s) * sc.sim.control_hz))
    return SitlSetup(sc, model, None, steps)


def position_every(setup: SitlSetup) -> int:
    """Mocap position samples every n-th exchange (the in-process runner's rate)."""
    if setup.position_every is None:
        from mars_link.flight.build import position_every as scenario_position_every

        setup.position_every = scenario_position_every(setup.scenario)
    return setup.position_every


def _start_pose(setup: SitlSetup):
    """Where the assembly's CoM starts (as the in-process runner puts it) and its yaw."""
    from mars_link.flight.build import start_pose

    return start_pose(setup.scenario, setup.model)


def _trajectory(sc, model):
    from mars_link.flight.build import make_trajectory

    return make_trajectory(sc, model)


class _Stop:
    """SIGTERM/SIGINT -> a flag the loops poll (the process ends cleanly, summaries written)."""

    def __init__(self) -> None:
        self.requested = False
        self.ended = False  # (the world: the coordinator ended the flight of pieces)
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._set)

    def _set(self, *_) -> None:
        self.requested = True


def _await_peers(link: Link, wanted: set[int], timeout_s: float, stop: _Stop | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while not wanted <= set(link.peers) and time.monotonic() < deadline and not (stop and stop.requested):
        link.receive(0.05)
    missing = wanted - set(link.peers)
    if missing and not (stop and stop.requested):
        raise SystemExit(f"timed out waiting for {sorted(missing)} to say hello")


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


# ----------------------------------------------------------------------------- world
def run_world(setup: SitlSetup, ports: Ports, out: Path, seed: int, unit_timeout_s: float = WORLD_UNIT_TIMEOUT_S,
              speed: float = 0.0, start: tuple[np.ndarray, float] | None = None, mcap: bool = False,
              foxglove: str | None = None, key: bytes | None = None) -> int:
    """Own the bodies, run the lockstep; `speed` > 0 paces sim time to that many x wall time. `start`
    (CoM NED, yaw) as the launcher computed it, else from the scenario's trajectory. `mcap`: run.mcap in
    `out`; `foxglove`: HOST:PORT of the live Foxglove view (mars_link.processes.view_feed says why the world hosts them)."""
    world_start = start
    from mars_link.flight.build import make_world, outdoor_profile, sensor_params
    from sitl.world import FreeUnitsWorld, WorldConfig

    sc = setup.scenario
    cfg = WorldConfig(sc.sim.physics_hz, sc.sim.control_hz, seed, sc.sim.noise, position_every(setup),
                      environment=sc.environment if sc.environment.moves_air else None, sensors=sensor_params(sc),
                      battery=sc.battery, outdoor=outdoor_profile(sc))
    if setup.pieces:  # one body per piece of the executor's start (the coordinator builds the same executor)
        from mars_link.flight.build import make_executor, make_pieces_world, make_trajectory, world_config

        executor = make_executor(sc, setup.model, make_trajectory(sc, setup.model))[0]
        cfg = dataclasses.replace(world_config(sc, seed), position_every=position_every(setup))
        world = make_pieces_world(sc, setup.model, seed, executor, config=cfg)
        columns = ",".join(f"u{u}_{c}" for u in setup.unit_ids for c in ("n_m", "e_m", "d_m"))
    elif setup.docked:
        com, yaw = world_start or _start_pose(setup)
        world = make_world(sc, setup.model, seed, com, yaw, config=cfg)
        columns = "pos_n_m,pos_e_m,pos_d_m,qw,qx,qy,qz"
    else:
        world = FreeUnitsWorld(setup.free_units, setup.model.vehicle, cfg)
        columns = ",".join(f"u{u}_{c}" for u in setup.unit_ids for c in ("pos_n_m", "pos_e_m", "pos_d_m", "qw", "qx", "qy", "qz"))
    stop = _Stop()
    link = Link(ports.open("world"), WORLD_SYSID, key=key)  # with a key: HIL both ways and the shutdown signed
    scale = setup.model.vehicle.full_scale_thrust_n
    control_min = 0.0 if setup.model.vehicle.rotor_min_thrust_n is not None else -1.0  # as the units' intake
    live = set(setup.unit_ids)
    out.mkdir(parents=True, exist_ok=True)
    status_path = out / "world_status.json"
    from mars_link.logs.outputs import SafeWriter

    # a write error stops the log, never the world; its own thread writes it, so a slow disk never paces the world
    truth_log = SafeWriter.open(out / "world_truth.csv", background=True)
    truth_log.write("t_s," + columns + "\n")
    wall0 = time.perf_counter()
    next_status = 0.0
    deaths: list[dict] = []
    latch_sent: dict[int, int] = {}  # the latch mask each unit last heard
    truth_row = world.units_row if setup.pieces else world.truth_row
    view, feed, reference, eta_at = _world_view(setup, world, out, mcap, foxglove)
    writer_pid = view.process.pid if view is not None and mcap else None
    try:
        _await_peers(link, live | ({COORDINATOR_SYSID} if setup.coordinated else set()), 60.0, stop)
        link.prepare_peers(live)  # (the first sends' set-up, paid in the first step, stalled a paced start)
        coordinator_addr = link.peers.get(COORDINATOR_SYSID) if setup.coordinated else None
        step_sent = step_sent_packer(link)
        stall = _stall_from_env()
        wall0 = time.perf_counter()
        # sim time on the wall clock at `speed`; behind it, the world catches up (no re-anchoring): the
        # lockstep's real-time factor stays the one asked for
        # (anchored at the first step's wait, once its datagrams are ready: the first sensing and logging,
        # slow the first time, then belong to start-up as in every later step they precede the wait)
        pacer = Pacer(speed, reanchor_s=math.inf, clock=time.perf_counter)
        loop = LoopMeter()  # the stepping loop alone (start-up excluded)
        idle = IdleMeter()  # the machine's idle cores over the loop: behind the wall clock, starved or at fault?
        valve = OverloadValve()  # (armed in SCHED_FIFO only)
        k = 0
        while (setup.steps is None or k < setup.steps) and not stop.requested:
            t = world.t_s
            truth_log.write("%.6f," % t + ",".join("%.9f" % x for x in truth_row()) + "\n")
            if view is not None:
                view.write_step(t, world, feed.point(None if reference is None else reference.sample(t)),
                                eta_at(t), [deaths, feed.events])
            if time.monotonic() >= next_status:
                next_status = time.monotonic() + STATUS_PERIOD_S
                _write_world_status(status_path, world, setup, live, t, time.perf_counter() - wall0, writer_pid)
                truth_log.flush()
            datagrams = []  # sampled and encoded before the pacing wait: at t they only go out
            for p in world.sense():
                if p.unit_id in live:
                    latch = []
                    if setup.pieces and latch_sent.get(p.unit_id) != p.latches:  # the latch sensor, on change
                        latch_sent[p.unit_id] = p.latches
                        latch = [latch_message(p.t_s, p.latches)]
                    datagrams.append((link.pack(unit_sensor_messages(world, p, latch)), link.peers[p.unit_id]))
            pacer.wait(t)
            if valve.armed and valve.check(behind_s := -pacer.wait_s(t), t):
                print(f"world: {behind_s:.1f} s behind the wall clock at t={t:.2f}: leaving SCHED_FIFO, so that the "
                      "flight shares the machine", file=sys.stderr)
            for i, (data, addr) in enumerate(datagrams):
                link.send_bytes(data, addr)
                if i == 0 and stall is not None and t >= stall[0]:  # (test hook: stopped between two units)
                    time.sleep(stall[1])
                    stall = None
            if coordinator_addr is not None:  # every unit has its step: the coordinator may now time them
                link.send_bytes(step_sent(usec(t)), coordinator_addr)
            if pacer.paced:  # the answers are read in one go from mid-period on, so the world is not
                # woken once per unit while the units and the coordinator work on the step (2-core machines)
                time.sleep(max(0.0, pacer.wait_s(t + ANSWER_READ_PHASE / cfg.exchange_hz)))
            waiting = set(live)
            deadline = SilenceDeadline(unit_timeout_s)  # (time this process did not run is nobody's silence)
            t_us = usec(t)
            while waiting and not (stop.requested or stop.ended):
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
                        if feed is not None and m.get_srcSystem() == COORDINATOR_SYSID:
                            feed.take(m)
                        continue
                    if m.time_usec != t_us or m.get_srcSystem() not in waiting:
                        link.drop("stale_actuator")
                        continue
                    if not actuator_controls_ok(m.controls, control_min):
                        link.drop("bad_actuator")  # NaN/inf/out of range: never into the physics
                        continue
                    world.actuate(actuator_output_from_message(m, scale))
                    waiting.discard(m.get_srcSystem())
            if stop.requested or stop.ended:
                break
            for unit in sorted(waiting):  # silent units are dead: motors off, the flight goes on
                world.declare_dead(unit)
                live.discard(unit)
                deaths.append(unit_died(t, unit))
                print(f"world: unit {unit} silent for {unit_timeout_s:.1f} s at t={t:.2f}: declared dead", file=sys.stderr)
            world.advance()
            k += 1
        wall = time.perf_counter() - wall0
        _write_world_status(status_path, world, setup, live, world.t_s, wall, writer_pid)
        summary = {"sim_time_s": world.t_s, "wall_time_s": wall, "real_time_factor": world.t_s / max(wall, 1e-9),
                   "steps": k, "units": setup.unit_ids, "dead_units": sorted(set(setup.unit_ids) - live),
                   "deaths": deaths, "dropped": link.dropped, "stopped": stop.requested, "cpu_s": time.process_time(),
                   **loop.figures(), "realtime_class_left_at_s": valve.left_at_s, "cores_idle_fraction": idle.fraction(),
                   "force_integral_n2s": getattr(world, "force_integral_n2s", None),  # (free units: none)
                   "latch_events": getattr(world, "latch_events", []),
                   "bodies": [list(b.units) for b in getattr(world, "bodies", [])], "logging": truth_log.status()}
        packs = getattr(world, "packs", None)
        if packs is not None:  # the packs' truth at the end (unit id order)
            summary["batteries"] = {"soc": packs.soc.round(6).tolist(), "voltage_v": packs.voltage_v.round(4).tolist(),
                                    "drawn_c": packs.drawn_c.round(4).tolist()}
        _write_world_summary(out, summary)
    finally:
        truth_log.close()
        try:  # run.mcap before the link: a Zenoh session can take seconds to close, and the file must be
            if view is not None:  # whole when `sitl up` ends
                view.finish(event_lists=[deaths, feed.events])
                mcap = view.status()
                if mcap is not None and mcap["stopped_reason"] and (out / "world_summary.json").exists():
                    _write_world_summary(out, {**json.loads((out / "world_summary.json").read_text()),
                                               "mcap_stopped_reason": mcap["stopped_reason"]})
        finally:
            world.close()
            link.close()
    return 0


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


def _write_world_summary(out: Path, summary: dict) -> None:
    """world_summary.json; a full disk is one line (the parent's summary then says the world's figures are
    missing), never a traceback that would read as a crashed world."""
    try:
        write_json(out / "world_summary.json", summary)
    except OSError as exc:
        print(f"world: world_summary.json: {exc.strerror or exc} (not written)", file=sys.stderr)


def _world_view(setup: SitlSetup, world, out: Path, mcap: bool, live: str | None):
    """(FlightView, ViewFeed, the scenario's trajectory or None, t -> rotor eta) of a docked world; Nones if
    neither run.mcap nor a live view is asked for. Free units (--units): each its own body, no coordinator (no
    reference, estimate or events but the world's own)."""
    if not (mcap or live):
        return None, None, None, None
    from mars_link.flight.build import tracked_offset
    from mars_link.flight.flight_view import open_view
    from mars_link.config.scenario import eta_after
    from mars_link.processes.view_feed import ViewFeed

    sc, model = setup.scenario, setup.model
    if not setup.docked:
        model = world.view_model
        duration = setup.steps / sc.sim.control_hz if setup.steps is not None else math.inf
        view = open_view(out, model, sc, sc.sim.control_hz, None, duration, live, None, mcap)
        healthy = np.ones(model.n_rotors)
        return view, ViewFeed(np.zeros(3)), None, lambda t: healthy
    reference = _trajectory(sc, model) if setup.steps is not None else None  # --vehicle: the coordinator's only
    duration = setup.steps / sc.sim.control_hz if setup.steps is not None else math.inf
    view = open_view(out, model, sc, sc.sim.control_hz, reference, duration, live, sc.tracked_unit(), mcap)
    faults = sorted(sc.faults, key=lambda f: f.t_s)
    return view, ViewFeed(tracked_offset(model, sc)), reference, lambda t: eta_after(model, faults, t)  # (as rotors.csv)


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


def _write_world_status(path: Path, world, setup: SitlSetup, live: set[int], t_s: float, wall_s: float,
                        mcap_writer_pid: int | None = None) -> None:
    """The world's truth for operators and tests (units' centres, NED), replaced atomically; and the pid of
    the process writing run.mcap, which `sitl up` waits for if it outlives the world (`Run.stop`)."""
    from mars_link.processes.vehicle_io import write_json_atomic

    units = {}
    for u in setup.unit_ids:
        s = world.unit_truth(u)
        units[str(u)] = {"position_ned_m": [float(x) for x in s.position_ned_m],
                         "velocity_ned_mps": [float(x) for x in s.velocity_ned_mps],
                         "quaternion_wxyz": [float(x) for x in s.quaternion_wxyz],
                         "rotor_thrust_n": [float(x) for x in world.unit_rotor_thrust_n(u)]}
    write_json_atomic(path, {"sim_time_s": t_s, "wall_time_s": wall_s, "wall_clock_s": time.time(),
                             "real_time_factor": t_s / wall_s if wall_s > 0 else None,
                             "dead_units": sorted(set(setup.unit_ids) - live), "units": units,
                             "mcap_writer_pid": mcap_writer_pid})


# ----------------------------------------------------------------------------- unit
@dataclass
class UnitPorts:
    gcs_port: int = 14550
    api_port: int | None = None  # None: 14540 + index
    gcs_bind: int | None = None  # None: 18570 + index
    api_bind: int | None = None  # None: 14580 + index
    closed: bool = False  # no client links at all (`run --mode sitl` without --gcs: a batch run nobody can reach)


def px4_input_log_name(unit_id: int) -> str:
    """A unit's log of the PX4-interface samples it received: one JSON object a line, in arrival order, with
    the unit's sim time and the wall time on arrival, the key, and the CDR payload and attachment in hex
    (what a replay feeds the firmware again, and where rotors.csv finds the commands)."""
    return f"unit{unit_id}_px4_in.jsonl"


def run_units(setup: SitlSetup, unit_ids: list[int], ports: Ports, out: Path, clients: list[UnitPorts],
              command_timeout_s: float = UNIT_COMMAND_TIMEOUT_S, key: bytes | None = None,
              require_signing: bool = False, ulog: bool = True, run_key: bool = False) -> int:
    """Several units' firmwares in this process (`--units-per-process K`), each its own MAVLink system
    with its own links, tlog, ULog (unit<id>.ulg, unless `ulog` is False) and status file, served by one
    event loop: one wake-up serves every unit whose datagram came in, and the start-up (imports) is paid
    once. One unit is the default."""
    from mars_link.processes.vehicle_io import write_json_atomic

    out.mkdir(parents=True, exist_ok=True)
    stop = _Stop()
    units: list[_UnitLoop] = []
    sel = selectors.DefaultSelector()
    try:
        for u, client in zip(unit_ids, clients):
            unit = _UnitLoop(setup, u, ports, out, client, command_timeout_s, key, require_signing, ulog, run_key)
            units.append(unit)
            for name, t in unit.io.links.items():
                sel.register(t, selectors.EVENT_READ, (unit, name))
            if unit.px4_link is not None:
                sel.register(unit.px4_link, selectors.EVENT_READ, (unit, PX4_LINK))
        for unit in units:
            print(json.dumps({"ready": True, "unit": unit.unit_id, "ports": unit.io.ports()}), flush=True)
        loop = LoopMeter()
        active = list(units)
        while active and not stop.requested:
            now = time.monotonic()
            wake = min(unit.housekeeping(now) for unit in active)
            for unit in active:  # (a stall of this process is not the coordinator's silence)
                if unit.command_deadline is not None:
                    unit.command_deadline.before_wait(max(0.0, wake - now))
            for key_, _ in sel.select(max(0.0, wake - now)):
                unit, name = key_.data
                if name == PX4_LINK:
                    unit.drain_px4()
                else:
                    unit.io.drain(name, key_.fileobj)
            for unit in active:
                unit.check_command_timeout()
            for unit in [u for u in active if u.done]:
                active.remove(unit)
                unit.finish(loop.figures() if len(units) == 1 else None)
        for unit in active:
            unit.finish(loop.figures() if len(units) == 1 else None)
        if len(units) > 1:  # the process's CPU, once (each unit's status has its own counters only)
            write_json_atomic(out / f"unit_host{unit_ids[0]}_status.json",
                              {"units": unit_ids, "cpu_s": time.process_time(), **loop.figures()})
    finally:
        sel.close()
        for unit in units:
            unit.io.close()
            if unit.px4_link is not None:
                unit.px4_link.close()
                unit.px4_log.close()
    return 0


class _UnitLoop:
    """One unit's firmware, its links and its wall-clock housekeeping, driven by `run_units`' loop."""

    def __init__(self, setup: SitlSetup, unit_id: int, ports: Ports, out: Path, client: UnitPorts,
                 command_timeout_s: float, key: bytes | None, require_signing: bool, ulog: bool = True,
                 run_key: bool = False) -> None:
        from firmware_models.vehicle import LINK_COORDINATOR, LINK_HIL
        from mars_link.flight.build import make_unit
        from mars_link.processes.vehicle_io import LinkSpec, VehicleSockets, client_links

        sc = setup.scenario
        self.setup, self.unit_id, self.command_timeout_s = setup, unit_id, command_timeout_s
        index = setup.unit_ids.index(unit_id)
        vehicle = make_unit(sc, setup.model, unit_id, coordinator_driven=setup.coordinated, signing_key=key,
                            wall_time_s=time.time(), require_signing=require_signing, sign_hil=True,
                            client_links_keyed=not run_key)  # (a per-run key: clients keep the keyless rules)
        links = {} if client.closed else client_links(index, client.gcs_port, client.api_port, client.gcs_bind,
                                                      client.api_bind)
        links[LINK_HIL] = LinkSpec(0, ports.address("world"), False, ports.open(f"unit/{unit_id}", "world"))
        if setup.coordinated:
            links[LINK_COORDINATOR] = LinkSpec(0, ports.address("coordinator"), False,
                                               ports.open(f"unit/{unit_id}", "coordinator"))
        self.vehicle = vehicle
        self.io = VehicleSockets(vehicle, links, tlog=out / f"unit{unit_id}.tlog")
        self.io.batch = True
        if ulog:  # (its own writer thread, sampled in the step's slack: the lockstep never waits for the disk)
            from firmware_models.vehicle_ulog import UlogConfig

            vehicle.start_ulog(UlogConfig(out / f"unit{unit_id}.ulg", background=True))
        self.hello_links = [LINK_HIL] + ([LINK_COORDINATOR] if setup.coordinated else [])
        self.status_path = out / f"unit{unit_id}_status.json"
        self.next_hello = self.next_tick = self.next_status = 0.0
        self.command_deadline: SilenceDeadline | None = None  # (while a HIL step waits for its command)
        vehicle.defer_own_state = setup.coordinated  # (Vehicle.run_deferred: state bookkeeping in the step's slack)
        self.px4_link = None  # PX4's own interface over rmw_zenoh, beside the MAVLink persona (vehicle_px4)
        self.px4_log = None  # every rmw_zenoh sample it received, as received (px4_input_log_name)
        self.next_px4_telemetry = 0.0
        self.command_age = ports.taps.get(unit_id)
        if sc.unit_interface == "px4-zenoh":
            from mars_link.processes.px4_link import Px4UnitLink

            vehicle.px4_keepalive_timeout = not os.environ.get(BROKEN_KEEPALIVE_ENV)  # (conformance: a test switch)
            vehicle.px4_interface()
            self.px4_link = Px4UnitLink(ports.zenoh_session(), vehicle.px4_endpoint)
            self.px4_log = open(out / px4_input_log_name(unit_id), "w", encoding="utf-8")  # (replayable)

    def drain_px4(self) -> None:
        """Every rmw_zenoh sample received: into the firmware; its answers out (a HIL step it completes,
        command acks and status)."""
        vehicle, link, tap = self.vehicle, self.px4_link, self.command_age
        log = self.px4_log
        for key, payload, attachment in link.take():
            now = time.time()
            log.write(json.dumps({"sim_s": vehicle.sim_s, "wall_s": now, "key": key, "payload": payload.hex(),
                                  "attachment": None if attachment is None else attachment.hex()}) + "\n")
            out, samples = vehicle.px4_sample(key, payload, attachment, now)
            if tap is not None and ACTUATOR_MOTORS_TOPIC in key and vehicle._last_rotor_usec is not None:
                tap.on_command(vehicle._last_rotor_usec / 1e6, now)
            if out:
                self.io.send(out)
            if samples:
                link.publish(samples)

    @property
    def done(self) -> bool:
        return self.setup.steps is not None and self.vehicle.stats.get("hil_steps", 0) >= self.setup.steps

    def housekeeping(self, now: float) -> float:
        """The unit's own state, heartbeats, streams and status file when due; returns when to wake next.
        Housekeeping waits while a step is in flight, at most HOUSEKEEPING_DEFER_S past its time, and
        runs in the wake-up that answered the step: a wake-up of its own finds the caches cold after the
        other processes ran (with 25 unit processes that cost more than the work itself)."""
        from mars_link.processes.vehicle_io import vehicle_status, write_json_atomic

        vehicle, io = self.vehicle, self.io
        steps = vehicle.stats.get("hil_steps", 0)
        if vehicle.hil_pending:
            self.command_deadline = self.command_deadline or SilenceDeadline(self.command_timeout_s)
        due = min(self.next_hello, self.next_tick, self.next_status)
        in_flight = self.command_deadline is not None
        start_at = math.inf if in_flight else (now if vehicle.has_deferred else due)
        if now >= min(start_at, due + HOUSEKEEPING_DEFER_S):
            vehicle.run_deferred()
            if now >= self.next_hello:  # hello until the world talks, then the 1 Hz wall-clock heartbeat
                io.send([vehicle.hello(name) for name in self.hello_links])
                self.next_hello = now + (0.2 if steps == 0 else 1.0)
            if now >= self.next_tick:  # heartbeats and streams on wall time, even while the lockstep waits
                io.send(vehicle.tick(time.time(), vehicle.sim_s))
                if self.px4_link is not None and now >= self.next_px4_telemetry:  # /fmu/out
                    self.px4_link.publish(vehicle.px4_telemetry_samples())
                    self.next_px4_telemetry = now + PX4_TELEMETRY_PERIOD_S
                self.next_tick = now + TICK_PERIOD_S
            if now >= self.next_status:
                self.next_status = now + UNIT_STATUS_PERIOD_S
                write_json_atomic(self.status_path, vehicle_status(vehicle, vehicle.state, vehicle.sim_s, **io.counters()))
            due = min(self.next_hello, self.next_tick, self.next_status)
            start_at = math.inf if in_flight else due
        wake = min(start_at, due + HOUSEKEEPING_DEFER_S)
        if self.command_deadline is not None:
            wake = min(wake, self.command_deadline.at_s)
        return wake

    def check_command_timeout(self) -> None:
        vehicle = self.vehicle
        if vehicle.hil_pending and self.command_deadline is not None and self.command_deadline.left_s() == 0.0:
            print(f"unit {self.unit_id}: no coordinator command for {self.command_timeout_s:.1f} s at "
                  f"t={vehicle.sim_s:.2f}: answering with the held command / fail-safe", file=sys.stderr)
            self.io.send(vehicle.release_hil(time.time()))
        if not vehicle.hil_pending:
            self.command_deadline = None

    def finish(self, loop: dict[str, float | str] | None) -> None:
        """The last deferred work and the final status (`loop`: this process's stepping loop's CPU and
        wake-ups, `LoopMeter.figures`, when it hosts this unit alone; a host of several writes its own
        status file)."""
        from mars_link.processes.vehicle_io import vehicle_status, write_json_atomic

        vehicle = self.vehicle
        vehicle.run_deferred()
        cpu = {} if loop is None else {"cpu_s": time.process_time(), **loop}
        write_json_atomic(self.status_path, vehicle_status(vehicle, vehicle.state, vehicle.sim_s, **cpu,
                                                           **self.io.counters(), ulog=vehicle.stop_ulog()))


# ----------------------------------------------------------------------------- coordinator
def run_coordinator(setup: SitlSetup, ports: Ports, out: Path, unit_timeout_s: float = COORDINATOR_TIMEOUT_S,
                    key: bytes | None = None, vehicle=None, timing_log: bool = False,
                    require_signing: bool = False, view_feed: bool = False, run_key: bool = False) -> int:
    """Drive the docked assembly; with a signing `key` its link to the units is signed both ways.
    With `vehicle` (mars_link.processes.vehicle_host.VehiclePorts) the assembly is one MAVLink vehicle on those ports
    and its guidance, not the scenario's trajectory, is the coordinator's reference. `timing_log`:
    coordinator_timing.csv gets each step's wall-clock times (first and last telemetry in, commands
    computed, sent; CPU time of the step and of the sends): with the units' command_age logs, where a
    real-time step's time goes (wall time above CPU time = the coordinator waited for a CPU)."""
    from mars_link.flight.build import make_coordinator, make_detector, make_estimator
    from mars_link.config.scenario import eta_after

    sc = setup.scenario
    model = setup.model
    trajectory = _trajectory(sc, model)
    faults = sorted(sc.faults, key=lambda f: f.t_s)
    hosted = None
    end_s = None  # a flight of pieces: when it ends (the coordinator says so to the world)
    if setup.pieces and vehicle is None:
        from mars_link.flight.build import make_pieces_coordinator

        coordinator, end_s = make_pieces_coordinator(sc, model, trajectory)
    elif vehicle is not None:  # (one body or pieces: the vehicle flies until stopped)
        from mars_link.processes.vehicle_host import HostedVehicle

        detector = None if setup.pieces else make_detector(sc, model, float(_start_pose(setup)[0][2]))
        out.mkdir(parents=True, exist_ok=True)
        try:
            hosted = HostedVehicle(sc, model, detector, vehicle, out, None if run_key else key, require_signing)
        except UserInputError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        coordinator = hosted.coordinator
        print(json.dumps({"vehicle": hosted.endpoints()}), flush=True)
    else:
        coordinator = make_coordinator(sc, model, trajectory, make_estimator(sc, model),
                                       make_detector(sc, model, float(_start_pose(setup)[0][2])))
    stop = _Stop()
    link = Link(ports.open("coordinator"), COORDINATOR_SYSID, key=key)
    scale = model.vehicle.full_scale_thrust_n
    assembler = SensorPacketAssembler()
    latches = LatchSensor()
    batteries: dict[int, BatterySample] = {}  # each unit's last BATTERY_STATUS, until its packet comes
    escs: dict[int, EscSample] = {}  # ... and ESC_STATUS
    out.mkdir(parents=True, exist_ok=True)
    pieces_log = SafeWriter.open(out / "pieces_steps.csv") if setup.pieces else None  # (a full disk stops it)
    if pieces_log:
        pieces_log.write("t_s,mission,mission_t_s,ref_n_m,ref_e_m,ref_d_m,tracked_units,pieces\n")
    live = set(model.unit_ids)
    lost: list[dict] = []
    accepted: dict[int, set[int]] = {u: set() for u in model.unit_ids}  # commands each unit acknowledged
    next_fault = 0
    out.mkdir(parents=True, exist_ok=True)
    timing = SafeWriter.open(out / "coordinator_timing.csv") if timing_log else None
    if timing:
        timing.write("t_s,telemetry_first_wall_s,telemetry_all_wall_s,computed_wall_s,sent_wall_s,step_cpu_s,send_cpu_s\n")
    px4 = None  # PX4's own interface ([units] interface = "px4-zenoh"): the commands go over rmw_zenoh
    if sc.unit_interface == "px4-zenoh":
        from mars_link.processes.px4_link import Px4CoordinatorLink
        from mars_link.px4.commander import Px4Commander

        px4 = Px4CoordinatorLink(ports.zenoh_session(), model.unit_ids)
        keepalive_every = max(1, int(sc.sim.control_hz // PX4_KEEPALIVE_HZ))
        commanders = {u: Px4Commander(u, scale, model.vehicle.rotor_min_thrust_n is None, keepalive_every)
                      for u in model.unit_ids}
    try:
        _await_peers(link, live, 60.0, stop)
        link.prepare_peers(live)
        if px4 is not None:
            for u in live:
                px4.prepare(u)
        loop = LoopMeter()
        world = ports.address("world")
        link.peers.setdefault(WORLD_SYSID, world)  # (its step-sent markers come from there)
        events_fed = 0
        finish_at = None  # when the last period's fault detection runs (Coordinator.finish_step)
        link.heartbeat(world)
        next_hello = time.monotonic() + 0.2
        t_last = -math.inf  # the last step's time: a packet not newer is a backlog (a paused unit resumed)
        world_marks, world_sent_us = False, -1  # the world's step-sent markers: seen any, the latest step
        for k in (range(setup.steps) if setup.steps is not None else itertools.count()):
            if stop.requested:
                break
            packets: dict[int, SensorPacket] = {}
            # a unit is lost when it stays silent for unit_timeout_s after the first telemetry of the
            # step came in and the world said it had sent every unit the step (step_sent_message; a world
            # that sends no such marker: from the first telemetry); before that, the world may be waiting
            # for a dead unit (it drives the clock), or be stopped between two units' sensors
            idle_deadline = time.monotonic() + WORLD_IDLE_TIMEOUT_S
            deadline = None
            t_expected = None
            final = False  # past the deadline: read what is already queued, then stop waiting (after this
            while set(packets) < live and not stop.requested:  # process was stopped, the telemetry waits in its socket)
                now = time.monotonic()
                left = None if deadline is None else deadline.left_s()
                final = final or left == 0.0 or now >= idle_deadline
                if k == 0 and not packets and now >= next_hello:  # hello until the world starts
                    link.heartbeat(world)
                    next_hello = now + 0.2
                if finish_at is not None and now >= finish_at:
                    coordinator.finish_step()
                    finish_at = None
                wait_s = 0.0 if final else min(0.2, idle_deadline - now if left is None else left,
                                               math.inf if finish_at is None else finish_at - now)
                if deadline is not None:
                    deadline.before_wait(wait_s)
                if hosted is not None:  # client links and wall-clock heartbeats while the lockstep waits
                    wait_s = hosted.wait(link, wait_s)
                msgs = link.receive(wait_s)
                if final and not msgs:
                    break
                for m in msgs:
                    sent_us = _step_sent_us(m)
                    if sent_us is not None:
                        world_marks, world_sent_us = True, max(world_sent_us, sent_us)
                        continue
                    if m.get_type() == "COMMAND_ACK":
                        if m.result == mavlink.MAV_RESULT_ACCEPTED and m.get_srcSystem() in accepted:
                            accepted[m.get_srcSystem()].add(m.command)
                        continue
                    if m.get_type() == "NAMED_VALUE_INT":
                        if not latches.feed(m):
                            link.drop("bad_named_value")
                        continue
                    if m.get_type() == "BATTERY_STATUS":  # the unit's pack, for its next sensor packet
                        sample = battery_from_message(m)
                        if sample is None:
                            link.drop("bad_battery")
                        else:
                            batteries[m.get_srcSystem()] = sample
                        continue
                    if m.get_type() == "ESC_STATUS":  # the unit's ESC telemetry, for its next sensor packet
                        esc = esc_from_message(m)
                        if esc is None:
                            link.drop("bad_esc_status")
                        else:
                            escs[m.get_srcSystem()] = esc
                        continue
                    p = assembler.feed(m)
                    if p is None:
                        continue
                    p.latches = latches.mask.get(p.unit_id, 0)
                    if batteries:
                        p.battery = batteries.pop(p.unit_id, None)
                    if escs:
                        p.esc = escs.pop(p.unit_id, None)
                    if not telemetry_ok(p):
                        link.drop("bad_telemetry")  # non-finite: never into the estimator
                        continue
                    if p.unit_id not in live or p.t_s <= t_last:  # a lost unit stays lost; a stale packet
                        link.drop("stale_telemetry")  # never sets the step's time (it would make every
                        continue  # live unit's packet look stale and lose them all)
                    if t_expected is None:
                        t_expected = p.t_s
                        first_wall = time.time()
                    if p.t_s == t_expected and p.unit_id in live:
                        packets[p.unit_id] = p
                    else:
                        link.drop("stale_telemetry")
                if deadline is None and t_expected is not None and (not world_marks or world_sent_us >= usec(t_expected)):
                    deadline = SilenceDeadline(unit_timeout_s)  # (time this process did not run: not the units')
            if stop.requested:  # stopped mid-step: the units stop too; none of them is lost
                break
            if not packets:  # no telemetry at all for WORLD_IDLE_TIMEOUT_S: the world is gone
                if not stop.requested:
                    print(f"coordinator: no telemetry for {WORLD_IDLE_TIMEOUT_S:.0f} s: ending", file=sys.stderr)
                break
            t = t_last = t_expected
            if end_s is not None and (t >= end_s() - 1e-9 or coordinator.failed is not None):
                link.send_bytes(link.pack([shutdown_message()]), world)  # the flight of pieces is over
                break
            for unit in sorted(live - set(packets)):  # telemetry stopped: the unit is lost
                live.discard(unit)
                lost.append({"t_s": round(t, 6), "unit": unit})
                print(f"coordinator: unit {unit} silent for {unit_timeout_s:.1f} s at t={t:.2f}: lost", file=sys.stderr)
                if hasattr(coordinator, "unit_lost"):  # issue 5's hook (estimation / fault handling)
                    coordinator.unit_lost(unit, t)
                else:
                    eta = np.asarray(coordinator.eta_believed, dtype=float).copy()
                    eta[model.unit_slots(unit)] = 0.0
                    coordinator.set_faults(eta, t, f"unit {unit} lost")
            if sc.faults_known:
                while next_fault < len(faults) and faults[next_fault].t_s <= t + 1e-9:
                    next_fault += 1
                    coordinator.set_faults(eta_after(model, faults[:next_fault], t), t, "fault told to the coordinator")
            all_wall, step_cpu = time.time(), time.thread_time()
            ordered = [packets[u] for u in sorted(packets)]
            if finish_at is not None:  # the last period's fault detection, if not done in the slack yet
                coordinator.finish_step()
                finish_at = None
            commands = coordinator.commands(t, ordered) if hosted is None else hosted.step(t, ordered, live)
            computed_wall, send_cpu = time.time(), time.thread_time()
            step_cpu = send_cpu - step_cpu
            datagrams = []  # all encoded first, then sent back to back (a woken unit may take the CPU)
            if pieces_log is not None:
                _log_pieces_step(pieces_log, coordinator, t)
            samples = []  # (PX4's interface: the same, as rmw_zenoh samples)
            if px4 is not None:
                _px4_take_over(px4, commanders, [c.unit_id for c in commands if c.unit_id in live], t, accepted)
            for cmd in commands:
                if cmd.unit_id in live:
                    if px4 is not None:
                        samples += px4.encode(cmd.unit_id, commanders[cmd.unit_id].step(t, cmd.thrusts_n), t)
                        msgs = []
                    else:
                        msgs = _with_takeover(cmd.unit_id, accepted[cmd.unit_id], rotor_command_message(cmd, scale))
                    if hosted is not None:  # e.g. a failure injected on the vehicle, for this unit's motors
                        msgs += hosted.unit_commands(cmd.unit_id)
                    if msgs:
                        datagrams.append((link.pack(msgs), link.peers[cmd.unit_id]))
            if samples:
                px4.send(samples)
            for data, addr in datagrams:
                link.send_bytes(data, addr)
            sent_wall, send_cpu = time.time(), time.thread_time() - send_cpu
            if view_feed and coordinator.last is not None:  # after the commands: the world's view (mars_link.processes.view_feed)
                from mars_link.processes.view_feed import feed_messages

                link.send_bytes(link.pack(feed_messages(coordinator.last, coordinator.events[events_fed:])), world)
                events_fed = len(coordinator.events)
            if hosted is None:  # fault detection (Coordinator.finish_step: it changes the allocation from the
                # next period on) once the units have read their commands: they need the CPUs first
                finish_at = time.monotonic() + COORDINATOR_QUIET_S
            if timing:
                timing.write(f"{t:.6f},{first_wall:.6f},{all_wall:.6f},{computed_wall:.6f},{sent_wall:.6f},"
                             f"{step_cpu:.6f},{send_cpu:.6f}\n")
        if finish_at is not None:
            coordinator.finish_step()
        pieces = {} if not setup.pieces else {"pieces_final": coordinator.pieces_final(), "failed": coordinator.failed,
                                              "plan": coordinator.executor.plan.to_json()}
        write_json(out / "coordinator_summary.json",
            {"events": coordinator.all_events() if setup.pieces else coordinator.events, **pieces,
             "lost_units": lost, "dropped": link.dropped, "cpu_s": time.process_time(),
             "detections": [{"t_detected": round(d.t_detected, 6), "unit": d.unit, "rotor": d.rotor,
                             "eta_estimated": round(float(d.eta_estimated), 4), "reason": d.reason}
                            for d in coordinator.detections],
             **loop.figures(),
             "acknowledged": {str(u): sorted(c) for u, c in accepted.items()}})
    finally:
        if px4 is not None:
            px4.close()
        link.close()
        if timing:
            timing.close()
        if pieces_log:
            pieces_log.close()
        if hosted is not None:
            hosted.close()
    return 0


def _log_pieces_step(log, coordinator, t: float) -> None:
    """What the summary needs of a flight of pieces each step: whether the mission flies, its clock and
    reference, and which units carry the tracked point (the truth comes from the world's log)."""
    executor = coordinator.executor
    active = executor.mission_active(t)
    mt = executor.mission_time(t)
    ref = executor.mission.sample(mt).position_ned_m if active else (math.nan,) * 3
    piece = coordinator.tracked_piece()
    log.write(f"{t:.6f},{int(active)},{mt:.6f},{ref[0]:.9f},{ref[1]:.9f},{ref[2]:.9f},"
              f"{' '.join(str(u) for u in piece.units)},{len(coordinator.pieces)}\n")


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


# ----------------------------------------------------------------------------- entry point
def main(argv: list[str] | None = None) -> int:
    die_with_parent()  # started by the launcher: never outlive it (mars_link.processes.parent_watch)
    ap = argparse.ArgumentParser(prog="python -m mars_link.processes.lockstep")
    add_lockstep_options(ap)
    args = ap.parse_args(argv)
    if args.sched_realtime:  # (before the links open: Zenoh's threads take the same class)
        take_realtime_class(fallback_batch=args.role != "coordinator")
    try:
        setup = load_setup(args.scenario, args.units, args.layout, args.steps)
        key, args.require_signing = signing_from_args(args)
        link = _link_spec(args)
    except UserInputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.forever:
        setup.steps = None
    setup.external_offboard = args.external_offboard
    if link.unit_interface:  # (the command line over the scenario's [units] interface)
        setup.scenario.unit_interface = link.unit_interface
    try:
        link.check_unit_interface(setup.scenario.unit_interface)
    except UserInputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    ports = Ports(args.world_port, args.coordinator_port, args.world_fd, args.coordinator_fd, link,
                  1.0 / setup.scenario.sim.control_hz if args.command_age else None)
    out = Path(args.out)
    try:
        return _run_role(args, setup, ports, out, key)
    except EnvironmentFailure as e:  # e.g. a port that cannot be bound: this process could not start (exit 3)
        print(f"error: {e}", file=sys.stderr)
        return 3
    except UserInputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    finally:  # the links' logs written, the Zenoh session closed (an open one hangs the exit)
        ports.close(out)


def _link_spec(args) -> LinkSpec:
    """The transport every link of this process uses (`--transport` ...); bad options: UserInputError."""
    link = spec_from_args(args)
    if link.kind == "udp":
        if link.profile:
            raise UserInputError("--link-profile applies to the zenoh transport")
        if not 0 < args.world_port < 65536:
            raise UserInputError(f"--transport udp needs --world-port 1..65535, got {args.world_port}")
    if link.profile:
        from mars_link.transport.profiles import profile_from_name

        try:
            profile_from_name(link.profile)
        except ValueError as e:
            raise UserInputError(f"--link-profile: {e}") from None
    return link


def _int_list(text: str | None, option: str) -> list[int]:
    """"3" or "1,2,3" -> [3] / [1, 2, 3]; None -> []."""
    if text is None:
        return []
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise UserInputError(f"{option} {text!r}: expected integers separated by commas") from None


def _run_role(args, setup: SitlSetup, ports: Ports, out: Path, key: bytes | None) -> int:
    if args.role == "world":
        seed = args.seed if args.seed is not None else setup.scenario.sim.seed
        speed = args.speed if args.speed is not None else (0.0 if setup.docked else 1.0)
        setup.position_every = args.position_every
        start = None
        if args.start_pose:  # the launcher computed them: spares the world importing the coordinator stack
            n, e, d, yaw = (float(x) for x in args.start_pose.split(","))
            start = (np.array([n, e, d]), yaw)
        return run_world(setup, ports, out, seed, speed=speed, start=start, mcap=args.mcap, foxglove=args.foxglove,
                         key=key)
    if args.role == "unit":
        units, api_ports = _int_list(args.unit, "--unit"), _int_list(args.api_port, "--api-port")
        for u in units:
            if u not in setup.unit_ids:
                raise UserInputError(f"unit {u} is not in this run (units {setup.unit_ids})")
        if len(set(units)) != len(units):
            raise UserInputError(f"--unit {args.unit}: a unit named twice")
        if api_ports and len(api_ports) != len(units):
            raise UserInputError(f"--api-port {args.api_port}: one port per unit of --unit {args.unit}")
        clients = [UnitPorts(args.gcs_port, api_ports[i] if api_ports else None, args.gcs_bind, args.api_bind,
                             args.no_clients) for i in range(len(units))]
        return run_units(setup, units, ports, out, clients, key=key, require_signing=args.require_signing,
                         run_key=args.run_key)
    vehicle = None
    if args.vehicle:
        from mars_link.processes.vehicle_host import VehiclePorts

        given = {"sysid": args.vehicle_sysid, "gcs_port": args.vehicle_gcs_port, "api_port": args.vehicle_api_port,
                 "gcs_bind": args.vehicle_gcs_bind, "api_bind": args.vehicle_api_bind, "map_path": args.vehicle_map}
        vehicle = VehiclePorts(**{k: v for k, v in given.items() if v is not None})
        vehicle.check(setup.unit_ids)
    return run_coordinator(setup, ports, out, key=key, vehicle=vehicle, timing_log=args.timing_log,
                           require_signing=args.require_signing, view_feed=args.view_feed, run_key=args.run_key)


if __name__ == "__main__":
    sys.exit(main())
