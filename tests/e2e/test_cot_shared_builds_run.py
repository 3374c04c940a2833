"""CoT built once for all sinks alike, through ``fischer-gateway run``: the bytes do not change.

Four CoT UDP sinks take the same detections: two with the default options, one with its own
uid prefix, one in mesh protobuf. Every receiver must get, byte for byte, what a CoT sink of
its configuration builds on its own from the event the daemon published (read back from a
``jsonl`` archive): sharing a build between sinks whose options are equal changes nothing a
receiver sees, and a sink whose options differ never gets another sink's bytes. Loopback only.
"""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from gateway.events import Detection
from sinks.cot.codec import Encoded
from sinks.cot.event import build
from sinks.cot.sink import CotSink, CotSinkConfig
from tests.daemon_support import Airframe, archive_events, free_udp_port, running, wait_until

pytestmark = pytest.mark.timeout(90)

DETECTIONS = 3
OPTIONS = ({}, {}, {"uid_prefix": "blue-"}, {"protocol": "protobuf"})


def write_node(tmp_path: Path, link: int, receivers: list[int], archive: Path) -> Path:
    sinks = []
    for i, (port, extra) in enumerate(zip(receivers, OPTIONS, strict=True)):
        options = "".join(f", {key}: {value}" for key, value in extra.items())
        sinks.append(
            f"  - {{name: cot{i}, type: cot, options: {{destinations: "
            f"['udp://127.0.0.1:{port}']{options}}}}}"
        )
    names = ", ".join(f"cot{i}" for i in range(len(receivers)))
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
spool: {{path: '{tmp_path / "spool.db"}'}}
airframes:
  - id: F26E-001
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured, name: fleet}}]
sinks:
{chr(10).join(sinks)}
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [{names}, archive], kinds: [detection]}}
"""
    )
    return config


def receive(sock: socket.socket, datagrams: list[bytes]) -> None:
    """The detections waiting on ``sock`` (not the mesh's control-only announcements)."""
    while True:
        try:
            data = sock.recv(65_535)
        except BlockingIOError:
            return
        if b"-det-" in data:
            datagrams.append(data)


def test_every_receiver_gets_the_bytes_its_sink_would_build_alone(tmp_path: Path) -> None:
    receivers = []
    for _ in OPTIONS:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        receivers.append(sock)
    got: list[list[bytes]] = [[] for _ in receivers]
    link = free_udp_port()
    archive = tmp_path / "archive.jsonl"
    ports = [s.getsockname()[1] for s in receivers]
    config = write_node(tmp_path, link, ports, archive)
    airframe = Airframe(1)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        with running(config) as daemon:
            daemon.wait_event("gateway_started", 30)
            out.sendto(airframe.heartbeat() + airframe.position(), ("127.0.0.1", link))
            for _ in range(DETECTIONS):
                out.sendto(airframe.detection(), ("127.0.0.1", link))

            def arrived() -> bool:
                for sock, datagrams in zip(receivers, got, strict=True):
                    receive(sock, datagrams)
                return all(len(datagrams) >= DETECTIONS for datagrams in got) and (
                    len(archive_events(archive)) >= DETECTIONS
                )

            wait_until(arrived, 30, f"{DETECTIONS} detections at every receiver")
    finally:
        out.close()
        for sock in receivers:
            sock.close()
    events = [Detection.model_validate(e) for e in archive_events(archive)]
    for port, extra, datagrams in zip(ports, OPTIONS, got, strict=True):
        # What the sink as configured makes of each event on its own: build, then encode.
        options = CotSink(
            "alone",
            CotSinkConfig.model_validate({"destinations": [f"udp://127.0.0.1:{port}"], **extra}),
        ).options
        encoding = "mesh" if extra.get("protocol") == "protobuf" else "xml"
        expected = []
        for event in events:
            cot = build(event, options, {})
            assert cot is not None
            expected.append(Encoded(cot).get(encoding))
        assert len(datagrams) == len(expected) == DETECTIONS
        for data, want in zip(datagrams, expected, strict=True):
            # A mesh datagram may carry the TakControl advertisement before the event.
            assert data == want or (
                encoding == "mesh" and data[:3] == want[:3] and data.endswith(want[3:])
            )
    assert got[0] == got[1]
    assert got[2] != got[0]
    assert all(b'uid="blue-det-' in data for data in got[2])
