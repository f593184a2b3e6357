"""Zenoh session limits (issue 18, class 5): idle TCP connections to a listen port must not keep new
sessions out. With Zenoh's defaults 200 idle connections blocked the next session for about 10 s (the
first test shows it); with mars-link's limits (transport.zenoh_link.SessionLimits) the next unit's
session opens and delivers a frame at once, and a flood beyond the pending-handshake limit delays it
by rounds of the 2 s handshake timeout. Real sessions and real sockets, loopback only."""

from __future__ import annotations

import socket
import time

import pytest
import zenoh

from mars_link.transport.zenoh_link import SessionLimits, ZenohParams, ZenohTransport, free_tcp_port, make_config

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(120)]


def _idle(port: int, n: int) -> list[socket.socket]:
    """`n` TCP connections to the port that never say a word (what a scanner or an attacker leaves)."""
    socks = [socket.create_connection(("127.0.0.1", port)) for _ in range(n)]
    time.sleep(0.3)  # accepted by the listener, waiting for a handshake that never comes
    return socks


def _time_to_first_frame(listener: ZenohTransport, endpoint: str, timeout_s: float = 30.0) -> float:
    """Seconds from a new unit's first try to its first frame at the listener (its session retried as a
    unit process would be restarted)."""
    t0 = time.monotonic()
    unit = None
    while unit is None and time.monotonic() - t0 < timeout_s:
        try:
            unit = ZenohTransport(ZenohParams("unit/7", fleet="lim", connect=(endpoint,), first_send_wait_s=5.0))
        except zenoh.ZError:
            time.sleep(0.05)
    assert unit is not None, "no session within the timeout"
    try:
        frame = b"\xfd\x00\x00\x00\x00\x07\x01\x00\x00\x00\x00\x00"  # any bytes: validation off below
        while time.monotonic() - t0 < timeout_s:
            unit.send(frame, "world")
            if listener.recv(0.05) is not None:
                return time.monotonic() - t0
        raise AssertionError("no frame within the timeout")
    finally:
        unit.close()


def _listener(limits: SessionLimits | None) -> tuple[ZenohTransport, str, int]:
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    params = ZenohParams("world", fleet="lim", listen=(endpoint,), validate_frames=False, limits=limits)
    return ZenohTransport(params), endpoint, port


@pytest.mark.long  # (CI time: -m long; it measures Zenoh's own default, which our configs replace)
def test_zenohs_defaults_block_new_sessions_for_10_s() -> None:
    defaults = SessionLimits(accept_timeout_ms=10000, accept_pending=100, max_sessions=1000)
    cfg = zenoh.Config()  # Zenoh 1.10's own values
    assert [int(cfg.get_json(f"transport/unicast/{k}")) for k in ("accept_timeout", "accept_pending", "max_sessions")] \
        == [10000, 100, 1000]
    listener, endpoint, port = _listener(defaults)
    socks = _idle(port, 200)
    try:
        assert _time_to_first_frame(listener, endpoint) > 8.0
    finally:
        for s in socks:
            s.close()
        listener.close()


def test_200_idle_connections_do_not_block_a_new_session() -> None:
    listener, endpoint, port = _listener(None)
    socks = _idle(port, 200)
    try:
        assert _time_to_first_frame(listener, endpoint) < 1.0
    finally:
        for s in socks:
            s.close()
        listener.close()


def test_a_flood_beyond_the_pending_limit_delays_a_new_session_by_rounds_of_the_handshake_timeout() -> None:
    """Connections beyond `accept_pending` wait in the kernel's accept queue and take their turn when the
    first ones time out: N idle connections delay a new session by about ceil(N / 512) x 2 s (612: 2
    rounds, measured 4.9 s; Zenoh's defaults: ceil(N / 100) x 10 s)."""
    limits = SessionLimits()
    listener, endpoint, port = _listener(limits)
    n = limits.accept_pending + 100
    socks = _idle(port, n)
    try:
        rounds = -(-n // limits.accept_pending)
        assert _time_to_first_frame(listener, endpoint) < rounds * limits.accept_timeout_ms / 1e3 + 4.0  # (loaded machine)
    finally:
        for s in socks:
            s.close()
        listener.close()


def test_the_limits_are_in_every_session_config() -> None:
    cfg = make_config(ZenohParams("unit/1", mode="client", connect=("tcp/127.0.0.1:7447",)))
    got = {k: int(cfg.get_json(k)) for k in ("transport/unicast/accept_timeout", "transport/unicast/accept_pending",
                                              "transport/unicast/max_sessions", "transport/link/tx/lease")}
    assert got == {"transport/unicast/accept_timeout": 2000, "transport/unicast/accept_pending": 512,
                   "transport/unicast/max_sessions": 256, "transport/link/tx/lease": 10000}
