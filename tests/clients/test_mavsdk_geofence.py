"""MAVSDK 4.x uploads the fence MAVSDK-Python's geofence example puts on the wire (an inclusion polygon
plus a circle of radius 0 at 0 N 0 E; MAVSDK 4's own geofence plugin refuses a radius of 0 before
sending, so its mission_raw plugin sends the items) to a unit process and to `mars-link vehicle` (the
3x2 as one vehicle), over UDP on loopback: the upload succeeds, the fence reads back as sent, and the
polygon is enforced (a goto outside it is denied, the client receives the STATUSTEXT saying why, and
the body's JSBSim truth stays inside)."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import pytest

from mars_link.processes.udp_runner import free_udp_port, read_status, stop_unit

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio.plugins.action import ActionAsync, ActionError  # noqa: E402
from mavsdk.asyncio.plugins.mission_raw import MissionRawAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync  # noqa: E402
from mavsdk.plugins.mission_raw import MissionItem as RawItem  # noqa: E402
from test_mavsdk_mission import _latlon, spawn_api_unit  # noqa: E402
from test_mavsdk_unit import _until, autopilot  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(240)]

SQUARE_NE = [(-8.0, -8.0), (8.0, -8.0), (8.0, 8.0), (-8.0, 8.0)]
HOME_AMSL_M = 488.0
GLOBAL, POLYGON_INCLUSION, CIRCLE_INCLUSION, FENCE = 0, 5001, 5003, 1  # MAV_FRAME, MAV_CMD, MAV_MISSION_TYPE


def _example_fence() -> list:
    """The polygon's vertices (param1 = their count), then the circle: radius 0 at 0 N 0 E."""
    items = []
    for seq, (n, e) in enumerate(SQUARE_NE):
        lat, lon = _latlon(n, e)
        items.append(RawItem(seq, GLOBAL, POLYGON_INCLUSION, 0, 1, float(len(SQUARE_NE)), 0.0, 0.0, 0.0,
                             int(round(lat * 1e7)), int(round(lon * 1e7)), 0.0, FENCE))
    items.append(RawItem(len(SQUARE_NE), GLOBAL, CIRCLE_INCLUSION, 0, 1, 0.0, 0.0, 0.0, 0.0, 0, 0, 0.0, FENCE))
    return items


async def _fence_and_goto(api_port: int, status: Path) -> dict:
    res: dict = {"texts": []}
    async with autopilot(api_port) as system:
        telemetry, action, raw = TelemetryAsync(system), ActionAsync(system), MissionRawAsync(system)
        await _until(lambda: telemetry.health_all_ok(), 15.0, "health_all_ok")

        async def collect_texts():
            async for st in telemetry.subscribe_status_text():
                res["texts"].append(st.text)

        collector = asyncio.ensure_future(collect_texts())
        await raw.upload_geofence(_example_fence())
        res["read_back"] = [(it.command, it.param1, it.x, it.y) for it in await raw.download_geofence()]

        def truth():
            return read_status(status)["truth_position_ned_m"]

        await action.arm()
        await action.takeoff()

        async def hovering():
            return await telemetry.flight_mode() == FlightMode.HOLD and truth()[2] < -1.5

        await _until(hovering, 40.0, "HOLD after takeoff")
        start = truth()
        with pytest.raises(ActionError) as denied:
            await action.goto_location(*_latlon(20.0, 0.0), HOME_AMSL_M + 3.0, 0.0)
        res["goto_outside"] = denied.value.result.name
        await asyncio.sleep(2.0)
        res["moved_m"] = math.dist(truth()[:2], start[:2])
        res["north_m"] = truth()[0]
        await action.land()
        collector.cancel()
    return res


@pytest.mark.skipif(not hasattr(mavsdk, "asyncio"), reason="needs MAVSDK 4.x")
@pytest.mark.parametrize("vehicle", [pytest.param("unit", marks=pytest.mark.long), "assembly"])  # (CI time: -m long)
def test_mavsdk_geofence_example_fence_is_stored_and_enforced(tmp_path: Path, vehicle: str) -> None:
    api = free_udp_port()
    status = tmp_path / "status.json"
    if vehicle == "unit":
        proc, _ = spawn_api_unit(api, status)
    else:
        from mars_link.processes.realtime import spawn_vehicle

        proc, _ = spawn_vehicle(["--layout", "XXX,XXX", "--ftc", "qp", "--api-port", str(api), "--api-bind", "0",
                                 "--gcs-port", str(free_udp_port()), "--gcs-bind", "0"], status)
    try:
        res = asyncio.run(_fence_and_goto(api, status))
    finally:
        rc = stop_unit(proc)
    print(res)
    assert rc == 0
    assert res["read_back"] == [(it.command, it.param1, it.x, it.y) for it in _example_fence()]  # as PX4 stores it
    assert res["goto_outside"].endswith("COMMAND_DENIED")
    assert any(t.startswith("Goto refused: outside the inclusion fence") for t in res["texts"]), res["texts"]
    assert res["moved_m"] < 0.5 and res["north_m"] < 8.0  # the truth stayed inside the polygon
