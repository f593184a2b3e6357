"""The multi-process SITL on a chosen transport, `mars-link run --mode sitl`, and `mars-link coordinator`.

`start_sitl` starts the same processes as mars_link.processes.launcher (world, one per unit, coordinator), each given
`--transport zenoh|udp ...` (mars_link.processes.lockstep builds its links on that transport). Zenoh with no
endpoints given: peers on 127.0.0.1 (world and coordinator listen, units connect to both), or a router
session hosted by this process (closed when the run ends, also on Ctrl-C) that the children join.

`run_sitl_scenario` flies a scenario that way (lockstep: the same flight as inproc for the same seed;
the coordinator is not told the faults unless the scenario file sets [control] faults_known)
and writes the inproc outputs: summary.json (mode "sitl", plus a "sitl" block: transport, dead units,
drops, command age at the motor) with the figures of the flight recorder the world ran live on its truth,
telemetry.csv and units.csv (that recorder's, with the coordinator's reference and estimate of each step:
mars_link.processes.step_record), rotors.csv and the force integral from the units' .tlogs (the
coordinator's command in, what the unit drove its motors with out) and the plots.
"""

from __future__ import annotations

import contextlib
import json
import math
import signal
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mars_link.core.events import EventKind, event, unit_died
from mars_link.config.scenario_sensor_faults import sensor_fault_events
from mars_link.core.errors import Terminated, UserInputError
from mars_link.mavlink.codec import decode_frames, frame_message_id
from mars_link.mavlink.tlog import tlog_frames
from mars_link.mavlink.wire import new_mav
from mars_link.transport import LinkSpec


@dataclass
class SitlSession:
    run: object  # mars_link.processes.launcher.SitlRun
    link: LinkSpec
    router: object | None = None  # zenoh.Session in router mode, or None
    router_endpoint: str | None = None
    wake_latency: object | None = None  # transport.realtime.CpuWakeLatency while a real-time run lasts
    certificates: object | None = None  # transport.tls.RunCertificates: the run's CA and/or key (removed at close)
    signing_key_file: str | None = None  # the key the run's own links are signed with (the user's or the run's)

    def wait(self, timeout_s: float | None = None, units_may_die: bool = False) -> int:
        from mars_link.processes.launcher import wait

        try:
            return wait(self.run, timeout_s, units_may_die=units_may_die)
        finally:
            self.close()

    def stop(self) -> None:
        try:
            self.run.stop()
        finally:
            self.close()

    def close(self) -> None:
        if self.wake_latency is not None:
            self.wake_latency.close()
        if self.router is not None:
            self.router.close()
            self.router = None
        if self.certificates is not None:
            self.certificates.close()
            self.certificates = None


def start_sitl(scenario: str | None, out: Path, link: LinkSpec | None = None, seed: int | None = None,
               units: int | None = None, layout: str | None = None, realtime: bool = False,
               clients=None, speed: float | None = None, unit_prefix=None, roles: tuple[str, ...] = ("coordinator", "world", "units"),
               topology: str = "peer", signing_key_file: str | None = None, vehicle=None,
               require_signing: bool = False, view: tuple[str, ...] = (), units_per_process: int = 1,
               save_certs: bool = False, external_offboard: bool = False) -> SitlSession:
    """Start the SITL processes (mars_link.processes.launcher.start) with their links on `link` (default Zenoh).
    `unit_prefix(u)` -> argv to run unit u under (e.g. `ip netns exec NS`); `roles` may leave out the
    coordinator (one started elsewhere attaches).

    Zenoh without connect endpoints: `topology` "peer" (default, one hop): the world and the coordinator
    listen on 127.0.0.1, the coordinator connects to the world, units connect to both; "router": this
    process hosts a router session every child joins as a client (two hops; what an external
    coordinator attaches to). Zenoh is a closed bus unless `link.insecure`: mutual TLS with a per-run CA
    and access control (mars_link.transport.tls; `save_certs`: a copy in `out`/certs), or the user's
    certificates (`link.tls_ca`...), or the fleet's in `link.tls_dir`. The run's own links are MAVLink-signed
    with `signing_key_file` (or $MARS_LINK_SIGNING_KEY), else a per-run key in the run's private directory
    (`SitlSession.signing_key_file`: what a coordinator started elsewhere is given). `vehicle` (mars_link.processes.vehicle_host.VehiclePorts): the coordinator serves the
    assembly as one MAVLink vehicle (its client links on UDP) and the run goes on, paced to real time
    unless `speed` says otherwise, until stopped. `external_offboard`: no coordinator, the world and units
    run as for an off-board computer outside the run (`run --mode sitl --external-offboard`)."""
    from mars_link.mavlink.signing import load_key
    from mars_link.processes.launcher import ClientPorts, start
    from mars_link.processes.lockstep import load_setup

    link = link or LinkSpec("zenoh")
    setup = load_setup(scenario, units, layout)  # bad input: refused before any session opens
    interface = link.unit_interface or setup.scenario.unit_interface
    link.check_unit_interface(interface)
    if interface == "px4-zenoh" and setup.pieces:
        raise UserInputError("--unit-interface px4-zenoh carries no docking-latch commands: a flight of pieces "
                             "needs the mavlink interface")
    session = SitlSession(None, link)
    try:  # (the run's certificates and router session are closed on any failure to start)
        closed = link.kind == "zenoh" and not link.insecure and not link.tls_ca and not link.tls_dir
        own_key = signing_key_file is None and load_key() is None  # (no user key: a per-run one)
        if own_key and require_signing:
            raise UserInputError("--require-signing needs a key the clients share: --signing-key-file or "
                                 "$MARS_LINK_SIGNING_KEY (the run's own key signs only its internal links)")
        if closed or own_key:
            from mars_link.transport.tls import RunCertificates

            ids = list(setup.unit_ids)
            groups = [ids[i:i + max(1, units_per_process)] for i in range(0, len(ids), max(1, units_per_process))]
            router = not link.connect and (topology == "router" or bool(link.listen))
            session.certificates = RunCertificates.create(link.fleet, groups, tls=closed, signing_key=own_key,
                                                          router=router)
            if closed:
                link = session.link = replace(link, tls_dir=str(session.certificates.directory))
            if own_key:
                signing_key_file = str(session.certificates.signing_key_file)
            if save_certs:
                session.certificates.save(out)
        session.signing_key_file = signing_key_file
        role_links = {role: link for role in ("world", "coordinator", "unit")}
        if link.kind == "zenoh" and not link.connect:
            from mars_link.transport.tls import files_for
            from mars_link.transport.zenoh_link import free_tcp_port, open_router

            if topology == "router" or link.listen:
                session.router, session.router_endpoint = open_router(
                    listen=link.listen, fleet=link.fleet,
                    tls=files_for(link.tls_dir, link.tls_ca, link.tls_cert, link.tls_key, "router"))
                link = replace(link, zenoh_mode="client", connect=(session.router_endpoint,), listen=())
                role_links = {role: link for role in role_links}
            elif topology == "peer":
                w, c = (f"tcp/127.0.0.1:{free_tcp_port()}" for _ in range(2))
                role_links = {"world": replace(link, zenoh_mode="peer", listen=(w,)),
                              "coordinator": replace(link, zenoh_mode="peer", listen=(c,), connect=(w,)),
                              "unit": replace(link, zenoh_mode="peer", connect=(w, c))}
            else:
                raise UserInputError(f"zenoh topology {topology!r}: expected peer or router")
        role_args = {role: spec.to_args() for role, spec in role_links.items()}
        if realtime or link.kind != "udp":  # the units log the command age at the motor
            role_args["unit"].append("--command-age")
        if realtime:  # the coordinator logs its timing
            role_args["coordinator"].append("--timing-log")
            for role in ("world", "coordinator", "unit"):  # (mars_link.runtime.scheduling.take_realtime_class)
                role_args[role].append("--sched-realtime")
            from mars_link.transport.realtime import CpuWakeLatency

            session.wake_latency = CpuWakeLatency()
        if vehicle is not None:
            role_args["coordinator"] += vehicle.argv()
            speed = 1.0 if speed is None else speed
        if external_offboard:  # (lockstep: no coordinator to wait for; each unit answers its step at once)
            role_args["world"].append("--external-offboard")
            role_args["unit"].append("--external-offboard")
        if own_key:  # the per-run key signs the internal links only; the client links keep the keyless rules
            role_args["unit"].append("--run-key")
            role_args["coordinator"].append("--run-key")
        if require_signing:  # the client links of the units and of the vehicle (firmware_models.control_policy)
            role_args["unit"].append("--require-signing")
            role_args["coordinator"].append("--require-signing")
        session.run = start(scenario, out, units, layout, seed, 1.0 if realtime else speed,
                            clients or ClientPorts(bind_any=True), signing_key_file, role_args=role_args,
                            unit_prefix=unit_prefix, skip=() if "coordinator" in roles else ("coordinator",),
                            forever=vehicle is not None, view=view, units_per_process=units_per_process)
    except BaseException:
        session.close()
        raise
    return session


