"""Start the world, one process per unit and (for a docked assembly) the coordinator; stop every child
cleanly.

Children are ended by PID (SIGTERM, then SIGKILL after a grace period) on normal exit, on Ctrl-C /
SIGTERM and, with `stop_on_child_death`, as soon as the world or the coordinator dies before the world
finished (`mars-link sitl up`: one line names it, exit 1); a unit process that dies is a failed unit
(`units_may_die`: the world declares it dead, the coordinator's FTC flies on without it).
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from mars_link.core.errors import UserInputError
from mars_link.mavlink.signing import load_key
from mars_link.processes.parent_watch import child_env
from mars_link.processes.links import LOOPBACK
from mars_link.processes.lockstep import SitlSetup, _start_pose, load_setup, position_every


#: a child's exit code when the machine refused it at start (a busy port: mars_link.processes.lockstep.main), and
#: `wait`'s then (core.validation.EXIT_ENVIRONMENT)
COULD_NOT_START = 3
MCAP_FINISH_S = 30.0  # the most `Run.stop` waits for an orphaned run.mcap writer to finish the file


def _await_mcap_writer(status_path: Path, timeout_s: float) -> None:
    """Wait for the world's run.mcap writer (its pid in the world's status file) to end, if it is still
    writing: it finishes the file on its own once its pipe from the world closes. Only waits; never
    signals a process this one did not start."""
    try:
        pid = json.loads(status_path.read_text()).get("mcap_writer_pid")
    except (OSError, ValueError, AttributeError):
        return
    if not isinstance(pid, int):
        return

    def writing() -> bool:
        try:
            return b"_writer_main" in Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            return False

    deadline = time.monotonic() + timeout_s
    if writing():
        print(f"waiting for run.mcap to be finished (writer pid {pid})", file=sys.stderr)
    while writing() and time.monotonic() < deadline:
        time.sleep(0.05)


def bound_udp_socket() -> socket.socket:
    """A socket bound to a free loopback port, to hand down to a child (no race for the port)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((LOOPBACK, 0))
    return s


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


@dataclass
class ClientPorts:
    """Where each unit's client links go: GCS to `gcs_port` (QGC/MAVProxy), API of unit index i to
    `api_ports[i]` (default 14540+i); `bind_any` binds the unit side to free ports instead of PX4's
    18570+i / 14580+i (tests running side by side)."""

    gcs_port: int = 14550
    api_ports: list[int] | None = None
    bind_any: bool = False
    closed: bool = False  # no client links at all (`run --mode sitl` unless --gcs): nothing outside reaches a unit

    def api_port(self, index: int) -> int:
        return self.api_ports[index] if self.api_ports else 14540 + index

    @classmethod
    def consecutive(cls, gcs_port: int, api_base: int, n_units: int, bind_any: bool = False) -> "ClientPorts":
        """API ports api_base, api_base + 1, ... for n units, stepping over the ports already taken: the GCS
        port (PX4's 14540 + i would give the 11th unit QGC's 14550) and, unless `bind_any`, the ports the
        units and the assembly vehicle bind (18570 + i, 14580 + i, 18560, 14560)."""
        from mars_link.processes.vehicle_host import VEHICLE_API_BIND, VEHICLE_GCS_BIND

        taken = {gcs_port}
        if not bind_any:
            taken |= {VEHICLE_GCS_BIND, VEHICLE_API_BIND} | {b + i for b in (18570, 14580) for i in range(n_units)}
        ports, p = [], api_base
        while len(ports) < n_units:
            if p not in taken:
                ports.append(p)
            p += 1
        return cls(gcs_port, ports, bind_any)


def check_udp_ports_free(ports: list[tuple[int, str, str]]) -> None:
    """Each (port, what binds it, the option that moves it) free on loopback, else one line naming the
    first busy port and its option (PortUnavailable: exit 3). Checked before any process starts, so a
    busy port never leaves a half-started run (a unit that cannot bind its port, the rest waiting for it)."""
    from mars_link.core.errors import PortUnavailable

    for port, what, option in ports:
        if port == 0:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind((LOOPBACK, port))
            except OSError as exc:
                raise PortUnavailable(f"UDP port {port} ({what}) on {LOOPBACK} is in use ({exc.strerror or exc}): "
                                      f"move it with {option}") from None


def unit_bind_ports(clients: "ClientPorts", n_units: int) -> list[tuple[int, str, str]]:
    """The UDP ports the units bind for their client links (PX4's 18570+i and 14580+i), unless `bind_any`
    or `closed`: (port, what, the option that moves it) for `check_udp_ports_free`."""
    if clients.bind_any or clients.closed:
        return []
    return [(base + i, f"unit index {i}'s {link} link", "--any-bind")
            for i in range(n_units) for base, link in ((18570, "GCS"), (14580, "API"))]


