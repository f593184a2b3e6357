"""How the lockstep processes (mars_link.processes.lockstep) move MAVLink: every link is a `mars_link.transport.Transport`
chosen once at process start (`--transport udp|zenoh`); nothing above it knows which.

`Ports` opens this process's links and names its peers: on UDP, sockets on loopback (the world's and the
coordinator's ports, or the sockets the launcher bound for them and handed down) and `(host, port)`
addresses; on Zenoh, nodes "world", "coordinator" and "unit/<id>" on one session per process.
`Link` is the world's and the coordinator's MAVLink endpoint on such a transport.
"""

from __future__ import annotations

import os
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from pymavlink.dialects.v20 import common as mavlink

from mars_link.mavlink import codec as mavlink_codec
from mars_link.core.errors import PortUnavailable, UserInputError
from mars_link.transport import LinkSpec
from mars_link.transport.base import Address, Transport
from mars_link.mavlink.wire import new_mav

LOOPBACK = "127.0.0.1"
RECV_BUFFER_BYTES = 4 * 1024 * 1024
FIRST_SEND_WAIT_S = 20.0  # Zenoh: the lockstep sends some hellos once; wait for the other process to be up


@dataclass
class Ports:
    """Where this process's peers are and how its links are opened. `command_age_period_s` (a unit, real
    time): its HIL and coordinator links are tapped for the command age at the motor
    (mars_link.transport.realtime), written by `close`."""

    world: int = 0
    coordinator: int = 0
    world_fd: int | None = None  # sockets already bound by the launcher (inherited descriptors)
    coordinator_fd: int | None = None
    link: LinkSpec = field(default_factory=LinkSpec)
    command_age_period_s: float | None = None
    taps: dict = field(default_factory=dict)  # unit id -> CommandAgeTap
    _session: object | None = field(default=None, repr=False)  # this process's one Zenoh session

    def address(self, node: str) -> Address:
        """The address of peer `node` ("world" or "coordinator") on this transport."""
        if self.link.kind == "udp":
            return (LOOPBACK, self.world if node == "world" else self.coordinator)
        return node

    def open(self, node: str, peer: str | None = None) -> Transport:
        """This process's link as `node` ("world", "coordinator" or "unit/<id>"); `peer`: a unit link that
        talks to that node only (its HIL link: "world", its coordinator link: "coordinator")."""
        fd, port = {"world": (self.world_fd, self.world),
                    "coordinator": (self.coordinator_fd, self.coordinator)}.get(node, (None, 0))
        if fd is not None:  # adopted (or closed) once
            setattr(self, f"{node}_fd", None)
        if self.link.kind == "udp":
            from mars_link.transport.udp import UdpParams, UdpTransport

            try:
                t = UdpTransport(UdpParams(port=port, fd=fd, validate_frames=False,  # Link/Vehicle parse and count
                                           recv_buffer_bytes=RECV_BUFFER_BYTES))
            except OSError as e:
                raise PortUnavailable(f"cannot bind UDP port {port} on {LOOPBACK}: {e.strerror}") from None
        else:
            if fd is not None:  # the launcher's port reservation: unused on Zenoh
                os.close(fd)
            t = self._zenoh(node, peer)
        return self._tapped(t, node, peer)

    def _zenoh(self, node: str, peer: str | None) -> Transport:
        from mars_link.transport.tls import files_for
        from mars_link.transport.zenoh_link import ZenohParams, ZenohTransport, make_config, open_session

        spec = self.link
        params = ZenohParams(node=node, fleet=spec.fleet, mode=spec.zenoh_mode, connect=spec.connect,
                             listen=spec.listen, only_from=peer, first_send_wait_s=FIRST_SEND_WAIT_S,
                             tls=files_for(spec.tls_dir, spec.tls_ca, spec.tls_cert, spec.tls_key, node),
                             validate_frames=False)  # as on UDP: Link/Vehicle parse and count (no second parse)
        if self._session is None:
            import zenoh

            try:
                self._session = open_session(make_config(params))
            except (ValueError, zenoh.ZError) as e:
                raise UserInputError(f"zenoh: {e}") from None
        t = ZenohTransport(params, session=self._session)
        if spec.profile and (node == "coordinator" or peer == "coordinator"):  # the radio/network link only
            # (the HIL link world <-> unit stands for wires inside the simulated vehicle: never profiled)
            from mars_link.transport.profiles import ProfiledTransport, profile_from_name

            t = ProfiledTransport(t, profile_from_name(spec.profile), seed=spec.seed + zlib.crc32(f"{node}<{peer}".encode()))
        return t

    def zenoh_session(self):
        """This process's one Zenoh session (opened with its first link): what PX4's interface rides on
        (mars_link.processes.px4_link)."""
        if self.link.kind != "zenoh" or self._session is None:
            raise UserInputError("--unit-interface px4-zenoh needs --transport zenoh")
        return self._session

    def _tapped(self, t: Transport, node: str, peer: str | None) -> Transport:
        if self.command_age_period_s is None or not node.startswith("unit/") or peer not in ("world", "coordinator"):
            return t
        from mars_link.transport.realtime import CommandAgeTap

        unit = int(node[5:])
        tap = self.taps.setdefault(unit, CommandAgeTap(unit, self.command_age_period_s))
        return tap.hil_link(t) if peer == "world" else tap.coordinator_link(t)

    def close(self, out: Path | None = None) -> None:
        """Write the command-age logs to `out`; close the Zenoh session (a process that exits with one
        open and callback subscribers hangs)."""
        for tap in self.taps.values():
            if out is not None and tap.commands:
                tap.write(out)
        if self._session is not None:
            self._session.close()
            self._session = None


