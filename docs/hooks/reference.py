"""mkdocs hook: the reference pages, generated from the code inside every build so they cannot drift.

* reference/scenario.md: every key the scenario loader accepts. There is no single schema object: the loader
  checks each table against its own key set (mars_link.config.scenario and the modules it calls), so the page is
  built from those same key sets, with the defaults of the dataclasses the loader fills in, the value sets it
  checks against, and the unit read off the key's suffix.
* reference/cli.md: every subcommand and option, by walking `mars_link.apps.cli.build_parser()` (and the own
  parsers of the subcommands that parse their arguments themselves).
* reference/mavlink.md: what the unit firmware (firmware_models) handles: messages, commands, modes,
  parameters, streams.
* reference/outputs.md: the files of a run directory, from a real 3-second flight of `hover_1x1` made during
  the build: summary.json's fields, the CSV columns, the MCAP channels with the rates measured in that file.

`python docs/hooks/reference.py DIR` writes the four pages into DIR (to read them without mkdocs).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import inspect
import io
import json
import re
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

PAGES = ("reference/scenario.md", "reference/cli.md", "reference/mavlink.md", "reference/outputs.md")

#: unit of a key by its suffix (the project names SI units in its keys: `thrust_n`, `duration_s`)
SUFFIX_UNITS = (("_per_sqrt_s", "m/√s"), ("_mps2", "m/s²"), ("_mps", "m/s"), ("_radps", "rad/s"), ("_hz", "Hz"), ("_deg", "deg"),
                ("_m2", "m²"), ("_m", "m"), ("_s", "s"), ("_n", "N"), ("_ah", "Ah"), ("_ohm", "ohm"),
                ("_thr", "fraction"), ("_soc", "fraction"), ("_share", "fraction"))


def unit_of(key: str) -> str:
    if key in ("t", "redock_t"):
        return "s"
    if key == "T":
        return "s"
    for suffix, unit in SUFFIX_UNITS:
        if key.endswith(suffix):
            return unit
    return ""


def type_of(value) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "float"
    if isinstance(value, str):
        return "string"
    if isinstance(value, (list, tuple)):
        return "array"
    if isinstance(value, dict):
        return "table"
    return "—" if value is None else type(value).__name__


def shown(value) -> str:
    if value is None or value is inspect.Parameter.empty:
        return "—"
    if isinstance(value, (tuple, list)):
        return "`" + json.dumps([shown_plain(v) for v in value]) + "`"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, str):
        return f'`"{value}"`'
    if isinstance(value, float):
        return f"`{value:g}`"
    return f"`{value}`"


def shown_plain(v):
    return list(v) if isinstance(v, tuple) else v


def cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def table(head: list[str], rows: list[list]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(cell(c) for c in row) + " |" for row in rows]
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------- scenario keys
def scenario_sections() -> list[tuple[str, str, list[tuple[str, str, str, str, str, str]]]]:
    """(section, what, rows of (key, type, unit, default, allowed, notes)), from the loader's own key sets."""
    from mars_link.models import battery
    from mars_link.config import scenario as S, scenario_environment as E, scenario_sensor_faults as SF
    from mars_link.models import trajectories as T
    from mars_link.core.assembly import PRESETS
    from mars_link.models.environment import SEVERITIES, TURBULENCE_MODELS, EnvironmentParams
    from mars_link.models.sensor_profiles import GPS_FIGURES, PROFILES
    from firmware_models.sensor_failures import BASE_SENSORS, FAILURE_TYPES

    base = S.Scenario(name="x")
    sim = S.SimSpec()
    sections = []

    def row(key, default, allowed="", notes="", typ=None):
        return (f"`{key}`", typ or type_of(default), unit_of(key), shown(default), allowed, notes)

    top_notes = {"name": "default: the file's name", "vehicle": "table", "assembly": "table", "trajectory": "table",
                 "control": "table", "faults": "array of tables", "sim": "table", "reconfig": "table",
                 "docking": "table", "separations": "array of tables", "environment": "table", "sensors": "table",
                 "mission": "table", "battery": "table", "sensor_faults": "array of tables", "units": "table"}
    sections.append(("top level", "The tables and the name a scenario file may hold (mars_link.config.scenario._TOP_KEYS).",
                     [(f"`{k}`", "string" if k == "name" else
                       ("array of tables" if "array" in top_notes.get(k, "") else "table"), "", "—", "",
                       top_notes.get(k, "") if k == "name" else "")
                      for k in sorted(S._TOP_KEYS)]))

    from mars_link.core.assembly import vehicle_preset

    vp = vehicle_preset(S.DEFAULT_PRESET)
    vrows = [row("preset", S.DEFAULT_PRESET, ", ".join(f"`{p}`" for p in sorted(PRESETS)),
                 "a file naming no preset flies the realistic plant")]
    for key in sorted(S._VEHICLE_KEYS - {"preset"}):
        shown_default = None if key == "rotor_drag_coeff" else getattr(vp, key, None)  # (drag: when it is on)
        vrows.append(row(key, shown_default, "", f"default: the preset's (shown: {S.DEFAULT_PRESET})",
                         typ="float"))
    vrows.append(row("drag", None, "`true`, `false`", "default: on when [environment] moves the air", typ="bool"))
    vrows.append(row("drag_area_frd_m2", None, "3 numbers >= 0",
                     "body Cd·A per unit along x, y, z; default: the preset's when drag is on", typ="array"))
    assert {k for k in S._AERO_KEYS} <= {"drag", "drag_area_frd_m2"}
    sections.append(("[vehicle]", "The airframe: a preset and its overrides.", vrows))

    sections.append(("[assembly]", "Which units, how they sit, what is tracked.", [
        row("layout", list(base.layout), "rows of `X` (unit) and `.` (empty)", "first row = front; unit ids row-major"),
        row("tracked", base.tracked, "`com`, `unit:N`", "the point whose error is measured"),
        row("start", base.start, "`docked`, `free`", "free: units apart on the ground, assembled in the air"),
        row("free_spacing_m", base.free_spacing_m, "> unit pitch + 0.3 m", "start = free: centre distance"),
    ]))
    assert {"layout", "tracked", "start", "free_spacing_m"} == S._ASSEMBLY_KEYS

    sections.append(("[control]", "Controller and allocation.", [
        row("controller", base.controller, ", ".join(f"`{c}`" for c in S.CONTROLLERS)),
        row("ftc", base.ftc, ", ".join(f"`{m}`" for m in S.FTC_MODES),
            "default `qp` on the realistic plant (no preset named), else `none`"),
        row("faults_known", base.faults_known, "`true`, `false`", "false: the coordinator must detect the faults"),
    ]))
    sections.append(("[[faults]]", "Rotor faults: eta scales a rotor's thrust and torque.", [
        row("unit", None, "a unit id of the layout", "required", typ="int"),
        row("rotor", None, "1..4 (FR, FL, RL, RR)", "absent: all four rotors", typ="int"),
        row("eta", None, "0..1", "required for kind eta (else default 0); 0 = dead", typ="float"),
        row("t", 0.0, ">= 0", "when (simulated time)"),
        row("kind", "eta", ", ".join(f"`{k}`" for k in S.FAULT_KINDS),
            "what the ESC telemetry sees (mars_link.models.esc): eta a damaged propeller (RPM as commanded, "
            "current x eta), prop-loss (the motor runs unloaded, faster), motor-stop (RPM and current fall; eta 0)"),
    ]))
    assert S._FAULT_KEYS == {"t", "unit", "rotor", "eta", "kind"}
    sections.append(("[sim]", "Rates, duration, seed, noise.", [
        row("duration_s", sim.duration_s, f"> 0, <= {S.MAX_DURATION_S:g}", "absent: the trajectory's duration",
            typ="float"),
        row("physics_hz", sim.physics_hz, f"> 0, <= {S.MAX_PHYSICS_HZ:g}, a whole multiple of control_hz"),
        row("control_hz", sim.control_hz, "> 0"),
        row("seed", sim.seed, "0..2^32-1"),
        row("noise", sim.noise, "`true`, `false`", "false: perfect sensors"),
    ]))
    assert S._UNITS_KEYS == {"interface"}
    sections.append(("[units]", "How the coordinator commands the units (CLI `--unit-interface` overrides it).", [
        row("interface", S.Scenario(name="").unit_interface, ", ".join(f"`{i}`" for i in S.UNIT_INTERFACES),
            "mavlink: SET_ACTUATOR_CONTROL_TARGET; px4-zenoh: PX4 v1.17's OffboardControlMode + ActuatorMotors "
            "over rmw_zenoh (SITL needs `--transport zenoh`)"),
    ]))

    kinds = []
    for kind, (cls, schema, required) in T._KINDS.items():
        try:
            params = inspect.signature(cls.__init__).parameters
        except (TypeError, ValueError):
            params = {}
        for key, typ in schema.items():
            default = params[key].default if key in params else None
            note = "required" if key in required else ""
            kinds.append((f"`{key}`", {float: "float", list: "array", str: "string"}.get(typ, typ.__name__),
                          unit_of(key), shown(default), f"kind `{kind}`", note))
    sections.append(("[trajectory]", "What to fly: `kind` and that kind's keys (mars_link.models.trajectories._KINDS). "
                     "`kind = \"plan\"` plans around a map first; its `map` names a file or a bundled map "
                     "(`paper000_walls.csv`).",
                     [row("kind", base.trajectory["kind"], ", ".join(f"`{k}`" for k in T._KINDS))] + kinds))

    rdefaults = {}
    try:
        from mars_link.reconfig.execution import ExecutionParams

        rdefaults = {f.name: f.default for f in dataclasses.fields(ExecutionParams)}
    except Exception:  # (the executor's parameters moved: the keys stay listed)
        pass
    rrows = [row("enabled", False, "`true`, `false`"), row("moves", True, "`true`, `false`",
             "no plan found: fly the best single move"), row("ground", True, "`true`, `false`",
             "no move either: land and rebuild on the ground"),
             row("objective", "force", "`force`, `margin`", "what the target maximises: paper 001's force objective "
                 "or the worst-stage controllability margin (MARS-Reconfig); plans report both", typ="string"),
             row("target", None, "each unit id once, row-major", "plan to this allocation", typ="array")]
    for key in sorted(S._RECONFIG_NUMBERS):
        rrows.append(row(key, rdefaults.get(key), ">= 0" if key in ("at_s", "trigger_delay_s", "altitude_step_m")
                         else "> 0", typ="float"))
    sections.append(("[reconfig]", "Self-reconfiguration after faults (paper 001) and its executor.", rrows))

    dock_defaults = {"position_m": 0.02, "speed_mps": 0.05, "yaw_deg": 2.0, "tilt_deg": 3.0}
    try:
        from sitl.docking import DockTolerance

        dock_defaults = {f.name: f.default for f in dataclasses.fields(DockTolerance)
                         if f.name in S.DOCKING_RANGES} or dock_defaults
    except Exception:
        pass
    sections.append(("[docking]", "When facing latches close.", [
        row(k, dock_defaults.get(k), f"({lo:g}, {hi:g}]", typ="float") for k, (lo, hi) in S.DOCKING_RANGES.items()]))
    sections.append(("[[separations]]", "Commanded separations: a piece leaves and (optionally) docks back.", [
        row("t", None, ">= 0", "required", typ="float"),
        row("units", None, "unit ids, not all", "required", typ="array"),
        row("redock_t", None, "> t", "absent: never", typ="float"),
    ]))
    assert S._SEPARATION_KEYS == {"t", "units", "redock_t"}

    env = EnvironmentParams()
    sections.append(("[environment]", "Wind, turbulence and gusts (JSBSim's atmosphere).", [
        row("wind_ned_mps", [0.0, 0.0, 0.0], "3 numbers", "steady wind, NED (blowing towards)"),
        row("turbulence", "none", ", ".join(f"`{s}`" for s in SEVERITIES) + ", or W20 in m/s",
            "string or float"),
        row("turbulence_model", getattr(env, "turbulence_model", "milspec"), ", ".join(f"`{m}`" for m in TURBULENCE_MODELS)),
        row("gusts", [], "array of tables (below)", "one 1-cosine gust at a time"),
    ]))
    assert E._ENV_KEYS == {"wind_ned_mps", "turbulence", "turbulence_model", "gusts"}
    sections.append(("[[environment.gusts]]", "One 1-cosine gust.", [
        row("t", None, ">= 0", "required", typ="float"), row("duration_s", None, "> 0", "required; rise and fall",
                                                                typ="float"),
        row("ned_mps", None, "3 numbers, not all 0", "required", typ="array"), row("hold_s", 0.0, ">= 0"),
    ]))
    srows = [row("profile", "mocap", ", ".join(f"`{p}`" for p in PROFILES))]
    seen = set()
    for pname, profile in PROFILES.items():
        for key, value in profile.figures.items():
            if key in seen:
                continue
            seen.add(key)
            gps_only = key in GPS_FIGURES
            default = PROFILES["gps" if gps_only else "mocap"].figures.get(key, value)
            srows.append(row(key, default, ">= 0" if key != "mag_declination_deg" else "-180..180",
                             ("gps profile only; " if gps_only else "") + "default: the profile's (shown: "
                             + ("gps" if gps_only else "mocap") + ")"))
    srows.append(row("esc_telemetry", True, "`true`, `false`",
                     "the units' ESCs report RPM and current (ESC_STATUS, 50 Hz); false: fly without it"))
    sections.append(("[sensors]", "The position sensor profile and its figures, and the ESC telemetry.", srows))

    pack = battery.PackParams()
    brows = [row("enabled", None, "`true`, `false`", "default: on for the realistic plant or when the table has keys",
                 typ="bool")]
    for key in sorted(battery._PACK_KEYS):
        brows.append(row(key, getattr(pack, key, None), "", "default: the preset's pack (shown: 4S 2.2 Ah)"))
    for key, name in sorted(battery._FAILSAFE_KEYS.items()):
        brows.append(row(key, battery.FAILSAFE_DEFAULTS[name], "0, 2, 3" if name == "COM_LOW_BAT_ACT" else "0..0.5",
                         f"the units' PX4 parameter {name}"))
    brows.append(row("units", [], "array of tables: `unit` and any pack key", "per-unit packs ([[battery.units]])"))
    sections.append(("[battery]", "The units' packs and the low-battery failsafe.", brows))
    sections.append(("[mission]", "The assembly vehicle's mission legs.", [
        row("map", None, "a boxes `.csv` or `.pcd` file, or a bundled map", "legs planned around it", typ="string")]))
    sections.append(("[[sensor_faults]]", "Sensor failures on a schedule, in the units' firmware.", [
        row("t", None, ">= 0", "required", typ="float"),
        row("sensor", None, ", ".join(f"`{s}`" for s in (*BASE_SENSORS, "baro", "mag", "esc")), "required", typ="string"),
        row("type", None, ", ".join(f"`{t}`" for t in FAILURE_TYPES), "required (esc: ok, off, stuck)", typ="string"),
        row("unit", None, "a unit id", "absent: every unit", typ="int"),
        row("duration_s", None, "> 0", "absent: for good", typ="float"),
    ]))
    assert SF.KEYS == {"t", "sensor", "type", "unit", "duration_s"}
    return sections