@dataclass
class SitlRun:
    out: Path
    setup: SitlSetup
    world_port: int
    coordinator_port: int
    clients: ClientPorts
    processes: dict[str, subprocess.Popen] = field(default_factory=dict)
    unit_process: dict[int, str] = field(default_factory=dict)  # unit id -> the name of the process hosting it

    def stop(self, grace_s: float = 3.0, mcap_finish_s: float = MCAP_FINISH_S) -> None:
        """SIGTERM every child still running, wait, SIGKILL the ones that did not end (by PID). Then, if the
        world's run.mcap writer outlived the world (the world was killed before it finished the file), wait
        up to `mcap_finish_s` for it to finish: when this returns, run.mcap is whole."""
        for proc in self.processes.values():
            if proc.poll() is None:
                proc.terminate()
        deadline = time.monotonic() + grace_s
        for proc in self.processes.values():
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        _await_mcap_writer(self.out / "world_status.json", mcap_finish_s)

    def endpoints(self) -> list[str]:
        lines = [f"world: pid {self.processes['world'].pid}, HIL link udp {LOOPBACK}:{self.world_port} (lockstep)"]
        if "coordinator" in self.processes:
            lines.append(f"coordinator: pid {self.processes['coordinator'].pid}, udp {LOOPBACK}:{self.coordinator_port} "
                         "(unit telemetry in, per-rotor commands out)")
        for i, u in enumerate(self.setup.unit_ids):
            lines.append(f"unit {u}: pid {self.processes[self.unit_process[u]].pid}, system id {u}, "
                         f"GCS udp {LOOPBACK}:{self.clients.gcs_port}, API udp {LOOPBACK}:{self.clients.api_port(i)} "
                         f"(MAVSDK udpin://{LOOPBACK}:{self.clients.api_port(i)}), log {self.out / f'unit{u}.tlog'}")
        return lines


def start(scenario: str | None, out: Path, units: int | None = None, layout: str | None = None,
          seed: int | None = None, speed: float | None = None, clients: ClientPorts | None = None,
          signing_key_file: str | None = None, role_args: dict[str, list[str]] | None = None,
          unit_prefix=None, skip: tuple[str, ...] = (), forever: bool = False, view: tuple[str, ...] = (),
          units_per_process: int = 1) -> SitlRun:
    """Start every process of one run, `python -m mars_link.processes.lockstep ROLE ...` each (returns at once; `wait`
    follows it). The coordinator <-> unit links are signed with the key of `signing_key_file`, else of
    $MARS_LINK_SIGNING_KEY (inherited). For other wirings (mars_link.processes.sitl_mode): `role_args` adds
    arguments per role ("world", "coordinator", "unit"; e.g. `--transport zenoh ...`), `unit_prefix(u)` is
    an argv to run unit u under (e.g. `ip netns exec NS`), `skip` leaves roles out (a coordinator run
    elsewhere); `forever`: a docked run goes on until stopped (a flight flown from a ground station).
    `view`: the world's flight-view options (`--mcap`, `--foxglove HOST:PORT`; the coordinator then feeds it).
    `units_per_process` K: each process hosts K units (in order; the last one may have fewer), each its own
    MAVLink system with its own links; process "unit<u>" (K = 1) or "units<first>-<last>"."""
    setup = load_setup(scenario, units, layout)  # refuses bad input before any process starts
    if units_per_process < 1:
        raise UserInputError(f"--units-per-process must be >= 1, got {units_per_process}")
    load_key(signing_key_file)  # a bad key file too
    out.mkdir(parents=True, exist_ok=True)
    clients = clients or ClientPorts()
    world_sock = bound_udp_socket()
    coord_sock = bound_udp_socket() if setup.docked else None
    run = SitlRun(out, setup, world_sock.getsockname()[1], coord_sock.getsockname()[1] if coord_sock else 0, clients)
    common = [scenario or "-", "--world-port", str(run.world_port), "--coordinator-port", str(run.coordinator_port),
              "--out", str(out)]
    if units is not None:
        common += ["--units", str(units)]
    if layout is not None:
        common += ["--layout", layout]
    if setup.pieces and forever and "--vehicle" not in (role_args or {}).get("coordinator", ()):
        raise UserInputError("a flight of several bodies ends when its coordinator says so: it cannot run forever")
    if setup.docked and not setup.pieces:
        common += ["--steps", str(setup.steps)] + (["--forever"] if forever else [])
    if forever:
        setup.steps = None
    if signing_key_file is not None:
        common += ["--signing-key-file", str(Path(signing_key_file).resolve())]
    py = [sys.executable, "-m", "mars_link.processes.lockstep"]
    extra = role_args or {}

    def spawn(name: str, argv: list[str], sock: socket.socket | None = None, prefix: list[str] = ()) -> None:
        fds = () if sock is None else (sock.fileno(),)
        with open(out / f"{name}.log", "w") as log:
            run.processes[name] = subprocess.Popen([*prefix, *py, *argv], stdout=log, stderr=subprocess.STDOUT,
                                                   stdin=subprocess.DEVNULL, pass_fds=fds, env=child_env())

    try:
        if coord_sock is not None and "coordinator" not in skip:
            spawn("coordinator", ["coordinator", *common, "--coordinator-fd", str(coord_sock.fileno()),
                                  *extra.get("coordinator", []), *(["--view-feed"] if view else [])], coord_sock)
        world = ["world", *common, "--world-fd", str(world_sock.fileno()), "--position-every", str(position_every(setup))]
        world += [] if seed is None else ["--seed", str(seed)]
        if setup.docked and not setup.pieces:
            com, yaw = _start_pose(setup)
            world.append("--start-pose=" + ",".join(repr(float(x)) for x in (*com, yaw)))  # "=": may start with "-"
        spawn("world", world + ([] if speed is None else ["--speed", str(speed)]) + extra.get("world", []) + list(view), world_sock)
        ids = setup.unit_ids
        for first in range(0, len(ids), units_per_process):
            group = ids[first:first + units_per_process]
            ports = [str(clients.api_port(i)) for i in range(first, first + len(group))]
            argv = ["unit", *common, "--unit", ",".join(map(str, group)), "--gcs-port", str(clients.gcs_port),
                    "--api-port", ",".join(ports)]
            if clients.bind_any:
                argv += ["--gcs-bind", "0", "--api-bind", "0"]
            if clients.closed:
                argv.append("--no-clients")
            name = f"unit{group[0]}" if len(group) == 1 else f"units{group[0]}-{group[-1]}"
            run.unit_process.update({u: name for u in group})
            spawn(name, argv + extra.get("unit", []), prefix=list(unit_prefix(group[0])) if unit_prefix else [])
    except BaseException:
        run.stop()
        raise
    finally:  # the children hold their own copies
        world_sock.close()
        if coord_sock is not None:
            coord_sock.close()
    return run


