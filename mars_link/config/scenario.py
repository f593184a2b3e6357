"""Scenario files (TOML): load, validate and turn into plain dataclasses.

Every problem is reported as one `UserInputError` line that names the file and the key, so the CLI
can print it and exit 2 without a traceback. The keys are listed in the documentation's scenario reference,
which docs/hooks/reference.py generates from this module.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from mars_link.core.assembly import AssemblyModel, PRESETS, parse_layout, vehicle_preset
from mars_link.models.battery import BatterySpec, battery_table
from mars_link.models.esc import FAULT_KINDS
from mars_link.models.environment import EnvironmentParams
from mars_link.models.sensor_profiles import SensorProfile
from mars_link.core.errors import UserInputError
from mars_link.core.validation import (MAX_CSV_BYTES, MAX_TOML_BYTES, MAX_TOML_DEPTH, MAX_WAYPOINTS, check_id_digits,
                                  check_regular_file, check_seed, note_input, read_input_file)
from mars_link.core.table_checks import check_keys as _check_keys, integer as _integer, number as _number, table as _table

from mars_link.core.ftc import FTC_MODES  # (the one list; re-exported for the schema's callers)

CONTROLLERS = ("cascaded", "mars-ftcc-paper")
#: the bundled scenarios: package data (found from any working directory, also in a non-editable install)
SCENARIO_DIR = Path(str(resources.files("mars_link").joinpath("scenarios")))
DEFAULT_SCENARIO = "spiral_3x2"
#: what `mars-link vehicle`, `sitl up` and `mars-link coordinator` fly when no scenario is named: the realistic plant
INTERACTIVE_SCENARIO = "hover_3x2_real"
#: the plant of a scenario without [vehicle] preset: thrust limits, motor lag, batteries (mars_link.core.assembly)
DEFAULT_PRESET = "mars-real"


@dataclass
class FaultSpec:
    """Rotor efficiency change: `rotor` None = the whole unit (all four rotors). `kind` (FAULT_KINDS) is what
    the ESC sees (mars_link.models.esc): "eta" a damaged propeller, "prop-loss" a lost one (the motor runs on,
    unloaded), "motor-stop" a stopped motor (eta 0); the thrust lost is `eta`'s in every kind."""

    unit: int
    rotor: int | None
    eta: float
    t_s: float = 0.0
    kind: str = "eta"

    def describe(self) -> str:
        return f"{self._where()} {self._kind_text()}eta={self.eta:g} at t={self.t_s:g}s"

    def event_text(self) -> str:
        """The fault event's STATUSTEXT line, e.g. 'Fault: unit 2 rotor 2 eta 0.5'."""
        what = "failed" if self.rotor is None and self.eta == 0 else f"eta {self.eta:g}"
        if self.kind == "motor-stop":
            what = "motor stop"
        return f"Fault: {self._where()} {self._kind_text() if self.kind == 'prop-loss' else ''}{what}"

    def _kind_text(self) -> str:
        return "" if self.kind == "eta" else f"{self.kind} "

    def _where(self) -> str:
        return f"unit {self.unit}" + (f" rotor {self.rotor}" if self.rotor else "")


def eta_after(model: AssemblyModel, faults: list[FaultSpec], t_s: float):
    """Per-rotor efficiencies (4N, the model's slot order) once every fault at or before `t_s` acted."""
    eta = model.nominal_eta()
    for f in faults:
        if f.t_s <= t_s:
            sl = model.unit_slots(f.unit) if f.rotor is None else model.rotor_slot(f.unit, f.rotor)
            eta[sl] = f.eta
    return eta


@dataclass
class SimSpec:
    duration_s: float | None = None  # None = the trajectory's duration
    physics_hz: float = 500.0
    control_hz: float = 100.0
    seed: int = 1
    noise: bool = True


@dataclass(frozen=True)
class SeparationSpec:
    """[[separations]]: at `t_s` (sim time) the units `units` undock and fly as a piece of their own under
    the coordinator (the mission pauses); at `redock_t_s` they dock back where they were (None: never)."""

    t_s: float
    units: tuple[int, ...]
    redock_t_s: float | None = None


