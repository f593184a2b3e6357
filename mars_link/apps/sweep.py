"""`mars-link sweep`: many flights of one scenario over seeds, random faults and parameter values.

What a sweep is: the cartesian product of the `--param` values, each flown with `--seeds N` seeds.
Seed slot j (0..N-1) flies with seed `sweep seed + j` and draws its random faults from a generator
seeded with (sweep seed, j) only, so a flight's result does not depend on the worker count or on which
worker flew it, and every parameter value meets the same seeds and faults (paired comparisons). Each
row names its seed and faults in `mars-link run --seed S --fault U:R=ETA@T` form: one flight of a
sweep can be flown again alone. The flights run on `mars_link.apps.sweep_pool` (local processes or Dask).
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mars_link.config import scenario as scenario_module
from mars_link.core.assembly import ROTORS_PER_UNIT
from mars_link.core.errors import UserInputError
from mars_link.config.scenario import (FaultSpec, Scenario, parse_toml, read_toml_file, resolve_scenario_path,
                                scenario_from_dict, SCENARIO_DIR)
from mars_link.core.validation import MAX_SWEEP_FLIGHTS, SEED_MAX
from mars_link.flight.fault_scoring import FaultScore, score_flight

#: random faults act between these fractions of the flight (after take-off, with time left to see it)
FAULT_T_MIN_FRAC = 0.1
FAULT_T_MAX_FRAC = 0.6
#: bare --param keys and the scenario table they live in
PARAM_ALIASES = {
    "ftc": "control.ftc", "controller": "control.controller", "faults_known": "control.faults_known",
    "noise": "sim.noise", "physics_hz": "sim.physics_hz", "control_hz": "sim.control_hz",
    "duration_s": "sim.duration_s", "preset": "vehicle.preset",
}
PARAM_TABLES = ("vehicle", "assembly", "trajectory", "control", "sim", "reconfig", "docking", "environment", "sensors")
#: `--faults`: the grammar, shown whole in every refusal
FAULTS_GRAMMAR = "random:K or random:A-B[,rotors|units|whole-units][,eta=E1/E2/...][,kind=KIND]"
_COUNT_RE = re.compile(r"random:(?P<lo>\d{1,4})(?:-(?P<hi>\d{1,4}))?")
#: where random faults fall, and what each placement draws unless told (etas, one time for all or one each)
PLACEMENTS = {
    "rotors": "distinct rotors anywhere, eta 0, each at its own time",
    "units": "one rotor on each of distinct units, all at one time, etas 0 and 0.3 mixed (issue 41's simultaneous "
             "faults)",
    "whole-units": "distinct whole units, eta 0, each at its own time",
}
DEFAULT_ETAS = {"rotors": (0.0,), "units": (0.0, 0.3), "whole-units": (0.0,)}


@dataclass(frozen=True)
class RandomFaults:
    """`--faults random:K` or `random:A-B`: per flight, a count uniform in [A, B] of faults placed as `placement`
    says (PLACEMENTS), each eta uniform among `etas`; `kind`: the scenario's fault kind (None: its default)."""

    count_min: int
    count_max: int
    placement: str = "rotors"
    etas: tuple[float, ...] = (0.0,)
    kind: str | None = None

    @property
    def simultaneous(self) -> bool:
        return self.placement == "units"

    def text(self) -> str:
        count = f"{self.count_min}" if self.count_min == self.count_max else f"{self.count_min}-{self.count_max}"
        etas = "" if self.etas == DEFAULT_ETAS[self.placement] else ",eta=" + "/".join(f"{e:g}" for e in self.etas)
        return f"random:{count},{self.placement}{etas}" + (f",kind={self.kind}" if self.kind else "")


@dataclass(frozen=True)
class Param:
    """`--param KEY=V1,V2,...`: `key` is `table.key` of the scenario TOML."""

    key: str
    values: tuple[Any, ...]