def wait(run: SitlRun, timeout_s: float | None = None, stop_on_child_death: bool = True,
         units_may_die: bool = False) -> int:
    """Until the world ends (the scenario's end), a child dies (with `stop_on_child_death`) or the
    timeout; then stop all. 0 = the world finished, 1 = a child died first (one line on stderr names
    it), 3 = a child could not start (a busy port, exit 3 of its own: one line names it), 124 = timeout. `units_may_die`: a unit process that dies is a failed unit, not a failed run
    (the world declares it dead, the coordinator reallocates, the flight goes on); only the world or
    coordinator stop it."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    code = 0
    reported: set[str] = set()
    try:
        while True:
            world = run.processes["world"].poll()
            if world == 0:
                break
            dead = [n for n, p in run.processes.items() if p.poll() not in (None, 0)]  # killed or failed
            refused = [n for n in dead if run.processes[n].returncode == COULD_NOT_START]
            if refused:  # a child the machine refused (a port taken since the parent's check): the run cannot start
                p = run.processes[refused[0]]
                print(f"sitl: {refused[0]} (pid {p.pid}) could not start: {_last_line(run.out / f'{refused[0]}.log')}; "
                      "stopping every child", file=sys.stderr)
                code = COULD_NOT_START
                break
            if units_may_die:
                for name in sorted(n for n in dead if n.startswith("unit") and n not in reported):
                    reported.add(name)
                    print(f"sitl: {name} died ({exit_text(run.processes[name].returncode)}): a failed unit, "
                          "the flight goes on", file=sys.stderr)
                dead = [n for n in dead if not n.startswith("unit")]
            if world is not None or (dead and stop_on_child_death):
                print(death_line(run, dead or ["world"]), file=sys.stderr)
                code = 1
                break
            if deadline is not None and time.monotonic() > deadline:
                code = 124
                break
            time.sleep(0.05)
        if code == 0:  # let the others finish their last step (units of a flight of pieces run until stopped)
            for name, p in run.processes.items():
                if run.setup.pieces and name.startswith("unit"):
                    continue
                try:
                    p.wait(5.0)
                except subprocess.TimeoutExpired:
                    pass
    finally:
        run.stop()
    return code


def exit_text(returncode: int) -> str:
    """A child's end as people read it: "killed by SIGKILL" or "exit 3"."""
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exit {returncode}"


def death_line(run: SitlRun, dead: list[str]) -> str:
    """The one line `sitl up` prints when the world or the coordinator dies before the flight ends:
    who, how, the last line of its log if it failed on its own (a crash), and that the rest stop."""
    parts = []
    for name in dead:
        p = run.processes[name]
        last = _last_line(run.out / f"{name}.log") if p.returncode > 0 else ""
        parts.append(f"{name} (pid {p.pid}) died ({exit_text(p.returncode)})" + (f": {last}" if last else ""))
    return f"sitl: {'; '.join(parts)} before the flight ended: stopping every child (logs in {run.out})"


def _last_line(path: Path) -> str:
    try:
        lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1][:300] if lines else ""
