"""MAVLink over a serial line, tested over a pseudo-terminal pair: pyserial on the slave side, the raw
master descriptor on the other; frames split across writes, line noise, corruption."""

from __future__ import annotations

import os
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.transport.framing import MavlinkFramer, check_datagram
from mars_link.transport.serial_link import FdStream, SerialParams, SerialTransport


def _frames(n: int, sysid: int = 1) -> list[bytes]:
    mav = mavlink.MAVLink(None, sysid, 1)
    return [mavlink.MAVLink_hil_actuator_controls_message(1000 * i, [0.25] * 16, 0, 1).pack(mav) for i in range(n)]


@pytest.fixture()
def pty_pair():
    master, slave = os.openpty()
    a = SerialTransport(SerialParams(os.ttyname(slave), 57600))
    os.close(slave)  # pyserial holds its own descriptor
    b = SerialTransport(stream=FdStream(master, "pty-master"))
    try:
        yield a, b
    finally:
        a.close()
        b.close()


def test_frames_cross_the_pty_both_ways(pty_pair) -> None:
    a, b = pty_pair
    frames = _frames(5)
    for f in frames:
        b.send(f, "unit")
    got = [a.recv(2.0) for _ in frames]
    assert [g[0] for g in got] == frames and got[0][1] == a.local_address
    a.send(frames[0], "coordinator")
    assert b.recv(2.0) == (frames[0], "pty-master")
    assert a.counters.dropped == {} and b.counters.dropped == {}


def test_noise_and_corruption_cost_only_the_frames_they_touch(pty_pair) -> None:
    a, b = pty_pair
    f1, f2, f3 = _frames(3)
    bad = bytearray(f2)
    bad[20] ^= 0x55
    stream = b"\x00\xff noise" + f1 + bytes(bad) + f2[:7] + f3  # noise, good, corrupted, truncated, good
    for i in range(0, len(stream), 5):  # dribbled in small writes, as a UART delivers
        b.stream.write(stream[i:i + 5])
        time.sleep(0.001)
    assert a.recv(2.0)[0] == f1
    assert a.recv(2.0)[0] == f3
    assert a.recv(0.1) is None
    d = a.counters.dropped
    assert d["bad_crc"] >= 1 and d["bad_crc"] + d.get("unknown_msgid", 0) >= 2 and d["garbage_bytes"] > 0, d


def test_framer_byte_by_byte_and_datagram_check() -> None:
    frames = _frames(4, sysid=7)
    framer = MavlinkFramer()
    out = []
    for byte in b"".join(frames):
        out += framer.feed(bytes([byte]))
    assert out == frames and framer.counters.garbage_bytes == 0
    good, problems = check_datagram(frames[0] + b"\x01\x02" + frames[1][:-1])
    assert good == frames[0] and problems["truncated"] == 1
    unknown = bytearray(frames[0])
    unknown[7:10] = b"\xff\xff\x00"  # a message id this dialect does not have
    assert check_datagram(bytes(unknown))[0] == b""


def test_missing_device_is_one_clear_error() -> None:
    with pytest.raises(ValueError, match="serial /nonexistent/tty"):
        SerialTransport(SerialParams("/nonexistent/tty"))