@dataclass(frozen=True)
class FlightSpec:
    """One flight of a sweep: its index, seed slot and seed, parameter values and faults."""

    index: int
    seed_index: int
    seed: int
    params: tuple[tuple[str, Any], ...] = ()
    faults: tuple[FaultSpec, ...] = ()

    def params_text(self) -> str:
        return " ".join(f"{k}={_value_text(v)}" for k, v in self.params)

    def faults_text(self) -> str:
        return " ".join(fault_arg(f) for f in self.faults)


@dataclass
class SweepPlan:
    """A checked sweep: the scenario's TOML document, where it came from, and its flights."""

    doc: dict
    src: str
    name: str
    sweep_seed: int
    flights: list[FlightSpec] = field(default_factory=list)


# ----------------------------------------------------------------------------- parsing
def parse_faults(text: str | None) -> RandomFaults | None:
    """`--faults`: FAULTS_GRAMMAR (None or "none": no random faults); a bad spec is one line naming the part."""
    if text is None or text == "none":
        return None
    shown = f"--faults {text[:60]!r}"
    head, *parts = [p.strip() for p in text.strip().split(",")]
    m = _COUNT_RE.fullmatch(head)
    if not m:
        raise UserInputError(f"{shown}: expected {FAULTS_GRAMMAR}, e.g. random:1 or random:1-3,units")
    lo, hi = int(m["lo"]), int(m["hi"] or m["lo"])
    if not 1 <= lo <= hi:
        raise UserInputError(f"{shown}: expected random:K with K >= 1, or random:A-B with 1 <= A <= B")
    placement, etas, kind = None, None, None
    for part in parts:
        key, sep, value = part.partition("=")
        if not sep and part in PLACEMENTS and placement is None:
            placement = part
        elif key == "eta" and etas is None:
            etas = _parse_etas(value, shown)
        elif key == "kind" and kind is None and re.fullmatch(r"[a-z][a-z0-9-]{0,31}", value):
            kind = _check_kind(value, shown)
        else:
            raise UserInputError(f"{shown}: unknown or repeated part {part[:30]!r}; expected {FAULTS_GRAMMAR}")
    placement = placement or "rotors"
    return RandomFaults(lo, hi, placement, etas or DEFAULT_ETAS[placement], kind)


def _parse_etas(text: str, shown: str) -> tuple[float, ...]:
    try:
        etas = tuple(float(v) for v in text.split("/"))
    except ValueError:
        etas = ()
    if not etas or not all(0.0 <= e < 1.0 for e in etas) or len(set(etas)) != len(etas):
        raise UserInputError(f"{shown}: eta={text[:20]} must be distinct efficiencies in [0, 1) separated by /, "
                             "e.g. eta=0/0.3")
    return etas


def _check_kind(kind: str, shown: str) -> str:
    """A fault kind is the scenario's `[[faults]] kind`: refused while FaultSpec has none (or not this one)."""
    known = getattr(scenario_module, "FAULT_KINDS", None)
    if "kind" not in {f.name for f in dataclasses.fields(FaultSpec)} or not known:
        raise UserInputError(f"{shown}: fault kind {kind!r}: this version's faults have no kinds yet (eta only)")
    if kind not in known:
        raise UserInputError(f"{shown}: unknown fault kind {kind!r} (one of {', '.join(known)})")
    return kind


def parse_param(text: str) -> Param:
    """`KEY=V1,V2,...`; values are TOML literals (100, 0.02, true, "a") or bare words (qp)."""
    key, sep, rest = text.partition("=")
    key = key.strip()
    if not sep or not key or not rest.strip():
        raise UserInputError(f"--param {text[:60]!r}: expected KEY=V1,V2,... e.g. ftc=none,qp")
    key = PARAM_ALIASES.get(key, key)
    table, dot, name = key.partition(".")
    if not dot or table not in PARAM_TABLES or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise UserInputError(f"--param {text[:60]!r}: unknown key {key!r} (use TABLE.KEY with TABLE one of "
                             f"{', '.join(PARAM_TABLES)}, or one of {', '.join(PARAM_ALIASES)})")
    if key == "sim.seed":
        raise UserInputError("--param sim.seed: seeds are set with --seed and --seeds")
    values = tuple(_parse_value(v, key) for v in _split_values(rest))
    if len(set(map(repr, values))) != len(values):
        raise UserInputError(f"--param {key}: a value is listed twice")
    return Param(key, values)


