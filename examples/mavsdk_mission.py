"""Fly `mars-link vehicle` (the whole assembly as one MAVLink vehicle) with MAVSDK-Python.

Start the vehicle in another terminal first:

    mars-link vehicle

then run this script. It connects on the vehicle's API port (as MAVSDK does with PX4 SITL), waits for a
position, arms, takes off, uploads and flies a small mission (an L of two waypoints), lands where the
mission ended and prints where the vehicle was at every stage.

Needs MAVSDK 4 (`pip install mavsdk`, the native binding with the `mavsdk.asyncio` API).
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import time

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.exceptions import MavsdkConnectionError
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.mission import MissionAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.plugins.mission import MissionItem, MissionPlan

EARTH_RADIUS_M = 6371000.0


def offset_latlon(lat_deg: float, lon_deg: float, north_m: float, east_m: float) -> tuple[float, float]:
    """The point `north_m`, `east_m` from (lat, lon): fine for the few metres of this mission."""
    return (lat_deg + math.degrees(north_m / EARTH_RADIUS_M),
            lon_deg + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat_deg)))))


async def wait_for(check, what: str, timeout_s: float, period_s: float = 0.2):
    """Poll the coroutine function `check` until it returns something true (or give up after timeout_s)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = await check()
        if value:
            return value
        await asyncio.sleep(period_s)
    raise TimeoutError(f"gave up waiting for {what} after {timeout_s:g} s")


async def print_position(telemetry: TelemetryAsync, stage: str) -> None:
    """The vehicle's local position (north, east, down from home, in metres) as it reports it."""
    p = (await telemetry.position_velocity_ned()).position
    print(f"{stage:<18} north {p.north_m:6.2f} m  east {p.east_m:6.2f} m  down {p.down_m:6.2f} m", flush=True)


async def fly(args: argparse.Namespace) -> None:
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as sdk:
        await sdk.add_any_connection(args.url)
        print(f"waiting for a vehicle on {args.url} ...", flush=True)
        system = await sdk.first_autopilot(timeout_s=args.timeout)
        if system is None:
            raise TimeoutError(f"no vehicle on {args.url} (is `mars-link vehicle` running?)")
        telemetry, action, mission = TelemetryAsync(system), ActionAsync(system), MissionAsync(system)

        # Ready to fly once its estimator has a position and home is set (PX4's health checks)
        await wait_for(telemetry.health_all_ok, "health (position, home)", args.timeout)
        home = await telemetry.home()
        await print_position(telemetry, "on the ground")

        # Arm and take off to the takeoff altitude; the vehicle holds there
        await action.set_takeoff_altitude(args.altitude)
        await action.arm()
        await action.takeoff()

        async def at_altitude() -> bool:
            return (await telemetry.position()).relative_altitude_m > 0.9 * args.altitude

        await wait_for(at_altitude, f"{args.altitude:g} m altitude", args.timeout)
        await print_position(telemetry, "took off")

        # The mission: `--leg` metres north, then `--leg` metres east, at the takeoff altitude
        legs_ne = [(args.leg, 0.0), (args.leg, args.leg)]
        items = [MissionItem(*offset_latlon(home.latitude_deg, home.longitude_deg, n, e), args.altitude,
                             args.speed, False, acceptance_radius_m=0.3) for n, e in legs_ne]
        await mission.set_return_to_launch_after_mission(False)  # stay at the last waypoint: we land there
        await mission.upload_mission(MissionPlan(items))
        await mission.start_mission()
        print(f"mission of {len(items)} waypoints started", flush=True)
        await wait_for(mission.is_mission_finished, "the end of the mission", args.timeout)
        await print_position(telemetry, "mission done")

        # Land where the mission ended; PX4 (and mars-link) disarm by themselves after landing
        await action.land()

        async def on_ground_disarmed() -> bool:
            return not await telemetry.in_air() and not await telemetry.armed()

        await wait_for(on_ground_disarmed, "landing and disarm", args.timeout)
        await print_position(telemetry, "landed")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", default="udpin://127.0.0.1:14539",
                        help="where MAVSDK listens (default: %(default)s, the API port of `mars-link vehicle`)")
    parser.add_argument("--altitude", type=float, default=2.0, help="takeoff and mission altitude, m (default: %(default)s)")
    parser.add_argument("--leg", type=float, default=3.0, help="length of each mission leg, m (default: %(default)s)")
    parser.add_argument("--speed", type=float, default=2.0, help="mission speed, m/s (default: %(default)s)")
    parser.add_argument("--timeout", type=float, default=30.0, help="give up on any one step after this many seconds")
    args = parser.parse_args()
    try:
        asyncio.run(fly(args))
    except MavsdkConnectionError as exc:  # a malformed URL, a port in use
        print(f"mavsdk_mission: cannot connect on {args.url}: {exc}", file=sys.stderr)
        return 2
    except TimeoutError as exc:
        print(f"mavsdk_mission: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