@dataclass
class Scenario:
    name: str
    preset: str = "mars-ftcc"  # (built in code: the paper's plant; a TOML file naming none gets DEFAULT_PRESET)
    vehicle_options: dict[str, Any] = field(default_factory=dict)
    layout: tuple[str, ...] = ("XXX", "XXX")
    tracked: str = "unit:1"
    trajectory: dict[str, Any] = field(default_factory=lambda: {"kind": "mars-ftcc-spiral"})
    controller: str = "cascaded"
    ftc: str = "none"
    faults_known: bool = True
    faults: list[FaultSpec] = field(default_factory=list)
    sim: SimSpec = field(default_factory=SimSpec)
    source: str = "<built-in>"
    reconfig: dict[str, Any] = field(default_factory=dict)  # validated [reconfig] table (enabled, ...)
    start: str = "docked"  # "docked": one assembled body; "free": the units apart on the ground, assembled in the air
    free_spacing_m: float = 2.0  # start = "free": distance between neighbouring units' centres on the ground
    docking: dict[str, float] = field(default_factory=dict)  # [docking]: when facing latches close (sitl.docking)
    separations: list["SeparationSpec"] = field(default_factory=list)  # [[separations]], in time order
    environment: EnvironmentParams = field(default_factory=EnvironmentParams)  # [environment]: wind, gusts, turbulence
    sensors: SensorProfile = field(default_factory=SensorProfile)  # [sensors]: the position sensor (mocap, rtk)
    mission: dict[str, Any] = field(default_factory=dict)  # [mission]: map = obstacle map for the vehicle's legs
    battery: BatterySpec | None = None  # [battery]: the units' packs (mars_link.models.battery); None = an ideal supply
    sensor_faults: list = field(default_factory=list)  # [[sensor_faults]] (scenario_sensor_faults.SensorFaultSpec)
    unit_interface: str = "mavlink"  # [units] interface: "mavlink" | "px4-zenoh" (UNIT_INTERFACES)
    esc_telemetry: bool = True  # [sensors] esc_telemetry: the units' ESCs report RPM and current (models.esc)

    @property
    def starts_free(self) -> bool:
        return self.start == "free"

    @property
    def has_pieces(self) -> bool:
        """Whether the flight may be several bodies (a free start, a reconfiguration, a separation)."""
        return self.starts_free or bool(self.reconfig.get("enabled")) or bool(self.separations)

    def model(self) -> AssemblyModel:
        params = vehicle_preset(self.preset)
        if self.vehicle_options:
            params = params.with_options(**self.vehicle_options)
        return AssemblyModel.from_layout(self.layout, params)

    def tracked_unit(self) -> int | None:
        return None if self.tracked == "com" else int(self.tracked.split(":")[1])


# ----------------------------------------------------------------------------- parsing helpers
#: free units on the ground stand at least this far apart, edge to edge
FREE_CLEARANCE_M = 0.3
_TOP_KEYS = {"name", "vehicle", "assembly", "trajectory", "control", "faults", "sim", "reconfig", "docking",
             "separations", "environment", "sensors", "mission", "battery", "sensor_faults", "units"}
_VEHICLE_KEYS = {
    "preset",
    "motor_time_constant_s",
    "rotor_max_thrust_n",
    "rotor_min_thrust_n",
    "rotor_drag_coeff",
}
_AERO_KEYS = {"drag", "drag_area_frd_m2"}  # + rotor_drag_coeff (a number, above)
_ASSEMBLY_KEYS = {"layout", "tracked", "start", "free_spacing_m"}
_CONTROL_KEYS = {"controller", "ftc", "faults_known"}
_FAULT_KEYS = {"t", "unit", "rotor", "eta", "kind"}
_SIM_KEYS = {"duration_s", "physics_hz", "control_hz", "seed", "noise"}
_UNITS_KEYS = {"interface"}
#: [units] interface: how the coordinator commands the units: the MAVLink persona (SET_ACTUATOR_CONTROL_TARGET)
#: or PX4's own per-rotor interface (OffboardControlMode + ActuatorMotors, uORB over rmw_zenoh: mars_link.px4)
UNIT_INTERFACES = ("mavlink", "px4-zenoh")


