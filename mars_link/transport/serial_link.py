"""MAVLink over a serial line (telemetry radios, UARTs): a point-to-point byte stream framed into whole,
checksum-valid frames (mars_link.transport.framing). Tested over a pseudo-terminal pair."""

from __future__ import annotations

import os
import select
import time
from collections import deque
from dataclasses import dataclass

from mars_link.transport.base import Address, Transport
from mars_link.transport.framing import MavlinkFramer


@dataclass
class SerialParams:
    device: str = ""
    baud: int = 57600


class FdStream:
    """A raw file descriptor as a byte stream (e.g. the master side of a pty, which has no device path)."""

    def __init__(self, fd: int, name: str = "fd") -> None:
        self.fd = fd
        self.name = name

    def fileno(self) -> int:
        return self.fd

    def read_available(self, timeout_s: float) -> bytes:
        r, _, _ = select.select([self.fd], [], [], max(timeout_s, 0.0))
        if not r:
            return b""
        try:
            return os.read(self.fd, 4096)
        except OSError:  # the other side closed
            return b""

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            view = view[n:]

    def close(self) -> None:
        os.close(self.fd)


class PySerialStream:
    def __init__(self, params: SerialParams) -> None:
        import serial

        try:
            self.port = serial.Serial(params.device, params.baud, timeout=0)
        except serial.SerialException as exc:
            raise ValueError(f"serial {params.device}: {exc}") from None
        self.name = params.device

    def fileno(self) -> int:
        return self.port.fileno()

    def read_available(self, timeout_s: float) -> bytes:
        r, _, _ = select.select([self.port.fileno()], [], [], max(timeout_s, 0.0))
        if not r:
            return b""
        return self.port.read(self.port.in_waiting or 1)

    def write(self, data: bytes) -> None:
        self.port.write(data)

    def close(self) -> None:
        self.port.close()


class SerialTransport(Transport):
    kind = "serial"

    def __init__(self, params: SerialParams | None = None, stream=None) -> None:
        super().__init__()
        self.params = params or SerialParams()
        self.stream = stream if stream is not None else PySerialStream(self.params)
        self.framer = MavlinkFramer()
        self._frames: deque[bytes] = deque()
        self._reported = (0, 0, 0)

    @property
    def local_address(self) -> str:
        return self.stream.name

    def fileno(self) -> int:
        """Readable while bytes wait; frames already read come first from `recv` (drain it until None)."""
        return self.stream.fileno()

    def _send(self, data: bytes, peer: Address) -> None:
        self.stream.write(data)

    def _recv(self, timeout_s: float) -> tuple[bytes, Address] | None:
        deadline = time.monotonic() + timeout_s
        while not self._frames:
            chunk = self.stream.read_available(max(deadline - time.monotonic(), 0.0))
            if chunk:
                self._frames.extend(self.framer.feed(chunk))
                self._count_framer()
            elif time.monotonic() >= deadline:
                return None
        return self._frames.popleft(), self.stream.name

    def _count_framer(self) -> None:
        c = self.framer.counters
        g, b, u = self._reported
        if c.garbage_bytes > g:
            self.counters.drop("garbage_bytes", c.garbage_bytes - g)
        if c.bad_crc > b:
            self.counters.drop("bad_crc", c.bad_crc - b)
        if c.unknown_msgid > u:
            self.counters.drop("unknown_msgid", c.unknown_msgid - u)
        self._reported = (c.garbage_bytes, c.bad_crc, c.unknown_msgid)

    def _close(self) -> None:
        self.stream.close()
