"""A C2 server for tests: a real HTTPS server on loopback that requires a client certificate.

``HttpsPeer`` listens on 127.0.0.1 with TLS from its own trustme CA and requires a client
certificate from that CA (``ssl.CERT_REQUIRED``: a missing or foreign certificate is refused
at the handshake, and OpenSSL's alert is sent so the client can say why). It speaks enough
HTTP/1.1 for a client (Content-Length bodies, keep-alive) and hands each request to the
subclass's ``_answer(head, body)``, which returns ``(status, json_answer)`` or
``(status, json_answer, extra_headers)``. It can drop the connection for the first
``drop_first`` POSTs, and be ``down`` (every new connection closed before the handshake, and
a kept one at its next request, unanswered).

In an async test ``async with Peer(tmp_path) as peer: ...``; from a sync test (a daemon
subprocess, ``check_sink``) ``with Peer(tmp_path).in_thread() as peer: ...``. The CA, the
client certificate and its key are PEM files in ``directory`` from construction on
(``peer.ca_file``, ``peer.cert_file``, ``peer.key_file``); ``peer.port`` is known once the
server listens. ``GutePeer`` and ``SlbPeer`` build on it.
"""

from __future__ import annotations

import json
import ssl
from collections.abc import Iterator
from contextlib import AsyncExitStack, contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Self
from urllib.parse import parse_qs, urlsplit

import anyio
import anyio.abc
import trustme
from anyio.from_thread import start_blocking_portal
from anyio.streams.buffered import BufferedByteReceiveStream
from anyio.streams.tls import TLSStream

MAX_HEAD_BYTES = 16_384
MAX_BODY_BYTES = 1 << 20

Answer = tuple[int, Any] | tuple[int, Any, dict[str, str]]


@dataclass
class Request:
    """One request the peer answered (or dropped): what came and what went back."""

    method: str
    path: str
    headers: dict[str, str]
    status: int | None
    body: bytes = b""
    query: dict[str, list[str]] = field(default_factory=dict)


@dataclass
class Head:
    """A parsed request line and headers (names in lower case; the query split off)."""

    method: str
    path: str
    headers: dict[str, str] = field(default_factory=dict)
    query: dict[str, list[str]] = field(default_factory=dict)


class Malformed(Exception):
    """The request cannot be parsed; the connection is answered 400 and closed."""


class AlertingTLSStream(TLSStream):
    """A TLS stream that sends OpenSSL's alert when the handshake fails, as servers do.

    anyio's ``TLSStream`` drops the alert OpenSSL wrote on a failed handshake; without it a
    TLS 1.3 client only sees the connection reset, not *why* its certificate was refused.
    """

    async def _call_sslobject_method(self, func: Any, *args: Any) -> Any:
        try:
            return await super()._call_sslobject_method(func, *args)
        except ssl.SSLError:
            alert = self._write_bio.read()
            if alert:
                with suppress(OSError, anyio.BrokenResourceError, anyio.ClosedResourceError):
                    await self.transport_stream.send(alert)
            raise


