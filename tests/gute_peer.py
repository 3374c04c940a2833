"""A GUTE II battery for tests: a real HTTPS server on loopback that takes handoffs.

``GutePeer`` listens on 127.0.0.1 with TLS from its own trustme CA and requires a client
certificate from that CA (``ssl.CERT_REQUIRED``: a missing or foreign certificate is refused
at the handshake). It speaks enough HTTP/1.1 for a client (Content-Length bodies, keep-alive),
validates every body with ``jsonschema`` against the shipped schema (400 when it fails), and
records accepted handoffs by ``Idempotency-Key``: a repeated key answers ``duplicate_status``
and is not recorded twice. It can fail the first ``fail_first`` POSTs with 503, drop the
connection for the first ``drop_first`` POSTs, and refuse chosen keys with a chosen status.

In an async test::

    async with GutePeer(tmp_path) as peer:
        sink = GuteSink("gute", GuteSinkConfig(**peer.sink_options()))

From a sync test (a daemon subprocess, ``check_sink``), the server runs in a thread::

    with GutePeer(tmp_path).in_thread() as peer:
        write the daemon config with sinks: [{type: gute2, options: peer.sink_options()}]
        wait_until(lambda: len(peer.accepted) == 1, 10, "the handoff")

The CA, the client certificate and its key are PEM files in ``directory`` from construction
on (``peer.ca_file``, ``peer.cert_file``, ``peer.key_file``); ``peer.url`` is known once the
server listens.
"""

from __future__ import annotations

import json
import ssl
from collections.abc import Iterator, Mapping
from contextlib import AsyncExitStack, contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import anyio
import anyio.abc
import trustme
from anyio.from_thread import start_blocking_portal
from anyio.streams.buffered import BufferedByteReceiveStream
from anyio.streams.tls import TLSStream
from jsonschema import Draft202012Validator

from gateway.codecs.gute import load_schema

MAX_HEAD_BYTES = 16_384
MAX_BODY_BYTES = 1 << 20
PATH = "/gute2/handoffs"


@dataclass
class Request:
    """One request the peer answered (or dropped): what came and what went back."""

    method: str
    path: str
    headers: dict[str, str]
    status: int | None
    body: bytes = b""


@dataclass
class _Head:
    method: str
    path: str
    headers: dict[str, str] = field(default_factory=dict)


class _Malformed(Exception):
    """The request cannot be parsed; the connection is answered 400 and closed."""


class _AlertingTLSStream(TLSStream):
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


