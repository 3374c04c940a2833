"""A small HTTP/1.1 client for one HTTPS origin: kept TLS connections, bounded answers.

``Http1Origin`` POSTs a body to one ``https://`` URL and returns the ``Reply``: the status,
the headers and at most ``limit`` bytes of the body. It is what ``HttpsPoster`` POSTs with
(the ``gute2`` and ``slb`` sinks): a request is one write on a kept connection and its answer
is parsed here, without httpx's per-request machinery; with five ``gute2`` sinks that halved
the time from the track to the cue at the last battery (``bench/cue.py``).

- **TLS** is the caller's ``ssl.SSLContext`` (``gateway.transports.tls.tls_context``: the
  pinned CA, the hostname always checked, the client certificate presented); the server's
  name is the URL's host.
- **Kept connections.** A connection whose answer was read to its end, and that neither side
  asked to close, goes back to the idle pool (at most ``max_connections``); one the server has
  closed (or that holds bytes nobody asked for) is dropped before it is used.
- **A server closing a kept connection.** A POST sent on a *reused* connection that ends
  before a single byte of an answer came back is sent once more, on a new connection. The
  server may have received (and even processed) the first: every POST of the gateway carries
  an ``Idempotency-Key``, which the C2 server de-duplicates (answering 409, taken as
  delivered), so the second cannot be delivered twice. A POST on a *new* connection is never
  re-sent here; that failure goes to the caller (the sink's runner retries it later).
- **Bounds.** The answer's head is at most ``MAX_HEAD_BYTES`` and ``MAX_HEADERS`` lines, at
  most ``MAX_INTERIM`` interim (1xx) answers are skipped, a body is kept up to ``limit`` bytes
  and read on (so the connection can be kept) up to ``MAX_DRAIN_BYTES``, after which the
  connection is dropped instead. Content-Length, chunked and read-until-close bodies are read.
  Memory is bounded by the socket buffer: reading pauses past ``MAX_BUFFER_BYTES``.
- **No deadline here**: the caller bounds the whole exchange (``asyncio.timeout``); a
  cancelled exchange drops its connection.

Anything the server sends that is not an HTTP/1.1 answer within those bounds raises
``HttpAnswerError`` saying what; a connection lost raises ``ConnectionError`` (``OSError``),
TLS failures ``ssl.SSLError``.
"""

from __future__ import annotations

import asyncio
import ssl
from dataclasses import dataclass
from typing import cast
from urllib.parse import quote, urlsplit

import anyio

from gateway.errors import HttpAnswerError

__all__ = [
    "CLOSE_WAIT_S",
    "MAX_DRAIN_BYTES",
    "MAX_HEADERS",
    "MAX_HEAD_BYTES",
    "MAX_INTERIM",
    "Http1Origin",
    "Reply",
]

#: The longest answer head (status line and headers) read.
MAX_HEAD_BYTES = 16_384
#: The most header lines an answer may have.
MAX_HEADERS = 100
#: Interim (1xx) answers skipped before the final one, at most.
MAX_INTERIM = 8
#: A body is read to its end (so that the connection is kept) up to this size; past it the
#: connection is dropped rather than read on.
MAX_DRAIN_BYTES = 65_536
#: Reading from the socket pauses while this much is buffered and unread.
MAX_BUFFER_BYTES = 262_144
#: How long ``aclose`` waits for a server to answer the TLS close_notify, at most.
CLOSE_WAIT_S = 0.25
#: The longest chunk-size line of a chunked body.
_MAX_CHUNK_LINE = 1_024
#: What a chunk size is written in (RFC 9112 7.1: 1*HEXDIG).
_HEX_DIGITS = b"0123456789abcdefABCDEF"
#: Characters a request target keeps as they are (RFC 3986 pchar, "/" and escapes).
_TARGET_SAFE = "/%:@!$&'()*+,;=-._~"
#: How much of an unreadable answer is quoted in the error.
_QUOTE = 40


@dataclass(frozen=True, slots=True)
class Reply:
    """One final answer: status, headers (names in lower case) and the body, bounded."""

    status: int
    reason_phrase: str
    headers: dict[str, str]
    body: bytes


