"""PX4's speed parameters on the unit vehicle flying a JSBSim body in lockstep, with real MAVLink bytes
(and MAVSDK's action.set_maximum_speed against a unit process): a goto cruises at MPC_XY_CRUISE and
climbs at MPC_Z_VEL_MAX_UP, an offboard velocity stream is capped at MPC_XY_VEL_MAX (PX4's 12 m/s by
default), all measured on the body's truth."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink
from test_geofence import _set
from test_mission_protocol import _deg
from test_vehicle_protocol import LINK_API, Client, Flight, _ack, _vehicle

R = mavlink
NAN = math.nan


def _airborne(cruise: float | None = None, limits: dict | None = None):
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    for name, value in ({"MPC_XY_CRUISE": cruise} if cruise else {}).items() | (limits or {}).items():
        _set(api, name, value, f.wall)
    assert _ack(api.command(400, 1, wall=f.wall), 400) == 0
    assert _ack(api.command(22, wall=f.wall), 22) == 0
    f.run(5.0)
    return v, f, api


def _speeds(f: Flight, seconds: float, each=None) -> np.ndarray:
    """(S, 2) true horizontal and vertical (up) speed every control step."""
    out = []

    def watch(fl):
        if each is not None:
            each(fl)
        vel = fl.body.state().velocity_ned_mps
        out.append((math.hypot(vel[0], vel[1]), -vel[2]))

    f.run(seconds, watch)
    return np.array(out)


def _plateau(speed: np.ndarray, level: float, settle: int = 150) -> np.ndarray:
    """The speeds of the steady part: from 1.5 s after first reaching 95 % of `level` to the last time there
    (the transients at the ends of the acceleration ramps left out)."""
    at = np.nonzero(speed >= 0.95 * level)[0]
    assert len(at), f"never reached 95 % of {level}"
    return speed[at[0] + settle:at[-1] - settle // 5]


def _goto(api: Client, f: Flight, north_m: float, east_m: float, alt_amsl_m: float) -> None:
    lat, lon = _deg(north_m, east_m)
    msg = R.MAVLink_command_int_message(1, 1, R.MAV_FRAME_GLOBAL, R.MAV_CMD_DO_REPOSITION, 0, 0, -1, 0, 0, NAN,
                                        lat, lon, alt_amsl_m)
    assert _ack(api.send(msg, f.wall), R.MAV_CMD_DO_REPOSITION) == 0


@pytest.mark.parametrize("cruise", [1.0, 5.0])
def test_a_goto_cruises_at_mpc_xy_cruise(cruise: float) -> None:
    v, f, api = _airborne(cruise)
    start = f.pos.copy()
    _goto(api, f, start[0] + 40.0, start[1], 490.0)
    s = _speeds(f, 40.0 / cruise + 6.0)
    steady = _plateau(s[:, 0], cruise)
    print(f"MPC_XY_CRUISE {cruise}: true horizontal speed {steady.min():.3f}..{steady.max():.3f} m/s over "
          f"{len(steady) / 100:.1f} s of cruise, max {s[:, 0].max():.3f}")
    assert len(steady) > 100 and np.all(np.abs(steady / cruise - 1.0) < 0.03)
    assert s[:, 0].max() < cruise + 0.35  # the transient at the end of the 2 m/s^2 ramp
    assert math.dist(f.pos[:2], (start[0] + 40.0, start[1])) < 0.3  # and it arrives


def test_a_climbing_goto_keeps_mpc_z_vel_max_up_and_dn() -> None:
    v, f, api = _airborne(limits={"MPC_Z_VEL_MAX_UP": 0.6, "MPC_Z_VEL_MAX_DN": 0.4})
    p = f.pos.copy()
    _goto(api, f, p[0], p[1], 488.0 + 8.0)  # 6 m up
    up = _speeds(f, 14.0)
    _goto(api, f, p[0], p[1], 488.0 + 4.0)  # 4 m down
    down = _speeds(f, 14.0)
    climb, descent = _plateau(up[:, 1], 0.6), _plateau(-down[:, 1], 0.4)
    print(f"climb {climb.min():.3f}..{climb.max():.3f} m/s (0.6 asked), descent {descent.min():.3f}..{descent.max():.3f}"
          f" m/s (0.4 asked); peaks {up[:, 1].max():.3f} / {-down[:, 1].min():.3f}")
    assert len(climb) > 300 and np.all(np.abs(climb / 0.6 - 1.0) < 0.03)
    assert len(descent) > 300 and np.all(np.abs(descent / 0.4 - 1.0) < 0.03)
    assert abs(-f.pos[2] - 4.0) < 0.15


@pytest.mark.parametrize("vmax, asked, expected", [(12.0, 9.0, 9.0), (6.0, 9.0, 6.0)])
def test_offboard_velocity_is_capped_at_mpc_xy_vel_max(vmax: float, asked: float, expected: float) -> None:
    v, f, api = _airborne(limits={} if vmax == 12.0 else {"MPC_XY_VEL_MAX": vmax})
    assert v.params["MPC_XY_VEL_MAX"] == vmax  # 12 m/s: PX4's default
    vel = R.MAVLink_set_position_target_local_ned_message(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0,
                                                          asked, 0, 0, 0, 0, 0, 0, 0)

    def stream(fl):
        if round(fl.t * 100) % 5 == 0:
            api.send(vel, fl.wall)

    f.run(0.1, stream)
    assert _ack(api.command(176, 129, 6, 0, wall=f.wall), 176) == 0  # OFFBOARD
    s = _speeds(f, asked / 2.0 + 4.0, stream)  # the shaper accelerates at 2 m/s^2
    late = s[-200:, 0]
    print(f"MPC_XY_VEL_MAX {vmax}, {asked} m/s asked: true speed over the last 2 s {late.min():.3f}..{late.max():.3f}")
    assert np.all(np.abs(late / expected - 1.0) < 0.03) and s[:, 0].max() < expected + 0.35


@pytest.mark.long  # (35 s in real time, for CI's time: the lockstep tests above cover the ground)
@pytest.mark.sitl
def test_mavsdk_param_and_set_current_speed_set_the_goto_speed(tmp_path) -> None:
    """MAVSDK's param plugin writes MPC_XY_CRUISE, its action.set_current_speed sends DO_CHANGE_SPEED."""
    pytest.importorskip("mavsdk")
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.param import ParamAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
    from test_mavsdk_mission import _latlon
    from test_mavsdk_unit import _until, autopilot
    from unit_process import api_unit

    async def leg(action, truth, north_m: float, seconds: float) -> tuple[list, list]:
        await action.goto_location(*_latlon(north_m, 0.0), 488.0 + 2.0, 0.0)
        speeds = []
        for _ in range(int(seconds * 10)):
            v = truth("truth_velocity_ned_mps")
            speeds.append(math.hypot(v[0], v[1]))
            await asyncio.sleep(0.1)
        return speeds, truth("truth_position_ned_m")

    async def fly(api_port, truth) -> dict:
        async with autopilot(api_port) as system:
            telemetry, action, param = TelemetryAsync(system), ActionAsync(system), ParamAsync(system)
            await _until(lambda: telemetry.health_all_ok(), 15.0, "health_all_ok")
            await param.set_param_float("MPC_XY_CRUISE", 4.0)
            got = await param.get_param_float("MPC_XY_CRUISE")
            await action.arm()
            await action.takeoff()
            await asyncio.sleep(6.0)
            fast, end1 = await leg(action, truth, 30.0, 13.0)
            await action.set_current_speed(1.5)
            slow, end2 = await leg(action, truth, 20.0, 10.0)
            await action.land()
            return {"got": got, "fast": fast, "slow": slow, "end1": end1, "end2": end2}

    with api_unit(tmp_path) as (api_port, truth):
        res = asyncio.run(fly(api_port, truth))
    fast, slow = _plateau(np.array(res["fast"]), 4.0, settle=15), _plateau(np.array(res["slow"]), 1.5, settle=15)
    print(f"MAVSDK: MPC_XY_CRUISE 4 -> true speed {fast.min():.3f}..{fast.max():.3f} m/s; set_current_speed(1.5) -> "
          f"{slow.min():.3f}..{slow.max():.3f} m/s")
    assert res["got"] == pytest.approx(4.0)
    assert len(fast) >= 20 and np.all(np.abs(fast / 4.0 - 1.0) < 0.05) and max(res["fast"]) < 4.35
    assert len(slow) >= 20 and np.all(np.abs(slow / 1.5 - 1.0) < 0.05)
    assert math.dist(res["end1"][:2], (30.0, 0.0)) < 0.3 and math.dist(res["end2"][:2], (20.0, 0.0)) < 0.3
