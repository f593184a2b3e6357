"""Geofence and rally on the unit vehicle flying a JSBSim body in lockstep, with real MAVLink bytes:
a breach (polygon, circle, GF_MAX_HOR_DIST, GF_MAX_VER_DIST) is announced within 0.5 s of the moment
the body's truth crossed the fence and GF_ACTION is flown (warn, hold, return to the nearest rally
point, land); waypoints, goto, takeoff and offboard setpoints outside the fence are refused."""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mavlink
from test_mission_protocol import _deg, upload
from test_vehicle_protocol import LINK_API, Client, Flight, _ack, _vehicle

R = mavlink
NAN = math.nan
GLOBAL = R.MAV_FRAME_GLOBAL
REL = R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
FENCE, RALLY = R.MAV_MISSION_TYPE_FENCE, R.MAV_MISSION_TYPE_RALLY
PARAM_SET = R.MAVLink_param_set_message


def _vertices(corners_ne: list[tuple[float, float]], inclusion: bool = True) -> list:
    cmd = R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION if inclusion else R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION
    return [(cmd, len(corners_ne), ne) for ne in corners_ne]


def _fence_items(parts: list) -> list:
    """(command, param1, (north, east)) -> MISSION_ITEM_INT of the fence list, as QGC sends them."""
    out = []
    for seq, (cmd, p1, (n, e)) in enumerate(parts):
        lat, lon = _deg(n, e)
        out.append(R.MAVLink_mission_item_int_message(1, 1, seq, GLOBAL, cmd, 0, 1, p1, 0, 0, 0, lat, lon, 0.0, FENCE))
    return out


def _rally_items(points_ne: list[tuple[float, float]]) -> list:
    out = []
    for seq, (n, e) in enumerate(points_ne):
        lat, lon = _deg(n, e)
        out.append(R.MAVLink_mission_item_int_message(1, 1, seq, REL, R.MAV_CMD_NAV_RALLY_POINT, 0, 1, 0, 0, 0, 0,
                                                      lat, lon, 3.0, RALLY))
    return out


def _set(api: Client, name: str, value: float, wall: float, integer: bool = False) -> None:
    import struct
    wire = struct.unpack("<f", struct.pack("<i", int(value)))[0] if integer else float(value)
    kind = R.MAV_PARAM_TYPE_INT32 if integer else R.MAV_PARAM_TYPE_REAL32
    (pv,) = [m for m in api.send(PARAM_SET(1, 1, name.encode(), wire, kind), wall) if m.get_type() == "PARAM_VALUE"]
    got = struct.unpack("<i", struct.pack("<f", pv.param_value))[0] if integer else pv.param_value
    assert abs(got - value) < 1e-6, (name, got)


SQUARE = [(-6.0, -6.0), (-6.0, 6.0), (6.0, 6.0), (6.0, -6.0)]  # 12 m x 12 m around home


class Watch:
    """STATUSTEXTs with their sim time, and the first step the truth broke the fence."""

    def __init__(self, v, outside) -> None:
        self.gcs = Client(v, "gcs", 255, 190)
        self.outside = outside  # truth position -> bool, computed here (not by the vehicle's fence code)
        self.texts: list[tuple[float, str]] = []
        self.t_cross: float | None = None
        self.track: list[np.ndarray] = []

    def __call__(self, fl: Flight) -> None:
        for m in self.gcs.decode(fl.out):
            if m.get_type() == "STATUSTEXT":
                self.texts.append((fl.t, m.text))
        p = fl.body.state().position_ned_m
        self.track.append(p.copy())
        if self.t_cross is None and self.outside(p):
            self.t_cross = fl.t

    def first(self, prefix: str) -> float:
        return next(t for t, s in self.texts if s.startswith(prefix))


