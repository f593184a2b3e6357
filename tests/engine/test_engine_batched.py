"""The in-process units' batched steady state (InProcessUnits._drive_steady, HilService.drive_steady) flies
exactly as the units taken one by one: the same motor setpoints into the world at every step, the same
counts and drops in every unit, across faults, a unit's death, a separation and bad commands."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import sitl.world
from mars_link.flight.build import build_flight
from mars_link.flight.engine import Engine, InProcessUnits
from mars_link.flight.recorder import FlightRecorder
from mars_link.core.messages import RotorCommand
from mars_link.flight.runner import run_trial
from mars_link.config.scenario import FaultSpec, load_scenario


def _setpoints_into_the_world(monkeypatch, fly) -> tuple[list, object]:
    """(every world step's (time, rotor setpoints) as they were integrated, fly()'s result)."""
    seen = []
    advance = sitl.world.World.advance

    def recording(world) -> None:
        seen.append((world.t_s, world.rotor_setpoint_n.copy()))
        advance(world)

    monkeypatch.setattr(sitl.world.World, "advance", recording)
    result = fly()
    monkeypatch.setattr(sitl.world.World, "advance", advance)
    return seen, result


def _both_ways(monkeypatch, fly) -> tuple:
    out = {}
    for batched in (False, True):
        monkeypatch.setattr(InProcessUnits, "batched", batched)
        out[batched] = _setpoints_into_the_world(monkeypatch, fly)
    return out[False], out[True]


def _assert_same_setpoints(one_by_one: list, batched: list) -> None:
    assert len(one_by_one) == len(batched) > 100
    for (t_a, sp_a), (t_b, sp_b) in zip(one_by_one, batched):
        assert t_a == t_b and np.array_equal(sp_a, sp_b), f"setpoints differ at t = {t_a}"


def _hover_with_faults():
    sc = load_scenario("hover_3x2")
    sc.sim.duration_s = 4.0
    sc.faults = [FaultSpec(unit=2, rotor=3, eta=0.5, t_s=1.0), FaultSpec(unit=5, rotor=None, eta=0.0, t_s=2.5)]
    sc.faults_known = False
    return sc


def test_batched_units_fly_a_faulted_hover_with_a_death_exactly_as_one_by_one(monkeypatch) -> None:
    units = {}

    def fly():
        flight = build_flight(_hover_with_faults(), 3, unit_deaths={4: 2.0})
        engine = Engine(flight, [FlightRecorder(flight)])
        try:
            engine.run()
        finally:
            flight.world.close()
        units[InProcessUnits.batched] = flight.units
        return engine

    (a, engine_a), (b, engine_b) = _both_ways(monkeypatch, fly)
    _assert_same_setpoints(a, b)
    assert engine_a.events == engine_b.events and any(e["type"] == "unit_died" for e in engine_b.events)
    for u, va in units[False].vehicles.items():
        vb = units[True].vehicles[u]
        assert va.stats == vb.stats and va.intake.counters == vb.intake.counters, f"unit {u}"
        assert va.intake.accepted == vb.intake.accepted and va.intake.lost_events == vb.intake.lost_events
        assert np.array_equal(va.motors.eta, vb.motors.eta) and va.mode == vb.mode and va.armed == vb.armed
    # the batch really ran: the healthy units' steady state, and it is most of the flight
    assert units[True].vehicles[1].stats["hil_steps"] == 400


def test_batched_units_fly_a_separation_and_redock_exactly_as_one_by_one(monkeypatch) -> None:
    sc = load_scenario("separate_3x2")  # latches open, the 2x1 flies off, and docks back (sooner than as shipped)
    sc.separations = [dataclasses.replace(sc.separations[0], t_s=6.0, redock_t_s=12.0)]
    sc.trajectory["duration_s"] = 16.0

    def fly():
        return run_trial(sc, 2)

    (a, ra), (b, rb) = _both_ways(monkeypatch, fly)
    _assert_same_setpoints(a, b)
    assert ra.events == rb.events and {"separation", "split", "dock_latched"} <= {e["type"] for e in rb.events}
    assert ra.pieces_final == rb.pieces_final and len(rb.pieces_final) == 1


def test_batched_drops_bad_commands_exactly_as_one_by_one() -> None:
    """Out of range, not finite and out of order commands, and a latch opened, in the middle of a steady
    flight: the same drops counted in the same units, and the same setpoints and latches in the world."""
    worlds = {}
    for batched in (False, True):
        sc = load_scenario("hover_3x2")
        sc.sim.duration_s = 1.0
        flight = build_flight(sc, 1)
        Engine(flight, [FlightRecorder(flight)]).run()
        units = flight.units
        units.batched = batched
        v1 = units.vehicles[1]
        t = v1.sim_s + 1e-3
        full = v1.full_scale_n
        ok = np.full(4, 0.3 * full)
        steps = [
            [RotorCommand(t, u, ok * (4.0 if u == 3 else 1.0)) for u in units.vehicles],  # unit 3 out of range
            [RotorCommand(t + 1e-3, u, np.array([0.3 * full, np.nan, 0.3 * full, 0.3 * full]) if u == 2 else ok)
             for u in units.vehicles],  # unit 2 not finite: the whole step takes the general path
            [RotorCommand(t + 1e-3, u, ok * 0.9) for u in units.vehicles],  # out of order for all but unit 2
            [RotorCommand(t + 2e-3, u, ok, 0 if u == 4 else 15) for u in units.vehicles],  # unit 4 opens its latches
        ]
        setpoints = []
        for commands in steps:
            units.drive(commands)
            setpoints.append(flight.world.rotor_setpoint_n.copy())
        worlds[batched] = (setpoints, {u: dict(v.intake.counters) for u, v in units.vehicles.items()},
                           {u: dict(v.stats) for u, v in units.vehicles.items()}, dict(flight.world.latches.setpoint))
        flight.world.close()
    (sp_a, drops_a, stats_a, latches_a), (sp_b, drops_b, stats_b, latches_b) = worlds[False], worlds[True]
    assert drops_a == drops_b and stats_a == stats_b and latches_a == latches_b and latches_b[4] == 0
    assert all(np.array_equal(x, y) for x, y in zip(sp_a, sp_b))
    assert drops_b[3]["out_of_range"] == 1 and drops_b[2]["non_finite"] == 1
    assert drops_b[1]["out_of_order"] == 1 and "out_of_order" not in drops_b[2]


@pytest.mark.parametrize("layout", ["XXX,XXX", "XXXXX,XXXXX,XXXXX,XXXXX,XXXXX"])
def test_batched_helix_summary_equals_one_by_one(monkeypatch, layout) -> None:
    from mars_link.core.assembly import parse_layout

    sc = load_scenario("helix_plus5")
    sc.layout = parse_layout(layout)
    sc.ftc = "qp"
    sc.sim.noise = True
    sc.sim.duration_s = 2.0

    def fly():
        return run_trial(sc, 5)

    (a, ra), (b, rb) = _both_ways(monkeypatch, fly)
    _assert_same_setpoints(a, b)
    assert ra.mean_error_m == rb.mean_error_m and ra.max_error_m == rb.max_error_m


def test_batched_esc_samples_equal_one_by_one(monkeypatch) -> None:
    """Every unit's ESC sample taken for all units at once (mars_link.models.esc.sample_steady) equals the
    units' own (EscSensor.sample), bit for bit: through a motor lag (mars-real), sensor noise, a damaged
    propeller, a lost one, a stopped motor and one unit's telemetry stuck (those steps sample unit by unit)."""
    from mars_link.config.scenario import scenario_from_dict
    from tests.estimation.test_esc import _doc

    doc = _doc([{"t": 0.8, "unit": 2, "rotor": 3, "eta": 0.5}, {"t": 1.3, "unit": 3, "rotor": 1, "kind": "prop-loss", "eta": 0.3},
                {"t": 1.9, "unit": 5, "rotor": 2, "kind": "motor-stop"}], duration_s=3.0, seed=4)
    doc["vehicle"] = {"preset": "mars-real"}
    doc["sensor_faults"] = [{"t": 2.2, "sensor": "esc", "type": "stuck", "unit": 6}]
    samples: dict[bool, list] = {}

    def fly():
        flight = build_flight(scenario_from_dict(doc, "test"), 4)
        seen = samples.setdefault(InProcessUnits.batched, [])

        class Watch:
            def on_step(self, engine, view) -> bool:
                seen.append([(p.unit_id, p.esc) for p in view.telemetry])
                return False

        Engine(flight, [Watch()]).run()
        flight.world.close()
        return flight

    import mars_link.flight.engine as engine_module

    passes: list[bool] = []  # per step of the batched flight: whether the one pass sampled every unit
    one_pass = engine_module.sample_steady

    def counted(*args):
        out = one_pass(*args)
        passes.append(out is not None)
        return out

    monkeypatch.setattr(engine_module, "sample_steady", counted)
    (a, _), (b, _) = _both_ways(monkeypatch, fly)
    _assert_same_setpoints(a, b)
    assert samples[False] == samples[True]
    assert passes.count(True) > 100 and passes.count(False) > 100  # (after the faults: unit by unit)
    taken = [s for step in samples[True] for _, s in step if s is not None]
    assert len(taken) > 6 * 100 and len({s.rpm for s in taken}) > 100  # (noisy samples, every other step)
