"""The fault detector in moving air and at take-off, on the real in-process loop (JSBSim physics, the units'
motor models, sensor noise and the EKF; faults never told): a gust is not a fault, a partial rotor loss in
moderate turbulence is found with its efficiency, a dead corner unit in light air is found as fast as in still
air, and a unit dead before take-off is found once aloft
(the air-aware detector measures the residuals' spread aloft; that must not teach it a dead unit as normal)."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.vehicles.vehicle_sim import VehicleSim
from mars_link.flight.runner import run_trial
from mars_link.config.scenario import FaultSpec, load_scenario

pytestmark = pytest.mark.slow


def test_a_gust_is_not_a_fault() -> None:
    """The 3x2 hover meets a 5 m/s 1-cosine gust at 8-11 s: it is pushed off its point (the gust acts), and
    the detector, watching all along, reports nothing."""
    sc = load_scenario("hover_3x2_gust")
    sc.sim.duration_s = 12.0
    sc.faults_known = False
    r = run_trial(sc, 1)
    assert r.completed and r.max_error_m > 0.05, r.max_error_m  # the gust moved the assembly
    assert r.detections == []


def test_a_half_rotor_in_moderate_turbulence_is_found_with_its_eta() -> None:
    """Unit 2 rotor 2 at half thrust from 10 s of the spiral in 5 m/s wind and moderate turbulence: that
    rotor and no other, within 0.5 s, its efficiency within 0.15."""
    sc = load_scenario("spiral_3x2_wind")
    sc.sim.duration_s = 10.8
    sc.faults_known = False
    sc.faults.append(FaultSpec(2, 2, 0.5, 10.0))
    r = run_trial(sc, 1)
    found = [(d["unit"], d["rotor"]) for d in r.detections]
    assert found == [(2, 2)], r.detections
    d = r.detections[0]
    assert 10.0 <= d["t_detected"] < 10.5
    assert abs(d["eta_estimated"] - 0.5) <= 0.15


def test_a_dead_corner_unit_in_light_air_is_found_as_fast_as_in_still_air() -> None:
    """Unit 3 (a corner of the 3x2) dead at 10 s of the spiral in 5 m/s wind and light turbulence: a loss that
    large decides at the still-air min_isolation_s (0.06 s after its onset), not after the 0.18 s that gusty air
    asks of smaller losses (0.2 s on the wrong allocation lost this flight). Unit 3 and nothing else."""
    from mars_link.apps.reproduce import CASES, scenario_for

    case = next(c for c in CASES if c.name == "F3 units {3}")
    air = {"wind_ned_mps": [5.0, 0.0, 0.0], "turbulence": "light"}
    r = run_trial(scenario_for(case, "cascaded", "qp", 10.6, 10.0, False, air, None), 1)
    found = [(d["unit"], d["rotor"]) for d in r.detections]
    assert found == [(3, None)], r.detections
    assert 10.0 < r.detections[0]["t_detected"] < 10.12, r.detections


@pytest.mark.parametrize("esc", [True, False], ids=["esc", "motion-alone"])
def test_a_unit_dead_before_take_off_is_found_once_aloft(esc: bool) -> None:
    """`mars-link vehicle`'s 3x2 with unit 2 dead from the start, armed (at 0.3 s) and taking off by
    COMMAND_LONG bytes: the coordinator names unit 2 failed, the flight's only detection. Its ESCs show it
    within a few samples of the first commanded thrust; from motion alone, soon after lift-off."""
    sc = load_scenario("hover_3x2")
    sc.ftc, sc.faults_known, sc.esc_telemetry = "hybrid", False, esc
    sc.faults.append(FaultSpec(unit=2, rotor=None, eta=0.0, t_s=0.0))
    sim = VehicleSim(sc)
    gcs = mavlink.MAVLink(None, 245, 190)
    try:
        for _ in range(30):
            sim.step(sim.t_s)
        for cmd, p1 in ((400, 1.0), (22, 0.0)):  # arm, take off (MIS_TAKEOFF_ALT)
            msg = mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, 0, 0, 0, 0, 0, math.nan if cmd == 22 else 0.0)
            sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api")
        z0 = float(sim.vehicle.home_ned[2])
        while sim.t_s < 4.0:
            sim.step(sim.t_s)
        found = [(d.unit, d.rotor, d.t_detected) for d in sim.coordinator.detections]
        assert [(u, r) for u, r, _ in found] == [(2, None)], found
        assert (0.3 < found[0][2] < 0.45) if esc else (0.5 < found[0][2] < 2.5), found
        assert z0 - sim.truth().position_ned_m[2] > 1.0  # it climbed on the five live units
    finally:
        sim.close()


@pytest.mark.parametrize("seed", [5, 13])
def test_gusts_just_after_take_off_are_not_faults(seed: int) -> None:
    """The first 3 s of the moderate-turbulence spiral, seeds whose gusts raised the alarm within 0.4 s of
    lift-off, before the detector had measured the air (it named u4r4 at 1.0 s and u1r1 at 1.46 s when it
    judged those fits against its still-air models): nothing is reported."""
    from mars_link.apps.reproduce import fdi_false_alarm_flight

    air = {"wind_ned_mps": [5.0, 0.0, 0.0], "turbulence": "moderate"}
    assert fdi_false_alarm_flight(seed, "qp", 3.0, "cascaded", air, None) == []
