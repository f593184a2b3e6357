"""`mars-link` command line: the one tree of the product's subcommands and their options.

Every subcommand is added here; an option that several subcommands (or the internal entry points) share
is defined once in mars_link.processes.cli_options (one `add_*` per group: `--out`/`--force`, `--seed`,
the transport and its endpoints, client ports, `--duration`, `--quiet` ...), an option of one subcommand
alone beside it here. The command functions (`cmd_*`, or the modules' own `*_command(args)`) take the
parsed arguments. Internal process entry points that users do not type (`python -m
mars_link.processes.lockstep ROLE`, `python -m mars_link.processes.udp_runner`) keep their own parsers,
built from cli_options too.

Every user error is one line on stderr, "mars-link: error: ...", and exit code 2; a refusal from the
machine (disk, port, permission) one line and exit code 3 (mars_link.core.validation; the table of exit
codes: `EXIT_CODES_EPILOG`, docs/reference/exit-codes.md). `--duration` is
simulated seconds wherever it appears; a wall-clock limit is `--wall-time`.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

from mars_link.core import validation as v
from mars_link.core.errors import UserInputError, did_you_mean
from mars_link.processes.cli_options import (
    add_client_ports, add_duration, add_fault, add_flight_overrides, add_layout, add_link, add_map, add_out, add_params,
    add_plot_format, add_pool, add_quiet, add_run_ports, add_scenario, add_seed, add_signing, add_sitl_processes,
    add_view,
)

EXIT_USAGE = v.EXIT_USAGE


def _default_out(name: str) -> Path:
    """runs/<name>-<time>, the name sanitised to one path component (a scenario name may hold `/` or `..`)."""
    return Path("runs") / f"{v.safe_run_name(name)}-{time.strftime('%Y%m%d-%H%M%S')}"


def _apply_overrides(scenario, args) -> None:
    from mars_link.config.scenario import FTC_MODES, parse_fault_arg, validate_fault

    if getattr(args, "ftc", None):
        if args.ftc not in FTC_MODES:
            raise UserInputError(f"--ftc {args.ftc!r}: unknown mode (known: {', '.join(FTC_MODES)})")
        scenario.ftc = args.ftc
    if getattr(args, "controller", None):
        scenario.controller = args.controller
    for text in getattr(args, "fault", None) or []:
        fault = parse_fault_arg(text)
        validate_fault(fault, scenario.model(), f"--fault {text}")
        scenario.faults.append(fault)
    if getattr(args, "duration", None) is not None:  # finite and > 0 (validation.positive_float)
        scenario.sim.duration_s = args.duration
    if getattr(args, "no_noise", False):
        scenario.sim.noise = False
    if getattr(args, "unit_interface", None):  # (in process too: the same messages as objects)
        scenario.unit_interface = args.unit_interface
        if scenario.unit_interface == "px4-zenoh":
            from mars_link.flight.build import check_px4_interface

            check_px4_interface(scenario, scenario.model())


def cmd_run(args) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from mars_link.flight.build import check_flight
    from mars_link.config.scenario import check_faults_controllable, load_scenario

    scenario = load_scenario(args.scenario)
    _apply_overrides(scenario, args)
    from mars_link.flight.runner import run_scenario

    if args.mode not in ("inproc", "sitl"):
        raise UserInputError(f"--mode {args.mode!r}: expected inproc or sitl")
    v.check_link_endpoints(args)
    if args.mode != "sitl" and (args.gcs or args.gcs_port is not None or args.api_port is not None):
        raise UserInputError("--gcs, --gcs-port and --api-port apply to --mode sitl (an in-process run has no ports)")
    if args.mode != "sitl" and args.external_offboard:
        raise UserInputError("--external-offboard applies to --mode sitl (in process no off-board computer can reach "
                             "the units)")
    sitl_run = None
    if args.mode == "sitl":  # the multi-process SITL (mars_link.processes.sitl_mode); options checked before any output
        from mars_link.processes.sitl_mode import external_offboard_units, sitl_runner

        sitl_run = sitl_runner(args)
        if args.external_offboard:
            external_offboard_units(args.external_offboard, scenario)
    model = scenario.model()
    check_faults_controllable(scenario, model)
    if not scenario.reconfig.get("enabled"):
        check_flight(scenario, model)
    from mars_link.flight.flight_view import live_address

    live = live_address(args)  # a busy --foxglove port: one line, exit 3, before the flight
    out = v.claim_out_dir(args.out or _default_out(scenario.name), force=args.force)  # locked while we run
    console = Console(stderr=True)
    with Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
        TimeElapsedColumn(), console=console, transient=False, disable=args.quiet,
    ) as progress:
        task = progress.add_task(f"{scenario.name} x{args.trials}", total=args.trials)
        runner, options = run_scenario, {}
        if args.realtime and sitl_run is None:  # in-process: the engine paced to the wall clock
            options["realtime_rate"] = 1.0
        if args.logs and sitl_run is None:  # (SITL units always write theirs)
            options["logs"] = args.logs
        if sitl_run is not None:
            runner = sitl_run
        summary = runner(
            scenario, out, trials=args.trials, seed=args.seed,
            on_progress=lambda i, frac: progress.update(task, completed=i + frac), **options,
            mcap=not args.no_mcap, live=live, plot_format=args.plot_format,
        )
    from mars_link.flight.report import print_summary

    print_summary(summary, out)
    return 0 if summary["completed"] else 1


def _log_kinds(text: str) -> frozenset[str]:
    """`--logs ulog,tlog` -> the kinds; an unknown kind is one line (exit 2)."""
    from mars_link.logs import LOG_KINDS

    kinds = frozenset(k.strip() for k in text.split(",") if k.strip())
    unknown = sorted(kinds - set(LOG_KINDS))
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown log kind {unknown[0]!r} (known: {', '.join(LOG_KINDS)})")
    return kinds


def cmd_reproduce(args) -> int:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from mars_link.apps.reproduce import (
        CASCADED_MODES, estimate_table1, markdown_table, reproduce_table1, write_fig3, write_results,
    )

    if args.what != "table1":
        raise UserInputError(f"reproduce {args.what!r}: only 'table1' is available")
    if args.seeds < 1:
        raise UserInputError(f"--seeds must be >= 1, got {args.seeds}")
    modes = tuple(args.modes.split(",")) if args.modes else CASCADED_MODES
    for m in modes:
        if m not in CASCADED_MODES:
            raise UserInputError(f"--modes: unknown mode {m!r} (known: {', '.join(CASCADED_MODES)})")
    v.check_out_dir(args.out)  # its files are replaced on a re-run: a non-empty directory is fine here
    controllers = tuple(args.controllers.split(","))
    for c in controllers:
        if c not in ("mars-ftcc-paper", "cascaded"):
            raise UserInputError(f"--controllers: unknown controller {c!r}")
    from mars_link.apps.sweep_pool import PoolSpec, connect

    if args.scheduler:  # an unreachable scheduler: one line, exit 2, before any flight (as sweep)
        connect(args.scheduler).close()
    pool = PoolSpec(args.workers, args.scheduler)
    # how much and how long, before the first flight (a cluster's size is not known here: one worker's time)
    estimate = estimate_table1(args.seeds, controllers, modes, args.duration,
                               1 if args.scheduler else pool.local_workers())
    print(f"reproduce table1: {estimate.text()}", file=sys.stderr, flush=True)
    if args.dry_run:
        return 0
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), disable=args.quiet) as progress:
        task = progress.add_task("table1", total=None)

        def on_progress(done: int, total: int, name: str) -> None:
            progress.update(task, completed=done, total=total, description=name[:48])

        rows = reproduce_table1(args.seeds, controllers, modes, args.duration, on_progress, pool)
    path = write_results(rows, args.seeds, Path(args.out))
    print(markdown_table(rows, args.seeds))
    print(f"saved {path}")
    fig3 = write_fig3(rows, Path(args.out), args.plot_format)
    if fig3 is not None:
        print(f"saved {fig3}")
    return 0


def cmd_sweep(args) -> int:
    from mars_link.apps.sweep_cli import sweep_command

    return sweep_command(args, _default_out)


def cmd_sitl_up(args) -> int:
    """`mars-link sitl up`: every check first (one line, exit 2, before any process), then the one
    implementation (mars_link.processes.sitl_mode.sitl_up_command) on the chosen transport."""
    from mars_link.config.scenario import INTERACTIVE_SCENARIO, resolve_scenario_path
    from mars_link.processes.lockstep import load_setup

    if args.units is not None and args.layout is not None:
        raise UserInputError("--units and --layout exclude each other")
    if args.speed is not None and not (args.speed >= 0 and args.speed < float("inf")):
        raise UserInputError(f"--speed must be >= 0, got {args.speed}")
    if args.units is not None and args.scenario is None:
        path, name = None, "units"  # free units: built-in defaults unless a scenario is given
    else:
        path = str(resolve_scenario_path(args.scenario or INTERACTIVE_SCENARIO))
        name = Path(path).stem
    setup = load_setup(path, args.units, args.layout)  # refuse bad input before starting any process
    vehicle = _vehicle_ports(args, setup)
    v.check_link_endpoints(args)
    from mars_link.processes.sitl_mode import link_from_args

    link = link_from_args(args)
    if vehicle is not None and args.external_coordinator:
        raise UserInputError("--vehicle is served by the coordinator sitl up starts: not with --external-coordinator")
    if setup.docked:  # a docked assembly: the shared checks of `run` and `vehicle`
        from mars_link.flight.build import check_flight
        from mars_link.config.scenario import check_faults_controllable

        check_faults_controllable(setup.scenario, setup.model)
        if vehicle is None:  # --vehicle flies until Ctrl-C: no flight length to check
            check_flight(setup.scenario, setup.model)
    from mars_link.flight.flight_view import world_view_args

    view = world_view_args(args)  # a busy --foxglove port: one line, exit 3, before any process
    out = v.check_out_dir(args.out or _default_out(name + "-sitl"), force=args.force)
    from mars_link.mavlink.signing import signing_from_args

    _, require_signing = signing_from_args(args)  # a bad key file is refused before the run directory exists
    from mars_link.processes.launcher import ClientPorts

    clients = ClientPorts.consecutive(args.gcs_port, args.api_port, len(setup.unit_ids), args.any_bind)
    for what, port in (("--gcs-port", args.gcs_port), ("--api-port", args.api_port),
                       ("--api-port + units", clients.api_ports[-1])):
        if not 1 <= port <= 65535:
            raise UserInputError(f"{what} must be 1..65535, got {port}")
    from mars_link.processes.launcher import check_udp_ports_free, unit_bind_ports
    from mars_link.processes.sitl_mode import sitl_up_command

    busy_checks = unit_bind_ports(clients, len(setup.unit_ids))
    if vehicle is not None:
        busy_checks += [(vehicle.gcs_bind, "the vehicle's GCS link", "--any-bind"),
                        (vehicle.api_bind, "the vehicle's API link", "--any-bind")]
    check_udp_ports_free(busy_checks)  # a busy port: one line naming it, exit 3, before any process
    v.claim_out_dir(out, force=args.force)
    return sitl_up_command(args, path, out, link, clients, vehicle, view, require_signing)


def _vehicle_ports(args, setup):
    """`sitl up --vehicle` options -> mars_link.processes.vehicle_host.VehiclePorts (None without --vehicle)."""
    if not args.vehicle:
        return None
    from mars_link.processes.vehicle_host import VEHICLE_API_BIND, VEHICLE_GCS_BIND, VehiclePorts

    if not setup.docked:
        raise UserInputError("--vehicle needs a docked assembly (a scenario or --layout), not --units")
    if args.speed is not None and args.speed <= 0:
        raise UserInputError("--vehicle is flown in real time: --speed must be > 0")
    ports = VehiclePorts(args.vehicle_sysid, args.gcs_port if args.vehicle_gcs_port is None else args.vehicle_gcs_port,
                         args.vehicle_api_port, 0 if args.any_bind else VEHICLE_GCS_BIND, 0 if args.any_bind else VEHICLE_API_BIND)
    ports.check(setup.unit_ids)
    if args.map is not None:
        from mars_link.planning.pipeline import resolve_data_path
        from mars_link.processes.realtime import check_map

        check_map(args.map, "--map")
        ports.map_path = str(resolve_data_path(args.map).resolve())  # (the coordinator process may run elsewhere)
    return ports


def cmd_coordinator(args) -> int:
    v.check_link_endpoints(args)  # the shared checks first (endpoints, --out)
    v.check_out_dir(args.out)
    from mars_link.processes.sitl_mode import cmd_coordinator as coordinator_command

    return coordinator_command(args)


def cmd_vehicle(args) -> int:
    from mars_link.processes.realtime import vehicle_command

    return vehicle_command(args)


def cmd_scenarios(args) -> int:
    """The bundled scenarios: name and the first line of each file's header comment (--json: with paths)."""
    import json

    from mars_link.config.scenario import bundled_scenarios

    found = bundled_scenarios()
    if args.json:
        print(json.dumps(found, indent=2))
    else:
        width = max((len(s["name"]) for s in found), default=0)
        for s in found:
            print(f"{s['name']:<{width}}  {s['description']}")
    return 0


