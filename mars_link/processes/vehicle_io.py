"""Link plumbing shared by every runner of a `Vehicle` (the lone-unit UDP runner and the lockstep
SITL unit process): named links on loopback (UDP, or any `mars_link.transport.Transport` the runner
hands in, e.g. a lockstep unit's HIL and coordinator links on Zenoh), PX4's client-port conventions,
peer learning, status.

Client links ("gcs", "api") send to a fixed destination (QGC on 14550, MAVSDK on 14540+i) and also to
whoever last sent a valid frame to the bound port within `PEER_TIMEOUT_S` (MAVProxy `udpout`), as PX4
does. A link without a fixed destination (the coordinator in the lone-unit runner) answers the address
of the last frame that the vehicle accepted from its configured peer (after signing, where required).
"""

from __future__ import annotations

import os
import selectors
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from firmware_models.vehicle import LINK_COORDINATOR, Outgoing, Vehicle
from mars_link.core.errors import PortUnavailable, UserInputError
from mars_link.core.state import RigidBodyState
from mars_link.transport.base import Address, Transport
from mars_link.transport.udp import UdpParams, UdpTransport

LOOPBACK = "127.0.0.1"
RECV_BUFFER_BYTES = 4 * 1024 * 1024
MAX_DATAGRAMS_PER_WAKE = 4000  # per socket: keep the control loop on time during a flood
TLOG_MAX_BYTES = 100 * 2**20  # per .tlog file; then that log stops (one STATUSTEXT), the flight goes on
PEER_TIMEOUT_S = 10.0  # a client link also serves the last sender of valid frames (MAVProxy udpout)
from mars_link.mavlink.tlog import tlog_records  # noqa: F401  (its home is the MAVLink floor)
from mars_link.processes.ports import API_BIND_BASE, API_PORT_BASE, COORD_BIND_BASE, GCS_BIND_BASE, GCS_PORT  # noqa: F401


@dataclass
class LinkSpec:
    bind_port: int  # UDP on loopback, 0 = any free port (when no transport is given)
    dest: Address | None = None  # fixed destination; None = learnt from the peer
    learn_clients: bool = True  # also answer the last sender of valid frames (client links)
    transport: Transport | None = None  # this link's I/O (e.g. Zenoh); None: a UDP socket bound to bind_port


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


def bind_udp(port: int) -> UdpTransport:
    """A UDP link on loopback (frames are checked by the Vehicle, not here)."""
    try:
        return UdpTransport(UdpParams(port=port, validate_frames=False, recv_buffer_bytes=RECV_BUFFER_BYTES))
    except OSError as e:
        raise PortUnavailable(f"cannot bind UDP port {port} on {LOOPBACK}: {e.strerror}") from None


