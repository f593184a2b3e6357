"""pymavlink's .tlog format, written and read in one place: each MAVLink frame preceded by its 8-byte big-endian
microsecond time stamp. The SITL processes stamp wall time (as MAVProxy and QGroundControl do); an
in-process run stamps simulated time (mars_link.flight.unit_tlogs)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

from mars_link.mavlink.codec import frame_length


def tlog_records(data: bytes, t_s: float | None = None) -> bytes:
    """pymavlink .tlog records of one datagram: each frame preceded by its 8-byte big-endian
    microsecond timestamp (a datagram may carry several frames; bytes that are no frame go as one)."""
    stamp = int((time.time() if t_s is None else t_s) * 1e6).to_bytes(8, "big")
    parts = []
    i, n = 0, len(data)
    while i < n:
        size = frame_length(data, i) or n - i
        parts.append(stamp + data[i:i + size])
        i += size
    return b"".join(parts)


def tlog_frames(path: Path) -> Iterator[tuple[float, bytes]]:
    """(time stamp s, frame bytes) of a .tlog whose records may hold several frames (batched datagrams)."""
    data = path.read_bytes()
    i, n = 0, len(data)
    while i + 8 <= n:
        t = int.from_bytes(data[i:i + 8], "big") / 1e6
        i += 8
        while i < n and (size := frame_length(data, i)) is not None:
            yield t, data[i:i + size]
            i += size
