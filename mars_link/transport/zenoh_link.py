"""MAVLink frames over Zenoh key expressions.

Key space (one Zenoh sample = one datagram of whole MAVLink frames, payload = the raw frame bytes):

| key | carries |
|---|---|
| `mars/<fleet>/unit/<id>/mavlink/up/<dst>` | unit <id> -> node <dst> (`world`, `coordinator`, ...) |
| `mars/<fleet>/unit/<id>/mavlink/down/<src>` | node <src> -> unit <id> |
| `mars/<fleet>/<node>/mavlink/down/<src>` | node <src> -> node <node> (e.g. coordinator -> world) |

Node names are `world`, `coordinator` or any `[A-Za-z0-9_-]+` name, and `unit/<id>` (id 1..255). A unit
subscribes to its own `down/*`; another node to `<node>/mavlink/down/*` and `unit/*/mavlink/up/<node>`.
The sender is read from the key, so (as with a UDP source address) it is a claim the MAVLink layer above
checks against the system id.

Defaults keep everything on this machine: multicast scouting off, explicit `tcp/127.0.0.1` endpoints.
Several hosts: pass their `connect`/`listen` endpoints, or run one session in router mode (`mode="router"`,
no zenohd needed) and make the others clients. Sessions are closed by `close()` / the context manager:
a process that exits with an open session and a callback subscriber hangs (specs/dependencies.md §2.4).
"""

from __future__ import annotations

import collections
import json
import os
import re
import select
import signal
import socket
import threading
import time
from dataclasses import dataclass

import zenoh

from mars_link.transport.base import Address, Transport
from mars_link.transport.tls import TlsFiles, secure_endpoint
from mars_link.transport import tls as closed_bus

_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_UNIT = re.compile(r"^unit/(\d{1,3})$")


@dataclass
class ZenohParams:
    node: str                            # this endpoint: "world", "coordinator" or "unit/<id>"
    fleet: str = "default"
    mode: str = "peer"                   # peer | client | router
    listen: tuple[str, ...] = ()         # e.g. ("tcp/127.0.0.1:7447",)
    connect: tuple[str, ...] = ()
    gossip: bool = True                  # gossip scouting over established links (not multicast)
    multicast_scouting: bool = False     # off: nothing leaves the configured endpoints
    queue_frames: int = 10000            # receive queue; a flood beyond it is dropped and counted
    block_when_congested: bool = True    # lockstep must not lose frames; False: drop like a radio would
    only_from: str | None = None         # a unit link that talks to one node only (e.g. its HIL link: "world")
    validate_frames: bool = True         # drop bad MAVLink frames here (counted), pass whole valid ones
    first_send_wait_s: float = 0.0       # first frame to a node: wait up to this long for it to subscribe
    limits: SessionLimits | None = None  # None: SessionLimits() (see there)
    tls: TlsFiles | None = None          # mutual TLS (+ access control): tcp/ endpoints become tls/ (transport.tls)


@dataclass(frozen=True)
class SessionLimits:
    """What a listening session grants connections that have not finished Zenoh's handshake, and how
    many sessions it keeps. Zenoh's defaults (10 s to finish a handshake, 100 at once) let 100 idle TCP
    connections to the listen port refuse every new session for 10 s (issue 18: 200 idle connections
    blocked the next unit 9.8-10.1 s). On loopback a handshake takes milliseconds: 2 s and 512 pending
    let the issue's 200 through at once; N idle connections delay a new session by about
    ceil(N / 512) x 2 s (the rest wait in the kernel's accept queue for their turn). Lease: Zenoh's 10 s,
    so a process paused for a few seconds (SIGSTOP, a slow machine) keeps its session; the lockstep's
    own timeouts (1-3 s) declare a silent unit lost long before."""

    accept_timeout_ms: int = 2000     # a connection that has not finished the handshake by then is closed
    accept_pending: int = 512         # handshakes in progress at once; beyond, new connections are refused
    max_sessions: int = 256           # sessions at once (a SITL run: <= 36 units + world + coordinator)
    lease_ms: int = 10000             # a silent peer's session is closed after this long