def _split_values(text: str) -> list[str]:
    """Split on commas outside [...] (a value may be a TOML array)."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        depth += (ch == "[") - (ch == "]")
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    parts.append(cur)
    return [p.strip() for p in parts]


def _parse_value(text: str, key: str) -> Any:
    if not text:
        raise UserInputError(f"--param {key}: an empty value")
    try:
        return parse_toml(f"v = {text}", f"--param {key}")["v"]  # (nesting capped: MAX_TOML_DEPTH)
    except UserInputError:
        if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.:/+-]*", text):
            return text  # a bare word: a string (qp, modquad-cf2)
        raise UserInputError(f"--param {key}: {text[:40]!r} is not a value (a number, true/false, a word or "
                             "a TOML literal)") from None


def _value_text(v: Any) -> str:
    return str(v).lower() if isinstance(v, bool) else str(v)


def fault_arg(f: FaultSpec) -> str:
    """A fault in `mars-link run --fault` form: UNIT[:ROTOR]=ETA@T[/KIND] (the kind when not the default)."""
    kind = "" if f.kind == "eta" else f"/{f.kind}"
    return f"{f.unit}{f':{f.rotor}' if f.rotor else ''}={f.eta:g}@{f.t_s:g}{kind}"


def with_params(doc: dict, params: tuple[tuple[str, Any], ...]) -> dict:
    """A copy of the scenario document with each `table.key` set."""
    out = copy.deepcopy(doc)
    for key, value in params:
        table, _, name = key.partition(".")
        if not isinstance(out.setdefault(table, {}), dict):
            raise UserInputError(f"--param {key}: [{table}] is not a table in this scenario")
        out[table][name] = value
    return out


# ----------------------------------------------------------------------------- the plan
def read_scenario_doc(arg: str | None) -> tuple[dict, str]:
    """The scenario's TOML document and its source name (as mars_link.config.scenario.load_scenario names it)."""
    path = resolve_scenario_path(arg)
    src = path.name if path.resolve().is_relative_to(SCENARIO_DIR) else str(path)
    doc = read_toml_file(path, src)  # (the caps on size and depth of mars_link.core.validation)
    doc.setdefault("name", path.stem)
    return doc, src


def scenario_for(doc: dict, src: str, params: tuple[tuple[str, Any], ...]) -> Scenario:
    try:
        return scenario_from_dict(with_params(doc, params), src)
    except UserInputError as exc:
        shown = " ".join(f"{k}={_value_text(v)}" for k, v in params)
        raise UserInputError(f"--param {shown}: {exc}" if params else str(exc)) from None


