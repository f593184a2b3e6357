"""Bytes to MAVLink messages and back, in one place. Every reader of MAVLink bytes (the unit firmware's
links, the SITL processes' links, the serial framer, the .tlog writer and reader, the command-age tap, the
harnesses) finds and decodes frames here: `split_frames` / `decode_frames` (a datagram or a log record to
messages, what is dropped counted or skipped), `frame_length`, `header_length` and `frame_message_id` (a
frame's size and id from its header), and each frame's `decode` / `encode`.

Encode/decode are done with the per-message-type work done once: what pymavlink's
`MAVLink.decode` and `MAVLink_message.pack` do, byte for byte and field for field, at a third of the
cost (tests/core/test_mavlink_codec.py checks every message of the dialect against pymavlink).

Why: in real-time SITL every frame of the lockstep (world -> unit -> coordinator -> unit) is decoded
and encoded in Python on the sensor-to-motor path, eight processes share two cores, and pymavlink
spends most of its time on generic per-field loops (field reordering, string trimming, trailing-zero
stripping one byte at a time) that depend only on the message type. PX4's generated C headers do the
same thing with fixed layouts.

Scope: MAVLink 2 frames, signed or not (a signature is never checked here: callers verify it first,
HMAC-first, in mars_link.mavlink.signing). MAVLink 1 frames, and encoders with outgoing signing, go to
pymavlink unchanged. Errors raise pymavlink's MAVError with pymavlink's reasons.
"""

from __future__ import annotations

import functools
import hashlib
import math
import struct
from dataclasses import dataclass
from operator import itemgetter
from typing import Callable

from fastcrc.crc16 import mcrf4xx
from pymavlink.dialects.v20 import common as mavlink

MAGIC_V2 = 0xFD
MAGIC_V1 = 0xFE
HEADER_LEN_V2 = 10
HEADER_LEN_V1 = 6
SIGNATURE_LEN = 13
_HEADER_V2 = struct.Struct("<BBBBBBBHB")
#: a generated pymavlink message class (its class attributes describe the wire layout)
MessageClass = type[mavlink.MAVLink_message]
_CRC = struct.Struct("<H")
_SIGNATURE_HEAD = struct.Struct("<BQ")  # link id and timestamp; the timestamp is sent as its 6 low bytes


@dataclass(frozen=True)
class _TypePlan:
    """What decoding and encoding one message type needs, computed once."""

    cls: MessageClass
    crc_extra_byte: bytes
    size: int  # full (untrimmed) payload length
    to_fields: Callable[[tuple], list]  # struct tuple (wire order) -> constructor arguments (field order)
    to_wire: Callable[[object], tuple]  # message -> struct arguments (wire order)


