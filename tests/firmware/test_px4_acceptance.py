"""What PX4 accepts, the unit firmware accepts with PX4's meaning, and what it refuses it says why.

Fence circles as PX4 stores and checks them (a radius-0 circle at 0 N 0 E beside a polygon, as
MAVSDK's geofence example sends, changes nothing; an inclusion circle of radius 0 alone allows
nowhere); a takeoff altitude (AMSL) below home + MIS_TAKEOFF_ALT is raised to it, as PX4 does; every
refused COMMAND_LONG is followed by one STATUSTEXT naming the command and the reason. Real MAVLink
bytes into a unit vehicle flying a JSBSim body."""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as mavlink
from test_geofence import SQUARE, _fence_items, _vertices
from test_mission_protocol import upload
from test_vehicle_protocol import KEY, LINK_API, Client, Flight, _ack, _vehicle

R = mavlink
FENCE = R.MAV_MISSION_TYPE_FENCE
CIRCLE_IN = R.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION


def _null_island_circle(seq: int, radius_m: float) -> mavlink.MAVLink_mission_item_int_message:
    """An inclusion circle at 0 N 0 E (x = y = 0 degE7), altitude 0, as MAVSDK sends a default circle."""
    return R.MAVLink_mission_item_int_message(1, 1, seq, R.MAV_FRAME_GLOBAL, CIRCLE_IN, 0, 1, radius_m, 0, 0, 0,
                                              0, 0, 0.0, FENCE)


def _texts(v, f: Flight, client: Client) -> list[str]:
    """The STATUSTEXTs of the vehicle's next tick (where queued texts go out)."""
    return [m.text for m in client.decode(v.tick(f.wall, f.t)) if m.get_type() == "STATUSTEXT"]


def test_a_radius_0_circle_beside_a_polygon_is_stored_and_changes_nothing() -> None:
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    polygon = _fence_items(_vertices(SQUARE))
    items = polygon + [_null_island_circle(len(polygon), 0.0)]
    assert upload(api, items, FENCE, wall=f.wall)[-1].type == R.MAV_MISSION_ACCEPTED
    stored = v.mission.plans[FENCE]
    assert len(stored) == 5 and stored[-1].command == CIRCLE_IN and stored[-1].param1 == 0.0
    assert (stored[-1].x, stored[-1].y) == (0, 0)
    fence = v.geofence()
    assert fence.zone_violation(0.0, 0.0) is None and fence.zone_violation(5.0, -5.0) is None
    assert fence.zone_violation(8.0, 0.0) == "outside the inclusion fence"  # the polygon still holds
    assert fence.distance_inside_m(0.0, 0.0 + 1.0) > 4.9
    # NaN (MAVSDK's default radius) and a negative radius are stored too, as PX4 stores them
    for radius in (math.nan, -3.0):
        assert upload(api, polygon + [_null_island_circle(4, radius)], FENCE, wall=f.wall)[-1].type == 0


def test_an_inclusion_circle_of_radius_0_alone_allows_nowhere() -> None:
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    assert upload(api, [_null_island_circle(0, 0.0)], FENCE, wall=f.wall)[-1].type == R.MAV_MISSION_ACCEPTED
    assert v.geofence().zone_violation(0.0, 0.0) == "outside the inclusion fence"
    assert v.geofence().distance_inside_m(0.0, 0.0) == -math.inf
    assert _ack(api.command(400, 1, wall=f.wall), 400) == 0
    assert _ack(api.command(22, wall=f.wall), 22) == R.MAV_RESULT_DENIED
    assert "Takeoff refused: outside the inclusion fence" in _texts(v, f, api)
    f.run(1.0)
    assert f.pos[2] > -0.2  # it did not leave the ground


def test_takeoff_below_home_climbs_to_the_minimum_as_px4_does() -> None:
    """MAVProxy's `takeoff 10` is 10 m AMSL to PX4, far below home (488 m): accepted, MIS_TAKEOFF_ALT flown."""
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    assert _ack(api.command(400, 1, wall=f.wall), 400) == 0
    assert _ack(api.command(22, 0, 0, 0, math.nan, math.nan, math.nan, 10.0, wall=f.wall), 22) == 0
    texts = _texts(v, f, api)
    minimum_m = v.params["MIS_TAKEOFF_ALT"]
    assert f"Using minimum takeoff altitude: {minimum_m:.2f} m" in texts, texts
    f.run(6.0)
    assert abs(-f.pos[2] - minimum_m) < 0.2  # the body's truth


def test_every_refused_command_is_followed_by_one_statustext_saying_why() -> None:
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    cases = [  # (command, params, result, the STATUSTEXT)
        ((22,), R.MAV_RESULT_TEMPORARILY_REJECTED, "Takeoff refused: not armed"),
        ((400, 7), R.MAV_RESULT_DENIED, "Arming refused: param1 must be 0 or 1"),
        ((300,), R.MAV_RESULT_DENIED, "Mission start refused: no mission stored"),
        ((176, 1, 2, 0), R.MAV_RESULT_UNSUPPORTED, "Mode change refused: mode needs RC sticks"),
        ((34,), R.MAV_RESULT_TEMPORARILY_REJECTED, "Orbit refused: not flying (take off first)"),
        ((420, 101, 1, 9), R.MAV_RESULT_DENIED, "Failure injection refused: no motor 9 (1..4, 0 all)"),
        ((31000,), R.MAV_RESULT_UNSUPPORTED, "WAYPOINT_USER_1 refused: not supported"),
        ((55555,), R.MAV_RESULT_UNSUPPORTED, "Command 55555 refused: not supported"),
        ((512, 300), R.MAV_RESULT_UNSUPPORTED, "Message request refused: message 300 not sent"),
    ]
    for k, (params, result, text) in enumerate(cases):
        wall = f.wall + 2.0 * k
        assert _ack(api.command(*params, wall=wall), params[0]) == result, text
        said = [m.text for m in api.decode(v.tick(wall, f.t)) if m.get_type() == "STATUSTEXT"]
        assert len(said) == 1 and said[0].startswith(text[:50]), (text, said)
    # a client's identical retry within a second is acked again but not told twice
    assert _ack(api.command(22, wall=f.wall + 30.0), 22) == R.MAV_RESULT_TEMPORARILY_REJECTED
    assert _ack(api.command(22, wall=f.wall + 30.2), 22) == R.MAV_RESULT_TEMPORARILY_REJECTED
    said = [m.text for m in api.decode(v.tick(f.wall + 30.3, f.t)) if m.get_type() == "STATUSTEXT"]
    assert said == ["Takeoff refused: not armed"]
    # accepted commands say nothing of refusal
    assert _ack(api.command(400, 1, wall=f.wall + 40.0), 400) == 0
    assert not any("refused" in t for t in _texts(v, f, api))


def test_a_command_refused_for_want_of_signing_says_so() -> None:
    v = _vehicle(signing_key=KEY, sign_client_links=True)
    unsigned = Client(v, LINK_API)
    assert _ack(unsigned.command(22), 22) == R.MAV_RESULT_DENIED
    said = [m.text for m in unsigned.decode(v.tick(1.7e9 + 0.01, 0.01)) if m.get_type() == "STATUSTEXT"]
    assert said == ["Takeoff refused: needs a signed link"]
