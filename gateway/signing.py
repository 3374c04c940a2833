"""MAVLink 2 message signing, verified before the replay state moves.

For standard autopilots that cannot run the tunnel. The signature is the first 6 bytes of
SHA-256(secret_key ‖ frame up to the CRC ‖ link_id ‖ timestamp), the timestamp counting 10 µs
units since 2015-01-01. pymavlink records a stream's timestamp *before* checking the
signature, so one forged frame with a huge timestamp makes every later genuine frame look
replayed (specs/mavlink2.md); this verifier checks the signature first and only then
advances the stream, which is why the gateway does not use pymavlink's check.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable
from dataclasses import dataclass

from gateway.errors import AuthenticationFailed, Malformed, Replayed

__all__ = [
    "SIGNATURE_BYTES",
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
        elif timestamp <= last:
            self.counters.replayed += 1
            raise Replayed("signing timestamp not newer than the stream's last")
        self._streams[stream] = timestamp
        self._local_ts = max(self._local_ts, timestamp)
        self.counters.signed += 1
        return True


def _msgid(frame: bytes) -> int:
    if frame[0] == _STX_V2 and len(frame) >= 10:
        return frame[7] | frame[8] << 8 | frame[9] << 16
    if len(frame) >= 6:
        return frame[5]
    return -1