def _plan(cls: MessageClass) -> _TypePlan:
    unpacker = cls.unpacker
    orders, lengths = cls.orders, cls.lengths
    sample = unpacker.unpack(bytes(unpacker.size))
    text_items = {i for i, v in enumerate(sample) if isinstance(v, bytes)}  # char[] fields: one item each
    if sum(lengths) == len(lengths):  # no arrays: a permutation (as pymavlink's first branch)
        pick = itemgetter(*orders) if len(orders) > 1 else (lambda t, o=orders[0]: (t[o],))
        text_fields = [i for i, o in enumerate(orders) if o in text_items]

        def to_fields(t: tuple) -> list:
            values = list(pick(t))
            for i in text_fields:
                values[i] = values[i].rstrip(b"\x00")
            return values
    else:  # arrays: slices of the struct tuple (as pymavlink's second branch)
        spans = []
        for order in orders:
            tip = sum(lengths[:order])
            is_text = tip in text_items
            spans.append((tip, lengths[order], is_text))

        def to_fields(t: tuple) -> list:
            values = []
            for tip, n, is_text in spans:
                if is_text:
                    values.append(t[tip].rstrip(b"\x00"))
                elif n == 1:
                    values.append(t[tip])
                else:
                    values.append(list(t[tip:tip + n]))
            return values

    # encode: the struct arguments in wire order from the message's attributes (a char[] field's bytes
    # are kept as `_<name>_raw` where pymavlink also keeps a decoded str)
    blank = cls(*[b"" if t == "char" else [0] * n if n else 0
                  for t, n in zip(cls.fieldtypes, (cls.array_lengths[cls.ordered_fieldnames.index(f)]
                                                    for f in cls.fieldnames))])
    keys = []
    for name, n in zip(cls.ordered_fieldnames, cls.array_lengths):
        is_text = cls.fieldtypes[cls.fieldnames.index(name)] == "char"
        raw = f"_{name}_raw"
        keys.append((raw if is_text and raw in vars(blank) else name, 0 if is_text else n))
    if all(n == 0 for _, n in keys):
        getter = itemgetter(*(k for k, _ in keys)) if len(keys) > 1 else (lambda d, k=keys[0][0]: (d[k],))

        def to_wire(msg) -> tuple:
            return getter(msg.__dict__)
    else:
        def to_wire(msg) -> tuple:
            args = []
            d = msg.__dict__
            for key, n in keys:
                if n:
                    args.extend(d[key][:n])
                else:
                    args.append(d[key])
            return tuple(args)

    return _TypePlan(cls, bytes((cls.crc_extra,)), unpacker.size, to_fields, to_wire)


_PLANS: dict[int, _TypePlan] = {}


def _plan_for(msg_id: int) -> _TypePlan | None:
    plan = _PLANS.get(msg_id)
    if plan is None:
        cls = mavlink.mavlink_map.get(msg_id)
        if cls is None:
            return None
        plan = _PLANS[msg_id] = _plan(cls)
    return plan


def decode(frame: bytearray, fallback: mavlink.MAVLink) -> mavlink.MAVLink_message:
    """One complete frame -> the message pymavlink's `fallback.decode(frame)` returns (same fields,
    header, buffers, CRC). `fallback` (a decoder without a signing key) handles MAVLink 1."""
    if frame[0] != MAGIC_V2 or len(frame) < HEADER_LEN_V2 + 2:
        return fallback.decode(frame)
    _, mlen, incompat, compat, seq, src_system, src_component, id_low, id_high = _HEADER_V2.unpack_from(frame)
    msg_id = id_low | (id_high << 16)
    sig_len = SIGNATURE_LEN if incompat & mavlink.MAVLINK_IFLAG_SIGNED else 0
    end = len(frame) - 2 - sig_len
    if mlen != end - HEADER_LEN_V2:
        raise mavlink.MAVError("invalid MAVLink message length. Got %u expected %u, msgId=%u headerlen=%u"
                               % (end - HEADER_LEN_V2, mlen, msg_id, HEADER_LEN_V2))
    plan = _plan_for(msg_id)
    if plan is None:
        return mavlink.MAVLink_unknown(msg_id, frame)
    crc = _CRC.unpack_from(frame, end)[0]
    crc2 = mcrf4xx(plan.crc_extra_byte, mcrf4xx(bytes(frame[1:end]), 0xFFFF))
    if crc != crc2 and not mavlink.MAVLINK_IGNORE_CRC:
        raise mavlink.MAVError("invalid MAVLink CRC in msgID %u 0x%04x should be 0x%04x" % (msg_id, crc, crc2))
    if sig_len:
        fallback.signing.sig_count += 1  # (as pymavlink counts them)
    payload = bytes(frame[HEADER_LEN_V2:end])
    if len(payload) < plan.size:
        payload += bytes(plan.size - len(payload))  # MAVLink 2 trims trailing zeros
    try:
        msg = plan.cls(*plan.to_fields(plan.cls.unpacker.unpack(payload[:plan.size])))
    except Exception as e:  # noqa: BLE001 (pymavlink's wording)
        raise mavlink.MAVError("Unable to instantiate MAVLink message of type %s : %s" % (plan.cls, e)) from None
    msg._signed = False  # (pymavlink sets True only when it checked the signature itself)
    msg._msgbuf = frame
    msg._payload = frame[6:end]  # (pymavlink's slice, kept for equality)
    msg._crc = crc
    msg._header = mavlink.MAVLink_header(msg_id, incompat, compat, mlen, seq, src_system, src_component)
    return msg


