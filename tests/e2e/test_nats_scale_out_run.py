"""Several nodes, one picture: two ``fischer-gateway run`` nodes joined by NATS JetStream.

Each node has its own nats-server (JetStream, its own domain) started for the test with random
ports on loopback; leaf node ``b`` reaches hub ``a`` through a TCP relay the test controls.
Node ``b`` holds 30 simulated airframes and publishes through its ``nats`` sink; node ``a``
holds 10 (their sysids reuse ``b``'s), aggregates ``b`` through its ``nats`` source and fuses
every node's detections into its own tracks. The aggregating node's picture (its jsonl
archive) must hold every airframe and every detection exactly once, ``b``'s marked with
their origin; then the leaf link is cut for 5 s while ``b`` keeps detecting, and after
the link comes back nothing is lost and nothing is doubled. Last, node ``b``'s own
nats-server stops while it detects: its spool holds the detections, and they reach the hub
once the server is back; then node ``b`` is killed (SIGKILL) just after a round of
detections and started again on its spool: what it had taken in reaches the hub, once.
"""

from __future__ import annotations

import json
import socket
import time
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import anyio
import nats
import pytest
from daemon_support import (
    Airframe,
    archive_events,
    free_tcp_port,
    free_udp_port,
    running,
    wait_until,
)
from nats_server import NEEDS_NATS, NatsServer, TcpCut

from gateway.events import Position, Telemetry
from gateway.fleet.dialect import fischer_detection

pytestmark = [
    pytest.mark.timeout(150),
    NEEDS_NATS,
]

LEAF_AIRFRAMES = 30
HUB_AIRFRAMES = 10
CUT_S = 5.0
#: The battery node b cues (an id with a '.', as subjects must escape it).
BATTERY = "GUTE.1"


def node_config(
    tmp: Path,
    node: str,
    airframes: list[str],
    udp_port: int,
    nats_url: str,
    *,
    remotes: list[str] | None = None,
) -> tuple[Path, Path]:
    """A node's config: its airframes on one UDP port and a jsonl archive; with ``remotes``
    the aggregating node (fusion, the ``nats`` source), else a node with the ``nats`` sink."""
    archive = tmp / f"{node}.jsonl"
    lines = [
        "gateway: {shutdown_deadline_s: 2}",
        f"spool: {{path: '{tmp / (node + '.spool')}'}}",
        "health: {port: 0}",
        "airframes:",
    ]
    for sysid, airframe in enumerate(airframes, start=1):
        lines += [
            f"  - id: {airframe}",
            f"    sysid: {sysid}",
            f"    links: [{{uri: 'udp://127.0.0.1:{udp_port}', security: unsecured, name: l}}]",
        ]
    lines += [
        "sinks:",
        f"  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}",
    ]
    if remotes is not None:
        lines += [
            "processors:",
            "  - {name: fusion, type: fusion, options: {update_interval_s: 0.5, tick_s: 0.2}}",
            "sources:",
            f"  - {{name: brigades, type: nats, node: {node}, servers: ['{nats_url}'],"
            f" remotes: [{', '.join(remotes)}]}}",
            "routes:",
            "  - {kinds: [detection, telemetry, track, handoff], sinks: [archive]}",
        ]
    else:
        # The brigade node cues the battery near its airframes' objects (a handoff, a cue
        # for the battery's operator), and sends its cues to the hub as well.
        lines += [
            "  - {name: division, type: nats, retry_initial_s: 0.2, retry_max_s: 1,",
            f"     options: {{node: {node}, servers: ['{nats_url}'], request_timeout_s: 1}}}}",
            "processors:",
            "  - {name: fusion, type: fusion, options: {update_interval_s: 0.5, tick_s: 0.2}}",
            "  - {name: cuas, type: counter_uas, options: {min_confidence: 0.5, batteries:",
            f"     [{{id: {BATTERY}, lat_deg: 65.83, lon_deg: 21.7,",
            "       effectors: [TRIDON_MK2_40MM, EW_COUNTERMEASURES]}]}}",
            "routes:",
            "  - {kinds: [detection, telemetry, handoff], sinks: [archive, division]}",
            "  - {kinds: [track], sinks: [archive]}",
        ]
    config = tmp / f"{node}.yaml"
    config.write_text("\n".join(lines) + "\n")
    return config, archive


def detection(airframe: Airframe, index: int) -> bytes:
    airframe.detections += 1
    sysid = airframe.mav.srcSystem
    message = fischer_detection(
        time_usec=round(time.time() * 1e6),
        detection_id=airframe.detections,
        lat_e7=658_000_000 + sysid * 20_000 + index * 10,  # one object per airframe, ~220 m apart
        lon_e7=217_000_000,
        alt_msl_m=250.0,
        sigma_h_m=8.0,
        class_id=5,  # loitering_munition
        sensor=0,
        confidence_pct=85,
        subtype="LANCET",
    )
    return bytes(message.pack(airframe.mav))


