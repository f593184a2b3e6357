"""The mission microservice on the sans-IO unit vehicle, with real MAVLink bytes (pymavlink encoders):
QGroundControl's upload and download exchange replayed, MAVProxy's legacy float items, fence and rally
lists, retries, and hostile input (each refused with the right MISSION_ACK, the stored plan intact,
every reason counted)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.geo import GeoOrigin, origin_from_env
from firmware_models.mission_protocol import MissionLimits
from firmware_models.vehicle import LINK_API, LINK_GCS, Vehicle, VehicleConfig
from mars_link.core.errors import UserInputError
from mars_link.core.state import RigidBodyState

R = mavlink
NAN = math.nan
T0 = 1.7e9
HOME_LAT, HOME_LON = 47.397742, 8.545594
QGC = (255, 190)  # QGroundControl's ids


class Client:
    def __init__(self, v: Vehicle, link: str = LINK_GCS, ids: tuple[int, int] = QGC) -> None:
        self.v, self.link = v, link
        self.mav = R.MAVLink(None, srcSystem=ids[0], srcComponent=ids[1])
        self.dec = R.MAVLink(None, 1, 1)

    def decode(self, out) -> list:
        msgs = []
        for o in out:
            if o.link == self.link:
                msgs += self.dec.parse_buffer(o.data) or []
        return msgs

    def send(self, msg, wall: float = T0) -> list:
        return [m for m in self.decode(self.v.handle(msg.pack(self.mav), wall, self.link))
                if m.get_type() != "STATUSTEXT"]

    def tick(self, wall: float) -> list:
        return self.decode(self.v.tick(wall, 0.0))


def _vehicle() -> Vehicle:
    v = Vehicle(VehicleConfig(unit_id=1), T0)
    v.set_state(RigidBodyState(0.0, np.array([0.0, 0.0, -0.05]), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3),
                               on_ground=True))
    v.tick(T0, 0.0)
    return v


def _deg(north_m: float, east_m: float) -> tuple[int, int]:
    """degE7 of a point north/east of PX4 SITL's home (computed here, not with mars_link.core.geo)."""
    lat = HOME_LAT + math.degrees(north_m / 6371000.0)
    lon = HOME_LON + math.degrees(east_m / (6371000.0 * math.cos(math.radians(HOME_LAT))))
    return int(round(lat * 1e7)), int(round(lon * 1e7))


def qgc_plan() -> list:
    """What QGC sends PX4 for a takeoff, three waypoints, a speed change and RTL (frame 3 in
    MISSION_ITEM_INT, RTL in the MISSION frame, first item current)."""
    rel = R.MAV_FRAME_GLOBAL_RELATIVE_ALT
    wps = [(0.0, 0.0, 3.0), (5.0, 0.0, 3.0), (5.0, 5.0, 4.0), (0.0, 5.0, 4.0)]
    items = [(rel, R.MAV_CMD_NAV_TAKEOFF, [0, 0, 0, NAN], wps[0])]
    items += [(rel, R.MAV_CMD_NAV_WAYPOINT, [0, 0.5, 0, NAN], wp) for wp in wps[1:3]]
    items += [(R.MAV_FRAME_MISSION, R.MAV_CMD_DO_CHANGE_SPEED, [1, 1.5, -1, 0], (0, 0, 0))]
    items += [(rel, R.MAV_CMD_NAV_WAYPOINT, [1.0, 0.5, 0, NAN], wps[3])]
    items += [(R.MAV_FRAME_MISSION, R.MAV_CMD_NAV_RETURN_TO_LAUNCH, [0, 0, 0, 0], (0, 0, 0))]
    out = []
    for seq, (frame, cmd, p, (n, e, alt)) in enumerate(items):
        lat, lon = _deg(n, e) if frame == rel else (0, 0)
        out.append(R.MAVLink_mission_item_int_message(1, 1, seq, frame, cmd, int(seq == 0), 1, *p, lat, lon, alt, 0))
    return out