class GutePeer:
    """A GUTE II battery's handoff endpoint over real HTTPS with client certificates."""

    def __init__(
        self,
        directory: Path,
        *,
        fail_first: int = 0,
        drop_first: int = 0,
        refuse: Mapping[str, int] | None = None,
        duplicate_status: int = 409,
        server_name: str = "127.0.0.1",
    ) -> None:
        self.directory = directory
        self.fail_first = fail_first
        self.drop_first = drop_first
        self.refuse = dict(refuse or {})
        self.duplicate_status = duplicate_status
        self.ca = trustme.CA()
        self.server_cert = self.ca.issue_cert(server_name)
        client = self.ca.issue_cert("fischer-gateway")
        directory.mkdir(parents=True, exist_ok=True)
        self.ca_file = directory / "gute-ca.pem"
        self.cert_file = directory / "gute-client.pem"
        self.key_file = directory / "gute-client.key"
        self.ca.cert_pem.write_to_path(str(self.ca_file))
        for blob in client.cert_chain_pems:
            blob.write_to_path(str(self.cert_file), append=True)
        client.private_key_pem.write_to_path(str(self.key_file))
        self.port = 0
        #: Accepted documents by Idempotency-Key, in arrival order; a key at most once.
        self.accepted: dict[str, dict[str, Any]] = {}
        #: Every request in arrival order, with the status answered (None: dropped).
        self.requests: list[Request] = []
        #: Why each refused TLS handshake failed (a missing or foreign client certificate).
        self.handshake_failures: list[str] = []
        self._validator = Draft202012Validator(
            load_schema(), format_checker=Draft202012Validator.FORMAT_CHECKER
        )
        self._stack: AsyncExitStack | None = None

    # -- what tests and daemon configs need ---------------------------------------------------

    @property
    def url(self) -> str:
        """Where handoffs go: ``https://127.0.0.1:PORT/gute2/handoffs``."""
        return f"https://127.0.0.1:{self.port}{PATH}"

    def sink_options(self, **extra: Any) -> dict[str, Any]:
        """Options of a ``gute2`` sink that trusts this peer and is trusted by it."""
        return {
            "url": self.url,
            "ca_file": str(self.ca_file),
            "cert_file": str(self.cert_file),
            "key_file": str(self.key_file),
            **extra,
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

    # -- lifetime -----------------------------------------------------------------------------

    async def __aenter__(self) -> GutePeer:
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
    def in_thread(self) -> Iterator[GutePeer]:
        """Serve from an event loop in a thread for the block (for sync tests)."""
        with start_blocking_portal() as portal, portal.wrap_async_context_manager(self):
            yield self

    # -- one connection -----------------------------------------------------------------------

    async def _connection(self, raw: anyio.abc.ByteStream, context: ssl.SSLContext) -> None:
        try:
            stream = await _AlertingTLSStream.wrap(
                raw, server_side=True, ssl_context=context, standard_compatible=False
            )
        except (ssl.SSLError, OSError, anyio.BrokenResourceError, anyio.EndOfStream) as exc:
            self.handshake_failures.append(str(getattr(exc, "reason", None) or exc))
            await raw.aclose()
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
            await stream.aclose()

    async def _exchange(self, reader: BufferedByteReceiveStream, stream: TLSStream) -> bool:
        """Read one request and answer it; False when the connection is to close."""
        try:
            head = _parse_head(await reader.receive_until(b"\r\n\r\n", MAX_HEAD_BYTES))
            length = _content_length(head)
        except (_Malformed, anyio.DelimiterNotFound) as exc:
            await _respond(stream, 400, {"error": str(exc) or "request head too long"}, False)
            return False
        body = await reader.receive_exactly(length) if length else b""
        keep_alive = head.headers.get("connection", "").lower() != "close"
        request = Request(head.method, head.path, head.headers, None, body)
        self.requests.append(request)
        if head.method == "POST" and self.drop_first > 0:
            self.drop_first -= 1
            return False
        status, answer = self._answer(head, body)
        request.status = status
        await _respond(stream, status, answer, keep_alive)
        return keep_alive

    def _answer(self, head: _Head, body: bytes) -> tuple[int, dict[str, Any]]:
        if head.path != PATH:
            return 404, {"error": f"no such resource {head.path}"}
        if head.method != "POST":
            return 405, {"error": "handoffs are POSTed"}
        if self.fail_first > 0:
            self.fail_first -= 1
            return 503, {"error": "battery busy"}
        if head.headers.get("content-type", "").split(";")[0].strip() != "application/json":
            return 415, {"error": "expected application/json"}
        key = head.headers.get("idempotency-key", "")
        if not key:
            return 400, {"error": "Idempotency-Key is required"}
        try:
            document = json.loads(body)
        except ValueError as exc:
            return 400, {"error": f"not JSON: {exc}"}
        problems = sorted(self._validator.iter_errors(document), key=lambda e: list(e.path))
        if problems:
            where = "/".join(str(p) for p in problems[0].absolute_path)
            return 400, {"error": f"schema: /{where}: {problems[0].message}"}
        if document["idempotency_key"] != key:
            return 400, {"error": "Idempotency-Key differs from the document's idempotency_key"}
        if key in self.refuse:
            return self.refuse[key], {"error": f"handoff {key} refused by the test"}
        if key in self.accepted:
            return self.duplicate_status, {"status": "duplicate", "handoff_id": key}
        self.accepted[key] = document
        return 201, {"status": "accepted", "handoff_id": key}


def _parse_head(raw: bytes) -> _Head:
    try:
        lines = raw.decode("latin-1").split("\r\n")
        method, path, http_version = lines[0].split(" ")
    except ValueError:
        raise _Malformed("bad request line") from None
    if http_version != "HTTP/1.1":
        raise _Malformed(f"expected HTTP/1.1, got {http_version}")
    head = _Head(method, path)
    for line in lines[1:]:
        name, sep, value = line.partition(":")
        if not sep:
            raise _Malformed(f"bad header line {line!r}")
        head.headers[name.strip().lower()] = value.strip()
    return head


def _content_length(head: _Head) -> int:
    if "transfer-encoding" in head.headers:
        raise _Malformed("send Content-Length, not Transfer-Encoding")
    try:
        length = int(head.headers.get("content-length", "0"))
    except ValueError:
        raise _Malformed("bad Content-Length") from None
    if not 0 <= length <= MAX_BODY_BYTES:
        raise _Malformed(f"Content-Length {length} out of range")
    return length


_REASONS = {
    200: "OK",
    201: "Created",
    400: "Bad Request",
    404: "Not Found",
    405: "Method Not Allowed",
    409: "Conflict",
    415: "Unsupported Media Type",
    422: "Unprocessable Content",
    503: "Service Unavailable",
}


async def _respond(
    stream: TLSStream, status: int, answer: dict[str, Any], keep_alive: bool
) -> None:
    body = json.dumps(answer).encode()
    head = (
        f"HTTP/1.1 {status} {_REASONS.get(status, 'Status')}\r\n"
        "Content-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\n"
        f"Connection: {'keep-alive' if keep_alive else 'close'}\r\n\r\n"
    )
    await stream.send(head.encode() + body)
