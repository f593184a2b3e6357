"""`mars-link reconfig plan`: JSON contract, scenario faults, one-line errors with exit code 2."""

from __future__ import annotations

import json

import pytest

from mars_link.apps.cli import main


def run(argv, capsys):
    code = main(["reconfig", "plan", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_json_plan_for_a_layout_and_a_fault(capsys):
    code, out, err = run(["--layout", "XXX,XXX", "--preset", "modquad-cf2", "--fault", "1:1=0", "--json"], capsys)
    assert code == 0 and err == ""
    doc = json.loads(out)
    cells = {(p["row"], p["col"]) for p in doc["placement"]}
    assert cells == {(r, c) for r in range(2) for c in range(3)}
    assert sorted(p["unit"] for p in doc["placement"]) == [1, 2, 3, 4, 5, 6]
    assert isinstance(doc["cost_layers"], int) and doc["cost_layers"] >= 1
    assert doc["solve_time_s"] > 0
    kinds = [s["kind"] for s in doc["steps"]]
    assert kinds.count("split") >= doc["cost_layers"] and kinds.count("dock") == kinds.count("move") >= 1
    # the faulty unit ends up with its dead front-right rotor towards the middle (a rear cell)
    assert next(p for p in doc["placement"] if p["unit"] == 1)["row"] == 1
    assert doc["faults"] == [{"unit": 1, "rotor": 1, "eta": 0.0, "t": 0.0}]


def test_scenario_faults_and_trajectory_weights(tmp_path, capsys):
    path = tmp_path / "plus.toml"
    path.write_text(
        'name = "plus"\n[vehicle]\npreset = "modquad-cf2"\n[assembly]\nlayout = [".X.", "XXX", ".X."]\n'
        '[trajectory]\nkind = "helix"\n'
        '[[faults]]\nt = 2.0\nunit = 2\neta = 0.0\n'
        '[[faults]]\nt = 1.0\nunit = 2\nrotor = 3\neta = 1.0\n', encoding="utf-8")
    code, out, _ = run([str(path), "--json"], capsys)
    doc = json.loads(out)
    assert code == 0
    # the later fault wins: unit 2 is dead and belongs in the centre, but it cannot leave its
    # neighbours, so the plan either moves a flyable block or keeps the layout
    assert {f["unit"] for f in doc["faults"]} == {2}
    assert 0.0 < doc["snap_weights"]["w_x"] < 1.0
    assert doc["feasible"] is True and doc["cost_layers"] is not None
    # text output names the layout and the layers
    code, out, _ = run([str(path), "--fault", "4:1=0.5"], capsys)
    assert code == 0 and "disassembly layers" in out and ".X.,XXX,.X." in out


def test_no_change_needed(capsys):
    code, out, _ = run(["--layout", "XX,XX", "--json"], capsys)
    doc = json.loads(out)
    assert code == 0 and doc["cost_layers"] == 0 and doc["steps"] == []


def test_explicit_target(capsys):
    code, out, _ = run(["--layout", "XXXX", "--target", "4,3,2,1", "--json"], capsys)
    doc = json.loads(out)
    assert code == 0 and doc["cost_layers"] == 2 and doc["placement_solver"] == "given"
    assert [p["col"] for p in doc["placement"]] == [3, 2, 1, 0]


@pytest.mark.parametrize("argv,message", [
    (["--layout", "X.X"], "not connected"),
    (["--layout", "XX", "--fault", "3=0"], "unit 3 does not exist"),
    (["--layout", "XX", "--fault", "1:5=0"], "rotor 5 does not exist"),
    (["--layout", "XX", "--fault", "1=1.5"], "eta must be in [0, 1]"),
    (["--layout", "XX", "--fault", "one=0"], "expected UNIT[:ROTOR]=ETA[@T]"),
    (["--layout", "XXXX", "--fault", "1:3=0", "--target", "4,3,2,1"], "unreachable"),
    (["--layout", "XXX", "--target", "1,1,2"], "exactly once"),
    (["--layout", "XXX", "--target", "a,b,c"], "unit ids"),
    (["--layout", "XX", "--preset", "nope"], "unknown vehicle preset"),
    (["--layout", "XX", "--snap-weights", "1"], "two numbers"),
    (["--layout", "XX", "--snap-weights=-1,2"], "finite and >= 0"),
    ([], "give a scenario TOML or --layout"),
    (["no_such_scenario.toml"], "not found"),
    (["--layout", "XX", "--bogus"], "unrecognized arguments"),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    code, out, err = run(argv, capsys)
    assert code == 2 and out == ""
    assert message in err and err.count("\n") == 1 and err.startswith("mars-link: error: ")


def test_malformed_scenario(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text('[assembly]\nlayout = ["XX"]\n[[faults]]\nunit = 9\neta = 0.0\n', encoding="utf-8")
    code, _, err = run([str(path)], capsys)
    assert code == 2 and "unit 9 does not exist" in err
