"""The health endpoint over a real loopback socket, spoken to in raw HTTP/1.1."""

from __future__ import annotations

import contextlib
import json
from collections.abc import AsyncIterator, Callable, Mapping
from contextlib import asynccontextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import anyio
import anyio.abc
import pytest
from prometheus_client.parser import text_string_to_metric_families
from structlog.testing import capture_logs

from gateway.errors import LinkUnavailable
from gateway.ops import health
from gateway.ops.health import HealthServer
from gateway.ops.metrics import Registry

GET = b"GET %s HTTP/1.1\r\nHost: gateway\r\nUser-Agent: test\r\n\r\n"


class Response:
    """One parsed HTTP response."""

    def __init__(self, raw: bytes) -> None:
        head, _, self.body = raw.partition(b"\r\n\r\n")
        status_line, *lines = head.decode("ascii").split("\r\n")
        version, code, _reason = status_line.split(" ", 2)
        assert version == "HTTP/1.1"
        self.code = int(code)
        self.headers = {k.lower(): v for k, v in (line.split(": ", 1) for line in lines)}


async def exchange(port: int, raw: bytes, *, half_close: bool = True) -> Response:
    """Send ``raw`` and read the response until the server closes the connection."""
    async with await anyio.connect_tcp("127.0.0.1", port) as stream:
        await stream.send(raw)
        if half_close:
            await stream.send_eof()
        return Response(await receive_all(stream))


async def receive_all(stream: anyio.abc.ByteStream) -> bytes:
    """Everything the server sends until it closes its side."""
    data = b""
    while True:
        try:
            data += await stream.receive()
        except anyio.EndOfStream:
            return data


def make_server(
    *,
    registry: Registry | None = None,
    status: Callable[[], Mapping[str, Any]] = dict,
    is_ready: Callable[[], bool] = lambda: True,
) -> HealthServer:
    return HealthServer(
        "127.0.0.1", 0, registry=registry or Registry(), status=status, is_ready=is_ready
    )


@asynccontextmanager
async def serving(server: HealthServer) -> AsyncIterator[int]:
    """Run ``server`` for the body of the block, yielding its bound port."""
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            yield await tg.start(server.run)
            tg.cancel_scope.cancel()


@pytest.mark.anyio
async def test_healthz_answers_ok_and_closes() -> None:
    async with serving(make_server()) as port:
        # Like a real client: no half-close, it waits for the server to end the exchange.
        response = await exchange(port, GET % b"/healthz", half_close=False)
    assert (response.code, response.body) == (200, b"ok\n")
    assert response.headers["connection"] == "close"
    assert response.headers["content-length"] == "3"
    assert response.headers["content-type"] == "text/plain; charset=utf-8"


@pytest.mark.anyio
async def test_readyz_is_503_until_ready() -> None:
    ready = anyio.Event()
    async with serving(make_server(is_ready=ready.is_set)) as port:
        before = await exchange(port, GET % b"/readyz")
        ready.set()
        after = await exchange(port, GET % b"/readyz?verbose=1")
    assert (before.code, before.body) == (503, b"not ready\n")
    assert (after.code, after.body) == (200, b"ready\n")


@pytest.mark.anyio
async def test_metrics_serves_the_registry_in_prometheus_text_format() -> None:
    registry = Registry()
    registry.counter("fg_test_total", "Test.", ("link",)).labels('a"b').inc(2)
    async with serving(make_server(registry=registry)) as port:
        response = await exchange(port, GET % b"/metrics")
    assert response.code == 200
    assert response.headers["content-type"] == "text/plain; version=0.0.4; charset=utf-8"
    (family,) = text_string_to_metric_families(response.body.decode())
    assert [(s.name, s.labels, s.value) for s in family.samples] == [
        ("fg_test_total", {"link": 'a"b'}, 2.0)
    ]


@pytest.mark.anyio
async def test_status_is_json_with_other_values_as_strings() -> None:
    when = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    status = {"node": "n1", "started": when, "spool": Path("/var/spool"), "links": [1, 2]}
    async with serving(make_server(status=lambda: status)) as port:
        response = await exchange(port, GET % b"/status")
    assert response.code == 200
    assert response.headers["content-type"] == "application/json"
    assert json.loads(response.body) == {
        "node": "n1",
        "started": str(when),
        "spool": "/var/spool",
        "links": [1, 2],
    }


@pytest.mark.anyio
async def test_index_lists_every_endpoint() -> None:
    async with serving(make_server()) as port:
        response = await exchange(port, GET % b"/")
    assert response.code == 200
    for path in (b"/healthz", b"/readyz", b"/metrics", b"/status"):
        assert path in response.body


@pytest.mark.anyio
async def test_head_sends_the_get_headers_without_a_body() -> None:
    registry = Registry()
    registry.gauge("fg_up", "Up.").set(1)
    async with serving(make_server(registry=registry)) as port:
        got = await exchange(port, GET % b"/metrics")
        head = await exchange(port, b"HEAD /metrics HTTP/1.1\r\nHost: g\r\n\r\n")
    assert head.code == 200
    assert head.body == b""
    assert head.headers["content-length"] == str(len(got.body))


@pytest.mark.anyio
async def test_unknown_path_is_404() -> None:
    async with serving(make_server()) as port:
        response = await exchange(port, GET % b"/healthz/extra")
    assert (response.code, response.body) == (404, b"not found\n")


