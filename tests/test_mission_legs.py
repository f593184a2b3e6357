"""Missions flown by the assembly vehicle on planned legs (mars_link.mission_legs): a damaged 3x2 (unit 2
failed, found by the coordinator's fault detector, not told) flies a five-waypoint mission through the
CoppeliaSim walls (../shared/data/mars_ftcc_walls.csv). Every leg is planned for the layout and the
believed faults in a worker process: no wall contact of the true footprint. The same mission on
minimum-snap legs (no map) touches the walls; both counts are printed. A fault found mid-leg makes the
vehicle brake and plan the rest again."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as R

from mars_link.mission_legs import min_snap_leg, septic

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
HAVE_WALLS = (SHARED / "data" / "mars_ftcc_walls.csv").exists()
FRACTIONS = (0.3, 0.45, 0.7, 0.9, 1.0)  # of the published 3x2 path: straight lines between them cross walls


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


def _fly_walls_mission(use_map: bool, fault_t_s: float) -> dict:
    from mars_link.assembly_vehicle import AssemblySim, SimConfig
    from mars_link.planning.evaluate import PAPER_HEIGHT_M, WALLS_CSV, convert_published, published_csv, walls_map
    from mars_link.planning.footprint import Footprint, footprint_clearance
    from mars_link.rotations import quat_to_euler
    from mars_link.scenario import FaultSpec, load_scenario

    sc = load_scenario("hover_3x2")
    sc.ftc, sc.faults_known = "hybrid", False
    sc.faults.append(FaultSpec(unit=2, rotor=None, eta=0.0, t_s=fault_t_s))
    sim = AssemblySim(sc, SimConfig(start_north_m=0.175, start_east_m=0.35, params={"MPC_XY_VEL_MAX": 0.8},
                                    map_path=WALLS_CSV if use_map else None))
    rows = convert_published(published_csv("XXX,XXX", "ours"))
    wps = [rows[int(round(f * (len(rows) - 1)))][1:3] for f in FRACTIONS]
    gcs, dec = R.MAVLink(None, 245, 190), R.MAVLink(None, 0, 0)
    got: list = []
    res: dict = {"poses": [], "reached": [], "texts": []}

    def feed(out) -> None:
        for o in out:
            if o.link == "api":
                got.extend(dec.parse_buffer(o.data) or [])

    def send(msg) -> list:
        k = len(got)
        feed(sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api"))
        return got[k:]

    def run(seconds: float) -> None:
        for _ in range(int(round(seconds / sim.control_dt_s))):
            k = len(got)
            feed(sim.step(sim.t_s))
            s = sim.truth()
            res["poses"].append((*s.position_ned_m[:2], quat_to_euler(s.quaternion_wxyz)[2]))
            for m in got[k:]:
                if m.get_type() == "MISSION_ITEM_REACHED":
                    res["reached"].append((m.seq, s.position_ned_m.copy()))
                elif m.get_type() == "STATUSTEXT":
                    res["texts"].append((sim.t_s, m.text))

    try:
        run(0.3)
        items = []
        for seq, (n, e) in enumerate(wps):
            lat, lon = sim.vehicle.origin.to_global(np.array([n, e, 0.0]))[:2]
            items.append(R.MAVLink_mission_item_int_message(
                1, 1, seq, R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, R.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.5, 0.3, 0, math.nan,
                int(round(lat * 1e7)), int(round(lon * 1e7)), PAPER_HEIGHT_M, 0))
        replies = send(R.MAVLink_mission_count_message(1, 1, len(items), 0))
        for _ in items:
            replies = send(items[[m for m in replies if m.get_type() == "MISSION_REQUEST_INT"][-1].seq])
        assert [m.type for m in replies if m.get_type() == "MISSION_ACK"] == [R.MAV_MISSION_ACCEPTED]
        send(R.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
        send(R.MAVLink_command_long_message(1, 1, R.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0))
        while sim.t_s < 220.0 and len(res["reached"]) < len(items):
            run(1.0)
        run(1.0)
        clearance = footprint_clearance(Footprint.from_model(sim.model, 0.0), walls_map(), np.array(res["poses"]))
        hit = (clearance < 0).astype(int)
        res.update(contacts=int(np.count_nonzero(np.diff(np.concatenate([[0], hit])) == 1)),
                   contact_steps=int(hit.sum()), min_clearance_m=float(clearance.min()), sim_s=sim.t_s,
                   detections=[(d.unit, d.rotor, d.t_detected) for d in sim.coordinator.detections],
                   legs=sim.legs.log, waypoints=wps)
    finally:
        sim.close()
    return res


@pytest.mark.slow
@pytest.mark.skipif(not HAVE_WALLS, reason="shared data not beside the repository")
def test_damaged_3x2_flies_five_waypoints_through_the_walls_on_planned_legs() -> None:
    planned = _fly_walls_mission(True, 0.0)
    straight = _fly_walls_mission(False, 0.0)
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


@pytest.mark.slow
@pytest.mark.skipif(not HAVE_WALLS, reason="shared data not beside the repository")
def test_a_fault_found_mid_leg_brakes_and_plans_the_rest_again() -> None:
    res = _fly_walls_mission(True, 33.0)  # unit 2 fails while the first leg is flown
    assert [(u, r) for u, r, _ in res["detections"]] == [(2, None)] and res["detections"][0][2] >= 33.0
    replans = [leg["replan_at_s"] for leg in res["legs"] if "replan_at_s" in leg]
    assert len(replans) == 1 and 33.0 <= replans[0] < 34.0
    assert any(t.startswith("Faults changed") for _, t in res["texts"])
    assert [s for s, _ in res["reached"]] == [0, 1, 2, 3, 4]
    assert res["contacts"] == 0