def cmd_plan(args) -> int:
    from mars_link.apps.plan_cli import plan_command_args

    return plan_command_args(args)


def cmd_reconfig_plan(args) -> int:
    from mars_link.apps.reconfig_cli import reconfig_plan_args

    return reconfig_plan_args(args)


# ----------------------------------------------------------------------------- the parser
def _version() -> str:
    """The installed distribution's version, else the package's own (a source checkout on PYTHONPATH)."""
    from importlib import metadata

    try:
        return metadata.version("mars-link")
    except metadata.PackageNotFoundError:
        from mars_link import __version__

        return __version__


class _HelpFormatter(argparse.HelpFormatter):
    """Each option's help ends with its default, unless the text already says it (or there is none)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default in (None, False, argparse.SUPPRESS, []) or "default" in text or "%(default)" in text:
            return text
        if not action.option_strings and action.nargs not in ("?", "*"):
            return text
        return f"{text} (default: %(default)s)"


class _Parser(v.OneLineParser):
    """The product's parser (and every subcommand's): usage errors are one UserInputError line naming the
    subcommand ("mars-link: error: sitl up: ..."), an unknown name gets a "did you mean"."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:
        where = self.prog.removeprefix("mars-link").strip()
        raise UserInputError(f"{where}: {message}" if where else message)

    def _check_value(self, action: argparse.Action, value) -> None:
        choices = action.choices
        if choices is None or value in choices:
            return
        names = [str(c) for c in choices]
        what = "command" if isinstance(action, argparse._SubParsersAction) else "choice"
        if len(names) == 1:
            text = f"unknown {what} {value!r}: only {names[0]!r} is available"
        else:
            text = f"unknown {what} {value!r} (choose from {', '.join(names)}){did_you_mean(str(value), names)}"
        raise argparse.ArgumentError(None if what == "command" else action, text)


