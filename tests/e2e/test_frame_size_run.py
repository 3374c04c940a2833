"""A sensor frame that says its size is fused at once, through ``fischer-gateway run``.

FISCHER_DETECTION's ``frame_size`` extension tells the gateway how many detections a sensor
frame holds, so fusion need not wait ``frame_wait_s`` for more. The daemon runs with
``frame_wait_s`` at its largest (5 s) and a tick far off (60 s), so a frame not known to be
complete is held that long. Airframe 2 first sends two detections of a frame that claims
three (a size too large: it must wait as before), then airframe 1 a frame of two that says
two. Airframe 1's tracks must reach the archive first, before the wait has passed since
they were sent, and airframe 2's only after it: comparisons with the configured wait, never
an absolute bound.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Airframe, archive_events, free_udp_port, running, wait_until

from gateway.fleet.dialect import fischer_detection
from gateway.flow.localplane import displace

pytestmark = pytest.mark.timeout(90)

LAT, LON = 65.8, 21.7
FRAME_WAIT_S = 5.0


def frame(airframe: Airframe, spots: list[tuple[float, float]], *, frame_size: int) -> list[bytes]:
    """One sensor frame (one airframe, sensor and time): one datagram per detection."""
    time_usec = round(time.time() * 1e6)
    out = []
    for east, north in spots:
        airframe.detections += 1
        lat, lon = displace(LAT, LON, east, north)
        message = fischer_detection(
            time_usec=time_usec,
            detection_id=airframe.detections,
            lat_e7=round(lat * 1e7),
            lon_e7=round(lon * 1e7),
            alt_msl_m=250.0,
            sigma_h_m=10.0,
            class_id=5,  # loitering_munition
            sensor=1,
            confidence_pct=90,
            frame_size=frame_size,
        )
        out.append(bytes(message.pack(airframe.mav)))
    return out


def tracks_of(archive: Path, airframe: str) -> list[dict[str, Any]]:
    return [
        e
        for e in archive_events(archive)
        if e.get("kind") == "track" and e["airframes"] == [airframe]
    ]


def test_a_frame_that_says_its_size_is_tracked_without_the_frame_wait(tmp_path: Path) -> None:
    ports = [free_udp_port(), free_udp_port()]
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - {{id: F1, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{ports[0]}', security: unsecured}}]}}
  - {{id: F2, sysid: 2, links: [{{uri: 'udp://127.0.0.1:{ports[1]}', security: unsecured}}]}}
processors:
  - name: fusion
    type: fusion
    options: {{confirm_hits: 1, frame_wait_s: {FRAME_WAIT_S}, tick_s: 60}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive], kinds: [detection, track]}}
"""
    )
    one, two = Airframe(1), Airframe(2)
    # Two objects 5 km apart per frame: each detection starts its own track.
    spots = [(0.0, 0.0), (5000.0, 0.0)]
    far = [(0.0, 20_000.0), (5000.0, 20_000.0)]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock, running(config):
        sock.sendto(one.heartbeat(), ("127.0.0.1", ports[0]))
        sock.sendto(two.heartbeat(), ("127.0.0.1", ports[1]))
        held_sent = time.monotonic()
        for datagram in frame(two, far, frame_size=3):  # claims one more than it sends
            sock.sendto(datagram, ("127.0.0.1", ports[1]))
        full_sent = time.monotonic()
        for datagram in frame(one, spots, frame_size=2):
            sock.sendto(datagram, ("127.0.0.1", ports[0]))
        wait_until(lambda: len(tracks_of(archive, "F1")) == 2, 30, "the full frame's tracks")
        full_tracked = time.monotonic() - full_sent
        early = tracks_of(archive, "F2")
        wait_until(lambda: len(tracks_of(archive, "F2")) == 2, 30, "the held frame's tracks")
        held_tracked = time.monotonic() - held_sent

    assert early == [], "the frame claiming three was taken before its wait"
    assert full_tracked < FRAME_WAIT_S <= held_tracked
    events = archive_events(archive)
    kinds = [(e["kind"], e["airframe"] if e["kind"] == "detection" else e["airframes"][0])
             for e in events]  # fmt: skip
    # Airframe 1's frame was fused while airframe 2's, sent before it, was still held.
    first_f2_track = kinds.index(("track", "F2"))
    assert [k for k in kinds[:first_f2_track] if k[0] == "track"] == [("track", "F1")] * 2
    detections = [e for e in events if e["kind"] == "detection"]
    assert sorted((d["airframe"], d["frame_size"]) for d in detections) == [
        ("F1", 2),
        ("F1", 2),
        ("F2", 3),
        ("F2", 3),
    ]
    assert all(t["status"] == "created" for t in events if t["kind"] == "track")
