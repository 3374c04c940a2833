"""The HTTP health endpoint: /healthz, /readyz, /metrics, /status, on anyio sockets.

A deliberately small HTTP/1.1 server: GET and HEAD only, one request per connection,
request head bounded (8 KiB, 64 headers) and every connection under a deadline, so a slow
or hostile client cannot tie it up. It binds to 127.0.0.1 unless configured otherwise.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import Any

import anyio
import anyio.abc
import structlog

from gateway.errors import LinkUnavailable
from gateway.metrics import Registry

__all__ = ["HealthServer"]

log = structlog.get_logger(__name__)

MAX_HEAD_BYTES = 8192
MAX_HEADERS = 64
CONNECTION_DEADLINE_S = 5.0
_REASONS = {
    200: "OK",
    400: "Bad Request",
    404: "Not Found",
    405: "Method Not Allowed",
    431: "Request Header Fields Too Large",
    503: "Service Unavailable",
}
_INDEX = b"fischer-gateway\n/healthz\n/readyz\n/metrics\n/status\n"


class _BadRequest(Exception):
    def __init__(self, code: int) -> None:
        self.code = code


class HealthServer:
    """Serves the gateway's liveness, readiness, metrics and status."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        registry: Registry,
        status: Callable[[], Mapping[str, Any]],
        is_ready: Callable[[], bool],
    ) -> None:
        self.host = host
        self.port = port
        self._registry = registry
        self._status = status
        self._is_ready = is_ready

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[int] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind, report the bound port as started, and serve until cancelled."""
        try:
            listener = await anyio.create_tcp_listener(local_host=self.host, local_port=self.port)
        except OSError as exc:
            where = f"health endpoint {self.host}:{self.port}"
            raise LinkUnavailable(where, f"cannot listen: {exc.strerror or exc}") from exc
        port = int(listener.extra(anyio.abc.SocketAttribute.local_port))
        log.info("health_listening", host=self.host, port=port)
        task_status.started(port)
        async with listener:
            await listener.serve(self._handle)

    async def _handle(self, stream: anyio.abc.SocketStream) -> None:
        async with stream:
            with anyio.move_on_after(CONNECTION_DEADLINE_S):
                try:
                    method, path = await self._read_head(stream)
                except _BadRequest as exc:
                    log.info("health_request_rejected", code=exc.code)
                    await self._respond(stream, exc.code, b"", "text/plain", head_only=False)
                    return
                except (anyio.EndOfStream, anyio.BrokenResourceError, OSError):
                    return
                code, body, ctype = self._route(path)
                if method not in ("GET", "HEAD"):
                    code, body, ctype = 405, b"only GET and HEAD\n", "text/plain"
                try:
                    await self._respond(stream, code, body, ctype, head_only=method == "HEAD")
                except (anyio.BrokenResourceError, OSError):
                    return

    async def _read_head(self, stream: anyio.abc.SocketStream) -> tuple[str, str]:
        data = b""
        while b"\r\n\r\n" not in data:
            if len(data) > MAX_HEAD_BYTES:
                raise _BadRequest(431)
            data += await stream.receive(4096)
        head = data.split(b"\r\n\r\n", 1)[0]
        if len(head) > MAX_HEAD_BYTES:
            raise _BadRequest(431)
        lines = head.split(b"\r\n")
        if len(lines) - 1 > MAX_HEADERS:
            raise _BadRequest(431)
        parts = lines[0].split(b" ")
        if len(parts) != 3 or not parts[2].startswith(b"HTTP/1."):
            raise _BadRequest(400)
        try:
            return parts[0].decode("ascii"), parts[1].decode("ascii").split("?", 1)[0]
        except UnicodeDecodeError as exc:
            raise _BadRequest(400) from exc

    def _route(self, path: str) -> tuple[int, bytes, str]:
        if path == "/healthz":
            return 200, b"ok\n", "text/plain; charset=utf-8"
        if path == "/readyz":
            if self._is_ready():
                return 200, b"ready\n", "text/plain; charset=utf-8"
            return 503, b"not ready\n", "text/plain; charset=utf-8"
        if path == "/metrics":
            body = self._registry.render().encode()
            return 200, body, "text/plain; version=0.0.4; charset=utf-8"
        if path == "/status":
            body = json.dumps(self._status(), default=str, indent=1).encode()
            return 200, body, "application/json"
        if path == "/":
            return 200, _INDEX, "text/plain; charset=utf-8"
        return 404, b"not found\n", "text/plain; charset=utf-8"

    @staticmethod
    async def _respond(
        stream: anyio.abc.SocketStream, code: int, body: bytes, ctype: str, *, head_only: bool
    ) -> None:
        head = (
            f"HTTP/1.1 {code} {_REASONS.get(code, 'Error')}\r\n"
            f"Content-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
            "Connection: close\r\nCache-Control: no-store\r\n\r\n"
        ).encode("ascii")
        await stream.send(head if head_only else head + body)
