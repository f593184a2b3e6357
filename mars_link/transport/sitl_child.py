"""`python -m mars_link.transport.sitl_child ROLE ... --transport zenoh [...]`: one lockstep SITL process
(sitl.lockstep) with its MAVLink links on Zenoh instead of UDP.

The lockstep code is not changed: its world/coordinator `Link` socket and a unit's HIL and coordinator
sockets are swapped for TransportSockets right after they are made. A unit's client links (GCS 14550,
API 14540+i) stay on UDP, as ground stations expect. Units also log the command age at the motor
(mars_link.transport.realtime).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mars_link.transport import LinkSpec
from mars_link.transport.socket_shim import AddressMap, TransportSocket

FIRST_SEND_WAIT_S = 20.0  # the lockstep sends some hellos once: wait for the other process to be up


def _zenoh(spec: LinkSpec, node: str, only_from: str | None = None, seed: int = 0):
    from mars_link.transport.zenoh_link import ZenohParams, ZenohTransport

    t = ZenohTransport(ZenohParams(node=node, fleet=spec.fleet, mode=spec.zenoh_mode, connect=spec.connect,
                                   listen=spec.listen, only_from=only_from, first_send_wait_s=FIRST_SEND_WAIT_S))
    if spec.profile:
        import zlib

        from mars_link.transport.profiles import ProfiledTransport, profile_from_name

        t = ProfiledTransport(t, profile_from_name(spec.profile), seed=spec.seed + zlib.crc32(node.encode()))
    return t


def install(spec: LinkSpec, addresses: AddressMap, out: Path | None, control_period_s: float = 0.01) -> None:
    """Patch sitl.lockstep.Link and firmware_models.vehicle_io.VehicleSockets to use `spec` links."""
    import sitl.lockstep as lockstep

    link_init = lockstep.Link.__init__

    def patched_link_init(self, port, sysid, *a, **kw):
        link_init(self, port, sysid, *a, **kw)
        node = "world" if sysid == lockstep.WORLD_SYSID else "coordinator" if sysid == lockstep.COORDINATOR_SYSID else f"unit/{sysid}"
        self.sock.close()
        self.sock = TransportSocket(_zenoh(spec, node), addresses)

    lockstep.Link.__init__ = patched_link_init

    from firmware_models import vehicle_io
    from firmware_models.vehicle import LINK_COORDINATOR, LINK_HIL

    sockets_init = vehicle_io.VehicleSockets.__init__
    sockets_close = vehicle_io.VehicleSockets.close

    def patched_sockets_init(self, vehicle, links, tlog=None):
        import selectors

        from mars_link.transport.realtime import CommandAgeTap

        sockets_init(self, vehicle, links, tlog)
        unit = vehicle.config.unit_id if hasattr(vehicle, "config") else vehicle.sysid
        self.age_tap = CommandAgeTap(unit, control_period_s)
        taps = {LINK_HIL: self.age_tap.on_hil, LINK_COORDINATOR: self.age_tap.on_coordinator}
        peers = {LINK_HIL: "world", LINK_COORDINATOR: "coordinator"}
        for name in (LINK_HIL, LINK_COORDINATOR):
            if name not in self.socks:
                continue
            old = self.socks[name]
            self.sel.unregister(old)
            old.close()
            self.socks[name] = TransportSocket(_zenoh(spec, f"unit/{unit}", only_from=peers[name]), addresses, taps[name])
            self.socks[name].setblocking(False)  # VehicleSockets drains until BlockingIOError
            self.sel.register(self.socks[name], selectors.EVENT_READ, name)

    def patched_sockets_close(self):
        try:
            if out is not None and getattr(self, "age_tap", None) is not None and self.age_tap.commands:
                self.age_tap.write(out)
        finally:
            sockets_close(self)

    vehicle_io.VehicleSockets.__init__ = patched_sockets_init
    vehicle_io.VehicleSockets.close = patched_sockets_close


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
    if spec.kind != "udp":
        install(spec, AddressMap(args.world_port, args.coordinator_port), Path(args.out) if args.out else None,
                args.control_period_s)
    import sitl.lockstep as lockstep

    return lockstep.main(lockstep_argv)


if __name__ == "__main__":
    sys.exit(main())
