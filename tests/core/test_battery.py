"""Issue 15 item 5: batteries per unit. The world owns the packs (voltage under load, thrust that follows
it); the units measure them and report BATTERY_STATUS; a long hover crosses PX4's low and critical
levels with STATUSTEXT and the configured action (checked on the world's truth); a weak pack in a 3x2
makes the allocator move load off its unit; bad [battery] input is one line, exit 2."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.vehicles.vehicle_sim import VehicleSim
from mars_link.models.battery import FULL_CELL_V, PROPULSION, ocv_per_cell_v, soc_from_cell_v, thrust_scale
from mars_link.flight.build import build_flight
from mars_link.flight.engine import Engine
from mars_link.core.errors import UserInputError
from mars_link.config.scenario import scenario_from_dict
from sitl.battery import Packs

HOVER_3X2 = {"name": "hover", "assembly": {"layout": ["XXX", "XXX"], "tracked": "com"},
             "trajectory": {"kind": "hover", "duration_s": 8.0}, "control": {"ftc": "qp"}}


def test_pack_model_closed_forms() -> None:
    """OCV curve end points and inverse; I solves P = (E - I R) I; thrust max follows (V / V_full)^2."""
    assert ocv_per_cell_v(1.0) == pytest.approx(4.103, abs=1e-3) and ocv_per_cell_v(0.0) == pytest.approx(2.654, abs=1e-3)
    for soc in (0.05, 0.3, 0.5, 0.9):
        assert soc_from_cell_v(float(ocv_per_cell_v(soc))) == pytest.approx(soc, abs=2e-3)
    sc = scenario_from_dict({**HOVER_3X2, "assembly": {"layout": ["X"]}})
    packs = Packs(sc.battery, [1], 3.8)
    t = np.full(4, 1.275)  # the unit's hover thrust per rotor
    packs.add_power(t, 1.0)
    packs.step()
    p = float(PROPULSION["mars-real"].rotor_power_w(t).sum()) + 3.0
    e, r, i, v = 4 * FULL_CELL_V, 0.05, float(packs.current_a[0]), float(packs.voltage_v[0])
    assert (e - i * r) * i == pytest.approx(p, rel=1e-9) and v == pytest.approx(e - i * r)
    assert 60.0 < p < 90.0 and 4.0 < i < 6.0  # ~75 W for a 0.52 kg unit in hover (momentum theory, FM 0.6)
    assert packs.thrust_cap_n[0] == pytest.approx(3.8 * (v / e) ** 2)
    assert thrust_scale(2 * e, 4) == 1.0


def _command_long(sim: VehicleSim, gcs, cmd: int, p1: float = 0.0, p7: float = 0.0) -> list:
    msg = mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, 0, 0, 0, 0, 0, p7)
    return sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api")


def test_long_hover_runs_the_pack_to_low_then_critical_and_the_vehicle_lands() -> None:
    """`mars-link vehicle`'s in-process core on a 1x1 with a small pack (100 mAh at 20 %) and
    COM_LOW_BAT_ACT = 2: take off and hover; the pack crosses BAT_LOW_THR (STATUSTEXT, keeps hovering)
    and BAT_CRIT_THR (STATUSTEXT, lands); the world's truth shows it on the ground and disarmed, and
    BATTERY_STATUS follows the world's pack."""
    sc = scenario_from_dict({"name": "low", "assembly": {"layout": ["X"], "tracked": "com"},
                             "trajectory": {"kind": "hover"}, "sim": {"noise": False},
                             "battery": {"capacity_ah": 0.1, "initial_soc": 0.2, "com_low_bat_act": 2}})
    sim = VehicleSim(sc)
    gcs, dec = mavlink.MAVLink(None, 245, 190), mavlink.MAVLink(None, 0, 0)
    got: list = []
    seen: dict[str, tuple[float, float]] = {}  # STATUSTEXT -> (sim time, truth altitude)

    def feed(out) -> None:
        for o in out:
            if o.link == "api":
                for m in dec.parse_buffer(o.data) or []:
                    got.append(m)
                    if m.get_type() == "STATUSTEXT":
                        seen.setdefault(m.text, (sim.t_s, -float(sim.truth().position_ned_m[2])))

    try:
        for _ in range(30):
            feed(sim.step(sim.t_s))
        feed(_command_long(sim, gcs, 400, 1.0))
        feed(_command_long(sim, gcs, 22, 0.0, math.nan))
        alt = []
        for _ in range(3000):  # 30 s
            feed(sim.step(sim.t_s))
            alt.append(-float(sim.truth().position_ned_m[2]))
            if not sim.vehicle.armed and sim.t_s > 5.0:
                break
        texts = list(seen)
        low = next(t for t in texts if t.startswith("Low battery"))
        crit = next(t for t in texts if t.startswith("Critical battery"))
        assert crit.endswith(": landing")
        t_low, alt_low = seen[low]
        t_crit, alt_crit = seen[crit]
        assert t_crit > t_low and alt_low > 1.5 and alt_crit > 1.5  # crossed while hovering at 2 m
        soc_truth = float(sim.world.packs.soc[0])
        assert soc_truth < 0.07  # the world's pack is below the critical level by now
        assert not sim.vehicle.armed and sim.truth().on_ground and -sim.truth().position_ned_m[2] < 0.15
        assert "Landed" in texts
        bat = [m for m in got if m.get_type() == "BATTERY_STATUS"]
        assert bat and bat[-1].charge_state in (mavlink.MAV_BATTERY_CHARGE_STATE_CRITICAL,
                                               mavlink.MAV_BATTERY_CHARGE_STATE_EMERGENCY)
        # the unit's count against the world's charge drawn: within 1 % of the capacity
        drawn = float(sim.world.packs.drawn_c[0]) / (0.1 * 3600)
        assert sim.vehicle.battery.remaining == pytest.approx(0.2 - drawn, abs=0.01)
        print(f"low at {t_low:.1f} s ({low}), critical at {t_crit:.1f} s ({crit}), landed, "
              f"world soc {soc_truth:.3f}, reported {sim.vehicle.battery.remaining:.3f}")
    finally:
        sim.close()


