"""The map's time slider and local tiles through ``fischer-gateway run``, in headless Chromium.

The node archives to a ``jsonl`` sink and its ``map`` sink replays that archive
(``archive``) and draws an MBTiles file made here as its base map (``tiles``). An airframe
(MAVLink over UDP) and a platoon (CoT over UDP) report one position, then a few seconds later
another. In the browser the base map is the node's tiles (no world-atlas, nothing from beyond
the node); dragging the time slider back to an instant between the two reports shows both
where they were then, not where they are now; "Live" brings the live picture back.
The endpoints refuse hostile ``at`` values and tile addresses with a clear answer.
"""

from __future__ import annotations

import json
import socket
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any
from urllib.parse import quote

import pytest
from daemon_support import Airframe, Daemon, archive_events, free_udp_port, wait_until
from map_browser import map_page
from tile_support import write_mbtiles

pytestmark = pytest.mark.timeout(120)

TILE_COLOUR = (214, 64, 170)
THEN = {"airframe": (59.39, 18.27), "blue": (59.345, 18.21)}
NOW = {"airframe": (59.42, 18.32), "blue": (59.36, 18.26)}


def cot_unit(lat: float, lon: float) -> bytes:
    now = datetime.now(UTC)
    stamp = now.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
    stale = (now + timedelta(minutes=10)).strftime("%Y-%m-%dT%H:%M:%S.000Z")
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n<event version="2.0" uid="PLT-9" '
        f'type="a-f-G-U-C" how="m-g" time="{stamp}" start="{stamp}" stale="{stale}">'
        f'<point lat="{lat}" lon="{lon}" hae="9999999.0" ce="9999999.0" le="9999999.0"/>'
        '<detail><contact callsign="2. pluton"/></detail></event>'
    ).encode()


class Node:
    def __init__(self, tmp_path: Path) -> None:
        self.link, self.cot = free_udp_port(), free_udp_port()
        self.archive = tmp_path / "archive" / "archive.jsonl"
        tiles = write_mbtiles(
            tmp_path / "lm.mbtiles", range(4), lambda z, x, y: TILE_COLOUR, attribution="LM"
        )
        config = tmp_path / "node.yaml"
        config.write_text(
            f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: UAV-1, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{self.link}', security: unsecured,
     name: fleet}}]}}
