"""MAVSDK 4.x's mission plugin against one unit process, and against `mars-link vehicle` (the 3x2 as
one vehicle), over UDP on loopback: a 3-waypoint mission
around PX4 SITL's home with RTL after it (MAVSDK's set_return_to_launch_after_mission), uploaded,
downloaded back, flown in AUTO.MISSION with a pause to HOLD and a resume; checked against the JSBSim
truth from the runner's status file: every waypoint passed within its acceptance radius, a
MISSION_ITEM_REACHED for every uploaded item, MAVSDK's progress to the end, landed and disarmed at
home."""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import pytest

from mars_link.processes.udp_runner import free_udp_port, read_status, spawn_unit, stop_unit

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.mission import MissionAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync  # noqa: E402
from mavsdk.plugins.mission import MissionItem, MissionPlan  # noqa: E402
from test_mavsdk_unit import _until  # noqa: E402  (the unit MAVSDK test's helper)

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(180)]

EARTH_R_M = 6371000.0
HOME = (47.397742, 8.545594)
WAYPOINTS_NE = [(4.0, 0.0), (4.0, 4.0), (0.0, 4.0)]
ALT_M, RADIUS_M, SPEED_MPS, LOITER_S = 3.0, 0.3, 2.0, 0.5


def spawn_api_unit(api_port: int, status: Path, *extra: str):
    """A unit process (system 1) whose API link sends to `api_port`, writing its status to `status`."""
    return spawn_unit(["--unit", "1", "--gcs-port", str(free_udp_port()), "--gcs-bind", "0",
                       "--api-port", str(api_port), "--api-bind", "0", "--coord-bind", "0",
                       "--status-file", str(status), *extra])


def _latlon(north_m: float, east_m: float) -> tuple[float, float]:
    return (HOME[0] + math.degrees(north_m / EARTH_R_M),
            HOME[1] + math.degrees(east_m / (EARTH_R_M * math.cos(math.radians(HOME[0])))))


async def _fly(api_port: int, status_path: Path) -> dict:
    res: dict = {"truth": [], "progress": []}
    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(cfg) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{api_port}")
        system = await sdk.first_autopilot(timeout_s=15.0)
        assert system is not None, "MAVSDK did not find the unit"
        telemetry, action, mission = TelemetryAsync(system), ActionAsync(system), MissionAsync(system)
        await _until(lambda: telemetry.health_all_ok(), 10.0, "health_all_ok")
        home = await telemetry.home()
        res["home"] = (home.latitude_deg, home.longitude_deg, home.absolute_altitude_m)

        items = [MissionItem(*_latlon(n, e), ALT_M, SPEED_MPS, False, acceptance_radius_m=RADIUS_M,
                             loiter_time_s=LOITER_S) for n, e in WAYPOINTS_NE]
        await mission.set_return_to_launch_after_mission(True)
        t = time.monotonic()
        await mission.upload_mission(MissionPlan(items))
        res["upload_s"] = time.monotonic() - t
        back = await mission.download_mission()
        res["downloaded"] = [(i.latitude_deg, i.longitude_deg, i.relative_altitude_m, i.acceptance_radius_m)
                             for i in back.mission_items]
        res["rtl_after"] = await mission.get_return_to_launch_after_mission()

        async def progress():
            async for p in mission.subscribe_mission_progress():
                res["progress"].append((p.current, p.total))

        watcher = asyncio.ensure_future(progress())

        async def sample():
            st = read_status(status_path)
            res["truth"].append(st["truth_position_ned_m"])
            return st

        await action.arm()
        await mission.start_mission()
        await _until(lambda: _mode(telemetry, FlightMode.MISSION), 5.0, "MISSION mode")
        # pause on the second leg, hold, resume
        await _until(lambda: _current_is(mission, 1, sample), 30.0, "the second waypoint as current")
        await asyncio.sleep(0.8)
        await mission.pause_mission()
        await _until(lambda: _mode(telemetry, FlightMode.HOLD), 5.0, "HOLD")
        await asyncio.sleep(1.5)
        held = (await sample())["truth_position_ned_m"]
        await asyncio.sleep(1.0)
        res["hold_drift_m"] = math.dist(held, (await sample())["truth_position_ned_m"])
        await mission.start_mission()

        async def finished_and_disarmed():
            await sample()
            return await mission.is_mission_finished() and not await telemetry.armed()

        await _until(finished_and_disarmed, 45.0, "mission finished and disarmed after landing", 0.1)
        await asyncio.sleep(0.5)
        watcher.cancel()
        st = await sample()
        res["reached"] = st["mission_reached"]
        res["landed_at"] = st["truth_position_ned_m"]
        res["drops"] = {k: v for k, v in st["drops"].items() if k.startswith("mission.")}
        res["items_uploaded"] = st["mission_counts"].get("uploaded.mission", 0)
    return res


