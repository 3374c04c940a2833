"""An attacker on the hub's NATS, with the servers left open (what docs/scale-out.md warns of).

Hub ``a`` (``fischer-gateway run``, its own airframe ``A-1``, the ``nats`` source of ``b``)
and node ``b`` (``run``, the ``nats`` sink) each have a real nats-server on loopback, joined by
a leafnode link. A client with no credentials connects to the hub's server and publishes on
``b``'s subjects: a flood of garbage, a handoff that drops its operator's authorisation, a
well-formed handoff, a detection of the hub's own airframe and a status of an order under an
issuer's id. The hub stays up, logs the refusals a few times (not once per message), keeps
what it takes a cue, never lists its own airframe as ``b``'s, and shows ``b``'s order
status as ``b``'s order, not as a state of one of its own.
"""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path
from typing import Any

import anyio
import nats
import pytest
from daemon_support import archive_events, free_udp_port, running, wait_until
from nats_server import NEEDS_NATS, NatsServer

from gateway.contract import sample_events
from gateway.events import EventKind, Handoff, OrderState, OrderStatus
from sinks.nats.subjects import encode_event, subject_for

pytestmark = [pytest.mark.timeout(120), NEEDS_NATS]

FLOOD = 2000


def hub_config(tmp: Path, nats_url: str) -> tuple[Path, Path]:
    archive = tmp / "a.jsonl"
    config = tmp / "a.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
spool: {{path: '{tmp / "a.spool"}'}}
health: {{port: 0}}
airframes:
  - id: A-1
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{free_udp_port()}', security: unsecured}}]
sources:
  - {{name: nodes, type: nats, node: a, servers: ['{nats_url}'], remotes: [b]}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
  - {{name: map, type: map, options: {{port: 0}}}}
routes:
  - {{kinds: [detection, telemetry, handoff, order_status], sinks: [archive, map]}}
"""
    )
    return config, archive


def node_b_config(tmp: Path, nats_url: str) -> Path:
    """Node b: its airframe B-1 and the ``nats`` sink (which makes b's streams)."""
    config = tmp / "b.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - id: B-1
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{free_udp_port()}', security: unsecured}}]
sinks:
  - {{name: division, type: nats, options: {{node: b, servers: ['{nats_url}']}}}}
"""
    )
    return config


def hostile() -> list[tuple[str, bytes]]:
    """(subject, body) of what the attacker sends as node b, after the flood."""
    handoff = next(e for e in sample_events(frozenset({EventKind.HANDOFF})))
    assert isinstance(handoff, Handoff)
    unauthorised = json.loads(encode_event(handoff))
    unauthorised.update(event_id="HO-x-1", handoff_id="HO-x-1")
    unauthorised["operator_authorisation_required"] = False
    cue = handoff.model_copy(update={"event_id": "HO-x-2", "handoff_id": "HO-x-2"})
    detection = next(e for e in sample_events(frozenset({EventKind.DETECTION})))
    own = detection.model_copy(update={"airframe": "A-1", "event_id": "A-1-det-x"})
    status = OrderStatus(
        event_id="slb-order-1-completed",
        order_event_id="slb-order-1",  # an issuer's id: the hub may hold an order of that id
        order_id="1",
        source="slb",
        airframe="A-1",
        time=detection.time,
        status=OrderState.COMPLETED,
    )
    return [
        (subject_for("b", handoff), json.dumps(unauthorised).encode()),
        (subject_for("b", cue), encode_event(cue)),
        (subject_for("b", own), encode_event(own)),
        (subject_for("b", status), encode_event(status)),
    ]


async def attack(url: str) -> None:
    client = await nats.connect(url)  # no credentials: the server lets anyone in
    js = client.jetstream(domain="b")
    acks = [
        await js.publish_async("fsg.b.det.B-1", b"\x00garbage %d {" % n, headers=None)
        for n in range(FLOOD)
    ]
    for subject, body in hostile():
        acks.append(await js.publish_async(subject, body))
    for ack in acks:
        await ack
    await client.drain()


def test_an_open_hubs_attacker_ends_nothing_floods_no_log_and_gets_cues_only(
    tmp_path: Path,
) -> None:
    hub_server = NatsServer(tmp_path, "a", hub=True)
    b_server = NatsServer(tmp_path, "b", leaf_of=f"nats-leaf://127.0.0.1:{hub_server.leaf_port}")
    with hub_server, b_server:
        wait_until(lambda: len(hub_server.leafz().get("leafs") or []) == 1, 20, "the leaf link")
        a_config, a_archive = hub_config(tmp_path, hub_server.url)
        b_config = node_b_config(tmp_path, b_server.url)
        with running(b_config) as node_b, running(a_config) as hub:
            node_b.wait_event("sink_opened", 20.0)  # b's streams exist
            map_url = str(hub.wait_event("map_listening", 20.0)["url"])
            anyio.run(attack, hub_server.url)

            def counts() -> dict[str, int]:
                return dict(hub.status()["sources"][0]["counts"])

            wait_until(
                lambda: counts().get("bad", 0) == FLOOD + 1 and counts().get("order_status") == 1,
                30,
                "the flood refused and the rest taken",
            )
            taken = counts()
            assert hub.proc.poll() is None
            # One line for the first refusal, at most one more per 10 s: never one per message.
            assert 1 <= len(hub.events("nats_message_refused")) <= 3
            events = {e["event_id"]: e for e in archive_events(a_archive)}
            assert "HO-x-1" not in events  # a handoff without the operator's authorisation
            cue = events["HO-x-2"]
            assert (cue["kind"], cue["origin_node"]) == ("handoff", "b")
            assert cue["operator_authorisation_required"] is True
            assert taken["handoff"] == 1
            assert taken["detection"] == 1

            remote = hub.status()["remote"]
            assert remote["nodes"]["b"]["events"] == 3
            assert "A-1" not in remote["airframes"]  # the hub's own airframe stays its own

            with urllib.request.urlopen(map_url + "api/picture", timeout=10) as reply:  # noqa: S310
                picture: dict[str, Any] = json.loads(reply.read())
            layers = picture["layers"]
            (cue_entity,) = [c for c in layers["cue"] if c["id"] == "HO-x-2"]
            assert cue_entity["origin_node"] == "b"
            orders = {o["id"]: o for o in layers["order"]}
            assert "slb-order-1" not in orders  # not a state of the hub's own order
            assert orders["node/b/slb-order-1"]["status"] == "completed"
            assert orders["node/b/slb-order-1"]["origin_node"] == "b"