def upload(c: Client, items: list, kind: int = 0, wall: float = T0) -> list:
    """The client's side of an upload, answering exactly what the vehicle requests; all replies."""
    replies = c.send(R.MAVLink_mission_count_message(1, 1, len(items), kind), wall)
    log = list(replies)
    for k in range(len(items) + 2):
        req = [m for m in replies if m.get_type() in ("MISSION_REQUEST_INT", "MISSION_REQUEST")]
        if not req:
            break
        replies = c.send(items[req[0].seq], wall + 0.004 * k)  # (replies are rate-limited per link)
        log += replies
    return log


def download(c: Client, kind: int = 0, legacy: bool = False) -> list:
    (count,) = c.send(R.MAVLink_mission_request_list_message(1, 1, kind))
    assert count.get_type() == "MISSION_COUNT" and count.mission_type == kind
    got = []
    for seq in range(count.count):
        req = (R.MAVLink_mission_request_message if legacy else R.MAVLink_mission_request_int_message)(1, 1, seq, kind)
        (item,) = c.send(req)
        assert item.seq == seq and item.target_system == QGC[0]
        got.append(item)
    assert c.send(R.MAVLink_mission_ack_message(1, 1, R.MAV_MISSION_ACCEPTED, kind)) == []
    return got


def _fields(m) -> tuple:
    return (m.seq, m.frame, m.command, m.autocontinue, m.param1, m.param2, m.param3, m.param4, m.x, m.y, m.z,
            m.mission_type)


def _same(a, b) -> bool:
    return all(x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y)) for x, y in zip(_fields(a), _fields(b)))


# ----------------------------------------------------------------------------- QGC replay
def test_qgc_upload_and_download_exchange_replayed() -> None:
    v = _vehicle()
    qgc = Client(v)
    plan = qgc_plan()
    log = upload(qgc, plan)
    kinds = [m.get_type() for m in log]
    assert kinds == ["MISSION_REQUEST_INT"] * len(plan) + ["MISSION_ACK"]
    assert [m.seq for m in log[:-1]] == list(range(len(plan)))
    assert all((m.target_system, m.target_component) == QGC for m in log)
    assert (log[-1].type, log[-1].mission_type) == (R.MAV_MISSION_ACCEPTED, 0)
    got = download(qgc)
    assert len(got) == len(plan) and all(_same(a, b) for a, b in zip(got, plan))
    assert [m.current for m in got] == [1] + [0] * (len(plan) - 1)
    # MISSION_CURRENT now reports the plan (QGC shows it)
    cur = [m for m in qgc.tick(T0 + 1.1) if m.get_type() == "MISSION_CURRENT"]
    assert cur and (cur[-1].seq, cur[-1].total, cur[-1].mission_state) == (0, len(plan), R.MISSION_STATE_NOT_STARTED)
    assert v.mission.counts["uploaded.mission"] == 1
    assert not [k for k in v.drop_counts() if k.startswith("mission.")]


