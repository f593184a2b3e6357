"""MAVSDK 4.x's action, geofence, mission_raw (rally), manual_control, offboard and log_files plugins
against a unit process and against `mars-link vehicle` (the 3x2 as one vehicle), over UDP on loopback,
checked against the JSBSim truth from the runner's status file: goto flown and goto outside the fence
denied, orbit flown on its circle, position-mode sticks move and hold the vehicle, RTL lands at the
nearest rally point, an offboard attitude target tilts the vehicle as asked, an offboard descent ends
in a detected landing and a disarm, and the run's own .tlog downloaded byte for byte."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import pytest

from mars_link.processes.udp_runner import free_udp_port, read_status, stop_unit
from mars_link.config.scenario import INTERACTIVE_SCENARIO, load_scenario
from mars_link.core.assembly import vehicle_preset
from mars_link.core.rotations import quat_to_euler

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio.plugins.action import ActionAsync, ActionError  # noqa: E402
from mavsdk.asyncio.plugins.geofence import GeofenceAsync  # noqa: E402
from mavsdk.asyncio.plugins.log_files import LogFilesAsync  # noqa: E402
from mavsdk.asyncio.plugins.manual_control import ManualControlAsync  # noqa: E402
from mavsdk.asyncio.plugins.mission_raw import MissionRawAsync  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync  # noqa: E402
from mavsdk.plugins.action import OrbitYawBehavior  # noqa: E402
from mavsdk.plugins.geofence import FenceType, GeofenceData, Point, Polygon  # noqa: E402
from mavsdk.plugins.mission_raw import MissionItem as RawItem  # noqa: E402
from mavsdk.plugins.offboard import Attitude, VelocityNedYaw  # noqa: E402
from test_mavsdk_mission import _latlon, spawn_api_unit  # noqa: E402
from test_mavsdk_unit import _until, autopilot  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(300)]

FENCE_NE = [(-10.0, -10.0), (-10.0, 10.0), (10.0, 10.0), (10.0, -10.0)]
RALLY_NE = [(6.0, -4.0), (-9.0, 9.0)]
GOTO_NE = (3.0, 2.0)
ORBIT_CENTRE_NE, ORBIT_R_M = (0.5, 2.0), 2.5


def _rally_items() -> list:
    out = []
    for seq, (n, e) in enumerate(RALLY_NE):
        lat, lon = _latlon(n, e)
        out.append(RawItem(seq, 3, 5100, 0, 1, 0.0, 0.0, 0.0, 0.0, int(round(lat * 1e7)), int(round(lon * 1e7)), 3.0,
                           2))  # NAV_RALLY_POINT, relative altitude, mission_type rally
    return out


async def _flights(api_port: int, status: Path, tlog: Path, plant) -> dict:
    res: dict = {}
    async with autopilot(api_port) as system:
        telemetry, action, fence = TelemetryAsync(system), ActionAsync(system), GeofenceAsync(system)
        raw, manual, offboard = MissionRawAsync(system), ManualControlAsync(system), OffboardAsync(system)
        logs = LogFilesAsync(system)
        await _until(lambda: telemetry.health_all_ok(), 15.0, "health_all_ok")

        def truth():
            return read_status(status)["truth_position_ned_m"]

        async def near(ne, tol, z=None):
            p = truth()
            return math.dist(p[:2], ne) < tol and (z is None or abs(p[2] - z) < tol)

        await fence.upload_geofence(GeofenceData([Polygon([Point(*_latlon(n, e)) for n, e in FENCE_NE],
                                                          FenceType.INCLUSION)], []))
        await raw.upload_rally_points(_rally_items())
        ground_z = truth()[2]
        await action.arm()
        await action.takeoff()
        await _until(lambda: _flying_mode(telemetry, FlightMode.HOLD), 30.0, "HOLD after takeoff")

        # goto (DO_REPOSITION): flown; outside the fence: denied
        lat, lon = _latlon(*GOTO_NE)
        await action.goto_location(lat, lon, HOME_AMSL + 3.0, 0.0)
        await _until(lambda: near(GOTO_NE, 0.2, -3.0), 30.0, "goto reached")
        await asyncio.sleep(1.5)  # then it holds there (the error is read once settled, not on the way in)
        res["goto_error_m"] = math.dist(truth(), (*GOTO_NE, -3.0))
        with pytest.raises(ActionError) as denied:
            await action.goto_location(*_latlon(15.0, 0.0), HOME_AMSL + 3.0, 0.0)
        res["goto_outside"] = denied.value.result.name

        # orbit: on the circle, facing its centre
        await action.do_orbit(ORBIT_R_M, 1.0, OrbitYawBehavior.HOLD_FRONT_TO_CIRCLE_CENTER,
                              *_latlon(*ORBIT_CENTRE_NE), HOME_AMSL + 3.0)
        await asyncio.sleep(6.0)
        radii = []
        for _ in range(40):
            radii.append(math.dist(truth()[:2], ORBIT_CENTRE_NE))
            await asyncio.sleep(0.2)
        res["orbit_radius_m"] = (min(radii), max(radii))
        await action.hold()

        async def still() -> bool:  # (the hold brakes the orbit's 1 m/s: the stick test starts at rest)
            before = truth()
            await asyncio.sleep(0.5)
            return math.dist(before, truth()) < 0.02

        await _until(still, 15.0, "the hold at rest after the orbit")

        # position mode: half stick forward moves north, centred sticks hold
        sticks = [0.0, 0.0, 0.5, 0.0]

        async def stream_sticks():
            while True:
                await manual.set_manual_control_input(*sticks)
                await asyncio.sleep(0.05)

        streamer = asyncio.ensure_future(stream_sticks())
        await asyncio.sleep(0.5)
        await manual.start_position_control()
        start = truth()
        heading = quat_to_euler(np.array(read_status(status)["truth_quaternion_wxyz"]))[2]
        sticks[0] = 0.5
        await asyncio.sleep(3.0)
        sticks[0] = 0.0
        await asyncio.sleep(2.5)
        held = truth()
        await asyncio.sleep(1.5)
        res["manual_moved_m"] = ((held[0] - start[0]) * math.cos(heading) + (held[1] - start[1]) * math.sin(heading),
                                 -(held[0] - start[0]) * math.sin(heading) + (held[1] - start[1]) * math.cos(heading))
        res["manual_hold_drift_m"] = math.dist(held, truth())
        streamer.cancel()

        # RTL: to the nearest rally point, land, disarm
        await action.return_to_launch()
        await _until(lambda: _disarmed(telemetry), 60.0, "landed and disarmed after RTL")
        res["rtl_landed_at"] = truth()

        # offboard: attitude target, then a velocity descent to the ground (land detector)
        await action.arm()
        await action.takeoff()

        async def up():
            return truth()[2] < ground_z - 1.9 and await _flying_mode(telemetry, FlightMode.HOLD)

        await _until(up, 30.0, "2 m up, in HOLD, after the second takeoff")
        # the share of full thrust the plant hovers at (a 3x2 of its units at the same share as one unit)
        hover = plant.unit_mass_kg * 9.80665 / (4 * plant.full_scale_thrust_n)
        # turn to face south (back into the fence: it took off at the rally point 6 m north), then nose down 6 deg
        await offboard.set_attitude(Attitude(0.0, 0.0, 180.0, hover))
        await offboard.start()
        await asyncio.sleep(4.5)
        await offboard.set_attitude(Attitude(0.0, -6.0, 180.0, hover / math.cos(math.radians(6.0))))
        await asyncio.sleep(1.5)
        res["attitude_pitch_deg"] = (await telemetry.attitude_euler()).pitch_deg
        res["attitude_truth_pitch_deg"] = math.degrees(quat_to_euler(
            np.array(read_status(status)["truth_quaternion_wxyz"]))[1])
        await offboard.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.6, 0.0))
        try:
            await _until(lambda: _disarmed(telemetry), 30.0, "disarmed after the offboard descent")
        except AssertionError:
            st = read_status(status)
            raise AssertionError({k: st.get(k) for k in ("mode", "phase", "armed", "truth_position_ned_m", "stats")})
        res["descent_landed_at"] = truth()
        res["ground_z"] = ground_z

        # log download: the run's .tlog, byte for byte (the prefix as large as the entry was)
        entries = await logs.get_entries()
        res["log_entries"] = [(e.id, e.size_bytes) for e in entries]
        out = tlog.parent / "downloaded.tlog"
        async for result, _progress in logs.download_log_file(entries[0], str(out)):
            pass
        got = out.read_bytes()
        res["log_same"] = got == tlog.read_bytes()[:len(got)] and len(got) == entries[0].size_bytes
        res["log_bytes"] = len(got)
    return res


HOME_AMSL = 488.0


async def _flying_mode(telemetry, mode) -> bool:
    return await telemetry.flight_mode() == mode


async def _disarmed(telemetry) -> bool:
    return not await telemetry.armed()


@pytest.mark.skipif(not hasattr(mavsdk, "asyncio"), reason="needs MAVSDK 4.x")
@pytest.mark.parametrize("vehicle", [pytest.param("unit", marks=pytest.mark.long), pytest.param("assembly", marks=pytest.mark.long)])  # (CI time: -m long; MAVSDK on a unit: test_mavsdk_unit)
def test_mavsdk_goto_orbit_fence_manual_rally_attitude_land_and_logs(tmp_path: Path, vehicle: str) -> None:
    api = free_udp_port()
    status, tlog = tmp_path / "status.json", tmp_path / "run.tlog"
    if vehicle == "unit":
        proc, _ = spawn_api_unit(api, status, "--tlog", str(tlog))
    else:
        from mars_link.processes.realtime import spawn_vehicle

        proc, _ = spawn_vehicle(["--layout", "XXX,XXX", "--ftc", "qp", "--api-port", str(api), "--api-bind", "0",
                                 "--gcs-port", str(free_udp_port()), "--gcs-bind", "0", "--tlog", str(tlog)], status)
    try:
        # the unit process flies mars-ftcc (its --preset default), `mars-link vehicle` the interactive scenario's plant
        plant = (vehicle_preset("mars-ftcc") if vehicle == "unit"
                 else load_scenario(INTERACTIVE_SCENARIO).model().vehicle)
        res = asyncio.run(_flights(api, status, tlog, plant))
    finally:
        rc = stop_unit(proc)
    print(res)
    assert rc == 0
    assert res["goto_error_m"] < 0.1 and res["goto_outside"].endswith("COMMAND_DENIED")
    lo, hi = res["orbit_radius_m"]
    assert ORBIT_R_M - 0.3 < lo and hi < ORBIT_R_M + 0.3
    forward, sideways = res["manual_moved_m"]  # along the heading (half stick: 1 m/s for 3 s), across it
    assert forward > 2.0 and abs(sideways) < 0.2 and res["manual_hold_drift_m"] < 0.1
    assert math.dist(res["rtl_landed_at"][:2], RALLY_NE[0]) < 0.3
    assert abs(res["attitude_truth_pitch_deg"] + 6.0) < 1.0 and abs(res["attitude_pitch_deg"] + 6.0) < 1.0
    assert res["descent_landed_at"][2] > res["ground_z"] - 0.1
    assert res["log_entries"] and res["log_same"] and res["log_bytes"] > 10_000
