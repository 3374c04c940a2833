"""A serial link missing at start or lost while running degrades itself, not the daemon.

Through ``fischer-gateway run``: a node with a serial airframe on a pseudo-terminal that
does not exist yet, and a UDP airframe. The UDP airframe's telemetry keeps reaching the
archive while the serial device is missing, appears, and disappears again.
"""

from __future__ import annotations

import os
import socket
import tty
from pathlib import Path

import pytest
from daemon_support import Airframe, archive_events, free_udp_port, running, wait_until

pytestmark = pytest.mark.timeout(90)


def serial_link(status: dict[str, object]) -> dict[str, object]:
    links = status["links"]
    assert isinstance(links, list)
    return next(link for link in links if str(link["uri"]).startswith("serial://"))


def positions(archive: Path, airframe: str) -> int:
    return sum(
        1
        for event in archive_events(archive)
        if event.get("kind") == "telemetry" and event.get("airframe") == airframe
    )


def test_missing_then_lost_serial_device_leaves_the_other_airframe_flowing(
    tmp_path: Path,
) -> None:
    device = tmp_path / "radio"  # a symlink to a pty, made later
    udp_port = free_udp_port()
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - id: SER
    sysid: 5
    links: [{{uri: 'serial://{device}?baud=57600', security: unsecured,
              reconnect_initial_s: 0.05, reconnect_max_s: 0.2}}]
  - id: NET
    sysid: 6
    links: [{{uri: 'udp://127.0.0.1:{udp_port}', security: unsecured}}]
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive]}}
"""
    )
    ser, net = Airframe(5), Airframe(6)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def net_flows() -> None:
        before = positions(archive, "NET")
        sender.sendto(net.position(), ("127.0.0.1", udp_port))
        wait_until(lambda: positions(archive, "NET") > before, 10, "NET telemetry archived")

    try:
        with running(config) as daemon:
            assert daemon.get("/readyz")[0] == 200
            link = serial_link(daemon.status())
            assert link["state"] == "waiting for device"
            assert str(device) in str(link["reason"])
            net_flows()
            # The radio is plugged in.
            master, slave = os.openpty()
            tty.setraw(master)
            device.symlink_to(os.ttyname(slave))
            wait_until(lambda: serial_link(daemon.status())["state"] == "open", 10, "open")
            os.write(master, ser.position())
            wait_until(lambda: positions(archive, "SER") > 0, 10, "SER telemetry archived")
            # ... and pulled out again.
            os.close(slave)
            os.close(master)
            device.unlink()
            wait_until(
                lambda: serial_link(daemon.status())["state"] == "waiting for device",
                10,
                "the lost device noticed",
            )
            net_flows()
            assert daemon.get("/readyz")[0] == 200
            assert daemon.proc.poll() is None
            assert len(daemon.events("link_device_unavailable")) <= 3
    finally:
        sender.close()
    assert daemon.proc.returncode == 0
