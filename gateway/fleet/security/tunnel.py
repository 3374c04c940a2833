"""The AES-256-GCM tunnel between an airframe and the gateway: day keys, sealing, replay.

Frame layout (all integers big-endian; docs/tunnel.md has the rationale)::

    0   magic        2  b"F6"
    2   version      1  1
    3   key_day      2  days since 1970-01-01 (UTC) of the day key that sealed it
    5   id_len       1  1..64
    6   airframe id  id_len bytes, ASCII
    .   sent_ms      6  sender's UTC clock, milliseconds since 1970
    .   nonce       12  8-byte random session salt ‖ 4-byte counter
    .   ciphertext   n  the MAVLink frame(s)
    .   tag         16  GCM tag

Everything before the ciphertext is the AEAD's associated data, so any change to the header
fails authentication. Day keys are ``HKDF-SHA256(master, salt=b"YYYY-MM-DD", info=id)``;
an airframe holds only its own day keys. A frame is accepted only if its key day is today,
yesterday within the grace window after 00:00 UTC, or tomorrow within the clock-skew
allowance; its ``sent_ms`` is within the freshness window of the receiver's clock; and its
(session, counter) has not been seen (a sliding window per airframe, link and session).
Sessions idle for longer than the freshness window are forgotten: their frames are too old
to be accepted anyway, so forgetting them cannot re-open a replay. The windows live in
memory, so a frame sealed before the opener was made (before this process started) is
refused too: a capture replayed after a restart finds no window to stop it otherwise.
"""

from __future__ import annotations

import os
import struct
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, date, datetime, timedelta
from typing import NamedTuple

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.ciphers.aead import AESGCM
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from gateway.clock import Clock
from gateway.errors import AuthenticationFailed, Malformed, Oversize, Replayed

__all__ = [
    "MAGIC",
    "MAX_ID_BYTES",
    "OVERHEAD_BYTES",
    "DayKeys",
    "ReplayWindow",
    "Sealer",
    "TunnelOpener",
    "day_number",
    "derive_day_key",
]

MAGIC = b"F6"
VERSION = 1
MAX_ID_BYTES = 64
_EPOCH = date(1970, 1, 1)
_DAY_MS = 86_400_000
_TAG = 16
_NONCE = 12
_FIXED = struct.Struct(">2sBHB")
#: After the airframe id: sent_ms (6 bytes, read as 2 + 4), the nonce's salt and counter.
_TAIL = struct.Struct(">HI8sI")
_PLAIN_MAVLINK = (0xFD, 0xFE)  # MAVLink 2 and 1 start bytes
#: Nonces remembered per airframe across links (about 25 min of frames at 50 Hz).
_MAX_ACCEPTED = 65_536
#: The accepted nonces of an airframe are pruned every 1,024 insertions.
_PRUNE_MASK = 1023
#: Distinct headers (airframe id and key day) remembered before the memory starts again.
_MAX_HEADERS = 4096
#: Bytes a sealed frame adds to its payload, for an airframe id of 8 bytes.
OVERHEAD_BYTES = _FIXED.size + 8 + 6 + _NONCE + _TAG


def _utc_ms(now: datetime) -> int:
    """Milliseconds since 1970 (UTC) of an aware datetime."""
    return int(now.timestamp() * 1000)


def day_number(day: date) -> int:
    """Days since 1970-01-01: the key day as written in frames."""
    return (day - _EPOCH).days


def derive_day_key(master: bytes, airframe: str, day: date) -> bytes:
    """The 32-byte AES key of ``airframe`` for the UTC ``day``."""
    if len(master) < 32:
        raise ValueError("the master key must be at least 32 bytes")
    hkdf = HKDF(
        algorithm=hashes.SHA256(),
        length=32,
        salt=day.isoformat().encode("ascii"),
        info=airframe.encode("ascii"),
    )
    return hkdf.derive(master)


