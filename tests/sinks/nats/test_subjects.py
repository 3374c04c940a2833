"""Every field of another node's event is bounded before it reaches this node's bus.

The models check types and their own ranges; ``decode_event`` refuses what they let through
that no node of ours sends and that a sink would choke on or carry on for ever: long text
(CoT remarks, the map, C2 sinks), non-finite numbers (JSON's ``NaN``, ``Infinity``,
``1e400``), huge integers, a detection's σ beyond what the ingest takes, a time far ahead.
Then the same hostile messages go through a real nats-server to the ``nats`` source: each is
counted and dropped, one log line for all of them, and only the good events reach the bus.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import anyio
import nats
import pytest
from nats_server import NEEDS_NATS, NatsServer
from structlog.testing import capture_logs

from gateway.events import Detection, Event, Position, Sensor, Telemetry
from sinks.nats.sink import NatsSink, NatsSinkConfig
from sinks.nats.source import NatsSource, NatsSourceConfig
from sinks.nats.subjects import (
    MAX_TEXT_CHARS,
    BadMessage,
    airframe_token,
    decode_event,
    encode_event,
)

T0 = datetime.now(UTC) - timedelta(minutes=1)


def detection(airframe: str = "F1", n: int = 1) -> Detection:
    return Detection(
        event_id=f"{airframe}-det-{n}",
        airframe=airframe,
        time=T0,
        sensor=Sensor.EO,
        object_class="tank",
        subtype="T-72",
        confidence=0.9,
        position=Position(lat_deg=65.8, lon_deg=21.7, alt_msl_m=200.0),
        sigma_h_m=8.0,
    )


def telemetry(airframe: str = "F1") -> Telemetry:
    return Telemetry(
        event_id=f"{airframe}-tel-1",
        airframe=airframe,
        time=T0,
        position=Position(lat_deg=65.8, lon_deg=21.7),
        battery_pct=80.0,
        active_link="radio",
    )


def body(event: Event, **changes: str) -> bytes:
    """``event``'s JSON with each field in ``changes`` (``position__alt_msl_m`` for a nested
    one) written as the raw JSON text given: ``NaN`` and ``Infinity`` too."""
    data = json.loads(encode_event(event))
    for key in changes:
        target = data
        *path, last = key.split("__")
        for part in path:
            target = target[part]
        target[last] = f"@{key}@"
    text = json.dumps(data)
    for key, raw in changes.items():
        text = text.replace(f'"@{key}@"', raw)
    return text.encode()


#: (field, kind, body of airframe): each refused, its reason naming the field.
HOSTILE: list[tuple[str, str, Callable[[str], bytes]]] = [
    ("subtype", "det", lambda a: body(detection(a), subtype=json.dumps("S" * 60_000))),
    ("object_class", "det", lambda a: body(detection(a), object_class=json.dumps("c" * 300))),
    ("active_link", "tlm", lambda a: body(telemetry(a), active_link=json.dumps("l" * 1000))),
    ("ew_mode", "tlm", lambda a: body(telemetry(a), ew_mode=json.dumps("e" * 257))),
    ("battery_pct", "tlm", lambda a: body(telemetry(a), battery_pct="Infinity")),
    ("battery_pct", "tlm", lambda a: body(telemetry(a), battery_pct="1e400")),
    ("alt_msl_m", "det", lambda a: body(detection(a), position__alt_msl_m="NaN")),
    ("groundspeed_mps", "tlm", lambda a: body(telemetry(a), groundspeed_mps="-Infinity")),
    ("custom_mode", "tlm", lambda a: body(telemetry(a), custom_mode="9" * 40)),
    ("sigma_h_m", "det", lambda a: body(detection(a), sigma_h_m="1e308")),
    ("time", "det", lambda a: body(detection(a), time='"9999-12-31T23:59:59Z"')),
    (
        "time",
        "tlm",
        lambda a: body(telemetry(a), time=json.dumps((T0 + timedelta(hours=1)).isoformat())),
    ),
]


@pytest.mark.parametrize(("field", "kind", "make"), HOSTILE, ids=[h[0] for h in HOSTILE])
def test_an_out_of_bounds_field_is_refused_naming_it(
    field: str, kind: str, make: Callable[[str], bytes]
) -> None:
    with pytest.raises(BadMessage, match=field) as refused:
        decode_event(f"fsg.b.{kind}.F1", make("F1"))
    assert len(str(refused.value)) < 400


def test_bounded_events_pass_as_they_were() -> None:
    longest = detection().model_copy(
        update={"subtype": "s" * MAX_TEXT_CHARS, "object_class": "c" * MAX_TEXT_CHARS}
    )
    assert decode_event("fsg.b.det.F1", encode_event(longest)).subtype == "s" * MAX_TEXT_CHARS
    ahead = telemetry().model_copy(update={"time": datetime.now(UTC) + timedelta(minutes=4)})
    assert decode_event("fsg.b.tlm.F1", encode_event(ahead)).origin_node == "b"


@pytest.fixture
def nodes(tmp_path: Path) -> Iterator[tuple[NatsServer, NatsServer]]:
    hub = NatsServer(tmp_path, "a", hub=True)
    leaf = NatsServer(tmp_path, "b", leaf_of=f"nats-leaf://127.0.0.1:{hub.leaf_port}")
    with hub, leaf:
        deadline = time.monotonic() + 20
        while not hub.leafz().get("leafs") and time.monotonic() < deadline:
            time.sleep(0.02)
        yield hub, leaf


@NEEDS_NATS
def test_hostile_messages_through_a_real_server_are_counted_and_dropped_quietly(
    nodes: tuple[NatsServer, NatsServer],
) -> None:
    hub, leaf = nodes
    received: list[Event] = []
    flood = 20  # rounds of every hostile message

    async def main() -> dict[str, object]:
        sink = NatsSink("out", NatsSinkConfig(node="b", servers=[leaf.url]))
        await sink.open()  # makes node b's streams
        await sink.send([detection("G1", 1), telemetry("G1")])
        raw = await nats.connect(leaf.url)
        js = raw.jetstream()
        for n in range(flood):
            for index, (_, kind, make) in enumerate(HOSTILE):
                # Each its own airframe and message id: a flood, not one message repeated
                # (node b's telemetry stream keeps one message per airframe).
                airframe = f"H.{n}-{index}"
                await js.publish(
                    f"fsg.b.{kind}.{airframe_token(airframe)}",
                    make(airframe),
                    headers={"Nats-Msg-Id": f"hostile-{n}-{index}"},
                )
        await raw.close()
        await sink.send([detection("G1", 2)])
        source = NatsSource(
            "in",
            NatsSourceConfig(node="a", servers=[hub.url], remotes=["b"]),
            lambda event: received.append(event) is None,
            clock=lambda: datetime.now(UTC),
        )
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            with anyio.fail_after(60):
                while len(received) < 3:  # noqa: ASYNC110 - polling what a callback appends
                    await anyio.sleep(0.05)
                while source.status()["counts"].get("bad", 0) < flood * len(HOSTILE):  # noqa: ASYNC110
                    await anyio.sleep(0.05)
            tg.cancel_scope.cancel()
        await sink.aclose()
        return source.status()

    with capture_logs() as logs:
        status = anyio.run(main)
    assert status["counts"] == {"bad": flood * len(HOSTILE), "detection": 2, "telemetry": 1}
    assert sorted(e.event_id for e in received) == ["G1-det-1", "G1-det-2", "G1-tel-1"]
    refused = [line for line in logs if line["event"] == "nats_message_refused"]
    assert len(refused) == 1  # at most one line per 10 s, whatever the flood
