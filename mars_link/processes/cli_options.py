"""The product's command-line options, one definition each: the option groups `mars-link`'s subcommands share
(mars_link.apps.cli builds its tree from them) and the option sets of the entry points users do not type as
`mars-link ...`, which keep a parser of their own built from these: the SITL process roles the launcher
starts (`python -m mars_link.processes.lockstep ROLE`), the lone-unit runner (`python -m
mars_link.processes.udp_runner`) and the Foxglove probe (`python -m mars_link.apps.foxglove_probe`).

Why here and not beside the CLI in apps: the process mains sit on the processes' floor, below the apps, and
may only import from it or below (pyproject.toml, [tool.importlinter]).
"""

from __future__ import annotations

from mars_link.core import validation as v
from mars_link.flight.flight_view import DEFAULT_LIVE
from mars_link.flight.plots import PLOT_FORMATS, PNG_DPI
from mars_link.mavlink.signing import DEFAULT_KEY_ENV
from mars_link.processes.ports import GCS_PORT
from mars_link.transport import TRANSPORTS, UNIT_INTERFACES


# ----------------------------------------------------------------------------- shared by the subcommands
def add_scenario(p, default: str, why: str = "") -> None:
    p.add_argument("scenario", nargs="?", help=f"scenario TOML file or bundled name (default {default}{why})")


def add_out(p, default_text: str, force: bool = True) -> None:
    p.add_argument("--out", default=None, metavar="DIR",
                   help=f"run directory (default {default_text})" + ("; must be empty unless --force" if force else ""))
    if force:
        p.add_argument("--force", action="store_true", help="clear a non-empty --out first")


def add_seed(p, what: str = "the flight's random seed (default: the scenario's [sim] seed)") -> None:
    p.add_argument("--seed", type=v.seed, default=None, help=f"{what}; 0..{v.SEED_MAX}")


def add_duration(p, what: str) -> None:
    p.add_argument("--duration", type=v.positive_float, default=None, metavar="SECONDS",
                   help=f"{what} [simulated s]")


def add_plot_format(p) -> None:
    p.add_argument("--plot-format", choices=PLOT_FORMATS, default="png",
                   help=f"plots/ as PNG ({PNG_DPI} dpi) or vector PDF/SVG for a paper (default png)")


def add_quiet(p) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress lines")


def add_layout(p, what: str, required: bool = False) -> None:
    p.add_argument("--layout", default=None, required=required, metavar="ROWS",
                   help=f"layout rows separated by commas, e.g. XXX,XXX ({what})")


def add_fault(p, when: str = "T: simulated seconds after the start") -> None:
    p.add_argument("--fault", action="append", default=[], metavar="UNIT[:ROTOR]=ETA[@T]",
                   help=f"add a rotor (or whole-unit) failure: ETA is the remaining effectiveness 0..1, rotors 1..4 = "
                        f"FR, FL, RL, RR; {when}; repeatable")


def add_flight_overrides(p) -> None:
    """What `run` and `vehicle` may override in the scenario."""
    p.add_argument("--ftc", default=None, help="allocation mode: none, unit, partial, full, hybrid, qp "
                   "(default: the scenario's [control] ftc)")
    add_fault(p)
    p.add_argument("--no-noise", action="store_true", help="perfect sensors (the estimator gets the truth state)")


def add_view(p, where: str = "") -> None:
    """--no-mcap, --foxglove [HOST:PORT] (mars_link.flight.flight_view)."""
    p.add_argument("--no-mcap", action="store_true", help="write no run.mcap")
    p.add_argument("--foxglove", nargs="?", const=DEFAULT_LIVE, default=None, metavar="HOST:PORT",
                   help=f"live Foxglove view{where}: Foxglove's WebSocket server (without a value {DEFAULT_LIVE}); "
                        "open it in Foxglove with 'Open connection' -> Foxglove WebSocket")


