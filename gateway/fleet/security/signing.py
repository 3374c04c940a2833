"""MAVLink 2 message signing, verified before the replay state moves.

For standard autopilots that cannot run the tunnel. The signature is the first 6 bytes of
SHA-256(secret_key ‖ frame up to the CRC ‖ link_id ‖ timestamp), the timestamp counting 10 µs
units since 2015-01-01. pymavlink records a stream's timestamp *before* checking the
signature, so one forged frame with a huge timestamp makes every later genuine frame look
replayed (MAVLink 2 message signing, "timestamp"); this verifier checks the signature first
and only then advances the stream, which is why the gateway does not use pymavlink's check.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable
from dataclasses import dataclass

from gateway.errors import AuthenticationFailed, Malformed, Replayed

__all__ = [
    "SIGNATURE_BYTES",
    "OutboundSigner",
    "SigningCounters",
    "SigningVerifier",
    "mavlink_timestamp_now",
    "sign_frame",
]

SIGNATURE_BYTES = 13
_STX_V2 = 0xFD
_IFLAG_SIGNED = 0x01
_EPOCH_2015 = 1420070400
#: A new stream may start at most one minute behind our clock (the MAVLink signing rules).
_NEW_STREAM_LAG = 6_000_000


def mavlink_timestamp_now(unix_s: float) -> int:
    """The signing timestamp for a UNIX time: 10 µs units since 2015-01-01."""
    return int((unix_s - _EPOCH_2015) * 100_000)


def sign_frame(frame_unsigned: bytes, key: bytes, link_id: int, timestamp: int) -> bytes:
    """Append a signature to a MAVLink 2 frame whose INCOMPAT signed flag is already set."""
    tail = bytes([link_id]) + timestamp.to_bytes(6, "little")
    digest = hashlib.sha256(key + frame_unsigned + tail).digest()[:6]
    return frame_unsigned + tail + digest


@dataclass(slots=True)
class SigningCounters:
    """How many frames a verifier saw, by outcome."""

    signed: int = 0
    unsigned: int = 0
    bad_signature: int = 0
    replayed: int = 0


class SigningVerifier:
    """Checks signatures of the MAVLink 2 frames of one airframe (all of its links).

    ``verify(frame)`` returns True for a good signed frame and False for an unsigned frame
    that the policy accepts; it raises ``AuthenticationFailed`` for a bad signature or an
    unsigned frame on a require-signed link, and ``Replayed`` for an old timestamp.
    """

    def __init__(
        self,
        key: bytes,
        *,
        require_signed: bool,
        clock: Callable[[], float],
        accept_unsigned_msgids: frozenset[int] = frozenset(),
    ) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink signing key is 32 bytes")
        self._key = key
        self.require_signed = require_signed
        self._clock = clock
        self._accept_unsigned = accept_unsigned_msgids
        self._streams: dict[tuple[int, int, int], int] = {}
        self._local_ts = 0
        # Replay state lives in memory; a frame signed before this verifier existed could be
        # a capture from before a restart, so no stream may start earlier (docs/tunnel.md).
        self._started_ts = mavlink_timestamp_now(clock())
        self.counters = SigningCounters()

    def verify(self, frame: bytes) -> bool:
        """Verify one complete frame (header to signature); see the class docstring."""
        if len(frame) < 8 or (frame[0] == _STX_V2 and len(frame) < 12):
            raise Malformed("shorter than a MAVLink frame")
        if frame[0] != _STX_V2 or not frame[2] & _IFLAG_SIGNED:
            msgid = _msgid(frame)
            if self.require_signed and msgid not in self._accept_unsigned:
                self.counters.unsigned += 1
                raise AuthenticationFailed("unsigned frame on a link that requires signing")
            self.counters.unsigned += 1
            return False
        body_end = 10 + frame[1] + 2
        if len(frame) != body_end + SIGNATURE_BYTES:
            raise Malformed("signed frame has the wrong length")
        link_id = frame[body_end]
        timestamp = int.from_bytes(frame[body_end + 1 : body_end + 7], "little")
        expected = hashlib.sha256(self._key + frame[: body_end + 7]).digest()[:6]
        if not hmac.compare_digest(expected, frame[body_end + 7 :]):
            self.counters.bad_signature += 1
            raise AuthenticationFailed("MAVLink signature did not verify")
        stream = (link_id, frame[5], frame[6])
        last = self._streams.get(stream)
        now = max(self._local_ts, mavlink_timestamp_now(self._clock()))
        if last is None:
            if timestamp + _NEW_STREAM_LAG < now:
                self.counters.replayed += 1
                raise Replayed("new signing stream starts more than a minute in the past")
            if timestamp < self._started_ts:
                self.counters.replayed += 1
                raise Replayed("signed before the gateway started (a replay across a restart?)")
        elif timestamp <= last:
            self.counters.replayed += 1
            raise Replayed("signing timestamp not newer than the stream's last")
        self._streams[stream] = timestamp
        self._local_ts = max(self._local_ts, timestamp)
        self.counters.signed += 1
        return True


class OutboundSigner:
    """Signs MAVLink 2 frames the gateway sends to one airframe on a ``signed`` link.

    A ground station on the passthrough sends unsigned frames; on a signed link they go out
    signed with the airframe's key, never weaker than the link. ``sign`` needs the message's
    CRC_EXTRA (to recompute the CRC once the signed flag is set) and refuses MAVLink 1
    frames, which cannot carry a signature. Timestamps never repeat and never go back.
    """

    def __init__(
        self,
        key: bytes,
        *,
        crc_extra: Callable[[int], int | None],
        clock: Callable[[], float],
        link_id: int = 0,
    ) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink signing key is 32 bytes")
        self._key = key
        self._crc_extra = crc_extra
        self._clock = clock
        self.link_id = link_id
        self._last_ts = 0

    def sign(self, frame: bytes) -> bytes:
        """Return ``frame`` (one complete MAVLink 2 frame, signed or not) signed by us."""
        if len(frame) < 12 or frame[0] != _STX_V2:
            raise Malformed("only MAVLink 2 frames can be signed")
        body_end = 10 + frame[1]
        if len(frame) not in (body_end + 2, body_end + 2 + SIGNATURE_BYTES):
            raise Malformed("frame length does not match its header")
        extra = self._crc_extra(_msgid(frame))
        if extra is None:
            raise Malformed("unknown message id: its CRC cannot be recomputed")
        head = bytearray(frame[:body_end])
        head[2] |= _IFLAG_SIGNED
        crc = _x25(bytes(head[1:]) + bytes([extra]))
        timestamp = max(self._last_ts + 1, mavlink_timestamp_now(self._clock()))
        self._last_ts = timestamp
        return sign_frame(
            bytes(head) + crc.to_bytes(2, "little"), self._key, self.link_id, timestamp
        )


def _x25(data: bytes) -> int:
    """CRC-16/MCRF4XX, MAVLink's X.25 checksum."""
    crc = 0xFFFF
    for byte in data:
        tmp = byte ^ (crc & 0xFF)
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc


def _msgid(frame: bytes) -> int:
    if frame[0] == _STX_V2 and len(frame) >= 10:
        return frame[7] | frame[8] << 8 | frame[9] << 16
    if len(frame) >= 6:
        return frame[5]
    return -1
