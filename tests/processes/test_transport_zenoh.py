"""MAVLink frames over Zenoh between two real sessions on loopback: round trip, no multicast scouting,
no listener off loopback, bad input counted and dropped, sessions closed on exit and Ctrl-C."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.transport.zenoh_link import ZenohParams, ZenohTransport, free_tcp_port, key_for, make_config

ROOT = Path(__file__).resolve().parents[2]


def _frame(sysid: int, t_us: int = 123456) -> bytes:
    mav = mavlink.MAVLink(None, sysid, 1)
    return mavlink.MAVLink_set_actuator_control_target_message(t_us, 0, 3, 1, [0.1, 0.2, 0.3, 0.4, 0, 0, 0, 0]).pack(mav)


@pytest.fixture()
def pair():
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    a = ZenohTransport(ZenohParams("coordinator", fleet="t1", listen=(ep,)))
    b = ZenohTransport(ZenohParams("unit/3", fleet="t1", connect=(ep,), first_send_wait_s=5.0))
    a.params.first_send_wait_s = 5.0
    try:
        yield a, b
    finally:
        b.close()
        a.close()


def test_round_trip_between_two_sessions_is_byte_exact(pair) -> None:
    a, b = pair
    down = _frame(201)
    a.send(down, "unit/3")
    assert b.recv(5.0) == (down, "coordinator")
    up = _frame(3, 999) * 2  # one datagram, two frames
    b.send(up, "coordinator")
    assert a.recv(5.0) == (up, "unit/3")
    assert a.counters.sent == 1 and a.counters.received == 1 and a.counters.bytes_received == len(up)
    assert b.recv(0.05) is None  # nothing else arrived


def test_key_space() -> None:
    assert key_for("f", "unit/3", "world") == "mars/f/unit/3/mavlink/up/world"
    assert key_for("f", "coordinator", "unit/3") == "mars/f/unit/3/mavlink/down/coordinator"
    assert key_for("f", "coordinator", "world") == "mars/f/world/mavlink/down/coordinator"
    for bad in (("unit/3", "unit/4"), ("unit/0", "world"), ("a/b", "world"), ("world", "x*")):
        with pytest.raises(ValueError):
            key_for("f", *bad)


def _own_sockets() -> tuple[list[tuple[str, int]], list[tuple[str, int]]]:
    """(UDP sockets, listening TCP sockets) of this process as (ip hex, port)."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])

    def rows(table: str, want_state: str | None):
        out = []
        for path in (f"/proc/self/net/{table}", f"/proc/self/net/{table}6"):
            if not os.path.exists(path):
                continue
            for line in open(path).read().splitlines()[1:]:
                f = line.split()
                if f[9] in inodes and (want_state is None or f[3] == want_state):
                    ip, port = f[1].split(":")
                    out.append((ip, int(port, 16)))
        return out

    return rows("udp", None), rows("tcp", "0A")  # 0A = LISTEN


def test_scouting_is_off_and_nothing_listens_off_loopback(pair) -> None:
    a, _ = pair
    cfg = make_config(a.params)
    assert cfg.get_json("scouting/multicast/enabled") == "false"
    udp, listening = _own_sockets()
    assert not any(port == 7446 for _, port in udp), udp  # no multicast scouting socket
    assert listening, "the listening session should have a TCP socket"
    assert all(ip == "0100007F" for ip, _ in listening), listening  # 127.0.0.1 only


def test_malformed_and_spoofed_input_is_counted_and_dropped(pair) -> None:
    a, b = pair
    good = _frame(201)
    a.send(good, "unit/3")  # make sure the route exists
    assert b.recv(5.0) is not None
    s = a.session
    s.put("mars/t1/unit/3/mavlink/down/coordinator", b"\x00garbage\xff" * 5)
    corrupted = bytearray(good)
    corrupted[12] ^= 0xFF
    s.put("mars/t1/unit/3/mavlink/down/coordinator", bytes(corrupted))
    s.put("mars/t1/unit/3/mavlink/down/coordinator", good[:-4])  # truncated
    s.put("mars/t1/unit/3/mavlink/down/coordinator", b"\x00junk" + good)  # junk, then a valid frame
    b_to_a_spoof = "mars/t1/unit/999/mavlink/up/coordinator"  # unit ids are 1..255
    b.session.put(b_to_a_spoof, good)
    assert b.recv(2.0) == (good, "coordinator")  # only the valid frame of the last datagram
    assert b.recv(0.2) is None
    d = b.counters.dropped
    assert d["garbage_bytes"] > 0 and d["bad_crc"] >= 1 and d["truncated"] == 1, d
    time.sleep(0.2)
    assert a.recv(0.2) is None
    assert a.counters.dropped.get("bad_sender_key") == 1