# ----------------------------------------------------------------------------- run --mode sitl
def write_scenario_copy(scenario, path: Path) -> Path:
    """The (possibly overridden) scenario as a TOML file the child processes can load."""
    from mars_link.models.battery import BATTERY_BY_DEFAULT, battery_doc

    doc = {
        "name": scenario.name,
        "vehicle": {"preset": scenario.preset, **scenario.vehicle_options},
        "assembly": {"layout": list(scenario.layout), "tracked": scenario.tracked, "start": scenario.start,
                     "free_spacing_m": scenario.free_spacing_m},
        "trajectory": dict(scenario.trajectory),
        "control": {"controller": scenario.controller, "ftc": scenario.ftc, "faults_known": scenario.faults_known},
        "sim": {k: v for k, v in vars(scenario.sim).items() if v is not None},
        "faults": [{k: v for k, v in (("t", f.t_s), ("unit", f.unit), ("rotor", f.rotor), ("eta", f.eta),
                                      ("kind", None if f.kind == "eta" else f.kind)) if v is not None}
                   for f in scenario.faults],
    }
    if not doc["faults"]:
        del doc["faults"]
    if scenario.unit_interface != "mavlink":
        doc["units"] = {"interface": scenario.unit_interface}
    if scenario.reconfig:
        doc["reconfig"] = dict(scenario.reconfig)
    if scenario.docking:
        doc["docking"] = dict(scenario.docking)
    if scenario.separations:
        doc["separations"] = [{"t": s.t_s, "units": list(s.units), **({} if s.redock_t_s is None else
                                                                        {"redock_t": s.redock_t_s})}
                              for s in scenario.separations]
    if scenario.sensor_faults:  # (the units apply them: a copy without them flew SITL on healthy sensors)
        doc["sensor_faults"] = [{k: v for k, v in (("t", f.t_s), ("sensor", f.sensor), ("type", f.kind),
                                                   ("unit", f.unit), ("duration_s", f.duration_s)) if v is not None}
                                for f in scenario.sensor_faults]
    if scenario.mission:
        doc["mission"] = dict(scenario.mission)
    if scenario.sensors != type(scenario.sensors)():
        doc["sensors"] = {"profile": scenario.sensors.name, **scenario.sensors.written()}
    if not scenario.esc_telemetry:
        doc.setdefault("sensors", {})["esc_telemetry"] = False
    if scenario.battery is not None or scenario.preset in BATTERY_BY_DEFAULT:
        doc["battery"] = battery_doc(scenario.battery)
    if scenario.environment.moves_air:
        from mars_link.models.environment import environment_doc

        doc["environment"] = environment_doc(scenario.environment)
    path.write_text(_toml(doc), encoding="utf-8")
    return path




