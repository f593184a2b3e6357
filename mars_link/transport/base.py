"""The one interface every MAVLink link speaks: datagrams (one or more whole MAVLink frames) to and from
named peers, with counters. Runners do the I/O through it; cores never see a transport.

A peer address is whatever the transport uses to name an endpoint: `(host, port)` for UDP, a node name
such as "world" or "unit/3" for Zenoh, the device path for serial.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Hashable

Address = Hashable


@dataclass
class Counters:
    """What went through a link; `dropped` counts discarded input by reason (shared with the Link)."""

    sent: int = 0
    received: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    dropped: dict[str, int] = field(default_factory=dict)

    def drop(self, reason: str, n: int = 1) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + n

    def as_dict(self) -> dict:
        return {"sent": self.sent, "received": self.received, "bytes_sent": self.bytes_sent,
                "bytes_received": self.bytes_received, "dropped": dict(self.dropped)}


class Transport:
    """Base class: subclasses implement `_send`, `_recv` and `_close`; this one keeps the counters."""

    kind = "abstract"

    def __init__(self, validate_frames: bool = False) -> None:
        self.counters = Counters()
        self.closed = False
        self.validate_frames = validate_frames  # drop datagrams' bad frames here (framing.check_datagram)

    # -- interface ---------------------------------------------------------------------------
    def send(self, data: bytes, peer: Address) -> bool:
        """Send one datagram to `peer`; False if it could not be handed to the link (counted: e.g. an
        unreachable peer). Never blocks for long; a full link drops (counted)."""
        if self.closed:
            raise ValueError(f"{self.kind} transport is closed")
        if self._send(bytes(data), peer) is False:
            return False
        c = self.counters
        c.sent += 1
        c.bytes_sent += len(data)
        return True

    def prepare(self, peer: Address) -> None:
        """Get ready to send to `peer` (a Zenoh publisher is declared and matched), so that the first datagram
        of a paced run does not pay for it; nothing to do on links whose sends need no set-up."""

    def recv(self, timeout_s: float) -> tuple[bytes, Address] | None:
        """The next datagram and its sender, or None when nothing arrives within `timeout_s`
        (<= 0: only what is already waiting)."""
        if timeout_s <= 0:  # a poll (draining after a select): one try, no clock
            got = None if self.closed else self._recv(0.0)
            return None if got is None else self._received(got)
        deadline = time.monotonic() + timeout_s
        wait = timeout_s
        while not self.closed:
            got = self._recv(wait)
            if got is not None:
                got = self._received(got)
                if got is not None:
                    return got
            wait = deadline - time.monotonic()
            if wait <= 0:
                return None
        return None

    def _received(self, got: tuple[bytes, Address]) -> tuple[bytes, Address] | None:
        c = self.counters
        c.received += 1
        c.bytes_received += len(got[0])
        return self._validated(*got) if self.validate_frames else got

    def _validated(self, data: bytes, peer: Address) -> tuple[bytes, Address] | None:
        from mars_link.transport.framing import check_datagram

        good, problems = check_datagram(data)
        for reason, n in problems.items():
            self.counters.drop(reason, n)
        return (good, peer) if good else None

    @property
    def local_address(self) -> Address:
        raise NotImplementedError

    def fileno(self) -> int:
        """A descriptor that is readable while input waits (select/selectors), level-triggered."""
        raise NotImplementedError

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._close()

    def __enter__(self) -> "Transport":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- to implement --------------------------------------------------------------------------
    def _send(self, data: bytes, peer: Address) -> bool | None:
        """False: not handed to the link (count why); None or True: handed to it."""
        raise NotImplementedError

    def _recv(self, timeout_s: float) -> tuple[bytes, Address] | None:
        """May return None before the timeout (e.g. input dropped); `recv` then waits on."""
        raise NotImplementedError

    def _close(self) -> None:
        pass


class TappedTransport(Transport):
    """Any transport whose datagrams are also shown to callbacks `(data, wall time s)`: every one received
    and every one sent (e.g. transport.realtime.CommandAgeTap at a unit's links). Counters are the inner's."""

    def __init__(self, inner: Transport, on_receive=None, on_send=None) -> None:
        super().__init__()
        self.inner = inner
        self.kind = inner.kind
        self.counters = inner.counters
        self.on_receive = on_receive
        self.on_send = on_send

    @property
    def local_address(self) -> Address:
        return self.inner.local_address

    def fileno(self) -> int:
        return self.inner.fileno()

    def prepare(self, peer: Address) -> None:
        self.inner.prepare(peer)

    def send(self, data: bytes, peer: Address) -> bool:
        ok = self.inner.send(data, peer)
        if ok and self.on_send is not None:
            self.on_send(data, time.time())
        return ok

    def recv(self, timeout_s: float) -> tuple[bytes, Address] | None:
        got = self.inner.recv(timeout_s)
        if got is not None and self.on_receive is not None:
            self.on_receive(got[0], time.time())
        return got

    def _close(self) -> None:
        self.inner.close()