class Fleet:
    """Simulated airframes of one node on its shared UDP port."""

    def __init__(self, port: int, count: int) -> None:
        self.port = port
        self.airframes = [Airframe(sysid) for sysid in range(1, count + 1)]
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def state(self) -> None:
        for airframe in self.airframes:
            self.sock.sendto(airframe.heartbeat(), ("127.0.0.1", self.port))
            self.sock.sendto(airframe.position(65.8, 21.7), ("127.0.0.1", self.port))

    def detect(self, rounds: int) -> None:
        for index in range(rounds):
            self.state()  # airframes report their state all the time
            for airframe in self.airframes:
                self.sock.sendto(detection(airframe, index), ("127.0.0.1", self.port))
            time.sleep(0.05)  # each round its own time_usec


def claim_own_airframe(url: str, airframe: str) -> None:
    """A client of the hub's NATS forges node b's state of the hub's ``airframe``."""
    forged = Telemetry(
        event_id="forged",
        airframe=airframe,
        time=datetime.now(UTC),
        position=Position(lat_deg=10.0, lon_deg=10.0),
    )

    async def main() -> None:
        client = await nats.connect(url)
        await client.jetstream().publish(f"fsg.b.tlm.{airframe}", forged.model_dump_json().encode())
        await client.close()

    anyio.run(main)


def replay(url: str, event: dict[str, Any]) -> None:
    """A client of the hub's NATS sends ``event`` of node b again under a new message id."""
    body = {k: v for k, v in event.items() if k != "origin_node" and v is not None}
    subject = f"fsg.b.det.{event['airframe'].replace('.', '_2E')}"

    async def main() -> None:
        client = await nats.connect(url)
        await client.jetstream().publish(
            subject, json.dumps(body).encode(), headers={"Nats-Msg-Id": "replayed"}
        )
        await client.close()

    anyio.run(main)


def picture(archive: Path) -> list[dict[str, Any]]:
    return archive_events(archive)


def cues(archive: Path) -> Counter[str]:
    """The handoffs (cues) in a node's archive, by event id."""
    return Counter(e["event_id"] for e in picture(archive) if e["kind"] == "handoff")


def detections_by_airframe(events: list[dict[str, Any]]) -> Counter[str]:
    return Counter(e["airframe"] for e in events if e["kind"] == "detection")


