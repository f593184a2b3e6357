"""A ULog (.ulg) writer of our own: the binary log PX4 writes, which Flight Review, PlotJuggler, pyulog and
Foxglove open.

Format facts (restated from PX4's "ULog File Format" documentation, PX4 user guide, dev_log/ulog_file_format):
little endian; a 16-byte header (magic "ULog" 0x01 0x12 0x35, version 1, start time in microseconds); then
messages, each a 3-byte header (uint16 size of the payload, uint8 type) and its payload. The definitions
section holds the flag bits ('B', first, 40 bytes), format definitions ('F', "name:type field;..."),
information ('I', a typed key and its value) and parameters ('P', int32_t or float); the data section
starts with the first subscription ('A': multi instance, message id, topic name) or logged string
('L': level '0'..'7' as in the Linux kernel, time, text), and holds data ('D': message id, then the
fields packed, `timestamp` in microseconds, monotonic per message id) and sync markers ('S').

Why our own: it is ~200 lines, and the writer must go through `mars_link.logs.outputs.SafeWriter` (a full
disk stops the log with a reason, never the flight), which no ULog library offers. This module knows the
format only; what a vehicle logs is in `firmware_models.vehicle_ulog`.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

MAGIC = b"ULog\x01\x12\x35"
FILE_VERSION = 1
SYNC_MAGIC = bytes((0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12))
MAX_PAYLOAD_BYTES = 0xFFFF  # msg_size is a uint16

#: ULog's basic types -> struct codes (little endian, no alignment: fields are packed as declared)
TYPE_CODES = {
    "int8_t": "b", "uint8_t": "B", "int16_t": "h", "uint16_t": "H", "int32_t": "i", "uint32_t": "I",
    "int64_t": "q", "uint64_t": "Q", "float": "f", "double": "d", "bool": "?", "char": "c",
}
_INTEGER_TYPES = {"int8_t", "uint8_t", "int16_t", "uint16_t", "int32_t", "uint32_t", "int64_t", "uint64_t"}

#: 'L' log levels, as MAVLink's MAV_SEVERITY (0 emergency .. 7 debug), written as the characters '0'..'7'
LEVEL_EMERG, LEVEL_ALERT, LEVEL_CRIT, LEVEL_ERR, LEVEL_WARNING, LEVEL_NOTICE, LEVEL_INFO, LEVEL_DEBUG = range(8)


@dataclass(frozen=True)
class Field:
    """One field of a topic: a ULog basic type, a name, and an array length (1: a scalar)."""

    type: str
    name: str
    count: int = 1

    def declaration(self) -> str:
        return f"{self.type}[{self.count}] {self.name}" if self.count > 1 else f"{self.type} {self.name}"


class Topic:
    """A message format ('F'): its name and fields; packs a mapping of field values into a 'D' payload.

    Fields missing from the mapping are written as zero (NaN for floats), so a producer fills only
    what it knows. `timestamp` (uint64_t, microseconds) must be a field (ULog requires it)."""

    def __init__(self, name: str, fields: Iterable[Field]) -> None:
        self.name = name
        self.fields = tuple(fields)
        names = [f.name for f in self.fields]
        if len(set(names)) != len(names):
            raise ValueError(f"{name}: duplicate field names")
        if not any(f.name == "timestamp" and f.type == "uint64_t" and f.count == 1 for f in self.fields):
            raise ValueError(f"{name}: a uint64_t timestamp field is required")
        for f in self.fields:
            if f.type not in TYPE_CODES or f.count < 1:
                raise ValueError(f"{name}.{f.name}: unknown type {f.type!r} or bad count {f.count}")
        self.struct = struct.Struct("<" + "".join(f"{f.count}{TYPE_CODES[f.type]}" if f.count > 1 else TYPE_CODES[f.type]
                                                  for f in self.fields))
        # (name, count, default, padding of a short array) per field: `pack` runs for every sample
        self._plan = [(f.name, f.count, _default(f), [_default(Field(f.type, f.name))] * f.count) for f in self.fields]

    def format_text(self) -> str:
        return f"{self.name}:" + "".join(f.declaration() + ";" for f in self.fields)

    def pack(self, values: Mapping[str, Any]) -> bytes:
        """The fields' values in order (numbers, numpy scalars, sequences or arrays for array fields;
        bytes for char); a missing field is zero (NaN for floats), a short array padded the same way."""
        flat: list = []
        get = values.get
        for name, count, default, padding in self._plan:
            v = get(name, default)
            if count == 1:
                flat.append(v)
            else:
                items = v.tolist() if hasattr(v, "tolist") else list(v)
                if len(items) != count:
                    items = (items + padding)[:count]
                flat.extend(items)
        return self.struct.pack(*flat)


def _default(f: Field):
    one = math.nan if f.type in ("float", "double") else (b"\0" if f.type == "char" else 0)
    return one if f.count == 1 else [one] * f.count


class UlogWriter:
    """Writes one ULog file through `write` (e.g. `SafeWriter.write`, which never raises).

    Order of use: `info`/`parameter`/`define` (the definitions), then `subscribe`, `data`, `text`,
    `sync` (the data section). `parameter` and `info` stay allowed in the data section (a changed
    parameter). A data sample whose timestamp goes back for its message id is dropped and counted
    (`non_monotonic`): readers may rely on each series being monotonic."""

    def __init__(self, write: Callable[[bytes], object], start_us: int) -> None:
        self._write = write
        self._pending: list[bytes] = []
        self.batch = False  # True: messages wait for `commit`
        self.topics: dict[str, Topic] = {}
        self._in_data = False
        self._ids: dict[tuple[str, int], int] = {}
        self._id_topic: list[Topic] = []
        self._last_us: list[int] = []
        self.non_monotonic = 0
        self._pending.append(MAGIC + bytes((FILE_VERSION,)) + struct.pack("<Q", int(start_us)))
        # 'B' flag bits: no compat or incompat flag set, no appended data (40 bytes)
        self._message(b"B", bytes(8) + bytes(8) + struct.pack("<3Q", 0, 0, 0))

    def _message(self, kind: bytes, payload: bytes) -> None:
        if len(payload) > MAX_PAYLOAD_BYTES:
            raise ValueError(f"ULog message of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
        self._pending.append(struct.pack("<HB", len(payload), kind[0]))
        self._pending.append(payload)
        if not self.batch:
            self.commit()

    def commit(self) -> None:
        """Hand what was written since the last commit to `write`, in one call (`batch`: the caller
        commits once per sample of several topics)."""
        if self._pending:
            data = b"".join(self._pending)
            self._pending.clear()
            self._write(data)

    # ------------------------------------------------------------------ definitions
    def info(self, name: str, value: str | int | float, kind: str | None = None) -> None:
        """An information message: a string (char[n]) or a number of ULog type `kind` (int32_t by default
        for ints, float for floats)."""
        key, data = _typed_value(name, value, kind)
        self._message(b"I", bytes((len(key),)) + key + data)

    def parameter(self, name: str, value: int | float, integer: bool) -> None:
        """A parameter: int32_t when `integer`, else float (the two types ULog allows)."""
        key, data = _typed_value(name, int(value) if integer else float(value), "int32_t" if integer else "float")
        self._message(b"P", bytes((len(key),)) + key + data)

    def define(self, topic: Topic) -> None:
        if self._in_data:
            raise RuntimeError("formats are defined before the data section")
        if topic.name in self.topics:
            return
        self.topics[topic.name] = topic
        self._message(b"F", topic.format_text().encode())

    # ------------------------------------------------------------------ data
    def subscribe(self, topic_name: str, multi_id: int = 0) -> int:
        """The message id of (topic, instance), announced with an 'A' message the first time."""
        key = (topic_name, multi_id)
        msg_id = self._ids.get(key)
        if msg_id is not None:
            return msg_id
        topic = self.topics[topic_name]
        self._in_data = True
        msg_id = len(self._id_topic)
        self._ids[key] = msg_id
        self._id_topic.append(topic)
        self._last_us.append(-1)
        self._message(b"A", struct.pack("<BH", multi_id, msg_id) + topic_name.encode())
        return msg_id

    def data(self, msg_id: int, values: Mapping[str, Any]) -> bool:
        """One sample of a subscribed topic; False if dropped (its timestamp went back)."""
        t_us = int(values["timestamp"])
        if t_us < self._last_us[msg_id]:
            self.non_monotonic += 1
            return False
        self._last_us[msg_id] = t_us
        payload = self._id_topic[msg_id].pack(values)
        self._pending.append(struct.pack("<HBH", len(payload) + 2, 68, msg_id))  # 68: 'D'
        self._pending.append(payload)
        if not self.batch:
            self.commit()
        return True

    def text(self, level: int, t_us: int, message: str) -> None:
        """A logged string ('L'), level 0 (emergency) .. 7 (debug)."""
        self._in_data = True
        level_char = ord("0") + min(max(int(level), 0), 7)
        body = message.encode("utf-8", "replace")[:MAX_PAYLOAD_BYTES - 9]
        self._message(b"L", struct.pack("<BQ", level_char, max(0, int(t_us))) + body)

    def sync(self) -> None:
        """A sync marker: a reader recovers from a damaged message at the next one."""
        self._message(b"S", SYNC_MAGIC)


def _typed_value(name: str, value, kind: str | None) -> tuple[bytes, bytes]:
    if isinstance(value, str):
        data = value.encode("utf-8", "replace")
        return f"char[{len(data)}] {name}".encode(), data
    if kind is None:
        kind = "int32_t" if isinstance(value, int) else "float"
    if kind not in TYPE_CODES or kind in ("char", "bool") and not isinstance(value, (bool, int)):
        raise ValueError(f"{name}: unsupported type {kind!r}")
    value = int(value) if kind in _INTEGER_TYPES or kind == "bool" else float(value)
    return f"{kind} {name}".encode(), struct.pack("<" + TYPE_CODES[kind], value)
