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

Three set-ups (`SitlSetup`), each a world of bodies from a list (`build.make_bodies_world`: one body, one per
piece of the start, one 1x1 body per free unit):
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
           without stepping. The world logs every unit's centre (world_truth.csv).
Every set-up: the world runs the flight recorder on its truth (telemetry.csv, units.csv and the summary's
figures, world_summary.json "recorder"), with the coordinator's record of each step when a coordinator
runs (mars_link.processes.step_record says why there).
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

Loops: every process steps the flight's engine (mars_link.flight.engine.Engine), the order the in-process
flight steps; what a process does not host is a proxy over its links (mars_link.processes.engine_links:
`HilUnits` in the world, `LinkedUnits` in the coordinator, `HostedFirmware` in a unit process: the world
its HIL link, the coordinator its coordinator link or PX4's interface, the units its firmwares, whose frame
handlers then only receive). What keeps a loop of its own: the receive waits inside those proxies (in a
unit process, `run_units`' `serve`: frames into the firmwares, heartbeats, client links, status files)
and the pacer.

Links: every process builds its links once at start from `--transport udp|zenoh` (`mars_link.processes.links.Ports`)
and hands each to its I/O as a `mars_link.transport.Transport`: the world's and the coordinator's `Link`
(MAVLink parser, peer table, counters), a unit's HIL and coordinator links in
`mars_link.processes.vehicle_io.VehicleSockets` (its GCS/API client links stay UDP, as ground stations expect).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import selectors
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mars_link.mavlink.signing import signing_from_args
from mars_link.processes.cli_options import add_lockstep_options
from mars_link.processes.parent_watch import die_with_parent
from mars_link.core.errors import EnvironmentFailure, UserInputError
from mars_link.runtime.machine_load import IdleMeter, LoopMeter
from mars_link.logs.outputs import SafeWriter, write_json
from mars_link.runtime.pacing import Pacer, SilenceDeadline
from mars_link.runtime.scheduling import take_realtime_class
from mars_link.transport import LinkSpec, spec_from_args
from mars_link.processes.engine_links import (
    COORDINATOR_SYSID,
    COORDINATOR_TIMEOUT_S,
    WORLD_SYSID,
    WORLD_UNIT_TIMEOUT_S,
    HilUnits,
    HostedFirmware,
    LinkedUnits,
    LinksEnded,
    shutdown_message,
)
from mars_link.processes.links import Link, Ports
from mars_link.processes.step_record import StepRecordSender

if TYPE_CHECKING:
    from mars_link.core.assembly import AssemblyModel
    from mars_link.config.scenario import Scenario

MAX_FREE_UNITS = 10  # API ports 14540..14549 (14550 is the GCS port)
UNIT_COMMAND_TIMEOUT_S = 2.0
STATUS_PERIOD_S = 0.2  # world status (truth) file
UNIT_STATUS_PERIOD_S = 1.0  # unit status files (a file replace costs milliseconds here)
TICK_PERIOD_S = 0.02  # unit: heartbeats and streams (<= 20 Hz) served on this wall-clock grid
HOUSEKEEPING_DEFER_S = 0.02  # unit: housekeeping waits at most this long past its time for a step in flight
PX4_KEEPALIVE_HZ = 10.0  # coordinator: OffboardControlMode rate on PX4's interface (PX4 wants >= 2 Hz)
PX4_TELEMETRY_PERIOD_S = 0.1  # unit: /fmu/out telemetry at 10 Hz of wall time (vehicle_status also answers
# every command); what PX4's dds_topics.yaml allows is more, but it is CPU the lockstep shares
PX4_LINK = "px4"  # a unit's rmw_zenoh endpoint in the unit loop's selector (mars_link.processes.px4_link)
ACTUATOR_MOTORS_TOPIC = "/fmu/in/actuator_motors/"  # (in a unit's data key: a per-rotor command)
#: set (to anything) in a unit process's environment: its PX4 keep-alive never times out. A test switch for the
#: conformance harness's red run, never for flight (mars_link.px4.unit_interface keepalive_timeout_enabled)
BROKEN_KEEPALIVE_ENV = "MARS_LINK_TEST_BROKEN_PX4_KEEPALIVE"


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


# ----------------------------------------------------------------------------- world


class _WorldLogs:
    """Observer: the world's truth each step (world_truth.csv), its status file every STATUS_PERIOD_S of
    wall time, and the flight view (run.mcap, the live view) when asked for."""

    def __init__(self, world, truth_log, truth_row, write_status, write_view=None) -> None:
        self.world, self.truth_log, self.truth_row, self.write_status = world, truth_log, truth_row, write_status
        self.write_view = write_view
        self.next_status = 0.0

    def on_step(self, engine, v) -> bool:
        t = self.world.t_s
        self.truth_log.write("%.6f," % t + ",".join("%.9f" % x for x in self.truth_row()) + "\n")
        if self.write_view is not None:
            self.write_view(t)
        if time.monotonic() >= self.next_status:
            self.next_status = time.monotonic() + STATUS_PERIOD_S
            self.write_status(t)
            self.truth_log.flush()
        return False


def run_world(setup: SitlSetup, ports: Ports, out: Path, seed: int, unit_timeout_s: float = WORLD_UNIT_TIMEOUT_S,
              speed: float = 0.0, start: tuple[np.ndarray, float] | None = None, mcap: bool = False,
              foxglove: str | None = None, key: bytes | None = None) -> int:
    """Own the bodies, run the lockstep; `speed` > 0 paces sim time to that many x wall time. `start`
    (CoM NED, yaw) as the launcher computed it, else from the scenario's trajectory. `mcap`: run.mcap in
    `out`; `foxglove`: HOST:PORT of the live Foxglove view (mars_link.processes.view_feed says why the world hosts them)."""
    from mars_link.flight.build import docked_bodies, free_units_bodies, free_units_config, make_bodies_world, world_config
    from mars_link.flight.engine import Engine, Flight

    sc = setup.scenario
    cfg = dataclasses.replace(world_config(sc, seed), position_every=position_every(setup))
    world_model = setup.model
    if setup.pieces:  # one body per piece of the executor's start (the coordinator builds the same executor)
        from mars_link.flight.build import make_executor, make_trajectory, pieces_bodies

        bodies = pieces_bodies(setup.model, make_executor(sc, setup.model, make_trajectory(sc, setup.model))[0])
    elif setup.docked:
        bodies = docked_bodies(setup.model, *(start or _start_pose(setup)))
    else:
        world_model, bodies = free_units_bodies(setup.model.vehicle, setup.free_units)
        cfg = free_units_config(cfg)
    world = make_bodies_world(sc, world_model, bodies, seed, cfg)
    columns, truth_row = _truth_log(setup, world)
    stop = _Stop()
    link = Link(ports.open("world"), WORLD_SYSID, key=key)  # with a key: HIL both ways and the shutdown signed
    out.mkdir(parents=True, exist_ok=True)
    status_path = out / "world_status.json"
    # a write error stops the log, never the world; its own thread writes it, so a slow disk never paces the world
    truth_log = SafeWriter.open(out / "world_truth.csv", background=True)
    truth_log.write("t_s," + columns + "\n")
    wall0 = time.perf_counter()
    units = None
    from mars_link.flight.run_log import PLOT_ROWS_MAX, ROTOR_LOG_HZ, RunLog
    from mars_link.processes.step_record import StepRecords, WorldRecorder

    # the flight recorder's time series (the rotors' are the units': the run's parent writes rotors.csv)
    run_log = RunLog(out, world.model, rotor_log_hz=min(sc.sim.control_hz, ROTOR_LOG_HZ), plot_rows_max=PLOT_ROWS_MAX,
                     series=("telemetry", "units"))
    records = StepRecords(COORDINATOR_SYSID, link.dropped) if setup.coordinated else None
    view, feed, reference, eta_at = _world_view(setup, world, out, mcap, foxglove)
    writer_pid = view.process.pid if view is not None and mcap else None
    try:
        live = set(setup.unit_ids)
        _await_peers(link, live | ({COORDINATOR_SYSID} if setup.coordinated else set()), 60.0, stop)
        link.prepare_peers(live)  # (the first sends' set-up, paid in the first step, stalled a paced start)
        wall0 = time.perf_counter()
        # sim time on the wall clock at `speed`; behind it, the world catches up (no re-anchoring): the
        # lockstep's real-time factor stays the one asked for
        # (anchored at the first step's wait, once its datagrams are ready: the first sensing, slow the
        # first time, then belongs to start-up as in every later step it precedes the wait)
        pacer = Pacer(speed, reanchor_s=math.inf, clock=time.perf_counter)
        vehicle = setup.model.vehicle
        units = HilUnits(world, link, setup.unit_ids, stop, pacer, vehicle.full_scale_thrust_n,
                         0.0 if vehicle.rotor_min_thrust_n is not None else -1.0,  # (as the units' intake)
                         setup.coordinated, setup.pieces, feed, unit_timeout_s, records)
        write_view = None if view is None else lambda t: view.write_step(
            t, world, feed.point(None if reference is None else reference.sample(t)), eta_at(t), [units.deaths, feed.events])
        logs = _WorldLogs(world, truth_log, truth_row, lambda t: _write_world_status(
            status_path, world, setup, units.live, t, time.perf_counter() - wall0, writer_pid), write_view)
        flight = Flight(sc, setup.model, seed, None, world, units, None, sorted(sc.faults, key=lambda f: f.t_s),
                        duration_s=math.inf if setup.steps is None else setup.steps / sc.sim.control_hz)
        # (the coordinator is another process: its commands go to the units, the units' answers come here)
        recorder = WorldRecorder(flight, records, run_log)
        engine = Engine(flight, [logs, recorder], command_source=lambda t, telemetry: [])
        loop = LoopMeter()  # the stepping loop alone (start-up excluded)
        idle = IdleMeter()  # the machine's idle cores over the loop: behind the wall clock, starved or at fault?
        try:
            while not stop.requested and engine.step():
                pass
        except LinksEnded:
            pass
        wall = time.perf_counter() - wall0
        _write_world_status(status_path, world, setup, units.live, world.t_s, wall, writer_pid)
        summary = {"sim_time_s": world.t_s, "wall_time_s": wall, "real_time_factor": world.t_s / max(wall, 1e-9),
                   "steps": engine.steps, "units": setup.unit_ids, "dead_units": sorted(units.dead),
                   "deaths": units.deaths, "dropped": link.dropped, "stopped": stop.requested,
                   "cpu_s": time.process_time(), **loop.figures(), "realtime_class_left_at_s": units.valve.left_at_s,
                   "cores_idle_fraction": idle.fraction(), "force_integral_n2s": world.force_integral_n2s,
                   "latch_events": world.latch_events, "bodies": [list(b.units) for b in world.bodies],
                   "logging": truth_log.status(), "recorder": recorder.figures()}
        packs = world.packs
        if packs is not None:  # the packs' truth at the end (unit id order)
            summary["batteries"] = {"soc": packs.soc.round(6).tolist(), "voltage_v": packs.voltage_v.round(4).tolist(),
                                    "drawn_c": packs.drawn_c.round(4).tolist()}
        run_log.close()  # (its files' status in the summary: a full disk stopped them, or not)
        summary["run_log"] = run_log.status()
        _write_world_summary(out, summary)
    finally:
        truth_log.close()
        run_log.close()
        try:  # run.mcap before the link: a Zenoh session can take seconds to close, and the file must be
            if view is not None:  # whole when `sitl up` ends
                view.finish(event_lists=[[] if units is None else units.deaths, feed.events])
                mcap = view.status()
                if mcap is not None and mcap["stopped_reason"] and (out / "world_summary.json").exists():
                    _write_world_summary(out, {**json.loads((out / "world_summary.json").read_text()),
                                               "mcap_stopped_reason": mcap["stopped_reason"]})
        finally:
            world.close()
            link.close()
    return 0


def _truth_log(setup: SitlSetup, world) -> tuple[str, object]:
    """world_truth.csv's columns and its row of a step: a docked assembly's CoM and attitude; each unit's centre
    in a flight of pieces; each free unit's centre and attitude (the formats its readers know)."""
    if setup.pieces:
        return ",".join(f"u{u}_{c}" for u in setup.unit_ids for c in ("n_m", "e_m", "d_m")), world.units_row
    if setup.docked:
        return "pos_n_m,pos_e_m,pos_d_m,qw,qx,qy,qz", world.truth_row
    return (",".join(f"u{u}_{c}" for u in setup.unit_ids for c in ("pos_n_m", "pos_e_m", "pos_d_m", "qw", "qx", "qy", "qz")),
            lambda: _poses_row(world))


def _poses_row(world) -> list[float]:
    """Every unit's centre (NED) and attitude, in unit id order: the truth log of free units."""
    row: list[float] = []
    for u in world.model.unit_ids:
        s = world.unit_truth(u)
        row += [*s.position_ned_m, *s.quaternion_wxyz]
    return row


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
        model = world.model
        duration = setup.steps / sc.sim.control_hz if setup.steps is not None else math.inf
        view = open_view(out, model, sc, sc.sim.control_hz, None, duration, live, None, mcap)
        healthy = np.ones(model.n_rotors)
        return view, ViewFeed(np.zeros(3)), None, lambda t: healthy
    reference = _trajectory(sc, model) if setup.steps is not None else None  # --vehicle: the coordinator's only
    duration = setup.steps / sc.sim.control_hz if setup.steps is not None else math.inf
    view = open_view(out, model, sc, sc.sim.control_hz, reference, duration, live, sc.tracked_unit(), mcap)
    faults = sorted(sc.faults, key=lambda f: f.t_s)
    return view, ViewFeed(tracked_offset(model, sc)), reference, lambda t: eta_after(model, faults, t)  # (as rotors.csv)


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
    with its own links, tlog, ULog (unit<id>.ulg, unless `ulog` is False) and status file, stepped by one
    engine (`HostedFirmware`) whose waits serve every link: one wake-up serves every unit whose datagram
    came in, and the start-up (imports) is paid once. One unit is the default."""
    from mars_link.flight.engine import Engine, Flight
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

        held: dict[tuple, object] = {}  # (unit, link) -> transport: input left waiting while its unit's step runs

        def serve(until_s: float) -> None:
            """One wait of this process's I/O, at most until `until_s` (monotonic): every frame received into
            its firmware, every unit's housekeeping when due. A unit whose step may run (its command is in)
            takes no more input until the engine ran it: what follows the command is for the steps after."""
            now = time.monotonic()
            wake = min(until_s, *(unit.housekeeping(now) for unit in units))
            for unit in units:  # (a stall of this process is not the coordinator's silence)
                if unit.command_deadline is not None:
                    unit.command_deadline.before_wait(max(0.0, wake - now))
            due = [k for k in held if not k[0].step_runs]
            ready = {k: held.pop(k) for k in due}
            for key_, _ in sel.select(0.0 if due else max(0.0, wake - now)):
                ready[key_.data] = key_.fileobj
            for (unit, name), fileobj in ready.items():
                if name == PX4_LINK:
                    unit.drain_px4()
                else:
                    unit.io.drain(name, fileobj, lambda unit=unit: unit.step_runs)
                if unit.step_runs:
                    held[(unit, name)] = fileobj

        hosted = HostedFirmware(units, serve, stop)
        sc = setup.scenario
        flight = Flight(sc, setup.model, sc.sim.seed, None, hosted, hosted, None, [],
                        duration_s=math.inf if setup.steps is None else setup.steps / sc.sim.control_hz)
        engine = Engine(flight, command_source=hosted.commands)
        try:
            while not stop.requested and engine.step():
                pass
        except LinksEnded:
            pass
        for unit in units:
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
    """One unit's firmware, its links and its wall-clock housekeeping: stepped by `run_units`' engine,
    served by its waits."""

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
        vehicle.hil_stepped_by_host = True  # the process's engine takes each HIL step (HostedFirmware)
        self.px4_link = None  # PX4's own interface over rmw_zenoh, beside the MAVLink persona (vehicle_px4)
        self.px4_log = None  # every rmw_zenoh sample it received, as received (px4_input_log_name)
        self.px4_backlog: list = []  # samples received after the one that let a step run, for the steps after
        self.next_px4_telemetry = 0.0
        self.command_age = ports.taps.get(unit_id)
        if sc.unit_interface == "px4-zenoh":
            from mars_link.processes.px4_link import Px4UnitLink

            px4 = vehicle.px4_service
            px4.keepalive_timeout = not os.environ.get(BROKEN_KEEPALIVE_ENV)  # (conformance: a test switch)
            px4.ensure_interface()
            self.px4_link = Px4UnitLink(ports.zenoh_session(), px4.endpoint)
            self.px4_log = open(out / px4_input_log_name(unit_id), "w", encoding="utf-8")  # (replayable)

    @property
    def step_runs(self) -> bool:
        """The unit's HIL step may run now: taken, and its command is in (or it waits for none)."""
        return self.vehicle.hil_pending and self.vehicle.hil_service.command_in

    def drain_px4(self) -> None:
        """Every rmw_zenoh sample received, up to the one that lets the unit's step run (`step_runs`; the
        rest wait for the next drain): into the firmware; its answers out (command acks and status)."""
        vehicle, link, tap = self.vehicle, self.px4_link, self.command_age
        log = self.px4_log
        self.px4_backlog += link.take()
        while self.px4_backlog and not self.step_runs:
            key, payload, attachment = self.px4_backlog.pop(0)
            now = time.time()
            log.write(json.dumps({"sim_s": vehicle.sim_s, "wall_s": now, "key": key, "payload": payload.hex(),
                                  "attachment": None if attachment is None else attachment.hex()}) + "\n")
            out, samples = vehicle.px4_service.sample(key, payload, attachment, now)
            if tap is not None and ACTUATOR_MOTORS_TOPIC in key and vehicle.hil_service.last_rotor_usec is not None:
                tap.on_command(vehicle.hil_service.last_rotor_usec / 1e6, now)
            if out:
                self.io.send(out)
            if samples:
                link.publish(samples)

    def housekeeping(self, now: float) -> float:
        """The unit's own state, heartbeats, streams and status file when due; returns when to wake next.
        Housekeeping waits while a step is in flight, at most HOUSEKEEPING_DEFER_S past its time, and
        runs in the wake-up that answered the step: a wake-up of its own finds the caches cold after the
        other processes ran (with 25 unit processes that cost more than the work itself)."""
        from mars_link.processes.vehicle_io import vehicle_status, write_json_atomic

        vehicle, io = self.vehicle, self.io
        steps = vehicle.stats.get("hil_steps", 0)
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
                    self.px4_link.publish(vehicle.px4_service.telemetry_samples())
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


class _ViewFeedSender:
    """Observer: after the commands, the world's view gets the coordinator's estimate, reference and new
    events (mars_link.processes.view_feed)."""

    def __init__(self, link: Link, world, coordinator) -> None:
        self.link, self.world, self.coordinator = link, world, coordinator
        self.fed = 0

    def on_step(self, engine, v) -> bool:
        from mars_link.processes.view_feed import feed_messages

        c = self.coordinator
        if c.last is not None:
            self.link.send_bytes(self.link.pack(feed_messages(c.last, c.events[self.fed:])), self.world)
            self.fed = len(c.events)
        return False


class _TimingLog:
    """Observer: each step's wall-clock times (coordinator_timing.csv, LinkedUnits says which)."""

    def __init__(self, log, linked: LinkedUnits) -> None:
        self.log, self.linked = log, linked
        log.write("t_s,telemetry_first_wall_s,telemetry_all_wall_s,computed_wall_s,sent_wall_s,step_cpu_s,send_cpu_s\n")

    def on_step(self, engine, v) -> bool:
        x = self.linked
        self.log.write(f"{v.t_s:.6f},{x.first_wall:.6f},{x.all_wall:.6f},{x.computed_wall:.6f},{x.sent_wall:.6f},"
                       f"{x.step_cpu:.6f},{x.send_cpu:.6f}\n")
        return False


def run_coordinator(setup: SitlSetup, ports: Ports, out: Path, unit_timeout_s: float = COORDINATOR_TIMEOUT_S,
                    key: bytes | None = None, vehicle=None, timing_log: bool = False,
                    require_signing: bool = False, view_feed: bool = False, run_key: bool = False) -> int:
    """Drive the docked assembly: the flight's engine (mars_link.flight.engine.Engine) with the world and the
    units behind this process's link (`LinkedUnits`); with a signing `key` that link is signed both ways.
    With `vehicle` (mars_link.processes.vehicle_host.VehiclePorts) the assembly is one MAVLink vehicle on those ports
    and its guidance, not the scenario's trajectory, is the coordinator's reference. `timing_log`:
    coordinator_timing.csv gets each step's wall-clock times (`_TimingLog`): with the units' command_age logs,
    where a real-time step's time goes (wall time above CPU time = the coordinator waited for a CPU)."""
    from mars_link.flight.engine import Engine, Flight

    sc = setup.scenario
    model = setup.model
    trajectory = _trajectory(sc, model)
    hosted = None
    end_s = None  # a flight of pieces: when it ends (the coordinator says so to the world)
    if vehicle is None:  # a docked assembly is a flight of one piece: the one coordinator of every flight
        from mars_link.flight.build import make_pieces_coordinator

        coordinator, pieces_end_s = make_pieces_coordinator(sc, model, trajectory)
        end_s = pieces_end_s if setup.pieces else None
    else:  # (one body or pieces: the vehicle flies until stopped)
        from mars_link.processes.vehicle_host import HostedVehicle

        out.mkdir(parents=True, exist_ok=True)
        try:
            hosted = HostedVehicle(sc, model, vehicle, out, None if run_key else key, require_signing)
        except UserInputError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        coordinator = hosted.coordinator
        print(json.dumps({"vehicle": hosted.endpoints()}), flush=True)
    stop = _Stop()
    link = Link(ports.open("coordinator"), COORDINATOR_SYSID, key=key)
    scale = model.vehicle.full_scale_thrust_n
    out.mkdir(parents=True, exist_ok=True)
    timing = SafeWriter.open(out / "coordinator_timing.csv") if timing_log else None
    px4 = commanders = None  # PX4's own interface ([units] interface = "px4-zenoh"): the commands go over rmw_zenoh
    if sc.unit_interface == "px4-zenoh":
        from mars_link.processes.px4_link import Px4CoordinatorLink
        from mars_link.px4.commander import Px4Commander

        px4 = Px4CoordinatorLink(ports.zenoh_session(), model.unit_ids)
        keepalive_every = max(1, int(sc.sim.control_hz // PX4_KEEPALIVE_HZ))
        commanders = {u: Px4Commander(u, scale, model.vehicle.rotor_min_thrust_n is None, keepalive_every)
                      for u in model.unit_ids}
    linked = None
    try:
        _await_peers(link, set(model.unit_ids), 60.0, stop)
        link.prepare_peers(set(model.unit_ids))
        if px4 is not None:
            for u in model.unit_ids:
                px4.prepare(u)
        loop = LoopMeter()
        link.peers.setdefault(WORLD_SYSID, ports.address("world"))  # (its step-sent markers come from there)
        link.heartbeat(link.peers[WORLD_SYSID])
        linked = LinkedUnits(link, list(model.unit_ids), scale, stop, coordinator.unit_lost, unit_timeout_s,
                             None if hosted is not None else coordinator.finish_step, hosted, px4, commanders)
        flight = Flight(sc, model, sc.sim.seed, trajectory, linked, linked, coordinator, sorted(sc.faults, key=lambda f: f.t_s),
                        duration_s=math.inf if setup.steps is None else setup.steps / sc.sim.control_hz,
                        end_s=None if end_s is None else lambda: -math.inf if coordinator.failed is not None else end_s())
        # each step's record to the world, whose flight recorder measures it on the truth (mars_link.processes.step_record)
        observers: list = [StepRecordSender(link, linked.world, flight, WORLD_SYSID)]
        if view_feed:
            observers.append(_ViewFeedSender(link, linked.world, coordinator))
        if timing:
            observers.append(_TimingLog(timing, linked))
        commands = coordinator.commands if hosted is None else lambda t, packets: hosted.step(t, packets, linked.live)
        engine = Engine(flight, observers, command_source=commands)
        try:
            engine.run()
            if end_s is not None:  # the flight of pieces is over: instead of the first step not to be flown
                link.send_bytes(link.pack([shutdown_message()]), linked.world)
        except LinksEnded:
            pass
        linked.finish()
        pieces = {}
        if hosted is None:  # (what the in-process result says of the pieces: runner.trial_result)
            plan = coordinator.executor.plan
            pieces = {"pieces_final": coordinator.pieces_final(), "failed": coordinator.failed,
                      "shift_s": coordinator.executor.shift_s,
                      "plan": plan.to_json() if plan.disassembly_layers or plan.assembly_layers else None}
        write_json(out / "coordinator_summary.json",
            {"events": coordinator.all_events() if hosted is None else coordinator.events, **pieces,
             "lost_units": linked.lost, "dropped": link.dropped, "cpu_s": time.process_time(),
             "detections": [{"t_detected": round(d.t_detected, 6), "unit": d.unit, "rotor": d.rotor,
                             "eta_estimated": round(float(d.eta_estimated), 4), "reason": d.reason}
                            for d in coordinator.detections],
             **loop.figures(),
             "acknowledged": {str(u): sorted(c) for u, c in linked.accepted.items()}})
    finally:
        if px4 is not None:
            px4.close()
        link.close()
        if timing:
            timing.close()
        if hosted is not None:
            hosted.close()
    return 0


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
