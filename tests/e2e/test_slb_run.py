"""Detections and tracks to SLB, and SLB's orders back, in the daemon as operators run it.

``fischer-gateway run --config FILE`` in a child process: one airframe on loopback UDP, the
``fusion`` processor, an ``slb`` sink and an ``slb`` order source, both to a real HTTPS SLB
(``SlbPeer``: client certificate required, every body checked against the shipped schemas)
whose first two object item POSTs fail with 503 and ``Retry-After: 1``, and a jsonl archive.
``fischer-gateway simulate --scenario t72-column`` plays four T-72B3 on the road into Boden.

SLB must end with every archived detection and track exactly once, each a valid JC3IEDM
object item report; the order queued on SLB must come out of the archive as a FiveLineOrder
and its "received" receipt reach SLB; the malformed one must be answered "rejected" naming
its field.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from daemon_support import archive_events, free_udp_port, running, wait_until
from slb_peer import SlbPeer

pytestmark = pytest.mark.timeout(90)

ORDER = {
    "order_id": "SLB-E2E-1",
    "issuer": "NB S3",
    "issued": "2026-11-22T12:00:00Z",
    "task": "track_target",
    "location": {"mgrs": "34W EU 31783 00413"},
    "target": "T-72B3 column on road 97",
    "priority": "immediate",
    "control_measures": ["Stay above 400 m MSL"],
}


def write_config(tmp_path: Path, peer: SlbPeer, link: int) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    tls = peer.tls_options()
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}
sources:
  - name: brigade-slb
    type: slb
    base_url: '{peer.base_url}'
    ca_file: '{tls["ca_file"]}'
    cert_file: '{tls["cert_file"]}'
    key_file: '{tls["key_file"]}'
    poll_interval_s: 0.2
processors:
  - {{name: fusion, type: fusion, options: {{update_interval_s: 0.5}}}}
sinks:
  - name: slb
    type: slb
    options: {{base_url: '{peer.base_url}', ca_file: '{tls["ca_file"]}',
               cert_file: '{tls["cert_file"]}', key_file: '{tls["key_file"]}'}}
    retry_initial_s: 0.2
    retry_max_s: 0.5
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [slb], kinds: [detection, track]}}
  - {{sinks: [archive], kinds: [detection, track, order]}}
"""
    )
    return config, archive


@pytest.fixture(scope="module")
def column(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[SlbPeer, list[dict[str, Any]], dict[str, Any], int]:
    tmp_path = tmp_path_factory.mktemp("slb")
    link = free_udp_port()
    with SlbPeer(tmp_path / "pki", fail_first=2, retry_after="1").in_thread() as peer:
        peer.queue_order(ORDER)
        peer.queue_order({**ORDER, "order_id": "SLB-E2E-BAD", "task": "fire_mission"})
        config, archive = write_config(tmp_path, peer, link)
        with running(config) as daemon:
            command = [sys.executable, "-m", "gateway", "simulate", "--scenario", "t72-column"]
            command += ["--to", f"udp://127.0.0.1:{link}", "--duration", "20", "--speed", "8"]
            played = subprocess.run(command, capture_output=True, timeout=60, check=False)
            assert played.returncode == 0, played.stderr.decode(errors="replace")

            def reported() -> set[str]:
                return {
                    e["event_id"]
                    for e in archive_events(archive)
                    if e["kind"] in ("detection", "track")
                }

            def all_delivered() -> bool:
                return bool(reported()) and reported() <= set(peer.accepted)

            wait_until(all_delivered, 15.0, "every archived detection and track in SLB")
            wait_until(lambda: len(peer.receipts) >= 2, 10.0, "both orders answered")
            status = daemon.status()
        returncode = daemon.proc.returncode
        return peer, archive_events(archive), status, returncode


def test_slb_has_every_detection_and_track_once_and_valid(
    column: tuple[SlbPeer, list[dict[str, Any]], dict[str, Any], int],
) -> None:
    peer, events, status, returncode = column
    statuses = [request.status for request in peer.posts if "/object-items" in request.path]
    assert statuses[:2] == [503, 503]  # retried after SLB's Retry-After
    assert 400 not in statuses  # every body passed the schema and carried its key
    assert peer.handshake_failures == []
    archived = {e["event_id"]: e for e in events if e["kind"] in ("detection", "track")}
    assert set(peer.accepted) == set(archived)
    kinds = {d["fischer"]["kind"] for d in peer.accepted.values()}
    assert kinds == {"detection", "track"}
    (sink,) = [s for s in status["sinks"] if s["sink"] == "slb"]
    assert sink["dead_letters"] == 0
    assert returncode == 0


def test_tanks_are_reported_as_jc3iedm_object_items(
    column: tuple[SlbPeer, list[dict[str, Any]], dict[str, Any], int],
) -> None:
    peer, _, _, _ = column
    documents = list(peer.accepted.values())
    tracks = [d for d in documents if d["fischer"]["kind"] == "track"]
    detections = [d for d in documents if d["fischer"]["kind"] == "detection"]
    assert tracks
    assert detections
    for document in tracks:
        assert document["reporting_data"]["cat_code"] == "INFER"
        assert document["hostility_status"]["code"] == "HO"
        assert document["object_item"]["obj_item_id"].startswith("fg:track:T-")
    for document in detections:
        assert document["reporting_data"]["cat_code"] == "REP"
        assert document["hostility_status"]["code"] == "AHO"
        assert document["reporting_data"]["rep_org_name_txt"] == "Fischer26E-F26E-001"
    for document in documents:
        assert document["object_type"]["weapon_type"] == {"cat_code": "TANK"}
        assert document["object_type"]["name_txt"] == "T-72B3"
        assert document["location"]["lat_coord"] == pytest.approx(65.87, abs=0.05)
    # Four vehicles: at least one track each, each id stable over its reports.
    assert len({d["object_item"]["obj_item_id"] for d in tracks}) >= 4


def test_the_order_arrives_and_both_orders_are_answered(
    column: tuple[SlbPeer, list[dict[str, Any]], dict[str, Any], int],
) -> None:
    peer, events, status, _ = column
    (order,) = [e for e in events if e["kind"] == "order"]
    assert order["event_id"] == "slb-order-SLB-E2E-1"
    assert order["source"] == "brigade-slb"
    assert order["task"] == "track_target"
    assert order["location"]["mgrs"] == "34W EU 31783 00413"
    assert order["location"]["point"]["lat_deg"] == pytest.approx(65.83, abs=0.05)
    received = peer.receipts_for("SLB-E2E-1")
    assert [r["status"] for r in received] == ["received"]
    assert received[0]["event_id"] == "slb-order-SLB-E2E-1"
    (rejected,) = peer.receipts_for("SLB-E2E-BAD")
    assert rejected["status"] == "rejected"
    assert rejected["reason"].startswith("task: ")
    assert peer.orders == {}  # neither is offered any more
    (source,) = [s for s in status["sources"] if s["source"] == "brigade-slb"]
    assert source["state"] == "running"
    assert source["counts"]["received"] == 1
    assert source["counts"]["rejected"] == 1