def validate_fault(fault: FaultSpec, model: AssemblyModel, src: str = "fault") -> None:
    if fault.kind not in FAULT_KINDS:
        raise UserInputError(f"{src}: unknown fault kind {fault.kind!r} (known: {', '.join(FAULT_KINDS)})")
    if fault.kind == "motor-stop" and fault.eta != 0.0:
        raise UserInputError(f"{src}: a motor-stop fault makes no thrust: eta must be 0 (or left out), got {fault.eta!r}")
    if not 0.0 <= fault.eta <= 1.0 or not math.isfinite(fault.eta):
        raise UserInputError(f"{src}: eta must be in [0, 1], got {fault.eta!r}")
    if fault.t_s < 0 or not math.isfinite(fault.t_s):
        raise UserInputError(f"{src}: fault time must be >= 0, got {fault.t_s!r}")
    try:
        model.check_rotor(fault.unit, fault.rotor)
    except UserInputError as exc:
        raise UserInputError(f"{src}: {exc}") from None


_FAULT_RE = re.compile(
    r"^\s*(?P<unit>\d+)(?::(?P<rotor>\d+))?\s*=\s*(?P<eta>[-+0-9.eE]+)(?:\s*@\s*(?P<t>[-+0-9.eE]+))?"
    r"(?:\s*/\s*(?P<kind>[a-z-]+))?\s*$"
)


def parse_fault_arg(text: str) -> FaultSpec:
    """`UNIT[:ROTOR]=ETA[@T][/KIND]`, e.g. `2:2=0.5`, `3=0@10`, `1:2=0@5/prop-loss` (KIND: FAULT_KINDS)."""
    m = _FAULT_RE.match(text)
    if not m:
        shown = text if len(text) <= 60 else text[:40] + "..."
        raise UserInputError(
            f"--fault {shown!r}: expected UNIT[:ROTOR]=ETA[@T][/KIND], e.g. 2:2=0.5, 3=0@10 or 1:2=0@5/motor-stop"
        )
    kind = m["kind"] or "eta"
    if kind not in FAULT_KINDS:
        raise UserInputError(f"--fault {text[:60]!r}: unknown fault kind {kind!r} (known: {', '.join(FAULT_KINDS)})")
    try:
        eta = float(m["eta"])
        t = float(m["t"]) if m["t"] else 0.0
    except ValueError:
        raise UserInputError(f"--fault {text[:60]!r}: ETA and T must be numbers") from None
    unit = check_id_digits(m["unit"], f"--fault {text[:40]!r} unit")
    rotor = check_id_digits(m["rotor"], f"--fault {text[:40]!r} rotor") if m["rotor"] else None
    return FaultSpec(unit, rotor, eta, t, kind)


