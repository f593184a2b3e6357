"""AUTO.MISSION on the sans-IO unit vehicle flying a JSBSim body in lockstep (in process, faster than
real time): waypoints with hold time and acceptance radius checked against the body's truth, DO_*
items, a DO_JUMP loop, NAV_DELAY, LOITER_TIME, DO_SET_HOME moving the RTL landing spot, pause to HOLD
and resume, DO_SET_MISSION_CURRENT and MAV_CMD_MISSION_START."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink
from test_mission_protocol import _deg, upload
from test_vehicle_protocol import Client, Flight, _ack, _vehicle

R = mavlink
NAN = math.nan
REL = R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
pytestmark = pytest.mark.slow


def _item(seq, cmd, frame=REL, p=(0, 0, 0, NAN), ned=(0.0, 0.0, 0.0), kind=0):
    """ned: metres north/east of home and height above it (global frames) or local NED metres."""
    n, e, h = ned
    if frame in (R.MAV_FRAME_LOCAL_NED, R.MAV_FRAME_LOCAL_OFFSET_NED):
        x, y, z = int(round(n * 1e4)), int(round(e * 1e4)), -h
    elif frame == R.MAV_FRAME_MISSION:
        x, y, z = 0, 0, 0.0
    else:
        (x, y), z = _deg(n, e), h
    return R.MAVLink_mission_item_int_message(1, 1, seq, frame, cmd, 0, 1, *p, x, y, z, kind)


class Watch:
    """Everything the vehicle broadcast on the GCS link during a flight, and the truth at each step."""

    def __init__(self, f: Flight) -> None:
        self.gcs = Client(f.v, "gcs", 255, 190)
        self.reached: list[tuple[int, np.ndarray, float]] = []
        self.current: list[tuple[int, int]] = []
        self.speeds: list[tuple[int, float]] = []
        self.texts: list[str] = []

    def __call__(self, fl: Flight) -> None:
        for m in self.gcs.decode(fl.out):
            t = m.get_type()
            if t == "MISSION_ITEM_REACHED":
                self.reached.append((m.seq, fl.pos.copy(), fl.t))
            elif t == "MISSION_CURRENT" and (not self.current or self.current[-1] != (m.seq, m.mission_state)):
                self.current.append((m.seq, m.mission_state))
            elif t == "STATUSTEXT":
                self.texts.append(m.text)
        v = fl.body.state().velocity_ned_mps
        self.speeds.append((fl.v.runner.current, math.hypot(v[0], v[1])))


def _fly_until(f: Flight, watch: Watch, done, limit_s: float) -> None:
    t_end = f.t + limit_s
    while f.t < t_end and not done():
        f.run(0.5, watch)
    f.run(0.1, watch)  # what the last control step queued goes out with the next ticks


def test_mission_items_flown_against_the_truth() -> None:
    v = _vehicle()
    f = Flight(v)
    gcs = Client(v, "gcs", 255, 190)
    S, N = R.MAV_FRAME_MISSION, R.MAV_FRAME_LOCAL_OFFSET_NED
    plan = [
        _item(0, R.MAV_CMD_NAV_WAYPOINT, p=(1.0, 0.3, 0, NAN), ned=(4.0, 0.0, 3.0)),  # from the ground: climb first
        _item(1, R.MAV_CMD_DO_CHANGE_SPEED, S, p=(1, 1.0, -1, 0)),
        _item(2, R.MAV_CMD_NAV_WAYPOINT, p=(0.5, 0.3, 0, NAN), ned=(4.0, 4.0, 3.5)),
        _item(3, R.MAV_CMD_NAV_WAYPOINT, N, p=(0.0, 0.4, 0, NAN), ned=(1.0, 4.0, 3.0)),  # local, around home
        _item(4, R.MAV_CMD_DO_JUMP, S, p=(2, 1, 0, 0)),  # items 2-3 once more
        _item(5, R.MAV_CMD_NAV_DELAY, S, p=(1.0, -1, -1, -1)),
        _item(6, R.MAV_CMD_NAV_LOITER_TIME, p=(1.0, 0, 0, NAN), ned=(2.0, 2.0, 3.0)),
        _item(7, R.MAV_CMD_DO_SET_HOME, p=(0, 0, 0, NAN), ned=(2.0, 2.0, 0.0)),
        _item(8, R.MAV_CMD_NAV_RETURN_TO_LAUNCH, S),
    ]
    assert upload(gcs, plan, wall=f.wall)[-1].type == R.MAV_MISSION_ACCEPTED
    watch = Watch(f)
    assert _ack(gcs.command(400, 1, wall=f.wall), 400) == 0
    assert _ack(gcs.command(R.MAV_CMD_MISSION_START, 0, 0, wall=f.wall), R.MAV_CMD_MISSION_START) == 0
    assert v.mode == (4, 4)
    _fly_until(f, watch, lambda: v.runner.complete and v.landed, 90.0)
    seqs = [s for s, _, _ in watch.reached]
    assert seqs == [0, 1, 2, 3, 4, 2, 3, 4, 5, 6, 7, 8], seqs
    targets = {0: (4.0, 0.0, -3.0, 0.3), 2: (4.0, 4.0, -3.5, 0.3), 3: (1.0, 4.0, -3.0, 0.4), 6: (2.0, 2.0, -3.0, 0.5)}
    for seq, pos, _ in watch.reached:
        if seq in targets:
            *goal, radius = targets[seq]
            assert np.linalg.norm(pos - goal) <= radius, (seq, pos)
    # holds: 1 s at item 0, NAV_DELAY 1 s, LOITER_TIME 1 s
    times = {s: t for s, _, t in watch.reached}
    t0 = next(t for s, _, t in watch.reached if s == 0)
    t_after_0 = next(t for s, _, t in watch.reached if s == 1)
    assert t_after_0 - t0 >= 0.95
    assert times[6] - times[5] > 0.9 and times[7] - times[6] >= 0.95
    # DO_CHANGE_SPEED 1 m/s caps the reference on the legs after it (the first one flew at MPC_XY_CRUISE
    # 2 m/s); the truth overshoots a reference by up to ~0.3 m/s while the position loop catches up
    assert max(s for c, s in watch.speeds if c == 0) > 1.9
    assert max(s for c, s in watch.speeds if c in (2, 3)) < 1.4
    # RTL to the home DO_SET_HOME moved: landed there, disarmed, mission complete
    np.testing.assert_allclose(f.pos[:2], [2.0, 2.0], atol=0.2)
    assert f.pos[2] > -0.1
    f.run(3.0, watch)
    assert not v.armed
    assert watch.current[0][0] == 0 and (8, R.MISSION_STATE_COMPLETE) in watch.current


def test_pause_resume_set_current_and_mode_switch_start() -> None:
    v = _vehicle()
    f = Flight(v)
    gcs = Client(v, "gcs", 255, 190)
    plan = [_item(0, R.MAV_CMD_NAV_TAKEOFF, ned=(0.0, 0.0, 2.5)),
            _item(1, R.MAV_CMD_NAV_WAYPOINT, p=(0, 0.3, 0, NAN), ned=(8.0, 0.0, 2.5)),
            _item(2, R.MAV_CMD_NAV_WAYPOINT, p=(0, 0.3, 0, NAN), ned=(8.0, 8.0, 2.5)),
            _item(3, R.MAV_CMD_NAV_LAND, ned=(-2.0, 3.0, 0.0))]
    assert upload(gcs, plan, wall=f.wall)[-1].type == R.MAV_MISSION_ACCEPTED
    watch = Watch(f)
    # a mission with nothing stored is refused; the mode switch (MAVSDK's start_mission) starts it
    assert _ack(gcs.command(400, 1, wall=f.wall), 400) == 0
    assert _ack(gcs.command(176, 129, 4, 4, wall=f.wall), 176) == 0
    _fly_until(f, watch, lambda: v.runner.current == 1 and f.pos[0] > 3.0, 20.0)
    assert [s for s, _, _ in watch.reached] == [0]
    # pause: HOLD stops the vehicle mid-leg; it stays there
    assert _ack(gcs.command(176, 129, 4, 3, wall=f.wall), 176) == 0
    f.run(3.0, watch)
    held = f.pos.copy()
    f.run(2.0, watch)
    assert np.linalg.norm(f.pos - held) < 0.1 and held[0] < 7.0
    assert watch.current[-1] == (1, R.MISSION_STATE_PAUSED)
    # resume: the same item, from where it stopped
    assert _ack(gcs.command(176, 129, 4, 4, wall=f.wall), 176) == 0
    _fly_until(f, watch, lambda: len(watch.reached) >= 2, 15.0)
    assert [s for s, _, _ in watch.reached] == [0, 1]
    # skip item 2: DO_SET_MISSION_CURRENT 3 lands at item 3's spot
    assert _ack(gcs.command(R.MAV_CMD_DO_SET_MISSION_CURRENT, 3, wall=f.wall), R.MAV_CMD_DO_SET_MISSION_CURRENT) == 0
    assert _ack(gcs.command(R.MAV_CMD_DO_SET_MISSION_CURRENT, 9, wall=f.wall),
                R.MAV_CMD_DO_SET_MISSION_CURRENT) == R.MAV_RESULT_DENIED
    _fly_until(f, watch, lambda: v.runner.complete and v.landed, 40.0)
    assert [s for s, _, _ in watch.reached] == [0, 1, 3]
    np.testing.assert_allclose(f.pos[:2], [-2.0, 3.0], atol=0.3)
    # clearing the mission leaves AUTO.MISSION refused
    gcs.send(R.MAVLink_mission_clear_all_message(1, 1, 0), f.wall)
    f.run(3.0, watch)
    assert _ack(gcs.command(R.MAV_CMD_MISSION_START, 0, 0, wall=f.wall + 5), R.MAV_CMD_MISSION_START) == R.MAV_RESULT_DENIED


def test_the_3x2_assembly_vehicle_flies_a_mission_through_its_own_core() -> None:
    """`mars-link vehicle`'s sans-IO core (VehicleSim: JSBSim world, unit motor paths, EKF,
    coordinator): the same mission protocol and runner, the setpoints shaped for the coordinator."""
    from mars_link.vehicles.vehicle_sim import VehicleSim
    from mars_link.config.scenario import load_scenario

    sim = VehicleSim(load_scenario("hover_3x2"))
    gcs = R.MAVLink(None, 245, 190)
    dec = R.MAVLink(None, 0, 0)
    got: list = []

    def feed(out) -> None:
        for o in out:
            if o.link == "api":
                got.extend(dec.parse_buffer(o.data) or [])

    def send(msg) -> list:
        n = len(got)
        feed(sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api"))
        return got[n:]

    reached: list = []

    def run(seconds: float) -> None:
        for _ in range(int(round(seconds / sim.control_dt_s))):
            n = len(got)
            feed(sim.step(sim.t_s))
            reached.extend((m.seq, sim.truth().position_ned_m.copy()) for m in got[n:]
                           if m.get_type() == "MISSION_ITEM_REACHED")

    try:
        run(0.3)
        home = np.array(sim.vehicle.home_ned if sim.vehicle.home_ned is not None else sim.truth().position_ned_m)
        plan = [_item(0, R.MAV_CMD_NAV_TAKEOFF, ned=(0.0, 0.0, 2.0)),
                _item(1, R.MAV_CMD_NAV_WAYPOINT, p=(0.5, 0.3, 0, NAN), ned=(2.0, 0.0, 2.0)),
                _item(2, R.MAV_CMD_NAV_WAYPOINT, p=(0.5, 0.3, 0, NAN), ned=(2.0, 2.0, 2.0)),
                _item(3, R.MAV_CMD_NAV_LAND, ned=(0.0, 2.0, 0.0))]
        # home is where the vehicle stands: express the plan around it
        origin = sim.vehicle.origin
        plan = [R.MAVLink_mission_item_int_message(
            1, 1, m.seq, m.frame, m.command, 0, 1, m.param1, m.param2, m.param3, m.param4,
            *[int(round(c * 1e7)) for c in origin.to_global(home + [dn, de, 0.0])[:2]], m.z, 0)
            for m, (dn, de) in zip(plan, ((0, 0), (2, 0), (2, 2), (0, 2)))]
        replies = send(R.MAVLink_mission_count_message(1, 1, len(plan), 0))
        for _ in range(len(plan)):
            req = [m for m in replies if m.get_type() == "MISSION_REQUEST_INT"]
            replies = send(plan[req[-1].seq])
        assert [m.type for m in replies if m.get_type() == "MISSION_ACK"] == [R.MAV_MISSION_ACCEPTED]
        acks = [m for m in send(R.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
                if m.get_type() == "COMMAND_ACK"]
        acks += [m for m in send(R.MAVLink_command_long_message(1, 1, R.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0))
                 if m.get_type() == "COMMAND_ACK"]
        assert [a.result for a in acks] == [0, 0]
        for _ in range(60):
            run(0.5)
            if sim.vehicle.runner.complete and not sim.vehicle.armed:
                break
        run(0.1)
        assert [s for s, _ in reached] == [0, 1, 2, 3]
        for (seq, pos), (dn, de) in zip(reached[1:3], ((2, 0), (2, 2))):
            goal = home + [dn, de, -2.0]
            assert np.linalg.norm(pos - goal) <= 0.3 + 0.1, (seq, pos, goal)  # (radius on the EKF's estimate)
        end = sim.truth().position_ned_m
        assert np.linalg.norm(end[:2] - (home[:2] + [0, 2])) < 0.3 and not sim.vehicle.armed
    finally:
        sim.close()
