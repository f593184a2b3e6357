"""Follow-me (AUTO.FOLLOW_TARGET, firmware_models.vehicle_follow): a target walks north, then east; the
vehicle keeps FLW_TGT_DST behind it (FLW_TGT_FA 180) at FLW_TGT_HT above home, judged on the JSBSim
truth. In lockstep with FOLLOW_TARGET bytes once a second as MAVSDK sends them, on a lone unit and on
the 3x2 as one vehicle; and with MAVSDK's follow_me plugin against a unit process and against
`mars-link vehicle`."""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink
from test_geofence import _set
from test_vehicle_protocol import LINK_API, Client, Flight, _ack, _vehicle

from mars_link.core.geo import GeoOrigin

R = mavlink
SPEED_MPS = 1.0


def target_at(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The walk: 15 s north at 1 m/s, then east; (position NE, velocity NE)."""
    if t_s < 15.0:
        return np.array([SPEED_MPS * t_s, 0.0]), np.array([SPEED_MPS, 0.0])
    return np.array([15.0 * SPEED_MPS, SPEED_MPS * (t_s - 15.0)]), np.array([0.0, SPEED_MPS])


def follow_target_msg(origin: GeoOrigin, ne: np.ndarray, t_ms: int):
    lat, lon, _ = origin.to_global(np.array([ne[0], ne[1], 0.0]))
    # as MAVSDK packs it: position only (est_capabilities bit 0), velocity fields zero
    return R.MAVLink_follow_target_message(t_ms, 1, int(round(lat * 1e7)), int(round(lon * 1e7)), origin.amsl_m,
                                           [0.0] * 3, [math.nan] * 3, [1.0, math.nan, math.nan, math.nan],
                                           [math.nan] * 3, [math.nan] * 3, 0)


def check_following(track: list, dist_m: float, height_m: float, home_z: float) -> dict:
    """Behind the target by dist_m on its course and height_m above home, after 8 s to settle on each leg."""
    errs = []
    for t, p, tgt_ne, course in track:
        if 8.0 <= t < 15.0 or 23.0 <= t:
            want = tgt_ne - dist_m * np.array([math.cos(course), math.sin(course)])
            errs.append((np.hypot(*(p[:2] - want)), abs((home_z - p[2]) - height_m),
                         np.hypot(*(p[:2] - tgt_ne))))
    e = np.array(errs)
    return {"position_err_max_m": float(e[:, 0].max()), "position_err_p95_m": float(np.percentile(e[:, 0], 95)), "height_err_max_m": float(e[:, 1].max()),
            "distance_m": (float(e[:, 2].min()), float(e[:, 2].max())), "samples": len(e)}


def test_a_unit_follows_a_walking_target_at_the_configured_distance_and_height() -> None:
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    _set(api, "FLW_TGT_DST", 4.0, f.wall)
    _set(api, "FLW_TGT_HT", 3.0, f.wall)
    home_z = f.pos[2]
    assert _ack(api.command(176, 1, 4, 8, wall=f.wall), 176) == R.MAV_RESULT_TEMPORARILY_REJECTED  # on the ground
    assert _ack(api.command(400, 1, wall=f.wall), 400) == 0
    assert _ack(api.command(22, wall=f.wall), 22) == 0
    f.run(4.0)
    assert _ack(api.command(176, 1, 4, 8, wall=f.wall), 176) == 0  # AUTO.FOLLOW_TARGET, as MAVSDK sets it
    hb = [m for m in api.decode(v.tick(f.wall + 1.0, f.t)) if m.get_type() == "HEARTBEAT"]
    assert hb and hb[-1].custom_mode == (4 << 16) | (8 << 24)
    t0 = f.t
    track = []

    def walk(fl):
        t = fl.t - t0
        ne, vel = target_at(t)
        if round(t * 100) % 100 == 0:  # once a second
            api.send(follow_target_msg(v.origin, ne, int(t * 1000)), fl.wall)
        track.append((t, fl.pos.copy(), ne, math.atan2(vel[1], vel[0])))

    f.run(30.0, walk)
    res = check_following(track, 4.0, 3.0, home_z)
    print(f"unit following: {res}")
    assert res["samples"] > 1000
    assert res["position_err_max_m"] < 0.3 and res["height_err_max_m"] < 0.1
    # the target stops sending: lost after FOLLOW_LOST_S, the unit holds where it is
    f.run(3.0)
    held = f.pos.copy()
    f.run(2.0)
    assert np.linalg.norm(f.pos - held) < 0.1 and any("target lost" in t for _, t in v.events)


def test_the_3x2_follows_a_walking_target() -> None:
    from mars_link.vehicles.vehicle_sim import VehicleSim
    from mars_link.config.scenario import load_scenario

    sim = VehicleSim(load_scenario("hover_3x2"))
    try:
        gcs, dec = R.MAVLink(None, 245, 190), R.MAVLink(None, 0, 0)

        def send(msg) -> list:
            return [m for o in sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api") if o.link == "api"
                    for m in dec.parse_buffer(o.data) or []]

        def acked(msg) -> int:
            return next(m.result for m in send(msg) if m.get_type() == "COMMAND_ACK")

        for name, value in (("FLW_TGT_DST", 4.0), ("FLW_TGT_HT", 2.5)):
            send(R.MAVLink_param_set_message(1, 1, name.encode(), value, R.MAV_PARAM_TYPE_REAL32))
        for _ in range(30):
            sim.step(sim.t_s)
        home_z = sim.truth().position_ned_m[2]
        assert acked(R.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)) == 0
        assert acked(R.MAVLink_command_long_message(1, 1, 22, 0, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)) == 0
        while sim.t_s < 6.0:
            sim.step(sim.t_s)
        assert acked(R.MAVLink_command_long_message(1, 1, 176, 0, 1, 4, 8, 0, 0, 0, 0)) == 0
        t0, track = sim.t_s, []
        while sim.t_s - t0 < 30.0:
            t = sim.t_s - t0
            ne, vel = target_at(t)
            if round(t * 100) % 100 == 0:
                send(follow_target_msg(sim.vehicle.origin, ne, int(t * 1000)))
            sim.step(sim.t_s)
            track.append((t, sim.truth().position_ned_m.copy(), ne, math.atan2(vel[1], vel[0])))
        res = check_following(track, 4.0, 2.5, home_z)
        print(f"3x2 following: {res}")
        assert res["position_err_max_m"] < 0.3 and res["height_err_max_m"] < 0.15
    finally:
        sim.close()


@pytest.mark.long  # (45 s each in real time, for CI's time: the lockstep tests above cover the ground)
@pytest.mark.sitl
@pytest.mark.parametrize("vehicle", ["unit", "assembly"])
def test_mavsdk_follow_me_against_a_unit_and_mars_link_vehicle(vehicle: str, tmp_path) -> None:
    pytest.importorskip("mavsdk")
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.follow_me import FollowMeAsync
    from mavsdk.asyncio.plugins.param import ParamAsync
    from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync
    from mavsdk.plugins.follow_me import Config, TargetLocation
    from test_mavsdk_mission import _latlon, spawn_api_unit
    from test_mavsdk_unit import _until, autopilot

    from mars_link.processes.udp_runner import free_udp_port, read_status, stop_unit

    api_port = free_udp_port()
    status = tmp_path / "status.json"
    if vehicle == "unit":
        proc, _ = spawn_api_unit(api_port, status)
    else:
        from mars_link.processes.realtime import spawn_vehicle

        proc, _ = spawn_vehicle(["--layout", "XXX,XXX", "--api-port", str(api_port), "--api-bind", "0",
                                 "--gcs-port", str(free_udp_port()), "--gcs-bind", "0"], status)

    async def fly() -> dict:
        async with autopilot(api_port) as system:
            telemetry, action = TelemetryAsync(system), ActionAsync(system)
            follow, param = FollowMeAsync(system), ParamAsync(system)
            await _until(lambda: telemetry.health_all_ok(), 20.0, "health_all_ok")
            home_z = read_status(status)["truth_position_ned_m"][2]
            # MAVSDK's own minimum height is 8 m; 4 m behind (FLW_TGT_FA 180)
            cfg = Config(follow_height_m=8.0, follow_distance_m=4.0, responsiveness=0.1,
                         altitude_mode=Config.FollowAltitudeMode.CONSTANT, max_tangential_vel_m_s=5.0,
                         follow_angle_deg=180.0)
            await follow.set_config(cfg)
            got = tuple([await param.get_param_float(n) for n in ("FLW_TGT_HT", "FLW_TGT_DST", "FLW_TGT_MAX_VEL")])
            await action.arm()
            await action.takeoff()
            await asyncio.sleep(5.0)
            await follow.start()
            await _until(lambda: _in_follow(telemetry, FlightMode), 10.0, "FOLLOW_ME")
            t0, track = time.monotonic(), []
            while (t := time.monotonic() - t0) < 30.0:
                ne, vel = target_at(t)
                await follow.set_target_location(TargetLocation(*_latlon(*ne), 488.0, vel[0], vel[1], 0.0))
                track.append((t, np.array(read_status(status)["truth_position_ned_m"]), ne, math.atan2(vel[1], vel[0])))
                await asyncio.sleep(0.1)
            st = read_status(status)
            await follow.stop()
            await action.land()
            return {"got": got, "track": track, "home_z": home_z, "status": st}

    try:
        res = asyncio.run(fly())
    finally:
        stop_unit(proc)
    out = check_following(res["track"], 4.0, 8.0, res["home_z"])
    print(f"MAVSDK follow_me on the {vehicle}: FLW_TGT_HT/DST/MAX_VEL read back {res['got']}; {out}")
    assert res["got"] == (8.0, 4.0, 5.0)
    # real time on a shared machine: late steps of the vehicle's loop show as short lags (a 1.27 m maximum
    # once, at load 9 on two cores; 0.19 / 0.22 m otherwise): the 95th percentile is judged here, the
    # lockstep tests above hold the maximum to centimetres
    assert out["position_err_p95_m"] < 0.4 and out["height_err_max_m"] < 0.3


async def _in_follow(telemetry, FlightMode) -> bool:
    return await telemetry.flight_mode() == FlightMode.FOLLOW_ME