class _Wire(asyncio.Protocol):
    """One TLS connection's bytes: a bounded buffer the exchange reads from."""

    def __init__(self) -> None:
        self.transport: asyncio.Transport | None = None
        self.buffer = bytearray()
        self.closed = False
        self.error: BaseException | None = None
        #: True once a byte of the current exchange's answer has arrived.
        self.answer_started = False
        self._waiter: asyncio.Future[None] | None = None
        self._paused = False
        self._writable: asyncio.Future[None] | None = None
        self._gone = False
        self._lost_at: asyncio.Future[None] | None = None

    # -- asyncio.Protocol ------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # A stream connection (uvloop's TLS transport is one without subclassing it).
        self.transport = cast("asyncio.Transport", transport)

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        self.answer_started = True
        if len(self.buffer) > MAX_BUFFER_BYTES and self.transport is not None:
            self.transport.pause_reading()
            self._paused = True
        self._wake()

    def eof_received(self) -> bool | None:
        self.closed = True
        self._wake()
        return None  # close the transport

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = self._gone = True
        if self._lost_at is not None and not self._lost_at.done():
            self._lost_at.set_result(None)
        if exc is not None and self.error is None:
            self.error = exc
        self._wake()
        if self._writable is not None and not self._writable.done():
            self._writable.set_result(None)

    def pause_writing(self) -> None:
        if self._writable is None or self._writable.done():
            self._writable = asyncio.get_running_loop().create_future()

    def resume_writing(self) -> None:
        if self._writable is not None and not self._writable.done():
            self._writable.set_result(None)

    # -- the exchange's side ---------------------------------------------------------------

    def _wake(self) -> None:
        waiter, self._waiter = self._waiter, None
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    @property
    def idle_and_open(self) -> bool:
        """Open, nothing unread: fit for the next request."""
        return not self.closed and not self.buffer and self.transport is not None

    async def send(self, data: bytes) -> None:
        """Write ``data``, waiting while the transport's buffer is full."""
        if self.closed or self.transport is None:
            raise self._lost("before the request was sent")
        self.answer_started = False
        self.transport.write(data)
        if self._writable is not None and not self._writable.done():
            await self._writable
        if self.error is not None:
            raise self._lost("while sending the request")

    async def _more(self) -> None:
        """Wait for more bytes; raises if the connection ends first."""
        if self.closed:
            raise self._lost("mid-answer" if self.answer_started else "before any answer")
        if self._paused and self.transport is not None:
            self._paused = False
            self.transport.resume_reading()
        self._waiter = asyncio.get_running_loop().create_future()
        try:
            await self._waiter
        finally:
            self._waiter = None

    def _lost(self, when: str) -> OSError:
        """What to raise for a connection gone ``when``: its TLS error, else a reset."""
        cause = self.error
        if isinstance(cause, ssl.SSLError):
            return cause  # e.g. the server's alert refusing our certificate
        text = f"the server closed the connection {when}"
        if cause is not None:
            text += f" ({cause})"
        error = ConnectionResetError(text)
        error.__cause__ = cause
        return error

    async def read_until(self, delimiter: bytes, limit: int, what: str) -> bytes:
        """Bytes up to and including ``delimiter``, at most ``limit`` of them."""
        start = 0
        while True:
            at = self.buffer.find(delimiter, start)
            if at >= 0:
                end = at + len(delimiter)
                if end > limit:
                    break
                data = bytes(self.buffer[:end])
                del self.buffer[:end]
                return data
            if len(self.buffer) > limit:
                break
            start = max(0, len(self.buffer) - len(delimiter) + 1)
            await self._more()
        raise HttpAnswerError(f"{what} longer than {limit} bytes")

    async def read_exactly(self, n: int, keep: int) -> bytes:
        """Read ``n`` bytes; return the first ``keep`` of them."""
        kept = bytearray()
        while n > 0:
            if not self.buffer:
                await self._more()
                continue
            take = min(n, len(self.buffer))
            if len(kept) < keep:
                kept += self.buffer[: min(take, keep - len(kept))]
            del self.buffer[:take]
            n -= take
        return bytes(kept)

    async def read_to_close(self, keep: int, most: int) -> tuple[bytes, bool]:
        """Read until the server closes, at most ``most`` bytes; the first ``keep`` and whether
        the end was reached."""
        kept = bytearray()
        seen = 0
        while True:
            if self.buffer:
                take = len(self.buffer)
                if len(kept) < keep:
                    kept += self.buffer[: keep - len(kept)]
                del self.buffer[:take]
                seen += take
                if seen > most:
                    return bytes(kept), False
            elif self.closed:
                if self.error is not None and not isinstance(self.error, ssl.SSLError):
                    raise self._lost("mid-answer")
                return bytes(kept), True
            else:
                await self._more()

    def abort(self) -> None:
        """Drop the connection now (nothing more is sent)."""
        self.closed = True
        if self.transport is not None:
            self.transport.abort()

    def close(self) -> None:
        """Close the connection politely (TLS close_notify), without waiting."""
        self.closed = True
        if self.transport is not None:
            self.transport.close()

    async def wait_lost(self) -> None:
        """Until the connection is gone (``connection_lost``)."""
        if self._lost_at is None:
            self._lost_at = asyncio.get_running_loop().create_future()
        if not self._gone:
            await self._lost_at


