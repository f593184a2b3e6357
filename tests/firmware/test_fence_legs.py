"""The geofence as a constraint of the leg planner (mars_link.planning.mission_legs): the 3x2 as `mars-link vehicle`
flies it (VehicleSim, in process, JSBSim) takes a .plan whose straight legs would cross an exclusion
zone and cut the corner of an L-shaped inclusion fence; the legs are planned around both, and every
unit of the true assembly stays inside the inclusion and outside the exclusion all flight long."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import shapely
from pymavlink.dialects.v20 import common as R
from test_mavsdk_mission import HOME, _latlon

from firmware_models.qgc_plan import load_plan, preload
from mars_link.planning.mission_legs import fence_walls
from mars_link.core.rotations import quat_to_rotmat

ALT_M = 2.5
W1, W2 = (8.0, 0.0), (0.0, 10.0)  # the straight leg 0 -> W1 crosses the exclusion; W1 -> W2 leaves the L
EXCLUSION = [(3.0, -2.0), (3.0, 2.0), (5.0, 2.0), (5.0, -2.0)]
INCLUSION_L = [(-3.0, -5.0), (11.0, -5.0), (11.0, 4.0), (3.0, 4.0), (3.0, 14.0), (-3.0, 14.0)]


def fence_plan() -> dict:
    def simple(seq: int, cmd: int, p: list) -> dict:
        return {"autoContinue": True, "command": cmd, "doJumpId": seq + 1, "frame": 3, "params": p,
                "type": "SimpleItem"}

    items = [simple(0, 22, [0, 0, 0, None, HOME[0], HOME[1], ALT_M])]
    items += [simple(1, 16, [0.0, 0.3, 0, None, *_latlon(*W1), ALT_M])]
    items += [simple(2, 21, [0, 0, 0, None, *_latlon(*W2), 0])]
    poly = lambda pts, inc: {"inclusion": inc, "polygon": [list(_latlon(n, e)) for n, e in pts], "version": 1}  # noqa: E731
    return {"fileType": "Plan", "groundStation": "QGroundControl", "version": 1,
            "mission": {"items": items, "plannedHomePosition": [HOME[0], HOME[1], 488], "version": 2},
            "geoFence": {"version": 2, "polygons": [poly(INCLUSION_L, True), poly(EXCLUSION, False)], "circles": []},
            "rallyPoints": {"version": 2, "points": []}}


def test_fence_edges_become_walls_on_the_zone_boundaries() -> None:
    from firmware_models.geofence import Geofence

    fence = Geofence([shapely.Polygon(INCLUSION_L)], [shapely.Point(0.0, 0.0).buffer(1.0, quad_segs=8)])
    walls = np.array(fence_walls(fence))
    assert len(walls) == 6 + 32
    # each wall's centre line lies on a zone boundary, its length covers the edge
    boundary = shapely.union(fence.inclusion.boundary, fence.exclusion.boundary)
    assert max(boundary.distance(shapely.Point(n, e)) for n, e in walls[:, :2]) < 1e-9
    assert math.isclose(walls[:6, 2].sum() * 2 - 6 * 0.2, shapely.Polygon(INCLUSION_L).length, rel_tol=1e-9)


def test_the_3x2_plans_its_legs_around_the_fence(tmp_path: Path) -> None:
    from mars_link.vehicles.vehicle_sim import VehicleSim
    from mars_link.config.scenario import load_scenario

    path = tmp_path / "fence.plan"
    path.write_text(json.dumps(fence_plan()))
    sim = VehicleSim(load_scenario("hover_3x2"))
    sim.legs.wait_for_plans = True  # unpaced: the simulation waits for each plan
    inclusion, exclusion = shapely.Polygon(INCLUSION_L), shapely.Polygon(EXCLUSION)
    # the straight legs would not keep the fence
    assert shapely.LineString([(0, 0), W1]).intersects(exclusion)
    assert not inclusion.contains(shapely.LineString([W1, W2]))
    try:
        preload(sim.vehicle, load_plan(path), str(path))
        gcs, dec = R.MAVLink(None, 245, 190), R.MAVLink(None, 0, 0)
        got: list = []
        units: list = []

        def feed(out) -> None:
            for o in out:
                if o.link == "api":
                    got.extend(dec.parse_buffer(o.data) or [])

        def send(msg) -> None:
            feed(sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api"))

        offsets = np.array([sim.model.unit_position(u) for u in sim.model.unit_ids])
        for _ in range(30):
            feed(sim.step(sim.t_s))
        send(R.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
        send(R.MAVLink_command_long_message(1, 1, R.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0))
        while sim.t_s < 150.0 and not (sim.vehicle.runner.complete and not sim.vehicle.armed):
            feed(sim.step(sim.t_s))
            s = sim.truth()
            units.append(s.position_ned_m + offsets @ quat_to_rotmat(s.quaternion_wxyz).T)
        reached = sorted({m.seq for m in got if m.get_type() == "MISSION_ITEM_REACHED"})
        assert reached == [0, 1, 2] and not sim.vehicle.armed, (reached, sim.t_s)
        legs = [leg for leg in sim.legs.log if "kind" in leg]
        kinds = [leg["kind"] for leg in legs]
        assert kinds.count("planned") == 2 and all(leg["ok"] for leg in legs), legs
        pts = np.concatenate(units)
        inside = shapely.distance(inclusion.boundary, shapely.points(pts[:, :2]))
        outside = shapely.distance(exclusion, shapely.points(pts[:, :2]))
        assert shapely.contains_xy(inclusion, pts[:, 0], pts[:, 1]).all()
        print(f"unit centres: min distance to the inclusion edge {inside.min():.2f} m, to the exclusion "
              f"{outside.min():.2f} m; landed {math.dist(units[-1].mean(axis=0)[:2], W2):.2f} m from W2")
        assert outside.min() > 0.2 and inside.min() > 0.2  # a unit's half width (0.175 m) clear of every fence edge
        assert math.dist(units[-1].mean(axis=0)[:2], W2) < 0.5
    finally:
        sim.close()