def scenario_keys_accepted() -> set[str]:
    """Every key name the loader accepts, from its own key sets (what tests/apps/test_docs.py checks the page for)."""
    from mars_link.models import battery
    from mars_link.config import scenario as S, scenario_environment as E, scenario_sensor_faults as SF
    from mars_link.models import trajectories as T
    from mars_link.models.sensor_profiles import PROFILES

    keys = set(S._TOP_KEYS) | S._VEHICLE_KEYS | S._AERO_KEYS | S._ASSEMBLY_KEYS | S._CONTROL_KEYS | S._FAULT_KEYS
    keys |= S._SIM_KEYS | S._UNITS_KEYS | S._RECONFIG_NUMBERS | {"enabled", "target", "moves", "ground", "objective"} | set(S.DOCKING_RANGES)
    keys |= S._SEPARATION_KEYS | E._ENV_KEYS | E._GUST_KEYS | {"profile"} | battery._PACK_KEYS
    keys |= set(battery._FAILSAFE_KEYS) | {"units", "unit", "map", "kind"} | SF.KEYS
    keys |= {k for p in PROFILES.values() for k in p.figures} | {"esc_telemetry"}
    keys |= {k for _, schema, _ in T._KINDS.values() for k in schema}
    return keys


def scenario_page() -> str:
    from mars_link.config.scenario import bundled_scenarios

    out = ["# Scenario files (TOML)\n",
           "Generated from the loader (`mars_link/config/scenario.py` and the modules it calls) at every build. There is "
           "no single schema object: each table is checked against its own key set, and this page is built from "
           "those key sets, the defaults of the dataclasses the loader fills in, and the value sets it checks "
           "against. Units follow the key's suffix (`_s` seconds, `_m` metres, `_mps` m/s, `_hz`, `_deg`). An "
           "unknown key, a wrong type or a value out of range is one line on stderr naming the file and the key, "
           "exit code 2.\n",
           "A scenario is named by path or by the name of a bundled one (`mars-link scenarios`); the bundled "
           "files are package data, found from any directory.\n"]
    for section, what, rows in scenario_sections():
        out.append(f"## {section}\n\n{what}\n")
        out.append(table(["key", "type", "unit", "default", "allowed", "notes"], [list(r) for r in rows]))
    out.append("## Bundled scenarios\n")
    out.append(table(["name", "description"], [[f"`{s['name']}`", s["description"]] for s in bundled_scenarios()]))
    return "\n".join(out)