class DayKeys:
    """Where an endpoint's day keys come from: the master (gateway) or a key set (airframe).

    ``key(airframe, day)`` returns None when this holder has no key for that pair, which
    the opener treats as an authentication failure.
    """

    def __init__(
        self,
        *,
        master: bytes | None = None,
        keys: Mapping[tuple[str, date], bytes] | None = None,
    ) -> None:
        if (master is None) == (keys is None):
            raise ValueError("give either a master key or a set of day keys")
        self._master = master
        self._keys = dict(keys or {})
        self._cache: dict[tuple[str, date], AESGCM] = {}

    def aead(self, airframe: str, day: date) -> AESGCM | None:
        """The cipher for (airframe, day), derived once and cached."""
        cache_key = (airframe, day)
        cipher = self._cache.get(cache_key)
        if cipher is None:
            if self._master is not None:
                key: bytes | None = derive_day_key(self._master, airframe, day)
            else:
                key = self._keys.get((airframe, day))
            if key is None:
                return None
            if len(self._cache) > 4096:
                self._cache.clear()
            cipher = AESGCM(key)
            self._cache[cache_key] = cipher
        return cipher


class Sealer:
    """Seals outgoing payloads for one airframe; one per sending endpoint and process."""

    def __init__(self, airframe: str, keys: DayKeys, clock: Clock) -> None:
        raw_id = airframe.encode("ascii")
        if not 1 <= len(raw_id) <= MAX_ID_BYTES:
            raise ValueError(f"airframe id must be 1..{MAX_ID_BYTES} ASCII bytes")
        self.airframe = airframe
        self._id = raw_id
        self._keys = keys
        self._clock = clock
        self._new_session()

    def _new_session(self) -> None:
        self._salt = os.urandom(8)
        self._counter = 0

    def seal(self, payload: bytes) -> bytes:
        """Encrypt and authenticate ``payload`` under today's key."""
        now = self._clock()
        day = now.date()
        cipher = self._keys.aead(self.airframe, day)
        if cipher is None:
            raise AuthenticationFailed(f"no day key for {self.airframe} on {day}")
        if self._counter >= 0xFFFFFFFF:
            # A nonce must never repeat under one key: a fresh random salt starts a new session.
            self._new_session()
        self._counter += 1
        nonce = self._salt + self._counter.to_bytes(4, "big")
        sent_ms = int(now.timestamp() * 1000)
        header = (
            _FIXED.pack(MAGIC, VERSION, day_number(day), len(self._id))
            + self._id
            + sent_ms.to_bytes(6, "big")
            + nonce
        )
        return header + cipher.encrypt(nonce, payload, header)

    def reply_opener(self) -> TunnelOpener:
        """An opener for what the gateway seals to this airframe (its uplink).

        The gateway seals uplink frames under the airframe's own day keys, so the airframe
        opens them with the keys and clock it seals with, and accepts only its own id.
        """
        return TunnelOpener(self._keys, frozenset({self.airframe}), self._clock)


@dataclass(slots=True)
class ReplayWindow:
    """A sliding window over the counters of one session (RFC 4303 style bitmap)."""

    size: int = 1024
    highest: int = 0
    bitmap: int = 0
    last_seen_ms: int = 0
    mask: int = field(init=False, repr=False, compare=False)
    """``size`` ones: the bits the window keeps."""

    def __post_init__(self) -> None:
        self.mask = (1 << self.size) - 1

    def check(self, counter: int) -> bool:
        """True if ``counter`` is new and inside the window (does not record it)."""
        if counter > self.highest:
            return True
        offset = self.highest - counter
        return offset < self.size and not (self.bitmap >> offset) & 1

    def record(self, counter: int) -> None:
        """Mark ``counter`` as seen; call only after the frame authenticated."""
        if counter > self.highest:
            shift = counter - self.highest
            self.bitmap = ((self.bitmap << shift) | 1) & self.mask
            self.highest = counter
        else:
            self.bitmap |= 1 << (self.highest - counter)


class Opened(NamedTuple):
    """An authenticated frame: who sent it and the plaintext (a tuple: built once a frame)."""

    airframe: str
    payload: bytes
    key_day: date
    sent_ms: int
    """The sender's clock when it sealed the frame, milliseconds since 1970 (UTC)."""

    @property
    def sent(self) -> datetime:
        """``sent_ms`` as an aware datetime."""
        return datetime.fromtimestamp(self.sent_ms / 1000, tz=UTC)


_new_tuple = tuple.__new__
_Seen = dict[bytes, tuple[float, object]]
_Header = tuple[str, int, date, AESGCM, _Seen]


@dataclass(slots=True)
class _Sessions:
    windows: dict[bytes, ReplayWindow] = field(default_factory=dict)