def add_link(p, roles: str, process: bool = False) -> None:
    """The transport of the SITL processes' links and its endpoints. One default everywhere: Zenoh, the
    product's bus (`--transport udp`: plain loopback sockets, no Zenoh). `process`: the parser of a SITL
    process, which reads what its launcher hands it (`LinkSpec.to_args`): the Zenoh mode of its role and the
    run's TLS directory; whether the bus is open and where the run's secrets go are the launcher's choices."""
    p.add_argument("--transport", choices=TRANSPORTS, default="udp" if process else "zenoh",
                   help=f"the links between {roles}: zenoh (the product's bus) or udp (loopback sockets)")
    p.add_argument("--fleet", default="default", help="Zenoh key prefix mars/<fleet>/...")
    p.add_argument("--zenoh-connect", action="append", default=[] if process else None, metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; default: peers on 127.0.0.1)")
    p.add_argument("--zenoh-listen", action="append", default=[] if process else None, metavar="ENDPOINT",
                   help="extra Zenoh router endpoint to listen on (repeatable)")
    p.add_argument("--link-profile", default=None, metavar="PROFILE",
                   help="ideal | lan | wifi | radio57600 [,key=value...]: delays and losses on the coordinator <-> "
                        "unit links (zenoh only; default: none)")
    p.add_argument("--unit-interface", choices=UNIT_INTERFACES, default=None,
                   help="how the units are commanded: mavlink (SET_ACTUATOR_CONTROL_TARGET) or px4-zenoh (PX4 "
                        "v1.17's OffboardControlMode + ActuatorMotors over rmw_zenoh, /px4_<unit id>/fmu/...; needs "
                        "--transport zenoh); default: the scenario's [units] interface")
    if process:
        p.add_argument("--zenoh-mode", choices=("peer", "client", "router"), default="client",
                       help="this process's Zenoh session (the launcher gives each role its own)")
        p.add_argument("--tls-dir", default=None,
                       help="the run's CA, certificates and access-control list (mars_link.transport.tls)")
    else:
        p.add_argument("--insecure", action="store_true",
                       help="an open Zenoh bus: plain TCP, no TLS, no access control (for tools that cannot do TLS; "
                            "anyone who reaches the ports reads every key; the run's own links stay MAVLink-signed, "
                            "see the threat model in the docs)")
    p.add_argument("--tls-ca", default=None, metavar="FILE",
                   help="several hosts: the fleet's CA certificate (PEM); with --tls-cert and --tls-key, instead of "
                        "the per-run CA (mutual TLS, no per-role access control)")
    p.add_argument("--tls-cert", default=None, metavar="FILE", help="this host's certificate (PEM), signed by --tls-ca")
    p.add_argument("--tls-key", default=None, metavar="FILE", help="the private key of --tls-cert (PEM)")
    if not process:
        p.add_argument("--save-certs", action="store_true",
                       help="keep a copy of the run's secrets in RUN_DIR/certs (mode 0700/0600): its CA, certificates "
                            "and access-control list, and its per-run MAVLink signing key (default: they live in a "
                            "private directory removed at exit)")


def add_sitl_processes(p, realtime_help: str) -> None:
    """How the SITL processes run: units per process and wall-clock pacing."""
    p.add_argument("--units-per-process", type=v.bounded_int(1, 199), default=1, metavar="K",
                   help="host up to K unit firmwares per process (each its own MAVLink system and links)")
    p.add_argument("--realtime", action="store_true", help=realtime_help)


def add_client_ports(p, api_port: int, api_help: str) -> None:
    """The UDP ports the MAVLink clients listen on (PX4's SITL conventions)."""
    p.add_argument("--gcs-port", type=int, default=GCS_PORT,
                   help="UDP port ground stations listen on (QGroundControl, MAVProxy `udpin`)")
    p.add_argument("--api-port", type=int, default=api_port, help=api_help)


def add_signing(p, links: str, otherwise: str = "unsigned") -> None:
    p.add_argument("--signing-key-file", default=None, metavar="FILE",
                   help=f"MAVLink signing key for {links} (default: ${DEFAULT_KEY_ENV}, else {otherwise}); one key "
                        "per process, each link signs with its own link id")
    p.add_argument("--require-signing", "--sign-client-links", dest="require_signing", action="store_true",
                   help="every link requires signing: unsigned GCS/API clients may only read (telemetry, "
                        "parameters, mission download); the coordinator link drops unsigned frames")


