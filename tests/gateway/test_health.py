"""The health endpoint over a real loopback socket."""

from __future__ import annotations

import json

import anyio
import pytest

from gateway.health import HealthServer
from gateway.metrics import Registry


async def request(port: int, raw: bytes) -> tuple[int, bytes]:
    async with await anyio.connect_tcp("127.0.0.1", port) as stream:
        await stream.send(raw)
        data = b""
        while True:
            try:
                data += await stream.receive()
            except (anyio.EndOfStream, anyio.BrokenResourceError):
                break
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


@pytest.mark.anyio
async def test_endpoints() -> None:
    ready = [False]
    registry = Registry()
    registry.counter("fg_test_total", "Test.").inc()
    server = HealthServer(
        "127.0.0.1", 0, registry=registry, status=lambda: {"node": "n"}, is_ready=lambda: ready[0]
    )
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            port = await tg.start(server.run)
            get = b"GET %s HTTP/1.1\r\nHost: x\r\n\r\n"
            assert await request(port, get % b"/healthz") == (200, b"ok\n")
            assert (await request(port, get % b"/readyz"))[0] == 503
            ready[0] = True
            assert (await request(port, get % b"/readyz"))[0] == 200
            code, body = await request(port, get % b"/metrics")
            assert code == 200
            assert b"fg_test_total 1" in body
            code, body = await request(port, get % b"/status")
            assert json.loads(body) == {"node": "n"}
            assert (await request(port, get % b"/nope"))[0] == 404
            assert (await request(port, b"POST /status HTTP/1.1\r\n\r\n"))[0] == 405
            assert (await request(port, b"garbage\r\n\r\n"))[0] == 400
            huge = b"GET / HTTP/1.1\r\n" + b"X: y\r\n" * 2000 + b"\r\n"
            assert (await request(port, huge))[0] == 431
            tg.cancel_scope.cancel()