def plan_sweep(doc: dict, src: str, seeds: int, sweep_seed: int | None = None,
               faults: RandomFaults | None = None, params: list[Param] | None = None) -> SweepPlan:
    """Every flight of the sweep, each parameter combination checked now (one line, exit 2, before any
    flight): a bad value, a flight too short, random faults that do not fit the assembly."""
    from mars_link.flight.build import check_flight, flight_duration_s

    params = params or []
    keys = [p.key for p in params]
    if len(set(keys)) != len(keys):
        raise UserInputError("--param: a key is given twice (list its values in one --param KEY=V1,V2)")
    if not 1 <= seeds <= 100_000:
        raise UserInputError(f"--seeds must be 1..100000, got {seeds}")
    grid = math.prod(len(p.values) for p in params)  # counted, not listed: a refusal costs no memory
    if seeds * grid > MAX_SWEEP_FLIGHTS:
        raise UserInputError(f"sweep of {seeds * grid:,} flights ({seeds:,} seeds x {grid:,} parameter combinations): "
                             f"at most {MAX_SWEEP_FLIGHTS:,} (fewer --seeds or --param values, or several sweeps)")
    combos = [tuple(zip(keys, values)) for values in itertools.product(*(p.values for p in params))]
    base = scenario_for(doc, src, ())
    sweep_seed = base.sim.seed if sweep_seed is None else sweep_seed
    if sweep_seed + seeds - 1 > SEED_MAX:
        raise UserInputError(f"--seed {sweep_seed} + --seeds {seeds}: flight seeds go past {SEED_MAX}")
    plan = SweepPlan(doc, src, base.name, sweep_seed)
    for combo in combos:
        sc = scenario_for(doc, src, combo)
        model = sc.model()
        if not sc.has_pieces:
            check_flight(sc, model)
        duration = flight_duration_s(sc, model) if faults else 0.0
        for j in range(seeds):
            drawn = draw_faults(faults, sweep_seed, j, model, duration, sc.sim.control_hz) if faults else ()
            plan.flights.append(FlightSpec(len(plan.flights), j, sweep_seed + j, combo, drawn))
    return plan


def draw_faults(faults: RandomFaults, sweep_seed: int, seed_index: int, model, duration_s: float,
                control_hz: float) -> tuple[FaultSpec, ...]:
    """Seed slot `seed_index`'s faults, drawn from (sweep seed, slot) only: the count (a range only), the places,
    each rotor of `units`, the time(s) uniform in [FAULT_T_MIN_FRAC, FAULT_T_MAX_FRAC] of the flight on a control
    step, then the etas (several only). Why in this order: a fixed count with one eta draws exactly what sweeps
    drew before ranges and etas existed, so their flights fly again the same."""
    import numpy as np

    if faults.placement == "rotors":
        pool: list[tuple[int, int | None]] = [(u, r) for u in model.unit_ids for r in range(1, ROTORS_PER_UNIT + 1)]
    else:
        pool = [(u, None) for u in model.unit_ids]
    noun = "rotors" if faults.placement == "rotors" else "units"
    if faults.count_max > len(pool):
        raise UserInputError(f"--faults {faults.text()}: the assembly has only {len(pool)} {noun}")
    rng = np.random.default_rng([sweep_seed, seed_index])
    count = faults.count_min if faults.count_min == faults.count_max else int(
        rng.integers(faults.count_min, faults.count_max + 1))
    picks = [pool[int(k)] for k in rng.choice(len(pool), size=count, replace=False)]
    if faults.placement == "units":
        picks = [(u, int(r)) for (u, _), r in zip(picks, rng.integers(1, ROTORS_PER_UNIT + 1, size=count))]
    fracs = rng.uniform(FAULT_T_MIN_FRAC, FAULT_T_MAX_FRAC, size=1 if faults.simultaneous else count)
    fracs = np.repeat(fracs, count) if faults.simultaneous else fracs
    etas = [faults.etas[0]] * count if len(faults.etas) == 1 else [float(e) for e in rng.choice(faults.etas, size=count)]
    with_kind: dict[str, Any] = {"kind": faults.kind} if faults.kind else {}  # (FaultSpec.kind, once it exists)
    out = []
    for (unit, rotor), frac, eta in sorted(zip(picks, fracs, etas), key=lambda p: (p[1], p[0][0], p[0][1] or 0)):
        t = math.floor(duration_s * float(frac) * control_hz) / control_hz  # on a control step
        fault = FaultSpec(unit, rotor, 0.0 if faults.kind == "motor-stop" else eta, round(t, 6))  # (a stop: eta 0)
        out.append(dataclasses.replace(fault, **with_kind))
    return tuple(out)


