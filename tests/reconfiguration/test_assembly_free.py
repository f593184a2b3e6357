"""The modular life cycle, first part: a world of several rigid bodies, and free units that take off and
assemble in the air (paper 001's Algorithm 3 order) before they fly the mission as one body."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest

from mars_link.core.assembly import AssemblyModel
from mars_link.flight.build import build_flight
from mars_link.flight.engine import Engine
from mars_link.flight.run_log import TELEMETRY_COLUMNS
from mars_link.flight.runner import run_trial
from mars_link.reconfig.sequencing import plan_assembly
from mars_link.core.rotations import euler_to_quat
from mars_link.config.scenario import load_scenario
from mars_link.core.state import RigidBodyState
from sitl.docking import momentum
from sitl.world import World, WorldConfig


def _world_momentum(world: World, about: np.ndarray):
    return momentum([b.jsbsim.state() for b in world.bodies], [b.model for b in world.bodies], about_ned_m=about)


def test_world_splits_and_merges_its_bodies_keeping_momentum() -> None:
    model = AssemblyModel.from_layout("XXX", "mars-ftcc")
    state = RigidBodyState(0.0, np.array([1.0, 2.0, -5.0]), np.array([0.4, -0.3, 0.1]),
                           euler_to_quat(0.05, -0.03, 0.7), np.array([0.2, -0.1, 0.3]))
    world = World.of_bodies(model, WorldConfig(physics_hz=500, exchange_hz=100, noise=False),
                            [(model, (1, 2, 3), state, (0.0, 0.0, 0.0))])
    try:
        about = state.position_ned_m
        p0, l0 = _world_momentum(world, about)
        one = AssemblyModel.from_layout("X", model.vehicle)
        two = AssemblyModel.from_layout("XX", model.vehicle)
        off23 = (model.unit_position(2) + model.unit_position(3)) / 2
        world.split((1, 2, 3), [(one, (1,), model.unit_position(1)), (two, (2, 3), off23)])
        assert [b.units for b in world.bodies] == [(1,), (2, 3)]
        assert world.body_of(1) is not world.body_of(2) and world.body_of(2) is world.body_of(3)
        p1, l1 = _world_momentum(world, about)
        assert np.allclose(p1, p0, atol=1e-9) and np.allclose(l1, l0, atol=1e-9)
        # the world senses every unit of every body, in unit order, each from its own body
        packets = world.sense()
        assert [p.unit_id for p in packets] == [1, 2, 3]
        assert np.allclose(world.unit_truth(1).position_ned_m, packets[0].truth.position_ned_m, atol=1e-5)
        world.merge(2, 1, model, (1, 2, 3))
        assert len(world.bodies) == 1 and world.bodies[0].units == (1, 2, 3)
        p2, l2 = _world_momentum(world, world.bodies[0].jsbsim.state().position_ned_m)
        assert np.allclose(p2, p0, atol=1e-9)
        assert world.min_clearance_m() == np.inf  # one body: nothing to collide with
    finally:
        world.close()


def test_assembly_plan_takes_the_fewest_docking_layers() -> None:
    # ceil(log2 N) for rectangles; the plus needs 4: every straight cut of it peels off one arm
    for rows, layers in ((["XXX", "XXX"], 3), (["XXXX"] * 4, 4), ([".X.", "XXX", ".X."], 4), (["XX"], 1)):
        model = AssemblyModel.from_layout(rows, "mars-ftcc")
        plan = plan_assembly(model)
        assert plan.feasible and plan.assembly_layers == layers, (rows, plan.assembly_layers)
        assert plan.disassembly_layers == 0 and sorted(map(tuple, plan.pieces)) == [(u,) for u in model.unit_ids]
        # every merge joins two pieces that exist at that layer; the last one leaves the whole structure
        pieces = {frozenset([u]) for u in model.unit_ids}
        for layer in range(1, layers + 1):
            for m in (m for m in plan.merges if m.layer == layer):
                a, b = frozenset(m.stationary), frozenset(m.mover)
                assert a in pieces and b in pieces
                pieces -= {a, b}
                pieces.add(a | b)
        assert pieces == {frozenset(model.unit_ids)}


def test_six_free_units_assemble_into_the_3x2_and_fly_the_spiral() -> None:
    """Six units 2 m apart on the ground take off, dock in three layers into the 3x2 (each latch within
    the scenario's tolerance, no two bodies overlapping at any step), and the spiral then starts: its
    error is within 1.2x of the docked 3x2's on the same spiral. Sensor noise on: every piece flies on
    its own EKF; a dock hands the stationary piece's estimate, moved to the new CoM, to the new piece."""
    scenario = load_scenario("assemble_3x2")
    r = run_trial(scenario, 1)
    assert r.completed and not r.diverged and r.assembled
    assert r.pieces_final == [{"layout": ["XXX", "XXX"], "units": [1, 2, 3, 4, 5, 6]}]
    docks = [e for e in r.events if e["type"] == "dock"]
    assert sorted((e["layer"], e["result"]) for e in docks) == [
        (1, [2, 3]), (1, [5, 6]), (2, [1, 2, 3]), (2, [4, 5, 6]), (3, [1, 2, 3, 4, 5, 6])]
    latches = [e for e in r.events if e["type"] == "dock_latched"]
    # (the event rounds to 0.1 mm and 0.1 mm/s: the latch itself checks the strict limits)
    tol = scenario.docking
    assert len(latches) == 5 and all(e["position_error_m"] <= tol["position_m"] and e["speed_mps"] <= tol["speed_mps"]
                                     and e["yaw_deg"] <= tol["yaw_deg"] for e in latches)
    assert r.min_clearance_m >= 0.0, r.min_clearance_m  # bodies touch only at the latch: no overlap at any step
    start = next(e["t_s"] for e in r.events if e["type"] == "mission_resumed")
    assert start > next(e["t_s"] for e in r.events if e["type"] == "assembly_done")  # the clock starts after
    # the mission flown after the structure was complete, against the docked 3x2 on the same spiral
    docked = load_scenario("spiral_3x2")
    docked.ftc = "qp"
    assert scenario.sim.noise and docked.sim.noise
    baseline = run_trial(docked, 1)
    assert r.mean_error_m <= 1.2 * baseline.mean_error_m, (r.mean_error_m, baseline.mean_error_m)
    assert r.sim_time_s == pytest.approx(start + baseline.sim_time_s, abs=0.02)


@pytest.mark.parametrize("extra, message", [
    ('free_spacing_m = 0.2', "overlapping"),
    ('start = "parked"', "start must be"),
])
def test_bad_free_start_is_one_line_exit_2(tmp_path, extra, message) -> None:
    path = tmp_path / "s.toml"
    path.write_text(f'name = "t"\n[assembly]\nlayout = ["XX"]\nstart = "free"\n{extra}\n[sim]\nnoise = false\n'
                    .replace('start = "free"\nstart', 'start'))
    p = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", str(path), "--quiet", "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and message in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_free_start_with_told_faults_is_refused_in_both_modes(tmp_path) -> None:
    """Told faults are planned for before flight, which a free start (assembled first) cannot use: one line,
    exit 2 (faults found in flight are what a free start takes)."""
    path = tmp_path / "s.toml"
    path.write_text('name = "t"\n[assembly]\nlayout = ["XX"]\nstart = "free"\n[control]\nfaults_known = true\n'
                    '[sim]\nnoise = false\n[[faults]]\nt = 5.0\nunit = 1\nrotor = 1\neta = 0.5\n')
    for argv in (["run", str(path)], ["run", str(path), "--mode", "sitl"]):
        p = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", *argv, "--quiet", "--out", str(tmp_path / "o")],
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
        assert "faults_known = false" in p.stderr


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_assemble_then_a_fault_found_in_flight_reconfigures_and_the_spiral_resumes_where_it_paused() -> None:
    """assemble_fault_reconfig: six free units assemble into the 3x2 and fly the spiral; unit 1 loses three
    rotors at t = 70 s and nobody tells the coordinator. Its detector finds them, it plans from what it
    found, splits, moves the pieces, docks, and the spiral resumes at the mission time where it paused."""
    r = run_trial(load_scenario("assemble_fault_reconfig"), 1)
    assert r.completed and not r.diverged and r.assembled and r.reconfigured
    found = [e for e in r.events if e["type"] == "fault_detected"]
    assert sorted((e["unit"], e["rotor"]) for e in found) == [(1, 1), (1, 3), (1, 4)]
    assert all(70.0 <= e["t_s"] < 70.5 for e in found)
    kinds = [e["type"] for e in r.events]
    assert kinds.count("assembly_done") == 1 and kinds.count("reconfig_done") == 1
    assert kinds.index("assembly_done") < kinds.index("fault_detected") < kinds.index("reconfig_start")
    assert all(e["position_error_m"] <= 0.02 for e in r.events if e["type"] == "dock_latched")
    (final,) = r.pieces_final
    assert final["layout"] == ["XXX", "XXX"] and sorted(final["units"]) == [1, 2, 3, 4, 5, 6]
    assert final["units"] != [1, 2, 3, 4, 5, 6]  # the faulty unit moved
    tel = np.array(r.telemetry_rows)  # the mission clock stands still over the manoeuvre
    t, mission_t = tel[:, TELEMETRY_COLUMNS.index("t_s")], tel[:, TELEMETRY_COLUMNS.index("mission_t_s")]
    start = next(e["t_s"] for e in r.events if e["type"] == "reconfig_start")
    before, after = np.flatnonzero(t <= start + 1e-9)[-1], np.flatnonzero(t > start)[0]
    assert mission_t[after] - mission_t[before] < 0.05 and t[after] - t[before] > 10.0
    assert r.mean_error_m < 0.02 and math.isfinite(r.min_clearance_m)


@pytest.mark.long  # (CI time: a whole life cycle in process, about 30 s)
def test_a_unit_lost_while_reconfiguring_after_a_fault_found_leaves_the_pieces_apart_and_the_flight_ends() -> None:
    """assemble_fault_reconfig, seed 5, unit 5's process dies at 76.94 s, after the split of the manoeuvre
    the found fault started: the manoeuvre is abandoned and the mission resumes on the pieces there are. The
    detection the loss makes then asks for a plan, which cannot be made from two pieces: refused, said once,
    and the flight flies to its end (the coordinator raised ValueError there, in SITL a dead coordinator
    process, met when a loaded machine made the coordinator lose a unit over UDP)."""
    sc = dataclasses.replace(load_scenario("assemble_fault_reconfig"), faults_known=False)
    flight = build_flight(sc, 5, {5: 76.94})
    engine = Engine(flight)
    try:
        while engine.step():
            pass
    finally:
        flight.world.close()
    coord = flight.coordinator
    kinds = [e["type"] for e in sorted(coord.events + coord.executor.events, key=lambda e: e["t_s"])]
    assert kinds.index("split") < kinds.index("unit_lost") < kinds.index("reconfig_abandoned")
    assert kinds.count("reconfig_refused") == 1 and "reconfig_done" not in kinds and coord.failed is None
    assert len(coord.pieces) == 2 and flight.world.t_s >= flight.end_s() - 1e-9