def _fly_shares(weak_soc: float | None, ftc: str = "qp") -> tuple[np.ndarray, object]:
    doc = dict(HOVER_3X2, control={"ftc": ftc})
    if weak_soc is not None:
        doc["battery"] = {"units": [{"unit": 3, "initial_soc": weak_soc}]}
    flight = build_flight(scenario_from_dict(doc), 1)
    rows = []

    class Shares:
        def on_step(self, engine, view) -> bool:
            if view.t_s >= 6.0:
                rows.append(flight.world.rotor_thrust_n.reshape(-1, 4).sum(axis=1).copy())
            return False

    try:
        Engine(flight, [Shares()]).run()
    finally:
        flight.world.close()
    mean = np.mean(rows, axis=0)
    return mean / mean.sum(), flight


def test_a_weak_pack_in_a_3x2_sheds_load_to_the_fuller_units() -> None:
    """Hover 3x2 (default plant, qp): all packs full -> each unit carries 1/6; unit 3's pack at 15 % -> its
    reported voltage sags, the allocator's bounds follow, and its share drops (the others take it)."""
    even, _ = _fly_shares(None)
    weak, flight = _fly_shares(0.15)
    blind, _ = _fly_shares(0.15, "none")  # the pseudo-inverse splits evenly whatever the packs say
    print("shares % full packs:", np.round(even * 100, 2), " unit 3 at 15 %:", np.round(weak * 100, 2))
    assert np.allclose(even, 1 / 6, atol=0.002)
    assert weak[2] < even[2] - 0.012  # > 1.2 points of the total moved off unit 3
    assert np.allclose(blind, 1 / 6, atol=0.002)
    available = flight.coordinator.tracked_piece().coordinator.available  # (a docked flight: one piece)
    assert available[2] < 0.85 < available[0]
    truth = flight.world.truth().position_ned_m
    assert abs(truth[2] + 2.0) < 0.1 and math.hypot(truth[0], truth[1]) < 0.05  # it still hovers where asked


