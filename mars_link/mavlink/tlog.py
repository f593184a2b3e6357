"""pymavlink's .tlog format, written in one place: each MAVLink frame preceded by its 8-byte big-endian
microsecond time stamp. The SITL processes stamp wall time (as MAVProxy and QGroundControl do); an
in-process run stamps simulated time (mars_link.flight.unit_tlogs)."""

from __future__ import annotations

import time


def tlog_records(data: bytes, t_s: float | None = None) -> bytes:
    """pymavlink .tlog records of one datagram: each frame preceded by its 8-byte big-endian
    microsecond timestamp (a datagram may carry several frames; bytes that are no frame go as one)."""
    stamp = int((time.time() if t_s is None else t_s) * 1e6).to_bytes(8, "big")
    parts = []
    i, n = 0, len(data)
    while i < n:
        if data[i] == 0xFD and i + 3 <= n:
            size = 12 + data[i + 1] + (13 if data[i + 2] & 0x01 else 0)
        elif data[i] == 0xFE and i + 2 <= n:
            size = 8 + data[i + 1]
        else:
            size = n - i
        parts.append(stamp + data[i:i + size])
        i += size
    return b"".join(parts)