def _quote(data: bytes) -> str:
    return repr(bytes(data[:_QUOTE])) + ("..." if len(data) > _QUOTE else "")


def _parse_head(raw: bytes) -> tuple[int, str, str, dict[str, str]]:
    """Version, status, reason phrase and headers of an answer head (ends with CRLFCRLF)."""
    lines = raw[:-4].split(b"\r\n")
    status_line = lines[0]
    version, _, rest = status_line.partition(b" ")
    code, _, phrase = rest.partition(b" ")
    if version not in (b"HTTP/1.1", b"HTTP/1.0") or len(code) != 3 or not code.isdigit():
        raise HttpAnswerError(f"not an HTTP/1.1 answer: {_quote(status_line)}")
    if len(lines) - 1 > MAX_HEADERS:
        raise HttpAnswerError(f"more than {MAX_HEADERS} header lines in the answer")
    headers: dict[str, str] = {}
    for line in lines[1:]:
        name, sep, value = line.partition(b":")
        if not sep or not name or name != name.strip() or b" " in name or b"\t" in name:
            raise HttpAnswerError(f"bad header line in the answer: {_quote(line)}")
        key = name.decode("latin-1").lower()
        text = value.strip(b" \t").decode("latin-1")
        headers[key] = f"{headers[key]}, {text}" if key in headers else text
    return int(code), version.decode(), phrase.decode("latin-1").strip(), headers


def _content_length(headers: dict[str, str]) -> int | None:
    value = headers.get("content-length")
    if value is None:
        return None
    values = {v.strip() for v in value.split(",")}  # repeated, equal values are one
    if len(values) != 1 or not (only := values.pop()).isascii() or not only.isdigit():
        raise HttpAnswerError(f"bad Content-Length in the answer: {value[:_QUOTE]!r}")
    return int(only)