class TunnelOpener:
    """Authenticates and decrypts frames from many airframes; fails closed.

    ``open_frame`` raises ``Malformed``, ``Oversize``, ``AuthenticationFailed`` (bad tag,
    unknown airframe, key day outside the accepted range) or ``Replayed`` (seen before, or
    too old); it never returns unauthenticated data. Replay state is kept per ``stream``
    (the caller passes the link), so a frame duplicated on two links passes once per link
    and link-level de-duplication decides; but a frame that arrives on a second link more
    than ``cross_link_s`` after it was accepted on the first is a replay there, refused.
    """

    def __init__(
        self,
        keys: DayKeys,
        airframes: frozenset[str],
        clock: Clock,
        *,
        grace_s: float = 600.0,
        skew_s: float = 120.0,
        freshness_s: float = 30.0,
        max_frame_bytes: int = 2048,
        cross_link_s: float = 1.0,
    ) -> None:
        self._keys = keys
        self._airframes = airframes
        self._clock = clock
        self.grace_s = grace_s
        self.skew_s = skew_s
        self.freshness_s = freshness_s
        self.max_frame_bytes = max_frame_bytes
        self._streams: dict[tuple[object, str], _Sessions] = {}
        self.cross_link_s = cross_link_s
        self._accepted: dict[str, dict[bytes, tuple[float, object]]] = {}
        # The replay windows live in memory, so a frame sealed before this opener existed
        # could be a capture from before a restart: refuse it (docs/tunnel.md, "Restarts").
        self.started_ms = int(clock().timestamp() * 1000)
        self._days: dict[int, date] = {}
        #: Header bytes up to the airframe id, seen before -> airframe, key day, day, cipher
        #: and the airframe's accepted nonces (``cross_link_s``).
        self._headers: dict[bytes, _Header] = {}

    def accepted_days(self, now: datetime) -> tuple[date, ...]:
        """The key days a frame may use at ``now``: today, plus neighbours near midnight."""
        today = day_number(now.date())
        return tuple(self._day(n) for n in self._accepted_day_numbers(_utc_ms(now), today))

    def _accepted_day_numbers(self, now_ms: int, today: int) -> tuple[int, ...]:
        # Integer arithmetic on the ms clock: this runs once per frame.
        into_ms = now_ms - today * _DAY_MS
        days: tuple[int, ...] = (today,)
        if into_ms <= self.grace_s * 1000:
            days += (today - 1,)
        if _DAY_MS - into_ms <= self.skew_s * 1000:
            days += (today + 1,)
        return days

    def _day(self, key_day: int) -> date:
        day = self._days.get(key_day)
        if day is None:
            if len(self._days) > 64:
                self._days.clear()
            day = self._days[key_day] = _EPOCH + timedelta(days=key_day)
        return day

    def open_frame(self, frame: bytes, stream: object = None, now_ms: int | None = None) -> Opened:
        """Authenticate ``frame`` (from link ``stream``) and return its plaintext.

        ``now_ms``: the clock now (ms since 1970, UTC) when the caller has just read it.
        """
        # This runs once per frame: one struct read for the counters, the window inline.
        size = len(frame)
        if size > self.max_frame_bytes:
            raise Oversize(size, self.max_frame_bytes)
        if size < 6:  # _FIXED.size
            raise Malformed("shorter than a tunnel header")
        id_end = 6 + frame[5]
        # Magic, version, key day and airframe id: checked once per airframe and key day,
        # then found by one look-up.
        known = self._headers.get(frame[:id_end])
        if known is None:
            known = self._header(frame, size)
        airframe, key_day, day, cipher, seen = known
        header_end = id_end + 18  # sent_ms 6, nonce 12
        if size < header_end + _TAG:
            raise Malformed("tunnel header lengths are inconsistent")
        if now_ms is None:
            now_ms = _utc_ms(self._clock())
        today = now_ms // _DAY_MS
        if key_day != today and key_day not in self._accepted_day_numbers(now_ms, today):
            raise AuthenticationFailed("key day outside the accepted range")
        sent_high, sent_low, salt, counter = _TAIL.unpack_from(frame, id_end)
        sessions = self._streams.get((stream, airframe))
        if sessions is None:
            sessions = self._streams[(stream, airframe)] = _Sessions()
        window = sessions.windows.get(salt)
        if window is not None and counter <= window.highest:
            offset = window.highest - counter
            if offset >= window.size or (window.bitmap >> offset) & 1:
                raise Replayed("frame counter already seen or behind the window")
        nonce = frame[id_end + 6 : header_end]
        try:
            payload = cipher.decrypt(nonce, frame[header_end:], frame[:header_end])
        except InvalidTag as exc:
            raise AuthenticationFailed("authentication tag did not verify") from exc
        # Freshness is judged only after authentication, so a forged timestamp costs nothing.
        sent_ms = sent_high << 32 | sent_low
        if abs(now_ms - sent_ms) > self.freshness_s * 1000:
            raise Replayed("frame is older (or newer) than the freshness window")
        if sent_ms < self.started_ms:
            raise Replayed("frame sealed before the gateway started (a replay across a restart?)")
        # A frame first accepted on another link more than ``cross_link_s`` ago is refused:
        # the same sealed frame on two of an airframe's links at nearly the same time is
        # redundancy (ingest delivers it once); on a second link seconds later it is a capture
        # replayed there, which the per-link windows alone would accept.
        first = seen.get(nonce)
        if first is None:
            seen[nonce] = (time.monotonic(), stream)
            if len(seen) & _PRUNE_MASK == 0:
                self._prune_accepted(seen, time.monotonic())
        elif first[1] != stream and time.monotonic() - first[0] > self.cross_link_s:
            raise Replayed("frame already accepted on another link (a replay there?)")
        if window is None:
            self._forget_idle(sessions, now_ms)
            window = ReplayWindow()
            sessions.windows[salt] = window
        window.record(counter)
        window.last_seen_ms = now_ms
        return _new_tuple(Opened, (airframe, payload, day, sent_ms))

    def _header(self, frame: bytes, size: int) -> _Header:
        """Check a header not seen before: magic, version, lengths, airframe, key day.

        Raises as ``open_frame`` documents; a header that passes is remembered (bounded:
        configured airframes, accepted key days) with its airframe, day and cipher.
        """
        magic, version, key_day, id_len = _FIXED.unpack_from(frame)
        if magic != MAGIC:
            if frame[0] in _PLAIN_MAVLINK:
                raise Malformed("plain MAVLink on a tunnel link (does the sender have its key?)")
            raise Malformed("not a tunnel frame (bad magic)")
        if version != VERSION:
            raise Malformed(f"tunnel version {version} is not supported")
        id_end = _FIXED.size + id_len
        if id_len == 0 or id_len > MAX_ID_BYTES or size < id_end + 6 + _NONCE + _TAG:
            raise Malformed("tunnel header lengths are inconsistent")
        try:
            airframe = frame[_FIXED.size : id_end].decode("ascii")
        except UnicodeDecodeError as exc:
            raise Malformed("airframe id is not ASCII") from exc
        if airframe not in self._airframes:
            raise AuthenticationFailed("frame from an unknown airframe")
        # The key day is judged before a key is derived for it: an attacker's choice of day
        # costs no key derivation and takes no room here.
        now_ms = _utc_ms(self._clock())
        today = now_ms // _DAY_MS
        if key_day != today and key_day not in self._accepted_day_numbers(now_ms, today):
            raise AuthenticationFailed("key day outside the accepted range")
        day = self._day(key_day)
        cipher = self._keys.aead(airframe, day)
        if cipher is None:
            raise AuthenticationFailed("no key for this airframe and day")
        if len(self._headers) >= _MAX_HEADERS:
            self._headers.clear()  # days went by: the headers of today are learnt again
        seen = self._accepted.get(airframe)
        if seen is None:
            seen = self._accepted[airframe] = {}
        known = self._headers[bytes(frame[:id_end])] = (airframe, key_day, day, cipher, seen)
        return known

    def _prune_accepted(self, seen: _Seen, now: float) -> None:
        # Oldest first (a dict keeps insertion order): forget what the freshness window
        # refuses anyway, and cap the rest. Run every _PRUNE_MASK + 1 insertions, not per frame.
        horizon = now - 2 * self.freshness_s
        excess = len(seen) - _MAX_ACCEPTED
        stale = []
        for nonce, (accepted, _stream) in seen.items():
            if excess <= 0 and accepted >= horizon:
                break
            stale.append(nonce)
            excess -= 1
        for nonce in stale:
            del seen[nonce]

    def _forget_idle(self, sessions: _Sessions, now_ms: int) -> None:
        limit = self.freshness_s * 1000 * 2
        idle = [s for s, w in sessions.windows.items() if now_ms - w.last_seen_ms > limit]
        for salt in idle:
            del sessions.windows[salt]