def scenario_from_dict(doc: dict, src: str = "<scenario>") -> Scenario:
    _check_keys(doc, _TOP_KEYS, "the top level", src)
    name = doc.get("name", Path(src).stem if src.endswith(".toml") else "scenario")
    if not isinstance(name, str) or not name:
        raise UserInputError(f"{src}: name must be a non-empty string")
    sc = Scenario(name=name, source=src)

    vehicle = _table(doc, "vehicle", src)
    _check_keys(vehicle, _VEHICLE_KEYS | _AERO_KEYS, "[vehicle]", src)
    sc.preset = vehicle.get("preset", DEFAULT_PRESET)  # a scenario that names no preset flies the realistic plant
    if sc.preset not in PRESETS:
        raise UserInputError(
            f"{src}: unknown vehicle preset {sc.preset!r} (known: {', '.join(sorted(PRESETS))})"
        )
    from mars_link.config.scenario_environment import aero_options, environment_table, sensors_table

    sc.battery = battery_table(_table(doc, "battery", src), sc.preset, src)
    sc.environment = environment_table(_table(doc, "environment", src), src)
    sensors = dict(_table(doc, "sensors", src))
    sc.esc_telemetry = sensors.pop("esc_telemetry", True)
    if not isinstance(sc.esc_telemetry, bool):
        raise UserInputError(f"{src}: [sensors] esc_telemetry must be true or false")
    sc.sensors = sensors_table(sensors, src)
    sc.vehicle_options.update(aero_options(vehicle, sc.preset, sc.environment, src))
    for key in _VEHICLE_KEYS - {"preset"}:
        if key in vehicle:
            sc.vehicle_options[key] = _number(
                vehicle[key], f"[vehicle] {key}", src, nonneg=key != "rotor_min_thrust_n"
            )

    assembly = _table(doc, "assembly", src)
    _check_keys(assembly, _ASSEMBLY_KEYS, "[assembly]", src)
    layout = assembly.get("layout", list(sc.layout))
    if isinstance(layout, str):
        layout = [layout]
    if not isinstance(layout, list) or not all(isinstance(r, str) for r in layout):
        raise UserInputError(f"{src}: [assembly] layout must be a list of strings like [\"XXX\", \"XXX\"]")
    try:
        sc.layout = parse_layout(layout)
    except UserInputError as exc:
        raise UserInputError(f"{src}: [assembly] {exc}") from None
    sc.tracked = assembly.get("tracked", sc.tracked)
    sc.start = assembly.get("start", sc.start)
    if sc.start not in ("docked", "free"):
        raise UserInputError(f"{src}: [assembly] start must be \"docked\" or \"free\", got {sc.start!r}")
    if "free_spacing_m" in assembly:
        sc.free_spacing_m = _number(assembly["free_spacing_m"], "[assembly] free_spacing_m", src, positive=True)
    pitch = vehicle_preset(sc.preset).pitch_m
    if sc.starts_free and sc.free_spacing_m < pitch + FREE_CLEARANCE_M:
        raise UserInputError(f"{src}: [assembly] free_spacing_m {sc.free_spacing_m:g} m puts free units overlapping "
                             f"on the ground (need >= unit pitch {pitch:g} m + {FREE_CLEARANCE_M:g} m)")
    if not isinstance(sc.tracked, str) or not re.fullmatch(r"com|unit:\d+", sc.tracked):
        raise UserInputError(f"{src}: [assembly] tracked must be \"com\" or \"unit:N\", got {sc.tracked!r}")

    trajectory = _table(doc, "trajectory", src)
    if trajectory:
        if "kind" not in trajectory:
            raise UserInputError(f"{src}: [trajectory] needs a kind")
        sc.trajectory = dict(trajectory)
        _check_trajectory_inputs(sc.trajectory, src)

    control = _table(doc, "control", src)
    _check_keys(control, _CONTROL_KEYS, "[control]", src)
    sc.controller = control.get("controller", sc.controller)
    if sc.controller not in CONTROLLERS:
        raise UserInputError(
            f"{src}: unknown controller {sc.controller!r} (known: {', '.join(CONTROLLERS)})"
        )
    # a scenario on the default (realistic) plant allocates with qp unless it says otherwise: the one mode whose
    # priorities (roll/pitch > thrust > yaw) keep the attitude when rotors saturate (README, realistic plant)
    sc.ftc = control.get("ftc", "qp" if "preset" not in vehicle else sc.ftc)
    if sc.ftc not in FTC_MODES:
        raise UserInputError(f"{src}: unknown ftc mode {sc.ftc!r} (known: {', '.join(FTC_MODES)})")
    fk = control.get("faults_known", True)
    if not isinstance(fk, bool):
        raise UserInputError(f"{src}: [control] faults_known must be true or false")
    sc.faults_known = fk

    faults = doc.get("faults", [])
    if not isinstance(faults, list):
        raise UserInputError(f"{src}: faults must be an array of tables ([[faults]])")
    for i, f in enumerate(faults, 1):
        where = f"[[faults]] #{i}"
        if not isinstance(f, dict):
            raise UserInputError(f"{src}: {where} must be a table")
        _check_keys(f, _FAULT_KEYS, where, src)
        kind = f.get("kind", "eta")
        if kind not in FAULT_KINDS:
            raise UserInputError(f"{src}: {where} unknown kind {kind!r} (known: {', '.join(map(repr, FAULT_KINDS))})")
        for key in ("unit",) if kind != "eta" else ("unit", "eta"):  # (a lost prop or stopped motor: eta 0)
            if key not in f:
                raise UserInputError(f"{src}: {where} needs {key!r}")
        rotor = f.get("rotor")
        sc.faults.append(
            FaultSpec(
                unit=_integer(f["unit"], f"{where} unit", src),
                rotor=None if rotor is None else _integer(rotor, f"{where} rotor", src),
                eta=_number(f.get("eta", 0.0), f"{where} eta", src),
                t_s=_number(f.get("t", 0.0), f"{where} t", src),
                kind=kind,
            )
        )

    units = _table(doc, "units", src)
    _check_keys(units, _UNITS_KEYS, "[units]", src)
    if "interface" in units:
        if units["interface"] not in UNIT_INTERFACES:
            raise UserInputError(f"{src}: [units] interface must be one of {', '.join(map(repr, UNIT_INTERFACES))}, "
                                 f"got {units['interface']!r}")
        sc.unit_interface = units["interface"]

    sim = _table(doc, "sim", src)
    _check_keys(sim, _SIM_KEYS, "[sim]", src)
    if "duration_s" in sim:
        sc.sim.duration_s = _number(sim["duration_s"], "[sim] duration_s", src, positive=True)
        if sc.sim.duration_s > MAX_DURATION_S:
            raise UserInputError(f"{src}: [sim] duration_s must be <= {MAX_DURATION_S:g}, got {sc.sim.duration_s:g}")
    if "physics_hz" in sim:
        sc.sim.physics_hz = _number(sim["physics_hz"], "[sim] physics_hz", src, positive=True)
    if "control_hz" in sim:
        sc.sim.control_hz = _number(sim["control_hz"], "[sim] control_hz", src, positive=True)
    if "seed" in sim:
        sc.sim.seed = check_seed(_integer(sim["seed"], "[sim] seed", src), f"{src}: [sim] seed")
    if "noise" in sim:
        if not isinstance(sim["noise"], bool):
            raise UserInputError(f"{src}: [sim] noise must be true or false")
        sc.sim.noise = sim["noise"]
    check_rates(sc.sim, src)
    sc.reconfig = _reconfig_table(_table(doc, "reconfig", src), src)
    sc.docking = _docking_table(_table(doc, "docking", src), src)
    sc.separations = _separations(doc.get("separations", []), src)
    sc.mission = _table(doc, "mission", src)
    if set(sc.mission) - {"map"} or not isinstance(sc.mission.get("map", ""), str):
        raise UserInputError(f"{src}: [mission] takes one key, map = \"FILE\" (a boxes .csv or .pcd obstacle map)")

    if sc.trajectory.get("kind") == "plan":  # the planner needs the assembly and its faults
        sc.trajectory.setdefault("layout", list(sc.layout))
        sc.trajectory.setdefault("preset", sc.preset)
        sc.trajectory.setdefault("faults", [f"{f.unit}{f':{f.rotor}' if f.rotor else ''}={f.eta}" for f in sc.faults])

    model = sc.model()
    tracked = sc.tracked_unit()
    if tracked is not None:
        try:
            model.check_rotor(tracked, None)
        except UserInputError as exc:
            raise UserInputError(f"{src}: [assembly] tracked: {exc}") from None
    for i, fault in enumerate(sc.faults, 1):
        validate_fault(fault, model, f"{src}: [[faults]] #{i}")
    for unit in (sc.battery.overrides if sc.battery is not None else {}):
        try:
            model.check_rotor(unit, None)
        except UserInputError as exc:
            raise UserInputError(f"{src}: [[battery.units]]: {exc}") from None
    for i, sep in enumerate(sc.separations, 1):
        for u in sep.units:
            try:
                model.check_rotor(u, None)
            except UserInputError as exc:
                raise UserInputError(f"{src}: [[separations]] #{i}: {exc}") from None
        if len(sep.units) >= model.n_units:
            raise UserInputError(f"{src}: [[separations]] #{i}: units must leave at least one unit behind")
    from mars_link.config.scenario_sensor_faults import parse_sensor_faults

    sc.sensor_faults = parse_sensor_faults(doc.get("sensor_faults", []), src, model, sc.sensors.name, sc.sim.noise)
    if not sc.esc_telemetry and any(sf.sensor == "esc" for sf in sc.sensor_faults):
        raise UserInputError(f"{src}: [[sensor_faults]] sensor \"esc\" needs [sensors] esc_telemetry = true")
    target = sc.reconfig.get("target")
    if target is not None and sorted(target) != model.unit_ids:
        raise UserInputError(
            f"{src}: [reconfig] target must list each unit 1..{model.n_units} exactly once (one per cell, row-major)")
    return sc