# ----------------------------------------------------------------------------- CLI
def _option_rows(parser: argparse.ArgumentParser) -> list[list[str]]:
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        name = ", ".join(f"`{o}`" for o in action.option_strings) or f"`{action.dest}` (positional)"
        if action.metavar and action.option_strings:
            name += f" `{action.metavar if isinstance(action.metavar, str) else ' '.join(action.metavar)}`"
        typ = getattr(action.type, "__name__", "") if action.type else ""
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            typ = "flag"
        elif isinstance(action, argparse._AppendAction):
            typ = (typ + ", " if typ else "") + "repeatable"
        default = action.default
        shown_default = "—" if default in (None, argparse.SUPPRESS) or isinstance(
            action, argparse._StoreTrueAction) else f"`{default}`"
        choices = ", ".join(f"`{c}`" for c in action.choices) if action.choices else ""
        help_text = (action.help or "") % {"default": default, "prog": parser.prog} if action.help and "%(" in action.help \
            else (action.help or "")
        rows.append([name, typ, shown_default, choices, help_text])
    return rows


def walk_parsers(parser: argparse.ArgumentParser, prefix: str = "mars-link"):
    """(command path, parser, help) for the parser and every subparser under it, depth first."""
    yield prefix, parser, parser.description or ""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                for path, p, h in walk_parsers(sub, f"{prefix} {name}"):
                    yield path, p, h if path != f"{prefix} {name}" else (helps.get(name) or sub.description or "")


