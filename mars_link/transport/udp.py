"""Plain MAVLink over UDP (what ground stations and PX4 SITL speak): one socket, datagrams from
anywhere but the allowed hosts are counted and dropped."""

from __future__ import annotations

import socket
from dataclasses import dataclass

from mars_link.transport.base import Address, Transport

LOOPBACK = "127.0.0.1"


@dataclass
class UdpParams:
    bind_host: str = LOOPBACK
    port: int = 0  # 0: an ephemeral port
    allowed_hosts: tuple[str, ...] | None = (LOOPBACK,)  # None: accept any sender host
    validate_frames: bool = True  # drop bad MAVLink frames here (counted), pass whole valid ones


class UdpTransport(Transport):
    kind = "udp"

    def __init__(self, params: UdpParams | None = None) -> None:
        self.params = params or UdpParams()
        super().__init__(self.params.validate_frames)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((self.params.bind_host, self.params.port))

    @property
    def local_address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]


    def _send(self, data: bytes, peer: Address) -> None:
        try:
            self.sock.sendto(data, peer)
        except OSError:  # e.g. a full buffer or an unreachable peer: a datagram link loses it
            self.counters.drop("send_failed")

    def _recv(self, timeout_s: float) -> tuple[bytes, Address] | None:
        self.sock.settimeout(max(timeout_s, 1e-4))
        try:
            data, addr = self.sock.recvfrom(65536)
        except (TimeoutError, socket.timeout, BlockingIOError):
            return None
        except OSError:  # e.g. ICMP port unreachable reported on a later call
            return None
        allowed = self.params.allowed_hosts
        if allowed is not None and addr[0] not in allowed:
            self.counters.drop("not_loopback" if allowed == (LOOPBACK,) else "host_not_allowed")
            return None
        return data, addr

    def _close(self) -> None:
        self.sock.close()