class HttpsPeer:
    """A C2 server over real HTTPS with client certificates; subclasses answer requests."""

    def __init__(
        self,
        directory: Path,
        *,
        drop_first: int = 0,
        server_name: str = "127.0.0.1",
        file_prefix: str = "peer",
    ) -> None:
        self.directory = directory
        self.drop_first = drop_first
        #: True: every new connection is closed at once, before the TLS handshake, and a kept
        #: one when its next request has come, unanswered.
        self.down = False
        self.ca = trustme.CA()
        self.server_cert = self.ca.issue_cert(server_name)
        client = self.ca.issue_cert("fischer-gateway")
        directory.mkdir(parents=True, exist_ok=True)
        self.ca_file = directory / f"{file_prefix}-ca.pem"
        self.cert_file = directory / f"{file_prefix}-client.pem"
        self.key_file = directory / f"{file_prefix}-client.key"
        self.ca.cert_pem.write_to_path(str(self.ca_file))
        for blob in client.cert_chain_pems:
            blob.write_to_path(str(self.cert_file), append=True)
        client.private_key_pem.write_to_path(str(self.key_file))
        self.port = 0
        #: Every request in arrival order, with the status answered (None: dropped).
        self.requests: list[Request] = []
        #: Why each refused TLS handshake failed (a missing or foreign client certificate).
        self.handshake_failures: list[str] = []
        #: Connections (new or kept) closed unanswered because the peer was ``down``.
        self.refused_while_down = 0
        self._stack: AsyncExitStack | None = None

    def tls_options(self) -> dict[str, str]:
        """The TLS options of a client that trusts this peer and is trusted by it."""
        return {
            "ca_file": str(self.ca_file),
            "cert_file": str(self.cert_file),
            "key_file": str(self.key_file),
        }

    @property
    def posts(self) -> list[Request]:
        """The POST requests, in arrival order."""
        return [r for r in self.requests if r.method == "POST"]

    def server_context(self) -> ssl.SSLContext:
        """TLS for the listener: our server certificate, client certificates required."""
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.verify_mode = ssl.CERT_REQUIRED
        self.server_cert.configure_cert(context)
        self.ca.configure_trust(context)
        return context

    def _answer(self, head: Head, body: bytes) -> Answer:
        raise NotImplementedError

    # -- lifetime -----------------------------------------------------------------------------

    async def __aenter__(self) -> Self:
        async with AsyncExitStack() as stack:
            listener = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=0)
            await stack.enter_async_context(listener)
            self.port = int(listener.extra(anyio.abc.SocketAttribute.local_port))
            tg = await stack.enter_async_context(anyio.create_task_group())
            context = self.server_context()
            tg.start_soon(listener.serve, lambda stream: self._connection(stream, context))
            stack.callback(tg.cancel_scope.cancel)
            self._stack = stack.pop_all()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        stack, self._stack = self._stack, None
        if stack is not None:
            await stack.__aexit__(exc_type, exc, tb)

    @contextmanager
    def in_thread(self) -> Iterator[Self]:
        """Serve from an event loop in a thread for the block (for sync tests)."""
        with start_blocking_portal() as portal, portal.wrap_async_context_manager(self):
            yield self

    # -- one connection -----------------------------------------------------------------------

    async def _connection(self, raw: anyio.abc.ByteStream, context: ssl.SSLContext) -> None:
        try:
            if self.down:
                self.refused_while_down += 1
                return
            await self._serve(raw, context)
        finally:
            # Also when the peer is shut down mid-handshake: no socket outlives the test.
            await anyio.aclose_forcefully(raw)

    async def _serve(self, raw: anyio.abc.ByteStream, context: ssl.SSLContext) -> None:
        try:
            stream = await AlertingTLSStream.wrap(
                raw, server_side=True, ssl_context=context, standard_compatible=False
            )
        except (ssl.SSLError, OSError, anyio.BrokenResourceError, anyio.EndOfStream) as exc:
            self.handshake_failures.append(str(getattr(exc, "reason", None) or exc))
            return
        reader = BufferedByteReceiveStream(stream)
        try:
            while await self._exchange(reader, stream):
                pass
        except (anyio.EndOfStream, anyio.IncompleteRead, anyio.BrokenResourceError):
            pass
        except (ssl.SSLError, OSError):
            pass
        finally:
            await anyio.aclose_forcefully(stream)

    async def _exchange(self, reader: BufferedByteReceiveStream, stream: TLSStream) -> bool:
        """Read one request and answer it; False when the connection is to close."""
        try:
            head = parse_head(await reader.receive_until(b"\r\n\r\n", MAX_HEAD_BYTES))
            length = _content_length(head)
        except (Malformed, anyio.DelimiterNotFound) as exc:
            await respond(stream, 400, {"error": str(exc) or "request head too long"}, False)
            return False
        body = await reader.receive_exactly(length) if length else b""
        if self.down:
            # A server going down drops its kept connections too, unanswered.
            self.refused_while_down += 1
            return False
        keep_alive = head.headers.get("connection", "").lower() != "close"
        request = Request(head.method, head.path, head.headers, None, body, head.query)
        self.requests.append(request)
        if head.method == "POST" and self.drop_first > 0:
            self.drop_first -= 1
            return False
        status, answer, *extra = self._answer(head, body)
        request.status = status
        await respond(stream, status, answer, keep_alive, extra[0] if extra else None)
        return keep_alive


def parse_head(raw: bytes) -> Head:
    """The request line and headers of ``raw`` (up to the blank line)."""
    try:
        lines = raw.decode("latin-1").split("\r\n")
        method, target, http_version = lines[0].split(" ")
    except ValueError:
        raise Malformed("bad request line") from None
    if http_version != "HTTP/1.1":
        raise Malformed(f"expected HTTP/1.1, got {http_version}")
    parts = urlsplit(target)
    head = Head(method, parts.path, query=parse_qs(parts.query))
    for line in lines[1:]:
        name, sep, value = line.partition(":")
        if not sep:
            raise Malformed(f"bad header line {line!r}")
        head.headers[name.strip().lower()] = value.strip()
    return head


def _content_length(head: Head) -> int:
    if "transfer-encoding" in head.headers:
        raise Malformed("send Content-Length, not Transfer-Encoding")
    try:
        length = int(head.headers.get("content-length", "0"))
    except ValueError:
        raise Malformed("bad Content-Length") from None
    if not 0 <= length <= MAX_BODY_BYTES:
        raise Malformed(f"Content-Length {length} out of range")
    return length


_REASONS = {
    200: "OK",
    201: "Created",
    204: "No Content",
    400: "Bad Request",
    404: "Not Found",
    405: "Method Not Allowed",
    409: "Conflict",
    415: "Unsupported Media Type",
    422: "Unprocessable Content",
    429: "Too Many Requests",
    503: "Service Unavailable",
}


async def respond(
    stream: TLSStream,
    status: int,
    answer: Any,
    keep_alive: bool,
    headers: dict[str, str] | None = None,
) -> None:
    """Send one response: ``answer`` as JSON, or as it is if bytes (no body for 204)."""
    if status == 204:
        body = b""
    elif isinstance(answer, bytes):
        body = answer
    else:
        body = json.dumps(answer).encode()
    extra = "".join(f"{name}: {value}\r\n" for name, value in (headers or {}).items())
    head = (
        f"HTTP/1.1 {status} {_REASONS.get(status, 'Status')}\r\n"
        "Content-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\n"
        f"{extra}"
        f"Connection: {'keep-alive' if keep_alive else 'close'}\r\n\r\n"
    )
    await stream.send(head.encode() + body)