def cli_page() -> str:
    from mars_link.apps.cli import build_parser

    out = ["# Command line\n",
           "Generated at every build by walking `mars_link.apps.cli.build_parser()`. Exit codes: 0 done, 1 a flight "
           "diverged or the machine refused (disk, port), 2 bad input (one line on stderr).\n"]
    for path, parser, help_text in walk_parsers(build_parser()):
        rows = _option_rows(parser)
        out.append(f"## `{path}`\n\n{help_text}\n")
        out.append(f"```text\n{parser.format_usage().strip()}\n```\n")
        if rows:
            out.append(table(["option", "type", "default", "choices", "help"], rows))
    return "\n".join(out)


def cli_options() -> set[str]:
    """Every option string and positional of build_parser() (tests/apps/test_docs.py)."""
    from mars_link.apps.cli import build_parser

    names = set()
    for _, p, _ in walk_parsers(build_parser()):
        for a in p._actions:
            if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            names |= set(a.option_strings) or {a.dest}
    return names


# ----------------------------------------------------------------------------- MAVLink
FIRMWARE = ROOT / "firmware_models"


def _commands_in(files) -> list[str]:
    names = set()
    for f in files:
        names |= set(re.findall(r"\bMAV_CMD_[A-Z0-9_]+\b", f.read_text(encoding="utf-8")))
    return sorted(n for n in names if n != "MAV_CMD_")


