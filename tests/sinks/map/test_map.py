"""The map sink alone: its contract, its bounded picture, its stream and its guards.

The server is the real one (Starlette under hypercorn on loopback, in this test's event loop);
the clients are httpx, as a browser or an integrator's program would connect.
"""

from __future__ import annotations

import json
import os
import ssl
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import anyio
import httpx
import pytest
import trustme

from gateway.contract import check_sink, sample_events
from gateway.events import EventKind, Position, Track
from sinks.map import MapSink, MapSinkConfig
from sinks.map.hub import CLOSED, Hub
from sinks.map.picture import Limits, Picture

T0 = datetime(2026, 11, 27, 6, 0, tzinfo=UTC)
TOKEN = "f3a9c1d2e4b5a6978877665544332211"  # noqa: S105 - a test token


def track(track_id: str, i: int = 0, status: str = "updated") -> Track:
    when = T0 + timedelta(seconds=i)
    return Track(
        event_id=f"{track_id}-{i}",
        track_id=track_id,
        time=when,
        status=status,  # type: ignore[arg-type]
        object_class="loitering_munition",
        confidence=0.95,
        position=Position(lat_deg=65.8 + i * 1e-3, lon_deg=21.6),
        cep50_m=10.0,
        cep90_m=20.0,
        speed_mps=30.0,
        course_deg=90.0,
        first_seen=T0,
        last_seen=when,
        hostility="hostile",
        sidc="SHAPMFQ--------",
    )


def test_the_map_sink_keeps_the_gateway_contract() -> None:
    check_sink(MapSink, {"port": 0})


def test_the_picture_is_bounded_per_layer_and_evicts_the_oldest() -> None:
    picture = Picture(Limits(tracks=5, history_points=3))
    changes = [c for i in range(40) for c in picture.apply(track(f"T{i % 10}", i))]
    assert picture.sizes()["track"] == 5
    assert picture.evicted == 35
    assert {e["id"] for e in picture.snapshot()["track"]} == {f"T{i}" for i in range(5, 10)}
    assert all(len(e["history"]) <= 3 for e in picture.snapshot()["track"])
    assert {c["reason"] for c in changes if c["op"] == "remove"} == {"evicted"}
    # A lost track leaves the picture; one never seen is no change.
    assert picture.apply(track("T9", 50, "lost")) == [
        {"op": "remove", "layer": "track", "id": "T9", "reason": "lost"}
    ]
    assert picture.apply(track("T9", 51, "lost")) == []


def test_a_peer_sidc_that_is_not_one_is_replaced_by_a_generic_code() -> None:
    picture = Picture(Limits())
    bad = track("T1").model_copy(update={"sidc": "<img src=x onerror=alert(1)>"})
    (change,) = picture.apply(bad)
    assert change["data"]["sidc"] == "SHGP-----------"


def test_entities_not_updated_expire() -> None:
    now = [0.0]
    picture = Picture(Limits(expire_after_s=10), clock=lambda: now[0])
    for event in sample_events(frozenset(EventKind) - {EventKind.HOP}):
        picture.apply(event)
    now[0] = 11.0
    removed = picture.expire()
    assert {c["reason"] for c in removed} == {"expired"}
    assert sum(picture.sizes().values()) == 0


def test_a_slow_stream_is_cut_off_not_buffered() -> None:
    hub = Hub(queue_max=16)
    sub = hub.subscribe(["track"])
    hub.publish({"op": "upsert", "layer": "track", "id": str(i), "data": {}} for i in range(100))
    assert sub.overflowed
    assert hub.subscribers == 0
    assert hub.cut_off == 1
    assert sub.queue.qsize() <= 16
    messages = [sub.queue.get_nowait() for _ in range(sub.queue.qsize())]
    assert messages[-1] == CLOSED