def test_the_aggregating_node_holds_every_airframe_and_detection_once_across_a_cut(
    tmp_path: Path,
) -> None:
    leaf_port = free_tcp_port()
    with TcpCut(leaf_port) as link:
        hub_server = NatsServer(
            tmp_path, "a", hub=True, leaf_port=leaf_port, advertise=f"127.0.0.1:{link.port}"
        )
        leaf_server = NatsServer(
            tmp_path, "b", leaf_of=f"nats-leaf://127.0.0.1:{link.port}", port=free_tcp_port()
        )
        with hub_server, leaf_server:
            wait_until(lambda: bool(hub_server.leafz().get("leafs")), 20, "the leaf link")
            b_ids = [f"B-{n:02d}.bde2" for n in range(1, LEAF_AIRFRAMES + 1)]  # ids with '.'
            a_ids = [f"A-{n:02d}" for n in range(1, HUB_AIRFRAMES + 1)]
            b_udp, a_udp = free_udp_port(), free_udp_port()
            b_config, b_archive = node_config(tmp_path, "b", b_ids, b_udp, leaf_server.url)
            a_config, a_archive = node_config(
                tmp_path, "a", a_ids, a_udp, hub_server.url, remotes=["b"]
            )
            b_fleet, a_fleet = Fleet(b_udp, LEAF_AIRFRAMES), Fleet(a_udp, HUB_AIRFRAMES)
            with running(a_config) as hub, running(b_config) as leaf:
                b_fleet.state()
                a_fleet.state()
                b_fleet.detect(3)
                a_fleet.detect(3)
                expected = {**dict.fromkeys(b_ids, 3), **dict.fromkeys(a_ids, 3)}

                def all_in(want: dict[str, int]) -> bool:
                    return detections_by_airframe(picture(a_archive)) == Counter(want)

                wait_until(lambda: all_in(expected), 60, "every detection at the hub")
                claim_own_airframe(hub_server.url, a_ids[0])

                # The leaf link is cut; node b keeps detecting and keeps its own picture.
                link.cut()
                cut_at = time.monotonic()
                b_fleet.detect(3)
                wait_until(
                    lambda: (
                        sum(detections_by_airframe(picture(b_archive)).values())
                        == 6 * LEAF_AIRFRAMES
                    ),
                    30,
                    "node b's own picture during the cut",
                )
                time.sleep(max(0.0, CUT_S - (time.monotonic() - cut_at)))
                assert detections_by_airframe(picture(a_archive)) == Counter(expected)
                link.restore()
                expected.update(dict.fromkeys(b_ids, 6))
                wait_until(lambda: all_in(expected), 60, "the cut's detections at the hub")

                # Node b's own NATS server stops: b keeps working, its spool holds the
                # detections, and its sink catches up once the server is back.
                leaf_server.stop()
                b_fleet.detect(2)
                wait_until(
                    lambda: (
                        sum(detections_by_airframe(picture(b_archive)).values())
                        == 8 * LEAF_AIRFRAMES
                    ),
                    30,
                    "node b's own picture with its NATS down",
                )
                wait_until(
                    lambda: leaf.metric("fg_sink_send_failures_total", sink="division") > 0,
                    30,
                    "node b's nats sink failing",
                )
                leaf_server.start()
                expected.update(dict.fromkeys(b_ids, 8))
                wait_until(lambda: all_in(expected), 60, "the outage's detections at the hub")

                # kill -9 of node b just after a round of detections: whatever its spool had
                # taken in reaches the hub once it runs again, and nothing twice.
                b_fleet.detect(1)
                leaf.kill9()
                with running(b_config) as leaf:
                    b_fleet.state()

                    def b_took() -> Counter[str]:
                        ids = {
                            (e["airframe"], e["event_id"])
                            for e in picture(b_archive)
                            if e["kind"] == "detection"
                        }
                        return Counter(airframe for airframe, _ in ids)

                    def settled() -> bool:
                        took = b_took()
                        at_hub = detections_by_airframe(picture(a_archive))
                        return all(at_hub[a] == took[a] >= 8 for a in b_ids)

                    wait_until(settled, 60, "what node b took before the kill at the hub")
                    expected.update(b_took())
                    sink_counts = leaf.status()
                b_fleet.state()
                wait_until(
                    lambda: (
                        {e["airframe"] for e in picture(a_archive) if e["kind"] == "telemetry"}
                        == set(a_ids) | set(b_ids)
                    ),
                    30,
                    "every airframe's state at the hub",
                )
                # Every cue node b made (its archive has them) at the hub, with its id.
                wait_until(
                    lambda: bool(cues(b_archive)) and set(cues(a_archive)) == set(cues(b_archive)),
                    60,
                    "node b's cues at the hub",
                )
                time.sleep(1.0)  # anything doubled would arrive now
                events = picture(a_archive)
                source = hub.status()["sources"]
            # The hub restarts; an old detection of b's is sent again under a new message
            # id (past the stream's de-duplication), then forged news of a hub airframe
            # that shows when the source got past it: the spool still knows the old id.
            old = next(e for e in events if e["kind"] == "detection" and e.get("origin_node"))
            with running(a_config) as hub:
                replay(hub_server.url, old)
                claim_own_airframe(hub_server.url, a_ids[0])
                wait_until(
                    lambda: hub.status()["sources"][0]["counts"].get("own_airframe") == 1,
                    30,
                    "the restarted hub past the replay",
                )
                restarted = hub.status()["sources"][0]["counts"]
            assert restarted.get("duplicate") == 1, restarted
            assert "detection" not in restarted
            replayed = [e for e in picture(a_archive) if e.get("event_id") == old["event_id"]]
            assert len(replayed) == 1
            b_fleet.sock.close()
            a_fleet.sock.close()
    # Every detection once: by id, and no id twice.
    detections = [e for e in events if e["kind"] == "detection"]
    ids = Counter(e["event_id"] for e in detections)
    assert max(ids.values()) == 1, [i for i, n in ids.items() if n > 1][:5]
    assert detections_by_airframe(events) == Counter(expected)
    # b's are marked with their origin; a's own are not.
    for event in detections:
        assert event.get("origin_node") == ("b" if event["airframe"] in b_ids else None)
    # The forged state of the hub's own airframe was refused, never on its picture.
    assert source[0]["counts"]["own_airframe"] == 1
    assert not [e for e in events if e.get("airframe") in a_ids and e.get("origin_node")]
    # Every airframe of both nodes on the hub's picture.
    airframes = {e["airframe"] for e in events if e["kind"] == "telemetry"}
    assert airframes == set(a_ids) | set(b_ids)
    # Node b's cues reached the hub once each, with their ids, marked with their origin, and
    # still cues: for the battery's operator to authorise, nothing the hub commands.
    handoffs = [e for e in events if e["kind"] == "handoff"]
    assert handoffs
    assert max(Counter(e["event_id"] for e in handoffs).values()) == 1
    for cue in handoffs:
        assert cue["origin_node"] == "b"
        assert cue["battery"] == BATTERY
        assert cue["operator_authorisation_required"] is True
    assert not [e for e in events if e["kind"] in ("order", "order_status")]
    # The hub fused b's detections into its own tracks.
    tracked = {a for e in events if e["kind"] == "track" for a in e["airframes"]}
    assert tracked & set(b_ids), "no track from node b's detections"
    # The source took each of b's detections once; the link came back through the relay.
    taken = sum(n for airframe, n in expected.items() if airframe in b_ids)
    assert source[0]["counts"]["detection"] == taken
    assert source[0]["by_node"]["b"] >= taken + LEAF_AIRFRAMES
    division = next(sink for sink in sink_counts["sinks"] if sink["sink"] == "division")
    assert division["state"] == "open"
    assert link.connections >= 2