def encode(msg: mavlink.MAVLink_message, mav: mavlink.MAVLink) -> bytes:
    """The bytes `msg.pack(mav)` returns (and the same attributes set on `msg`), signed when `mav` signs
    (its signing timestamp advanced by one per frame, as pymavlink does)."""
    msg_id = msg._header.msgId
    plan = _plan_for(msg_id)
    if plan is None or type(msg) is not plan.cls:
        return msg.pack(mav)
    signing = mav.signing
    flags = mavlink.MAVLINK_IFLAG_SIGNED if signing.sign_outgoing else 0
    payload = plan.cls.unpacker.pack(*plan.to_wire(msg))
    trimmed = payload.rstrip(b"\x00") or payload[:1]  # MAVLink 2 trailing-zero truncation (>= 1 byte)
    header = _HEADER_V2.pack(MAGIC_V2, len(trimmed), flags, 0, mav.seq, mav.srcSystem, mav.srcComponent,
                             msg_id & 0xFFFF, msg_id >> 16)
    body = header + trimmed
    crc = mcrf4xx(plan.crc_extra_byte, mcrf4xx(body[1:], 0xFFFF))
    frame = body + _CRC.pack(crc)
    if flags:
        frame += _SIGNATURE_HEAD.pack(signing.link_id, signing.timestamp)[:7]  # link id, 48-bit timestamp
        keyed = _keyed_sha256(bytes(signing.secret_key)).copy()
        keyed.update(frame)
        frame += keyed.digest()[:6]
        signing.timestamp += 1
    msg._payload = trimmed
    msg._header = mavlink.MAVLink_header(msg_id, flags, 0, len(trimmed), mav.seq, mav.srcSystem, mav.srcComponent)
    msg._msgbuf = bytearray(frame)
    msg._crc = crc
    return frame


@functools.lru_cache(maxsize=8)
def _keyed_sha256(key: bytes) -> "hashlib._Hash":
    """SHA-256 that has taken the signing key (copied per frame: the key is hashed once per link, not per
    frame)."""
    return hashlib.sha256(key)


# ----------------------------------------------------------------------------- frames of a byte string
Bytes = bytes | bytearray


def frame_length(data: Bytes, i: int) -> int | None:
    """The length of the frame starting at data[i], as its header says (MAVLink 2 signed or not, MAVLink 1);
    None when data[i] starts no frame or its header is cut short."""
    start = data[i]
    if start == MAGIC_V2 and len(data) - i >= HEADER_LEN_V2:
        return HEADER_LEN_V2 + data[i + 1] + 2 + (SIGNATURE_LEN if data[i + 2] & mavlink.MAVLINK_IFLAG_SIGNED else 0)
    if start == MAGIC_V1 and len(data) - i >= HEADER_LEN_V1:
        return HEADER_LEN_V1 + data[i + 1] + 2
    return None


def frame_message_id(data: Bytes, i: int = 0) -> int:
    """The message id in the header of the frame starting at data[i] (to skip a frame without decoding it)."""
    return data[i + 7] | (data[i + 8] << 8) | (data[i + 9] << 16) if data[i] == MAGIC_V2 else data[i + 5]


def header_length(data: Bytes, i: int = 0) -> int:
    """The header length of the frame starting at data[i] (its payload follows)."""
    return HEADER_LEN_V2 if data[i] == MAGIC_V2 else HEADER_LEN_V1