def check_config(tmp_path: Path, options: str) -> subprocess.CompletedProcess[str]:
    path = tmp_path / "node.yaml"
    path.write_text(
        "gateway: {node_id: map-config}\n"
        "airframes: [{id: A1, sysid: 1, links: [{uri: 'udp://127.0.0.1:14550', name: l,\n"
        "             security: unsecured}]}]\n"
        "sinks:\n"
        "  - name: map\n"
        "    type: map\n"
        f"    options: {options}\n"
        "routes: [{sinks: [map]}]\n"
    )
    return subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env=dict(os.environ),
    )


def test_binding_beyond_loopback_without_token_or_client_certificates_is_refused(
    tmp_path: Path,
) -> None:
    result = check_config(tmp_path, "{host: 0.0.0.0, port: 0}")
    assert result.returncode == 2, result.stdout + result.stderr
    out = result.stdout + result.stderr
    assert "node.yaml:7" in out, out
    for words in ("not loopback", "token_file", "client_ca_file"):
        assert words in out, out
    # TLS without client certificates is not enough either.
    ca = trustme.CA()
    cert = ca.issue_cert("map.local")
    cert.cert_chain_pems[0].write_to_path(str(tmp_path / "cert.pem"))
    cert.private_key_pem.write_to_path(str(tmp_path / "key.pem"))
    tls = f"{{cert_file: '{tmp_path}/cert.pem', key_file: '{tmp_path}/key.pem'}}"
    assert check_config(tmp_path, f"{{host: 0.0.0.0, port: 0, tls: {tls}}}").returncode == 2
    # A token makes it acceptable; a short one is refused, naming the file.
    (tmp_path / "token").write_text(TOKEN + "\n")
    (tmp_path / "short").write_text("abc\n")
    good = check_config(tmp_path, f"{{host: 0.0.0.0, port: 0, token_file: '{tmp_path}/token'}}")
    assert good.returncode == 0, good.stdout + good.stderr
    short = check_config(tmp_path, f"{{host: 0.0.0.0, port: 0, token_file: '{tmp_path}/short'}}")
    assert short.returncode == 2
    assert "at least 16" in short.stdout + short.stderr


def test_without_the_extra_the_config_error_names_it(monkeypatch: pytest.MonkeyPatch) -> None:
    import sinks.map.sink as module

    monkeypatch.setattr(module, "_extra_installed", lambda: False)
    with pytest.raises(ValueError, match=r"fischer-gateway\[map\]"):
        MapSink("map", MapSinkConfig(port=0))


@asynccontextmanager
async def serving(**options: Any) -> AsyncIterator[MapSink]:
    sink = MapSink("map", MapSinkConfig(port=0, **options))
    await sink.open()
    try:
        async with anyio.create_task_group() as tg:
            await tg.start(sink.run)
            yield sink
            tg.cancel_scope.cancel()
    finally:
        await sink.aclose()


async def read_events(lines: AsyncIterator[str], count: int) -> list[tuple[str, Any]]:
    found: list[tuple[str, Any]] = []
    kind = ""
    async for line in lines:
        if line.startswith("event: "):
            kind = line[7:]
        elif line.startswith("data: "):
            found.append((kind, json.loads(line[6:])))
            if len(found) == count:
                break
    return found


def test_the_stream_starts_with_a_snapshot_then_sends_each_change_and_ends_on_close() -> None:
    async def main() -> None:
        async with serving() as sink:
            await sink.send([track("T1", 0)])
            assert sink.url is not None
            async with (
                httpx.AsyncClient(base_url=sink.url, timeout=10) as client,
                client.stream("GET", "/api/stream?layers=track,cue") as stream,
            ):
                assert stream.headers["content-type"].startswith("text/event-stream")
                lines = stream.aiter_lines()
                ((kind, snap),) = await read_events(lines, 1)
                assert kind == "snapshot"
                assert set(snap["layers"]) == {"track", "cue"}
                assert [t["id"] for t in snap["layers"]["track"]] == ["T1"]
                await sink.send([track("T1", 1), *sample_events(frozenset({EventKind.TELEMETRY}))])
                await sink.send([track("T1", 2, "lost")])
                changes = await read_events(lines, 2)  # the telemetry is not a track or cue
                assert [(k, c["op"], c["seq"]) for k, c in changes] == [
                    ("change", "upsert", snap["seq"] + 1),
                    ("change", "remove", snap["seq"] + 3),
                ]
                assert changes[0][1]["data"]["history"][-1] == [65.801, 21.6]
                # Cancelling the sink's lifetime (drain, reload) ends the open stream.
                with anyio.fail_after(10):
                    sink.hub.close()
                    async for _ in lines:
                        pass

    anyio.run(main)