def _child(code: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def test_sessions_close_on_error_and_on_ctrl_c() -> None:
    """A process with a Zenoh callback subscriber hangs at exit unless the session is closed."""
    def head() -> str:  # each child listens on its own port
        return f"""
        from mars_link.transport.zenoh_link import ZenohParams, ZenohTransport
        with ZenohTransport(ZenohParams("world", fleet="t2", listen=("tcp/127.0.0.1:{free_tcp_port()}",))) as t:
            print("up", flush=True)
    """
    err = _child(head() + "        raise RuntimeError('boom')\n")
    waiting = _child(head() + "        t.recv(60.0)\n")
    assert waiting.stdout.readline().strip() == "up"
    waiting.send_signal(signal.SIGINT)
    assert err.wait(20) == 1 and "boom" in err.stderr.read()
    assert waiting.wait(20) != 0  # KeyboardInterrupt, not a hang


def test_a_flood_is_dropped_at_the_queue_and_the_link_keeps_working() -> None:
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with ZenohTransport(ZenohParams("world", fleet="t3", listen=(ep,))) as rx, \
            ZenohTransport(ZenohParams("unit/2", fleet="t3", connect=(ep,), first_send_wait_s=5.0)) as tx:
        rx.params.queue_frames = 500  # small queue: the flood below overflows it while nobody reads
        frame = _frame(2)
        for _ in range(5000):
            tx.send(frame, "world")
        time.sleep(0.5)
        got = 0
        while rx.recv(0.05) is not None:
            got += 1
        assert got == 500 and rx.counters.dropped["queue_full"] == 4500
        tx.send(_frame(2, 7), "world")
        assert rx.recv(2.0) == (_frame(2, 7), "unit/2")


@pytest.mark.parametrize("eventfd", [True, False])
def test_wake_descriptor_is_readable_from_set_until_clear(monkeypatch, eventfd: bool) -> None:
    """The descriptor a loop selects on (an eventfd, or a socket pair where the OS has none): readable after
    any number of sets until one clear, and a set after close writes nothing (Zenoh's thread may be late)."""
    import select

    from mars_link.transport import zenoh_link

    if not eventfd:
        monkeypatch.delattr(zenoh_link.os, "eventfd", raising=False)
    elif not hasattr(os, "eventfd"):
        pytest.skip("no eventfd on this OS")
    wake = zenoh_link._WakeFd()
    assert (wake._pair is None) == eventfd

    def readable() -> bool:
        return bool(select.select([wake], [], [], 0)[0])

    assert not readable()
    wake.set()
    wake.set()
    assert readable()
    wake.clear()
    assert not readable()
    wake.clear()  # nothing to read: no error
    wake.set()
    assert readable()
    wake.close()
    wake.set()  # after close: ignored
    wake.close()


def test_a_burst_wakes_the_loop_once_and_every_frame_arrives(pair) -> None:
    """Ten frames sent at once: the link is readable, all ten come out in order, then it is not readable."""
    import select

    a, b = pair
    frames = [_frame(3, t_us=1000 + k) for k in range(10)]
    for f in frames:
        assert b.send(f, "coordinator")
    deadline = time.monotonic() + 5
    while len(a._queue) < 10 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert select.select([a], [], [], 1.0)[0]
    got = [a.recv(0) for _ in range(10)]
    assert [g[0] for g in got] == frames and {g[1] for g in got} == {"unit/3"}
    assert a.recv(0) is None
    assert not select.select([a], [], [], 0)[0]
