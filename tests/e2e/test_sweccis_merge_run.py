"""A merged track reaches SWECCIS as merged, naming the survivor, with ``fas_version: 2``.

``fischer-gateway run --config FILE`` in a child process: two airframes on loopback UDP, the
``fusion`` processor and a ``sweccis`` sink (``fas_version: 2``) to a real SWECCIS server
(``SweccisPeer``: TLS with client certificates, length frames, every document checked against
the shipped XSD of its own version). The airframes report one tank: F1 where it is, F2 first
60 m off and closing in, then agreeing (the tracker's own twin case, ``tests/tracking``), so
the second track is folded into the first.

The server must receive the second track's last Intel document with Status ``merged`` and
``MergedInto`` naming the first, valid against the version 2 XSD, and never a ``lost`` for it.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest
from daemon_support import Airframe, free_udp_port, running, wait_until
from lxml import etree
from sweccis_peer import SweccisPeer

from gateway.fleet.dialect import fischer_detection
from sinks.sweccis.fasxml import SCHEMA_VERSIONS, load_schema

pytestmark = pytest.mark.timeout(90)

NS2 = f"{{{SCHEMA_VERSIONS['2']}}}"
LAT_E7, LON_E7 = 658_000_000, 217_000_000
M_PER_E7_LON = 0.0111 * 0.41  # metres per 1e-7 degree of longitude at 65.8 N (cos 65.8°)


def write_config(tmp_path: Path, peer: SweccisPeer, ports: list[int]) -> Path:
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
  - {{id: F1, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{ports[0]}', security: unsecured,
     name: l1}}]}}
  - {{id: F2, sysid: 2, links: [{{uri: 'udp://127.0.0.1:{ports[1]}', security: unsecured,
     name: l2}}]}}
processors:
  # The reports carry their own times, a second apart, replayed in a few seconds: nothing
  # ages or coasts meanwhile, and every update is published at once.
  - {{name: fusion, type: fusion,
     options: {{update_interval_s: 0, coast_after_s: 120, lost_after_s: 300, tick_s: 60}}}}
sinks:
  - name: sweccis
    type: sweccis
    options: {{client_id: node-e2e, fas_version: 2, kinds: [track], {files}}}
    retry_initial_s: 0.2
    retry_max_s: 0.5
routes:
  - {{sinks: [sweccis], kinds: [track]}}
"""
    )
    return config


def report(airframe: Airframe, at_usec: int, *, sensor: int, east_m: float) -> bytes:
    airframe.detections += 1
    message = fischer_detection(
        time_usec=at_usec,
        detection_id=airframe.detections,
        lat_e7=LAT_E7,
        lon_e7=LON_E7 + round(east_m / M_PER_E7_LON),
        alt_msl_m=40.0,
        sigma_h_m=5.0,
        class_id=1,  # tank
        sensor=sensor,
        confidence_pct=90,
        subtype="T-72B3",
    )
    return bytes(message.pack(airframe.mav))


def tracks(peer: SweccisPeer) -> list[etree._Element]:
    """The Track element of every Intel document the server accepted, in arrival order."""
    found = [root.find(f"{NS2}Track") for root in peer.accepted.values()]
    return [track for track in found if track is not None]


def test_a_merged_track_arrives_as_merged_naming_the_survivor(tmp_path: Path) -> None:
    ports = [free_udp_port(), free_udp_port()]
    one, two = Airframe(1), Airframe(2)
    start_usec = round((time.time() - 60.0) * 1e6)  # a minute ago, a second per report
    with (
        SweccisPeer(tmp_path / "pki").in_thread() as peer,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock,
    ):
        config = write_config(tmp_path, peer, ports)
        with running(config):
            sock.sendto(one.heartbeat(), ("127.0.0.1", ports[0]))
            sock.sendto(two.heartbeat(), ("127.0.0.1", ports[1]))
            for i in range(40):  # F2's reports start 60 m off and close in on F1's
                at = start_usec + i * 1_000_000
                sock.sendto(report(one, at, sensor=0, east_m=0.0), ("127.0.0.1", ports[0]))
                time.sleep(0.03)  # each its own frame
                far = max(0.0, 60.0 - 3.0 * i)
                sock.sendto(
                    report(two, at + 500_000, sensor=1, east_m=far), ("127.0.0.1", ports[1])
                )
                time.sleep(0.03)

            def merged_arrived() -> bool:
                return any(t.findtext(f"{NS2}Status") == "merged" for t in tracks(peer))

            wait_until(merged_arrived, 20.0, "a merged track at the SWECCIS server")
    assert peer.invalid == []
    schema = etree.XMLSchema(etree.fromstring(load_schema("2")))
    for root in peer.accepted.values():
        assert root.get("version") == "2"
        assert schema.validate(root), schema.error_log
    documents = tracks(peer)
    created = [
        t.findtext(f"{NS2}TrackId") for t in documents if t.findtext(f"{NS2}Status") == "created"
    ]
    assert len(created) == 2, created
    survivor, twin = created
    (merged,) = [t for t in documents if t.findtext(f"{NS2}Status") == "merged"]
    assert merged.findtext(f"{NS2}TrackId") == twin
    assert merged.findtext(f"{NS2}MergedInto") == survivor
    assert not [t for t in documents if t.findtext(f"{NS2}Status") == "lost"]
    # The survivor lives on: it is updated after the merge.
    after = documents[documents.index(merged) + 1 :]
    assert any(t.findtext(f"{NS2}TrackId") == survivor for t in after)
