"""Tunnel frames on stream links (TCP, serial): a 2-byte length prefix, and resynchronisation.

On a datagram link each datagram is one tunnel frame. A stream has no boundaries, so each
frame is preceded by its length (big-endian u16). After garbage, a cut connection or a
corrupted length the deframer slides forward one byte at a time until a length and the
tunnel magic line up again and the frame authenticates.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from gateway.errors import FrameError
from gateway.fleet.security.tunnel import MAGIC

__all__ = ["StreamDeframer", "frame_for_stream"]

T = TypeVar("T")
_MIN_FRAME = 2 + 1 + 2 + 1 + 1 + 6 + 12 + 16


def frame_for_stream(sealed: bytes) -> bytes:
    """Prefix a sealed tunnel frame with its length, for a stream link."""
    if len(sealed) > 0xFFFF:
        raise ValueError("a tunnel frame on a stream is at most 65535 bytes")
    return len(sealed).to_bytes(2, "big") + sealed


class StreamDeframer:
    """Splits a byte stream into tunnel frames and opens them with ``open_frame``.

    ``feed`` returns what ``open_frame`` returned for every frame that opened; every frame
    that failed is counted in ``errors`` (by ``FrameError.reason``) and skipped, and the
    buffered bytes never exceed ``max_frame_bytes`` + 2.
    """

    def __init__(self, max_frame_bytes: int = 2048) -> None:
        self.max_frame_bytes = max_frame_bytes
        self._buf = bytearray()
        self.errors: dict[str, int] = {}
        self.skipped_bytes = 0
        #: Frames that failed authentication since the last one that opened.
        self.failed_in_a_row = 0
        self._in_garbage = False

    def _skip(self, count: int) -> None:
        del self._buf[:count]
        self.skipped_bytes += count
        if not self._in_garbage:
            # A run of bytes that are not frames counts once, as one malformed frame.
            self._in_garbage = True
            self.errors["malformed"] = self.errors.get("malformed", 0) + 1

    def feed(self, data: bytes, open_frame: Callable[[bytes], T]) -> list[T]:
        """Add ``data`` and return the opened frames it completed."""
        self._buf += data
        out: list[T] = []
        buf = self._buf
        while len(buf) >= 4:
            length = int.from_bytes(buf[:2], "big")
            if length < _MIN_FRAME or length > self.max_frame_bytes or buf[2:4] != MAGIC:
                # Not a frame start: slide to the next byte that could begin one.
                nxt = buf.find(MAGIC, 3)
                self._skip(nxt - 2 if nxt >= 2 else max(len(buf) - 3, 1))
                continue
            if len(buf) < 2 + length:
                break
            frame = bytes(buf[2 : 2 + length])
            try:
                out.append(open_frame(frame))
            except FrameError as exc:
                self.errors[exc.reason] = self.errors.get(exc.reason, 0) + 1
                self.failed_in_a_row += 1
                if exc.reason in ("malformed", "auth"):
                    # It may have been garbage that looked like a header: resync inside it.
                    self._in_garbage = True  # counted just now
                    self._skip(1)
                    continue
            else:
                self.failed_in_a_row = 0
            self._in_garbage = False
            del buf[: 2 + length]
        return out