# ----------------------------------------------------------------------------- one flight (in a worker)
#: the isolation figures of each flight (mars_link.flight.fault_scoring: FlightFaultScore.row)
SCORE_FIELDS = ("faults_injected", "faults_isolated", "faults_isolated_in_time", "faults_never_found",
                "isolation_delay_max_s", "eta_error_max", "false_beliefs", "false_belief_max_s")
ROW_FIELDS = ("flight", "seed", "faults", "params", "completed", "diverged", "mean_error_m", "rmse_m", "max_error_m",
              "force_integral_n2s", "detection_time_s", *SCORE_FIELDS, "sim_time_s", "wall_time_s", "error")
#: faults.csv: one row per injected fault of every flight (its FaultScore)
FAULT_FIELDS = ("flight", "seed", "params", "unit", "rotor", "eta", "t_s", "found", "isolated", "isolated_in_time",
                "delay_s", "eta_estimated", "eta_error")
#: what must be equal between two sweeps of the same flights (all but the wall time)
RESULT_FIELDS = tuple(f for f in ROW_FIELDS if f != "wall_time_s")


def fly_flight(doc: dict, src: str, spec: FlightSpec, mcap_dir: str | None = None) -> dict:
    """Fly one flight of a sweep in this process; its row. `mcap_dir`: write its run.mcap there."""
    import time

    t0 = time.perf_counter()
    sc = scenario_for(doc, src, spec.params)
    sc.faults.extend(spec.faults)
    out = None if mcap_dir is None else Path(mcap_dir)
    if out is not None:  # (run.mcap's writer is a subprocess: a daemonic Dask worker may start it)
        out.mkdir(parents=True, exist_ok=True)
    from mars_link.flight.flight_view import flight_view
    from mars_link.flight.runner import run_trial

    r = run_trial(sc, spec.seed, view=None if out is None else (lambda flight: flight_view(flight, out)))
    return row_of(spec, r, [d["t_detected"] for d in r.detections], time.perf_counter() - t0)


def row_of(spec: FlightSpec, r, detected_t_s: list[float], wall_s: float) -> dict:
    """A flight's row: its figures as the flight gave them (floats kept whole, so equal flights give equal rows),
    with its fault isolation scored from its events; `fault_scores` (not a CSV column): faults.csv's rows."""
    t_fault = min((f.t_s for f in spec.faults), default=None)
    after = sorted(t for t in detected_t_s if t_fault is not None and t >= t_fault - 1e-9)
    score = score_flight(r.events, float(r.sim_time_s), bool(r.diverged))
    return {**score.row(), "fault_scores": [fault_row(spec, f) for f in score.faults],
        "flight": spec.index, "seed": spec.seed, "faults": spec.faults_text(), "params": spec.params_text(),
        "completed": bool(r.completed), "diverged": bool(r.diverged), "mean_error_m": float(r.mean_error_m),
        "rmse_m": float(r.rmse_m), "max_error_m": float(r.max_error_m),
        "force_integral_n2s": float(r.force_integral_n2s),
        "detection_time_s": (after[0] - t_fault) if after else None,
        "sim_time_s": float(r.sim_time_s), "wall_time_s": wall_s, "error": None,
    }


def fault_row(spec: FlightSpec, f: FaultScore) -> dict:
    """One injected fault's row of faults.csv."""
    return {"flight": spec.index, "seed": spec.seed, "params": spec.params_text(), "unit": f.unit, "rotor": f.rotor,
            "eta": f.eta, "t_s": f.t_s, "found": f.found, "isolated": f.isolated,
            "isolated_in_time": f.isolated_in_time, "delay_s": f.delay_s, "eta_estimated": f.eta_estimated,
            "eta_error": f.eta_error}


def error_row(spec: FlightSpec, error: str, wall_s: float) -> dict:
    """The row of a flight that raised: its error, no figures."""
    row = {k: None for k in ROW_FIELDS}
    row.update(flight=spec.index, seed=spec.seed, faults=spec.faults_text(), params=spec.params_text(),
               completed=False, diverged=False, wall_time_s=wall_s, error=error)
    return row