class VehicleSockets:
    """One transport per vehicle link (a UDP socket unless the spec brings one), fed into `Vehicle.handle`,
    answering `Outgoing`."""

    def __init__(self, vehicle: Vehicle, links: dict[str, LinkSpec], tlog: Path | None = None,
                 batch: bool = False, tlog_max_bytes: int = TLOG_MAX_BYTES) -> None:
        """`batch`: frames for the same link from one `send` call share datagrams (up to
        `BATCH_BYTES`), as PX4 fills its UDP buffer: one syscall (and one wake-up of the receiver)
        instead of one per frame. The given transports are closed with this object.
        `tlog`: what was sent, and every received frame that passed the vehicle's parser and signature
        check (junk is never logged), up to `tlog_max_bytes`; a write error or the cap stops the log with
        one STATUSTEXT and `counters()["logging_stopped"]`, never the flight."""
        self.vehicle = vehicle
        self.batch = batch
        self.specs = links
        self.links: dict[str, Transport] = {}
        self.sel: selectors.BaseSelector | None = None
        self._tlog = None
        try:
            for name, spec in links.items():
                self.links[name] = spec.transport if spec.transport is not None else bind_udp(spec.bind_port)
        except UserInputError:
            for spec in links.values():
                if spec.transport is not None:
                    spec.transport.close()
            self.close()
            raise
        self.dest = {name: spec.dest for name, spec in links.items()}
        self.peers: dict[str, tuple[Address, float] | None] = {}
        self.sel = selectors.DefaultSelector()
        for name, t in self.links.items():
            self.sel.register(t, selectors.EVENT_READ, name)
        self.datagrams = 0
        self.send_errors = 0
        self._tlog = None
        if tlog:
            from mars_link.logs.outputs import SafeWriter

            # unbuffered, by a thread of its own: on disk as it goes, and a stalled write() never holds up
            # the frames between the unit's sensors and its answer (a unit late by 1 s is lost)
            self._tlog = SafeWriter.open(tlog, "ab", max_bytes=tlog_max_bytes, background=True,
                                         on_stop=lambda reason: vehicle.notify(f"Log off: {reason.split(' (logging')[0]}"[:50]))
            vehicle.on_frame_in = lambda link, frame: self._log(bytes(frame))

    def ports(self) -> dict[str, int | str]:
        """Each link's UDP port (or, on another transport, its local address: e.g. a Zenoh node)."""
        addrs = {name: t.local_address for name, t in self.links.items()}
        return {name: a[1] if isinstance(a, tuple) else a for name, a in addrs.items()}

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
                if self.links[link].send(data, addr):
                    sent = True
                else:  # nobody listening (ICMP refused) or buffer full: best effort
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

    def drain(self, link: str, transport: Transport, until: Callable[[], bool] | None = None) -> int:
        """Every datagram waiting on `link` (senders off loopback: dropped and counted by the transport), or
        those up to the one after which `until()` holds (the rest wait in the transport)."""
        v = self.vehicle
        n = 0
        for _ in range(MAX_DATAGRAMS_PER_WAKE):
            if until is not None and until():
                break
            got = transport.recv(0.0)
            if got is None:
                break
            data, addr = got
            n += 1
            self.datagrams += 1
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

    def counters(self) -> dict:
        not_loopback = sum(t.counters.dropped.get("not_loopback", 0) for t in self.links.values())
        out = {"datagrams": self.datagrams, "not_loopback": not_loopback, "send_errors": self.send_errors}
        if self._tlog is not None and self._tlog.stopped_reason:
            out["logging_stopped"] = self._tlog.stopped_reason
        return out

    @property
    def logging_stopped(self) -> str | None:
        return self._tlog.stopped_reason if self._tlog is not None else None

    def close(self) -> None:
        if self.sel is not None:
            self.sel.close()
        for t in self.links.values():
            t.close()
        if self._tlog:
            self._tlog.close()


def vehicle_status(vehicle: Vehicle, truth: RigidBodyState | None, sim_time_s: float, **extra) -> dict:
    """A JSON-able snapshot of one vehicle (mode, counters, motor model) and, where the runner owns
    the body, its truth."""
    v = vehicle
    status = {
        "unit": v.sysid, "sim_time_s": sim_time_s, "wall_time_s": time.time(), "armed": v.armed,
        "mode": list(v.mode), "source": v.source, "phase": v.autopilot.phase.value,
        "motor_eta": [float(x) for x in v.motors.eta], "motor_thrust_n": [float(x) for x in v.motors.thrust_n],
        "drops": v.drop_counts(), "stats": v.stats, "intake_accepted": v.intake.accepted,
        "foreign_traffic": v.foreign_traffic_events(),
    }
    if truth is not None:
        status.update(
            truth_position_ned_m=[float(x) for x in truth.position_ned_m],
            truth_velocity_ned_mps=[float(x) for x in truth.velocity_ned_mps],
            truth_quaternion_wxyz=[float(x) for x in truth.quaternion_wxyz],
        )
    ulog = extra.pop("ulog", None) or (v.ulog.status() if v.ulog is not None else None)
    if ulog is not None:  # (a stopped .ulg is a stopped log too: the run's summary lists it)
        status["ulog"] = ulog
        if ulog["stopped_reason"] and not extra.get("logging_stopped"):
            status["logging_stopped"] = ulog["stopped_reason"]
    status.update(extra)
    return status


def write_json_atomic(path: Path, doc: dict) -> bool:
    """Strict JSON (NaN/inf -> null, mars_link.logs.outputs), replaced atomically; False (and the old file
    left as it was) if the disk refuses: a status snapshot is never flight-critical."""
    from mars_link.logs.outputs import dumps

    tmp = path.with_suffix(".tmp")
    try:
        tmp.write_text(dumps(doc, indent=None))
        os.replace(tmp, path)
    except OSError:
        try:
            tmp.unlink()
        except OSError:
            pass
        return False
    return True