def command_files():
    return sorted(FIRMWARE.glob("vehicle*.py")) + [FIRMWARE / "control_policy.py"]


def mission_files():
    return [p for p in (FIRMWARE / n for n in ("mission_protocol.py", "mission_runner.py", "geofence.py",
                                               "qgc_plan.py", "vehicle_geofence.py")) if p.exists()]


def mavlink_page() -> str:
    from pymavlink.dialects.v20 import common as R

    from firmware_models import vehicle, vehicle_modes as M, vehicle_streams
    from firmware_models.params import unit_param_specs
    from mars_link.core.assembly import vehicle_preset

    out = ["# MAVLink surface of a unit\n",
           "Generated at every build from `firmware_models/`: what one unit's firmware (and `mars-link vehicle`, "
           "the assembly as one vehicle, which runs the same firmware) answers. The persona is PX4's "
           "(MAV_AUTOPILOT_PX4, PX4's custom modes and parameter names) so stock clients work unchanged.\n"]
    handlers = getattr(vehicle, "_HANDLERS", {})
    out.append("## Messages received\n")
    out.append(table(["message", "handled by"], [[f"`{m}`", f"`{'.'.join(h)}`"] for m, h in handlers.items()]))
    cmds = _commands_in(command_files())
    out.append("## Commands (COMMAND_LONG, COMMAND_INT)\n")
    out.append(table(["command", "id"], [[f"`{c}`", getattr(R, c, "")] for c in cmds]))
    items = _commands_in(mission_files())
    out.append("## Mission, fence and rally items\n")
    out.append(table(["item", "id"], [[f"`{c}`", getattr(R, c, "")] for c in items]))
    out.append("## Flight modes (PX4 custom modes)\n")
    mains = {v: k for k, v in vars(M).items() if k.startswith("MAIN_")}
    rows = []
    for name, value in vars(M).items():
        if name.startswith("MODE_") and isinstance(value, tuple):
            main, sub_mode = value
            rows.append([f"`{name.removeprefix('MODE_')}`", mains.get(main, main).removeprefix("MAIN_"), sub_mode,
                         (main << 16) | (sub_mode << 24)])
    out.append(table(["mode", "main mode", "sub mode", "custom_mode"], rows))
    out.append("## Parameters\n")
    specs = unit_param_specs(1, vehicle_preset("mars-real"))
    out.append(table(["name", "type", "default", "min", "max", "read-only", "what"],
                     [[f"`{s.name}`", "INT32" if s.kind == R.MAV_PARAM_TYPE_INT32 else "REAL32", f"{s.default:g}",
                       f"{s.min_value:g}", f"{s.max_value:g}", "yes" if s.read_only else "", s.doc] for s in specs]))
    out.append("## Telemetry streams (default rates, wall clock)\n")
    names = {getattr(R, n): n.removeprefix("MAVLINK_MSG_ID_") for n in dir(R) if n.startswith("MAVLINK_MSG_ID_")}
    out.append(table(["message", "rate [Hz]"], [[f"`{names.get(i, i)}`", f"{hz:g}"]
                                                for i, hz in vehicle_streams.DEFAULT_STREAM_HZ.items()]))
    return "\n".join(out)


