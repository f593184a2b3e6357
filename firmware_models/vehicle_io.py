"""Socket plumbing shared by every runner of a `Vehicle` (the lone-unit UDP runner and the lockstep
SITL unit process): named UDP links on loopback, PX4's client-port conventions, peer learning, status.

Client links ("gcs", "api") send to a fixed destination (QGC on 14550, MAVSDK on 14540+i) and also to
whoever last sent a valid frame to the bound port within `PEER_TIMEOUT_S` (MAVProxy `udpout`), as PX4
does. A link without a fixed destination (the coordinator in the lone-unit runner) answers the address
of the last frame that the vehicle accepted from its configured peer (after signing, where required).
"""

from __future__ import annotations

import os
import selectors
import socket
import time
from dataclasses import dataclass
from pathlib import Path

from firmware_models.vehicle import LINK_COORDINATOR, Outgoing, Vehicle
from mars_link.errors import PortUnavailable, UserInputError
from mars_link.state import RigidBodyState

LOOPBACK = "127.0.0.1"
RECV_BUFFER_BYTES = 4 * 1024 * 1024
MAX_DATAGRAMS_PER_WAKE = 4000  # per socket: keep the control loop on time during a flood
PEER_TIMEOUT_S = 10.0  # a client link also serves the last sender of valid frames (MAVProxy udpout)
GCS_PORT = 14550
API_PORT_BASE = 14540  # + unit index (0-based)
GCS_BIND_BASE = 18570
API_BIND_BASE = 14580
COORD_BIND_BASE = 14600
SOCKETS_HOOK = None  # (VehicleSockets) -> None; may swap or tap entries of .socks (mars_link.transport.sitl_child)


@dataclass
class LinkSpec:
    bind_port: int  # 0 = any free port
    dest: tuple[str, int] | None = None  # fixed destination; None = learnt from the peer
    learn_clients: bool = True  # also answer the last sender of valid frames (client links)


def client_links(index: int, gcs_port: int = GCS_PORT, api_port: int | None = None,
                 gcs_bind: int | None = None, api_bind: int | None = None) -> dict[str, LinkSpec]:
    """PX4's SITL ports for instance `index` (0-based): GCS 18570+i -> 14550, API 14580+i -> 14540+i."""
    pick = lambda v, d: d if v is None else v  # noqa: E731
    return {
        "gcs": LinkSpec(pick(gcs_bind, GCS_BIND_BASE + index), (LOOPBACK, gcs_port)),
        "api": LinkSpec(pick(api_bind, API_BIND_BASE + index), (LOOPBACK, pick(api_port, API_PORT_BASE + index))),
    }


BATCH_BYTES = 1400  # one Ethernet-sized datagram


def _coalesce(out: list[Outgoing]) -> list[Outgoing]:
    """Frames per link joined into datagrams of at most BATCH_BYTES, order kept within each link."""
    chunks: dict[str, list[bytearray]] = {}
    for link, data in out:
        parts = chunks.setdefault(link, [bytearray()])
        if parts[-1] and len(parts[-1]) + len(data) > BATCH_BYTES:
            parts.append(bytearray())
        parts[-1] += data
    return [Outgoing(link, bytes(b)) for link, parts in chunks.items() for b in parts]


def bind_udp(port: int) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
    except OSError:
        pass
    try:
        s.bind((LOOPBACK, port))
    except OSError as e:
        s.close()
        raise PortUnavailable(f"cannot bind UDP port {port} on {LOOPBACK}: {e.strerror}") from None
    s.setblocking(False)
    return s


