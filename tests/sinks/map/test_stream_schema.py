"""The picture and its change stream hold to the JSON Schema shipped for integrators.

``sinks/map/schemas/stream.schema.json`` is what docs/map.md points a program at that
subscribes to the stream instead of writing a sink. Every kind of event the map draws is fed
through a served map sink and what ``/api/picture`` and ``/api/stream`` answer is validated
against it; every field an entity carries must be declared in the schema, so the schema
cannot fall behind the code.
"""

from __future__ import annotations

import json
from datetime import timedelta
from importlib import resources
from typing import Any

import anyio
import httpx
import jsonschema
from test_map import read_events, serving

from gateway.contract import sample_events
from gateway.events import Event, EventKind, LinkState, OrderState, OrderStatus, Track
from sinks.map.picture import LAYERS, Limits, Picture

SCHEMA: dict[str, Any] = json.loads(
    resources.files("sinks.map").joinpath("schemas/stream.schema.json").read_text()
)


def validator(definition: str) -> jsonschema.Draft202012Validator:
    return jsonschema.Draft202012Validator(
        {**SCHEMA, "oneOf": [{"$ref": f"#/$defs/{definition}"}]},
        format_checker=jsonschema.Draft202012Validator.FORMAT_CHECKER,
    )


def every_kind() -> list[Event]:
    """One event of each kind, and the later events that change what is drawn."""
    first = list(sample_events(frozenset(EventKind)))
    start = first[0].time
    cue = next(e for e in first if e.kind == EventKind.HANDOFF)
    order = next(e for e in first if e.kind == EventKind.ORDER)
    telemetry = next(e for e in first if e.kind == EventKind.TELEMETRY)
    later = start + timedelta(seconds=5)
    return [
        *first,
        LinkState(
            event_id="ls-2",
            airframe=telemetry.airframe,
            time=later,
            link="radio",
            is_up=False,
            is_active=False,
            loss_pct=12.5,
            reason="silent",
        ),
        cue.model_copy(update={"revision": 1, "time": later, "note": "revised"}),
        OrderStatus(
            event_id="os-2",
            order_event_id=order.event_id,
            order_id=order.order_id,
            source=order.source,
            time=later,
            status=OrderState.EXECUTING,
            airframe=telemetry.airframe,
        ),
    ]


def declared(layer: str) -> set[str]:
    return set(SCHEMA["$defs"][layer]["properties"])


def test_every_change_of_every_layer_holds_to_the_schema_and_declares_its_fields() -> None:
    picture = Picture(Limits())
    changes = [c for event in every_kind() for c in picture.apply(event)]
    track = next(e for e in sample_events(frozenset({EventKind.TRACK})) if isinstance(e, Track))
    changes += picture.apply(track.model_copy(update={"status": "lost", "event_id": "lost"}))
    check = validator("change")
    for seq, change in enumerate(changes, start=1):
        check.validate({"seq": seq, **change})
        if change["op"] == "upsert":
            assert set(change["data"]) <= declared(change["layer"]), change["layer"]
    drawn = {c["layer"] for c in changes if c["op"] == "upsert"}
    assert drawn == set(LAYERS)
    assert any(c["op"] == "remove" and c["reason"] == "lost" for c in changes)


def test_what_a_program_reads_from_the_node_holds_to_the_schema() -> None:
    events = every_kind()

    async def main() -> None:
        async with serving() as sink:
            await sink.send(events[:-2])
            assert sink.url is not None
            async with httpx.AsyncClient(base_url=sink.url, timeout=10) as client:
                picture = (await client.get("/api/picture")).json()
                validator("snapshot").validate(picture)
                assert {layer for layer, items in picture["layers"].items() if items} == set(LAYERS)
                async with client.stream("GET", "/api/stream") as stream:
                    lines = stream.aiter_lines()
                    ((kind, snapshot),) = await read_events(lines, 1)
                    assert kind == "snapshot"
                    validator("snapshot").validate(snapshot)
                    await sink.send(events[-2:])  # the revised cue, the order executing
                    changes = await read_events(lines, 2)
                    for kind, change in changes:
                        assert kind == "change"
                        validator("change").validate(change)
                    assert {c["layer"] for _, c in changes} == {"cue", "order"}

    anyio.run(main)


def test_another_nodes_airframe_detection_cue_and_fused_track_carry_their_nodes() -> None:
    picture = Picture(Limits())
    first = sample_events(
        frozenset({EventKind.TELEMETRY, EventKind.DETECTION, EventKind.TRACK, EventKind.HANDOFF})
    )
    remote: list[Event] = []
    for event in first:
        if isinstance(event, Track):
            remote.append(event.model_copy(update={"origin_nodes": ("b", "c")}))
        else:
            remote.append(event.model_copy(update={"origin_node": "b"}))
    changes = [c for event in remote for c in picture.apply(event)]
    check = validator("change")
    shown: dict[str, object] = {}
    for seq, change in enumerate(changes, start=1):
        check.validate({"seq": seq, **change})
        data = change["data"]
        shown[change["layer"]] = data.get("origin_nodes", data.get("origin_node"))
    assert shown == {"airframe": "b", "detection": "b", "track": ["b", "c"], "cue": "b"}
    bad = {**changes[0], "seq": 1, "data": {**changes[0]["data"], "origin_node": "<b>"}}
    assert not check.is_valid(bad)


def test_another_nodes_status_never_rewrites_this_nodes_order_of_the_same_id() -> None:
    # Order event ids are the issuer's (slb-order-<id>): node b's status of an order of that
    # id, or one forged on b's subjects, is b's entity, not a new state of this node's order.
    picture = Picture(Limits())
    order = next(e for e in sample_events(frozenset({EventKind.ORDER})))
    picture.apply(order)
    remote = OrderStatus(
        event_id=f"{order.event_id}-completed",
        order_event_id=order.event_id,
        order_id=order.order_id,
        source=order.source,
        time=order.time,
        status=OrderState.COMPLETED,
        origin_node="b",
    )
    (change,) = picture.apply(remote)
    validator("change").validate({"seq": 1, **change})
    orders = {entity["id"]: entity for entity in picture.snapshot()["order"]}
    assert orders[order.event_id]["status"] == "received"
    assert orders[order.event_id]["origin_node"] is None
    theirs = orders[f"node/b/{order.event_id}"]
    assert (theirs["status"], theirs["origin_node"]) == ("completed", "b")
