"""The fault scorer (mars_link/flight/fault_scoring.py) on event records as flights write them: a fault isolated
(right unit, rotor, eta within 0.1) and its delay, a wrong eta or a wrong rotor not isolated, healthy rotors believed
failed (a wrong rotor, a whole unit declared for one rotor, a belief before the fault) and for how long (to a
retraction, a re-estimate as healthy, the rotor's own later fault, or the end)."""

from __future__ import annotations

import pytest

from mars_link.core.events import EventKind, event
from mars_link.flight.fault_scoring import ISOLATION_DEADLINE_S, score_flight


def fault(t: float, unit: int, rotor: int | None, eta: float) -> dict:
    return event(t, EventKind.FAULT, unit=unit, rotor=rotor, eta=eta)


def found(t: float, unit: int, rotor: int | None, eta: float) -> dict:
    return event(t, EventKind.FAULT_DETECTED, unit=unit, rotor=rotor, eta_estimated=eta, t_onset=t - 0.05)


def retracted(t: float, unit: int, rotor: int | None) -> dict:
    return event(t, "fault_retracted", unit=unit, rotor=rotor)


def test_isolated_in_time_late_and_with_a_wrong_eta():
    events = [fault(10.0, 1, 2, 0.0), fault(10.0, 6, 4, 0.3), fault(10.0, 8, 1, 0.3),
              found(10.12, 1, 2, 0.04),  # right, 0.12 s
              found(10.2, 8, 1, 0.55), found(10.9, 8, 1, 0.35),  # named at once, its eta right only 0.9 s later
              found(10.3, 6, 4, 0.75)]  # named, eta 0.45 off: never isolated
    s = score_flight(events, 30.0, diverged=False)
    f1, f6, f8 = s.faults
    assert (f1.found, f1.isolated, f1.isolated_in_time) == (True, True, True)
    assert f1.delay_s == pytest.approx(0.12) and f1.eta_error == pytest.approx(0.04)
    assert (f8.found, f8.isolated, f8.isolated_in_time) == (True, True, False)
    assert f8.delay_s == pytest.approx(0.9) and f8.delay_s > ISOLATION_DEADLINE_S and f8.eta_estimated == 0.35
    assert (f6.found, f6.isolated, f6.delay_s, f6.eta_estimated) == (True, False, None, 0.75)
    row = s.row()
    assert row["faults_injected"] == 3 and row["faults_isolated"] == 2 and row["faults_isolated_in_time"] == 1
    assert row["faults_never_found"] == 0 and row["false_beliefs"] == 0 and row["false_belief_max_s"] is None
    assert row["isolation_delay_max_s"] == pytest.approx(0.9)


def test_false_beliefs_wrong_rotor_whole_unit_retraction_and_end():
    events = [fault(15.0, 1, 2, 0.0), fault(15.0, 6, 4, 0.0),
              found(15.1, 5, 1, 0.2),  # healthy rotor: believed failed until retracted at 15.6
              retracted(15.6, 5, 1),
              found(15.2, 6, None, 0.0),  # whole unit 6 for its rotor 4: rotors 1-3 believed failed to the end
              found(15.3, 2, 3, 0.5), found(16.3, 2, 3, 0.97)]  # re-estimated healthy: 1.0 s
    s = score_flight(events, 20.0, diverged=True)
    f1, f6 = s.faults
    assert not f1.found and not f6.found  # unit 1 never named; unit 6 named whole, not its rotor 4
    held = {(b.unit, b.rotor): b for b in s.false_beliefs}
    assert set(held) == {(5, 1), (6, 1), (6, 2), (6, 3), (2, 3)}  # (6, 4) really failed: not a false belief
    assert held[(5, 1)].duration_s == pytest.approx(0.5) and not held[(5, 1)].held_to_end
    assert held[(2, 3)].duration_s == pytest.approx(1.0)
    assert held[(6, 2)].duration_s == pytest.approx(4.8) and held[(6, 2)].held_to_end
    assert s.row()["faults_never_found"] == 2 and s.row()["false_belief_max_s"] == pytest.approx(4.8)
    assert s.as_dict()["diverged"] is True


def test_a_belief_before_the_fault_is_false_until_the_fault_and_unit_faults_count():
    events = [found(4.0, 3, 2, 0.0), fault(6.0, 3, 2, 0.0),  # believed 2 s before it failed: 2 s false
              event(8.0, EventKind.UNIT_DIED, unit=4), event(8.3, EventKind.UNIT_LOST, unit=4, reason="silent"),
              fault(9.0, 7, None, 0.0), found(9.2, 7, None, 0.0)]
    s = score_flight(events, 12.0, diverged=False)
    f3, f4, f7 = s.faults
    assert not f3.found  # the only belief came before it
    assert (f4.unit, f4.rotor, f4.isolated) == (4, None, True) and f4.delay_s == pytest.approx(0.3)
    assert f7.isolated and f7.delay_s == pytest.approx(0.2)
    ((b,),) = [s.false_beliefs]
    assert (b.unit, b.rotor, b.duration_s, b.held_to_end) == (3, 2, pytest.approx(2.0), False)


def test_untrusted_records_are_ignored():
    events = [fault(1.0, 1, 1, 0.0), {"t_s": 1.1, "type": "fault_detected", "unit": "1", "rotor": 1},
              {"t_s": 1.2, "type": "fault_detected", "unit": True, "rotor": 1}, found(1.3, 0, 1, 0.0)]
    s = score_flight(events, 5.0, diverged=False)
    assert not s.faults[0].found and s.false_beliefs == ()


def test_a_flight_summary_scores_its_trial():
    """summary.json's `fault_isolation` of a real flight: paper 000's 3x2 spiral, noise on, unit 2 failing at 10 s
    untold (spiral_3x2_fdi cut to 12 s, before its second fault): found whole, within the deadline, nothing else."""
    from mars_link.config.scenario import load_scenario
    from mars_link.flight.metrics import summarize
    from mars_link.flight.runner import run_trial

    sc = load_scenario("spiral_3x2_fdi")
    sc.sim.duration_s = 12.0
    (score,) = summarize(sc, [run_trial(sc, 1)], 1)["fault_isolation"]
    assert score["faults_injected"] == 1 and score["faults_isolated_in_time"] == 1 and score["false_beliefs"] == 0
    (f,) = score["faults"]
    assert (f["unit"], f["rotor"], f["eta"], f["t_s"]) == (2, None, 0.0, 10.0)
    assert 0.0 < f["delay_s"] <= ISOLATION_DEADLINE_S and f["eta_error"] <= 0.1
