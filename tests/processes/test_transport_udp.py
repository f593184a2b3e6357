"""Plain MAVLink over UDP behind the transport interface: round trip, senders off loopback and bad frames
counted and dropped, the link keeps working."""

from __future__ import annotations

import socket

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.transport.udp import UdpTransport


def _frame(sysid: int) -> bytes:
    return mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3).pack(mavlink.MAVLink(None, sysid, 1))


def _non_loopback_ip() -> str | None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("10.255.255.255", 1))  # no packet is sent; picks the outgoing interface address
            ip = s.getsockname()[0]
        except OSError:
            return None
    return None if ip.startswith("127.") else ip


def test_round_trip_and_bad_input() -> None:
    with UdpTransport() as a, UdpTransport() as b:
        f = _frame(5)
        a.send(f + f, b.local_address)
        assert b.recv(1.0) == (f + f, a.local_address)
        raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        raw.bind(("127.0.0.1", 0))
        raw.sendto(b"\xfd\x09garbage", b.local_address)
        raw.sendto(f[:-3], b.local_address)
        raw.sendto(b"noise" + f, b.local_address)
        assert b.recv(1.0) == (f, raw.getsockname())  # the valid frame of the last datagram
        assert b.recv(0.05) is None
        raw.close()
        d = b.counters.dropped
        assert d["truncated"] == 2 and d["garbage_bytes"] > 0, d
        assert b.counters.received == 4 and b.counters.sent == 0


def test_senders_off_loopback_are_dropped() -> None:
    ip = _non_loopback_ip()
    if ip is None:
        pytest.skip("no non-loopback IPv4 address on this machine")
    with UdpTransport() as rx:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind((ip, 0))
        s.sendto(_frame(9), rx.local_address)
        s.close()
        assert rx.recv(0.3) is None
        assert rx.counters.dropped == {"not_loopback": 1}
