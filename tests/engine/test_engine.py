"""The one engine: the composition root builds the parts, the loop runs them in one order, the units
are their firmware in-process too, and pacing is a parameter."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_models.vehicle import MODE_OFFBOARD
from mars_link.flight.build import build_flight
from mars_link.flight.engine import Engine
from mars_link.flight.recorder import FlightRecorder
from mars_link.core.messages import RotorCommand
from mars_link.runtime.pacing import Pacer
from mars_link.flight.runner import run_trial
from mars_link.config.scenario import FaultSpec, load_scenario


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _fly(scenario) -> tuple:
    """One in-process flight through the engine (build_flight + Engine + FlightRecorder)."""
    flight = build_flight(scenario, 1)
    engine = Engine(flight, [FlightRecorder(flight)])
    try:
        engine.run()
    finally:
        flight.world.close()
    return flight, engine


def test_pacer_keeps_sim_time_on_the_wall_clock_at_its_rate() -> None:
    clock = _Clock()
    pacer = Pacer(2.0, clock=clock)  # twice real time
    pacer.start(0.0)
    assert pacer.is_due(0.0) and not pacer.is_due(1.0)
    assert pacer.wait_s(1.0) == pytest.approx(0.5)
    clock.now += 0.5
    assert pacer.is_due(1.0)
    clock.now += 5.0  # far behind: re-anchored, not raced
    assert pacer.is_due(1.01) and pacer.overruns == 1
    assert not pacer.is_due(2.0) and pacer.wait_s(2.0) == pytest.approx(0.495)
    assert Pacer(0.0).is_due(1e9)  # rate 0: as fast as possible
    with pytest.raises(ValueError):
        Pacer(-1.0)


def test_inprocess_units_are_their_firmware_and_take_every_command() -> None:
    scenario = load_scenario("hover_3x2")
    scenario.sim.duration_s = 2.0
    flight, engine = _fly(scenario)
    assert engine.steps == 200
    for u, v in flight.units.vehicles.items():
        assert v.armed and v.mode == MODE_OFFBOARD and v.source == "coordinator"
        assert v.stats["rotor_commands"] == 200 and v.stats["hil_steps"] == 200
        assert v.drop_counts() == {}
    # the unit's own intake checks apply in-process: a command beyond full scale is dropped, not flown
    v = flight.units.vehicles[1]
    held = v.intake.command_n(v.sim_s).copy()
    too_much = RotorCommand(v.sim_s + 0.01, 1, np.full(4, 2 * v.full_scale_n))
    assert not v.hil_service.take_rotor_command(too_much)
    assert v.drop_counts() == {"intake.out_of_range": 1} and np.array_equal(v.intake.command_n(v.sim_s), held)


def test_faults_act_in_the_unit_motor_model_not_in_the_coordinator() -> None:
    scenario = load_scenario("hover_3x2")
    scenario.sim.duration_s = 3.0
    scenario.faults = [FaultSpec(unit=2, rotor=3, eta=0.5, t_s=1.0)]
    scenario.faults_known = False
    flight, engine = _fly(scenario)
    assert flight.units.vehicles[2].motors.eta.tolist() == [1.0, 1.0, 0.5, 1.0]
    assert all(v.motors.eta.tolist() == [1.0] * 4 for u, v in flight.units.vehicles.items() if u != 2)
    fault = next(e for e in engine.events if e["type"] == "fault")
    assert fault["t_s"] == pytest.approx(1.0)
    found = [d for d in flight.coordinator.detections if d.unit == 2 and d.rotor == 3]
    assert found and 1.0 < found[0].t_detected < 1.5  # learnt from the residuals, not told


def test_inprocess_real_time_run_is_paced_to_the_wall_clock() -> None:
    scenario = load_scenario("hover_1x1")
    scenario.sim.duration_s = 2.0
    r = run_trial(scenario, 1, realtime_rate=1.0)
    assert r.completed and r.sim_time_s == pytest.approx(2.0)
    # never ahead of the wall clock; a loaded machine may only make it later
    assert r.wall_time_s >= 0.98 * r.sim_time_s
    fast = run_trial(scenario, 1)
    assert fast.mean_error_m == r.mean_error_m  # pacing changes when, never what


def test_wire_thrust_fast_path_rounds_exactly_as_numpy_float32() -> None:
    """One unit's rotors go through struct's float32 packing (cheaper): the same bits as numpy's cast."""
    from mars_link.core.messages import f32, wire_thrust

    rng = np.random.default_rng(7)
    for n in (1, 4, 8, 24):
        for _ in range(2000):
            x = rng.normal(0.0, 3.0, n) * 10 ** rng.uniform(-8, 3)
            assert np.array_equal(wire_thrust(x, 5.099458), f32(x / 5.099458) * 5.099458)
    special = np.array([np.nan, np.inf, -np.inf, 1e300])
    with np.errstate(over="ignore"):
        assert np.array_equal(wire_thrust(special, 5.0), f32(special / 5.0) * 5.0, equal_nan=True)
