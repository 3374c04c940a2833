"""SWECCIS both ways in the daemon as operators run it: ``fischer-gateway run --config FILE``.

A child process with two simulated airframes on loopback UDP, the fusion processor, a
``sweccis`` sink and a ``sweccis`` order source, both to one real SWECCIS server
(``SweccisPeer``: TLS with client certificates, length frames, every document checked against
the shipped XSD). ``fischer-gateway simulate --scenario loitering-munitions`` plays a few
seconds; the server holds an order before the daemon starts, so it is sent as soon as the
source registers for Orders.

The server must end with XSD-valid Intel (detections and tracks), Logistics and Operations
documents, Operations no faster than once a second per airframe, and the order's ack
``accepted``; the order must be in the jsonl archive as a FiveLineOrder.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
from collections import defaultdict
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from daemon_support import archive_events, free_udp_port, running, wait_until
from lxml import etree
from sweccis_peer import NS, SweccisPeer, order_document

pytestmark = pytest.mark.timeout(120)


def write_config(tmp_path: Path, peer: SweccisPeer, link: int) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    tls = peer.link_options()
    files = (
        f"uri: '{tls['uri']}', ca_file: '{tls['ca_file']}', cert_file: '{tls['cert_file']}', "
        f"key_file: '{tls['key_file']}'"
    )
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
  - {{name: brigade-orders, type: sweccis, client_id: node-e2e, reconnect_initial_s: 0.2,
     {files}}}
processors:
  - {{name: fusion, type: fusion, options: {{max_speed_mps: 300}}}}
sinks:
  - name: sweccis
    type: sweccis
    options: {{client_id: node-e2e, {files}}}
    retry_initial_s: 0.2
    retry_max_s: 0.5
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [sweccis], kinds: [detection, track, telemetry]}}
  - {{sinks: [archive]}}
"""
    )
    return config, archive


@pytest.fixture(scope="module")
def sweccis_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[SweccisPeer, list[Any], str]:
    tmp_path = tmp_path_factory.mktemp("sweccis")
    link = free_udp_port()
    with SweccisPeer(tmp_path / "pki").in_thread() as peer:
        order = order_document(
            "swc-doc-1", "ORD-77", task="observe_point", mgrs="34W DA 12345 67890",
            priority="flash", measures=["stay east of PL BLUE"],
        )  # fmt: skip
        peer.call(peer.push_order, order)
        config, archive = write_config(tmp_path, peer, link)
        checked = subprocess.run(
            [sys.executable, "-m", "gateway", "check-config", str(config)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert checked.returncode == 0, checked.stdout + checked.stderr
        with running(config):
            command = [sys.executable, "-m", "gateway", "simulate", "--scenario"]
            command += ["loitering-munitions", "--to", f"udp://127.0.0.1:{link}"]
            command += ["--duration", "20", "--speed", "4"]
            played = subprocess.run(command, capture_output=True, timeout=60, check=False)
            assert played.returncode == 0, played.stderr.decode(errors="replace")

            def everything_arrived() -> bool:
                events = archive_events(archive)
                published = {e["event_id"] for e in events if e["kind"] in ("detection", "track")}
                return bool(published) and published <= set(peer.accepted) and any(
                    e["kind"] == "order" for e in events
                ) and bool(peer.order_acks)  # fmt: skip

            wait_until(everything_arrived, 20.0, "every detection and track at the server")
        return peer, archive_events(archive), checked.stdout


def test_check_config_lists_the_sink_and_the_source(
    sweccis_run: tuple[SweccisPeer, list[Any], str],
) -> None:
    _, _, checked = sweccis_run
    assert "sweccis" in checked


def test_the_server_got_valid_intel_logistics_and_operations(
    sweccis_run: tuple[SweccisPeer, list[Any], str],
) -> None:
    peer, events, _ = sweccis_run
    assert peer.invalid == []
    assert peer.handshake_failures == []
    registered = {tuple(publish) for _, publish, _ in peer.registrations if publish}
    # The sink publishes the three data FAS; the order source publishes order statuses.
    assert registered == {("Intel", "Logistics", "Operations"), ("Orders",)}
    intel = peer.of("Intel")
    kinds = {etree.QName(doc[0]).localname for doc in intel}
    assert kinds == {"Detection", "Track"}
    classes = {doc[0].findtext(f"{NS}Class") for doc in intel}
    assert "loitering_munition" in classes
    for kind in ("Logistics", "Operations"):
        airframes = {doc[0].findtext(f"{NS}Airframe") for doc in peer.of(kind)}
        assert airframes == {"F26E-001", "F26E-002"}, kind
        for doc in peer.of(kind):  # the id names the telemetry event and the FAS
            airframe = doc[0].findtext(f"{NS}Airframe")
            assert doc.get("id").startswith(f"{airframe}-tel-"), doc.get("id")
            assert doc.get("id").endswith(f"/{kind.lower()}"), doc.get("id")
    assert any(e["kind"] == "telemetry" for e in events)


def test_operations_come_at_most_once_a_second_per_airframe(
    sweccis_run: tuple[SweccisPeer, list[Any], str],
) -> None:
    peer, _, _ = sweccis_run
    times: dict[str, list[datetime]] = defaultdict(list)
    for doc in peer.of("Operations"):
        state = doc[0]
        when = datetime.fromisoformat(state.findtext(f"{NS}Time").replace("Z", "+00:00"))
        times[state.findtext(f"{NS}Airframe")].append(when)
    assert times
    for airframe, stamps in times.items():
        gaps = [(b - a).total_seconds() for a, b in itertools.pairwise(stamps)]
        assert len(stamps) >= 3, airframe
        assert min(gaps) >= 1.0, (airframe, gaps)


def test_the_order_reached_the_archive_and_the_server_got_its_ack(
    sweccis_run: tuple[SweccisPeer, list[Any], str],
) -> None:
    peer, events, _ = sweccis_run
    (order,) = [e for e in events if e["kind"] == "order"]
    assert order["event_id"] == "sweccis-order-ORD-77"
    assert order["source"] == "brigade-orders"
    assert (order["task"], order["priority"]) == ("observe_point", "flash")
    assert order["location"]["mgrs"] == "34W DA 12345 67890"
    assert order["control_measures"] == ["stay east of PL BLUE"]
    assert peer.order_acks == [("swc-doc-1", "accepted", None)]
    assert peer.outbox == {}
    subscribed = [subscribe for _, _, subscribe in peer.registrations if subscribe]
    assert subscribed[0] == ["Orders"]
