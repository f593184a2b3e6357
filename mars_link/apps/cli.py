"""`mars-link` command line. Every user error is one line on stderr and exit code 2; a refusal from
the machine (disk, port, permission) one line and exit code 1 (mars_link.core.validation)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mars_link.core import validation as v
from mars_link.core.errors import UserInputError

EXIT_USAGE = v.EXIT_USAGE
_Parser = v.OneLineParser  # one-line usage errors (errors.OneLineArgumentParser)


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
    sitl_run = None
    if args.mode == "sitl":  # the multi-process SITL (mars_link.processes.sitl_mode); options checked before any output
        from mars_link.processes.sitl_mode import sitl_runner

        sitl_run = sitl_runner(args)
    model = scenario.model()
    check_faults_controllable(scenario, model)
    if not scenario.reconfig.get("enabled"):
        check_flight(scenario, model)
    from mars_link.flight.flight_view import live_address

    live = live_address(args)  # a busy --foxglove port: one line, exit 2, before the flight
    out = v.claim_out_dir(args.out or _default_out(scenario.name), force=args.force)  # locked while we run
    console = Console(stderr=True)
    with Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
        TimeElapsedColumn(), console=console, transient=False, disable=args.quiet,
    ) as progress:
        task = progress.add_task(f"{scenario.name} x{args.trials}", total=args.trials)
        runner, pacing = run_scenario, {}
        if args.realtime and sitl_run is None:  # in-process: the engine paced to the wall clock
            pacing = {"realtime_rate": 1.0}
        if scenario.has_pieces:  # several bodies (mars_link.flight.reconfig_flight)
            from mars_link.flight.reconfig_flight import run_reconfig_scenario as runner

            if args.trials != 1:
                raise UserInputError("--trials: a [reconfig] flight runs one trial (vary --seed instead)")
        if sitl_run is not None:
            runner = sitl_run
        summary = runner(
            scenario, out, trials=args.trials, seed=args.seed,
            on_progress=lambda i, frac: progress.update(task, completed=i + frac), **pacing,
            mcap=not args.no_mcap, live=live,
        )
    print_summary(summary, out)
    return 0 if summary["completed"] else 1


def print_summary(summary: dict, out: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"mars-link run: {summary['scenario']}", show_header=False)
    def fig(key: str, form: str) -> str:
        """A summary figure, or "n/a" where this mode does not measure it (the SITL pieces: no body tilt)."""
        value = summary.get(key)
        return "n/a" if value is None else format(value, form)

    rows = [
        ("layout / preset", f"{','.join(summary['layout'])} / {summary['preset']}"),
        ("controller / ftc", f"{summary['controller']} / {summary['ftc']}"),
        ("trials (seed)", f"{summary['trials']} ({summary['seed']})"),
        ("completed", str(summary["completed"])),
        ("diverged", str(summary["diverged"])),
        ("mean error", f"{fig('mean_error_m', '.4f')} m ± {fig('mean_error_std_m', '.4f')}"),
        ("rmse / max error", f"{fig('rmse_m', '.4f')} / {fig('max_error_m', '.4f')} m"),
        ("max tilt", f"{fig('max_tilt_deg', '.2f')} deg"),
        ("force integral", f"{fig('force_integral_n2s', '.1f')} N²s"),
        ("sim / wall time", f"{summary['sim_time_s']:.2f} s / {summary['wall_time_s']:.2f} s"),
        ("real-time factor", f"{fig('real_time_factor', '.1f')}x"),
        ("events", str(len(summary["events"]))),
        ("run directory", str(out)),
    ]
    sitl = summary.get("sitl") or {}
    if sitl.get("realtime"):  # paced to the wall clock: how late the commands reached the motors, and why
        from mars_link.runtime.scheduling import describe_classes

        age = sitl.get("command_age") or {}
        if age.get("n"):
            rows.append(("command age at motor", f"p50 {age['p50_ms']:.2f} / p99 {age['p99_ms']:.2f} ms "
                         f"({age.get('deadline_misses', 0)}/{age['n']} late)"))  # (older than a control period)
        rows.append(("scheduling", describe_classes(sitl.get("scheduling") or {})))
    logging = summary.get("logging") or {}
    if logging.get("stopped_reason"):  # a write error stopped a log; the flight went on
        more = len(logging.get("stopped", [])) - 1
        rows.append(("logging stopped", logging["stopped_reason"] + (f" (+{more} more logs)" if more > 0 else "")))
    for key, value in rows:
        table.add_row(key, value)
    Console().print(table)


def cmd_reproduce(args) -> int:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from mars_link.apps.reproduce import CASCADED_MODES, markdown_table, reproduce_table1, write_results

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
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), disable=args.quiet) as progress:
        task = progress.add_task("table1", total=None)

        def on_progress(done: int, total: int, name: str) -> None:
            progress.update(task, completed=done, total=total, description=name[:48])

        from mars_link.apps.sweep_pool import pool_from_args

        rows = reproduce_table1(args.seeds, controllers, modes, args.duration, on_progress, pool_from_args(args))
    path = write_results(rows, args.seeds, Path(args.out))
    print(markdown_table(rows, args.seeds))
    print(f"saved {path}")
    return 0


def cmd_sweep(args) -> int:
    from mars_link.apps.sweep_cli import sweep_command

    return sweep_command(args, _default_out)


def cmd_sitl(args) -> int:
    from mars_link.config.scenario import INTERACTIVE_SCENARIO, resolve_scenario_path
    from mars_link.processes.launcher import sitl_up
    from mars_link.processes.lockstep import load_setup

    if args.action != "up":
        raise UserInputError(f"sitl {args.action!r}: only 'up' is available")
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
    if setup.docked:  # a docked assembly: the shared checks of `run` and `vehicle`
        from mars_link.flight.build import check_flight
        from mars_link.config.scenario import check_faults_controllable

        check_faults_controllable(setup.scenario, setup.model)
        if vehicle is None:  # --vehicle flies until Ctrl-C: no flight length to check
            check_flight(setup.scenario, setup.model)
    from mars_link.flight.flight_view import world_view_args

    view = world_view_args(args)  # a busy --foxglove port: one line, exit 2, before any process
    out = v.check_out_dir(args.out or _default_out(name + "-sitl"), force=args.force)
    from mars_link.mavlink.signing import signing_from_args

    _, require_signing = signing_from_args(args)  # a bad key file is refused before the run directory exists
    from mars_link.processes.launcher import ClientPorts

    n = len(setup.unit_ids)  # the client ports of either transport (sitl_mode builds the same)
    clients = ClientPorts.consecutive(args.gcs_port, args.api_port, n, args.any_bind)
    for what, port in (("--gcs-port", args.gcs_port), ("--api-port", args.api_port),
                       ("--api-port + units", clients.api_ports[-1])):
        if not 1 <= port <= 65535:
            raise UserInputError(f"{what} must be 1..65535, got {port}")
    if getattr(args, "transport", None) not in (None, "udp") or getattr(args, "external_coordinator", False) \
            or getattr(args, "realtime", False) or getattr(args, "link_profile", None):
        if vehicle is not None and getattr(args, "external_coordinator", False):
            raise UserInputError("--vehicle is served by the coordinator sitl up starts: not with --external-coordinator")
        from mars_link.processes.sitl_mode import sitl_up_command

        v.claim_out_dir(out, force=args.force)
        return sitl_up_command(args, path, out, vehicle, view)
    v.claim_out_dir(out, force=args.force)
    code = sitl_up(path, out, units=args.units, layout=args.layout, seed=args.seed, speed=args.speed, clients=clients,
                   signing_key_file=args.signing_key_file, vehicle=vehicle, require_signing=require_signing,
                   view=view, units_per_process=args.units_per_process)
    print(f"run directory: {out}")
    return code


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


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mars-link", description="SITL flight stack for modular aerial robots")
    sub = parser.add_subparsers(dest="command", parser_class=_Parser)

    run = sub.add_parser("run", help="fly a scenario (default: the bundled 3x2 spiral)")
    run.add_argument("scenario", nargs="?", help="scenario TOML file or bundled name")
    run.add_argument("--out", help="run directory (default runs/<name>-<time>); must be empty unless --force")
    run.add_argument("--force", action="store_true", help="clear a non-empty --out first")
    run.add_argument("--seed", type=v.seed, default=None, help=f"0..{v.SEED_MAX}")
    run.add_argument("--trials", type=v.bounded_int(1, 100_000), default=1)
    run.add_argument("--ftc", help="allocation mode: none, unit, partial, full, hybrid, qp")
    run.add_argument("--controller", choices=("cascaded", "mars-ftcc-paper"))
    run.add_argument("--fault", action="append", metavar="UNIT[:ROTOR]=ETA[@T]")
    run.add_argument("--duration", type=v.positive_float, help="override the simulated duration [s]")
    run.add_argument("--no-noise", action="store_true", help="perfect sensors (truth state)")
    run.add_argument("--mode", default="inproc", help="inproc (default) or sitl")
    from mars_link.processes.sitl_mode import add_sitl_run_arguments, add_coordinator_arguments, cmd_coordinator

    add_sitl_run_arguments(run)  # --transport, --realtime, --link-profile (with --mode sitl)
    from mars_link.flight.flight_view import add_view_arguments

    add_view_arguments(run)  # --no-mcap, --foxglove [HOST:PORT]
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.set_defaults(func=cmd_run)

    scen = sub.add_parser("scenarios", help="list the bundled scenarios (name and one-line description)")
    scen.add_argument("--json", action="store_true", help="a JSON list of {name, description, path}")
    scen.set_defaults(func=cmd_scenarios)

    sitl = sub.add_parser("sitl", help="up [SCENARIO] [--units N | --layout ROWS]: world, one process per unit (MAVLink), coordinator; lockstep")
    sitl.add_argument("action", help="up")
    sitl.add_argument("scenario", nargs="?", help="scenario TOML file or bundled name (default: hover_3x2_real, the "
                      "realistic plant)")
    sitl.add_argument("--out", help="run directory (default runs/<name>-sitl-<time>); must be empty unless --force")
    sitl.add_argument("--force", action="store_true", help="clear a non-empty --out first")
    sitl.add_argument("--seed", type=v.seed, default=None, help=f"0..{v.SEED_MAX}")
    sitl.add_argument("--units", type=int, default=None,
                      help="N free units side by side on the ground, each flying itself (no coordinator)")
    sitl.add_argument("--layout", default=None, help="docked assembly of these rows, e.g. XXX,XXX (with coordinator)")
    sitl.add_argument("--speed", type=float, default=None,
                      help="world pacing, x real time (default 1 for --units, 0 = as fast as possible otherwise)")
    sitl.add_argument("--gcs-port", type=int, default=14550, help="UDP port the units send GCS traffic to (QGC, MAVProxy)")
    sitl.add_argument("--api-port", type=int, default=14540, help="API port of unit index 0 (MAVSDK); unit i uses this + i")
    from mars_link.mavlink.signing import add_signing_args

    add_signing_args(sitl, "the coordinator <-> unit links, signed both ways, and the client links")
    sitl.add_argument("--any-bind", action="store_true",
                      help="bind the units' client sockets to free ports instead of PX4's 18570+i / 14580+i")
    from mars_link.processes.vehicle_host import DEFAULT_VEHICLE_API_PORT, DEFAULT_VEHICLE_SYSID

    sitl.add_argument("--vehicle", action="store_true",
                      help="the docked assembly as ONE MAVLink vehicle (served by the coordinator; arm, takeoff, "
                           "offboard, land from MAVSDK/QGC); runs in real time until Ctrl-C")
    sitl.add_argument("--vehicle-sysid", type=int, default=DEFAULT_VEHICLE_SYSID,
                      help=f"with --vehicle: its MAVLink system id (default {DEFAULT_VEHICLE_SYSID})")
    sitl.add_argument("--vehicle-api-port", type=int, default=DEFAULT_VEHICLE_API_PORT,
                      help=f"with --vehicle: MAVSDK's port (default {DEFAULT_VEHICLE_API_PORT}: udpin://127.0.0.1:"
                           f"{DEFAULT_VEHICLE_API_PORT})")
    sitl.add_argument("--vehicle-gcs-port", type=int, default=None,
                      help="with --vehicle: its ground-station port (default: --gcs-port, 14550)")
    sitl.add_argument("--map", default=None, metavar="FILE",
                      help="with --vehicle: obstacle map (boxes .csv or .pcd); mission legs planned around it")
    sitl.set_defaults(func=cmd_sitl)
    add_view_arguments(sitl)  # --no-mcap, --foxglove [HOST:PORT] (served by the world process)
    from mars_link.processes.sitl_mode import add_sitl_up_arguments

    add_sitl_up_arguments(sitl)  # --transport zenoh|udp and its options (mars_link.processes.sitl_mode)

    coord = sub.add_parser("coordinator", help="the coordinator process alone, attaching to running units")
    add_coordinator_arguments(coord)

    def checked_coordinator(args) -> int:  # the shared checks first (endpoints, --out)
        v.check_link_endpoints(args)
        v.check_out_dir(args.out)
        return cmd_coordinator(args)

    coord.set_defaults(func=checked_coordinator)

    veh = sub.add_parser("vehicle", help="the assembly as one MAVLink vehicle in real time (MAVSDK, MAVProxy, QGC)")
    from mars_link.processes.realtime import add_arguments

    add_arguments(veh)
    veh.set_defaults(func=cmd_vehicle)

    sub.add_parser("plan", help="plan MAP --layout ROWS --start N,E,D --goal N,E,D [--method ours|svsdf] --out DIR")
    sub.add_parser("reconfig", help="reconfig plan SCENARIO.toml [--fault ...] [--json]: paper 001 reconfiguration plan")

    rep = sub.add_parser("reproduce", help="reproduce a paper table (table1: paper 000 Table I + Fig. 3)")
    rep.add_argument("what", help="table1")
    rep.add_argument("--seeds", type=v.bounded_int(1, 10_000), default=10)
    rep.add_argument("--controllers", default="mars-ftcc-paper,cascaded")
    rep.add_argument("--modes", help="cascaded FTC modes, comma-separated (default: all)")
    rep.add_argument("--duration", type=v.positive_float, help="shorten every flight [s] (quick look)")
    rep.add_argument("--out", default="runs/table1")
    rep.add_argument("--quiet", action="store_true")
    from mars_link.apps.sweep_pool import add_pool_arguments

    add_pool_arguments(rep)  # --workers / --scheduler: the flights go through the sweep's executor
    rep.set_defaults(func=cmd_reproduce)

    from mars_link.apps.sweep_cli import add_arguments as add_sweep_arguments

    swp = sub.add_parser("sweep", help="many flights of a scenario over seeds, random faults and parameters, "
                                       "on local cores or a Dask cluster (mars_link.apps.sweep)")
    add_sweep_arguments(swp)
    swp.set_defaults(func=cmd_sweep)
    return parser


def main(argv: list[str] | None = None) -> int:
    from mars_link.processes.parent_watch import hear_stop_signals

    hear_stop_signals()  # Ctrl-C stops every command, whatever mask the parent left
    argv = sys.argv[1:] if argv is None else argv
    if argv[:2] == ["reconfig", "plan"]:  # its own parser and exit codes (0 plan, 1 none feasible, 2 bad input)
        from mars_link.apps.reconfig_cli import reconfig_plan_command

        return reconfig_plan_command(argv[2:])
    if argv[:1] == ["plan"]:  # collision-free planning: its own parser (0 plan, 1 none found, 2 bad input)
        from mars_link.apps.plan_cli import plan_command

        return plan_command(argv[1:])
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help()
            return EXIT_USAGE
        return args.func(args)
    except KeyboardInterrupt:
        print("mars-link: interrupted", file=sys.stderr)
        return 130
    except (UserInputError, v.EnvironmentFailure, OSError) as exc:  # OSError: an unexpected disk/port refusal
        line, code = v.report(exc)
        print(line, file=sys.stderr)
        return code
    except Exception as exc:  # a Zenoh session that cannot open (port taken): one line, exit 1
        if type(exc).__module__.split(".")[0] != "zenoh":
            raise
        line, code = v.report(exc)
        print(line, file=sys.stderr)
        return code
    finally:
        v.release_out_dirs()


if __name__ == "__main__":
    sys.exit(main())