def free_tcp_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def make_config(p: ZenohParams) -> zenoh.Config:
    if p.mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode {p.mode!r}: expected peer, client or router")
    cfg = zenoh.Config()

    def put(key: str, value) -> None:
        cfg.insert_json5(key, json.dumps(value))

    put("mode", p.mode)
    listen, connect = list(p.listen), list(p.connect)
    if p.tls is not None:
        listen, connect = [secure_endpoint(e) for e in listen], [secure_endpoint(e) for e in connect]
        closed_bus.apply(put, p.tls)
    put("listen/endpoints", listen)
    put("connect/endpoints", connect)
    put("scouting/multicast/enabled", bool(p.multicast_scouting))
    put("scouting/gossip/enabled", bool(p.gossip))
    limits = p.limits or SessionLimits()
    put("transport/unicast/accept_timeout", limits.accept_timeout_ms)
    put("transport/unicast/accept_pending", limits.accept_pending)
    put("transport/unicast/max_sessions", limits.max_sessions)
    put("transport/link/tx/lease", limits.lease_ms)
    return cfg


def _check_node(name: str) -> str:
    if _UNIT.match(name):
        uid = int(_UNIT.match(name).group(1))
        if not 1 <= uid <= 255:
            raise ValueError(f"zenoh node {name!r}: unit id must be 1..255")
        return name
    if not _NAME.match(name):
        raise ValueError(f"zenoh node {name!r}: expected unit/<id> or a name of [A-Za-z0-9_-]")
    return name


def key_for(fleet: str, src: str, dst: str) -> str:
    """The key a frame from node `src` to node `dst` is published on."""
    src, dst = _check_node(src), _check_node(dst)
    if src.startswith("unit/") and dst.startswith("unit/"):
        raise ValueError("unit-to-unit frames have no key (units talk to the world and the coordinator)")
    if src.startswith("unit/"):
        return f"mars/{fleet}/{src}/mavlink/up/{dst}"
    return f"mars/{fleet}/{dst}/mavlink/down/{src}"


_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


def open_session(config: zenoh.Config) -> zenoh.Session:
    """zenoh.open with Ctrl-C and SIGTERM blocked in the threads it starts (they inherit the opening
    thread's mask): the kernel then hands those signals to a thread that lets Python see them, not to a
    Zenoh worker while the main thread sleeps in select() and never wakes up to stop."""
    if not hasattr(signal, "pthread_sigmask"):  # (not POSIX)
        return zenoh.open(config)
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
    try:
        return zenoh.open(config)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


