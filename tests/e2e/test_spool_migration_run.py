"""A spool of schema 1 from a running node, taken over by this gateway: ``fischer-gateway run``.

The file is what a schema 1 gateway left on a node whose sinks were behind (a ``pending`` row
per sink and event, a dead letter, a detection id taken in). The daemon migrates it at start;
each sink (a jsonl archive: the peer) then gets exactly the events it was owed, once, in their
order, and the live detections after them; a restart finds nothing owed and sends nothing
again. Loopback only.
"""

from __future__ import annotations

import socket
from datetime import UTC, datetime
from pathlib import Path

import pytest

from gateway.events import Detection, Position, Sensor
from tests.daemon_support import Airframe, archive_events, free_udp_port, running, wait_until
from tests.spool_v1 import write_v1

pytestmark = pytest.mark.timeout(120)

T0 = datetime(2026, 11, 27, 9, 0, tzinfo=UTC)
LIVE = 3


def detection(n: int) -> Detection:
    return Detection(
        event_id=f"F26E-001-det-old-{n}",
        airframe="F26E-001",
        time=T0,
        sensor=Sensor.EO,
        object_class="tank",
        confidence=0.8,
        position=Position(lat_deg=65.85, lon_deg=21.70),
        sigma_h_m=10.0,
    )


def write_node(tmp_path: Path, link: int) -> Path:
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
  - {{name: north, type: jsonl, options: {{path: '{tmp_path / "north.jsonl"}'}}}}
  - {{name: south, type: jsonl, options: {{path: '{tmp_path / "south.jsonl"}'}}}}
routes:
  - {{sinks: [north, south], kinds: [detection]}}
"""
    )
    return config


def ids(path: Path) -> list[str]:
    return [str(event["event_id"]) for event in archive_events(path)]


def test_a_schema_1_spool_is_migrated_and_delivers_what_it_owed_once(tmp_path: Path) -> None:
    old = [detection(n) for n in range(40)]
    # north had confirmed up to 19, south up to 9 and refused 3 for good.
    write_v1(
        tmp_path / "spool.db",
        old,
        {"north": range(20, 40), "south": [*range(4, 40)]},
        dead=[("south", old[3], "refused by the peer")],
        seen=[old[39].event_id],
    )
    owed_north = [e.event_id for e in old[20:]]
    owed_south = [e.event_id for e in old[4:]]
    link = free_udp_port()
    config = write_node(tmp_path, link)
    airframe = Airframe(1)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        with running(config) as daemon:
            migrated = daemon.wait_event("spool_migrated", 20)
            wait_until(
                lambda: (
                    ids(tmp_path / "north.jsonl") == owed_north
                    and ids(tmp_path / "south.jsonl") == owed_south
                ),
                30,
                "the owed events at both archives",
            )
            out.sendto(airframe.heartbeat() + airframe.position(), ("127.0.0.1", link))
            for _ in range(LIVE):
                out.sendto(airframe.detection(), ("127.0.0.1", link))
            wait_until(
                lambda: (
                    len(ids(tmp_path / "north.jsonl")) == len(owed_north) + LIVE
                    and len(ids(tmp_path / "south.jsonl")) == len(owed_south) + LIVE
                ),
                30,
                "the live detections at both archives",
            )
            wait_until(lambda: daemon.metric("fg_spool_pending_events") == 0, 20, "nothing owed")
            assert daemon.metric("fg_spool_dead_letters") == 1
        north, south = ids(tmp_path / "north.jsonl"), ids(tmp_path / "south.jsonl")
        with running(config) as again:
            status = again.status()["spool"]
            assert again.events("spool_migrated") == []
            assert again.events("spool_resumed") == []
    finally:
        out.close()
    assert migrated["pending"] == {"north": 20, "south": 36}
    assert status["pending"] == {}
    assert status["dead_letters"] == 1
    assert north[: len(owed_north)] == owed_north  # owed first, in their order, once
    assert south[: len(owed_south)] == owed_south
    live = north[len(owed_north) :]
    assert len(live) == len(set(live)) == LIVE
    assert live == south[len(owed_south) :]
    assert not set(live) & {e.event_id for e in old}
    # The restart sent nothing again.
    assert (ids(tmp_path / "north.jsonl"), ids(tmp_path / "south.jsonl")) == (north, south)
