"""Sans-IO MAVLink framing over a byte stream (serial, radios): bytes in, whole CRC-checked frames out.

Resynchronises on the next magic byte after garbage or a bad frame, so line noise costs the frames it
touches, never the link. Counts what it throws away.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as mavlink
from pymavlink.generator.mavcrc import x25crc

from mars_link.mavlink.codec import MAGIC_V1, MAGIC_V2, frame_length, frame_message_id, header_length


@dataclass
class FramerCounters:
    frames: int = 0
    garbage_bytes: int = 0   # bytes skipped while looking for a frame start
    bad_crc: int = 0         # frames whose checksum failed (corrupted or truncated + resynced)
    unknown_msgid: int = 0   # frames of a message this dialect does not know (checksum unverifiable)
    dropped: dict[str, int] = field(default_factory=dict)


class MavlinkFramer:
    def __init__(self, max_buffer: int = 4096) -> None:
        self.buf = bytearray()
        self.max_buffer = max_buffer
        self.counters = FramerCounters()

    def feed(self, data: bytes) -> list[bytes]:
        """Append stream bytes; return every complete, checksum-valid frame now available."""
        self.buf += data
        out: list[bytes] = []
        while True:
            frame = self._next()
            if frame is None:
                break
            out.append(frame)
        if len(self.buf) > self.max_buffer:  # cannot happen with valid lengths; keep memory bounded
            self.counters.garbage_bytes += len(self.buf)
            self.buf.clear()
        return out

    def _next(self) -> bytes | None:
        buf = self.buf
        while buf:
            start = _find_magic(buf)
            if start < 0:
                self.counters.garbage_bytes += len(buf)
                buf.clear()
                return None
            if start:
                self.counters.garbage_bytes += start
                del buf[:start]
            total = frame_length(buf, 0)
            if total is None:  # (its header is not all there yet)
                return None
            header = header_length(buf)
            msgid = frame_message_id(buf)
            if len(buf) < total:
                return None
            plen = buf[1]
            cls = mavlink.mavlink_map.get(msgid)
            if cls is None:
                self.counters.unknown_msgid += 1
                del buf[:1]
                continue
            crc = x25crc(bytes(buf[1:header + plen]))
            crc.accumulate(bytes([cls.crc_extra]))
            if crc.crc != buf[header + plen] | (buf[header + plen + 1] << 8):
                self.counters.bad_crc += 1
                del buf[:1]  # resync: a real frame may start inside this one
                continue
            frame = bytes(buf[:total])
            del buf[:total]
            self.counters.frames += 1
            return frame
        return None


def _find_magic(buf: bytearray) -> int:
    a, b = buf.find(MAGIC_V2), buf.find(MAGIC_V1)
    if a < 0:
        return b
    if b < 0:
        return a
    return min(a, b)


def check_datagram(data: bytes) -> tuple[bytes, dict[str, int]]:
    """The valid frames of one datagram (a datagram holds whole frames) and what was thrown away."""
    f = MavlinkFramer()
    good = b"".join(f.feed(data))
    c = f.counters
    leftover = len(f.buf)  # a truncated last frame
    problems = {k: v for k, v in (("garbage_bytes", c.garbage_bytes + leftover), ("bad_crc", c.bad_crc),
                                  ("unknown_msgid", c.unknown_msgid)) if v}
    if leftover:
        problems["truncated"] = 1
    return good, problems
