"""Several nodes, one picture, each detection once, with the node of origin shown.

Three ``fischer-gateway run`` nodes, each with its own nats-server (JetStream, its own
domain, random ports on loopback): hub ``a`` aggregates leaves ``b`` and ``c`` through its
``nats`` source and fuses every node's detections. Airframe ``S.x`` is heard by the hub
itself and by ``b`` (its datagrams reach both, in either order); airframe ``T`` by ``b`` and
``c``; ``A-1``, ``B-1`` and ``C-1``, one of each node, see one object, so the hub's track of
it holds detections of both leaves. At the hub every detection is taken once (by id and by
count), and the node of origin shows where a user looks: the hub's ``/status`` (``remote``:
per node and per airframe), the CoT its ``cot`` sink sends (remarks, read with lxml) and its
map (the picture a program reads, and the page in headless Chromium).
"""

from __future__ import annotations

import json
import socket
import threading
import time
import urllib.request
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Airframe, archive_events, free_udp_port, running, wait_until
from map_browser import map_page
from nats_server import NEEDS_NATS, NatsServer
from test_nats_scale_out_run import detection, node_config

pytestmark = [pytest.mark.timeout(150), NEEDS_NATS]

etree = pytest.importorskip("lxml.etree")

ROUNDS = 3


def hub_config(tmp: Path, udp_port: int, nats_url: str, cot_port: int) -> tuple[Path, Path]:
    """Hub ``a``: airframes A-1 (sysid 1) and S.x (2), fusion, the ``nats`` source of b and c,
    and its picture in a jsonl archive, a CoT receiver and the map."""
    archive = tmp / "a.jsonl"
    link = f"links: [{{uri: 'udp://127.0.0.1:{udp_port}', security: unsecured, name: l}}]"
    config = tmp / "a.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
spool: {{path: '{tmp / "a.spool"}'}}
health: {{port: 0}}
airframes:
  - {{id: A-1, sysid: 1, {link}}}
  - {{id: S.x, sysid: 2, {link}}}
processors:
  - {{name: fusion, type: fusion, options: {{update_interval_s: 0.2, tick_s: 0.2}}}}
