"""Missions flown by the assembly vehicle on planned legs (mars_link.planning.mission_legs): a damaged 3x2 (unit 2
failed, found by the coordinator's fault detector, not told) flies a five-waypoint mission through the
walls of paper 000's planning scenes (the bundled map paper000_walls.csv). Every leg is planned for the layout and the
believed faults in a worker process: no wall contact of the true footprint. The same mission on
minimum-snap legs (no map) touches the walls; both counts are printed. A fault found mid-leg makes the
vehicle brake and plan the rest again."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mars_link.planning.mission_legs import min_snap_leg, septic
from mars_link.apps.planning_eval import walls_mission_flight



def test_minimum_snap_leg_starts_and_ends_at_rest_within_its_limits() -> None:
    leg = min_snap_leg(np.array([1.0, 2.0]), np.array([7.0, -6.0]), 0.3, v_max=0.8, a_max=0.5)
    speed = np.hypot(*leg.ne[:, 1].T)
    acc = np.hypot(*leg.ne[:, 2].T)
    np.testing.assert_allclose(leg.ne[0, 0], [1.0, 2.0])
    np.testing.assert_allclose(leg.ne[-1, 0], [7.0, -6.0], atol=1e-9)
    assert speed[0] == speed[-1] == 0.0 and acc[0] == acc[-1] == 0.0
    assert speed.max() <= 0.8 + 1e-9 and acc.max() <= 0.5 + 1e-3
    # the derivatives are the numerical ones of the position
    np.testing.assert_allclose(np.gradient(leg.ne[:, 0, 0], leg.t_s)[5:-5], leg.ne[5:-5, 1, 0], atol=1e-3)
    assert np.allclose(septic(np.array([0.0, 1.0]))[0], [0.0, 1.0])


@pytest.mark.slow
@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_damaged_3x2_flies_five_waypoints_through_the_walls_on_planned_legs() -> None:
    planned = walls_mission_flight(True, 0.0)
    straight = walls_mission_flight(False, 0.0)
    print(f"planned legs: {planned['contacts']} wall contacts (min clearance {planned['min_clearance_m']:.3f} m); "
          f"minimum-snap legs: {straight['contacts']} contacts ({straight['contact_steps']} steps, "
          f"min clearance {straight['min_clearance_m']:.3f} m)")
    for res in (planned, straight):
        assert [(u, r) for u, r, _ in res["detections"]] == [(2, None)]  # found, not told
        assert [s for s, _ in res["reached"]] == [0, 1, 2, 3, 4]
        for (seq, pos), wp in zip(res["reached"], res["waypoints"]):
            assert math.dist(pos[:2], wp) <= 0.32, (seq, pos, wp)  # the 0.3 m radius, judged on the estimate
    assert planned["contacts"] == 0 and planned["min_clearance_m"] > 0.0
    assert straight["contacts"] >= 1
    legs = [leg for leg in planned["legs"] if "kind" in leg]
    assert [leg["kind"] for leg in legs] == ["planned"] * 5 and all(leg["ok"] for leg in legs)
    assert all(leg["min_clearance_m"] > 0.2 for leg in legs)  # the planner's own check, with its margin


@pytest.mark.long  # (a second walls flight, for CI's time: run with -m long)
def test_a_fault_found_mid_leg_brakes_and_plans_the_rest_again() -> None:
    res = walls_mission_flight(True, 33.0)  # unit 2 fails while the first leg is flown
    assert [(u, r) for u, r, _ in res["detections"]] == [(2, None)] and res["detections"][0][2] >= 33.0
    replans = [leg["replan_at_s"] for leg in res["legs"] if "replan_at_s" in leg]
    assert len(replans) == 1 and 33.0 <= replans[0] < 34.0
    assert any(t.startswith("Faults changed") for _, t in res["texts"])
    assert [s for s, _ in res["reached"]] == [0, 1, 2, 3, 4]
    assert res["contacts"] == 0


@pytest.mark.parametrize("text, needle", [
    (None, "no such file"),
    ("cx,cy\n1,2\n", "the header must be"),
    ("cx,cy,length_m,thickness_m,height_m,yaw_deg\n1,2,nan,0.1,2,0\n", "finite"),
])
def test_a_bad_vehicle_map_is_one_line_and_exit_2(text, needle, tmp_path, capsys) -> None:
    from mars_link.apps.cli import main

    path = tmp_path / "map.csv"
    if text is not None:
        path.write_text(text)
    assert main(["vehicle", "--gcs-bind", "0", "--api-bind", "0", "--duration", "0.1", "--map", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err, err