sources:
  - {{name: atak, uri: 'udp://127.0.0.1:{self.cot}'}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{self.archive}'}}}}
  - name: map
    type: map
    options:
      port: 0
      archive: '{self.archive}'
      tiles: {{path: '{tiles}', attribution: 'Test tiles, not Lantmäteriet'}}
routes:
  - {{sinks: [archive, map], kinds: [telemetry, link_state, blue_force]}}
"""
        )
        self.daemon = Daemon(config)
        self.url = str(self.daemon.wait_event("map_listening", 20.0)["url"])
        self.airframe = Airframe(1)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def report(self, where: dict[str, tuple[float, float]]) -> None:
        """Both entities at ``where``, until the archive holds it; when it first did."""
        lat, lon = where["airframe"]
        blue_lat, blue_lon = where["blue"]

        def archived() -> list[dict[str, Any]]:
            found = []
            for e in archive_events(self.archive):
                p = e.get("position") or {}
                here = (p.get("lat_deg"), p.get("lon_deg"))
                if (e["kind"], here) in (("telemetry", (lat, lon)), ("blue_force", where["blue"])):
                    found.append(e)
            return found

        def send_and_look() -> bool:
            self.sock.sendto(self.airframe.heartbeat(), ("127.0.0.1", self.link))
            self.sock.sendto(self.airframe.position(lat, lon), ("127.0.0.1", self.link))
            self.sock.sendto(cot_unit(blue_lat, blue_lon), ("127.0.0.1", self.cot))
            time.sleep(0.2)
            return {e["kind"] for e in archived()} == {"telemetry", "blue_force"}

        wait_until(send_and_look, 20.0, f"the archive holding {where}")

    def stop(self) -> None:
        self.sock.close()
        assert self.daemon.stop() == 0


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Node]:
    node = Node(tmp_path_factory.mktemp("map-archive"))
    try:
        yield node
    finally:
        node.stop()


def times(archive: Path, where: dict[str, tuple[float, float]]) -> list[datetime]:
    points = {("telemetry", where["airframe"]), ("blue_force", where["blue"])}
    found = []
    for e in archive_events(archive):
        p = e.get("position") or {}
        if (e["kind"], (p.get("lat_deg"), p.get("lon_deg"))) in points:
            found.append(datetime.fromisoformat(e["time"]))
    return found


def get(url: str) -> tuple[int, dict[str, Any] | bytes]:
    try:
        with urllib.request.urlopen(url, timeout=20) as response:  # noqa: S310 - loopback
            body = response.read()
            status = response.status
            kind = response.headers.get("content-type", "")
    except urllib.error.HTTPError as exc:
        body, status, kind = exc.read(), exc.code, exc.headers.get("content-type", "")
    return status, (json.loads(body) if kind.startswith("application/json") else body)


def test_the_slider_shows_the_picture_as_it_was_over_the_nodes_own_tiles(
    node: Node, tmp_path: Path
) -> None:
    node.report(THEN)
    time.sleep(4.0)  # the instant we go back to lies 2 s after the first reports
    node.report(NOW)
    then = max(
        min(t)
        for t in (
            times(node.archive, {**THEN, "blue": (0, 0)}),
            times(node.archive, {**THEN, "airframe": (0, 0)}),
        )
    )
    later = min(times(node.archive, NOW))
    at = then + timedelta(seconds=2)  # the slider picks it to the second
    assert at + timedelta(seconds=1) < later, (then, later)

    with map_page(node.url) as shown:
        page, errors, foreign, requested = shown.page, shown.errors, shown.foreign, shown.requested
        page.wait_for_function(
            "() => fgMap.position('airframe', 'UAV-1') && fgMap.position('blue', 'PLT-9')"
        )

        # The base map is the node's tiles: drawn where nothing else is, no world-atlas.
        page.wait_for_function("() => fgMap.state.baseKind === 'tiles'")
        page.wait_for_function(
            """() => Array.from(document.querySelectorAll('img.leaflet-tile-loaded'))
                  .filter(t => t.src.includes('/tiles/') && t.naturalWidth === 256)
                  .length > 0"""
        )
        under = page.evaluate(
            """() => { const m = document.getElementById('map').getBoundingClientRect();
              const x = m.left + 4, y = m.bottom - 30;
              return Array.from(document.querySelectorAll('img.leaflet-tile-loaded'))
                .filter(t => { const r = t.getBoundingClientRect();
                  return r.left <= x && x < r.right && r.top <= y && y < r.bottom; })
                .map(t => t.src); }"""
        )
        assert any("/tiles/" in src for src in under), under
        assert "Test tiles, not Lantmäteriet" in page.inner_text("#map")
        assert not any("world-atlas" in url for url in requested)

        live = {
            layer: page.evaluate(f"fgMap.position('{layer}', '{ident}')")
            for layer, ident in (("airframe", "UAV-1"), ("blue", "PLT-9"))
        }
        for layer, (lat, lon) in NOW.items():
            assert (live[layer]["lat"], live[layer]["lon"]) == (lat, lon)

        size = page.evaluate("fgMap.map.getSize()")
        size = {"width": size["x"], "height": size["y"]}
        # The operator drags the slider back to an instant between the two reports.
        page.wait_for_selector("#time", state="visible")
        value = page.evaluate("iso => fgMap.sliderValueFor(iso)", at.isoformat())
        page.wait_for_function("v => Number(document.getElementById('time').max) > v", arg=value)
        page.locator("#time").fill(str(value))
        page.wait_for_function("() => fgMap.state.mode === 'replay' && fgMap.state.replays >= 1")
        page.wait_for_function("() => fgMap.position('airframe', 'UAV-1') !== null")
        past = {
            layer: page.evaluate(f"fgMap.position('{layer}', '{ident}')")
            for layer, ident in (("airframe", "UAV-1"), ("blue", "PLT-9"))
        }
        for layer, (lat, lon) in THEN.items():
            assert (past[layer]["lat"], past[layer]["lon"]) == (lat, lon), layer
            moved = abs(past[layer]["x"] - live[layer]["x"]) + abs(
                past[layer]["y"] - live[layer]["y"]
            )
            assert moved >= 10, (layer, past[layer], live[layer])
            assert 0 <= past[layer]["x"] <= size["width"], past[layer]  # in sight
            assert 0 <= past[layer]["y"] <= size["height"], past[layer]
        assert page.inner_text("#link") == "archive"
        replay_at = datetime.fromisoformat(page.evaluate("fgMap.state.replayAt"))
        assert abs((replay_at - at).total_seconds()) <= 1.5
        page.screenshot(path=str(tmp_path / "map-replay.png"))

        # "Live" returns to the live picture.
        page.click("#live")
        page.wait_for_function("() => fgMap.state.mode === 'live' && fgMap.state.snapshots >= 2")
        back = page.evaluate("fgMap.position('airframe', 'UAV-1')")
        assert (back["lat"], back["lon"]) == NOW["airframe"]
        page.wait_for_function("() => document.getElementById('link').textContent === 'live'")
        assert errors == []
        assert foreign == []


def test_hostile_times_and_tile_addresses_get_a_clear_refusal(node: Node) -> None:
    api = node.url + "api/picture?at="
    for bad, why in (
        ("yesterday", "not an ISO 8601 time"),
        ("2026-11-27T06:00:00", "time zone"),
        ("9999-01-01T00:00:00Z", "future"),
        ("1970-01-01T00:00:00Z", "before 2000"),
        ("../../../etc/passwd", "not an ISO 8601 time"),
        ("2026-11-27T06:00:00Z" + "0" * 100, "longer than"),
    ):
        status, body = get(api + quote(bad))
        assert status == 400, bad
        assert isinstance(body, dict)
        assert body["error"].startswith("at: ")
        assert why in body["error"]
    status, body = get(
        node.url + "api/picture?layers=track&at=" + quote("2026-11-27T06:00:00+01:00")
    )
    assert status == 200
    assert isinstance(body, dict)
    assert set(body["layers"]) == {"track"}
    assert body["replay"]["truncated"] is None
    for path in (
        "tiles/25/0/0",
        "tiles/3/8/0",
        "tiles/3/0/8",
        "tiles/-1/0/0",
        "tiles/..%2f..%2fnode.yaml/0/0",
        "tiles/3/0/0.png",
    ):
        status, _ = get(node.url + path)
        assert status == 404, path
    status, tile = get(node.url + "tiles/3/4/2")
    assert status == 200
    assert isinstance(tile, bytes)
    assert tile.startswith(b"\x89PNG")
