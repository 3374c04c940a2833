"""CoT built once for every sink that sends the same bytes (``sinks.cot.shared``).

A reused build must be byte for byte what the sink would have built on its own, whatever
its options or the airframe types it learnt; memory stays bounded.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from test_cot_event import DETECTION, EVENTS, TELEMETRY, TRACK, options

from gateway.events import Event
from sinks.cot.codec import Encoded, Encoding
from sinks.cot.event import CotOptions, build
from sinks.cot.shared import MAX_AIRFRAME_TYPES, AirframeTypes, SharedBuilds
from sinks.cot.sink import CotSink, CotSinkConfig

ENCODINGS: tuple[Encoding, ...] = ("xml", "mesh", "stream")


def fresh(event: Event, opts: CotOptions, own_types: dict[str, str]) -> dict[str, bytes]:
    """The bytes of each encoding as the sink made them before builds were shared."""
    cot = build(event, opts, own_types)
    assert cot is not None
    encoded = Encoded(cot)
    return {encoding: encoded.get(encoding) for encoding in ENCODINGS}


def shared(
    builds: SharedBuilds, event: Event, opts: CotOptions, own_types: dict[str, str]
) -> dict[str, bytes]:
    encoded = builds.encoded(event, builds.canonical(opts), own_types)
    assert encoded is not None
    return {encoding: encoded.get(encoding) for encoding in ENCODINGS}


@pytest.mark.parametrize("event", EVENTS, ids=lambda e: e.kind.value)
def test_five_sinks_with_equal_options_build_once_and_get_the_same_bytes(event: Event) -> None:
    builds = SharedBuilds()
    expected = fresh(event, options(), {"F26E-007": "a-f-A-M-F-Q"})
    for _ in range(5):
        assert shared(builds, event, options(), {"F26E-007": "a-f-A-M-F-Q"}) == expected
    assert (builds.misses, builds.hits) == (1, 4)


@pytest.mark.parametrize(
    "changes",
    [
        {"uid_prefix": "other-"},
        {"callsign_prefix": "X "},
        {"detection_hostility": "suspect"},
        {"loitering_munition": "missile"},
        {"geoid": None},
        {"group": ("Cyan", "Team Member")},
        {"version": "9"},
    ],
    ids=lambda c: next(iter(c)),
)
def test_sinks_whose_options_differ_each_get_their_own_bytes(changes: dict[str, object]) -> None:
    builds = SharedBuilds()
    for event in EVENTS:
        plain = shared(builds, event, options(), {})
        other = shared(builds, event, options(**changes), {})
        assert plain == fresh(event, options(), {})
        assert other == fresh(event, options(**changes), {})
    assert builds.hits == 0


@pytest.mark.parametrize("event", [DETECTION, TRACK], ids=lambda e: e.kind.value)
def test_the_link_follows_each_sinks_own_airframe_types(event: Event) -> None:
    # One sink saw the airframe's telemetry (a quadrotor), the other did not (a fixed wing).
    builds = SharedBuilds()
    told: dict[str, str] = {}
    quad = TELEMETRY.model_copy(update={"mav_type": 2})
    assert builds.encoded(quad, builds.canonical(options()), told) is not None
    assert told == {"F26E-007": "a-f-A-M-H-Q"}
    knows = shared(builds, event, options(), dict(told))
    blind = shared(builds, event, options(), {})
    assert knows == fresh(event, options(), dict(told))
    assert blind == fresh(event, options(), {})
    assert knows["xml"] != blind["xml"]
    assert b'type="a-f-A-M-H-Q" relation="p-p"' in knows["xml"]


def test_a_reused_telemetry_build_teaches_the_sink_its_airframe_type() -> None:
    builds = SharedBuilds()
    first: dict[str, str] = {}
    second: dict[str, str] = {}
    builds.encoded(TELEMETRY, builds.canonical(options()), first)
    builds.encoded(TELEMETRY, builds.canonical(options()), second)
    assert builds.hits == 1
    assert second == first == {"F26E-007": "a-f-A-M-F-Q"}


def test_an_equal_event_that_is_another_object_is_built_anew() -> None:
    # A spooled copy, or a new event under a recycled id(): never someone else's bytes.
    builds = SharedBuilds()
    copy = DETECTION.model_copy(update={"confidence": 0.5})
    shared(builds, DETECTION, options(), {})
    assert shared(builds, copy, options(), {}) == fresh(copy, options(), {})
    assert builds.hits == 0


def test_memory_is_bounded_oldest_dropped_first() -> None:
    builds = SharedBuilds(size=4)
    events = [DETECTION.model_copy(update={"event_id": f"d{n}"}) for n in range(100)]
    for event in events:
        shared(builds, event, options(), {})
    assert len(builds) == 4
    shared(builds, events[-1], options(), {})
    assert builds.hits == 1  # the newest is kept
    shared(builds, events[0], options(), {})
    assert builds.hits == 1  # the oldest is gone
    with pytest.raises(ValueError, match="size"):
        SharedBuilds(size=0)


def test_an_event_without_cot_is_none_for_every_sink() -> None:
    builds = SharedBuilds()
    nowhere = TELEMETRY.model_copy(update={"position": None})
    told: dict[str, str] = {}
    assert builds.encoded(nowhere, builds.canonical(options()), told) is None
    assert builds.encoded(nowhere, builds.canonical(options()), {}) is None
    assert told == {"F26E-007": "a-f-A-M-F-Q"}  # build still learns the type


@contextmanager
def receivers(count: int) -> Iterator[list[socket.socket]]:
    socks = []
    try:
        for _ in range(count):
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
            sock.settimeout(10)
            socks.append(sock)
        yield socks
    finally:
        for sock in socks:
            sock.close()


@pytest.mark.anyio
async def test_sinks_on_real_sockets_send_what_each_would_alone() -> None:
    builds = SharedBuilds()
    configs = [{}, {}, {}, {"uid_prefix": "b-"}, {"protocol": "protobuf"}]
    with receivers(len(configs)) as socks:
        sinks = [
            CotSink(
                f"cot{n}",
                CotSinkConfig.model_validate(
                    {"destinations": [f"udp://127.0.0.1:{s.getsockname()[1]}"], **extra}
                ),
                builds=builds,
            )
            for n, (s, extra) in enumerate(zip(socks, configs, strict=True))
        ]
        alone = [
            CotSink(sink.name, sink.config, builds=SharedBuilds()) for sink in sinks
        ]  # each with builds of its own: the bytes of a sink on its own
        for sink in sinks:
            await sink.open()
            await sink.send(list(EVENTS))
        got = [[s.recv(65536) for _ in EVENTS] for s in socks]
        for sink in alone:
            await sink.open()
            await sink.send(list(EVENTS))
        want = [[s.recv(65536) for _ in EVENTS] for s in socks]
        for sink in sinks + alone:
            await sink.aclose()
    assert got == want
    assert got[0] == got[1] == got[2] != got[3]
    assert builds.misses == 2 * len(EVENTS)  # the default options, and the b- prefix


def test_a_sinks_airframe_types_keep_the_newest_airframes_only() -> None:
    # Remote nodes' telemetry (the nats source) may name any number of airframe ids: the
    # sink's map of airframe -> CoT type must not grow with them.
    builds = SharedBuilds()
    types = AirframeTypes(limit=3)
    for n in range(50):
        telemetry = TELEMETRY.model_copy(update={"airframe": f"GHOST-{n}"})
        builds.encoded(telemetry, builds.canonical(options()), types)
    assert list(types) == ["GHOST-47", "GHOST-48", "GHOST-49"]
    types["GHOST-47"] = "a-f-A"  # set again: now the newest
    types["GHOST-50"] = "a-f-A"
    assert list(types) == ["GHOST-49", "GHOST-47", "GHOST-50"]
    with pytest.raises(ValueError, match="limit"):
        AirframeTypes(limit=0)


def test_the_cot_sink_bounds_its_airframe_types() -> None:
    sink = CotSink("atak", CotSinkConfig.model_validate({"destinations": ["udp://127.0.0.1:9"]}))
    assert isinstance(sink._own_types, AirframeTypes)
    assert sink._own_types.limit == MAX_AIRFRAME_TYPES
