"""mars_link.mavlink.codec against pymavlink itself, for every message type of the dialect: the same
bytes out, the same message (fields, header, buffers, CRC) back, the same errors."""

from __future__ import annotations

import copy
import hashlib
import random

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.mavlink.signing import enable_outgoing_signing
from mars_link.mavlink.codec import decode, encode

INT_RANGES = {"int8_t": (-128, 127), "uint8_t": (0, 255), "int16_t": (-32768, 32767), "uint16_t": (0, 65535),
              "int32_t": (-2**31, 2**31 - 1), "uint32_t": (0, 2**32 - 1), "int64_t": (-2**63, 2**63 - 1),
              "uint64_t": (0, 2**64 - 1), "uint8_t_mavlink_version": (0, 255)}
CLASSES = sorted(mavlink.mavlink_map.values(), key=lambda c: c.id)


def _value(rng: random.Random, ftype: str, zero: bool):
    if ftype in ("float", "double"):
        return 0.0 if zero else rng.randint(-10**6, 10**6) / 64.0  # exact in float32
    lo, hi = INT_RANGES[ftype]
    return 0 if zero else rng.randint(lo, hi)


def random_message(cls, rng: random.Random, zero_tail: bool = False):
    """An instance with random field values; `zero_tail` zeroes the second half of the fields (so the
    MAVLink 2 payload is trimmed)."""
    args = []
    n = len(cls.fieldnames)
    for i, (name, ftype) in enumerate(zip(cls.fieldnames, cls.fieldtypes)):
        length = cls.array_lengths[cls.ordered_fieldnames.index(name)]
        zero = zero_tail and i >= n // 2
        if ftype == "char":
            size = length or 1
            args.append(b"" if zero else bytes(rng.choice(b"abcXYZ09_") for _ in range(rng.randint(1, size))))
        elif length:
            args.append([_value(rng, ftype, zero) for _ in range(length)])
        else:
            args.append(_value(rng, ftype, zero))
    return cls(*args)


def same_message(a, b) -> None:
    assert type(a) is type(b) and a.get_type() == b.get_type()
    assert a.to_dict() == b.to_dict()
    assert vars(a._header) == vars(b._header)
    assert bytes(a._msgbuf) == bytes(b._msgbuf) and bytes(a._payload) == bytes(b._payload)
    assert a._crc == b._crc and a._signed == b._signed


@pytest.mark.parametrize("zero_tail", [False, True])
def test_every_message_type_encodes_and_decodes_as_pymavlink(zero_tail: bool) -> None:
    rng = random.Random(7 + zero_tail)
    for cls in CLASSES:
        for _ in range(3):
            msg = random_message(cls, rng, zero_tail)
            ours_mav, ref_mav = mavlink.MAVLink(None, 42, 7), mavlink.MAVLink(None, 42, 7)
            ours_mav.seq = ref_mav.seq = rng.randint(0, 255)
            ref = bytes(msg.pack(ref_mav))
            ours = encode(msg, ours_mav)
            assert ours == ref, cls.__name__
            frame = bytearray(ref)
            same_message(decode(bytearray(frame), mavlink.MAVLink(None, 1, 1)),
                         mavlink.MAVLink(None, 1, 1).decode(bytearray(frame)))


def _signer(key: bytes, link_id: int) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None, 201, 1)
    enable_outgoing_signing(mav, key, link_id, 1.7e9)
    return mav


@pytest.mark.parametrize("zero_tail", [False, True])
def test_every_message_type_signs_as_pymavlink(zero_tail: bool) -> None:
    """Signed encoding (link id, 48-bit timestamp, SHA-256 of key and frame) gives pymavlink's bytes and
    message attributes, and advances the encoder's signing timestamp by one per frame as pymavlink does."""
    rng = random.Random(11 + zero_tail)
    for key, link_id in ((hashlib.sha256(b"k").digest(), 1), (bytes(range(32)), 250)):
        ours_mav, ref_mav = _signer(key, link_id), _signer(key, link_id)
        for cls in CLASSES:
            msg = random_message(cls, rng, zero_tail)
            twin = copy.deepcopy(msg)
            ours_mav.seq = ref_mav.seq = rng.randint(0, 255)
            ref = bytes(twin.pack(ref_mav))
            assert encode(msg, ours_mav) == ref, cls.__name__
            assert ours_mav.signing.timestamp == ref_mav.signing.timestamp
            assert vars(msg._header) == vars(twin._header) and bytes(msg._msgbuf) == bytes(twin._msgbuf)
            assert bytes(msg._payload) == bytes(twin._payload) and msg._crc == twin._crc


def test_signed_frames_decode_as_pymavlink_without_a_key() -> None:
    rng = random.Random(3)
    signer = _signer(hashlib.sha256(b"k").digest(), 1)
    msg = random_message(mavlink.MAVLink_set_actuator_control_target_message, rng)
    frame = encode(msg, signer)
    assert frame[2] & mavlink.MAVLINK_IFLAG_SIGNED
    ours_dec, ref_dec = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None, 1, 1)
    same_message(decode(bytearray(frame), ours_dec), ref_dec.decode(bytearray(frame)))
    assert ours_dec.signing.sig_count == ref_dec.signing.sig_count == 1


def test_errors_and_other_frames_as_pymavlink() -> None:
    mav = mavlink.MAVLink(None, 5, 1)
    good = bytearray(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(mav))
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    with pytest.raises(mavlink.MAVError, match="CRC"):
        decode(bad_crc, mav)
    bad_len = bytearray(good)
    bad_len[1] += 1
    with pytest.raises(mavlink.MAVError, match="length"):
        decode(bad_len, mav)
    unknown = bytearray(good)
    unknown[7:10] = (0x33, 0x33, 0x03)  # no such message id
    assert isinstance(decode(unknown, mav), mavlink.MAVLink_unknown)
    v1 = bytearray(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(mav, force_mavlink1=True))
    same_message(decode(bytearray(v1), mav), mavlink.MAVLink(None, 1, 1).decode(bytearray(v1)))