async def _mode(telemetry, mode) -> bool:
    return await telemetry.flight_mode() == mode


async def _current_is(mission, index: int, sample) -> bool:
    await sample()
    return (await mission.mission_progress()).current == index


@pytest.mark.skipif(not hasattr(mavsdk, "asyncio"), reason="needs MAVSDK 4.x")
@pytest.mark.parametrize("vehicle", [pytest.param(v, marks=pytest.mark.long) for v in ("unit", "assembly")])  # (CI time:
# -m long; examples/mavsdk_mission.py flies a MAVSDK mission against the truth in the default run)
def test_mavsdk_mission_flown_against_the_truth(tmp_path: Path, vehicle: str) -> None:
    """`unit`: a lone unit process; `assembly`: `mars-link vehicle` (the 3x2, qp allocation)."""
    api = free_udp_port()
    status = tmp_path / "status.json"
    if vehicle == "unit":
        proc, _ = spawn_api_unit(api, status)
    else:
        from mars_link.processes.realtime import spawn_vehicle

        proc, _ = spawn_vehicle(["--layout", "XXX,XXX", "--ftc", "qp", "--api-port", str(api), "--api-bind", "0",
                                 "--gcs-port", str(free_udp_port()), "--gcs-bind", "0"], status)
    t0 = time.monotonic()
    try:
        res = asyncio.run(_fly(api, status))
    finally:
        rc = stop_unit(proc)
    wall_s = time.monotonic() - t0
    print({k: v for k, v in res.items() if k not in ("truth",)}, f"wall {wall_s:.1f} s")
    assert rc == 0
    assert res["home"][:2] == pytest.approx(HOME, abs=1e-7) and res["home"][2] == pytest.approx(488.0, abs=0.1)
    assert res["items_uploaded"] == 1 and res["rtl_after"] is True and res["upload_s"] < 1.0
    assert len(res["downloaded"]) == 3
    for (lat, lon, alt, radius), (n, e) in zip(res["downloaded"], WAYPOINTS_NE):
        assert (lat, lon) == pytest.approx(_latlon(n, e), abs=2e-7) and alt == pytest.approx(ALT_M)
        assert radius == pytest.approx(RADIUS_M)
    # the world's truth: every waypoint passed within its acceptance radius (sampled ~10 Hz while it
    # loitered there 0.5 s), and where the vehicle was when it reported each item reached
    truth = res["truth"]
    for n, e in WAYPOINTS_NE:
        closest = min(math.dist(p, (n, e, -ALT_M)) for p in truth)
        assert closest <= RADIUS_M, ((n, e), closest)
    reached = res["reached"]
    seqs = sorted({r["seq"] for r in reached})
    n_items = max(seqs) + 1
    assert seqs == list(range(n_items)) and n_items >= 4  # waypoints (+ MAVSDK's speed items) + RTL
    wp_reached = [r["position_ned_m"] for r in reached if any(math.dist(r["position_ned_m"], (n, e, -ALT_M)) <= RADIUS_M
                                                           for n, e in WAYPOINTS_NE)]
    assert len(wp_reached) >= 3
    # MAVSDK saw the progress through every item to the end
    currents = [c for c, _ in res["progress"]]
    assert currents and currents[-1] == res["progress"][-1][1] == 3 and sorted(set(currents)) == [0, 1, 2, 3]
    # paused: held still; finished: RTL landed at home, disarmed
    assert res["hold_drift_m"] < 0.1
    assert math.hypot(*res["landed_at"][:2]) < 0.3 and res["landed_at"][2] > -0.1
    assert res["drops"] == {}
    assert wall_s < 60.0


# ----------------------------------------------------------------------------- mission_raw + QGC .plan
def qgc_plan_json() -> dict:
    """A QGroundControl .plan as QGC saves it for PX4: takeoff, two waypoints, land; an inclusion
    polygon and an exclusion circle; two rally points."""
    def simple(seq: int, cmd: int, frame: int, p: list) -> dict:
        return {"AMSLAltAboveTerrain": None, "Altitude": p[6], "AltitudeMode": 1, "autoContinue": True,
                "command": cmd, "doJumpId": seq + 1, "frame": frame, "params": p, "type": "SimpleItem"}

    wp = [_latlon(n, e) for n, e in RAW_WAYPOINTS_NE]
    land = _latlon(*RAW_LAND_NE)
    items = [simple(0, 22, 3, [0, 0, 0, None, HOME[0], HOME[1], RAW_ALT_M])]
    items += [simple(i + 1, 16, 3, [0.5, RADIUS_M, 0, None, lat, lon, RAW_ALT_M]) for i, (lat, lon) in enumerate(wp)]
    items += [simple(3, 21, 3, [0, 0, 0, None, land[0], land[1], 0])]
    square = [list(_latlon(n, e)) for n, e in ((-15, -15), (-15, 15), (15, 15), (15, -15))]
    return {
        "fileType": "Plan", "groundStation": "QGroundControl", "version": 1,
        "mission": {"cruiseSpeed": 15, "firmwareType": 12, "hoverSpeed": 2, "items": items,
                    "plannedHomePosition": [HOME[0], HOME[1], 488], "vehicleType": 2, "version": 2},
        "geoFence": {"version": 2, "polygons": [{"inclusion": True, "polygon": square, "version": 1}],
                     "circles": [{"circle": {"center": list(_latlon(-8, -8)), "radius": 2.0}, "inclusion": False,
                                  "version": 1}]},
        "rallyPoints": {"version": 2, "points": [[*_latlon(5, -5), 10.0], [*_latlon(-5, 5), 10.0]]},
    }