# ----------------------------------------------------------------------------- outputs
SUMMARY_NOTES = {
    "scenario": "scenario name", "source": "bundled name or the path given", "mode": "`inproc` or `sitl`",
    "mean_error_m": "mean 3-D distance of the tracked point to the reference, averaged over trials",
    "rmse_m": "root mean square of that distance", "max_error_m": "its maximum over trials",
    "sim_time_s": "simulated seconds flown (mean over trials)", "wall_time_s": "wall seconds, all trials",
    "real_time_factor": "simulated over wall time", "force_integral_n2s": "Σ rotors ∫ thrust² dt",
    "max_tilt_deg": "largest tilt of any body", "events": "faults, detections, reallocations, docks, splits",
    "detections": "faults the detector found, with the time of the fault each names",
    "provenance": "package version, git commit (null outside a checkout), the scenario as resolved",
    "logging": "whether every time series was written whole, and why not", "stage_time_s": "wall time per stage",
    "reconfigured": "a reconfiguration was done", "reconfig_time_s": "how long the manoeuvre took",
    "plan": "the executor's plan (null without moves)", "plans": "every plan of the flight with both objectives",
    "assembled": "a free start became the whole structure",
    "min_clearance_m": "smallest gap between units of different bodies (inf: one body all along)",
    "pieces_final": "each piece at the end: layout rows and unit ids", "units_lost": "each unit lost, and its fate",
    "mission_force_integral_n2s": "the force integral while the mission flies (the manoeuvre excluded)",
}