#: what a reconfiguration plan maximises ([reconfig] objective): paper 001's force objective, or the worst-stage
#: controllability margin (mars_link.reconfig.margin)
RECONFIG_OBJECTIVES = ("force", "margin")

_RECONFIG_NUMBERS = {"at_s", "trigger_delay_s", "speed_mps", "approach_speed_mps", "stop_s", "settle_s",
                     "altitude_step_m", "separation_m", "predock_m", "dock_timeout_s"}


def _reconfig_table(table: dict, src: str) -> dict:
    """[reconfig]: enabled (bool), target (unit ids per cell, row-major), moves and ground (bools, default true), and the
    executor's timing and distances (mars_link.reconfig.execution.ExecutionParams); checked against the layout later."""
    _check_keys(table, {"enabled", "target", "moves", "ground", "objective"} | _RECONFIG_NUMBERS, "[reconfig]", src)
    out: dict[str, Any] = {"enabled": table.get("enabled", False)}
    # moves: where paper 001 finds no plan, fly the best single move; ground: where no move either, land
    # and rebuild on the ground
    for key in ("enabled", "moves", "ground"):
        if key in table and not isinstance(table[key], bool):
            raise UserInputError(f"{src}: [reconfig] {key} must be true or false")
    for key in ("moves", "ground"):
        if key in table:
            out[key] = table[key]
    # objective: where the units go, "force" (paper 001's placement) or "margin" (MARS-Reconfig: the largest
    # controllability margin of the weakest piece along the whole sequence)
    if "objective" in table:
        if table["objective"] not in RECONFIG_OBJECTIVES:
            raise UserInputError(f"{src}: [reconfig] objective must be one of {', '.join(RECONFIG_OBJECTIVES)}, "
                                 f"got {table['objective']!r}")
        out["objective"] = table["objective"]
    if "target" in table:
        target = table["target"]
        if not isinstance(target, list) or not all(isinstance(u, int) and not isinstance(u, bool) for u in target):
            raise UserInputError(f"{src}: [reconfig] target must be a list of unit ids, e.g. [2, 3, 1]")
        out["target"] = list(target)
    for key in _RECONFIG_NUMBERS & set(table):
        out[key] = _number(table[key], f"[reconfig] {key}", src, nonneg=key in ("at_s", "trigger_delay_s", "altitude_step_m"),
                           positive=key not in ("at_s", "trigger_delay_s", "altitude_step_m"))
    return out