class Link:
    """A transport with a MAVLink parser, a peer table keyed by system id, and counters.

    With a signing `key`, every frame sent is signed and every frame received must carry a genuine
    signature (checked HMAC-first, before decoding: mars_link.mavlink.signing); the rest is dropped and
    counted as signing.<reason>.
    """

    def __init__(self, transport: Transport, sysid: int, tlog: Path | None = None, key: bytes | None = None) -> None:
        self.transport = transport
        self.mav = new_mav(sysid)  # decoder, never given a key (pymavlink's own check can be poisoned)
        self.enc = self.mav
        self.verifier = None
        if key is not None:
            from mars_link.mavlink.signing import SignatureVerifier, enable_outgoing_signing

            self.enc = new_mav(sysid)
            enable_outgoing_signing(self.enc, key, 1, time.time())
            self.verifier = SignatureVerifier(key)
        self.peers: dict[int, Address] = {}
        self.dropped: dict[str, int] = transport.counters.dropped  # one count per reason: link and transport
        from mars_link.logs.outputs import SafeWriter

        self._tlog = SafeWriter.open(tlog, "ab") if tlog else None  # (a full disk stops the log, not the link)

    def fileno(self) -> int:
        """Readable while input waits (select on the link next to other sockets)."""
        return self.transport.fileno()

    def drop(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1

    def send(self, msg, addr: Address) -> None:
        self.send_many([msg], addr)

    def send_many(self, msgs: list, addr: Address) -> None:
        """Several frames in one datagram (one syscall; the receiver splits them)."""
        self.send_bytes(self.pack(msgs), addr)

    def pack(self, msgs: list) -> bytes:
        """The datagram of `msgs` (signed with a key), to send later with `send_bytes`."""
        if self.verifier is not None:
            from mars_link.mavlink.signing import advance_outgoing_clock

            advance_outgoing_clock(self.enc, time.time())
        return b"".join(mavlink_codec.encode(m, self.enc) for m in msgs)

    def send_bytes(self, data: bytes, addr: Address) -> None:
        self.transport.send(data, addr)  # a peer gone (send_failed, counted): its silence is handled by the timeouts
        self._log(data)

    def prepare_peers(self, sysids) -> None:
        """Ready the path to the peers `sysids` before a paced run's first step: the transport's set-up (a
        Zenoh publisher), then one HEARTBEAT through it (the route and the receiver's first datagram, slow
        the first time, are paid before the clock starts)."""
        for sysid in sysids:
            addr = self.peers[sysid]
            self.transport.prepare(addr)
            self.heartbeat(addr)

    def heartbeat(self, addr: Address) -> None:
        self.send(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3), addr)

    def receive(self, timeout_s: float) -> list:
        """Frames that arrive within `timeout_s` (at least one datagram, or none on timeout)."""
        got = self.transport.recv(timeout_s)
        if got is None:
            return []
        data, addr = got
        self._log(data)
        check = None
        if self.verifier is not None:
            from mars_link.mavlink.signing import ACCEPTED

            verifier, now = self.verifier, time.time()

            def genuine(raw) -> bool:
                result = verifier.verify(raw, now)
                if result != ACCEPTED:
                    self.drop(f"signing.{result}")
                return result == ACCEPTED

            check = genuine

        out = []
        for m, _ in mavlink_codec.split_frames(data, self.mav, self.drop, check):  # junk, bad CRC, forged: counted
            src = m.get_srcSystem()
            known = self.peers.get(src)
            if m.get_type() == "HEARTBEAT" and known is None:
                self.peers[src] = addr  # first come: a later claim from elsewhere is a spoof
            elif known != addr:
                self.drop("unknown_sender")
                continue
            out.append(m)
        return out

    def _log(self, data: bytes) -> None:
        if self._tlog:
            from mars_link.mavlink.tlog import tlog_records

            self._tlog.write(tlog_records(data))

    def close(self) -> None:
        if self._tlog:
            self._tlog.close()
        self.transport.close()
