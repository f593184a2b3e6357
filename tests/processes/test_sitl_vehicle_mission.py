"""`mars-link sitl up hover_3x2 --vehicle` flies a mission: MAVSDK 4.x's mission plugin uploads three
waypoints with return-to-launch after them to the assembly vehicle the lockstep coordinator serves (six
unit processes, the JSBSim world process), starts it, and the world's truth is checked: each waypoint
passed within its acceptance radius, MAVSDK's progress to the end, landed at home and disarmed; every
child process is gone after `sitl up` is stopped."""

from __future__ import annotations

import asyncio
import math
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mars_link.processes.udp_runner import read_status

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.mission import MissionAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync  # noqa: E402
from mavsdk.plugins.mission import MissionItem, MissionPlan  # noqa: E402
from test_mavsdk_mission import _latlon  # noqa: E402
from test_mavsdk_unit import _until, autopilot  # noqa: E402
from test_sitl_vehicle import REPO, _alive, _port_block, truth_com_ned  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(180)]
WAYPOINTS_NE = [(3.0, 0.0), (3.0, 3.0), (0.0, 3.0)]
ALT_M, RADIUS_M = 2.5, 0.3


async def _mission(api_port: int, out: Path) -> dict:
    r: dict = {"truth": [], "progress": []}
    async with autopilot(api_port, 20.0) as system:
        telemetry, action, mission = TelemetryAsync(system), ActionAsync(system), MissionAsync(system)
        await _until(lambda: telemetry.health_all_ok(), 15.0, "health_all_ok")
        r["ground"] = truth_com_ned(out)
        items = [MissionItem(*_latlon(n, e), ALT_M, 1.0, False, acceptance_radius_m=RADIUS_M, loiter_time_s=0.5)
                 for n, e in WAYPOINTS_NE]
        await mission.set_return_to_launch_after_mission(True)
        await mission.upload_mission(MissionPlan(items))

        async def progress():
            async for p in mission.subscribe_mission_progress():
                r["progress"].append((p.current, p.total))

        watcher = asyncio.ensure_future(progress())
        await action.arm()
        await mission.start_mission()

        async def done() -> bool:
            r["truth"].append(truth_com_ned(out))
            return await mission.is_mission_finished() and not await telemetry.armed()

        await _until(done, 90.0, "the mission flown, landed and disarmed", 0.1)
        watcher.cancel()
        r["landed_at"] = truth_com_ned(out)
    return r


@pytest.mark.long  # (CI time: -m long)
@pytest.mark.skipif(not hasattr(mavsdk, "asyncio"), reason="needs MAVSDK 4.x")
def test_sitl_up_vehicle_flies_a_mavsdk_mission(tmp_path: Path) -> None:
    out = tmp_path / "run"
    base = _port_block(8)
    cmd = [sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", "hover_3x2", "--vehicle", "--transport", "udp", "--any-bind",
           "--vehicle-api-port", str(base), "--gcs-port", str(base + 1), "--api-port", str(base + 2), "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    children: list[int] = []
    try:
        while True:
            line = proc.stdout.readline()
            assert line, f"sitl up ended early: {lines}"
            lines.append(line.strip())
            if line.startswith("assembly vehicle"):
                break
        children = [int(p) for p in re.findall(r"pid (\d+)", "\n".join(lines))]
        deadline = time.monotonic() + 20.0
        while not ((out / "vehicle_status.json").exists() and (out / "world_status.json").exists()):
            assert time.monotonic() < deadline, "the world or the vehicle did not start"
            time.sleep(0.1)
        r = asyncio.run(_mission(base, out))
        vehicle = read_status(out / "vehicle_status.json")
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    deadline = time.monotonic() + 5.0
    while any(_alive(p) for p in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert children and not [p for p in children if _alive(p)], "children left running"
    ground = r["ground"]
    closest = [min(math.dist(p, (n, e, ground[2] - ALT_M)) for p in r["truth"]) for n, e in WAYPOINTS_NE]
    print({"closest_m": closest, "progress": r["progress"][-3:], "landed_at": r["landed_at"],
           "statustext": vehicle["statustext"][-8:]})
    assert max(closest) <= RADIUS_M + 0.05  # sampled at ~10 Hz through a 0.5 s loiter at each
    assert r["progress"][-1] == (3, 3) and sorted({c for c, _ in r["progress"]}) == [0, 1, 2, 3]
    assert math.dist(r["landed_at"][:2], ground[:2]) < 0.3 and abs(r["landed_at"][2] - ground[2]) < 0.05
    assert "Mission finished: landed" in vehicle["statustext"]
