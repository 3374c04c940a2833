"""The live map through ``fischer-gateway run``: the brigade scenario on the page and its stream.

The daemon runs as an operator runs it, with the ``fusion`` and ``counter_uas`` processors and
a ``map`` sink on loopback (port 0: its URL is read from the ``map_listening`` log line).
``fischer-gateway simulate --scenario brigade`` plays the operation faster than real time: two
airframes over UDP, the platoons over CoT.

- An integrator's client (plain HTTP, Server-Sent Events) receives the snapshot and then the
  tracks, airframes, blue forces and cues as they change.
- Debian's Chromium, headless and held to the node by its launch flags and a route that
  aborts any other request, loads the page: the base map and the libraries come from the
  node; the symbols drawn equal the picture's entities; a track's symbol moves when the track
  does; a cue appears; the time slider, moved back to a second after the first cue, shows the
  cued track where the node's JSONL archive says it was then, and the cue. The screenshot is
  kept in the test's temporary folder, and also where ``FG_MAP_SCREENSHOT`` says:
  ``FG_MAP_SCREENSHOT=docs/map.png pytest tests/e2e/test_map_run.py`` makes the README's
  picture (docs/map.md §9).
"""

from __future__ import annotations

import http.client
import json
import os
import shutil
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
from daemon_support import Daemon, archive_events, free_udp_port, wait_until
from map_browser import map_page

from gateway.sim.scenario import load_scenario
from sinks.map.picture import entity_count

pytestmark = pytest.mark.timeout(150)

SPEED = 6.0
SYMBOL_LAYERS = ("airframe", "track", "blue", "cue")


def write_config(tmp_path: Path, link: int, cot: int) -> Path:
    battery = load_scenario("brigade").batteries[0]
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}
  - {{id: F26E-002, sysid: 2, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}
sources:
  - {{name: atak, uri: 'udp://127.0.0.1:{cot}'}}
processors:
  - {{name: fusion, type: fusion, options: {{speed_scale: {SPEED}}}}}
  - name: cuas
    type: counter_uas
    options:
      batteries:
        - id: {battery.id}
          lat_deg: {battery.lat_deg}
          lon_deg: {battery.lon_deg}
          effectors: {list(battery.effectors)}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{tmp_path / "archive.jsonl"}'}}}}
  - name: map
    type: map
    options: {{port: 0, title: Brigade, archive: '{tmp_path / "archive.jsonl"}'}}
routes:
  - sinks: [map, archive]
    kinds: [telemetry, link_state, detection, track, blue_force, handoff]
"""
    )
    return config


@dataclass
class StreamReader:
    """An integrator's client: reads the SSE stream in a thread and keeps every message."""

    url: str
    messages: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    error: BaseException | None = None

    def start(self) -> None:
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        parts = urlsplit(self.url)
        conn = http.client.HTTPConnection(parts.hostname or "", parts.port, timeout=60)
        try:
            conn.request("GET", "/api/stream", headers={"accept": "text/event-stream"})
            response = conn.getresponse()
            assert response.status == 200, response.status
            kind = ""
            while True:
                line = response.readline()
                if not line:
                    return
                text = line.decode().rstrip("\n")
                if text.startswith("event: "):
                    kind = text[7:]
                elif text.startswith("data: "):
                    self.messages.append((kind, json.loads(text[6:])))
        except (OSError, AssertionError, ValueError) as exc:
            self.error = exc
        finally:
            conn.close()

    def changes(self, layer: str) -> list[dict[str, Any]]:
        return [m for k, m in list(self.messages) if k == "change" and m["layer"] == layer]


@dataclass
class Node:
    daemon: Daemon
    url: str
    stream: StreamReader
    sim: subprocess.Popen[bytes]
    archive: Path


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Node]:
    tmp_path = tmp_path_factory.mktemp("map")
    link, cot = free_udp_port(), free_udp_port()
    daemon = Daemon(write_config(tmp_path, link, cot))
    sim: subprocess.Popen[bytes] | None = None
    try:
        url = str(daemon.wait_event("map_listening", 20.0)["url"])
        stream = StreamReader(url)
        stream.start()
        wait_until(lambda: bool(stream.messages), 10.0, "the stream's snapshot")
        command = [sys.executable, "-m", "gateway", "simulate", "--scenario", "brigade"]
        command += ["--to", f"udp://127.0.0.1:{link}", "--cot", f"udp://127.0.0.1:{cot}"]
        command += ["--speed", str(SPEED)]
        sim = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        yield Node(daemon, url, stream, sim, tmp_path / "archive.jsonl")
    finally:
        if sim is not None:
            if sim.poll() is None:
                sim.terminate()
            sim.communicate(timeout=10)  # and its pipe closed
        assert daemon.stop() == 0


def picture(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url + "api/picture", timeout=10) as response:  # noqa: S310
        return json.loads(response.read())  # type: ignore[no-any-return]


