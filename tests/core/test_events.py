"""Events are typed: every kind a producer names is in `EventKind` (one list, one meaning each), and
flights that exercise faults, sensors, the failsafe, assembly and reconfiguration record only known kinds
with summary.json's keys."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from mars_link.config.scenario import load_scenario
from mars_link.core.events import MEANINGS, EventKind, event, unknown_kinds
from mars_link.flight.runner import run_scenario

ROOT = Path(__file__).resolve().parents[2]


def test_every_kind_has_one_meaning_and_a_record_keeps_the_summary_keys() -> None:
    assert set(MEANINGS) == set(EventKind) and all(MEANINGS[k].strip() for k in EventKind)
    record = event(1.23456789, EventKind.FAULT, unit=2, rotor=3, eta=0.0, text="Fault: unit 2 rotor 3 eta 0")
    assert list(record) == ["t_s", "type", "unit", "rotor", "eta", "text"]
    assert record["t_s"] == 1.234568 and record["type"] == "fault" and type(record["type"]) is str


def _literal_kinds() -> set[str]:
    """The kinds the product's code passes to event() (or a producer's _event) as literals. (mars_link.px4
    keeps its own: the PX4 interface's state changes, Px4UnitEvent, are no flight records.)"""
    kinds = set()
    for path in [*ROOT.joinpath("mars_link").rglob("*.py"), *ROOT.joinpath("sitl").rglob("*.py")]:
        if "px4" in path.relative_to(ROOT).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Call) or len(node.args) < 2:
                continue
            name = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", "")
            if name not in ("event", "_event"):
                continue
            kind = node.args[1]
            if isinstance(kind, ast.Attribute) and isinstance(kind.value, ast.Name) and kind.value.id == "EventKind":
                kinds.add(EventKind[kind.attr].value)
            elif isinstance(kind, ast.Constant) and isinstance(kind.value, str):
                kinds.add(kind.value)
    return kinds


def test_the_kinds_the_code_names_are_listed() -> None:
    kinds = _literal_kinds()
    assert len(kinds) > 20
    assert kinds <= {k.value for k in EventKind}, kinds - {k.value for k in EventKind}


@pytest.mark.slow
@pytest.mark.parametrize("name, duration_s", [("spiral_3x2_fdi", 12.0), ("spiral_3x2_gps_loss", 30.0),
                                              ("docking_3x1", None)])
def test_flights_record_only_known_kinds(tmp_path: Path, name: str, duration_s: float | None) -> None:
    sc = load_scenario(name)
    if duration_s is not None:
        sc.sim.duration_s = duration_s
    summary = run_scenario(sc, tmp_path, plots=False, mcap=False)
    assert summary["events"] and not unknown_kinds(summary["events"])
    assert all({"t_s", "type"} <= set(e) for e in summary["events"])
