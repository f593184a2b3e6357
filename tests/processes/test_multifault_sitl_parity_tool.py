"""tools/multifault_sitl_parity.py (issue 41's cases, in process against lockstep SITL): its scenario copies
and its answer to bad arguments. The flights themselves are offline work (docs/results/2026-12-sweeps.md)."""

from __future__ import annotations

import pytest

from mars_link.config.scenario import load_scenario
from tests.repo_files import load_script


def test_the_esc_setting_goes_into_a_copy_of_the_bundled_case(tmp_path) -> None:
    tool = load_script("tools/multifault_sitl_parity.py")
    for case in tool.CASES:
        bundled = load_scenario(case)
        for esc in ("on", "off"):
            copy = load_scenario(str(tool.scenario_file(case, esc, tmp_path)))
            assert copy.esc_telemetry is (esc == "on")
            assert copy.layout == bundled.layout and copy.faults == bundled.faults and not copy.faults_known


def test_bad_arguments_are_one_line_and_exit_2(capsys) -> None:
    tool = load_script("tools/multifault_sitl_parity.py")
    assert tool.main(["--cases", "spiral_3x2"]) == 2
    assert tool.main(["--esc", "maybe"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("multifault_sitl_parity: ") for line in err)


def test_a_belief_is_compared_with_its_eta_and_onset() -> None:
    """summary.json names a belief's eta `eta_estimated`: two flights that differ only there are not equal."""
    tool = load_script("tools/multifault_sitl_parity.py")
    found = {"t_s": 15.06, "type": "fault_detected", "unit": 2, "rotor": 3, "eta_estimated": 0.0112, "t_onset": 15.0,
             "text": "Fault found: Unit 2 rotor 3 eta 0.01"}
    other = {**found, "eta_estimated": 0.0113}
    assert tool.belief_events({"events": [found, {"t_s": 0.0, "type": "fault"}]}) == [
        ["fault_detected", 2, 3, 15.06, 0.0112, 15.0]]
    assert tool.belief_events({"events": [found]}) != tool.belief_events({"events": [other]})


def test_eta_errors_of_the_first_and_last_belief_naming_each_fault() -> None:
    """multifault_3x2_unit_and_rotor: unit 3 dead and unit 5 rotor 2 at 0.3 at 15 s. A belief before the fault or
    at another place names neither; a whole unit is named by a belief without a rotor."""
    tool = load_script("tools/multifault_sitl_parity.py")
    faults = load_scenario("multifault_3x2_unit_and_rotor").faults
    events = [{"type": "fault_detected", "unit": 5, "rotor": 2, "t_s": 10.0, "eta_estimated": 0.9},
              {"type": "fault_detected", "unit": 3, "rotor": None, "t_s": 15.08, "eta_estimated": 0.0},
              {"type": "fault_detected", "unit": 5, "rotor": 2, "t_s": 15.1, "eta_estimated": 0.45},
              {"type": "fault_detected", "unit": 4, "rotor": 2, "t_s": 15.2, "eta_estimated": 0.5},
              {"type": "fault_detected", "unit": 5, "rotor": 2, "t_s": 15.9, "eta_estimated": 0.31}]
    errors = tool.eta_errors({"events": events}, faults)
    assert len(errors) == 2 and errors[0] == [0.0, 0.0]
    assert errors[1][0] == pytest.approx(0.15) and errors[1][1] == pytest.approx(0.01)
