"""Real-time runner: the assembly (in-process JSBSim physics + coordinator) behind its MAVLink endpoint.

    mars-link vehicle [SCENARIO.toml] [--layout ROWS] [--gcs-port P] [--api-port P] [--sysid N]

`VehicleSim` (mars_link.vehicles.vehicle_sim) is stepped once per control period, paced to wall time
(scaled by --speed); between steps the UDP sockets are drained into the vehicle. Links, all on
127.0.0.1 (PX4's SITL conventions, specs/mavlink.md §1.1):
  gcs  the vehicle sends to --gcs-port (default 14550: QGroundControl, MAVProxy `udpin`) from
       --gcs-bind (default 18560)
  api  the vehicle sends to --api-port (default 14539: MAVSDK `udpin://127.0.0.1:14539`, as under
       `sitl up --vehicle`, whose units take PX4's 14540+i) from --api-bind (default 14560)
  On both, whoever last sent a valid frame to the bound port also gets the traffic (MAVProxy
  `--master=udpout:127.0.0.1:18560`). A bind port 0 means any free port.
Socket handling (flood limits, loopback-only senders, peers) is every Vehicle runner's
(`mars_link.processes.vehicle_io.VehicleSockets`).
Runs until Ctrl-C / SIGTERM, --duration simulated seconds or --wall-time wall seconds. A machine too slow to keep up is re-anchored
(counted as an overrun) instead of racing to catch up.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from firmware_models.vehicle import LINK_API, LINK_GCS
from mars_link.processes.vehicle_io import API_PORT_BASE, LOOPBACK, LinkSpec, VehicleSockets, write_json_atomic
from mars_link.vehicles.vehicle_sim import SimConfig, VehicleSim
from mars_link.core import validation
from mars_link.core.errors import UserInputError
from mars_link.runtime.pacing import Pacer
from mars_link.processes.ports import VEHICLE_API_BIND, VEHICLE_GCS_BIND
from mars_link.config.scenario import INTERACTIVE_SCENARIO as DEFAULT_SCENARIO  # (the realistic plant)

STATUS_PERIOD_S = 0.2
API_PORT = API_PORT_BASE  # PX4 SITL instance 0's API port (the vehicle's default until it agreed with sitl up --vehicle)
GCS_BIND, API_BIND = VEHICLE_GCS_BIND, VEHICLE_API_BIND  # below the units' 18570+i / 14580+i


class AssemblyRunner:
    """Sockets (mars_link.processes.vehicle_io.VehicleSockets, as every Vehicle runner) and clocks for an
    VehicleSim."""

    def __init__(self, sim: VehicleSim, ports: dict[str, int], speed: float = 1.0,
                 status_file: str | None = None, duration_s: float | None = None, tlog: str | None = None,
                 wall_time_s: float | None = None) -> None:
        self.sim = sim
        self.vehicle = sim.vehicle
        self.speed = speed
        self.io = VehicleSockets(sim.vehicle, {
            LINK_GCS: LinkSpec(ports["gcs_bind"], (LOOPBACK, ports["gcs_port"])),
            LINK_API: LinkSpec(ports["api_bind"], (LOOPBACK, ports["api_port"])),
        }, Path(tlog) if tlog else None)
        self.status_path = Path(status_file) if status_file else None
        self.duration_s = duration_s  # simulated seconds
        self.wall_time_s = wall_time_s
        self.running = True
        self.pacer = Pacer(speed)  # overruns (re-anchored) and late steps are counted there
        self.steps = 0
        self._step_s: list[float] = []  # compute time per step (a rolling window)

    def endpoints(self) -> dict:
        p = self.io.ports()
        return {"sysid": self.vehicle.sysid, "gcs": {"to": self.io.dest[LINK_GCS][1], "from": p[LINK_GCS]},
                "api": {"to": self.io.dest[LINK_API][1], "from": p[LINK_API]}}

    def write_status(self) -> None:
        if self.status_path is None:
            return
        v, sim = self.vehicle, self.sim
        s = sim.truth()
        est = sim.estimate
        steps = np.array(self._step_s[-2000:]) if self._step_s else np.zeros(1)
        status = {
            "sysid": v.sysid, "layout": list(sim.scenario.layout), "sim_time_s": sim.t_s, "wall_time_s": time.time(),
            "armed": v.armed, "mode": list(v.mode), "phase": v.autopilot.phase.value, "landed": bool(v.landed),
            "truth_position_ned_m": [float(x) for x in s.position_ned_m],
            "truth_velocity_ned_mps": [float(x) for x in s.velocity_ned_mps],
            "truth_quaternion_wxyz": [float(x) for x in s.quaternion_wxyz],
            "estimate_position_ned_m": None if est is None else [float(x) for x in est.position_ned_m],
            "unit_eta": sim.unit_eta(), "eta_believed": [float(x) for x in sim.eta_believed()],
            "rotor_thrust_n": [float(x) for x in sim.world.rotor_thrust_n],
            "events": sorted(sum(sim.event_lists(), []), key=lambda e: e["t_s"])[-50:], "statustext": [t for _, t in v.events[-50:]],
            "drops": v.drop_counts(), "stats": v.stats, "estimator_resets": sim.estimator_resets,
            **self.io.counters(), "overruns": self.overruns, "steps": self.steps, "late_steps": self.late_steps,
            "step_p50_ms": float(np.percentile(steps, 50) * 1e3), "step_p99_ms": float(np.percentile(steps, 99) * 1e3),
            "endpoints": self.endpoints(),
            "mission_reached": v.mission_service.reached, "mission_counts": v.mission.counts,
        }
        write_json_atomic(self.status_path, status)

    def run(self) -> int:
        start = time.monotonic()
        pacer = self.pacer
        pacer.start(self.sim.t_s)
        next_status = start
        self.write_status()
        while self.running:
            now = time.monotonic()
            if self.wall_time_s is not None and now - start >= self.wall_time_s:
                break
            if self.duration_s is not None and self.sim.t_s >= self.duration_s - 1e-9:
                break
            self.io.poll(pacer.wait_s(self.sim.t_s))
            now = time.monotonic()
            if pacer.is_due(self.sim.t_s, self.sim.control_dt_s):
                c0 = time.perf_counter()
                self.io.send(self.sim.step(time.time()))
                self._step_s.append(time.perf_counter() - c0)
                if len(self._step_s) > 20000:
                    del self._step_s[:10000]
                self.steps += 1
            if now >= next_status:
                next_status = now + STATUS_PERIOD_S
                self.write_status()
        self.write_status()
        return 0

    @property
    def overruns(self) -> int:
        return self.pacer.overruns

    @property
    def late_steps(self) -> int:
        return self.pacer.late_steps

    def close(self) -> None:
        self.io.close()
        self.sim.close()


# ----------------------------------------------------------------------------- command line (options: mars_link.apps.cli)
def _check_port(name: str, value: int, allow_zero: bool) -> int:
    lo = 0 if allow_zero else 1
    if not lo <= value <= 65535:
        raise UserInputError(f"{name} must be {lo}..65535, got {value}")
    return value


def build_sim(args: argparse.Namespace) -> VehicleSim:
    """Scenario + command-line overrides -> VehicleSim; every problem is a UserInputError."""
    from mars_link.core.assembly import parse_layout
    from mars_link.config.scenario import FTC_MODES, load_scenario, parse_fault_arg, validate_fault

    scenario = load_scenario(args.scenario or DEFAULT_SCENARIO)
    if args.layout is not None:
        scenario.layout = parse_layout(args.layout)
    if args.ftc:
        if args.ftc not in FTC_MODES:
            raise UserInputError(f"--ftc {args.ftc!r}: unknown mode (known: {', '.join(FTC_MODES)})")
        scenario.ftc = args.ftc
    for text in args.fault or []:
        scenario.faults.append(parse_fault_arg(text))
    model = scenario.model()
    for f in scenario.faults:
        validate_fault(f, model, f"fault {f.describe()}")
    from mars_link.config.scenario import check_faults_controllable

    check_faults_controllable(scenario, model)  # the check `run` and `sitl up` make
    if args.seed is not None:
        scenario.sim.seed = args.seed
    if args.no_noise:
        scenario.sim.noise = False
    if not (math.isfinite(args.speed) and 0.05 <= args.speed <= 20.0):
        raise UserInputError(f"--speed must be 0.05..20, got {args.speed}")
    for name, value in (("--duration", args.duration), ("--wall-time", getattr(args, "wall_time", None))):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise UserInputError(f"{name} must be > 0, got {value}")
    if scenario.controller != "cascaded":
        raise UserInputError(f"controller {scenario.controller!r}: the vehicle flies setpoints with 'cascaded' only")
    if not 1 <= args.sysid <= 250 or args.sysid in (200, 201):
        raise UserInputError(f"--sysid must be 1..250 and not 200/201 (world, coordinator), got {args.sysid}")
    from mars_link.mavlink.signing import signing_from_args
    from mars_link.processes.udp_runner import _params  # NAME=VALUE parsing, as the unit runner's --param

    key, require = signing_from_args(args)
    map_path = args.map or scenario.mission.get("map")
    if map_path is not None:
        check_map(map_path, "--map" if args.map else f"{scenario.source}: [mission] map")
    return VehicleSim(scenario, SimConfig(sysid=args.sysid, params=_params(args.param), signing_key=key,
                                          require_signing=require, map_path=map_path), time.time())


def check_map(path: str, what: str) -> None:
    """The map loads (before any socket opens): else one UserInputError line."""
    from mars_link.planning.maps import load_map
    from mars_link.planning.pipeline import resolve_data_path

    resolved = resolve_data_path(path)
    if not resolved.is_file():
        raise UserInputError(f"{what} {path!r}: no such file")
    try:
        load_map(resolved)
    except (OSError, ValueError) as exc:
        raise UserInputError(f"{what} {path!r}: {exc}") from None


def vehicle_command(args: argparse.Namespace) -> int:
    ports = {
        "gcs_port": _check_port("--gcs-port", args.gcs_port, False),
        "api_port": _check_port("--api-port", args.api_port, False),
        "gcs_bind": _check_port("--gcs-bind", args.gcs_bind, True),
        "api_bind": _check_port("--api-bind", args.api_bind, True),
    }
    validation.check_file_parent(args.status_file, "--status-file")
    validation.check_file_parent(args.tlog, "--tlog")
    from mars_link.flight.flight_view import live_address

    live = live_address(args)  # a busy --foxglove port: one line, exit 3, before the vehicle starts
    out = None
    if args.out is not None:
        out = validation.check_out_dir(args.out)
        validation.prepare_out_dir(out)
    sim = build_sim(args)
    try:
        if args.mission is not None:
            from firmware_models.qgc_plan import load_plan, preload

            preload(sim.vehicle, load_plan(args.mission), args.mission)
        runner = AssemblyRunner(sim, ports, args.speed, args.status_file, args.duration, args.tlog,
                                getattr(args, "wall_time", None))
    except (UserInputError, OSError) as exc:
        sim.close()
        if isinstance(exc, OSError):
            raise UserInputError(f"cannot open {exc.filename}: {exc.strerror}") from None
        raise
    view = _attach_view(sim, None if args.no_mcap else out, live)
    record = _attach_record(sim, out) if out is not None else None
    if out is not None:  # the vehicle's ULog, as PX4 SITL writes one (mars_link.logs; closed by sim.close)
        from firmware_models.vehicle_ulog import UlogConfig

        sim.vehicle.start_ulog(UlogConfig(out / "vehicle.ulg", background=True))
    from firmware_models.vehicle_logs import LogStore

    sim.vehicle.log_service.store = LogStore([args.tlog, out / "run.mcap" if out is not None else None,  # LOG_*
                                              out / "vehicle.ulg" if out is not None else None])
    ep = runner.endpoints()
    s = sim.scenario
    print(f"mars-link vehicle: {s.name}, layout {','.join(s.layout)} ({sim.model.n_units} units, "
          f"{sim.model.n_rotors} rotors), ftc {s.ftc}, MAVLink system {ep['sysid']} component 1")
    print(f"  GCS: udp {LOOPBACK}:{ep['gcs']['from']} -> {LOOPBACK}:{ep['gcs']['to']}  "
          f"(QGroundControl; mavproxy.py --master=udpout:{LOOPBACK}:{ep['gcs']['from']})")
    print(f"  API: udp {LOOPBACK}:{ep['api']['from']} -> {LOOPBACK}:{ep['api']['to']}  "
          f"(MAVSDK udpin://{LOOPBACK}:{ep['api']['to']})")
    print("  Ctrl-C to stop", flush=True)
    from mars_link.processes.vehicle_host import DEFAULT_VEHICLE_API_PORT, DEFAULT_VEHICLE_SYSID

    if args.api_port == DEFAULT_VEHICLE_API_PORT and args.sysid == DEFAULT_VEHICLE_SYSID:  # the defaults that moved
        print(f"mars-link: note: the vehicle is MAVLink system {DEFAULT_VEHICLE_SYSID} on API port "
              f"{DEFAULT_VEHICLE_API_PORT}, as under `sitl up --vehicle` (it was system 1 on 14540: "
              f"--sysid 1 --api-port {API_PORT})", file=sys.stderr, flush=True)
    if args.duration is not None:  # the one change of meaning: said once, after every check passed
        print(f"mars-link: note: vehicle --duration {args.duration:g} is simulated seconds (it was wall seconds; "
              "--wall-time SECONDS limits wall time)", file=sys.stderr, flush=True)

    def stop(*_):
        runner.running = False

    old = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    wall0 = time.perf_counter()
    try:
        code = runner.run()
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        runner.close()
        if view is not None:
            view.finish(sim.engine)
    print(f"stopped after {sim.t_s:.1f} s simulated; overruns {runner.overruns}, late steps {runner.late_steps}",
          flush=True)
    if runner.io.logging_stopped:  # a write error (or the size cap) stopped the .tlog; the flight went on
        print(f"logging stopped: {runner.io.logging_stopped}", flush=True)
    if record is not None:
        summary = record.finish(sim, time.perf_counter() - wall0, args.plot_format)
        from mars_link.flight.report import print_summary

        print_summary(summary, out)
    return code


class _VehicleRecord:
    """`vehicle --out`: what `run` writes (telemetry.csv, rotors.csv, units.csv, summary.json, plots/), from
    the same recorder observing the vehicle's engine, one body or several. The error is the tracked point's
    against the reference its coordinator flies (the vehicle's own setpoints); steps on the ground (the
    coordinator idle) are not recorded; a divergence is reported, it does not stop a vehicle a client flies."""

    def __init__(self, sim: VehicleSim, out: Path) -> None:
        from mars_link.flight.recorder import FlightRecorder
        from mars_link.flight.run_log import PLOT_ROWS_MAX, ROTOR_LOG_HZ, RunLog

        s = sim.scenario
        self.log = RunLog(out, sim.model, rotor_log_hz=min(s.sim.control_hz, ROTOR_LOG_HZ), plot_rows_max=PLOT_ROWS_MAX)
        self.log.new_trial()
        self.recorder = FlightRecorder(sim.engine.flight, self.log, 0, ends_on_divergence=False)
        self.out = out
        sim.engine.observers.append(self.recorder)

    def finish(self, sim: VehicleSim, wall_s: float, plot_format: str) -> dict:
        from mars_link.flight.metrics import summarize
        from mars_link.flight.runner import trial_result, write_plots_safely
        from mars_link.logs.outputs import write_json

        self.log.close()
        flight, engine = sim.engine.flight, sim.engine
        latched = [e for e in flight.world.latch_events if e["type"] == "dock_latched"]
        events = [e for events in sim.event_lists() for e in events] + engine.events + latched
        result = trial_result(flight, engine, self.recorder, sim.scenario.sim.seed, wall_s, events=events)
        summary = summarize(sim.scenario, [result], sim.scenario.sim.seed, mode="vehicle")
        summary["completed"] = not result.diverged  # (a vehicle flies until stopped: stopping is its end)
        if self.recorder.metrics.n == 0:  # (it never flew a mission step: no tracking figures, never a clean 0 m)
            for key in ("mean_error_m", "mean_error_std_m", "rmse_m", "max_error_m"):
                summary[key] = None
            summary["per_trial"][0].update(mean_error_m=None, rmse_m=None, max_error_m=None)
        summary["logging"] = self.log.status()
        write_json(self.out / "summary.json", summary)
        from mars_link.flight.plots import write_flight_plots

        write_plots_safely(self.log, lambda: write_flight_plots(self.out, self.log, sim.scenario, summary["events"],
                                                                plot_format))
        return summary


def _attach_record(sim: VehicleSim, out: Path) -> _VehicleRecord:
    return _VehicleRecord(sim, out)


def _attach_view(sim: VehicleSim, out: Path | None, live: str | None):
    """run.mcap in `out` and/or the live Foxglove view, as an observer of the vehicle's engine (or None)."""
    from mars_link.flight.flight_view import open_view

    view = open_view(out, sim.model, sim.scenario, sim.scenario.sim.control_hz, None, math.inf, live,
                     sim.scenario.tracked_unit())
    if view is not None:
        view.event_lists = sim.event_lists()  # faults (scenario and MAVLink), the coordinator's
        if sim.scenario.has_pieces:  # the tracked point is the followed piece's, not the coordinator's record
            from mars_link.flight.flight_view import pieces_point

            view.point_of = pieces_point
        sim.engine.observers.append(view)
    return view


def spawn_vehicle(args: list[str], status_file: str | os.PathLike, timeout_s: float = 60.0) -> tuple[subprocess.Popen, dict]:
    """Start `mars-link vehicle ARGS --status-file F` and return the process and its first status once
    it is up (endpoints under "endpoints"). Stop it with `mars_link.processes.udp_runner.stop_unit`."""
    from mars_link.processes.udp_runner import read_status, stop_unit

    status_file = Path(status_file)
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", "vehicle", *args, "--status-file", str(status_file)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if status_file.exists():
            return proc, read_status(status_file)
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    if proc.poll() is None:
        stop_unit(proc)
        raise RuntimeError("vehicle did not start in time")
    err = proc.stderr.read()[-2000:]
    stop_unit(proc)
    raise RuntimeError(f"vehicle did not start: {err}")