def _fly_out(action: int, fence: list, outside, velocity_ned, limits: dict | None = None, rally=None,
             seconds: float = 12.0):
    """Take off (2 m), then fly an offboard velocity stream out of the fence with GF_ACTION = action."""
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    if fence:
        assert upload(api, _fence_items(fence), FENCE, wall=f.wall)[-1].type == R.MAV_MISSION_ACCEPTED
    if rally:
        assert upload(api, _rally_items(rally), RALLY, wall=f.wall)[-1].type == R.MAV_MISSION_ACCEPTED
    _set(api, "GF_ACTION", action, f.wall, integer=True)
    for name, value in (limits or {}).items():
        _set(api, name, value, f.wall)
    assert _ack(api.command(400, 1, wall=f.wall), 400) == 0
    assert _ack(api.command(22, wall=f.wall), 22) == 0
    f.run(5.0)
    vel = R.MAVLink_set_position_target_local_ned_message(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0,
                                                          *velocity_ned, 0, 0, 0, 0, 0)
    watch = Watch(v, outside)

    def stream(fl):
        watch(fl)
        if round(fl.t * 100) % 5 == 0:
            api.send(vel, fl.wall)

    f.run(0.1, stream)
    assert _ack(api.command(176, 129, 6, 0, wall=f.wall), 176) == 0
    f.run(seconds, stream)
    return v, f, watch


def _latency(watch: Watch) -> float:
    assert watch.t_cross is not None, "the truth never left the fence"
    return watch.first("Geofence breached") - watch.t_cross


def test_polygon_breach_holds_within_half_a_second_of_the_truth_crossing() -> None:
    v, f, w = _fly_out(2, _vertices(SQUARE), lambda p: abs(p[0]) > 6.0 or abs(p[1]) > 6.0, (2.0, 0.0, 0.0))
    assert 0.0 <= _latency(w) <= 0.5, w.texts
    assert v.mode == (4, 3) and v.stats["geofence_breach"] == 1  # AUTO.LOITER (Hold)
    assert np.linalg.norm(f.body.state().velocity_ned_mps) < 0.1  # stopped, the stream notwithstanding
    assert 6.0 < f.pos[0] < 8.0  # just past the fence, not carried on at 2 m/s
    assert v.geofence_service.breaches[0]["action"] == "hold"


def test_warn_only_keeps_flying_and_land_lands_outside_and_disarms() -> None:
    v, f, w = _fly_out(1, _vertices(SQUARE), lambda p: abs(p[0]) > 6.0, (2.0, 0.0, 0.0), seconds=6.0)
    assert 0.0 <= _latency(w) <= 0.5
    assert v.mode == (6, 0) and f.pos[0] > 10.0  # warned, still in offboard
    v, f, w = _fly_out(5, _vertices(SQUARE), lambda p: abs(p[0]) > 6.0, (2.0, 0.0, 0.0), seconds=10.0)
    assert 0.0 <= _latency(w) <= 0.5
    f.run(3.0)
    assert v.landed and not v.armed and 6.0 < f.pos[0] < 9.0 and f.pos[2] > -0.1


def test_max_distance_breach_returns_to_the_nearest_rally_point() -> None:
    """GF_MAX_HOR_DIST 5 m, GF_ACTION return: RTL lands at the rally point nearest the vehicle, not home."""
    rally = [(4.0, -3.0), (-8.0, 8.0)]
    v, f, w = _fly_out(3, [], lambda p: math.hypot(p[0], p[1]) > 5.0, (1.5, 0.0, 0.0),
                       limits={"GF_MAX_HOR_DIST": 5.0}, rally=rally, seconds=30.0)
    assert 0.0 <= _latency(w) <= 0.5
    assert v.landed and np.linalg.norm(f.pos[:2] - np.array([4.0, -3.0])) < 0.2, f.pos


def test_height_limit_and_exclusion_circle_land() -> None:
    v, f, w = _fly_out(5, [], lambda p: -p[2] - 0.05 > 4.0, (0.0, 0.0, -1.0), limits={"GF_MAX_VER_DIST": 4.0},
                       seconds=10.0)
    assert 0.0 <= _latency(w) <= 0.5 and v.landed
    circle = [(R.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION, 2.0, (5.0, 0.0))]  # a 2 m disc 5 m north
    v, f, w = _fly_out(2, circle, lambda p: math.hypot(p[0] - 5.0, p[1]) < 2.0, (1.5, 0.0, 0.0), seconds=6.0)
    assert 0.0 <= _latency(w) <= 0.5 and v.mode == (4, 3)
    assert math.hypot(f.pos[0] - 5.0, f.pos[1]) > 1.0  # held at the disc's edge