sources:
  - {{name: nodes, type: nats, node: a, servers: ['{nats_url}'], remotes: [b, c]}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
  - {{name: cot, type: cot, options: {{destinations: [{{uri: 'udp://127.0.0.1:{cot_port}'}}]}}}}
  - {{name: map, type: map, options: {{port: 0, title: Division}}}}
routes:
  - {{kinds: [detection, telemetry, track], sinks: [archive, cot, map]}}
"""
    )
    return config, archive


class CotReceiver:
    """A CoT peer on loopback UDP: the remarks of the newest event of each uid."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = int(self.sock.getsockname()[1])
        self.remarks: dict[str, str] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            event = etree.fromstring(data)
            self.remarks[event.get("uid")] = event.findtext("detail/remarks") or ""

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.sock.close()


def send(sock: socket.socket, frame: bytes, *ports: int) -> None:
    for port in ports:
        sock.sendto(frame, ("127.0.0.1", port))


def test_each_detection_once_at_the_hub_with_its_node_shown(tmp_path: Path) -> None:
    hub_server = NatsServer(tmp_path, "a", hub=True)
    leaf = f"nats-leaf://127.0.0.1:{hub_server.leaf_port}"
    b_server, c_server = (
        NatsServer(tmp_path, "b", leaf_of=leaf),
        NatsServer(tmp_path, "c", leaf_of=leaf),
    )
    receiver = CotReceiver()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with hub_server, b_server, c_server:
        wait_until(lambda: len(hub_server.leafz().get("leafs") or []) == 2, 20, "the leaf links")
        a_udp, b_udp, c_udp = free_udp_port(), free_udp_port(), free_udp_port()
        a_config, a_archive = hub_config(tmp_path, a_udp, hub_server.url, receiver.port)
        b_config, _ = node_config(tmp_path, "b", ["B-1", "S.x", "T"], b_udp, b_server.url)
        c_config, _ = node_config(tmp_path, "c", ["C-1", "C-2", "T"], c_udp, c_server.url)
        own = {port: Airframe(1) for port in (a_udp, b_udp, c_udp)}  # A-1, B-1, C-1
        shared_s, shared_t = Airframe(2), Airframe(3)
        with running(a_config) as hub, running(b_config), running(c_config):
            map_url = str(hub.wait_event("map_listening", 20.0)["url"])
            for port, airframe in own.items():
                send(sock, airframe.heartbeat(), port)
                send(sock, airframe.position(65.8, 21.7), port)
            for frame in (shared_s.heartbeat(), shared_s.position(65.8, 21.7)):
                send(sock, frame, a_udp, b_udp)
            for frame in (shared_t.heartbeat(), shared_t.position(65.8, 21.7)):
                send(sock, frame, b_udp, c_udp)
            for index in range(ROUNDS):
                for port, airframe in own.items():
                    send(sock, detection(airframe, index), port)
                # S.x: heard by the hub itself and relayed by b; the second copy is sent once
                # the first is on the hub's picture (b's in rounds 0 and 2, the hub's in 1).
                first, second = (a_udp, b_udp) if index % 2 else (b_udp, a_udp)
                frame = detection(shared_s, index)
                send(sock, frame, first)
                wait_until(
                    lambda n=index + 1: (
                        sum(e.get("airframe") == "S.x" for e in archive_events(a_archive)
                            if e["kind"] == "detection") == n
                    ),
                    30,
                    f"S.x's detection {index + 1} at the hub",
                )  # fmt: skip
                send(sock, frame, second)
                send(sock, detection(shared_t, index), b_udp, c_udp)  # T: b and c
                time.sleep(0.05)
            expected = Counter(dict.fromkeys(["A-1", "B-1", "C-1", "S.x", "T"], ROUNDS))

            def detections() -> list[dict[str, Any]]:
                return [e for e in archive_events(a_archive) if e["kind"] == "detection"]

            def fused_from_both() -> bool:
                return any(
                    e["kind"] == "track" and e.get("origin_nodes") == ["b", "c"]
                    for e in archive_events(a_archive)
                )

            wait_until(
                lambda: Counter(e["airframe"] for e in detections()) == expected,
                60,
                "every detection at the hub",
            )
            wait_until(fused_from_both, 30, "a track fused from b's and c's detections")
            time.sleep(1.0)  # anything doubled would arrive now
            events = archive_events(a_archive)
            status = hub.status()
            acked = {
                result: hub.metric(
                    "fg_detections_acknowledged_total", airframe="S.x", result=result
                )
                for result in ("held", "duplicate")
            }

            # The map: what a program reads, and what the page shows.
            with urllib.request.urlopen(map_url + "api/picture", timeout=10) as answer:  # noqa: S310
                layers = json.loads(answer.read())["layers"]
            with map_page(map_url) as shown:
                page = shown.page
                page.wait_for_function(
                    "() => document.getElementById('airframes').innerText.includes('from node c')"
                )
                listed = page.inner_text("#airframes")
                assert not shown.errors
            wait_until(
                lambda: {"fischer-B-1", "fischer-C-1", "fischer-T"} <= set(receiver.remarks),
                30,
                "the remote airframes' CoT at the receiver",
            )
            remarks = dict(receiver.remarks)
    receiver.close()
    sock.close()

    # Each detection once: S.x heard directly and relayed, T heard by two nodes.
    found = [e for e in events if e["kind"] == "detection"]
    assert Counter(e["event_id"] for e in found).most_common(1)[0][1] == 1
    assert Counter(e["airframe"] for e in found) == expected
    origin = {e["airframe"]: e.get("origin_node") for e in found}
    assert origin["A-1"] is None
    assert origin["B-1"] == "b"
    assert origin["C-1"] == "c"
    assert origin["T"] in {"b", "c"}
    counts = status["sources"][0]["counts"]
    # Of each of S.x's detections the copy the hub heard second was dropped at the door: b's
    # in the source (counted duplicate), its own acknowledged DUPLICATE to the airframe and
    # not published. The source took B-1's, C-1's and T's, and S.x's it heard first.
    s_origins = [e.get("origin_node") for e in found if e["airframe"] == "S.x"]
    assert s_origins == ["b", None, "b"]
    assert acked == {"held": 1.0, "duplicate": 2.0}
    assert counts["detection"] == 3 * ROUNDS + 2
    assert counts.get("duplicate", 0) >= 1  # (and T's second copies, unless the stream's)

    # /status: per node and per remote airframe, never the hub's own airframes.
    remote = status["remote"]
    assert set(remote["nodes"]) == {"b", "c"}
    for node in ("b", "c"):
        assert remote["nodes"][node]["events"] > 0
        assert remote["nodes"][node]["last_heard_age_s"] < 120
    assert remote["airframes"]["B-1"]["origin_node"] == "b"
    assert remote["airframes"]["C-1"]["origin_node"] == "c"
    assert remote["airframes"]["T"]["origin_node"] in {"b", "c"}
    assert "A-1" not in remote["airframes"]
    # b's state of S.x (the hub's own airframe) is refused; a detection of it may be b's.
    assert counts["own_airframe"] >= 1

    # CoT: remote airframes and detections say their node; the fused track both leaves'.
    assert remarks["fischer-B-1"].endswith("from node b")
    assert remarks["fischer-C-1"].endswith("from node c")
    assert "node" not in remarks["fischer-A-1"]
    assert "node" not in remarks["fischer-S.x"]
    b_det = next(e for e in found if e["airframe"] == "B-1")
    assert remarks[f"fischer-det-{b_det['event_id']}"].endswith("; from node b")
    a_det = next(e for e in found if e["airframe"] == "A-1")
    assert "node" not in remarks[f"fischer-det-{a_det['event_id']}"]
    fused = [r for uid, r in remarks.items() if uid.startswith("fischer-trk-")]
    assert any(r.endswith("; detections from nodes b, c") for r in fused), fused

    # The map: the entities carry their nodes; the page lists the remote airframes' nodes.
    airframes = {e["id"]: e["origin_node"] for e in layers["airframe"]}
    assert airframes["B-1"] == "b"
    assert airframes["C-1"] == "c"
    assert airframes["A-1"] is None
    assert ["b", "c"] in [e["origin_nodes"] for e in layers["track"]]
    assert {e["origin_node"] for e in layers["detection"]} >= {None, "b", "c"}
    assert "from node b" in listed
    assert "from node c" in listed
