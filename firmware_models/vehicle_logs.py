"""Log download (MAVLink's LOG_* microservice) serving the run's own logs: its .tlog and run.mcap.

Why read-only: the files are the run's record (a test's evidence, an operator's flight log), so
LOG_ERASE is answered with a STATUSTEXT saying they are kept; LOG_REQUEST_LIST lists them (ids from
0, sizes as they are at that moment: a .tlog still grows), LOG_REQUEST_DATA streams LOG_DATA chunks
of 90 bytes from the requested offset (count 0 at the end of the file), up to LOG_CHUNKS_PER_TICK per
tick, one transfer at a time; LOG_REQUEST_END stops it. The runner hands the paths over
(`vehicle.log_service.store = LogStore([...])`); the vehicle itself never opens a file otherwise.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle_links import Link, Outgoing

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle

R = mavlink
CHUNK_BYTES = 90
LOG_CHUNKS_PER_TICK = 40  # 100 Hz ticks: ~360 kB/s on loopback
ALL_BYTES = 0xFFFFFFFF


class LogStore:
    """The run's log files, in a fixed order (their ids)."""

    def __init__(self, paths: list[str | os.PathLike | None]) -> None:
        self.paths = [Path(p) for p in paths if p is not None]

    def entries(self) -> list[tuple[int, int, int]]:
        """(id, size in bytes, modification time in UTC seconds) of the files that exist now."""
        out = []
        for i, p in enumerate(self.paths):
            try:
                st = p.stat()
            except OSError:
                continue
            out.append((i, st.st_size, int(st.st_mtime)))
        return out

    def read(self, log_id: int, offset: int, n: int) -> bytes | None:
        """Up to n bytes from offset (b"" at the end); None if the file cannot be read."""
        try:
            with open(self.paths[log_id], "rb") as f:
                f.seek(offset)
                return f.read(n)
        except (OSError, IndexError):
            return None


@dataclass
class _Transfer:
    link: str
    sender: tuple
    log_id: int
    offset: int
    end: int


class LogService:
    """LOG_* requests. Owns the log files handed over (`store`) and the transfer in progress. Asks of the
    vehicle: its links, the current sender, `_for_me`, `_reply`, `_send`, `_text`, `_count`, `_drop`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.store: LogStore | None = None
        self.xfer: _Transfer | None = None

    def on_request_list(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=True):
            v._drop("wrong_target")
            return
        entries = self.store.entries() if self.store is not None else []
        v._count("log.list")
        if not entries:  # PX4: one LOG_ENTRY with num_logs 0
            v._reply(lk, R.MAVLink_log_entry_message(0, 0, 0, 0, 0), out)
            return
        last = entries[-1][0]
        for log_id, size, t_utc in entries:
            if msg.start <= log_id <= msg.end:
                if not v._reply(lk, R.MAVLink_log_entry_message(log_id, len(entries), last, t_utc, size), out):
                    break

    def on_request_data(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            v._drop("wrong_target")
            return
        sizes = {i: size for i, size, _ in (self.store.entries() if self.store is not None else [])}
        if msg.id not in sizes:
            v._drop("log.unknown_id")
            v._reply(lk, R.MAVLink_log_data_message(msg.id, msg.ofs, 0, [0] * CHUNK_BYTES), out)
            return
        end = sizes[msg.id] if msg.count == ALL_BYTES else min(sizes[msg.id], msg.ofs + msg.count)
        self.xfer = _Transfer(lk.name, v._sender, msg.id, msg.ofs, max(end, msg.ofs))
        v._count("log.request_data")
        self.tick(out)

    def on_request_end(self, msg, lk: Link, out: list[Outgoing]) -> None:
        self.xfer = None
        self.v._count("log.request_end")

    def on_erase(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            v._drop("wrong_target")
            return
        v._count("log.erase_refused")
        v._text("Logs kept: the run's own logs are not erased", R.MAV_SEVERITY_NOTICE)

    def tick(self, out: list[Outgoing]) -> None:
        """Stream the transfer in progress (from tick and right after the request)."""
        v = self.v
        x = self.xfer
        if x is None:
            return
        lk = v.links[x.link]
        for _ in range(LOG_CHUNKS_PER_TICK):
            n = min(CHUNK_BYTES, x.end - x.offset)
            data = self.store.read(x.log_id, x.offset, n) if n > 0 else b""
            if data is None:
                v._drop("log.read_error")
                self.xfer = None
                return
            v._send(lk, R.MAVLink_log_data_message(x.log_id, x.offset, len(data),
                                                   list(data) + [0] * (CHUNK_BYTES - len(data))), out)
            v._count("log.data")
            x.offset += len(data)
            if not data or x.offset >= x.end:
                self.xfer = None
                return
