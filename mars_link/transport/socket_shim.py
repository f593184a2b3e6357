"""A Transport behind the socket calls the SITL processes already make (sendto / recvfrom / fileno), so
the lockstep world, coordinator and unit run unchanged on Zenoh.

Addresses stay UDP-shaped for the code above: a node is ("127.0.0.1", id) with id = the world's or the
coordinator's port from the command line, and the unit id (1..255, never a port the launcher hands out)
for unit/<id>. Those ids only name Zenoh nodes; nothing is bound to them.
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass

from mars_link.transport.base import Transport

LOOPBACK = "127.0.0.1"


@dataclass
class AddressMap:
    world_port: int
    coordinator_port: int

    def node(self, addr) -> str | None:
        port = addr[1]
        if port == self.world_port:
            return "world"
        if port == self.coordinator_port:
            return "coordinator"
        if isinstance(port, int) and 1 <= port <= 255:
            return f"unit/{port}"
        return None

    def addr(self, node: str) -> tuple[str, int] | None:
        if node == "world":
            return (LOOPBACK, self.world_port)
        if node == "coordinator":
            return (LOOPBACK, self.coordinator_port)
        if node.startswith("unit/"):
            return (LOOPBACK, int(node[5:]))
        return None


class TransportSocket:
    def __init__(self, transport: Transport, addresses: AddressMap, on_receive=None, on_send=None) -> None:
        self.transport = transport
        self.addresses = addresses
        self.on_receive = on_receive  # called with every datagram received (e.g. a CommandAgeTap)
        self.on_send = on_send  # ... and sent
        self._timeout: float | None = None

    # socket API used by sitl.lockstep.Link and firmware_models.vehicle_io.VehicleSockets
    def fileno(self) -> int:
        return self.transport.fileno()

    def setblocking(self, flag: bool) -> None:
        self._timeout = None if flag else 0.0

    def settimeout(self, value: float | None) -> None:
        self._timeout = value

    def setsockopt(self, *args) -> None:
        pass

    def bind(self, addr) -> None:
        pass

    def getsockname(self) -> tuple[str, int]:
        return self.addresses.addr(self.transport.local_address) or (LOOPBACK, 0)

    def sendto(self, data: bytes, addr) -> int:
        node = self.addresses.node(addr)
        if node is None:
            self.transport.counters.drop("unknown_destination")
            return len(data)
        self.transport.send(data, node)
        if self.on_send is not None:
            self.on_send(data, time.time())
        return len(data)

    def recvfrom(self, bufsize: int = 65536):
        timeout = self._timeout
        got = self.transport.recv(1e9 if timeout is None else timeout)
        if got is None:
            if timeout == 0.0:
                raise BlockingIOError("no datagram")
            raise socket.timeout("timed out")
        data, sender = got
        addr = self.addresses.addr(str(sender))
        if addr is None:
            self.transport.counters.drop("unknown_sender_node")
            raise BlockingIOError("dropped") if timeout == 0.0 else socket.timeout("dropped")
        if self.on_receive is not None:
            self.on_receive(data, time.time())
        return data[:bufsize], addr

    def close(self) -> None:
        self.transport.close()