def sample_run(out_dir: Path) -> dict:
    """Fly hover_1x1 for 3 s into out_dir through the CLI; the summary."""
    from mars_link.apps.cli import main

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = main(["run", "hover_1x1", "--duration", "3", "--out", str(out_dir), "--quiet", "--force"])
    if code != 0:
        raise RuntimeError(f"the reference flight (mars-link run hover_1x1) exited {code}")
    return json.loads((out_dir / "summary.json").read_text(encoding="utf-8"))


def mcap_channels(path: Path, duration_s: float) -> list[list]:
    try:
        from mcap.reader import make_reader
    except ImportError:
        return []
    counts: dict[str, list] = {}
    with path.open("rb") as f:
        reader = make_reader(f)
        for schema, channel, _message in reader.iter_messages():
            entry = counts.setdefault(channel.topic, [schema.name if schema else channel.message_encoding, 0])
            entry[1] += 1
    return [[f"`{topic}`", f"`{schema}`", n, f"{n / duration_s:.1f}"] for topic, (schema, n) in sorted(counts.items())]


def outputs_page() -> str:
    out = ["# Run outputs\n",
           "Generated at every build from a real flight (`mars-link run hover_1x1 --duration 3`): the files of "
           "its run directory, summary.json's fields, the CSV columns, and the MCAP channels with the rates "
           "counted in that file (messages per simulated second). CSV files are written and flushed as the "
           "flight goes. Exit code 0 when every trial completed, 1 when one diverged, 2 for bad input.\n"]
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        summary = sample_run(run_dir)
        files = sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*") if p.is_file())
        out.append("## Files\n")
        out.append("\n".join(f"- `{f}`" for f in files) + "\n")
        out.append("## summary.json\n")
        out.append(table(["field", "type", "what"], [[f"`{k}`", type_of(v), SUMMARY_NOTES.get(k, "")]
                                                     for k, v in summary.items()]))
        for name in ("telemetry.csv", "rotors.csv", "units.csv"):
            path = run_dir / name
            if path.exists():
                header = path.read_text(encoding="utf-8").splitlines()[0].split(",")
                out.append(f"## {name}\n")
                out.append(table(["column", "unit"], [[f"`{c}`", unit_of(c)] for c in header]))
        mcap = run_dir / "run.mcap"
        if mcap.exists():
            rows = mcap_channels(mcap, float(summary["sim_time_s"]))
            out.append("## run.mcap (Foxglove)\n")
            out.append("Log time = simulation time. Rates measured in the reference flight's file "
                       "(control at 100 Hz).\n")
            out.append(table(["channel", "schema", "messages in 3 s", "rate [Hz]"], rows) if rows else
                       "(the `mcap` package is not installed: channel rates not measured)\n")
    return "\n".join(out)


GENERATORS = {"reference/scenario.md": scenario_page, "reference/cli.md": cli_page,
              "reference/mavlink.md": mavlink_page, "reference/outputs.md": outputs_page}


# ----------------------------------------------------------------------------- mkdocs
def on_files(files, config):
    from mkdocs.structure.files import File

    for uri, make in GENERATORS.items():
        existing = files.get_file_from_path(uri)
        if existing is not None:
            files.remove(existing)
        files.append(File.generated(config, uri, content=make()))
    return files


if __name__ == "__main__":
    target = Path(sys.argv[1] if len(sys.argv) > 1 else "site-reference")
    for uri, make in GENERATORS.items():
        (target / uri).parent.mkdir(parents=True, exist_ok=True)
        (target / uri).write_text(make(), encoding="utf-8")
        print(target / uri)
