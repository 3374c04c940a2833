"""Clients of the map's listener that stop reading, against ``fischer-gateway run``.

As many streams as ``max_connections`` allows are opened by a client that never reads.
While the airframe's telemetry keeps the picture changing, their receive windows fill and
each response ends up stuck in its write (the hub cuts a stream off once its queue is full,
but the write stays stuck): before ``stall_s`` those connections held every place for as long
as the client kept them open, and the operator's page got HTTP 503. Now the kernel aborts
them (``TCP_USER_TIMEOUT``), the places come back, a detection sent meanwhile reaches another
sink, the daemon logs no line per connection, and a tile address of thousands of digits is a
404, not a server error.
"""

from __future__ import annotations

import http.client
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from daemon_support import Airframe, Daemon, archive_events, free_udp_port, wait_until

pytestmark = pytest.mark.timeout(120)

PLACES = 4


def get(port: int, path: str) -> int:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", path)
        response = conn.getresponse()
        response.read()
        return response.status
    finally:
        conn.close()


@pytest.fixture
def stalled() -> Iterator[list[socket.socket]]:
    made: list[socket.socket] = []
    yield made
    for conn in made:
        conn.close()


def test_clients_that_stop_reading_give_the_maps_places_back(
    tmp_path: Path, stalled: list[socket.socket]
) -> None:
    link = free_udp_port()
    probe = tmp_path / "probe.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: UAV-1, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}
sinks:
  - {{name: probe, type: jsonl, options: {{path: '{probe}'}}}}
  - name: map
    type: map
    options: {{port: 0, max_connections: {PLACES}, queue_max: 64, stall_s: 1}}
routes:
  - {{sinks: [map], kinds: [telemetry, link_state, detection]}}
  - {{sinks: [probe], kinds: [detection]}}
"""
    )
    daemon = Daemon(config)
    try:
        port = urlsplit(str(daemon.wait_event("map_listening", 20.0)["url"])).port
        assert port is not None
        airframe = Airframe(1)
        radio = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        step = [0]

        def fly(n: int = 20) -> None:
            for _ in range(n):
                step[0] += 1
                lat = 59.3 + (step[0] % 1000) * 1e-5
                radio.sendto(airframe.position(lat, 18.1), ("127.0.0.1", link))
            time.sleep(0.01)

        def streams() -> int:
            for sink in daemon.status()["sinks"]:
                if sink["sink"] == "map":
                    return int(sink["detail"]["streams"])
            raise AssertionError("no map sink on /status")

        radio.sendto(airframe.heartbeat(), ("127.0.0.1", link))
        for _ in range(PLACES):
            conn = socket.socket()
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
            conn.connect(("127.0.0.1", port))
            conn.sendall(b"GET /api/stream HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            stalled.append(conn)
        wait_until(lambda: streams() == PLACES, 20.0, "the streams open")
        assert get(port, "/api/info") == 503  # every place taken

        # The picture keeps changing: their windows fill and stay shut. The kernel aborts
        # them after stall_s and the places come back while the client keeps them open.
        radio.sendto(airframe.detection(), ("127.0.0.1", link))

        def served() -> bool:
            fly()
            return get(port, "/api/info") == 200

        wait_until(served, 60.0, "a place on the map's listener")
        wait_until(
            lambda: any(e["kind"] == "detection" for e in archive_events(probe)),
            20.0,
            "the detection in the other sink",
        )
        assert get(port, "/tiles/1/" + "9" * 5000 + "/0") == 404
        assert daemon.proc.poll() is None
        assert len(daemon.events("asyncio_error")) <= 1  # once per kind, not per connection
        assert daemon.events("map_server_error") == []
        radio.close()
    finally:
        assert daemon.stop() == 0
