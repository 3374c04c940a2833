"""The HTTP health endpoint: /healthz, /readyz, /metrics and /status, on anyio sockets.

A deliberately small, strict HTTP/1.1 server: GET and HEAD only, one request per connection,
the request head bounded (8 KiB, 64 header lines), at most 32 connections held at once (more
are closed as soon as they are accepted, see ``gateway.transports.listener``) and each under a 5 s
deadline, so a slow or hostile client cannot tie it up nor exhaust the daemon's descriptors;
rejections are counted and logged at most once a minute per reason. Anything it does not
understand is refused with 400 rather than guessed at. It binds to 127.0.0.1 unless the
config says otherwise.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Mapping
from typing import Any

import anyio
import anyio.abc
import structlog

from gateway.ops.logsetup import RateLimit
from gateway.ops.metrics import Registry
from gateway.transports.listener import Connection, TcpListener

__all__ = ["HealthServer"]

log = structlog.get_logger(__name__)

MAX_HEAD_BYTES = 8192
MAX_HEADERS = 64
MAX_CONNECTIONS = 32
CONNECTION_DEADLINE_S = 5.0
_LOG_INTERVAL_S = 60.0
# After answering, read and discard what the client still sends (up to this much, for up to
# this long) before closing: closing with unread input makes the kernel send a reset, which
# can destroy the response (a 431 above all) before the client reads it.
LINGER_MAX_BYTES = 65536
LINGER_DEADLINE_S = 1.0

_TOKEN = re.compile(rb"[!#$%&'*+\-.^_`|~0-9A-Za-z]+")
_TARGET = re.compile(rb"/[\x21-\x7e]*")
_FIELD_VALUE = re.compile(rb"[\t\x20-\x7e\x80-\xff]*")
_VERSIONS = (b"HTTP/1.0", b"HTTP/1.1")
_REASONS = {
    200: "OK",
    400: "Bad Request",
    404: "Not Found",
    405: "Method Not Allowed",
    431: "Request Header Fields Too Large",
    503: "Service Unavailable",
}
_TEXT = "text/plain; charset=utf-8"
_METRICS = "text/plain; version=0.0.4; charset=utf-8"
_INDEX = (
    b"fischer-gateway health endpoint\n"
    b"/healthz  200 while the event loop answers\n"
    b"/readyz   200 once every component has started, else 503\n"
    b"/metrics  Prometheus text format 0.0.4\n"
    b"/status   JSON status of links and sinks\n"
)


class _Rejected(Exception):
    """Raised while reading a request that gets an error response instead of a route."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


class HealthServer:
    """Serves the gateway's liveness, readiness, metrics and status over HTTP/1.1."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        registry: Registry,
        status: Callable[[], Mapping[str, Any]],
        is_ready: Callable[[], bool],
        max_connections: int = MAX_CONNECTIONS,
    ) -> None:
        self.host = host
        self.port = port
        self._registry = registry
        self._status = status
        self._is_ready = is_ready
        self._listener = TcpListener(
            host, port, name="health", what="health endpoint", max_connections=max_connections
        )
        self.stats = self._listener.stats
        self._log_limit = RateLimit(interval_s=_LOG_INTERVAL_S)
        self.rejected = 0
        """Requests refused with 400, 405 or 431, or that timed out."""

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[int] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind, report the bound port through ``task_status``, and serve until cancelled.

        Port 0 binds an ephemeral port. Raises ``LinkUnavailable`` if the address cannot be
        bound (in use, not local, no permission).
        """
        port = self._listener.bind()
        log.info("health_listening", host=self.host, port=port)
        task_status.started(port)
        await self._listener.run(self._handle)

    def _reject_logged(self, reason: str) -> bool:
        self.rejected += 1
        return self._log_limit.allow(reason)

    async def _handle(self, stream: Connection) -> None:
        peer = f"{stream.peer[0]}:{stream.peer[1]}"
        try:
            with anyio.fail_after(CONNECTION_DEADLINE_S):
                await self._serve_one(stream, peer)
        except TimeoutError:
            if self._reject_logged("timeout"):
                log.warning(
                    "health_request_rejected", reason="timeout", peer=peer, total=self.rejected
                )
        except (anyio.BrokenResourceError, anyio.ClosedResourceError, OSError):
            # The client went away mid-exchange; there is nobody left to answer.
            log.debug("health_connection_lost", peer=peer)

    async def _serve_one(self, stream: Connection, peer: str) -> None:
        try:
            method, path = _parse_head(await _read_head(stream))
        except anyio.EndOfStream:
            return  # a bare connect-and-close, as TCP health checks do
        except _Rejected as exc:
            if self._reject_logged(exc.reason):
                log.warning(
                    "health_request_rejected",
                    reason=exc.reason,
                    code=exc.code,
                    peer=peer,
                    total=self.rejected,
                )
            await _respond(stream, exc.code, f"{exc.reason}\n".encode(), _TEXT, head_only=False)
            return
        if method not in (b"GET", b"HEAD"):
            if self._reject_logged("method"):
                log.warning(
                    "health_request_rejected",
                    reason="method",
                    code=405,
                    peer=peer,
                    total=self.rejected,
                )
            body = b"only GET and HEAD\n"
            await _respond(stream, 405, body, _TEXT, head_only=False, allow=True)
            return
        code, body, content_type = self._route(path)
        log.debug("health_request_served", path=path, code=code, peer=peer)
        await _respond(stream, code, body, content_type, head_only=method == b"HEAD")

    def _route(self, path: str) -> tuple[int, bytes, str]:
        if path == "/healthz":
            return 200, b"ok\n", _TEXT
        if path == "/readyz":
            if self._is_ready():
                return 200, b"ready\n", _TEXT
            return 503, b"not ready\n", _TEXT
        if path == "/metrics":
            return 200, self._registry.render().encode(), _METRICS
        if path == "/status":
            body = json.dumps(self._status(), default=str, indent=1) + "\n"
            return 200, body.encode(), "application/json"
        if path == "/":
            return 200, _INDEX, _TEXT
        return 404, b"not found\n", _TEXT


