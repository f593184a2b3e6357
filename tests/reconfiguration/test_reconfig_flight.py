"""Reconfiguration executed in flight (mars_link/flight/recorder.py): several JSBSim bodies, split and
docked, FTC on every piece; paper 000's docking scenario; `mars-link run` dispatch and bad input."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mars_link.flight.build import make_trajectory
from mars_link.flight.run_log import TELEMETRY_COLUMNS
from mars_link.flight.runner import run_trial
from mars_link.reconfig.plans import make_plan, unhoverable_pieces
from mars_link.config.scenario import eta_after
from mars_link.config.scenario import load_scenario, scenario_from_dict

FAST = {"at_s": 5.0, "speed_mps": 0.6, "approach_speed_mps": 0.3, "settle_s": 0.5, "stop_s": 1.0}


def docking(ftc: str):
    sc = load_scenario("docking_3x1")
    sc.ftc = ftc
    sc.reconfig.update(FAST)
    sc.trajectory["duration_s"] = 7.0
    return sc


def yaw_deviation_deg(result, unit: int = 3) -> float:
    """Max |yaw - yaw just before the separation| of `unit`, from the separation to 2 s after the dock."""
    rows = np.array([r for r in result.unit_rows if int(r[1]) == unit])
    t, yaw = rows[:, 0], rows[:, 10]
    split = next(e["t_s"] for e in result.events if e["type"] == "split")
    dock = next(e["t_s"] for e in result.events if e["type"] == "dock")
    yaw0 = yaw[(t >= split - 0.5) & (t < split)].mean()
    window = (t >= split) & (t <= dock + 2.0)
    return float(np.max(np.abs((yaw[window] - yaw0 + 180) % 360 - 180)))


def test_docking_scenario_faulty_unit_yaw_ours_vs_baseline():
    ours = run_trial(docking("qp"), 1)
    base = run_trial(docking("none"), 1)
    for r in (ours, base):
        kinds = [e["type"] for e in r.events]
        assert r.completed and r.reconfigured, r.events
        assert kinds.count("split") == 1 and kinds.count("dock") == 1 and "mission_resumed" in kinds
        split = next(e for e in r.events if e["type"] == "split")
        assert split["detached"] == [1] and split["rest"] == [2, 3]
        latch = next(e for e in r.events if e["type"] == "dock_latched")
        assert latch["position_error_m"] <= 0.02 and latch["speed_mps"] <= 0.05 and latch["yaw_deg"] < 2.0
        # unit 1 docked on the far side of the faulty unit: order 2-3-1 from left to right
        cells = next(e for e in r.events if e["type"] == "reconfig_done")["cells"]
        assert cells["2"][1] < cells["3"][1] < cells["1"][1] and len({c[0] for c in cells.values()}) == 1
    # paper 000's claim: the faulty unit's yaw varies by at most 1 deg with FTC; the baseline
    # (the controller ignores the dead rotor) swings by more
    assert yaw_deviation_deg(ours) <= 1.0
    assert yaw_deviation_deg(base) > 1.0 > yaw_deviation_deg(ours)
    # back on the mission after the manoeuvre: the whole 3x1 holds the hover point again
    assert ours.telemetry_rows[-1][TELEMETRY_COLUMNS.index("error_m")] < 0.05


def test_unit_one_really_flew_round():
    """Unit 1 leaves its row, flies at its own altitude to the far side and comes back down."""
    r = run_trial(docking("qp"), 1)
    u1 = np.array([row for row in r.unit_rows if int(row[1]) == 1])
    u3 = np.array([row for row in r.unit_rows if int(row[1]) == 3])
    assert u1[:, 3].min() < u3[0, 3] - 0.7 and u1[-1, 3] > u3[-1, 3] + 0.3  # east: from the left to the right
    assert u1[:, 4].min() < u3[:, 4].min() - 0.5  # it climbed above the others on the way (NED: down)
    assert abs(u1[-1, 4] - u3[-1, 4]) < 0.01


def test_flight_plans_only_use_pieces_that_can_hover():
    """Donut 4x4 with a dead corner module: paper 001's quadrant rule alone plans a piece [1, 2, 3]
    that cannot hover within the ModQuad thrust limits (the executor's guard names it); the flight
    planner adds the exact hover LP to the rule, so none of its pieces fails, and with the dead
    module no reachable allocation beats the current one. With 3 dead rotors both rules agree."""
    from mars_link.reconfig.placement import SnapWeights, health_from_eta
    from mars_link.reconfig.sequencing import plan_reconfiguration

    def donut(faults):
        return scenario_from_dict({
            "vehicle": {"preset": "modquad-cf2"}, "assembly": {"layout": ["XXXX", "X..X", "X..X", "XXXX"]},
            "trajectory": {"kind": "hover"}, "control": {"ftc": "qp"},
            "faults": [{"unit": 1, "rotor": r, "eta": 0.0} for r in faults],
            "sim": {"noise": False}, "reconfig": {"enabled": True}})

    for faults, quadrant_rule_bad in (((1, 2, 3, 4), True), ((1, 3, 4), False)):
        sc = donut(faults)
        model = sc.model()
        eta = eta_after(model, sc.faults, math.inf)
        paper = plan_reconfiguration(model, health_from_eta(model, eta), SnapWeights())
        bad = unhoverable_pieces(paper, model, eta)
        assert paper.feasible and paper.disassembly_layers >= 1
        assert bool(bad) is quadrant_rule_bad, bad
        if quadrant_rule_bad:
            assert "piece [1, 2, 3]" in bad[0] and "cannot hover" in bad[0]
        flight = make_plan(sc, model, make_trajectory(sc, model))
        assert flight.feasible and unhoverable_pieces(flight, model, eta) == []
        assert (flight.disassembly_layers == 0) is quadrant_rule_bad


def _cli(tmp_path: Path, text: str, *extra: str) -> subprocess.CompletedProcess:
    path = tmp_path / "s.toml"
    path.write_text(text, encoding="utf-8")
    return subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", str(path), "--out", str(tmp_path / "out"),
                           "--quiet", *extra], capture_output=True, text=True, timeout=120)


DOCK = (Path(__file__).resolve().parents[2] / "mars_link" / "scenarios" / "docking_3x1.toml").read_text(encoding="utf-8")


def test_mars_link_run_dispatches_reconfig_scenarios(tmp_path):
    text = DOCK.replace("at_s = 8.0", "at_s = 5.0").replace("speed_mps = 0.3", "speed_mps = 0.6")
    text = text.replace("duration_s = 14.0", "duration_s = 7.0")
    proc = _cli(tmp_path, text)
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "out"
    summary = json.loads((out / "summary.json").read_text())
    for key in ("mean_error_m", "rmse_m", "force_integral_n2s", "diverged", "events", "reconfig_time_s"):
        assert key in summary
    assert summary["reconfigured"] and not summary["diverged"]
    assert {"split", "dock", "fault"} <= {e["type"] for e in summary["events"]}
    texts = [e["text"] for e in summary["events"]]  # each fits one MAVLink STATUSTEXT
    assert len(texts) == len(summary["events"]) and all(0 < len(x) <= 50 and x.isascii() for x in texts)
    assert "Split L1: u1 off" in texts and "Docked L1: u1-3" in texts
    assert summary["force_integral_n2s"] > 0 and summary["reconfig_time_s"] > 5
    for name in ("telemetry.csv", "units.csv", "plots/units.png", "plots/error.png"):
        assert (out / name).stat().st_size > 0


@pytest.mark.parametrize("edit,needle", [
    # an unreachable target: the dead-rotor unit 1 would have to fly alone to get to the far end
    (lambda t: t.replace('layout = ["XXX"]', 'layout = ["XXXX"]').replace("unit = 3", "unit = 1")
     .replace("target = [2, 3, 1]", "target = [4, 3, 2, 1]"), "unreachable"),
    (lambda t: t.replace('layout = ["XXX"]', 'layout = ["X.XX"]'), "not connected"),
    (lambda t: t.replace("unit = 3", "unit = 5"), "unit 5 does not exist"),
    (lambda t: t.replace("target = [2, 3, 1]", "target = [2, 2, 1]"), "exactly once"),
    (lambda t: t.replace("enabled = true", "enabled = true\nspeed = 2"), "unknown key 'speed'"),
    (lambda t: t.replace("speed_mps = 0.3", "speed_mps = -1"), "speed_mps must be > 0"),
    (lambda t: t + "\n[docking]\nposition_m = 0.5\n", "[docking] position_m must be in (0, 0.1]"),
    (lambda t: t + "\n[docking]\nyaw_deg = 0\n", "[docking] yaw_deg must be > 0"),
])
def test_bad_reconfig_input_is_one_line_exit_2(tmp_path, edit, needle):
    proc = _cli(tmp_path, edit(DOCK))
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    err = proc.stderr.strip()
    assert "Traceback" not in proc.stderr and len(err.splitlines()) == 1 and needle in err, err
    assert not (tmp_path / "out").exists()


def test_unit_sets_are_written_as_ranges():
    from mars_link.reconfig.execution import units_text

    assert units_text([3, 1, 2, 4, 9, 11, 12]) == "1-4,9,11-12"
    assert units_text({5}) == "5"


def test_a_flight_of_pieces_paced_by_the_engine_flies_the_same_in_the_wall_clock_it_asks_for():
    """Pacing is a parameter of the one engine: docking_3x1 at 5x real time takes sim time / 5 of wall time
    and gives the flight it gives unpaced (same events, same error)."""
    fast = run_trial(docking("qp"), 1)
    paced = run_trial(docking("qp"), 1, realtime_rate=5.0)
    assert [(e["t_s"], e["type"]) for e in paced.events] == [(e["t_s"], e["type"]) for e in fast.events]
    assert paced.mean_error_m == fast.mean_error_m
    assert paced.wall_time_s >= 0.97 * paced.sim_time_s / 5.0


def test_a_docked_flight_is_one_piece_flying_the_mission_itself_with_the_scenario_controller():
    """`build_flight` makes every flight through the coordinator of pieces: a docked structure is one piece
    whose coordinator flies the tracked unit's centre on the mission itself (not a CoM reference moved
    back and forth), with the scenario's controller, and names the structure's units in its events."""
    from mars_link.flight.build import build_flight
    from mars_link.control.paper import PaperController
    from mars_link.flight.engine import Engine
    from mars_link.coordination.pieces import PiecesCoordinator
    from mars_link.apps.reproduce import CASES, scenario_for

    case = next(c for c in CASES if c.name == "F3 units {2}")
    flight = build_flight(scenario_for(case, "mars-ftcc-paper", "unit", duration_s=2.0), 1)
    coord = flight.coordinator
    assert isinstance(coord, PiecesCoordinator) and len(coord.pieces) == 1
    (piece,) = coord.pieces.values()
    assert isinstance(piece.coordinator.controller, PaperController)
    assert piece.coordinator.controller.tracked_unit_id == 1
    for t in (0.0, 0.7, 1.3):  # bit for bit the mission's point
        a, b = piece.coordinator.trajectory.sample(t), flight.trajectory.sample(t)
        assert np.array_equal(a.position_ned_m, b.position_ned_m) and a.yaw_rad == b.yaw_rad
    Engine(flight).run()
    flight.world.close()
    lost = [e for e in coord.events if e["type"] == "reallocation"]
    assert lost and "u2 dead" in lost[0]["text"]


def test_a_piece_reference_off_the_mission_is_its_com_reference_moved_to_the_tracked_point():
    """Off the mission (a quintic move) the tracked point's reference is the CoM reference moved out by the
    tracked unit's offset (yaw applied): what the controller moves back to the CoM."""
    from mars_link.reconfig.execution import PieceReference, TrackedPointReference
    from mars_link.models.trajectories import TrajectoryPoint

    com = PieceReference(TrajectoryPoint(np.array([1.0, 2.0, -1.0]), yaw_rad=math.pi / 2))
    com.move(0.0, np.array([3.0, 2.0, -1.5]), 0.5)
    offset = np.array([0.35, -0.175, 0.0])
    tracked = TrackedPointReference(com, offset)
    for t in (0.0, 1.0, 2.5, 10.0):
        c, p = com.sample(t), tracked.sample(t)
        np.testing.assert_allclose(p.position_ned_m - c.position_ned_m, [0.175, 0.35, 0.0], atol=1e-12)
        np.testing.assert_allclose(p.velocity_ned_mps, c.velocity_ned_mps, atol=1e-12)  # (no yaw rate)
