"""Socket I/O for one unit: a `Vehicle` on UDP links, flying a JSBSim body of its own in real time.

    python -m mars_link.processes.udp_runner --unit 1

Links (PX4's SITL conventions, specs/mavlink.md §1.1; all on 127.0.0.1 and configurable):
  gcs          the unit sends to --gcs-port (default 14550, where QGC/MAVProxy listen) from
               --gcs-bind (default 18570+i), i = unit - 1
  api          the unit sends to --api-port (default 14540+i, MAVSDK `udpin://`) from --api-bind
               (default 14580+i)
               on both client links, whoever last sent a valid frame to the bound port (within 10 s)
               also gets the traffic, as PX4 does (MAVProxy `--master=udpout:127.0.0.1:<bind>`)
  coordinator  the unit listens on --coord-bind (default 14600+i) and answers the address of the
               last frame that came from the configured coordinator and passed signing (if required)
A port 0 means "any free port"; the chosen ports are printed as one JSON line on stdout once ready.

Physics: this runner is for a lone unit (MAVSDK/MAVProxy/QGC tests and demos), flown by the one engine
(`mars_link.flight.engine.Engine`) on the world every mode uses (`build.make_world`: a 1x1 body, JSBSim at
--physics-hz, motor lag, perfect sensors): each control period the unit takes its sensors, flies itself
(its motor model applies limits and injected faults) and the world advances; the runner only moves the
MAVLink bytes and paces the steps to real time (scaled by --speed). `--status-file` gets a JSON
snapshot (truth, mode, counters, where each MISSION_ITEM_REACHED was sent) a few times per second for tests and operators; it is not a channel
any coordinator reads.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import selectors
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from mars_link.mavlink.signing import signing_from_args
from mars_link.processes.cli_options import add_unit_runner_options
from firmware_models.vehicle import LINK_COORDINATOR, Vehicle, VehicleConfig
from firmware_models.vehicle_logs import LogStore
from mars_link.processes.vehicle_io import (
    COORD_BIND_BASE,
    LOOPBACK,
    LinkSpec,
    VehicleSockets,
    client_links,
    vehicle_status,
    write_json_atomic,
)
from mars_link.core.assembly import AssemblyModel
from mars_link.core import validation as v
from mars_link.core.errors import UserInputError
from mars_link.runtime.pacing import Pacer, StallMeter

STATUS_PERIOD_S = 0.2
WORLD_UNIT = 1  # the world's name for its one unit (the vehicle keeps its own system id on the wire)


def _parser() -> argparse.ArgumentParser:
    p = v.OneLineParser(prog="python -m mars_link.processes.udp_runner", description=__doc__.split("\n")[0])
    add_unit_runner_options(p)
    return p


def _params(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise UserInputError(f"--param {item[:60]!r} is not NAME=NUMBER (a finite number)") from None
        if not sep or not math.isfinite(out[name.strip()]):
            raise UserInputError(f"--param {item[:60]!r} is not NAME=NUMBER (a finite number)")
    return out


class UnitRunner:
    """Owns the sockets and the pacing; the engine steps the world and the unit, the vehicle decides
    everything else."""

    def __init__(self, args: argparse.Namespace) -> None:
        i = args.unit - 1
        if not (args.physics_hz > 0 and args.control_hz > 0 and args.speed > 0):
            raise UserInputError("--physics-hz, --control-hz and --speed must be positive")
        ratio = args.physics_hz / args.control_hz
        if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
            raise UserInputError("--physics-hz must be a whole multiple of --control-hz")
        key, require_signing = signing_from_args(args)
        self.vehicle = Vehicle(VehicleConfig(
            unit_id=args.unit, vehicle=args.preset, coordinator_sysid=args.coordinator_sysid,
            coordinator_compid=args.coordinator_compid, signing_key=key, sign_client_links=require_signing,
            control_hz=args.control_hz, params=_params(args.param)), time.time())
        self.control_dt_s = 1.0 / args.control_hz
        self.speed = args.speed
        self.engine = _lone_unit_engine(self.vehicle, args, self._tick)
        self.world = self.engine.flight.world
        self.vehicle.set_state(self.world.unit_truth(WORLD_UNIT))
        pick = lambda v, d: d if v is None else v  # noqa: E731
        links = client_links(i, args.gcs_port, args.api_port, args.gcs_bind, args.api_bind)
        links[LINK_COORDINATOR] = LinkSpec(pick(args.coord_bind, COORD_BIND_BASE + i), None, learn_clients=False)
        self.io = VehicleSockets(self.vehicle, links, Path(args.tlog) if args.tlog else None)
        self.vehicle.log_service.store = LogStore([args.tlog])  # (LOG_* download of the run's own .tlog)
        self.status_path = Path(args.status_file) if args.status_file else None
        self.duration_s = args.duration
        self.running = True
        self.sim_s = 0.0
        self.pacer = Pacer(self.speed)
        self.stalls = StallMeter()  # (read at each tick: the vehicle's watchdogs run there)

    def ports(self) -> dict[str, int]:
        return self.io.ports()

    def write_status(self) -> None:
        if self.status_path is None:
            return
        write_json_atomic(self.status_path, vehicle_status(
            self.vehicle, self.world.unit_truth(WORLD_UNIT), self.sim_s, overruns=self.pacer.overruns, ports=self.ports(),
            motor_thrust_n=[float(x) for x in self.world.unit_rotor_thrust_n(WORLD_UNIT)],  # (what the rotors make)
            mission_reached=self.vehicle.mission_service.reached, mission_counts=self.vehicle.mission.counts,
            **self.io.counters()))

    def run(self) -> int:
        print(json.dumps({"ready": True, "unit": self.vehicle.sysid, "ports": self.ports()}), flush=True)
        start = time.monotonic()
        pacer = self.pacer
        pacer.start(self.sim_s)
        next_status = start
        while self.running:
            now = time.monotonic()
            if self.duration_s is not None and now - start >= self.duration_s:
                break
            wait_s = pacer.wait_s(self.sim_s)
            self.stalls.waiting(wait_s)
            self.io.poll(wait_s)
            now = time.monotonic()
            if pacer.is_due(self.sim_s):  # (fell behind on a busy machine: re-anchored, an overrun)
                self.engine.step()  # sensors -> the unit flies itself (its _tick below) -> motors -> physics
                self.sim_s = self.world.t_s
            if now >= next_status:
                next_status = now + STATUS_PERIOD_S
                self.write_status()
        self.write_status()
        return 0

    def _tick(self, t_s: float, telemetry) -> list:
        """The engine's command source for a lone unit: no coordinator; the unit's heartbeats, streams and
        replies go out (its control step runs when it drives its motors, right after)."""
        wall_s = time.time()
        stalled_s = self.stalls.take()
        if stalled_s:  # the host stalled this process, and most likely its clients too
            self.vehicle.discount_stall(stalled_s, wall_s)
        self.io.send(self.vehicle.tick(wall_s, t_s))
        return []

    def close(self) -> None:
        self.io.close()
        self.world.close()


def _lone_unit_engine(vehicle: Vehicle, args: argparse.Namespace, tick):
    """The engine over a world of one 1x1 body (perfect sensors: the unit flies on its own state) and this
    unit's firmware, with no coordinator."""
    from mars_link.flight.build import make_world
    from mars_link.flight.engine import Engine, Flight, InProcessUnits
    from mars_link.config.scenario import Scenario, SimSpec

    model = AssemblyModel.from_layout(["X"], vehicle.vehicle)
    sc = Scenario(name=f"unit{vehicle.sysid}", preset=vehicle.vehicle.name, layout=("X",),
                  sim=SimSpec(physics_hz=args.physics_hz, control_hz=args.control_hz, noise=False))
    world = make_world(sc, model, 1, np.array([args.north, args.east, 0.0]), math.radians(args.yaw_deg))
    units = InProcessUnits({WORLD_UNIT: vehicle}, world)  # (the vehicle keeps its own system id)
    flight = Flight(sc, model, 1, None, world, units, None, [], duration_s=math.inf)
    return Engine(flight, command_source=tick)


