"""A loopback HTTPS endpoint for the demo's stand-ins: JSON POSTs with client certificates.

``PostServer`` listens on 127.0.0.1 with TLS, requires a client certificate from the demo
CA, reads HTTP/1.1 requests with a ``Content-Length`` body (head and body bounded), and
answers ``201`` for a new ``Idempotency-Key`` and ``409`` for one it already has, handing
each new JSON object to ``on_post(path, document)`` once. It is a peer for the demo, not a
server for a node: enough HTTP for the gateway's own HTTPS sinks and no more.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import anyio
import anyio.abc
from anyio.streams.buffered import BufferedByteReceiveStream

from gateway.sim.pki import DemoPki
from gateway.sim.tlspeer import TlsPeer

__all__ = ["MAX_KEYS", "PostServer"]

_MAX_HEAD = 16 * 1024
_MAX_BODY = 256 * 1024
#: Idempotency keys remembered; the oldest are forgotten first.
MAX_KEYS = 100_000
_REASONS = {201: "Created", 400: "Bad Request", 409: "Conflict", 413: "Content Too Large"}


class PostServer(TlsPeer):
    """See the module docstring; its loopback port is bound (``port``) when it is made."""

    def __init__(self, pki: DemoPki, on_post: Callable[[str, dict[str, Any]], None]) -> None:
        super().__init__(pki)
        self._on_post = on_post
        self.keys: dict[str, None] = {}

    async def _connection(self, stream: anyio.abc.ByteStream) -> None:
        async with stream:
            buffered = BufferedByteReceiveStream(stream)
            try:
                while await self._exchange(stream, buffered):
                    pass
            except (anyio.EndOfStream, anyio.IncompleteRead, anyio.BrokenResourceError):
                return
            except anyio.DelimiterNotFound:
                await self._answer(stream, 413, {"error": "header too large"})

    async def _exchange(
        self, stream: anyio.abc.ByteStream, buffered: BufferedByteReceiveStream
    ) -> bool:
        head = await buffered.receive_until(b"\r\n\r\n", _MAX_HEAD)
        lines = head.decode("latin-1").split("\r\n")
        method, _, rest = lines[0].partition(" ")
        path = rest.partition(" ")[0]
        headers = {}
        for line in lines[1:]:
            name, _, value = line.partition(":")
            headers[name.strip().lower()] = value.strip()
        try:
            length = int(headers.get("content-length", "0"))
        except ValueError:
            length = -1
        if not 0 <= length <= _MAX_BODY:
            await self._answer(stream, 413, {"error": "body missing or too large"})
            return False
        body = await buffered.receive_exactly(length) if length else b""
        key = headers.get("idempotency-key", "")
        if method != "POST" or not key:
            await self._answer(stream, 400, {"error": "POST with an Idempotency-Key only"})
            return True
        try:
            document = json.loads(body)
        except ValueError:
            document = None
        if not isinstance(document, dict):
            await self._answer(stream, 400, {"error": "body is not a JSON object"})
            return True
        if key in self.keys:
            await self._answer(stream, 409, {"status": "already received", "key": key})
            return True
        self.keys[key] = None
        if len(self.keys) > MAX_KEYS:
            del self.keys[next(iter(self.keys))]
        self._on_post(path, document)
        await self._answer(stream, 201, {"status": "received", "key": key})
        return True

    @staticmethod
    async def _answer(stream: anyio.abc.ByteStream, status: int, body: dict[str, Any]) -> None:
        data = json.dumps(body).encode()
        await stream.send(
            f"HTTP/1.1 {status} {_REASONS.get(status, 'Error')}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(data)}\r\n\r\n".encode()
            + data
        )
