"""MAVLink 2 frame encode/decode with the per-message-type work done once: what pymavlink's
`MAVLink.decode` and `MAVLink_message.pack` do, byte for byte and field for field, at a third of the
cost (tests/test_mavlink_codec.py checks every message of the dialect against pymavlink).

Why: in real-time SITL every frame of the lockstep (world -> unit -> coordinator -> unit) is decoded
and encoded in Python on the sensor-to-motor path, eight processes share two cores, and pymavlink
spends most of its time on generic per-field loops (field reordering, string trimming, trailing-zero
stripping one byte at a time) that depend only on the message type. PX4's generated C headers do the
same thing with fixed layouts.

Scope: MAVLink 2 frames, signed or not (a signature is never checked here: callers verify it first,
HMAC-first, in firmware_models.signing). MAVLink 1 frames, and encoders with outgoing signing, go to
pymavlink unchanged. Errors raise pymavlink's MAVError with pymavlink's reasons.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from operator import itemgetter
from typing import Callable

from fastcrc.crc16 import mcrf4xx
from pymavlink.dialects.v20 import common as mavlink

MAGIC_V2 = 0xFD
HEADER_LEN_V2 = 10
SIGNATURE_LEN = 13
_HEADER_V2 = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")


@dataclass(frozen=True)
class _TypePlan:
    """What decoding and encoding one message type needs, computed once."""

    cls: type
    crc_extra_byte: bytes
    size: int  # full (untrimmed) payload length
    to_fields: Callable[[tuple], list]  # struct tuple (wire order) -> constructor arguments (field order)
    to_wire: Callable[[object], tuple]  # message -> struct arguments (wire order)


def _plan(cls: type) -> _TypePlan:
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
    """The bytes `msg.pack(mav)` returns (and the same attributes set on `msg`); a signing `mav` is
    left to pymavlink."""
    if mav.signing.sign_outgoing:
        return msg.pack(mav)
    msg_id = msg._header.msgId
    plan = _plan_for(msg_id)
    if plan is None or type(msg) is not plan.cls:
        return msg.pack(mav)
    payload = plan.cls.unpacker.pack(*plan.to_wire(msg))
    trimmed = payload.rstrip(b"\x00") or payload[:1]  # MAVLink 2 trailing-zero truncation (>= 1 byte)
    header = _HEADER_V2.pack(MAGIC_V2, len(trimmed), 0, 0, mav.seq, mav.srcSystem, mav.srcComponent,
                             msg_id & 0xFFFF, msg_id >> 16)
    body = header + trimmed
    crc = mcrf4xx(plan.crc_extra_byte, mcrf4xx(body[1:], 0xFFFF))
    frame = body + _CRC.pack(crc)
    msg._payload = trimmed
    msg._header = mavlink.MAVLink_header(msg_id, 0, 0, len(trimmed), mav.seq, mav.srcSystem, mav.srcComponent)
    msg._msgbuf = bytearray(frame)
    msg._crc = crc
    return frame