#: the exit codes of `run` and `sitl up`, in their --help (and docs/reference/exit-codes.md)
EXIT_CODES_EPILOG = (
    "Exit codes: 0 completed (also when a log stopped on a full disk: the reason is in summary.json); "
    "1 diverged or ended early, for any reason (summary.json: completed false and end_reason); 2 bad input; "
    "3 could not start (a busy port, no disk for the summary; one line names it); 130 interrupted by SIGINT "
    "(Ctrl-C); 143 interrupted by SIGTERM (the summary of the part flown is written)."
)


def _command(sub, name: str, help: str, description: str, func, epilog: str | None = None) -> argparse.ArgumentParser:
    """One subcommand: `help` is its line in the parent's list, `description` the top of its own --help."""
    p = sub.add_parser(name, help=help, description=description, epilog=epilog)
    p.set_defaults(func=func)
    return p


# The assembly as one MAVLink vehicle: `vehicle` and `sitl up --vehicle` give it the same system id and
# ports, so a client set up for one works with the other. Why not PX4's instance-0 ports (14540, system
# 1): `sitl up` gives those to its units (unit i: system i, API port 14540 + i), and the vehicle beside them.
def _vehicle_defaults() -> tuple[int, int]:
    from mars_link.processes.ports import DEFAULT_VEHICLE_API_PORT, DEFAULT_VEHICLE_SYSID

    return DEFAULT_VEHICLE_SYSID, DEFAULT_VEHICLE_API_PORT


