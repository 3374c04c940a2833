"""The fusion processor in the daemon as operators run it: two airframes, one loitering munition.

``fischer-gateway run --config FILE`` in a child process with two unsecured airframes on
loopback UDP, the ``fusion`` processor and a jsonl archive. Airframe 1 reports the munition
on EO at 0.80 in three frames (the tracker confirms a track after three detections: M of N)
and airframe 2 on IR at 0.75, a few metres away; the archive must hold one track for it,
created and then updated to the seed's 0.95 with both airframes, and (with a short
``lost_after_s``) lost once the reports stop.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Airframe, archive_events, free_udp_port, running, wait_until

from gateway.fleet.dialect import fischer_detection

pytestmark = pytest.mark.timeout(90)

LAT_E7, LON_E7 = 658_000_000, 217_000_000


def write_config(tmp_path: Path, ports: list[int]) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - id: F1
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{ports[0]}', security: unsecured, name: l1}}]
  - id: F2
    sysid: 2
    links: [{{uri: 'udp://127.0.0.1:{ports[1]}', security: unsecured, name: l2}}]
processors:
  - name: fusion
    type: fusion
    options: {{lost_after_s: 3, update_interval_s: 0.5, tick_s: 0.2}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{kinds: [track], sinks: [archive]}}
"""
    )
    return config, archive


def detection_frame(airframe: Airframe, *, sensor: int, confidence_pct: int, dlat_e7: int) -> bytes:
    airframe.detections += 1
    message = fischer_detection(
        time_usec=round(time.time() * 1e6),
        detection_id=airframe.detections,
        lat_e7=LAT_E7 + dlat_e7,
        lon_e7=LON_E7,
        alt_msl_m=250.0,
        sigma_h_m=8.0,
        class_id=5,  # loitering_munition
        sensor=sensor,
        confidence_pct=confidence_pct,
        subtype="LANCET",
    )
    return bytes(message.pack(airframe.mav))


def tracks(archive: Path) -> list[dict[str, Any]]:
    return [e for e in archive_events(archive) if e.get("kind") == "track"]


def test_two_airframes_fuse_into_one_track_updated_to_095_then_lost(tmp_path: Path) -> None:
    ports = [free_udp_port(), free_udp_port()]
    config, archive = write_config(tmp_path, ports)
    one, two = Airframe(1), Airframe(2)
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock,
        running(config),
    ):
        sock.sendto(one.heartbeat(), ("127.0.0.1", ports[0]))
        sock.sendto(two.heartbeat(), ("127.0.0.1", ports[1]))
        for _ in range(3):  # three frames: a tentative track confirmed, then published
            eo = detection_frame(one, sensor=0, confidence_pct=80, dlat_e7=0)
            sock.sendto(eo, ("127.0.0.1", ports[0]))
            time.sleep(0.01)  # each its own frame (time_usec)
        wait_until(lambda: len(tracks(archive)) >= 1, 15, "the track created")
        ir = detection_frame(two, sensor=1, confidence_pct=75, dlat_e7=20)  # about 2 m north
        sock.sendto(ir, ("127.0.0.1", ports[1]))
        wait_until(
            lambda: any(t["status"] == "lost" for t in tracks(archive)), 30, "the track lost"
        )
    events = tracks(archive)
    assert len({e["track_id"] for e in events}) == 1
    statuses = [e["status"] for e in events]
    assert statuses[0] == "created"
    assert statuses[-1] == "lost"
    assert statuses.count("lost") == 1
    assert "updated" in statuses
    created = events[0]
    assert created["confidence"] == pytest.approx(0.80)
    assert created["airframes"] == ["F1"]
    updated = next(e for e in events if e["status"] == "updated")
    assert updated["confidence"] == pytest.approx(0.95)
    assert updated["airframes"] == ["F1", "F2"]
    assert updated["sensors"] == ["eo", "ir"]
    assert updated["object_class"] == "loitering_munition"
    assert updated["hostility"] == "hostile"
    assert updated["detection_count"] == 4
    assert created["detection_count"] == 3
    assert len({e["event_id"] for e in events}) == len(events)
