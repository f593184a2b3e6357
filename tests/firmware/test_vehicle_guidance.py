"""Client-steered guidance on the unit vehicle flying a JSBSim body in lockstep, with real MAVLink
bytes, checked against the body's truth: MAV_CMD_DO_ORBIT, MANUAL_CONTROL in position mode, offboard
SET_ATTITUDE_TARGET, and the land detector that disarms after a descent to the ground in any mode."""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mavlink
from test_mission_protocol import _deg
from test_vehicle_protocol import LINK_API, Flight, _ack, _airborne, _vehicle, Client

from mars_link.core.rotations import euler_to_quat, quat_to_euler

R = mavlink
NAN = math.nan


def _stream(api: Client, msg, every: int = 5):
    def send(fl):
        if round(fl.t * 100) % every == 0:
            api.send(msg() if callable(msg) else msg, fl.wall)
    return send


def test_orbit_flies_the_circle_facing_its_centre() -> None:
    v, f, api = _airborne(5.0)
    lat, lon = _deg(2.0, 0.0)
    on_ground = _vehicle()
    assert _ack(Client(on_ground, LINK_API).command(R.MAV_CMD_DO_ORBIT, 3.0), R.MAV_CMD_DO_ORBIT) == \
        R.MAV_RESULT_TEMPORARILY_REJECTED
    too_small = R.MAVLink_command_int_message(1, 1, R.MAV_FRAME_GLOBAL, R.MAV_CMD_DO_ORBIT, 0, 0, 0.5, 1.0, 0, NAN,
                                              lat, lon, NAN)
    assert _ack(api.send(too_small, f.wall), R.MAV_CMD_DO_ORBIT) == R.MAV_RESULT_DENIED
    orbit = R.MAVLink_command_int_message(1, 1, R.MAV_FRAME_GLOBAL, R.MAV_CMD_DO_ORBIT, 0, 0, 3.0, 1.5, 0, NAN,
                                          lat, lon, NAN)
    assert _ack(api.send(orbit, f.wall + 0.1), R.MAV_CMD_DO_ORBIT) == 0
    assert v.custom_mode == (3 << 16) | (1 << 24)  # POSCTL.ORBIT, as PX4 reports it
    f.run(10.0)  # onto the circle
    radii, angles, heading_err, speeds = [], [], [], []

    def watch(fl):
        s = fl.body.state()
        d = s.position_ned_m[:2] - np.array([2.0, 0.0])
        radii.append(math.hypot(*d))
        angles.append(math.atan2(d[1], d[0]))
        to_centre = math.atan2(-d[1], -d[0])
        heading_err.append(abs((quat_to_euler(s.quaternion_wxyz)[2] - to_centre + math.pi) % (2 * math.pi) - math.pi))
        speeds.append(math.hypot(*s.velocity_ned_mps[:2]))

    f.run(20.0, watch)
    turned = np.sum(np.abs((np.diff(np.unwrap(angles)))))
    assert max(abs(r - 3.0) for r in radii) < 0.15, (min(radii), max(radii))
    assert np.all(np.diff(np.unwrap(angles)) > 0)  # clockwise (north -> east), radius > 0
    assert turned > 2 * math.pi * 1.4  # 20 s at 1.5 m/s on an 18.8 m circle: 1.6 turns
    assert abs(np.mean(speeds) - 1.5) < 0.1 and max(heading_err) < math.radians(10)
    assert abs(f.pos[2] + 2.05) < 0.1  # at the height it had (altitude NaN)
    assert _ack(api.command(176, 1 | 128, 4, 3, wall=f.wall + 1), 176) == 0  # HOLD ends it
    f.run(3.0)
    held = f.pos.copy()
    f.run(2.0)
    assert np.linalg.norm(f.pos - held) < 0.05


