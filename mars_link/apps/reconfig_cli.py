"""`mars-link reconfig plan`: the reconfiguration a fault set calls for, as text or JSON (options: mars_link.apps.cli).

Exit codes: 0 a plan was found, 1 no feasible plan (the JSON still says why), 2 bad input (one
line on stderr).
"""

from __future__ import annotations

import math

from mars_link.core.errors import UserInputError
from mars_link.logs.outputs import dumps

EXIT_OK, EXIT_INFEASIBLE, EXIT_USAGE = 0, 1, 2


def _parse_pair(text: str, what: str) -> tuple[float, float]:
    parts = text.split(",")
    try:
        values = tuple(float(x) for x in parts)
    except ValueError:
        values = ()
    if len(values) != 2 or not all(math.isfinite(v) for v in values):
        raise UserInputError(f"{what} {text!r}: expected two numbers separated by a comma")
    return values


def _parse_target(text: str, model) -> dict[int, tuple[int, int]]:
    try:
        ids = [int(x) for x in text.split(",")]
    except ValueError:
        raise UserInputError(f"--target {text!r}: expected unit ids separated by commas, e.g. 3,2,1") from None
    if sorted(ids) != model.unit_ids:
        raise UserInputError(
            f"--target {text!r}: must list each unit 1..{model.n_units} exactly once (one per cell, row-major)")
    cells = [model.unit_cells[u] for u in model.unit_ids]
    return {u: cell for u, cell in zip(ids, cells)}


def _setup(args):
    """Model, faults, health and snap weights from the scenario and the overrides."""
    from mars_link.core.assembly import AssemblyModel
    from mars_link.reconfig.placement import SnapWeights, health_from_eta
    from mars_link.flight.build import make_trajectory
    from mars_link.core.limits import check_planned_unit_count
    from mars_link.config.scenario import eta_after
    from mars_link.config.scenario import load_scenario, parse_fault_arg, validate_fault

    if args.scenario is None and args.layout is None:
        raise UserInputError("give a scenario TOML or --layout ROWS")
    scenario = load_scenario(args.scenario) if args.scenario is not None else None
    preset = args.preset or (scenario.preset if scenario else "modquad-cf2")
    layout = args.layout if args.layout is not None else list(scenario.layout)
    model = AssemblyModel.from_layout(layout, preset)
    check_planned_unit_count(model.n_units)
    faults = []
    if scenario is not None:
        for i, f in enumerate(scenario.faults, 1):
            validate_fault(f, model, f"{scenario.source}: [[faults]] #{i}")
            faults.append(f)
    for text in args.fault:
        f = parse_fault_arg(text)
        validate_fault(f, model, f"--fault {text}")
        faults.append(f)
    health = health_from_eta(model, eta_after(model, sorted(faults, key=lambda f: f.t_s), math.inf))
    if args.snap_weights:
        weights = SnapWeights.from_integrals(*_parse_pair(args.snap_weights, "--snap-weights"))
    elif scenario is not None and args.layout is None:
        weights = SnapWeights.from_trajectory(make_trajectory(scenario, model))
    else:
        weights = SnapWeights()
    return model, faults, health, weights


def _grid(model, cells: dict[int, tuple[int, int]]) -> list[str]:
    at = {c: u for u, c in cells.items()}
    width = len(str(model.n_units))
    n_cols = max(len(r) for r in model.layout)
    return [" ".join(str(at[(r, c)]).rjust(width) if (r, c) in at else ".".rjust(width) for c in range(n_cols))
            for r in range(len(model.layout))]


def _print_text(model, faults, weights, plan) -> None:
    print(f"layout {','.join(model.layout)}  preset {model.vehicle.name}  "
          f"faults: {', '.join(f.describe() for f in faults) or 'none'}  "
          f"snap weights w_x={weights.w_x:.3f} w_y={weights.w_y:.3f}")
    print("now -> target (unit ids by cell, front row first)")
    for a, b in zip(_grid(model, plan.initial), _grid(model, plan.target)):
        print(f"  {a}    {b}")
    how = plan.placement.solver + (" after binding " + str(plan.placement.forced_blocks) if plan.fallback_used else "")
    if not plan.feasible:
        print(f"no feasible plan: {plan.reason}")
        return
    print(f"disassembly layers: {plan.disassembly_layers}  assembly layers: {plan.assembly_layers}  "
          f"(placement by {how}; {plan.timings_s['total'] * 1e3:.1f} ms)")
    for s in plan.steps():
        line = s.get("line")
        where = f" across {line['axis']} line {line['index']}" if line else ""
        if s["kind"] == "split":
            print(f"  D{s['layer']} split {s['body']}{where}: detach {s['detached']} from {s['rest']}")
        elif s["kind"] == "move":
            print(f"  A{s['layer']} move {s['body']} at altitude slot {s['altitude_slot']} beside {s['beside']}")
        else:
            print(f"  A{s['layer']} dock {s['bodies'][1]} to {s['bodies'][0]}{where}")


def reconfig_plan_args(args) -> int:
    """The verb, its options parsed by mars_link.apps.cli; a bad input raises (one line there, exit 2)."""
    from mars_link.reconfig.margin import plan_figures
    from mars_link.reconfig.plans import plan_for_margin
    from mars_link.reconfig.sequencing import plan_reconfiguration

    model, faults, health, weights = _setup(args)
    target = _parse_target(args.target, model) if args.target else None
    if args.objective == "margin" and target is None:
        plan = plan_for_margin(model, health.ravel(), weights)
    else:
        plan = plan_reconfiguration(model, health, weights, target=target)
    figures = plan_figures(plan, model.vehicle, {u: health[u - 1] for u in model.unit_ids}) if plan.feasible else {}
    if args.json:
        out = plan.to_json()
        out.update(figures)
        out.update({
            "preset": model.vehicle.name,
            "faults": [{"unit": f.unit, "rotor": f.rotor, "eta": f.eta, "t": f.t_s} for f in faults],
            "snap_weights": {"w_x": weights.w_x, "w_y": weights.w_y},
        })
        print(dumps(out, indent=None))  # strict JSON (NaN/inf -> null)
    else:
        _print_text(model, faults, weights, plan)
        if figures:
            print(f"chosen by {plan.objective}: force objective {figures['force_objective']:.4f}, controllability "
                  f"margin worst stage {figures['worst_stage_margin']:.3f}, final {figures['final_margin']:.3f}")
    return EXIT_OK if plan.feasible else EXIT_INFEASIBLE