_VEHICLE_WHY = "the same as `sitl up --vehicle`, whose units take systems 1..N and PX4's API ports 14540+i"


def build_parser() -> argparse.ArgumentParser:
    """Every subcommand and option of `mars-link`."""
    from mars_link.config.scenario import DEFAULT_SCENARIO, INTERACTIVE_SCENARIO

    parser = _Parser(prog="mars-link", description="SITL flight stack for modular aerial robots (MARS): fly a "
                     "scenario in one process or as MAVLink processes, serve it to ground stations, plan, sweep, "
                     "reproduce the papers' results.")
    parser.add_argument("--version", action="version", version=f"mars-link {_version()}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    vehicle_sysid, vehicle_api_port = _vehicle_defaults()

    # -- run
    run = _command(sub, "run", "fly a scenario and write its results (summary.json, telemetry, plots, run.mcap)",
                   "Fly a scenario, in this process (--mode inproc) or as the multi-process MAVLink SITL (--mode "
                   "sitl, lockstep: the same flight for the same seed), and write summary.json, telemetry.csv, "
                   "rotors.csv, plots/ and run.mcap; print a one-screen table.", cmd_run, EXIT_CODES_EPILOG)
    add_scenario(run, DEFAULT_SCENARIO, ", the 3x2 spiral")
    add_out(run, "runs/<name>-<time>")
    add_seed(run)
    run.add_argument("--trials", type=v.bounded_int(1, 100_000), default=1,
                     help="flights with seeds SEED, SEED+1, ... (in-process only)")
    add_flight_overrides(run)
    run.add_argument("--controller", choices=("cascaded", "mars-ftcc-paper"), default=None,
                     help="position/attitude controller (default: the scenario's [control] controller)")
    add_duration(run, "override the scenario's flight length")
    run.add_argument("--mode", choices=("inproc", "sitl"), default="inproc",
                     help="inproc: one process, the engine steps everything; sitl: world, one process per unit "
                          "and the coordinator, talking MAVLink over --transport")
    add_link(run, "the SITL processes (with --mode sitl)")
    run.add_argument("--gcs", action="store_true",
                     help="with --mode sitl: open the units' ground-station ports (PX4's: GCS 14550, API 14540+i; "
                          "default: none, a batch run no client can reach)")
    run.add_argument("--gcs-port", type=int, default=None,
                     help="with --mode sitl: the GCS port the units send to (implies --gcs; default 14550)")
    run.add_argument("--api-port", type=int, default=None,
                     help="with --mode sitl: API port of unit index 0, unit i uses this + i (implies --gcs; default 14540)")
    run.add_argument("--external-offboard", default=None, metavar="UNITS",
                     help="with --mode sitl and --unit-interface px4-zenoh: start no coordinator; the units (all, or "
                          "their ids: a docked assembly is one body, so every one) wait for your own off-board "
                          "computer on the run's Zenoh bus (PX4's /px4_<id>/fmu topics), the world runs in real time "
                          "for the run's duration, and summary.json says who flew them (no tracking figures)")
    add_sitl_processes(run, "pace the flight to the wall clock (in-process: the engine; with --mode sitl: the world)")
    run.add_argument("--logs", type=_log_kinds, default=frozenset(), metavar="KINDS",
                     help="per-unit logs of an in-process run, comma-separated: ulog (unit<id>.ulg, PX4's topics), "
                          "tlog (unit<id>.tlog: the unit's MAVLink exchange with the coordinator, sim-time "
                          "stamps); --mode sitl always writes both")
    add_view(run)
    add_plot_format(run)
    add_quiet(run)

    # -- scenarios
    scen = _command(sub, "scenarios", "list the bundled scenarios (name and one-line description)",
                    "List the scenarios bundled with mars-link: the name to give `run`, `sitl up` or `sweep`, and the "
                    "first line of each file's header comment.", cmd_scenarios)
    scen.add_argument("--json", action="store_true", help="a JSON list of {name, description, path}")

    # -- sitl up
    sitl = sub.add_parser("sitl", help="the multi-process SITL for clients: `sitl up` (world, one MAVLink process "
                                       "per unit, coordinator)",
                          description="The multi-process SITL, interactive: units that MAVLink clients connect to.")
    sitl_sub = sitl.add_subparsers(dest="action", metavar="ACTION", title="actions", required=True)
    up = _command(sitl_sub, "up", "start the world, one process per unit and the coordinator; run until the flight "
                  "ends or Ctrl-C",
                  "Start the world, one MAVLink process per unit (PX4's client ports: unit i sends to GCS port "
                  "14550 and API port 14540+i, like PX4 SITL instance i) and, for a docked assembly, the "
                  "coordinator; print the endpoints; run until the flight ends, Ctrl-C or a child's death. "
                  "--vehicle adds the whole assembly as one MAVLink vehicle.", cmd_sitl_up, EXIT_CODES_EPILOG)
    add_scenario(up, INTERACTIVE_SCENARIO, ", the realistic plant")
    add_out(up, "runs/<name>-sitl-<time>")
    add_seed(up)
    up.add_argument("--units", type=int, default=None,
                    help="N free units side by side on the ground, each flying itself (no coordinator; default: "
                         "the scenario's assembly)")
    add_layout(up, "a docked assembly, with coordinator; overrides the scenario")
    up.add_argument("--speed", type=float, default=None, metavar="X",
                    help="world pacing, x real time (default 1 for --units and --vehicle, 0 = as fast as possible "
                         "otherwise)")
    add_client_ports(up, 14540, "API port of unit index 0 (MAVSDK); unit i uses this + i (PX4's ports)")
    add_signing(up, "the run's own links (world, units, coordinator; HIL frames and the shutdown included), "
                     "signed both ways, and the client links", "a per-run key made at start")
    up.add_argument("--any-bind", action="store_true",
                    help="bind the units' client sockets to free ports instead of PX4's 18570+i / 14580+i")
    up.add_argument("--vehicle", action="store_true",
                    help="the docked assembly as ONE MAVLink vehicle (served by the coordinator; arm, takeoff, "
                         "offboard, land from MAVSDK/QGC); runs in real time until Ctrl-C")
    up.add_argument("--vehicle-sysid", type=int, default=vehicle_sysid,
                    help=f"with --vehicle: its MAVLink system id ({_VEHICLE_WHY}; default {vehicle_sysid})")
    up.add_argument("--vehicle-api-port", type=int, default=vehicle_api_port,
                    help=f"with --vehicle: MAVSDK's port, udpin://127.0.0.1:PORT ({_VEHICLE_WHY}; default "
                         f"{vehicle_api_port})")
    up.add_argument("--vehicle-gcs-port", type=int, default=None,
                    help="with --vehicle: its ground-station port (default: --gcs-port, 14550)")
    add_map(up, "with --vehicle")
    add_view(up, " (served by the world process)")
    add_plot_format(up)
    add_link(up, "the world, the units and the coordinator (the clients' links are UDP either way)")
    add_sitl_processes(up, "pace the world to the wall clock")
    up.add_argument("--external-coordinator", action="store_true",
                    help="start no coordinator: attach one with `mars-link coordinator` (printed)")

    # -- coordinator
    coord = _command(sub, "coordinator", "the coordinator process alone, attaching to the units of a running "
                     "`sitl up --external-coordinator`",
                     "Run the coordinator in this process, attached to the world and units that `mars-link sitl up "
                     "--external-coordinator` started (it prints this command); Ctrl-C ends it.", cmd_coordinator)
    add_scenario(coord, INTERACTIVE_SCENARIO, ", as sitl up")
    coord.add_argument("--out", default=".", metavar="DIR", help="where coordinator_summary.json goes")
    add_run_ports(coord, " (printed by sitl up)")
    coord.add_argument("--signing-key-file", default=None, metavar="FILE",
                       help="sign the unit links (default: $MARS_LINK_SIGNING_KEY, else unsigned)")
    add_link(coord, "the coordinator and the units (as the `sitl up` it attaches to)")

    # -- vehicle
    from mars_link.processes.ports import VEHICLE_API_BIND as API_BIND, VEHICLE_GCS_BIND as GCS_BIND

    veh = _command(sub, "vehicle", "the assembly as one MAVLink vehicle in real time (MAVSDK, MAVProxy, QGC)",
                   "The assembly (physics and coordinator in this process) behind one MAVLink endpoint, paced to "
                   "real time: arm, take off, fly missions, offboard and land from a ground station or MAVSDK. "
                   "The scenario's vehicle, layout, control and faults are used, not its trajectory. Runs until "
                   "Ctrl-C, --duration (simulated) or --wall-time.", cmd_vehicle)
    add_scenario(veh, INTERACTIVE_SCENARIO, ", the realistic plant")
    add_layout(veh, "overrides the scenario")
    veh.add_argument("--sysid", type=int, default=vehicle_sysid,
                     help=f"MAVLink system id ({_VEHICLE_WHY}; default {vehicle_sysid})")
    add_client_ports(veh, vehicle_api_port, f"MAVSDK listens here, udpin://127.0.0.1:PORT ({_VEHICLE_WHY}; "
                      f"default {vehicle_api_port})")
    veh.add_argument("--gcs-bind", type=int, default=GCS_BIND,
                     help=f"local port of the gcs link (0: any; default {GCS_BIND}, below the units' 18570+i)")
    veh.add_argument("--api-bind", type=int, default=API_BIND,
                     help=f"local port of the api link (0: any; default {API_BIND}, below the units' 14580+i)")
    add_seed(veh)
    add_flight_overrides(veh)
    add_params(veh)
    veh.add_argument("--mission", default=None, metavar="FILE.plan",
                     help="QGroundControl .plan preloaded (mission, geofence, rally), as if a client had uploaded it")
    add_map(veh, "default: the scenario's [mission] map")
    veh.add_argument("--speed", type=float, default=1.0, metavar="X",
                     help="simulation speed, x real time (0.05..20)")
    veh.add_argument("--status-file", default=None, metavar="FILE",
                     help="JSON snapshot (truth, mode, counters) a few times a second")
    veh.add_argument("--tlog", default=None, metavar="FILE",
                     help="MAVLink log of both links (pymavlink .tlog), appended and flushed as it goes")
    add_duration(veh, "stop after this much simulated time (it once meant wall seconds: that is --wall-time now)")
    veh.add_argument("--wall-time", type=v.positive_float, default=None, metavar="SECONDS",
                     help="stop after this many wall-clock seconds [wall s]")
    add_signing(veh, "the gcs and api links")
    add_out(veh, "none: nothing written; with DIR: run.mcap, vehicle.ulg, summary.json, telemetry, plots", force=False)
    add_view(veh)
    add_plot_format(veh)

    # -- plan
    plan = _command(sub, "plan", "a collision-free trajectory for an assembly on a map (trajectory.csv, plan.json, "
                    "plan.png)",
                    "Plan a collision-free trajectory for an assembly on an obstacle map; write trajectory.csv (the "
                    "'csv' trajectory kind replays it), plan.json and plan.png. Exit 0 = a collision-free plan, "
                    "1 = none found (reason on stderr and in plan.json), 2 = bad input.", cmd_plan)
    plan.add_argument("map", help="boxes .csv (columns cx,cy,length_m,thickness_m,height_m,yaw_deg; z-up scene frame) "
                      "or ASCII .pcd")
    add_layout(plan, "the assembly to plan for", required=True)
    add_fault(plan, "counted as in effect for the whole plan")
    plan.add_argument("--start", required=True, metavar="N,E,D", help="start position [m, NED]")
    plan.add_argument("--goal", required=True, metavar="N,E,D", help="goal position [m, NED] (same D: planning is planar)")
    plan.add_argument("--start-yaw", type=float, default=0.0, metavar="DEG", help="start yaw [deg, NED]")
    plan.add_argument("--method", default="ours", help="ours (dynamics-aware) or svsdf (baseline)")
    plan.add_argument("--preset", default="mars-ftcc", help="vehicle preset")
    plan.add_argument("--margin", type=float, default=None, metavar="M", help="footprint inflation [m] (default 0.1)")
    plan.add_argument("--out", required=True, metavar="DIR", help="output directory (must be empty unless --force)")
    plan.add_argument("--force", action="store_true", help="clear a non-empty --out first")
    add_quiet(plan)

    # -- reconfig plan
    reconfig = sub.add_parser("reconfig", help="self-reconfiguration (paper 001): `reconfig plan`",
                              description="Self-reconfiguration of an assembly with faulty units (paper 001).")
    reconfig_sub = reconfig.add_subparsers(dest="action", metavar="ACTION", title="actions", required=True)
    rplan = _command(reconfig_sub, "plan", "the reconfiguration the scenario's faults call for, as text or JSON",
                     "Plan the self-reconfiguration (paper 001) for the scenario's faults and --fault: which unit "
                     "goes to which cell, and the split/move/dock layers. Exit 0 = a plan, 1 = no feasible plan "
                     "(the JSON still says why), 2 = bad input.", cmd_reconfig_plan)
    rplan.add_argument("scenario", nargs="?", default=None,
                       help="scenario TOML file or bundled name (default: none; then --layout is needed)")
    add_fault(rplan, "T is ignored: every fault counts")
    add_layout(rplan, "overrides the scenario")
    rplan.add_argument("--preset", default=None, help="vehicle preset (overrides the scenario; default modquad-cf2)")
    rplan.add_argument("--target", default=None, metavar="IDS",
                       help="plan to this allocation instead of the optimal one: unit ids for the layout's cells in "
                            "row-major order, e.g. 3,2,1")
    rplan.add_argument("--objective", choices=("force", "margin"), default="force",
                       help="what the target maximises: force (paper 001's placement) or margin (MARS-Reconfig: the "
                            "worst-stage controllability margin); both are printed (default: force)")
    rplan.add_argument("--snap-weights", default=None, metavar="BX,BY",
                       help="snap integrals along north and east (default: from the scenario's trajectory, else equal)")
    rplan.add_argument("--json", action="store_true", help="print one JSON object")

    # -- reproduce
    rep = _command(sub, "reproduce", "reproduce a paper's table (table1: paper 000 Table I + Fig. 3)",
                   "Fly every flight of a paper's table and print it beside the paper's numbers (table1: paper 000 "
                   "Table I and Fig. 3, controllers x FTC modes x seeds). Prints the number of flights and an "
                   "estimate of the time first (--dry-run: only that); writes table1.md, table1.json and the "
                   "Fig. 3 figure (fig3.png, or --plot-format pdf/svg) with the paper's values beside ours.",
                   cmd_reproduce)
    rep.add_argument("what", choices=("table1",), help="the table: table1")
    rep.add_argument("--seeds", type=v.bounded_int(1, 10_000), default=10, help="flights per controller and mode")
    rep.add_argument("--controllers", default="mars-ftcc-paper,cascaded", help="comma-separated")
    rep.add_argument("--modes", default=None, help="cascaded FTC modes, comma-separated (default: all)")
    add_duration(rep, "shorten every flight (a quick look; default: the paper's)")
    rep.add_argument("--out", default="runs/table1", metavar="DIR", help="where the results go (replaced on a re-run)")
    rep.add_argument("--dry-run", action="store_true",
                     help="print the number of flights and the time estimate, fly nothing")
    add_plot_format(rep)
    add_quiet(rep)
    add_pool(rep)

    # -- sweep
    swp = _command(sub, "sweep", "many flights of a scenario over seeds, random faults and parameters, on local "
                   "cores or a Dask cluster",
                   "Fly a scenario many times: over seeds, random faults and parameter grids, on local cores or a "
                   "Dask cluster; write sweep.csv (rows appended to sweep.partial.csv as flights finish), sweep.md, "
                   "sweep.json and plots/. Exit 0 when every flight flew (diverged or not), 1 when one raised.",
                   cmd_sweep)
    add_scenario(swp, DEFAULT_SCENARIO)
    swp.add_argument("--seeds", type=v.bounded_int(1, 100_000), default=10, help="flights per parameter combination")
    add_seed(swp, "the sweep seed (default: the scenario's); seed slot j flies seed SEED + j")
    swp.add_argument("--faults", default=None, metavar="random:K|A-B[,rotors|units|whole-units][,eta=E1/E2][,kind=KIND]",
                     help="random faults per flight, drawn from the sweep seed and the slot: K (or A to B) distinct "
                          "rotors (eta 0, each at its own time), units (one rotor each, all at one time, etas 0 and "
                          "0.3 mixed) or whole units (eta 0); eta=E1/E2 sets the etas drawn from; scored against the "
                          "coordinator's beliefs in faults.csv")
    swp.add_argument("--param", action="append", default=[], metavar="KEY=V1,V2,...",
                     help="scenario TABLE.KEY (or ftc, controller, noise, ...) values to sweep; repeat for a grid")
    add_pool(swp)
    add_out(swp, "runs/<name>-sweep-<time>")
    swp.add_argument("--mcap", action="store_true", help="each flight writes flights/<i>/run.mcap")
    swp.add_argument("--no-plots", action="store_true", help="write no plots/")
    add_quiet(swp)

    # -- conformance
    conf = _command(sub, "conformance", "the unit command pipeline's conformance checks, in simulated time",
                    "Check a unit's command pipeline on its command interfaces, in simulated time (lockstep, the unit "
                    "firmware on the ground in the in-process world, commands as wire bytes): keep-alive loss and "
                    "its bound, recovery only on a fresh arm, arming and OFFBOARD gating, NaN and out-of-range "
                    "controls, stale and reordered messages, and a recorded command stream replayed to the same "
                    "motor outputs byte for byte. One table per interface; exit 1 when a check fails.",
                    cmd_conformance)
    conf.add_argument("--unit-interface", choices=("both", "px4-zenoh", "mavlink"), default="both",
                      help="the interface to check: px4-zenoh (PX4 v1.17's OffboardControlMode, VehicleCommand, "
                           "ActuatorMotors as rmw_zenoh samples), mavlink (SET_ACTUATOR_CONTROL_TARGET), or both")
    conf.add_argument("--target", choices=("inproc", "process"), default="inproc",
                      help="inproc: the unit firmware object in this process (fast); process: a unit process as sitl "
                           "up starts it, reached over the network (PX4's interface over Zenoh, MAVLink over UDP), "
                           "its world and off-board computer played by the harness, still in simulated time")
    conf.add_argument("--check", action="append", default=None, metavar="NAME",
                      help="run only this check (repeatable): keepalive-loss, fresh-arm, arming-gating, "
                           "offboard-gating, nan, out-of-range, stale, replay (default: all)")
    conf.add_argument("--test-broken-keepalive", action="store_true",
                      help="test switch: a unit whose PX4 keep-alive never times out (the checks must fail; "
                           "with --target process the unit process is started with it)")
    return parser


def cmd_conformance(args) -> int:
    from mars_link.apps.conformance import conformance_command

    return conformance_command(args)


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Every subcommand's parser by its full name ("run", "sitl up", ...), nested ones included: for the
    documentation generator and the tests that walk the tree."""
    found: dict[str, argparse.ArgumentParser] = {}

    def walk(p: argparse.ArgumentParser, prefix: str) -> None:
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, child in action.choices.items():
                    full = f"{prefix} {name}".strip()
                    found[full] = child
                    walk(child, full)

    walk(parser, "")
    return found


def _sigterm_raises_terminated() -> Callable[[], None]:
    """SIGTERM raises core.errors.Terminated in the main thread, as Ctrl-C raises KeyboardInterrupt: the same
    cleanup (children stopped by PID, the summary of the part flown), exit 143. An ignored SIGTERM stays ignored.
    Returns what puts the caller's handler back (main() called from Python leaves the process as it found it)."""
    import signal
    import threading

    from mars_link.core.errors import Terminated

    previous = signal.getsignal(signal.SIGTERM)
    if threading.current_thread() is not threading.main_thread() or previous == signal.SIG_IGN:
        return lambda: None

    def terminate(*_) -> None:
        raise Terminated

    signal.signal(signal.SIGTERM, terminate)
    return lambda: signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    from mars_link.processes.parent_watch import hear_stop_signals

    hear_stop_signals()  # Ctrl-C stops every command, whatever mask the parent left
    restore_sigterm = _sigterm_raises_terminated()
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["plan"]:  # before numpy loads: threaded BLAS is 10x slower for the planner (spec §6.1)
        import os

        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    try:
        parser = build_parser()
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # --help, --version: printed, exit 0
            return exc.code if isinstance(exc.code, int) else 0
        if not getattr(args, "func", None):
            parser.print_help()
            return EXIT_USAGE
        return args.func(args)
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (Terminated): the run wrote the summary of the part flown
        from mars_link.core.errors import Terminated

        terminated = isinstance(exc, Terminated)
        print(f"mars-link: interrupted by {'SIGTERM' if terminated else 'SIGINT'}", file=sys.stderr)
        return v.EXIT_SIGTERM if terminated else v.EXIT_SIGINT
    except (UserInputError, v.EnvironmentFailure, OSError) as exc:  # OSError: an unexpected disk/port refusal
        line, code = v.report(exc)
        print(line, file=sys.stderr)
        return code
    except Exception as exc:  # a Zenoh session that cannot open (port taken): one line, exit 3
        if type(exc).__module__.split(".")[0] != "zenoh":
            raise
        line, code = v.report(exc)
        print(line, file=sys.stderr)
        return code
    finally:
        v.release_out_dirs()
        restore_sigterm()


if __name__ == "__main__":
    sys.exit(main())