_SEPARATION_KEYS = {"t", "units", "redock_t"}


def _separations(items: Any, src: str) -> list[SeparationSpec]:
    """[[separations]] t, units (a list of unit ids), redock_t (optional, after t); in time order, apart."""
    if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
        raise UserInputError(f"{src}: separations must be an array of tables ([[separations]])")
    out = []
    for i, item in enumerate(items, 1):
        where = f"[[separations]] #{i}"
        _check_keys(item, _SEPARATION_KEYS, where, src)
        for key in ("t", "units"):
            if key not in item:
                raise UserInputError(f"{src}: {where} needs {key!r}")
        units = item["units"]
        if not isinstance(units, list) or not units:
            raise UserInputError(f"{src}: {where} units must be a non-empty list of unit ids, e.g. [1]")
        ids = tuple(_integer(u, f"{where} units", src) for u in units)
        if len(set(ids)) != len(ids):
            raise UserInputError(f"{src}: {where} units lists a unit twice")
        t = _number(item["t"], f"{where} t", src, nonneg=True)
        redock = None
        if "redock_t" in item:
            redock = _number(item["redock_t"], f"{where} redock_t", src, positive=True)
            if redock <= t:
                raise UserInputError(f"{src}: {where} redock_t must be after t ({redock:g} <= {t:g})")
        if out and (out[-1].redock_t_s is None or t <= out[-1].redock_t_s):
            raise UserInputError(f"{src}: {where} must start after the previous separation re-docked")
        out.append(SeparationSpec(t, ids, redock))
    return out