@pytest.mark.parametrize("table, needle", [
    ({"capacity_ah": 0}, "capacity_ah must be > 0"),
    ({"capacity_ah": -1.0}, "capacity_ah must be > 0"),
    ({"cells": 0}, "cells must be an integer 1..14"),
    ({"initial_soc": 1.5}, "initial_soc must be in [0, 1]"),
    ({"units": [{"unit": 9, "capacity_ah": 1.0}]}, "[[battery.units]]"),
    ({"units": [{"unit": 2, "capacity_ah": 0.0}]}, "[[battery.units]] #1 capacity_ah must be > 0"),
    ({"bat_low_thr": 0.05, "bat_crit_thr": 0.1}, "low >= critical >= emergency"),
    ({"com_low_bat_act": 1}, "com_low_bat_act must be 0"),
    ({"volts": 3}, "unknown key 'volts' in [battery]"),
])
def test_bad_battery_tables_are_one_line(table, needle) -> None:
    with pytest.raises(UserInputError) as e:
        scenario_from_dict({**HOVER_3X2, "battery": table}, "s.toml")
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_zero_capacity_at_the_cli_is_one_line_exit_2(tmp_path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text('name = "bad"\n[assembly]\nlayout = ["X"]\n[trajectory]\nkind = "hover"\n'
                    '[battery]\ncapacity_ah = 0\n', encoding="utf-8")
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", str(path), "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().count("\n") == 0 and "capacity_ah must be > 0" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists() or not any(out.iterdir())


def test_a_lone_unit_flying_itself_lands_on_its_own_critical_battery() -> None:
    """The unit firmware itself (as `sitl up --units N` runs it, here by direct calls): its own pack in the
    free-units world, COM_LOW_BAT_ACT = 2 among its parameters; after take-off it hovers until the critical
    level, says so, lands and disarms (on the world's truth)."""
    import dataclasses

    from mars_link.flight.build import make_free_units_world, make_unit
    from sitl.world import WorldConfig

    sc = scenario_from_dict({"name": "lone", "assembly": {"layout": ["X"], "tracked": "com"},
                             "trajectory": {"kind": "hover"}, "sim": {"noise": False},
                             "battery": {"capacity_ah": 0.1, "initial_soc": 0.12, "com_low_bat_act": 2}})
    world = make_free_units_world(sc, sc.model().vehicle, 1, 1, WorldConfig(500.0, 100.0, 1, False, battery=sc.battery))
    v = make_unit(sc, sc.model(), 1, coordinator_driven=False)
    assert v.params["COM_LOW_BAT_ACT"] == 2 and v.params["BAT1_CAPACITY"] == pytest.approx(100.0)
    try:
        took_off = False
        for k in range(2500):
            for p in world.sense():
                v.hil_service.take_sensors(p, world.unit_truth(1))
            if k == 20:
                assert v.arm() == mavlink.MAV_RESULT_ACCEPTED
                assert v.command_service.takeoff(math.nan) == mavlink.MAV_RESULT_ACCEPTED
            world.actuate(dataclasses.replace(v.hil_service.drive_motors(), unit_id=1))
            v.tick(world.t_s, world.t_s)  # heartbeats, streams and watchdogs (auto-disarm after landing)
            world.advance()
            took_off = took_off or -world.unit_truth(1).position_ned_m[2] > 1.5
            if took_off and not v.armed:
                break
        texts = [t for _, t in v.events]
        assert took_off and any(t.startswith("Low battery") for t in texts)
        assert any(t.startswith("Critical battery") and t.endswith(": landing") for t in texts)
        assert not v.armed and -world.unit_truth(1).position_ned_m[2] < 0.15  # landed, disarmed
        assert world.packs.soc[0] < 0.07
    finally:
        world.close()


def test_a_sagging_pack_is_not_read_as_a_rotor_fault() -> None:
    """Faults not told (the detector on), unit 3's pack at 12 %: 20 s of hover give no detection (the
    detector's thrust model clips as the packs do); a half rotor on unit 2 at 6 s is still found in < 0.5 s."""
    from mars_link.flight.runner import run_trial

    base = {"name": "fdi", "assembly": {"layout": ["XXX", "XXX"], "tracked": "com"},
            "trajectory": {"kind": "hover", "duration_s": 20.0}, "control": {"ftc": "qp", "faults_known": False},
            "battery": {"units": [{"unit": 3, "initial_soc": 0.12}]}}
    quiet = run_trial(scenario_from_dict(base), 1)
    assert quiet.completed and quiet.detections == []
    faulty = run_trial(scenario_from_dict({**base, "trajectory": {"kind": "hover", "duration_s": 10.0},
                                           "faults": [{"t": 6.0, "unit": 2, "rotor": 2, "eta": 0.5}]}), 1)
    d = faulty.detections[0]
    assert (d["unit"], d["rotor"]) == (2, 2) and d["t_detected"] - 6.0 < 0.5 and abs(d["eta_estimated"] - 0.5) < 0.15


def test_battery_table_round_trips_to_the_sitl_children(tmp_path) -> None:
    """`run --mode sitl` hands the child processes a TOML copy of the scenario: the packs go with it."""
    from mars_link.config.scenario import load_scenario
    from mars_link.processes.sitl_mode import write_scenario_copy

    sc = scenario_from_dict({**HOVER_3X2, "battery": {"capacity_ah": 1.5, "com_low_bat_act": 3,
                                                      "units": [{"unit": 3, "initial_soc": 0.3, "cells": 3}]}})
    back = load_scenario(str(write_scenario_copy(sc, tmp_path / "copy.toml")))
    assert back.battery == sc.battery and back.preset == "mars-real"
    off = scenario_from_dict({**HOVER_3X2, "battery": {"enabled": False}})
    assert off.battery is None and load_scenario(str(write_scenario_copy(off, tmp_path / "off.toml"))).battery is None
