"""QGroundControl `.plan` files preloaded into the assembly vehicle (`mars-link vehicle --mission x.plan`):
mission, geofence and rally stored as uploads would store them (downloadable, enforced), the mission
flown by the 3x2 in process against the JSBSim truth; bad plans are one line and exit 2."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as R
from test_mavsdk_mission import RAW_ALT_M, RAW_LAND_NE, RAW_WAYPOINTS_NE, _latlon, qgc_plan_json

from firmware_models.qgc_plan import load_plan, preload


def test_a_qgc_plan_is_preloaded_and_flown_by_the_3x2(tmp_path: Path) -> None:
    from mars_link.vehicles.vehicle_sim import VehicleSim
    from mars_link.config.scenario import load_scenario

    path = tmp_path / "x.plan"
    path.write_text(json.dumps(qgc_plan_json()))
    sim = VehicleSim(load_scenario("hover_3x2"))
    try:
        preload(sim.vehicle, load_plan(path), str(path))
        m = sim.vehicle.mission
        assert [len(m.plans[k]) for k in (0, 1, 2)] == [4, 5, 2]  # takeoff, 2 waypoints, land; 4+1 fence; 2 rally
        assert not sim.vehicle.geofence().empty and sim.vehicle.geofence().zones == 2
        gcs, dec = R.MAVLink(None, 245, 190), R.MAVLink(None, 0, 0)
        got: list = []
        truth: list = []

        def feed(out) -> None:
            for o in out:
                if o.link == "api":
                    got.extend(dec.parse_buffer(o.data) or [])

        def send(msg) -> list:
            k = len(got)
            feed(sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api"))
            return got[k:]

        for _ in range(30):
            feed(sim.step(sim.t_s))
        (count,) = [x for x in send(R.MAVLink_mission_request_list_message(1, 1, 1)) if x.get_type() == "MISSION_COUNT"]
        assert count.count == 5  # the fence is served as if uploaded
        send(R.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
        send(R.MAVLink_command_long_message(1, 1, R.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0))
        assert sim.vehicle.mode == (4, 4)
        while sim.t_s < 60.0 and not (sim.vehicle.runner.complete and not sim.vehicle.armed):
            feed(sim.step(sim.t_s))
            truth.append(sim.truth().position_ned_m.copy())
        reached = sorted({x.seq for x in got if x.get_type() == "MISSION_ITEM_REACHED"})
        assert reached == [0, 1, 2, 3] and not sim.vehicle.armed
        home_z = truth[0][2]
        for n, e in RAW_WAYPOINTS_NE:
            assert min(math.dist(p, (n, e, home_z - RAW_ALT_M)) for p in truth) < 0.3
        assert math.dist(truth[-1][:2], RAW_LAND_NE) < 0.3 and abs(truth[-1][2] - home_z) < 0.05
    finally:
        sim.close()


def _bad(doc_change) -> dict:
    doc = copy.deepcopy(qgc_plan_json())
    doc_change(doc)
    return doc


@pytest.mark.parametrize("doc, needle", [
    ("{not json", "not a QGroundControl .plan"),
    ({"fileType": "Mission"}, "fileType must be"),
    (_bad(lambda d: d["mission"]["items"].append({"type": "ComplexItem", "complexItemType": "survey"})),
     "only SimpleItem"),
    (_bad(lambda d: d["mission"]["items"][1]["params"].__setitem__(4, 91.0)), "invalid latitude"),
    (_bad(lambda d: d["mission"]["items"][1]["params"].__setitem__(4, _latlon(40.0, 0.0)[0])),
     "outside the inclusion fence"),
    (_bad(lambda d: d["rallyPoints"]["points"].append([1.0, 2.0])), "rally point 3"),
    ("[" * 100_000 + "]" * 100_000, "nested too deep"),  # (past Python's JSON recursion)
])
def test_a_bad_plan_is_one_line_and_exit_2(doc, needle, tmp_path, capsys) -> None:
    from mars_link.apps.cli import main

    path = tmp_path / "bad.plan"
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    assert main(["vehicle", "--gcs-bind", "0", "--api-bind", "0", "--duration", "0.1", "--mission", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err, err