def add_pool(p) -> None:
    """--workers / --scheduler: flights go through the sweep's executor (mars_link.apps.sweep_pool)."""
    p.add_argument("--workers", "--jobs", type=v.bounded_int(1, 4096), default=None,
                   help="local worker processes flying at once (default: every core)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="fly on the Dask cluster of this scheduler (tcp://HOST:PORT) instead (default: local)")


def add_run_ports(p, where: str = "") -> None:
    """The UDP ports of a running SITL's world (HIL) and coordinator (telemetry): what its processes are handed,
    and what a coordinator attaching to a running `sitl up` is told."""
    p.add_argument("--world-port", type=int, default=0, help=f"udp: the world's HIL port{where}")
    p.add_argument("--coordinator-port", type=int, default=0, help=f"udp: the port units send telemetry to{where}")


def add_params(p) -> None:
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="start-up parameter value")


def add_map(p, what: str) -> None:
    p.add_argument("--map", default=None, metavar="FILE",
                   help=f"obstacle map (boxes .csv or .pcd): mission legs planned around it ({what})")


# ----------------------------------------------------------------------------- the internal entry points
def add_lockstep_options(p) -> None:
    """`python -m mars_link.processes.lockstep ROLE SCENARIO ...`: what the launcher hands a SITL process."""
    p.add_argument("role", choices=("world", "unit", "coordinator"))
    p.add_argument("scenario", help="scenario file or bundled name; - for built-in defaults")
    p.add_argument("--units", type=int, default=None)
    p.add_argument("--layout", default=None)
    p.add_argument("--unit", default="1", help="unit id, or ids a,b,c: several units in this process")
    p.add_argument("--steps", type=int, default=None, help="exchanges of a docked run (else from the scenario)")
    p.add_argument("--start-pose", default=None, help="world: N,E,D,YAW of the assembly's CoM (else from the scenario)")
    p.add_argument("--position-every", type=int, default=None, help="world: mocap samples every n-th exchange")
    add_run_ports(p)
    p.add_argument("--world-fd", type=int, default=None, help="inherited bound socket of the world")
    p.add_argument("--coordinator-fd", type=int, default=None, help="inherited bound socket of the coordinator")
    p.add_argument("--out", required=True)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--speed", type=float, default=None, help="world pacing, x real time (0: as fast as possible)")
    add_signing(p, "the coordinator <-> unit links")
    p.add_argument("--run-key", action="store_true",
                   help="the key is the run's own, for its internal links only: the client links keep the rules "
                        "of a vehicle without a key")
    p.add_argument("--gcs-port", type=int, default=GCS_PORT)
    p.add_argument("--api-port", default=None, help="the unit's API port, or one per unit of --unit a,b,c")
    p.add_argument("--gcs-bind", type=int, default=None)
    p.add_argument("--api-bind", type=int, default=None)
    p.add_argument("--no-clients", action="store_true", help="unit: no GCS/API client links (a closed batch run)")
    p.add_argument("--forever", action="store_true", help="docked: run until stopped (ignores --steps)")
    p.add_argument("--external-offboard", action="store_true",
                   help="world, unit: no coordinator in this run; an off-board computer outside it drives the units "
                        "(the units answer each step with what they drive; run --mode sitl --external-offboard)")
    p.add_argument("--vehicle", action="store_true", help="coordinator: serve the assembly as one MAVLink vehicle")
    p.add_argument("--sched-realtime", action="store_true",
                   help="real time: SCHED_FIFO when permitted; else world/unit SCHED_BATCH (mars_link.runtime.scheduling)")
    p.add_argument("--timing-log", action="store_true",
                   help="coordinator: each step's wall-clock times (coordinator_timing.csv)")
    p.add_argument("--mcap", action="store_true", help="world: run.mcap in --out (mars_link.flight.flight_view)")
    p.add_argument("--foxglove", default=None, metavar="HOST:PORT", help="world: the live Foxglove view there")
    p.add_argument("--view-feed", action="store_true",
                   help="coordinator: send the world its estimate, reference and events for the view "
                        "(mars_link.processes.view_feed)")
    p.add_argument("--vehicle-sysid", type=int, default=None)
    p.add_argument("--vehicle-gcs-port", type=int, default=None)
    p.add_argument("--vehicle-map", default=None, help="coordinator --vehicle: obstacle map for the mission legs")
    p.add_argument("--vehicle-api-port", type=int, default=None)
    p.add_argument("--vehicle-gcs-bind", type=int, default=None)
    p.add_argument("--vehicle-api-bind", type=int, default=None)
    add_link(p, "this process and the others of its run", process=True)
    p.add_argument("--command-age", action="store_true",
                   help="unit: log the command age at the motor (command_age_unit<id>.csv/.json; real-time runs)")


def add_unit_runner_options(p) -> None:
    """`python -m mars_link.processes.udp_runner`: one unit flying itself in real time, its links on UDP."""
    p.add_argument("--unit", type=v.bounded_int(1, 250), default=1, help="unit id = MAVLink system id (1..250)")
    p.add_argument("--preset", default="mars-ftcc", help="vehicle preset (mars-ftcc, modquad-cf2)")
    p.add_argument("--gcs-port", type=v.port, default=GCS_PORT)
    p.add_argument("--gcs-bind", type=v.port_or_zero, default=None, help="default 18570 + unit - 1")
    p.add_argument("--api-port", type=v.port, default=None, help="default 14540 + unit - 1")
    p.add_argument("--api-bind", type=v.port_or_zero, default=None, help="default 14580 + unit - 1")
    p.add_argument("--coord-bind", type=v.port_or_zero, default=None, help="default 14600 + unit - 1")
    p.add_argument("--coordinator-sysid", type=v.bounded_int(1, 255), default=201)
    p.add_argument("--coordinator-compid", type=v.bounded_int(0, 255), default=1)
    add_signing(p, "the coordinator link (with a key it requires signing) and gcs/api")
    p.add_argument("--physics-hz", type=v.positive_float, default=500.0)
    p.add_argument("--control-hz", type=v.positive_float, default=100.0)
    p.add_argument("--speed", type=v.positive_float, default=1.0, help="simulation speed, x real time")
    p.add_argument("--north", type=v.finite_float, default=0.0, help="start position, m north of the origin")
    p.add_argument("--east", type=v.finite_float, default=0.0)
    p.add_argument("--yaw-deg", type=v.finite_float, default=0.0)
    add_params(p)
    p.add_argument("--status-file", default=None)
    p.add_argument("--duration", type=v.positive_float, default=None, help="stop after this many wall seconds")
    p.add_argument("--tlog", default=None, help="MAVLink log of the client links (.tlog), served by LOG_* download")


def add_foxglove_probe_options(p) -> None:
    """`python -m mars_link.apps.foxglove_probe [URL]`: what a Foxglove server sends, topic by topic."""
    p.add_argument("url", nargs="?", default=f"ws://{DEFAULT_LIVE}")
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--topics", default=None, help="comma-separated (default: all advertised)")
