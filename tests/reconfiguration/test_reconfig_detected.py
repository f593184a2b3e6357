"""Reconfiguration on faults the coordinator finds (not told), every piece on its own EKF: paper 001's
donut with 3 dead rotors at t = 5 s (tools/reconfig_detect_eval.py flies the whole table)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))

from reconfig_detect_eval import FAULT_T_S, detected_scenario, fly  # noqa: E402

from mars_link.flight.runner import run_trial  # noqa: E402

PLUS = [".X.", "XXX", ".X."]


@pytest.mark.slow
def test_donut_reconfigures_on_detected_faults_and_beats_flying_on():
    nr, r = fly(3, "NR"), fly(3, "R")  # donut 4x4, unit 1 rotors 1, 3, 4 dead at 5 s
    for res in (nr, r):
        assert res["completed"] and not res["diverged"] and res["false_alarms"] == 0
        assert res["detection_s"] is not None and res["detection_s"] < 0.5
        assert sorted((u, rot) for u, rot, _ in res["detected"]) == [(1, 1), (1, 3), (1, 4)]
    assert r["reconfigured"] and not nr["reconfigured"]
    assert r["rmse_m"] <= nr["rmse_m"]
    assert r["mission_force_integral_n2s"] < nr["mission_force_integral_n2s"]


def test_plus5_six_faults_found_and_the_rebuild_on_the_ground_turned_off_the_coordinator_says_why():
    """plus-5, unit 1 dead and unit 2's rotors 1 and 4: found in < 0.5 s; paper 001's plan has nothing to
    fly and no piece can split off and dock back with every body hovering (tests/reconfiguration/test_reconfig_moves.py);
    with the rebuild on the ground turned off (`[reconfig] ground = false`) the coordinator says so (an
    event) and flies on with FTC."""
    sc = detected_scenario(PLUS, 6, True)
    r = run_trial(dataclasses.replace(sc, reconfig={**sc.reconfig, "ground": False}), 1)
    assert r.completed and not r.reconfigured and not r.diverged
    found = [e for e in r.events if e["type"] == "fault_detected"]
    assert found and found[0]["t_s"] - FAULT_T_S < 0.5
    refused = next(e["reason"] for e in r.events if e["type"] == "reconfig_refused")
    assert "no piece can split off" in refused


def test_plus5_faulty_tip_cannot_be_carried_to_the_centre():
    """Why paper 001's plans cannot improve the plus-5: the faulty tip (unit 1) reaches the centre only as the pair
    {1, 3} (the tips touch the centre only), and that pair cannot hover with ModQuad's thrust limits: 116 %
    of a rotor's maximum with unit 1's rotor 2 left (3 faults), and at no thrust with unit 1 dead."""
    import math

    import numpy as np
    from reconfig_eval import scenario

    from mars_link.allocation import hover_thrust_share
    from mars_link.core.assembly import AssemblyModel

    vehicle = scenario([".X.", "XXX", ".X."], [], "qp", {"enabled": False}).model().vehicle
    pair = AssemblyModel.from_layout(["X", "X"], vehicle)
    three = np.array([0.0, 1.0, 0.0, 0.0, 1, 1, 1, 1])
    share = hover_thrust_share(pair, three, vehicle.rotor_max_thrust_n)
    assert 1.1 < share < 1.25, share
    assert hover_thrust_share(pair, np.array([0.0] * 4 + [1.0] * 4), vehicle.rotor_max_thrust_n) == math.inf
    assert hover_thrust_share(pair, np.ones(8), vehicle.rotor_max_thrust_n) < 0.6  # healthy: it hovers easily


def test_plus5_six_faults_found_as_a_dead_unit_and_two_rotors_of_its_neighbour():
    """plus-5, paper 001's six faults (unit 1 dead, unit 2 rotors 1 and 4) at once: the detector's
    combined hypothesis (a unit and part of another) names them exactly; before it, "units 1+5 failed"
    (pure lift, no moment) won and the helix diverged."""
    r = fly(2, "NR")
    assert r["detection_s"] is not None and r["detection_s"] < 0.5 and r["false_alarms"] == 0
    assert sorted((u, rot or 0) for u, rot, _ in r["detected"]) == [(1, 0), (2, 1), (2, 4)]
    assert r["completed"] and not r["diverged"]


def test_paper000_docking_with_noise_and_the_fault_found_keeps_the_faulty_unit_within_1_deg(tmp_path):
    """docking_3x1 through the engine, sensor noise on (each piece on its EKF), the dead rotor not told: the
    detector finds it once airborne, the manoeuvre is planned from that, and unit 3's yaw stays within
    paper 000's 1 deg over separation and docking."""
    from docking_eval import faulty_unit_figures
    from docking_eval import fly as fly_docking

    r = fly_docking("docking_3x1", "qp", tmp_path, noise=True, detected=True)
    assert r.completed and r.reconfigured
    (found,) = r.detections
    assert (found["unit"], found["rotor"]) == (3, 4) and found["eta_estimated"] < 0.15
    assert faulty_unit_figures(r)["max_yaw_deviation_deg"] <= 1.0
    assert r.pieces_final == [{"layout": ["XXX"], "units": [2, 3, 1]}]


@pytest.mark.slow
@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_a_second_fault_set_is_planned_from_the_structure_the_first_manoeuvre_left():
    """The donut: unit 1 loses 3 rotors at 5 s (found, reconfigured: unit 1 moves), then unit 12 loses 3 at
    45 s. The second plan starts from the structure the first one left (not the layout's numbering), and
    both manoeuvres complete."""
    import dataclasses

    from reconfig_eval import CASES, paper_faults, scenario

    from mars_link.flight.runner import run_trial
    from mars_link.config.scenario import FaultSpec

    _, layout, _ = CASES[3]
    faults = [FaultSpec(f.unit, f.rotor, f.eta, 5.0) for f in paper_faults(3)]
    faults += [FaultSpec(12, r, 0.0, 45.0) for r in (1, 3, 4)]
    sc = scenario(layout, faults, "qp", {"enabled": True})
    sc = dataclasses.replace(sc, faults_known=False, sim=dataclasses.replace(sc.sim, noise=True))
    r = run_trial(sc, 1)
    assert r.completed and not r.diverged
    kinds = [e["type"] for e in r.events]
    assert kinds.count("reconfig_done") == 2 and kinds.count("plan") == 2
    second = [e for e in r.events if e["type"] == "plan"][1]
    assert second["t_s"] > 45.0 and second["disassembly_layers"] >= 1
    (final,) = r.pieces_final
    assert final["layout"] == list(layout) and final["units"] != list(range(1, 13))