def test_the_page_draws_the_picture_moves_a_track_and_shows_a_cue(
    node: Node, tmp_path: Path
) -> None:
    with map_page(node.url) as shown:
        page, errors, foreign = shown.page, shown.errors, shown.foreign
        page.wait_for_function("() => window.fgMap.state.baseMap === true")
        assert page.evaluate("fgMap.state.baseKind") == "world-atlas"

        # A track's symbol moves when the track does.
        page.wait_for_function("() => window.fgMap.ids('track').length > 0", timeout=60_000)
        track_id = page.evaluate("window.fgMap.ids('track')[0]")
        before = page.evaluate("id => window.fgMap.position('track', id)", track_id)
        page.wait_for_function(
            """([id, x, y]) => {
                const p = window.fgMap.position('track', id);
                return p === null || Math.hypot(p.x - x, p.y - y) >= 2;
            }""",
            arg=[track_id, before["x"], before["y"]],
            timeout=60_000,
        )
        after = page.evaluate("id => window.fgMap.position('track', id)", track_id)
        if after is not None:  # else it was lost or merged meanwhile: removed, not stuck
            assert (after["lat"], after["lon"]) != (before["lat"], before["lon"])

        # A GUTE II cue appears, with its battery's symbol.
        page.wait_for_selector(".fg-layer-cue", timeout=60_000)
        assert "GUTE-1" in page.inner_text("#cues")

        # The symbols drawn are the picture's entities, compared at one seq.
        matched = None
        for _ in range(200):
            drawn = page.evaluate(
                "({seq: window.fgMap.state.seq, symbols: window.fgMap.symbols()})"
            )
            current = picture(node.url)
            if current["seq"] == drawn["seq"]:
                matched = (drawn["symbols"], entity_count(current["layers"], SYMBOL_LAYERS))
                break
            time.sleep(0.05)
        assert matched is not None, "the page never caught up with the picture"
        assert matched[0] == matched[1]
        assert matched[0] > 0

        # A symbol's tooltip is its entity, as text.
        page.hover(".fg-layer-airframe", force=True)
        tooltip = page.wait_for_selector(".leaflet-tooltip")
        assert tooltip is not None
        assert "battery" in tooltip.inner_text()

        page.mouse.move(640, 400)
        page.wait_for_function(
            "() => document.getElementById('mgrs').textContent.startsWith('MGRS 3')"
        )
        page.screenshot(path=str(tmp_path / "map.png"))
        keep = os.environ.get("FG_MAP_SCREENSHOT")
        if keep:
            shutil.copyfile(tmp_path / "map.png", keep)

        # The time slider: a second after the first cue, the cued track was where the
        # archive says it was then, and the cue stood.
        go_back_in_time(page, node)
        assert errors == []
        assert foreign == []


def go_back_in_time(page: Any, node: Node) -> None:
    handoffs = [e for e in archive_events(node.archive) if e["kind"] == "handoff"]
    assert handoffs, "the cue is on the page, so in the archive"
    first = handoffs[0]
    instant = datetime.fromisoformat(first["time"]) + timedelta(seconds=1)
    wait_until(lambda: datetime.now(UTC) > instant + timedelta(seconds=2), 10.0, "the instant")
    page.wait_for_selector("#time", state="visible")
    value = page.evaluate("iso => fgMap.sliderValueFor(iso)", instant.isoformat())
    page.wait_for_function("v => Number(document.getElementById('time').max) > v", arg=value)
    page.locator("#time").fill(str(value))
    page.wait_for_function("() => fgMap.state.mode === 'replay' && fgMap.state.replays >= 1")
    replayed = datetime.fromisoformat(page.evaluate("fgMap.state.replayAt"))
    assert abs((replayed - instant).total_seconds()) <= 1.5
    events = archive_events(node.archive)
    track_id = first["track"]["track_id"]
    then = [
        e
        for e in events
        if e["kind"] == "track"
        and e["track_id"] == track_id
        and datetime.fromisoformat(e["time"]) <= replayed
    ]
    shown = page.evaluate("id => fgMap.position('track', id)", track_id)
    if then[-1]["status"] in ("lost", "merged"):
        assert shown is None
    else:
        where = then[-1]["position"]
        assert shown is not None
        assert (shown["lat"], shown["lon"]) == (
            round(where["lat_deg"], 7),
            round(where["lon_deg"], 7),
        )
    assert first["handoff_id"] in page.evaluate("fgMap.ids('cue')")
    page.click("#live")
    page.wait_for_function("() => fgMap.state.mode === 'live' && fgMap.state.snapshots >= 2")


def test_an_integrators_stream_client_receives_tracks_airframes_blue_forces_and_cues(
    node: Node,
) -> None:
    stream = node.stream

    def seen_all() -> bool:
        return all(stream.changes(layer) for layer in ("track", "airframe", "blue", "cue"))

    wait_until(seen_all, 90.0, "tracks, airframes, blue forces and cues on the stream")
    assert stream.error is None
    kind, snapshot = stream.messages[0]
    assert kind == "snapshot"
    assert set(snapshot["layers"]) == {"order", "detection", "cue", "blue", "track", "airframe"}
    seqs = [m["seq"] for k, m in list(stream.messages)[1:] if k == "change"]
    assert seqs == list(range(snapshot["seq"] + 1, snapshot["seq"] + 1 + len(seqs)))
    tracks = [c for c in stream.changes("track") if c["op"] == "upsert"]
    assert {t["data"]["object_class"] for t in tracks} >= {"loitering_munition"}
    for change in tracks:
        data = change["data"]
        assert data["sidc"]
        assert data["cep50_m"] >= 0
        assert data["history"][-1] == [data["lat"], data["lon"]]
    airframes = {c["id"] for c in stream.changes("airframe")}
    assert airframes == {"F26E-001", "F26E-002"}
    assert any(c["data"]["battery_pct"] is not None for c in stream.changes("airframe"))
    cue = stream.changes("cue")[0]["data"]
    assert cue["battery"] == "GUTE-1"
    assert cue["operator_authorisation_required"] is True
    assert {c["data"]["callsign"] for c in stream.changes("blue")} >= {"VIDAR 1"}