#: [docking] keys and their allowed range (sitl.docking.DockTolerance): a latch must not close farther than a
#: few centimetres off its pose, faster than a gentle approach, or across a visible misalignment
DOCKING_RANGES = {"position_m": (0.0, 0.1), "speed_mps": (0.0, 0.5), "yaw_deg": (0.0, 15.0), "tilt_deg": (0.0, 15.0)}


def _docking_table(table: dict, src: str) -> dict[str, float]:
    """[docking] position_m, speed_mps, yaw_deg, tilt_deg: the docking tolerance (defaults 2 cm, 5 cm/s,
    2 deg, 3 deg), each > 0 and at most its DOCKING_RANGES bound."""
    _check_keys(table, set(DOCKING_RANGES), "[docking]", src)
    out = {}
    for key, (lo, hi) in DOCKING_RANGES.items():
        if key in table:
            value = _number(table[key], f"[docking] {key}", src, positive=True)
            if not lo < value <= hi:
                raise UserInputError(f"{src}: [docking] {key} must be in ({lo:g}, {hi:g}], got {value:g}")
            out[key] = value
    return out


MAX_PHYSICS_HZ = 100_000.0  # a sane bound: beyond it a second of flight is minutes of stepping
MAX_DURATION_S = 1e6  # 11.6 days of simulated flight


def check_rates(sim: SimSpec, src: str) -> None:
    if sim.physics_hz > MAX_PHYSICS_HZ:
        raise UserInputError(f"{src}: [sim] physics_hz must be <= {MAX_PHYSICS_HZ:g}, got {sim.physics_hz:g}")
    ratio = sim.physics_hz / sim.control_hz
    if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
        raise UserInputError(
            f"{src}: [sim] physics_hz ({sim.physics_hz:g}) must be a whole multiple of control_hz "
            f"({sim.control_hz:g})"
        )


def check_faults_controllable(scenario: Scenario, model: AssemblyModel | None = None) -> None:
    """The one controllability check of `run`, `vehicle` and `sitl up`: with every fault of the
    scenario applied, the assembly must still produce the full wrench and hover within its thrust
    limits (mars_link.allocation.check_controllable). A UserInputError line otherwise."""
    if not scenario.faults:
        return
    from mars_link.allocation import check_controllable

    model = model or scenario.model()
    eta = model.nominal_eta()  # every fault applied (the runners' eta_after at t = inf)
    for f in sorted(scenario.faults, key=lambda f: f.t_s):
        eta[model.unit_slots(f.unit) if f.rotor is None else model.rotor_slot(f.unit, f.rotor)] = f.eta
    check_controllable(model, eta, (model.vehicle.rotor_min_thrust_n, model.vehicle.rotor_max_thrust_n))


def resolve_scenario_path(arg: str | None) -> Path:
    """A path, or the name of a bundled scenario (`spiral_3x2`), or None for the default."""
    if arg is None:
        arg = DEFAULT_SCENARIO
    path = Path(arg)
    if path.exists():
        return path
    bundled = SCENARIO_DIR / (arg if arg.endswith(".toml") else f"{arg}.toml")
    if bundled.exists():
        return bundled
    from mars_link.core.errors import did_you_mean

    hint = did_you_mean(Path(arg).name.removesuffix(".toml"), bundled_scenario_names()) or \
        "; `mars-link scenarios` lists them"
    raise UserInputError(f"scenario {arg!r} not found (no such file, and no bundled scenario of that name){hint}")


