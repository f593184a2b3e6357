"""MAVLink 2 message signing for command links: key loading, HMAC-first verification, outgoing signing.

Why not pymavlink's own check: pymavlink 2.4.50 stores a stream's timestamp *before* it compares the
HMAC, so one forged frame with a spoofed (link_id, sysid, compid) and a far-future timestamp makes every
later genuine frame of that stream look like a replay (specs/mavlink.md §5.2). `SignatureVerifier`
compares the truncated SHA-256 first, in constant time, and touches no state for a bad signature; only
a genuine frame may advance the stream's timestamp (as the C library's `mavlink_signature_check`).

Signature block (13 bytes, after the CRC): link_id, 48-bit timestamp in 10 µs units since
2015-01-01 00:00 UTC, first 6 bytes of SHA-256(key + frame up to and including the timestamp).
"""

from __future__ import annotations

import hashlib
import hmac
import os
from pathlib import Path

from mars_link.core.errors import UserInputError
from mars_link.core.validation import note_input

SIGNATURE_BLOCK_LEN = 13
IFLAG_SIGNED = 0x01
MAVLINK2_STX = 0xFD
EPOCH_2015_UNIX_S = 1420070400
TICKS_PER_S = 100_000  # 10 µs units
NEW_STREAM_MAX_AGE_TICKS = 60 * TICKS_PER_S  # a new stream may start at most 1 minute behind us
DEFAULT_KEY_ENV = "MARS_LINK_SIGNING_KEY"

#: verification results (also the counter names)
ACCEPTED = "accepted"
UNSIGNED = "unsigned"
BAD_SIGNATURE = "bad_signature"
REPLAY = "replay"  # timestamp not newer than the stream's last genuine frame
STALE_STREAM = "stale_stream"  # a new stream more than a minute behind the local clock
MALFORMED = "malformed"


def signing_timestamp(unix_time_s: float) -> int:
    """Signing clock value (10 µs ticks since 2015) for a Unix time."""
    return max(0, int((unix_time_s - EPOCH_2015_UNIX_S) * TICKS_PER_S))


def key_from_passphrase(passphrase: str) -> bytes:
    """SHA-256 of the passphrase: MAVProxy's `signing key <passphrase>` convention."""
    if not passphrase:
        raise UserInputError("signing passphrase is empty")
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


def _key_from_text(text: str, origin: str) -> bytes:
    text = text.strip()
    if not text:
        raise UserInputError(f"signing key in {origin} is empty")
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    return key_from_passphrase(text)


def load_key(path: str | os.PathLike | None = None, env_var: str = DEFAULT_KEY_ENV) -> bytes | None:
    """The 32-byte signing key from a file (preferred) or an environment variable; None if neither.

    A file of exactly 32 bytes is the raw key; otherwise (file or variable) 64 hex digits are the key
    and any other text is a passphrase hashed with SHA-256, as MAVProxy does.
    """
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise UserInputError(f"signing key file {str(p)!r} does not exist")
        note_input(p)  # (an input of the run: --force keeps it)
        raw = p.read_bytes()
        if len(raw) == 32:
            return raw
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise UserInputError(
                f"signing key file {str(p)!r} is neither 32 raw bytes nor text"
            ) from None
        return _key_from_text(text, f"file {str(p)!r}")
    value = os.environ.get(env_var)
    if value is None:
        return None
    return _key_from_text(value, f"environment variable {env_var}")


def _check_key(key: bytes) -> bytes:
    if not isinstance(key, (bytes, bytearray)) or len(key) != 32:
        raise UserInputError("a MAVLink signing key must be exactly 32 bytes")
    return bytes(key)


def is_signed(frame: bytes | bytearray) -> bool:
    return len(frame) > 2 and frame[0] == MAVLINK2_STX and bool(frame[2] & IFLAG_SIGNED)


class SignatureVerifier:
    """Per-link verifier: HMAC first, then replay protection per (link_id, sysid, compid) stream."""

    def __init__(self, key: bytes) -> None:
        self.key = _check_key(key)
        self._keyed = hashlib.sha256(self.key)  # (copied per frame: the key is hashed once)
        self.local_timestamp = 0  # advanced by the wall clock and by genuine frames
        self.streams: dict[tuple[int, int, int], int] = {}
        self.counters: dict[str, int] = {}

    def _count(self, reason: str) -> str:
        self.counters[reason] = self.counters.get(reason, 0) + 1
        return reason

    def verify(self, frame: bytes | bytearray, now_unix_s: float) -> str:
        """Classify one complete frame; returns ACCEPTED or the reason it must be dropped."""
        self.local_timestamp = max(self.local_timestamp, signing_timestamp(now_unix_s))
        if not is_signed(frame):
            return self._count(UNSIGNED)
        if len(frame) < 10 + 2 + SIGNATURE_BLOCK_LEN or frame[1] + 10 + 2 + SIGNATURE_BLOCK_LEN != len(frame):
            return self._count(MALFORMED)
        keyed = self._keyed.copy()
        keyed.update(memoryview(frame)[:-6])
        digest = keyed.digest()[:6]
        if not hmac.compare_digest(digest, bytes(frame[-6:])):
            return self._count(BAD_SIGNATURE)  # no state touched: a forger cannot poison a stream
        link_id = frame[-13]
        timestamp = int.from_bytes(frame[-12:-6], "little")
        stream = (link_id, frame[5], frame[6])
        last = self.streams.get(stream)
        if last is not None:
            if timestamp <= last:
                return self._count(REPLAY)
        elif timestamp + NEW_STREAM_MAX_AGE_TICKS < self.local_timestamp:
            return self._count(STALE_STREAM)
        self.streams[stream] = timestamp
        self.local_timestamp = max(self.local_timestamp, timestamp)
        return self._count(ACCEPTED)


def enable_outgoing_signing(mav, key: bytes, link_id: int, now_unix_s: float) -> None:
    """Make a pymavlink MAVLink encoder sign what it packs (its timestamp starts at `now`).

    Use a separate MAVLink object for decoding: a key on the decoder would switch on pymavlink's
    vulnerable check.
    """
    if not 0 <= link_id <= 255:
        raise UserInputError(f"signing link_id must be 0..255, got {link_id}")
    mav.signing.secret_key = _check_key(key)
    mav.signing.link_id = link_id
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = signing_timestamp(now_unix_s)


def advance_outgoing_clock(mav, now_unix_s: float) -> None:
    """Keep an encoder's signing clock at least at wall time (pymavlink adds 1 tick per frame only)."""
    ts = signing_timestamp(now_unix_s)
    if ts > mav.signing.timestamp:
        mav.signing.timestamp = ts


def signing_from_args(args) -> tuple[bytes | None, bool]:
    """(key, require_signing) from `--signing-key-file` and `--require-signing` (defined by
    mars_link.processes.cli_options.add_signing); --require-signing without a key is a UserInputError."""
    key = load_key(getattr(args, "signing_key_file", None))
    require = bool(getattr(args, "require_signing", False))
    if require and key is None:
        raise UserInputError(f"--require-signing needs a key: --signing-key-file or ${DEFAULT_KEY_ENV}")
    return key, require