def test_manual_control_in_position_mode_climbs_moves_holds_and_lands() -> None:
    v = _vehicle()
    f = Flight(v)
    api = Client(v, LINK_API)
    sticks = [0, 0, 500, 0]

    def manual():
        return R.MAVLink_manual_control_message(1, *sticks, 0)

    send = _stream(api, manual)
    assert _ack(api.command(400, 1, wall=f.wall), 400) == 0
    f.run(0.2, send)
    assert _ack(api.command(176, 1 | 128, 3, 0, wall=f.wall), 176) == 0  # POSCTL
    f.run(1.0, send)
    assert v.armed and f.pos[2] > -0.1  # centred sticks on the ground: stays down
    sticks[2] = 800  # throttle up: climb at 0.6 x MPC_Z_VEL_MAX_UP
    f.run(3.0, send)
    sticks[2] = 500
    f.run(2.0, send)
    z_hold = f.pos[2]
    assert z_hold < -1.5
    f.run(2.0, send)
    assert abs(f.pos[2] - z_hold) < 0.05  # height held with the throttle centred
    sticks[0] = 500  # half forward: 1 m/s north (heading north)
    f.run(4.0, send)
    assert abs(f.body.state().velocity_ned_mps[0] - 1.0) < 0.05 and abs(f.pos[1]) < 0.05
    sticks[0] = 0
    f.run(2.0, send)
    stop = f.pos.copy()
    f.run(2.0, send)
    assert np.linalg.norm(f.pos - stop) < 0.05  # centred: braked and holding
    stale = f.pos.copy()
    f.run(2.0)  # sticks lost: treated as centred
    assert np.linalg.norm(f.pos - stale) < 0.05
    sticks[2] = 0  # throttle down to the ground: the land detector, then COM_DISARM_LAND
    f.run(8.0, send)
    assert f.pos[2] > -0.1 and not v.armed
    assert v.stats["manual_control"] > 100


def test_offboard_attitude_target_is_flown_then_a_descent_lands_and_disarms() -> None:
    v, f, api = _airborne(5.0)
    hover = v.autopilot.model.mass_kg * 9.80665 / (4 * v.full_scale_n)
    target = [0.0, 0.0, hover]  # pitch (rad), yaw (rad), thrust

    def att():
        q = euler_to_quat(0.0, target[0], target[1])
        return R.MAVLink_set_attitude_target_message(0, 1, 1, 0x07, list(map(float, q)), 0, 0, 0, target[2])

    send = _stream(api, att)
    f.run(0.1, send)
    assert _ack(api.command(176, 1 | 128, 6, 0, wall=f.wall), 176) == 0
    f.run(1.0, send)
    target[:2] = [math.radians(-8.0), math.radians(30.0)]  # nose down 8 deg, heading 30 deg
    target[2] = hover / math.cos(math.radians(8.0))  # (the vertical share of the thrust stays the weight)
    pitches, yaws, vz = [], [], []

    def watch(fl):
        send(fl)
        r, p, y = quat_to_euler(fl.body.state().quaternion_wxyz)
        pitches.append(p)
        yaws.append(y)
        vz.append(fl.body.state().velocity_ned_mps[2])

    f.run(3.0, watch)
    assert abs(np.mean(pitches[-100:]) - math.radians(-8.0)) < math.radians(0.5)
    assert abs(np.mean(yaws[-100:]) - math.radians(30.0)) < math.radians(1.0)
    vel = f.body.state().velocity_ned_mps
    assert math.hypot(vel[0], vel[1]) > 2.5  # accelerating along the heading
    assert abs(math.atan2(vel[1], vel[0]) - math.radians(30.0)) < math.radians(3.0)
    assert max(abs(x) for x in vz[-100:]) < 0.3  # thrust matched to hold height, roughly
    target[:] = [0.0, math.radians(30.0), 0.9 * hover]  # level, a little under hover: it sinks to the ground
    f.run(12.0, send)
    assert f.pos[2] > -0.1 and not v.armed  # landed, detected, disarmed (COM_DISARM_LAND 2 s)


def test_an_offboard_velocity_descent_to_the_ground_is_detected_and_disarms() -> None:
    v, f, api = _airborne(5.0)
    down = R.MAVLink_set_position_target_local_ned_message(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0,
                                                           0, 0, 0.5, 0, 0, 0, 0, 0)
    send = _stream(api, down)
    f.run(0.1, send)
    assert _ack(api.command(176, 1 | 128, 6, 0, wall=f.wall), 176) == 0
    gcs = Client(v, "gcs", 255, 190)
    states = []

    def watch(fl):
        send(fl)
        states.extend(m.landed_state for m in gcs.decode(fl.out) if m.get_type() == "EXTENDED_SYS_STATE")

    f.run(6.0, watch)
    assert f.pos[2] > -0.1 and v.landed and states[-1] == R.MAV_LANDED_STATE_ON_GROUND
    f.run(2.5, send)  # the descent stream goes on: it does not lift the landed vehicle
    assert not v.armed and "Disarmed after landing" in [t for _, t in v.events]
