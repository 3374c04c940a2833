"""A crafted sensor frame against the tracker, through ``fischer-gateway run``.

Anyone on an unsecured link can send detections as the airframe configured on it. One sensor
frame (one airframe, sensor and time) of 1,000 detections 2 m apart, dropped on 1,000
tracks, asks the tracker to gate every detection against every track: in pure Python that
held the event loop for seconds. A frame now examines at most ``MAX_FRAME_PAIRS`` pairs and
refuses the rest, counted: the node keeps answering and says what it refused.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest
from daemon_support import Airframe, Daemon, free_udp_port, running, wait_until

from gateway.fleet.dialect import fischer_detection
from gateway.flow.localplane import displace

pytestmark = pytest.mark.timeout(120)

LAT, LON = 65.8, 21.7


def frame(airframe: Airframe, spots: list[tuple[float, float]], time_usec: int) -> list[bytes]:
    """One sensor frame: detections of one airframe and sensor at one time, one datagram each."""
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
            class_id=1,
            sensor=1,
            confidence_pct=80,
            subtype="T-72",
        )
        out.append(bytes(message.pack(airframe.mav)))
    return out


def fusion_status(daemon: Daemon) -> dict[str, int]:
    (fusion,) = [p for p in daemon.status()["processors"] if p["processor"] == "fusion"]
    detail: dict[str, int] = fusion["detail"]
    return detail


def test_a_crafted_crowded_frame_is_cut_to_its_budget_and_the_node_answers(
    tmp_path: Path,
) -> None:
    link = free_udp_port()
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - {{id: F1, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured}}]}}
processors:
  # One frame must stay one frame while its 1,000 datagrams arrive: no early flush.
  - name: fusion
    type: fusion
    queue_max: 5000
    options: {{confirm_hits: 1, max_tracks: 5000, frame_wait_s: 5, tick_s: 30}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{tmp_path / "archive.jsonl"}'}}}}
routes:
  - {{sinks: [archive], kinds: [track]}}
"""
    )
    airframe = Airframe(1)
    now_usec = round(time.time() * 1e6)
    # 1,000 detections 2 m apart: as one frame they start 1,000 tracks (a frame's detections
    # never join each other); the same spots a second later gate against all of them.
    crowd = [((n % 40) * 2.0, (n // 40) * 2.0) for n in range(1000)]
    with running(config) as daemon, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.sendto(airframe.heartbeat(), ("127.0.0.1", link))
        for datagram in frame(airframe, crowd, now_usec):
            sock.sendto(datagram, ("127.0.0.1", link))
            time.sleep(0.0005)  # the kernel's buffer, not the gateway, is the limit here
        for datagram in frame(airframe, crowd, now_usec + 1_000_000):
            sock.sendto(datagram, ("127.0.0.1", link))
            time.sleep(0.0005)
        # The next frame of the same source completes the crowd's (no need to wait 5 s).
        sock.sendto(
            frame(airframe, [(5000.0, 5000.0)], now_usec + 2_000_000)[0], ("127.0.0.1", link)
        )
        wait_until(
            lambda: fusion_status(daemon)["overload_refused"] > 0,
            30,
            "the crowd cut to its budget",
        )
        assert daemon.get("/healthz")[0] == 200
        refused = fusion_status(daemon)["overload_refused"]
    assert 0 < refused < 1000