def test_waypoints_goto_takeoff_and_setpoints_outside_the_fence_are_refused() -> None:
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    rel = R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT

    def wp(seq, n, e):
        lat, lon = _deg(n, e)
        return R.MAVLink_mission_item_int_message(1, 1, seq, rel, R.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0.5, 0, NAN,
                                                  lat, lon, 2.0, 0)

    inside = [wp(0, 2.0, 0.0), wp(1, 4.0, 4.0)]
    assert upload(api, inside, wall=f.wall)[-1].type == R.MAV_MISSION_ACCEPTED  # no fence yet
    # a broken polygon (4 vertices announced, 3 sent) is refused whole
    broken = _fence_items(_vertices(SQUARE)[:3] + [(R.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, 3.0, (0.0, 0.0))])
    ack = upload(api, broken, FENCE, wall=f.wall)[-1]
    assert ack.get_type() == "MISSION_ACK" and ack.type == R.MAV_MISSION_INVALID_PARAM1
    assert v.mission.plans[FENCE] == ()
    small = _vertices([(-3.0, -3.0), (-3.0, 3.0), (3.0, 3.0), (3.0, -3.0)])
    assert upload(api, _fence_items(small), FENCE, wall=f.wall)[-1].type == R.MAV_MISSION_ACCEPTED
    _set(api, "GF_MAX_VER_DIST", 2.5, f.wall)  # (a fail-safe parameter: set before arming)
    # the stored mission's item 1 is now outside: the mission does not start
    assert _ack(api.command(400, 1, wall=f.wall), 400) == 0
    assert _ack(api.command(R.MAV_CMD_MISSION_START, 0, 0, wall=f.wall), R.MAV_CMD_MISSION_START) == R.MAV_RESULT_DENIED
    # an upload with a waypoint outside: MAV_MISSION_ERROR, the stored plan unchanged, the reason counted
    before = v.mission.plans[0]
    ack = upload(api, [wp(0, 1.0, 1.0), wp(1, 2.0, 2.0), wp(2, 9.0, 0.0)], wall=f.wall)[-1]
    assert ack.get_type() == "MISSION_ACK" and ack.type == R.MAV_MISSION_ERROR
    assert v.mission.plans[0] == before and v.drop_counts()["mission.refused.outside_fence"] == 1
    texts = [m.text for m in api.decode(v.tick(f.wall, f.t)) if m.get_type() == "STATUSTEXT"]
    assert any("item 2" in t and "fence" in t for t in texts), texts
    # takeoff above GF_MAX_VER_DIST is refused; within it, flown
    assert _ack(api.command(22, NAN, NAN, NAN, NAN, NAN, NAN, 488.0 + 3.0, wall=f.wall), 22) == R.MAV_RESULT_DENIED
    assert _ack(api.command(22, wall=f.wall), 22) == 0
    f.run(5.0)
    # goto outside: DENIED and not flown; inside: flown
    lat, lon = _deg(5.0, 0.0)
    goto = R.MAVLink_command_int_message(1, 1, GLOBAL, 192, 0, 0, -1, 0, 0, NAN, lat, lon, 490.0)
    assert _ack(api.send(goto, f.wall), 192) == R.MAV_RESULT_DENIED
    f.run(1.0)
    assert abs(f.pos[0]) < 0.1
    # offboard position setpoints outside: dropped and counted, the vehicle stays inside
    out_sp = R.MAVLink_set_position_target_local_ned_message(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0x09F8, 8.0, 0, -2.0,
                                                             0, 0, 0, 0, 0, 0, 0, 0)
    for k in range(10):
        api.send(out_sp, f.wall + 0.05 * k)
    assert v.drop_counts()["setpoint_outside_fence"] == 10
    assert _ack(api.command(176, 129, 6, 0, wall=f.wall + 0.5), 176) == R.MAV_RESULT_DENIED  # no live setpoint
    f.run(1.0)
    assert abs(f.pos[0]) < 0.1 and v.stats.get("geofence_breach", 0) == 0
