"""MAVLink 1 and 2 parsing on pymavlink, bounded and with errors translated once.

One ``MavlinkParser`` per byte stream (a TCP connection, a serial device): the parser is
stateful, so two streams must never share one. A datagram link needs no per-sender parser:
each datagram is parsed on its own (``feed(..., whole=True)``) and what it leaves unfinished
is counted as truncated and dropped, never joined to the next sender's bytes. pymavlink's
v2.0 ``ardupilotmega`` dialect reads MAVLink 1 frames too, and real logs mix both.
"""

from __future__ import annotations

import struct
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as dialect

from gateway.errors import Malformed, Oversize

# Imported for their side effect: they register the project dialect's messages with the parser.
from gateway.fleet import dialect as _detection_messages  # noqa: F401
from gateway.fleet import hopdialect as _hop_messages  # noqa: F401
from gateway.fleet.fastdecode import default_decoder

_STX_V1 = 0xFE
_STX_V2 = 0xFD

__all__ = ["MAX_FRAME_BYTES", "MavMessage", "MavlinkParser", "crc_extra", "dialect", "split_frames"]

#: 10-byte header + 255 payload + 2 CRC + 13 signature: nothing longer is one MAVLink frame.
MAX_FRAME_BYTES = 280

MavMessage = Any
"""A pymavlink message object (pymavlink is untyped); never passes ``normalise``."""

_BAD_TYPES = frozenset({"BAD_DATA"})


class MavlinkParser:
    """Turns chunks of bytes from one stream into MAVLink messages.

    With ``fast=True`` (ingest's parsers), a datagram (``whole=True``) of whole frames is cut
    by their headers and each frame of a message the gateway handles is decoded by the fast
    path built from the dialect XML (``gateway.fleet.fastdecode``, held to pymavlink field
    for field; its messages read like pymavlink's but cannot be packed again); any other
    frame, and any stream, goes through pymavlink. ``feed`` returns the good messages and
    counts what was not: ``bad`` (CRC or framing failures, garbage bytes), ``unknown`` (a
    message id this dialect does not know, whose CRC cannot be checked) and ``truncated`` (a
    datagram that ended inside a frame). It raises ``Oversize`` for a chunk over
    ``max_chunk_bytes`` and never lets a pymavlink exception escape: those become
    ``Malformed`` after the parser state is reset.
    """

    __slots__ = ("_fast", "_mav", "bad", "max_chunk_bytes", "truncated", "unknown")

    def __init__(self, *, max_chunk_bytes: int = 2048, fast: bool = False) -> None:
        self.max_chunk_bytes = max_chunk_bytes
        self.bad = 0
        self.unknown = 0
        self.truncated = 0
        self._mav = self._new_mav()
        self._fast = default_decoder() if fast else None

    @staticmethod
    def _new_mav() -> Any:
        mav = dialect.MAVLink(None, srcSystem=0, srcComponent=0)
        mav.robust_parsing = True
        return mav

    def feed(self, data: bytes, *, whole: bool = False) -> list[MavMessage]:
        """Parse ``data``; return the complete, CRC-checked messages it finished.

        ``whole=True`` says ``data`` is a complete datagram: bytes left inside an unfinished
        frame are counted in ``truncated`` and dropped, so nothing carries over to the next.
        """
        if len(data) > self.max_chunk_bytes:
            raise Oversize(len(data), self.max_chunk_bytes)
        fast = self._fast
        if whole and fast is not None:
            size = len(data)
            if size >= 8 and size == (
                12 + data[1] + (13 if data[2] & 1 else 0)
                if data[0] == _STX_V2
                else 8 + data[1]
                if data[0] == _STX_V1
                else -1
            ):
                # One frame per datagram, the common case: decoded without cutting a list.
                try:
                    message = fast.decode(data)
                except Malformed:
                    self.bad += 1  # a CRC, length or flag pymavlink refuses too
                    return []
                return [message] if message is not None else self._pymavlink(data, whole=True)
            try:
                frames = split_frames(data)
            except Malformed:
                frames = []  # garbage or a frame cut short: pymavlink counts it, below
            if frames:
                return self._whole_frames(frames)
        return self._pymavlink(data, whole=whole)

    def _whole_frames(self, frames: list[bytes]) -> list[MavMessage]:
        """The frames of one datagram: the gateway's own messages by the fast path
        (``gateway.fleet.fastdecode``), every other one by pymavlink."""
        fast = self._fast
        assert fast is not None  # noqa: S101 - feed() calls this only with a fast decoder
        good: list[MavMessage] = []
        for frame in frames:
            try:
                message = fast.decode(frame)
            except Malformed:
                self.bad += 1  # a CRC, length or flag pymavlink refuses too
                continue
            if message is not None:
                good.append(message)
            else:
                good += self._pymavlink(frame, whole=True)
        return good

    def _pymavlink(self, data: bytes, *, whole: bool) -> list[MavMessage]:
        mav = self._mav
        try:
            # parse_buffer() always asks for one more message; a datagram usually holds
            # exactly one frame, so stop as soon as the buffer is empty.
            first = mav.parse_char(data)
            if first is None:
                parsed = []
            elif mav.buf_len() == 0:
                parsed = [first]
            else:
                parsed = [first]
                while (more := mav.parse_char(b"")) is not None:
                    parsed.append(more)
        except (dialect.MAVError, struct.error, IndexError, ValueError, TypeError) as exc:
            # pymavlink's buffer is in an unknown state after it raised: start clean.
            self._mav = self._new_mav()
            self.bad += 1
            raise Malformed(f"MAVLink parse failed: {type(exc).__name__}") from exc
        if whole and mav.buf_len():
            self.truncated += 1
            self._mav = self._new_mav()
        if not parsed:
            return []
        good: list[MavMessage] = []
        for msg in parsed:
            name = msg.get_type()
            if name in _BAD_TYPES:
                self.bad += 1
            elif name.startswith("UNKNOWN_"):
                self.unknown += 1
            else:
                good.append(msg)
        return good


def crc_extra(msgid: int) -> int | None:
    """The CRC_EXTRA byte of message ``msgid`` in our dialect; None if it is unknown."""
    cls = dialect.mavlink_map.get(msgid)
    return None if cls is None else int(cls.crc_extra)


def split_frames(data: bytes) -> list[bytes]:
    """Cut ``data`` into whole MAVLink frames by their headers (no CRC check).

    Raises ``Malformed`` for bytes that do not start a frame or a frame cut short.
    """
    frames: list[bytes] = []
    at = 0
    while at < len(data):
        stx = data[at]
        if stx == _STX_V2 and at + 3 <= len(data):
            length = 12 + data[at + 1] + (13 if data[at + 2] & 1 else 0)
        elif stx == _STX_V1 and at + 2 <= len(data):
            length = 8 + data[at + 1]
        else:
            raise Malformed("bytes that do not start a MAVLink frame")
        if at + length > len(data):
            raise Malformed("a MAVLink frame cut short")
        frames.append(data[at : at + length])
        at += length
    return frames