def bundled_scenario_names() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def scenario_description(path: Path) -> str:
    """A scenario file's one-line description: the first line of its header comment ("" when it has none)."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return ""
    for line in lines:
        if line.strip():
            return line.strip().lstrip("#").strip() if line.lstrip().startswith("#") else ""
    return ""


def bundled_scenarios() -> list[dict[str, str]]:
    """Every bundled scenario: name, one-line description and path (what `mars-link scenarios` prints)."""
    return [{"name": p.stem, "description": scenario_description(p), "path": str(p)}
            for p in sorted(SCENARIO_DIR.glob("*.toml"))]


def load_scenario(arg: str | None) -> Scenario:
    path = resolve_scenario_path(arg)
    src = str(path) if not path.is_relative_to(SCENARIO_DIR) else path.name
    return scenario_from_dict(read_toml_file(path, src), src)


def read_toml_file(path: Path, src: str) -> dict:
    """A scenario file's TOML document, within the caps of mars_link.core.validation (MAX_TOML_BYTES, a
    regular file, MAX_TOML_DEPTH): anything else is one UserInputError line, before it is parsed whole."""
    text = read_input_file(path, f"{src}: scenario", MAX_TOML_BYTES)
    doc = parse_toml(text, src)
    _note_named_files(doc, path)
    return doc


def _check_trajectory_inputs(trajectory: dict, src: str) -> None:
    """The caps on a trajectory's inputs (mars_link.core.validation), checked with the scenario: before the run
    directory is made, although the trajectory is built later."""
    points = trajectory.get("points")
    if trajectory.get("kind") == "waypoints" and isinstance(points, list) and len(points) > MAX_WAYPOINTS:
        raise UserInputError(f"{src}: [trajectory] {len(points):,} waypoints: at most {MAX_WAYPOINTS:,} "
                             "(split the mission)")
    csv_path = trajectory.get("path")  # (a file missing here may be on a sweep's workers: theirs to read)
    if trajectory.get("kind") == "csv" and isinstance(csv_path, str) and "\x00" not in csv_path \
            and os.path.exists(csv_path):
        check_regular_file(csv_path, f"{src}: [trajectory] csv file", MAX_CSV_BYTES)


def _note_named_files(doc: dict, path: Path) -> None:
    """The files a scenario names (a trajectory's csv, map or plan, the mission's map) are inputs of its run
    (mars_link.core.validation.note_input: `--force` keeps them), noted before the run directory is cleared
    (some are read only later). Each as given and beside the scenario, the two places they are looked for."""
    for table, key in (("trajectory", "path"), ("trajectory", "map"), ("trajectory", "plan"), ("mission", "map")):
        section = doc.get(table)
        name = section.get(key) if isinstance(section, dict) else None
        if isinstance(name, str) and name and "\x00" not in name:
            note_input(name)
            note_input(path.parent / name)


def parse_toml(text: str, src: str) -> dict:
    """`tomllib.loads`, its errors as one line: malformed, or nested deeper than MAX_TOML_DEPTH (the
    parser recurses per level: a deep enough nesting raises RecursionError, also reported as one line)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserInputError(f"{src}: malformed TOML: {exc}") from None
    except RecursionError:
        raise UserInputError(f"{src}: TOML nested too deep (at most {MAX_TOML_DEPTH} levels)") from None
    depth = toml_depth(doc)
    if depth > MAX_TOML_DEPTH:
        raise UserInputError(f"{src}: TOML nested {depth} levels deep (at most {MAX_TOML_DEPTH})")
    return doc


def toml_depth(doc: Any) -> int:
    """How deep tables and arrays nest in `doc` (a scalar 0, a table of scalars 1), without recursion."""
    deepest, stack = 0, [(doc, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, (dict, list)):
            deepest = max(deepest, depth)
            children = value.values() if isinstance(value, dict) else value
            stack.extend((child, depth + 1) for child in children if isinstance(child, (dict, list)))
    return deepest
