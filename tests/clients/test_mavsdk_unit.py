"""MAVSDK 4.x (native binding, asyncio API) flies one unit process over UDP on loopback: connect,
telemetry against the JSBSim truth, arm, takeoff, offboard 1 m north and back, land, disarm, then a
motor failure injected through MAVSDK's failure plugin changes how the unit flies."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time
from pathlib import Path

import pytest

from mars_link.processes.udp_runner import free_udp_port, read_status, spawn_unit, stop_unit

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.failure import FailureAsync, FailureType, FailureUnit  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync, PositionNedYaw  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(240)]



@contextlib.asynccontextmanager
async def autopilot(port: int, timeout_s: float = 15.0):
    """MAVSDK as a ground station listening on 127.0.0.1:port, and the first autopilot it finds."""
    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(cfg) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await sdk.first_autopilot(timeout_s=timeout_s)
        assert system is not None, "MAVSDK did not find the autopilot"
        yield system


# The waits below bound a hang, they claim no speed: the unit is paced to the wall clock and a loaded
# machine runs it behind (a 15 s leg took longer beside CPU-heavy tests), so each bound is stretched.
PATIENCE = 4.0


async def _until(predicate, timeout_s: float, what: str, period_s: float = 0.1):
    deadline = time.monotonic() + PATIENCE * timeout_s
    while time.monotonic() < deadline:
        value = await predicate()
        if value:
            return value
        await asyncio.sleep(period_s)
    raise AssertionError(f"timed out waiting for {what}")


async def _mode(telemetry) -> FlightMode:
    return await telemetry.flight_mode()


async def _fly(api_port: int, status_path: Path) -> dict:
    results: dict = {}
    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(cfg) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{api_port}")
        system = await sdk.first_autopilot(timeout_s=15.0)
        assert system is not None, "MAVSDK did not find the unit"
        telemetry, action = TelemetryAsync(system), ActionAsync(system)
        offboard, failure = OffboardAsync(system), FailureAsync(system)
        assert await system.get_system_id() == 4

        async def pv():
            return await telemetry.position_velocity_ned()

        async def rel_alt():
            return (await telemetry.position()).relative_altitude_m

        # telemetry on the ground: truth vs what MAVSDK shows
        await _until(lambda: telemetry.health_all_ok(), 10.0, "health_all_ok")

        async def ground_position():  # MAVSDK reports NaN until the first LOCAL_POSITION_NED is in
            q = (await pv()).position
            return q if math.isfinite(q.north_m + q.east_m + q.down_m) else None

        p = await _until(ground_position, 5.0, "a position from MAVSDK")
        truth = read_status(status_path)["truth_position_ned_m"]
        results["ground_error_m"] = math.dist((p.north_m, p.east_m, p.down_m), truth)
        results["armed_before"] = await telemetry.armed()
        assert await action.get_takeoff_altitude() == pytest.approx(2.0)

        await action.arm()
        await _until(lambda: telemetry.armed(), 5.0, "armed telemetry")
        await action.takeoff()
        await _until(lambda: _is(telemetry, FlightMode.TAKEOFF, FlightMode.HOLD), 5.0, "TAKEOFF mode")
        await _until(lambda: _near(rel_alt, 2.0, 0.1), 20.0, "2 m altitude")
        await _until(lambda: _is(telemetry, FlightMode.HOLD), 10.0, "HOLD after takeoff")
        await asyncio.sleep(1.0)
        # hovering: MAVSDK's position vs the JSBSim truth at (almost) the same moment
        errs = []
        for _ in range(5):
            p = (await pv()).position
            truth = read_status(status_path)["truth_position_ned_m"]
            errs.append(math.dist((p.north_m, p.east_m, p.down_m), truth))
            await asyncio.sleep(0.2)
        results["hover_error_m"] = min(errs)
        start = (await pv()).position
        results["hover_altitude_m"] = await rel_alt()

        # offboard: 1 m north and back
        await offboard.set_position_ned(PositionNedYaw(start.north_m + 1.0, start.east_m, start.down_m, 0.0))
        await offboard.start()
        await _until(lambda: _is(telemetry, FlightMode.OFFBOARD), 5.0, "OFFBOARD mode")
        await _until(lambda: _north_near(pv, start.north_m + 1.0), 15.0, "1 m north")
        results["north_reached_m"] = (await pv()).position.north_m - start.north_m
        await offboard.set_position_ned(PositionNedYaw(start.north_m, start.east_m, start.down_m, 0.0))
        await _until(lambda: _north_near(pv, start.north_m), 15.0, "back at the start")
        await offboard.stop()
        await _until(lambda: _is(telemetry, FlightMode.HOLD), 5.0, "HOLD after offboard")

        await action.land()
        await _until(lambda: _not(telemetry.in_air), 20.0, "landed")
        await _until(lambda: _not(telemetry.armed), 10.0, "auto-disarm after landing")
        results["armed_after_landing"] = await telemetry.armed()

        # second flight: a motor failure injected with MAVSDK's failure plugin
        await action.arm()
        await action.takeoff()
        await _until(lambda: _near(rel_alt, 2.0, 0.15), 20.0, "2 m altitude again")
        await asyncio.sleep(1.5)
        tilt_before = _tilt_deg(read_status(status_path))
        alt_before = await rel_alt()
        await failure.inject(FailureUnit.SYSTEM_MOTOR, FailureType.OFF, 1)
        worst_tilt, lowest = tilt_before, alt_before
        for _ in range(30):
            await asyncio.sleep(0.1)
            st = read_status(status_path)
            worst_tilt = max(worst_tilt, _tilt_deg(st))
            lowest = min(lowest, -st["truth_position_ned_m"][2])
        st = read_status(status_path)
        results.update(tilt_before_deg=tilt_before, worst_tilt_deg=worst_tilt, alt_before_m=alt_before,
                       lowest_after_m=lowest, eta=st["motor_eta"], drops=st["drops"])
        await action.kill()
    return results


def _tilt_deg(status: dict) -> float:
    w, x, y, z = status["truth_quaternion_wxyz"]
    return math.degrees(math.acos(max(-1.0, min(1.0, 1 - 2 * (x * x + y * y)))))


async def _is(telemetry, *modes) -> bool:
    return await telemetry.flight_mode() in modes


async def _not(getter) -> bool:
    return not await getter()


async def _near(getter, value: float, tol: float) -> bool:
    return abs(await getter() - value) < tol


async def _at_altitude(telemetry, altitude_m: float, tol_m: float = 0.05) -> bool:
    return abs((await telemetry.position()).relative_altitude_m - altitude_m) < tol_m


async def _north_near(pv, north: float) -> bool:
    s = await pv()
    return abs(s.position.north_m - north) < 0.05 and abs(s.velocity.north_m_s) < 0.1


def test_mavsdk_flies_a_unit_and_injects_a_motor_failure(tmp_path: Path) -> None:
    api = free_udp_port()
    status = tmp_path / "status.json"
    proc, ready = spawn_unit([
        "--unit", "4", "--api-port", str(api), "--api-bind", "0", "--gcs-port", str(free_udp_port()),
        "--gcs-bind", "0", "--coord-bind", "0", "--status-file", str(status),
    ])
    try:
        r = asyncio.run(_fly(api, status))
    finally:
        assert stop_unit(proc) == 0
    print(json.dumps(r, indent=1))
    assert r["ground_error_m"] < 0.1 and r["hover_error_m"] < 0.1
    assert r["armed_before"] is False and r["armed_after_landing"] is False
    assert abs(r["hover_altitude_m"] - 2.0) < 0.1
    assert abs(r["north_reached_m"] - 1.0) < 0.05
    # the failure reached the motor model only, and visibly changed the flight
    assert r["eta"] == [0.0, 1.0, 1.0, 1.0]
    assert r["tilt_before_deg"] < 5.0
    assert r["worst_tilt_deg"] > 30.0 or r["alt_before_m"] - r["lowest_after_m"] > 0.5
    assert not r["drops"], r["drops"]  # MAVSDK's own traffic is all understood