def test_legacy_float_items_and_fence_and_rally_lists() -> None:
    v = _vehicle()
    mp = Client(v, LINK_API, ids=(255, 230))  # MAVProxy's ids
    lat, lon = _deg(3.0, 4.0)
    legacy = [R.MAVLink_mission_item_message(1, 1, 0, R.MAV_FRAME_GLOBAL_RELATIVE_ALT, R.MAV_CMD_NAV_TAKEOFF, 0, 1,
                                             0, 0, 0, 0, 0, 0, 2.5, 0),
              R.MAVLink_mission_item_message(1, 1, 1, R.MAV_FRAME_GLOBAL_RELATIVE_ALT, R.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                             0, 0, 0, 0, lat * 1e-7, lon * 1e-7, 2.5, 0)]
    log = upload(mp, legacy)
    # the first request is MISSION_REQUEST_INT; once a float MISSION_ITEM came, the vehicle asks in kind
    assert [m.get_type() for m in log] == ["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"]
    assert log[-1].type == R.MAV_MISSION_ACCEPTED
    got = download(mp, legacy=True)
    assert [m.get_type() for m in got] == ["MISSION_ITEM"] * 2
    assert abs(got[1].x - lat * 1e-7) < 1e-6 and abs(got[1].y - lon * 1e-7) < 1e-6
    # geofence: a 4-vertex inclusion polygon and an exclusion circle; rally: two points
    poly = [_deg(n, e) for n, e in ((-20, -20), (-20, 20), (20, 20), (20, -20))]
    fence = [R.MAVLink_mission_item_int_message(1, 1, i, R.MAV_FRAME_GLOBAL, R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                                                0, 1, 4, 0, 0, 0, la, lo, 0, 1) for i, (la, lo) in enumerate(poly)]
    fence.append(R.MAVLink_mission_item_int_message(1, 1, 4, R.MAV_FRAME_GLOBAL, R.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
                                                    0, 1, 3.0, 0, 0, 0, *_deg(5, 5), 0, 1))
    rally = [R.MAVLink_mission_item_int_message(1, 1, i, R.MAV_FRAME_GLOBAL_RELATIVE_ALT, R.MAV_CMD_NAV_RALLY_POINT,
                                                0, 1, 0, 0, 0, 0, *_deg(n, 0), 5.0, 2) for i, n in enumerate((10, -10))]
    assert upload(mp, fence, 1)[-1].type == R.MAV_MISSION_ACCEPTED
    assert upload(mp, rally, 2)[-1].type == R.MAV_MISSION_ACCEPTED
    assert [len(download(mp, k)) for k in (0, 1, 2)] == [2, 5, 2]
    # a waypoint in a fence list, a fence vertex in a mission: unsupported there
    wrong = [R.MAVLink_mission_item_int_message(1, 1, 0, R.MAV_FRAME_GLOBAL, R.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
                                                *_deg(1, 1), 3.0, 1)]
    assert upload(mp, wrong, 1)[-1].type == R.MAV_MISSION_UNSUPPORTED
    # clear one list, then all
    assert mp.send(R.MAVLink_mission_clear_all_message(1, 1, 2))[0].type == R.MAV_MISSION_ACCEPTED
    assert [len(v.mission.plans[k]) for k in (0, 1, 2)] == [2, 5, 0]
    assert mp.send(R.MAVLink_mission_clear_all_message(1, 1, 255))[0].type == R.MAV_MISSION_ACCEPTED
    assert [len(v.mission.plans[k]) for k in (0, 1, 2)] == [0, 0, 0]


def test_missing_item_is_re_requested_then_the_upload_is_cancelled() -> None:
    v = _vehicle()
    qgc = Client(v)
    plan = qgc_plan()
    assert upload(qgc, plan)[-1].type == R.MAV_MISSION_ACCEPTED
    stored = v.mission.plans[0]
    first = qgc.send(R.MAVLink_mission_count_message(1, 1, 3, 0))
    assert first[0].get_type() == "MISSION_REQUEST_INT" and first[0].seq == 0
    assert qgc.send(plan[0])[0].seq == 1
    # the client goes quiet: item 1 is asked for again every 0.5 s, five times, then cancelled
    requests, acks = [], []
    for k in range(1, 500):
        for m in qgc.tick(T0 + k * 0.01):
            if m.get_type() == "MISSION_REQUEST_INT":
                requests.append((round(k * 0.01, 2), m.seq))
            elif m.get_type() == "MISSION_ACK":
                acks.append((round(k * 0.01, 2), m.type))
    assert [s for _, s in requests] == [1] * 5
    assert all(0.45 <= b - a <= 0.55 for (a, _), (b, _) in zip([(0.0, 0)] + requests, requests))
    assert len(acks) == 1 and acks[0][1] == R.MAV_MISSION_OPERATION_CANCELLED and 2.9 <= acks[0][0] <= 3.1
    assert v.mission.plans[0] == stored  # abandoned halfway: the stored plan is intact
    assert v.drop_counts()["mission.cancelled_timeout"] == 1
    # a re-requested item that does arrive continues the upload
    qgc.send(R.MAVLink_mission_count_message(1, 1, 2, 0), T0 + 10)
    qgc.send(plan[0], T0 + 10)
    again = [m for m in qgc.tick(T0 + 10.6) if m.get_type() == "MISSION_REQUEST_INT"]
    assert [m.seq for m in again] == [1]
    assert qgc.send(plan[1], T0 + 10.7)[0].type == R.MAV_MISSION_ACCEPTED
    assert len(v.mission.plans[0]) == 2


