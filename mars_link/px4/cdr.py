"""CDR (XCDR1, little endian) encoding of the px4_msgs types, with the 4-byte encapsulation header that
rmw_zenoh puts in front of every payload (00 01 00 00: CDR_LE, no options).

The types here hold only primitives and fixed arrays, so each message has one static layout: every value
aligned to its own size (8 for 64-bit values) counted from the first byte after the header, arrays
without a length prefix, no padding after the last field. One precompiled `struct.Struct` per type packs
and unpacks a message in one call.

Messages are dataclasses generated from the specs in `definitions` (`ActuatorMotors(control=...)`); the
spec's constants are class attributes (`VehicleStatus.ARMING_STATE_ARMED`). Arrays are numpy arrays.
"""

from __future__ import annotations

import dataclasses
import struct
from typing import Any

import numpy as np

from mars_link.px4 import definitions as d

ENCAPSULATION_CDR_LE = b"\x00\x01\x00\x00"
ENCAPSULATION_CDR_BE = b"\x00\x00\x00\x00"

# type -> (struct code, size in bytes, numpy dtype)
_PRIMITIVE = {
    "bool": ("?", 1, np.bool_), "int8": ("b", 1, np.int8), "uint8": ("B", 1, np.uint8),
    "int16": ("h", 2, np.int16), "uint16": ("H", 2, np.uint16),
    "int32": ("i", 4, np.int32), "uint32": ("I", 4, np.uint32),
    "int64": ("q", 8, np.int64), "uint64": ("Q", 8, np.uint64),
    "float32": ("f", 4, np.float32), "float64": ("d", 8, np.float64),
}


class CdrError(ValueError):
    """A payload that is not a CDR encoding of the expected type."""


def _layout(spec: d.MessageSpec) -> tuple[str, int]:
    """The struct format (without byte order) and the encoded size after the header."""
    fmt, offset = [], 0
    for f in spec.fields:
        code, size, _ = _PRIMITIVE[f.type]
        pad = (-offset) % size
        if pad:
            fmt.append(f"{pad}x")
            offset += pad
        count = f.array_length or 1
        fmt.append(f"{count}{code}" if f.array_length is not None else code)
        offset += size * count
    return "".join(fmt), offset


def _array_default(dtype, length: int):
    return lambda: np.zeros(length, dtype=dtype)


def _make_class(spec: d.MessageSpec) -> type:
    fields = []
    for f in spec.fields:
        _, _, dtype = _PRIMITIVE[f.type]
        if f.array_length is not None:
            default = dataclasses.field(default_factory=_array_default(dtype, f.array_length))
            fields.append((f.name, np.ndarray, default))
        elif f.type == "bool":
            fields.append((f.name, bool, dataclasses.field(default=False)))
        elif f.type.startswith("float"):
            fields.append((f.name, float, dataclasses.field(default=0.0)))
        else:
            fields.append((f.name, int, dataclasses.field(default=0)))
    namespace: dict[str, Any] = {c.name: c.value for c in spec.constants}
    namespace["SPEC"] = spec
    namespace["__doc__"] = f"{spec.ros_type_name} (PX4 {d.PX4_RELEASE}); constants as class attributes."
    return dataclasses.make_dataclass(spec.name, fields, namespace=namespace, eq=False)


class _Codec:
    def __init__(self, spec: d.MessageSpec):
        self.spec = spec
        body, self.size = _layout(spec)
        self.le = struct.Struct("<" + body)
        self.be = struct.Struct(">" + body)
        self.cls = _make_class(spec)

    def flatten(self, msg: Any) -> list:
        values: list = []
        for f in self.spec.fields:
            value = getattr(msg, f.name)
            if f.array_length is not None:
                arr = np.asarray(value)
                if arr.shape != (f.array_length,):
                    raise CdrError(f"{self.spec.name}.{f.name}: expected {f.array_length} values, "
                                   f"got shape {arr.shape}")
                values.extend(arr.tolist() if f.type != "bool" else [bool(v) for v in arr])
            elif f.type == "bool":
                values.append(bool(value))
            elif f.type.startswith("float"):
                values.append(float(value))
            else:
                values.append(int(value))
        return values

    def build(self, values: tuple) -> Any:
        kwargs, i = {}, 0
        for f in self.spec.fields:
            if f.array_length is not None:
                _, _, dtype = _PRIMITIVE[f.type]
                kwargs[f.name] = np.array(values[i:i + f.array_length], dtype=dtype)
                i += f.array_length
            else:
                kwargs[f.name] = values[i]
                i += 1
        return self.cls(**kwargs)


_CODECS: dict[str, _Codec] = {spec.name: _Codec(spec) for spec in d.ALL_MESSAGES}

OffboardControlMode = _CODECS["OffboardControlMode"].cls
ActuatorMotors = _CODECS["ActuatorMotors"].cls
VehicleCommand = _CODECS["VehicleCommand"].cls
VehicleCommandAck = _CODECS["VehicleCommandAck"].cls
VehicleStatus = _CODECS["VehicleStatus"].cls
VehicleOdometry = _CODECS["VehicleOdometry"].cls
SensorCombined = _CODECS["SensorCombined"].cls
BatteryStatus = _CODECS["BatteryStatus"].cls
VehicleLocalPosition = _CODECS["VehicleLocalPosition"].cls


def message_class(name: str) -> type:
    return _CODECS[name].cls


def encoded_size(name: str) -> int:
    """Bytes of a payload of this type, header included."""
    return 4 + _CODECS[name].size


def encode(msg: Any, *, big_endian: bool = False) -> bytes:
    """The rmw_zenoh payload of `msg` (one of this module's message classes): header + CDR body."""
    spec = getattr(type(msg), "SPEC", None)
    if spec is None or spec.name not in _CODECS:
        raise CdrError(f"{type(msg).__name__} is not a px4 message class of this module")
    codec = _CODECS[spec.name]
    packer = codec.be if big_endian else codec.le
    try:
        body = packer.pack(*codec.flatten(msg))
    except struct.error as e:
        raise CdrError(f"{spec.name}: {e}") from e
    return (ENCAPSULATION_CDR_BE if big_endian else ENCAPSULATION_CDR_LE) + body


def decode(name: str, payload: bytes | bytearray | memoryview) -> Any:
    """A message of type `name` from an rmw_zenoh payload. Accepts both byte orders and trailing
    alignment bytes some serializers append; refuses short payloads and unknown encapsulations."""
    codec = _CODECS.get(name)
    if codec is None:
        raise CdrError(f"unknown px4 message type {name!r}")
    data = bytes(payload)
    if len(data) < 4:
        raise CdrError(f"{name}: payload of {len(data)} bytes has no encapsulation header")
    header = data[:4]
    if header[:2] == ENCAPSULATION_CDR_LE[:2]:
        unpacker = codec.le
    elif header[:2] == ENCAPSULATION_CDR_BE[:2]:
        unpacker = codec.be
    else:
        raise CdrError(f"{name}: encapsulation {header[:2].hex()} is not plain CDR (0000 or 0001)")
    if len(data) - 4 < codec.size:
        raise CdrError(f"{name}: payload body of {len(data) - 4} bytes, the type needs {codec.size}")
    return codec.build(unpacker.unpack_from(data, 4))