async def _read_head(stream: Connection) -> bytes:
    """The request line and header lines, without the blank line that ends them."""
    data = bytearray()
    while len(data) < MAX_HEAD_BYTES:
        # The terminator may straddle two reads, so search from just before the new bytes.
        start = max(len(data) - 3, 0)
        try:
            data += await stream.receive(4096)
        except anyio.EndOfStream:
            if data:
                raise _Rejected(400, "incomplete request") from None
            raise
        end = data.find(b"\r\n\r\n", start)
        if end >= 0:
            if end + 4 > MAX_HEAD_BYTES:
                break
            return bytes(data[:end])
    raise _Rejected(431, "request head too large")


def _parse_head(head: bytes) -> tuple[bytes, str]:
    """The method and the path (query string dropped) of a well-formed request head."""
    request_line, *fields = head.split(b"\r\n")
    if len(fields) > MAX_HEADERS:
        raise _Rejected(431, "too many header fields")
    parts = request_line.split(b" ")
    if len(parts) != 3:
        raise _Rejected(400, "malformed request line")
    method, target, version = parts
    if not _TOKEN.fullmatch(method) or not _TARGET.fullmatch(target):
        raise _Rejected(400, "malformed request line")
    if version not in _VERSIONS:
        raise _Rejected(400, "unsupported HTTP version")
    hosts = 0
    for field in fields:
        name, colon, value = field.partition(b":")
        # No whitespace before the colon and no line folding (RFC 9112 §5.1, §5.2).
        if not colon or not _TOKEN.fullmatch(name) or not _FIELD_VALUE.fullmatch(value):
            raise _Rejected(400, "malformed header field")
        hosts += name.lower() == b"host"
    # HTTP/1.1 requires exactly one Host (RFC 9112 §3.2); more would be ambiguous in 1.0 too.
    if hosts > 1 or (version == b"HTTP/1.1" and hosts == 0):
        raise _Rejected(400, "missing or repeated Host")
    return method, target.split(b"?", 1)[0].decode("ascii")


async def _respond(
    stream: Connection,
    code: int,
    body: bytes,
    content_type: str,
    *,
    head_only: bool,
    allow: bool = False,
) -> None:
    """Send one response, then half-close and drain so the client reads all of it."""
    head = (
        f"HTTP/1.1 {code} {_REASONS[code]}\r\n"
        f"Content-Type: {content_type}\r\n"
        f"Content-Length: {len(body)}\r\n"
        + ("Allow: GET, HEAD\r\n" if allow else "")
        + "Cache-Control: no-store\r\nConnection: close\r\n\r\n"
    ).encode("ascii")
    await stream.send(head if head_only else head + body)
    stream.send_eof()
    drained = 0
    with anyio.move_on_after(LINGER_DEADLINE_S):
        while drained < LINGER_MAX_BYTES:
            try:
                drained += len(await stream.receive(4096))
            except anyio.EndOfStream:
                return
