"""Datagram links carrying MAVLink frames: one small interface (`Transport`: send bytes to a peer,
receive (bytes, peer) with a timeout, close; a context manager; counters) over

* `udp`    - plain MAVLink over UDP (ground stations, PX4-style SITL),
* `zenoh`  - MAVLink frames on Zenoh key expressions (key space in `zenoh_link`),
* `serial` - MAVLink over a byte stream, framed and checksum-checked (`framing`),

and `profiles.ProfiledTransport`, which makes any of them behave like a LAN, Wi-Fi or a 57600-baud radio.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

from mars_link.transport.base import Address, Counters, Transport

TRANSPORTS = ("udp", "zenoh")  # what the SITL processes can run on (serial is point to point)


@dataclass
class LinkSpec:
    """How SITL processes build their links (passed to every child on its command line)."""

    kind: str = "udp"                      # udp | zenoh
    fleet: str = "default"
    zenoh_mode: str = "client"             # SITL children are clients of the launcher's router by default
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    profile: str | None = None             # a profiles.PRESETS name (+ overrides) on every link
    seed: int = 0

    def to_args(self) -> list[str]:
        args = ["--transport", self.kind]
        if self.kind == "zenoh":
            args += ["--fleet", self.fleet, "--zenoh-mode", self.zenoh_mode]
            for e in self.connect:
                args += ["--zenoh-connect", e]
            for e in self.listen:
                args += ["--zenoh-listen", e]
        if self.profile:
            args += ["--link-profile", self.profile]
        return args


def node_name(sysid: int, world_sysid: int = 200, coordinator_sysid: int = 201) -> str:
    if sysid == world_sysid:
        return "world"
    if sysid == coordinator_sysid:
        return "coordinator"
    return f"unit/{sysid}"


def open_transport(spec: LinkSpec, port: int, node: str) -> Transport:
    """The transport for one SITL endpoint (`port` is used by UDP only, `node` by Zenoh)."""
    if spec.kind == "udp":
        from mars_link.transport.udp import UdpParams, UdpTransport

        t: Transport = UdpTransport(UdpParams(port=port))
    elif spec.kind == "zenoh":
        from mars_link.transport.zenoh_link import ZenohParams, ZenohTransport

        t = ZenohTransport(ZenohParams(node=node, fleet=spec.fleet, mode=spec.zenoh_mode,
                                       connect=spec.connect, listen=spec.listen))
    else:
        raise ValueError(f"transport {spec.kind!r}: expected one of {', '.join(TRANSPORTS)}")
    if spec.profile:
        from mars_link.transport.profiles import ProfiledTransport, profile_from_name

        t = ProfiledTransport(t, profile_from_name(spec.profile), seed=spec.seed + zlib.crc32(f"{node}:{port}".encode()) % 100000)
    return t


def add_link_args(ap) -> None:
    """The command-line options every SITL process takes to build its links (see LinkSpec.to_args)."""
    ap.add_argument("--transport", choices=TRANSPORTS, default="udp")
    ap.add_argument("--fleet", default="default")
    ap.add_argument("--zenoh-mode", choices=("peer", "client", "router"), default="client")
    ap.add_argument("--zenoh-connect", action="append", default=[])
    ap.add_argument("--zenoh-listen", action="append", default=[])
    ap.add_argument("--link-profile", default=None)
    ap.add_argument("--realtime", action="store_true", help="pace the world to the wall clock")


def spec_from_args(args) -> LinkSpec:
    return LinkSpec(args.transport, args.fleet, args.zenoh_mode, tuple(args.zenoh_connect),
                    tuple(args.zenoh_listen), args.link_profile)


__all__ = ["add_link_args", "spec_from_args", "Address", "Counters", "LinkSpec", "Transport", "TRANSPORTS", "node_name", "open_transport"]