def split_frames(data: Bytes, decoder: mavlink.MAVLink, drop: Callable[[str], None],
                 pre_check: Callable[[bytearray], bool] | None = None,
                 ) -> list[tuple[mavlink.MAVLink_message, bytearray]]:
    """Decode every complete, CRC-valid frame of one datagram; count the rest via `drop(reason)`.

    Resynchronises one byte after a bad frame (a random 0xFD in junk must not hide a good frame).
    `pre_check(frame) -> bool` runs on the raw bytes before decoding (signature verification: an
    unsigned or forged frame costs a flag test or one SHA-256, never a decode).
    """
    out = []
    n = len(data)
    i = 0
    junk = False
    while i < n:
        b = data[i]
        if b == MAGIC_V2:
            if n - i < HEADER_LEN_V2 + 2:
                drop("parse.truncated")
                break
            flags = data[i + 2]
            if flags & ~mavlink.MAVLINK_IFLAG_SIGNED:
                drop("parse.unknown_flags")
                i += 1
                continue
        elif b == MAGIC_V1:
            if n - i < HEADER_LEN_V1 + 2:
                drop("parse.truncated")
                break
        else:
            nxt = min((j for j in (data.find(b"\xfd", i), data.find(b"\xfe", i)) if j >= 0), default=n)
            junk = True
            i = nxt
            continue
        flen = frame_length(data, i)
        assert flen is not None  # (a whole header is there)
        if i + flen > n:
            drop("parse.truncated")
            i += 1
            continue
        frame = bytearray(data[i:i + flen])
        if pre_check is not None and not pre_check(frame):
            i += flen
            continue
        try:
            msg = decode(frame, decoder)
        except Exception as e:  # pymavlink raises MAVError and, on odd payloads, others
            drop("parse.bad_crc" if "CRC" in str(e) else "parse.malformed")
            i += 1
            continue
        if isinstance(msg, mavlink.MAVLink_unknown) or msg.get_type() == "BAD_DATA":
            drop("parse.unknown_message")
        else:
            out.append((msg, frame))
        i += flen
    if junk:
        drop("parse.junk")
    return out


def decode_frames(data: Bytes, decoder: mavlink.MAVLink) -> list[mavlink.MAVLink_message]:
    """The messages of bytes holding whole frames (a datagram a unit sent, one .tlog frame); what does not
    decode is skipped (a reader that counts it uses split_frames)."""
    return [m for m, _ in split_frames(data, decoder, _ignore)]


def _ignore(reason: str) -> None:
    """(a drop not counted)"""


# ----------------------------------------------------------------------------- wire ranges
# Why: a field value outside its wire type (a modelled current of 400 A in an int16 centiamp field, a
# NaN in an integer field) makes struct raise inside a telemetry send, which used to end the flight.
# Telemetry must never stop a flight: such a message is clamped to the wire range instead, and a NaN
# integer becomes the field's "invalid" value from the MAVLink definition (common.xml `invalid=`).
ENCODE_ERRORS = (struct.error, OverflowError, ValueError, TypeError)
FLT_MAX = 3.4028234663852886e38
_INT_RANGES = {"int8_t": (-2**7, 2**7 - 1), "uint8_t": (0, 2**8 - 1), "int16_t": (-2**15, 2**15 - 1),
               "uint16_t": (0, 2**16 - 1), "int32_t": (-2**31, 2**31 - 1), "uint32_t": (0, 2**32 - 1),
               "int64_t": (-2**63, 2**63 - 1), "uint64_t": (0, 2**64 - 1), "uint8_t_mavlink_version": (0, 255)}
_INVALID: dict[str, dict[str, str]] | None = None


def _invalid_table() -> dict[str, dict[str, str]]:
    """message name -> field name -> `invalid` attribute, read once from the dialect's own XML (shipped
    beside pymavlink's generated module)."""
    global _INVALID
    if _INVALID is None:
        import xml.etree.ElementTree as ET
        from pathlib import Path

        table: dict[str, dict[str, str]] = {}
        xml = Path(mavlink.__file__).with_suffix(".xml")
        try:
            for m in ET.parse(xml).getroot().iter("message"):
                fields = {f.get("name", ""): f.get("invalid", "") for f in m.iter("field")
                          if f.get("invalid") is not None}
                if fields:
                    table[m.get("name", "")] = fields
        except (OSError, ET.ParseError):
            pass
        _INVALID = table
    return _INVALID