def test_bad_uploads_refused_with_the_right_ack_plan_intact_and_counted() -> None:
    v = _vehicle()
    qgc = Client(v)
    plan = qgc_plan()
    assert upload(qgc, plan)[-1].type == R.MAV_MISSION_ACCEPTED
    stored = v.mission.plans[0]

    def item(seq, cmd=R.MAV_CMD_NAV_WAYPOINT, frame=R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, p=(0, 0, 0, NAN),
             xy=None, z=3.0, kind=0):
        x, y = _deg(1.0, 1.0) if xy is None else xy
        return R.MAVLink_mission_item_int_message(1, 1, seq, frame, cmd, 0, 1, *p, x, y, z, kind)

    def refused(items: list, count: int | None = None, kind: int = 0) -> int:
        replies = qgc.send(R.MAVLink_mission_count_message(1, 1, len(items) if count is None else count, kind))
        for it in items:
            if replies and replies[-1].get_type() == "MISSION_ACK":
                break
            replies = qgc.send(it)
        acks = [m for m in replies if m.get_type() == "MISSION_ACK"]
        assert len(acks) == 1, replies
        return acks[0].type

    cases = {
        "oversized": (refused([], count=1001), R.MAV_MISSION_NO_SPACE),
        "oversized_rally": (refused([], count=33, kind=2), R.MAV_MISSION_NO_SPACE),
        "wrong_mission_type": (refused([item(0)], kind=7), R.MAV_MISSION_UNSUPPORTED),
        "item_of_other_type": (refused([item(0, kind=1)]), R.MAV_MISSION_ERROR),
        "out_of_order": (refused([item(0), item(2)], count=3), R.MAV_MISSION_INVALID_SEQUENCE),
        "nan_altitude": (refused([item(0, z=NAN)]), R.MAV_MISSION_INVALID_PARAM7),
        "latitude_out_of_range": (refused([item(0, xy=(95 * 10**7, 0))]), R.MAV_MISSION_INVALID_PARAM5_X),
        "longitude_out_of_range": (refused([item(0, xy=(int(HOME_LAT * 1e7), -2_000_000_000))]),
                                   R.MAV_MISSION_INVALID_PARAM6_Y),
        "far_away": (refused([item(0, xy=(0, 0))]), R.MAV_MISSION_INVALID_PARAM5_X),  # 0 N 0 E: 5000 km off
        "wrong_frame": (refused([item(0, frame=R.MAV_FRAME_BODY_FRD)]), R.MAV_MISSION_UNSUPPORTED_FRAME),
        "terrain_frame": (refused([item(0, frame=R.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)]), R.MAV_MISSION_UNSUPPORTED_FRAME),
        "unsupported_command": (refused([item(0, cmd=R.MAV_CMD_DO_SET_SERVO, frame=R.MAV_FRAME_MISSION)]),
                                R.MAV_MISSION_UNSUPPORTED),
        "negative_hold": (refused([item(0, p=(-1, 0, 0, NAN))]), R.MAV_MISSION_INVALID_PARAM1),
        "bad_jump": (refused([item(0), item(1, cmd=R.MAV_CMD_DO_JUMP, frame=R.MAV_FRAME_MISSION, p=(5, 1, 0, 0))]),
                     R.MAV_MISSION_INVALID_PARAM1),
        "bad_speed": (refused([item(0, cmd=R.MAV_CMD_DO_CHANGE_SPEED, frame=R.MAV_FRAME_MISSION, p=(1, 500, -1, 0))]),
                      R.MAV_MISSION_INVALID_PARAM2),
    }
    for name, (got, want) in cases.items():
        assert got == want, (name, got, want)
    # NaN coordinates in legacy float items (MAVProxy's MISSION_ITEM)
    qgc.send(R.MAVLink_mission_count_message(1, 1, 1, 0))
    nan_x = qgc.send(R.MAVLink_mission_item_message(1, 1, 0, R.MAV_FRAME_GLOBAL_RELATIVE_ALT, R.MAV_CMD_NAV_WAYPOINT,
                                                    0, 1, 0, 0, 0, NAN, NAN, HOME_LON, 3.0, 0))
    assert nan_x[0].type == R.MAV_MISSION_INVALID_PARAM5_X
    qgc.send(R.MAVLink_mission_count_message(1, 1, 1, 0))
    nan_y = qgc.send(R.MAVLink_mission_item_message(1, 1, 0, R.MAV_FRAME_GLOBAL_RELATIVE_ALT, R.MAV_CMD_NAV_WAYPOINT,
                                                    0, 1, 0, 0, 0, NAN, HOME_LAT, math.inf, 3.0, 0))
    assert nan_y[0].type == R.MAV_MISSION_INVALID_PARAM6_Y
    # an item nobody asked for, and an upload from a second client while one is in progress
    assert qgc.send(item(0))[0].type == R.MAV_MISSION_ERROR
    other = Client(v, LINK_API, ids=(245, 190))
    assert qgc.send(R.MAVLink_mission_count_message(1, 1, 2, 0))[0].get_type() == "MISSION_REQUEST_INT"
    assert other.send(R.MAVLink_mission_count_message(1, 1, 2, 0))[0].type == R.MAV_MISSION_DENIED
    # a duplicate of the item just received is ignored and the next one asked for again
    assert qgc.send(item(0))[0].seq == 1
    assert qgc.send(item(0))[0].seq == 1
    # the client cancels: nothing stored
    assert qgc.send(R.MAVLink_mission_ack_message(1, 1, R.MAV_MISSION_OPERATION_CANCELLED, 0)) == []
    assert v.mission.plans[0] == stored and v.runner.items == stored
    drops = v.drop_counts()
    expected = {"no_space": 2, "unsupported_mission_type": 1, "item_wrong_mission_type": 1, "out_of_order": 1,
                "invalid_z": 1, "invalid_latitude": 1, "invalid_longitude": 1, "too_far": 1, "unsupported_frame": 2,
                "unsupported_command": 1, "invalid_hold_time": 1, "invalid_jump_target": 1, "invalid_speed": 1,
                "invalid_x": 1, "invalid_y": 1, "item_without_upload": 1, "busy": 1}
    for reason, n in expected.items():
        assert drops.get(f"mission.refused.{reason}") == n, (reason, drops)
    assert drops["mission.duplicate_item"] == 1 and drops["mission.cancelled_by_client"] == 1
    # a named refusal for the item we cannot fly
    texts = [t for _, t in v.events]
    assert "mission item 0 DO_SET_SERVO: unsupported" in texts
    # a long command name still fits one STATUSTEXT with the verdict
    qgc.send(R.MAVLink_mission_count_message(1, 1, 20, 0))
    for seq in range(12):
        qgc.send(item(seq))
    qgc.send(item(12, cmd=R.MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, frame=R.MAV_FRAME_MISSION))
    text = v.events[-1][1]
    assert text.startswith("mission item 12 DO_GIMBAL_MANAGER") and text.endswith(": unsupported") and len(text) <= 50


