"""MAVLink encoding of world/unit/coordinator messages: real bytes, exact round trip at wire precision."""

from __future__ import annotations

import numpy as np

from mars_link.core.messages import ActuatorOutput, RotorCommand, SensorPacket
from mars_link.core.state import ImuSample, PositionSample, RigidBodyState
from mars_link.mavlink.wire import (
    SensorPacketAssembler,
    actuator_output_from_message,
    actuator_output_message,
    new_mav,
    rotor_command_from_message,
    rotor_command_message,
    sensor_packet_messages,
)


def _bytes_roundtrip(sender_id: int, msgs):
    tx = new_mav(sender_id)
    rx = new_mav(250)
    out = []
    for m in msgs:
        data = m.pack(tx)
        out.extend(rx.parse_buffer(data) or [])
    return out


def _packet(rng, with_pos=True, with_truth=True) -> SensorPacket:
    t = 12.34
    imu = ImuSample(t, 3, rng.normal(size=3), rng.normal(size=3) - [0, 0, 9.8])
    pos = PositionSample(t, 3, rng.normal(size=3) * 10, rng.normal(size=3)) if with_pos else None
    q = rng.normal(size=4)
    truth = RigidBodyState(t, rng.normal(size=3), rng.normal(size=3), q / np.linalg.norm(q), rng.normal(size=3)) if with_truth else None
    return SensorPacket(t, 3, imu, pos, truth).as_wire()


def test_sensor_packet_roundtrip_is_exact_at_wire_precision() -> None:
    rng = np.random.default_rng(1)
    for with_pos, with_truth in ((True, True), (True, False), (False, False)):
        for upstream in (False, True):
            pkt = _packet(rng, with_pos, with_truth)
            asm = SensorPacketAssembler()
            got = [asm.feed(m) for m in _bytes_roundtrip(3, sensor_packet_messages(pkt, upstream))]
            done = [g for g in got if g is not None]
            assert len(done) == 1
            back = done[0]
            assert back.t_s == pkt.t_s and back.unit_id == 3
            np.testing.assert_array_equal(back.imu.gyro_frd_radps, pkt.imu.gyro_frd_radps)
            np.testing.assert_array_equal(back.imu.accel_frd_mps2, pkt.imu.accel_frd_mps2)
            assert (back.position is None) == (pkt.position is None)
            if pkt.position is not None:
                np.testing.assert_array_equal(back.position.position_ned_m, pkt.position.position_ned_m)
                np.testing.assert_array_equal(back.position.velocity_ned_mps, pkt.position.velocity_ned_mps)
            if pkt.truth is not None:
                np.testing.assert_array_equal(back.truth.quaternion_wxyz, pkt.truth.quaternion_wxyz)
                np.testing.assert_array_equal(back.truth.velocity_ned_mps, pkt.truth.velocity_ned_mps)


def test_packet_missing_its_position_frame_is_dropped_and_counted() -> None:
    pkt = _packet(np.random.default_rng(2))
    msgs = sensor_packet_messages(pkt)
    asm = SensorPacketAssembler()
    assert all(asm.feed(m) is None for m in _bytes_roundtrip(3, msgs[1:]))  # position frame lost
    assert asm.dropped_incomplete == 1


def test_rotor_command_and_actuator_output_roundtrip() -> None:
    scale = 5.1
    cmd = RotorCommand(0.07, 4, np.array([1.27, 1.31, -0.2, 7.9])).as_wire(scale)
    (msg,) = _bytes_roundtrip(250, [rotor_command_message(cmd, scale)])
    back = rotor_command_from_message(msg, scale)
    assert back.unit_id == 4 and back.t_s == cmd.t_s
    np.testing.assert_array_equal(back.thrusts_n, cmd.thrusts_n)
    out = ActuatorOutput(0.07, 4, np.array([1.0, 2.0, 3.0, 0.0])).as_wire(scale)
    (msg,) = _bytes_roundtrip(4, [actuator_output_message(out, scale)])
    back = actuator_output_from_message(msg, scale)
    assert back.unit_id == 4 and msg.flags == 1
    np.testing.assert_array_equal(back.thrusts_n, out.thrusts_n)


def test_a_units_forward_built_from_received_fields_equals_the_packet_path() -> None:
    """SensorFrames.upstream_messages (what a unit forwards to the coordinator, no arrays) gives the
    same bytes as encoding the decoded packet, with and without position, truth and velocity."""
    from mars_link.mavlink.wire import SensorFrameAssembler

    rng = np.random.default_rng(4)
    world, unit = new_mav(200), new_mav(3)
    cases = [(True, True), (True, False), (False, True), (False, False)]
    for with_pos, with_truth in cases:
        packet = _packet(rng, with_pos, with_truth)
        if with_pos and rng.random() < 0.5:
            packet.position.velocity_ned_mps = None  # sent as NaN, forwarded as NaN
        asm = SensorFrameAssembler()
        frames = None
        for m in sensor_packet_messages(packet):
            frames = asm.feed_frames(world.parse_buffer(m.pack(world))[0]) or frames
        assert frames is not None
        fast = b"".join(m.pack(unit) for m in frames.upstream_messages())
        slow = b"".join(m.pack(unit) for m in sensor_packet_messages(frames.packet(), upstream=True))
        assert fast == slow, (with_pos, with_truth)
