"""Length-prefixed frames over a TLS client stream: a 4-byte big-endian length, then the bytes.

``connect_tls`` opens a TCP connection (``open_tcp``: non-blocking, keep-alive, no Nagle
delay; here the keep-alive probes start after ``KEEPALIVE_IDLE_S`` so a peer that vanished
without closing is noticed within about a minute even on a silent connection) and runs the
TLS handshake with a context from ``gateway.transports.tls`` (CA pinned, hostname checked,
client certificate presented). ``FrameStream`` carries frames on it:

- ``receive`` reads one whole frame or raises: ``Oversize`` when the length is over
  ``max_frame_bytes`` (nothing more is read: the stream cannot be followed after it),
  ``Malformed`` when the peer hangs up inside a frame, ``LinkClosed`` when it hangs up
  between frames or the connection fails. It is cancellation-safe: bytes already read stay
  buffered for the next call.
- ``send`` writes one frame; a send cut short (an error or a cancellation) leaves half a frame
  on the wire, so the stream must then be closed.

The caller's deadline bounds every call; nothing here waits on its own.
"""

from __future__ import annotations

import errno
import socket
import ssl
import struct

import anyio
import anyio.abc
from anyio.streams.tls import TLSStream

from gateway.errors import LinkClosed, Malformed, Oversize
from gateway.transports.stream import open_tcp

__all__ = ["HEADER", "KEEPALIVE_IDLE_S", "FrameStream", "connect_tls", "describe"]

#: The frame header: the payload's length as an unsigned 32-bit big-endian integer.
HEADER = struct.Struct(">I")
#: Seconds of silence before TCP keep-alive probes start (then every 10 s, 3 unanswered: gone).
KEEPALIVE_IDLE_S = 30
_READ_CHUNK = 65_536
_STREAM_ERRORS = (
    anyio.BrokenResourceError,
    anyio.ClosedResourceError,
    ssl.SSLError,
    OSError,
)


def _keepalive(sock: socket.socket) -> None:
    for option, value in (("TCP_KEEPIDLE", KEEPALIVE_IDLE_S), ("TCP_KEEPINTVL", 10)):
        if hasattr(socket, option):  # Linux names; elsewhere the system's defaults apply
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, option), value)
    if hasattr(socket, "TCP_KEEPCNT"):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT, 3)


async def connect_tls(
    host: str, port: int, context: ssl.SSLContext, hostname: str
) -> anyio.abc.ByteStream:
    """A TLS stream to ``host:port`` whose certificate must be valid for ``hostname``.

    Raises ``OSError`` when no connection is made or the peer hangs up during the handshake,
    and ``ssl.SSLError`` (or anyio's ``BrokenResourceError``) when the handshake fails. The
    caller sets the deadline.
    """
    raw = await open_tcp(host, port)
    try:
        _keepalive(raw)
        stream = await anyio.abc.SocketStream.from_socket(raw)
    except BaseException:
        raw.close()
        raise
    try:
        return await TLSStream.wrap(
            stream, hostname=hostname, ssl_context=context, standard_compatible=False
        )
    except anyio.EndOfStream:
        await anyio.aclose_forcefully(stream)
        raise OSError(
            errno.ECONNRESET, "the peer closed the connection during the TLS handshake"
        ) from None
    except BaseException:
        await anyio.aclose_forcefully(stream)
        raise


def describe(exc: BaseException) -> str:
    """The reason of a stream failure, looking through anyio's wrapping to OpenSSL's."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, ssl.SSLError):
            return str(seen.reason or seen)
        if isinstance(seen, OSError) and seen.strerror:
            return seen.strerror
        seen = seen.__cause__ or seen.__context__
    return str(exc) or type(exc).__name__


class FrameStream:
    """Frames on one byte stream, each within ``max_frame_bytes``; ``link`` names it in errors."""

    def __init__(self, stream: anyio.abc.ByteStream, *, max_frame_bytes: int, link: str) -> None:
        self.stream = stream
        self.max_frame_bytes = max_frame_bytes
        self.link = link
        self._buffer = bytearray()

    def _lost(self, exc: BaseException) -> LinkClosed:
        return LinkClosed(self.link, f"connection lost: {describe(exc)}", what="")

    async def send(self, payload: bytes) -> None:
        """Write ``payload`` as one frame; ``Oversize`` if it is over the bound."""
        if len(payload) > self.max_frame_bytes:
            raise Oversize(len(payload), self.max_frame_bytes, link=self.link)
        try:
            await self.stream.send(HEADER.pack(len(payload)) + payload)
        except _STREAM_ERRORS as exc:
            raise self._lost(exc) from exc

    async def _fill(self, size: int, *, between_frames: bool) -> bytes:
        while len(self._buffer) < size:
            try:
                chunk = await self.stream.receive(_READ_CHUNK)
            except anyio.EndOfStream:
                if between_frames and not self._buffer:
                    raise LinkClosed(self.link, "the peer closed the connection", what="") from None
                raise Malformed(
                    f"the connection ended inside a frame ({len(self._buffer)} of {size} bytes)",
                    link=self.link,
                ) from None
            except _STREAM_ERRORS as exc:
                raise self._lost(exc) from exc
            self._buffer += chunk
        data = bytes(self._buffer[:size])
        del self._buffer[:size]
        return data

    async def receive(self) -> bytes:
        """One frame's payload (possibly empty); see the module docstring for the errors."""
        (size,) = HEADER.unpack(await self._fill(HEADER.size, between_frames=True))
        if size > self.max_frame_bytes:
            raise Oversize(size, self.max_frame_bytes, link=self.link)
        # The header stays consumed even if this is cancelled: put it back in that case.
        try:
            return await self._fill(size, between_frames=False) if size else b""
        except BaseException:
            self._buffer[:0] = HEADER.pack(size)
            raise

    async def aclose(self) -> None:
        """Close the stream without waiting on the peer."""
        await anyio.aclose_forcefully(self.stream)