RAW_WAYPOINTS_NE = [(3.0, 0.0), (3.0, -3.0)]
RAW_LAND_NE = (0.0, -3.0)
RAW_ALT_M = 2.5


async def _fly_raw(api_port: int, status_path: Path, plan_path: Path) -> dict:
    from mavsdk.asyncio.plugins.mission_raw import MissionRawAsync

    res: dict = {"truth": []}
    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(cfg) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{api_port}")
        system = await sdk.first_autopilot(timeout_s=15.0)
        assert system is not None
        telemetry, action, raw = TelemetryAsync(system), ActionAsync(system), MissionRawAsync(system)
        await _until(lambda: telemetry.health_all_ok(), 10.0, "health_all_ok")
        imported = await raw.import_qgroundcontrol_mission(str(plan_path))
        res["imported"] = [len(imported.mission_items), len(imported.geofence_items), len(imported.rally_items)]
        await raw.upload_mission(imported.mission_items)
        await raw.upload_geofence(imported.geofence_items)
        await raw.upload_rally_points(imported.rally_items)
        res["down"] = [(await raw.download_mission()), (await raw.download_geofence()),
                       (await raw.download_rallypoints())]
        res["sent"] = [imported.mission_items, imported.geofence_items, imported.rally_items]
        await action.arm()
        await raw.start_mission()

        async def finished_and_disarmed():
            res["truth"].append(read_status(status_path)["truth_position_ned_m"])
            return await raw.is_mission_finished() and not await telemetry.armed()

        await _until(finished_and_disarmed, 40.0, "mission finished and disarmed", 0.1)
        st = read_status(status_path)
        res["reached"] = st["mission_reached"]
        res["landed_at"] = st["truth_position_ned_m"]
        res["counts"] = st["mission_counts"]
        res["progress"] = await raw.mission_progress()
    return res


def _raw_fields(item) -> tuple:
    return (item.seq, item.frame, item.command, item.param1, item.param2, item.x, item.y, item.z, item.mission_type)


@pytest.mark.skipif(not hasattr(mavsdk, "asyncio"), reason="needs MAVSDK 4.x")
@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_mavsdk_mission_raw_imports_a_qgc_plan_with_fence_and_rally(tmp_path: Path) -> None:
    import json

    plan_path = tmp_path / "mission.plan"
    plan_path.write_text(json.dumps(qgc_plan_json(), indent=2))
    api = free_udp_port()
    status = tmp_path / "status.json"
    proc, _ = spawn_unit(["--unit", "1", "--gcs-port", str(free_udp_port()), "--gcs-bind", "0",
                          "--api-port", str(api), "--api-bind", "0", "--coord-bind", "0", "--status-file", str(status)])
    t0 = time.monotonic()
    try:
        res = asyncio.run(_fly_raw(api, status, plan_path))
    finally:
        rc = stop_unit(proc)
    wall_s = time.monotonic() - t0
    print(res["imported"], res["counts"], res["reached"], res["landed_at"], f"wall {wall_s:.1f} s")
    assert rc == 0
    assert res["imported"] == [4, 5, 2]  # 4 mission items; 4 polygon vertices + 1 circle; 2 rally points
    for sent, down in zip(res["sent"], res["down"]):  # stored as sent, for all three lists
        assert [_raw_fields(i) for i in down] == [_raw_fields(i) for i in sent]
    assert (res["counts"]["uploaded.mission"], res["counts"]["uploaded.fence"], res["counts"]["uploaded.rally"]) == (1, 1, 1)
    assert [r["seq"] for r in res["reached"]] == [0, 1, 2, 3]
    assert res["progress"].current == res["progress"].total == 4
    for n, e in RAW_WAYPOINTS_NE:
        assert min(math.dist(p, (n, e, -RAW_ALT_M)) for p in res["truth"]) <= RADIUS_M
    assert math.dist(res["landed_at"][:2], RAW_LAND_NE) < 0.3 and res["landed_at"][2] > -0.1
    assert wall_s < 60.0