class VehicleSockets:
    """One non-blocking UDP socket per vehicle link, fed into `Vehicle.handle`, answering `Outgoing`."""

    def __init__(self, vehicle: Vehicle, links: dict[str, LinkSpec], tlog: Path | None = None,
                 batch: bool = False) -> None:
        """`batch`: frames for the same link from one `send` call share datagrams (up to
        `BATCH_BYTES`), as PX4 fills its UDP buffer: one syscall (and one wake-up of the receiver)
        instead of one per frame."""
        self.vehicle = vehicle
        self.batch = batch
        self.specs = links
        self.socks: dict[str, socket.socket] = {}
        self.sel: selectors.BaseSelector | None = None
        self._tlog = None
        try:
            for name, spec in links.items():
                self.socks[name] = bind_udp(spec.bind_port)
        except UserInputError:
            self.close()
            raise
        self.dest = {name: spec.dest for name, spec in links.items()}
        self.peers: dict[str, tuple[tuple[str, int], float] | None] = {}
        if SOCKETS_HOOK is not None:
            SOCKETS_HOOK(self)
        self.sel = selectors.DefaultSelector()
        for name, s in self.socks.items():
            self.sel.register(s, selectors.EVENT_READ, name)
        self.datagrams = 0
        self.send_errors = 0
        self.not_loopback = 0
        self._tlog = open(tlog, "ab", buffering=0) if tlog else None  # unbuffered: flushed as it goes

    def ports(self) -> dict[str, int]:
        return {name: s.getsockname()[1] for name, s in self.socks.items()}

    def send(self, out: list[Outgoing]) -> None:
        if self.batch and len(out) > 1:
            out = _coalesce(out)
        now = time.monotonic()
        for link, data in out:
            dest = self.dest.get(link)
            peer = self.peers.get(link)
            if peer is not None and now - peer[1] > PEER_TIMEOUT_S:
                peer = self.peers[link] = None
            sent = False
            for addr in (dest, peer[0] if peer is not None and peer[0] != dest else None):
                if addr is None:
                    continue
                try:
                    self.socks[link].sendto(data, addr)
                    sent = True
                except OSError:  # nobody listening (ICMP refused) or buffer full: best effort
                    self.send_errors += 1
            if sent:
                self._log(data)

    def poll(self, timeout_s: float) -> int:
        """Wait up to `timeout_s` for input on any link, hand every datagram to the vehicle and send
        its answers; returns the number of datagrams handled."""
        n = 0
        for key, _ in self.sel.select(max(0.0, timeout_s)):
            n += self.drain(key.data, key.fileobj)
        return n

    def drain(self, link: str, sock: socket.socket) -> int:
        v = self.vehicle
        n = 0
        for _ in range(MAX_DATAGRAMS_PER_WAKE):
            try:
                data, addr = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. ICMP port unreachable reported on a later recv
                continue
            n += 1
            self.datagrams += 1
            if addr[0] != LOOPBACK:
                self.not_loopback += 1
                continue
            self._log(data)
            before = v.stats.get("from_coordinator", 0)
            rx = v.stats.get("rx", 0)
            out = v.handle(data, time.time(), link)
            if link == LINK_COORDINATOR and self.specs[link].dest is None:
                if v.stats.get("from_coordinator", 0) > before:
                    self.dest[LINK_COORDINATOR] = addr
            elif self.specs[link].learn_clients and v.stats.get("rx", 0) > rx:
                self.peers[link] = (addr, time.monotonic())  # a client that sends valid MAVLink gets telemetry
            self.send(out)
        return n

    def _log(self, data: bytes) -> None:
        if self._tlog:
            self._tlog.write(tlog_records(data))

    def counters(self) -> dict[str, int]:
        return {"datagrams": self.datagrams, "not_loopback": self.not_loopback, "send_errors": self.send_errors}

    def close(self) -> None:
        if self.sel is not None:
            self.sel.close()
        for s in self.socks.values():
            s.close()
        if self._tlog:
            self._tlog.close()


def tlog_records(data: bytes, t_s: float | None = None) -> bytes:
    """pymavlink .tlog records of one datagram: each frame preceded by its 8-byte big-endian
    microsecond timestamp (a datagram may carry several frames; bytes that are no frame go as one)."""
    stamp = int((time.time() if t_s is None else t_s) * 1e6).to_bytes(8, "big")
    parts = []
    i, n = 0, len(data)
    while i < n:
        if data[i] == 0xFD and i + 3 <= n:
            size = 12 + data[i + 1] + (13 if data[i + 2] & 0x01 else 0)
        elif data[i] == 0xFE and i + 2 <= n:
            size = 8 + data[i + 1]
        else:
            size = n - i
        parts.append(stamp + data[i:i + size])
        i += size
    return b"".join(parts)


def vehicle_status(vehicle: Vehicle, truth: RigidBodyState | None, sim_time_s: float, **extra) -> dict:
    """A JSON-able snapshot of one vehicle (mode, counters, motor model) and, where the runner owns
    the body, its truth."""
    v = vehicle
    status = {
        "unit": v.sysid, "sim_time_s": sim_time_s, "wall_time_s": time.time(), "armed": v.armed,
        "mode": list(v.mode), "source": v.source, "phase": v.autopilot.phase.value,
        "motor_eta": [float(x) for x in v.motors.eta], "motor_thrust_n": [float(x) for x in v.motors.thrust_n],
        "drops": v.drop_counts(), "stats": v.stats, "intake_accepted": v.intake.accepted,
    }
    if truth is not None:
        status.update(
            truth_position_ned_m=[float(x) for x in truth.position_ned_m],
            truth_velocity_ned_mps=[float(x) for x in truth.velocity_ned_mps],
            truth_quaternion_wxyz=[float(x) for x in truth.quaternion_wxyz],
        )
    status.update(extra)
    return status


def write_json_atomic(path: Path, doc: dict) -> None:
    """Strict JSON (NaN/inf -> null, mars_link.outputs), replaced atomically."""
    from mars_link.outputs import dumps

    tmp = path.with_suffix(".tmp")
    tmp.write_text(dumps(doc, indent=None))
    os.replace(tmp, path)