def free_udp_port() -> int:
    """A UDP port on loopback that was free a moment ago (for tests running side by side)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


def spawn_unit(args: list[str], timeout_s: float = 60.0, env: dict | None = None) -> tuple[subprocess.Popen, dict]:
    """Start a runner process with these CLI arguments; return it and its ready line (ports) once it
    is up. The caller stops it with `stop_unit` (by its PID)."""
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.processes.udp_runner", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            if sel.select(max(0.0, deadline - time.monotonic())):
                line = proc.stdout.readline()
                if not line:
                    break
                if line.startswith("{"):
                    return proc, json.loads(line)
        stop_unit(proc)
        raise RuntimeError(f"unit runner did not start: {proc.stderr.read()[-2000:]}")
    finally:
        sel.close()


def read_status(path: str | os.PathLike, timeout_s: float = 2.0) -> dict:
    """The runner's latest status snapshot (retries while the file is being replaced)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return json.loads(Path(path).read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)


def stop_unit(proc: subprocess.Popen, timeout_s: float = 10.0) -> int:
    """SIGTERM, wait, then SIGKILL: only this process (by PID)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout_s)
    for f in (proc.stdout, proc.stderr):
        if f:
            f.close()
    return proc.returncode


def main(argv: list[str] | None = None) -> int:
    from mars_link.core.validation import check_file_parent, report

    try:
        args = _parser().parse_args(argv)
        check_file_parent(args.status_file, "--status-file")
        check_file_parent(args.tlog, "--tlog")
        runner = UnitRunner(args)
    except (UserInputError, OSError, RuntimeError) as e:  # bad input: 2; port taken, disk: 1 (one line)
        line, code = report(e, "udp_runner")
        print(line, file=sys.stderr)
        return code

    def stop(*_):
        runner.running = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        return runner.run()
    finally:
        runner.close()


if __name__ == "__main__":
    sys.exit(main())