def invalid_value(msg_name: str, field: str, ftype: str):
    """The value MAVLink defines as "unknown / not sent" for this field (0 if it defines none; NaN
    for float fields)."""
    if ftype in ("float", "double"):
        return float("nan")
    text = _invalid_table().get(msg_name, {}).get(field, "0").strip("[]")
    lo, hi = _INT_RANGES.get(ftype, (0, 0))
    named = {"INT8_MAX": 2**7 - 1, "UINT8_MAX": 2**8 - 1, "INT16_MAX": 2**15 - 1, "UINT16_MAX": 2**16 - 1,
             "INT32_MAX": 2**31 - 1, "UINT32_MAX": 2**32 - 1, "INT64_MAX": 2**63 - 1, "UINT64_MAX": 2**64 - 1}
    try:
        value = named[text] if text in named else int(text, 0)
    except ValueError:
        return 0
    return min(max(value, lo), hi)


def _clamp_one(value, ftype: str, unknown):
    if ftype in ("float", "double"):
        try:
            x = float(value)
        except (TypeError, ValueError):
            return float("nan")
        return max(-FLT_MAX, min(FLT_MAX, x)) if ftype == "float" and math.isfinite(x) else x
    lo, hi = _INT_RANGES[ftype]
    try:
        x = float(value) if not isinstance(value, int) else value
    except (TypeError, ValueError):
        return unknown
    if isinstance(x, float):
        if math.isnan(x):
            return unknown
        if math.isinf(x):
            return hi if x > 0 else lo
        x = int(round(x))
    return min(max(int(x), lo), hi)


def clamp_fields(msg: mavlink.MAVLink_message) -> int:
    """Clamp every numeric field of `msg`, in place, to its wire type's range (NaN in an integer
    field -> its invalid value); returns how many values changed."""
    changed = 0
    msg_class: type = type(msg)  # (as `type`: mypy takes type[Any] for unhashable, lru_cache needs hashable)
    for name, ftype, n, unknown in _numeric_fields(msg_class):
        value = getattr(msg, name)
        if n:
            items = list(value) if isinstance(value, (list, tuple)) else [value] * n
            items = (items + [unknown] * n)[:n]
            new = [_clamp_one(x, ftype, unknown) for x in items]
            same = len(items) == len(value) if isinstance(value, (list, tuple)) else False
            changed += sum(1 for a, b in zip(items, new) if not _same(a, b)) + (0 if same else 1)
        else:
            new = _clamp_one(value, ftype, unknown)
            changed += 0 if _same(value, new) else 1
        setattr(msg, name, new)
    return changed


@functools.lru_cache(maxsize=None)
def _numeric_fields(cls: MessageClass) -> tuple:
    """(name, type, array length, invalid value) of each numeric field, once per message type."""
    return tuple((name, ftype, cls.array_lengths[cls.ordered_fieldnames.index(name)],
                  invalid_value(cls.msgname, name, ftype))
                 for name, ftype in zip(cls.fieldnames, cls.fieldtypes) if ftype != "char")


def _same(a, b) -> bool:
    return type(a) is type(b) and (a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)))


def encode_clamped(msg: mavlink.MAVLink_message, mav: mavlink.MAVLink) -> tuple[bytes, int]:
    """`encode`, and when a field does not fit its wire type, `clamp_fields` then encode: (frame,
    number of values clamped). The fast path costs nothing extra; a message that still cannot be
    encoded raises one of ENCODE_ERRORS (or MAVError) for the caller to count and drop."""
    try:
        return encode(msg, mav), 0
    except ENCODE_ERRORS:
        n = clamp_fields(msg)
        return encode(msg, mav), max(n, 1)
