"""`python -m mars_link.transport.sitl_child ROLE ... --transport zenoh [...]`: one lockstep SITL process
(sitl.lockstep) with its MAVLink links on Zenoh instead of UDP.

The lockstep code is not changed: its hooks (sitl.lockstep.SOCKET_HOOK, firmware_models.vehicle_io.
SOCKETS_HOOK) swap the world/coordinator `Link` socket and a unit's HIL and coordinator sockets for
TransportSockets right after they are made. A unit's client links (GCS 14550,
API 14540+i) stay on UDP, as ground stations expect. Units also log the command age at the motor
(mars_link.transport.realtime).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mars_link.transport import LinkSpec
from mars_link.transport.socket_shim import AddressMap, TransportSocket

FIRST_SEND_WAIT_S = 20.0  # the lockstep sends some hellos once: wait for the other process to be up


class TappedSocket:
    """A UDP socket whose datagrams are also shown to a tap (command age on the UDP path)."""

    def __init__(self, sock, on_receive, on_send=None) -> None:
        self._sock = sock
        self._on_receive = on_receive
        self._on_send = on_send

    def recvfrom(self, bufsize: int):
        data, addr = self._sock.recvfrom(bufsize)
        self._on_receive(data, time.time())
        return data, addr

    def sendto(self, data, addr):
        n = self._sock.sendto(data, addr)
        if self._on_send is not None:
            self._on_send(data, time.time())
        return n

    def __getattr__(self, name):
        return getattr(self._sock, name)


_SESSION: list = []  # this process's one Zenoh session, shared by its links; closed in main()


def _zenoh(spec: LinkSpec, node: str, only_from: str | None = None, seed: int = 0):
    from mars_link.transport.zenoh_link import ZenohParams, ZenohTransport, make_config

    params = ZenohParams(node=node, fleet=spec.fleet, mode=spec.zenoh_mode, connect=spec.connect,
                         listen=spec.listen, only_from=only_from, first_send_wait_s=FIRST_SEND_WAIT_S)
    if not _SESSION:
        import zenoh

        _SESSION.append(zenoh.open(make_config(params)))
    t = ZenohTransport(params, session=_SESSION[0])
    if spec.profile and (node == "coordinator" or only_from == "coordinator"):  # the radio/network link only
        # (the HIL link world <-> unit stands for wires inside the simulated vehicle: never profiled)
        import zlib

        from mars_link.transport.profiles import ProfiledTransport, profile_from_name

        t = ProfiledTransport(t, profile_from_name(spec.profile), seed=spec.seed + zlib.crc32(f"{node}<{only_from}".encode()))
    return t


_TAPS: list = []  # this process's command-age taps, written in main()


def install(spec: LinkSpec, addresses: AddressMap, control_period_s: float = 0.01) -> None:
    """Set the lockstep's socket hooks: `Link` sockets (world, coordinator) on Zenoh; a unit's HIL and
    coordinator sockets on Zenoh (UDP: kept), both tapped for the command age."""
    import sitl.lockstep as lockstep
    from firmware_models import vehicle_io

    if spec.kind == "zenoh":
        def link_socket(sock, sysid):
            sock.close()
            node = "world" if sysid == lockstep.WORLD_SYSID else "coordinator" if sysid == lockstep.COORDINATOR_SYSID else f"unit/{sysid}"
            return TransportSocket(_zenoh(spec, node), addresses)

        lockstep.SOCKET_HOOK = link_socket

    def unit_sockets(io) -> None:
        from firmware_models.vehicle import LINK_COORDINATOR, LINK_HIL
        from mars_link.transport.realtime import CommandAgeTap

        unit = io.vehicle.config.unit_id
        tap = CommandAgeTap(unit, control_period_s)
        _TAPS.append(tap)
        for name, peer, feed, sent in ((LINK_HIL, "world", tap.on_hil, tap.on_motor_output),
                                       (LINK_COORDINATOR, "coordinator", tap.on_coordinator, None)):
            if name not in io.socks:
                continue
            if spec.kind == "zenoh":
                io.socks[name].close()
                io.socks[name] = TransportSocket(_zenoh(spec, f"unit/{unit}", only_from=peer), addresses, feed, sent)
                io.socks[name].setblocking(False)  # VehicleSockets drains until BlockingIOError
            else:
                io.socks[name] = TappedSocket(io.socks[name], feed, sent)

    vehicle_io.SOCKETS_HOOK = unit_sockets


def main(argv: list[str] | None = None) -> int:
    from mars_link.transport import add_link_args, spec_from_args

    ap = argparse.ArgumentParser(prog="python -m mars_link.transport.sitl_child", add_help=False)
    add_link_args(ap)
    ap.add_argument("--world-port", type=int, required=True)
    ap.add_argument("--coordinator-port", type=int, default=0)
    ap.add_argument("--out", default=None)
    ap.add_argument("--control-period-s", type=float, default=0.01)
    args, rest = ap.parse_known_args(argv)
    spec = spec_from_args(args)
    lockstep_argv = rest + ["--world-port", str(args.world_port), "--coordinator-port", str(args.coordinator_port)]
    if args.out:
        lockstep_argv += ["--out", args.out]
    if args.realtime:
        lockstep_argv += ["--speed", "1"]
    if spec.kind != "udp" or args.realtime:  # Zenoh: swap the links; UDP in real time: tap them (command age)
        install(spec, AddressMap(args.world_port, args.coordinator_port), args.control_period_s)
    import sitl.lockstep as lockstep

    try:
        return lockstep.main(lockstep_argv)
    finally:  # a process with an open session and callback subscribers would hang at exit
        for tap in _TAPS:
            if args.out and tap.commands:
                tap.write(Path(args.out))
        for s in _SESSION:
            s.close()
        _SESSION.clear()


if __name__ == "__main__":
    sys.exit(main())