def test_cancelling_the_lifetime_with_streams_open_stops_the_server_promptly() -> None:
    async def main() -> None:
        sink = MapSink("map", MapSinkConfig(port=0))
        await sink.open()
        assert sink.url is not None
        async with (
            httpx.AsyncClient(base_url=sink.url, timeout=10) as client,
            anyio.create_task_group() as tg,
        ):
            await tg.start(sink.run)
            async with client.stream("GET", "/api/stream") as stream:
                await read_events(stream.aiter_lines(), 1)
                tg.cancel_scope.cancel()  # ends within _STOP_S: the test's timeout would tell
        await sink.aclose()

    anyio.run(main)


def test_a_token_is_required_in_a_header_the_address_or_its_cookie(tmp_path: Path) -> None:
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN)

    async def main() -> None:
        async with serving(token_file=token_file) as sink:
            assert sink.url is not None
            async with httpx.AsyncClient(base_url=sink.url, timeout=10) as client:
                assert (await client.get("/api/picture")).status_code == 401
                wrong = {"authorization": "Bearer " + "x" * len(TOKEN)}
                assert (await client.get("/api/picture", headers=wrong)).status_code == 401
                right = {"authorization": "Bearer " + TOKEN}
                assert (await client.get("/api/picture", headers=right)).status_code == 200
                first = await client.get(f"/?token={TOKEN}")
                assert first.status_code == 303
                assert first.headers["location"] == "/"
                assert "httponly" in first.headers["set-cookie"].lower()
                # The client now holds the cookie: the page and its stream need nothing more.
                assert (await client.get("/")).status_code == 200
                assert (await client.get("/api/picture")).status_code == 200
            assert sink.status()["refused_token"] == 2

    anyio.run(main)


def test_requests_beyond_the_connection_cap_are_refused_and_foreign_hosts_too() -> None:
    async def main() -> None:
        async with serving(max_connections=2) as sink:
            assert sink.url is not None
            async with (
                httpx.AsyncClient(base_url=sink.url, timeout=10) as a,
                httpx.AsyncClient(base_url=sink.url, timeout=10) as b,
                httpx.AsyncClient(base_url=sink.url, timeout=10) as c,
                a.stream("GET", "/api/stream") as one,
                b.stream("GET", "/api/stream") as two,
            ):
                await read_events(one.aiter_lines(), 1)
                await read_events(two.aiter_lines(), 1)
                busy = await c.get("/api/picture")
                assert busy.status_code == 503
                rebinding = await c.get("/", headers={"host": "attacker.example"})
                assert rebinding.status_code in (400, 503)
            async with httpx.AsyncClient(base_url=sink.url, timeout=10) as c:
                assert (await c.get("/api/picture")).status_code == 200
                rebinding = await c.get("/", headers={"host": "attacker.example"})
                assert rebinding.status_code == 400
            assert sink.status()["refused_busy"] >= 1

    anyio.run(main)