def _toml(doc: dict) -> str:
    def value(v) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):  # inline table (e.g. [environment] gusts)
            return "{" + ", ".join(f"{kk} = {value(vv)}" for kk, vv in v.items()) + "}"
        raise TypeError(f"cannot write {v!r} to TOML")

    lines = []
    for k, v in doc.items():
        if not isinstance(v, (dict, list)) or (isinstance(v, list) and not (v and isinstance(v[0], dict))):
            lines.append(f"{k} = {value(v)}")
    for k, v in doc.items():
        if isinstance(v, dict):
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {value(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                lines.append(f"\n[[{k}]]")
                lines += [f"{kk} = {value(vv)}" for kk, vv in item.items()]
    return "\n".join(lines) + "\n"


def run_sitl_scenario(scenario, out: Path, seed: int | None = None, link: LinkSpec | None = None,
                      realtime: bool = False, timeout_s: float | None = None, plots: bool = True,
                      on_progress=None, view: tuple[str, ...] = ("--mcap",), units_per_process: int = 1,
                      plot_format: str = "png", clients=None, save_certs: bool = False,
                      external_offboard: tuple[int, ...] = ()) -> dict:
    """Fly `scenario` through the multi-process SITL; write and return the inproc-style summary
    (`plot_format`: plots/ as png at 300 dpi, pdf or svg). `clients` (launcher.ClientPorts): the units'
    ground-station ports; None: none at all (a batch run that no client on the machine can reach, arm or steer).
    `save_certs`: a copy of the run's secrets in `out`/certs. `external_offboard` (unit ids,
    `external_offboard_units`): no coordinator; those units wait for an off-board computer outside the
    run, the world paced to the wall clock for the run's duration, and the summary says who flew them."""
    from mars_link.processes.launcher import ClientPorts

    link = link or LinkSpec("zenoh")
    if link.unit_interface:  # (the command line over the scenario's [units] interface)
        scenario = replace(scenario, unit_interface=link.unit_interface)
    check_unit_interface(scenario, link)
    if external_offboard:
        external_offboard_units(",".join(map(str, external_offboard)), scenario)  # (what it cannot carry: refused)
    seed = scenario.sim.seed if seed is None else seed
    if not _sets_faults_known(scenario):  # SITL: the coordinator learns faults from what it observes
        scenario = replace(scenario, faults_known=False)
    out.mkdir(parents=True, exist_ok=True)
    from mars_link.flight.runner import write_starting_summary

    write_starting_summary(out, scenario, seed, 1)  # first: there is always one (no disk for it: exit 3)
    copy = write_scenario_copy(_absolute_paths(scenario), out / "scenario.toml")
    wall0 = time.perf_counter()
    external = bool(external_offboard)
    session = start_sitl(str(copy), out, link, seed, realtime=realtime, view=view, units_per_process=units_per_process,
                         clients=clients or ClientPorts(bind_any=True, closed=True),
                         save_certs=save_certs or (external and not link.insecure and not link.tls_ca),
                         roles=("world", "units") if external else ("coordinator", "world", "units"),
                         topology="router" if external else "peer", speed=1.0 if external else None,
                         external_offboard=external)
    if external:
        print(external_offboard_text(session, out, external_offboard), file=sys.stderr, flush=True)
    watcher = _ProgressWatcher(out / "world_status.json", scenario, on_progress)
    try:
        with _sigterm_as_interrupt():
            code = session.wait(timeout_s, units_may_die=True)  # a dead unit process is a failed unit
    except KeyboardInterrupt as exc:  # SIGTERM or Ctrl-C: every child was stopped by SIGTERM and wrote its summary;
        _summarize_interrupted(scenario, out, seed, time.perf_counter() - wall0, session, exc,  # the part flown
                               external_offboard)
        raise
    finally:
        watcher.stop()
    wall = time.perf_counter() - wall0
    logs = ", ".join(sorted(p.name for p in out.glob("*.log")))
    if code == 3 or not (out / "world_truth.csv").exists():  # nothing flown: the run could not start
        from mars_link.core.errors import EnvironmentFailure

        raise EnvironmentFailure(f"SITL run could not start (exit {code}); process logs in {out}: {logs}")
    failure = None if code == 0 else f"a process of the run died (exit {code}; logs in {out}: {logs})"
    held = session.wake_latency.state if session.wake_latency is not None else None
    return summarize_sitl_run(scenario, out, seed, wall, session.link, plots, realtime, held, plot_format,
                              failure=failure, tracked=not external, external_offboard=external_offboard)


def external_offboard_units(text: str, scenario) -> tuple[int, ...]:
    """`--external-offboard all|IDS` -> the unit ids left to an off-board computer outside the run; what it
    cannot be, one UserInputError line. A docked assembly is one rigid body: one off-board computer flies
    all of it or none (a coordinator flying some of its units while another computer drives the others
    would each see the other's thrust as a disturbance), so IDS must name every unit; a flight of pieces
    needs the coordinator (it ends the flight, and PX4's interface carries no latch commands)."""
    if scenario.has_pieces:
        raise UserInputError("--external-offboard: a flight of pieces is run by its coordinator (docking, latches): "
                             "give a docked assembly")
    if scenario.unit_interface != "px4-zenoh":
        raise UserInputError("--external-offboard needs --unit-interface px4-zenoh (the MAVLink persona takes per-rotor "
                             "commands from the run's own coordinator link only)")
    ids = tuple(scenario.model().unit_ids)
    if text.strip() == "all":
        return ids
    try:
        given = tuple(sorted({int(x) for x in text.split(",")}))
    except ValueError:
        raise UserInputError(f"--external-offboard {text!r}: expected all or unit ids separated by commas") from None
    unknown = [u for u in given if u not in ids]
    if unknown:
        raise UserInputError(f"--external-offboard: unit {unknown[0]} is not in this assembly (units {list(ids)})")
    if given != ids:
        raise UserInputError(f"--external-offboard {text}: a docked assembly is one rigid body, flown by one off-board "
                             f"computer: name all its units ({','.join(map(str, ids))}) or use all")
    return ids


def external_offboard_text(session: SitlSession, out: Path, units: tuple[int, ...]) -> str:
    """Where an off-board computer outside the run connects, and what it finds there (one paragraph)."""
    link = session.link
    where = ", ".join(link.listen) or session.router_endpoint
    names = ", ".join(f"/px4_{u}/fmu" for u in units)
    if link.insecure:
        access = "open bus (--insecure)"
    elif link.tls_ca:
        access = "your TLS certificates: the off-board computer's needs the coordinator's rights"
    else:
        access = f"closed bus: connect with TLS as the coordinator ({out / 'certs'}: ca.crt, coordinator.crt, coordinator.key)"
    return (f"external off-board: the coordinator flies none of units {','.join(map(str, units))}; an off-board computer "
            f"drives them over PX4's interface (rmw_zenoh domain 0: {names}/in/..., /fmu/out/...) on zenoh {where}; "
            f"{access}; the world runs in real time until the run's end")


def check_unit_interface(scenario, link: LinkSpec) -> None:
    """PX4's interface needs Zenoh and a flight it can carry (UserInputError, one line)."""
    link.check_unit_interface(scenario.unit_interface)
    if scenario.unit_interface == "px4-zenoh":
        from mars_link.flight.build import check_px4_interface

        check_px4_interface(scenario, scenario.model())


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM raises KeyboardInterrupt while the flight runs (main thread only), so the children are
    stopped by PID and the part flown is summarised, as on Ctrl-C."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(*_):
        raise Terminated

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _summarize_interrupted(scenario, out: Path, seed: int, wall_s: float, session: SitlSession,
                           exc: KeyboardInterrupt, external_offboard: tuple[int, ...] = ()) -> None:
    """summary.json of an interrupted flight (completed: false; the world says it was stopped) from the
    logs the children closed; the starting summary stays if the world logged nothing yet."""
    if not (out / "world_summary.json").exists() or not (out / "world_truth.csv").exists():
        return
    failure = f"interrupted by {'SIGTERM' if isinstance(exc, Terminated) else 'SIGINT'}"
    summarize_sitl_run(scenario, out, seed, wall_s, session.link, plots=False, failure=failure,
                       tracked=not external_offboard, external_offboard=external_offboard)


def _sets_faults_known(scenario) -> bool:
    """Whether the scenario file says [control] faults_known itself (else --mode sitl uses false)."""
    import tomllib

    from mars_link.config.scenario import resolve_scenario_path

    try:  # source: a path, or a bundled scenario's file name
        with open(resolve_scenario_path(scenario.source), "rb") as f:
            return "faults_known" in tomllib.load(f).get("control", {})
    except (OSError, ValueError, UserInputError):
        return True  # built in or not a file: keep what the scenario object says


def _absolute_paths(scenario):
    traj = dict(scenario.trajectory)
    if "path" in traj and not Path(traj["path"]).is_absolute() and scenario.source not in ("", "<built-in>"):
        traj["path"] = str((Path(scenario.source).parent / traj["path"]).resolve())
    if isinstance(traj.get("plan"), str):  # kind "mission": as make_trajectory finds it
        from mars_link.planning.mission_trajectory import resolve_plan_path

        traj["plan"] = str(resolve_plan_path(traj["plan"], scenario.source).resolve())
    return replace(scenario, trajectory=traj)


class _ProgressWatcher:
    """Reports the world's sim time (world_status.json) to `on_progress(fraction)` from a thread."""

    def __init__(self, path: Path, scenario, on_progress) -> None:
        import threading

        self._stop = threading.Event()
        self._thread = None
        if on_progress is None:
            return
        from mars_link.flight.build import make_trajectory

        duration = scenario.sim.duration_s or make_trajectory(scenario, scenario.model()).duration_s

        def loop() -> None:
            while not self._stop.wait(0.25):
                try:
                    t = json.loads(path.read_text())["sim_time_s"]
                except (OSError, ValueError, KeyError):
                    continue
                on_progress(min(1.0, t / duration))

        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)


def _scheduling_classes(out: Path, world: dict, coordinator: dict) -> dict:
    """The CPU scheduling class each process's stepping loop ran in: the world's, the coordinator's, and
    each class the unit processes ran in (their status files; a host of several units writes its own)."""
    units = set()
    for path in [*out.glob("unit_host*_status.json"), *out.glob("unit[0-9]*_status.json")]:
        label = _read_json(path).get("scheduling")
        if label:
            units.add(label)
    return {"world": world.get("scheduling"), "coordinator": coordinator.get("scheduling"), "units": sorted(units)}


def _end_reason(scenario, trajectory, world: dict, divergence: dict | None, coordinator_failed: str | None,
                failure: str | None, judge_duration: bool) -> str | None:
    """Why a SITL flight ended before its end (None: flown to the end). Whatever stopped it (a signal, a
    shutdown command, a dead process), a flight that did not reach its duration is not completed;
    `divergence`: the recorder's event, None if the flight did not diverge; `judge_duration` False: the
    flight has no fixed duration to judge by (its coordinator ends a flight of pieces; clients fly
    `sitl up --vehicle` until stopped)."""
    from mars_link.flight.metrics import ended_early_reason

    sim_t = float(world.get("sim_time_s", 0.0))
    if divergence is not None:
        at = divergence.get("t_s")
        return "diverged" if at is None else f"diverged at {at:.2f} s"
    if coordinator_failed:
        return "the coordinator's mission failed"
    if not judge_duration:
        if not scenario.has_pieces:
            return failure
        why = failure or ("stopped" if world.get("stopped") else None)
        return None if why is None else f"{why} at {sim_t:.2f} s"
    duration = scenario.sim.duration_s or trajectory.duration_s
    why = failure or ("stopped" if world.get("stopped") else "the world ended")
    early = ended_early_reason(sim_t, duration, scenario.sim.control_hz, why)
    return early or (f"{failure} at the end" if failure else None)


def _figure(recorded: dict, name: str, unknown: float = math.nan) -> float:
    """One of the world recorder's figures (JSON null: NaN, or `unknown`)."""
    value = recorded.get(name)
    return unknown if value is None else float(value)


def summarize_sitl_run(scenario, out: Path, seed: int, wall_s: float, link: LinkSpec, plots: bool = True,
                       realtime: bool = False, cpu_wake_latency: str | None = None, plot_format: str = "png",
                       failure: str | None = None, tracked: bool = True,
                       external_offboard: tuple[int, ...] = ()) -> dict:
    """summary.json of a SITL run, one body or several, with the in-process keys: the processes' figures become
    a `TrialResult` and go through the in-process `summarize` (mars_link.flight.metrics). The tracked point's
    error, the tilt, the clearance, the mission's force and the lost units' fates are the world's: its process
    ran the in-process flight recorder live on its truth, with the coordinator's record of each step
    (world_summary.json "recorder"; mars_link.processes.step_record). rotors.csv and the force integral come
    from the units' .tlogs (the coordinator's command in, what each unit drove its motors with out).
    `tracked` False (`sitl up --vehicle`: the clients' commands are the reference): no tracking error (null
    figures), and stopping it is its end. `external_offboard`: the units an off-board computer outside the
    run drove (not tracked either); the flight still ends at the run's duration."""
    from mars_link.flight.build import make_trajectory
    from mars_link.flight.metrics import TrialResult, summarize
    from mars_link.flight.run_log import PLOT_ROWS_MAX, ROTOR_LOG_HZ, RunLog

    model = scenario.model()
    trajectory = make_trajectory(scenario, model)
    world = _read_json(out / "world_summary.json")
    coordinator = _read_json(out / "coordinator_summary.json")
    recorded = world.get("recorder") or {}
    log = RunLog(out, model, rotor_log_hz=min(scenario.sim.control_hz, ROTOR_LOG_HZ), plot_rows_max=PLOT_ROWS_MAX,
                 series=("rotors",))
    try:
        force_integral = _write_rotor_log(log, scenario, model, out)
    finally:
        log.close()
    sim_t = float(world.get("sim_time_s", 0.0))
    last_t = _figure(recorded, "last_step_t_s", -1.0)
    events = [event(f.t_s, EventKind.FAULT, unit=f.unit, rotor=f.rotor, eta=f.eta, text=f.event_text())
              for f in scenario.faults if f.t_s <= last_t + 1e-9]  # (the world applies them as they come due)
    events += [unit_died(d["t_s"], d["unit"]) for d in world.get("deaths", [])]
    events += [e for e in world.get("latch_events", []) if e["type"] == "dock_latched"]
    events += foreign_traffic_events(out, model.unit_ids)
    events += sensor_fault_events(scenario.sensor_faults, scenario.sim.control_hz, last_t)
    events += coordinator.get("events", [])
    events += recorded.get("events", [])  # (the recorder's: a divergence, a failed manoeuvre)
    events.sort(key=lambda e: e.get("t_s", 0.0))
    kinds = [e["type"] for e in events]
    divergence = recorded.get("divergence") if recorded.get("diverged") else None
    end_reason = _end_reason(scenario, trajectory, world, divergence, coordinator.get("failed"), failure,
                             judge_duration=(tracked or bool(external_offboard)) and not scenario.has_pieces)
    begun = next((e["t_s"] for e in events if e["type"] == "reconfig_start"), None)
    reconfigured = "reconfig_done" in kinds
    reasons = {e["unit"]: e.get("reason") for e in coordinator.get("events", []) if e["type"] == "unit_lost"}
    result = TrialResult(
        seed=seed, completed=end_reason is None, end_reason=end_reason, diverged=divergence is not None,
        mean_error_m=_figure(recorded, "mean_error_m"), rmse_m=_figure(recorded, "rmse_m"),
        max_error_m=_figure(recorded, "max_error_m"), sim_time_s=sim_t, wall_time_s=wall_s,
        force_integral_n2s=float(world.get("force_integral_n2s", force_integral)),
        max_tilt_deg=_figure(recorded, "max_tilt_deg"),
        events=events, control_steps=int(recorded.get("control_steps", 0)),
        detections=_detections(scenario, coordinator, world), reconfigured=reconfigured,
        reconfig_time_s=float(coordinator.get("shift_s", 0.0)) if reconfigured else (sim_t - begun if begun is not None else 0.0),
        plan=coordinator.get("plan"), assembled="assembly_done" in kinds,
        min_clearance_m=_figure(recorded, "min_clearance_m", math.inf),  # (JSON null: one body, never a gap)
        pieces_final=coordinator.get("pieces_final", []),
        mission_force_integral_n2s=_figure(recorded, "mission_force_integral_n2s"),
        units_lost=[{**lost, "reason": reasons.get(lost["unit"], lost.get("reason"))}
                    for lost in recorded.get("units_lost", [])])
    summary = summarize(scenario, [result], seed, mode="sitl-pieces" if scenario.has_pieces else "sitl")
    if not tracked:
        summary.update(mode="sitl-external-offboard" if external_offboard else "sitl-vehicle", mean_error_m=None,
                       mean_error_std_m=None, rmse_m=None, max_error_m=None)
    summary["bodies_final"] = world.get("bodies", [])
    summary["sitl"] = {
        "transport": link.kind,
        "bus": link.bus(),
        "link_profile": link.profile,
        "world_real_time_factor": world.get("real_time_factor"),
        "world_cores_idle_fraction": world.get("cores_idle_fraction"),
        "dead_units": world.get("dead_units", []),
        "world_dropped": world.get("dropped", {}),
        "coordinator_dropped": coordinator.get("dropped", {}),
        "lost_units": coordinator.get("lost_units", []),
        "realtime": realtime,
        "rotor_bounds_n": [model.vehicle.rotor_min_thrust_n, model.vehicle.rotor_max_thrust_n],
        "faults_known": scenario.faults_known,
        # sim time is wall time only when paced: as fast as possible, an age would mean nothing
        "command_age": command_age_summary(out) if realtime else {"n": 0, "note": "measured with --realtime only"},
        "cpu_wake_latency": cpu_wake_latency,  # real time: idle CPUs kept awake (transport.realtime.CpuWakeLatency)
        "scheduling": _scheduling_classes(out, world, coordinator),  # (mars_link.runtime.scheduling)
    }
    if external_offboard:  # who flew: not the coordinator (none ran), so no tracking figures
        summary["sitl"]["external_offboard"] = {
            "units": list(external_offboard), "coordinator": None, "paced": "real time",
            "note": "these units were driven by an off-board computer outside the run, not by the mars-link "
                    "coordinator: rotors.csv and world_truth.csv are the world's truth of what they drove; no tracking error"}
    from mars_link.flight.runner import write_plots_safely, write_summary

    if plots:
        _read_recorded_rows(log, out)
    if plots and log.telemetry_rows:
        from mars_link.flight.plots import write_flight_plots

        write_plots_safely(log, lambda: write_flight_plots(out, log, scenario, summary.get("events", ()), plot_format))
    summary["logging"] = _logging_status(log.status(), world, out, scenario)
    write_summary(out, summary)
    return summary


def _read_recorded_rows(log, out: Path) -> None:
    """The world recorder's telemetry.csv and units.csv rows into `log` (its memory only), for the plots."""
    from mars_link.flight.run_log import TELEMETRY_COLUMNS, UNIT_COLUMNS

    for name, width, take in (("telemetry", len(TELEMETRY_COLUMNS), log.telemetry),
                              ("units", len(UNIT_COLUMNS), None)):
        path = out / f"{name}.csv"
        if not path.exists():
            continue
        sample: list[list[float]] = []
        with open(path, encoding="utf-8") as f:
            next(f, None)
            for line in f:
                try:
                    row = [float(x) for x in line.split(",")]
                except ValueError:  # (a torn last line)
                    continue
                if len(row) != width:
                    continue
                if take is not None:
                    take(row)
                    continue
                if sample and row[0] != sample[0][0]:  # units.csv: every unit's row of one time, then the next
                    log.units(0, sample)
                    sample = []
                sample.append(row)
        if sample:
            log.units(0, sample)


def foreign_traffic_events(out: Path, unit_ids) -> list[dict]:
    """summary.json events: command or mission traffic that reached a unit from anyone but the coordinator
    (the units' status files, firmware_models.vehicle.FOREIGN_CONTROL_MESSAGES)."""
    events = []
    for unit in unit_ids:
        for f in _read_json(out / f"unit{unit}_status.json").get("foreign_traffic") or []:
            events.append({"type": EventKind.FOREIGN_TRAFFIC.value, "unit": unit, **f,  # (a count over the run: no t_s)
                           "text": f"Unit {unit}: {f['message']} x{f['count']} from system {f['sysid']} on {f['link']}"})
    return events


def _logging_status(own: dict, world: dict, out: Path, scenario) -> dict:
    """summary.json "logging" for a SITL run: this process's logs and every child's (the world's truth
    log and its recorder's telemetry.csv and units.csv, each unit's .tlog). A log stopped by a write error
    (or its size cap) is listed with its reason; the flight and its figures (measured live, not from the
    logs) went on."""
    recorded = world.get("run_log") or {}  # the world recorder's telemetry.csv and units.csv
    own = {**own, "files": own.get("files", []) + recorded.get("files", [])}
    stopped = [r for r in (own.get("stopped_reason"), recorded.get("stopped_reason")) if r]
    truth = world.get("logging") or {}
    if truth.get("stopped_reason"):
        stopped.append(truth["stopped_reason"])
    if world.get("mcap_stopped_reason"):  # the world's run.mcap writer
        stopped.append(world["mcap_stopped_reason"])
    for path in sorted(out.glob("command_age_unit*.json")):
        if _read_json(path).get("logging_stopped"):
            stopped.append(_read_json(path)["logging_stopped"])
    for unit in scenario.model().unit_ids:
        reason = _read_json(out / f"unit{unit}_status.json").get("logging_stopped")
        if reason:
            stopped.append(reason)
    return {**own, "complete": not stopped, "stopped_reason": stopped[0] if stopped else None, "stopped": stopped}


def _write_rotor_log(log, scenario, model, out: Path) -> float:
    """rotors.csv from the units' .tlogs: the coordinator's command (SET_ACTUATOR_CONTROL_TARGET in) and
    what each unit drove its motors with (HIL_ACTUATOR_CONTROLS out, faults included); returns the force
    integral Σ rotors ∫ thrust² dt over the control steps."""
    from mars_link.config.scenario import eta_after

    scale = model.vehicle.full_scale_thrust_n
    cmd: dict[int, dict[int, np.ndarray]] = {}
    drv: dict[int, dict[int, np.ndarray]] = {}
    for u in model.unit_ids:
        path = out / f"unit{u}.tlog"
        if not path.exists():
            continue
        parser = new_mav(255, 0)
        cmd[u], drv[u] = {}, {}
        for _, frame in tlog_frames(path):
            msgid = frame_message_id(frame)
            if msgid not in (139, 93):  # SET_ACTUATOR_CONTROL_TARGET, HIL_ACTUATOR_CONTROLS
                continue
            for m in decode_frames(frame, parser):  # (none: a frame the unit itself dropped as malformed)
                if msgid == 139 and m.get_srcSystem() != u:
                    cmd[u][m.time_usec] = np.array(m.controls[:4]) * scale
                elif msgid == 93 and m.get_srcSystem() == u:
                    drv[u][m.time_usec] = np.array(m.controls[:4]) * scale
        if not cmd[u]:  # PX4's interface ([units] interface = "px4-zenoh"): the ActuatorMotors it received
            cmd[u] = _px4_commands(out, u, scale)
    steps = sorted(set().union(*[set(d) for d in drv.values()])) if drv else []
    dt = 1.0 / scenario.sim.control_hz
    nan4 = np.full(4, np.nan)
    integral = 0.0
    for t_us in steps:
        c = np.concatenate([cmd.get(u, {}).get(t_us, nan4) for u in model.unit_ids])
        d = np.concatenate([drv.get(u, {}).get(t_us, np.zeros(4)) for u in model.unit_ids])
        integral += float(np.sum(d * d)) * dt
        log.rotors(0, t_us / 1e6, c, d, eta_after(model, scenario.faults, t_us / 1e6))
    return integral if steps else math.nan


def _px4_commands(out: Path, unit: int, scale: float) -> dict[int, np.ndarray]:
    """time_usec -> commanded thrusts (N) of every ActuatorMotors in the unit's PX4 input log (none: {})."""
    from mars_link.processes.lockstep import px4_input_log_name
    from mars_link.px4 import cdr

    path = out / px4_input_log_name(unit)
    commands: dict[int, np.ndarray] = {}
    if not path.exists():
        return commands
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            record = json.loads(line)
            if "/fmu/in/actuator_motors/" in record["key"]:
                m = cdr.decode("ActuatorMotors", bytes.fromhex(record["payload"]))
                commands[int(m.timestamp)] = np.asarray(m.control[:4], dtype=float) * scale
        except (ValueError, KeyError, TypeError):  # a torn last line, a sample the unit dropped as malformed
            continue
    return commands


def _detections(scenario, coordinator: dict, world: dict) -> list[dict]:
    """summary.json `detections` as in-process: t_fault from the scenario's faults or the world's
    declared deaths (a killed unit process), None for a false alarm."""
    from mars_link.flight.metrics import fault_time

    deaths = {d["unit"]: d["t_s"] for d in world.get("deaths", [])}
    return [{"t_fault": fault_time(scenario.faults, d["unit"], d["rotor"], deaths), **d}
            for d in coordinator.get("detections", [])]


def command_age_summary(out: Path) -> dict:
    """Command age at the motor over every unit (from the units' command_age_unit<i>.csv)."""
    from mars_link.transport.realtime import percentiles_ms

    ages, misses = [], 0
    for path in sorted(out.glob("command_age_unit*.json")):
        misses += _read_json(path).get("deadline_misses", 0)
    for path in sorted(out.glob("command_age_unit*.csv")):
        a = _read_csv(path)
        ages += list(np.atleast_1d(a["age_s"]))
    stats = percentiles_ms(ages)
    stats["deadline_misses"] = misses
    return stats


def stage_times(out: Path) -> dict:
    """Medians over steps (ms after the sample time) of a real-time run's stages: the last unit reading
    its sensors (`sensors_in`), the coordinator holding all telemetry (`telemetry_in`), commands
    `computed` and `sent`, the last unit reading its command (`commands_in`) and driving its motors with it
    (`at_motors`: the command age). Empty if not logged."""
    epochs = [_read_json(p).get("epoch_s") for p in out.glob("command_age_unit*.json")]
    epochs = [e for e in epochs if isinstance(e, float) and math.isfinite(e)]
    coordinator = out / "coordinator_timing.csv"
    if not epochs or not coordinator.exists():
        return {}
    epoch = min(epochs)  # each unit's estimate is the epoch plus its smallest delay: take the smallest
    per_step: dict[float, dict[str, float]] = {}
    for path in sorted(out.glob("command_age_unit*.csv")):
        offset = _read_json(path.with_suffix(".json")).get("epoch_s", epoch) - epoch
        for row in np.atleast_1d(_read_csv(path)):
            step = per_step.setdefault(round(float(row["t_s"]), 6), {})
            for stage, column in (("sensors_in", "sensors_in_s"), ("commands_in", "command_in_s"), ("at_motors", "age_s")):
                value = float(row[column]) + offset
                if math.isfinite(value):
                    step[stage] = max(step.get(stage, -math.inf), value)
    columns = {"telemetry_in": "telemetry_all_wall_s", "computed": "computed_wall_s", "sent": "sent_wall_s"}
    for row in np.atleast_1d(_read_csv(coordinator)):
        t = round(float(row["t_s"]), 6)
        step = per_step.setdefault(t, {})
        for stage, column in columns.items():
            step[stage] = float(row[column]) - epoch - t
    return {stage: float(np.median([s[stage] for s in per_step.values() if stage in s])) * 1e3
            for stage in ("sensors_in", "telemetry_in", "computed", "sent", "commands_in", "at_motors")
            if any(stage in s for s in per_step.values())}


def _read_csv(path: Path):
    """A child's CSV log as a structured array; a last row cut by a write error (a full disk) is left out."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (genfromtxt warns of each row it leaves out)
        return np.genfromtxt(path, delimiter=",", names=True, ndmin=1, invalid_raise=False)


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


# ----------------------------------------------------------------------------- command line
def _endpoint(text: str) -> str:
    import re

    if not re.match(r"^(tcp|udp|tls|quic)/[^/\s]+:\d{1,5}$", text):
        raise UserInputError(f"zenoh endpoint {text!r}: expected e.g. tcp/127.0.0.1:7447")
    return text


def _check_listen_free(endpoint: str) -> None:
    """A Zenoh TCP listen endpoint that something already holds: PortUnavailable naming it and its option."""
    import errno
    import socket

    from mars_link.core.errors import PortUnavailable

    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto != "tcp" or not port.isdigit() or int(port) == 0:
        return
    host = host.strip("[]")
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, int(port)))
    except OSError as exc:
        if exc.errno in (errno.EADDRINUSE, errno.EACCES):  # refused; others (an unknown host) are zenoh's to report
            raise PortUnavailable(f"--zenoh-listen {endpoint}: TCP port {port} is in use ({exc.strerror}): move it "
                                  f"with --zenoh-listen") from None


def link_from_args(args) -> LinkSpec:
    """The links of the SITL processes from the command line (mars_link.apps.cli `--transport` and its options)."""
    kind = getattr(args, "transport", None) or "zenoh"
    if kind not in ("udp", "zenoh"):
        raise UserInputError(f"--transport {kind!r}: expected zenoh or udp")
    profile = getattr(args, "link_profile", None)
    if profile:
        from mars_link.transport.profiles import profile_from_name

        try:
            profile_from_name(profile)
        except ValueError as e:
            raise UserInputError(f"--link-profile: {e}") from None
        if kind != "zenoh":
            raise UserInputError("--link-profile applies to the zenoh transport")
    connect = tuple(_endpoint(e) for e in getattr(args, "zenoh_connect", None) or [])
    listen = tuple(_endpoint(e) for e in getattr(args, "zenoh_listen", None) or [])
    for endpoint in listen:  # a busy one: one line naming it, exit 3, before any process
        _check_listen_free(endpoint)
    fleet = getattr(args, "fleet", "default")
    import re

    if not re.match(r"^[A-Za-z0-9_-]+$", fleet):
        raise UserInputError(f"--fleet {fleet!r}: letters, digits, _ and - only")
    from mars_link.transport.tls import check_user_files

    insecure = bool(getattr(args, "insecure", False))
    tls_ca, tls_cert, tls_key = (getattr(args, name, None) for name in ("tls_ca", "tls_cert", "tls_key"))
    problem = check_user_files(tls_ca, tls_cert, tls_key)
    if problem:
        raise UserInputError(problem)
    if tls_ca and (insecure or kind != "zenoh"):
        raise UserInputError("--tls-ca/--tls-cert/--tls-key need the closed Zenoh bus (--transport zenoh without --insecure)")
    if tls_ca:
        tls_ca, tls_cert, tls_key = (str(Path(f).resolve()) for f in (tls_ca, tls_cert, tls_key))
    link = LinkSpec(kind, fleet, "client", connect, listen, profile, insecure=insecure,
                    tls_ca=tls_ca, tls_cert=tls_cert, tls_key=tls_key,
                    unit_interface=getattr(args, "unit_interface", None))
    if link.unit_interface:
        link.check_unit_interface(link.unit_interface)
    return link


def sitl_runner(args):
    """`run_scenario`'s signature for `mars-link run --mode sitl` (options checked here, before any output)."""
    link = link_from_args(args)
    if getattr(args, "trials", 1) != 1:
        raise UserInputError("--mode sitl runs one trial (vary --seed instead)")

    from mars_link.flight.flight_view import world_view_args

    view = world_view_args(args)  # (a busy --foxglove port: refused now, before any process)
    clients = run_client_ports(args)

    def runner(scenario, out, trials=1, seed=None, on_progress=None, mcap=True, live=None, plot_format="png"):
        if trials != 1:
            raise UserInputError("--mode sitl runs one trial (vary --seed instead)")
        cb = None if on_progress is None else (lambda frac: on_progress(0, frac))
        external = getattr(args, "external_offboard", None)
        units = external_offboard_units(external, scenario) if external else ()
        try:
            return run_sitl_scenario(scenario, out, seed, link, realtime=args.realtime, on_progress=cb, view=view,
                                     units_per_process=args.units_per_process, plot_format=plot_format,
                                     clients=clients, save_certs=getattr(args, "save_certs", False),
                                     external_offboard=units)
        except RuntimeError as e:
            raise UserInputError(str(e)) from None

    return runner


def run_client_ports(args):
    """`run --mode sitl`'s ground-station ports (launcher.ClientPorts), or None: closed unless --gcs,
    --gcs-port or --api-port asks for them (then PX4's, moved as in `sitl up`)."""
    gcs_port, api_port = getattr(args, "gcs_port", None), getattr(args, "api_port", None)
    if not (getattr(args, "gcs", False) or gcs_port is not None or api_port is not None):
        return None
    from mars_link.processes.launcher import ClientPorts
    from mars_link.processes.vehicle_io import GCS_PORT

    n_units = 256  # (more than any layout has units)
    clients = ClientPorts.consecutive(GCS_PORT if gcs_port is None else gcs_port, 14540 if api_port is None else api_port,
                                      n_units, bind_any=True)
    for what, port in (("--gcs-port", clients.gcs_port), ("--api-port", clients.api_port(0))):
        if not 1 <= port <= 65535:
            raise UserInputError(f"{what} must be 1..65535, got {port}")
    return clients


def sitl_up_command(args, scenario_path: str | None, out: Path, link: LinkSpec, clients, vehicle=None,
                    view: tuple[str, ...] = (), require_signing: bool = False) -> int:
    """`mars-link sitl up` (its options checked by mars_link.apps.cli first): start the processes on `link`,
    print the endpoints, run until the flight ends, Ctrl-C or a child's death. With `vehicle`
    (mars_link.processes.vehicle_host.VehiclePorts) the coordinator serves the docked assembly as one MAVLink vehicle and
    the run goes on, paced to real time (unless --speed), until stopped."""
    import signal

    roles = ("world", "units") if args.external_coordinator else ("coordinator", "world", "units")
    previous = signal.getsignal(signal.SIGTERM)

    def interrupt(*_):
        raise Terminated

    signal.signal(signal.SIGTERM, interrupt)
    session = None
    wall0 = time.perf_counter()
    try:
        session = start_sitl(scenario_path, out, link, args.seed, units=args.units, layout=args.layout,
                             realtime=args.realtime, clients=clients, speed=args.speed, roles=roles,
                             topology="router" if args.external_coordinator else "peer",
                             signing_key_file=args.signing_key_file, vehicle=vehicle,
                             require_signing=require_signing, view=view, units_per_process=args.units_per_process,
                             save_certs=getattr(args, "save_certs", False) or bool(args.external_coordinator))
        for line in _endpoints(session, link):
            print(line, flush=True)
        if vehicle is not None:
            print(vehicle.describe(out), flush=True)
        if link.kind == "zenoh":
            where = session.router_endpoint or ", ".join(link.connect) or "none (peers: world and coordinator listen on 127.0.0.1)"
            print(f"zenoh: fleet {link.fleet!r}, router {where}" + (f" (+ {', '.join(link.listen)})" if link.listen else "")
                  + f"; keys mars/{link.fleet}/unit/<id>/mavlink/up|down/<node>; bus {session.link.bus()}", flush=True)
        own_key = session.certificates is not None and session.certificates.signing_key_file is not None
        print(f"internal links: MAVLink-signed with {'a per-run key' if own_key else 'your key'}"
              + (f" (saved in {out / 'certs'})" if own_key and (out / "certs").exists() else ""), flush=True)
        if (link.unit_interface or session.run.setup.scenario.unit_interface) == "px4-zenoh":
            print("px4: every unit speaks PX4 v1.17's per-rotor interface over rmw_zenoh (domain 0): subscribes "
                  "/px4_<unit id>/fmu/in/{offboard_control_mode,actuator_motors,vehicle_command}, publishes "
                  "/px4_<unit id>/fmu/out/{vehicle_status,vehicle_command_ack,vehicle_odometry,sensor_combined,"
                  "battery_status,vehicle_local_position}", flush=True)
        if args.external_coordinator:
            attach = f"mars-link coordinator {scenario_path or ''} --out {out}"
            if args.signing_key_file:
                attach += f" --signing-key-file {Path(args.signing_key_file).resolve()}"
            elif session.certificates is not None and session.certificates.signing_key_file is not None:
                attach += f" --signing-key-file {out.resolve() / 'certs' / 'signing.key'}"  # (the run's own, saved)
            attach += (f" --transport zenoh --zenoh-connect {(link.listen or (session.router_endpoint,))[0]}" if link.kind == "zenoh"
                       else f" --transport udp --world-port {session.run.world_port} --coordinator-port {session.run.coordinator_port}")
            if session.link.tls_dir:  # the run's certificates were saved for it (mars_link.transport.tls)
                certs = out.resolve() / "certs"
                attach += (f" --tls-ca {certs / 'ca.crt'} --tls-cert {certs / 'coordinator.crt'}"
                           f" --tls-key {certs / 'coordinator.key'}")
            elif session.link.tls_ca:
                attach += " --tls-ca CA --tls-cert CERT --tls-key KEY"
            elif link.kind == "zenoh":
                attach += " --insecure"
            print(f"waiting for a coordinator: {attach}", flush=True)
        steps = session.run.setup.steps
        control_hz = session.run.setup.scenario.sim.control_hz
        print(f"running {'until Ctrl-C' if steps is None else f'{steps / control_hz:.1f} s of sim time'}; "
              f"run directory {out}", flush=True)
        code = session.wait(units_may_die=True)  # a dead unit is a failed unit (FTC flies on)
        early = _sitl_up_ended_early(out, steps, control_hz) if code == 0 else None
        if early:
            print(f"sitl: the flight ended early: {early}", file=sys.stderr)
            code = 1
        _finish_sitl_up(session, args, out, time.perf_counter() - wall0, None if code == 0 else early or
                        f"a process of the run died (exit {code})", vehicle is not None)
        print(f"run directory: {out}")
        return code
    except KeyboardInterrupt as exc:
        print("sitl: interrupted, stopping every child", file=sys.stderr)
        if session is not None:
            session.stop()
            stopped_by = f"interrupted by {'SIGTERM' if isinstance(exc, Terminated) else 'SIGINT'}"
            _finish_sitl_up(session, args, out, time.perf_counter() - wall0, None if vehicle is not None else stopped_by,
                            vehicle is not None)
        return 143 if isinstance(exc, Terminated) else 130
    finally:
        signal.signal(signal.SIGTERM, previous)


def _finish_sitl_up(session: SitlSession, args, out: Path, wall_s: float, failure: str | None,
                    vehicle: bool) -> None:
    """`sitl up` ends as `run` does: summary.json, telemetry.csv, rotors.csv, plots/ (beside the run.mcap and
    the processes' logs) and the one-screen table, from what the processes logged. Never a traceback:
    a run whose world logged nothing yet, or an unexpected gap in the logs, is one line. With `--vehicle`
    the clients' commands are the reference, not the scenario's trajectory: no tracking figures then, and
    Ctrl-C is how it ends (completed)."""
    if not (out / "world_truth.csv").exists() or not (out / "world_summary.json").exists():
        return
    scenario = session.run.setup.scenario
    seed = scenario.sim.seed if args.seed is None else args.seed
    try:
        summary = summarize_sitl_run(scenario, out, seed, wall_s, session.link, True, args.realtime,
                                     plot_format=getattr(args, "plot_format", "png"), failure=failure,
                                     tracked=not vehicle)
    except Exception as exc:  # (after the flight: what the logs cannot give is one line, never a traceback)
        print(f"sitl: no summary of this run ({type(exc).__name__}: {exc})", file=sys.stderr)
        return
    from mars_link.flight.report import print_summary

    print_summary(summary, out)


def _sitl_up_ended_early(out: Path, steps: int | None, control_hz: float) -> str | None:
    """Why a `sitl up` flight of `steps` exchanges ended before them (the world's summary), else None."""
    from mars_link.flight.metrics import ended_early_reason

    if steps is None:  # until stopped, or a flight of pieces the coordinator ends
        return None
    world = _read_json(out / "world_summary.json")
    return ended_early_reason(float(world.get("sim_time_s", 0.0)), steps / control_hz, control_hz,
                              "stopped" if world.get("stopped") else "the world ended")


def _endpoints(session, link: LinkSpec) -> list[str]:
    run = session.run
    if link.kind == "udp":
        return run.endpoints()
    lines = [f"{name}: pid {run.processes[name].pid}, zenoh node {name!r}" for name in ("world", "coordinator")
             if name in run.processes]
    for i, u in enumerate(run.setup.unit_ids):
        lines.append(f"unit {u}: pid {run.processes[run.unit_process[u]].pid}, system id {u}, zenoh node 'unit/{u}', "
                     f"GCS udp 127.0.0.1:{run.clients.gcs_port}, API udp 127.0.0.1:{run.clients.api_port(i)} "
                     f"(MAVSDK udpin://127.0.0.1:{run.clients.api_port(i)}), log {run.out / f'unit{u}.tlog'}")
    return lines


def cmd_coordinator(args) -> int:
    """`mars-link coordinator ...`: the coordinator process alone, in this process (Ctrl-C ends it)."""
    from mars_link.config.scenario import load_scenario, resolve_scenario_path

    from mars_link.config.scenario import INTERACTIVE_SCENARIO

    path = resolve_scenario_path(args.scenario or INTERACTIVE_SCENARIO)
    load_scenario(str(path))
    link = link_from_args(args)
    if link.kind == "zenoh" and not link.connect:
        raise UserInputError("coordinator --transport zenoh needs --zenoh-connect ENDPOINT (the router `sitl up` prints)")
    if link.kind == "zenoh" and not link.insecure and not link.tls_ca:
        raise UserInputError("coordinator --transport zenoh needs --tls-ca/--tls-cert/--tls-key (the certificates "
                             "`sitl up` saved in RUN_DIR/certs) or --insecure (an open bus)")
    if link.kind == "udp" and not (0 < args.world_port < 65536 and 0 < args.coordinator_port < 65536):
        raise UserInputError("coordinator --transport udp needs --world-port and --coordinator-port (printed by sitl up)")
    from mars_link.processes.lockstep import main as lockstep_main

    argv = ["coordinator", str(path), "--out", args.out, *link.to_args()]
    if link.kind == "udp":
        argv += ["--world-port", str(args.world_port), "--coordinator-port", str(args.coordinator_port)]
    if args.signing_key_file:
        from mars_link.mavlink.signing import load_key

        load_key(args.signing_key_file)  # a bad key file: one line, exit 2
        argv += ["--signing-key-file", str(Path(args.signing_key_file).resolve())]
    return lockstep_main(argv)
