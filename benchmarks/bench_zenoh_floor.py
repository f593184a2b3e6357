"""The Python Zenoh binding's floor on one host: round trips of one SITL-sized datagram between two
processes, over loopback UDP, Zenoh (peer, TCP loopback, declared publisher and callback subscriber:
what mars_link.transport.zenoh_link does) and Zenoh with shared-memory buffers (zenoh.shm, unstable API).

    python benchmarks/bench_zenoh_floor.py [--n 2000] [--bytes 200]

A round trip is two hops (ping, pong); the one-hop floor is half of it. Medians and p99 of one run,
printed with their ratio to UDP: the machine is shared, compare rows of one run only.
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


def ping(kind: str, n: int, size: int) -> list[float]:
    """Round-trip times (s) of `n` datagrams of `size` bytes to a `pong` child."""
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
            for _ in range(n):
                t0 = time.perf_counter()
                s.sendto(payload, ("127.0.0.1", port))
                s.recvfrom(65536)
                rtts.append(time.perf_counter() - t0)
            s.sendto(b"stop", ("127.0.0.1", port))
            s.close()
        else:
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
            for _ in range(n):
                got.clear()
                t0 = time.perf_counter()
                pub.put(wrap(payload))
                if got.wait(2.0):
                    rtts.append(time.perf_counter() - t0)
            pub.put(b"stop")
            time.sleep(0.1)
            sub.undeclare()
            pub.undeclare()
            session.close()
        child.wait(10)
        return rtts
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--bytes", type=int, default=200, help="datagram size (a unit's sensor datagram: ~180 B)")
    ap.add_argument("--pong", nargs=2, metavar=("KIND", "ENDPOINT"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.pong:
        pong(a.pong[0], a.pong[1], a.bytes)
        return 0
    if a.n < 10 or not 16 <= a.bytes <= 60000:
        ap.error("--n must be >= 10 and --bytes 16..60000")
    rows = []
    for kind in ("udp", "zenoh", "zenoh-shm"):
        rtts = sorted(ping(kind, a.n, a.bytes))
        p99 = rtts[int(0.99 * (len(rtts) - 1))]
        rows.append((kind, statistics.median(rtts) * 1e6, p99 * 1e6, len(rtts)))
    udp = rows[0]
    print(f"{a.n} round trips of {a.bytes} B between two processes on loopback (one hop = half a round trip)")
    print(f"{'link':>10} {'median us':>10} {'p99 us':>8} {'x UDP median':>13} {'answered':>9}")
    for kind, med, p99, got in rows:
        print(f"{kind:>10} {med:>10.0f} {p99:>8.0f} {med / udp[1]:>13.2f} {got:>9}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