def test_tls_with_client_certificates_refuses_a_client_without_one(tmp_path: Path) -> None:
    ca = trustme.CA()
    server = ca.issue_cert("127.0.0.1")
    client_cert = ca.issue_cert("operator")
    server.private_key_and_cert_chain_pem.write_to_path(str(tmp_path / "server.pem"))
    ca.cert_pem.write_to_path(str(tmp_path / "ca.pem"))
    tls = {
        "cert_file": tmp_path / "server.pem",
        "key_file": tmp_path / "server.pem",
        "client_ca_file": tmp_path / "ca.pem",
    }

    async def main() -> None:
        async with serving(tls=tls) as sink:
            assert sink.url is not None
            assert sink.url.startswith("https://")
            trusted = ssl.create_default_context(cafile=str(tmp_path / "ca.pem"))
            async with httpx.AsyncClient(base_url=sink.url, verify=trusted, timeout=10) as anon:
                with pytest.raises(
                    (httpx.ConnectError, httpx.ReadError, httpx.RemoteProtocolError)
                ):
                    await anon.get("/api/picture")
            client_cert.configure_cert(trusted)
            async with httpx.AsyncClient(base_url=sink.url, verify=trusted, timeout=10) as ok:
                assert (await ok.get("/api/picture")).status_code == 200

    anyio.run(main)


def test_the_mgrs_readout_answers_and_refuses_nonsense() -> None:
    async def main() -> None:
        async with serving() as sink:
            assert sink.url is not None
            async with httpx.AsyncClient(base_url=sink.url, timeout=10) as client:
                answer = (await client.get("/api/mgrs?lat=65.8252&lon=21.6886")).json()
                assert answer["mgrs"].startswith("34W")
                for query in ("lat=nan&lon=1", "lat=91&lon=0", "lat=x", ""):
                    assert (await client.get("/api/mgrs?" + query)).status_code == 400

    anyio.run(main)


def test_an_ipv6_literal_in_brackets_is_listened_on_without_them(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # "[::1]" passes the loopback rule as "::1" does; the listener must get the bare address
    # (getaddrinfo knows no brackets) and the URL one pair of brackets. Bound on 127.0.0.1
    # here: the tests stay in 127.0.0.0/8.
    import sinks.map.server as server

    asked: list[str] = []
    bind = server.listen

    def listen(host: str, port: int, stall_s: float | None = None) -> Any:
        asked.append(host)
        return bind("127.0.0.1", port, stall_s)

    monkeypatch.setattr(server, "listen", listen)

    async def main() -> None:
        async with serving(host="[::1]") as sink:
            assert asked == ["::1"]
            assert sink.url is not None
            assert sink.url.startswith("http://[::1]:")

    anyio.run(main)


def test_streams_whose_clients_stopped_reading_give_their_places_back() -> None:
    # A client that never reads fills its receive window; the hub cuts its subscription off
    # but the response stays blocked in the write. The kernel aborts such a connection after
    # stall_s (TCP_USER_TIMEOUT, inherited from the listener), which frees its place under
    # max_connections: clients that stop reading cannot hold the map's every place.
    import socket

    if not hasattr(socket, "TCP_USER_TIMEOUT"):
        pytest.skip("TCP_USER_TIMEOUT is Linux's")

    async def main() -> None:
        async with serving(max_connections=2, queue_max=64, stall_s=1) as sink:
            assert sink.url is not None
            port = int(sink.url.rsplit(":", 1)[1].strip("/"))
            stalled = []
            for _ in range(2):
                conn = socket.socket()
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
                conn.connect(("127.0.0.1", port))
                conn.sendall(b"GET /api/stream HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
                stalled.append(conn)
            try:
                async with httpx.AsyncClient(base_url=sink.url, timeout=10) as client:
                    await anyio.sleep(0.2)
                    assert (await client.get("/api/info")).status_code == 503
                    # Changes until the hub has cut both off: their writes are stuck by then.
                    i = 0
                    with anyio.fail_after(60):
                        while sink.status()["streams"] > 0:
                            await sink.send([track(f"T-{n % 50}", n) for n in range(i, i + 10)])
                            i += 10
                            await anyio.sleep(0.01)
                    status = 503
                    with anyio.fail_after(60):  # generous: the abort comes after stall_s
                        while status == 503:
                            await anyio.sleep(0.2)
                            status = (await client.get("/api/info")).status_code
                    assert status == 200
            finally:
                for conn in stalled:
                    conn.close()

    anyio.run(main)
