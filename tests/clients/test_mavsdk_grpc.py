"""MAVSDK-Python's gRPC API (the `mavsdk-grpc` package, imported as `mavsdk_grpc`: no clash with the
native `mavsdk` 4.x binding) against a unit process over UDP on loopback: the flows of the published
examples geofence.py, goto.py, do_orbit.py and mission.py (written here in their shape, not copied),
each checked against the JSBSim truth from the runner's status file."""

from __future__ import annotations

import asyncio
import math
import socket
from pathlib import Path

import pytest

from mars_link.processes.udp_runner import free_udp_port, read_status, stop_unit
from test_mavsdk_mission import _latlon, spawn_api_unit

mavsdk_grpc = pytest.importorskip("mavsdk_grpc")
from mavsdk_grpc import System  # noqa: E402
from mavsdk_grpc.action import ActionError, OrbitYawBehavior  # noqa: E402
from mavsdk_grpc.geofence import FenceType, GeofenceData, Point, Polygon  # noqa: E402
from mavsdk_grpc.mission import MissionItem, MissionPlan  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(240)]

HOME_AMSL = 488.0
WAYPOINTS_NE = [(4.0, 0.0), (4.0, -4.0), (0.0, -4.0)]


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def _wait(predicate, timeout_s: float, what: str) -> None:
    deadline = asyncio.get_running_loop().time() + timeout_s
    while asyncio.get_running_loop().time() < deadline:
        if await predicate():
            return
        await asyncio.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


async def _examples(api_port: int, status: Path) -> dict:
    res: dict = {}
    drone = System(port=_free_tcp_port())  # its own mavsdk_server on a free gRPC port
    await drone.connect(system_address=f"udpin://127.0.0.1:{api_port}")
    try:
        async for state in drone.core.connection_state():
            if state.is_connected:
                break
        async for health in drone.telemetry.health():
            if health.is_global_position_ok and health.is_home_position_ok:
                break

        def truth():
            return read_status(status)["truth_position_ned_m"]

        # geofence.py: an inclusion polygon around home
        square = [Point(*_latlon(n, e)) for n, e in ((-12, -12), (-12, 12), (12, 12), (12, -12))]
        await drone.geofence.upload_geofence(GeofenceData([Polygon(square, FenceType.INCLUSION)], []))

        # goto.py: arm, take off, fly to a point (AMSL altitude), and one outside the fence refused
        await drone.action.arm()
        await drone.action.takeoff()
        await asyncio.sleep(6.0)
        await drone.action.goto_location(*_latlon(3.0, 3.0), HOME_AMSL + 3.0, 0.0)

        async def at_goto():
            return math.dist(truth(), (3.0, 3.0, -3.0)) < 0.2

        await _wait(at_goto, 20.0, "the goto point")
        res["goto_error_m"] = math.dist(truth(), (3.0, 3.0, -3.0))
        try:
            await drone.action.goto_location(*_latlon(20.0, 0.0), HOME_AMSL + 3.0, 0.0)
            res["goto_outside"] = "accepted"
        except ActionError as e:
            res["goto_outside"] = str(e._result.result)

        # do_orbit.py: a 2 m circle around a point 2 m south of where it is, facing the centre
        await drone.action.do_orbit(2.0, 0.8, OrbitYawBehavior.HOLD_FRONT_TO_CIRCLE_CENTER,
                                    *_latlon(1.0, 3.0), HOME_AMSL + 3.0)
        await asyncio.sleep(6.0)
        radii = []
        for _ in range(30):
            radii.append(math.dist(truth()[:2], (1.0, 3.0)))
            await asyncio.sleep(0.2)
        res["orbit_radius_m"] = (min(radii), max(radii))
        await drone.action.hold()

        # mission.py: three waypoints, return to launch after the mission, progress to the end
        items = [MissionItem(*_latlon(n, e), 3.0, 2.0, False, math.nan, math.nan, MissionItem.CameraAction.NONE,
                             0.5, math.nan, 0.3, math.nan, math.nan, MissionItem.VehicleAction.NONE)
                 for n, e in WAYPOINTS_NE]
        await drone.mission.set_return_to_launch_after_mission(True)
        await drone.mission.upload_mission(MissionPlan(items))
        progress, track = [], []

        async def watch_progress():  # (a stream: it yields when the progress changes)
            async for p in drone.mission.mission_progress():
                progress.append((p.current, p.total))

        watcher = asyncio.ensure_future(watch_progress())
        await drone.mission.start_mission()

        async def finished():
            track.append(truth())
            return await drone.mission.is_mission_finished() and not await _first(drone.telemetry.armed())

        await _wait(finished, 60.0, "the mission finished and the vehicle disarmed")
        watcher.cancel()
        res["closest_m"] = [min(math.dist(p, (n, e, -3.0)) for p in track) for n, e in WAYPOINTS_NE]
        res["progress"] = progress[-1]
        res["landed_at"] = truth()
    finally:
        drone._stop_mavsdk_server()
    return res


async def _first(stream):
    async for x in stream:
        return x


@pytest.mark.long  # (CI time: -m long; MAVSDK 4.x flies the same commands in test_mavsdk_commands)
@pytest.mark.skipif(not hasattr(mavsdk_grpc, "System"), reason="needs mavsdk-grpc")
def test_mavsdk_grpc_example_flows_geofence_goto_orbit_mission(tmp_path: Path) -> None:
    api = free_udp_port()
    status = tmp_path / "status.json"
    proc, _ = spawn_api_unit(api, status)
    try:
        res = asyncio.run(_examples(api, status))
    finally:
        rc = stop_unit(proc)
    print(res)
    assert (rc, res["goto_outside"]) == (0, "COMMAND_DENIED") and res["goto_error_m"] < 0.2
    assert 1.7 < min(res["orbit_radius_m"]) and max(res["orbit_radius_m"]) < 2.3
    assert max(res["closest_m"]) <= 0.3  # each waypoint passed within its acceptance radius
    assert res["progress"][0] == res["progress"][1] == 3
    assert math.hypot(*res["landed_at"][:2]) < 0.3 and res["landed_at"][2] > -0.1
