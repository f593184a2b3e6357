"""Datagram links carrying MAVLink frames: one small interface (`Transport`: send bytes to a peer,
receive (bytes, peer) with a timeout, close; a context manager; counters) over

* `udp`    - plain MAVLink over UDP (ground stations, PX4-style SITL),
* `zenoh`  - MAVLink frames on Zenoh key expressions (key space in `zenoh_link`),
* `serial` - MAVLink over a byte stream, framed and checksum-checked (`framing`),

and `profiles.ProfiledTransport`, which makes any of them behave like a LAN, Wi-Fi or a 57600-baud radio.
"""

from __future__ import annotations

from dataclasses import dataclass

from mars_link.transport.base import Address, Counters, Transport

TRANSPORTS = ("udp", "zenoh")  # what the SITL processes can run on (serial is point to point)
UNIT_INTERFACES = ("mavlink", "px4-zenoh")  # (as mars_link.config.scenario.UNIT_INTERFACES: this floor is below it)


@dataclass
class LinkSpec:
    """How SITL processes build their links (passed to every child on its command line)."""

    kind: str = "udp"                      # udp | zenoh
    fleet: str = "default"
    zenoh_mode: str = "client"             # peer | client | router (start_sitl sets it per role)
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    profile: str | None = None             # a profiles.PRESETS name (+ overrides): coordinator <-> unit links
    seed: int = 0                          # link-profile randomness (mixed with each link's name)
    unit_interface: str | None = None      # how the coordinator commands the units: "mavlink" | "px4-zenoh"
    # (PX4's own per-rotor interface over rmw_zenoh, zenoh only); None: the scenario's [units] interface
    insecure: bool = False                 # zenoh: plain TCP, no access control (`--insecure`)
    tls_dir: str | None = None             # zenoh: the run's CA, per-role certificates and ACL (transport.tls)
    tls_ca: str | None = None              # zenoh: the user's CA, certificate and key (several hosts; mTLS, no ACL)
    tls_cert: str | None = None
    tls_key: str | None = None

    @property
    def closed_bus(self) -> bool:
        """Whether the Zenoh sessions use mutual TLS (a run's CA or the user's certificates)."""
        return self.kind == "zenoh" and bool(self.tls_dir or self.tls_ca)

    def bus(self) -> str:
        """What summary.json says of the bus: `tls+acl`, `tls` (the user's certificates), `insecure`, `udp`."""
        if self.kind != "zenoh":
            return self.kind
        return "tls+acl" if self.tls_dir else "tls" if self.tls_ca else "insecure"

    def to_args(self) -> list[str]:
        args = ["--transport", self.kind]
        if self.kind == "zenoh":
            args += ["--fleet", self.fleet, "--zenoh-mode", self.zenoh_mode]
            for e in self.connect:
                args += ["--zenoh-connect", e]
            for e in self.listen:
                args += ["--zenoh-listen", e]
            if self.tls_dir:
                args += ["--tls-dir", self.tls_dir]
            for option, value in (("--tls-ca", self.tls_ca), ("--tls-cert", self.tls_cert), ("--tls-key", self.tls_key)):
                if value:
                    args += [option, value]
        if self.profile:
            args += ["--link-profile", self.profile]
        if self.unit_interface:
            args += ["--unit-interface", self.unit_interface]
        return args

    def check_unit_interface(self, interface: str) -> None:
        """PX4's interface rides on Zenoh: refused (UserInputError) on another transport."""
        if interface == "px4-zenoh" and self.kind != "zenoh":
            from mars_link.core.errors import UserInputError

            raise UserInputError(f"--unit-interface px4-zenoh needs --transport zenoh (got --transport {self.kind})")


def spec_from_args(args) -> LinkSpec:
    """The links of a SITL process from its command line (options: mars_link.processes.cli_options.add_link)."""
    return LinkSpec(args.transport, args.fleet, args.zenoh_mode, tuple(args.zenoh_connect),
                    tuple(args.zenoh_listen), args.link_profile,
                    unit_interface=getattr(args, "unit_interface", None), tls_dir=args.tls_dir, tls_ca=args.tls_ca,
                    tls_cert=args.tls_cert, tls_key=args.tls_key)


__all__ = ["spec_from_args", "Address", "Counters", "LinkSpec", "Transport", "TRANSPORTS"]