def test_partial_write_replaces_a_range_and_a_lost_ack_is_sent_again() -> None:
    v = _vehicle()
    qgc = Client(v)
    plan = qgc_plan()
    assert upload(qgc, plan)[-1].type == R.MAV_MISSION_ACCEPTED
    # the client missed our ACK and repeats its last item: the ACK again, nothing changes
    again = qgc.send(plan[-1], T0 + 1)
    assert [(m.get_type(), m.type) for m in again] == [("MISSION_ACK", R.MAV_MISSION_ACCEPTED)]
    before = v.mission.plans[0]
    new = [R.MAVLink_mission_item_int_message(1, 1, seq, R.MAV_FRAME_GLOBAL_RELATIVE_ALT, R.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                              2.0, 0.4, 0, NAN, *_deg(9.0, seq), 6.0, 0) for seq in (2, 3)]
    first = qgc.send(R.MAVLink_mission_write_partial_list_message(1, 1, 2, 3, 0), T0 + 10)
    assert [(m.get_type(), m.seq) for m in first] == [("MISSION_REQUEST_INT", 2)]
    assert qgc.send(new[0], T0 + 10)[0].seq == 3
    assert qgc.send(new[1], T0 + 10)[0].type == R.MAV_MISSION_ACCEPTED
    after = v.mission.plans[0]
    assert len(after) == len(before) and after[:2] == before[:2] and after[4:] == before[4:]
    assert [(i.seq, i.param1, i.z) for i in after[2:4]] == [(2, 2.0, 6.0), (3, 2.0, 6.0)]
    assert [m.seq for m in download(qgc)] == list(range(len(plan)))
    bad = qgc.send(R.MAVLink_mission_write_partial_list_message(1, 1, 4, 9, 0), T0 + 11)
    assert bad[0].type == R.MAV_MISSION_INVALID_SEQUENCE and v.mission.plans[0] == after


