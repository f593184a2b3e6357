"""Signing: key loading, HMAC-first verification (no stream poisoning), replay and age rules."""

from __future__ import annotations

import hashlib
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.mavlink import signing
from mars_link.mavlink.signing import SignatureVerifier, enable_outgoing_signing, load_key
from mars_link.core.errors import UserInputError

KEY = hashlib.sha256(b"unit-1 test key").digest()


def _encoder(key: bytes = KEY, link_id: int = 1, sysid: int = 201, now: float | None = None):
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
    enable_outgoing_signing(mav, key, link_id, time.time() if now is None else now)
    return mav


def _command(mav) -> bytes:
    return bytes(mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(mav))


def test_key_from_raw_file_hex_file_passphrase_file_and_env(tmp_path, monkeypatch) -> None:
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    assert load_key(raw) == KEY
    hexfile = tmp_path / "hex.key"
    hexfile.write_text(KEY.hex() + "\n")
    assert load_key(hexfile) == KEY
    phrase = tmp_path / "phrase.key"
    phrase.write_text("correct horse\n")
    assert load_key(phrase) == hashlib.sha256(b"correct horse").digest()
    monkeypatch.setenv("MARS_TEST_KEY", "battery staple")
    assert load_key(None, "MARS_TEST_KEY") == hashlib.sha256(b"battery staple").digest()
    monkeypatch.delenv("MARS_TEST_KEY")
    assert load_key(None, "MARS_TEST_KEY") is None


def test_bad_key_sources_are_one_line_user_errors(tmp_path, monkeypatch) -> None:
    with pytest.raises(UserInputError, match="does not exist"):
        load_key(tmp_path / "missing.key")
    empty = tmp_path / "empty.key"
    empty.write_text("  \n")
    with pytest.raises(UserInputError, match="empty"):
        load_key(empty)
    monkeypatch.setenv("MARS_TEST_KEY", "")
    with pytest.raises(UserInputError, match="empty"):
        load_key(None, "MARS_TEST_KEY")
    with pytest.raises(UserInputError, match="32 bytes"):
        SignatureVerifier(b"short")


def test_genuine_frames_pass_and_everything_else_is_counted_by_reason() -> None:
    now = time.time()
    v = SignatureVerifier(KEY)
    good = _encoder(now=now)
    first = _command(good)
    assert v.verify(first, now) == signing.ACCEPTED
    assert v.verify(_command(good), now) == signing.ACCEPTED
    assert v.verify(first, now) == signing.REPLAY  # captured and sent again
    unsigned = bytes(mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(
        mavlink.MAVLink(None, srcSystem=201, srcComponent=1)))
    assert v.verify(unsigned, now) == signing.UNSIGNED
    wrong = _encoder(key=hashlib.sha256(b"other").digest(), link_id=2, now=now)
    assert v.verify(_command(wrong), now) == signing.BAD_SIGNATURE
    tampered = bytearray(_command(good))
    tampered[12] ^= 0x01  # a payload byte
    assert v.verify(bytes(tampered), now) == signing.BAD_SIGNATURE
    assert v.verify(first[:-3], now) == signing.MALFORMED
    assert v.counters == {"accepted": 2, "replay": 1, "unsigned": 1, "bad_signature": 2, "malformed": 1}


def test_forged_far_future_frame_does_not_block_the_genuine_sender() -> None:
    """The pymavlink 2.4.50 weakness (spec §5.2): a forged frame for the same stream with a far-future
    timestamp and a garbage signature must not advance the stream's timestamp."""
    now = time.time()
    v = SignatureVerifier(KEY)
    good = _encoder(link_id=7, now=now)
    assert v.verify(_command(good), now) == signing.ACCEPTED
    forger = _encoder(key=hashlib.sha256(b"guess").digest(), link_id=7, now=now + 10 * 365 * 86400)
    assert v.verify(_command(forger), now) == signing.BAD_SIGNATURE
    for _ in range(3):
        assert v.verify(_command(good), now) == signing.ACCEPTED
    assert v.counters[signing.ACCEPTED] == 4


def test_new_stream_more_than_a_minute_old_is_rejected_but_a_recent_one_accepted() -> None:
    now = time.time()
    v = SignatureVerifier(KEY)
    assert v.verify(_command(_encoder(link_id=3, now=now - 120)), now) == signing.STALE_STREAM
    assert v.verify(_command(_encoder(link_id=4, now=now - 30)), now) == signing.ACCEPTED


def test_outgoing_signing_clock_follows_wall_time() -> None:
    now = time.time()
    mav = _encoder(now=now)
    signing.advance_outgoing_clock(mav, now + 5.0)
    frame = _command(mav)
    ts = int.from_bytes(frame[-12:-6], "little")
    assert ts >= signing.signing_timestamp(now + 5.0)