class Http1Origin:
    """HTTP/1.1 over kept TLS connections to the origin of ``url``; POSTs to ``url``."""

    def __init__(self, url: str, context: ssl.SSLContext, *, max_connections: int) -> None:
        parts = urlsplit(url)
        if parts.scheme != "https" or not parts.hostname:
            raise ValueError(f"expected an https:// URL, got {url!r}")
        self.url = url
        self.host = parts.hostname
        self.port = parts.port or 443
        self.context = context
        self.max_connections = max_connections
        # As a browser sends it: what may not stand in a request target percent-encoded.
        target = quote(parts.path or "/", safe=_TARGET_SAFE)
        if parts.query:
            target += "?" + quote(parts.query, safe=_TARGET_SAFE + "?")
        #: The request target sent: the URL's path and query, percent-encoded where need be.
        self.target = target
        authority = parts.netloc.rpartition("@")[2]
        self._request_line = f"POST {target} HTTP/1.1\r\nHost: {authority}\r\n".encode("ascii")
        self._idle: list[_Wire] = []
        self._open: set[_Wire] = set()

    async def post(self, headers: dict[str, str], body: bytes, *, limit: int) -> Reply:
        """POST ``body`` with ``headers`` (plus Host and Content-Length); the final answer.

        ``ValueError`` if a header cannot be sent (a control character); raises
        ``HttpAnswerError``, ``OSError`` or ``ssl.SSLError`` when no answer could be read.
        """
        request = self._request(headers, body)
        wire = self._take_idle()
        if wire is not None:
            try:
                return await self._exchange(wire, request, limit)
            except ConnectionError:
                if wire.answer_started:
                    raise
                # The server closed the kept connection before answering: once more on a new
                # one (the idempotency key makes a second delivery a 409, never a duplicate).
        wire = await self._connect()
        return await self._exchange(wire, request, limit)

    def _request(self, headers: dict[str, str], body: bytes) -> bytes:
        head = bytearray(self._request_line)
        for name, value in headers.items():
            line = f"{name}: {value}\r\n"
            if not line[:-2].isprintable() or not line.isascii():
                raise ValueError(f"header {name} cannot be sent: {value[:_QUOTE]!r}")
            head += line.encode("ascii")
        head += b"Content-Length: %d\r\n\r\n" % len(body)
        return bytes(head) + body

    def _take_idle(self) -> _Wire | None:
        while self._idle:
            wire = self._idle.pop()
            if wire.idle_and_open:
                return wire
            self._forget(wire)
        return None

    async def _connect(self) -> _Wire:
        loop = asyncio.get_running_loop()
        wire = _Wire()
        await loop.create_connection(
            lambda: wire, self.host, self.port, ssl=self.context, server_hostname=self.host
        )
        self._open.add(wire)
        return wire

    def _forget(self, wire: _Wire) -> None:
        wire.abort()
        self._open.discard(wire)

    async def _exchange(self, wire: _Wire, request: bytes, limit: int) -> Reply:
        keep = False
        try:
            await wire.send(request)
            reply, keep = await self._answer(wire, limit)
        finally:
            if keep and len(self._idle) < self.max_connections:
                self._idle.append(wire)
            else:
                self._forget(wire)
        return reply

    async def _answer(self, wire: _Wire, limit: int) -> tuple[Reply, bool]:
        for _ in range(MAX_INTERIM + 1):
            raw = await wire.read_until(b"\r\n\r\n", MAX_HEAD_BYTES, "the answer's head")
            status, version, phrase, headers = _parse_head(raw)
            if status == 101:  # Switching Protocols: we asked for none
                raise HttpAnswerError("the server switched protocols unasked (101)")
            if status >= 200:  # a final answer
                break
        else:
            raise HttpAnswerError(f"more than {MAX_INTERIM} interim (1xx) answers")
        connection = headers.get("connection", "").lower()
        keep = "close" not in connection and (version == "HTTP/1.1" or "keep-alive" in connection)
        if status in (204, 304):
            return Reply(status, phrase, headers, b""), keep
        if "transfer-encoding" in headers:
            codings = [c.strip() for c in headers["transfer-encoding"].lower().split(",")]
            if codings[-1] != "chunked":
                raise HttpAnswerError(
                    f"unreadable Transfer-Encoding: {headers['transfer-encoding'][:_QUOTE]!r}"
                )
            body, ended = await self._chunked(wire, limit)
            # With a Content-Length too, the answer was smuggled or mangled: do not keep it.
            keep = keep and ended and "content-length" not in headers
            return Reply(status, phrase, headers, body), keep
        length = _content_length(headers)
        if length is None:
            body, _ = await wire.read_to_close(limit, MAX_DRAIN_BYTES)
            return Reply(status, phrase, headers, body), False
        if length > MAX_DRAIN_BYTES:
            body = await wire.read_exactly(min(length, limit), limit)
            return Reply(status, phrase, headers, body), False
        return Reply(status, phrase, headers, await wire.read_exactly(length, limit)), keep

    async def _chunked(self, wire: _Wire, limit: int) -> tuple[bytes, bool]:
        """A chunked body's first ``limit`` bytes, and whether it was read to its end."""
        kept = bytearray()
        seen = 0
        while True:
            line = await wire.read_until(b"\r\n", _MAX_CHUNK_LINE, "a chunk-size line")
            size_text = line[:-2].split(b";", 1)[0].strip(b" \t")
            # Hex digits only: int(..., 16) alone also takes a sign, "0x" and underscores.
            if not size_text or size_text.strip(_HEX_DIGITS):
                raise HttpAnswerError(f"bad chunk size in the answer: {_quote(line)}")
            size = int(size_text, 16)
            if size == 0:
                break
            seen += size
            if seen > MAX_DRAIN_BYTES:
                kept += await wire.read_exactly(min(size, limit), limit - len(kept))
                return bytes(kept[:limit]), False
            kept += await wire.read_exactly(size, max(0, limit - len(kept)))
            if await wire.read_exactly(2, 2) != b"\r\n":
                raise HttpAnswerError("a chunk of the answer does not end with CRLF")
        # Trailers, if any, then the blank line; bounded like a head.
        for _ in range(MAX_HEADERS + 1):
            if await wire.read_until(b"\r\n", MAX_HEAD_BYTES, "a trailer line") == b"\r\n":
                return bytes(kept), True
        raise HttpAnswerError(f"more than {MAX_HEADERS} trailer lines in the answer")

    async def aclose(self, timeout_s: float) -> None:
        """Close every connection: TLS close_notify, then up to ``timeout_s`` (at most
        ``CLOSE_WAIT_S``) for the server's side before the socket is dropped. Shielded: a
        cancelled caller still leaves no socket open; a server that never answers the
        close_notify does not hold a shutdown."""
        wires, self._open = list(self._open), set()
        self._idle.clear()
        with anyio.CancelScope(shield=True), anyio.move_on_after(min(timeout_s, CLOSE_WAIT_S)):
            for wire in wires:
                wire.close()
            for wire in wires:
                await wire.wait_lost()
        for wire in wires:
            wire.abort()
