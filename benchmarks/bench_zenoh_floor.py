"""The Python Zenoh binding's floor on one host: round trips of one SITL-sized datagram between two
processes, over loopback UDP and over Zenoh (peer, TCP loopback, declared express publishers) with
different ways of receiving, and with shared-memory buffers (zenoh.shm, unstable API).

    python benchmarks/bench_zenoh_floor.py [--n 2000] [--bytes 200] [--quick] [--json]

Zenoh receive paths, both ends alike:
- `zenoh`: a callback subscriber that answers in the callback (the least Python work a sample can cost);
- `zenoh-link`: mars_link.transport.zenoh_link.ZenohTransport, what the SITL processes use: the callback
  queues the frame and wakes a socket the main loop waits on with its UDP sockets and timers;
- `zenoh-direct`: the same, with the callback run on Zenoh's network thread (`handlers.Callback(...,
  indirect=False)`) instead of the binding's own Python thread;
- `zenoh-fifo`: a FIFO-channel subscriber, the main thread blocked in its `recv()` (no descriptor to
  select on and no timeout in eclipse-zenoh 1.10: a loop that also waits on sockets, timers or Ctrl-C
  cannot sleep this way);
- `zenoh-shm`: as `zenoh`, payloads in shared-memory buffers.
A round trip is two hops (ping, pong); the one-hop floor is half of it. Printed: medians and p99 of the
round trips, their ratio to UDP, and the ping process's CPU per round trip (one send and one receive:
what a hop costs the CPU at both ends). The machine is shared: compare rows of one run only.
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from record import Recorder, add_json_option, apply_quick  # noqa: E402


def _zenoh_session(listen: str | None, connect: str | None, shm: bool):
    import zenoh

    from mars_link.transport.zenoh_link import ZenohParams, make_config

    cfg = make_config(ZenohParams(node="bench", listen=(listen,) if listen else (), connect=(connect,) if connect else ()))
    cfg.insert_json5("transport/shared_memory/enabled", json.dumps(shm))
    return zenoh.open(cfg)


def _shm_writer(shm: bool, size: int):
    """bytes -> what to put: the bytes themselves, or a shared-memory buffer holding them."""
    if not shm:
        return lambda data: data
    from zenoh.shm import BlockOn, GarbageCollect, ShmProvider

    provider = ShmProvider.default_backend(1 << 20)
    policy = BlockOn(GarbageCollect())

    def put(data: bytes):
        buf = provider.alloc(len(data), policy)
        buf[:] = data
        return buf

    return put


KINDS = ("udp", "zenoh", "zenoh-link", "zenoh-direct", "zenoh-fifo", "zenoh-shm")


def _zenoh_ends(kind: str, endpoint: str, listen: bool, me: str, other: str, size: int):
    """(send(bytes), recv(timeout_s) -> bytes | None, close()) of one end of a Zenoh `kind` other than
    `zenoh` and `zenoh-shm` (those answer in their callback)."""
    import collections
    import select

    import zenoh

    from mars_link.transport.zenoh_link import ZenohParams, ZenohTransport, make_config

    if kind in ("zenoh-link", "zenoh-direct"):
        nodes = {"ping": "coordinator", "pong": "unit/1"}
        params = ZenohParams(node=nodes[me], listen=(endpoint,) if listen else (),
                             connect=() if listen else (endpoint,), validate_frames=False, first_send_wait_s=10.0)
        link = ZenohTransport(params)
        if kind == "zenoh-direct":  # the same queue and wake-up, called on Zenoh's network thread
            for sub in link._subs:
                sub.undeclare()
            f = params.fleet
            key = f"mars/{f}/{link.node}/mavlink/down/*"
            on = link._on_down
            if link.node == "coordinator":
                key, on = f"mars/{f}/unit/*/mavlink/up/coordinator", link._on_up
            link._subs = [link.session.declare_subscriber(key, zenoh.handlers.Callback(on, indirect=False))]
        peer = nodes[other]
        link.prepare(peer)

        def recv(timeout_s: float):
            got = link.recv(timeout_s)
            return None if got is None else got[0]

        return (lambda data: link.send(data, peer)), recv, link.close
    session = _zenoh_session(endpoint if listen else None, None if listen else endpoint, False)
    pub = session.declare_publisher(f"floor/{other}", express=True)
    sub = session.declare_subscriber(f"floor/{me}", zenoh.handlers.FifoChannel(1024))
    deadline = time.monotonic() + 10
    while not pub.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.01)

    def close() -> None:
        sub.undeclare()
        pub.undeclare()
        session.close()

    return pub.put, (lambda timeout_s: sub.recv().payload.to_bytes()), close


def pong(kind: str, endpoint: str, size: int) -> None:
    """The echo side (a child process): every datagram straight back."""
    if kind == "udp":
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", int(endpoint)))
        print("ready", flush=True)
        while True:
            data, addr = s.recvfrom(65536)
            if data == b"stop":
                return
            s.sendto(data, addr)
    if kind not in ("zenoh", "zenoh-shm"):
        send, recv, close = _zenoh_ends(kind, endpoint, True, "pong", "ping", size)
        print("ready", flush=True)
        try:
            while True:
                data = recv(30.0)
                if data is None or data == b"stop":
                    return
                send(data)
        finally:
            close()
    shm = kind == "zenoh-shm"
    session = _zenoh_session(endpoint, None, shm)
    wrap = _shm_writer(shm, size)
    pub = session.declare_publisher("floor/pong", express=True)
    done = threading.Event()

    def on_ping(sample) -> None:
        data = sample.payload.to_bytes()
        if data == b"stop":
            done.set()
        else:
            pub.put(wrap(data))

    sub = session.declare_subscriber("floor/ping", on_ping)
    print("ready", flush=True)
    done.wait()
    sub.undeclare()
    pub.undeclare()
    session.close()


def ping(kind: str, n: int, size: int) -> tuple[list[float], float]:
    """Round-trip times (s) of `n` datagrams of `size` bytes to a `pong` child, and this process's CPU
    seconds per round trip."""
    from mars_link.transport.zenoh_link import free_tcp_port

    port = free_tcp_port()
    endpoint = str(port) if kind == "udp" else f"tcp/127.0.0.1:{port}"
    child = subprocess.Popen([sys.executable, __file__, "--pong", kind, endpoint, "--bytes", str(size)],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        payload = bytes(range(256)) * (size // 256 + 1)
        payload = payload[:size]
        rtts = []
        if kind == "udp":
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            cpu0 = time.process_time()
            for _ in range(n):
                t0 = time.perf_counter()
                s.sendto(payload, ("127.0.0.1", port))
                s.recvfrom(65536)
                rtts.append(time.perf_counter() - t0)
            cpu = time.process_time() - cpu0
            s.sendto(b"stop", ("127.0.0.1", port))
            s.close()
        elif kind in ("zenoh", "zenoh-shm"):
            shm = kind == "zenoh-shm"
            session = _zenoh_session(None, endpoint, shm)
            wrap = _shm_writer(shm, size)
            got = threading.Event()
            sub = session.declare_subscriber("floor/pong", lambda sample: got.set())
            pub = session.declare_publisher("floor/ping", express=True)
            deadline = time.monotonic() + 10
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.01)
            time.sleep(0.3)  # the pong's publisher matched too
            cpu0 = time.process_time()
            for _ in range(n):
                got.clear()
                t0 = time.perf_counter()
                pub.put(wrap(payload))
                if got.wait(2.0):
                    rtts.append(time.perf_counter() - t0)
            cpu = time.process_time() - cpu0
            pub.put(b"stop")
            time.sleep(0.1)
            sub.undeclare()
            pub.undeclare()
            session.close()
        else:
            send, recv, close = _zenoh_ends(kind, endpoint, False, "ping", "pong", size)
            try:
                time.sleep(0.3)  # the pong's publisher matched too
                for _ in range(20):  # warm: both ends' first frames
                    send(payload)
                    recv(2.0)
                cpu0 = time.process_time()
                for _ in range(n):
                    t0 = time.perf_counter()
                    send(payload)
                    if recv(2.0) is not None:
                        rtts.append(time.perf_counter() - t0)
                cpu = time.process_time() - cpu0
                send(b"stop")
                time.sleep(0.1)
            finally:
                close()
        child.wait(10)
        return rtts, cpu / n
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--bytes", type=int, default=200, help="datagram size (a unit's sensor datagram: ~180 B)")
    ap.add_argument("--kinds", default=",".join(KINDS), help=f"comma-separated, of {', '.join(KINDS)} (udp is "
                    "always measured: the ratios' base)")
    ap.add_argument("--pong", nargs=2, metavar=("KIND", "ENDPOINT"), help=argparse.SUPPRESS)
    ap.add_argument("--quick", action="store_true", help="300 round trips per link")
    add_json_option(ap)
    a = ap.parse_args()
    if a.pong:
        pong(a.pong[0], a.pong[1], a.bytes)
        return 0
    apply_quick(ap, a, n=300)
    if a.n < 10 or not 16 <= a.bytes <= 60000:
        ap.error("--n must be >= 10 and --bytes 16..60000")
    kinds = ["udp"] + [k for k in a.kinds.split(",") if k and k != "udp"]
    unknown = sorted(set(kinds) - set(KINDS))
    if unknown:
        ap.error(f"--kinds: unknown {', '.join(unknown)} (expected some of {', '.join(KINDS)})")
    rec = Recorder.start("bench_zenoh_floor", a)
    rows = []
    for k, kind in enumerate(kinds):
        print(f"[{k + 1}/{len(kinds)}] {kind} ...", file=sys.stderr, flush=True)
        rtts, cpu = ping(kind, a.n, a.bytes)
        rtts.sort()
        p99 = rtts[int(0.99 * (len(rtts) - 1))]
        rows.append((kind, statistics.median(rtts) * 1e6, p99 * 1e6, cpu * 1e6, len(rtts)))
    udp = rows[0]
    print(f"{a.n} round trips of {a.bytes} B between two processes on loopback (one hop = half a round trip)")
    print(f"{'link':>12} {'median us':>10} {'p99 us':>8} {'x UDP median':>13} {'ping CPU us':>12} {'answered':>9}")
    for kind, med, p99, cpu, got in rows:
        print(f"{kind:>12} {med:>10.0f} {p99:>8.0f} {med / udp[1]:>13.2f} {cpu:>12.0f} {got:>9}")
        rec.figure(f"rtt_median_{kind}_us", med, "us", f"{a.bytes} B round trip between two processes; p99 {p99:.0f} us")
        if kind != "udp":
            (rec.headline if kind == "zenoh-link" else rec.figure)(
                f"rtt_{kind}_vs_udp", med / udp[1], "ratio", f"median round trip over {kind} / over UDP (same run)")
    rec.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
