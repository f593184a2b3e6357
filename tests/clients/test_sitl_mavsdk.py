"""MAVSDK 4.x flies one unit of `sitl up --units 1`: a world process and a unit process in lockstep
(the unit's full firmware on its HIL link, the world's JSBSim body). Telemetry is checked against the
WORLD's truth (its status file), not against anything the unit reports about itself. The world runs
at 2x real time (--speed 2) to keep the test short; MAVSDK's timing is wall-clock throughout."""

from __future__ import annotations

import asyncio
import json
import math
import time
from pathlib import Path

import pytest

from mars_link.processes.udp_runner import read_status
from mars_link.processes.launcher import ClientPorts, free_udp_port, start, wait
from test_mavsdk_unit import _is, _near, _north_near, _not, _until

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.failure import FailureAsync, FailureType, FailureUnit  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync, PositionNedYaw  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(180),
              pytest.mark.exclusive]  # (flights paced to the wall clock, judged at wall-clock instants)


def _truth(out: Path) -> dict:
    return read_status(out / "world_status.json")["units"]["1"]


async def _truth_north(out: Path, start_north_m: float, target_m: float, timeout_s: float = 3.0) -> float:
    """The world's truth north of the start, once within 0.1 m of `target_m` (else the last one read).

    MAVSDK's estimate says the unit has arrived; the world's status file lags it by up to its 0.2 s wall
    period (more when the machine is slow), so the truth gets a moment to say the same."""
    deadline = time.monotonic() + timeout_s
    while True:
        north = _truth(out)["position_ned_m"][0] - start_north_m
        if abs(north - target_m) < 0.1 or time.monotonic() > deadline:
            return north
        await asyncio.sleep(0.05)


def _tilt_deg(q) -> float:
    w, x, y, z = q
    return math.degrees(math.acos(max(-1.0, min(1.0, 1 - 2 * (x * x + y * y)))))


async def _fly(api_port: int, out: Path) -> dict:
    r: dict = {}
    async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{api_port}")
        system = await sdk.first_autopilot(timeout_s=30.0)
        assert system is not None, "MAVSDK did not find the unit"
        telemetry, action = TelemetryAsync(system), ActionAsync(system)
        offboard, failure = OffboardAsync(system), FailureAsync(system)
        r["sysid"] = await system.get_system_id()

        async def pv():
            return await telemetry.position_velocity_ned()

        async def rel_alt():
            return (await telemetry.position()).relative_altitude_m

        async def error_to_truth() -> float:
            async def position():  # MAVSDK reports NaN until the first LOCAL_POSITION_NED is in
                q = (await pv()).position
                return q if math.isfinite(q.north_m + q.east_m + q.down_m) else None

            p = await _until(position, 5.0, "a position from MAVSDK")
            return math.dist((p.north_m, p.east_m, p.down_m), _truth(out)["position_ned_m"])

        await _until(lambda: telemetry.health_all_ok(), 15.0, "health_all_ok")
        r["ground_error_m"] = await error_to_truth()
        r["armed_before"] = await telemetry.armed()
        r["mode_before"] = str(await telemetry.flight_mode())

        await action.arm()
        await _until(lambda: telemetry.armed(), 5.0, "armed telemetry")
        await action.takeoff()
        await _until(lambda: _near(rel_alt, 2.0, 0.1), 20.0, "2 m altitude")
        await _until(lambda: _is(telemetry, FlightMode.HOLD), 10.0, "HOLD after takeoff")
        r["hover_error_m"] = min([await error_to_truth() for _ in range(3)])
        r["hover_truth_down_m"] = _truth(out)["position_ned_m"][2]
        start = (await pv()).position

        await offboard.set_position_ned(PositionNedYaw(start.north_m + 1.0, start.east_m, start.down_m, 0.0))
        await offboard.start()
        await _until(lambda: _is(telemetry, FlightMode.OFFBOARD), 5.0, "OFFBOARD mode")
        await _until(lambda: _north_near(pv, start.north_m + 1.0), 15.0, "1 m north")
        r["north_truth_m"] = await _truth_north(out, start.north_m, 1.0)
        await offboard.set_position_ned(PositionNedYaw(start.north_m, start.east_m, start.down_m, 0.0))
        await _until(lambda: _north_near(pv, start.north_m), 15.0, "back at the start")
        r["back_truth_m"] = await _truth_north(out, start.north_m, 0.0)
        await offboard.stop()

        await action.land()
        await _until(lambda: _not(telemetry.in_air), 20.0, "landed")
        await _until(lambda: _not(telemetry.armed), 10.0, "auto-disarm after landing")
        r["landed_truth_down_m"] = _truth(out)["position_ned_m"][2]

        # second flight: a motor failure injected with MAVSDK's failure plugin
        await action.arm()
        await action.takeoff()
        await _until(lambda: _near(rel_alt, 2.0, 0.15), 20.0, "2 m altitude again")
        await asyncio.sleep(1.0)
        before = _truth(out)
        r["tilt_before_deg"] = _tilt_deg(before["quaternion_wxyz"])
        await failure.inject(FailureUnit.SYSTEM_MOTOR, FailureType.OFF, 1)
        worst, lowest = r["tilt_before_deg"], -before["position_ned_m"][2]
        for _ in range(12):  # 1.2 s of wall time, 2.4 s simulated
            await asyncio.sleep(0.1)
            t = _truth(out)
            worst, lowest = max(worst, _tilt_deg(t["quaternion_wxyz"])), min(lowest, -t["position_ned_m"][2])
        r.update(worst_tilt_deg=worst, alt_before_m=-before["position_ned_m"][2], lowest_after_m=lowest,
                 eta=read_status(out / "unit1_status.json")["motor_eta"])
        await action.kill()
    return r


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_mavsdk_flies_one_lockstep_sitl_unit(tmp_path: Path) -> None:
    api = free_udp_port()
    out = tmp_path / "run"
    run = start(None, out, units=1, speed=2.0, clients=ClientPorts(free_udp_port(), [api], bind_any=True))
    try:
        r = asyncio.run(_fly(api, out))
    finally:
        code = wait(run, timeout_s=0.1)  # stops every child (by PID)
    print(json.dumps(r, indent=1))
    assert code == 124 and all(p.returncode == 0 for p in run.processes.values())  # stopped cleanly
    assert r["sysid"] == 1
    assert r["ground_error_m"] < 0.1 and r["hover_error_m"] < 0.1
    assert r["armed_before"] is False
    assert abs(-r["hover_truth_down_m"] - 2.0) < 0.15  # the world's body really is at 2 m
    assert abs(r["north_truth_m"] - 1.0) < 0.1 and abs(r["back_truth_m"]) < 0.1
    assert r["landed_truth_down_m"] > -0.1
    # the failure reached the motor model only, and the world's body shows it
    assert r["eta"] == [0.0, 1.0, 1.0, 1.0]
    assert r["tilt_before_deg"] < 5.0
    assert r["worst_tilt_deg"] > 30.0 or r["alt_before_m"] - r["lowest_after_m"] > 0.5
    world = json.loads((out / "world_summary.json").read_text())
    assert world["dead_units"] == [] and world["dropped"] == {}
    assert (out / "unit1.tlog").stat().st_size > 10_000  # logged as it went