def test_malformed_frames_are_dropped_and_the_vehicle_keeps_answering() -> None:
    v = _vehicle()
    qgc = Client(v)
    assert upload(qgc, qgc_plan())[-1].type == R.MAV_MISSION_ACCEPTED
    good = qgc_plan()[1].pack(qgc.mav)
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    truncated = good[: len(good) // 2]
    for junk in (bytes(bad_crc), truncated, b"\xfd\x05garbage", bytes(300)):
        assert qgc.decode(v.handle(junk, T0, LINK_GCS)) == []
    drops = v.drop_counts()
    assert drops.get("parse.bad_crc", 0) + drops.get("parse.truncated", 0) + drops.get("parse.junk", 0) >= 3
    assert len(download(qgc)) == 6


def test_storage_bounds_hold_1000_items() -> None:
    v = _vehicle()
    qgc = Client(v)
    items = [R.MAVLink_mission_item_int_message(1, 1, i, R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, R.MAV_CMD_NAV_WAYPOINT,
                                                0, 1, 0, 0, 0, NAN, *_deg(i * 0.1, 0), 3.0, 0) for i in range(1000)]
    log = upload(qgc, items)
    assert log[-1].type == R.MAV_MISSION_ACCEPTED and len(v.mission.plans[0]) == 1000
    assert MissionLimits().capacity(1) == 256 and MissionLimits().capacity(2) == 32


def test_home_origin_default_and_env(monkeypatch) -> None:
    o = origin_from_env({})
    assert (o.lat_deg, o.lon_deg, o.amsl_m) == (HOME_LAT, HOME_LON, 488.0)
    o = origin_from_env({"PX4_HOME_LAT": "-35.363261", "PX4_HOME_LON": "149.165230", "PX4_HOME_ALT": "584"})
    assert (o.lat_deg, o.lon_deg, o.amsl_m) == (-35.363261, 149.165230, 584.0)
    with pytest.raises(UserInputError, match="PX4_HOME_LAT"):
        origin_from_env({"PX4_HOME_LAT": "north"})
    with pytest.raises(UserInputError, match="latitude"):
        origin_from_env({"PX4_HOME_LAT": "91"})
    o = GeoOrigin()
    p = o.to_ned(*o.to_global([12.5, -7.25, -3.0]))
    np.testing.assert_allclose(p, [12.5, -7.25, -3.0], atol=1e-6)
    monkeypatch.setenv("PX4_HOME_ALT", "600")
    v = _vehicle()
    gpi = [m for m in Client(v).tick(T0 + 2.0) if m.get_type() == "GLOBAL_POSITION_INT"][0]
    assert gpi.alt == pytest.approx(600_050, abs=2) and gpi.lat == int(round(HOME_LAT * 1e7))