@pytest.mark.anyio
async def test_post_is_405_with_allow_and_logged() -> None:
    calls: list[str] = []

    def status() -> dict[str, str]:
        calls.append("status")
        return {}

    server = make_server(status=status)
    with capture_logs() as logs:
        async with serving(server) as port:
            request = b"POST /status HTTP/1.1\r\nHost: g\r\nContent-Length: 2\r\n\r\n{}"
            response = await exchange(port, request)
    assert response.code == 405
    assert response.headers["allow"] == "GET, HEAD"
    assert calls == []  # refused before the status callback runs
    assert server.rejected == 1
    (rejected,) = [e for e in logs if e["event"] == "health_request_rejected"]
    assert rejected["reason"] == "method"
    assert rejected["code"] == 405
    assert rejected["log_level"] == "warning"
    assert rejected["peer"].startswith("127.0.0.1:")


@pytest.mark.anyio
async def test_oversize_header_is_431_while_the_client_is_still_sending() -> None:
    """The 431 must reach the client, not be lost to a reset from unread input."""
    request = b"GET / HTTP/1.1\r\nHost: g\r\nX-Big: " + b"y" * 200_000 + b"\r\n\r\n"

    async def send_all(stream: anyio.abc.ByteStream) -> None:
        # The server stops reading past 8 KiB, so the tail of this may be refused.
        with contextlib.suppress(anyio.BrokenResourceError):
            await stream.send(request)

    async with (
        serving(make_server()) as port,
        await anyio.connect_tcp("127.0.0.1", port) as stream,
        anyio.create_task_group() as tg,
    ):
        tg.start_soon(send_all, stream)
        data = await receive_all(stream)
    assert Response(data).code == 431


@pytest.mark.anyio
async def test_more_than_64_header_fields_is_431_and_64_is_fine() -> None:
    def with_fields(count: int) -> bytes:
        fields = b"Host: g\r\n" + b"".join(b"X-%d: v\r\n" % i for i in range(count - 1))
        return b"GET /healthz HTTP/1.1\r\n" + fields + b"\r\n"

    async with serving(make_server()) as port:
        at_limit = await exchange(port, with_fields(64))
        over = await exchange(port, with_fields(65))
    assert at_limit.code == 200
    assert over.code == 431


@pytest.mark.parametrize(
    "request_bytes",
    [
        pytest.param(b"garbage\r\n\r\n", id="no-version"),
        pytest.param(b"GET / HTTP/1.1\r\n\r\n", id="no-host"),
        pytest.param(b"GET / HTTP/1.1\r\nHost: a\r\nhost: b\r\n\r\n", id="two-hosts"),
        pytest.param(b"GET / HTTP/2.0\r\nHost: g\r\n\r\n", id="http2"),
        pytest.param(b"GET healthz HTTP/1.1\r\nHost: g\r\n\r\n", id="relative-target"),
        pytest.param(b"GET /a b HTTP/1.1\r\nHost: g\r\n\r\n", id="space-in-target"),
        pytest.param(b"GET  / HTTP/1.1\r\nHost: g\r\n\r\n", id="double-space"),
        pytest.param(b"GET / HTTP/1.1\r\nHost : g\r\n\r\n", id="space-before-colon"),
        pytest.param(b"GET / HTTP/1.1\r\nHost: g\r\n folded\r\n\r\n", id="obs-fold"),
        pytest.param(b"GET / HTTP/1.1\r\nHost: g\rX: y\r\n\r\n", id="bare-cr"),
        pytest.param(b"GET / HTTP/1.1\nHost: g\n\n", id="bare-lf-never-ends"),
    ],
)
@pytest.mark.anyio
async def test_malformed_requests_are_400(request_bytes: bytes) -> None:
    server = make_server()
    async with serving(server) as port:
        response = await exchange(port, request_bytes)
    assert response.code == 400
    assert server.rejected == 1


@pytest.mark.anyio
async def test_http_1_0_without_host_is_served() -> None:
    async with serving(make_server()) as port:
        response = await exchange(port, b"GET /healthz HTTP/1.0\r\n\r\n")
    assert (response.code, response.body) == (200, b"ok\n")


@pytest.mark.anyio
async def test_connect_and_close_is_not_a_rejection() -> None:
    server = make_server()
    with capture_logs() as logs:
        async with serving(server) as port:
            await (await anyio.connect_tcp("127.0.0.1", port)).aclose()
            response = await exchange(port, GET % b"/healthz")
    assert response.code == 200
    assert server.rejected == 0
    assert [e for e in logs if e["event"] == "health_request_rejected"] == []


@pytest.mark.anyio
async def test_silent_client_is_dropped_at_the_deadline(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(health, "CONNECTION_DEADLINE_S", 0.2)
    server = make_server()
    with capture_logs() as logs:
        async with (
            serving(server) as port,
            await anyio.connect_tcp("127.0.0.1", port) as stream,
        ):
            await stream.send(b"GET /healthz HTTP/1.1\r\n")  # and never the rest
            with pytest.raises(anyio.EndOfStream):
                await stream.receive()
    assert server.rejected == 1
    assert {"event": "health_request_rejected", "reason": "timeout"}.items() <= logs[-1].items()


@pytest.mark.anyio
async def test_port_in_use_raises_link_unavailable() -> None:
    with anyio.fail_after(10):
        async with await anyio.create_tcp_listener(local_host="127.0.0.1") as taken:
            port = taken.extra(anyio.abc.SocketAttribute.local_port)
            server = HealthServer(
                "127.0.0.1", port, registry=Registry(), status=dict, is_ready=lambda: True
            )
            with pytest.raises(LinkUnavailable, match=f"127.0.0.1:{port}: cannot listen"):
                await server.run()
