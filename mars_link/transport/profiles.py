"""Hardware-like links: per-link latency, jitter, loss and bandwidth, applied around any transport.

`LinkModel` is the sans-IO core (frame size and send time in, delivery time or a drop out; seeded), so
its statistics are testable exactly; `ProfiledTransport` runs it on a scheduler thread that hands each
datagram to the wrapped transport at its delivery time.

Bandwidth is a serial line's: a frame occupies the link for bits / rate, frames queue behind each other,
and a queue longer than `max_queue_s` drops (a radio's buffer overflowing). Delivery is in order unless
`reorder` is set (a byte stream cannot reorder).
"""

from __future__ import annotations

import heapq
import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from mars_link.transport.base import Address, Transport


@dataclass(frozen=True)
class LinkProfile:
    name: str
    latency_s: float = 0.0           # one-way propagation + processing
    jitter_s: float = 0.0            # standard deviation of a Gaussian added to the latency (truncated at 0)
    loss: float = 0.0                # probability a frame is lost
    bandwidth_bps: float = math.inf  # line rate in bits per second
    bits_per_byte: float = 8.0       # 10 for 8N1 serial (start + 8 data + stop)
    overhead_bytes: int = 0          # per-frame framing added by the link (e.g. radio packet header)
    max_queue_s: float = 1.0         # backlog beyond this is dropped
    reorder: bool = False


PRESETS: dict[str, LinkProfile] = {
    "ideal": LinkProfile("ideal"),
    "lan": LinkProfile("lan", latency_s=0.0002, jitter_s=0.00005, bandwidth_bps=1e9),
    "wifi": LinkProfile("wifi", latency_s=0.002, jitter_s=0.001, loss=0.002, bandwidth_bps=20e6),
    # SiK-class 433/915 MHz telemetry radio on a 57600-baud 8N1 UART (the MAVLink default for radios)
    "radio57600": LinkProfile("radio57600", latency_s=0.010, jitter_s=0.003, loss=0.01,
                              bandwidth_bps=57600, bits_per_byte=10.0, max_queue_s=0.5),
}


def profile_from_name(text: str) -> LinkProfile:
    """A preset name, optionally with overrides: `wifi`, `radio57600,loss=0.05`, `ideal,latency_s=0.003`."""
    name, *overrides = [p.strip() for p in text.split(",") if p.strip()] or [""]
    if name not in PRESETS:
        raise ValueError(f"link profile {name!r}: unknown (known: {', '.join(PRESETS)})")
    profile = PRESETS[name]
    for item in overrides:
        key, _, value = item.partition("=")
        if key not in ("latency_s", "jitter_s", "loss", "bandwidth_bps", "max_queue_s"):
            raise ValueError(f"link profile override {item!r}: expected latency_s, jitter_s, loss, bandwidth_bps or max_queue_s")
        try:
            v = float(value)
        except ValueError:
            raise ValueError(f"link profile override {item!r}: not a number") from None
        if not math.isfinite(v) and key != "bandwidth_bps" or v < 0 or (key == "loss" and v > 1):
            raise ValueError(f"link profile override {item!r}: out of range")
        change: dict[str, Any] = {key: v}  # (one float field, named at run time)
        profile = replace(profile, **change)
    return profile


class LinkModel:
    """Sans-IO: `schedule(now_s, nbytes)` -> delivery time, or None if the frame is lost."""

    def __init__(self, profile: LinkProfile, seed: int = 0) -> None:
        self.profile = profile
        self.rng = np.random.default_rng(seed)
        self.link_free_s = -math.inf
        self.last_delivery_s = -math.inf
        self.sent = 0
        self.lost = 0
        self.overflowed = 0

    def schedule(self, now_s: float, nbytes: int) -> float | None:
        p = self.profile
        self.sent += 1
        start = max(now_s, self.link_free_s)
        if start - now_s > p.max_queue_s:
            self.overflowed += 1
            return None
        tx = (nbytes + p.overhead_bytes) * p.bits_per_byte / p.bandwidth_bps
        self.link_free_s = start + tx  # a lost frame still used the air time
        if p.loss > 0 and self.rng.random() < p.loss:
            self.lost += 1
            return None
        jitter = max(self.rng.normal(0.0, p.jitter_s), -p.latency_s) if p.jitter_s > 0 else 0.0
        due = self.link_free_s + p.latency_s + jitter
        if not p.reorder:
            due = max(due, self.last_delivery_s)
        self.last_delivery_s = due
        return due


class ProfiledTransport(Transport):
    """Wraps a transport: sends go out through a LinkModel (one per peer), received frames pass as is."""

    def __init__(self, inner: Transport, profile: LinkProfile, seed: int = 0) -> None:
        super().__init__()
        self.inner = inner
        self.profile = profile
        self.kind = f"{inner.kind}+{profile.name}"
        self.counters = inner.counters  # one set of counters for the link
        self._seed = seed
        self._models: dict[Address, LinkModel] = {}
        self._heap: list[tuple[float, int, bytes, Address]] = []
        self._seq = 0
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._run, name=f"link-{profile.name}", daemon=True)
        self._thread.start()

    @property
    def local_address(self) -> Address:
        return self.inner.local_address


    def fileno(self) -> int:
        return self.inner.fileno()

    def prepare(self, peer: Address) -> None:
        self.inner.prepare(peer)

    def model(self, peer: Address) -> LinkModel:
        m = self._models.get(peer)
        if m is None:
            m = self._models[peer] = LinkModel(self.profile, self._seed + len(self._models))
        return m

    def send(self, data: bytes, peer: Address) -> bool:  # counted by the inner transport when it goes out
        if self.closed:
            raise ValueError(f"{self.kind} transport is closed")
        now = time.monotonic()
        with self._cv:
            due = self.model(peer).schedule(now, len(data))
            if due is None:  # lost on the way: the sender cannot know (as with a radio)
                self.counters.drop("link_lost")
                return True
            if due <= now and not self._heap:
                return self.inner.send(data, peer)
            heapq.heappush(self._heap, (due, self._seq, bytes(data), peer))
            self._seq += 1
            self._cv.notify()
        return True

    def recv(self, timeout_s: float) -> tuple[bytes, Address] | None:
        return self.inner.recv(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self.closed and (not self._heap or self._heap[0][0] > time.monotonic()):
                    wait = None if not self._heap else self._heap[0][0] - time.monotonic()
                    self._cv.wait(wait)
                if self.closed:
                    return
                _, _, data, peer = heapq.heappop(self._heap)
            try:
                self.inner.send(data, peer)
            except (ValueError, OSError):
                return

    def _close(self) -> None:
        with self._cv:
            self._cv.notify_all()
        self._thread.join(timeout=1.0)
        self.inner.close()
