"""Plain MAVLink over UDP (what ground stations and PX4 SITL speak): one socket, datagrams from
anywhere but the allowed hosts are counted and dropped."""

from __future__ import annotations

import socket
from dataclasses import dataclass
from typing import cast

from mars_link.transport.base import Address, Transport

LOOPBACK = "127.0.0.1"


@dataclass
class UdpParams:
    bind_host: str = LOOPBACK
    port: int = 0  # 0: an ephemeral port
    allowed_hosts: tuple[str, ...] | None = (LOOPBACK,)  # None: accept any sender host
    validate_frames: bool = True  # drop bad MAVLink frames here (counted), pass whole valid ones
    fd: int | None = None  # adopt this already bound socket (handed down by a launcher) instead of binding
    recv_buffer_bytes: int | None = None  # SO_RCVBUF (best effort)


class UdpTransport(Transport):
    kind = "udp"

    def __init__(self, params: UdpParams | None = None) -> None:
        """Raises OSError if the port cannot be bound."""
        self.params = p = params or UdpParams()
        super().__init__(p.validate_frames)
        if p.fd is not None:
            self.sock = socket.socket(fileno=p.fd)
        else:
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                self.sock.bind((p.bind_host, p.port))
            except OSError:
                self.sock.close()
                raise
        if p.recv_buffer_bytes:
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, p.recv_buffer_bytes)
            except OSError:
                pass
        self._timeout: float | None = None  # the socket's, set only when it changes (a syscall each time)
        self._allowed = p.allowed_hosts

    @property
    def local_address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def fileno(self) -> int:
        return self.sock.fileno()

    def _send(self, data: bytes, peer: Address) -> bool:
        try:
            self.sock.sendto(data, cast(tuple[str, int], peer))  # (a UDP link's peers are (host, port))
        except OSError:  # e.g. a full buffer or an unreachable peer: a datagram link loses it
            self.counters.drop("send_failed")
            return False
        return True

    def _recv(self, timeout_s: float) -> tuple[bytes, Address] | None:
        timeout = max(timeout_s, 1e-4) if timeout_s > 0 else 0.0  # 0: non-blocking
        if timeout != self._timeout:
            self.sock.settimeout(timeout)
            self._timeout = timeout
        try:
            data, addr = self.sock.recvfrom(65536)
        except (TimeoutError, socket.timeout, BlockingIOError, InterruptedError):
            return None
        except OSError:  # e.g. ICMP port unreachable reported on a later call
            return None
        allowed = self._allowed
        if allowed is not None and addr[0] not in allowed:
            self.counters.drop("not_loopback" if allowed == (LOOPBACK,) else "host_not_allowed")
            return None
        return data, addr

    def _close(self) -> None:
        self.sock.close()