class ZenohTransport(Transport):
    kind = "zenoh"

    def __init__(self, params: ZenohParams, session: zenoh.Session | None = None) -> None:
        """`session`: share one already open session (several links of one process); its owner closes it."""
        super().__init__(params.validate_frames)
        self.params = params
        self.node = _check_node(params.node)
        if not _NAME.match(params.fleet):
            raise ValueError(f"zenoh fleet {params.fleet!r}: expected [A-Za-z0-9_-]")
        self._queue: collections.deque = collections.deque()  # (appended by Zenoh's thread, popped by ours)
        self._armed = False  # the wake descriptor is set: no further system call until we cleared it
        self._publishers: dict[Address, zenoh.Publisher] = {}  # by peer: its key is formed and checked once
        self._congestion = zenoh.CongestionControl.BLOCK if params.block_when_congested else zenoh.CongestionControl.DROP
        # readable while frames wait, so a selector can wait on this link next to UDP sockets
        self._wake_fd = _WakeFd()
        self._owns_session = session is None
        self.session = session if session is not None else open_session(make_config(params))
        try:
            f = params.fleet
            src = _check_node(params.only_from) if params.only_from else "*"
            self._subs = [self.session.declare_subscriber(f"mars/{f}/{self.node}/mavlink/down/{src}", self._on_down)]
            if not self.node.startswith("unit/"):
                self._subs.append(self.session.declare_subscriber(f"mars/{f}/unit/*/mavlink/up/{self.node}", self._on_up))
        except BaseException:
            if self._owns_session:
                self.session.close()
            raise

    # zenoh threads: keep these short
    def _on_down(self, sample: zenoh.Sample) -> None:
        self._enqueue(sample, str(sample.key_expr).rsplit("/", 1)[1])

    def _on_up(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")  # mars, fleet, unit, <id>, mavlink, up, <node>
        sender = f"unit/{parts[3]}"
        if not _UNIT.match(sender) or not 1 <= int(parts[3]) <= 255:
            self.counters.drop("bad_sender_key")
            return
        self._enqueue(sample, sender)

    def _enqueue(self, sample: zenoh.Sample, sender: str) -> None:
        if len(self._queue) >= self.params.queue_frames:
            self.counters.drop("queue_full")
            return
        self._queue.append((sample.payload.to_bytes(), sender))
        if not self._armed:  # one wake-up per burst, not one system call per frame
            self._armed = True
            self._wake_fd.set()

    def fileno(self) -> int:
        """A descriptor that is readable while received frames wait (for select/selectors)."""
        return self._wake_fd.fileno()

    @property
    def local_address(self) -> str:
        return self.node


    def _send(self, data: bytes, peer: Address) -> None:
        (self._publishers.get(peer) or self._publisher(peer)).put(data)

    def prepare(self, peer: Address) -> None:
        self._publisher(peer)

    def _publisher(self, peer: Address) -> zenoh.Publisher:
        """The publisher to `peer`, declared once (and, the first time, matched: up to first_send_wait_s)."""
        pub = self._publishers.get(peer)
        if pub is None:
            key = key_for(self.params.fleet, self.node, str(peer))
            pub = self._publishers[peer] = self.session.declare_publisher(
                key, express=True, congestion_control=self._congestion)
            deadline = time.monotonic() + self.params.first_send_wait_s
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.005)  # a process still starting up; later frames go out at once
        return pub

    def _recv(self, timeout_s: float) -> tuple[bytes, Address] | None:
        if not self._queue and timeout_s > 0:
            select.select([self._wake_fd], [], [], timeout_s)
        try:
            item = self._queue.popleft()
        except IndexError:
            return None
        if not self._queue:  # level-triggered readiness: clear, then re-arm if a frame slipped in meanwhile
            self._armed = False
            self._wake_fd.clear()
            if self._queue:
                self._armed = True
                self._wake_fd.set()
        return item

    def _close(self) -> None:
        try:
            for pub in self._publishers.values():
                pub.undeclare()
            for sub in self._subs:
                sub.undeclare()
        finally:
            if self._owns_session:
                self.session.close()
            self._wake_fd.close()


class _WakeFd:
    """A descriptor that is readable once `set` until `clear`ed: how Zenoh's receiving thread wakes a loop
    that waits in select() (selectors) next to sockets and timers. An eventfd where the OS has one (Linux):
    one system call to set and one to clear, where a socket pair takes a send, and a recv until it would
    block (`bench_zenoh_floor.py --kinds zenoh-link`, 5 runs each alternated: round trip 292 -> 267 us, CPU
    per round trip 170 -> 145 us); a socket pair elsewhere."""

    def __init__(self) -> None:
        self._lock = threading.Lock()  # a late `set` from Zenoh's thread never writes to a closed (reused) number
        self._closed = False
        if hasattr(os, "eventfd"):
            self._fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
            self._pair = None
        else:
            self._pair = socket.socketpair()
            for end in self._pair:
                end.setblocking(False)
            self._fd = self._pair[0].fileno()

    def fileno(self) -> int:
        return self._fd

    def set(self) -> None:
        with self._lock:
            if self._closed:
                return
            try:
                if self._pair is None:
                    os.eventfd_write(self._fd, 1)
                else:
                    self._pair[1].send(b"\0")
            except OSError:  # full: it is readable anyway
                pass

    def clear(self) -> None:
        if self._closed:  # (the number may belong to another file by now)
            return
        try:
            if self._pair is None:
                os.eventfd_read(self._fd)  # reads and zeroes the counter
            else:
                while self._pair[0].recv(4096):
                    pass
        except OSError:  # (nothing to read: already clear)
            pass

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._pair is None:
                os.close(self._fd)
            else:
                for end in self._pair:
                    end.close()


def open_router(port: int | None = None, listen: tuple[str, ...] = (), fleet: str = "default",
                tls: TlsFiles | None = None) -> tuple[zenoh.Session, str]:
    """A router-mode session (no zenohd needed) that SITL clients connect to; returns it and its endpoint.
    The caller closes it."""
    port = port or free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cfg = make_config(ZenohParams(node="router", fleet=fleet, mode="router", listen=(endpoint, *listen), tls=tls))
    return open_session(cfg), endpoint
